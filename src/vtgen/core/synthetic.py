"""Procedural, ViTac-like synthetic visual-tactile fabric dataset (SYNTHETIC data).

Each sample is one physical patch of cloth: a height field (yarn geometry) and an
albedo (dye and print). Two renderers look at the same patch:

- :func:`render_visual`: a macro photo, albedo times Lambert shading of the relief under an
  oblique light plus ambient, with occlusion in the gaps, blur, vignetting and sensor noise.
- :func:`render_gelsight`: a GelSight frame, the elastomer pressed onto the relief (only the
  top of the relief touches, the gel smooths it), its normals shaded by a red, a green and a
  blue light from three azimuths over the flat-gel colour, a grid of dark marker dots, noise.
  The tactile image never sees the albedo.

:func:`vtgen.stages.render.render_dataset` writes the project's generic layout, either aligned (visual and
tactile of one patch, paired by name) or unaligned like ViTac (independent patches of the
same class). Everything is vectorised numpy and OpenCV; each sample draws from its own
generator, derived from ``(seed, class index, sample index)``, so the output does not depend
on the number of worker processes.

Scale: features are sized in pixels for a 256-pixel tile (yarns of 6-18 px, GelSight markers
about 68 px apart, like the real ViTac tiles) and scaled by ``sqrt(size / 256)``, so a small
tile still resolves yarns (at 64 px a yarn is 3-9 px) and a large one shows more cloth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np


FABRICS: tuple[str, ...] = (
    "plain_weave",
    "twill_2_1",
    "twill_3_1",
    "satin",
    "basket_weave",
    "rib_knit",
    "jersey_knit",
    "denim",
    "corduroy",
    "herringbone",
    "felt",
    "printed",
)

MIN_SIZE = 16


@dataclass(frozen=True)
class Patch:
    """One physical patch of cloth.

    height: (H, W) float32 relief in [0, 1] (1 = top of the highest yarn).
    albedo: (H, W, 3) float32 linear RGB reflectance in [0, 1].
    """

    height: np.ndarray
    albedo: np.ndarray

    def __post_init__(self) -> None:
        h, a = self.height, self.albedo
        if h.ndim != 2 or a.shape != h.shape + (3,):
            raise ValueError(f"Patch needs height (H, W) and albedo (H, W, 3); got {h.shape} and {a.shape}")


# --------------------------------------------------------------------------- small helpers


def _pixel_scale(size: int) -> float:
    """Pixels per 'reference pixel' of a 256-px tile (see module docstring)."""
    return float(np.sqrt(size / 256.0))


def _linear(srgb: Sequence[float]) -> np.ndarray:
    """8-bit sRGB triple -> linear RGB in [0, 1] (gamma 2.2)."""
    return (np.asarray(srgb, np.float32) / 255.0) ** 2.2


def _dye(srgb: Sequence[float], rng: np.random.Generator, spread: float = 1.0) -> np.ndarray:
    """A class colour with per-sample dye variation (brightness and per-channel tint), linear RGB."""
    tint = np.exp(rng.normal(0.0, 0.05 * spread, 3) + rng.normal(0.0, 0.10 * spread))
    return np.clip(_linear(srgb) * tint, 0.0, 1.0).astype(np.float32)


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _lowfreq(size: int, cells: int, rng: np.random.Generator, rows: int | None = None) -> np.ndarray:
    """Smooth random field of shape (rows or size, size), zero mean, unit std, about `cells` blobs across."""
    grid = rng.standard_normal((cells + 1, cells + 1)).astype(np.float32)
    field = cv2.resize(grid, (size, rows or size), interpolation=cv2.INTER_CUBIC)
    return (field - field.mean()) / (field.std() + 1e-6)


def _periodic_noise(rng: np.random.Generator, n: int = 64) -> np.ndarray:
    """An n x n white-noise texture, sampled later with wrap-around."""
    return rng.standard_normal((n, n)).astype(np.float32)


def _sample(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sample of a periodic texture at float coordinates (texels)."""
    th, tw = tex.shape
    mx = np.mod(x, tw).astype(np.float32)
    my = np.mod(y, th).astype(np.float32)
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _fabric_coords(
    size: int, rng: np.random.Generator, period_u: float, period_v: float, angle_deg: float, wobble: float = 0.12
) -> tuple[np.ndarray, np.ndarray]:
    """Fabric coordinates in yarn periods: u across the warp ends, v along them.

    The grid is rotated by `angle_deg`, gently distorted (real cloth is never perfectly
    regular) and shifted by a random phase.
    """
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) - (size - 1) / 2.0
    t = np.deg2rad(angle_deg)
    xr = np.cos(t) * x + np.sin(t) * y
    yr = -np.sin(t) * x + np.cos(t) * y
    xr = xr + wobble * period_u * _lowfreq(size, 3, rng)
    yr = yr + wobble * period_v * _lowfreq(size, 3, rng)
    u = xr / period_u + rng.uniform(0.0, 64.0)
    v = yr / period_v + rng.uniform(0.0, 64.0)
    return u.astype(np.float64), v.astype(np.float64)


