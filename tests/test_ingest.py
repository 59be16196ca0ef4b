import json
import re
import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from conftest import write_jpegs, random_rgb, write_image
from vtgen.io.images import ImageError, read_rgb8
from vtgen.stages.ingest import ingest_dataset, IngestError, run_ingest


@pytest.fixture
def messy_generic(tmp_path):
    """A generic-layout dataset holding one of each kind of bad input next to good images."""
    rng = np.random.default_rng(0)
    root = tmp_path / "raw"
    for cls in ("cotton", "wool"):
        for name in ("a", "b", "c"):
            for modality in ("visual", "tactile"):
                write_image(root / cls / modality / f"{name}.png", random_rgb(rng))
    good_jpeg = write_image(tmp_path / "good.jpg", random_rgb(rng, 64))
    (root / "cotton" / "visual" / "truncated.jpg").write_bytes(good_jpeg.read_bytes()[:300])
    (root / "cotton" / "visual" / "text.jpg").write_text("this is not an image\n")
    (root / "cotton" / "visual" / "zero.png").write_bytes(b"")
    (root / "cotton" / "visual" / "notes.txt").write_text("lab notes\n")
    write_image(root / "cotton" / "tactile" / "gray.png", rng.integers(0, 256, (32, 32), dtype=np.uint8))
    write_image(root / "cotton" / "tactile" / "deep.png", np.full((32, 32), 65535, dtype=np.uint16))
    write_image(root / "wool" / "visual" / "alpha.png", rng.integers(0, 256, (32, 32, 4), dtype=np.uint8))
    write_image(root / "wool" / "visual" / "palette.png", random_rgb(rng), convert="P")
    (root / "empty_class").mkdir()
    for name in ("x", "y"):
        write_image(root / "silk" / "visual" / f"{name}.png", random_rgb(rng))
    (root / "linen" / "depth").mkdir(parents=True)
    (root / "README.md").write_text("how this data was collected\n")
    write_image(root / "stray.png", random_rgb(rng))
    return root


def test_generic_reader_keeps_good_converts_and_quarantines_bad(messy_generic):
    manifest, quarantine, summary = ingest_dataset(messy_generic, "generic", workers=2, progress=False)
    reasons = dict(zip(quarantine["path"].map(lambda p: p.split("raw/")[1]), quarantine["reason"]))

    assert "truncated image" in reasons["cotton/visual/truncated.jpg"]
    assert "not a decodable image" in reasons["cotton/visual/text.jpg"]
    assert "empty file" in reasons["cotton/visual/zero.png"]
    assert "not an image file" in reasons["cotton/visual/notes.txt"]
    assert "empty class" in reasons["empty_class"]
    # a class with one modality is kept (classification and splits still use it), and said so
    assert "silk/visual/x.png" not in reasons and "silk/visual/y.png" not in reasons
    assert summary["translation"]["possible"] and "silk" in summary["translation"]["reason"]
    assert "not a modality folder" in reasons["linen/depth"]
    assert "image at the top level" in reasons["stray.png"]
    assert summary["ignored_top_level_files"] == ["README.md"]

    notes = dict(zip(manifest["path"].map(lambda p: p.split("raw/")[1]), manifest["note"]))
    assert "grayscale" in notes["cotton/tactile/gray.png"]
    assert "16-bit" in notes["cotton/tactile/deep.png"]
    assert "alpha" in notes["wool/visual/alpha.png"]
    assert "palette" in notes["wool/visual/palette.png"]
    assert notes["cotton/visual/a.png"] == ""

    deep = manifest.set_index("path").loc[str(messy_generic / "cotton/tactile/deep.png")]
    assert (deep["bit_depth"], deep["channels"], deep["width"]) == (16, 1, 32)
    assert read_rgb8(messy_generic / "cotton/tactile/deep.png").rgb.max() == 255

    # nothing silently dropped: every entry found is kept or quarantined
    assert summary["entries_in"] == summary["kept"] + summary["quarantined"] == len(manifest) + len(quarantine)
    assert set(manifest["class"]) == {"cotton", "wool", "silk"}
    assert set(manifest["modality"]) == {"visual", "tactile"}
    assert manifest["md5"].str.fullmatch(r"[0-9a-f]{32}").all()
    # aligned views: the same name in both modalities shares pair_key and source
    a = manifest[manifest["path"].str.endswith("cotton/visual/a.png") | manifest["path"].str.endswith("cotton/tactile/a.png")]
    assert a["pair_key"].nunique() == 1 and a["source"].nunique() == 1 and len(a) == 2


