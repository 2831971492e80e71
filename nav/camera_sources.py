"""The companion's camera sources besides the simulator's stream: a V4L2 (or any OpenCV) device, a video file, a
Raspberry Pi camera through picamera2, an RTSP/HTTP stream, a GStreamer pipeline where OpenCV has GStreamer.

Every source is opened at the calibrated size of the camera file (``width_px`` x ``height_px``) and, where it has a
rate to set, at ``[companion] camera_fps``; what the device granted is read back (the first frame's own size, not
the driver's word).  A source that cannot give the calibrated size raises :class:`CameraSetupError` naming both
sizes: at start that is a fatal setup error of ``gsoe companion`` (one line, exit 2), never a flood of per-frame
rejections.  A video file is paced at its own frame rate and stamped with its own timestamps (file time from the
first frame, on the companion's clock), or read as fast as it decodes and stamped when read
(``video_pacing = "as_fast_as_possible"``); at its end the source is finished, not reopened.

``read()`` returns ``(t_us, frame)`` with ``t_us`` the exposure time on the companion's clock (the capture time less
``camera_latency_s`` for live sources), or None when the source stopped; :attr:`FrameSource.why` says why.
"""

from __future__ import annotations

import functools
import importlib.util
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

log = logging.getLogger(__name__)

SIM_SCHEME = "sim://"
PICAMERA_SCHEME = "picam://"  # picam://0: the Raspberry Pi camera number 0 through picamera2
STREAM_SCHEMES = ("rtsp://", "rtsps://", "http://", "https://")
GSTREAMER_MARK = "!"  # a GStreamer pipeline links its elements with '!'
# A video file's frames are paced by its own times; a source this much behind its schedule drops the wait
MAX_PACING_SLEEP_S = 1.0
# frames read from a device at open to let its automatic exposure and size settle before the size is judged
FIRST_FRAME_TRIES = 5


class CameraSetupError(OSError):
    """The source opened but cannot be used as calibrated (size) or cannot be opened at all as asked (no GStreamer,
    no picamera2): a setup error, not a transient loss."""


@functools.cache
def gstreamer_available() -> bool:
    """Whether the installed OpenCV was built with GStreamer (``cv2.getBuildInformation()``: ``GStreamer: YES``);
    the pip ``opencv-python-headless`` wheels are not."""
    for line in cv2.getBuildInformation().splitlines():
        if line.strip().startswith("GStreamer:"):
            return "YES" in line.split(":", 1)[1].upper()
    return False


def picamera2_available() -> bool:
    return importlib.util.find_spec("picamera2") is not None


def source_help() -> str:
    """The ``--camera`` help: only the kinds this installation can open."""
    kinds = ["a V4L2 device (0 or /dev/video0)", "a video file", "an RTSP/HTTP stream URL",
             "sim://HOST:PORT (the simulator's frame stream)"]
    if picamera2_available():
        kinds.insert(1, "picam://N (Raspberry Pi camera N through picamera2)")
    if gstreamer_available():
        kinds.append("a GStreamer pipeline ending in appsink")
    return "camera: " + ", ".join(kinds)


def kind_of(source: str) -> str:
    """``"sim"``, ``"picamera"``, ``"stream"``, ``"gstreamer"``, ``"device"`` or ``"file"``."""
    if source.startswith(SIM_SCHEME):
        return "sim"
    if source.startswith(PICAMERA_SCHEME):
        return "picamera"
    if source.startswith(STREAM_SCHEMES):
        return "stream"
    if GSTREAMER_MARK in source:
        return "gstreamer"
    if source.isdigit() or source.startswith("/dev/"):
        return "device"
    return "file"


def size_mismatch(source: str, got: tuple[int, int], want: tuple[int, int]) -> str:
    return (f"camera {source!r} gives {got[0]}x{got[1]} frames, the camera file is calibrated for {want[0]}x{want[1]}"
            f": set the source to {want[0]}x{want[1]} or calibrate it at its size (gsoe calibrate)")


def _frame_size(frame: Any) -> tuple[int, int] | None:
    if not isinstance(frame, np.ndarray) or frame.ndim < 2:
        return None
    return int(frame.shape[1]), int(frame.shape[0])


