"""A telemetry log's samples are placed by the autopilot's own clock, not by when they were received.

From the real ALFA log (``../shared/data/flightlogs``; skipped when absent) a copy is built whose receive times
arrive in bursts of up to 4 s (every message of a burst received at its end, as a link that holds messages back and
then delivers them together), and one whose receive clock runs 100 ppm fast and starts elsewhere.  The reader gives
the same samples at the same times, and the replay the same figures."""

from __future__ import annotations

import math
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


def _synthetic_tlog(path: Path, rng: np.random.Generator) -> Path:
    """60 s of an ArduPilot-like stream: HEARTBEAT, ATTITUDE (boot ms) and VFR_HUD (no stamp) at 5 Hz, a GPS fix
    at 2 Hz stamped in UNIX time, received after 20-80 ms of link delay plus bursts of up to 3 s; one ATTITUDE
    carries a stamp from after a reboot (1 s since boot)."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    link = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    unix0_us = 1_532_986_742_000_000
    boot0_us = 361_000_000
    msgs: list[tuple[int, bytes]] = []
    for k in range(300):
        boot_us = boot0_us + k * 200_000
        hb = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0, 3)
        stamp_ms = 1000 if k == 150 else boot_us // 1000
        att = mav.MAVLink_attitude_message(stamp_ms, 0.1 * math.sin(k / 10), 0.05, k / 300, 0.0, 0.0, 0.0)
        hud = mav.MAVLink_vfr_hud_message(18.0 + k / 100, 17.0, 90, 50, 100.0, 0.0)
        for m in (hb, att, hud):
            msgs.append((boot_us, bytes(m.pack(link))))
        if k % 2 == 0:
            gps = mav.MAVLink_gps_raw_int_message(unix0_us + (boot_us - boot0_us), 3, 405_900_000 + 10 * k,
                                                  -799_000_000, 400_000, 100, 100, 1700, 9000, 10)
            msgs.append((boot_us + 1000, bytes(gps.pack(link))))
    recv, burst_end = [], 0
    for t, _ in msgs:
        r = t + int(rng.uniform(20_000, 80_000)) + 5_000_000_000
        if r > burst_end:
            burst_end = r + int(rng.uniform(0.0, 3.0) * 1e6) if rng.uniform() < 0.2 else 0
        recv.append(max(r, burst_end) if burst_end else r)
    recv = list(np.maximum.accumulate(recv))
    return _write(path, [(int(r), frame) for r, (_, frame) in zip(recv, msgs, strict=True)])


def test_unix_stamped_gnss_and_unstamped_messages_on_the_boot_clock(tmp_path):
    from nav.logreader import AirspeedSample, AttitudeSample, GnssSample

    flog = read_log(_synthetic_tlog(tmp_path / "synthetic.tlog", np.random.default_rng(8)))
    t0 = flog.report.t0_boot_us
    assert t0 == 361_000_000
    atts = flog.of_type(AttitudeSample)
    # the reboot-stamped ATTITUDE (k = 150) is placed at the newest trusted stamp sent before it (ATTITUDE 149)
    assert sorted(a.t_us for a in atts) == sorted([k * 200_000 for k in range(300) if k != 150] + [149 * 200_000])
    assert any("1 messages whose autopilot timestamp disagrees" in w for w in flog.report.warnings)
    # GPS_RAW_INT in UNIX time: on the boot clock through the two clocks' fits (1 ms after its slot, to the fits'
    # few-ms agreement)
    gnss = flog.of_type(GnssSample)
    err_ms = [(g.t_us - (k * 400_000 + 1000)) / 1e3 for k, g in enumerate(gnss)]
    assert len(gnss) == 150 and max(abs(e) for e in err_ms) < 40.0
    # VFR_HUD has no stamp: at the ATTITUDE sent just before it, whatever the bursts (after the untrusted one: at
    # the trusted one before that)
    air = flog.of_type(AirspeedSample)
    assert [a.t_us for a in air] == [(k - (k == 150)) * 200_000 for k in range(300)]
