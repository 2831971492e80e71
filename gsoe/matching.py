"""Template matching on the stabilised images (paper 2.4): SSD search, sub-pixel refinement and match quality.

Coordinates
    A match is the position of the template's *centre* in base-image pixel coordinates ``(x_px, y_px)`` =
    (column, row), pixel centres at integers (OpenCV's convention): a template cut from the base image with its
    centre at integer pixel ``(u, v)`` matches at exactly ``(u, v)``.

Similarity
    The sum of squared differences (paper eq. 5) of the template against every candidate position;
    ``"exhaustive"`` evaluates it everywhere with one ``cv2.matchTemplate(..., TM_SQDIFF)`` call on float32;
    ``"window"`` (matching where the motion is) evaluates it only on the positions within ``radius_px`` of the
    predicted position ``start_xy`` plus ``cfg.window_margin_px`` either side (the cycle passes its step gate's
    reach: 13 x 13 of the paper geometry's 103 x 55 positions), and widens to the exhaustive search on a miss: a
    minimum in the margin, a low or ambiguous peak on the window's surface (whose sidelobe is then the window
    outside the excluded one, so the PSR is a local one, 1.2-1.5 times the whole surface's on the simulator's
    frames), or no prediction.  A window without the true match holds a match passing the gates in 1.3 % of cases
    on the test tiles; the step gate stands behind it.  ``"three_step"`` and ``"diamond"`` are the classic
    block-matching searches that evaluate it only at their candidate positions (one ``cv2.norm`` per candidate,
    memoised), starting at ``start_xy``.  On sharp imagery the SSD valley is about 1 px wide and these local
    searches are sometimes captured by a nearby local minimum (three-step 0-7 %, diamond 0-10 % of templates on the
    test textures when started within 3 px).

Sub-pixel refinement (``cfg.subpixel``)
    Two stages, both minimising the same SSD over continuous shifts.  (1) A least-squares 2-D quadratic
    ``a + b x + c y + d x^2 + e x y + f y^2`` fitted to the 3x3 SSD neighbourhood of the discrete minimum (closed
    form): near its minimum the SSD of a smooth image is a quadratic form in the shift, and the cross term keeps
    oblique valleys (diagonal edges, road verges) unbiased, which separable parabolas are not; when the fit is not
    a bowl or its bottom lies outside the neighbourhood, separable parabolas are used.  (2) ``GN_ITERATIONS``
    Gauss-Newton steps of the inverse-compositional Lucas-Kanade form on the template interior (template
    gradients and the 2x2 normal matrix computed once, the base sampled bilinearly at the current shift), started
    from (1).  On the real textures, area-downsampled from 8x resolution with known shifts, (1) alone leaves
    0.05-0.12 px RMS error (the SSD valley of sharp 0.8 m town imagery is about 1 px wide, so a quadratic on the
    1 px grid is a crude model; separable parabolas alone give 0.06-0.13 px) and (2) brings it to 0.02-0.035 px
    for two 17x17 bilinear samplings.  The Gauss-Newton result is used only while the template's normal matrix
    is well conditioned and the estimate stays within ``_MAX_SUBPIXEL_OFFSET_PX`` of the discrete minimum;
    otherwise the estimate of (1) stands.

Quality (:class:`common.samples.MatchQuality`)
    ``psr``: peak-to-sidelobe ratio of the SSD surface taken in the log domain,
    ``(mean_side(L) - L_min) / std_side(L)`` with ``L = ln(max(SSD, n_px * SSD_FLOOR_PER_PX))``, where the sidelobe
    is the surface outside a ``(2 e + 1)^2`` window around the minimum (``e = cfg.sidelobe_exclude_px``).  Why log:
    the SSD is non-negative, so on the linear surface even a perfect match scores only ``mean / std`` of the
    surface, which on textured ground is 1-3 whatever the match (measured on the project's textures with 19 px
    templates: true matches' 5th percentile 1.0-2.8, templates from elsewhere up to 2.6: no threshold separates
    them).  The log surface measures how deep the valley is *relative* to the sidelobe level, which is what tells
    a match from the best of many non-matches: true matches' 1st percentile 3.9 (with or without sensor noise of
    sigma 2), templates from elsewhere median 2.6, 22 % >= 3, 5 % >= 4.  The floor (8-bit quantisation noise)
    keeps an exact copy finite.  For the exhaustive search the sidelobe statistics come from the whole log surface
    (one ``cv2.meanStdDev`` masked to the sidelobe); the searches do not compute the whole surface, so their
    sidelobe is the ring of a local window of half-width ``e + LOCAL_RING_PX`` around the optimum (one small
    matchTemplate): a local PSR, measuring the depth of the minimum but not ambiguity beyond the ring.
    ``texture_std``: the template's intensity standard deviation.  ``ssd_per_px``: the SSD at the discrete
    minimum divided by the template's pixel count.  ``valid`` is false when ``psr < cfg.psr_min``,
    ``texture_std < cfg.texture_std_min``, the minimum lies on the border of the search surface (the true minimum
    may lie outside it, and the 3x3 fit is impossible), the match is ambiguous (another local minimum of the log
    surface within ``AMBIGUITY_MIN_GAP`` sidelobe standard deviations of the best: a repeated structure, where
    the pick is a coin toss) or the input is bad.  Intensities are on the 0-255 scale.
    No single-surface score can reject every template that has *no* true match in the base: the best of ~5000
    positions of a 19 px template on self-similar ground is sometimes convincing (22 % of such templates pass
    ``psr >= 3`` on the test textures, 5 % pass 4).  Keeping the template inside the base image is the cycle's
    job (critical position, data filter).

Bad input
    Programming errors raise :class:`ValueError`: an argument that is not a 2-D numpy array of a real numeric
    dtype (bool, complex and object arrays are rejected), a ``start_xy`` that is not two numbers.
    Data problems return an invalid result with ``x_px = y_px = nan``: an empty image or template, a template
    larger than the base image or leaving a search surface smaller than 3x3, non-finite pixel values, values so
    far outside the 0-255 scale that the float32 SSD overflows, a non-finite ``start_xy``.  No OpenCV error
    escapes: every input is checked before it reaches OpenCV.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from common.samples import MatchQuality
from gsoe.config import MatchConfig

log = logging.getLogger(__name__)

# Classic three-step search: the first step is 4 px (a power of two), then 2, then 1, so the search reaches +-7 px
# from its start.
THREE_STEP_FIRST_STEP_PX = 4
# Diamond search (Zhu & Ma 2000): the large diamond moves until its centre is best, then the small diamond refines.
# A large-diamond move advances at most 2 px, so this bounds the walk to half of a 121 px base image.
DIAMOND_MAX_MOVES = 32
_LARGE_DIAMOND = ((0, 0), (2, 0), (-2, 0), (0, 2), (0, -2), (1, 1), (1, -1), (-1, 1), (-1, -1))
_SMALL_DIAMOND = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))
# Width of the ring outside the excluded window whose SSD values are the sidelobe of the searches' local PSR.
LOCAL_RING_PX = 4
# A search's result is walked downhill on the 3x3 neighbourhood (inside its local window) at most this many times,
# so that the refinement starts at a discrete local minimum (the diamond's last pattern checks only 4 neighbours).
_MAX_POLISH_MOVES = 3
# Largest sub-pixel offset from the discrete minimum (px): a quadratic whose bottom lies farther is replaced by
# separable parabolas, and a Gauss-Newton result beyond it is discarded.
_MAX_SUBPIXEL_OFFSET_PX = 1.0
# Gauss-Newton (inverse-compositional Lucas-Kanade) iterations after the quadratic fit; the second one reduces the
# RMS error on the test textures by a further 5-25 %, a third changes nothing measurable.
GN_ITERATIONS = 2
# Gauss-Newton is skipped when the template's gradient normal matrix is this close to singular (ratio of its
# eigenvalues): a template textured along one direction only (a straight edge) cannot fix the other.
_GN_MIN_EIG_RATIO = 1e-3
# Floor of the SSD per template pixel before taking its log for the PSR (intensity units^2): the variance of 8-bit
# rounding (1/12), the smallest difference real 8-bit images can express.
SSD_FLOOR_PER_PX = 1.0 / 12.0

# A match is ambiguous, and invalid, when another local minimum of the log SSD surface (outside the excluded
# window) lies less than this many sidelobe standard deviations above the best one: two nearly equal valleys
# (repeated structures: cars in a car park, a bridge's truss) make the pick a coin toss.  Measured: true matches
# 1st percentile 1.6 on the area-downsampled textures, 5th percentile 0.9 on rendered fisheye frames over the
# town (about 2 % of those fall below 0.5); two wrong matches seen in a rendered 30 deg/s turn over the town: 0.04
# and 0.27; a true match duplicated elsewhere with independent noise: median 0.16.
AMBIGUITY_MIN_GAP = 0.5

_ACCEPTED_KINDS = "uif"


@dataclass(frozen=True, slots=True)
class MatchResult:
    """Where the template's centre lies on the base image (column, row; pixel centres at integers), sub-pixel,
    and how trustworthy that is.  ``x_px``/``y_px`` are nan when the input was bad."""

    x_px: float
    y_px: float
    quality: MatchQuality


def _invalid(reason: str) -> MatchResult:
    log.debug("match invalid: %s", reason)
    return MatchResult(math.nan, math.nan, MatchQuality(psr=0.0, texture_std=0.0, ssd_per_px=math.nan, valid=False))


def _check_array(name: str, a: object) -> NDArray:
    if not isinstance(a, np.ndarray):
        raise ValueError(f"{name}: expected a numpy array, got {type(a).__name__}")
    if a.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D intensity image, got shape {a.shape} (use to_intensity)")
    if a.dtype.kind not in _ACCEPTED_KINDS:
        raise ValueError(f"{name}: expected a real numeric dtype, got {a.dtype}")
    return a


def _as_float32(a: NDArray) -> NDArray[np.float32]:
    """The array as contiguous float32, without a copy when it already is one."""
    return np.ascontiguousarray(a, dtype=np.float32)


def texture_std(image: NDArray) -> float:
    """Intensity standard deviation of a single-channel image (DN): the texture criterion of a match
    (``MatchConfig.texture_std_min``)."""
    return float(cv2.meanStdDev(image)[1][0, 0])


def to_intensity(image: NDArray) -> NDArray[np.float32]:
    """Paper eq. 4: intensity = 0.299 R' + 0.587 G' + 0.114 B', as float32 (no rounding to integers).

    ``image`` is (H, W) grey (returned as float32, without a copy if it already is), (H, W, 1), or (H, W, 3) BGR
    / (H, W, 4) BGRA in OpenCV's channel order (alpha ignored).  Other shapes or dtypes raise ValueError.
    """
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image: expected a numpy array, got {type(image).__name__}")
    if image.dtype.kind not in _ACCEPTED_KINDS:
        raise ValueError(f"image: expected a real numeric dtype, got {image.dtype}")
    if image.ndim == 2:
        return _as_float32(image)
    if image.ndim == 3 and image.shape[2] == 1:
        return _as_float32(image[:, :, 0])
    if image.ndim == 3 and image.shape[2] in (3, 4) and image.shape[0] > 0 and image.shape[1] > 0:
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        # converting to float32 first makes OpenCV use the exact weights instead of its 8-bit fixed point
        return np.asarray(cv2.cvtColor(_as_float32(image), code), dtype=np.float32)
    raise ValueError(f"image: expected (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA, got shape {image.shape}")


def _quadratic_hessian(n3: list[list[float]]) -> tuple[float, float, float]:
    """``(h_xx, h_yy, h_xy)``: the Hessian of the least-squares quadratic ``a + b x + c y + d x^2 + e x y + f y^2``
    fitted to a 3x3 SSD neighbourhood (rows of floats, centre at [1][1]; ``h_xx = 2 d``, ``h_yy = 2 f``,
    ``h_xy = e``)."""
    (v00, v01, v02), (v10, v11, v12), (v20, v21, v22) = n3
    left, mid_c, right = v00 + v10 + v20, v01 + v11 + v21, v02 + v12 + v22
    top, mid_r, bottom = v00 + v01 + v02, v10 + v11 + v12, v20 + v21 + v22
    return (right + left - 2.0 * mid_c) / 3.0, (bottom + top - 2.0 * mid_r) / 3.0, (v00 + v22 - v02 - v20) / 4.0


def ssd_precision_px(n3: NDArray, ssd_min: float, n_px: int) -> float:
    """One-sigma error (px, per axis) of a match position implied by its SSD surface, or nan.

    Near the minimum ``SSD(d) = SSD_min + d' (H / 2) d``, and in the Gauss-Newton view ``H / 2 = sum grad I
    grad I'`` over the template, the Fisher information of the shift for a residual of variance ``s^2`` per pixel.
    So the shift's covariance is ``C = s^2 (H / 2)^-1 = 2 s^2 H^-1`` with ``s^2 = SSD_min / n_px`` (the residual
    holds both images' noise and whatever the shift does not explain), and the value returned is
    ``sqrt(trace(C) / 2) = sqrt(s^2 (h_xx + h_yy) / det H)``.  ``H`` is that of the quadratic fitted to the 3x3
    neighbourhood ``n3``; nan when it is not positive definite (a valley: no precision along it).  The same
    curvature is what makes a match precise on sharp ground and imprecise on smooth ground (5 m farmland imagery
    seen at 0.35 m/px: 0.2 px against 0.03-0.05 px on the 10 cm tiles, with sensor noise of sigma 3; the errors'
    normalised squares average 1.5-1.9 on the real tiles against the chi-square's 2, tests/test_matching.py).
    """
    return _precision_from_hessian(_quadratic_hessian(np.asarray(n3, dtype=float).tolist()), ssd_min, n_px)


def _precision_from_hessian(h: tuple[float, float, float], ssd_min: float, n_px: int) -> float:
    """:func:`ssd_precision_px` from the fitted Hessian ``(h_xx, h_yy, h_xy)`` (the matcher computes it once)."""
    hxx, hyy, hxy = h
    det = hxx * hyy - hxy * hxy
    if not (hxx > 0.0 and det > 0.0 and n_px > 0 and math.isfinite(ssd_min)):
        return math.nan
    s2 = max(ssd_min, 0.0) / n_px
    return math.sqrt(s2 * (hxx + hyy) / det)


def _quadratic_offset(n3: list[list[float]], h: tuple[float, float, float]) -> tuple[float, float]:
    """Sub-pixel offset (dx, dy) of the minimum of a 3x3 SSD neighbourhood (rows of floats, centre at [1][1]),
    given the fit's Hessian ``h`` (:func:`_quadratic_hessian`).

    Least squares of ``a + b x + c y + d x^2 + e x y + f y^2`` on x, y in {-1, 0, 1}; on this grid the normal
    equations decouple into the column/row sums below.  When the fit is not a bowl or its bottom lies farther than
    ``_MAX_SUBPIXEL_OFFSET_PX``, separable parabolas through the centre row and column are used instead.
    """
    (v00, v01, v02), (v10, v11, v12), (v20, v21, v22) = n3
    left, right = v00 + v10 + v20, v02 + v12 + v22
    top, bottom = v00 + v01 + v02, v20 + v21 + v22
    b = (right - left) / 6.0
    c = (bottom - top) / 6.0
    hxx, hyy, hxy = h
    det = hxx * hyy - hxy * hxy
    lim = _MAX_SUBPIXEL_OFFSET_PX
    if hxx > 0.0 and det > 0.0:
        dx = (-b * hyy + c * hxy) / det
        dy = (-c * hxx + b * hxy) / det
        if abs(dx) <= lim and abs(dy) <= lim:
            return dx, dy
    # not a bowl, or its bottom lies outside the neighbourhood (a long oblique valley fitted badly)
    cx = v10 - 2.0 * v11 + v12
    cy = v01 - 2.0 * v11 + v21
    dx = 0.5 * (v10 - v12) / cx if cx > 0.0 else 0.0
    dy = 0.5 * (v01 - v21) / cy if cy > 0.0 else 0.0
    return min(max(dx, -lim), lim), min(max(dy, -lim), lim)


def _gauss_newton(base: NDArray[np.float32], tpl: NDArray[np.float32], x: float, y: float, iu: int,
                  iv: int) -> tuple[float, float] | None:
    """Refine the template's top-left position (x, y) on ``base`` by inverse-compositional Gauss-Newton on the SSD.

    Works on the template interior (central differences need both neighbours); the base is sampled bilinearly
    (``cv2.getRectSubPix``).  Returns None when the normal matrix is near singular or the estimate leaves the
    +-``_MAX_SUBPIXEL_OFFSET_PX`` neighbourhood of the discrete minimum (iu, iv).
    """
    th, tw = tpl.shape
    # twice the central differences of the interior, x then y, and the interior itself as the rows of one (3, n)
    # matrix, so that one product gives the normal matrix and the template's projection G T (few NumPy calls: this
    # runs every frame); the factor 2 of the gradient is the factor 1/2 of the steps below
    G = np.empty((3, th - 2, tw - 2), np.float32)
    cv2.subtract(tpl[1:-1, 2:], tpl[1:-1, :-2], dst=G[0])
    cv2.subtract(tpl[2:, 1:-1], tpl[:-2, 1:-1], dst=G[1])
    G[2] = tpl[1:-1, 1:-1]
    G3 = G.reshape(3, -1)
    Gm = G3[:2]
    (hxx, hxy, tx), (_, hyy, ty) = Gm.dot(G3.T).tolist()
    det = hxx * hyy - hxy * hxy
    tr = hxx + hyy
    # lam_min / lam_max >= det / tr^2 of the 2x2 normal matrix; small means texture along one direction only
    if not (tr > 0.0 and det > _GN_MIN_EIG_RATIO * tr * tr):
        return None
    # the residual's projection G (I(x) - T) is G I(x) - G T: each step samples the base straight into a flat
    # vector (one getRectSubPix and one product per step)
    sampled = np.empty((th - 2) * (tw - 2), np.float32)
    patch = sampled.reshape(th - 2, tw - 2)
    size = (tw - 2, th - 2)
    # getRectSubPix takes the patch centre: the interior's first sample is at (x + 1, y + 1)
    cx, cy = 1.0 + (tw - 3) / 2.0, 1.0 + (th - 3) / 2.0
    lim = _MAX_SUBPIXEL_OFFSET_PX
    for _ in range(GN_ITERATIONS):
        cv2.getRectSubPix(base, size, (x + cx, y + cy), patch=patch)
        bx, by = Gm.dot(sampled).tolist()
        bx -= tx
        by -= ty
        x -= 2.0 * (hyy * bx - hxy * by) / det
        y -= 2.0 * (hxx * by - hxy * bx) / det
        if not (abs(x - iu) <= lim and abs(y - iv) <= lim):
            return None
    return x, y


_KERNEL_3X3 = np.ones((3, 3), np.uint8)


@functools.lru_cache(maxsize=1024)
def _sidelobe_mask(h: int, w: int, r0: int, r1: int, c0: int, c1: int) -> NDArray[np.uint8]:
    """The sidelobe of an (h, w) surface as an OpenCV mask: 255 outside rows r0..r1-1 x columns c0..c1-1, 0 inside
    (read-only: shared by every surface of that shape and window)."""
    mask = np.full((h, w), 255, np.uint8)
    mask[r0:r1, c0:c1] = 0
    mask.flags.writeable = False
    return mask


def _log_psr_and_unambiguous(surface: NDArray, iu: int, iv: int, exclude: int, floor: float) -> tuple[float, bool]:
    """Log-domain PSR of the SSD minimum at (iu, iv) (column, row), in sidelobe standard deviations of the log
    surface, and whether the match is unambiguous: no other local minimum in the sidelobe (``surface`` outside the
    excluded window) within ``AMBIGUITY_MIN_GAP`` of those standard deviations of the minimum.  The sidelobe's
    statistics come from one masked ``cv2.meanStdDev`` (in double).  The sidelobe's lowest point bounds its local
    minima from below, so when it lies far enough above the minimum, as it does for most matches, the local minima
    need not be found.
    """
    h, w = surface.shape
    r0, r1 = max(iv - exclude, 0), min(iv + exclude + 1, h)
    c0, c1 = max(iu - exclude, 0), min(iu + exclude + 1, w)
    if h * w - (r1 - r0) * (c1 - c0) < 2:
        return 0.0, False
    side = _sidelobe_mask(h, w, r0, r1, c0, c1)
    log_s = np.maximum(surface, floor)
    np.log(log_s, out=log_s)
    mean, std = cv2.meanStdDev(log_s, mask=side)
    side_mean, side_std = float(mean[0, 0]), float(std[0, 0])
    if not (side_std > 0.0 and math.isfinite(side_std)):
        return 0.0, False
    l_min = float(log_s[iv, iu])
    psr = (side_mean - l_min) / side_std
    psr = psr if math.isfinite(psr) else 0.0
    if (cv2.minMaxLoc(log_s, mask=side)[0] - l_min) / side_std >= AMBIGUITY_MIN_GAP:
        return psr, True
    # other local minima: points no higher than their 8 neighbours (erosion's default border, +inf, keeps an edge
    # point's neighbourhood to the surface), in the sidelobe
    local_min = cv2.compare(log_s, cv2.erode(log_s, _KERNEL_3X3), cv2.CMP_LE)
    local_min[r0:r1, c0:c1] = 0
    other_min, _, loc, _ = cv2.minMaxLoc(log_s, mask=local_min)
    # (-1, -1): no other valley in view
    return psr, loc[0] < 0 or (other_min - l_min) / side_std >= AMBIGUITY_MIN_GAP


class _SsdProbe:
    """SSD (double precision, ``cv2.norm`` L2SQR) at integer template positions (top-left corners), memoised."""

    def __init__(self, base: NDArray[np.float32], template: NDArray[np.float32]) -> None:
        self.base = base
        self.template = template
        self.th, self.tw = template.shape
        self.nv, self.nu = base.shape[0] - self.th + 1, base.shape[1] - self.tw + 1
        self.cache: dict[tuple[int, int], float] = {}

    def ssd(self, u: int, v: int) -> float:
        val = self.cache.get((u, v))
        if val is None:
            val = cv2.norm(self.base[v:v + self.th, u:u + self.tw], self.template, cv2.NORM_L2SQR)
            self.cache[(u, v)] = val
        return val

    def best(self, centre: tuple[int, int], offsets: tuple[tuple[int, int], ...]) -> tuple[int, int]:
        """The candidate ``centre + offset`` inside the surface with the lowest SSD; ties keep the earlier one
        (offsets start with (0, 0), so the centre wins ties)."""
        cu, cv = centre
        best, best_val = centre, self.ssd(cu, cv)
        for du, dv in offsets[1:]:
            u, v = cu + du, cv + dv
            if 0 <= u < self.nu and 0 <= v < self.nv:
                val = self.ssd(u, v)
                if val < best_val:
                    best, best_val = (u, v), val
        return best


def _scaled(offsets: tuple[tuple[int, int], ...], k: int) -> tuple[tuple[int, int], ...]:
    return tuple((k * du, k * dv) for du, dv in offsets)


_RING = ((0, 0), (-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1))
_THREE_STEP_PATTERNS = tuple(_scaled(_RING, THREE_STEP_FIRST_STEP_PX >> i)
                             for i in range(THREE_STEP_FIRST_STEP_PX.bit_length()))


def _three_step(probe: _SsdProbe, start: tuple[int, int]) -> tuple[int, int]:
    pos = start
    for pattern in _THREE_STEP_PATTERNS:  # steps 4, 2, 1
        pos = probe.best(pos, pattern)
    return pos


def _diamond(probe: _SsdProbe, start: tuple[int, int]) -> tuple[int, int]:
    pos = start
    for _ in range(DIAMOND_MAX_MOVES):
        nxt = probe.best(pos, _LARGE_DIAMOND)
        if nxt == pos:
            break
        pos = nxt
    return probe.best(pos, _SMALL_DIAMOND)


def match_template(base: NDArray, template: NDArray, cfg: MatchConfig,
                   start_xy: tuple[float, float] | None = None, radius_px: int | None = None) -> MatchResult:
    """Find ``template`` in ``base`` by SSD (paper eq. 5) with the search method ``cfg.method``.

    Parameters
    ----------
    base, template
        2-D intensity images on the 0-255 scale (any real dtype; float32 avoids a conversion), the template no
        larger than the base.
    cfg
        Method, sub-pixel switch and quality gates.
    start_xy
        Where the searches start: the expected template centre (column, row) in base pixels, rounded to the
        nearest position and clipped into the search surface; default the base image's centre.  For
        ``"window"`` the centre of the window; ignored by ``"exhaustive"``.
    radius_px
        ``"window"`` only: how far (positions, either axis) from ``start_xy`` a match may lie; the window searched
        is ``cfg.window_margin_px`` wider either side (the peak's neighbourhood and sidelobe), and a minimum in
        that margin is a miss.  None (or no ``start_xy``): the whole surface.

    Returns
    -------
    MatchResult
        Template centre (column, row) on the base image, sub-pixel when ``cfg.subpixel``, with its quality.
        See the module docstring for what raises and what returns an invalid result.
    """
    base = _check_array("base", base)
    template = _check_array("template", template)
    sx = sy = 0.0
    if start_xy is not None:
        try:
            sx, sy = map(float, start_xy)
        except (TypeError, ValueError):
            raise ValueError(f"start_xy: expected two numbers (x, y), got {start_xy!r}") from None
        if not (math.isfinite(sx) and math.isfinite(sy)):
            return _invalid(f"non-finite start_xy {start_xy!r}")
    if radius_px is not None and not (isinstance(radius_px, int | np.integer) and radius_px >= 1):
        raise ValueError(f"radius_px: expected an integer >= 1 or None, got {radius_px!r}")
    bh, bw = base.shape
    th, tw = template.shape
    if th == 0 or tw == 0 or bh == 0 or bw == 0:
        return _invalid("empty image or template")
    if th > bh or tw > bw:
        return _invalid(f"template {template.shape} larger than base {base.shape}")
    nv, nu = bh - th + 1, bw - tw + 1
    if nu < 3 or nv < 3 or th < 3 or tw < 3:
        return _invalid(f"template {template.shape} on base {base.shape}: search surface {nv}x{nu}, need 3x3")
    base32 = _as_float32(base)
    tpl32 = _as_float32(template)
    tpl_mean, tpl_sd = cv2.meanStdDev(tpl32)
    tpl_std = float(tpl_sd[0, 0])
    if not math.isfinite(float(tpl_mean[0, 0]) + tpl_std):
        return _invalid("non-finite pixel values")
    exclude = cfg.sidelobe_exclude_px
    floor = th * tw * SSD_FLOOR_PER_PX

    if cfg.method == "window" and start_xy is not None and radius_px is not None:
        cu, cv_ = _clipped_start(sx, sy, tw, th, nu, nv)
        r = radius_px + cfg.window_margin_px
        u0, v0 = max(cu - r, 0), max(cv_ - r, 0)
        u1, v1 = min(cu + r, nu - 1), min(cv_ + r, nv - 1)
        if (u1 - u0 + 1) * (v1 - v0 + 1) < nu * nv:
            res = _match_in(base32, tpl32, u0, v0, u1, v1, tpl_std, cfg, floor)
            # a template without texture is invalid wherever it is searched; a miss (a minimum farther than
            # radius_px from the start, a low or ambiguous peak, bad data) widens to the whole surface
            if tpl_std < cfg.texture_std_min:
                return res
            if res.quality.valid and (abs(res.x_px - (tw - 1) / 2.0 - cu) <= radius_px + 0.5
                                      and abs(res.y_px - (th - 1) / 2.0 - cv_) <= radius_px + 0.5):
                return res
    if cfg.method in ("exhaustive", "window"):
        return _match_in(base32, tpl32, 0, 0, nu - 1, nv - 1, tpl_std, cfg, floor)
    if not math.isfinite(float(base32.sum(dtype=np.float64))):
        return _invalid("non-finite pixel values")
    probe = _SsdProbe(base32, tpl32)
    start = ((nu - 1) // 2, (nv - 1) // 2) if start_xy is None else _clipped_start(sx, sy, tw, th, nu, nv)
    iu, iv = _three_step(probe, start) if cfg.method == "three_step" else _diamond(probe, start)
    # Local window around the optimum: its ring gives the local PSR, its centre the 3x3 neighbourhood.  The
    # optimum is first walked downhill over its 8 neighbours so that the refinement starts at a local minimum.
    r = exclude + LOCAL_RING_PX
    for _ in range(_MAX_POLISH_MOVES + 1):
        u0, v0 = max(iu - r, 0), max(iv - r, 0)
        u1, v1 = min(iu + r, nu - 1), min(iv + r, nv - 1)
        surface = cv2.matchTemplate(base32[v0:v1 + th, u0:u1 + tw], tpl32, cv2.TM_SQDIFF)
        lu, lv = iu - u0, iv - v0
        nb = surface[max(lv - 1, 0):lv + 2, max(lu - 1, 0):lu + 2]
        mv, mu = divmod(int(np.argmin(nb)), nb.shape[1])
        if nb[mv, mu] >= surface[lv, lu]:
            break
        iu, iv = max(lu - 1, 0) + mu + u0, max(lv - 1, 0) + mv + v0
    on_border = iu == 0 or iv == 0 or iu == nu - 1 or iv == nv - 1
    return _result(base32, tpl32, surface, u0, v0, iu - u0, iv - v0, on_border, cv2.minMaxLoc(surface)[1], tpl_std,
                   cfg, floor)


def _clipped_start(sx: float, sy: float, tw: int, th: int, nu: int, nv: int) -> tuple[int, int]:
    """The surface position (template top-left) nearest the template centre ``(sx, sy)``, clipped into it."""
    return min(max(round(sx - (tw - 1) / 2.0), 0), nu - 1), min(max(round(sy - (th - 1) / 2.0), 0), nv - 1)


def _match_in(base32: NDArray[np.float32], tpl32: NDArray[np.float32], u0: int, v0: int, u1: int, v1: int,
              tpl_std: float, cfg: MatchConfig, floor: float) -> MatchResult:
    """The SSD surface over the template positions ``u0..u1`` x ``v0..v1`` (inclusive), its minimum and quality; a
    minimum on the edge of that window is on the border (the true one may lie outside)."""
    th, tw = tpl32.shape
    region = base32[v0:v1 + th, u0:u1 + tw]
    if not cv2.checkRange(region)[0]:
        return _invalid("non-finite pixel values")
    surface = cv2.matchTemplate(region, tpl32, cv2.TM_SQDIFF)
    _, ssd_max, (lu, lv), _ = cv2.minMaxLoc(surface)
    on_border = lu == 0 or lv == 0 or lu == u1 - u0 or lv == v1 - v0
    return _result(base32, tpl32, surface, u0, v0, lu, lv, on_border, ssd_max, tpl_std, cfg, floor)


def _result(base32: NDArray[np.float32], tpl32: NDArray[np.float32], surface: NDArray, u0: int, v0: int,
            lu: int, lv: int, on_border: bool, ssd_max: float, tpl_std: float, cfg: MatchConfig,
            floor: float) -> MatchResult:
    """Quality gates and sub-pixel refinement of the minimum at ``(lu, lv)`` of ``surface``, whose position (0, 0)
    is the template position ``(u0, v0)`` on the base."""
    th, tw = tpl32.shape
    iu, iv = lu + u0, lv + v0
    ssd_min = float(surface[lv, lu])
    if not (math.isfinite(ssd_max) and math.isfinite(ssd_min)):
        return _invalid("SSD overflow (pixel values far outside the 0-255 scale)")
    psr, unambiguous = _log_psr_and_unambiguous(surface, lu, lv, cfg.sidelobe_exclude_px, floor)
    valid = (not on_border) and psr >= cfg.psr_min and tpl_std >= cfg.texture_std_min and unambiguous
    # off the border the minimum has its full 3x3 neighbourhood (the local searches' window keeps a ring round it)
    n3 = surface[lv - 1:lv + 2, lu - 1:lu + 2].tolist() if not on_border else None
    hess = _quadratic_hessian(n3) if n3 is not None else None
    sigma = _precision_from_hessian(hess, ssd_min, th * tw) if hess is not None else math.nan
    quality = MatchQuality(psr=psr, texture_std=tpl_std, ssd_per_px=max(ssd_min, 0.0) / (th * tw),
                           valid=bool(valid), match_sigma_px=sigma)
    x, y = float(iu), float(iv)
    if cfg.subpixel and n3 is not None and hess is not None:
        dx, dy = _quadratic_offset(n3, hess)
        x, y = iu + dx, iv + dy
        refined = _gauss_newton(base32, tpl32, x, y, iu, iv)
        if refined is not None:
            x, y = refined
    return MatchResult(x_px=x + (tw - 1) / 2.0, y_px=y + (th - 1) / 2.0, quality=quality)
