"""The declared field ranges (:class:`common.config.In`): one validator for direct construction and for ``build``."""

from __future__ import annotations

import dataclasses
import importlib
import math
from typing import Annotated, Any

import pytest

from common.config import FINITE, ConfigError, In, Validated, build, field_ranges
from gsoe.config import CameraConfig, GsoeConfig, StabConfig
from nav.gnss_monitor import GnssMonitorConfig
from nav.link import LinkConfig
from nav.tracker import TemplateTrackerConfig
from sim.autopilot import AutopilotGains, Waypoint
from sim.scenario import GnssConfig, MissionConfig, OutageConfig, WaypointConfig, WindConfig, build_scenario

# Every module whose config dataclasses declare their ranges.
CONFIG_MODULES = ("gsoe.config", "sim.autopilot", "sim.dynamics", "sim.scenario", "sim.wind", "nav.companion",
                  "nav.gnss_monitor", "nav.guidance", "nav.link", "nav.replay", "nav.tracker")


def _camera(**kw: Any) -> CameraConfig:
    args: dict[str, Any] = dict(model="pinhole", width_px=640, height_px=480, fx_px=400.0, fy_px=400.0, cx_px=320.0,
                                cy_px=240.0, dist=(0.0, 0.0, 0.0, 0.0, 0.0), hfov_deg=77.0, vfov_deg=62.0)
    return CameraConfig(**{**args, **kw})


@pytest.mark.parametrize(("make", "message"), [
    (lambda: StabConfig(template_px=-5), "template_px: must be in [3, 201], got -5"),
    (lambda: StabConfig(base_cross_px=120), "base_cross_px: must be odd, got 120"),
    (lambda: StabConfig(template_px=19.0), "template_px: must be an integer, got 19.0"),
    (lambda: TemplateTrackerConfig(template_px=30), "template_px: must be odd, got 30"),
    (lambda: _camera(dist=(0.0, 0.0, math.nan, 0.0, 0.0)), "dist[2]: must be in [-10.0, 10.0], got nan"),
    (lambda: GnssMonitorConfig(hacc_ok_m=0.0), "hacc_ok_m: must be in (0.0, 10000.0], got 0.0"),
    (lambda: LinkConfig(system_id=0), "system_id: must be in [1, 255], got 0"),
    (lambda: AutopilotGains(pitch_rate_ki=-0.1), "pitch_rate_ki: must be in [0.0, 100.0], got -0.1"),
    (lambda: Waypoint(0.0, 0.0, 100.0, 70.0), "airspeed_m_s: must be in [5.0, 60.0], got 70.0"),
    (lambda: OutageConfig(start_s=10.0, length_s=0.0), "length_s: must be in (0.0, 86400.0], got 0.0"),
    (lambda: WindConfig(speed_m_s=math.inf), "speed_m_s: must be in [0.0, 30.0], got inf"),
])
def test_direct_construction_rejects_out_of_range(make: Any, message: str) -> None:
    with pytest.raises(ConfigError) as ei:
        make()
    assert str(ei.value) == message


@pytest.mark.parametrize(("cls", "where", "data", "message"), [
    (StabConfig, "stab", {"template_px": -5}, "stab.template_px: must be in [3, 201], got -5"),
    (GnssMonitorConfig, "companion.gnss", {"timeout_s": 0.0},
     "companion.gnss.timeout_s: must be in [0.01, 600.0], got 0.0"),
    (LinkConfig, "companion.link", {"queue_size": 8}, "companion.link.queue_size: must be in [16, 1000000], got 8"),
    (GnssConfig, "sensors.gnss", {"outages": [{"start_s": -1.0, "length_s": 5.0}]},
     "sensors.gnss.outages[0].start_s: must be in [0.0, 86400.0], got -1.0"),
])
def test_build_from_mapping_rejects_out_of_range_with_dotted_name(cls: type, where: str, data: dict[str, Any],
                                                                   message: str) -> None:
    with pytest.raises(ConfigError) as ei:
        build(cls, data, where)
    assert str(ei.value) == message


def test_scenario_names_the_nested_field() -> None:
    data = {"name": "t", "mission": {"waypoints": [{"north_m": 0.0, "east_m": 500.0, "height_m": 100.0,
                                                    "airspeed_m_s": 20.0}], "loop": False},
            "sensors": {"imu": {"rate_hz": 50.0}}}
    with pytest.raises(ConfigError, match=r"^sensors\.imu\.rate_hz: must be in \[100\.0, 2000\.0\], got 50\.0$"):
        build_scenario(data)


