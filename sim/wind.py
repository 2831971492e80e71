"""Wind field of the simulator (the truth; what the estimators assume lives in ``config/``).

The wind is the velocity of the air in NED (the direction it blows *to*); its parameters name the direction it
blows *from* (clockwise from north), as the paper and MAVLink do.  Four parts, each switched and scaled by
:class:`WindParams`:

steady
    ``speed_m_s`` from ``from_rad`` measured at ``ref_height_m`` (the paper: 6 m).
shear
    MIL-F-8785C logarithmic profile ``W(h) = W(h_ref) ln(h / z0) / ln(h_ref / z0)`` with surface roughness
    ``z0 = roughness_m`` (the standard uses 0.15 ft for terminal flight phases and 2 ft otherwise); zero at and
    below ``z0``.  Off: the steady wind is the same at every height.
turbulence
    Dryden (MIL-F-8785C, low altitude) with our own filters driven by the ``np.random.Generator`` the field is
    given, so that a run is reproducible from its seed and every random draw comes from the run's generator.
    (JSBSim 1.3's own Milspec/Tustin turbulence draws from its internal generator, seedable through the
    ``simulation/randomseed`` and ``atmosphere/randomseed`` properties; we keep it off, ``atmosphere/turb-type``
    0, so that the turbulence part of the truth wind is known exactly.)  Intensities ``sigma_w = 0.1 W20``,
    ``sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4`` and scales ``L_w = h``,
    ``L_u = L_v = h / (0.177 + 0.000823 h)^1.2`` (h in ft, clamped to the low-altitude model's 10-1000 ft), with
    ``W20 = turbulence_w20_m_s`` (15 kt light, 30 kt moderate, 45 kt severe) times ``turbulence_scale``.  The
    longitudinal component lies along the mean wind's direction (the direction it blows to), the lateral one
    90 deg clockwise of it, the vertical one down.
    Transfer functions (Taylor's frozen turbulence at airspeed V):
    ``H_u = sigma_u sqrt(2 L_u / (pi V)) / (1 + L_u s / V)``,
    ``H_v = sigma_v sqrt(L_v / (pi V)) (1 + sqrt(3) L_v s / V) / (1 + L_v s / V)^2`` (and ``H_w`` alike),
    discretised *exactly* for the white-noise input (the state covariance over one step is integrated in closed
    form), so the output variance is ``sigma^2`` at any step size and the states start from their stationary
    distribution (no warm-up).
    Rate: a call whose ``dt_s`` is at least one period of ``turbulence_rate_hz`` advances the filters exactly by
    ``dt_s`` (one row of draws per call).  The default, 240 Hz, is the default dynamics rate, so a default run
    steps the filters at every dynamics step, as the model always did (same draws, same wind for a seed).  A lower
    rate (e.g. 50 Hz: the wind then costs about a third as much per dynamics step) steps them once per period and
    interpolates the wind linearly toward the next sample, computed one period ahead (no lag).  Why that keeps the
    model: the Dryden spectra have their corners at ``V / L``, below 1 rad/s at the paper's 80-150 m and 7 rad/s
    even at the model's floor of 10 ft, and fall as ``1 / f^2`` beyond: the share of the variance above ``f`` is
    ``V / (pi^2 L f)`` (longitudinal; 1.5 times that for the others), about 0.1 % above 25 Hz at 100 m.  Gusts
    shorter than the wing span (1.7 m: above ``V / b`` = 12 Hz at 20 m/s) are averaged over the wing in reality
    (and a wing's lift builds up over a few chord lengths of travel), so a point-gust model's content there is an
    artefact; it shows in the specific force.  Where ``L / V`` is short (low heights) the filter step shrinks to
    ``L / V / TURB_SAMPLES_PER_TIME_SCALE``, which bounds the variance the interpolation removes (about
    ``(1 - rho) / 3`` of it on average over a step, ``rho = exp(-1 / 50)``: under 1 %).  At the filter's sample
    instants the output is the exact discretisation.
gusts
    1-cosine discrete gusts ``v(t) = A / 2 (1 - cos(2 pi t / T))`` over ``T = 2 gust_length_m / V`` (the gust
    reaches its peak ``A = gust_amplitude_m_s`` after ``gust_length_m`` of flight), in a direction drawn
    uniformly on the sphere from the generator; they start at the scheduled ``gust_times_s`` and at random
    (Poisson) times of mean rate ``gust_rate_hz``.  Overlapping gusts add.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Final

import numpy as np
from numpy.typing import NDArray

from common.config import FINITE, In, Validated, require

FT_M: Final = 0.3048
TURB_HEIGHT_MIN_M: Final = 10.0 * FT_M
"""Lower end of MIL-F-8785C's low-altitude Dryden model (10 ft); lower heights use its values."""
TURB_HEIGHT_MAX_M: Final = 1000.0 * FT_M
"""Upper end of the low-altitude model (1000 ft); the mini-UAV flies below it, higher heights use its values."""
TURB_AIRSPEED_MIN_M_S: Final = 1.0
"""Airspeed below which the filters use this value (Taylor's hypothesis is meaningless at rest)."""
LIGHT_W20_M_S: Final = 15.0 * 0.514444
"""MIL-F-8785C wind speed at 20 ft for light turbulence (15 kt); moderate is 30 kt, severe 45 kt."""
TURB_SAMPLES_PER_TIME_SCALE: Final = 50.0
"""Least number of turbulence filter samples per Dryden time scale ``L / V`` (bounds the interpolation's loss)."""
TURB_TIME_TOLERANCE_S: Final = 1e-9
"""Clock tolerance of the turbulence filter's sample schedule (absorbs the rounding of a clock summed from steps)."""
_SQRT3: Final = math.sqrt(3.0)
_NOISE_BLOCK: Final = 4096
_SERIES_X_MAX: Final = 1e-2
"""Below it the series (error < x^5 / 840) replaces the closed forms of the second-order filter's noise integrals,
whose cancellation error is ~1e-16 / x^3."""


