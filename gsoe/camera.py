"""Calibrated camera model (paper 2.1): intrinsics, distortion and the mounting rotation in the body frame.

Projection and unprojection go through OpenCV (``cv2.fisheye`` for the Kannala-Brandt fisheye model,
``cv2.projectPoints``/``cv2.undistortPoints`` for the pinhole radial-tangential model); this class only keeps the
parameters together and handles the rays OpenCV cannot (behind the camera, beyond the lens' field).
Frames as in :mod:`gsoe`: rays are in the raw camera frame ``c``; ``R_bc`` rotates them into the body frame.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from gsoe.config import CameraConfig
from gsoe.rotation import R_bc_from_mount

_ZERO3 = np.zeros(3)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
# Rays whose angle off the optical axis exceeds the widest image corner by this factor are treated as outside
# the lens' field (the Kannala-Brandt polynomial is only trustworthy over the calibrated field).
_FIELD_MARGIN = 1.05


@dataclass(frozen=True)
class CameraModel:
    """A calibrated camera. Build it with :meth:`from_config`."""

    config: CameraConfig
    K: NDArray[np.float64]
    D: NDArray[np.float64]
    R_bc: NDArray[np.float64]
    max_off_axis_rad: float

    @classmethod
    def from_config(cls, config: CameraConfig) -> CameraModel:
        K = np.array([[config.fx_px, 0.0, config.cx_px], [0.0, config.fy_px, config.cy_px], [0.0, 0.0, 1.0]])
        D = np.asarray(config.dist, dtype=np.float64)
        R_bc = R_bc_from_mount(*np.deg2rad(config.mount_rpy_deg))
        tmp = cls(config=config, K=K, D=D, R_bc=R_bc, max_off_axis_rad=np.pi / 2)
        corners = np.array(
            [[0.0, 0.0], [config.width_px, 0.0], [0.0, config.height_px], [config.width_px, config.height_px]]
        )
        rays = tmp.unproject(corners)
        max_angle = float(np.max(np.arccos(np.clip(rays[:, 2], -1.0, 1.0))))
        limit = min(max_angle * _FIELD_MARGIN, np.deg2rad(89.5) if config.model == "pinhole" else np.pi * 0.95)
        return cls(config=config, K=K, D=D, R_bc=R_bc, max_off_axis_rad=float(limit))

    @property
    def model(self) -> str:
        return self.config.model

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height)."""
        return self.config.width_px, self.config.height_px

    @property
    def focal_px(self) -> float:
        """Mean focal length at the image centre."""
        return 0.5 * (self.config.fx_px + self.config.fy_px)

    def project(self, rays_c: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Project rays or points in the camera frame, shape (N, 3), to pixels (N, 2).

        Returns ``(pixels, valid)``; ``valid`` is false for rays behind the camera, beyond the lens' field or
        landing outside the image.  Invalid pixels are set to -1.
        """
        pts = np.ascontiguousarray(rays_c, dtype=np.float64).reshape(-1, 3)
        norm = np.linalg.norm(pts, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            off_axis = np.arccos(np.clip(pts[:, 2] / norm, -1.0, 1.0))
        ok = (norm > 0) & (pts[:, 2] > 0) & (off_axis <= self.max_off_axis_rad)
        px = np.full((pts.shape[0], 2), -1.0)
        if np.any(ok):
            obj = pts[ok].reshape(-1, 1, 3)
            if self.model == "fisheye":
                img, _ = cv2.fisheye.projectPoints(obj, _ZERO3, _ZERO3, self.K, self.D)
            else:
                img, _ = cv2.projectPoints(obj, _ZERO3, _ZERO3, self.K, self.D)
            px[ok] = img.reshape(-1, 2)
        w, h = self.size_px
        inside = ok & (px[:, 0] >= -0.5) & (px[:, 0] <= w - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= h - 0.5)
        px[~inside] = -1.0
        return px, inside

    def project_in_frame(self, rays_c: NDArray[np.float64],
                         corners: NDArray[np.intp] | None = None) -> NDArray[np.float64] | None:
        """Lean :meth:`project` for the per-frame path: pixels (N, 2) if every ray lands inside the image, else None.

        ``corners``: the indices of the rays whose cone holds all of them (a grid of rays through a plane: its four
        corners).  The lens' field is a convex cone while it is at most a half-space, so only those rays need the
        field test then.  (Every NumPy call here costs about a microsecond on the template's 16 rays: they are
        counted.)"""
        c = self._cos_max_off_axis
        if corners is not None and c >= 0.0:
            for x, y, z in rays_c[corners].tolist():
                if not z > c * math.sqrt(x * x + y * y + z * z):
                    return None
        elif not (rays_c[:, 2] > c * np.sqrt(np.einsum("ij,ij->i", rays_c, rays_c))).all():
            return None
        if self.config.model == "fisheye":
            # the lens applied to the normalised coordinates: projectPoints' pixels to rounding, without its pose
            # and its Jacobians (half the cost); OpenCV's division by z wants z > 0, which a field narrower than a
            # half-space has just ensured
            norm = (cv2.convertPointsFromHomogeneous(rays_c) if c > 0.0
                    else (rays_c[:, :2] / rays_c[:, 2:]).reshape(-1, 1, 2))
            img = cv2.fisheye.distortPoints(norm, self.K, self.D)
        else:
            img, _ = cv2.projectPoints(rays_c.reshape(-1, 1, 3), _ZERO3, _ZERO3, self.K, self.D)
        px = cast("NDArray[np.float64]", img.reshape(-1, 2))    # (a string: no runtime subscript per call)
        xs, ys = px.T.tolist()     # (Python's min and max of 16 floats: a third of NumPy's reductions' cost)
        w, h = self._frame_limits
        if min(xs) < -0.5 or min(ys) < -0.5 or max(xs) > w or max(ys) > h:
            return None
        return px

    @functools.cached_property
    def _cos_max_off_axis(self) -> float:
        return float(np.cos(self.max_off_axis_rad))

    @functools.cached_property
    def _frame_limits(self) -> tuple[float, float]:
        """The largest pixel coordinates (x, y) inside the image (pixel centres at integers)."""
        return self.config.width_px - 0.5, self.config.height_px - 0.5

    def unproject(self, pixels: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unit rays in the camera frame, shape (N, 3), for pixel coordinates (N, 2)."""
        pts = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if self.model == "fisheye":
            norm = cv2.fisheye.undistortPoints(pts, self.K, self.D, criteria=_UNDISTORT_CRITERIA)
        else:
            norm = cv2.undistortPoints(pts, self.K, self.D, criteria=_UNDISTORT_CRITERIA)
        xy = norm.reshape(-1, 2)
        rays = np.column_stack([xy, np.ones(len(xy))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def forward_camera(camera: CameraModel, depression_rad: float) -> CameraModel:
    """The same lens mounted looking forward, its optical axis ``depression_rad`` below the body x axis (the
    tracking camera of the video-tracking guidance and of the simulator's tracker hook).

    Camera axes in the body frame: x_c = right wing, z_c = forward tilted down, y_c = z_c x x_c (image down).
    """
    cd, sd = math.cos(depression_rad), math.sin(depression_rad)
    z_c = np.array([cd, 0.0, sd])
    x_c = np.array([0.0, 1.0, 0.0])
    y_c = np.cross(z_c, x_c)
    R_bc = np.column_stack([x_c, y_c, z_c])
    return replace(camera, R_bc=R_bc)
