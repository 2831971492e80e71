"""Ground textures for the camera renderer: an infinite flat world in metres, mip-mapped for anti-aliased sampling.

A :class:`GroundWorld` is one texture *tile* repeated mirror-periodically (tile, flipped tile, tile, ...) in both
directions, so the world is continuous everywhere and infinite.  Texel ``(col, row)`` of level 0 covers
``m_per_px`` metres; columns grow east, rows grow south (a north-up map), and the world origin ``(N, E) = (0, 0)``
lies at the centre of the tile as given.  The stored value is *intensity* per the paper's eq. 4
(``0.299 R' + 0.587 G' + 0.114 B'``, the weights ``cv2.cvtColor(..., COLOR_BGR2GRAY)`` uses), float32 on the
0-255 scale; an optional BGR colour copy serves pictures only.

Worlds by name (:data:`TEXTURE_NAMES`): the real 10 cm orthophotos ``town_river``, ``dry_grassland``,
``forest_road``, the 5 m NAIP ``farmland`` (RGB of its RGBN bands), ``mosaic`` (the three 10 cm tiles in a
2 x 2 arrangement), and the procedural ``noise`` (multi-octave value noise, well textured), ``uniform_grass``
(near-uniform, tiny variation) and ``water`` (near-uniform with faint ripples).  Origins and licences of the real
tiles: ``sim/data/textures/SOURCES.md``.  No-data areas of a real tile are cut away (largest valid axis-aligned
rectangle), so no-data never enters the world.  No-data is only what is declared (:func:`read_nodata_mask`): the
file's GeoTIFF no-data tag (``GDAL_NODATA``), its alpha channel, or an explicit value given with the tile (the
``nodata_bgr`` of :data:`REAL_TEXTURES`, or a caller's); never a colour, since real ground can be black (open
water in shadow, fresh asphalt).

Mip-mapping: the tile's pyramid (a binomial low-pass and decimation like ``cv2.pyrDown``, but centred between
texels so that the levels nest exactly; mirror border, consistent with the mirror tiling, see :func:`downsample`)
is packed into one *atlas* image, each level with a one-texel mirrored border, so the renderer samples any level
with a single ``cv2.remap`` (bilinear) per frame and blends two levels (trilinear filtering).
Worlds by name are cached per process (:func:`functools.lru_cache`), keyed by ``(name, seed, color)``.
"""

from __future__ import annotations

import functools
import logging
import math
import re
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sim import diskcache

logger = logging.getLogger(__name__)

TEXTURE_DIR = Path(__file__).resolve().parent / "data" / "textures"

REAL_TEXTURES: dict[str, tuple[str, float, tuple[int, int, int] | None]] = {
    # name -> (file in TEXTURE_DIR, metres per texel, explicit no-data colour (B, G, R) or None)
    # The OAM tile's corner outside the survey is written as 0 and the file declares no no-data value: declared here.
    "town_river": ("oam_town_river_10cm.tif", 0.10, (0, 0, 0)),
    "dry_grassland": ("oam_dry_grassland_10cm.tif", 0.10, None),
    "forest_road": ("neon_yell_forest_road_10cm.png", 0.10, None),
    # NAIP declares GDAL_NODATA 0 (no pixel has it in every band; its dark water stays ground)
    "farmland": ("naip_farmland_wetland_2010_5m.tif", 5.0, None),
}
# mosaic cells, row by row: (tile, rotated by 180 deg)
MOSAIC_LAYOUT: tuple[tuple[tuple[str, bool], ...], ...] = (
    (("town_river", False), ("dry_grassland", False)),
    (("forest_road", False), ("town_river", True)),
)
PROCEDURAL_TEXTURES: tuple[str, ...] = ("noise", "uniform_grass", "water")
TEXTURE_NAMES: tuple[str, ...] = (*REAL_TEXTURES, "mosaic", *PROCEDURAL_TEXTURES)