class FrameSource:
    """What :class:`nav.companion.CameraThread` reads from (besides the simulator's stream)."""

    finished = False  # a video file at its end: not to be reopened
    why = ""

    def read(self) -> tuple[int, Any] | None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class CaptureSource(FrameSource):
    """A ``cv2.VideoCapture`` device, stream or GStreamer pipeline, set to the calibrated size and ``fps`` (0: the
    device's rate) and checked on its first frame."""

    def __init__(self, source: str, size_px: tuple[int, int], fps: float, latency_s: float,
                 clock: Callable[[], int]) -> None:
        self.source, self.clock = source, clock
        self.latency_us = int(latency_s * 1e6)
        kind = kind_of(source)
        if kind == "gstreamer" and not gstreamer_available():
            raise CameraSetupError(f"camera {source!r} is a GStreamer pipeline, but this OpenCV has no GStreamer "
                                   "(cv2.getBuildInformation(): GStreamer NO)")
        if kind == "device":
            dev: int | str = int(source) if source.isdigit() else source
            node = f"/dev/video{dev}" if isinstance(dev, int) else dev
            if sys.platform.startswith("linux") and not os.path.exists(node):
                raise OSError(f"no device {node}")
            cap = cv2.VideoCapture(dev, cv2.CAP_V4L2 if sys.platform.startswith("linux") else cv2.CAP_ANY)
        elif kind == "gstreamer":
            cap = cv2.VideoCapture(source, cv2.CAP_GSTREAMER)
        else:
            cap = cv2.VideoCapture(source)
        if not cap.isOpened():
            cap.release()
            raise OSError(f"cv2.VideoCapture could not open {source!r}")
        self.cap = cap
        w, h = size_px
        if kind == "device":
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)
            if fps > 0:
                cap.set(cv2.CAP_PROP_FPS, fps)
        self._first: tuple[int, Any] | None = None
        for _ in range(FIRST_FRAME_TRIES):
            got = self._grab()
            if got is not None:
                self._first = got
                break
        if self._first is None:
            self.close()
            raise OSError(f"camera {source!r} opened but gave no frame")
        size = _frame_size(self._first[1])
        if size != (w, h):
            self.close()
            raise CameraSetupError(size_mismatch(source, size or (0, 0), (w, h)))
        granted = cap.get(cv2.CAP_PROP_FPS)
        if fps > 0 and granted > 0 and abs(granted - fps) > 0.5:
            log.warning("camera %s runs at %.1f fps (asked %.1f)", source, granted, fps)
        log.info("camera %s: %dx%d at %.1f fps", source, w, h, granted)

    def _grab(self) -> tuple[int, Any] | None:
        ok, frame = self.cap.read()
        got_us = self.clock()
        if not ok:
            return None
        return got_us - self.latency_us, frame

    def read(self) -> tuple[int, Any] | None:
        if self._first is not None:
            first, self._first = self._first, None
            return first
        got = self._grab()
        if got is None:
            self.why = "no frame from cv2.VideoCapture"
        return got

    def close(self) -> None:
        self.cap.release()


class VideoFileSource(FrameSource):
    """A video file, paced at its frame rate with its own timestamps (module docstring)."""

    def __init__(self, path: str, size_px: tuple[int, int], as_fast_as_possible: bool,
                 clock: Callable[[], int]) -> None:
        if not Path(path).is_file():
            raise OSError(f"no video file {path}")
        cap = cv2.VideoCapture(path)
        if not cap.isOpened():
            cap.release()
            raise CameraSetupError(f"camera {path!r}: cv2.VideoCapture cannot read this video file")
        self.cap, self.path, self.clock = cap, path, clock
        self.fast = as_fast_as_possible
        self.fps = float(cap.get(cv2.CAP_PROP_FPS))
        self.index = 0
        self._t0_us: int | None = None
        ok, frame = cap.read()
        size = _frame_size(frame) if ok else None
        if size is None:
            self.close()
            raise CameraSetupError(f"camera {path!r}: the video file holds no frame")
        if size != (size_px[0], size_px[1]):
            self.close()
            raise CameraSetupError(size_mismatch(path, size, size_px))
        self._pending: Any = frame
        self._pending_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
        log.info("video file %s: %dx%d at %.2f fps, %s", path, size[0], size[1], self.fps,
                 "as fast as it decodes" if self.fast else "paced at its own timestamps")

    def _file_time_us(self, pos_ms: float) -> int:
        """The frame's own time in the file: the container's stamp, or its index over the rate."""
        if self.index > 0 and pos_ms <= 0.0 and self.fps > 0:
            return int(round(self.index / self.fps * 1e6))
        return int(round(pos_ms * 1000.0))

    def read(self) -> tuple[int, Any] | None:
        if self._pending is None:
            ok, frame = self.cap.read()
            if not ok:
                self.finished = True
                self.why = "end of video file"
                return None
            self._pending, self._pending_ms = frame, float(self.cap.get(cv2.CAP_PROP_POS_MSEC))
        frame, self._pending = self._pending, None
        file_us = self._file_time_us(self._pending_ms)
        self.index += 1
        if self.fast:
            return self.clock(), frame
        if self._t0_us is None:
            self._t0_us = self.clock() - file_us
        due_us = self._t0_us + file_us
        wait_s = (due_us - self.clock()) / 1e6
        if wait_s > 0:
            time.sleep(min(wait_s, MAX_PACING_SLEEP_S))
        return due_us, frame

    def close(self) -> None:
        self.cap.release()


