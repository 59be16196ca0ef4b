"""Bad input, tried systematically: the image reader, the ingest stage and the command line.

Every case must end in one of two ways: a clear error (ImageError from the reader; exit code 2
and one line naming the file or key from the command line) or a recorded entry (the manifest,
possibly with a conversion note, or the quarantine table with its reason). Nothing may raise
anything else, and no valid image may be lost.

Each test counts the cases it tried in CASES; run ``pytest tests/test_fuzz.py -s`` to see the
totals printed at the end of the module.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import os
import struct
import zlib
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from PIL import Image

from conftest import tiny_params
from vtgen import cli
from vtgen.io.params import model_settings
from vtgen.io.images import display_path, ImageError, MAX_PIXELS, read_rgb8
from vtgen.stages.ingest import IngestError, run_ingest
from vtgen.core.models import UNetGenerator
from vtgen.io.checkpoints import save_generator

# corrupt files make Pillow warn (bad EXIF, decompression bomb) before the reader refuses them
pytestmark = [pytest.mark.filterwarnings("ignore::UserWarning:PIL"),
              pytest.mark.filterwarnings("ignore::PIL.Image.DecompressionBombWarning")]
CASES: Counter = Counter()
def fuzz(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.fixture(scope="module", autouse=True)
def report_counts():
    yield
    print("\nfuzz cases tried:", json.dumps(dict(sorted(CASES.items())), indent=1), f"\ntotal {sum(CASES.values())}")


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    """One folder for the per-example files of the hypothesis tests (function fixtures do not reset per example)."""
    return tmp_path_factory.mktemp("fuzz")


# ---------------------------------------------------------------------------------------------
# Images in every mode and format the reader accepts, with the RGB a person would expect from them

LOSSLESS = {"PNG", "BMP", "TIFF", "WEBP"}  # WEBP is written lossless below
MODES_PER_FORMAT = {
    "PNG": ["1", "L", "LA", "P", "RGB", "RGBA", "I;16", "RGB;16"],
    "JPEG": ["L", "RGB", "CMYK"],
    "BMP": ["1", "L", "P", "RGB"],
    "TIFF": ["1", "L", "LA", "P", "RGB", "RGBA", "I;16", "CMYK"],
    "WEBP": ["RGB", "RGBA"],
}
EXTENSION = {"PNG": ".png", "JPEG": ".jpg", "BMP": ".bmp", "TIFF": ".tif", "WEBP": ".webp"}


def make_image(fmt: str, mode: str, width: int, height: int, seed: int) -> tuple[bytes, np.ndarray]:
    """Encoded bytes of a random image, and the (H, W, 3) uint8 RGB the reader should return."""
    rng = np.random.default_rng(seed)
    if mode == "RGB;16":  # Pillow cannot write 16-bit RGB; OpenCV can (it stores BGR)
        deep = rng.integers(0, 65536, (height, width, 3), dtype=np.uint16)
        ok, data = cv2.imencode(".png", deep[:, :, ::-1])
        assert ok
        return data.tobytes(), np.rint(deep * (255 / 65535)).astype(np.uint8)
    if mode == "I;16":
        deep = rng.integers(0, 65536, (height, width), dtype=np.uint16)
        image = Image.fromarray(deep)
        expected = np.repeat(np.rint(deep * (255 / 65535)).astype(np.uint8)[:, :, None], 3, axis=2)
    else:
        rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        alpha = rng.integers(0, 256, (height, width), dtype=np.uint8)
        base = Image.fromarray(rgb)
        if mode == "RGBA":
            image = Image.fromarray(np.dstack([rgb, alpha]))
            expected = rgb
        elif mode == "LA":
            grey = np.asarray(base.convert("L"))
            image = Image.fromarray(np.dstack([grey, alpha]), "LA")
            expected = np.repeat(grey[:, :, None], 3, axis=2)
        elif mode == "P":
            image = base.convert("P", palette=Image.Palette.ADAPTIVE, colors=int(rng.integers(2, 257)))
            expected = np.asarray(image.convert("RGB"))
        elif mode == "CMYK":
            image = base.convert("CMYK")
            expected = np.asarray(image.convert("RGB"))
        else:
            image = base.convert(mode) if mode != "RGB" else base
            expected = np.asarray(image.convert("RGB"))
    buffer = io.BytesIO()
    image.save(buffer, fmt, **({"lossless": True, "exact": True} if fmt == "WEBP" else {}))  # exact: keep RGB under alpha 0
    return buffer.getvalue(), np.asarray(expected, dtype=np.uint8)


@st.composite
def valid_images(draw):
    fmt = draw(st.sampled_from(sorted(MODES_PER_FORMAT)))
    mode = draw(st.sampled_from(MODES_PER_FORMAT[fmt]))
    width, height = draw(st.integers(1, 40)), draw(st.integers(1, 40))
    return fmt, mode, width, height, draw(st.integers(0, 2**16))


# a pool of encoded images to truncate and corrupt: one per format and a few modes
POOL = [make_image(fmt, mode, 23, 17, i)[0] for i, (fmt, mode) in enumerate(
    [("PNG", "RGB"), ("PNG", "P"), ("PNG", "I;16"), ("PNG", "RGBA"), ("JPEG", "RGB"), ("JPEG", "L"),
     ("BMP", "RGB"), ("TIFF", "RGB"), ("TIFF", "I;16"), ("WEBP", "RGB")])]
POOL_EXT = [".png", ".png", ".png", ".png", ".jpg", ".jpg", ".bmp", ".tif", ".tif", ".webp"]


def outcome(path: Path) -> str:
    """'kept' or 'refused'; anything but an ImageError from the reader fails the test."""
    try:
        image = read_rgb8(path)
    except ImageError as exc:
        message = str(exc)
        assert message and "\n" not in message, repr(message)
        return "refused"
    assert image.rgb.dtype == np.uint8 and image.rgb.ndim == 3 and image.rgb.shape[2] == 3
    assert image.rgb.shape[0] >= 1 and image.rgb.shape[1] >= 1
    assert image.bit_depth in (8, 16)
    return "kept"


@fuzz(150)
@given(image=valid_images())
@example(image=("PNG", "RGB", 1, 1, 0))
@example(image=("PNG", "I;16", 1, 1, 0))
@example(image=("JPEG", "CMYK", 1, 1, 0))
@example(image=("TIFF", "P", 1, 40, 0))
def test_every_valid_image_is_read_with_the_expected_pixels(scratch, image):
    fmt, mode, width, height, seed = image
    data, expected = make_image(fmt, mode, width, height, seed)
    path = scratch / f"valid{EXTENSION[fmt]}"
    path.write_bytes(data)
    CASES["reader: valid image (mode x format x size)"] += 1
    decoded = read_rgb8(path)  # a valid image must never be refused
    assert decoded.rgb.shape == (height, width, 3)
    if fmt in LOSSLESS:
        np.testing.assert_array_equal(decoded.rgb, expected)
    if mode not in ("RGB",):
        assert decoded.note, f"{mode} {fmt}: conversion not noted"
    if mode in ("I;16", "RGB;16"):
        assert decoded.bit_depth == 16


MAGIC = [b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff\xe0", b"BM", b"II*\x00", b"MM\x00*", b"RIFF\x10\x00\x00\x00WEBPVP8 "]


@fuzz(200)
@given(magic=st.sampled_from(MAGIC), body=st.binary(max_size=3000), ext=st.sampled_from(sorted(EXTENSION.values())))
@example(magic=b"", body=b"", ext=".png")
@example(magic=b"", body=b"this is not an image\n", ext=".jpg")
def test_random_bytes_named_as_images_are_refused_with_a_reason(scratch, magic, body, ext):
    path = scratch / f"random{ext}"
    path.write_bytes(magic + body)
    CASES["reader: random bytes behind a format's magic number"] += 1
    result = outcome(path)
    if not (magic + body).startswith((b"BM", b"\x89PNG", b"\xff\xd8", b"II", b"MM", b"RIFF")):
        assert result == "refused"  # without a magic number no decoder even starts


@fuzz(200)
@given(which=st.integers(0, len(POOL) - 1), cut=st.floats(0, 1))
@example(which=0, cut=1.0)
@example(which=4, cut=0.5)
def test_truncated_images_are_refused_or_read_whole(scratch, which, cut):
    data = POOL[which]
    keep = int(len(data) * cut)
    path = scratch / f"truncated{POOL_EXT[which]}"
    path.write_bytes(data[:keep])
    CASES["reader: truncated image"] += 1
    result = outcome(path)
    if keep == len(data):
        assert result == "kept"
    if result == "kept":
        assert read_rgb8(path).rgb.shape == (17, 23, 3)  # whatever was read is the whole picture


@fuzz(200)
@given(which=st.integers(0, len(POOL) - 1),
       edits=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=8))
def test_corrupted_images_never_crash_the_reader(scratch, which, edits):
    data = bytearray(POOL[which])
    for where, value in edits:
        data[int(where * len(data))] = value
    path = scratch / f"corrupt{POOL_EXT[which]}"
    path.write_bytes(bytes(data))
    CASES["reader: corrupted bytes in a valid image"] += 1
    outcome(path)


def png_header_only(width: int, height: int) -> bytes:
    """A PNG that declares ``width`` x ``height`` pixels but holds almost no data (a decompression bomb's header)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))


@pytest.mark.parametrize("width, height", [(100_000, 100_000), (20_000, 5_000), (1, 2**31 - 1)])
def test_images_declaring_huge_dimensions_are_refused_before_decoding(tmp_path, width, height):
    path = tmp_path / "bomb.png"
    path.write_bytes(png_header_only(width, height))
    CASES["reader: declared huge dimensions"] += 1
    assert width * height > MAX_PIXELS
    with pytest.raises(ImageError, match="too large"):
        read_rgb8(path)


def test_unusual_but_valid_files_are_kept_with_a_note(tmp_path):
    rng = np.random.default_rng(0)
    jpeg, _ = make_image("JPEG", "RGB", 8, 8, 1)
    (tmp_path / "jpeg_named.png").write_bytes(jpeg)
    png, expected = make_image("PNG", "RGB", 8, 8, 2)
    (tmp_path / "png_named.jpg").write_bytes(png)
    Image.fromarray(np.arange(64, dtype=np.int32).reshape(8, 8) * 1000).save(tmp_path / "int32_in_16bit.tif")
    Image.fromarray(np.full((8, 8), 70_000, dtype=np.int32)).save(tmp_path / "int32_beyond.tif")
    transparent = Image.fromarray(rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)).convert("P")
    transparent.info["transparency"] = 0
    transparent.save(tmp_path / "palette_transparency.png")
    CASES["reader: explicit unusual files"] += 5

    assert "file holds JPEG data but is named .png" in read_rgb8(tmp_path / "jpeg_named.png").note
    named_jpg = read_rgb8(tmp_path / "png_named.jpg")
    assert "PNG data" in named_jpg.note
    np.testing.assert_array_equal(named_jpg.rgb, expected)
    deep = read_rgb8(tmp_path / "int32_in_16bit.tif")
    assert "32-bit integer" in deep.note and deep.rgb[7, 7, 0] == round(63_000 * 255 / 65535)
    with pytest.raises(ImageError, match="value range is unknown"):
        read_rgb8(tmp_path / "int32_beyond.tif")
    assert "palette" in read_rgb8(tmp_path / "palette_transparency.png").note