@dataclass(frozen=True)
class WindParams(Validated):
    """True wind of a run (SI units, radians).  See the module docstring for the model of each part."""

    speed_m_s: Annotated[float, In(0.0, 60.0)] = 0.0
    from_rad: Annotated[float, FINITE] = 0.0
    ref_height_m: Annotated[float, In(0.1, 1000.0)] = 6.0
    shear: bool = True
    roughness_m: Annotated[float, In(1e-4, 3.0)] = 0.15 * FT_M
    turbulence: bool = False
    turbulence_w20_m_s: Annotated[float, In(0.0, 60.0)] = LIGHT_W20_M_S
    turbulence_scale: Annotated[float, In(0.0, 10.0)] = 1.0
    turbulence_rate_hz: Annotated[float, In(1.0, 10000.0)] = 240.0
    gusts: bool = False
    gust_amplitude_m_s: Annotated[float, In(0.0, 40.0)] = 3.0
    gust_length_m: Annotated[float, In(1.0, 2000.0)] = 30.0
    gust_rate_hz: Annotated[float, In(0.0, 1.0)] = 0.0
    gust_times_s: Annotated[tuple[float, ...], In(0.0, 1e7)] = ()

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.ref_height_m > self.roughness_m, "ref_height_m",
                f"must be above roughness_m ({self.roughness_m} m), got {self.ref_height_m}")


@dataclass(frozen=True, slots=True)
class WindSample:
    """Wind at one instant and place (NED, m/s, the air's velocity): the total and its parts."""

    total_ned_m_s: NDArray[np.float64]
    steady_ned_m_s: NDArray[np.float64]
    turbulence_ned_m_s: NDArray[np.float64]
    gust_ned_m_s: NDArray[np.float64]


