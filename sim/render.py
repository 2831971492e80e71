"""Camera renderer: the raw frame a calibrated belly camera sees over a flat textured ground.

Forward model, frames as in :mod:`gsoe`: every raw pixel's unit ray (``camera.unproject``, computed once) is
rotated camera -> body (``camera.R_bc``) -> NED (``R_nb``) and intersected with the ground plane ``z = 0``; the
aircraft is at ``pos_ned_m`` with ``pos_ned_m[2] = -height``.  Rays that do not reach the ground (down component
below :data:`MIN_DOWN_COS`) see the sky (:data:`SKY_INTENSITY_DN`).

The texture is prefiltered to each pixel's ground footprint (mip-mapping with trilinear filtering): the
footprint is ``distance * pixel_angle / cos(incidence)`` (``pixel_angle`` is the angle a raw pixel subtends,
from the calibrated model, so the fisheye's compression towards the edge counts), the mip level is
``log2(footprint / m_per_px)``, and the two nearest levels are sampled bilinearly with ``cv2.remap`` from the
world's atlas and blended.  The per-pixel arithmetic runs in compiled loops over the requested region of interest
(:mod:`sim.render_kernels`, numba), the look-ups are ``cv2.remap``; only the region is computed (the rest of the
frame is 0, or left as it was in a caller's ``out`` array), so rendering just what the estimator reads is cheap
and gives the same pixels as a full-frame render.

Options per frame: exposure-time motion blur (the mean of :data:`MOTION_BLUR_SUBSAMPLES` sub-renders spread
over the exposure, position advanced by ``vel_ned_m_s * dt`` and attitude by ``rates_b_rad_s * dt``; the pose
given is the one at mid-exposure), a gain (brightness change) and additive Gaussian sensor noise drawn from the
caller's generator, then rounding to uint8.  The noise is drawn by inverse-transform sampling from a table
(:data:`NOISE_TABLE_SIZE` equiprobable quantiles of the standard normal, scaled to unit variance; one 16-bit
uniform integer per pixel), four times faster than ``Generator.standard_normal``: it was a quarter of a region's
render time.  The table's quantisation (1/65536 of probability) and its tails (cut at 4.3 sigma, 2e-5 of the
samples) do not show once the intensity is rounded to whole DN.
"""

from __future__ import annotations

import math
import sys
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtri

from gsoe.camera import CameraModel
from sim import diskcache
from sim.render_kernels import blend_add, ground_maps, to_dn
from sim.textures import GroundWorld

# Sub-renders averaged across the exposure for motion blur.
MOTION_BLUR_SUBSAMPLES = 5
# Blur shorter than this (image motion during the exposure, px at the image centre) is not drawn: one sub-render per
# this many pixels of motion, up to ``blur_subsamples``.  One pixel is enough: every sub-render is already low-passed
# to the pixel's footprint (mip-mapping) and sampled bilinearly, so sub-renders one pixel apart sum to a box of the
# motion's length convolved with the one-pixel triangle every render has (0.5 px spacing cost twice the renders,
# about a quarter of a Monte Carlo run's time with long exposures, for the same pixels to within the noise).
BLUR_PX_PER_SUBSAMPLE = 1.0
# Lenses whose per-pixel ray tables are kept (a process renders with one or two).
PIXEL_TABLE_CACHE_SIZE = 2
# Intensity (DN, 0-255) and colour (BGR) of rays that miss the ground.
SKY_INTENSITY_DN = 200.0
SKY_COLOR_BGR = (235.0, 206.0, 135.0)
# A ray reaches the ground when its down component (cos of the incidence angle on the ground) exceeds this.
MIN_DOWN_COS = 1e-3
# Added to every pixel's mip level (0: texel = footprint; positive blurs, negative sharpens and may alias).
LOD_BIAS = 0.0
# Tolerance on R_nb being a rotation matrix (max |R^T R - I|).
ROTATION_TOL = 1e-6
# Frame intensity range (uint8).
_DN_MAX = 255.0