# Smallest side (texels) of the coarsest mip level; the pyramid stops before a level would be smaller.
TOP_LEVEL_MIN_PX = 8
# TIFF tags of GDAL's no-data value (ASCII) and metadata (XML, with each band's colour interpretation).
TIFF_TAG_GDAL_NODATA = 42113
TIFF_TAG_GDAL_METADATA = 42112
# No-data is cut away on a grid of blocks this size; a block touching no-data, or next to a block that does
# (to drop the anti-aliased rim of the no-data edge), is invalid.
NODATA_BLOCK_PX = 16
# Side (texels) of a mosaic cell: each real tile is mirror-extended to fill its cell.
MOSAIC_CELL_PX = 2048
# Procedural tiles: size and texel size.
PROCEDURAL_SIZE_PX = 2048
PROCEDURAL_M_PER_PX = 0.10
# "noise": octaves of value noise with wavelengths 2, 4, ... 2**NOISE_OCTAVES texels, amplitude ~ wavelength**
# NOISE_AMPLITUDE_EXPONENT (small: fine detail stays strong), normalised to this mean and standard deviation (DN).
NOISE_OCTAVES = 9
NOISE_AMPLITUDE_EXPONENT = 0.25
NOISE_MEAN_DN = 128.0
NOISE_STD_DN = 40.0
# "uniform_grass": a flat level with a tiny value-noise variation (std in DN), far below a matcher's texture gate.
UNIFORM_GRASS_MEAN_DN = 105.0
UNIFORM_GRASS_STD_DN = 0.8
# "water": a dark flat level with faint ripples: a few sinusoidal wave trains around one wind direction.
WATER_MEAN_DN = 70.0
WATER_RIPPLE_STD_DN = 1.0
WATER_N_WAVES = 6
WATER_WAVELENGTH_M = (0.4, 2.5)
WATER_SPREAD_RAD = 0.6
# Colours given to procedural textures (BGR) for pictures; intensity is what the estimator sees.
PROCEDURAL_TINT_BGR: dict[str, tuple[float, float, float]] = {
    "noise": (95.0, 125.0, 135.0),
    "uniform_grass": (60.0, 140.0, 90.0),
    "water": (120.0, 95.0, 60.0),
}
_GRAY_WEIGHTS_BGR = np.array([0.114, 0.587, 0.299])  # eq. 4, in OpenCV's BGR channel order
_WORLD_CACHE_SIZE = 8
_SAMPLE_ROW_PX = 4096
_MIP_KERNEL = np.array([1.0, 3.0, 3.0, 1.0], np.float32) / 8.0


@contextmanager
def _quiet_opencv() -> Iterator[None]:
    """Silence OpenCV's log while reading: it warns about every GeoTIFF tag libtiff does not know."""
    old = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(old)


def intensity_from_bgr(bgr: NDArray[np.uint8]) -> NDArray[np.float32]:
    """Intensity per the paper's eq. 4 (0.299 R + 0.587 G + 0.114 B): ``cv2.cvtColor`` BGR2GRAY on float32."""
    return np.asarray(cv2.cvtColor(np.asarray(bgr, dtype=np.float32), cv2.COLOR_BGR2GRAY), dtype=np.float32)


def mirror_wrap(u: NDArray[np.floating], size_px: int) -> NDArray[np.floating]:
    """Fold texel coordinates (texel centres at integers) of a mirror-periodic tile of ``size_px`` texels into
    ``[-0.5, size_px - 0.5]``: the period is ``2 * size_px``, the second half mirrored.  Vectorised, keeps a
    float dtype (``floor`` based: ``np.mod`` is an order of magnitude slower on large arrays)."""
    dt = u.dtype.type if isinstance(u, np.ndarray) and np.issubdtype(u.dtype, np.floating) else np.float64
    q = np.asarray(u + dt(0.5), dtype=dt)
    q *= dt(1.0 / (2 * size_px))  # phase in periods
    q -= np.floor(q)
    q *= dt(2.0)
    q -= dt(1.0)
    np.abs(q, out=q)
    q *= dt(-size_px)
    q += dt(size_px - 0.5)
    return q


def _largest_valid_rectangle(valid: NDArray[np.bool_]) -> tuple[int, int, int, int]:
    """(row0, row1, col0, col1), end exclusive, of the largest all-true axis-aligned rectangle (histogram method)."""
    rows, cols = valid.shape
    heights = np.zeros(cols + 1, dtype=np.int64)  # trailing 0 flushes the stack
    best = (0, (0, 0, 0, 0))
    for r in range(rows):
        heights[:cols] = np.where(valid[r], heights[:cols] + 1, 0)
        stack: list[int] = []
        for c in range(cols + 1):
            start = c
            while stack and heights[stack[-1]] >= heights[c]:
                top = stack.pop()
                h = int(heights[top])
                start = stack[-1] + 1 if stack else 0
                area = h * (c - start)
                if area > best[0]:
                    best = (area, (r + 1 - h, r + 1, start, c))
            stack.append(c)
    return best[1]