# ---------------------------------------------------------------------------------------------
# The ingest stage over whole folders of good and bad entries

# kind -> (file name suffix, does it hold a usable image?, words expected in its quarantine reason)
KINDS = {
    "valid": (".png", True, None),
    "one_pixel": (".png", True, None),
    "jpeg_named_png": (".png", True, None),
    "sixteen_bit": (".tif", True, None),
    "palette": (".bmp", True, None),
    "zero_bytes": (".png", False, "empty file"),
    "random_bytes": (".jpg", False, "not a decodable image"),
    "truncated": (".png", False, "truncated"),
    "text_named_jpg": (".jpeg", False, "not a decodable image"),
    "not_image_extension": (".txt", False, "not an image file"),
    "non_utf8_name": (".png", False, "not valid UTF-8"),
    "file_link_loop": (".png", False, "symbolic link loop"),
    "dangling_link": (".png", False, "broken symbolic link"),
    "folder_link_to_parent": ("", False, "symbolic link to a folder"),
    "huge_header": (".png", False, "too large"),
}


def write_entry(folder: Path, name: str, kind: str, seed: int) -> Path:
    """Create one entry of ``kind`` in ``folder``; return its path as ingest will record it."""
    folder.mkdir(parents=True, exist_ok=True)
    suffix = KINDS[kind][0]
    path = folder / f"{name}{suffix}"
    if kind == "valid":
        path.write_bytes(make_image("PNG", "RGB", 12, 9, seed)[0])
    elif kind == "one_pixel":
        path.write_bytes(make_image("PNG", "RGB", 1, 1, seed)[0])
    elif kind == "jpeg_named_png":
        path.write_bytes(make_image("JPEG", "RGB", 12, 9, seed)[0])
    elif kind == "sixteen_bit":
        path.write_bytes(make_image("TIFF", "I;16", 12, 9, seed)[0])
    elif kind == "palette":
        path.write_bytes(make_image("BMP", "P", 12, 9, seed)[0])
    elif kind == "zero_bytes":
        path.write_bytes(b"")
    elif kind == "random_bytes":
        path.write_bytes(b"\x00junk" + np.random.default_rng(seed).bytes(200))
    elif kind == "truncated":
        path.write_bytes(make_image("PNG", "RGB", 64, 64, seed)[0][:2000])
    elif kind == "text_named_jpg":
        path.write_text("lab notes, not a picture\n")
    elif kind == "not_image_extension":
        path.write_text("a note\n")
    elif kind == "non_utf8_name":
        raw = os.fsencode(folder) + b"/" + name.encode() + b"\xff\xfe" + suffix.encode()
        with open(raw, "wb") as handle:
            handle.write(make_image("PNG", "RGB", 12, 9, seed)[0])
        path = Path(os.fsdecode(raw))
    elif kind == "file_link_loop":
        partner = folder / f"{name}_partner.png"
        path.symlink_to(partner.name)
        partner.symlink_to(path.name)
    elif kind == "dangling_link":
        path.symlink_to("nowhere_to_be_found.png")
    elif kind == "folder_link_to_parent":
        path.symlink_to("..")
    elif kind == "huge_header":
        path.write_bytes(png_header_only(100_000, 100_000))
    return path