def _yarn_profile(f: np.ndarray, width: float) -> np.ndarray:
    """Rounded cross-section of a yarn centred at f = 0.5 of its cell, `width` = fraction of the cell."""
    d = np.abs(f - 0.5) / (width / 2.0)
    return np.clip(1.0 - d * d, 0.0, 1.0) ** 0.6


def _finish(height: np.ndarray, albedo: np.ndarray, rng: np.random.Generator, fuzz: float = 0.12) -> Patch:
    """Add hairiness (soft bumps a few pixels wide, scaled by `fuzz`), normalise the relief to [0, 1]
    (robust top) and pack a Patch."""
    size = height.shape[1]
    white = rng.standard_normal(height.shape).astype(np.float32)
    bumps = cv2.GaussianBlur(white, (0, 0), 1.5 * _pixel_scale(size))
    height = height * (1.0 + fuzz * bumps / (bumps.std() + 1e-6))
    h = height - height.min()
    top = np.percentile(h, 99.5)
    h = np.clip(h / max(top, 1e-6), 0.0, 1.0)
    return Patch(height=h.astype(np.float32), albedo=np.clip(albedo, 0.0, 1.0).astype(np.float32))


# --------------------------------------------------------------------------- woven fabrics


def _interlace(weave: np.ndarray, i: np.ndarray, j: np.ndarray, f: np.ndarray, along_v: bool) -> np.ndarray:
    """Smoothly interpolated weave state (1 = warp over weft) along a yarn.

    Along a warp end (`along_v`), the state changes between weft crossings i and i +- 1;
    along a weft pick, between warp crossings j and j +- 1. `f` is the fractional position
    in the current cell; the curve passes through the state at each cell centre.
    """
    n, m = weave.shape
    step = np.where(f >= 0.5, 1, -1)
    s0 = weave[i % n, j % m]
    s1 = weave[(i + step) % n, j % m] if along_v else weave[i % n, (j + step) % m]
    w = _smoothstep(np.abs(f - 0.5))  # 0 at the own centre, 0.5 at the cell border
    return s0 + (s1 - s0) * w


