"""The paper's data filter (eq. 6) and data-integrity filter (2.7) on scripted sequences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.angles import angle_diff
from gsoe.config import IntegrityConfig
from gsoe.integrity import RECOVERY_CYCLES, IntegrityFilter, circular_median, data_filter_fires

CFG = IntegrityConfig()  # history 5, max jump 5 deg, min 3 steps, min travel 4 px
GOOD = {"n_steps": 9, "travel_px": 27.0}
D = math.radians


def _run(filt: IntegrityFilter, drifts_deg, t0_us: int = 0, **kw):
    args = {**GOOD, **kw}
    return [filt.update(t0_us + (i + 1) * 300_000, D(d), **args) for i, d in enumerate(drifts_deg)]


def _warm(level_deg: float = 10.0) -> IntegrityFilter:
    f = IntegrityFilter(CFG)
    _run(f, [level_deg] * CFG.history_cycles)
    return f


# ---------------------------------------------------------------------------------------------------------------
# eq. 6


def test_data_filter_hand_cases():
    assert data_filter_fires((2.0, 3.0), (6.5, 7.0), 4.0)  # both change by >= 4 (4.5 and exactly 4)
    assert not data_filter_fires((2.0, 3.0), (6.5, 6.9), 4.0)  # y changes by 3.9 only
    assert not data_filter_fires((2.0, 3.0), (12.0, 3.0), 4.0)  # one component is not enough
    assert data_filter_fires((2.0, 3.0), (-3.0, -2.0), 4.0)  # absolute changes
    assert data_filter_fires((2.0, 3.0), (2.0, 3.0), 0.0)  # zeta 0 fires on every step
    assert data_filter_fires((2.0, 3.0), (math.nan, 3.0), 4.0)  # non-finite: an anomaly
    with pytest.raises(ValueError):
        data_filter_fires((0.0, 0.0), (1.0, 1.0), -1.0)
    with pytest.raises(ValueError):
        data_filter_fires((0.0, 0.0, 0.0), (1.0, 1.0), 1.0)


def test_circular_median_across_the_wrap():
    m = circular_median(np.deg2rad([179.0, -179.0, 178.0, -178.0, 179.5]))
    assert angle_diff(m, D(179.5)) == pytest.approx(0.0, abs=1e-12)
    # robust: one wild value does not move it (a mean would move by 36 deg)
    m = circular_median(np.deg2rad([10.0, 11.0, 9.0, 10.5, 190.0]))
    assert m == pytest.approx(D(10.5))
    assert math.isnan(circular_median([]))


# ---------------------------------------------------------------------------------------------------------------
# 2.7


def test_start_up_needs_agreeing_cycles_then_releases():
    f = IntegrityFilter(CFG)
    v = _run(f, [10.0, 10.8, 9.5, 10.2])
    assert [x.released for x in v] == [False] * (RECOVERY_CYCLES - 1) + [True, True]
    assert v[RECOVERY_CYCLES - 1].drift_rad == pytest.approx(D(9.5))
    assert all(math.isnan(x.drift_rad) for x in v[:RECOVERY_CYCLES - 1])
    assert "no history" in v[0].reason


def test_outlier_rejected_and_does_not_disturb():
    f = _warm(10.0)
    rng = np.random.default_rng(21)
    level = 10.0 + rng.normal(0.0, 1.0, 12)
    seq = list(level[:4]) + [40.0] + list(level[4:8]) + [-25.0] + list(level[8:])
    v = _run(f, seq, t0_us=10_000_000)
    released = [x.released for x in v]
    assert released == [True] * 4 + [False] + [True] * 4 + [False] + [True] * 4
    assert v[4].reason.startswith("jump 29.")  # 40 deg against a median near 10.4
    for x, d in zip(v, seq, strict=True):
        if x.released:
            assert x.drift_rad == pytest.approx(D(d))
    assert angle_diff(f.reference_rad, D(10.0)) == pytest.approx(0.0, abs=D(1.5))


def test_step_change_in_true_drift_is_accepted_after_recovery_cycles():
    f = _warm(10.0)
    v = _run(f, [25.0, 24.5, 25.5, 25.2, 24.8], t0_us=10_000_000)
    assert [x.released for x in v] == [False] * (RECOVERY_CYCLES - 1) + [True] * (6 - RECOVERY_CYCLES)
    assert "new level" in v[RECOVERY_CYCLES - 1].reason
    assert angle_diff(f.reference_rad, D(25.0)) == pytest.approx(0.0, abs=D(0.6))
    # and the old level is now the outlier
    assert not f.update(20_000_000, D(10.0), **GOOD).released


def test_slow_drift_change_is_followed():
    f = _warm(0.0)
    v = _run(f, np.arange(1.0, 30.0, 1.0), t0_us=10_000_000)  # 1 deg per cycle, as in a slow turn
    assert all(x.released for x in v)


def test_disagreeing_rejections_do_not_make_a_level():
    f = _warm(10.0)
    v = _run(f, [40.0, -30.0, 60.0, -45.0, 40.0, 10.5], t0_us=10_000_000)
    assert [x.released for x in v] == [False] * 5 + [True]


def test_wrap_at_180():
    f = IntegrityFilter(CFG)
    seq = [179.0, -179.0, 178.5, -178.0, 179.5, -179.5, 0.0, 178.8]
    v = _run(f, seq)
    assert [x.released for x in v] == [False, False, True, True, True, True, False, True]
    for x in v:
        if x.released:
            assert -math.pi <= x.drift_rad < math.pi
    assert abs(angle_diff(f.reference_rad, D(180.0))) < D(1.5)
    # a step across the wrap (from -170 to +170 is 20 deg, not 340) recovers like any other
    v = _run(f, [170.0, 170.5, 169.5, 170.2], t0_us=10_000_000)
    assert [x.released for x in v] == [False, False, True, True]


def test_quality_gates_reject_without_touching_candidates():
    f = _warm(10.0)
    t = 10_000_000
    assert not f.update(t + 1, D(25.0), **GOOD).released  # candidate 1
    short = f.update(t + 2, D(25.0), n_steps=2, travel_px=27.0)
    assert not short.released and "min_steps" in short.reason
    little = f.update(t + 3, D(25.0), n_steps=9, travel_px=3.0)
    assert not little.released and "min_travel_px" in little.reason
    assert not f.update(t + 4, D(25.0), **GOOD).released  # candidate 2
    assert f.update(t + 5, D(25.0), **GOOD).released  # candidate 3: new level
    nan = f.update(t + 6, math.nan, **GOOD)
    assert not nan.released and math.isnan(nan.drift_rad)


def test_time_must_advance():
    f = _warm(10.0)
    assert f.update(9_000_000, D(10.0), **GOOD).released
    back = f.update(9_000_000, D(10.0), **GOOD)
    assert not back.released and "t_us" in back.reason
    assert f.update(9_000_001, D(10.0), **GOOD).released


def test_history_is_the_last_released_cycles():
    """The median of the last N released drifts lags a ramp by (N + 1) / 2 cycles at the next cycle: with a ramp of
    2 deg per cycle that is 4 deg for N = 3 (within max_jump 5: all released) and 6 deg for N = 5 (rejected
    until the recovery rule catches up)."""
    short = IntegrityFilter(IntegrityConfig(history_cycles=3))
    long = IntegrityFilter(IntegrityConfig(history_cycles=5))
    ramp = [2.0 * k for k in range(15)]
    assert all(x.released for x in _run(short, ramp)[RECOVERY_CYCLES - 1:])
    v = _run(long, ramp)[RECOVERY_CYCLES - 1:]
    assert not all(x.released for x in v)
    assert sum(x.released for x in v) >= len(v) // 2  # the recovery rule keeps it from locking out


def test_bad_recovery_setting_raises():
    with pytest.raises(ValueError):
        IntegrityFilter(CFG, recovery_cycles=0)