@st.composite
def messy_datasets(draw):
    """A generic-layout dataset: a list of (kind, class, modality) entries."""
    entry = st.tuples(st.sampled_from(sorted(KINDS)), st.sampled_from(["cotton", "wool", "silk"]),
                      st.sampled_from(["visual", "tactile"]))
    return draw(st.lists(entry, min_size=1, max_size=14))


@fuzz(30)
@given(entries=messy_datasets())
@example(entries=[("valid", "cotton", "visual"), ("valid", "cotton", "tactile"), ("non_utf8_name", "cotton", "visual"),
                  ("file_link_loop", "cotton", "tactile"), ("folder_link_to_parent", "cotton", "visual"),
                  ("huge_header", "wool", "visual"), ("one_pixel", "wool", "tactile")])
@example(entries=[("zero_bytes", "cotton", "visual")])
def test_ingest_keeps_every_valid_image_and_records_every_bad_entry(scratch, entries):
    case = CASES["ingest: messy dataset folders"] = CASES["ingest: messy dataset folders"] + 1
    CASES["ingest: entries in those folders"] += len(entries)
    root, out = scratch / f"data{case}", scratch / f"out{case}"
    made = []
    for i, (kind, cls, modality) in enumerate(entries):
        path = write_entry(root / cls / modality, f"e{i:02d}_{kind}", kind, seed=i)
        made.append((kind, cls, modality, display_path(path)))
    usable = {(cls, m) for kind, cls, m, _ in made if KINDS[kind][1]}
    complete = {cls for cls, _ in usable}  # a class with one modality is data too (its classifier can run)

    if not complete:
        with pytest.raises(IngestError, match="no usable images left"):
            run_ingest(root, "generic", out, workers=2)
        # a failed ingest keeps its quarantine table and summary, and no manifest
        assert not (out / "manifest.parquet").exists()
        assert json.loads((out / "summary.json").read_text())["status"] == "failed"
        quarantined = set(pd.read_parquet(out / "quarantine.parquet")["path"])
        assert {path for *_, path in made} <= quarantined  # every entry, with its reason
        return
    summary = run_ingest(root, "generic", out, workers=2)
    manifest = pd.read_parquet(out / "manifest.parquet")
    quarantine = pd.read_parquet(out / "quarantine.parquet")
    assert len(pd.read_csv(out / "quarantine.csv")) == len(quarantine)
    assert json.loads((out / "summary.json").read_text())["entries_in"] == summary["entries_in"]

    # nothing silently dropped, and the counts add up
    assert summary["entries_in"] == summary["kept"] + summary["quarantined"] == len(manifest) + len(quarantine)
    reasons = dict(zip(quarantine["path"], quarantine["reason"]))
    kept = set(manifest["path"])
    for kind, cls, modality, path in made:
        is_usable, reason = KINDS[kind][1:]
        if is_usable and cls in complete:
            assert path in kept, f"valid {kind} image lost: {path} ({reasons.get(path)})"
            row = manifest.set_index("path").loc[path]
            assert row["class"] == cls and row["modality"] == modality
        else:
            assert path not in kept, f"bad {kind} entry kept: {path}"
            assert reason in reasons[path], (kind, reasons.get(path))
    assert set(manifest["class"]) == complete


