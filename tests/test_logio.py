"""The CSV log format of common.logio: round trip of every value type, and a torn last line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from common.logio import RunLog, read_log


def test_round_trip_of_every_value_type(tmp_path: Path) -> None:
    recs = [
        {"t_us": 1, "x_m": 0.1, "y_m": np.float64(1e-17), "ok": True, "n": np.int64(7), "note": "a,b\nc",
         "z_m": None, "f32": np.float32(0.5)},
        {"t_us": 2, "x_m": math.inf, "y_m": -math.inf, "ok": np.bool_(False), "n": 3, "note": "plain",
         "z_m": math.nan, "f32": 2.0},
        {"t_us": 3, "x_m": 1.0 / 3.0, "y_m": 123456789.123, "ok": False, "n": 0, "note": ""},  # f32 missing
    ]
    with RunLog(tmp_path) as log:
        for r in recs:
            log.write("s", r)
    got = read_log(tmp_path / "s.csv")
    assert list(got["t_us"]) == [1, 2, 3]
    assert got["x_m"][0] == 0.1 and got["x_m"][1] == math.inf and got["x_m"][2] == 1.0 / 3.0  # exact round trip
    assert got["y_m"][0] == 1e-17 and got["y_m"][1] == -math.inf and got["y_m"][2] == 123456789.123
    assert list(got["ok"]) == [1.0, 0.0, 0.0]
    assert list(got["n"]) == [7, 3, 0]
    assert list(got["note"]) == ["a;b c", "plain", ""]
    assert math.isnan(got["z_m"][0]) and math.isnan(got["z_m"][1])
    assert got["f32"][0] == 0.5 and math.isnan(got["f32"][2])
    # numpy's reader (documented) agrees
    arr = np.genfromtxt(tmp_path / "s.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert arr["x_m"][2] == 1.0 / 3.0 and list(arr["ok"]) == [1, 0, 0] and arr["y_m"][1] == -math.inf


def test_torn_last_line_is_dropped(tmp_path: Path) -> None:
    with RunLog(tmp_path) as log:
        for i in range(3):
            log.write("s", {"t_us": i, "v_m": float(i)})
    p = tmp_path / "s.csv"
    p.write_text(p.read_text() + "3,")  # a write cut by a kill
    got = read_log(p)
    assert list(got["t_us"]) == [0, 1, 2]


def test_reopen_appends_without_second_header(tmp_path: Path) -> None:
    for i in range(2):
        with RunLog(tmp_path) as log:
            log.write("s", {"t_us": i, "v_m": 1.5})
    assert (tmp_path / "s.csv").read_text().splitlines() == ["t_us,v_m", "0,1.5", "1,1.5"]


if __name__ == "__main__":
    pytest.main([__file__])