def read_nodata_mask(path: str | Path, nodata_bgr: tuple[int, int, int] | None = None
                     ) -> tuple[NDArray[np.bool_] | None, str]:
    """The texels a tile file declares as no-data, and where the declaration came from (``""``: none).

    * GeoTIFF ``GDAL_NODATA`` tag: texels whose every band equals that value;
    * an alpha channel (PNG or TIFF with alpha; a TIFF band GDAL's metadata calls anything but ``Alpha`` is not
      one: NAIP's fourth band is near infrared): texels of alpha 0;
    * ``nodata_bgr``: texels of exactly that colour (B, G, R), for a file that declares nothing.
    Never a colour the file does not declare.  None when nothing is declared or no texel is no-data."""
    from PIL import Image

    masks: list[NDArray[np.bool_]] = []
    how: list[str] = []
    with Image.open(path) as im:
        tags = dict(getattr(im, "tag_v2", {}) or {})
        bands = np.asarray(im)
        mode = im.mode
    if bands.ndim == 2:
        bands = bands[:, :, None]
    tag = tags.get(TIFF_TAG_GDAL_NODATA)
    if tag is not None:
        try:
            value = float(str(tag).strip().strip("\x00"))
        except ValueError:
            value = math.nan
        if math.isfinite(value):
            masks.append(np.all(bands == value, axis=2))
            how.append(f"GDAL_NODATA {value:g}")
    if mode in ("RGBA", "LA", "PA") and _last_band_is_alpha(str(tags.get(TIFF_TAG_GDAL_METADATA, "")),
                                                            bands.shape[2]):
        masks.append(bands[:, :, -1] == 0)
        how.append("alpha channel")
    if nodata_bgr is not None:
        rgb = bands[:, :, :3]
        masks.append(np.all(rgb == np.asarray(nodata_bgr[::-1]), axis=2))
        how.append(f"declared colour BGR {tuple(nodata_bgr)}")
    if not masks:
        return None, ""
    mask = np.logical_or.reduce(masks)
    return (mask if mask.any() else None), ", ".join(how)


def _last_band_is_alpha(gdal_metadata: str, n_bands: int) -> bool:
    """False when GDAL's metadata gives the last band a colour interpretation other than alpha."""
    m = re.search(rf'name="COLORINTERP" sample="{n_bands - 1}"[^>]*>([^<]*)<', gdal_metadata)
    return m is None or m.group(1).strip().lower() == "alpha"


