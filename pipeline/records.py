"""One record builder per CSV stream the pipeline writes (columns as in :mod:`common.logio`).

Every driver (simulator, companion, replay) logs through these, so a stream has the same columns whoever wrote it.
"""

from __future__ import annotations

from typing import Any

from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, GsoeStep, ImuSample
from gsoe.baseline import BaselineEstimate


def imu_record(s: ImuSample) -> dict[str, Any]:
    g, a = s.gyro_b_rad_s, s.accel_b_m_s2
    return {"t_us": s.t_us, "gyro_x_rad_s": g[0], "gyro_y_rad_s": g[1], "gyro_z_rad_s": g[2],
            "accel_x_m_s2": a[0], "accel_y_m_s2": a[1], "accel_z_m_s2": a[2]}


def attitude_record(s: AttitudeSample) -> dict[str, Any]:
    return {"t_us": s.t_us, "roll_rad": s.roll_rad, "pitch_rad": s.pitch_rad, "yaw_rad": s.yaw_rad}


def airspeed_record(s: AirspeedSample) -> dict[str, Any]:
    return {"t_us": s.t_us, "tas_m_s": s.tas_m_s, "eas_m_s": s.eas_m_s}


def baro_record(s: BaroSample, ground_alt_m: float) -> dict[str, Any]:
    """``alt_m`` as measured; ``height_m`` the height above the ground level the pipeline refers it to."""
    return {"t_us": s.t_us, "alt_m": s.alt_m, "height_m": s.alt_m - ground_alt_m}


def gnss_record(s: GnssSample, fused: bool) -> dict[str, Any]:
    p, v = s.pos_ned_m, s.vel_ned_m_s
    return {"t_us": s.t_us, "pos_n_m": p[0], "pos_e_m": p[1], "pos_d_m": p[2], "vel_n_m_s": v[0],
            "vel_e_m_s": v[1], "vel_d_m_s": v[2], "fix_ok": s.fix_ok, "n_sats": s.n_sats, "h_acc_m": s.h_acc_m,
            "v_acc_m_s": s.v_acc_m_s, "lat_deg": s.lat_deg, "lon_deg": s.lon_deg, "alt_msl_m": s.alt_msl_m,
            "fused": fused}


def step_record(s: GsoeStep) -> dict[str, Any]:
    q = s.quality
    return {"t_us": s.t_us, "base_t_us": s.base_t_us, "cycle_id": s.cycle_id, "step": s.step, "dx_px": s.dx_px,
            "dy_px": s.dy_px, "base_yaw_rad": s.base_yaw_rad, "yaw_rad": s.yaw_rad, "gsd_m_px": s.gsd_m_px,
            "height_agl_m": s.height_agl_m, "rel_rot_rad": s.rel_rot_rad, "psr": q.psr,
            "texture_std": q.texture_std, "ssd_per_px": q.ssd_per_px, "match_sigma_px": q.match_sigma_px,
            "valid": s.valid, "new_cycle": s.new_cycle}


def baseline_record(b: BaselineEstimate) -> dict[str, Any]:
    return {"t_us": b.t_us, "drift_rad": b.drift_rad, "heading_rad": b.heading_rad,
            "ground_speed_m_s": b.ground_speed_m_s, "ata_rad": b.ata_rad, "wind_speed_m_s": b.wind_speed_m_s,
            "wind_from_rad": b.wind_from_rad, "released": b.released, "reason": b.reason}