@pytest.mark.parametrize("layout", ["generic", "vitac"])
def test_symlink_loops_anywhere_in_the_tree_end_in_quarantine_not_in_a_hang(tmp_path, layout):
    root = tmp_path / "raw"
    if layout == "generic":
        good = [write_entry(root / "cotton" / m, "a", "valid", seed=i) for i, m in enumerate(("visual", "tactile"))]
        (root / "loop").symlink_to(root)                            # a class folder that is the dataset itself
        (root / "wool").mkdir()
        (root / "wool" / "visual").symlink_to("visual_again")      # a modality folder that is a link loop
        (root / "wool" / "visual_again").symlink_to("visual")
        (root / "cotton" / "tactile" / "deeper").symlink_to(root)  # a folder link inside a modality folder
        expected = {"loop": "symbolic link to a folder that is already read", "wool/visual": "not a folder",
                    "cotton/tactile/deeper": "symbolic link to a folder"}
    else:
        good = [write_entry(root / folder, name, "valid", seed=i)
                for i, (folder, name) in enumerate([("11t", "131_1"), ("11v", "IMG_2460_1")])]
        (root / "11t" / "back").symlink_to("..")
        (root / "12v").symlink_to("12v")                            # a ViTac folder name that loops onto itself
        expected = {"11t/back": "symbolic link to a folder"}
    CASES["ingest: symlink loops placed in the tree"] += len(expected)
    summary = run_ingest(root, layout, tmp_path / "out", workers=1)
    manifest = pd.read_parquet(tmp_path / "out/manifest.parquet")
    quarantine = pd.read_parquet(tmp_path / "out/quarantine.parquet")
    assert sorted(manifest["path"]) == sorted(map(str, good))
    assert summary["entries_in"] == len(manifest) + len(quarantine)
    reasons = {str(Path(p).relative_to(root)): r for p, r in zip(quarantine["path"], quarantine["reason"])}
    for where, words in expected.items():
        assert words in reasons[where], (where, reasons.get(where))
    if layout == "vitac":
        assert summary["ignored_top_level_files"] == ["12v"]  # not a folder: listed, like other top-level files


