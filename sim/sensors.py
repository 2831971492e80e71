"""Simulated sensors: the simulator's truth (:class:`sim.truth.TruthState`) in, timestamped samples out.

Truth apart from assumption (STYLE section 8): :class:`SensorErrors` holds the *true* error parameters of one run,
drawn by :func:`draw_sensor_errors` from the distributions of a scenario's ``[sensors]`` section; what the
estimators assume about the sensors lives in ``config/`` and may differ on purpose.

Every sensor has its own explicit :class:`numpy.random.Generator`, a sample period ``1/rate_hz`` on the simulation
clock (samples fall on the first dynamics step at or after each multiple of the period, so the rate may not exceed
the dynamics rate) and the pair ``due(t_s) -> bool`` / ``sample(truth) -> Sample``.  :class:`SensorSuite` ties
them together: call :meth:`SensorSuite.step` once per dynamics step.  Samples carry ``t_us`` on the one
simulation clock (the stamp the sensor reports, which for the AHRS and the camera differs from the time the
measured quantity belongs to).  Frames and units as in :mod:`gsoe`.

Cost: noise is drawn in blocks (:class:`_NormalBlocks`; the IMU's whole error path, bias walk plus white noise,
:data:`NOISE_BLOCK_ROWS` samples at a time), so a sample costs a few microseconds; the per-step path
(:meth:`SensorSuite.step`, :meth:`Imu.sample`) works on Python floats and builds each output array once.  The
draws and their order do not depend on this: a seed gives the same samples as drawing one sample at a time.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from common.angles import angle_diff, wrap_pi
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from sim.scenario import (
    AhrsConfig,
    AirspeedConfig,
    BaroConfig,
    CameraSimConfig,
    GnssConfig,
    ImuConfig,
    SensorsConfig,
)
from sim.truth import TruthState

# A sample is due when the simulation time is within this tolerance of its scheduled time (absorbs the rounding
# of a clock built by adding dt_s steps).
SCHEDULE_TOLERANCE_S = 1e-6
# Rows of standard normal draws fetched from a generator at once (only affects speed; a given seed always gives
# the same sequence).
NOISE_BLOCK_ROWS = 2048


class _NormalBlocks:
    """Normal rows of fixed width with per-column std ``scale``, drawn from ``rng`` in blocks of
    :data:`NOISE_BLOCK_ROWS` to keep the per-sample cost small; rows come as lists of Python floats."""

    __slots__ = ("_rng", "_scale", "_rows", "_i")

    def __init__(self, rng: np.random.Generator, scale: NDArray[np.float64] | list[float]) -> None:
        self._rng = rng
        self._scale = np.asarray(scale, dtype=np.float64)
        self._rows = self._draw()
        self._i = 0

    def _draw(self) -> list[list[float]]:
        return (self._rng.standard_normal((NOISE_BLOCK_ROWS, self._scale.size)) * self._scale).tolist()

    def next(self) -> list[float]:
        if self._i >= NOISE_BLOCK_ROWS:
            self._rows = self._draw()
            self._i = 0
        row = self._rows[self._i]
        self._i += 1
        return row


class _Schedule:
    """Sample times ``k / rate_hz``: ``due(t)`` once ``t`` reaches the next one; ``advance(t)`` moves past ``t``."""

    __slots__ = ("period_s", "next_s", "last_s")

    def __init__(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz
        self.next_s = 0.0
        self.last_s: float | None = None

    def due(self, t_s: float) -> bool:
        return t_s + SCHEDULE_TOLERANCE_S >= self.next_s

    def advance(self, t_s: float) -> float:
        """Mark a sample taken at ``t_s``; returns the time since the previous sample (one period for the first)."""
        k = math.floor((t_s + SCHEDULE_TOLERANCE_S) / self.period_s) + 1
        self.next_s = k * self.period_s
        dt = self.period_s if self.last_s is None else t_s - self.last_s
        self.last_s = t_s
        return dt


# --------------------------------------------------------------------------------------------------------------
# True errors of one run


@dataclass(frozen=True)
class SensorErrors:
    """The true error parameters of one run (drawn once; the random walks then evolve inside the sensors).

    Biases and scale errors are per body axis (FRD); scale errors are fractions (measured = (1 + s) * true + ...).
    ``ahrs_bias_rad`` is (roll, pitch, yaw).  ``camera_timestamp_offset_s`` is the full offset (configured value
    plus the per-run draw) between a frame's stamp and its true mid-exposure time.
    """

    gyro_bias_b_rad_s: NDArray[np.float64]
    gyro_scale: NDArray[np.float64]
    accel_bias_b_m_s2: NDArray[np.float64]
    accel_scale: NDArray[np.float64]
    ahrs_bias_rad: NDArray[np.float64]
    airspeed_scale: float
    baro_bias_m: float
    baro_drift_rate_m_s: float
    camera_timestamp_offset_s: float

    def to_dict(self) -> dict[str, float | list[float]]:
        """Plain form for logs and metrics."""
        out: dict[str, float | list[float]] = {}
        for k, v in self.__dict__.items():
            out[k] = [float(x) for x in v] if isinstance(v, np.ndarray) else float(v)
        return out


def draw_sensor_errors(cfg: SensorsConfig, rng: np.random.Generator, camera: CameraSimConfig) -> SensorErrors:
    """Draw one run's true sensor errors from the scenario's ``[sensors]`` and ``[camera]`` distributions.

    All draws are zero-mean normal with the configured std; the camera's configured timestamp offset is added to
    its draw.
    """
    imu, ahrs = cfg.imu, cfg.ahrs
    return SensorErrors(
        gyro_bias_b_rad_s=rng.normal(0.0, imu.gyro_bias_std_rad_s, 3),
        gyro_scale=rng.normal(0.0, imu.gyro_scale_std, 3),
        accel_bias_b_m_s2=rng.normal(0.0, imu.accel_bias_std_m_s2, 3),
        accel_scale=rng.normal(0.0, imu.accel_scale_std, 3),
        ahrs_bias_rad=rng.normal(0.0, 1.0, 3) * np.array([ahrs.bias_std_rad, ahrs.bias_std_rad, ahrs.yaw_bias_std_rad]),
        airspeed_scale=float(rng.normal(0.0, cfg.airspeed.scale_error_std)),
        baro_bias_m=float(rng.normal(0.0, cfg.baro.bias_std_m)),
        baro_drift_rate_m_s=float(rng.normal(0.0, cfg.baro.drift_rate_std_m_s)),
        camera_timestamp_offset_s=float(camera.timestamp_offset_s + rng.normal(0.0, camera.timestamp_offset_std_s)),
    )


# --------------------------------------------------------------------------------------------------------------
# Camera exposure (AirspeedSample, BaroSample, GnssSample live in common.samples)


@dataclass(frozen=True, slots=True)
class CameraFrame:
    """One camera exposure: frame ``index``, true mid-exposure time ``t_s`` (simulation clock), exposure length,
    and the stamp the camera reports, ``t_us`` = true mid-exposure time + timestamp offset."""

    index: int
    t_s: float
    exposure_s: float
    t_us: int

    @property
    def exposure_start_s(self) -> float:
        return self.t_s - 0.5 * self.exposure_s

    @property
    def exposure_end_s(self) -> float:
        return self.t_s + 0.5 * self.exposure_s


def _us(t_s: float) -> int:
    return int(round(t_s * 1e6))


# --------------------------------------------------------------------------------------------------------------
# Sensors


class Imu:
    """Gyro and accelerometer: ``(1 + scale) * truth + bias + white noise``; the biases random-walk, one step of a
    nominal sample period ``1 / rate_hz`` per sample.

    The errors are computed in blocks of :data:`NOISE_BLOCK_ROWS` samples (bias path + white noise), so a sample
    costs two vector multiply-adds.  :attr:`gyro_bias_b_rad_s` and :attr:`accel_bias_b_m_s2` are the true biases
    of the last sample (for logging the truth).
    """

    def __init__(self, cfg: ImuConfig, errors: SensorErrors, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self._sched = _Schedule(cfg.rate_hz)
        self._rng = rng
        sqrt_rate = math.sqrt(cfg.rate_hz)
        sqrt_period = math.sqrt(self._sched.period_s)
        self._white_std = np.array(
            [cfg.gyro_noise_density_rad_s_sqrt_hz * sqrt_rate] * 3
            + [cfg.accel_noise_density_m_s2_sqrt_hz * sqrt_rate] * 3
        )
        self._walk_std = np.array(
            [cfg.gyro_bias_walk_rad_s_sqrt_s * sqrt_period] * 3 + [cfg.accel_bias_walk_m_s2_sqrt_s * sqrt_period] * 3
        )
        self._gyro_scale = 1.0 + errors.gyro_scale
        self._accel_scale = 1.0 + errors.accel_scale
        self._scale6 = tuple(self._gyro_scale.tolist() + self._accel_scale.tolist())
        self._err_rows: list[list[float]] = []
        self._bias0 = np.concatenate([errors.gyro_bias_b_rad_s, errors.accel_bias_b_m_s2]).astype(np.float64)
        self._bias_path = np.empty((0, 6))
        self._i = 0
        self._first_block = True
        self._refill()

    def _refill(self) -> None:
        w = self._rng.standard_normal((NOISE_BLOCK_ROWS, 12))
        steps = w[:, 6:] * self._walk_std
        if self._first_block:
            steps[0] = 0.0  # the first sample carries the turn-on bias itself
            start = self._bias0
            self._first_block = False
        else:
            start = self._bias_path[-1]
        self._bias_path = start + np.cumsum(steps, axis=0)
        self._err_rows = (self._bias_path + w[:, :6] * self._white_std).tolist()
        self._i = 0

    @property
    def gyro_bias_b_rad_s(self) -> NDArray[np.float64]:
        return self._bias_path[max(self._i - 1, 0), 0:3].copy()

    @property
    def accel_bias_b_m_s2(self) -> NDArray[np.float64]:
        return self._bias_path[max(self._i - 1, 0), 3:6].copy()

    def due(self, t_s: float) -> bool:
        return self._sched.due(t_s)

    def sample(self, truth: TruthState) -> ImuSample:
        sched = self._sched  # _Schedule.advance, written out (the IMU samples at up to every dynamics step)
        t_s = sched.last_s = truth.t_s
        sched.next_s = (math.floor((t_s + SCHEDULE_TOLERANCE_S) / sched.period_s) + 1) * sched.period_s
        if self._i >= NOISE_BLOCK_ROWS:
            self._refill()
        e0, e1, e2, e3, e4, e5 = self._err_rows[self._i]
        self._i += 1
        s0, s1, s2, s3, s4, s5 = self._scale6
        p, q, r = truth.rates_b_rad_s.tolist()
        ax, ay, az = truth.accel_b_m_s2.tolist()
        return ImuSample(t_us=int(round(t_s * 1e6)), gyro_b_rad_s=np.array((s0 * p + e0, s1 * q + e1, s2 * r + e2)),
                         accel_b_m_s2=np.array((s3 * ax + e3, s4 * ay + e4, s5 * az + e5)))


class Ahrs:
    """Attitude with white noise, a constant bias and a latency.

    The sample stamped ``t`` reports the true attitude of ``t - latency_s`` (linearly interpolated between the truth
    states pushed so far; before enough history exists, the oldest one).  :meth:`push` must see every dynamics
    step (:class:`SensorSuite` does it); :meth:`sample` pushes its own truth too.
    """

    def __init__(self, cfg: AhrsConfig, errors: SensorErrors, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self._sched = _Schedule(cfg.rate_hz)
        self._noise = _NormalBlocks(rng, [cfg.noise_rad] * 3)
        self._bias_f: tuple[float, float, float] = tuple(errors.ahrs_bias_rad.astype(np.float64).tolist())
        self._latency = cfg.latency_s
        self._hist: deque[tuple[float, float, float, float]] = deque()

    def due(self, t_s: float) -> bool:
        return self._sched.due(t_s)

    def push(self, truth: TruthState) -> None:
        h = self._hist
        if h and truth.t_s <= h[-1][0]:
            return
        h.append((truth.t_s, truth.roll_rad, truth.pitch_rad, truth.yaw_rad))
        # Keep one state older than the oldest time still needed (t - latency) for the interpolation.
        cutoff = truth.t_s - self._latency
        while len(h) > 2 and h[1][0] <= cutoff:
            h.popleft()

    def _delayed(self, t_s: float) -> tuple[float, float, float]:
        h = self._hist
        if t_s <= h[0][0]:
            return h[0][1], h[0][2], h[0][3]
        # Pruning keeps the wanted time between the first two entries, so this loop normally stops at once.
        for i in range(len(h) - 1):
            t1, r1, p1, y1 = h[i + 1]
            if t1 > t_s:
                t0, r0, p0, y0 = h[i]
                f = (t_s - t0) / (t1 - t0)
                return (
                    r0 + f * float(angle_diff(r1, r0)),
                    p0 + f * (p1 - p0),
                    y0 + f * float(angle_diff(y1, y0)),
                )
        return h[-1][1], h[-1][2], h[-1][3]

    def sample(self, truth: TruthState) -> AttitudeSample:
        self.push(truth)
        self._sched.advance(truth.t_s)
        r, p, y = self._delayed(truth.t_s - self._latency)
        n0, n1, n2 = self._noise.next()
        b0, b1, b2 = self._bias_f
        return AttitudeSample(
            t_us=truth.t_us,
            roll_rad=float(wrap_pi(r + (b0 + n0))),
            pitch_rad=p + (b1 + n1),
            yaw_rad=float(wrap_pi(y + (b2 + n2))),
        )


class Airspeed:
    """Pitot true airspeed: ``(1 + scale) * tas + white noise``, never negative."""

    def __init__(self, cfg: AirspeedConfig, errors: SensorErrors, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self._sched = _Schedule(cfg.rate_hz)
        self._noise = _NormalBlocks(rng, [cfg.noise_m_s])
        self._scale = 1.0 + errors.airspeed_scale

    def due(self, t_s: float) -> bool:
        return self._sched.due(t_s)

    def sample(self, truth: TruthState) -> AirspeedSample:
        self._sched.advance(truth.t_s)
        n = self._noise.next()[0]
        return AirspeedSample(t_us=truth.t_us, tas_m_s=max(0.0, self._scale * truth.tas_m_s + n))


class Baro:
    """Barometric height: truth + turn-on offset + drift rate * t + random walk + white noise."""

    def __init__(self, cfg: BaroConfig, errors: SensorErrors, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self._sched = _Schedule(cfg.rate_hz)
        self._noise = _NormalBlocks(rng, [cfg.noise_m, cfg.walk_m_sqrt_s])
        self._bias = errors.baro_bias_m
        self._rate = errors.baro_drift_rate_m_s
        self.walk_m = 0.0
        self._first = True

    def due(self, t_s: float) -> bool:
        return self._sched.due(t_s)

    def error_m(self, t_s: float) -> float:
        """The slowly varying part of the error at ``t_s`` (offset + drift + walk so far), without white noise."""
        return self._bias + self._rate * t_s + self.walk_m

    def sample(self, truth: TruthState) -> BaroSample:
        dt = self._sched.advance(truth.t_s)
        w = self._noise.next()
        if not self._first and dt > 0.0:
            self.walk_m += math.sqrt(dt) * float(w[1])
        self._first = False
        alt = -float(truth.pos_ned_m[2]) + self.error_m(truth.t_s) + float(w[0])
        return BaroSample(t_us=truth.t_us, alt_m=alt)


class Gnss:
    """GNSS position (first-order Gauss-Markov errors) and velocity (white noise); no fix inside outage windows."""

    def __init__(self, cfg: GnssConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self._sched = _Schedule(cfg.rate_hz)
        self._noise = _NormalBlocks(rng, [cfg.pos_noise_m, cfg.pos_noise_m, cfg.alt_noise_m] + [cfg.vel_noise_m_s] * 3)
        self._pos_err: NDArray[np.float64] | None = None
        self._nan3 = np.full(3, np.nan)

    def due(self, t_s: float) -> bool:
        return self._sched.due(t_s)

    def _step_pos_err(self, dt: float, w: NDArray[np.float64]) -> NDArray[np.float64]:
        """First-order Gauss-Markov step; ``w`` already has the stationary std."""
        tau = self.cfg.pos_corr_time_s
        if self._pos_err is None or tau <= 0.0:
            self._pos_err = w.copy()
        else:
            a = math.exp(-dt / tau)
            self._pos_err = a * self._pos_err + math.sqrt(1.0 - a * a) * w
        return self._pos_err

    def sample(self, truth: TruthState) -> GnssSample:
        dt = self._sched.advance(truth.t_s)
        w = np.array(self._noise.next())
        # The error process runs through outages too, so the draws do not depend on the outage windows.
        pos_err = self._step_pos_err(dt, w[0:3])
        if self.cfg.in_outage(truth.t_s):
            return GnssSample(t_us=truth.t_us, pos_ned_m=self._nan3.copy(), vel_ned_m_s=self._nan3.copy(),
                              fix_ok=False, n_sats=0, h_acc_m=math.inf, v_acc_m_s=math.inf)
        return GnssSample(
            t_us=truth.t_us,
            pos_ned_m=truth.pos_ned_m + pos_err,
            vel_ned_m_s=truth.vel_ned_m_s + w[3:6],
            fix_ok=True,
            n_sats=self.cfg.n_sats,
            h_acc_m=self.cfg.pos_noise_m,
            v_acc_m_s=self.cfg.vel_noise_m_s,
        )


class CameraClock:
    """Frame exposure times at ``rate_hz``: frame k is exposed around the first dynamics step at or after
    ``k / rate_hz`` and stamped with that time plus the run's timestamp offset."""

    def __init__(self, cfg: CameraSimConfig, errors: SensorErrors) -> None:
        self.cfg = cfg
        self._sched = _Schedule(cfg.rate_hz)
        self._offset_s = errors.camera_timestamp_offset_s
        self._index = 0

    def due(self, t_s: float) -> bool:
        return self._sched.due(t_s)

    def frame(self, t_s: float) -> CameraFrame:
        self._sched.advance(t_s)
        f = CameraFrame(index=self._index, t_s=t_s, exposure_s=self.cfg.exposure_s, t_us=_us(t_s + self._offset_s))
        self._index += 1
        return f


