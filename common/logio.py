"""The project's log format: one folder per run or flight, one CSV file per stream.

Format (documented once, read by ``pandas.read_csv(path)`` or ``numpy.genfromtxt(path, delimiter=",",
names=True)``): the first line is the header of column names, each with its unit suffix (``t_us``,
``roll_rad``, ``wind_n_m_s``); every following line is one record; numbers are written with the shortest
representation that reads back to the same float (Python's ``repr``), booleans 0/1, a missing number ``nan``,
infinities ``inf``/``-inf``, and text with its commas and newlines replaced by ``;`` and a space.  Every stream
starts with ``t_us`` (integer microseconds of one clock: simulation time in ``gsoe sim``, the companion's
monotonic clock in flight).  Streams used by ``gsoe sim`` and
the companion: ``truth.csv`` (simulator only), ``imu.csv``, ``attitude.csv``, ``airspeed.csv``, ``baro.csv``,
``gnss.csv``, ``gsoe.csv`` (optical steps), ``baseline.csv`` (the paper's filtered drift), ``ekf.csv`` (EKF
outputs with sigmas), ``aid_status.csv`` (per aid source and step: innovation, variance, test ratio, fused),
``outputs.csv`` (what was sent to the autopilot), ``events.csv`` (companion state changes and rejected inputs).

Writes are append-only and flushed to the OS at least every ``flush_interval_s`` (and on close), so a killed
process loses at most that much; a partially written last line is dropped by readers (``read_log``).

Runs never mix: ``gsoe sim``, ``gsoe replay`` and the companion take their folder through :func:`claim_run_folder`,
the one place that decides whether a folder holds another run's logs (a ``*.csv`` stream or ``metrics.json``) and
what then happens: refused (:class:`RunFolderInUse`), cleared of that run's files (``overwrite``), or a new
numbered folder beside it (``numbered``: ``DIR-2``, ``DIR-3``, ...).
"""

from __future__ import annotations

import csv
import io
import operator
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_FLUSH_INTERVAL_S = 0.5

_PLAIN_TYPES = frozenset((float, int, np.float64))
"""Types the C ``csv`` writer formats exactly as :func:`_fmt` would (shortest round-trip repr)."""


def _fmt(v: Any) -> str:
    """One CSV field (exact type checks first)."""
    t = type(v)
    if t is float or t is np.float64:
        return repr(float(v))
    if t is int:
        return str(v)
    if t is bool or t is np.bool_:
        return "1" if v else "0"
    if t is str:
        return v.replace(",", ";").replace("\n", " ")
    if v is None:
        return "nan"
    if isinstance(v, np.integer):
        return str(int(v))
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v).replace(",", ";").replace("\n", " ")
    return repr(f)


class CsvStream:
    """One append-only CSV stream with a fixed header."""

    def __init__(self, path: Path, columns: Sequence[str], flush_interval_s: float) -> None:
        self.path = path
        self.columns = tuple(columns)
        new = not path.exists() or path.stat().st_size == 0
        self._fh = path.open("a", buffering=1 << 16, newline="")
        if new:
            self._fh.write(",".join(self.columns) + "\n")
        self._writer = csv.writer(self._fh, lineterminator="\n")
        self._get = operator.itemgetter(*self.columns) if len(self.columns) > 1 else None
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()

    def write(self, record: Mapping[str, Any]) -> None:
        """Append one record; missing columns are written ``nan``, extra keys are ignored."""
        try:
            vals = list(self._get(record)) if self._get is not None else [record[self.columns[0]]]
        except KeyError:
            vals = [record.get(c) for c in self.columns]
        if not _PLAIN_TYPES.issuperset(map(type, vals)):  # the C writer's float/int output is already ours
            vals = [v if type(v) in _PLAIN_TYPES else _fmt(v) for v in vals]
        self._writer.writerow(vals)
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval_s:
            self.flush()
            self._last_flush = now

    def flush(self) -> None:
        self._fh.flush()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._fh.close()


#: files that mark a folder as holding a run's logs
RUN_LOG_PATTERNS = ("*.csv", "metrics.json")
#: files of a run that ``overwrite`` deletes (the logs, the metrics, the report and its figures)
RUN_OUTPUT_PATTERNS = ("*.csv", "metrics.json", "report.html", "*.png")


class RunFolderInUse(FileExistsError):
    """The folder holds another run's logs (the message names the folder, what is there, and the ways out)."""


def run_files(folder: str | Path, patterns: Sequence[str] = RUN_LOG_PATTERNS) -> list[Path]:
    """The files directly in ``folder`` that match ``patterns`` (none when it does not exist), sorted."""
    p = Path(folder)
    if not p.is_dir():
        return []
    return sorted({f for pat in patterns for f in p.glob(pat) if f.is_file()})


