"""The companion's own per-frame work at its frame rate, without the autopilot link and the camera thread (figures for
``gsoe bench``; ``python -m nav.bench_companion perf`` measures the whole companion against the simulated vehicle over
MAVLink).

:func:`companion_loop_cpu` replays a flight's telemetry samples and camera frames, in time order, through what
:class:`nav.companion.Companion` does with them between the link's queue and the link's send calls: each sample into
the :class:`~nav.companion.CompanionEstimator` (the navigation pipeline behind the GNSS monitor), each frame through
the companion's frame check and frozen-frame checksum into the pipeline, and after each processed frame the estimate
mapped onto the link's :class:`~nav.link.OutputEstimate` and the ``outputs`` record; every record goes to a
:class:`common.logio.RunLog` as the companion writes it.  The CPU time this takes per second of flight is the
fraction of one core the companion's estimate costs at that frame rate (the MAVSDK link's encoding and sockets and
the camera's decoding come on top).
"""

from __future__ import annotations

import math
import statistics
import time
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from common.logio import RunLog
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from nav.companion import CompanionEstimator, check_frame, companion_config_from_raw

US_PER_S = 1_000_000


def companion_loop_cpu(gsoe_cfg: GsoeConfig, raw: dict[str, Any], camera: CameraModel, samples: Sequence[Any],
                       frames: Sequence[tuple[int, Any]], log_dir: str | Path, *, warmup_s: float = 2.0,
                       frame_lag_us: int = 20_000) -> dict[str, Any]:
    """Run the companion's estimate path over ``samples`` (telemetry samples of :mod:`common.samples` and
    :class:`nav.link.HomeReading`, time-ordered by ``t_us``) and ``frames`` (``(t_us, image)`` at the camera's rate);
    each frame is handed over once the samples stamped up to ``frame_lag_us`` after its exposure are in (the link's
    telemetry arrives while the frame is read).

    Returns ``cpu_s`` and ``flight_s`` after the first ``warmup_s`` of flight, ``cpu_one_core_frac`` (their ratio),
    ``frame_rate_hz``, the per-frame time from hand-over to the output computed (``frame_to_output_us_median``,
    ``_p95``), and ``frames``, ``outputs_valid``.
    """
    cfg = companion_config_from_raw(raw)
    runlog = RunLog(log_dir, flush_interval_s=cfg.log_flush_s)

    def sink(stream: str, record: dict[str, Any]) -> None:       # as Companion._log
        runlog.write(stream, {k: v.item() if isinstance(v, np.generic) else v for k, v in record.items()})

    est = CompanionEstimator(gsoe_cfg, camera, raw, cfg, sink=sink)
    pipe = est.pipe
    t0_us = frames[0][0] + round(warmup_s * US_PER_S)
    i_s = 0
    last_crc: int | None = None
    lat: list[float] = []
    n_valid = 0
    cpu0: float | None = None
    t_first = t_last = 0
    for t_us, image in frames:
        if cpu0 is None and t_us >= t0_us:
            cpu0, t_first = time.process_time(), t_us
        while i_s < len(samples) and samples[i_s].t_us <= t_us + frame_lag_us:
            est.feed(samples[i_s])
            i_s += 1
        est.tick(samples[i_s - 1].t_us if i_s else t_us)
        c0 = time.perf_counter()
        gray, why = check_frame(image, camera)
        if gray is None:
            raise ValueError(f"bench frame rejected: {why}")
        crc = zlib.crc32(np.ascontiguousarray(gray).data)
        if crc == last_crc:
            continue
        last_crc = crc
        pipe.on_frame(t_us, gray)
        for res in pipe.drain():
            out = est.output(res.t_us)
            n_valid += int(out.valid)
            sink("outputs", {"t_us": res.t_us, "sent": out.valid, "reason": out.reason,
                             "drift_rad": out.drift_rad, "drift_sigma_rad": out.drift_sigma_rad,
                             "ata_rad": out.ata_rad, "vel_n_m_s": out.vel_ne_m_s[0], "vel_e_m_s": out.vel_ne_m_s[1],
                             "wind_n_m_s": out.wind_ne_m_s[0], "wind_e_m_s": out.wind_ne_m_s[1],
                             "quality": out.quality, "gnss_state": int(est.monitor.state), "latency_us": None})
        if cpu0 is not None:
            lat.append(1e6 * (time.perf_counter() - c0))
            t_last = t_us
    cpu = time.process_time() - cpu0 if cpu0 is not None else math.nan
    runlog.close()
    flight_s = (t_last - t_first) / US_PER_S + (frames[1][0] - frames[0][0]) / US_PER_S
    return {"cpu_s": cpu, "flight_s": flight_s, "cpu_one_core_frac": cpu / flight_s if flight_s > 0 else math.nan,
            "frame_rate_hz": len(lat) / flight_s if flight_s > 0 else math.nan, "frames": len(lat),
            "frame_to_output_us_median": statistics.median(lat) if lat else math.nan,
            "frame_to_output_us_p95": float(np.percentile(lat, 95)) if lat else math.nan, "outputs_valid": n_valid}
