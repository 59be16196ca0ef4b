"""Tests of the pure ROI functions: geometry, tiles, markers and contact regions.

Real GelSight tiles come from ../shared/data/vitac_cloth11 (never copied into the repo);
the tests that need them are skipped when that folder is missing.
"""

from dataclasses import FrozenInstanceError
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from skimage.filters import threshold_otsu

from vtgen.core.roi import _close_ellipse, Box, centre_box, contact_box, cut_tile, cut_tiles_without_markers, marker_mask, remove_markers, tile_boxes

DATA = Path(__file__).resolve().parents[2] / "shared/data/vitac_cloth11"
TACTILE = sorted((DATA / "11t").glob("*.jpg")) + sorted((DATA / "11t_test").glob("*.jpg"))
needs_data = pytest.mark.skipif(not TACTILE, reason=f"real ViTac tiles not found under {DATA}")

GEL_COLOUR = (168, 172, 190)  # light bluish grey of a flat, untouched gel
DOT_COLOUR = (35, 35, 45)


def load(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def iou(a: Box, b: Box) -> float:
    ix = max(0, min(a.x + a.w, b.x + b.w) - max(a.x, b.x))
    iy = max(0, min(a.y + a.h, b.y + b.h) - max(a.y, b.y))
    inter = ix * iy
    return inter / (a.w * a.h + b.w * b.h - inter)


def draw_dots(image: np.ndarray, centres, radius: int) -> np.ndarray:
    for c in centres:
        cv2.circle(image, c, radius, DOT_COLOUR, -1, lineType=cv2.LINE_AA)
    return image


def dot_grid(size: int, spacing: int = 40) -> list[tuple[int, int]]:
    return [(x, y) for y in range(spacing // 2, size, spacing) for x in range(spacing // 2, size, spacing)]


def gel_frame(texture: np.ndarray | None = None, rect: Box | None = None, size: int = 256) -> np.ndarray:
    """A synthetic GelSight frame: flat gel with sensor noise, optional texture in ``rect``, dots everywhere."""
    rng = np.random.default_rng(0)
    frame = np.zeros((size, size, 3)) + GEL_COLOUR + rng.normal(0, 1.5, (size, size, 3))
    if rect is not None:
        frame[rect.y : rect.y + rect.h, rect.x : rect.x + rect.w] = texture[: rect.h, : rect.w]
    frame = np.clip(frame, 0, 255).astype(np.uint8)
    return draw_dots(frame, dot_grid(size), radius=5)


# --- Box ---------------------------------------------------------------------------------


def test_box_validates_and_is_frozen():
    Box(0, 0, 1, 1)
    for bad in [(0, 0, 0, 5), (0, 0, 5, 0), (-1, 0, 5, 5), (0, -1, 5, 5), (0, 0, -3, 5)]:
        with pytest.raises(ValueError):
            Box(*bad)
    with pytest.raises(FrozenInstanceError):
        Box(0, 0, 1, 1).x = 3


def test_box_fits():
    box = Box(10, 20, 30, 40)
    assert box.fits(40, 60)
    assert not box.fits(39, 60)
    assert not box.fits(40, 59)


# --- centre_box --------------------------------------------------------------------------


def test_centre_box_is_centred_square_of_the_asked_fraction():
    assert centre_box(300, 200) == Box(50, 0, 200, 200)
    assert centre_box(300, 200, 0.5) == Box(100, 50, 100, 100)
    assert centre_box(200, 300, 0.33) == Box(67, 117, 66, 66)  # floor(0.33 * 200) = 66
    assert centre_box(101, 100) == Box(0, 0, 100, 100)  # odd leftover pixel goes right


@pytest.mark.parametrize("fraction", [0.0, -0.1, 1.01])
def test_centre_box_rejects_fraction_out_of_range(fraction):
    with pytest.raises(ValueError):
        centre_box(100, 100, fraction)


def test_centre_box_rejects_empty_square():
    with pytest.raises(ValueError):
        centre_box(10, 10, 0.05)


# --- tile_boxes --------------------------------------------------------------------------


def test_tile_boxes_non_overlapping_grid_in_row_major_order():
    boxes = tile_boxes(256, 256, 64)
    assert len(boxes) == 16
    assert boxes[0] == Box(0, 0, 64, 64)
    assert boxes[1] == Box(64, 0, 64, 64)  # along the row first
    assert boxes[4] == Box(0, 64, 64, 64)
    assert boxes[-1] == Box(192, 192, 64, 64)


def test_tile_boxes_grid_is_centred_and_in_bounds():
    boxes = tile_boxes(100, 70, 30)
    assert len(boxes) == 3 * 2
    assert all(b.fits(100, 70) and b.w == b.h == 30 for b in boxes)
    left, top = min(b.x for b in boxes), min(b.y for b in boxes)
    right, bottom = 100 - max(b.x + b.w for b in boxes), 70 - max(b.y + b.h for b in boxes)
    assert (left, right) == (5, 5) and (top, bottom) == (5, 5)
    boxes = tile_boxes(101, 30, 30)  # odd leftover: 11 px, 5 left, 6 right
    assert [b.x for b in boxes] == [5, 35, 65]


def test_tile_boxes_stride_overlaps():
    boxes = tile_boxes(64, 64, 32, stride=16)
    assert len(boxes) == 9
    assert [b.x for b in boxes[:3]] == [0, 16, 32]
    assert [b.y for b in boxes[::3]] == [0, 16, 32]
    overlap = boxes[0].x + boxes[0].w - boxes[1].x
    assert overlap == 16


@pytest.mark.parametrize(("tile", "stride"), [(0, None), (-4, None), (65, None), (16, 0)])
def test_tile_boxes_rejects_bad_sizes(tile, stride):
    with pytest.raises(ValueError):
        tile_boxes(64, 80, tile, stride)


# --- cut_tile ----------------------------------------------------------------------------


def test_cut_tile_sizes_and_interpolation():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (120, 200, 3), dtype=np.uint8)
    box = Box(40, 10, 100, 100)
    crop = image[10:110, 40:140]
    same = cut_tile(image, box, 100)
    assert same.dtype == np.uint8 and np.array_equal(same, crop)
    same[0, 0] = 0  # a copy, not a view
    assert np.array_equal(image[10:110, 40:140], crop)
    small = cut_tile(image, box, 50)
    assert small.shape == (50, 50, 3) and small.dtype == np.uint8
    assert np.array_equal(small, cv2.resize(crop, (50, 50), interpolation=cv2.INTER_AREA))
    large = cut_tile(image, box, 256)
    assert large.shape == (256, 256, 3) and large.dtype == np.uint8
    assert np.array_equal(large, cv2.resize(crop, (256, 256), interpolation=cv2.INTER_CUBIC))
    assert cut_tile(image, Box(0, 0, 200, 120), 64).shape == (64, 64, 3)


def test_cut_tile_rejects_box_that_does_not_fit():
    image = np.zeros((120, 200, 3), np.uint8)
    with pytest.raises(ValueError, match=r"Box\(x=150.*200x120"):
        cut_tile(image, Box(150, 0, 60, 60), 32)
    with pytest.raises(ValueError):
        cut_tile(image, Box(0, 100, 30, 30), 32)


def test_cut_tile_rejects_non_rgb_uint8():
    with pytest.raises(ValueError, match="uint8 RGB"):
        cut_tile(np.zeros((64, 64), np.uint8), Box(0, 0, 8, 8), 8)
    with pytest.raises(ValueError, match="uint8 RGB"):
        cut_tile(np.zeros((64, 64, 3), np.float32), Box(0, 0, 8, 8), 8)


# --- marker_mask and remove_markers ------------------------------------------------------


def gradient_background(size: int = 256) -> np.ndarray:
    ramp = np.linspace(0, 1, size)
    image = np.empty((size, size, 3))
    image[..., 0] = 90 + 110 * ramp[None, :]
    image[..., 1] = 150 + 20 * ramp[:, None]
    image[..., 2] = 120 + 80 * ramp[:, None]
    image += np.random.default_rng(2).normal(0, 2, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def test_marker_mask_finds_dots_at_known_positions_on_a_gradient():
    size, radius = 256, 4
    rng = np.random.default_rng(3)
    centres = [(x + int(rng.integers(-4, 5)), y + int(rng.integers(-4, 5))) for x, y in dot_grid(size, 32)]
    image = draw_dots(gradient_background(size), centres, radius)
    mask = marker_mask(image)
    assert mask.dtype == bool and mask.shape == (size, size)

    yy, xx = np.mgrid[:size, :size]
    distance = np.min([np.hypot(xx - cx, yy - cy) for cx, cy in centres], axis=0)
    dots = distance <= radius
    assert mask[dots].mean() > 0.9  # recall of dot pixels
    false = mask & (distance > radius + 3)  # the mask is dilated by 2 px: allow that margin
    assert false.sum() < 0.002 * size * size
    assert all(mask[cy, cx] for cx, cy in centres)


def test_marker_mask_is_empty_on_smooth_background():
    assert marker_mask(gradient_background()).mean() < 0.001
    flat = np.full((128, 128, 3), GEL_COLOUR, np.uint8)
    assert not marker_mask(flat).any()


@needs_data
@pytest.mark.parametrize("path", TACTILE[::7], ids=lambda p: p.name)
def test_marker_mask_on_real_tile_is_a_regular_grid_of_dots(path):
    mask = marker_mask(load(path))
    count, _, stats, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8))
    areas = stats[1:, cv2.CC_STAT_AREA]
    assert 10 <= count - 1 <= 200
    assert 0.02 < mask.mean() < 0.15
    typical = (areas > 0.5 * np.median(areas)) & (areas < 2 * np.median(areas))
    assert typical.sum() >= 9  # most dots have similar sizes (the rest are cut by the border)
    points = centroids[1:][typical]
    gaps = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.fill_diagonal(gaps, np.inf)
    nearest = gaps.min(axis=1)
    assert np.all((nearest > 0.85 * np.median(nearest)) & (nearest < 1.3 * np.median(nearest)))


@needs_data
@pytest.mark.parametrize("path", TACTILE[::7], ids=lambda p: p.name)
def test_remove_markers_paints_dots_out_and_leaves_the_rest(path):
    frame = load(path)
    before = frame.copy()
    cleaned = remove_markers(frame)
    assert np.array_equal(frame, before)  # input untouched
    assert cleaned.dtype == np.uint8 and cleaned.shape == frame.shape and cleaned is not frame

    mask = marker_mask(frame)
    surroundings = cv2.medianBlur(frame, 41).astype(float)  # a reference with the dots blurred away
    error_before = np.abs(frame[mask] - surroundings[mask]).mean()
    error_after = np.abs(cleaned[mask] - surroundings[mask]).mean()
    assert error_after < 0.4 * error_before

    assert np.array_equal(cleaned[~mask], frame[~mask])  # only marker pixels change


def test_remove_markers_without_dots_returns_an_equal_copy():
    image = gradient_background(64)
    cleaned = remove_markers(image)
    assert np.array_equal(cleaned, image) and cleaned is not image


# --- the fast paths: the same marker mask, and tiles as if cut from the cleaned frame ------


def direct_marker_mask(frame: np.ndarray, max_dot: int | None = None) -> np.ndarray:
    """The marker mask computed directly, as marker_mask's docstring says (its first implementation)."""
    height, width = frame.shape[:2]
    max_dot = max(3, min(height, width) // 8) if max_dot is None else max_dot
    grey = cv2.medianBlur(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), 5)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (int(1.25 * max_dot) // 2 * 2 + 1,) * 2)
    closed = cv2.morphologyEx(grey, cv2.MORPH_CLOSE, kernel).astype(np.float64)
    depth = (closed - grey) / np.maximum(closed, 1)
    if depth.max() <= 0.2:
        return np.zeros((height, width), bool)
    level = max(threshold_otsu(depth), 0.2)
    deeper = max(threshold_otsu(depth[depth > level]), level)

    def dot_like(candidates):
        count, labels, stats, _ = cv2.connectedComponentsWithStats(candidates.astype(np.uint8), connectivity=8)
        keep = np.zeros(count, bool)
        for i in range(1, count):
            x, y, w, h, area = stats[i]
            on_border = x == 0 or y == 0 or x + w == width or y + h == height
            elongated = max(w, h) > 3 * min(w, h) and not on_border
            keep[i] = 9 <= area <= max_dot**2 and not elongated and area >= 0.4 * w * h
        return keep[labels]

    dots = dot_like(depth > level) | dot_like(depth > deeper)
    return cv2.dilate(dots.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))).astype(bool)