def crop_nodata(bgr: NDArray[np.uint8], name: str, nodata: NDArray[np.bool_] | None) -> NDArray[np.uint8]:
    """Cut a tile down to its largest rectangle free of the declared no-data texels ``nodata`` (a mask of the
    tile's shape from :func:`read_nodata_mask`; None: nothing to cut).

    Works on blocks of :data:`NODATA_BLOCK_PX` texels, dropping blocks next to no-data too (the anti-aliased rim).
    Raises ``ValueError`` when nothing valid is left."""
    if nodata is None or not nodata.any():
        return bgr
    if nodata.shape != bgr.shape[:2]:
        raise ValueError(f"texture {name!r}: no-data mask {nodata.shape} does not match the tile {bgr.shape[:2]}")
    b = NODATA_BLOCK_PX
    h, w = nodata.shape
    hb, wb = -(-h // b), -(-w // b)
    padded = np.zeros((hb * b, wb * b), dtype=np.uint8)
    padded[:h, :w] = nodata
    bad = padded.reshape(hb, b, wb, b).max(axis=(1, 3))
    bad = cv2.dilate(bad, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    r0, r1, c0, c1 = _largest_valid_rectangle(bad == 0)
    if r1 <= r0 or c1 <= c0:
        raise ValueError(f"texture {name!r}: no area free of no-data")
    crop = bgr[r0 * b : min(r1 * b, h), c0 * b : min(c1 * b, w)]
    logger.debug("texture %s: %.1f %% no-data, kept rows %d:%d cols %d:%d", name, 100 * nodata.mean(),
                 r0 * b, r1 * b, c0 * b, c1 * b)
    return np.ascontiguousarray(crop)


def read_bgr(path: str | Path) -> NDArray[np.uint8]:
    """Read an image file as BGR uint8 without OpenCV's GeoTIFF-tag warnings.  ``IMREAD_COLOR`` keeps the first
    three bands (the RGB of NAIP's RGBN) in BGR order."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(str(p))
    with _quiet_opencv():
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"OpenCV cannot read {p}")
    return np.asarray(bgr, dtype=np.uint8)


def load_tile(path: str | Path, nodata_bgr: tuple[int, int, int] | None = None, name: str = "") -> NDArray[np.uint8]:
    """A tile file as BGR uint8 with its declared no-data (:func:`read_nodata_mask`) cropped away."""
    mask, how = read_nodata_mask(path, nodata_bgr)
    if mask is not None:
        logger.debug("texture %s: no-data from %s", name or path, how)
    return crop_nodata(read_bgr(path), name or str(path), mask)


def load_real_tile(name: str) -> tuple[NDArray[np.uint8], float]:
    """The real tile ``name`` as BGR uint8 (declared no-data cropped away) and its metres per texel."""
    file, m_per_px, nodata_bgr = REAL_TEXTURES[name]
    return load_tile(TEXTURE_DIR / file, nodata_bgr, name), m_per_px


def _reflect_pad_to(a: NDArray, height: int, width: int) -> NDArray:
    """Extend ``a`` at its bottom and right to (height, width) by mirroring (repeatedly for small tiles)."""
    while a.shape[0] < height or a.shape[1] < width:
        pad_r = min(height - a.shape[0], a.shape[0]) if a.shape[0] < height else 0
        pad_c = min(width - a.shape[1], a.shape[1]) if a.shape[1] < width else 0
        a = cv2.copyMakeBorder(a, 0, pad_r, 0, pad_c, cv2.BORDER_REFLECT)
    return a


def _mosaic_tile() -> tuple[NDArray[np.uint8], float]:
    """The real 10 cm tiles in the 2 x 2 :data:`MOSAIC_LAYOUT`, each cropped or mirror-extended to its cell."""
    rows = []
    for layout_row in MOSAIC_LAYOUT:
        cells = []
        for name, rotate_180 in layout_row:
            bgr, m_per_px = load_real_tile(name)
            if m_per_px != PROCEDURAL_M_PER_PX:
                raise ValueError(f"mosaic: tile {name!r} is {m_per_px} m/px, expected {PROCEDURAL_M_PER_PX}")
            if rotate_180:
                bgr = np.ascontiguousarray(bgr[::-1, ::-1])
            cells.append(_reflect_pad_to(bgr[:MOSAIC_CELL_PX, :MOSAIC_CELL_PX], MOSAIC_CELL_PX, MOSAIC_CELL_PX))
        rows.append(np.hstack(cells))
    return np.ascontiguousarray(np.vstack(rows)), PROCEDURAL_M_PER_PX


def _value_noise(rng: np.random.Generator, size_px: int, wavelength_px: int) -> NDArray[np.float32]:
    """One octave: unit-variance random values on a grid of ``wavelength_px`` spacing, bicubically interpolated."""
    n = max(2, size_px // wavelength_px + 1)
    grid = rng.standard_normal((n, n)).astype(np.float32)
    return np.asarray(cv2.resize(grid, (size_px, size_px), interpolation=cv2.INTER_CUBIC), dtype=np.float32)


def _fractal_noise(rng: np.random.Generator, size_px: int) -> NDArray[np.float32]:
    out = np.zeros((size_px, size_px), np.float32)
    for k in range(1, NOISE_OCTAVES + 1):
        wl = 2**k
        out += np.float32(wl**NOISE_AMPLITUDE_EXPONENT) * _value_noise(rng, size_px, wl)
    return (out - out.mean()) / max(float(out.std()), 1e-12)


def procedural_texture(name: str, rng: np.random.Generator,
                       size_px: int = PROCEDURAL_SIZE_PX) -> tuple[NDArray[np.float32], float]:
    """Intensity tile (float32, 0-255 scale) of procedural texture ``name`` drawn from ``rng``, and m per texel."""
    m = PROCEDURAL_M_PER_PX
    if name == "noise":
        img = NOISE_MEAN_DN + NOISE_STD_DN * _fractal_noise(rng, size_px)
    elif name == "uniform_grass":
        img = UNIFORM_GRASS_MEAN_DN + UNIFORM_GRASS_STD_DN * _fractal_noise(rng, size_px)
    elif name == "water":
        yy, xx = np.mgrid[0:size_px, 0:size_px].astype(np.float32) * np.float32(m)
        base_dir = rng.uniform(0.0, 2 * np.pi)
        waves = np.zeros((size_px, size_px), np.float32)
        for _ in range(WATER_N_WAVES):
            ang = base_dir + rng.uniform(-WATER_SPREAD_RAD, WATER_SPREAD_RAD)
            k = np.float32(2 * np.pi / rng.uniform(*WATER_WAVELENGTH_M))
            phase = np.float32(rng.uniform(0.0, 2 * np.pi))
            waves += np.float32(rng.uniform(0.5, 1.0)) * np.sin(
                k * (np.float32(np.cos(ang)) * xx + np.float32(np.sin(ang)) * yy) + phase)
        waves /= max(float(waves.std()), 1e-12)
        img = WATER_MEAN_DN + WATER_RIPPLE_STD_DN * waves
    else:
        raise ValueError(f"unknown procedural texture {name!r}; valid: {', '.join(PROCEDURAL_TEXTURES)}")
    return np.clip(img, 0.0, 255.0).astype(np.float32), m


def _tint(intensity: NDArray[np.float32], tint_bgr: tuple[float, float, float]) -> NDArray[np.uint8]:
    tint = np.asarray(tint_bgr, np.float32)
    scale = tint / np.float32(_GRAY_WEIGHTS_BGR @ tint)
    return np.clip(intensity[..., None] * scale, 0, 255).astype(np.uint8)


def _pack_atlas(levels: list[NDArray]) -> tuple[NDArray, NDArray[np.float32]]:
    """Pack pyramid levels into one image, each with a 1-texel mirrored border.  Level 0 on the left, the others
    stacked in a column to its right.  Returns the atlas and the atlas (x, y) of texel (0, 0) of each level."""
    h0, w0 = levels[0].shape[:2]
    right_w = max((lv.shape[1] + 2 for lv in levels[1:]), default=0)
    right_h = sum(lv.shape[0] + 2 for lv in levels[1:])
    shape = (max(h0 + 2, right_h), w0 + 2 + right_w, *levels[0].shape[2:])
    atlas = np.zeros(shape, dtype=levels[0].dtype)
    origins = np.zeros((len(levels), 2), np.float32)
    x, y = 0, 0
    for k, lv in enumerate(levels):
        h, w = lv.shape[:2]
        atlas[y : y + h + 2, x : x + w + 2] = cv2.copyMakeBorder(lv, 1, 1, 1, 1, cv2.BORDER_REFLECT)
        origins[k] = (x + 1, y + 1)
        if k == 0:
            x = w0 + 2
        else:
            y += h + 2
    return atlas, origins


def downsample(img: NDArray) -> NDArray:
    """Next mip level: binomial [1 3 3 1]/8 low-pass in each axis, then every second texel.

    Output texel ``j`` covers input texels ``2j-1 .. 2j+2`` and is centred at ``2j + 0.5``, so the levels nest
    exactly (texel ``j`` of level ``k`` is centred at level-0 texel ``2**k * (j + 0.5) - 0.5``) and the mirrored
    border matches the world's mirror tiling.  (``cv2.pyrDown``'s 5-tap kernel centres output texel ``j`` on input
    texel ``2j``, a quarter-texel misalignment per level that shifted features by up to half a frame pixel.)  The
    filter has a zero at the Nyquist frequency, like pyrDown's."""
    smoothed = cv2.sepFilter2D(img, -1, _MIP_KERNEL, _MIP_KERNEL, anchor=(1, 1), borderType=cv2.BORDER_REFLECT)
    return np.ascontiguousarray(smoothed[::2, ::2])


def _pyramid(img: NDArray, n_levels: int) -> list[NDArray]:
    levels = [img]
    for _ in range(1, n_levels):
        levels.append(downsample(levels[-1]))
    return levels


@dataclass(frozen=True, eq=False)
class GroundWorld:
    """An infinite flat ground: a mirror-tiled, mip-mapped intensity tile.  Build with :meth:`from_name` or
    :meth:`from_array`.  All arrays are read-only (worlds by name are shared through a cache).

    ``m_per_px``: level-0 texel size (m); ``tile_px``: (width, height) of the (padded) tile in level-0 texels;
    ``origin_px``: level-0 texel coordinates (col, row) of the world origin; ``atlas``: float32 intensity of all
    levels; ``level_origin_px[k]``: atlas (x, y) of texel (0, 0) of level ``k``; ``color_atlas``: optional BGR.
    """

    name: str
    m_per_px: float
    tile_px: tuple[int, int]
    origin_px: tuple[float, float]
    atlas: NDArray[np.float32]
    level_origin_px: NDArray[np.float32]
    color_atlas: NDArray[np.uint8] | None = None

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_name(cls, name: str, *, seed: int = 0, color: bool = False) -> GroundWorld:
        """World ``name`` (one of :data:`TEXTURE_NAMES`).  Procedural textures draw from
        ``np.random.default_rng(seed)``; real ones ignore ``seed``.  ``color`` also keeps a BGR copy for pictures.
        Cached per process."""
        if name not in TEXTURE_NAMES:
            raise ValueError(f"unknown texture {name!r}; valid names: {', '.join(TEXTURE_NAMES)}")
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        return _world_by_name(name, int(seed) if name in PROCEDURAL_TEXTURES else 0, bool(color))

    @classmethod
    def from_array(cls, image: ArrayLike, m_per_px: float, *, name: str = "array",
                   color_bgr: NDArray[np.uint8] | None = None) -> GroundWorld:
        """World from a tile: ``image`` is intensity (H, W) on the 0-255 scale, or a BGR uint8 image (H, W, 3)
        converted per eq. 4.  Texel ``(col, row)`` of ``image`` sits at ``texel_to_ground(col, row)``; the world
        origin is the centre of ``image``.  ``color_bgr`` (H, W, 3) optionally adds colour for pictures."""
        img = np.asarray(image)
        if not (isinstance(m_per_px, int | float | np.floating) and math.isfinite(m_per_px) and m_per_px > 0):
            raise ValueError(f"m_per_px must be a positive finite number, got {m_per_px!r}")
        if img.ndim == 3 and img.shape[2] == 3:
            if color_bgr is None and img.dtype == np.uint8:
                color_bgr = img
            img = intensity_from_bgr(img)
        if img.ndim != 2 or min(img.shape) < 2:
            raise ValueError(f"image must be (H, W) intensity or (H, W, 3) BGR with H, W >= 2, got {img.shape}")
        if not np.issubdtype(img.dtype, np.number) or img.dtype == np.bool_:
            raise ValueError(f"image must be numeric, got {img.dtype}")
        gray = img.astype(np.float32)
        if not np.all(np.isfinite(gray)):
            raise ValueError("image contains non-finite values")
        if color_bgr is not None:
            color_bgr = np.asarray(color_bgr)
            if color_bgr.shape != (*gray.shape, 3) or color_bgr.dtype != np.uint8:
                raise ValueError(f"color_bgr must be uint8 {(*gray.shape, 3)}, got {color_bgr.dtype} {color_bgr.shape}")
        h, w = gray.shape
        n_levels = 1 + max(0, int(math.floor(math.log2(min(h, w) / TOP_LEVEL_MIN_PX))))
        # Pad (mirrored, so the tile stays continuous under mirror tiling) to a multiple of 2**(n_levels-1) texels,
        # so that every pyramid level has exactly half the texels of the one below and folds at the same place.
        q = 2 ** (n_levels - 1)
        hp, wp = -(-h // q) * q, -(-w // q) * q
        gray = _reflect_pad_to(gray, hp, wp)
        atlas, origins = _pack_atlas(_pyramid(gray, n_levels))
        color_atlas = None
        if color_bgr is not None:
            color_atlas, _ = _pack_atlas(_pyramid(_reflect_pad_to(color_bgr, hp, wp), n_levels))
            color_atlas.setflags(write=False)
        atlas.setflags(write=False)
        origins.setflags(write=False)
        return cls(name=name, m_per_px=float(m_per_px), tile_px=(gray.shape[1], gray.shape[0]),
                   origin_px=((w - 1) / 2.0, (h - 1) / 2.0), atlas=atlas, level_origin_px=origins,
                   color_atlas=color_atlas)

    # ---------------------------------------------------------------- geometry
    @property
    def n_levels(self) -> int:
        return len(self.level_origin_px)

    @property
    def tile_size_m(self) -> tuple[float, float]:
        """(east-west, north-south) extent of one tile in metres (the world repeats every twice this)."""
        return self.tile_px[0] * self.m_per_px, self.tile_px[1] * self.m_per_px

    def level(self, k: int) -> NDArray[np.float32]:
        """Intensity of mip level ``k`` (a view into the atlas; level ``k`` texels are ``m_per_px * 2**k``)."""
        if not 0 <= k < self.n_levels:
            raise ValueError(f"level must be in [0, {self.n_levels - 1}], got {k}")
        x, y = (int(v) for v in self.level_origin_px[k])
        w, h = self.tile_px[0] >> k, self.tile_px[1] >> k
        return self.atlas[y : y + h, x : x + w]

    def ground_to_texel(self, n_m: ArrayLike, e_m: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Unwrapped level-0 texel coordinates (col, row) of ground points (north, east) in metres."""
        u = np.asarray(e_m, dtype=np.float64) / self.m_per_px + self.origin_px[0]
        v = -np.asarray(n_m, dtype=np.float64) / self.m_per_px + self.origin_px[1]
        return u, v

    def texel_to_ground(self, col: ArrayLike, row: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(north, east) in metres of level-0 texel (col, row) of the tile copy at the origin."""
        n = -(np.asarray(row, dtype=np.float64) - self.origin_px[1]) * self.m_per_px
        e = (np.asarray(col, dtype=np.float64) - self.origin_px[0]) * self.m_per_px
        return n, e

    def reduce_texel(self, u: float, v: float) -> tuple[float, float]:
        """Reduce unwrapped level-0 texel coordinates by whole mirror periods (exact, keeps float32 precision for
        the small offsets the renderer adds per pixel)."""
        w, h = self.tile_px
        return float(np.mod(u + 0.5, 2 * w) - 0.5), float(np.mod(v + 0.5, 2 * h) - 0.5)

    def fold_texel(self, u: NDArray[np.floating], v: NDArray[np.floating]) -> tuple[NDArray, NDArray]:
        """Mirror-fold unwrapped level-0 texel coordinates into the tile (see :func:`mirror_wrap`)."""
        return mirror_wrap(u, self.tile_px[0]), mirror_wrap(v, self.tile_px[1])

    def atlas_maps(self, uf: NDArray[np.float32], vf: NDArray[np.float32], level: int
                   ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """``cv2.remap`` maps into the atlas for *folded* level-0 texel coordinates ``(uf, vf)`` (from
        :meth:`fold_texel`) at mip ``level``, clipped to the pyramid (see :attr:`level_tables`)."""
        k = int(np.clip(int(level), 0, self.n_levels - 1))
        scale, ox, oy = self.level_tables
        mx = (uf + np.float32(0.5)) * scale[k] + ox[k]
        my = (vf + np.float32(0.5)) * scale[k] + oy[k]
        return mx.astype(np.float32, copy=False), my.astype(np.float32, copy=False)

    @functools.cached_property
    def level_tables(self) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """Per mip level ``k`` (float32, read-only): the scale ``2**-k`` and the atlas x and y of level ``k``'s texel
        (0, 0) minus half a texel, so that a folded level-0 coordinate ``u`` samples atlas x
        ``(u + 0.5) * scale[k] + x[k]`` (the renderer's kernels read the same tables)."""
        k = np.arange(self.n_levels)
        tables = (np.exp2(-k).astype(np.float32), (self.level_origin_px[k, 0] - 0.5).astype(np.float32),
                  (self.level_origin_px[k, 1] - 0.5).astype(np.float32))
        for t in tables:
            t.setflags(write=False)
        return tables

    @functools.cached_property
    def mean_intensity(self) -> float:
        """Mean intensity of the tile (what the ground averages to at an infinite footprint)."""
        return float(self.level(0).mean(dtype=np.float64))

    @functools.cached_property
    def mean_color_bgr(self) -> NDArray[np.float32]:
        """Mean BGR colour of the tile (needs ``color_atlas``)."""
        if self.color_atlas is None:
            raise ValueError(f"world {self.name!r} has no colour")
        x, y = (int(v) for v in self.level_origin_px[0])
        tile = self.color_atlas[y : y + self.tile_px[1], x : x + self.tile_px[0]]
        return tile.reshape(-1, 3).mean(axis=0, dtype=np.float64).astype(np.float32)

    def sample(self, n_m: ArrayLike, e_m: ArrayLike, level: int = 0) -> NDArray[np.float32]:
        """Intensity (bilinear, float32) at ground points (north, east) in metres from mip ``level``."""
        if isinstance(level, bool) or not isinstance(level, int | np.integer) or not 0 <= level < self.n_levels:
            raise ValueError(f"level must be an integer in [0, {self.n_levels - 1}], got {level!r}")
        n = np.asarray(n_m, dtype=np.float64)
        e = np.asarray(e_m, dtype=np.float64)
        shape = np.broadcast_shapes(n.shape, e.shape)
        u, v = self.ground_to_texel(np.broadcast_to(n, shape).ravel(), np.broadcast_to(e, shape).ravel())
        w, h = self.tile_px
        u = np.mod(u + 0.5, 2 * w) - 0.5
        v = np.mod(v + 0.5, 2 * h) - 0.5
        uf, vf = self.fold_texel(u.astype(np.float32), v.astype(np.float32))
        mx, my = self.atlas_maps(uf, vf, level)
        # cv2.remap needs maps smaller than 32767 on each side: lay the points out in rows of _SAMPLE_ROW_PX
        count = mx.size
        width = max(1, min(count, _SAMPLE_ROW_PX))
        rows = -(-count // width)
        mx = np.pad(mx, (0, rows * width - count), mode="edge").reshape(rows, width)
        my = np.pad(my, (0, rows * width - count), mode="edge").reshape(rows, width)
        out = np.asarray(cv2.remap(self.atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        return np.asarray(out.reshape(-1)[:count].reshape(shape), dtype=np.float32)


def _cached_world(name: str, build: Callable[[], GroundWorld], files: Iterable[Path]) -> GroundWorld:
    """A colourless :class:`GroundWorld` through :mod:`sim.diskcache`: ``build()`` makes it; ``files`` (the tiles it
    is made from) and this module's source are the key."""
    def arrays() -> diskcache.Built:
        w = build()
        return ({"atlas": w.atlas, "level_origin_px": w.level_origin_px},
                {"m_per_px": w.m_per_px, "tile_px": list(w.tile_px), "origin_px": list(w.origin_px)})

    a, m = diskcache.cached("world", diskcache.fingerprint(files=files, modules=[sys.modules[__name__]], world=name),
                            arrays)
    return GroundWorld(name=name, m_per_px=float(m["m_per_px"]), tile_px=(int(m["tile_px"][0]), int(m["tile_px"][1])),
                       origin_px=(float(m["origin_px"][0]), float(m["origin_px"][1])), atlas=a["atlas"],
                       level_origin_px=a["level_origin_px"])


@functools.lru_cache(maxsize=_WORLD_CACHE_SIZE)
def _world_by_name(name: str, seed: int, color: bool) -> GroundWorld:
    t0 = time.perf_counter()
    if name in REAL_TEXTURES or name == "mosaic":
        def build() -> GroundWorld:
            bgr, m_per_px = _mosaic_tile() if name == "mosaic" else load_real_tile(name)
            return GroundWorld.from_array(intensity_from_bgr(bgr), m_per_px, name=name,
                                          color_bgr=bgr if color else None)

        # the intensity world of a real tile is the same in every run: kept on disk (sim.diskcache)
        world = build() if color else _cached_world(
            name, build, [TEXTURE_DIR / f for f, _, _ in REAL_TEXTURES.values()])
    else:
        gray, m_per_px = procedural_texture(name, np.random.default_rng(seed))
        world = GroundWorld.from_array(gray, m_per_px, name=name,
                                       color_bgr=_tint(gray, PROCEDURAL_TINT_BGR[name]) if color else None)
    logger.debug("world %s (seed %d): %d x %d texels, %d levels, built in %.2f s", name, seed, *world.tile_px,
                 world.n_levels, time.perf_counter() - t0)
    return world