def test_nothing_usable_fails_with_clear_message(tmp_path):
    root = tmp_path / "raw"
    (root / "cotton" / "visual").mkdir(parents=True)
    (root / "cotton" / "visual" / "broken.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(IngestError, match=r"no usable images left .*1 image files decoded"):
        ingest_dataset(root, "generic", progress=False)


def test_missing_folder_and_unknown_source(tmp_path):
    with pytest.raises(IngestError, match="dataset folder does not exist"):
        ingest_dataset(tmp_path / "absent", "generic", progress=False)
    with pytest.raises(IngestError, match="unknown dataset source 'imagenet'"):
        ingest_dataset(tmp_path, "imagenet", progress=False)


def test_synthetic_reader_requires_its_metadata(tmp_path):
    write_image(tmp_path / "c" / "visual" / "s0000.png", random_rgb(np.random.default_rng(1)))
    with pytest.raises(IngestError, match="no dataset.json"):
        ingest_dataset(tmp_path, "synthetic", progress=False)


def test_read_rgb8_refuses_float_images(tmp_path):
    path = tmp_path / "f.tif"
    from PIL import Image

    Image.fromarray(np.zeros((4, 4), dtype=np.float32)).save(path)
    with pytest.raises(ImageError, match="floating-point"):
        read_rgb8(path)


def test_vitac_sample_is_read_with_its_splits(vitac_root, tmp_path):
    summary = run_ingest(vitac_root, "vitac", tmp_path / "ingest")
    manifest = pd.read_parquet(tmp_path / "ingest" / "manifest.parquet")
    assert len(manifest) == 60 and summary["kept"] == 60 and summary["quarantined"] == 0
    assert summary["ignored_top_level_files"] == ["SOURCE.md"]
    counts = manifest.groupby(["modality", "split"]).size().to_dict()
    assert counts == {("tactile", "train"): 20, ("tactile", "test"): 10, ("visual", "train"): 20, ("visual", "test"): 10}
    assert set(manifest["class"]) == {"11"}
    assert (manifest[["width", "height", "channels"]] == [256, 256, 3]).all().all()
    tactile = manifest[manifest["modality"] == "tactile"]
    assert set(tactile.loc[tactile["split"] == "test", "source"]) == {"11t:frame131", "11t:frame132", "11t:frame133"}
    assert set(manifest.loc[manifest["modality"] == "visual", "source"]) == {"11v:IMG_2460"}
    assert (manifest["pair_key"] == "").all()  # ViTac modalities are not aligned
    assert (tmp_path / "ingest" / "quarantine.csv").is_file()


# --- streaming: bounded work in flight, memory that does not grow with the pixels -------------


def test_stream_map_reads_items_lazily_and_keeps_a_bounded_window():
    import threading

    from vtgen.io.images import stream_map

    pulled, lock = [], threading.Lock()

    def items():
        for i in range(200):
            pulled.append(i)
            yield i

    def work(i):
        with lock:
            return i * i

    results = []
    for result in stream_map(work, items(), workers=2, window=5):
        # never more than `window` items taken from the input and not yet handed back
        assert len(pulled) - len(results) <= 5
        results.append(result)
    assert results == [i * i for i in range(200)]  # in input order


def test_stream_map_raises_the_first_error_and_cancels_the_rest():
    from vtgen.io.images import stream_map

    started = []

    def work(i):
        started.append(i)
        if i == 3:
            raise ValueError("bad item 3")
        return i

    with pytest.raises(ValueError, match="bad item 3"):
        list(stream_map(work, iter(range(1000)), workers=2, window=4))
    assert len(started) < 20  # the other 980-odd items were never started


def _square_in_a_process(i):
    import os

    if i == 37:
        raise ValueError(f"bad item 37 (in process {os.getpid()})")
    return i * i, os.getpid()


def test_stream_map_in_processes_keeps_order_across_batches_and_raises_the_item_error():
    import os

    from vtgen.io.images import stream_map

    pulled = []

    def items(n):
        for i in range(n):
            pulled.append(i)
            yield i

    results = list(stream_map(_square_in_a_process, items(30), workers=2, processes=True, batch=4, window=2))
    assert [square for square, _ in results] == [i * i for i in range(30)]  # 30 = 7 full batches and one of 2
    assert os.getpid() not in {pid for _, pid in results}  # the work ran in the pool's processes
    pulled.clear()
    with pytest.raises(ValueError, match="bad item 37"):
        for _ in stream_map(_square_in_a_process, items(10_000), workers=2, processes=True, batch=4, window=2):
            # at most `window` batches taken from the input and not yet handed back, plus the batch being filled
            pass
    assert len(pulled) < 37 + 3 * 4


EARLY_ERROR_SCRIPT = """
from vtgen.io.images import stream_map

def fails_at_5(i):
    if i == 5:
        raise ValueError("bad item 5")
    return i

for trial in range(100):
    try:
        for _ in stream_map(fails_at_5, range(10_000), workers=2, processes=True, batch=2, window=2):
            pass
    except ValueError:
        pass
print("done", flush=True)
"""


def test_stream_map_process_pool_shuts_down_after_an_early_error_every_time():
    """An error soon after a task is submitted leaves futures to cancel while the pool shuts down. On Python
    3.11.2 cancelling them one by one hung that shutdown within about 30 tries (CPython gh-94440), which
    hung CI; stream_map lets the shutdown cancel them, which cannot hang. (On Python >= 3.11.3 the old code
    passes too: there the test guards against going back to per-future cancels on an older Python.)"""
    from conftest import ENV

    try:
        done = subprocess.run([sys.executable, "-c", EARLY_ERROR_SCRIPT], capture_output=True, text=True,
                              timeout=120, env=ENV)
    except subprocess.TimeoutExpired:
        pytest.fail("stream_map's process pool hung in its shutdown after an error (CPython gh-94440)")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["done"]


def _dies_at_item_5(i):
    import os

    if i == 5:
        os._exit(1)  # as the kernel's OOM killer would end it: no exception, no cleanup
    return i


def test_a_worker_process_that_dies_is_an_error_that_says_so():
    from vtgen.io.images import stream_map

    with pytest.raises(RuntimeError, match="roi: a worker process ended abruptly"):
        list(stream_map(_dies_at_item_5, range(40), workers=2, desc="roi", processes=True, batch=2))


OPENCV_FORK_SCRIPT = """
import cv2, numpy as np
from vtgen.io.images import stream_map

def blur(i):
    return float(cv2.GaussianBlur(np.full((512, 512), i, np.float32), (31, 31), 5).mean())

cv2.setNumThreads(2)
big = np.random.default_rng(0).random((2048, 2048), dtype=np.float32)
for _ in range(5):
    cv2.GaussianBlur(big, (31, 31), 5)  # OpenCV's own thread pool is running in the parent now
assert [round(v) for v in stream_map(blur, range(24), 2, processes=True, batch=2)] == list(range(24))
print("threads after", cv2.getNumThreads())
"""


def test_stream_map_processes_work_after_opencv_used_its_thread_pool_and_restore_its_threads():
    """A process forked while OpenCV's thread pool runs hangs in its first OpenCV call: stream_map shuts
    that pool while its worker processes live, and gives OpenCV its thread count back afterwards."""
    done = subprocess.run([sys.executable, "-c", OPENCV_FORK_SCRIPT], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["threads", "after", "2"]


WORKER_POOL_SCRIPT = """
import os, sys, time
from vtgen.io.images import stream_map

def slow(i):
    time.sleep(0.05)
    return i

if sys.argv[1] == "stuck":  # each worker hangs in its first OpenCV call, as after a fork during OpenCV's pool
    import cv2
    parent, set_threads = os.getpid(), cv2.setNumThreads
    cv2.setNumThreads = lambda n: time.sleep(3600) if os.getpid() != parent else set_threads(n)
print(os.getpid(), flush=True)
for _ in stream_map(slow, range(10_000), 2, processes=True):
    pass
"""


@pytest.mark.parametrize("workers", ["working", "stuck"])
def test_stream_map_worker_processes_end_when_their_parent_is_killed(workers):
    import signal
    import subprocess
    import sys
    import time

    import psutil

    from conftest import ENV

    parent = subprocess.Popen([sys.executable, "-c", WORKER_POOL_SCRIPT, workers], stdout=subprocess.PIPE, text=True,
                              env=ENV)
    try:
        int(parent.stdout.readline())
        deadline = time.monotonic() + 60
        while len(workers := psutil.Process(parent.pid).children()) < 2:
            assert time.monotonic() < deadline, "the pool's workers never started"
            time.sleep(0.05)
    finally:
        parent.send_signal(signal.SIGKILL)  # as Snakemake or a user would: no chance to shut the pool down
        parent.wait()
    gone, alive = psutil.wait_procs(workers, timeout=10)
    assert not alive, f"orphaned workers still running: {[p.pid for p in alive]}"


def traced_peak(func) -> int:
    """Peak of the memory Python (and numpy) allocated while ``func`` ran, in bytes."""
    import gc
    import tracemalloc

    gc.collect()
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        func()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.slow
def test_ingest_memory_grows_with_metadata_not_with_pixels(tmp_path):
    side, n = 96, 60
    small = write_jpegs(tmp_path / "small", n, side)
    large = write_jpegs(tmp_path / "large", 4 * n, side)
    ingest_dataset(small, "generic", workers=2, progress=False)  # warm-up: lazy imports and caches
    peaks = {count: traced_peak(lambda root=root: ingest_dataset(root, "generic", workers=2, progress=False))
             for count, root in ((n, small), (4 * n, large))}
    per_image = (peaks[4 * n] - peaks[n]) / (3 * n)
    # Holding each decoded image (27 KiB at 96 px), or a queue entry per file, would add at least
    # 2 KiB per extra image; streaming adds only its row of metadata (about 0.5 KiB here).
    assert per_image < 1500, f"ingest peak memory grows {per_image:.0f} bytes per image: {peaks}"
    assert per_image < side * side * 3 / 16


# --- datasets described by a pattern or a manifest ------------------------------------------------

from pathlib import Path

from vtgen.core.grouping import near_duplicate_pairs
from vtgen.io.decoding import _decode_fast
from vtgen.io.layouts import compile_layout
from vtgen.stages.pairs import assign_splits

VT60 = Path(__file__).resolve().parents[2] / "shared" / "data" / "vt60_subset"
VT60_DATASET = {"source": "pattern", "pattern": "{modality}/{class}/{instance}/{name}.jpg",
                "near_duplicates": {"rms": 1.5, "relative": 0.05}}


def tiles_of(manifest: pd.DataFrame) -> pd.DataFrame:
    """A tile table as the roi stage writes it, one full-frame tile per image (for splitting and pairing)."""
    return manifest.assign(image_path=manifest["path"], tile_path=manifest["path"], tile_index=0, box_x=0, box_y=0,
                           box_w=manifest["width"], box_h=manifest["height"], frame_w=manifest["width"],
                           frame_h=manifest["height"])


@pytest.fixture
def vt60_root() -> Path:
    if not VT60.is_dir():
        pytest.skip(f"vt60 subset not found at {VT60}")
    return VT60


@pytest.mark.slow
def test_vt60_described_by_a_pattern_keeps_instances_whole(vt60_root):
    manifest, quarantine, summary = ingest_dataset(vt60_root, VT60_DATASET, workers=2, progress=False)
    assert len(manifest) == 720 and quarantine.empty and summary["ignored_top_level_files"] == ["SOURCE.md"]
    assert len(summary["classes"]) == 10 and summary["modalities"] == ["tactile", "visual"]
    counts = manifest.groupby("modality").size().to_dict()
    assert counts == {"tactile": 480, "visual": 240}  # touch -> tactile, vision -> visual
    assert summary["translation"]["possible"]
    # the group of every image is its instance; near-duplicate frames exist and stay in their instance's group
    instance = manifest["class"] + "/" + manifest["path"].str.split("/").str[-2]
    assert (manifest["group"] == instance).all()
    dup = summary["duplicates"]
    assert dup["near_duplicate_files"] > 0 and dup["exact_duplicate_files"] == 0
    assert dup["groups_before_merging"] == dup["groups_after_merging"] == 20
    assert summary["groups_per_class"] == {c: 2 for c in summary["classes"]}
    tiles = tiles_of(manifest)
    for seed in range(5):
        tiles["split"], _ = assign_splits(tiles, 0.0, 0.5, seed)
        assert (tiles.groupby(["class", "group"])["split"].nunique() == 1).all()
        assert set(tiles.loc[tiles["split"] == "test", "group"].str.split("/").str[0]) == set(summary["classes"])


@pytest.mark.slow
def test_vt60_exact_and_near_duplicates_merge_their_groups(vt60_root, tmp_path):
    # two classes linked file by file; a touch frame of 01_stapler/01 also appears under 01_stapler/02,
    # and a re-encoded copy (PNG, one pixel changed) of a frame of 02_bottleempty/01 under 02_bottleempty/02
    # (copies, not links: a link that leads outside dataset.path is refused, see test_ingest_reads_only_inside_...)
    root = tmp_path / "vt60"
    for path in sorted(vt60_root.glob("*/0[12]_*/*/*.jpg")):
        copy = root / path.relative_to(vt60_root)
        copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, copy)
    stapler = sorted((vt60_root / "touch" / "01_stapler" / "01").glob("*.jpg"))
    shutil.copy(stapler[0], root / "touch/01_stapler/02/copy.jpg")
    from PIL import Image

    bottle = sorted((vt60_root / "touch" / "02_bottleempty" / "01").glob("*.jpg"))
    near = np.asarray(Image.open(bottle[5])).astype(np.int16)
    near[0, 0] += 40
    Image.fromarray(np.clip(near, 0, 255).astype(np.uint8)).save(root / "touch/02_bottleempty/02/near.png")
    dataset = {**VT60_DATASET, "pattern": "{modality}/{class}/{instance}/{name}.{ext}"}
    manifest, _, summary = ingest_dataset(root, dataset, workers=2, progress=False)
    dup = summary["duplicates"]
    assert dup["exact_duplicate_files"] == 2  # the frame and its copy
    assert dup["near_duplicate_files"] == 2  # the frame and its re-encoded copy
    assert dup["groups_before_merging"] == 4 and dup["groups_after_merging"] == 2  # each class's instances merged
    assert (manifest.groupby("class")["group"].nunique() == 1).all()
    # without near-duplicate merging only the exact copy joins groups
    _, _, exact_only = ingest_dataset(root, {**dataset, "near_duplicates": {"rms": 0, "relative": 0.05}}, progress=False)
    assert exact_only["duplicates"]["groups_after_merging"] == 3


def test_near_duplicate_rule_separates_copies_from_flat_textures():
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (16, 16)).astype(np.uint8)
    noisy = np.clip(base + rng.integers(-1, 2, (16, 16)), 0, 255).astype(np.uint8)
    flat_a = np.full((16, 16), 120, np.uint8) + rng.integers(0, 2, (16, 16)).astype(np.uint8)
    flat_b = np.full((16, 16), 120, np.uint8) + rng.integers(0, 2, (16, 16)).astype(np.uint8)
    other = rng.integers(0, 256, (16, 16)).astype(np.uint8)
    thumbs = np.stack([base, other, flat_a, noisy, flat_b])
    # the copy with +-1 noise is found; two flat thumbnails within 1 grey level are not (no contrast to compare)
    assert near_duplicate_pairs(thumbs, 1.5, 0.05) == [(0, 3)]
    assert near_duplicate_pairs(thumbs, 0, 0.05) == []
    assert near_duplicate_pairs(thumbs, 1.5, 10.0) == [(0, 3), (2, 4)]  # without the contrast rule they would be
    many = np.repeat(base[None], 100, axis=0)  # more than one block: every pair once
    assert len(near_duplicate_pairs(many, 1.5, 0.05)) == 100 * 99 // 2