class PicameraSource(FrameSource):
    """A Raspberry Pi camera through picamera2 (libcamera): the calibrated size in its main stream (YUV420, the Y
    plane is the gray image), the frame duration from ``fps``, stamped by the sensor's timestamp where it reads on
    the companion's clock (else the capture time less the latency)."""

    def __init__(self, source: str, size_px: tuple[int, int], fps: float, latency_s: float,
                 clock: Callable[[], int]) -> None:
        if not picamera2_available():
            raise CameraSetupError(f"camera {source!r} needs picamera2, which is not installed (on Raspberry Pi OS: "
                                   "apt install python3-picamera2, and a venv made with --system-site-packages)")
        from picamera2 import Picamera2

        index_text = source[len(PICAMERA_SCHEME):] or "0"
        if not index_text.isdigit():
            raise CameraSetupError(f"camera {source!r}: expected picam://N with N the camera number")
        self.source, self.clock = source, clock
        self.latency_us = int(latency_s * 1e6)
        self.w, self.h = size_px
        try:
            self.cam = Picamera2(int(index_text))
        except (IndexError, RuntimeError) as e:
            raise OSError(f"picamera2 cannot open camera {index_text}: {e}") from None
        controls = {"FrameDurationLimits": (int(1e6 / fps), int(1e6 / fps))} if fps > 0 else {}
        config = self.cam.create_video_configuration(main={"size": (self.w, self.h), "format": "YUV420"},
                                                     controls=controls)
        self.cam.configure(config)
        granted = tuple(int(v) for v in config["main"]["size"])
        if granted != (self.w, self.h):
            self.cam.close()
            raise CameraSetupError(size_mismatch(source, (granted[0], granted[1]), (self.w, self.h)))
        self.cam.start()

    def read(self) -> tuple[int, Any] | None:
        try:
            request = self.cam.capture_request()
        except Exception as e:  # a camera that stops answering is a lost camera (the thread reopens it)
            self.why = f"picamera2: {e}"
            return None
        got_us = self.clock()
        try:
            yuv = request.make_array("main")
            meta = request.get_metadata()
        finally:
            request.release()
        gray = np.ascontiguousarray(yuv[: self.h, : self.w])
        t_us = got_us - self.latency_us
        sensor_ns = meta.get("SensorTimestamp") if isinstance(meta, dict) else None
        if sensor_ns:  # libcamera stamps on CLOCK_BOOTTIME; the companion's clock is CLOCK_MONOTONIC
            age_us = (time.clock_gettime_ns(time.CLOCK_BOOTTIME) - int(sensor_ns)) // 1000
            if 0 <= age_us < 1_000_000:
                t_us = got_us - age_us
        return t_us, gray

    def close(self) -> None:
        self.cam.stop()
        self.cam.close()


def open_source(source: str, size_px: tuple[int, int], fps: float, latency_s: float, as_fast_as_possible: bool,
                clock: Callable[[], int]) -> FrameSource:
    """Open any source but the simulator's stream (module docstring); ``OSError`` when it cannot be opened now,
    :class:`CameraSetupError` (an ``OSError`` too) when it can never be used as asked."""
    kind = kind_of(source)
    if kind == "picamera":
        return PicameraSource(source, size_px, fps, latency_s, clock)
    if kind == "file":
        return VideoFileSource(source, size_px, as_fast_as_possible, clock)
    return CaptureSource(source, size_px, fps, latency_s, clock)


def check_source_at_start(source: str, size_px: tuple[int, int], fps: float) -> None:
    """Open a source once and close it, so that a setup error (wrong size, no GStreamer, no picamera2, a file that
    is not a video) stops the companion at start; a source that is only absent now (a camera not yet plugged in,
    a stream not yet up) is left to the camera thread's retries."""
    if kind_of(source) == "sim":
        return
    try:
        src = open_source(source, size_px, fps, 0.0, True, time.monotonic_ns)
    except CameraSetupError:
        raise
    except OSError as e:
        log.warning("camera %s not available at start (%s): retrying in the loop", source, e)
        return
    src.close()
