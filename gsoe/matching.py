"""Template matching on the stabilised images (paper 2.4): SSD search, sub-pixel refinement and match quality.

Coordinates
    A match is the position of the template's *centre* in base-image pixel coordinates ``(x_px, y_px)`` =
    (column, row), pixel centres at integers (OpenCV's convention): a template cut from the base image with its
    centre at integer pixel ``(u, v)`` matches at exactly ``(u, v)``.

Similarity
    The sum of squared differences (paper eq. 5) of the template against every candidate position;
    ``"exhaustive"`` evaluates it everywhere with one ``cv2.matchTemplate(..., TM_SQDIFF)`` call on float32,
    ``"three_step"`` and ``"diamond"`` are the classic block-matching searches that evaluate it only at their
    candidate positions (a gather of a few windows, vectorised in numpy), starting at ``start_xy``.

Sub-pixel refinement
    A least-squares 2-D quadratic ``a + b x + c y + d x^2 + e x y + f y^2`` fitted to the 3x3 SSD neighbourhood of
    the discrete minimum; its stationary point is the sub-pixel minimum.  Near its minimum the SSD of a smooth
    image is a quadratic form in the shift (second-order Taylor expansion of the template), so a quadratic is the
    right model (a Gaussian fit suits correlation peaks, not SSD valleys); the cross term ``e`` keeps oblique
    valleys (diagonal edges, road verges) unbiased, which separable parabolas are not.  When the fitted quadratic
    is not a bowl (not positive definite), separable 1-D parabolas through the centre row and column are used,
    and an axis without positive curvature keeps its integer position.  The fit is a fixed 6x9 matrix product.

Quality (:class:`gsoe.types.MatchQuality`)
    ``psr``: peak-to-sidelobe ratio of the SSD surface, ``(mean_side - ssd_min) / std_side`` where the sidelobe
    is the surface outside a ``(2 e + 1)^2`` window around the minimum (``e = cfg.sidelobe_exclude_px``).  For the
    exhaustive search the sidelobe statistics come from the whole surface (its sums, from one
    ``cv2.meanStdDev``, minus the window's); the searches do not compute the whole surface, so their sidelobe is
    the ring of a local window of half-width ``e + LOCAL_RING_PX`` around the optimum (one small matchTemplate):
    a local PSR, measuring the sharpness of the minimum but not ambiguity beyond the ring.
    ``texture_std``: the template's intensity standard deviation (0-255 scale).  ``ssd_per_px``: the SSD at the
    discrete minimum divided by the template's pixel count.  ``valid`` is false when ``psr < cfg.psr_min``,
    ``texture_std < cfg.texture_std_min``, the minimum lies on the border of the search surface (the true minimum
    may lie outside it, and the 3x3 fit is impossible) or the input is bad.

Bad input
    Programming errors raise :class:`ValueError`: an argument that is not a 2-D numpy array of a real numeric
    dtype (bool, complex and object arrays are rejected), a ``start_xy`` that is not two numbers.
    Data problems return an invalid result with ``x_px = y_px = nan``: an empty image or template, a template
    larger than the base image or leaving a search surface smaller than 3x3, non-finite pixel values, a
    non-finite ``start_xy``.  Nothing reaches OpenCV unchecked.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from gsoe.config import MatchConfig
from gsoe.types import MatchQuality

log = logging.getLogger(__name__)

# Classic three-step search: the first step is 4 px, then 2, then 1, so the search reaches +-7 px from its start.
THREE_STEP_FIRST_STEP_PX = 4
# Diamond search (Zhu & Ma 2000): the large diamond moves until its centre is best, then the small diamond refines.
# A large-diamond move advances at most 2 px, so this bounds the walk to half of a 121 px base image.
DIAMOND_MAX_MOVES = 32
_LARGE_DIAMOND = np.array([(0, 0), (2, 0), (-2, 0), (0, 2), (0, -2), (1, 1), (1, -1), (-1, 1), (-1, -1)])
_SMALL_DIAMOND = np.array([(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)])
# Width of the ring outside the excluded window whose SSD values are the sidelobe of the searches' local PSR.
LOCAL_RING_PX = 4
# A search's result is walked downhill on the 3x3 neighbourhood (inside its local window) at most this many times,
# so that the refinement starts at a discrete local minimum (the diamond's last pattern checks only 4 neighbours).
_MAX_POLISH_MOVES = 3
# Largest sub-pixel offset accepted from the quadratic fit (px); a stationary point farther away is not a minimum
# of the 3x3 neighbourhood and is clipped.
_MAX_SUBPIXEL_OFFSET_PX = 1.0

# Least-squares fit of a + b x + c y + d x^2 + e xy + f y^2 on the 3x3 grid x, y in {-1, 0, 1} (row-major).
_YY, _XX = np.mgrid[-1:2, -1:2]
_QUAD_DESIGN = np.column_stack([np.ones(9), _XX.ravel(), _YY.ravel(), _XX.ravel() ** 2, (_XX * _YY).ravel(),
                                _YY.ravel() ** 2])
_QUAD_PINV = np.linalg.pinv(_QUAD_DESIGN)

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
        return cv2.cvtColor(_as_float32(image), code)
    raise ValueError(f"image: expected (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA, got shape {image.shape}")


def _refine(n3: NDArray) -> tuple[float, float]:
    """Sub-pixel offset (dx, dy) of the minimum of a 3x3 SSD neighbourhood (row-major, centre at [1, 1])."""
    a = _QUAD_PINV @ n3.ravel().astype(np.float64)
    _, b, c, d, e, f = a
    hxx, hxy, hyy = 2.0 * d, e, 2.0 * f
    det = hxx * hyy - hxy * hxy
    if hxx > 0.0 and det > 0.0:
        dx = (-b * hyy + c * hxy) / det
        dy = (-c * hxx + b * hxy) / det
    else:  # not a bowl: separable parabolas through the centre row and column
        row, col = n3[1].astype(np.float64), n3[:, 1].astype(np.float64)
        cx = row[0] - 2.0 * row[1] + row[2]
        cy = col[0] - 2.0 * col[1] + col[2]
        dx = 0.5 * (row[0] - row[2]) / cx if cx > 0.0 else 0.0
        dy = 0.5 * (col[0] - col[2]) / cy if cy > 0.0 else 0.0
    lim = _MAX_SUBPIXEL_OFFSET_PX
    return float(np.clip(dx, -lim, lim)), float(np.clip(dy, -lim, lim))


def _psr_from_sums(s1: float, s2: float, n: int, ssd_min: float) -> float:
    """PSR from the sidelobe's sum, sum of squares and count."""
    if n < 2:
        return 0.0
    mean = s1 / n
    var = max(s2 / n - mean * mean, 0.0)
    std = math.sqrt(var)
    if not (std > 0.0 and math.isfinite(std)):
        return 0.0
    return (mean - ssd_min) / std


