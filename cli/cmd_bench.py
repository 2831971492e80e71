"""``gsoe bench``: per-frame cost of the optical pipeline, the renderer, the EKF step and the companion's loop (figures,
not tests).

The optical pipeline is timed from the raw fisheye frame to the displacement (``GsoeEstimator.process_frame``),
one OpenCV thread, with Intel IPP on and off (``cv2.ipp.setUseIPP(False)`` is the path an ARM board takes), beside
the naive path the paper describes: undistort the whole frame (``cv2.fisheye`` maps, precomputed), crop the base
image and template around the eq. 2-3 nadir point, full SSD.  The configured matcher (``[match] method``, the window
around the predicted position) and the exhaustive search are timed too.  The three run in turns over blocks of 30
frames (:data:`BLOCK_FRAMES`), so that a loaded machine slows them alike and their ratio holds.  Frames come from a
scripted flight over a real orthophoto (straight and a 30 deg/s turn at 100 m, 18 m/s).

The companion's loop (:func:`nav.bench_loop.companion_loop_cpu`): the same flight's telemetry at the autopilot link's
rates (attitude and IMU 50 Hz, airspeed and baro 10 Hz, GNSS 5 Hz for the first ``--gnss-s`` seconds) and its frames
at the camera rate, through the companion's estimate path and log; the CPU time per second of flight is the
fraction of one core it takes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import tempfile
import time
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from common.hostref import describe, host_reference
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
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
    p.add_argument("--gnss-s", type=float, default=10.0,
                   help="companion loop: GNSS fixes for this long, then lost (default 10 s)")
    p.add_argument("--no-geometry", action="store_true",
                   help="skip the base-geometry comparison (two rendered flights)")


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


def _push_attitude(ests: list[GsoeEstimator], imu: list, i_imu: int, t_us: int) -> int:
    """The bench's IMU and attitude samples up to ``t_us`` into every estimator; the next index."""
    while i_imu < len(imu) and imu[i_imu][0] <= t_us:
        ti, R, w = imu[i_imu]
        yaw, pitch, roll = R.as_euler("ZYX")
        for est in ests:
            est.push_imu(ImuSample(ti, w, np.zeros(3)))
            est.push_attitude(AttitudeSample(ti, roll, pitch, yaw))
        i_imu += 1
    return i_imu