def write_dataset(root: Path, files: dict[str, np.ndarray]) -> Path:
    for rel, array in files.items():
        write_image(root / rel, array)
    return root


def test_duplicates_never_straddle_splits(tmp_path):
    rng = np.random.default_rng(3)
    files = {}
    for i in range(12):
        image = random_rgb(rng, 48)
        files[f"cotton/visual/s{i:02d}.png"] = image
        files[f"cotton/tactile/s{i:02d}.png"] = random_rgb(rng, 48)
    # byte-identical copy of s00 under another name, and a near-identical copy of s01 (one pixel changed)
    files["cotton/visual/copy_of_s00.png"] = files["cotton/visual/s00.png"]
    near = files["cotton/visual/s01.png"].copy()
    near[0, 0] ^= 1
    files["cotton/visual/near_s01.png"] = near
    files["wool/visual/s00.png"] = files["cotton/visual/s00.png"]  # the same bytes in another class: label noise
    files["wool/tactile/s00.png"] = random_rgb(rng, 48)
    root = write_dataset(tmp_path / "raw", files)
    manifest, _, summary = ingest_dataset(root, "generic", progress=False)
    dup = summary["duplicates"]
    assert dup["exact_duplicate_files"] == 2 and dup["near_duplicate_files"] == 2
    assert dup["files_identical_to_another_class"] == 1
    assert any("different classes" in w for w in summary["warnings"])
    group = dict(zip(manifest["path"].str.split("raw/").str[1], manifest["group"]))
    assert group["cotton/visual/copy_of_s00.png"] == group["cotton/visual/s00.png"] == group["cotton/tactile/s00.png"]
    assert group["cotton/visual/near_s01.png"] == group["cotton/visual/s01.png"]
    assert group["wool/visual/s00.png"] != group["cotton/visual/s00.png"]  # never merged across classes
    tiles = tiles_of(manifest)
    path_split = {}
    for seed in range(20):
        tiles["split"], _ = assign_splits(tiles, 0.2, 0.3, seed)
        split = dict(zip(tiles["path"].str.split("raw/").str[1], tiles["split"]))
        assert split["cotton/visual/copy_of_s00.png"] == split["cotton/visual/s00.png"]
        assert split["cotton/visual/near_s01.png"] == split["cotton/visual/s01.png"]
        path_split[seed] = split["cotton/visual/s00.png"]
    assert len(set(path_split.values())) > 1  # the merged group does move between splits with the seed


