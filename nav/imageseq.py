"""Real image sequences with per-frame attitude and height, for ``gsoe replay-frames`` (:mod:`nav.replay_frames`).

An :class:`ImageSequence` is a list of frames, each with its exposure time ``t_us`` (one clock, microseconds since
the first frame), the image file, the aircraft's attitude at the exposure (3-2-1 Euler, body FRD to NED, as
:class:`common.samples.AttitudeSample`), the height above the ground under the aircraft and, where the source has
one, a reference ground velocity (NED, m/s; nan where absent).  The camera is a
:class:`gsoe.config.CameraConfig`: the sequence's own (CLIF's bundle-adjusted intrinsics and mount) or the camera
file the caller gives.

Readers
    :func:`read_csv_sequence`  a generic CSV (columns below), images named relative to the CSV's folder;
    :func:`read_clif2007`      the CLIF 2007 sample (``jpg/``, ``pos/``, ``krtd/``; see ``../shared/data/SOURCES.md``).

Generic CSV (one header line; one row per frame, in time order; ``#`` starts a comment line)
    ``t_us``                          exposure time, integer microseconds (any origin; the reader subtracts the first)
    ``image``                         image file, relative to the CSV's folder
    ``roll_deg, pitch_deg, yaw_deg``  body attitude (3-2-1 Euler, FRD to NED; yaw clockwise from north), or
    ``qw_nc, qx_nc, qy_nc, qz_nc``    the camera's orientation instead: the rotation from the camera frame ``c``
                                      (OpenCV: x right, y down, z along the optical axis) to NED, Hamilton, scalar
                                      first; the body attitude is then ``R_nb = R_nc R_bc^T`` with the camera file's
                                      mount (so the estimator sees exactly ``R_nc`` whatever the mount)
    ``height_agl_m``                  height above the ground under the aircraft, m
    ``vn_m_s, ve_m_s, vd_m_s``        optional reference ground velocity, NED (``vd_m_s`` may be left out)
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from common.samples import AttitudeSample
from gsoe.config import CameraConfig
from gsoe.rotation import R_BC_NOMINAL, R_nb_from_euler, euler_from_R_nb

US_PER_S = 1_000_000
FT_TO_M = 0.3048  #: international foot
#: R_ne for a local east-north-up frame: NED = T @ ENU.
R_NED_ENU: NDArray[np.float64] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# WGS-84 (for the CLIF track's local frame)
_WGS84_A_M = 6378137.0
_WGS84_E2 = 6.69437999014e-3

#: CLIF 2007: the ground under the orbit (Ohio State University, Columbus) lies at about 230-250 m above mean sea
#: level (``../shared/data/SOURCES.md``); 10 m of error is 0.4 % of the 2570 m height, so of the ground speed.
CLIF_GROUND_MSL_M = 240.0
#: ORB features per frame and the RANSAC homography threshold (px) of the tie points that locate the ground in the
#: bundle adjustment's frame (:func:`ground_level_from_cameras`).
TIE_POINT_FEATURES = 1500
TIE_POINT_RANSAC_PX = 3.0


class SequenceError(ValueError):
    """The sequence cannot be read (missing columns, files, bad values); the message says which."""


@dataclass(frozen=True, slots=True)
class SequenceFrame:
    """One frame: exposure time, image file, body attitude, height above ground, reference velocity (or nan)."""

    t_us: int
    image: Path
    attitude: AttitudeSample
    height_agl_m: float
    ref_vel_ned_m_s: NDArray[np.float64]


@dataclass(frozen=True)
class ImageSequence:
    """A real image sequence (module docstring).  ``camera`` None: the caller's camera file applies."""

    name: str
    frames: tuple[SequenceFrame, ...]
    camera: CameraConfig | None = None
    notes: tuple[str, ...] = ()
    info: dict[str, float] = field(default_factory=dict)

    @property
    def has_reference(self) -> bool:
        return any(np.all(np.isfinite(f.ref_vel_ned_m_s[:2])) for f in self.frames)


# --------------------------------------------------------------------------------------------------------------
# Camera mount helpers


def mount_rpy_deg_from_R_bc(R_bc: NDArray[np.float64]) -> tuple[float, float, float]:
    """The camera file's ``mount_rpy_deg`` for a camera-to-body rotation (the inverse of
    :func:`gsoe.rotation.R_bc_from_mount`): roll, pitch, yaw of ``R_bc R_BC_NOMINAL^T``."""
    roll, pitch, yaw = euler_from_R_nb(R_bc @ R_BC_NOMINAL.T)
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


