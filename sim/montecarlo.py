"""Monte Carlo campaigns of simulated flights: seeded parameter draws, local or Dask execution, aggregation.

A campaign flies ``n_runs`` variations of a base scenario.  Run ``i`` draws its parameters from the distributions
of a *spec* file (``config/montecarlo/*.toml``) with generators seeded from ``(base_seed, i)`` only, and flies
with the seed :func:`run_seed` ``(base_seed, i)``; so any run can be re-flown alone, bit for bit
(``gsoe montecarlo --only I --out DIR``), by the same code: every record carries :func:`code_fingerprint`, the hash
of the files that decide a flight (the packages and ``config/``), and a re-flight says when it differs (a record
flown by other code may differ in the last digits).

Spec file layout (validated like every config: errors name the field, ``params."wind.speed_m_s".low: ...``)::

    name, description, base_scenario, base_seed, n_runs, duration_s, runner, fail_runs, crash_runs
    [fixed]   "dotted.scenario.key" = value                 (applied to every run)
    [params]  "dotted.scenario.key" = { dist = "uniform", low = 0.0, high = 12.0 }
    [[goals]] name, metric, op, threshold, stat, min_wind_m_s   (default: the goals of issue 6)

Distributions (:class:`Dist`): ``uniform`` (low, high), ``loguniform`` (0 < low < high), ``normal`` (mean, std,
truncated to [low, high]: bounds are required so that no draw can leave the scenario's valid range), ``choice``
(values, optional weights) and ``constant`` (value).  Keys are the dotted scenario fields of
:func:`sim.scenario.scenario_with_overrides`, plus these *virtual* keys (prefix ``mc.``) that stand for several
fields at once:

``mc.mean_agl_m``
    scales the height above ground of the start point and of every waypoint so that the waypoints' mean height
    above ground is the drawn value (the mission keeps its relative altitude changes).
``mc.mean_airspeed_m_s``
    scales the start and waypoint airspeeds the same way.
``mc.gnss_outage_start_s`` + ``mc.gnss_outage_length_s`` or ``mc.gnss_outage_start_frac`` + ``..._length_frac``
    one GNSS outage (``sensors.gnss.outages``), in seconds or as fractions of the run's duration.
``mc.camera_focal_error_frac``, ``mc.camera_cx_error_px``, ``mc.camera_cy_error_px``,
``mc.camera_mount_{roll,pitch,yaw}_error_deg``
    camera calibration error: the optical estimator is given a camera (``camera.gsoe_overrides.camera``) whose
    focal length, principal point and mounting differ from the nominal camera of ``config/default.toml`` by the
    drawn amounts.  This is a calibration error only as long as the simulator renders with the nominal camera
    (a truth-side camera error in the scenario would make it independent of that).

Test hooks (documented, off by default): ``fail_runs = [i, ...]`` makes those runs raise :class:`InjectedFailure`
after their parameters are drawn; ``crash_runs = [i, ...]`` makes their worker process exit abruptly (as a
segfault would); ``runner = "module:function"`` replaces :func:`sim.run.run_flight` by a function of the same
signature.

Output folder ``DIR``: ``campaign.json`` (the resolved spec, seed, duration, one entry per session),
``runs/run_00042.json`` (one :class:`RunRecord` per run, each written atomically as soon as it finishes),
``summary.json`` (:func:`summarize`) and, written from these by :func:`sim.mc_report.write_report` (the caller's
choice: ``gsoe montecarlo`` does), ``report.html``.  Non-finite numbers are stored as JSON ``null``.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import copy
import dataclasses
import functools
import hashlib
import importlib
import importlib.util
import json
import logging
import math
import multiprocessing
import os
import resource
import socket
import sys
import time
import traceback
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from scipy import stats as sps

from common.config import ConfigError, In, Validated, build, in_range, require, to_dict
from common.configfile import CONFIG_DIR, read_toml
from common.hostref import host_reference
from common.metrics import nees_bounds
from gsoe.config import CameraConfig
from pipeline.config import load_gsoe_config
from sim.scenario import SEED_MAX, Scenario, build_scenario, load_scenario, scenario_path, scenario_with_overrides

log = logging.getLogger(__name__)

MONTECARLO_DIR = CONFIG_DIR / "montecarlo"
DEFAULT_SPEC = MONTECARLO_DIR / "default.toml"
DEFAULT_RUNNER = "sim.run:run_flight"

RUNS_DIR = "runs"
CAMPAIGN_FILE = "campaign.json"
SUMMARY_FILE = "summary.json"
CAMPAIGN_FORMAT = 1
#: Folders (beside ``config/``) whose files decide a flight: hashed by :func:`code_fingerprint`.
CODE_PACKAGES = ("common", "gsoe", "fusion", "pipeline", "sim", "config")
#: Hex digits of the SHA-256 kept as the fingerprint.
CODE_FINGERPRINT_HEX = 16
MAX_RUNS = 1_000_000
# Lists longer than this in a run's metrics are not kept in its record (100 runs must not fill the disk).
MAX_METRIC_LIST_LEN = 20_000
# Metric keys whose values depend on the machine, not on the flight; left out of bit-for-bit comparisons.
TIMING_KEY_PARTS: tuple[str, ...] = ("wall", "realtime", "elapsed", "cpu_s", "rss", "_us_per_", "per_frame_us",
                                     "time_split")
# Metric flags with which run_flight reports that it stopped early; such a run is recorded as failed (its metrics
# are kept in the record).
FLIGHT_FAILURE_FLAGS: tuple[str, ...] = ("crashed",)
INTERRUPTED_FLAG = "interrupted"  # Ctrl-C inside run_flight: the run is not recorded
# Metrics where larger is better (their worst run is the smallest); ``baseline_`` variants included.
HIGHER_IS_BETTER: frozenset[str] = frozenset({"heading_coverage", "nees_in_bounds_frac", "realtime_factor",
                                              "valid_frac", "frames"})
# Runs listed as the worst in the summary and report, ranked by this metric (NaN ranks worst).
N_WORST_RUNS = 10
WORST_BY_METRIC = "drift_mae_deg"
# Wind direction errors are meaningful only in wind at least this strong (issue 6).
WIND_DIR_MIN_WIND_M_S = 3.0
# Cause analysis of a missed goal: groups smaller than this are not compared; a parameter whose distribution
# differs between bad and good runs with a p-value below SIGNIFICANCE_P is reported as shared by the bad runs.
MIN_GROUP_RUNS = 2
SIGNIFICANCE_P = 0.05
WORST_FRACTION = 0.1  # "worst decile" fallback when all or no runs miss a goal
MAX_CATEGORIES_IN_FINDING = 3
# Issue 6 throughput goal: the 100 x 600 s campaign within 15 minutes on the reference (2-core) machine.
THROUGHPUT_GOAL_SIM_S = 100 * 600.0
THROUGHPUT_GOAL_WALL_S = 15 * 60.0
PEAK_RSS_GOAL_MB = 1024.0
NEES_CONFIDENCE = 0.95
# A local worker process that dies (segfault, out of memory) takes the pool down; the runs it may have been flying
# are then flown alone, one per fresh single-process pool, so that only the run that kills its process is blamed.
_STARTED_MARKER_FMT = ".started_{:05d}"
_STARTED_MARKER_GLOB = ".started_*"

VIRTUAL_PREFIX = "mc."
VIRTUAL_KEYS: frozenset[str] = frozenset({
    "mc.mean_agl_m", "mc.mean_airspeed_m_s",
    "mc.gnss_outage_start_s", "mc.gnss_outage_length_s", "mc.gnss_outage_start_frac", "mc.gnss_outage_length_frac",
    "mc.camera_focal_error_frac", "mc.camera_cx_error_px", "mc.camera_cy_error_px",
    "mc.camera_mount_roll_error_deg", "mc.camera_mount_pitch_error_deg", "mc.camera_mount_yaw_error_deg",
})
_MOUNT_KEYS = ("mc.camera_mount_roll_error_deg", "mc.camera_mount_pitch_error_deg", "mc.camera_mount_yaw_error_deg")


class InjectedFailure(RuntimeError):
    """Raised on purpose for the runs listed in a spec's ``fail_runs`` (test hook)."""


class FlightStopped(RuntimeError):
    """The flight returned metrics but says it did not fly to the end (a flag of FLIGHT_FAILURE_FLAGS)."""


# --------------------------------------------------------------------------------------------------------------
# Spec