def _second_order_step(x1: float, x2: float, y: float, e: float, em1: float, xi1: float, xi2: float
                       ) -> tuple[float, float]:
    """One exact step of the states of ``(1 + sqrt(3) tau s) / (1 + tau s)^2`` (see :class:`_DrydenFilters`) by
    ``y = dt / tau > 0``, given ``e = exp(-y)``, ``em1 = expm1(-2 y)`` and two standard normal draws."""
    q11 = -0.5 * em1
    x = 2.0 * y
    if x < _SERIES_X_MAX:  # error < x^5 / 840
        f1 = 0.5 - x * (1.0 / 3.0 - x * (1.0 / 8.0 - x * (1.0 / 30.0 - x / 144.0)))
        f2 = 1.0 / 3.0 - x * (0.25 - x * (0.1 - x * (1.0 / 36.0 - x / 168.0)))
    else:
        ex = math.exp(-x)
        f1 = (1.0 - ex * (1.0 + x)) / (x * x)
        f2 = (2.0 - ex * (x * x + 2.0 * x + 2.0)) / (x * x * x)
    q12 = y * y * f1
    q22 = y * y * y * f2
    l11 = math.sqrt(q11)
    l21 = q12 / l11
    l22 = math.sqrt(max(q22 - l21 * l21, 0.0))
    return e * x1 + l11 * xi1, e * (y * x1 + x2) + l21 * xi1 + l22 * xi2


class _DrydenFilters:
    """Unit-variance states of the three Dryden shaping filters, exactly discretised for their white-noise input.

    Longitudinal: first-order Gauss-Markov ``u``.  Lateral and vertical: ``(1 + sqrt(3) tau s) / (1 + tau s)^2``
    driven by white noise of intensity ``tau``, states ``tau x1' = -x1 + n``, ``tau x2' = x1 - x2``, output
    ``sqrt(3) x1 + (1 - sqrt(3)) x2``; their stationary covariance is [[1/2, 1/4], [1/4, 1/4]] whatever tau, so a
    changing tau keeps the variance.  The covariance of one step's noise is ``q11 = (1 - exp(-2y)) / 2``,
    ``q12 = y^2 f1(2y)``, ``q22 = y^3 f2(2y)`` with ``f1(x) = int_0^1 u exp(-x u) du`` and
    ``f2(x) = int_0^1 u^2 exp(-x u) du``; below :data:`_SERIES_X_MAX` short series replace their closed forms,
    which cancel.
    """

    __slots__ = ("u", "v1", "v2", "w1", "w2")

    def __init__(self, xi: list[float]) -> None:
        """Stationary start from five standard normal draws (second order: Cholesky factor of the covariance,
        [[sqrt(1/2), 0], [sqrt(1/8), sqrt(1/8)]])."""
        self.u = xi[0]
        self.v1 = math.sqrt(0.5) * xi[1]
        self.v2 = math.sqrt(0.125) * (xi[1] + xi[2])
        self.w1 = math.sqrt(0.5) * xi[3]
        self.w2 = math.sqrt(0.125) * (xi[3] + xi[4])

    def outputs(self) -> tuple[float, float, float]:
        """Unit-variance longitudinal, lateral and vertical outputs."""
        return self.u, _SQRT3 * self.v1 + (1.0 - _SQRT3) * self.v2, _SQRT3 * self.w1 + (1.0 - _SQRT3) * self.w2

    def step(self, y_uv: float, y_w: float, xi: list[float]) -> tuple[float, float, float]:
        """Advance by ``y = dt / tau > 0`` (``y_uv`` longitudinal and lateral, ``y_w`` vertical) with five standard
        normal draws; returns :meth:`outputs`."""
        e = math.exp(-y_uv)
        em1 = math.expm1(-2.0 * y_uv)
        self.u = e * self.u + math.sqrt(-em1) * xi[0]
        self.v1, self.v2 = _second_order_step(self.v1, self.v2, y_uv, e, em1, xi[1], xi[2])
        self.w1, self.w2 = _second_order_step(self.w1, self.w2, y_w, math.exp(-y_w), math.expm1(-2.0 * y_w), xi[3],
                                              xi[4])
        return self.u, _SQRT3 * self.v1 + (1.0 - _SQRT3) * self.v2, _SQRT3 * self.w1 + (1.0 - _SQRT3) * self.w2


