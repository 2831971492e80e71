"""Matching where the motion is (``[match] method = "window"``): the window around the predicted position gives the
exhaustive search's answer where that answer lies inside it, widens to the whole base image on a miss, and the TM
cycle searches the window its step gate can accept."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import gsoe.cycle as cycle_mod
from gsoe.config import MatchConfig
from gsoe.matching import match_template
from sim.optical_run import fly_optical
from sim.render import CameraRenderer
from sim.textures import GroundWorld
from sim.trajectory import ScriptedFlight, Segment
from tests.test_matching import _textured_cases

WINDOW = MatchConfig(method="window")
EXHAUSTIVE = MatchConfig(method="exhaustive")
RADIUS_PX = 2           # the step gate's reach (px); the window is the config's margin wider


@pytest.mark.parametrize("tile", ["town_river_sw", "forest_road", "dry_grassland_textured"])
def test_window_around_the_truth_gives_the_exhaustive_answer(tile):
    """Started within the step gate (2 px) of the truth, the window's minimum is the whole surface's: the same
    position to rounding (its surface comes from a smaller image) and the same verdict when the exhaustive match is
    valid."""
    rng = np.random.default_rng(11)
    base, cases = _textured_cases(tile, 25, rng, margin=8)
    for tpl, (tx, ty) in cases:
        ex = match_template(base, tpl, EXHAUSTIVE)
        off = rng.uniform(-2.0, 2.0, 2)
        w = match_template(base, tpl, WINDOW, (tx + off[0], ty + off[1]), RADIUS_PX)
        if ex.quality.valid:
            assert w.quality.valid
            assert w.x_px == pytest.approx(ex.x_px, abs=2e-3) and w.y_px == pytest.approx(ex.y_px, abs=2e-3)


def test_a_miss_widens_to_the_whole_base_image():
    """Started far from the truth, the window's minimum mostly lies in its margin or is no clear peak: the search
    widens and returns the exhaustive answer.  A window without the truth can still hold a local minimum within the
    gate's reach of its centre that passes the gates on its own surface (measured on the five test tiles: 1.3 % of
    such windows, against 22 % of templates from elsewhere passing ``psr_min`` on a whole base image, see
    :mod:`gsoe.matching`); in the cycle the step gate stands behind both."""
    base, cases = _textured_cases("forest_road", 40, np.random.default_rng(12), margin=8)
    same = 0
    for tpl, (tx, ty) in cases:
        ex = match_template(base, tpl, EXHAUSTIVE)
        start = (tx + 25.0 if tx < 60 else tx - 25.0, ty)
        w = match_template(base, tpl, WINDOW, start, RADIUS_PX)
        same += (w.x_px, w.y_px, w.quality.valid) == (ex.x_px, ex.y_px, ex.quality.valid)
    assert same >= 0.9 * len(cases)


def test_without_a_prediction_the_window_method_is_exhaustive():
    base, cases = _textured_cases("town_river_ne", 5, np.random.default_rng(13), margin=8)
    for tpl, (tx, ty) in cases:
        ex = match_template(base, tpl, EXHAUSTIVE)
        assert match_template(base, tpl, WINDOW) == ex
        assert match_template(base, tpl, WINDOW, (tx, ty)) == ex           # no radius
        assert match_template(base, tpl, WINDOW, None, RADIUS_PX) == ex    # no centre


def test_a_featureless_template_is_not_searched_again():
    base, _ = _textured_cases("forest_road", 1, np.random.default_rng(14))
    calls = []
    flat = np.full((19, 19), 100.0, np.float32)
    import gsoe.matching as m

    orig = m._match_in

    def spy(*a, **k):
        calls.append(a[2:6])
        return orig(*a, **k)

    m._match_in = spy
    try:
        r = match_template(base, flat, WINDOW, (60.0, 36.0), RADIUS_PX)
    finally:
        m._match_in = orig
    assert not r.quality.valid and len(calls) == 1


@pytest.mark.parametrize("radius", [0, -3, 2.5, "4"])
def test_radius_must_be_a_positive_integer(radius):
    base, cases = _textured_cases("forest_road", 1, np.random.default_rng(15))
    with pytest.raises(ValueError, match="radius_px"):
        match_template(base, cases[0][0], WINDOW, (60.0, 36.0), radius)


def test_the_cycle_searches_the_gate_window_and_flies_as_the_exhaustive_search(gsoe_config, camera):
    """A straight and a turning stretch over real imagery: with the window every step is where the exhaustive search
    puts it (to 0.01 px) with the same verdict, and the window is the step gate's plus the margin around the
    position the previous step predicts (the whole image only at a cycle's start without a carried step)."""
    flight = ScriptedFlight([Segment(2.0), Segment(2.0, math.radians(25.0))], tas_m_s=20.0, height_m=100.0,
                            wind_ned_m_s=(2.0, -5.0, 0.0))
    renderer = CameraRenderer(camera, GroundWorld.from_name("forest_road"))
    runs = {}
    radii: list[int | None] = []
    orig = cycle_mod.match_template

    def spy(base, tpl, cfg, start=None, radius=None):
        radii.append(radius)
        return orig(base, tpl, cfg, start, radius)

    for method in ("exhaustive", "window"):
        cfg = dataclasses.replace(gsoe_config, match=dataclasses.replace(gsoe_config.match, method=method))
        cycle_mod.match_template = spy
        try:
            radii.clear()
            runs[method] = fly_optical(flight, cfg, camera, renderer)
        finally:
            cycle_mod.match_template = orig
    gate = math.ceil(gsoe_config.cycle.step_gate_px)
    assert {r for r in radii if r is not None} == {gate}
    assert sum(r is None for r in radii) <= 2          # the first cycle's first match
    ex, win = runs["exhaustive"].steps, runs["window"].steps
    assert len(ex) == len(win) and sum(s.valid for s in win) >= 0.9 * len(win)
    for a, b in zip(ex, win, strict=True):
        assert (a.cycle_id, a.step, a.valid) == (b.cycle_id, b.step, b.valid)
        assert b.dx_px == pytest.approx(a.dx_px, abs=0.01) and b.dy_px == pytest.approx(a.dy_px, abs=0.01)