def attitude_from_camera(t_us: int, R_nc: NDArray[np.float64], R_bc: NDArray[np.float64]) -> AttitudeSample:
    """The body attitude that puts the camera (mount ``R_bc``) at orientation ``R_nc``."""
    roll, pitch, yaw = euler_from_R_nb(R_nc @ R_bc.T)
    return AttitudeSample(t_us=t_us, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw)


# --------------------------------------------------------------------------------------------------------------
# Generic CSV

_EULER = ("roll_deg", "pitch_deg", "yaw_deg")
_QUAT = ("qw_nc", "qx_nc", "qy_nc", "qz_nc")
_VEL = ("vn_m_s", "ve_m_s", "vd_m_s")


def read_csv_sequence(path: str | Path, camera: CameraConfig) -> ImageSequence:
    """Read the generic CSV (module docstring); ``camera`` gives the mount a camera quaternion is converted with."""
    p = Path(path)
    lines = [ln for ln in p.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    rows = list(csv.DictReader(lines))
    if not rows:
        raise SequenceError(f"{p}: no frames")
    cols = set(rows[0])
    missing = [c for c in ("t_us", "image", "height_agl_m") if c not in cols]
    if missing:
        raise SequenceError(f"{p}: missing column(s) {', '.join(missing)}")
    euler = all(c in cols for c in _EULER)
    if not euler and not all(c in cols for c in _QUAT):
        raise SequenceError(f"{p}: needs the attitude as {', '.join(_EULER)} or the camera quaternion "
                            f"{', '.join(_QUAT)}")
    R_bc = _camera_R_bc(camera)
    frames: list[SequenceFrame] = []
    t0: int | None = None
    for k, row in enumerate(rows, start=2):
        try:
            t_raw = int(row["t_us"])
            height = float(row["height_agl_m"])
            t0 = t_raw if t0 is None else t0
            t_us = t_raw - t0
            if euler:
                r, pch, y = (math.radians(float(row[c])) for c in _EULER)
                att = AttitudeSample(t_us=t_us, roll_rad=r, pitch_rad=pch, yaw_rad=y)
            else:
                q = np.array([float(row[c]) for c in _QUAT])
                R_nc = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()
                att = attitude_from_camera(t_us, R_nc, R_bc)
            vel = np.array([float(row[c]) if row.get(c, "") not in ("", None) else math.nan for c in _VEL])
        except (TypeError, ValueError) as e:
            raise SequenceError(f"{p}: line {k}: {e}") from None
        if frames and t_us <= frames[-1].t_us:
            raise SequenceError(f"{p}: line {k}: t_us not increasing")
        frames.append(SequenceFrame(t_us=t_us, image=p.parent / row["image"], attitude=att, height_agl_m=height,
                                    ref_vel_ned_m_s=vel))
    return ImageSequence(name=p.stem, frames=tuple(frames))


def _camera_R_bc(camera: CameraConfig) -> NDArray[np.float64]:
    from gsoe.rotation import R_bc_from_mount

    return R_bc_from_mount(*np.deg2rad(camera.mount_rpy_deg))


# --------------------------------------------------------------------------------------------------------------
# CLIF 2007


@dataclass(frozen=True)
class _Krtd:
    K: NDArray[np.float64]
    R_cw: NDArray[np.float64]          # world (the bundle adjustment's local frame, z up) to camera
    centre_w_m: NDArray[np.float64]


def _read_krtd(path: Path) -> _Krtd:
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    try:
        K = np.array(rows[0:3], dtype=float)
        R = np.array(rows[3:6], dtype=float)
        t = np.array(rows[6], dtype=float)
    except (ValueError, IndexError) as e:
        raise SequenceError(f"{path}: not a krtd camera ({e})") from None
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise SequenceError(f"{path}: not a krtd camera (K, R 3x3, t 3)")
    dist = [float(v) for row in rows[7:] for v in row]
    if any(d != 0.0 for d in dist):
        raise SequenceError(f"{path}: non-zero distortion is not read")
    return _Krtd(K=K, R_cw=R, centre_w_m=-R.T @ t)


def _local_en_m(lat_deg: NDArray[np.float64], lon_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """Flat-earth east, north (m) about the track's mean latitude and longitude."""
    lat0, lon0 = math.radians(float(np.mean(lat_deg))), math.radians(float(np.mean(lon_deg)))
    s2 = math.sin(lat0) ** 2
    r_n = _WGS84_A_M / math.sqrt(1 - _WGS84_E2 * s2)
    r_m = r_n * (1 - _WGS84_E2) / (1 - _WGS84_E2 * s2)
    north = (np.radians(lat_deg) - lat0) * r_m
    east = (np.radians(lon_deg) - lon0) * r_n * math.cos(lat0)
    return np.column_stack([east, north])


def _horizontal_rotation_rad(src_xy: NDArray[np.float64], dst_xy: NDArray[np.float64]) -> float:
    """Angle of the 2-D rotation (counter-clockwise, x towards y) that best maps ``src`` onto ``dst`` after removing
    means and scale (Procrustes)."""
    a = src_xy - src_xy.mean(axis=0)
    b = dst_xy - dst_xy.mean(axis=0)
    return math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a[:, 0] * b[:, 0]
                                                                                         + a[:, 1] * b[:, 1])))