@dataclass(frozen=True)
class Dist:
    """One parameter's distribution (see the module docstring); ``draw(rng)`` returns a plain Python value."""

    dist: Literal["uniform", "loguniform", "normal", "choice", "constant"]
    low: float | None = None
    high: float | None = None
    mean: float | None = None
    std: float | None = None
    values: tuple[Any, ...] | None = None
    weights: tuple[float, ...] | None = None
    value: Any = None

    def __post_init__(self) -> None:
        need = {"uniform": {"low", "high"}, "loguniform": {"low", "high"}, "normal": {"mean", "std", "low", "high"},
                "choice": {"values"}, "constant": {"value"}}[self.dist]
        allowed = need | ({"weights"} if self.dist == "choice" else set())
        for f in ("low", "high", "mean", "std", "values", "weights", "value"):
            v = getattr(self, f)
            require(v is not None or f not in need, f, f"required by dist = {self.dist!r}")
            require(v is None or f in allowed, f, f"not used by dist = {self.dist!r} (it takes {sorted(allowed)})")
        if self.low is not None and self.high is not None:
            require(self.low < self.high, "high", f"must be greater than low = {self.low}, got {self.high}")
        if self.dist == "loguniform":
            in_range(float(self.low or 0.0), 0.0, math.inf, "low", lo_open=True)
        if self.dist == "normal":
            in_range(float(self.std or 0.0), 0.0, math.inf, "std", lo_open=True)
            lo, hi, mu = float(self.low or 0.0), float(self.high or 0.0), float(self.mean or 0.0)
            require(lo <= mu <= hi, "mean", f"must lie within [low, high] = [{lo}, {hi}], got {mu}")
        if self.dist == "choice":
            vals = self.values or ()
            require(len(vals) >= 1, "values", "must hold at least one value")
            if self.weights is not None:
                w = self.weights
                require(len(w) == len(vals), "weights", f"must have one weight per value ({len(vals)}), got {len(w)}")
                require(all(x >= 0.0 for x in w) and sum(w) > 0.0, "weights", "must be >= 0 with a positive sum")

    def _f(self, name: str) -> float:
        v = getattr(self, name)
        assert v is not None, name  # guaranteed by __post_init__ for the fields a distribution uses
        return float(v)

    def draw(self, rng: np.random.Generator) -> Any:
        if self.dist == "uniform":
            return float(rng.uniform(self._f("low"), self._f("high")))
        if self.dist == "loguniform":
            return float(np.exp(rng.uniform(math.log(self._f("low")), math.log(self._f("high")))))
        if self.dist == "normal":
            mu, sd = self._f("mean"), self._f("std")
            a, b = (self._f("low") - mu) / sd, (self._f("high") - mu) / sd
            return float(sps.truncnorm.rvs(a, b, loc=mu, scale=sd, random_state=rng))
        if self.dist == "choice":
            vals = self.values or ()
            p = None if self.weights is None else np.asarray(self.weights, dtype=float) / float(sum(self.weights))
            return copy.deepcopy(vals[int(rng.choice(len(vals), p=p))])
        return copy.deepcopy(self.value)

    def extremes(self) -> list[Any]:
        """The values whose validity implies that of every draw (bounds of a range, every choice)."""
        if self.dist in ("uniform", "loguniform", "normal"):
            return [self._f("low"), self._f("high")]
        if self.dist == "choice":
            return list(self.values or ())
        return [self.value]


_Seed = Annotated[int, In(0, SEED_MAX)]
_NRuns = Annotated[int, In(1, MAX_RUNS)]
_RunIndices = Annotated[tuple[int, ...], In(0, MAX_RUNS)]


@dataclass(frozen=True)
class Goal(Validated):
    """An accuracy goal: ``stat`` over the (eligible) runs of per-run ``metric`` must be ``op`` ``threshold``.

    ``min_wind_m_s``: only runs whose scenario wind (``wind.speed_m_s``) is at least this count.  The fraction of
    runs meeting the goal counts each eligible run whose own value satisfies ``op threshold`` (failed runs and
    missing values do not).
    """

    name: str
    metric: str
    op: Literal["<=", ">="]
    threshold: float
    stat: Literal["median", "mean", "p95", "p05", "max", "min"] = "median"
    min_wind_m_s: Annotated[float, In(0.0, 100.0)] = 0.0
    description: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        require(bool(self.name.strip()), "name", "must not be empty")
        require(bool(self.metric.strip()), "metric", "must not be empty")

    def ok(self, value: float) -> bool:
        return math.isfinite(value) and (value <= self.threshold if self.op == "<=" else value >= self.threshold)


# The goals of issue 6 (over 100 seeded runs of 600 s).
DEFAULT_GOALS: tuple[Goal, ...] = (
    Goal("drift_mae_median", "drift_mae_deg", "<=", 0.3, "median", description="EKF drift MAE vs truth, median"),
    Goal("drift_mae_p95", "drift_mae_deg", "<=", 1.0, "p95", description="EKF drift MAE vs truth, p95 over runs"),
    Goal("heading_coverage", "heading_coverage", ">=", 0.99, "median", description="heading coverage"),
    Goal("wind_speed_rmse", "wind_speed_rmse_m_s", "<=", 0.3, "median", description="wind speed RMSE"),
    Goal("wind_dir_rmse", "wind_dir_rmse_deg", "<=", 5.0, "median", WIND_DIR_MIN_WIND_M_S,
         description="wind direction RMSE (wind >= 3 m/s)"),
    Goal("dr_error", "dr_error_pct_of_distance", "<=", 1.0, "median",
         description="dead-reckoning error in % of distance flown"),
    Goal("nees_in_bounds", "nees_in_bounds_frac", ">=", 0.90, "mean",
         description="fraction of steps whose NEES lies inside the 95 % chi-square interval"),
    Goal("peak_memory", "peak_rss_mb", "<=", PEAK_RSS_GOAL_MB, "max", description="worker peak memory (MB)"),
)


@dataclass(frozen=True)
class _SpecFile(Validated):
    """What a spec file holds (validated by :func:`common.config.build`)."""

    name: str
    description: str = ""
    base_scenario: str = "paper_sil"
    base_seed: _Seed = 0
    n_runs: _NRuns = 100
    duration_s: Annotated[float, In(0.0, 86_400.0, doc="each flight's length, s (0: the base scenario's)")] = 0.0
    runner: str = DEFAULT_RUNNER
    fail_runs: _RunIndices = ()
    crash_runs: _RunIndices = ()
    fixed: Any = field(default_factory=dict)
    params: Any = field(default_factory=dict)
    goals: tuple[Goal, ...] = DEFAULT_GOALS

    def __post_init__(self) -> None:
        super().__post_init__()
        require(bool(self.name.strip()), "name", "must not be empty")
        _check_runner(self.runner, "runner")
        require(isinstance(self.fixed, Mapping), "fixed", "must be a table of dotted keys")
        require(isinstance(self.params, Mapping), "params", "must be a table of dotted keys")
        for k in self.params:
            require(k not in self.fixed, f'params."{k}"', "also set in [fixed]")
        names = [g.name for g in self.goals]
        require(len(set(names)) == len(names), "goals", "goal names must be unique")


def _check_runner(runner: str, where: str) -> None:
    mod, sep, fn = runner.partition(":")
    require(bool(sep and mod and fn.isidentifier()), where, f"must be 'module:function', got {runner!r}")


@dataclass(frozen=True)
class MonteCarloSpec(Validated):
    """A validated campaign: base scenario, per-run distributions, goals (see the module docstring).

    ``camera`` is the nominal camera the ``mc.camera_*`` calibration-error keys perturb; ``duration_s`` is each
    flight's length (s).
    """

    name: str
    description: str
    base: Scenario
    camera: CameraConfig
    base_seed: _Seed
    n_runs: _NRuns
    duration_s: Annotated[float, In(0.0, 86_400.0, lo_open=True)]
    runner: str
    fixed: Mapping[str, Any]
    params: Mapping[str, Dist]
    goals: tuple[Goal, ...]
    fail_runs: _RunIndices = ()
    crash_runs: _RunIndices = ()
    source: str = ""

    def with_options(self, *, n_runs: int | None = None, base_seed: int | None = None,
                     duration_s: float | None = None) -> MonteCarloSpec:
        """This spec with the command line's ``-n``, ``--seed``, ``--duration`` applied (validated)."""
        n = self.n_runs if n_runs is None else n_runs
        seed = self.base_seed if base_seed is None else base_seed
        dur = self.duration_s if duration_s is None else duration_s
        return dataclasses.replace(self, n_runs=n, base_seed=seed, duration_s=float(dur))


