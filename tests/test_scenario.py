"""Scenario files: every shipped file loads with the paper's conditions; bad input is rejected naming the field."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from common.angles import angle_diff_deg
from common.config import ConfigError
from pipeline.config import load_gsoe_config
from sim.scenario import (
    SCENARIO_DIR,
    TEXTURES,
    Scenario,
    build_scenario,
    gsoe_config_for,
    load_scenario,
    scenario_path,
    scenario_with_overrides,
)

SCENARIO_FILES = sorted(SCENARIO_DIR.glob("*.toml"))
G_M_S2 = 9.80665


def minimal() -> dict:
    return {
        "name": "t",
        "mission": {"waypoints": [{"north_m": 300.0, "east_m": 0.0, "height_m": 100.0, "airspeed_m_s": 20.0},
                                  {"north_m": 300.0, "east_m": 300.0, "height_m": 100.0, "airspeed_m_s": 20.0}]},
    }


def leg_headings_deg(scn: Scenario) -> np.ndarray:
    m = scn.mission
    pts = np.array([[m.start.north_m, m.start.east_m]] + [[w.north_m, w.east_m] for w in m.waypoints])
    if m.loop:
        pts = np.vstack([pts, pts[1]])
    d = np.diff(pts, axis=0)
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0


def test_scenario_files_exist() -> None:
    names = {p.stem for p in SCENARIO_FILES}
    assert {"paper_sil", "paper_flight", "strong_wind", "low_texture", "gnss_outage"} <= names


@pytest.mark.parametrize("path", SCENARIO_FILES, ids=lambda p: p.stem)
def test_every_scenario_file_loads(path: Path) -> None:
    scn = load_scenario(path)
    assert scn.name == path.stem
    assert scn == load_scenario(path.stem)  # bare name resolves to the same file
    assert scn.n_steps == math.ceil(scn.duration_s / scn.dt_s - 1e-6)
    assert 25.0 <= scn.camera.rate_hz <= 60.0
    assert scn.sensors.imu.rate_hz >= 200.0
    # the optical configuration for it builds
    assert gsoe_config_for(scn, load_gsoe_config()[0]).cycle.rate_hz == scn.camera.rate_hz


def test_paper_sil_matches_paper_section_3_2() -> None:
    scn = load_scenario("paper_sil")
    assert scn.duration_s == 2000.0
    assert (scn.wind.speed_m_s, scn.wind.from_deg, scn.wind.ref_height_m) == (5.0, 45.0, 6.0)
    assert scn.wind.shear and scn.wind.turbulence and scn.wind.gusts
    assert scn.camera.rate_hz == 30.0
    g = gsoe_config_for(scn, load_gsoe_config()[0])
    assert (g.stab.base_cross_px, g.stab.base_along_px, g.stab.template_px) == (121, 73, 19)
    assert (g.camera.width_px, g.camera.height_px, g.camera.hfov_deg) == (800, 600, 110.0)
    wp = scn.mission.waypoints
    heights = [w.height_m for w in wp]
    speeds = [w.airspeed_m_s for w in wp]
    assert min(heights) == 80.0 and max(heights) == 150.0
    assert min(speeds) == 18.0 and max(speeds) == 24.0
    # many sharp turns: a turn of more than 45 deg at 20 m/s saturates the 45 deg bank limit
    h = leg_headings_deg(scn)
    turns = np.abs(angle_diff_deg(h[1:], h[:-1]))
    assert np.sum(turns > 45.0) >= 20
    # straight legs in every 45-degree sector of heading
    assert set(np.floor(h / 45.0).astype(int)) == set(range(8))
    # legs long enough to roll out of a 45-degree-bank turn (radius V^2 / (g tan 45) at the fastest airspeed)
    pts = np.array([[w.north_m, w.east_m] for w in wp])
    legs = np.hypot(*np.diff(np.vstack([pts, pts[:1]]), axis=0).T)
    assert legs.min() > 4 * max(speeds) ** 2 / (G_M_S2 * math.tan(math.radians(45.0)))


def test_paper_flight_matches_paper_section_4_2() -> None:
    scn = load_scenario("paper_flight")
    assert scn.duration_s == 1440.0
    assert (scn.wind.speed_m_s, scn.wind.from_deg, scn.wind.ref_height_m) == (1.5, 180.0, 6.0)
    assert scn.camera.rate_hz == 25.0
    assert all(w.airspeed_m_s == pytest.approx(75.0 / 3.6, abs=0.01) for w in scn.mission.waypoints)


def test_special_scenarios() -> None:
    assert 10.0 <= load_scenario("strong_wind").wind.speed_m_s <= 12.0
    assert load_scenario("low_texture").terrain.texture in ("dry_grassland", "uniform_grass", "water")
    scn = load_scenario("gnss_outage")
    (out,) = scn.sensors.gnss.outages
    assert out.length_s == 600.0
    assert 0.0 < out.start_s and out.end_s < scn.duration_s  # mid-flight, GNSS before and after
    assert scn.sensors.gnss.in_outage(out.start_s + 1.0) and not scn.sensors.gnss.in_outage(out.end_s)
    # extends = "paper_sil": same mission, only the listed keys changed
    sil = load_scenario("paper_sil")
    assert scn.mission == sil.mission and scn.wind == sil.wind
    assert scn.sensors.gnss.rate_hz == sil.sensors.gnss.rate_hz


def test_wind_and_angle_properties() -> None:
    wind = load_scenario("paper_sil").wind
    # from 45 deg: the air moves to the south-west
    np.testing.assert_allclose(wind.steady_ned_m_s, [-5.0 / math.sqrt(2), -5.0 / math.sqrt(2), 0.0], atol=1e-12)
    assert wind.from_rad == pytest.approx(math.pi / 4)


def test_minimal_scenario_gets_defaults() -> None:
    scn = build_scenario(minimal())
    assert scn.dt_s == pytest.approx(1.0 / 240.0)
    assert scn.terrain.texture == "mosaic" and scn.mission.loop
    np.testing.assert_allclose(scn.mission.waypoints_ned_m[0], [300.0, 0.0, -100.0])


# --------------------------------------------------------------------------------------------------------------
# Validation errors name the field


def _with(path: str, value: object) -> dict:
    d = minimal()
    node = d
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    return d


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        ("colour", "red", "colour"),
        ("wind.speedd_m_s", 3.0, "wind.speedd_m_s"),
        ("wind.speed_m_s", 45.0, "wind.speed_m_s"),
        ("wind.speed_m_s", -1.0, "wind.speed_m_s"),
        ("wind.from_deg", "north", "wind.from_deg"),
        ("wind.turbulence_rate_hz", 2.0, "wind.turbulence_rate_hz"),
        ("wind.turbulence_rate_hz", float("nan"), "wind.turbulence_rate_hz"),
        ("terrain.texture", "moon", "terrain.texture"),
        ("sensors.gnss.outages", [{"start_s": 10.0, "length_s": -5.0}], "sensors.gnss.outages[0].length_s"),
        ("sensors.gnss.outages", [{"start_s": 10.0}], "sensors.gnss.outages[0].length_s"),
        ("sensors.imu.rate_hz", 50.0, "sensors.imu.rate_hz"),
        ("sensors.imu.rate_hz", 500.0, "sensors.imu.rate_hz"),  # faster than the 240 Hz dynamics
        ("sensors.ahrs.latency_s", -0.1, "sensors.ahrs.latency_s"),
        ("camera.rate_hz", 150.0, "camera.rate_hz"),
        ("camera.exposure_s", 0.05, "camera.exposure_s"),  # longer than a 30 Hz frame
        ("camera.gsoe_overrides", {"stab": {"templat_px": 21}}, "camera.gsoe_overrides.stab.templat_px"),
        ("camera.gsoe_overrides", {"stabb": {}}, "camera.gsoe_overrides.stabb"),
        ("camera.gsoe_overrides", {"cycle": {"rate_hz": 60.0}}, "camera.gsoe_overrides.cycle.rate_hz"),
        ("duration_s", 0.0, "duration_s"),
        ("seed", -1, "seed"),
        ("seed", 1.5, "seed"),
        ("dt_s", 1.0, "dt_s"),
        ("name", "  ", "name"),
        ("mission.start.yaw_deg", 400.0, "mission.start.yaw_deg"),
    ],
)
def test_bad_values_are_rejected_naming_the_field(path: str, value: object, field: str) -> None:
    with pytest.raises(ConfigError) as ei:
        build_scenario(_with(path, value))
    assert ei.value.field_path == field


def test_bad_waypoints_name_the_waypoint() -> None:
    d = minimal()
    del d["mission"]["waypoints"][1]["height_m"]
    with pytest.raises(ConfigError, match=r"^mission\.waypoints\[1\]\.height_m: missing"):
        build_scenario(d)
    d = minimal()
    d["mission"]["waypoints"][1]["airspeed_m_s"] = 3.0
    with pytest.raises(ConfigError, match=r"^mission\.waypoints\[1\]\.airspeed_m_s"):
        build_scenario(d)
    d = minimal()
    d["mission"]["waypoints"][1].update(north_m=302.0, east_m=1.0)  # 2 m leg: a duplicated waypoint
    with pytest.raises(ConfigError, match=r"^mission\.waypoints\[1\]: leg"):
        build_scenario(d)
    d = minimal()
    d["mission"]["waypoints"] = []
    with pytest.raises(ConfigError, match=r"^mission\.waypoints"):
        build_scenario(d)
    with pytest.raises(ConfigError, match=r"^mission: missing"):
        build_scenario({"name": "x"})


def test_file_errors_name_file_and_field(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text('name = "bad"\nextends = "paper_sil"\n[wind]\nspeed_m_s = 31.0\n')
    with pytest.raises(ConfigError) as ei:
        load_scenario(p)
    assert ei.value.field_path == f"{p}: wind.speed_m_s"
    with pytest.raises(ConfigError, match="unknown scenario; known: .*paper_sil"):
        load_scenario("no_such_scenario")
    p.write_text("name = [unclosed\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(p)
    p.write_text('extends = "loop.toml"\n')
    (tmp_path / "loop.toml").write_text('extends = "bad.toml"\n')
    with pytest.raises(ConfigError, match="extends"):
        load_scenario(p)


def test_extends_merges_tables_and_replaces_arrays(tmp_path: Path) -> None:
    p = tmp_path / "mine.toml"
    p.write_text(
        'extends = "paper_sil"\nname = "mine"\n[wind]\nspeed_m_s = 8.0\n'
        "[mission]\nwaypoints = [{ north_m = 500.0, east_m = 0.0, height_m = 200.0, airspeed_m_s = 22.0 },"
        " { north_m = 0.0, east_m = 500.0, height_m = 200.0, airspeed_m_s = 22.0 }]\n"
    )
    scn = load_scenario(p)
    sil = load_scenario("paper_sil")
    assert scn.wind.speed_m_s == 8.0 and scn.wind.from_deg == sil.wind.from_deg
    assert len(scn.mission.waypoints) == 2 and scn.mission.start == sil.mission.start
    assert scenario_path("paper_sil") == SCENARIO_DIR / "paper_sil.toml"
    assert scenario_path(p) == p


# --------------------------------------------------------------------------------------------------------------
# Overrides (Monte Carlo)


def test_overrides_make_a_new_validated_scenario() -> None:
    sil = load_scenario("paper_sil")
    assert scenario_with_overrides(sil, {}) == sil
    outages = [{"start_s": 100.0, "length_s": 50.0}]
    scn = scenario_with_overrides(sil, {
        "wind.speed_m_s": 9.0,
        "terrain.texture": "water",
        "mission.waypoints[3].height_m": 250.0,
        "sensors.gnss.outages": outages,
        "sensors.ahrs.latency_s": 0.05,
        "seed": 77,
        "camera.gsoe_overrides.stab.template_start": "trailing",
    })
    assert scn.wind.speed_m_s == 9.0 and scn.terrain.texture == "water" and scn.seed == 77
    assert scn.mission.waypoints[3].height_m == 250.0 and scn.mission.waypoints[2] == sil.mission.waypoints[2]
    assert scn.sensors.gnss.outages[0].end_s == 150.0 and scn.sensors.ahrs.latency_s == 0.05
    assert gsoe_config_for(scn, load_gsoe_config()[0]).stab.template_start == "trailing"
    outages[0]["length_s"] = 1.0  # the scenario owns its data
    assert scn.sensors.gnss.outages[0].length_s == 50.0
    assert sil.wind.speed_m_s == 5.0 and sil.camera.gsoe_overrides == {}  # original untouched


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"wind.speed_m_s": 31.0}, "wind.speed_m_s"),
        ({"wind.sped_m_s": 3.0}, "wind.sped_m_s"),
        ({"windy.speed_m_s": 3.0}, "windy"),
        ({"terrain.texture": "lava"}, "terrain.texture"),
        ({"mission.waypoints[99].height_m": 100.0}, "mission.waypoints[99]"),
        ({"mission.waypoints[0].height_m": 5.0}, "mission.waypoints[0].height_m"),
        ({"sensors.gnss.outages": [{"start_s": 5.0, "length_s": -1.0}]}, "sensors.gnss.outages[0].length_s"),
        ({"wind.speed_m_s.x": 1.0}, "wind.speed_m_s.x"),
        ({"wind..speed": 1.0}, "wind..speed"),
    ],
)
def test_bad_overrides_name_the_field(overrides: dict, field: str) -> None:
    with pytest.raises(ConfigError) as ei:
        scenario_with_overrides(load_scenario("paper_sil"), overrides)
    assert ei.value.field_path == field


def test_gsoe_override_checked_against_the_full_optical_config() -> None:
    scn = scenario_with_overrides(load_scenario("paper_sil"), {"camera.gsoe_overrides.stab.template_px": 18})
    with pytest.raises(ConfigError) as ei:
        gsoe_config_for(scn, load_gsoe_config()[0])
    assert ei.value.field_path == "camera.gsoe_overrides.stab.template_px"


def test_texture_names_match_the_renderer() -> None:
    textures = pytest.importorskip("sim.textures")
    assert set(TEXTURES) == set(textures.TEXTURE_NAMES)


def test_turbulence_rate_is_a_scenario_field_with_the_wind_models_default() -> None:
    from sim.wind import WindParams

    assert build_scenario(_with("wind.turbulence_rate_hz", 50.0)).wind.turbulence_rate_hz == 50.0
    assert build_scenario(minimal()).wind.turbulence_rate_hz == WindParams().turbulence_rate_hz
