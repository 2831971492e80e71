"""The camera mount's yaw from a flight's own estimate.

The EKF's optical-rotation state (``opt_rot_rad`` in ``ekf.csv``, :mod:`fusion.state`) is the rotation the optical
displacement needs on top of the camera file's mount.  With GNSS and turns it is learnt apart from the AHRS heading
error (on a straight line only their difference is seen); its most certain value in a flight is what the camera
file's mount yaw (``mount_rpy_deg[2]``) should be corrected by.  With the mount so calibrated, ``[ekf]
init_opt_rot_sigma_deg`` can be set to the calibration's sigma: the state then no longer takes the AHRS heading error
on straight departures (docs/ardupilot.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.logio import read_log

#: a calibration less certain than this (deg, one sigma) is not one: the flight had too few turns with GNSS
MAX_SIGMA_DEG = 0.5


@dataclass(frozen=True)
class MountYawCalibration:
    """``correction_deg``: add to the camera file's mount yaw; ``sigma_deg``: its one-sigma; ``t_s``: the time of the
    estimate it comes from (s on the run's clock); ``n_valid``: valid estimates in the log."""

    correction_deg: float
    sigma_deg: float
    t_s: float
    n_valid: int

    @property
    def usable(self) -> bool:
        return self.sigma_deg <= MAX_SIGMA_DEG


def mount_yaw_from_log(folder: str | Path) -> MountYawCalibration:
    """The calibration from ``folder/ekf.csv``: its valid estimate whose ``opt_rot_sigma_rad`` is smallest.
    Raises ``FileNotFoundError`` without the file and ``ValueError`` when it holds no usable estimate."""
    path = Path(folder) / "ekf.csv"
    if not path.is_file():
        raise FileNotFoundError(2, "no ekf.csv in the run folder", str(path))
    log = read_log(path)
    missing = [c for c in ("t_us", "opt_rot_rad", "opt_rot_sigma_rad", "valid") if c not in log]
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)} column (logs written before the mount calibration)")
    sigma = np.asarray(log["opt_rot_sigma_rad"], dtype=float)
    rot = np.asarray(log["opt_rot_rad"], dtype=float)
    ok = (np.asarray(log["valid"], dtype=float) > 0.5) & np.isfinite(sigma) & np.isfinite(rot)
    if not np.any(ok):
        raise ValueError(f"{path}: no valid estimate")
    i = int(np.flatnonzero(ok)[np.argmin(sigma[ok])])
    return MountYawCalibration(correction_deg=math.degrees(float(rot[i])), sigma_deg=math.degrees(float(sigma[i])),
                               t_s=float(log["t_us"][i]) * 1e-6, n_valid=int(np.count_nonzero(ok)))