def _resolve_scenario(name: str, spec_dir: Path | None) -> Path:
    p = scenario_path(name)
    if not p.is_absolute() and spec_dir is not None and not p.exists() and (spec_dir / p).exists():
        return spec_dir / p
    return p


def _spec_from_file(f: _SpecFile, base: Scenario, camera: CameraConfig, where: str, source: str) -> MonteCarloSpec:
    params: dict[str, Dist] = {}
    for key, table in f.params.items():
        try:
            params[str(key)] = build(Dist, table, f'params."{key}"')
        except ConfigError as e:
            raise ConfigError(f"{where}: {e.field_path}", str(e).split(": ", 1)[1]) from None
    spec = MonteCarloSpec(
        name=f.name, description=f.description, base=base, camera=camera, base_seed=f.base_seed, n_runs=f.n_runs,
        duration_s=float(f.duration_s or base.duration_s), runner=f.runner, fixed=copy.deepcopy(dict(f.fixed)),
        params=params, goals=f.goals, fail_runs=f.fail_runs, crash_runs=f.crash_runs, source=source)
    _validate_against_scenario(spec, where)
    return spec


def _validate_against_scenario(spec: MonteCarloSpec, where: str) -> None:
    """Every fixed value and every extreme of every distribution must give a valid scenario (alone)."""
    prefix = f"{where}: " if where else ""
    keys = set(spec.params) | set(spec.fixed)
    for key in sorted(k for k in keys if k.startswith(VIRTUAL_PREFIX)):
        if key not in VIRTUAL_KEYS:
            sect = "params" if key in spec.params else "fixed"
            raise ConfigError(f'{prefix}{sect}."{key}"',
                              f"unknown virtual key (known: {', '.join(sorted(VIRTUAL_KEYS))})")
    for a, b in (("start_s", "length_s"), ("start_frac", "length_frac")):
        ka, kb = f"mc.gnss_outage_{a}", f"mc.gnss_outage_{b}"
        if (ka in keys) != (kb in keys):
            missing = kb if ka in keys else ka
            raise ConfigError(f'{prefix}params."{missing}"', f"needed together with {ka if ka in keys else kb}")
    if "mc.gnss_outage_start_s" in keys and "mc.gnss_outage_start_frac" in keys:
        raise ConfigError(f'{prefix}params."mc.gnss_outage_start_frac"', "give the outage in seconds or as fractions, "
                          "not both")
    if "mc.gnss_outage_start_s" in keys or "mc.gnss_outage_start_frac" in keys:
        if "sensors.gnss.outages" in keys:
            raise ConfigError(f'{prefix}params."sensors.gnss.outages"', "set together with mc.gnss_outage_*")
    try:
        base_tree = _apply(spec, dict(spec.fixed))
    except ConfigError as e:
        raise ConfigError(f"{prefix}fixed", f"rejected by the scenario: {e}") from None
    del base_tree
    neutral = {k: d.extremes()[0] for k, d in spec.params.items()}
    for key, d in spec.params.items():
        for value in d.extremes():
            trial = {**spec.fixed, **neutral, key: value}
            try:
                _apply(spec, trial)
            except ConfigError as e:
                raise ConfigError(f'{prefix}params."{key}"', f"value {value!r} rejected by the scenario: {e}") from None


def load_spec(path: str | Path | None = None, *, base_scenario: str | Path | None = None) -> MonteCarloSpec:
    """Read and validate a spec file (default ``config/montecarlo/default.toml``); a bare name is a file in
    ``config/montecarlo``.  ``base_scenario`` replaces the spec's (``--scenario``).  Errors name the file and
    field."""
    p = Path(path) if path is not None else DEFAULT_SPEC
    if p.suffix == "" and len(p.parts) == 1:
        p = MONTECARLO_DIR / f"{p.name}.toml"
    raw = read_toml(p)
    try:
        f = build(_SpecFile, raw, "")
    except ConfigError as e:
        raise ConfigError(f"{p}: {e.field_path}", str(e).split(": ", 1)[1]) from None
    scn_name = str(base_scenario) if base_scenario is not None else f.base_scenario
    base = load_scenario(_resolve_scenario(scn_name, p.parent))
    camera = load_gsoe_config()[0].camera
    return _spec_from_file(f, base, camera, str(p), str(p))


def spec_to_dict(spec: MonteCarloSpec) -> dict[str, Any]:
    """Self-contained plain form (base scenario and camera included) stored in ``campaign.json``."""
    return {
        "name": spec.name, "description": spec.description, "base_scenario": _plain(to_dict(spec.base)),
        "camera": _plain(to_dict(spec.camera)), "base_seed": spec.base_seed, "n_runs": spec.n_runs,
        "duration_s": spec.duration_s, "runner": spec.runner, "fixed": _plain(spec.fixed),
        "params": {k: {f: v for f, v in _plain(to_dict(d)).items() if v is not None} for k, d in spec.params.items()},
        "goals": [_plain(to_dict(g)) for g in spec.goals], "fail_runs": list(spec.fail_runs),
        "crash_runs": list(spec.crash_runs), "source": spec.source,
    }


def spec_from_dict(data: Mapping[str, Any], where: str = CAMPAIGN_FILE) -> MonteCarloSpec:
    """Inverse of :func:`spec_to_dict` (validated again)."""
    try:
        base = build_scenario(data["base_scenario"])
        camera = build(CameraConfig, data["camera"], "camera")
    except KeyError as e:
        raise ConfigError(f"{where}: spec.{e.args[0]}", "missing") from None
    file_keys = {f.name for f in dataclasses.fields(_SpecFile)} - {"base_scenario"}
    try:
        f = build(_SpecFile, {k: v for k, v in data.items() if k in file_keys}, "spec")
    except ConfigError as e:
        raise ConfigError(f"{where}: {e.field_path}", str(e).split(": ", 1)[1]) from None
    return _spec_from_file(f, base, camera, where, str(data.get("source", where)))


# --------------------------------------------------------------------------------------------------------------
# Per-run draws and scenarios


def _key_stream(key: str) -> int:
    return zlib.crc32(key.encode("utf-8"))


def draw_run_params(spec: MonteCarloSpec, base_seed: int, i: int) -> dict[str, Any]:
    """The parameters of run ``i``: one draw per spec key, each from its own generator
    ``np.random.default_rng([base_seed, i, crc32(key)])``, so a run's draws depend only on ``(base_seed, i)`` and
    adding or removing one key leaves the others' draws unchanged."""
    require(0 <= i < MAX_RUNS, "run index", f"must be in [0, {MAX_RUNS}), got {i}")
    return {key: d.draw(np.random.default_rng([base_seed, i, _key_stream(key)])) for key, d in spec.params.items()}


def run_seed(base_seed: int, i: int) -> int:
    """The flight seed of run ``i`` (the ``--seed`` of ``gsoe sim``): a 32-bit word of ``SeedSequence([base_seed,
    i])``'s first child, independent of the parameter draws."""
    child = np.random.SeedSequence([base_seed, i]).spawn(1)[0]
    return int(child.generate_state(1, dtype=np.uint32)[0])


def _scaled_heights(tree_mission: Mapping[str, Any], ground_m: float, mean_agl_m: float) -> dict[str, Any]:
    wps = tree_mission["waypoints"]
    agl = [w["height_m"] - ground_m for w in wps]
    k = mean_agl_m / (sum(agl) / len(agl))
    start = dict(tree_mission["start"])
    start["height_m"] = ground_m + (start["height_m"] - ground_m) * k
    return {"mission.start": start,
            "mission.waypoints": [{**w, "height_m": ground_m + a * k} for w, a in zip(wps, agl, strict=True)]}