def claim_run_folder(folder: str | Path, *, overwrite: bool = False, numbered: bool = False) -> Path:
    """The folder a new run writes into, created; never one that holds another run's logs (:data:`RUN_LOG_PATTERNS`).

    When ``folder`` holds them: with ``overwrite`` the earlier run's files (:data:`RUN_OUTPUT_PATTERNS`, directly in
    the folder; anything else is left) are deleted first; else with ``numbered`` the first of ``folder-2``,
    ``folder-3``, ... that holds no run's logs is returned; else :class:`RunFolderInUse` is raised and nothing is
    touched.  ``NotADirectoryError`` when ``folder`` (or a numbered one) is a file.
    """
    p = Path(folder)
    if p.exists() and not p.is_dir():
        raise NotADirectoryError(f"{p} is a file, not a folder")
    held = run_files(p)
    if held and overwrite:
        for f in run_files(p, RUN_OUTPUT_PATTERNS):
            f.unlink()
    elif held and numbered:
        n = 2
        while run_files(p.with_name(f"{p.name}-{n}")) or p.with_name(f"{p.name}-{n}").is_file():
            n += 1
        p = p.with_name(f"{p.name}-{n}")
    elif held:
        names = ", ".join(f.name for f in held[:3]) + (", ..." if len(held) > 3 else "")
        raise RunFolderInUse(f"{p} holds the logs of another run ({names}); choose another folder or add "
                             "--overwrite to replace them")
    p.mkdir(parents=True, exist_ok=True)
    return p


class RunLog:
    """A log folder of CSV streams, created on first write of each stream."""

    def __init__(self, folder: str | Path, flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._streams: dict[str, CsvStream] = {}
        self._flush_interval_s = flush_interval_s

    def write(self, stream: str, record: Mapping[str, Any]) -> None:
        s = self._streams.get(stream)
        if s is None:
            s = CsvStream(self.folder / f"{stream}.csv", list(record.keys()), self._flush_interval_s)
            self._streams[stream] = s
        s.write(record)

    def flush(self) -> None:
        for s in self._streams.values():
            s.flush()

    def close(self) -> None:
        for s in self._streams.values():
            s.close()

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Decimator:
    """A sink in front of :meth:`RunLog.write` that writes a stream's record only when at least ``periods_s[stream]``
    has passed since the last one written (streams not named: every record).  Records are told apart by
    ``keys[stream]`` columns, each value combination with its own clock (``aid_status``: per source and per
    rejected/not, so every change from fused to rejected is written).  Records without a ``t_us`` pass."""

    def __init__(self, write: Callable[[str, Mapping[str, Any]], None], periods_s: Mapping[str, float],
                 keys: Mapping[str, Sequence[str]] | None = None) -> None:
        self._write = write
        self._period_us = {k: round(v * 1e6) for k, v in periods_s.items()}
        self._keys = dict(keys or {})
        self._last: dict[tuple[Any, ...], int] = {}
        self.dropped: dict[str, int] = {}

    def __call__(self, stream: str, record: Mapping[str, Any]) -> None:
        period = self._period_us.get(stream)
        t = record.get("t_us")
        if period is None or not isinstance(t, int | np.integer):
            self._write(stream, record)
            return
        key = (stream, *(record.get(c) for c in self._keys.get(stream, ())))
        last = self._last.get(key)
        if last is not None and last <= t < last + period:
            self.dropped[stream] = self.dropped.get(stream, 0) + 1
            return
        self._last[key] = int(t)
        self._write(stream, record)

    def wants(self, stream: str, t_us: Any, *key: Any) -> bool:
        """Whether a record of ``stream`` stamped ``t_us`` (with ``key``: the values of its ``keys[stream]``
        columns) would be written now.  One that would not is counted as dropped here, so a writer may skip
        building it (a record per IMU sample, of which one in 24 is written)."""
        period = self._period_us.get(stream)
        if period is None or not isinstance(t_us, int | np.integer):
            return True
        last = self._last.get((stream, *key))
        if last is not None and last <= t_us < last + period:
            self.dropped[stream] = self.dropped.get(stream, 0) + 1
            return False
        return True


def read_log(path: str | Path) -> dict[str, Any]:
    """Read one stream into a dict of numpy arrays (column name -> array), dropping a torn last line."""
    text = Path(path).read_text()
    lines = text.splitlines()
    if not lines:
        return {}
    header = lines[0].split(",")
    rows = [ln for ln in lines[1:] if ln.count(",") == len(header) - 1]
    if text and not text.endswith("\n") and rows and rows[-1] == lines[-1]:
        rows = rows[:-1]  # torn write
    reader = csv.reader(io.StringIO("\n".join(rows)))
    cols: list[list[str]] = [[] for _ in header]
    for r in reader:
        for i, v in enumerate(r):
            cols[i].append(v)
    out: dict[str, Any] = {}
    for name, vals in zip(header, cols, strict=True):
        try:
            out[name] = np.array([float(v) for v in vals])
        except ValueError:
            out[name] = np.array(vals)
    return out