def test_cross_field_rules_still_apply_after_the_ranges() -> None:
    with pytest.raises(ConfigError, match="^template_px: must be at least 4 px smaller"):
        StabConfig(template_px=19, base_along_px=21)
    with pytest.raises(ConfigError, match="^throttle_max: must be above throttle_min"):
        AutopilotGains(throttle_min=0.5, throttle_max=0.5)
    with pytest.raises(ConfigError, match="^cx_px: must be in"):
        _camera(cx_px=700.0)


def test_in_checks_a_plain_value_and_finite_means_finite() -> None:
    In(0.0, 1.0).check(0.5, "x")
    with pytest.raises(ConfigError, match=r"^x: must be in \(0.0, 1.0\], got 0.0$"):
        In(0.0, 1.0, lo_open=True).check(0.0, "x")
    with pytest.raises(ConfigError, match="^y: must be finite, got nan$"):
        FINITE.check(math.nan, "y")
    with pytest.raises(ConfigError, match="^z: must be a number, got 'a'$"):
        In(0.0, 1.0).check("a", "z")


# Annotations are resolved in the module's namespace (as :func:`build` does), so aliases live at module level.
Ratio = Annotated[float, In(0.0, 1.0, doc="a fraction")]


@dataclasses.dataclass(frozen=True)
class _Example(Validated):
    a: Ratio = 0.5
    n: Annotated[int, In(1, 9, odd=True)] = 3
    free: float = 7.0


def test_ranges_are_read_from_the_annotations_and_shared_aliases() -> None:
    names = [(name, rng.doc, integer) for name, rng, integer in field_ranges(_Example)]
    assert names == [("a", "a fraction", False), ("n", "", True)]
    with pytest.raises(ConfigError, match=r"^n: must be odd, got 4$"):
        _Example(n=4)
    with pytest.raises(ConfigError, match=r"^demo\.a: must be in \[0\.0, 1\.0\], got 2\.0$"):
        build(_Example, {"a": 2.0}, "demo")


def _validated_classes() -> list[type]:
    for name in CONFIG_MODULES:
        importlib.import_module(name)
    seen: list[type] = []
    todo = list(Validated.__subclasses__())
    while todo:
        cls = todo.pop()
        todo.extend(cls.__subclasses__())
        if cls.__module__ in CONFIG_MODULES and cls not in seen:
            seen.append(cls)
    return sorted(seen, key=lambda c: f"{c.__module__}.{c.__qualname__}")


def _out_of_range(rng: In, default: Any, integer: bool) -> Any:
    if isinstance(default, tuple):
        return (*default[:-1], _out_of_range(rng, 0.0, integer)) if default else (_out_of_range(rng, 0.0, integer),)
    if rng is FINITE or (math.isinf(rng.lo) and math.isinf(rng.hi)):
        return math.nan
    if math.isfinite(rng.hi):
        return int(rng.hi) + 1 if integer else rng.hi * 2.0 + 1.0
    return int(rng.lo) - 1 if integer else rng.lo - 1.0


_WAYPOINTS = [{"north_m": 0.0, "east_m": 500.0, "height_m": 100.0, "airspeed_m_s": 20.0}]
# A valid instance of each config class with fields that have no default.
SAMPLES: dict[str, Any] = {
    "CameraConfig": _camera,
    "GsoeConfig": lambda: GsoeConfig(camera=_camera()),
    "Waypoint": lambda: Waypoint(0.0, 500.0, 100.0, 20.0),
    "WaypointConfig": lambda: WaypointConfig(**_WAYPOINTS[0]),
    "MissionConfig": lambda: build(MissionConfig, {"waypoints": _WAYPOINTS, "loop": False}),
    "OutageConfig": lambda: OutageConfig(start_s=10.0, length_s=5.0),
    "Scenario": lambda: build_scenario({"name": "t", "mission": {"waypoints": _WAYPOINTS, "loop": False}}),
}


def test_every_declared_range_is_enforced_on_direct_construction() -> None:
    """Every config class rejects each field beyond its declared range (a subclass with cross-field rules that
    forgot ``super().__post_init__()`` would fail here)."""
    classes = _validated_classes()
    assert len(classes) >= 30
    checked = 0
    for cls in classes:
        if cls.__name__ in SAMPLES:
            base = SAMPLES[cls.__name__]()
        else:
            base = cls()  # a new class with required fields: add a sample above
        for name, rng, integer in field_ranges(cls):
            bad = _out_of_range(rng, getattr(base, name), integer)
            with pytest.raises(ConfigError) as ei:
                dataclasses.replace(base, **{name: bad})
            assert ei.value.field_path.split("[")[0] == name, (cls.__name__, name, str(ei.value))
            checked += 1
    assert checked >= 200
