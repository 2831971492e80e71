"""common.config.Radians: a config class's degrees field read in radians, refused when it names no field."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Annotated

import pytest

from common.config import In, Radians, Validated, build


@dataclass(frozen=True)
class _Angles(Validated):
    yaw_deg: Annotated[float, In(-360.0, 360.0)] = 30.0
    yaw_rad = Radians("yaw_deg")


def test_radians_reads_the_degrees_field_and_is_no_field_of_its_own():
    assert _Angles().yaw_rad == pytest.approx(math.pi / 6, abs=1e-15)
    assert _Angles(yaw_deg=-270.0).yaw_rad == pytest.approx(-1.5 * math.pi, abs=1e-15)
    assert build(_Angles, {"yaw_deg": 90.0}).yaw_rad == pytest.approx(math.pi / 2, abs=1e-15)
    assert [f.name for f in dataclasses.fields(_Angles)] == ["yaw_deg"]
    with pytest.raises(ValueError, match="yaw_rad"):
        build(_Angles, {"yaw_rad": 1.0})            # not a key of the configuration
    assert isinstance(_Angles.yaw_rad, Radians)      # on the class: the declaration itself


def test_radians_of_a_name_that_is_no_field_is_refused_with_the_class():
    # Python 3.11 wraps an error of __set_name__ in a RuntimeError (3.12 on: the TypeError itself)
    with pytest.raises((TypeError, RuntimeError)) as err:
        @dataclass(frozen=True)
        class _Typo(Validated):
            yaw_deg: float = 0.0
            yaw_rad = Radians("pitch_deg")
    assert "'pitch_deg', not a field" in f"{err.value} {err.value.__cause__}"