def _window_psr(surface: NDArray[np.float32], iu: int, iv: int, exclude: int) -> float:
    """PSR of the SSD minimum at (iu, iv) (column, row): the sidelobe is ``surface`` outside the excluded window.

    The sidelobe's sums are the whole surface's (one ``cv2.meanStdDev``, in double) minus the small window's.
    """
    mean, std = cv2.meanStdDev(surface)
    n_all = surface.size
    m, s = float(mean[0, 0]), float(std[0, 0])
    s1_all = n_all * m
    s2_all = n_all * (s * s + m * m)
    h, w = surface.shape
    win = surface[max(iv - exclude, 0):min(iv + exclude + 1, h), max(iu - exclude, 0):min(iu + exclude + 1, w)]
    win64 = win.astype(np.float64)
    s1 = s1_all - float(win64.sum())
    s2 = s2_all - float(np.dot(win64.ravel(), win64.ravel()))
    return _psr_from_sums(s1, s2, n_all - win.size, float(surface[iv, iu]))


def _quality(psr: float, texture_std: float, ssd_min: float, n_px: int, on_border: bool,
             cfg: MatchConfig) -> MatchQuality:
    valid = (not on_border) and psr >= cfg.psr_min and texture_std >= cfg.texture_std_min and math.isfinite(psr)
    return MatchQuality(psr=float(psr), texture_std=float(texture_std), ssd_per_px=max(ssd_min, 0.0) / n_px,
                        valid=bool(valid))


class _SsdProbe:
    """SSD at arbitrary integer template positions (top-left corners), memoised, evaluated in vectorised batches."""

    def __init__(self, base: NDArray[np.float32], template: NDArray[np.float32]) -> None:
        th, tw = template.shape
        self.windows = np.lib.stride_tricks.sliding_window_view(base, (th, tw))
        self.template = template
        self.nv, self.nu = self.windows.shape[:2]
        self.cache: dict[tuple[int, int], float] = {}

    def inside(self, u: int, v: int) -> bool:
        return 0 <= u < self.nu and 0 <= v < self.nv

    def best(self, centre: tuple[int, int], offsets: NDArray) -> tuple[int, int]:
        """The candidate ``centre + offsets`` (inside the surface) with the lowest SSD; ties keep the centre."""
        cand = [(centre[0] + int(du), centre[1] + int(dv)) for du, dv in offsets]
        cand = [p for p in cand if self.inside(*p)]
        todo = [p for p in cand if p not in self.cache]
        if todo:
            us = np.fromiter((p[0] for p in todo), dtype=np.intp, count=len(todo))
            vs = np.fromiter((p[1] for p in todo), dtype=np.intp, count=len(todo))
            diff = self.windows[vs, us] - self.template
            ssd = np.einsum("kij,kij->k", diff, diff, dtype=np.float64)
            self.cache.update(zip(todo, ssd.tolist(), strict=True))
        best = centre
        best_val = self.cache[centre]
        for p in cand:
            if self.cache[p] < best_val:
                best, best_val = p, self.cache[p]
        return best