def test_pattern_with_regex_fields_reads_a_vitac_like_layout(tmp_path):
    rng = np.random.default_rng(0)
    root = write_dataset(tmp_path / "raw", {
        "11t_test/131_1.jpg": random_rgb(rng), "11t/121_2.jpg": random_rgb(rng), "11v/IMG_2460_3.jpg": random_rgb(rng),
        "12touch/5_1.jpg": random_rgb(rng)})
    dataset = {"source": "pattern", "pattern": "{class}{modality}{split}/{source}_{tile}.jpg",
               "fields": {"class": r"\d+", "modality": "[a-z]+?", "split": "(?:_test)?", "frame": r"[A-Z_]*\d+"}}
    manifest, quarantine, summary = ingest_dataset(root, dataset, progress=False)
    rows = manifest.set_index(manifest["path"].str.split("raw/").str[1])
    assert rows.loc["11t_test/131_1.jpg", ["class", "modality", "split"]].tolist() == ["11", "tactile", "test"]
    assert rows.loc["11v/IMG_2460_3.jpg", ["modality", "split", "source"]].tolist() == ["visual", "train", "11/IMG_2460"]
    assert rows.loc["12touch/5_1.jpg", "modality"] == "tactile"
    assert quarantine.empty


def test_pattern_mistakes_are_refused_naming_the_key(tmp_path):
    for pattern, words in [("{modality}/{name}.jpg", "no {class} field"),
                           ("{class}/{name}.jpg", "no {modality} field"),
                           ("{class}/{modality/{name}.jpg", "dataset.pattern"),
                           ("{class}/{modality:[t}/{name}.jpg", "invalid regular expression"),
                           ("../{class}/{modality}/{name}.jpg", "relative to dataset.path")]:
        with pytest.raises(ValueError, match=re.escape(words)):
            compile_layout({"source": "pattern", "pattern": pattern})
    with pytest.raises(ValueError, match="dataset.fields.class"):
        compile_layout({"source": "pattern", "pattern": "{class}/{modality}/{name}", "fields": {"class": "("}})
    with pytest.raises(ValueError, match="dataset.modality_aliases.depth"):
        compile_layout({"source": "pattern", "pattern": "{class}/{modality}/{n}", "modality_aliases": {"depth": "sound"}})
    with pytest.raises(IngestError, match="dataset.pattern: required"):
        ingest_dataset(tmp_path, {"source": "pattern"}, progress=False)


