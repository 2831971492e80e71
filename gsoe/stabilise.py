"""Attitude-stabilised cropping: the *virtual nadir camera* (paper 2.2-2.3, generalised to full attitude).

A pixel ``(u, v)`` of a stabilised image (frame ``s``, see :mod:`gsoe`) looks at the flat ground point
``right = (u - u0) * g``, ``forward = (v0 - v) * g`` metres from a reference ground point, in a level frame rotated
by the cycle's base heading; ``g`` is the ground sample distance and ``(u0, v0)`` the pixel of the reference.
For the base image the reference is the nadir point at the base snapshot; for a template it is the nadir point
at the current frame.  The ray to that ground point, in NED, is rotated into the body by the full attitude
``R_nb`` (roll, pitch *and* yaw relative to the base heading), into the camera by ``R_cb`` (the mount, any
rotation) and projected through the calibrated model (fisheye or pinhole, :class:`gsoe.camera.CameraModel`) into
the raw frame; ``cv2.remap`` samples just those pixels.  The raw frame is never undistorted as a whole.

The reference ground point may lie off the nadir by an offset (forward, right, in stabilised pixels of the
heading frame): ``stab.roi_centre = "view"`` centres the base image on the ground point the raw image's centre
looks at (:meth:`VirtualNadirCamera.view_offset_px`), which an oblique or narrow camera needs, since it never sees
the nadir.  Over flat ground an offset only moves the window: the image is the same orthographic map.

Cost: rays are projected only on a coarse grid (every ``map_grid_px`` pixels plus the last row/column) and the
sampling map is interpolated bilinearly between them with two small precomputed interpolation matrices
(``A_v @ grid @ A_u.T``).  Lens distortion is smooth on that scale (the test bounds the interpolation error).

The paper's own cropping point (eq. 2-3, roll and pitch only) is :func:`gsoe.equations.nadir_pixel_paper`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from gsoe import quat
from gsoe.camera import CameraModel
from gsoe.matching import to_intensity
from gsoe.quat import Quat
from gsoe.rotation import R_z

#: A view-centred base image (``stab.roi_centre = "view"``) needs the raw image's centre ray at least this far below
#: the horizon (20 deg: the ground point lies within 2.7 heights of the nadir, where flat ground is a fair model).
VIEW_MIN_DEPRESSION_RAD = math.radians(20.0)

def _interp_matrix(n_out: int, step: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Grid node positions (0, step, 2 step, ..., n_out - 1) and the (n_out x n_nodes) linear interpolation
    matrix from node values to every pixel."""
    nodes = np.arange(0, n_out - 1, step, dtype=float)
    nodes = np.append(nodes, float(n_out - 1)) if nodes.size == 0 or nodes[-1] != n_out - 1 else nodes
    A = np.zeros((n_out, nodes.size))
    x = np.arange(n_out, dtype=float)
    j = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, nodes.size - 2) if nodes.size > 1 else np.zeros(
        n_out, dtype=int)
    if nodes.size == 1:
        A[:, 0] = 1.0
        return nodes, A
    w = (x - nodes[j]) / (nodes[j + 1] - nodes[j])
    A[np.arange(n_out), j] = 1.0 - w
    A[np.arange(n_out), j + 1] = w
    return nodes, A


# A raw frame: the image itself, or a callable that returns it with at least the pixels of a region of interest
# ``(x0, y0, x1, y1)`` (end exclusive) filled in.  A simulator renders only what the estimator reads that way.
Frame = NDArray | Callable[[tuple[int, int, int, int]], NDArray]


@dataclass(frozen=True)
class Patch:
    """A stabilised image: intensity (float32) and whether every sample fell inside the raw frame."""

    image: NDArray[np.float32]
    valid: bool


#: A patch with at most this many (pixel, grid node) pairs is interpolated through one joint matrix (the template:
#: 361 x 16); larger ones (the base image: 8833 x 160) through the two separable ones.
_JOINT_INTERP_MAX = 20_000


