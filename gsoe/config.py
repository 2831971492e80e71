"""Validated, frozen configuration of the optical estimator (``[camera]``, ``[stab]``, ``[match]``, ``[cycle]``,
``[integrity]`` in ``config/default.toml``), built by :func:`common.config.build`.

Degrees appear here (``*_deg``) because configuration is an edge; code reads the ``*_rad`` properties.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from common.config import In, Validated, in_range, require

# --------------------------------------------------------------------------------------------------------------
# Optical estimator configuration

# Ranges that several fields share (one meaning, one declaration)
_ImageSidePx = Annotated[int, In(16, 16384)]
_FocalPx = Annotated[float, In(1.0, 1e5)]
_FovDeg = Annotated[float, In(1.0, 360.0)]
_PatchSidePx = Annotated[int, In(9, 2001, odd=True)]
_TiltLimitDeg = Annotated[float, In(0.0, 89.0)]
# a margin around a position on the base image or the SSD surface
_MarginPx = Annotated[int, In(0, 50)]
# a difference of two per-frame template steps
_StepChangePx = Annotated[float, In(0.0, 100.0)]


@dataclass(frozen=True)
class CameraConfig(Validated):
    """A calibrated camera (the *camera file*, see ``config/camera/*.toml``).

    ``model`` is ``"fisheye"`` (OpenCV ``cv2.fisheye``, Kannala-Brandt, ``dist = [k1, k2, k3, k4]``) or
    ``"pinhole"`` (OpenCV radial-tangential, ``dist = [k1, k2, p1, p2, k3]``).  ``mount_rpy_deg`` is the camera's
    mounting rotation in the body frame on top of the nominal belly mounting (see :mod:`gsoe`): roll, pitch, yaw of
    the 3-2-1 sequence, any rotation (a small misalignment, or an oblique or turned camera; pitch within +-90 deg).
    ``hfov_deg``/``vfov_deg`` are the nominal fields of view the paper's eq. 2-3 and 10-11 use.
    """

    model: Literal["fisheye", "pinhole"]
    width_px: _ImageSidePx
    height_px: _ImageSidePx
    fx_px: _FocalPx
    fy_px: _FocalPx
    cx_px: float
    cy_px: float
    dist: Annotated[tuple[float, ...], In(-10.0, 10.0)]
    hfov_deg: _FovDeg
    vfov_deg: _FovDeg
    mount_rpy_deg: Annotated[tuple[float, float, float], In(-180.0, 180.0)] = (0.0, 0.0, 0.0)
    rms_px: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        in_range(self.cx_px, 0.0, self.width_px, "cx_px")
        in_range(self.cy_px, 0.0, self.height_px, "cy_px")
        need = 4 if self.model == "fisheye" else 5
        require(len(self.dist) == need, "dist", f"{self.model} model needs {need} coefficients, got {len(self.dist)}")
        in_range(self.mount_rpy_deg[1], -90.0, 90.0, "mount_rpy_deg[1]")


@dataclass(frozen=True)
class StabConfig(Validated):
    """Virtual nadir camera: base image and template geometry in the stabilised frame ``s``.

    ``base_cross_px`` x ``base_along_px`` is the base image (the paper: 121 across x 73 along).  ``template_start``
    is where the template starts on the base image: ``"centre"`` (the paper) or ``"trailing"`` (near the trailing
    edge, so it can travel the whole base image).  ``focal_px`` is the virtual camera's focal length (0: the raw
    camera's ``fx_px``), which sets ``gsd_m_px = height_agl_m / focal_px``.  ``map_grid_px`` is the spacing of the
    coarse grid of projected rays from which the sampling map is interpolated.  ``use_gyro``: compose the template's
    attitude from the base attitude and the gyro-integrated rotation since the base snapshot; ``gyro_bias_tau_s``:
    time constant of the gyro-bias complementary filter (0: off).

    ``roi_centre``: where on the ground the base image lies.  ``"nadir"`` (the paper): around the point under the
    aircraft, the template at the current nadir, so it migrates across the base.  ``"view"``: around the ground
    point the raw image's centre looks at (an oblique or narrow camera that never sees the nadir); each template
    is cut where the base's centre is predicted to lie in the current frame, so it lands near the base's centre
    and the base only has to cover the prediction's error (see :mod:`gsoe.cycle`).  Both report the nadir's
    migration.
    """

    base_cross_px: _PatchSidePx = 121
    base_along_px: _PatchSidePx = 73
    template_px: Annotated[int, In(3, 201, odd=True)] = 19
    template_start: Literal["centre", "trailing"] = "centre"
    focal_px: Annotated[float, In(0.0, 1e5)] = 0.0
    map_grid_px: Annotated[int, In(1, 256)] = 8
    roll_limit_deg: _TiltLimitDeg = 45.0
    pitch_limit_deg: _TiltLimitDeg = 20.0
    use_gyro: bool = True
    gyro_bias_tau_s: Annotated[float, In(0.0, 3600.0)] = 20.0
    scale_template_to_base: bool = True
    roi_centre: Literal["nadir", "view"] = "nadir"

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.template_px + 4 <= min(self.base_cross_px, self.base_along_px), "template_px",
                "must be at least 4 px smaller than both base image sides")


@dataclass(frozen=True)
class MatchConfig(Validated):
    """Template matching (paper 2.4) and its quality gates.

    ``method``: ``"window"`` searches the positions the cycle's step gate can accept around the predicted position
    (``cycle.step_gate_px``, rounded up) and ``window_margin_px`` more either side (the peak's neighbourhood and
    sidelobe), and widens to the whole base image on a miss (the minimum in that margin, a low or ambiguous peak)
    or when there is no prediction (a cycle without a step to predict from, or the gate off); ``"exhaustive"``
    always searches the
    whole base image; ``"three_step"`` and ``"diamond"`` are the classic block-matching searches
    (:mod:`gsoe.matching`).  ``psr_min``: peak-to-sidelobe ratio of the SSD surface below which a match is invalid;
    ``texture_std_min``: minimum intensity standard deviation (0-255 scale) of the template;
    ``sidelobe_exclude_px``: half-width of the window around the peak excluded from the sidelobe statistics.
    """

    method: Literal["window", "exhaustive", "three_step", "diamond"] = "window"
    subpixel: bool = True
    psr_min: Annotated[float, In(0.0, 1e3)] = 3.0
    texture_std_min: Annotated[float, In(0.0, 255.0)] = 4.0
    sidelobe_exclude_px: _MarginPx = 2
    window_margin_px: Annotated[int, In(1, 100)] = 4


@dataclass(frozen=True)
class CycleConfig(Validated):
    """TM cycle (paper 2.4-2.5): sample rate and the conditions that start a new cycle.

    A new cycle starts when the template comes within ``edge_margin_px`` of the base image edge (the critical
    position), after ``max_cycle_s``, or when the data filter of eq. 6 fires: both components of the per-frame
    template step change by at least ``data_filter_zeta_px`` (``data_filter`` on).  Eq. 6 needs *both* components
    to jump, so a false match displaced along track only passes it; ``step_gate_px`` (0: off) also rejects a step
    whose vector differs from the previous one by more than that (Euclidean).  The previous step is carried into
    the next cycle (rotated to its base heading), so the first match of a cycle is checked too.  Physically the
    per-frame step changes by ``a dt^2 / gsd``: under 0.1 px for a 1 g turn at 50 m and 30 Hz.

    Featureless ground (water, even grass, snow): a base image whose intensity standard deviation is below
    ``match.texture_std_min`` starts no cycle (every template of the cycle shows ground inside it, so would be
    invalid for the same reason), and no new base is tried for ``featureless_retry_s`` (0: every frame): the
    ground moves a small fraction of the base's footprint meanwhile, and a companion computer over the sea stops
    sampling and matching every frame for nothing.

    ``step_prediction``: how the previous step predicts the next one (the template's expected position, the data
    filter and the step gate).  ``"per_frame"``: the same step again (a camera at a steady rate); ``"per_second"``:
    the same velocity, so the step scales with the time since the previous frame (irregular frame intervals, a
    low-rate sequence with dropped frames).  The gates then compare the step with that prediction.
    """

    rate_hz: Annotated[float, In(1.0, 240.0)] = 30.0
    edge_margin_px: _MarginPx = 1
    max_cycle_s: Annotated[float, In(0.05, 60.0)] = 3.0
    data_filter: bool = True
    data_filter_zeta_px: _StepChangePx = 4.0
    step_gate_px: _StepChangePx = 2.0
    featureless_retry_s: Annotated[float, In(0.0, 10.0)] = 0.1
    step_prediction: Literal["per_frame", "per_second"] = "per_frame"


@dataclass(frozen=True)
class IntegrityConfig(Validated):
    """The paper's heuristic data-integrity filter (2.7), kept as the baseline the EKF replaces.

    A cycle's drift is released when it agrees within ``max_jump_deg`` with the median of the last
    ``history_cycles`` released cycles and the cycle had at least ``min_steps`` valid matches.
    """

    history_cycles: Annotated[int, In(1, 100)] = 5
    max_jump_deg: Annotated[float, In(0.0, 180.0)] = 5.0
    min_steps: Annotated[int, In(1, 1000)] = 3
    min_travel_px: Annotated[float, In(0.0, 1000.0)] = 4.0


@dataclass(frozen=True)
class GsoeConfig(Validated):
    """Everything the optical estimator needs (``config/default.toml`` sections ``[stab]``, ``[match]``, ...)."""

    camera: CameraConfig
    stab: StabConfig = field(default_factory=StabConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    cycle: CycleConfig = field(default_factory=CycleConfig)
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)