def _virtual_overrides(spec: MonteCarloSpec, values: Mapping[str, Any], duration_s: float,
                       mission: Mapping[str, Any]) -> dict[str, Any]:
    """Real scenario overrides for the ``mc.*`` keys among ``values`` (``mission`` after the plain overrides)."""
    base = spec.base
    out: dict[str, Any] = {}
    if "mc.mean_agl_m" in values:
        ground = base.terrain.ground_elevation_m
        scaled = _scaled_heights(mission, ground, float(values["mc.mean_agl_m"]))
        mission = {**mission, "start": scaled["mission.start"], "waypoints": scaled["mission.waypoints"]}
    if "mc.mean_airspeed_m_s" in values:
        wps = mission["waypoints"]
        k = float(values["mc.mean_airspeed_m_s"]) / (sum(w["airspeed_m_s"] for w in wps) / len(wps))
        mission = {**mission, "start": {**mission["start"], "airspeed_m_s": mission["start"]["airspeed_m_s"] * k},
                   "waypoints": [{**w, "airspeed_m_s": w["airspeed_m_s"] * k} for w in wps]}
    if "mc.mean_agl_m" in values or "mc.mean_airspeed_m_s" in values:
        out["mission.start"] = mission["start"]
        out["mission.waypoints"] = mission["waypoints"]
    if "mc.gnss_outage_start_s" in values:
        out["sensors.gnss.outages"] = [{"start_s": float(values["mc.gnss_outage_start_s"]),
                                        "length_s": float(values["mc.gnss_outage_length_s"])}]
    if "mc.gnss_outage_start_frac" in values:
        out["sensors.gnss.outages"] = [{"start_s": float(values["mc.gnss_outage_start_frac"]) * duration_s,
                                        "length_s": float(values["mc.gnss_outage_length_frac"]) * duration_s}]
    cam_keys = [k for k in values if k.startswith("mc.camera_")]
    if cam_keys:
        cam = {**_plain(to_dict(spec.camera)), **base.camera.gsoe_overrides.get("camera", {})}
        est: dict[str, Any] = {}
        if "mc.camera_focal_error_frac" in values:
            k = 1.0 + float(values["mc.camera_focal_error_frac"])
            est["fx_px"], est["fy_px"] = cam["fx_px"] * k, cam["fy_px"] * k
        if "mc.camera_cx_error_px" in values:
            est["cx_px"] = cam["cx_px"] + float(values["mc.camera_cx_error_px"])
        if "mc.camera_cy_error_px" in values:
            est["cy_px"] = cam["cy_px"] + float(values["mc.camera_cy_error_px"])
        if any(k in values for k in _MOUNT_KEYS):
            est["mount_rpy_deg"] = [float(a) + float(values.get(k, 0.0))
                                    for a, k in zip(cam["mount_rpy_deg"], _MOUNT_KEYS, strict=True)]
        # Keep the other gsoe_overrides tables; build() then validates the estimator camera's ranges.
        for name, v in est.items():
            out[f"camera.gsoe_overrides.camera.{name}"] = v
    return out


def _apply(spec: MonteCarloSpec, values: Mapping[str, Any], duration_s: float | None = None) -> Scenario:
    dur = spec.duration_s if duration_s is None else duration_s
    plain = {k: v for k, v in values.items() if not k.startswith(VIRTUAL_PREFIX)}
    virtual = {k: v for k, v in values.items() if k.startswith(VIRTUAL_PREFIX)}
    scn = scenario_with_overrides(spec.base, {**plain, "duration_s": dur})
    if not virtual:
        return scn
    mission = _plain(to_dict(scn.mission))
    return scenario_with_overrides(scn, _virtual_overrides(spec, virtual, dur, mission))


def scenario_for_run(spec: MonteCarloSpec, params: Mapping[str, Any], duration_s: float | None = None) -> Scenario:
    """The validated scenario of a run: base + ``[fixed]`` + drawn ``params`` (virtual keys expanded), flown for
    ``duration_s`` (default the spec's)."""
    return _apply(spec, {**spec.fixed, **params}, duration_s)


def scenario_features(scn: Scenario) -> dict[str, Any]:
    """Summary quantities of a run's scenario that the report plots errors against."""
    wps = scn.mission.waypoints
    ground = scn.terrain.ground_elevation_m
    outages = scn.sensors.gnss.outages
    return {
        "wind_speed_m_s": scn.wind.speed_m_s,
        "wind_from_deg": scn.wind.from_deg,
        "wind_ref_height_m": scn.wind.ref_height_m,
        "mean_agl_m": float(np.mean([w.height_m - ground for w in wps])),
        "mean_airspeed_m_s": float(np.mean([w.airspeed_m_s for w in wps])),
        "texture": scn.terrain.texture,
        "gnss_outage_s": float(sum(min(o.end_s, scn.duration_s) - o.start_s for o in outages
                                   if o.start_s < scn.duration_s)),
    }