class PatchSampler:
    """Samples one stabilised patch geometry (``width_px`` x ``height_px``, reference pixel ``ref_uv``)."""

    def __init__(self, camera: CameraModel, width_px: int, height_px: int, ref_uv: tuple[float, float],
                 grid_px: int) -> None:
        self.camera = camera
        self.width_px = width_px
        self.height_px = height_px
        self.ref_uv = ref_uv
        nodes_u, self._A_u = _interp_matrix(width_px, grid_px)
        nodes_v, self._A_v = _interp_matrix(height_px, grid_px)
        self._A_uT = np.ascontiguousarray(self._A_u.T)
        uu, vv = np.meshgrid(nodes_u, nodes_v)
        # ground offsets of the grid nodes in pixels: forward (x) and right (y) in the heading frame, one row a node
        self._nodes_fr = np.column_stack([(ref_uv[1] - vv).ravel(), (uu - ref_uv[0]).ravel()])
        self._grid_shape = uu.shape
        # the nodes' rays in the heading frame, (forward, right, 1 / scale) pixels: ground offset over height, up to
        # the length (which projection ignores), so that only the last column changes from frame to frame
        self._rays_h = np.column_stack([self._nodes_fr, np.ones(self._nodes_fr.shape[0])])
        # the grid's four corner nodes (row-major): every node's ray lies in their cone
        nu, nv = nodes_u.size, nodes_v.size
        self._corners = np.array(sorted({0, nu - 1, (nv - 1) * nu, nv * nu - 1}), dtype=np.intp)
        # pixel (row-major) from the nodes (row-major): A_v (x) A_u, for the small patches
        joint = width_px * height_px * self._nodes_fr.shape[0] <= _JOINT_INTERP_MAX
        self._A_joint = np.kron(self._A_v, self._A_u) if joint else None
        # the joint product's float32 2-channel map (x, y) per pixel, written in place each frame
        self._xy = np.empty((height_px, width_px, 2), np.float32) if joint else None
        self._xy_flat = self._xy.reshape(-1, 2) if self._xy is not None else None
        self._R_z: tuple[float, NDArray[np.float64]] = (math.nan, np.eye(3))    # the last heading's R_z

    def R_hc(self, R_cn: NDArray[np.float64], base_yaw_rad: float) -> NDArray[np.float64]:
        """Camera-to-heading-frame rotation (the heading frame: NED turned by ``base_yaw_rad``)."""
        if self._R_z[0] != base_yaw_rad:          # one heading per cycle
            self._R_z = (base_yaw_rad, R_z(base_yaw_rad))
        return (R_cn @ self._R_z[1]).T

    def _pixels(self, R_hc: NDArray[np.float64], scale: float,
                offset_fwd_right_px: tuple[float, float]) -> NDArray[np.float64] | None:
        """Raw-frame pixels (N, 2) of the grid nodes, or None when one leaves the frame or ``scale`` is not
        positive.  (A per-frame path of a few small arrays: every NumPy call costs about a microsecond, so they are
        few.)"""
        if not scale > 0.0:                    # (NaN too) no ground at that scale: nothing to sample
            return None
        if offset_fwd_right_px == (0.0, 0.0):
            rays_h = self._rays_h
        else:
            rays_h = np.empty_like(self._rays_h)
            np.add(self._nodes_fr, offset_fwd_right_px, out=rays_h[:, :2])
        rays_h[:, 2] = 1.0 / scale
        return self.camera.project_in_frame(rays_h @ R_hc, self._corners)

    def sample_map(self, R_cn: NDArray[np.float64], base_yaw_rad: float, scale: float,
                   offset_fwd_right_px: tuple[float, float] = (0.0, 0.0)
                   ) -> tuple[NDArray[np.float32], NDArray[np.float32], bool]:
        """Raw-frame sampling maps (map_x, map_y) for this patch.

        ``R_cn`` rotates NED into the camera frame at the exposure time; ``scale`` is ground pixels per unit
        height (``1 / focal_px`` times the height ratio base/current); ``offset_fwd_right_px`` shifts the
        reference ground point (in stabilised pixels).
        """
        return self.sample_map_h(self.R_hc(R_cn, base_yaw_rad), scale, offset_fwd_right_px)

    def sample_map_h(self, R_hc: NDArray[np.float64], scale: float,
                     offset_fwd_right_px: tuple[float, float] = (0.0, 0.0)
                     ) -> tuple[NDArray[np.float32], NDArray[np.float32], bool]:
        """:meth:`sample_map` from the camera-to-heading-frame rotation ``R_hc`` (:meth:`R_hc`)."""
        px = self._pixels(R_hc, scale, offset_fwd_right_px)
        if px is None:
            return np.empty((0, 0), np.float32), np.empty((0, 0), np.float32), False
        # both maps interpolated at once: (2, nodes_v, nodes_u) -> (2, height, width)
        maps = (self._A_v @ px.T.reshape(2, *self._grid_shape) @ self._A_uT).astype(np.float32)
        return maps[0], maps[1], True

    def sample(self, raw: Frame, R_cn: NDArray[np.float64], base_yaw_rad: float, scale: float,
               offset_fwd_right_px: tuple[float, float] = (0.0, 0.0)) -> Patch:
        return self.sample_h(raw, self.R_hc(R_cn, base_yaw_rad), scale, offset_fwd_right_px)

    def sample_h(self, raw: Frame, R_hc: NDArray[np.float64], scale: float,
                 offset_fwd_right_px: tuple[float, float] = (0.0, 0.0)) -> Patch:
        """:meth:`sample` from the camera-to-heading-frame rotation ``R_hc`` (:meth:`R_hc`)."""
        joint, xy = self._A_joint, self._xy
        map2: NDArray[np.float32] | None
        if joint is None or xy is None:
            map1, map2, ok = self.sample_map_h(R_hc, scale, offset_fwd_right_px)
        else:                         # one product, one 2-channel map (x, y) per pixel
            px = self._pixels(R_hc, scale, offset_fwd_right_px)
            ok = px is not None
            if px is not None:
                np.matmul(joint, px, out=self._xy_flat)
            map1, map2 = xy, None
        if not ok:
            return Patch(np.zeros((self.height_px, self.width_px), np.float32), False)
        if callable(raw):
            map_x, map_y = (map1, map2) if map2 is not None else (map1[:, :, 0], map1[:, :, 1])
            w, h = self.camera.size_px
            roi = (max(0, int(map_x.min()) - 1), max(0, int(map_y.min()) - 1),
                   min(w, int(map_x.max()) + 3), min(h, int(map_y.max()) + 3))
            raw = raw(roi)
        patch = cv2.remap(raw, map1, map2, interpolation=cv2.INTER_LINEAR,   # type: ignore[arg-type]
                          borderMode=cv2.BORDER_REPLICATE)
        return Patch(to_intensity(patch), True)