def read_clif2007(folder: str | Path, ground_level_m: float | None = None) -> ImageSequence:
    """The CLIF 2007 sample: frames ``jpg/*.jpg``, INS records ``pos/*.txt``, bundle-adjusted cameras ``krtd/``.

    POS record (one CSV line): heading, pitch, roll (deg; read as the 3-2-1 Euler attitude of the INS frame, FRD,
    which makes the bundle-adjusted cameras agree with one fixed mount within a median 1.1 deg, against 12 deg with
    the roll's sign flipped), latitude, longitude (deg), altitude (ft, said to be above mean sea level), GPS seconds
    of the week, GPS week, velocity north, east, up (m/s), three flags.  ``t_us`` is the GPS time since the first frame;
    the reference velocity is the INS velocity.

    Height above ground: the INS altitude minus the ground's level on the same datum, ``ground_level_m``, or, when
    None, the level the bundle adjustment puts the ground at (:func:`ground_level_from_cameras`: the median height
    of tie points triangulated between consecutive bundle-adjusted cameras, whose centres lie at the INS
    altitude).  It comes out at about 105 m, not the 230-250 m of the map (SOURCES.md): the altitude's datum is not
    mean sea level, or the cameras' altitude is not the aircraft's.  The difference (2705 against 2570 m) is 5 % of
    the height, so of every optical speed; :data:`CLIF_GROUND_MSL_M` gives the map's value.

    Camera: the krtd files' intrinsics (their mean; no distortion), and their mount: each gives ``R_bc = R_nb^T
    R_nc`` with ``R_nc`` from the krtd rotation, whose local frame (x, y, z up) is turned about the vertical to
    NED by the angle that maps the INS track's east/north onto the cameras' centres (1.3 deg here: the UTM grid
    convergence at Columbus); the mount is the chordal mean of those rotations.  ``info`` holds the spread.
    """
    root = Path(folder)
    jpgs = sorted((root / "jpg").glob("*.jpg"))
    if not jpgs:
        raise SequenceError(f"{root}: no jpg/*.jpg frames")
    recs = []
    for j in jpgs:
        pos = root / "pos" / (j.stem + ".txt")
        try:
            vals = [float(v) for v in pos.read_text().strip().split(",")]
        except FileNotFoundError:
            raise SequenceError(f"{pos}: missing POS record") from None
        except ValueError as e:
            raise SequenceError(f"{pos}: {e}") from None
        if len(vals) < 11:
            raise SequenceError(f"{pos}: expected at least 11 fields, got {len(vals)}")
        recs.append(vals)
    P = np.array([r[:11] for r in recs])
    t_s = P[:, 6] + 604800.0 * (P[:, 7] - P[0, 7])
    t_us = np.round((t_s - t_s[0]) * US_PER_S).astype(np.int64)
    if np.any(np.diff(t_us) <= 0):
        raise SequenceError(f"{root}: POS times not increasing")
    atts = [AttitudeSample(t_us=int(t), roll_rad=math.radians(r[2]), pitch_rad=math.radians(r[1]),
                           yaw_rad=math.radians(r[0])) for t, r in zip(t_us, P, strict=True)]
    vel = np.column_stack([P[:, 8], P[:, 9], -P[:, 10]])
    camera, info, cams = _clif_camera(root, jpgs, P, atts)
    if ground_level_m is None:
        ground_level_m, n_points = ground_level_from_cameras([c for _, c in cams], [jpgs[k] for k, _ in cams])
        how = f"the bundle adjustment's ground ({n_points} tie points)"
    else:
        how = "given"
    heights = P[:, 5] * FT_TO_M - ground_level_m
    frames = tuple(SequenceFrame(t_us=int(t_us[k]), image=jpgs[k], attitude=atts[k], height_agl_m=float(heights[k]),
                                 ref_vel_ned_m_s=vel[k]) for k in range(len(jpgs)))
    info["ground_level_m"] = ground_level_m
    info["height_agl_median_m"] = float(np.median(heights))
    notes = (f"height above ground = INS altitude - {ground_level_m:.1f} m ({how}); median "
             f"{np.median(heights):.0f} m",
             f"camera mount from {int(info['krtd_cameras'])} bundle-adjusted cameras: spread about the mean "
             f"{info['mount_spread_median_deg']:.2f} deg median, {info['mount_spread_max_deg']:.2f} deg max")
    return ImageSequence(name="clif2007", frames=frames, camera=camera, notes=notes, info=info)


