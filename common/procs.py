"""Local processes of the software-in-the-loop harnesses (``nav.bench_companion``, ``sim.fuzz``,
``sim.sitl_mission``): a free port on 127.0.0.1 and stopping one process we started, by its id."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess

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