Roi = tuple[int, int, int, int]
_NO_NOISE = np.zeros((0, 0), np.uint16)
# Entries of the sensor-noise table: the standard normal's quantiles at the midpoints of 2**16 equal-probability
# bins, indexed by uniform uint16 draws.
NOISE_TABLE_SIZE = 1 << 16


def _normal_table() -> NDArray[np.float32]:
    q = ndtri((np.arange(NOISE_TABLE_SIZE) + 0.5) / NOISE_TABLE_SIZE)
    q /= math.sqrt(float(np.mean(q * q)))      # exactly unit variance (the mean is 0 by symmetry)
    table = q.astype(np.float32)
    table.setflags(write=False)
    return table


_NOISE_TABLE = _normal_table()


_EYE3 = np.eye(3)


def _vec3(value: ArrayLike | None, name: str) -> NDArray[np.float64]:
    arr = np.zeros(3) if value is None else np.asarray(value, dtype=np.float64)
    # (a sum is finite only if every term is: one cheap check per call on this hot path)
    if arr.shape != (3,) or not math.isfinite(float(arr.sum())):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return arr


def _rotation(R: ArrayLike, name: str = "R_nb") -> NDArray[np.float64]:
    arr = np.asarray(R, dtype=np.float64)
    if arr.shape != (3, 3) or not math.isfinite(float(arr.sum())):
        raise ValueError(f"{name} must be a finite 3x3 matrix, got shape {arr.shape}")
    (a, b, c), (d, e, f), (g, h, i) = arr.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if not float(np.abs(arr.T @ arr - _EYE3).max()) <= ROTATION_TOL or det <= 0:
        raise ValueError(f"{name} is not a rotation matrix (orthonormal, det +1)")
    return arr


def _nonneg(value: float, name: str, *, positive: bool = False) -> float:
    ok = isinstance(value, int | float | np.floating | np.integer) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or value < 0 or (positive and value == 0):
        raise ValueError(f"{name} must be a {'positive' if positive else 'non-negative'} finite number, got {value!r}")
    return float(value)


_PIXEL_TABLES: dict[tuple[Any, ...], tuple[NDArray[np.float32], NDArray[np.float32]]] = {}