def test_modality_aliases_unknown_names_and_one_modality_folder(tmp_path):
    rng = np.random.default_rng(1)
    root = write_dataset(tmp_path / "raw", {"a/GelSight/1.png": random_rgb(rng), "a/Depth/1.png": random_rgb(rng),
                                            "a/RGB/1.png": random_rgb(rng)})
    manifest, quarantine, _ = ingest_dataset(root, {"source": "pattern", "pattern": "{class}/{modality}/{name}.png"},
                                             progress=False)
    assert sorted(manifest["modality"]) == ["tactile", "visual"]
    assert "not a modality folder: 'Depth'" in quarantine["reason"].iloc[0]
    manifest, quarantine, _ = ingest_dataset(root, {"source": "pattern", "pattern": "{class}/{modality}/{name}.png",
                                                    "modality_aliases": {"depth": "visual"}}, progress=False)
    assert len(manifest) == 3 and quarantine.empty
    flat = write_dataset(tmp_path / "flat", {"cotton_1.png": random_rgb(rng), "wool_2.png": random_rgb(rng)})
    manifest, _, summary = ingest_dataset(flat, {"source": "pattern", "pattern": "{class}_{name}.png",
                                                 "modality": "touch"}, progress=False)
    assert sorted(manifest["class"]) == ["cotton", "wool"] and set(manifest["modality"]) == {"tactile"}
    assert not summary["translation"]["possible"] and "no usable visual" in summary["translation"]["reason"]