def test_cli_ingest_and_roi_on_a_messy_folder_record_everything(tmp_path, capsys):
    root = tmp_path / "raw"
    made = [write_entry(root / cls / m, f"{cls}_{m}_{kind}", kind, seed=i)
            for i, (kind, cls, m) in enumerate([(k, "cotton", m) for k in KINDS for m in ("visual", "tactile")])]
    (root / "README.md").write_text("about this data\n")
    params = tiny_params(dataset={"source": "generic", "path": str(root)}, roi={"crop_fraction": 0.5})
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    CASES["cli: ingest + roi of a folder holding every kind of entry"] += len(made)

    assert cli.main(["ingest", "--params", str(tmp_path / "params.yaml"), "--out", str(tmp_path / "ingest")]) == 0
    summary = json.loads((tmp_path / "ingest/summary.json").read_text())
    assert summary["kept"] == 2 * sum(usable for _, usable, _ in KINDS.values())
    assert summary["entries_in"] == summary["kept"] + summary["quarantined"]
    quarantine = pd.read_csv(tmp_path / "ingest/quarantine.csv")
    assert quarantine["path"].str.contains(r"\xff\xfe", regex=False).sum() == 2  # the non-UTF-8 names, escaped
    out = capsys.readouterr().out
    assert "quarantined x2: file name is not valid UTF-8" in out

    # roi: the 1x1 images give no centre crop at crop_fraction 0.5; they are skipped and recorded, the rest is cut
    assert cli.main(["roi", "--params", str(tmp_path / "params.yaml"), "--manifest",
                     str(tmp_path / "ingest/manifest.parquet"), "--out", str(tmp_path / "roi")]) == 0
    roi = json.loads((tmp_path / "roi/summary.json").read_text())
    assert roi["tiles"] == summary["kept"] - 2
    assert [Path(s["path"]).name for s in roi["skipped"]] == ["cotton_tactile_one_pixel.png", "cotton_visual_one_pixel.png"]
    assert all("too small" in s["reason"] for s in roi["skipped"])