class VirtualNadirCamera:
    """Base-image and template samplers sharing one camera and one virtual focal length."""

    def __init__(self, camera: CameraModel, base_size_px: tuple[int, int], base_ref_uv: tuple[float, float],
                 template_px: int, focal_px: float, grid_px: int) -> None:
        self.camera = camera
        self.focal_px = focal_px if focal_px > 0 else camera.config.fx_px
        half = (template_px - 1) / 2.0
        self.base = PatchSampler(camera, base_size_px[0], base_size_px[1], base_ref_uv, grid_px)
        self.template = PatchSampler(camera, template_px, template_px, (half, half), grid_px)
        self._q_bc = quat.from_matrix(camera.R_bc)
        self._q_hn: tuple[float, Quat] = (math.nan, quat.IDENTITY)    # the last heading's NED-to-heading rotation

    def R_cn(self, R_nb: NDArray[np.float64]) -> NDArray[np.float64]:
        """NED-to-camera rotation for a body attitude ``R_nb`` (3x3)."""
        return self.camera.R_bc.T @ R_nb.T

    def R_hc(self, q_nb: Quat, base_yaw_rad: float) -> NDArray[np.float64]:
        """Camera-to-heading-frame rotation for a body attitude ``q_nb``: one product of quaternions, one matrix
        (the per-frame path)."""
        if self._q_hn[0] != base_yaw_rad:          # one heading per cycle
            self._q_hn = (base_yaw_rad, (math.cos(0.5 * base_yaw_rad), 0.0, 0.0, -math.sin(0.5 * base_yaw_rad)))
        return quat.to_matrix(quat.mul(quat.mul(self._q_hn[1], q_nb), self._q_bc))

    def sample_base(self, raw: Frame, R_nb: NDArray[np.float64], base_yaw_rad: float,
                    offset_fwd_right_px: tuple[float, float] = (0.0, 0.0)) -> Patch:
        """Base image around the nadir, or ``offset_fwd_right_px`` (stabilised px) away from it."""
        return self.base.sample(raw, self.R_cn(R_nb), base_yaw_rad, 1.0 / self.focal_px, offset_fwd_right_px)

    def sample_template(self, raw: Frame, q_nb: Quat, base_yaw_rad: float,
                        height_ratio: float, offset_fwd_right_px: tuple[float, float] = (0.0, 0.0)) -> Patch:
        """Template at the current nadir (body attitude ``q_nb``), or ``offset_fwd_right_px`` away from it (in the
        base image's pixels); ``height_ratio = h_base / h_now`` rescales it to the base image's GSD."""
        return self.template.sample_h(raw, self.R_hc(q_nb, base_yaw_rad), height_ratio / self.focal_px,
                                      offset_fwd_right_px)

    def template_fits(self, q_nb: Quat, base_yaw_rad: float, height_ratio: float,
                      offset_fwd_right_px: tuple[float, float]) -> bool:
        """Whether a template at ``offset_fwd_right_px`` from the nadir lies inside the raw frame at ``q_nb``."""
        return self.template.sample_map_h(self.R_hc(q_nb, base_yaw_rad), height_ratio / self.focal_px,
                                          offset_fwd_right_px)[2]

    def view_offset_px(self, R_nb: NDArray[np.float64], base_yaw_rad: float) -> tuple[float, float] | None:
        """Ground point of the raw image's centre, relative to the nadir, in stabilised pixels (forward, right of
        ``base_yaw_rad``) at this virtual focal length; None when that ray does not reach the ground at least
        ``VIEW_MIN_DEPRESSION_RAD`` below the horizon."""
        w, h = self.camera.size_px
        ray_c = self.camera.unproject(np.array([[(w - 1) / 2.0, (h - 1) / 2.0]]))[0]
        ray_h = R_z(base_yaw_rad).T @ (R_nb @ (self.camera.R_bc @ ray_c))
        if not ray_h[2] > math.sin(VIEW_MIN_DEPRESSION_RAD):
            return None
        return float(self.focal_px * ray_h[0] / ray_h[2]), float(self.focal_px * ray_h[1] / ray_h[2])
