"""A telemetry log's samples are placed by the autopilot's own clock, not by when they were received.

From the real ALFA log (``../shared/data/flightlogs``; skipped when absent) a copy is built whose receive times
arrive in bursts of up to 4 s (every message of a burst received at its end, as a link that holds messages back and
then delivers them together), and one whose receive clock runs 100 ppm fast and starts elsewhere.  The reader gives
the same samples at the same times, and the replay the same figures."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from nav.logreader import read_log
from nav.replay import run_replay
from tests.conftest import shared_data

LONG = "alfa_carbonZ_2018-07-30-17-36-35_engine_failure.tlog"
_HEADER = struct.Struct(">Q")
_V1, _V2 = 0xFE, 0xFD


def _records(data: bytes) -> list[tuple[int, bytes]]:
    """(receive us, MAVLink frame) of every record of a tlog (8-byte big-endian time, then the frame)."""
    out, ofs = [], 0
    while ofs + _HEADER.size + 2 <= len(data):
        (t,) = _HEADER.unpack_from(data, ofs)
        start = ofs + _HEADER.size
        magic, n = data[start], data[start + 1]
        if magic == _V1:
            size = 8 + n
        elif magic == _V2:
            size = 12 + n + (13 if data[start + 2] & 0x01 else 0)
        else:
            raise AssertionError(f"no MAVLink frame at byte {start}")
        out.append((t, data[start:start + size]))
        ofs = start + size
    assert ofs == len(data)
    return out


def _write(path: Path, records: list[tuple[int, bytes]]) -> Path:
    path.write_bytes(b"".join(_HEADER.pack(t) + frame for t, frame in records))
    return path


def _bursty(records: list[tuple[int, bytes]], rng: np.random.Generator, max_burst_s: float) -> list[tuple[int, bytes]]:
    """Consecutive bursts of 0.2-``max_burst_s`` s of receive time, each message received when its burst ends
    (plus a microsecond per message, to keep the order)."""
    out: list[tuple[int, bytes]] = []
    i = 0
    while i < len(records):
        end_t = records[i][0] + int(rng.uniform(0.2, max_burst_s) * 1e6)
        j = i
        while j < len(records) and records[j][0] <= end_t:
            j += 1
        last = records[j - 1][0]
        out.extend((last + k, frame) for k, (_, frame) in enumerate(records[i:j]))
        i = j
    return out


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    src = shared_data("flightlogs", LONG)
    records = _records(src.read_bytes())
    folder = tmp_path_factory.mktemp("tlogs")
    rng = np.random.default_rng(21)
    t0 = records[0][0]
    return {
        "original": src,
        "bursty": _write(folder / "bursty.tlog", _bursty(records, rng, 4.0)),
        "drifting": _write(folder / "drifting.tlog",
                           [(int(t0 + 3_600_000_000 + (t - t0) * 1.0001), f) for t, f in records]),
    }


def test_bursty_receive_times_do_not_move_samples(logs):
    ref = read_log(logs["original"])
    for name in ("bursty", "drifting"):
        got = read_log(logs[name])
        assert got.report.counts == ref.report.counts
        assert got.report.t0_boot_us == ref.report.t0_boot_us
        assert len(got.samples) == len(ref.samples)
        for a, b in zip(ref.samples, got.samples, strict=True):
            assert type(a) is type(b) and a.t_us == b.t_us, (name, a, b)
        assert got.report.warnings == ref.report.warnings


def test_bursty_receive_times_leave_the_replay_unchanged(logs, tmp_path):
    a = run_replay(logs["original"], plots=False).metrics
    b = run_replay(logs["bursty"], plots=False).metrics
    for k in ("wind_rmse_vs_autopilot_m_s", "pos_error_rms_with_gnss_m", "ekf_start_s", "optical_steps"):
        assert b[k] == a[k], k