# --------------------------------------------------------------------------------------------------------------
# Scheduler


class SensorReadings(NamedTuple):
    """What the sensors produced at one dynamics step (``None``: that sensor had no sample due).

    A named tuple (immutable, built cheaply once per dynamics step; see :class:`sim.truth.TruthState`).
    """

    imu: ImuSample | None
    ahrs: AttitudeSample | None
    airspeed: AirspeedSample | None
    baro: BaroSample | None
    gnss: GnssSample | None
    frame: CameraFrame | None


class SensorSuite:
    """All sensors of one run, each with its own generator spawned from ``rng``; :meth:`step` once per dynamics step.

    The true errors are drawn from ``rng`` first (or passed in as ``errors``, e.g. to inject chosen values).
    """

    def __init__(
        self,
        cfg: SensorsConfig,
        camera: CameraSimConfig,
        rng: np.random.Generator,
        errors: SensorErrors | None = None,
    ) -> None:
        self.errors = errors if errors is not None else draw_sensor_errors(cfg, rng, camera)
        r_imu, r_ahrs, r_air, r_baro, r_gnss = rng.spawn(5)
        self.imu = Imu(cfg.imu, self.errors, r_imu)
        self.ahrs = Ahrs(cfg.ahrs, self.errors, r_ahrs)
        self.airspeed = Airspeed(cfg.airspeed, self.errors, r_air)
        self.baro = Baro(cfg.baro, self.errors, r_baro)
        self.gnss = Gnss(cfg.gnss, r_gnss)
        self.camera = CameraClock(camera, self.errors)

    def step(self, truth: TruthState) -> SensorReadings:
        """The samples due at ``truth.t_s`` (each sensor's ``due`` test, written out here for speed)."""
        t = truth.t_s
        t_due = t + SCHEDULE_TOLERANCE_S
        imu, ahrs, air, baro, gnss, cam = self.imu, self.ahrs, self.airspeed, self.baro, self.gnss, self.camera
        ahrs.push(truth)
        return SensorReadings(
            imu.sample(truth) if t_due >= imu._sched.next_s else None,
            ahrs.sample(truth) if t_due >= ahrs._sched.next_s else None,
            air.sample(truth) if t_due >= air._sched.next_s else None,
            baro.sample(truth) if t_due >= baro._sched.next_s else None,
            gnss.sample(truth) if t_due >= gnss._sched.next_s else None,
            cam.frame(t) if t_due >= cam._sched.next_s else None,
        )