def write_run_scenario(spec: MonteCarloSpec, params: Mapping[str, Any], duration_s: float, path: Path) -> Path:
    """Write the complete scenario of a run as a scenario TOML file (``gsoe sim FILE`` flies it)."""
    import tomli_w

    scn = scenario_for_run(spec, params, duration_s)
    tree = _plain(to_dict(scn))
    header = (f"# Monte Carlo run of campaign {spec.name!r}: the base scenario {spec.base.name!r} with the run's "
              f"drawn parameters applied.\n# Parameters: {json.dumps(_plain(params), sort_keys=True)}\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write_text(path, header + tomli_w.dumps(tree))
    return path


# --------------------------------------------------------------------------------------------------------------
# One run


@dataclass
class RunRecord:
    """Everything about one flown (or failed) run; ``metrics`` is the flat ``metrics.json`` of ``gsoe sim``."""

    index: int
    base_seed: int
    run_seed: int
    duration_s: float
    status: Literal["ok", "failed"]
    params: dict[str, Any] = field(default_factory=dict)
    features: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    error: str = ""
    traceback: str = ""
    wall_s: float = math.nan
    peak_rss_mb: float = math.nan
    worker: str = ""
    dropped_keys: list[str] = field(default_factory=list)
    #: :func:`code_fingerprint` of the code that flew it ("" in records written before it existed)
    code: str = ""

    def to_dict(self) -> dict[str, Any]:
        return _plain(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RunRecord:
        known = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in data.items() if k in known}
        for k in ("wall_s", "peak_rss_mb"):
            if kw.get(k) is None:
                kw[k] = math.nan
        return cls(**kw)

    def deterministic(self) -> dict[str, Any]:
        """The parts that must be identical when a run is re-flown (timing and host left out)."""
        return {"index": self.index, "base_seed": self.base_seed, "run_seed": self.run_seed,
                "duration_s": self.duration_s, "status": self.status, "params": self.params,
                "features": self.features, "error": self.error,
                "metrics": {k: v for k, v in self.metrics.items() if not is_timing_key(k)}}


@functools.cache
def code_fingerprint() -> str:
    """First :data:`CODE_FINGERPRINT_HEX` hex digits of the SHA-256 of the files under :data:`CODE_PACKAGES` (their
    paths relative to the tree and their bytes, in sorted order; compiled caches left out): two runs with the same
    seed and parameters fly the same flight when their fingerprints match (and the libraries are the same)."""
    root = Path(__file__).resolve().parent.parent  # the tree holding the packages (and config/ in a checkout)
    files = sorted(f for pkg in CODE_PACKAGES for f in (root / pkg).rglob("*")
                   if f.is_file() and "__pycache__" not in f.parts and f.suffix != ".pyc")
    h = hashlib.sha256()
    for f in files:
        h.update(f.relative_to(root).as_posix().encode())
        h.update(b"\0")
        h.update(f.read_bytes())
    return h.hexdigest()[:CODE_FINGERPRINT_HEX]


def is_timing_key(key: str) -> bool:
    return any(part in key for part in TIMING_KEY_PARTS)


def _peak_rss_mb() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return float(peak) / (1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0)


def _load_runner(runner: str) -> Callable[..., Mapping[str, Any]]:
    mod, _, fn = runner.partition(":")
    return getattr(importlib.import_module(mod), fn)


def _sanitize_metrics(metrics: Mapping[str, Any]) -> tuple[dict[str, Any], list[str]]:
    out: dict[str, Any] = {}
    dropped: list[str] = []
    for k, v in metrics.items():
        if isinstance(v, np.ndarray):
            v = v.tolist()
        if isinstance(v, list | tuple) and len(v) > MAX_METRIC_LIST_LEN:
            dropped.append(str(k))
            continue
        try:
            out[str(k)] = _plain(v)
        except TypeError:
            dropped.append(str(k))
    return out, dropped


def run_one(spec: MonteCarloSpec | str | Path, base_seed: int, i: int, duration_s: float | None = None, *,
            out_dir: Path | None = None, started_marker: Path | None = None) -> RunRecord:
    """Fly run ``i`` of a campaign and return its record; never raises for a failing flight (status ``failed``
    with the traceback).  ``out_dir``: where the flight writes its logs and plots (None: nowhere).
    ``started_marker``: a file touched when the run starts (the local pool's crash attribution)."""
    t0 = time.perf_counter()
    if started_marker is not None:
        started_marker.touch()
    sp = spec if isinstance(spec, MonteCarloSpec) else load_spec(spec)
    dur = float(sp.duration_s if duration_s is None else duration_s)
    rec = RunRecord(index=i, base_seed=base_seed, run_seed=run_seed(base_seed, i), duration_s=dur, status="failed",
                    worker=f"{socket.gethostname()}:{os.getpid()}", code=code_fingerprint())
    try:
        rec.params = _plain(draw_run_params(sp, base_seed, i))
        scn = scenario_for_run(sp, rec.params, dur)
        rec.features = _plain(scenario_features(scn))
        if i in sp.fail_runs:
            raise InjectedFailure(f"run {i} is listed in the spec's fail_runs (test hook)")
        if i in sp.crash_runs:
            log.error("run %d is listed in the spec's crash_runs (test hook): exiting the worker abruptly", i)
            os._exit(70)
        result = _load_runner(sp.runner)(scn, seed=rec.run_seed, duration_s=dur, out_dir=out_dir, progress=False)
        if not isinstance(result, Mapping):
            raise TypeError(f"{sp.runner} returned {type(result).__name__}, expected a mapping of metrics")
        if result.get(INTERRUPTED_FLAG):
            # Not a result: no record, so that --resume flies the run again.
            raise KeyboardInterrupt(f"run {i} was interrupted")
        rec.metrics, rec.dropped_keys = _sanitize_metrics(result)
        for flag in FLIGHT_FAILURE_FLAGS:
            if result.get(flag):
                raise FlightStopped(f"the flight reports {flag}: {result[flag]}")
        rec.status = "ok"
    except Exception as e:  # noqa: BLE001 - a failing run is recorded, never fatal to the campaign
        rec.error = f"{type(e).__name__}: {e}"
        rec.traceback = traceback.format_exc()
        log.warning("run %d failed: %s", i, rec.error)
    rec.wall_s = time.perf_counter() - t0
    rec.peak_rss_mb = _peak_rss_mb()
    return rec


# --------------------------------------------------------------------------------------------------------------
# Files


def _plain(obj: Any) -> Any:
    """JSON-ready copy: numpy scalars/arrays to Python, tuples to lists, non-finite floats to None."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        f = float(obj)
        return f if math.isfinite(f) else None
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in a run record")


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as JSON atomically (temporary file, then ``os.replace``)."""
    _atomic_write_text(path, json.dumps(_plain(data), indent=1, allow_nan=False) + "\n")


def run_path(out_dir: Path, i: int) -> Path:
    return Path(out_dir) / RUNS_DIR / f"run_{i:05d}.json"


def write_record(out_dir: Path, rec: RunRecord) -> Path:
    p = run_path(out_dir, rec.index)
    p.parent.mkdir(parents=True, exist_ok=True)
    write_json(p, rec.to_dict())
    return p


def read_record(path: Path) -> RunRecord:
    try:
        return RunRecord.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
    except (json.JSONDecodeError, TypeError) as e:
        raise ConfigError(str(path), f"not a run record: {e}") from None


def read_records(out_dir: Path, n_runs: int | None = None) -> list[RunRecord]:
    """All run records of a campaign folder (indices below ``n_runs`` when given), by index."""
    recs = [read_record(p) for p in sorted((Path(out_dir) / RUNS_DIR).glob("run_*.json"))]
    return [r for r in recs if n_runs is None or r.index < n_runs]


def finished_indices(out_dir: Path) -> set[int]:
    out = set()
    for p in (Path(out_dir) / RUNS_DIR).glob("run_*.json"):
        with contextlib.suppress(ValueError):
            out.add(int(p.stem.split("_")[1]))
    return out


def read_campaign(out_dir: Path) -> dict[str, Any] | None:
    p = Path(out_dir) / CAMPAIGN_FILE
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ConfigError(str(p), f"not valid JSON: {e}") from None


def load_campaign_spec(out_dir: Path) -> MonteCarloSpec:
    """The spec a campaign folder was flown with (from its ``campaign.json``)."""
    camp = read_campaign(out_dir)
    if camp is None:
        raise ConfigError(str(Path(out_dir) / CAMPAIGN_FILE), "file not found (not a campaign folder)")
    return spec_from_dict(camp["spec"], str(Path(out_dir) / CAMPAIGN_FILE))


# --------------------------------------------------------------------------------------------------------------
# Campaign


@dataclass
class CampaignResult:
    out_dir: Path
    flown: list[int]
    skipped: list[int]
    failed: list[int]
    wall_s: float
    backend: str
    workers: int


def default_workers() -> int:
    """All cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _failed_record(spec: MonteCarloSpec, i: int, duration_s: float, error: str, tb: str = "") -> RunRecord:
    rec = RunRecord(index=i, base_seed=spec.base_seed, run_seed=run_seed(spec.base_seed, i), duration_s=duration_s,
                    status="failed", error=error, traceback=tb)
    with contextlib.suppress(Exception):
        rec.params = _plain(draw_run_params(spec, spec.base_seed, i))
        rec.features = _plain(scenario_features(scenario_for_run(spec, rec.params, duration_s)))
    return rec


def _run_serial(spec: MonteCarloSpec, todo: Sequence[int], emit: Callable[[RunRecord], None]) -> None:
    for i in todo:
        emit(run_one(spec, spec.base_seed, i, spec.duration_s))


def _pool(workers: int) -> cf.ProcessPoolExecutor:
    # 'spawn': fresh interpreters, safe with OpenCV's and JSBSim's threads and state (no fork of a live process).
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))


def _run_local(spec: MonteCarloSpec, todo: Sequence[int], workers: int, out_dir: Path,
               emit: Callable[[RunRecord], None]) -> None:
    runs = Path(out_dir) / RUNS_DIR
    try:
        _run_local_pools(spec, todo, workers, runs, emit)
    finally:
        for m in runs.glob(_STARTED_MARKER_GLOB):
            m.unlink(missing_ok=True)


def _run_local_pools(spec: MonteCarloSpec, todo: Sequence[int], workers: int, runs: Path,
                     emit: Callable[[RunRecord], None]) -> None:
    pending = list(todo)
    while pending:
        markers = {i: runs / _STARTED_MARKER_FMT.format(i) for i in pending}
        for m in markers.values():
            m.unlink(missing_ok=True)
        done: set[int] = set()
        pool = _pool(min(workers, len(pending)))
        try:
            futs = {pool.submit(run_one, spec, spec.base_seed, i, spec.duration_s, started_marker=markers[i]): i
                    for i in pending}
            broken = False
            for fut in cf.as_completed(futs):
                i = futs[fut]
                try:
                    rec = fut.result()
                except BrokenProcessPool:
                    broken = True
                    continue
                done.add(i)
                markers[i].unlink(missing_ok=True)
                emit(rec)
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown(wait=True)
        pending = [i for i in pending if i not in done]
        if not broken:
            break
        suspects = [i for i in pending if markers[i].exists()]
        log.warning("a worker process died; flying the %d run(s) it may have been flying alone: %s",
                    len(suspects), suspects)
        for i in suspects:
            markers[i].unlink(missing_ok=True)
            with _pool(1) as solo:
                try:
                    rec = solo.submit(run_one, spec, spec.base_seed, i, spec.duration_s).result()
                except BrokenProcessPool as e:
                    rec = _failed_record(spec, i, spec.duration_s,
                                         f"WorkerDied: the worker process flying run {i} ended abruptly "
                                         "(crash in native code, out of memory, or os._exit)", repr(e))
            emit(rec)
            pending.remove(i)


def _run_dask(spec: MonteCarloSpec, todo: Sequence[int], scheduler: str, emit: Callable[[RunRecord], None]) -> int:
    from distributed import Client, as_completed

    with Client(scheduler) as client:
        n_workers = len(client.scheduler_info().get("workers", {}))
        log.info("Dask scheduler %s with %d workers", scheduler, n_workers)
        futs = {client.submit(run_one, spec, spec.base_seed, i, spec.duration_s, pure=False, retries=0): i
                for i in todo}
        index_of = {f.key: i for f, i in futs.items()}
        try:
            for fut in as_completed(list(futs)):
                i = index_of[fut.key]
                try:
                    rec = fut.result()
                except KeyboardInterrupt:
                    log.warning("run %d was interrupted on its worker; not recorded (--resume flies it again)", i)
                    continue
                except Exception as e:  # noqa: BLE001 - e.g. KilledWorker: the run killed its worker
                    rec = _failed_record(spec, i, spec.duration_s, f"{type(e).__name__}: {e}",
                                         "".join(traceback.format_exception(e)))
                emit(rec)
        except BaseException:
            client.cancel(list(futs))
            raise
    return n_workers


def _check_campaign_folder(out_dir: Path, spec: MonteCarloSpec, resume: bool) -> None:
    camp = read_campaign(out_dir)
    finished = finished_indices(out_dir)
    if not resume:
        if camp is not None or finished:
            raise ConfigError(str(out_dir), "already holds a campaign; pass --resume to complete it or choose "
                              "another --out")
        return
    if camp is None:
        if finished:
            raise ConfigError(str(out_dir / CAMPAIGN_FILE), "missing although runs exist; cannot resume safely")
        return
    old = camp.get("spec", {})
    new = spec_to_dict(spec)
    for key in ("base_scenario", "camera", "base_seed", "duration_s", "runner", "fixed", "params",
                "fail_runs", "crash_runs"):
        if _plain(old.get(key)) != _plain(new.get(key)):
            raise ConfigError(f"{out_dir / CAMPAIGN_FILE}: spec.{key}",
                              "differs from this campaign's; resume with the same spec, seed and duration, or "
                              "choose another --out")


def run_campaign(spec: MonteCarloSpec, out_dir: str | Path, *, indices: Iterable[int] | None = None,
                 scheduler: str | None = None, workers: int | None = None, resume: bool = False,
                 retry_failed: bool = False, progress: bool = True) -> CampaignResult:
    """Fly the runs of ``spec`` (all ``n_runs``, or ``indices``) into ``out_dir``, then write ``summary.json``
    (``report.html`` is :func:`sim.mc_report.write_report`'s, from the folder).

    ``scheduler``: address of a Dask scheduler (``tcp://HOST:PORT``); otherwise a local process pool of
    ``workers`` processes (default all cores; 0 flies the runs in this process, for debugging).  ``resume``: skip
    runs whose record exists (the folder must hold a campaign of the same spec, seed and duration);
    ``retry_failed`` (with ``resume``): fly the runs recorded as failed again.
    """
    require(resume or not retry_failed, "retry_failed", "only makes sense with resume")
    out = Path(out_dir)
    _check_campaign_folder(out, spec, resume)
    (out / RUNS_DIR).mkdir(parents=True, exist_ok=True)
    wanted = sorted(set(range(spec.n_runs) if indices is None else indices))
    for i in wanted:
        require(0 <= i < spec.n_runs, "indices", f"run index {i} outside [0, {spec.n_runs})")
    have = finished_indices(out) if resume else set()
    if retry_failed:
        have -= {r.index for r in read_records(out) if r.status != "ok"}
    todo = [i for i in wanted if i not in have]
    skipped = [i for i in wanted if i in have]
    camp = read_campaign(out) or {"format": CAMPAIGN_FORMAT, "sessions": []}
    camp["spec"] = spec_to_dict(spec)
    write_json(out / CAMPAIGN_FILE, camp)

    n_workers = default_workers() if workers is None else workers
    require(n_workers >= 0, "workers", f"must be >= 0, got {n_workers}")
    backend = f"dask {scheduler}" if scheduler else ("serial" if n_workers == 0 else "local pool")
    log.info("campaign %r: %d runs to fly (%d already done) of %.0f s each, %s", spec.name, len(todo), len(skipped),
             spec.duration_s, backend)
    flown: list[int] = []
    failed: list[int] = []
    sim_s_flown = [0.0]
    host = host_reference()     # the session's throughput is this host's (common.hostref)
    t0 = time.perf_counter()
    started = datetime.now(UTC).isoformat(timespec="seconds")
    bar = _progress_bar(len(todo), progress)

    def emit(rec: RunRecord) -> None:
        write_record(out, rec)
        flown.append(rec.index)
        if rec.status != "ok":
            failed.append(rec.index)
        else:
            v = metric_value(rec, "sim_s")
            sim_s_flown[0] += v if math.isfinite(v) else rec.duration_s
        bar.update(1)
        bar.set_postfix(failed=len(failed), refresh=False)

    try:
        if todo:
            if scheduler:
                n_workers = _run_dask(spec, todo, scheduler, emit)
            elif n_workers == 0:
                _run_serial(spec, todo, emit)
            else:
                _run_local(spec, todo, n_workers, out, emit)
    finally:
        bar.close()
        wall = time.perf_counter() - t0
        camp["sessions"].append({"started_utc": started, "wall_s": wall, "flown": len(flown),
                                 "failed": len(failed), "sim_s": sim_s_flown[0], "backend": backend,
                                 "workers": n_workers, "code": code_fingerprint(), "host": host})
        write_json(out / CAMPAIGN_FILE, camp)
    write_summary(out, spec)
    return CampaignResult(out, sorted(flown), skipped, sorted(failed), wall, backend, n_workers)


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def set_postfix(self, **kw: Any) -> None:
        pass

    def close(self) -> None:
        pass


def _progress_bar(total: int, enabled: bool) -> Any:
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc="montecarlo", unit="run", dynamic_ncols=True)


def refly(out_dir: str | Path, i: int, *, spec: MonteCarloSpec | None = None, keep_outputs: bool = True
          ) -> tuple[RunRecord, list[str] | None]:
    """Re-fly run ``i`` of the campaign in ``out_dir`` alone (its spec from ``campaign.json`` unless given), with
    its logs and plots in ``out_dir/reflown/run_0000i`` (``keep_outputs``; the outputs of an earlier re-flight
    there are moved to ``run_0000i.old1``, ``.old2``, ...).  Returns the record and the list of fields that differ
    from the campaign's record of the run (None when there is none)."""
    out = Path(out_dir)
    sp = spec if spec is not None else load_campaign_spec(out)
    require(0 <= i < MAX_RUNS, "only", f"run index must be in [0, {MAX_RUNS}), got {i}")
    run_dir = out / "reflown" / f"run_{i:05d}"
    if run_dir.is_dir() and any(run_dir.iterdir()):
        # an earlier re-flight's logs: kept beside, since the CSV writers would append to them
        k = 1
        while run_dir.with_name(f"{run_dir.name}.old{k}").exists():
            k += 1
        run_dir.rename(run_dir.with_name(f"{run_dir.name}.old{k}"))
        log.info("re-fly of run %d: the previous outputs moved to %s.old%d", i, run_dir.name, k)
    run_dir.mkdir(parents=True, exist_ok=True)
    rec = run_one(sp, sp.base_seed, i, sp.duration_s, out_dir=run_dir if keep_outputs else None)
    write_json(run_dir / "record.json", rec.to_dict())
    orig = run_path(out, i)
    if not orig.exists():
        return rec, None
    a, b = read_record(orig).deterministic(), RunRecord.from_dict(rec.to_dict()).deterministic()
    return rec, _diff(a, b)


def _diff(a: Any, b: Any, path: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k, "<missing>"), b.get(k, "<missing>"), f"{path}.{k}" if path else str(k))
        return out
    return [] if a == b else [path]


def rerun_commands(out_dir: Path, spec: MonteCarloSpec, rec: RunRecord, scenario_file: Path | None) -> list[str]:
    """Shell commands that re-fly a run: ``gsoe sim`` on the run's scenario file (when the runner is the
    simulator's) and ``gsoe montecarlo --only``."""
    import shlex

    cmds = []
    if scenario_file is not None and spec.runner == DEFAULT_RUNNER:
        cmds.append(f"gsoe sim {shlex.quote(str(scenario_file))} --seed {rec.run_seed} --duration {rec.duration_s:g} "
                    f"--out {shlex.quote(str(out_dir / 'reflown' / f'sim_{rec.index:05d}'))}")
    cmds.append(f"gsoe montecarlo --only {rec.index} --out {shlex.quote(str(out_dir))}")
    return cmds


# --------------------------------------------------------------------------------------------------------------
# Aggregation


def metric_value(rec: RunRecord, key: str) -> float:
    """A run's numeric figure ``key`` (from its metrics, else the record: ``wall_s``, ``peak_rss_mb``); NaN when
    missing, non-numeric or the run failed."""
    if rec.status != "ok":
        return math.nan
    v = rec.metrics.get(key, getattr(rec, key, None) if key in ("wall_s", "peak_rss_mb") else None)
    if isinstance(v, bool) or not isinstance(v, int | float):
        return math.nan
    return float(v)


def _higher_is_better(key: str) -> bool:
    return key.removeprefix("baseline_") in HIGHER_IS_BETTER


def _stat(values: np.ndarray, stat: str) -> float:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return math.nan
    fn: dict[str, Callable[[np.ndarray], float]] = {
        "median": lambda x: float(np.median(x)), "mean": lambda x: float(np.mean(x)),
        "p95": lambda x: float(np.percentile(x, 95)), "p05": lambda x: float(np.percentile(x, 5)),
        "max": lambda x: float(np.max(x)), "min": lambda x: float(np.min(x))}
    return fn[stat](v)


def metric_stats(records: Sequence[RunRecord], key: str) -> dict[str, Any]:
    """Mean, median, p05, p95, min, max over runs, and the worst run (largest; smallest for higher-is-better)."""
    vals = np.array([metric_value(r, key) for r in records], dtype=float)
    idx = np.array([r.index for r in records])
    ok = np.isfinite(vals)
    out: dict[str, Any] = {s: _stat(vals, s) for s in ("mean", "median", "p05", "p95", "min", "max")}
    out["n"] = int(ok.sum())
    out["n_missing"] = int((~ok).sum())
    out["higher_is_better"] = _higher_is_better(key)
    if ok.any():
        j = int(np.argmin(np.where(ok, vals, np.inf)) if out["higher_is_better"]
                else np.argmax(np.where(ok, vals, -np.inf)))
        out["worst"], out["worst_run"] = float(vals[j]), int(idx[j])
    else:
        out["worst"], out["worst_run"] = math.nan, None
    return out


def _scalar_metric_keys(records: Sequence[RunRecord]) -> list[str]:
    keys: set[str] = set()
    for r in records:
        for k, v in r.metrics.items():
            if isinstance(v, int | float) and not isinstance(v, bool):
                keys.add(k)
    return sorted(keys)


def _wind(rec: RunRecord) -> float:
    v = rec.features.get("wind_speed_m_s")
    return float(v) if isinstance(v, int | float) else math.nan


def goal_results(records: Sequence[RunRecord], goals: Sequence[Goal]) -> list[dict[str, Any]]:
    """Each goal: the statistic over eligible runs, whether it is met, the fraction of eligible runs meeting the
    threshold on their own, and the indices of those that do not."""
    out = []
    for g in goals:
        elig = [r for r in records if not (g.min_wind_m_s > 0.0 and not _wind(r) >= g.min_wind_m_s)]
        vals = np.array([metric_value(r, g.metric) for r in elig], dtype=float)
        value = _stat(vals, g.stat)
        ok_runs = [g.ok(v) for v in vals]
        out.append({
            "name": g.name, "description": g.description, "metric": g.metric, "stat": g.stat, "op": g.op,
            "threshold": g.threshold, "min_wind_m_s": g.min_wind_m_s, "value": value,
            "met": bool(g.ok(value)), "n_eligible": len(elig), "n_with_value": int(np.isfinite(vals).sum()),
            "frac_runs_meeting": float(np.mean(ok_runs)) if elig else math.nan,
            "bad_runs": [r.index for r, ok in zip(elig, ok_runs, strict=True) if not ok],
        })
    return out


def _numeric_param(values: list[Any]) -> bool:
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)


def parameter_effects(records: Sequence[RunRecord], bad: Sequence[bool]) -> list[dict[str, Any]]:
    """Which drawn parameters the ``bad`` runs share, most significant first.

    Numeric parameters: medians of the bad and good runs, the Mann-Whitney U test's p-value and its effect size
    AUC = P(bad value > good value).  Categorical parameters (texture, booleans, ...): each category's share of
    bad runs, and the chi-square test of independence's p-value.  ``shared`` marks p < SIGNIFICANCE_P.
    """
    bad_arr = np.asarray(bad, dtype=bool)
    n_bad, n_good = int(bad_arr.sum()), int((~bad_arr).sum())
    if n_bad < MIN_GROUP_RUNS or n_good < MIN_GROUP_RUNS:
        return []
    keys = sorted({k for r in records for k in r.params})
    out = []
    for key in keys:
        vals = [r.params.get(key) for r in records]
        have = np.array([v is not None for v in vals])
        if have.sum() < 2 * MIN_GROUP_RUNS:
            continue
        if _numeric_param([v for v in vals if v is not None]):
            x = np.array([float(v) if v is not None else math.nan for v in vals])
            xb, xg = x[bad_arr & have], x[~bad_arr & have]
            if xb.size < MIN_GROUP_RUNS or xg.size < MIN_GROUP_RUNS or np.ptp(x[have]) == 0.0:
                continue
            u = sps.mannwhitneyu(xb, xg, alternative="two-sided")
            auc = float(u.statistic) / (xb.size * xg.size)
            out.append({"param": key, "kind": "numeric", "p_value": float(u.pvalue), "auc": auc,
                        "bad_median": float(np.median(xb)), "good_median": float(np.median(xg)),
                        "shared": bool(u.pvalue < SIGNIFICANCE_P),
                        "finding": f"bad runs have {'higher' if auc > 0.5 else 'lower'} {key} (median "
                                   f"{np.median(xb):.4g} vs {np.median(xg):.4g})"})
        else:
            cats = [json.dumps(v, sort_keys=True) if not isinstance(v, str) else v for v in vals]
            names = sorted({c for c, h in zip(cats, have, strict=True) if h})
            if len(names) < 2:
                continue
            table = np.array([[sum(1 for c, b, h in zip(cats, bad_arr, have, strict=True) if h and c == n and b == bb)
                               for n in names] for bb in (True, False)])
            p = float(sps.chi2_contingency(table).pvalue) if (table.sum(axis=1) > 0).all() else 1.0
            per_cat = {n: {"n": int(table[:, j].sum()), "bad_frac": float(table[0, j] / table[:, j].sum())}
                       for j, n in enumerate(names)}
            overall = n_bad / (n_bad + n_good)
            ranked = sorted(per_cat, key=lambda n: -per_cat[n]["bad_frac"])
            above = [n for n in ranked if per_cat[n]["bad_frac"] > overall][:MAX_CATEGORIES_IN_FINDING] or ranked[:1]
            listed = ", ".join(f"{n} {per_cat[n]['bad_frac']:.0%} of {per_cat[n]['n']}" for n in above)
            out.append({"param": key, "kind": "categorical", "p_value": p, "categories": per_cat,
                        "shared": bool(p < SIGNIFICANCE_P),
                        "finding": f"{key}: bad runs are {listed} (all runs: {overall:.0%})"})
    out.sort(key=lambda d: d["p_value"])
    return out


def _cause_analysis(records: Sequence[RunRecord], goals: Sequence[Goal], results: Sequence[dict[str, Any]]
                    ) -> dict[str, Any]:
    out: dict[str, Any] = {}
    by_name = {g.name: g for g in goals}
    for res in results:
        if res["met"]:
            continue
        g = by_name[res["name"]]
        elig = [r for r in records if not (g.min_wind_m_s > 0.0 and not _wind(r) >= g.min_wind_m_s)]
        bad = [r.index in set(res["bad_runs"]) for r in elig]
        how = "runs missing the threshold vs the rest"
        if sum(bad) < MIN_GROUP_RUNS or len(bad) - sum(bad) < MIN_GROUP_RUNS:
            vals = np.array([metric_value(r, g.metric) for r in elig], dtype=float)
            sign = -1.0 if g.op == ">=" else 1.0
            score = np.where(np.isfinite(vals), sign * vals, np.inf)  # missing values rank worst
            n_worst = max(MIN_GROUP_RUNS, int(math.ceil(WORST_FRACTION * len(elig))))
            cut = np.sort(score)[::-1][min(n_worst, len(elig)) - 1] if len(elig) else np.inf
            bad = [bool(s >= cut) for s in score]
            how = f"worst {WORST_FRACTION:.0%} of runs by {g.metric} vs the rest"
        out[g.name] = {"comparison": how, "n_bad": int(sum(bad)), "n_good": int(len(bad) - sum(bad)),
                       "bad_runs": [r.index for r, b in zip(elig, bad, strict=True) if b],
                       "eligible_runs": [r.index for r in elig], "effects": parameter_effects(elig, bad)}
    return out


def _nees_summary(records: Sequence[RunRecord]) -> dict[str, Any]:
    """navlie-style consistency: the NEES averaged across runs at each time against the chi-square interval of
    ``dof * n_runs`` degrees of freedom divided by ``n_runs``, when runs report a series (``nees_t_s``,
    ``nees_series``, ``nees_dof``); always the per-run in-bounds fractions."""
    ok = [r for r in records if r.status == "ok"]
    fr = np.array([metric_value(r, "nees_in_bounds_frac") for r in ok], dtype=float)
    out: dict[str, Any] = {"in_bounds_frac_mean": _stat(fr, "mean"), "in_bounds_frac_median": _stat(fr, "median"),
                           "n_runs_with_frac": int(np.isfinite(fr).sum()), "series": None}
    series = [r for r in ok if isinstance(r.metrics.get("nees_series"), list) and isinstance(r.metrics.get("nees_t_s"),
                                                                                               list)]
    if not series:
        out["note"] = "the run metrics carry no NEES time series (nees_t_s, nees_series, nees_dof)"
        return out
    dofs = {r.metrics.get("nees_dof") for r in series}
    if len(dofs) != 1 or not isinstance(next(iter(dofs)), int):
        out["note"] = f"runs report different or missing nees_dof: {sorted(map(str, dofs))}"
        return out
    dof = int(next(iter(dofs)))  # type: ignore[arg-type]
    t_ref = np.asarray(series[0].metrics["nees_t_s"], dtype=float)
    t_end = min(float(np.nanmax(np.asarray(r.metrics["nees_t_s"], dtype=float))) for r in series)
    t_ref = t_ref[t_ref <= t_end]
    stack = []
    for r in series:
        t = np.asarray(r.metrics["nees_t_s"], dtype=float)
        e = np.array([math.nan if v is None else v for v in r.metrics["nees_series"]], dtype=float)
        if t.shape != e.shape or t.size < 2:
            continue
        same = t.size >= t_ref.size and np.array_equal(t[: t_ref.size], t_ref)
        stack.append(e[: t_ref.size] if same else np.interp(t_ref, t, e))
    if not stack or t_ref.size == 0:
        out["note"] = "the NEES series of the runs are empty or malformed (nees_t_s and nees_series lengths differ)"
        return out
    arr = np.vstack(stack)
    n_per_t = np.isfinite(arr).sum(axis=0)
    with _quiet_nan_warnings():
        avg = np.nanmean(np.where(np.isfinite(arr), arr, np.nan), axis=0)
    n_runs = len(stack)
    lo, hi = nees_bounds(dof, n_runs, NEES_CONFIDENCE)
    inside = (avg >= lo) & (avg <= hi) & (n_per_t == n_runs)
    out["series"] = {"t_s": t_ref.tolist(), "avg_nees": avg.tolist(), "dof": dof, "n_runs": n_runs,
                     "bounds": [lo, hi], "confidence": NEES_CONFIDENCE,
                     "avg_in_bounds_frac": float(inside.sum() / max(1, int((n_per_t == n_runs).sum())))}
    return out


def _heading_table(records: Sequence[RunRecord], key: str = "drift_err_by_heading_deg") -> dict[str, Any] | None:
    rows: list[list[Any]] = [r.metrics[key] for r in records if r.status == "ok" and isinstance(r.metrics.get(key),
                                                                                                 list)]
    if not rows:
        return None
    n = max(len(x) for x in rows)
    arr = np.full((len(rows), n), np.nan)
    for j, row in enumerate(rows):
        if len(row) == n and all(v is None or (isinstance(v, int | float) and not isinstance(v, bool)) for v in row):
            arr[j] = [math.nan if v is None else float(v) for v in row]
    width = 360.0 / n
    with np.errstate(all="ignore"), _quiet_nan_warnings():
        med = np.nanmedian(np.abs(arr), axis=0)
        p95 = np.nanpercentile(np.abs(arr), 95, axis=0)
    return {"key": key, "bin_centres_deg": ((np.arange(n) + 0.5) * width).tolist(), "median_abs": med.tolist(),
            "p95_abs": p95.tolist(), "n_runs": len(rows)}


@contextlib.contextmanager
def _quiet_nan_warnings() -> Iterator[None]:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def summarize(records: Sequence[RunRecord], spec: MonteCarloSpec, campaign: Mapping[str, Any] | None = None
              ) -> dict[str, Any]:
    """The campaign's ``summary.json`` (see the issue: statistics per metric, goals, EKF vs baseline, NEES,
    throughput and memory, worst runs, and for each missed goal the parameters its bad runs share)."""
    recs = sorted(records, key=lambda r: r.index)
    ok = [r for r in recs if r.status == "ok"]
    keys = _scalar_metric_keys(ok)
    metrics = {k: metric_stats(recs, k) for k in keys}
    for k in ("wall_s", "peak_rss_mb"):
        metrics[k] = metric_stats(recs, k)
    windy = [r for r in recs if _wind(r) >= WIND_DIR_MIN_WIND_M_S]
    conditional = {f"{k}@wind>={WIND_DIR_MIN_WIND_M_S:g}m_s": metric_stats(windy, k)
                   for k in ("wind_dir_rmse_deg", "baseline_wind_dir_rmse_deg") if k in keys}
    side = {}
    for k in keys:
        b = f"baseline_{k}"
        if k.startswith("baseline_") or b not in keys:
            continue
        e_v = np.array([metric_value(r, k) for r in recs])
        b_v = np.array([metric_value(r, b) for r in recs])
        both = np.isfinite(e_v) & np.isfinite(b_v)
        better = (e_v > b_v) if _higher_is_better(k) else (e_v < b_v)
        side[k] = {"ekf": metrics[k], "baseline": metrics[b],
                   "ekf_better_frac": float(np.mean(better[both])) if both.any() else math.nan}
    results = goal_results(recs, spec.goals)
    # Throughput over every session of the campaign (resumes included).
    # Sessions that flew nothing (re-aggregation) do not count.
    sessions = [s for s in (campaign or {}).get("sessions", []) if s.get("flown", 0) > 0]
    wall_total = float(sum(s.get("wall_s", 0.0) for s in sessions))
    flown_total = int(sum(s.get("flown", 0) for s in sessions))
    sim_total = float(sum(s.get("sim_s", 0.0) for s in sessions))
    sim_per_wall = sim_total / wall_total if wall_total > 0 else math.nan
    by_worker: dict[str, float] = {}
    for r in recs:
        if r.worker and math.isfinite(r.peak_rss_mb):
            by_worker[r.worker] = max(by_worker.get(r.worker, 0.0), r.peak_rss_mb)
    projected = THROUGHPUT_GOAL_SIM_S / sim_per_wall if sim_per_wall and math.isfinite(sim_per_wall) else math.nan
    throughput = {"sessions": sessions, "campaign_wall_s": wall_total, "runs_flown_in_sessions": flown_total,
                  "sim_s_flown_ok": sim_total, "sim_s_per_wall_s": sim_per_wall,
                  "runs_per_hour": (flown_total / wall_total * 3600.0) if wall_total > 0 else math.nan,
                  "run_wall_s_mean": metrics["wall_s"]["mean"],
                  "projected_wall_s_100x600": projected,
                  "throughput_goal_met": bool(math.isfinite(projected) and projected <= THROUGHPUT_GOAL_WALL_S),
                  "peak_rss_mb_by_worker": by_worker,
                  "peak_rss_mb_max": max(by_worker.values()) if by_worker else math.nan}
    worst = sorted(recs, key=lambda r: (r.status == "ok", -_rank_value(r)))[:N_WORST_RUNS]
    return {
        "campaign": {"name": spec.name, "description": spec.description, "base_scenario": spec.base.name,
                     "base_seed": spec.base_seed, "n_runs": spec.n_runs, "duration_s": spec.duration_s,
                     "runner": spec.runner, "n_records": len(recs), "n_ok": len(ok),
                     "n_failed": len(recs) - len(ok), "missing_runs": sorted(set(range(spec.n_runs)) -
                                                                            {r.index for r in recs}),
                     "failed_runs": [{"index": r.index, "error": r.error} for r in recs if r.status != "ok"]},
        "goals": results,
        "all_goals_met": all(g["met"] for g in results),
        "metrics": metrics,
        "conditional": conditional,
        "ekf_vs_baseline": side,
        "nees": _nees_summary(recs),
        "drift_by_heading": _heading_table(recs),
        "throughput": throughput,
        "worst_runs": [{"index": r.index, "run_seed": r.run_seed, "status": r.status, "error": r.error,
                        WORST_BY_METRIC: metric_value(r, WORST_BY_METRIC), "params": r.params,
                        "features": r.features} for r in worst],
        "causes": _cause_analysis(recs, spec.goals, results),
    }


def _rank_value(rec: RunRecord) -> float:
    v = metric_value(rec, WORST_BY_METRIC)
    return v if math.isfinite(v) else math.inf


def write_summary(out_dir: str | Path, spec: MonteCarloSpec | None = None) -> dict[str, Any]:
    """Aggregate the run records of ``out_dir`` into ``summary.json`` (and return it)."""
    out = Path(out_dir)
    sp = spec if spec is not None else load_campaign_spec(out)
    summary = summarize(read_records(out, sp.n_runs), sp, read_campaign(out))
    write_json(out / SUMMARY_FILE, summary)
    return summary