def _clif_camera(root: Path, jpgs: Sequence[Path], P: NDArray[np.float64], atts: Sequence[AttitudeSample]
                 ) -> tuple[CameraConfig, dict[str, float], list[tuple[int, _Krtd]]]:
    index = {j.stem: k for k, j in enumerate(jpgs)}
    cams: list[tuple[int, _Krtd]] = []
    for f in sorted((root / "krtd").glob("*.krtd")):
        if f.stem in index:
            cams.append((index[f.stem], _read_krtd(f)))
    if len(cams) < 2:
        raise SequenceError(f"{root}: needs at least two krtd cameras of the frames (camera and mount)")
    ks = [k for k, _ in cams]
    en = _local_en_m(P[ks, 3], P[ks, 4])
    centres = np.array([c.centre_w_m[:2] for _, c in cams])
    turn = _horizontal_rotation_rad(en, centres)          # local frame's xy = R(turn) @ east/north
    c_t, s_t = math.cos(turn), math.sin(turn)
    R_enu_w = np.array([[c_t, s_t, 0.0], [-s_t, c_t, 0.0], [0.0, 0.0, 1.0]])
    mounts = []
    for k, c in cams:
        a = atts[k]
        R_nc = R_NED_ENU @ R_enu_w @ c.R_cw.T
        mounts.append(R_nb_from_euler(a.roll_rad, a.pitch_rad, a.yaw_rad).T @ R_nc)
    rot = Rotation.from_matrix(np.array(mounts))
    mean = rot.mean()
    spread = np.degrees((mean.inv() * rot).magnitude())
    K = np.mean([c.K for _, c in cams], axis=0)
    h, w = (int(v) for v in _image_size(jpgs[0]))
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    camera = CameraConfig(model="pinhole", width_px=w, height_px=h, fx_px=fx, fy_px=fy, cx_px=cx, cy_px=cy,
                          dist=(0.0, 0.0, 0.0, 0.0, 0.0), hfov_deg=math.degrees(2 * math.atan(w / (2 * fx))),
                          vfov_deg=math.degrees(2 * math.atan(h / (2 * fy))),
                          mount_rpy_deg=mount_rpy_deg_from_R_bc(mean.as_matrix()))
    info = {"krtd_cameras": float(len(cams)), "krtd_frame_turn_deg": math.degrees(turn),
            "mount_spread_median_deg": float(np.median(spread)), "mount_spread_max_deg": float(spread.max())}
    return camera, info, cams


def ground_level_from_cameras(cams: Sequence[_Krtd], images: Sequence[Path]) -> tuple[float, int]:
    """The ground's level (m, the cameras' vertical datum) and the number of tie points it comes from: the median
    height of the points triangulated (``cv2.triangulatePoints``) between each camera and the next from ORB
    matches that agree with one homography (RANSAC, :data:`TIE_POINT_RANSAC_PX`), i.e. lie on the dominant plane."""
    import cv2

    orb = cv2.ORB.create(TIE_POINT_FEATURES)
    feats = []
    for path in images:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SequenceError(f"{path}: not a readable image")
        feats.append(orb.detectAndCompute(img, None))
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    heights = []
    for i in range(len(cams) - 1):
        (kp_a, des_a), (kp_b, des_b) = feats[i], feats[i + 1]
        if des_a is None or des_b is None:
            continue
        m = matcher.match(des_a, des_b)
        if len(m) < 8:
            continue
        pa = np.array([kp_a[x.queryIdx].pt for x in m], dtype=np.float64)
        pb = np.array([kp_b[x.trainIdx].pt for x in m], dtype=np.float64)
        _, inl = cv2.findHomography(pa, pb, cv2.RANSAC, TIE_POINT_RANSAC_PX)
        if inl is None:
            continue
        keep = inl.ravel() == 1
        a, b = cams[i], cams[i + 1]
        P_a = a.K @ np.column_stack([a.R_cw, -a.R_cw @ a.centre_w_m])
        P_b = b.K @ np.column_stack([b.R_cw, -b.R_cw @ b.centre_w_m])
        X = cv2.triangulatePoints(P_a, P_b, pa[keep].T, pb[keep].T)
        heights.append(X[2] / X[3])
    if not heights:
        raise SequenceError("no tie points between the bundle-adjusted cameras: give the ground level")
    z = np.concatenate(heights)
    return float(np.median(z)), int(z.size)


def _image_size(path: Path) -> tuple[int, int]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SequenceError(f"{path}: not a readable image")
    return int(img.shape[0]), int(img.shape[1])
