"""Target trackers for video-tracking guidance: an interface and a template tracker (OpenCV ``matchTemplate``).

A tracker is designated a target (a pixel in one frame) and then, frame by frame, reports where the target is in
the raw image (column, row in pixels, the camera frame ``c`` convention of :mod:`gsoe`), with a score and a
verdict.  Any implementation of :class:`Tracker` plugs into the companion (an OpenCV contrib tracker, a neural
detector on a coprocessor, an external video tracker reporting over MAVLink).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from common.config import In, Validated, in_range


@dataclass(frozen=True, slots=True)
class TrackResult:
    """Target position ``xy_px`` (column, row) in the raw image at ``t_us``; ``score`` in [-1, 1] (normalised
    correlation for the template tracker); ``valid`` false with ``reason`` when the target is lost."""

    t_us: int
    xy_px: tuple[float, float]
    score: float
    valid: bool
    reason: str = ""


class Tracker(Protocol):
    """What the companion needs from a tracker."""

    def designate(self, t_us: int, frame: NDArray[np.uint8], xy_px: tuple[float, float]) -> bool:
        """Start tracking the target at ``xy_px`` in ``frame``; false when it cannot (e.g. off image, no texture)."""
        ...

    def update(self, t_us: int, frame: NDArray[np.uint8]) -> TrackResult:
        """Find the target in ``frame``."""
        ...

    @property
    def active(self) -> bool:
        """A target is designated."""
        ...


@dataclass(frozen=True)
class TemplateTrackerConfig(Validated):
    """``[companion.tracker]``: template tracker parameters.

    ``template_px`` (odd) square template around the target; ``search_px``: half-size of the search window around
    the last position; ``min_score``: normalised correlation (TM_CCOEFF_NORMED) below which the target is lost;
    ``update_score``: above this the template is refreshed from the current frame (follows the slow change of the
    target's appearance as range and perspective change); ``min_texture_std``: intensity std (0-255) a template
    needs; ``max_lost_frames``: after this many lost frames in a row the target is dropped.
    """

    template_px: Annotated[int, In(5, 255, odd=True)] = 31
    search_px: Annotated[int, In(1, 1024)] = 48
    min_score: Annotated[float, In(-1.0, 1.0)] = 0.7
    update_score: Annotated[float, In(-1.0, 1.0)] = 0.85
    min_texture_std: Annotated[float, In(0.0, 255.0)] = 4.0
    max_lost_frames: Annotated[int, In(1, 100000)] = 30


def _gray(frame: NDArray[np.uint8]) -> NDArray[np.uint8] | None:
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.size == 0:
        return None
    if frame.ndim == 2:
        return frame
    if frame.ndim == 3 and frame.shape[2] == 3:
        return np.asarray(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    if frame.ndim == 3 and frame.shape[2] == 1:
        return frame[:, :, 0]
    return None


class TemplateTracker:
    """Normalised cross-correlation tracking of a square template in a window around the last position."""

    def __init__(self, config: TemplateTrackerConfig | None = None) -> None:
        self.config = config or TemplateTrackerConfig()
        self._template: NDArray[np.uint8] | None = None
        self._xy = (math.nan, math.nan)
        self._lost = 0

    @property
    def active(self) -> bool:
        return self._template is not None

    def drop(self) -> None:
        self._template = None
        self._lost = 0

    def _cut(self, gray: NDArray[np.uint8], xy: tuple[float, float]) -> NDArray[np.uint8] | None:
        half = self.config.template_px // 2
        c, r = int(round(xy[0])), int(round(xy[1]))
        h, w = gray.shape
        if c - half < 0 or r - half < 0 or c + half >= w or r + half >= h:
            return None
        return gray[r - half:r + half + 1, c - half:c + half + 1].copy()

    def designate(self, t_us: int, frame: NDArray[np.uint8], xy_px: tuple[float, float]) -> bool:
        gray = _gray(frame)
        if gray is None or not all(math.isfinite(v) for v in xy_px):
            return False
        tpl = self._cut(gray, xy_px)
        if tpl is None or float(np.std(tpl)) < self.config.min_texture_std:
            return False
        self._template = tpl
        self._xy = (float(xy_px[0]), float(xy_px[1]))
        self._lost = 0
        return True

    def update(self, t_us: int, frame: NDArray[np.uint8]) -> TrackResult:
        if self._template is None:
            return TrackResult(t_us, (math.nan, math.nan), math.nan, False, "no target designated")
        gray = _gray(frame)
        if gray is None:
            return self._lose(t_us, "unusable frame")
        half = self.config.template_px // 2
        reach = half + self.config.search_px
        c, r = int(round(self._xy[0])), int(round(self._xy[1]))
        h, w = gray.shape
        c0, c1 = max(0, c - reach), min(w, c + reach + 1)
        r0, r1 = max(0, r - reach), min(h, r + reach + 1)
        window = gray[r0:r1, c0:c1]
        if window.shape[0] < self.config.template_px or window.shape[1] < self.config.template_px:
            return self._lose(t_us, "target at the image edge")
        if float(np.std(window)) < self.config.min_texture_std:
            return self._lose(t_us, "no texture in the search window")
        surface = cv2.matchTemplate(window, self._template, cv2.TM_CCOEFF_NORMED)
        _, score, _, loc = cv2.minMaxLoc(surface)
        if not math.isfinite(score) or score < self.config.min_score:
            return self._lose(t_us, f"match score {score:.2f} < {self.config.min_score}")
        dx, dy = self._subpixel(np.asarray(surface, dtype=np.float32), (int(loc[0]), int(loc[1])))
        xy = (c0 + loc[0] + dx + half, r0 + loc[1] + dy + half)
        self._xy = (float(xy[0]), float(xy[1]))
        self._lost = 0
        if score >= self.config.update_score:
            tpl = self._cut(gray, self._xy)
            if tpl is not None and float(np.std(tpl)) >= self.config.min_texture_std:
                self._template = tpl
        return TrackResult(t_us, self._xy, float(score), True)

    @staticmethod
    def _subpixel(surface: NDArray[np.float32], loc: tuple[int, int]) -> tuple[float, float]:
        """Parabola through the peak and its neighbours, per axis (0 at the border)."""
        x, y = loc
        out = []
        for d, (lo, hi) in enumerate((((x - 1, y), (x + 1, y)), ((x, y - 1), (x, y + 1)))):
            size = surface.shape[1] if d == 0 else surface.shape[0]
            idx = x if d == 0 else y
            if idx <= 0 or idx >= size - 1:
                out.append(0.0)
                continue
            a, b, c = float(surface[lo[1], lo[0]]), float(surface[y, x]), float(surface[hi[1], hi[0]])
            den = a - 2.0 * b + c
            out.append(0.0 if den >= 0.0 else max(-0.5, min(0.5, 0.5 * (a - c) / den)))
        return out[0], out[1]

    def _lose(self, t_us: int, reason: str) -> TrackResult:
        self._lost += 1
        if self._lost > self.config.max_lost_frames:
            self._template = None
            reason += "; target dropped"
        return TrackResult(t_us, self._xy, math.nan, False, reason)


class ExternalTracker:
    """The output of an external video tracker (a gimbal camera's tracker, a detector on a coprocessor, or the
    simulator's tracking-camera hook) reported over MAVLink as CAMERA_TRACKING_IMAGE_STATUS.

    :meth:`push` takes each report (:class:`nav.link.TrackReading`: a point normalised to the image, 0 at the left/top
    image edge and 1 at the right/bottom edge); :meth:`update` returns the newest one as pixels (column, row, pixel
    centres at integers: ``x_px = x_norm * width - 0.5``) of a camera of ``size_px`` when it is active and at most
    ``max_age_s`` old.  The target is designated on the tracker's side, so :meth:`designate` only reports whether
    the tracker is active.
    """

    def __init__(self, size_px: tuple[int, int], max_age_s: float) -> None:
        in_range(max_age_s, 0.0, 60.0, "max_age_s", lo_open=True)
        self.size_px = size_px
        self.max_age_us = int(max_age_s * 1e6)
        self._last: tuple[int, float, float, bool] | None = None

    def push(self, t_us: int, x_norm: float, y_norm: float, active: bool) -> None:
        self._last = (int(t_us), float(x_norm), float(y_norm), bool(active))

    @property
    def active(self) -> bool:
        return self._last is not None and self._last[3]

    def designate(self, t_us: int, frame: NDArray[np.uint8], xy_px: tuple[float, float]) -> bool:
        return self.active

    def drop(self) -> None:
        self._last = None

    def update(self, t_us: int, frame: NDArray[np.uint8] | None = None) -> TrackResult:
        nan2 = (math.nan, math.nan)
        if self._last is None:
            return TrackResult(t_us, nan2, math.nan, False, "no tracker report")
        t, x, y, active = self._last
        if not active:
            return TrackResult(t_us, nan2, math.nan, False, "external tracker not tracking")
        if not (0 <= t_us - t <= self.max_age_us):
            return TrackResult(t_us, nan2, math.nan, False, f"tracker report {abs(t_us - t) / 1e6:.2f} s old")
        if not (math.isfinite(x) and math.isfinite(y) and 0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
            return TrackResult(t_us, nan2, math.nan, False, "tracker point outside the image")
        w, h = self.size_px
        return TrackResult(t_us, (x * w - 0.5, y * h - 0.5), 1.0, True)