def test_user_manifest_lists_the_images(tmp_path):
    rng = np.random.default_rng(2)
    root = write_dataset(tmp_path / "raw", {"x/1.png": random_rgb(rng), "x/2.png": random_rgb(rng),
                                            "y/3.png": random_rgb(rng), "stray.png": random_rgb(rng)})
    pd.DataFrame({"path": ["x/1.png", "x/2.png", "y/3.png", "missing.png"], "modality": ["touch", "camera", "t", "v"],
                  "class": ["a", "a", "b", "b"], "pair": ["p1", "p1", "", ""], "instance": ["i1", "i1", "i2", "i2"]}
                 ).to_csv(root / "files.csv", index=False)
    manifest, quarantine, summary = ingest_dataset(root, {"source": "manifest", "manifest": "files.csv"}, progress=False)
    assert sorted(manifest["modality"]) == ["tactile", "tactile", "visual"]
    assert set(manifest.loc[manifest["class"] == "a", "pair_key"]) == {"a/p1"}
    assert set(manifest["group"]) == {"a/i1", "b/i2"}
    reasons = dict(zip(quarantine["path"].str.split("raw/").str[1], quarantine["reason"]))
    assert "not listed in the manifest" in reasons["stray.png"] and "missing.png" in reasons
    assert summary["ignored_top_level_files"] == []
    pd.DataFrame({"file": ["x/1.png"]}).to_csv(root / "bad.csv", index=False)
    with pytest.raises(IngestError, match=r"bad.csv lacks column\(s\) path, class, modality"):
        ingest_dataset(root, {"source": "manifest", "manifest": "bad.csv"}, progress=False)


