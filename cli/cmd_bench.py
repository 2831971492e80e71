"""``gsoe bench``: per-frame cost of the optical pipeline, the renderer and the EKF step (figures, not tests).

The optical pipeline is timed from the raw fisheye frame to the displacement (``GsoeEstimator.process_frame``),
one OpenCV thread, with Intel IPP on and off (``cv2.ipp.setUseIPP(False)`` is the path an ARM board takes), beside
the naive path the paper describes: undistort the whole frame (``cv2.fisheye`` maps, precomputed), crop the base
image and template around the eq. 2-3 nadir point, full SSD.  Frames come from a scripted flight over a real
orthophoto (straight and a 30 deg/s turn at 100 m, 18 m/s).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from common.samples import AttitudeSample, ImuSample
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from gsoe.cycle import GsoeEstimator
from gsoe.equations import nadir_pixel_paper
from pipeline.config import load_gsoe_config
from sim.render import CameraRenderer
from sim.textures import GroundWorld
from sim.trajectory import ScriptedFlight, Segment


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=1200, help="frames to time (default 1200)")
    p.add_argument("--config", default=None, help="configuration file (default config/default.toml)")
    p.add_argument("--texture", default="forest_road")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")


def _frames(cfg: GsoeConfig, camera: CameraModel, texture: str, n: int, rate_hz: float
            ) -> tuple[list[tuple[int, np.ndarray, float]], list[tuple[int, Rotation, np.ndarray]], ScriptedFlight]:
    duration = n / rate_hz + 0.2
    flight = ScriptedFlight([Segment(duration / 2), Segment(duration / 2, math.radians(30.0))], tas_m_s=18.0,
                            height_m=100.0, wind_ned_m_s=(0.0, 5.0, 0.0))
    renderer = CameraRenderer(camera, GroundWorld.from_name(texture))
    frames = []
    imu = []
    t_imu = 0.0
    for k in range(n):
        t = 0.1 + k / rate_hz
        while t_imu <= t + 1e-9:
            tr = flight.truth(t_imu)
            imu.append((int(round(t_imu * 1e6)), Rotation.from_euler("ZYX", [tr.yaw_rad, tr.pitch_rad, tr.roll_rad]),
                        tr.rates_b_rad_s))
            t_imu += 1.0 / 300.0
        tr = flight.truth(t)
        R = Rotation.from_euler("ZYX", [tr.yaw_rad, tr.pitch_rad, tr.roll_rad]).as_matrix()
        frames.append((int(round(t * 1e6)), renderer.render(tr.pos_ned_m, R), tr.height_agl_m))
    return frames, imu, flight


def _time_pipeline(cfg: GsoeConfig, camera: CameraModel, frames: list, imu: list) -> dict[str, float]:
    est = GsoeEstimator(cfg, camera)
    times = []
    valid = 0
    i_imu = 0
    for t_us, image, h in frames:
        while i_imu < len(imu) and imu[i_imu][0] <= t_us:
            ti, R, w = imu[i_imu]
            yaw, pitch, roll = R.as_euler("ZYX")
            est.push_imu(ImuSample(ti, w, np.zeros(3)))
            est.push_attitude(AttitudeSample(ti, roll, pitch, yaw))
            i_imu += 1
        t0 = time.perf_counter()
        steps = est.process_frame(t_us, image, h)
        times.append(time.perf_counter() - t0)
        valid += sum(1 for s in steps if s.valid and not s.new_cycle)
    return {"median_ms": 1e3 * statistics.median(times), "p95_ms": 1e3 * float(np.percentile(times, 95)),
            "valid_matches": valid}


def _time_naive(cfg: GsoeConfig, camera: CameraModel, frames: list, imu: list) -> dict[str, float]:
    """Undistort the whole frame to a pinhole view, crop around eq. 2-3, full SSD against a base snapshot."""
    w, h = camera.size_px
    f = camera.config.fx_px
    K_new = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    map1, map2 = cv2.fisheye.initUndistortRectifyMap(camera.K, camera.D, np.eye(3), K_new, (w, h), cv2.CV_16SC2)
    hfov = 2 * math.atan(w / 2 / f)
    vfov = 2 * math.atan(h / 2 / f)
    bw, bh, tp = cfg.stab.base_cross_px, cfg.stab.base_along_px, cfg.stab.template_px
    att = {t: R for t, R, _ in imu}
    times = []
    base = None
    for k, (t_us, image, _) in enumerate(frames):
        R = att.get(t_us) or min(att.items(), key=lambda kv: abs(kv[0] - t_us))[1]
        yaw, pitch, roll = R.as_euler("ZYX")
        t0 = time.perf_counter()
        und = cv2.remap(image, map1, map2, cv2.INTER_LINEAR)
        # eq. 2-3 in our camera: image x follows roll, image y follows pitch (nose up moves the nadir down)
        xs, ys = nadir_pixel_paper(roll, pitch, w, h, hfov, vfov)
        xi, yi = int(round(xs)), int(round(ys))
        if base is None or k % 10 == 0:
            base = und[max(0, yi - bh // 2): yi + bh // 2 + 1, max(0, xi - bw // 2): xi + bw // 2 + 1].astype(
                np.float32)
        tpl = und[yi - tp // 2: yi + tp // 2 + 1, xi - tp // 2: xi + tp // 2 + 1].astype(np.float32)
        if base.shape[0] >= tp and base.shape[1] >= tp and tpl.shape == (tp, tp):
            cv2.minMaxLoc(cv2.matchTemplate(base, tpl, cv2.TM_SQDIFF))
        times.append(time.perf_counter() - t0)
    return {"median_ms": 1e3 * statistics.median(times)}


def _time_render(camera: CameraModel, texture: str, flight: ScriptedFlight, cfg: GsoeConfig) -> dict[str, float]:
    renderer = CameraRenderer(camera, GroundWorld.from_name(texture))
    est = GsoeEstimator(cfg, camera)
    full, roi = [], []
    for k in range(60):
        tr = flight.truth(0.1 + k * 0.05)
        R = Rotation.from_euler("ZYX", [tr.yaw_rad, tr.pitch_rad, tr.roll_rad])
        t0 = time.perf_counter()
        renderer.render(tr.pos_ned_m, R.as_matrix())
        t1 = time.perf_counter()
        renderer.render(tr.pos_ned_m, R.as_matrix(), roi=est.raw_roi(R.as_matrix(), 12))
        t2 = time.perf_counter()
        full.append(t1 - t0)
        roi.append(t2 - t1)
    return {"full_frame_ms": 1e3 * statistics.median(full), "estimator_roi_ms": 1e3 * statistics.median(roi)}


def _geometry_comparison(cfg: GsoeConfig, camera: CameraModel, texture: str) -> dict[str, dict[str, float]]:
    """Drift error of the cycles' last steps for the paper's base geometry and the long-along-track one with the
    template starting at the trailing edge, over the same noisy scripted flight (AHRS 0.1 deg, gyro 0.02 deg/s)."""
    import dataclasses

    from common.angles import angle_diff, circular_mean
    from gsoe.cycle import chord_drift_rad
    from sim.optical_run import fly_optical

    flight = ScriptedFlight([Segment(4.0), Segment(6.0, math.radians(20.0)), Segment(4.0)], tas_m_s=20.0,
                            height_m=100.0, wind_ned_m_s=(2.0, -5.0, 0.0))
    renderer = CameraRenderer(camera, GroundWorld.from_name(texture))
    geometries = {
        "paper_121x73_centre": cfg.stab,
        "long_73x121_trailing": dataclasses.replace(cfg.stab, base_cross_px=73, base_along_px=121,
                                                    template_start="trailing"),
    }
    out = {}
    for name, stab in geometries.items():
        run = fly_optical(flight, dataclasses.replace(cfg, stab=stab), camera, renderer,
                          att_noise_rad=math.radians(0.1), gyro_noise_rad_s=math.radians(0.02),
                          rng=np.random.default_rng(1))
        last: dict[int, int] = {}
        for i, st in enumerate(run.steps):
            if st.valid and not st.new_cycle:
                last[st.cycle_id] = i
        errs, travel = [], []
        for i in last.values():
            st, tr, tb = run.steps[i], run.truth_at_step[i], run.truth_at_base[i]
            d = tr.pos_ned_m[:2] - tb.pos_ned_m[:2]
            true = angle_diff(math.atan2(d[1], d[0]), circular_mean([tb.yaw_rad, tr.yaw_rad]))
            errs.append(abs(math.degrees(angle_diff(chord_drift_rad(st), true))))
            travel.append(math.hypot(st.dx_px, st.dy_px))
        out[name] = {"cycles": len(errs), "drift_mae_deg": float(np.mean(errs)),
                     "drift_p95_deg": float(np.percentile(errs, 95)), "travel_px_median": float(np.median(travel))}
    return out


def run(args: argparse.Namespace) -> int:
    cfg, raw = load_gsoe_config(args.config)
    camera = CameraModel.from_config(cfg.camera)
    cv2.setNumThreads(1)
    print(f"gsoe bench: rendering {args.frames} frames over '{args.texture}' ...", flush=True)
    frames, imu, flight = _frames(cfg, camera, args.texture, args.frames, cfg.cycle.rate_hz)
    results: dict[str, Any] = {"frames": args.frames, "opencv": cv2.__version__, "ipp_available": cv2.ipp.useIPP()}
    for ipp in (True, False):
        cv2.ipp.setUseIPP(ipp)
        key = "ipp_on" if ipp else "ipp_off"
        results[f"pipeline_{key}"] = _time_pipeline(cfg, camera, frames, imu)
        results[f"naive_{key}"] = _time_naive(cfg, camera, frames, imu)
    cv2.ipp.setUseIPP(True)
    results["render"] = _time_render(camera, args.texture, flight, cfg)
    results["geometry"] = _geometry_comparison(cfg, camera, args.texture)
    try:
        from fusion.bench import bench_ekf_step
    except ImportError:
        results["ekf_step"] = "fusion.bench not available"
    else:
        results["ekf_step"] = bench_ekf_step(2000)
    print(f"{'':28s}{'median ms/frame':>18s}{'vs naive':>10s}")
    for key in ("ipp_on", "ipp_off"):
        p = results[f"pipeline_{key}"]["median_ms"]
        n = results[f"naive_{key}"]["median_ms"]
        print(f"{'GSOE pipeline (' + key + ')':28s}{p:18.3f}{n / p:9.1f}x")
        print(f"{'naive path (' + key + ')':28s}{n:18.3f}")
    print(f"{'render full 800x600':28s}{results['render']['full_frame_ms']:18.3f}")
    print(f"{'render estimator ROI':28s}{results['render']['estimator_roi_ms']:18.3f}")
    print(f"EKF step: {results['ekf_step']}")
    print(f"valid matches: {results['pipeline_ipp_on']['valid_matches']} of {args.frames} frames")
    print("base geometry (cycle-end drift error, noisy AHRS/gyro, 20 m/s at 100 m, straight + 20 deg/s turn):")
    for name, g in results["geometry"].items():
        print(f"  {name:24s} cycles {g['cycles']:4d}  drift MAE {g['drift_mae_deg']:.3f} deg  "
              f"p95 {g['drift_p95_deg']:.3f} deg  template travel {g['travel_px_median']:.1f} px")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=2, default=str)
    return 0