def _three_step(probe: _SsdProbe, start: tuple[int, int]) -> tuple[int, int]:
    pos = start
    step = THREE_STEP_FIRST_STEP_PX
    ring = np.array([(du, dv) for dv in (-1, 0, 1) for du in (-1, 0, 1)])
    while step >= 1:
        pos = probe.best(pos, ring * step)
        step //= 2
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
                   start_xy: tuple[float, float] | None = None) -> MatchResult:
    """Find ``template`` in ``base`` by SSD (paper eq. 5) with the search method ``cfg.method``.

    Parameters
    ----------
    base, template
        2-D intensity images (any real dtype; float32 avoids a conversion), template no larger than base.
    cfg
        Method, sub-pixel switch and quality gates.
    start_xy
        Where the searches (``"three_step"``, ``"diamond"``) start: the expected template centre (column, row) in
        base pixels; default the base image's centre.  Ignored by ``"exhaustive"``.

    Returns
    -------
    MatchResult
        Template centre position (column, row) on the base image, sub-pixel when ``cfg.subpixel``, with quality.
        See the module docstring for what raises and what returns an invalid result.
    """
    base = _check_array("base", base)
    template = _check_array("template", template)
    if start_xy is not None:
        if len(start_xy) != 2:
            raise ValueError(f"start_xy: expected (x, y), got {start_xy!r}")
        sx, sy = float(start_xy[0]), float(start_xy[1])
        if not (math.isfinite(sx) and math.isfinite(sy)):
            return _invalid(f"non-finite start_xy {start_xy!r}")
    bh, bw = base.shape
    th, tw = template.shape
    if th == 0 or tw == 0 or bh == 0 or bw == 0:
        return _invalid("empty image or template")
    if th > bh or tw > bw:
        return _invalid(f"template {template.shape} larger than base {base.shape}")
    nv, nu = bh - th + 1, bw - tw + 1
    if nu < 3 or nv < 3:
        return _invalid(f"search surface {nv}x{nu} smaller than 3x3")
    base32 = _as_float32(base)
    tpl32 = _as_float32(template)
    if not (math.isfinite(float(base32.sum(dtype=np.float64))) and math.isfinite(float(tpl32.sum(dtype=np.float64)))):
        return _invalid("non-finite pixel values")
    texture_std = float(cv2.meanStdDev(tpl32)[1][0, 0])
    hx, hy = (tw - 1) / 2.0, (th - 1) / 2.0
    exclude = cfg.sidelobe_exclude_px

    if cfg.method == "exhaustive":
        surface = cv2.matchTemplate(base32, tpl32, cv2.TM_SQDIFF)
        _, _, (iu, iv), _ = cv2.minMaxLoc(surface)
        psr = _window_psr(surface, iu, iv, exclude)
        on_border = iu == 0 or iv == 0 or iu == nu - 1 or iv == nv - 1
        n3 = None if on_border else surface[iv - 1:iv + 2, iu - 1:iu + 2]
        ssd_min = float(surface[iv, iu])
    else:
        probe = _SsdProbe(base32, tpl32)
        if start_xy is None:
            start = ((nu - 1) // 2, (nv - 1) // 2)
        else:
            start = (int(round(sx - hx)), int(round(sy - hy)))
            start = (min(max(start[0], 0), nu - 1), min(max(start[1], 0), nv - 1))
        iu, iv = _three_step(probe, start) if cfg.method == "three_step" else _diamond(probe, start)
        # local window around the optimum: its ring gives the local PSR, its centre the 3x3 neighbourhood
        r = exclude + LOCAL_RING_PX
        for _ in range(_MAX_POLISH_MOVES + 1):
            u0, u1 = max(iu - r, 0), min(iu + r, nu - 1)
            v0, v1 = max(iv - r, 0), min(iv + r, nv - 1)
            local = cv2.matchTemplate(base32[v0:v1 + th, u0:u1 + tw], tpl32, cv2.TM_SQDIFF)
            lu, lv = iu - u0, iv - v0
            nb = local[max(lv - 1, 0):lv + 2, max(lu - 1, 0):lu + 2]
            k = int(np.argmin(nb))
            mv, mu = divmod(k, nb.shape[1])
            nu_, nv_ = max(lu - 1, 0) + mu + u0, max(lv - 1, 0) + mv + v0
            if (nu_, nv_) == (iu, iv) or nb.flat[k] >= local[lv, lu]:
                break
            iu, iv = nu_, nv_
        lu, lv = iu - u0, iv - v0
        psr = _window_psr(local, lu, lv, exclude)
        on_border = iu == 0 or iv == 0 or iu == nu - 1 or iv == nv - 1
        n3 = None if on_border else local[lv - 1:lv + 2, lu - 1:lu + 2]
        ssd_min = float(local[lv, lu])

    quality = _quality(psr, texture_std, ssd_min, th * tw, on_border, cfg)
    dx = dy = 0.0
    if cfg.subpixel and n3 is not None:
        dx, dy = _refine(n3)
    return MatchResult(x_px=iu + hx + dx, y_px=iv + hy + dy, quality=quality)
