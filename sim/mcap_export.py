"""A run folder's CSV logs as one MCAP file (``gsoe report LOGDIR --mcap``), for Foxglove and PlotJuggler.

Why MCAP: Foxglove opens it with no plugin, PlotJuggler (3.8 and later) ships its MCAP loader, and ROS 2 records
in it, so it is the file ArduPilot and PX4 users with a ROS or Foxglove setup already open.  The CSV logs stay the
project's format (PlotJuggler reads them too, but one file per stream, each to be given its time column); the MCAP
file puts every stream on one time axis.

Layout: one channel per CSV stream, topic ``/gsoe/<stream>`` (``/gsoe/ekf``, ``/gsoe/aid_status``, ...), JSON
messages (``message_encoding = "json"``) with a JSON Schema (``jsonschema``) per stream whose properties are the
CSV's columns with the same names, so with the same unit suffixes (``wind_n_m_s``, ``drift_rad``), and a
description naming the unit.  Each row is one message at ``log_time = publish_time = t_us * 1000`` ns (the log's
clock: simulation time, or the companion's monotonic clock); numbers are numbers, ``nan`` and infinities ``null``
(JSON has no NaN), text columns strings.  Rows with a negative ``t_us`` (an aid source's status before its first
sample) are left out.  Messages are written in time order, zstd-compressed chunks.
"""

from __future__ import annotations

import heapq
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from common.logio import read_log

MCAP_FILE = "flight.mcap"
TOPIC_PREFIX = "/gsoe/"
NS_PER_US = 1000
# unit suffixes of the log's column names (common.logio) -> the unit's name in the schema
UNITS = {"_us": "microseconds", "_s": "s", "_m": "m", "_m_s": "m/s", "_m_s2": "m/s^2", "_rad": "rad",
         "_rad_s": "rad/s", "_deg": "deg", "_px": "px", "_hz": "Hz", "_m_px": "m/px", "_ms": "ms"}


def unit_of(column: str) -> str:
    """The unit a column's suffix names (the longest matching suffix), or ``""``."""
    best = ""
    for suffix in UNITS:
        if column.endswith(suffix) and len(suffix) > len(best):
            best = suffix
    return UNITS.get(best, "")


def _schema(stream: str, columns: dict[str, Any]) -> dict[str, Any]:
    props: dict[str, Any] = {}
    for name, values in columns.items():
        kind = ["number", "null"] if np.asarray(values).dtype.kind in "fiu" else "string"
        props[name] = {"type": kind, **({"description": unit_of(name)} if unit_of(name) else {})}
    return {"title": f"gsoe.{stream}", "type": "object", "properties": props}


def _rows(stream: str, cols: dict[str, Any]) -> Iterator[tuple[int, str, bytes]]:
    names = list(cols)
    numeric = {n: np.asarray(cols[n]).dtype.kind in "fiu" for n in names}
    t = np.asarray(cols["t_us"], dtype=float)
    for i in range(t.size):
        if not math.isfinite(t[i]) or t[i] < 0:
            continue
        rec: dict[str, Any] = {}
        for n in names:
            v = cols[n][i]
            if numeric[n]:
                f = float(v)
                rec[n] = (int(f) if n.endswith("_us") else f) if math.isfinite(f) else None
            else:
                rec[n] = str(v)
        yield int(t[i]), stream, json.dumps(rec, separators=(",", ":")).encode()


def export_mcap(folder: str | Path, out: str | Path | None = None) -> Path:
    """Write ``folder``'s ``*.csv`` streams (those with a ``t_us`` column) to ``out`` (default
    ``folder/flight.mcap``); returns the path."""
    from mcap.writer import CompressionType, Writer

    src = Path(folder)
    dst = Path(out) if out is not None else src / MCAP_FILE
    streams = {}
    for p in sorted(src.glob("*.csv")):
        cols = read_log(p)
        if cols and "t_us" in cols and np.asarray(cols["t_us"]).dtype.kind in "fiu":
            streams[p.stem] = cols
    if not streams:
        raise FileNotFoundError(2, "no CSV log with a t_us column", str(src))
    tmp = dst.with_suffix(".mcap.tmp")
    with tmp.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile="", library="gsoe-nav")
        channel = {}
        for name, cols in streams.items():
            sid = w.register_schema(name=f"gsoe.{name}", encoding="jsonschema",
                                    data=json.dumps(_schema(name, cols)).encode())
            channel[name] = w.register_channel(topic=TOPIC_PREFIX + name, message_encoding="json", schema_id=sid)
        seq: dict[str, int] = dict.fromkeys(streams, 0)
        for t_us, name, data in heapq.merge(*(_rows(n, c) for n, c in streams.items()), key=lambda r: r[0]):
            w.add_message(channel_id=channel[name], log_time=t_us * NS_PER_US, publish_time=t_us * NS_PER_US,
                          data=data, sequence=seq[name])
            seq[name] += 1
        w.finish()
    tmp.replace(dst)
    return dst