def _pixel_tables(camera: CameraModel) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Read-only per-pixel tables of a lens, kept for the last :data:`PIXEL_TABLE_CACHE_SIZE` lenses (keyed on the
    model, size and intrinsics, all they depend on): unit camera rays (h, w, 3) and log2 of the angle a pixel
    subtends (the larger of its two sides, from the rays through its edge midpoints)."""
    w, h = camera.size_px
    key = (camera.model, w, h, camera.K.tobytes(), camera.D.tobytes())
    if key in _PIXEL_TABLES:
        return _PIXEL_TABLES[key]
    # the same in every run of this lens: kept on disk (sim.diskcache)
    rays, log2_angle = diskcache.cached_arrays("pixel_tables", diskcache.fingerprint(
        modules=[sys.modules[__name__]], model=camera.model, size=[w, h], K=camera.K.tolist(), D=camera.D.tolist()),
        lambda: _build_pixel_tables(camera))
    while len(_PIXEL_TABLES) >= PIXEL_TABLE_CACHE_SIZE:
        del _PIXEL_TABLES[next(iter(_PIXEL_TABLES))]
    _PIXEL_TABLES[key] = (rays, log2_angle)
    return rays, log2_angle


def _build_pixel_tables(camera: CameraModel) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    w, h = camera.size_px
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    px = np.column_stack([cols.ravel(), rows.ravel()])
    rays = np.ascontiguousarray(camera.unproject(px).reshape(h, w, 3), dtype=np.float32)
    half = np.array([0.5, 0.0])

    def side_angle(offset: NDArray[np.float64]) -> NDArray[np.float64]:
        a = camera.unproject(px - offset)
        b = camera.unproject(px + offset)
        return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))

    pixel_angle = np.maximum(side_angle(half), side_angle(half[::-1])).reshape(h, w)
    log2_angle = np.log2(pixel_angle).astype(np.float32)
    for arr in (rays, log2_angle):
        arr.setflags(write=False)
    return rays, log2_angle


class CameraRenderer:
    """Renders raw frames of ``camera`` over ``world``.

    Parameters
    ----------
    camera : the calibrated camera (intrinsics, distortion, mounting ``R_bc``).
    world : the ground texture.
    blur_subsamples : number of sub-renders averaged for motion blur.
    mipmap : prefilter to the pixel footprint (``False`` samples level 0 only: aliases; for tests and demos).
    """

    def __init__(self, camera: CameraModel, world: GroundWorld, *, blur_subsamples: int = MOTION_BLUR_SUBSAMPLES,
                 mipmap: bool = True) -> None:
        if isinstance(blur_subsamples, bool) or not isinstance(blur_subsamples, int) or blur_subsamples < 1:
            raise ValueError(f"blur_subsamples must be a positive integer, got {blur_subsamples!r}")
        self.camera = camera
        self.world = world
        self.blur_subsamples = blur_subsamples
        self.mipmap = bool(mipmap)
        w, h = camera.size_px
        self.width_px, self.height_px = w, h
        # Unit rays per pixel in the camera frame (h, w, 3) float32 and log2 of the angle each pixel subtends; the
        # same for every renderer of this lens (a Monte Carlo worker builds one per flight), so computed once.
        self._rays_c, self._log2_pixel_angle = _pixel_tables(camera)

    # ------------------------------------------------------------------------------------------------ helpers
    def _check_roi(self, roi: Roi | None) -> Roi:
        if roi is None:
            return 0, 0, self.width_px, self.height_px
        try:
            x0, y0, x1, y1 = (int(v) for v in roi)
            ok = all(int(v) == v for v in roi)
        except (TypeError, ValueError):
            raise ValueError(f"roi must be (x0, y0, x1, y1) integers, got {roi!r}") from None
        if not ok or not (0 <= x0 < x1 <= self.width_px and 0 <= y0 < y1 <= self.height_px):
            raise ValueError(f"roi must be integers with 0 <= x0 < x1 <= {self.width_px} and "
                             f"0 <= y0 < y1 <= {self.height_px}, got {roi!r}")
        return x0, y0, x1, y1

    def _maps(self, pos: NDArray[np.float64], R_nb: NDArray[np.float64], roi: Roi) -> dict[str, Any]:
        """Per-pixel sampling of one pose over ``roi``: atlas maps of the two mip levels, blend weight, far fade,
        hit mask (:func:`sim.render_kernels.ground_maps`)."""
        x0, y0, x1, y1 = roi
        shape = (y1 - y0, x1 - x0)
        world = self.world
        u_c, v_c = world.reduce_texel(*(float(c) for c in world.ground_to_texel(pos[0], pos[1])))
        m0x, m0y = np.empty(shape, np.float32), np.empty(shape, np.float32)
        m1x, m1y = np.empty(shape, np.float32), np.empty(shape, np.float32)
        frac = np.zeros(shape, np.float32)
        far = np.empty(shape, np.float32)
        hit = np.empty(shape, np.bool_)
        scale, ox, oy = world.level_tables
        any_far = ground_maps(self._rays_c[y0:y1, x0:x1], self._log2_pixel_angle[y0:y1, x0:x1],
                              R_nb @ self.camera.R_bc, -float(pos[2]), float(world.m_per_px), u_c, v_c,
                              int(world.tile_px[0]), int(world.tile_px[1]), scale, ox, oy, float(LOD_BIAS),
                              MIN_DOWN_COS, self.mipmap, m0x, m0y, m1x, m1y, frac, far, hit)
        if not self.mipmap:
            return {"m0": (m0x, m0y), "m1": None, "frac": frac, "far": None, "hit": hit}
        return {"m0": (m0x, m0y), "m1": (m1x, m1y), "frac": frac, "far": far if any_far else None, "hit": hit}

    @staticmethod
    def _sample(atlas: NDArray[Any], mean: float | NDArray[np.float32], maps: dict[str, Any]) -> NDArray[np.float32]:
        """Colour sampling (``render_color``): the two levels' bilinear samples blended, faded to ``mean``."""
        mx, my = maps["m0"]
        a = np.asarray(cv2.remap(atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), dtype=np.float32)
        if maps["m1"] is not None:
            mx, my = maps["m1"]
            b = np.asarray(cv2.remap(atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
            frac = maps["frac"] if a.ndim == 2 else maps["frac"][..., None]
            b = b.astype(np.float32, copy=False) - a
            b *= frac
            a += b
        if maps["far"] is not None:
            far = maps["far"] if a.ndim == 2 else maps["far"][..., None]
            a += (mean - a) * far
        return a

    def _add_pose(self, pos: NDArray[np.float64], R_nb: NDArray[np.float64], roi: Roi,
                  acc: NDArray[np.float32]) -> None:
        """Add the intensity seen from one pose over ``roi`` to ``acc``."""
        maps = self._maps(pos, R_nb, roi)
        atlas = self.world.atlas
        mx, my = maps["m0"]
        # the atlas is uint8, so is what remap samples from it (OpenCV's stubs do not say)
        a = cast(NDArray[np.uint8], cv2.remap(atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        if maps["m1"] is not None:
            mx, my = maps["m1"]
            b = cast(NDArray[np.uint8], cv2.remap(atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        else:
            b = a
        far = maps["far"]
        blend_add(a, b, maps["frac"], maps["frac"] if far is None else far, far is not None,
                  float(self.world.mean_intensity), maps["hit"], SKY_INTENSITY_DN, acc)

    def _check_pose(self, pos_ned_m: ArrayLike, R_nb: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        pos = _vec3(pos_ned_m, "pos_ned_m")
        if pos[2] >= 0:
            raise ValueError(f"pos_ned_m[2] must be negative (camera above the ground plane z = 0), got {pos[2]!r}")
        return pos, _rotation(R_nb)

    # ------------------------------------------------------------------------------------------------ public
    def render_intensity(self, pos_ned_m: ArrayLike, R_nb: ArrayLike, *, roi: Roi | None = None,
                         exposure_s: float = 0.0, vel_ned_m_s: ArrayLike | None = None,
                         rates_b_rad_s: ArrayLike | None = None) -> NDArray[np.float32]:
        """Ideal intensity (float32, 0-255 scale, no gain, noise or rounding) of the ROI only, shape
        ``(y1 - y0, x1 - x0)``.  Arguments as in :meth:`render`."""
        pos, R = self._check_pose(pos_ned_m, R_nb)
        box = self._check_roi(roi)
        exposure = _nonneg(exposure_s, "exposure_s")
        vel = _vec3(vel_ned_m_s, "vel_ned_m_s")
        rates = _vec3(rates_b_rad_s, "rates_b_rad_s")
        acc = np.zeros((box[3] - box[1], box[2] - box[0]), np.float32)
        n = self._blur_count(pos, exposure, vel, rates)
        if n <= 1:
            self._add_pose(pos, R, box, acc)
            return acc
        for dt in exposure * ((np.arange(n) + 0.5) / n - 0.5):
            p = pos + vel * dt
            if p[2] >= 0:
                raise ValueError("the camera crosses the ground plane during the exposure")
            self._add_pose(p, R @ cv2.Rodrigues(rates * dt)[0], box, acc)   # (scipy's Rotation: 30 us a call)
        acc *= np.float32(1.0 / n)
        return acc

    def _blur_count(self, pos: NDArray[np.float64], exposure: float, vel: NDArray[np.float64],
                    rates: NDArray[np.float64]) -> int:
        """Sub-renders for the motion blur: one per ``BLUR_PX_PER_SUBSAMPLE`` of image motion at the centre during
        the exposure (translation over the height plus rotation), at most ``blur_subsamples``."""
        if exposure == 0.0:
            return 1
        f_px = self.camera.focal_px
        vx, vy, vz = vel.tolist()
        wx, wy, wz = rates.tolist()
        blur_px = exposure * f_px * (math.sqrt(vx * vx + vy * vy + vz * vz) / max(-float(pos[2]), 1e-3)
                                     + math.sqrt(wx * wx + wy * wy + wz * wz))
        return max(1, min(self.blur_subsamples, math.ceil(blur_px / BLUR_PX_PER_SUBSAMPLE)))

    def render(self, pos_ned_m: ArrayLike, R_nb: ArrayLike, *, roi: Roi | None = None, exposure_s: float = 0.0,
               vel_ned_m_s: ArrayLike | None = None, rates_b_rad_s: ArrayLike | None = None,
               noise_std: float = 0.0, gain: float = 1.0, rng: np.random.Generator | None = None,
               out: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
        """The raw frame (``height_px x width_px`` uint8 intensity) seen from ``pos_ned_m`` (NED, m; ``[2]`` is
        minus the height above the ground plane) with attitude ``R_nb`` (body to NED).

        ``roi = (x0, y0, x1, y1)`` (raw pixels, end exclusive) computes only that rectangle; the rest is 0, or, with
        ``out`` (a uint8 array of the frame's shape, written in place and returned), left as it was.
        ``exposure_s`` > 0 with ``vel_ned_m_s`` (m/s, NED) and/or ``rates_b_rad_s`` (body rates, rad/s) adds
        motion blur, the pose being the one at mid-exposure.  The intensity is multiplied by ``gain`` and
        Gaussian noise of ``noise_std`` DN drawn from ``rng`` is added (``rng`` required when ``noise_std > 0``).
        """
        noise = _nonneg(noise_std, "noise_std")
        g = _nonneg(gain, "gain", positive=True)
        if noise > 0 and not isinstance(rng, np.random.Generator):
            raise ValueError("noise_std > 0 needs rng, a numpy.random.Generator")
        shape = (self.height_px, self.width_px)
        if out is None:
            out = np.zeros(shape, np.uint8)
        elif not (isinstance(out, np.ndarray) and out.shape == shape and out.dtype == np.uint8):
            raise ValueError(f"out must be a uint8 array of shape {shape}, got {type(out).__name__} "
                             f"{getattr(out, 'shape', '')} {getattr(out, 'dtype', '')}")
        box = self._check_roi(roi)
        img = self.render_intensity(pos_ned_m, R_nb, roi=box, exposure_s=exposure_s, vel_ned_m_s=vel_ned_m_s,
                                    rates_b_rad_s=rates_b_rad_s)
        z = _NO_NOISE
        if noise > 0:
            assert rng is not None
            z = rng.integers(0, NOISE_TABLE_SIZE, img.shape, dtype=np.uint16)
        x0, y0, x1, y1 = box
        to_dn(img, g, z, _NOISE_TABLE, noise, out[y0:y1, x0:x1])
        return out

    def render_color(self, pos_ned_m: ArrayLike, R_nb: ArrayLike, *, roi: Roi | None = None) -> NDArray[np.uint8]:
        """Colour picture (BGR uint8, ``height_px x width_px x 3``) of the same view, for looking at; needs a world
        built with colour (``GroundWorld.from_name(..., color=True)``)."""
        if self.world.color_atlas is None:
            raise ValueError(f"world {self.world.name!r} has no colour (build it with color=True)")
        pos, R = self._check_pose(pos_ned_m, R_nb)
        x0, y0, x1, y1 = self._check_roi(roi)
        maps = self._maps(pos, R, (x0, y0, x1, y1))
        img = self._sample(self.world.color_atlas, self.world.mean_color_bgr, maps)
        img[~maps["hit"]] = SKY_COLOR_BGR
        out = np.zeros((self.height_px, self.width_px, 3), np.uint8)
        out[y0:y1, x0:x1] = np.rint(np.clip(img, 0.0, _DN_MAX))
        return out