def rendered_gelsight(seed: int, size: int = 256) -> np.ndarray:
    """A GelSight frame from vtgen.synthetic (markers on a rendered fabric), through JPEG like the ViTac tiles."""
    from vtgen.core.synthetic import FABRICS, render_gelsight, render_patch

    rng = np.random.default_rng(seed)
    frame = render_gelsight(render_patch(FABRICS[seed % len(FABRICS)], size, rng), rng)
    _, jpeg = cv2.imencode(".jpg", frame[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    return np.ascontiguousarray(cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[..., ::-1])


@pytest.fixture(scope="module")
def rendered_frames() -> list[np.ndarray]:
    return [rendered_gelsight(seed) for seed in range(6)]


@pytest.mark.parametrize("size", [1, 3, 5, 9, 13, 21, 23, 25, 41, 63])
def test_close_ellipse_equals_the_cv2_closing(size):
    rng = np.random.default_rng(size)
    for shape in [(61, 83), (8, 5), (256, 256)]:
        grey = rng.integers(0, 256, shape, dtype=np.uint8)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        assert np.array_equal(_close_ellipse(grey, size), cv2.morphologyEx(grey, cv2.MORPH_CLOSE, kernel))


def test_marker_mask_equals_the_direct_computation(rendered_frames):
    rng = np.random.default_rng(7)
    dotted = draw_dots(gradient_background(), dot_grid(256, 32), radius=4)
    noise = rng.integers(0, 256, (120, 90, 3), dtype=np.uint8)  # hundreds of components (the int32 label path)
    frames = [*rendered_frames, gel_frame(), dotted, noise, cv2.resize(rendered_frames[0], (150, 97))]
    for frame in frames:
        for max_dot in (None, 6, 20):
            assert np.array_equal(marker_mask(frame, max_dot), direct_marker_mask(frame, max_dot))


@needs_data
def test_marker_mask_equals_the_direct_computation_on_real_tiles():
    for path in TACTILE:
        frame = load(path)
        assert np.array_equal(marker_mask(frame), direct_marker_mask(frame)), path.name


def tile_mask(frame: np.ndarray, box: Box, size: int) -> np.ndarray:
    """Tile pixels that average at least one marker pixel of the frame."""
    inside = marker_mask(frame)[box.y : box.y + box.h, box.x : box.x + box.w]
    return cv2.resize(inside.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA) > 0


# Tiles shrunk 2x (the main job: 128 px centre crop -> 64 px) and 4x (whole frame -> 64 px) are
# inpainted at the tile's resolution. Against cut_tile(remove_markers(frame)), measured on the 30
# real tiles: mean |difference| per tile 0.36 grey levels on average, at most 0.57 (2x, centre and
# tiles); 0.78, at most 1.02 (4x); on rendered frames about half that. A tile cut without marker
# removal differs from the reference by 2 to 5 grey levels (at least 1.9 per tile), so a tolerance
# per tile of 1 (2x) or 1.5 (4x), and of 0.5 (2x) or 1 (4x) on average over the tiles, catches a fast
# path that stops removing the dots or drifts from the reference. Tile pixels that average no marker
# pixel must be identical.
SHRINKING = [("centre", 0.5, 64, 1.0, 0.5), ("tiles", 0.5, 64, 1.0, 0.5), ("centre", 1.0, 64, 1.5, 1.0)]


def check_fast_tiles(frames: list[np.ndarray], visual_crop: str, fraction: float, size: int, tolerance: float,
                     mean_tolerance: float):
    from vtgen.stages.roi import crop_boxes

    differences, raw_differences = [], []
    for frame in frames:
        height, width = frame.shape[:2]
        boxes = crop_boxes(Box(0, 0, width, height), visual_crop, fraction)
        reference = remove_markers(frame)
        for box, tile in zip(boxes, cut_tiles_without_markers(frame, boxes, size)):
            expected = cut_tile(reference, box, size)
            assert tile.shape == expected.shape and tile.dtype == np.uint8
            holes = tile_mask(frame, box, size)
            assert np.array_equal(tile[~holes], expected[~holes])  # no marker pixel under it: exact
            difference = np.abs(tile.astype(int) - expected).mean()
            assert difference <= tolerance, (box, difference)
            differences.append(difference)
            raw_differences.append(np.abs(cut_tile(frame, box, size).astype(int) - expected).mean())
    assert np.mean(differences) <= mean_tolerance
    assert np.mean(raw_differences) > 4 * np.mean(differences)  # far closer than not removing the dots


@pytest.mark.parametrize(("visual_crop", "fraction", "size", "tolerance", "mean_tolerance"), SHRINKING)
def test_cut_tiles_without_markers_is_close_to_cleaning_the_whole_frame(rendered_frames, visual_crop, fraction,
                                                                         size, tolerance, mean_tolerance):
    check_fast_tiles(rendered_frames, visual_crop, fraction, size, tolerance, mean_tolerance)


@needs_data
@pytest.mark.parametrize(("visual_crop", "fraction", "size", "tolerance", "mean_tolerance"), SHRINKING)
@pytest.mark.slow
def test_cut_tiles_without_markers_is_close_to_cleaning_the_whole_real_frame(visual_crop, fraction, size,
                                                                              tolerance, mean_tolerance):
    check_fast_tiles([load(path) for path in TACTILE], visual_crop, fraction, size, tolerance, mean_tolerance)


@pytest.mark.parametrize(
    ("box", "size"),
    [(Box(64, 64, 128, 128), 128), (Box(64, 64, 128, 128), 160), (Box(0, 100, 100, 100), 128),
     (Box(190, 0, 66, 80), 72)],
    ids=str,
)
def test_cut_tiles_without_markers_equals_the_reference_when_not_shrinking(rendered_frames, box, size):
    """A tile as large as its box or larger is inpainted at the frame's resolution around the box: exact."""
    frames = rendered_frames[:3] + ([load(TACTILE[0])] if TACTILE else [])
    for frame in frames:
        (tile,) = cut_tiles_without_markers(frame, [box], size)
        assert np.array_equal(tile, cut_tile(remove_markers(frame), box, size))


def dot_contrasts(tile: np.ndarray, frame: np.ndarray, box: Box, size: int) -> np.ndarray:
    """|grey at each detected dot's centre (3x3 mean) - median grey of a ring just outside the dot|, in the tile."""
    mask = marker_mask(frame)
    count, labels, _, centres = cv2.connectedComponentsWithStats(mask.astype(np.uint8))
    grey = cv2.cvtColor(tile, cv2.COLOR_RGB2GRAY).astype(float)
    scale = size / box.w
    out = []
    for i in range(1, count):
        x, y = int((centres[i][0] - box.x) * scale), int((centres[i][1] - box.y) * scale)
        if not (2 <= x < size - 2 and 2 <= y < size - 2):
            continue
        dot = (labels == i)[box.y : box.y + box.h, box.x : box.x + box.w].astype(np.float32)
        dot = (cv2.resize(dot, (size, size), interpolation=cv2.INTER_AREA) > 0).astype(np.uint8)
        ring = cv2.dilate(dot, np.ones((7, 7), np.uint8)) > cv2.dilate(dot, np.ones((3, 3), np.uint8))
        out.append(abs(grey[y - 1 : y + 2, x - 1 : x + 2].mean() - np.median(grey[ring])))
    return np.array(out)


@pytest.mark.parametrize("real", [False, True], ids=["rendered", "real"])
def test_cut_tiles_without_markers_paints_the_dots_out(rendered_frames, real):
    if real and not TACTILE:
        pytest.skip(f"real ViTac tiles not found under {DATA}")
    frames = [load(path) for path in TACTILE[::3]] if real else rendered_frames
    box, size = Box(64, 64, 128, 128), 64  # the main job's crop
    before, after = [], []
    for frame in frames:
        before.extend(dot_contrasts(cut_tile(frame, box, size), frame, box, size))
        after.extend(dot_contrasts(cut_tiles_without_markers(frame, [box], size)[0], frame, box, size))
    # measured: raw dots 64 to 95 grey levels below their ring; after removal 2 on average, at most 9
    assert len(before) >= 2 * len(frames) and min(before) > 40
    assert np.mean(after) < 5 and max(after) < 16


def test_cut_tiles_without_markers_edge_cases():
    smooth = gradient_background(96)
    boxes = [Box(0, 0, 96, 96), Box(10, 20, 40, 40)]
    assert cut_tiles_without_markers(smooth, [], 32) == []
    for tile, box in zip(cut_tiles_without_markers(smooth, boxes, 32), boxes):
        assert np.array_equal(tile, cut_tile(smooth, box, 32))  # no dots: the plain tiles
    with pytest.raises(ValueError, match="does not fit"):
        cut_tiles_without_markers(smooth, [Box(80, 0, 32, 32)], 16)
    with pytest.raises(ValueError, match="uint8 RGB"):
        cut_tiles_without_markers(smooth[..., 0], boxes, 32)


@needs_data
def test_roi_stage_cuts_marker_free_tiles_from_full_frames(tmp_path):
    """The ROI stage with the main job's settings (full frame, centre crop 0.5, remove_markers) uses the fast path."""
    import pandas as pd

    from vtgen.io.images import read_rgb8
    from vtgen.stages.roi import cut_dataset_tiles

    paths = TACTILE[:4]
    manifest = pd.DataFrame({"path": [str(p) for p in paths], "class": "11", "modality": "tactile", "split": "train",
                             "source": [p.stem for p in paths], "group": [p.stem for p in paths],
                             "pair_key": [p.stem for p in paths], "width": 256, "height": 256})
    roi = {"size": 64, "tactile_box": "full", "remove_markers": True, "visual_crop": "centre", "crop_fraction": 0.5}
    tiles = cut_dataset_tiles(manifest, roi, tmp_path, workers=2, progress=False)
    assert len(tiles) == len(paths) and (tiles[["box_x", "box_y", "box_w", "box_h"]] == [64, 64, 128, 128]).all().all()
    for path, tile_path in zip(paths, tiles["tile_path"]):
        frame = read_rgb8(path).rgb
        written = read_rgb8(tmp_path / tile_path).rgb
        assert np.array_equal(written, cut_tiles_without_markers(frame, [Box(64, 64, 128, 128)], 64)[0])
        reference = cut_tile(remove_markers(frame), Box(64, 64, 128, 128), 64)
        assert np.abs(written.astype(int) - reference).mean() < 1.0


# --- contact_box -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real_texture() -> np.ndarray:
    if not TACTILE:
        pytest.skip(f"real ViTac tiles not found under {DATA}")
    return remove_markers(load(TACTILE[7]))


@needs_data
@pytest.mark.parametrize(
    "rect",
    [Box(70, 50, 120, 140), Box(10, 100, 90, 80), Box(0, 0, 200, 120), Box(120, 120, 136, 136)],
    ids=str,
)
def test_contact_box_recovers_pasted_real_texture(real_texture, rect):
    box = contact_box(gel_frame(real_texture, rect))
    assert iou(box, rect) > 0.9, box


def test_contact_box_recovers_zero_mean_synthetic_texture():
    rng = np.random.default_rng(4)
    rect = Box(40, 60, 150, 110)
    noise = cv2.GaussianBlur(rng.normal(0, 1, (rect.h, rect.w)), (0, 0), 2)
    texture = GEL_COLOUR + (noise / noise.std() * 15)[..., None] * [1.0, 0.8, 0.6]
    assert iou(contact_box(gel_frame(texture, rect)), rect) > 0.9


def test_contact_box_without_contact_gives_whole_frame():
    assert contact_box(gel_frame()) == Box(0, 0, 256, 256)
    assert contact_box(np.full((100, 150, 3), GEL_COLOUR, np.uint8)) == Box(0, 0, 150, 100)


@needs_data
@pytest.mark.parametrize("rect", [Box(60, 60, 60, 60), Box(108, 108, 44, 44)], ids=str)
def test_marker_mask_keeps_dots_that_touch_a_dark_contact_region(real_texture, rect):
    """A contact patch much darker than the gel, about the black-hat kernel's size, must not swallow dots."""
    mask = marker_mask(gel_frame(real_texture, rect))
    assert all(mask[cy, cx] for cx, cy in dot_grid(256))


@needs_data
def test_contact_box_ignores_contact_below_min_fraction(real_texture):
    rect = Box(108, 108, 44, 44)  # 3 % of the frame
    frame = gel_frame(real_texture, rect)
    assert contact_box(frame) == Box(0, 0, 256, 256)
    assert iou(contact_box(frame, min_fraction=0.02), rect) > 0.9


@needs_data
@pytest.mark.parametrize("path", TACTILE, ids=lambda p: p.name)
def test_contact_box_of_all_contact_real_tile_is_whole_frame(path):
    assert contact_box(load(path)) == Box(0, 0, 256, 256)


# --- the ROI stage streams: memory grows with the tile table, not with the pixels ---------------


@pytest.mark.slow
def test_roi_stage_memory_grows_with_the_tile_table_not_with_pixels(tmp_path):
    import gc
    import tracemalloc

    from conftest import write_jpegs
    from vtgen.stages.ingest import ingest_dataset
    from vtgen.stages.roi import cut_dataset_tiles

    side, n = 96, 60
    roi = {"size": 32, "tactile_box": "full", "remove_markers": False, "visual_crop": "centre", "crop_fraction": 1.0}
    manifests = {count: ingest_dataset(write_jpegs(tmp_path / f"raw{count}", count, side), "generic", progress=False)[0]
                 for count in (n, 4 * n)}
    cut_dataset_tiles(manifests[n], roi, tmp_path / "warm", progress=False)  # warm-up: lazy imports and caches
    peaks = {}
    for count, manifest in manifests.items():
        gc.collect()
        tracemalloc.start()
        try:
            tiles = cut_dataset_tiles(manifest, roi, tmp_path / f"tiles{count}", workers=2, progress=False)
            peaks[count] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert len(tiles) == count
    per_image = (peaks[4 * n] - peaks[n]) / (3 * n)
    # One decoded image is 27 KiB and its tile 3 KiB; a row dict and a future per image would be
    # about 3 KiB; the streamed stage keeps only the tile table (a few hundred bytes per tile).
    assert per_image < 1000, f"roi peak memory grows {per_image:.0f} bytes per image: {peaks}"


# --- image_tiles: the per-image rule the stage applies ---------------------------------------------------


@needs_data
@pytest.mark.parametrize("roi", [
    {"size": 64, "tactile_box": "full", "remove_markers": True, "visual_crop": "centre", "crop_fraction": 0.5},
    {"size": 32, "tactile_box": "auto", "remove_markers": True, "visual_crop": "tiles", "crop_fraction": 0.5},
    {"size": 48, "tactile_box": [10, 20, 200, 180], "remove_markers": False, "visual_crop": "centre", "crop_fraction": 1.0},
], ids=["full-clean", "auto-tiles", "fixed"])
def test_image_tiles_gives_the_stage_tiles(tmp_path, roi):
    import pandas as pd

    from vtgen.core.roi import image_tiles
    from vtgen.io.images import read_rgb8
    from vtgen.stages.roi import cut_dataset_tiles

    paths = TACTILE[:2] + sorted((DATA / "11v").glob("*.jpg"))[:1]
    modalities = ["tactile", "tactile", "visual"]
    manifest = pd.DataFrame({"path": [str(p) for p in paths], "class": "11", "modality": modalities, "split": "train",
                             "source": [p.stem for p in paths], "group": [p.stem for p in paths],
                             "pair_key": [p.stem for p in paths], "width": 256, "height": 256})
    table = cut_dataset_tiles(manifest, roi, tmp_path, workers=2, progress=False)
    for path, modality in zip(paths, modalities):
        boxes, tiles, reason = image_tiles(read_rgb8(path).rgb, modality, roi)
        assert reason == "" and tiles and all(t.shape == (roi["size"], roi["size"], 3) for t in tiles)
        rows = table[table["image_path"] == str(path)].sort_values("tile_index")
        assert [Box(*r) for r in rows[["box_x", "box_y", "box_w", "box_h"]].itertuples(index=False)] == boxes
        for tile_path, tile in zip(rows["tile_path"], tiles):
            assert np.array_equal(read_rgb8(tmp_path / tile_path).rgb, tile)


def test_image_tiles_reports_an_image_too_small():
    from vtgen.core.roi import image_tiles

    roi = {"size": 8, "tactile_box": "full", "remove_markers": False, "visual_crop": "centre", "crop_fraction": 0.4}
    boxes, tiles, reason = image_tiles(np.zeros((2, 2, 3), np.uint8), "visual", roi)
    assert (boxes, tiles) == ([], []) and "too small" in reason


# --- round sensors: find_disc, disc_square, regions ------------------------------------------------------

VT60 = Path(__file__).resolve().parents[2] / "shared/data/vt60_subset"
VT60_TOUCH = sorted((VT60 / "touch").glob("*/*/*.jpg"))
needs_vt60 = pytest.mark.skipif(not VT60_TOUCH, reason=f"vt60 touch frames not found under {VT60}")
AUTO = {"size": 64, "tactile_box": "auto", "remove_markers": True, "visual_crop": "centre", "crop_fraction": 0.5}


def disc_frame(centre=(300, 250), radius=180, inside=230, outside=30, shape=(480, 640), texture=0.0, seed=0):
    """A grey frame: a disc of level ``inside`` (plus zero-mean texture of std ``texture``) on ``outside``, sensor noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    disc = (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius**2
    frame = np.full(shape, float(outside)) + rng.normal(0, 2, shape)
    pattern = cv2.GaussianBlur(rng.normal(0, 1, shape), (0, 0), 3)
    frame[disc] = inside + (pattern / pattern.std() * texture)[disc]
    return np.clip(frame, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("kwargs", [
    {},                                                                  # bright disc on dark
    {"inside": 120, "outside": 250, "centre": (215, 225), "radius": 270},  # dark disc on white, cut by the frame (vt60-like)
    {"inside": 128, "outside": 128, "texture": 25.0},                    # a disc of zero-mean texture on flat grey
    {"centre": (128, 120), "radius": 90, "shape": (256, 256)},           # smaller frame, no downscale factor of 4
], ids=["bright", "clipped", "texture", "small"])
def test_find_disc_recovers_centre_and_radius(kwargs):
    from vtgen.core.roi import find_disc

    frame = disc_frame(**kwargs)
    cx, cy = kwargs.get("centre", (300, 250))
    radius = kwargs.get("radius", 180)
    for image in (frame, cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)):
        disc = find_disc(image)
        assert disc.found, disc
        assert abs(disc.cx - cx) <= 3 and abs(disc.cy - cy) <= 3 and abs(disc.radius - radius) <= 3, disc
        assert disc.support > 0.8 and disc.overlap > 0.95


def test_find_disc_tolerates_contact_as_bright_as_the_surround():
    """Contact that whitens part of the disc up to its rim (as on vt60) must not move the fit."""
    from vtgen.core.roi import find_disc

    frame = disc_frame(inside=120, outside=250, centre=(215, 225), radius=270)
    cv2.ellipse(frame, (330, 120), (150, 70), 30, 0, 360, 250, -1)  # a bright contact band reaching the rim
    disc = find_disc(frame)
    assert disc.found and abs(disc.cx - 215) <= 4 and abs(disc.cy - 225) <= 4 and abs(disc.radius - 270) <= 4, disc


def test_gelsight_rectangle_is_no_disc_and_still_a_rectangle():
    from vtgen.core.roi import find_disc, image_roi

    rng = np.random.default_rng(4)
    rect = Box(40, 60, 150, 110)
    noise = cv2.GaussianBlur(rng.normal(0, 1, (rect.h, rect.w)), (0, 0), 2)
    frame = gel_frame(GEL_COLOUR + (noise / noise.std() * 15)[..., None] * [1.0, 0.8, 0.6], rect)
    assert not find_disc(frame).found
    result = image_roi(frame, "tactile", {**AUTO, "remove_markers": False})
    assert result.region.shape == "rectangle" and iou(result.region.box, rect) > 0.9
    assert result.region.box == contact_box(frame) and "no disc" in result.region.note
    cleaned = image_roi(frame, "tactile", AUTO)  # as before round sensors: contact found on the cleaned frame
    assert cleaned.region.box == contact_box(remove_markers(frame))
    assert np.array_equal(cleaned.tiles[0], cut_tile(remove_markers(frame), cleaned.boxes[0], 64))


def test_featureless_frame_falls_back_to_the_whole_frame():
    from vtgen.core.roi import find_disc, image_roi

    flat = np.full((120, 160), 90, np.uint8)
    disc = find_disc(flat)
    assert not disc.found and "flat" in disc.reason and np.isnan(disc.radius)
    result = image_roi(flat, "tactile", AUTO)
    assert result.region.shape == "frame" and result.region.box == Box(0, 0, 160, 120)
    assert "no disc" in result.region.note and "whole frame" in result.region.note
    assert result.boxes == [Box(50, 30, 60, 60)] and np.array_equal(result.tiles[0], np.full((64, 64, 3), 90, np.uint8))


@needs_data
@pytest.mark.parametrize("path", TACTILE[::3], ids=lambda p: p.name)
def test_real_gelsight_tiles_are_no_disc(path):
    from vtgen.core.roi import find_disc

    assert not find_disc(load(path)).found


@pytest.mark.parametrize(("cx", "cy", "r", "width", "height"), [
    (320, 240, 100, 640, 480), (215.3, 224.7, 270, 640, 480), (20, 240, 200, 640, 480), (50, 50, 400, 100, 100)])
def test_disc_square_lies_inside_the_disc_and_the_frame(cx, cy, r, width, height):
    from vtgen.core.roi import Disc, disc_square

    box = disc_square(Disc(cx, cy, r, 1.0, 1.0, True), width, height)
    assert box.fits(width, height) and box.w == box.h
    corners = [(box.x - 0.5, box.y - 0.5), (box.x + box.w - 0.5, box.y - 0.5), (box.x - 0.5, box.y + box.h - 0.5),
               (box.x + box.w - 0.5, box.y + box.h - 0.5)]
    assert all(np.hypot(x - cx, y - cy) <= r + 1 for x, y in corners)
    if 2 * min(cx, width - cx, cy, height - cy) > np.sqrt(2) * r + 2:  # the frame does not cut it: the inscribed square
        assert box.w == int(np.floor(np.sqrt(2) * r))
        assert abs(box.x + box.w / 2 - 0.5 - cx) <= 1 and abs(box.y + box.h / 2 - 0.5 - cy) <= 1


def test_disc_markers_are_painted_out_near_the_crop_only():
    from vtgen.core.roi import image_roi

    frame = disc_frame(inside=200, outside=250, centre=(320, 240), radius=200)
    dots = [(x, y) for y in range(150, 340, 24) for x in range(230, 420, 24)]
    for c in dots:
        cv2.circle(frame, c, 5, 40, -1, lineType=cv2.LINE_AA)
    clean = image_roi(frame, "tactile", AUTO)
    kept = image_roi(frame, "tactile", {**AUTO, "remove_markers": False})
    assert clean.region.shape == "disc" and clean.boxes == kept.boxes
    box = clean.boxes[0]
    scale = 64 / box.w
    centres = [(round((x - box.x + 0.5) * scale - 0.5), round((y - box.y + 0.5) * scale - 0.5)) for x, y in dots
               if box.x + 8 <= x < box.x + box.w - 8 and box.y + 8 <= y < box.y + box.h - 8]
    assert centres
    dark_before = np.mean([kept.tiles[0][y, x, 0] for x, y in centres])
    dark_after = np.mean([clean.tiles[0][y, x, 0] for x, y in centres])
    assert dark_before < 150 and dark_after > 185, (dark_before, dark_after)
    assert (clean.tiles[0][..., 0] == clean.tiles[0][..., 2]).all()


# --- real round-sensor frames: vt60 ---------------------------------------------------------------------


@pytest.mark.slow
@needs_vt60
def test_every_vt60_touch_frame_gets_a_plausible_disc_and_grey_tiles():
    from vtgen.core.roi import image_roi

    shapes, centres, radii = [], [], []
    for path in VT60_TOUCH:
        frame = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        result = image_roi(frame, "tactile", AUTO)
        shapes.append(result.region.shape)
        disc = result.region.disc
        assert disc is not None and np.isfinite(disc.radius), path
        centres.append((disc.cx, disc.cy))
        radii.append(disc.radius)
        assert len(result.tiles) == 1
        tile = result.tiles[0]
        assert (tile[..., 0] == tile[..., 1]).all() and (tile[..., 1] == tile[..., 2]).all()
    shapes, centres, radii = np.array(shapes), np.array(centres), np.array(radii)
    assert (shapes == "disc").mean() >= 0.98, dict(zip(*np.unique(shapes, return_counts=True)))
    found = shapes == "disc"
    # the sensor disc: radius about 270 px, centre about (214, 225), a little left of the 640x480 frame's centre
    assert (np.abs(centres[found] - [320, 240]) <= [0.25 * 640, 0.25 * 480]).all()
    assert (np.abs(radii[found] - 270) <= 15).all()
    assert np.ptp(centres[found], axis=0).max() <= 60  # one sensor: the disc barely moves between frames
    # every disc found lies over the frame's middle, so its crop does too
    assert (shapes[~found] == "rectangle").all() or (shapes[~found] == "frame").all()


@needs_vt60
def test_read_for_roi_gives_the_pixels_of_read_rgb8():
    from vtgen.io.images import read_rgb8
    from vtgen.stages.roi import read_for_roi

    paths = VT60_TOUCH[::60] + sorted((VT60 / "vision").glob("*/*/*.jpg"))[::60] + TACTILE[::10]
    for path in paths:
        fast, reference = read_for_roi(path), read_rgb8(path).rgb
        if fast.ndim == 2:
            fast = np.repeat(fast[:, :, None], 3, axis=2)
        assert np.array_equal(fast, reference), path


@needs_vt60
def test_roi_stage_on_vt60_records_discs_and_one_channel(tmp_path):
    import json

    import pandas as pd

    from vtgen.core.roi import image_tiles
    from vtgen.io.images import read_rgb8
    from vtgen.stages.roi import REGION_COLUMNS, run_roi

    touch = VT60_TOUCH[::40]
    vision = sorted((VT60 / "vision").glob("*/*/*.jpg"))[::40]
    paths = touch + vision
    manifest = pd.DataFrame({"path": [str(p) for p in paths], "class": [p.parts[-3] for p in paths],
                             "modality": ["tactile"] * len(touch) + ["visual"] * len(vision), "split": "train",
                             "source": [p.stem for p in paths], "group": [p.parts[-2] for p in paths],
                             "pair_key": [p.stem for p in paths], "width": 0, "height": 0})
    manifest.to_parquet(tmp_path / "manifest.parquet")
    summary = run_roi(tmp_path / "manifest.parquet", AUTO, tmp_path / "roi", workers=2)
    assert summary["channels"] == {"tactile": 1, "visual": 3}
    assert summary["regions"]["visual"] == {"frame": len(vision)}
    assert summary["regions"]["tactile"].get("disc", 0) >= len(touch) - 1
    written = json.loads((tmp_path / "roi/summary.json").read_text())
    assert written["channels"] == summary["channels"]
    regions = pd.read_parquet(tmp_path / "roi/regions.parquet")
    assert list(regions.columns) == REGION_COLUMNS and len(regions) == len(paths)
    assert list(regions["image_path"]) == [str(p) for p in paths]
    discs = regions[regions["shape"] == "disc"]
    assert (discs["disc_support"] >= 0.6).all() and discs["disc_found"].all() and (abs(discs["disc_radius"] - 270) < 15).all()
    assert regions.loc[regions["modality"] == "visual", "disc_found"].isna().all()
    tiles = pd.read_parquet(tmp_path / "roi/tiles.parquet")
    for path, modality in zip(paths[::3], manifest["modality"][::3]):
        boxes, expected, reason = image_tiles(read_rgb8(path).rgb, modality, AUTO)  # RGB in: the stage decoded grey
        rows = tiles[tiles["image_path"] == str(path)].sort_values("tile_index")
        assert reason == "" and [Box(*r) for r in rows[["box_x", "box_y", "box_w", "box_h"]].itertuples(index=False)] == boxes
        for tile_path, tile in zip(rows["tile_path"], expected):
            assert np.array_equal(read_rgb8(tmp_path / "roi/tiles" / tile_path).rgb, tile)


# --- speed-ups that must not change the results (issue 16) ------------------------------------------------


@pytest.mark.parametrize("factor", [2, 3, 4, 8])
def test_area_downscale_equals_the_cv2_area_resize(factor):
    from vtgen.core.roi import _area_downscale

    rng = np.random.default_rng(factor)
    for shape in [(480, 640), (120, 160), (64, 96), (8, 8)]:
        size = (shape[1] // factor, shape[0] // factor)
        for image in (rng.integers(0, 256, shape, dtype=np.uint8), np.full(shape, 255, np.uint8),
                      (rng.integers(0, 2, shape) * 255).astype(np.uint8), disc_frame(shape=shape, radius=min(shape) // 3,
                                                                                    centre=(shape[1] // 2, shape[0] // 2))):
            assert np.array_equal(_area_downscale(image, size), cv2.resize(image, size, interpolation=cv2.INTER_AREA))


@pytest.mark.parametrize("remove_markers", [True, False])
def test_grey_frames_give_the_tiles_of_their_rgb_replica(remove_markers):
    """A grey frame stays one channel through the disc and marker work: same discs and tiles as its RGB copy."""
    from vtgen.core.roi import image_roi

    rng = np.random.default_rng(3)
    roi = {**AUTO, "remove_markers": remove_markers}
    inpainted = 0
    for seed in range(12):
        frame = disc_frame(inside=int(rng.integers(150, 240)), outside=250, centre=(320, 240), radius=200, seed=seed,
                           texture=float(rng.uniform(0, 10)))
        for _ in range(int(rng.integers(0, 60))):
            centre = (int(rng.integers(200, 440)), int(rng.integers(120, 360)))
            cv2.circle(frame, centre, int(rng.integers(2, 7)), int(rng.integers(20, 90)), -1, lineType=cv2.LINE_AA)
        grey, rgb = image_roi(frame, "tactile", roi), image_roi(cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB), "tactile", roi)
        assert grey.region == rgb.region and grey.boxes == rgb.boxes
        assert all(np.array_equal(a, b) for a, b in zip(grey.tiles, rgb.tiles))
        plain = image_roi(frame, "tactile", {**roi, "remove_markers": False})
        inpainted += not np.array_equal(plain.tiles[0], grey.tiles[0])
    assert inpainted >= 4 if remove_markers else inpainted == 0  # the inpainting path was taken


@needs_vt60
def test_find_disc_on_real_frames_equals_the_direct_computation(monkeypatch):
    """On 20 real vt60 frames the fast downscale gives exactly the discs of find_disc on cv2.resize's image."""
    import vtgen.core.roi as core

    frames = [cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) for path in VT60_TOUCH[::24]]
    assert len(frames) == 20
    fast = [core.find_disc(frame) for frame in frames]
    monkeypatch.setattr(core, "_area_downscale", lambda grey, size: cv2.resize(grey, size, interpolation=cv2.INTER_AREA))
    for frame, disc in zip(frames, fast):
        direct = core.find_disc(frame)
        assert disc == direct and disc.found