def test_ingest_reads_only_inside_the_dataset_folder_and_names_what_it_refuses(tmp_path, capsys):
    """Issue 25: links (files or folders) and manifest rows that resolve outside dataset.path, and names with
    control characters, are quarantined with the reason; a link that stays inside is read."""
    outside = write_jpegs(tmp_path / "elsewhere", 4)
    root = write_jpegs(tmp_path / "raw", 8)
    (root / "c0" / "visual" / "to_a_file.jpg").symlink_to(outside / "c0" / "visual" / "s00000.jpg")
    (root / "c9").symlink_to(outside / "c1")
    (root / "c1" / "visual" / "inside.jpg").symlink_to(root / "c1" / "visual" / "s00001.jpg")
    shutil.copy(outside / "c0" / "visual" / "s00000.jpg", root / "c0" / "visual" / "two\nlines.jpg")
    pattern = {"source": "pattern", "pattern": "{class}/{modality}/{name}.jpg"}
    run_ingest(root, pattern, tmp_path / "out", workers=1)
    manifest = pd.read_parquet(tmp_path / "out/manifest.parquet")
    quarantine = pd.read_parquet(tmp_path / "out/quarantine.parquet")
    reasons = {str(Path(p).relative_to(root)): r for p, r in zip(quarantine["path"], quarantine["reason"])}
    assert reasons == {
        "c0/visual/to_a_file.jpg": f"symbolic link to a file outside dataset.path (it resolves to {outside}/c0/visual/"
                                   f"s00000.jpg): not read; every image a run reads must lie inside dataset.path, so "
                                   f"that a change to it reruns the run",
        "c9": f"symbolic link to a folder outside dataset.path (it resolves to {outside}/c1): not read; every image a "
              f"run reads must lie inside dataset.path, so that a change to it reruns the run",
        "c0/visual/two\nlines.jpg": "file name contains a control character (a line break, tab or other), which would "
                                    "reach tile file names and tables; rename it to use it"}
    assert len(manifest) == 9 and str(root / "c1" / "visual" / "inside.jpg") in set(manifest["path"])
    assert "quarantined x1: symbolic link to a file outside dataset.path" in capsys.readouterr().out

    pd.DataFrame({"path": ["c0/visual/s00000.jpg", str(outside / "c0/visual/s00000.jpg"), "../elsewhere/c1/visual/s00001.jpg",
                           "../../../../etc/passwd", "c9/visual/s00001.jpg"],
                  "modality": ["visual"] * 5, "class": ["c0", "c0", "c1", "c1", "c1"]}).to_csv(root / "files.csv",
                                                                                            index=False)
    manifest, quarantine, _ = ingest_dataset(root, {"source": "manifest", "manifest": "files.csv"}, progress=False)
    assert list(manifest["path"]) == [str(root / "c0/visual/s00000.jpg")]
    refused = quarantine[quarantine["reason"].str.contains("outside dataset.path")]
    assert sorted(refused["reason"].str.extract(r"^(files.csv line \d+|symbolic link to a \w+)")[0]) == [
        "files.csv line 3", "files.csv line 4", "files.csv line 5", "files.csv line 6", "symbolic link to a file",
        "symbolic link to a folder"]
    assert quarantine["path"].is_unique  # c9, listed and found by the walk, gives one row