def _woven(
    size: int,
    rng: np.random.Generator,
    weave: np.ndarray,
    *,
    period: float,
    width: float,
    warp_rgb: Sequence[float],
    weft_rgb: Sequence[float],
    angle: float = 0.0,
    sink: float = 0.45,
    fibre: float = 0.12,
    tone: float = 0.05,
) -> Patch:
    """Render a woven patch from a weave matrix (rows = weft picks, columns = warp ends, 1 = warp on top).

    Per-sample jitter: zoom, warp and weft spacing, yarn width, rotation, fibre noise, dye.
    """
    weave = np.asarray(weave, np.float32)
    zoom = _pixel_scale(size) * np.exp(rng.normal(0.0, 0.08))
    pu = period * zoom * rng.uniform(0.92, 1.08)
    pv = period * zoom * rng.uniform(0.92, 1.08)
    wu = float(np.clip(width * rng.uniform(0.9, 1.1), 0.5, 0.98))
    wv = float(np.clip(width * rng.uniform(0.9, 1.1), 0.5, 0.98))
    u, v = _fabric_coords(size, rng, pu, pv, angle + rng.normal(0.0, 6.0))
    j = np.floor(u).astype(np.int64)
    i = np.floor(v).astype(np.int64)
    fu, fv = u - j, v - i

    warp_over = _interlace(weave, i, j, fv, along_v=True)
    weft_over = 1.0 - _interlace(weave, i, j, fu, along_v=False)
    tex = _periodic_noise(rng)
    fib_warp = _sample(tex, u * 6.0, v * 0.8)  # fibres run along the warp (v)
    fib_weft = _sample(tex, v * 6.0 + 17.0, u * 0.8 + 31.0)
    twist = rng.uniform(2.5, 4.0)  # ply twist: faint diagonal stripes on each yarn
    hw = _yarn_profile(fu, wu) * (sink + (1 - sink) * warp_over)
    hw = hw * (1 + fibre * fib_warp + 0.05 * np.sin(2 * np.pi * (fu + twist * v)))
    hf = _yarn_profile(fv, wv) * (sink + (1 - sink) * weft_over)
    hf = hf * (1 + fibre * fib_weft + 0.05 * np.sin(2 * np.pi * (fv + twist * u)))
    warp_top = (hw >= hf)[..., None]
    height = np.maximum(hw, hf)

    warp_tone = 1 + tone * rng.standard_normal(64)[j % 64]
    weft_tone = 1 + tone * rng.standard_normal(64)[i % 64]
    warp_c = _dye(warp_rgb, rng)
    weft_c = warp_c if tuple(weft_rgb) == tuple(warp_rgb) else _dye(weft_rgb, rng)
    a_warp = warp_c * (warp_tone * (1 + 0.08 * fib_warp))[..., None]
    a_weft = weft_c * (weft_tone * (1 + 0.08 * fib_weft))[..., None]
    albedo = np.where(warp_top, a_warp, a_weft)
    return _finish(height, albedo, rng)


def _twill(over: int, under: int, direction: int = 1) -> np.ndarray:
    """Twill weave matrix: warp over `over` picks and under `under`, stepping one end per pick."""
    n = over + under
    r, c = np.mgrid[0:n, 0:n]
    return ((c - direction * r) % n < over).astype(np.float32)


def _plain_weave(size: int, rng: np.random.Generator) -> Patch:
    cotton = (205, 195, 175)
    return _woven(size, rng, [[1, 0], [0, 1]], period=10, width=0.8, warp_rgb=cotton, weft_rgb=cotton)


def _twill_2_1(size: int, rng: np.random.Generator) -> Patch:
    return _woven(size, rng, _twill(2, 1), period=8, width=0.9, warp_rgb=(165, 145, 100), weft_rgb=(150, 132, 92))


def _twill_3_1(size: int, rng: np.random.Generator) -> Patch:
    return _woven(size, rng, _twill(3, 1), period=7, width=0.92, warp_rgb=(72, 88, 115), weft_rgb=(95, 105, 120))


def _satin(size: int, rng: np.random.Generator) -> Patch:
    """5-end warp-faced satin: long smooth floats, one interlacing per five picks."""
    r, c = np.mgrid[0:5, 0:5]
    weave = (c != (2 * r) % 5).astype(np.float32)
    return _woven(size, rng, weave, period=6, width=0.97, warp_rgb=(218, 172, 178), weft_rgb=(200, 160, 165),
                  sink=0.7, fibre=0.05, tone=0.02)