@dataclass(frozen=True, slots=True)
class _Gust:
    start_s: float
    duration_s: float
    peak_ned_m_s: tuple[float, float, float]


def dryden_sigmas_scales(height_m: float, w20_m_s: float) -> tuple[float, float, float, float]:
    """MIL-F-8785C low-altitude Dryden ``(sigma_uv_m_s, sigma_w_m_s, L_uv_m, L_w_m)`` at ``height_m``."""
    h_ft = min(max(height_m, TURB_HEIGHT_MIN_M), TURB_HEIGHT_MAX_M) / FT_M
    k = 0.177 + 0.000823 * h_ft
    sigma_w = 0.1 * w20_m_s
    sigma_uv = sigma_w / k**0.4
    l_w = h_ft * FT_M
    l_uv = h_ft / k**1.2 * FT_M
    return sigma_uv, sigma_w, l_uv, l_w


class WindField:
    """The wind the aircraft flies in; call :meth:`update` (or its lean form :meth:`advance`) once per dynamics step.

    ``rng`` drives the turbulence and the random gusts; the same seed and the same sequence of calls give the
    same wind.  The turbulence runs on the clock summed from the ``dt_s`` of the calls.  A call of at least one
    filter period (``1 / turbulence_rate_hz``) steps the filters by its ``dt_s``; shorter calls step them (one
    row of normal draws) when that clock passes their latest sample, to the next sample a filter period ahead, and
    interpolate in between (see the module docstring).  The intensities ``sigma`` are evaluated when the filters
    step, at the height of that call.
    """

    def __init__(self, params: WindParams, rng: np.random.Generator) -> None:
        if not isinstance(params, WindParams):
            raise TypeError(f"params must be WindParams, got {type(params).__name__}")
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy Generator, got {type(rng).__name__}")
        self.params = params
        self._rng = rng
        to_rad = params.from_rad + math.pi
        self._to_n = math.cos(to_rad)
        self._to_e = math.sin(to_rad)
        self._log_ref = math.log(params.ref_height_m / params.roughness_m)
        self._turb_period_s = 1.0 / params.turbulence_rate_hz
        self._w20 = params.turbulence_w20_m_s * params.turbulence_scale
        self.reset()

    def reset(self) -> None:
        """Restart at ``t = 0``: turbulence states drawn from their stationary distribution, gusts rescheduled."""
        self._noise: list[list[float]] = self._rng.standard_normal((_NOISE_BLOCK, 5)).tolist()
        self._k = 0
        xi = self._draw()
        self._filters = _DrydenFilters(xi)
        # The turbulence clock, the unit-variance filter outputs at the last two filter samples (t_a <= t_b), and
        # the turbulence (NED, m/s) at t_a with its rate of change toward t_b (the linear interpolation).
        self._t = 0.0
        self._ta = self._tb = 0.0
        self._out_a = self._out_b = self._filters.outputs()
        self._sig_uv = self._sig_w = math.nan  # set at the first call
        self._turb_a = (0.0, 0.0, 0.0)
        self._turb_rate = (0.0, 0.0, 0.0)
        self._last_parts = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self._gusts: list[_Gust] = []
        self._scheduled = sorted(self.params.gust_times_s)
        self._next_random_s = self._draw_gap() if self.params.gusts else math.inf

    def _draw(self) -> list[float]:
        if self._k >= _NOISE_BLOCK:
            self._noise = self._rng.standard_normal((_NOISE_BLOCK, 5)).tolist()
            self._k = 0
        row = self._noise[self._k]
        self._k += 1
        return row

    def _draw_gap(self) -> float:
        rate = self.params.gust_rate_hz
        return float(self._rng.exponential(1.0 / rate)) if rate > 0.0 else math.inf

    def steady_speed_m_s(self, height_m: float) -> float:
        """Steady wind speed at ``height_m`` above the ground (with the shear profile when it is on)."""
        p = self.params
        if not p.shear:
            return p.speed_m_s
        return p.speed_m_s * max(math.log(max(height_m, p.roughness_m) / p.roughness_m), 0.0) / self._log_ref

    def steady_ned(self, height_m: float) -> NDArray[np.float64]:
        """Steady wind (air velocity, NED, m/s) at ``height_m``."""
        s = self.steady_speed_m_s(height_m)
        return np.array([s * self._to_n, s * self._to_e, 0.0])

    def _start_gust(self, t_s: float, airspeed_m_s: float) -> None:
        p = self.params
        v = self._rng.standard_normal(3)
        v /= max(float(np.linalg.norm(v)), 1e-12)
        a = p.gust_amplitude_m_s
        duration = 2.0 * p.gust_length_m / max(airspeed_m_s, TURB_AIRSPEED_MIN_M_S)
        self._gusts.append(_Gust(t_s, duration, (a * float(v[0]), a * float(v[1]), a * float(v[2]))))

    def _gust_at(self, t_s: float, airspeed_m_s: float) -> tuple[float, float, float]:
        if not self.params.gusts:
            return 0.0, 0.0, 0.0
        while self._scheduled and self._scheduled[0] <= t_s:
            self._start_gust(self._scheduled.pop(0), airspeed_m_s)
        while self._next_random_s <= t_s:
            self._start_gust(self._next_random_s, airspeed_m_s)
            self._next_random_s += self._draw_gap()
        if not self._gusts:
            return 0.0, 0.0, 0.0
        gn = ge = gd = 0.0
        alive = []
        for g in self._gusts:
            tau = t_s - g.start_s
            if tau > g.duration_s:
                continue
            alive.append(g)
            shape = 0.5 * (1.0 - math.cos(2.0 * math.pi * tau / g.duration_s))
            gn += shape * g.peak_ned_m_s[0]
            ge += shape * g.peak_ned_m_s[1]
            gd += shape * g.peak_ned_m_s[2]
        self._gusts = alive
        return gn, ge, gd

    def _turbulence_step(self, height_m: float, airspeed_m_s: float) -> None:
        """Intensities at ``height_m``; when the clock has passed the latest filter sample, the next sample; then
        the turbulence at ``t_a`` and its rate toward ``t_b`` in NED."""
        v = max(airspeed_m_s, TURB_AIRSPEED_MIN_M_S)
        sig_uv, sig_w, l_uv, l_w = dryden_sigmas_scales(height_m, self._w20)
        self._sig_uv, self._sig_w = sig_uv, sig_w
        if self._t > self._tb + TURB_TIME_TOLERANCE_S:
            period = min(self._turb_period_s, min(l_uv, l_w) / (v * TURB_SAMPLES_PER_TIME_SCALE))
            h = max(period, self._t - self._tb)
            xi = self._draw()
            out = self._filters.step(h * v / l_uv, h * v / l_w, xi)
            self._ta, self._out_a = self._tb, self._out_b
            self._tb += h
            self._out_b = out
        ua, va, wa = self._out_a
        ub, vb, wb = self._out_b
        tn_a, te_a = self._rotate(sig_uv * ua, sig_uv * va)
        tn_b, te_b = self._rotate(sig_uv * ub, sig_uv * vb)
        span = self._tb - self._ta
        self._turb_a = (tn_a, te_a, sig_w * wa)
        self._turb_rate = ((tn_b - tn_a) / span, (te_b - te_a) / span, sig_w * (wb - wa) / span) if span > 0.0 \
            else (0.0, 0.0, 0.0)

    def _turbulence_exact(self, dt_s: float, height_m: float, airspeed_m_s: float) -> tuple[float, float, float]:
        """The filters advanced by ``dt_s`` at once (no interpolation): the turbulence (NED, m/s) at the clock."""
        v = max(airspeed_m_s, TURB_AIRSPEED_MIN_M_S)
        sig_uv, sig_w, l_uv, l_w = dryden_sigmas_scales(height_m, self._w20)
        xi = self._draw()
        out = self._filters.step(dt_s * v / l_uv, dt_s * v / l_w, xi)
        u = sig_uv * out[0]
        lat = sig_uv * out[1]
        tn, te, td = u * self._to_n - lat * self._to_e, u * self._to_e + lat * self._to_n, sig_w * out[2]
        # the interpolation restarts from this sample (for later calls with steps shorter than a filter period)
        self._ta = self._tb = self._t
        self._out_a = self._out_b = out
        self._sig_uv, self._sig_w = sig_uv, sig_w
        self._turb_a, self._turb_rate = (tn, te, td), (0.0, 0.0, 0.0)
        return tn, te, td

    def _rotate(self, along_m_s: float, lateral_m_s: float) -> tuple[float, float]:
        """North and east of a (longitudinal, lateral) turbulence pair: along the mean wind, and 90 deg clockwise."""
        return along_m_s * self._to_n - lateral_m_s * self._to_e, along_m_s * self._to_e + lateral_m_s * self._to_n

    def advance(self, t_s: float, dt_s: float, height_m: float, airspeed_m_s: float
                ) -> tuple[float, float, float, float, float]:
        """:meth:`update` without building arrays: ``(total_n, total_e, total_d, steady_n, steady_e)`` (m/s).

        The turbulence and gust parts of the call are kept for :meth:`update`.  Same checks as :meth:`update`.
        """
        if not math.isfinite(t_s + dt_s + height_m + airspeed_m_s):  # a sum is finite only if every term is
            raise ValueError(f"wind update needs finite inputs, got t_s={t_s}, dt_s={dt_s}, height_m={height_m}, "
                             f"airspeed_m_s={airspeed_m_s}")
        if dt_s < 0.0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s}")
        p = self.params
        if p.shear:  # steady_speed_m_s, written out
            s = p.speed_m_s * max(math.log(max(height_m, p.roughness_m) / p.roughness_m), 0.0) / self._log_ref
        else:
            s = p.speed_m_s
        sn, se = s * self._to_n, s * self._to_e
        tn = te = td = 0.0
        if p.turbulence:
            t = self._t = self._t + dt_s
            if dt_s >= self._turb_period_s - TURB_TIME_TOLERANCE_S:  # a whole filter period or more: exact step
                tn, te, td = self._turbulence_exact(dt_s, height_m, airspeed_m_s)
            else:
                if t > self._tb + TURB_TIME_TOLERANCE_S or self._sig_uv != self._sig_uv:  # passed, or NaN: unset
                    self._turbulence_step(height_m, airspeed_m_s)
                tau = t - self._ta  # in [0, t_b - t_a]
                (tn, te, td), (rn, re, rd) = self._turb_a, self._turb_rate
                tn += tau * rn
                te += tau * re
                td += tau * rd
        if p.gusts and (self._gusts or t_s >= self._next_random_s or (self._scheduled and self._scheduled[0] <= t_s)):
            gn, ge, gd = self._gust_at(t_s, airspeed_m_s)
            self._last_parts = (tn, te, td, gn, ge, gd)
            return sn + tn + gn, se + te + ge, td + gd, sn, se
        self._last_parts = (tn, te, td, 0.0, 0.0, 0.0)  # no gust alive and none starting
        return sn + tn, se + te, td, sn, se

    def update(self, t_s: float, dt_s: float, height_m: float, airspeed_m_s: float) -> WindSample:
        """Advance the turbulence by ``dt_s`` and return the wind at time ``t_s`` and height ``height_m`` (AGL).

        ``airspeed_m_s`` is the aircraft's true airspeed (it sets the time scales of the frozen turbulence and the
        duration of new gusts).  Non-finite inputs raise ``ValueError``.
        """
        wn, we, wd, sn, se = self.advance(t_s, dt_s, height_m, airspeed_m_s)
        tn, te, td, gn, ge, gd = self._last_parts
        return WindSample(
            total_ned_m_s=np.array([wn, we, wd]),
            steady_ned_m_s=np.array([sn, se, 0.0]),
            turbulence_ned_m_s=np.array([tn, te, td]),
            gust_ned_m_s=np.array([gn, ge, gd]),
        )