class _NaivePath:
    """Undistort the whole frame to a pinhole view, crop around eq. 2-3, full SSD against a base snapshot (a new
    one every 10 frames)."""

    def __init__(self, cfg: GsoeConfig, camera: CameraModel, imu: list) -> None:
        w, h = camera.size_px
        f = camera.config.fx_px
        K_new = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
        self.map1, self.map2 = cv2.fisheye.initUndistortRectifyMap(camera.K, camera.D, np.eye(3), K_new, (w, h),
                                                                   cv2.CV_16SC2)
        self.size = (w, h)
        self.fov = (2 * math.atan(w / 2 / f), 2 * math.atan(h / 2 / f))
        self.geom = (cfg.stab.base_cross_px, cfg.stab.base_along_px, cfg.stab.template_px)
        self.att = {t: R for t, R, _ in imu}
        self.base: np.ndarray | None = None
        self.k = 0

    def step(self, t_us: int, image: np.ndarray) -> float:
        """One frame; returns its time (s)."""
        R = self.att.get(t_us) or min(self.att.items(), key=lambda kv: abs(kv[0] - t_us))[1]
        yaw, pitch, roll = R.as_euler("ZYX")
        bw, bh, tp = self.geom
        t0 = time.perf_counter()
        und = cv2.remap(image, self.map1, self.map2, cv2.INTER_LINEAR)
        # eq. 2-3 in our camera: image x follows roll, image y follows pitch (nose up moves the nadir down)
        xs, ys = nadir_pixel_paper(roll, pitch, *self.size, *self.fov)
        xi, yi = int(round(float(xs))), int(round(float(ys)))
        if self.base is None or self.k % 10 == 0:
            self.base = und[max(0, yi - bh // 2): yi + bh // 2 + 1, max(0, xi - bw // 2): xi + bw // 2 + 1].astype(
                np.float32)
        tpl = und[yi - tp // 2: yi + tp // 2 + 1, xi - tp // 2: xi + tp // 2 + 1].astype(np.float32)
        if self.base.shape[0] >= tp and self.base.shape[1] >= tp and tpl.shape == (tp, tp):
            cv2.minMaxLoc(cv2.matchTemplate(self.base, tpl, cv2.TM_SQDIFF))
        self.k += 1
        return time.perf_counter() - t0


#: The optical paths are timed in turns over blocks of this many frames (each path runs every frame, in order): a
#: block is long enough that each path runs with its own data in the caches, as it would alone, and short enough
#: that a loaded machine's slow and quiet spells fall on all paths alike.
BLOCK_FRAMES = 30


def _time_optical(cfg: GsoeConfig, camera: CameraModel, frames: list, imu: list) -> dict[str, dict[str, float]]:
    """The configured pipeline, the pipeline with the exhaustive search and the naive path, in turns over blocks of
    :data:`BLOCK_FRAMES` frames: median and 95th percentile per frame (ms), valid matches."""
    cfg_ex = dataclasses.replace(cfg, match=dataclasses.replace(cfg.match, method="exhaustive"))
    ests = {"pipeline": GsoeEstimator(cfg, camera), "pipeline_exhaustive": GsoeEstimator(cfg_ex, camera)}
    naive = _NaivePath(cfg, camera, imu)
    times: dict[str, list[float]] = {"pipeline": [], "pipeline_exhaustive": [], "naive": []}
    valid = dict.fromkeys(ests, 0)
    i_imu = dict.fromkeys(ests, 0)
    order = ["pipeline", "pipeline_exhaustive", "naive"]
    for b, k0 in enumerate(range(0, len(frames), BLOCK_FRAMES)):
        block = frames[k0:k0 + BLOCK_FRAMES]
        for name in order[b % 3:] + order[:b % 3]:
            for t_us, image, h in block:
                if name == "naive":
                    times[name].append(naive.step(t_us, image))
                    continue
                i_imu[name] = _push_attitude([ests[name]], imu, i_imu[name], t_us)
                t0 = time.perf_counter()
                steps = ests[name].process_frame(t_us, image, h)
                times[name].append(time.perf_counter() - t0)
                valid[name] += sum(1 for s in steps if s.valid and not s.new_cycle)
    out: dict[str, dict[str, float]] = {}
    for name, ts in times.items():
        out[name] = {"median_ms": 1e3 * statistics.median(ts), "p95_ms": 1e3 * float(np.percentile(ts, 95))}
        if name in valid:
            out[name]["valid_matches"] = valid[name]
    return out


def _telemetry(flight: ScriptedFlight, t_end_s: float, gnss_s: float, home_amsl_m: float = 500.0) -> list[Any]:
    """The flight's telemetry at the autopilot link's rates (attitude and IMU 50 Hz on the same stamps, airspeed and
    baro 10 Hz, GNSS 5 Hz with a fix for the first ``gnss_s`` seconds, home 1 Hz), time-ordered."""
    from nav.link import HomeReading

    out: list[tuple[int, int, Any]] = []
    for rate, kind in ((50.0, 0), (10.0, 1), (5.0, 2), (1.0, 3)):
        for k in range(int(t_end_s * rate) + 1):
            t = k / rate
            tr = flight.truth(t)
            t_us = int(round(t * 1e6))
            if kind == 0:
                out.append((t_us, 0, AttitudeSample(t_us, tr.roll_rad, tr.pitch_rad, tr.yaw_rad)))
                out.append((t_us, 1, ImuSample(t_us, tr.rates_b_rad_s, tr.accel_b_m_s2)))
            elif kind == 1:
                out.append((t_us, 2, AirspeedSample(t_us, tr.tas_m_s)))
                out.append((t_us, 3, BaroSample(t_us, home_amsl_m + tr.height_agl_m)))
            elif kind == 2:
                fix = t < gnss_s
                out.append((t_us, 4, GnssSample(t_us, tr.pos_ned_m.copy(), tr.vel_ned_m_s.copy(), fix, 12 if fix else 0,
                                                h_acc_m=1.0, v_acc_m_s=0.3, alt_msl_m=home_amsl_m + tr.height_agl_m,
                                                alt_acc_m=2.0)))
            else:
                out.append((t_us, 5, HomeReading(t_us, home_amsl_m + tr.height_agl_m, tr.height_agl_m)))
    out.sort(key=lambda e: (e[0], e[1]))
    return [s for _, _, s in out]


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
    results: dict[str, Any] = {"frames": args.frames, "opencv": cv2.__version__, "ipp_available": cv2.ipp.useIPP(),
                               "match_method": cfg.match.method, "host": host_reference()}
    for ipp in (True, False):
        cv2.ipp.setUseIPP(ipp)
        results["ipp_on" if ipp else "ipp_off"] = _time_optical(cfg, camera, frames, imu)
    cv2.ipp.setUseIPP(True)
    results["render"] = _time_render(camera, args.texture, flight, cfg)
    if not args.no_geometry:
        results["geometry"] = _geometry_comparison(cfg, camera, args.texture)
    try:
        from fusion.bench import bench_ekf_step
    except ImportError:
        results["ekf_step"] = "fusion.bench not available"
    else:
        results["ekf_step"] = bench_ekf_step(2000)
    from nav.bench_loop import companion_loop_cpu

    samples = _telemetry(flight, frames[-1][0] / 1e6 + 0.1, args.gnss_s)
    with tempfile.TemporaryDirectory() as tmp:
        results["companion_loop"] = companion_loop_cpu(cfg, raw, camera, samples, [(t, im) for t, im, _ in frames],
                                                       tmp)
    results["host_after"] = host_reference()     # a shared host's speed drifts: the reference at both ends
    print(describe(results["host"]))
    print(f"  after the bench: {describe(results['host_after'])}")
    print(f"{'':36s}{'median ms/frame':>16s}{'p95':>8s}{'vs naive':>10s}")
    for key in ("ipp_on", "ipp_off"):
        r = results[key]
        n = r["naive"]["median_ms"]
        for name, label in (("pipeline", f"GSOE pipeline, {cfg.match.method}"),
                            ("pipeline_exhaustive", "GSOE pipeline, exhaustive"), ("naive", "naive path")):
            p = r[name]
            ratio = f"{n / p['median_ms']:9.1f}x" if name != "naive" else ""
            print(f"{label + ' (' + key + ')':36s}{p['median_ms']:16.3f}{p['p95_ms']:8.3f}{ratio}")
    print(f"{'render full 800x600':36s}{results['render']['full_frame_ms']:16.3f}")
    print(f"{'render estimator ROI':36s}{results['render']['estimator_roi_ms']:16.3f}")
    e = results["ekf_step"]
    if isinstance(e, dict):
        print(f"EKF step (predict + the updates of one camera frame): median {e['frame_us_median']:.1f} us, "
              f"p95 {e['frame_us_p95']:.1f} us (IMU {e['imu_us_per_frame']:.1f}, optical {e['optical_us']:.1f}, "
              f"airspeed + sideslip + AoA {e['airspeed_us']:.1f}, baro {e['baro_us']:.1f} us)")
    else:
        print(f"EKF step: {e}")
    c = results["companion_loop"]
    print(f"companion loop at {c['frame_rate_hz']:.0f} Hz (estimate path and log, no link): "
          f"{100 * c['cpu_one_core_frac']:.1f} % of one core, frame -> output median "
          f"{c['frame_to_output_us_median'] / 1e3:.2f} ms (p95 {c['frame_to_output_us_p95'] / 1e3:.2f} ms), "
          f"{c['outputs_valid']} of {c['frames']} estimates valid")
    print(f"valid matches: {results['ipp_on']['pipeline']['valid_matches']} of {args.frames} frames "
          f"({results['ipp_on']['pipeline_exhaustive']['valid_matches']} exhaustive)")
    if "geometry" in results:
        print("base geometry (cycle-end drift error, noisy AHRS/gyro, 20 m/s at 100 m, straight + 20 deg/s turn):")
        for name, g in results["geometry"].items():
            print(f"  {name:24s} cycles {g['cycles']:4d}  drift MAE {g['drift_mae_deg']:.3f} deg  "
                  f"p95 {g['drift_p95_deg']:.3f} deg  template travel {g['travel_px_median']:.1f} px")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=2, default=str)
    return 0