# ---------------------------------------------------------------------------------------------
# The command line: params files and stage inputs

def run_cli(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(argv)
    return code, err.getvalue()


def assert_clean_error(code: int, err: str, stage: str, *must_name: str) -> None:
    assert code == 2, err
    assert err.startswith(f"vtgen {stage}: error: "), err
    assert "Traceback" not in err
    for name in must_name:
        assert name in err, (name, err)


BASE = tiny_params()


def leaf_keys(tree: dict, prefix: tuple = ()) -> list[tuple]:
    keys = []
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            keys.extend(leaf_keys(value, prefix + (key,)))
        else:
            keys.append(prefix + (key,))
    return keys


LEAVES = leaf_keys(BASE)
WRONG = {bool: ["yes please", 3, [1]], int: ["twelve", [1], {"a": 1}, None, True], float: ["half", [0.5], None],
         str: [7, ["a"], {"a": 1}, None], list: ["all", 5, {"a": 1}], type(None): [[1]], dict: ["none", [1], 3]}


def set_key(tree: dict, key: tuple, value) -> dict:
    tree = copy.deepcopy(tree)
    node = tree
    for part in key[:-1]:
        node = node[part]
    node[key[-1]] = value
    return tree


def write_params(folder: Path, params) -> Path:
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False, allow_unicode=True))
    return path


@fuzz(150)
@given(key=st.sampled_from(LEAVES), pick=st.integers(0, 4))
@pytest.mark.slow
def test_params_with_a_wrong_type_stop_every_stage_naming_the_key(scratch, key, pick):
    original = BASE
    for part in key:
        original = original[part]
    choices = WRONG[type(original)]
    value = choices[pick % len(choices)]
    if key == ("roi", "tactile_box") and isinstance(value, list):
        value = "everywhere"
    if key == ("translation", "class_gan", "skips") and isinstance(value, int):
        value = "some"  # a whole number of skips is one of the allowed kinds
    if (key[:3] == ("translation", "class_gan", "iterations") or key[-1] == "translation.class_gan.iterations") \
            and value is None:
        value = "twelve"  # null (the preset's length) is one of the allowed kinds, in a recipe too
    CASES["cli: params with one value of a wrong type"] += 1
    path = write_params(scratch, set_key(BASE, key, value))
    code, err = run_cli(["pairs", "--params", str(path), "--tiles", "absent.parquet", "--out", str(scratch / "never")])
    assert_clean_error(code, err, "pairs", ".".join(key))


@fuzz(60)
@given(section=st.sampled_from([(), *[(s,) for s in sorted(BASE) if s not in ("presets", "recipes")], ("presets", "fast"),
                                 ("recipes", "quick")]),
       key=st.text(st.characters(codec="utf-8", exclude_categories=["Cs", "Cc"]), min_size=1, max_size=12))
@pytest.mark.slow
def test_params_with_an_unknown_key_are_refused_naming_it(scratch, section, key):
    # `presets` and `recipes` are open (any name is a block), so one of their blocks is tried instead
    tree = copy.deepcopy(BASE)
    node = tree
    for part in section:
        node = node[part]
    if key in node:
        return
    node[key] = 1
    CASES["cli: params with an unknown key"] += 1
    code, err = run_cli(["ingest", "--params", str(write_params(scratch, tree)), "--out", str(scratch / "never")])
    assert_clean_error(code, err, "ingest", f"unknown key '{key}'")


