"""Local processes of the software-in-the-loop harnesses (``nav.bench_companion``, ``sim.fuzz``,
``sim.sitl_mission``): a free port on 127.0.0.1, stopping one process we started, by its id, and what a flight of
the simulated vehicle and the companion left in its folder."""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

STOP_GRACE_S = 20.0        # time a process gets to exit after its signal before SIGKILL


def free_port(kind: int) -> int:
    """A free port on 127.0.0.1 (``socket.SOCK_DGRAM`` or ``socket.SOCK_STREAM``)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stop_process(p: subprocess.Popen[bytes], sig: int = signal.SIGINT, timeout_s: float = STOP_GRACE_S) -> None:
    """Stop one process we started, by its id: ``sig``, then SIGKILL after ``timeout_s``."""
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            p.send_signal(sig)
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=timeout_s)


@dataclass(frozen=True)
class SilFlight:
    """One SIL flight's results: the vehicle's JSON summary, the companion's final status, their folder."""

    vehicle: dict[str, Any]
    companion: dict[str, Any]
    companion_rc: int
    out_dir: Path

    @property
    def log_dir(self) -> Path:
        return self.out_dir / "log"


def sil_results(out_dir: Path,
                companion: subprocess.Popen[bytes] | None) -> tuple[dict[str, Any], dict[str, Any], int]:
    """What a SIL flight left: the vehicle's summary (``vehicle.json``), the companion's final status (its stdout,
    ``companion.out``), each ``{}`` when absent or empty, and the companion's exit code (-1: never started)."""
    summary = out_dir / "vehicle.json"
    vehicle = json.loads(summary.read_text()) if summary.exists() else {}
    text = (out_dir / "companion.out").read_text()
    return vehicle, json.loads(text) if text.strip() else {}, companion.returncode if companion is not None else -1