def test_fast_decoding_gives_what_read_rgb8_gives(tmp_path):
    rng = np.random.default_rng(4)
    for name, array in [("g.jpg", rng.integers(0, 256, (20, 30), dtype=np.uint8)), ("c.png", random_rgb(rng, 17)),
                        ("g.png", rng.integers(0, 256, (9, 5), dtype=np.uint8)), ("c.jpg", random_rgb(rng, 40))]:
        path = write_image(tmp_path / name, array)
        fast = _decode_fast(path.read_bytes(), str(path))
        full = read_rgb8(path)
        assert fast is not None, name
        assert (fast[1], fast[2], fast[3]) == (full.note, full.channels, full.bit_depth)
        grey = fast[0] if fast[0].ndim == 2 else fast[0]
        assert grey.shape[:2] == full.rgb.shape[:2]
        assert np.array_equal(fast[0] if fast[0].ndim == 3 else np.repeat(fast[0][:, :, None], 3, 2), full.rgb)
    # anything else is left to read_rgb8
    write_image(tmp_path / "p.png", random_rgb(rng), convert="P")
    write_image(tmp_path / "named.png", random_rgb(rng))
    (tmp_path / "named.png").rename(tmp_path / "named.jpg")  # PNG data named .jpg
    assert _decode_fast((tmp_path / "p.png").read_bytes(), str(tmp_path / "p.png")) is None
    assert _decode_fast((tmp_path / "named.jpg").read_bytes(), str(tmp_path / "named.jpg")) is None


def test_failed_ingest_keeps_quarantine_and_summary_and_replaces_old_output(tmp_path):
    rng = np.random.default_rng(5)
    good = write_dataset(tmp_path / "good", {"a/visual/1.png": random_rgb(rng), "a/tactile/1.png": random_rgb(rng)})
    out = tmp_path / "ingest"
    run_ingest(good, "generic", out)
    assert (out / "manifest.parquet").is_file()
    bad = tmp_path / "bad"
    (bad / "a" / "visual").mkdir(parents=True)
    (bad / "a" / "visual" / "broken.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(IngestError, match="no usable images left"):
        run_ingest(bad, "generic", out)
    assert not (out / "manifest.parquet").exists()  # no stale manifest from the other dataset
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and "no usable images" in summary["error"] and summary["root"] == str(bad)
    quarantine = pd.read_parquet(out / "quarantine.parquet")
    assert list(quarantine["path"]) == [str(bad / "a" / "visual" / "broken.png")]
    # a description error too leaves a failed summary, not the old manifest
    run_ingest(good, "generic", out)
    with pytest.raises(IngestError, match="dataset folder does not exist"):
        run_ingest(tmp_path / "absent", "generic", out)
    assert not (out / "manifest.parquet").exists()
    assert json.loads((out / "summary.json").read_text())["status"] == "failed"


def test_grey_thumbnail_equals_the_cv2_area_resize():
    """The integer-shrink shortcut (cell sums by cv2.reduce) gives OpenCV's INTER_AREA thumbnail exactly."""
    import cv2

    from vtgen.core.grouping import grey_thumbnail, THUMB

    rng = np.random.default_rng(0)
    for shape in [(480, 640), (640, 480), (480, 480), (240, 320), (256, 256), (48, 48), (32, 32), (300, 300), (1024, 768)]:
        for image in (rng.integers(0, 256, shape, dtype=np.uint8), np.full(shape, 255, np.uint8),
                      (rng.integers(0, 2, shape) * 255).astype(np.uint8), rng.integers(0, 256, (*shape, 3), dtype=np.uint8)):
            grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
            assert np.array_equal(grey_thumbnail(image), cv2.resize(grey, (THUMB, THUMB), interpolation=cv2.INTER_AREA))