def _basket_weave(size: int, rng: np.random.Generator) -> Patch:
    """2/2 basket: pairs of ends and picks interlace like one yarn of a plain weave."""
    weave = np.kron([[1, 0], [0, 1]], np.ones((2, 2)))
    return _woven(size, rng, weave, period=9, width=0.95, warp_rgb=(192, 172, 136), weft_rgb=(150, 128, 95))


def _denim(size: int, rng: np.random.Generator) -> Patch:
    """3/1 warp-faced twill, indigo warp and white weft, slubby (uneven) yarns."""
    return _woven(size, rng, _twill(3, 1, direction=-1), period=9, width=0.9, warp_rgb=(38, 58, 108),
                  weft_rgb=(225, 220, 205), tone=0.12, fibre=0.16)


def _herringbone(size: int, rng: np.random.Generator) -> Patch:
    """2/2 twill whose diagonal reverses every `k` ends (zig-zag columns)."""
    k = int(rng.integers(4, 7))
    left, right = _twill(2, 2, 1), _twill(2, 2, -1)
    cols = [left[:, c % 4] if (c // k) % 2 == 0 else right[:, c % 4] for c in range(2 * k)]
    weave = np.stack(cols, axis=1)
    return _woven(size, rng, weave, period=7, width=0.9, warp_rgb=(68, 68, 72), weft_rgb=(178, 172, 160))


# --------------------------------------------------------------------------- knits


def _knit_face(u: np.ndarray, v: np.ndarray, lean: float = 0.3) -> np.ndarray:
    """Face of a knit: in every stitch cell two leaning legs form a 'V'; legs overlap the next course."""
    d = np.array([lean, 1.0]) / np.hypot(lean, 1.0)  # direction of the left leg (down and inwards)
    fu = u - np.floor(u) - 0.5
    h = np.zeros_like(u)
    for dr in (-1, 0, 1):  # legs reach into the neighbouring courses
        y = v - (np.floor(v) + dr + 0.5)
        for sx in (-1.0, 1.0):  # left and right leg
            x = sx * fu + 0.2
            a = x * d[0] + y * d[1]
            b = -x * d[1] + y * d[0]
            h = np.maximum(h, np.clip(1.0 - (a / 0.68) ** 2 - (b / 0.2) ** 2, 0.0, 1.0) ** 0.5)
    return h


def _purl_face(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Reverse side of a knit: rows of horizontal loop heads."""
    fu = u - np.floor(u) - 0.5
    fv = v - np.floor(v) - 0.5
    return np.clip(1.0 - (fu / 0.55) ** 2 - (fv / 0.3) ** 2, 0.0, 1.0) ** 0.5


def _knit(size: int, rng: np.random.Generator, *, rib: int, width: float, course: float,
          rgb: Sequence[float]) -> Patch:
    """Weft knit; `rib` > 0 alternates `rib` knit wales with `rib` recessed purl wales."""
    zoom = _pixel_scale(size) * np.exp(rng.normal(0.0, 0.08))
    pu = width * zoom * rng.uniform(0.92, 1.08)
    pv = course * zoom * rng.uniform(0.92, 1.08)
    u, v = _fabric_coords(size, rng, pu, pv, rng.normal(0.0, 6.0), wobble=0.15)
    tex = _periodic_noise(rng)
    fibre = _sample(tex, u * 5.0, v * 5.0)
    h = _knit_face(u, v, lean=rng.uniform(0.25, 0.4))
    j = np.floor(u).astype(np.int64)
    if rib:
        is_knit = (j % (2 * rib)) < rib
        ridge = 0.5 + 0.5 * np.cos(2 * np.pi * ((u / (2 * rib)) % 1.0 - rib / (4 * rib)))
        h = np.where(is_knit, h * (0.7 + 0.3 * ridge), 0.5 * _purl_face(u, v))
    h = h * (1 + 0.1 * fibre)
    colour = _dye(rgb, rng)
    wale_tone = 1 + 0.04 * rng.standard_normal(64)[j % 64]
    albedo = colour * (wale_tone * (1 + 0.07 * fibre))[..., None]
    return _finish(h, albedo, rng)


def _jersey_knit(size: int, rng: np.random.Generator) -> Patch:
    return _knit(size, rng, rib=0, width=10, course=8, rgb=(176, 150, 150))


def _rib_knit(size: int, rng: np.random.Generator) -> Patch:
    return _knit(size, rng, rib=2, width=8, course=8, rgb=(140, 36, 56))


# --------------------------------------------------------------------------- pile, non-woven, print


def _corduroy(size: int, rng: np.random.Generator) -> Patch:
    """Raised, rounded pile ribs (wales) with fuzzy tips over a flat plain-weave ground."""
    zoom = _pixel_scale(size) * np.exp(rng.normal(0.0, 0.08))
    pw = 18 * zoom * rng.uniform(0.9, 1.1)
    u, v = _fabric_coords(size, rng, pw, pw, rng.normal(0.0, 6.0), wobble=0.05)
    fu = u - np.floor(u)
    tex = _periodic_noise(rng)
    pile = _sample(tex, u * 14.0, v * 3.0)  # short tufts, a bit longer along the wale
    rib = _yarn_profile(fu, rng.uniform(0.75, 0.88)) ** 0.7
    ground = 0.12 * (0.5 + 0.5 * np.sin(2 * np.pi * u * 4) * np.sin(2 * np.pi * v * 4))
    h = np.maximum(rib * (0.88 + 0.12 * pile), ground)
    colour = _dye((128, 84, 50), rng)
    shade = (0.72 + 0.28 * rib) * (1 + 0.06 * pile)
    return _finish(h, colour * shade[..., None], rng)


def _felt(size: int, rng: np.random.Generator) -> Patch:
    """Matted random fibres (no yarn grid) over soft lumps."""
    s = _pixel_scale(size) * np.exp(rng.normal(0.0, 0.08))
    canvas = np.zeros((size, size), np.uint8)
    n = int(size * size / 10)
    layers = 4
    for k in range(layers):  # later layers lie on top: brighter = higher
        m = n // layers
        start = rng.uniform(-10, size + 10, (m, 2))
        ang = rng.uniform(0, np.pi, m)
        length = rng.uniform(6, 22, m) * s
        d = np.stack([np.cos(ang), np.sin(ang)], 1) * length[:, None]
        bend = np.stack([-d[:, 1], d[:, 0]], 1) * rng.normal(0, 0.15, (m, 1))
        pts = np.stack([start, start + d / 2 + bend, start + d], 1)
        pts = np.round(pts * 16).astype(np.int32).reshape(m, 3, 1, 2)
        cv2.polylines(canvas, list(pts), False, int(110 + 48 * k), 1, cv2.LINE_AA, shift=4)
    fibres = cv2.GaussianBlur(canvas.astype(np.float32) / 255.0, (0, 0), 0.6 * s + 0.3)
    lumps = _lowfreq(size, 6, rng)
    h = 0.8 * fibres + 0.06 * lumps
    colour = _dye((58, 116, 78), rng)
    albedo = colour * (0.85 + 0.2 * fibres + 0.05 * lumps)[..., None]
    return _finish(h, albedo, rng, fuzz=0.05)


_INKS = ((200, 40, 50), (40, 70, 170), (235, 190, 40), (50, 140, 70), (230, 120, 40),
         (120, 60, 150), (30, 140, 140), (30, 30, 35), (230, 110, 160))


def _print_layer(size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A procedural print: (ink colour (H, W, 3) linear RGB, coverage (H, W) in [0, 1]).

    Motif (flowers, dots or stripes), its scale, angle and inks are drawn per sample,
    independently of the weave underneath.
    """
    zoom = _pixel_scale(size) * np.exp(rng.normal(0.0, 0.1))
    inks = np.stack([_dye(_INKS[k], rng, 0.5) for k in rng.choice(len(_INKS), 3, replace=False)])
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    t = rng.uniform(0, np.pi)
    xr, yr = np.cos(t) * x + np.sin(t) * y, -np.sin(t) * x + np.cos(t) * y
    motif = rng.choice(["flowers", "dots", "stripes"])
    if motif == "stripes":
        p = 22 * zoom * rng.uniform(0.8, 1.3)
        band = np.floor(xr / p).astype(np.int64) + int(rng.integers(0, 1000))
        table = rng.integers(0, 4, 16)  # 0 = unprinted ground
        idx = table[band % 16]
        cover = cv2.GaussianBlur((idx > 0).astype(np.float32), (0, 0), 0.6)  # soft edges
        ink = cv2.GaussianBlur(inks[np.maximum(idx - 1, 0)], (0, 0), 0.6)
        return ink, cover
    p = (58 if motif == "flowers" else 26) * zoom * rng.uniform(0.85, 1.2)
    gu, gv = xr / p + rng.uniform(0, 50), yr / p + rng.uniform(0, 50)
    row = np.floor(gv).astype(np.int64)
    gu = gu + 0.5 * (row % 2)  # staggered lattice
    col = np.floor(gu).astype(np.int64)
    cell = (row % 32) * 32 + (col % 32)
    jitter = rng.uniform(-0.15, 0.15, (1024, 2)) if motif == "flowers" else np.zeros((1024, 2))
    dx = (gu - col - 0.5 - jitter[cell, 0]) * p
    dy = (gv - row - 0.5 - jitter[cell, 1]) * p
    r = np.hypot(dx, dy)
    if motif == "dots":
        radius = p * rng.uniform(0.18, 0.32)
        cover = np.clip(radius - r + 0.5, 0, 1)
        ink = inks[rng.integers(0, 2, 1024)[cell]]
        return ink, cover.astype(np.float32)
    petals = rng.integers(5, 7, 1024)[cell]
    phase = rng.uniform(0, 2 * np.pi, 1024)[cell]
    size_r = p * rng.uniform(0.26, 0.36, 1024)[cell]
    theta = np.arctan2(dy, dx)
    outline = size_r * (0.45 + 0.55 * np.abs(np.cos(petals * theta / 2 + phase)))
    petal = np.clip(outline - r + 0.5, 0, 1)
    centre = np.clip(0.22 * size_r - r + 0.5, 0, 1)
    petal_ink = inks[rng.integers(0, 2, 1024)[cell]]
    ink = petal_ink * (1 - centre)[..., None] + inks[2] * centre[..., None]
    return ink, np.maximum(petal, centre).astype(np.float32)


def _printed(size: int, rng: np.random.Generator) -> Patch:
    """A white plain weave carrying a procedural colour print (the print has no relief)."""
    base = _woven(size, rng, [[1, 0], [0, 1]], period=7, width=0.9, warp_rgb=(236, 232, 224),
                        weft_rgb=(236, 232, 224), fibre=0.08, tone=0.03)
    ink, cover = _print_layer(size, rng)
    ink = ink * (0.9 + 0.1 * base.height)[..., None]  # dye soaks less into the gaps: slightly lighter print
    albedo = base.albedo * (1 - cover[..., None]) + ink * cover[..., None]
    return Patch(height=base.height, albedo=np.clip(albedo, 0, 1).astype(np.float32))


_GENERATORS: dict[str, Callable[[int, np.random.Generator], Patch]] = {
    "plain_weave": _plain_weave,
    "twill_2_1": _twill_2_1,
    "twill_3_1": _twill_3_1,
    "satin": _satin,
    "basket_weave": _basket_weave,
    "rib_knit": _rib_knit,
    "jersey_knit": _jersey_knit,
    "denim": _denim,
    "corduroy": _corduroy,
    "herringbone": _herringbone,
    "felt": _felt,
    "printed": _printed,
}
assert tuple(_GENERATORS) == FABRICS


# --------------------------------------------------------------------------- public rendering API


def render_patch(fabric: str, size: int, rng: np.random.Generator) -> Patch:
    """Render one random patch of `fabric` at `size` x `size` pixels.

    Raises ValueError for an unknown fabric (naming it and the valid ones) or size < 16.
    """
    if fabric not in _GENERATORS:
        raise ValueError(f"unknown fabric {fabric!r}; valid fabrics: {', '.join(FABRICS)}")
    if int(size) != size or size < MIN_SIZE:
        raise ValueError(f"size must be an integer >= {MIN_SIZE}, got {size!r}")
    return _GENERATORS[fabric](int(size), rng)


def _to_uint8_srgb(linear: np.ndarray) -> np.ndarray:
    return np.round(np.clip(linear, 0.0, 1.0) ** (1 / 2.2) * 255.0).astype(np.uint8)


def _normals(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normals (nx, ny, nz) of a surface z(x, y) given in pixels; y points down."""
    gx = cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
    gy = cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
    norm = np.sqrt(gx * gx + gy * gy + 1.0)
    return -gx / norm, -gy / norm, 1.0 / norm


def _light(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    a, e = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], np.float32)


def render_visual(patch: Patch, rng: np.random.Generator) -> np.ndarray:
    """Macro photo of the patch: (H, W, 3) uint8 sRGB.

    albedo x (ambient + Lambert under one oblique light) x cavity occlusion, then defocus
    blur, vignetting, exposure jitter and shot/read noise.
    """
    h = patch.height.astype(np.float32)
    rows, size = h.shape
    s = _pixel_scale(size)
    nx, ny, nz = _normals(h * (3.0 * s))
    light = _light(rng.uniform(200, 250), rng.uniform(35, 55))  # from the upper left
    lambert = np.maximum(nx * light[0] + ny * light[1] + nz * light[2], 0.0)
    cavity = np.clip(cv2.GaussianBlur(h, (0, 0), 2.5 * s) - h, 0.0, None)
    occlusion = np.clip(1.0 - 1.0 * cavity, 0.5, 1.0) * (0.8 + 0.2 * h)
    shade = (0.5 + 0.65 * lambert) * occlusion
    img = patch.albedo * shade[..., None]
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.8, 1.3) * s)
    y, x = np.mgrid[0:rows, 0:size].astype(np.float32)
    cx, cy = np.array([size - 1, rows - 1]) / 2 * (1 + rng.uniform(-0.2, 0.2, 2))
    r2 = ((x - cx) ** 2 + (y - cy) ** 2) / (0.5 * size * rows)
    vignette = 1.0 - rng.uniform(0.1, 0.25) * r2
    img = img * (vignette * rng.uniform(0.9, 1.15))[..., None]
    noise = rng.standard_normal(img.shape).astype(np.float32)
    img = img + noise * np.sqrt(0.0015**2 + 0.0004 * np.clip(img, 0, None))
    return _to_uint8_srgb(img)


GEL_RGB = (138.0, 115.0, 127.0)  # flat-gel colour, tuned so frames match the ViTac GelSight tiles (sRGB, 0-255)
# colours of the red, green and blue LEDs as the camera sees them through the gel (not pure primaries)
_GEL_LIGHTS = np.array([[1.0, 0.25, 0.4], [0.3, 1.0, 0.45], [0.35, 0.35, 1.0]], np.float32)
_GEL_GAIN = 130.0  # 8-bit levels per unit of (n . l) change


def render_gelsight(patch: Patch, rng: np.random.Generator) -> np.ndarray:
    """GelSight frame of the patch: (H, W, 3) uint8 RGB. Depends on the height only, never the albedo.

    The gel is pressed onto the relief: it smooths it (Gaussian low-pass, the elastomer) and
    only the part above the press level touches; the rest stays flat and shows the gel
    colour. The deformed surface's normals are lit by a red, a green and a blue light from
    three azimuths; a regular grid of dark marker dots and sensor noise are added.
    """
    h = patch.height.astype(np.float32)
    rows, size = h.shape
    s = _pixel_scale(size)
    smooth = cv2.GaussianBlur(h, (0, 0), rng.uniform(1.2, 1.8) * s)
    lo, hi = np.percentile(smooth, [1.0, 99.5])
    press = rng.uniform(0.4, 0.7) * (hi - lo)  # depth of relief that touches the gel
    pressure = 1.0 + 0.25 * _lowfreq(size, 2, rng, rows)  # uneven pressing over the frame
    if press > 1e-4:
        contact = np.clip(smooth - (hi - press * pressure), 0.0, None) / press
        contact = cv2.GaussianBlur(contact, (0, 0), 0.7 * s)
    else:  # a flat surface leaves the gel flat
        contact = np.zeros_like(smooth)
    z = contact * (2.2 * s) + _lowfreq(size, 2, rng, rows) * (1.5 * s)  # pixels; plus a gentle global bend
    nx, ny, nz = _normals(z.astype(np.float32))

    y, x = np.mgrid[0:rows, 0:size].astype(np.float32)
    px, py = (x / (size - 1) - 0.5) * 2, (y / (rows - 1) - 0.5) * 2
    base_az = 270.0 + rng.normal(0.0, 5.0)  # red light at the top of the frame
    gel = np.asarray(GEL_RGB, np.float32) + rng.normal(0.0, 3.0, 3)
    img = np.broadcast_to(gel, (rows, size, 3)).astype(np.float32)
    for colour, offset in zip(_GEL_LIGHTS, (0.0, 120.0, 240.0)):
        light = _light(base_az + offset, 35.0)
        shading = nx * light[0] + ny * light[1] + nz * light[2] - light[2]  # 0 on the flat gel
        falloff = 0.18 * (px * light[0] + py * light[1]) / np.hypot(light[0], light[1])
        img = img + (falloff * 128.0 + _GEL_GAIN * shading)[..., None] * colour
    img = cv2.GaussianBlur(img, (0, 0), 0.5 * s)

    # marker dots: rounded squares on a regular grid, slightly displaced by the contact shear
    spacing = 68.0 * s * rng.uniform(0.95, 1.05)
    ox, oy = rng.uniform(0, spacing, 2)
    gx, gy = (x - ox) / spacing, (y - oy) / spacing
    ix, iy = np.round(gx).astype(np.int64), np.round(gy).astype(np.int64)
    cell = (iy % 16) * 16 + (ix % 16)
    shift = rng.normal(0.0, 1.0 * s, (256, 2))
    radius = 7.5 * s * rng.uniform(0.85, 1.15, 256)[cell]
    dx = (gx - ix) * spacing - shift[cell, 0]
    dy = (gy - iy) * spacing - shift[cell, 1]
    d = (np.abs(dx) ** 3 + np.abs(dy) ** 3) ** (1 / 3)
    marker = np.clip(radius - d + 0.5, 0.0, 1.0)
    marker = cv2.GaussianBlur(marker.astype(np.float32), (0, 0), 0.9 * s)[..., None]
    img = img * (1 - marker) + np.array([32.0, 26.0, 30.0], np.float32) * marker + 0.15 * img * marker

    img = img + rng.normal(0.0, 2.5, img.shape)
    return np.round(np.clip(img, 0, 255)).astype(np.uint8)


# --------------------------------------------------------------------------- dataset writer


def sample_rngs(seed: int, class_index: int, index: int) -> list[np.random.Generator]:
    """Four independent generators of one sample: patch (visual), patch (tactile), visual, tactile."""
    children = np.random.SeedSequence([seed, class_index, index]).spawn(4)
    return [np.random.default_rng(c) for c in children]