@pytest.mark.parametrize("key", LEAVES[:40:3] + [("dataset",), ("presets",)])
def test_params_missing_a_key_are_refused_naming_it(tmp_path, key):
    tree = copy.deepcopy(BASE)
    node = tree
    for part in key[:-1]:
        node = node[part]
    del node[key[-1]]
    CASES["cli: params missing a required key"] += 1
    code, err = run_cli(["ingest", "--params", str(write_params(tmp_path, tree)), "--out", str(tmp_path / "never")])
    assert_clean_error(code, err, "ingest", f"'{key[-1]}' is a required property")


@fuzz(100)
@given(content=st.one_of(
    st.binary(max_size=400),
    st.text(max_size=200).map(str.encode),
    st.sampled_from([b"", b"\xff\xfe\x00garbage", b"- a\n- list\n", b"just a string", b"42", b"roi: [unclosed",
                     b"dataset: !!python/object:os.system {}", b"\t- tab", b"null", b"{}"])))
@pytest.mark.slow
def test_params_files_that_are_not_a_params_mapping_are_refused(scratch, content):
    path = scratch / "garbage.yaml"
    path.write_bytes(content)
    CASES["cli: params file holding arbitrary bytes or YAML"] += 1
    code, err = run_cli(["ingest", "--params", str(path), "--out", str(scratch / "never")])
    assert_clean_error(code, err, "ingest", str(path))
    assert not (scratch / "never").exists()


def table_inputs(folder: Path) -> dict[str, Path]:
    """Things that are not the table a stage expects: missing, a folder, empty, random bytes, CSV, wrong columns."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "empty.parquet").write_bytes(b"")
    (folder / "random.parquet").write_bytes(np.random.default_rng(0).bytes(512))
    (folder / "csv.parquet").write_text("path,class\na.png,x\n")
    pd.DataFrame({"unrelated": [1, 2]}).to_parquet(folder / "columns.parquet")
    (folder / "a_folder.parquet").mkdir(exist_ok=True)
    return {name: folder / f"{name}.parquet" for name in ("missing", "a_folder", "empty", "random", "csv", "columns")}


@pytest.mark.parametrize("stage, flag", [("roi", "--manifest"), ("pairs", "--tiles")])
@pytest.mark.slow
def test_stage_inputs_that_are_not_the_expected_table_give_one_line_naming_the_file(tmp_path, stage, flag):
    path = write_params(tmp_path, BASE)
    for name, table in table_inputs(tmp_path / "inputs").items():
        CASES["cli: stage input table that is not one"] += 1
        code, err = run_cli([stage, "--params", str(path), flag, str(table), "--out", str(tmp_path / "out")])
        assert_clean_error(code, err, stage, str(table))
        assert err.count("\n") == 1, err
        assert not (tmp_path / "out").exists() and not (tmp_path / ".out.tmp").exists()


@pytest.mark.parametrize("stage", ["train", "generate"])
@pytest.mark.parametrize("name", ["missing", "random", "columns"])
def test_training_and_generation_refuse_a_pairs_folder_that_is_not_one(tmp_path, stage, name):
    path = write_params(tmp_path, BASE)
    inputs = table_inputs(tmp_path / "inputs")
    pairs = tmp_path / "pairs"
    pairs.mkdir()
    for table in ("v2t", "t2v", "splits"):
        if name != "missing":
            (pairs / f"{table}.parquet").write_bytes(inputs[name].read_bytes())
    if stage == "generate":  # a real (untrained) generator, so that only the pairs folder is wrong
        settings = model_settings(BASE)
        (tmp_path / "models/all").mkdir(parents=True)
        save_generator(tmp_path / "models/all/generator.pt", UNetGenerator(settings["size"], settings["ngf"],
                                                                           settings["kernel"]), settings, "v2t", "all")
    CASES["cli: train/generate pairs folder that is not one"] += 1
    extra = ["--scope", "all"] if stage == "train" else ["--models", str(tmp_path / "models")]
    code, err = run_cli([stage, "--params", str(path), "--direction", "v2t", "--pairs", str(pairs), *extra,
                         "--out", str(tmp_path / "out")])
    assert_clean_error(code, err, stage)
    assert err.count("\n") == 1, err
