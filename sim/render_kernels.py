"""Compiled per-pixel kernels of :mod:`sim.render` (numba).

The renderer's work per region of interest is a handful of arithmetic steps per pixel (rotate the ray, intersect
the ground, fold into the mirror-tiled texture, pick the mip levels) and two bilinear look-ups.  Written as numpy
expressions over a small region it is some thirty array calls of a few microseconds each, whatever the region's
size: the simulator renders ~40 000 regions per 1000 s of flight.  These kernels do the per-pixel arithmetic in one
compiled loop each; the bilinear look-ups stay ``cv2.remap`` (so the sampling is OpenCV's).  Frames and conventions
as in :mod:`sim.render` and :mod:`gsoe`; all arrays are C-contiguous or strided views, float32 unless stated.

Compiled on first use and cached on disk next to this file (numba's ``cache=True``; a read-only install compiles
once per process instead).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray


@njit(cache=True, nogil=True, error_model="numpy")
def _mirror_fold(u: float, size: int) -> float:
    """:func:`sim.textures.mirror_wrap` for one coordinate."""
    q = (u + 0.5) * (1.0 / (2 * size))
    q -= math.floor(q)
    q = abs(2.0 * q - 1.0)
    return q * (-size) + (size - 0.5)


@njit(cache=True, nogil=True, error_model="numpy")
def ground_maps(rays_c: NDArray[np.float32], log2_pixel_angle: NDArray[np.float32], R_nc: NDArray[np.float64],
                height_m: float, m_per_px: float, u_c: float, v_c: float, tile_w: int, tile_h: int,
                level_scale: NDArray[np.float32], level_ox: NDArray[np.float32], level_oy: NDArray[np.float32],
                lod_bias: float, min_down_cos: float, mipmap: bool,
                m0x: NDArray[np.float32], m0y: NDArray[np.float32], m1x: NDArray[np.float32],
                m1y: NDArray[np.float32], frac: NDArray[np.float32], far: NDArray[np.float32],
                hit: NDArray[np.bool_]) -> bool:
    """Atlas sampling maps of one pose over a region (``rays_c``: its unit camera rays, shape (h, w, 3)).

    Per pixel: the ray in NED ``R_nc @ ray``; ``hit`` when its down component exceeds ``min_down_cos``; the
    ground point's level-0 texel coordinates ``(u_c + d_e t, v_c - d_n t)`` with ``t = height / m_per_px / d_d``,
    mirror-folded into the ``tile_w x tile_h`` tile; the mip level ``log2(t / d_d) + log2_pixel_angle + lod_bias``
    clipped to the pyramid (``len(level_scale)`` levels): ``m0`` maps into its floor level, ``m1`` into the next
    (both ``(uf + 0.5) * 2**-k + origin_k - 0.5``), ``frac`` the blend weight of ``m1``, ``far`` the fade to the
    tile mean beyond the coarsest level.  Without ``mipmap`` only ``m0`` (level 0) and ``hit`` are written.
    Returns whether any pixel needs the far fade.
    """
    h, w = hit.shape
    top = level_scale.shape[0] - 1
    r00, r01, r02 = R_nc[0, 0], R_nc[0, 1], R_nc[0, 2]
    r10, r11, r12 = R_nc[1, 0], R_nc[1, 1], R_nc[1, 2]
    r20, r21, r22 = R_nc[2, 0], R_nc[2, 1], R_nc[2, 2]
    k_t = height_m / m_per_px
    any_far = False
    for i in range(h):
        for j in range(w):
            cx, cy, cz = rays_c[i, j, 0], rays_c[i, j, 1], rays_c[i, j, 2]
            d_n = r00 * cx + r01 * cy + r02 * cz
            d_e = r10 * cx + r11 * cy + r12 * cz
            d_d = r20 * cx + r21 * cy + r22 * cz
            hit[i, j] = d_d > min_down_cos
            if d_d < min_down_cos:
                d_d = min_down_cos
            t = k_t / d_d
            uf = _mirror_fold(u_c + d_e * t, tile_w)
            vf = _mirror_fold(v_c - d_n * t, tile_h)
            if not mipmap:
                m0x[i, j] = (uf + 0.5) * level_scale[0] + level_ox[0]
                m0y[i, j] = (vf + 0.5) * level_scale[0] + level_oy[0]
                continue
            lod = math.log2(t / d_d) + log2_pixel_angle[i, j] + lod_bias
            f = lod - top
            if f > 0.0:
                any_far = True
                far[i, j] = 1.0 if f > 1.0 else f
            else:
                far[i, j] = 0.0
            if lod < 0.0:
                lod = 0.0
            elif lod > top:
                lod = top
            k = int(math.floor(lod))
            frac[i, j] = lod - k
            k1 = k + 1 if k < top else top
            m0x[i, j] = (uf + 0.5) * level_scale[k] + level_ox[k]
            m0y[i, j] = (vf + 0.5) * level_scale[k] + level_oy[k]
            m1x[i, j] = (uf + 0.5) * level_scale[k1] + level_ox[k1]
            m1y[i, j] = (vf + 0.5) * level_scale[k1] + level_oy[k1]
    return any_far


@njit(cache=True, nogil=True, error_model="numpy")
def blend_add(a: NDArray[np.uint8], b: NDArray[np.uint8], frac: NDArray[np.float32], far: NDArray[np.float32],
              use_far: bool, mean: float, hit: NDArray[np.bool_], sky: float, acc: NDArray[np.float32]) -> None:
    """Add one pose's intensity to ``acc``: the two mip levels' samples ``a`` (floor level) and ``b`` blended by
    ``frac``, faded to ``mean`` by ``far`` (when ``use_far``), ``sky`` where the ray misses the ground."""
    h, w = acc.shape
    for i in range(h):
        for j in range(w):
            if not hit[i, j]:
                acc[i, j] += sky
                continue
            x = float(a[i, j])
            x += (float(b[i, j]) - x) * frac[i, j]
            if use_far:
                x += (mean - x) * far[i, j]
            acc[i, j] += x


@njit(cache=True, nogil=True, error_model="numpy")
def to_dn(acc: NDArray[np.float32], scale: float, noise_idx: NDArray[np.uint16], noise_table: NDArray[np.float32],
          noise_std: float, out: NDArray[np.uint8]) -> None:
    """``out = rint(clip(acc * scale + noise_std * noise_table[noise_idx], 0, 255))`` (``noise_idx`` may be empty
    when ``noise_std`` is 0)."""
    h, w = acc.shape
    use_noise = noise_std > 0.0
    for i in range(h):
        for j in range(w):
            x = acc[i, j] * scale
            if use_noise:
                x += noise_std * noise_table[noise_idx[i, j]]
            if x < 0.0:
                x = 0.0
            elif x > 255.0:
                x = 255.0
            out[i, j] = np.uint8(np.rint(x))
