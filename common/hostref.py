"""What host a speed figure was measured on: its CPU, its Python build and three reference timings.

The speed goals are figures "on this machine", and machines of one kind differ, even from one minute to the next on a
shared host (docs/speed.md).  Every benchmark prints this record beside its figures, so that a figure can be
compared with one from another host by the reference timings, not by the host's name:

- ``python_loop_ns``: one iteration of a fixed pure-Python loop (float arithmetic, a call, a list append), the
  interpreter's speed, which the filter's and the simulator's per-sample code follows;
- ``numpy_matmul_24_us``: a 24 x 24 ``@`` (the EKF covariance's size), NumPy's per-call cost;
- ``match_template_us``: ``cv2.matchTemplate`` (SSD) of a 19 x 19 template in a 121 x 73 image, IPP off, one thread
  (the paper's exhaustive search; native code).

Each timing is the median of several repeats; the whole record takes under a second.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import sysconfig
import time
from collections.abc import Callable
from typing import Any

import numpy as np

_REPEATS = 7


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if line.lower().startswith(("model name", "hardware", "cpu model")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _median_per_call(fn: Callable[[], object], calls: int) -> float:
    """Median over :data:`_REPEATS` of the time per call of ``fn`` run ``calls`` times (s)."""
    out = []
    for _ in range(_REPEATS):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        out.append((time.perf_counter() - t0) / calls)
    return statistics.median(out)


def _python_loop() -> None:
    acc: list[float] = []
    x = 0.5
    for i in range(1000):
        x = x * 0.999 + abs(i - 500.0) * 1e-3
        acc.append(x)


def _python_loop_ns() -> float:
    return 1e9 * _median_per_call(_python_loop, 20) / 1000.0


def _numpy_matmul_us() -> float:
    a = np.random.default_rng(0).standard_normal((24, 24))
    return 1e6 * _median_per_call(lambda: a @ a, 500)


def _match_template_us() -> float:
    import cv2

    rng = np.random.default_rng(0)
    image = rng.uniform(0.0, 255.0, (73, 121)).astype(np.float32)
    tpl = image[27:46, 51:70].copy()
    ipp, threads = cv2.ipp.useIPP(), cv2.getNumThreads()
    cv2.ipp.setUseIPP(False)
    cv2.setNumThreads(1)
    try:
        return 1e6 * _median_per_call(lambda: cv2.matchTemplate(image, tpl, cv2.TM_SQDIFF), 100)
    finally:
        cv2.ipp.setUseIPP(ipp)
        cv2.setNumThreads(threads)


def host_reference() -> dict[str, Any]:
    """The host record (module docstring)."""
    config_args = str(sysconfig.get_config_var("CONFIG_ARGS") or "")
    return {
        "cpu": _cpu_model(),
        "machine": platform.machine(),
        "cores": os.cpu_count() or 0,
        "python": platform.python_version(),
        "python_optimized_build": "--enable-optimizations" in config_args,   # PGO
        "python_executable": sys.executable,
        "python_loop_ns": round(_python_loop_ns(), 1),
        "numpy_matmul_24_us": round(_numpy_matmul_us(), 2),
        "match_template_us": round(_match_template_us(), 1),
    }


def describe(ref: dict[str, Any]) -> str:
    """One line for a benchmark's output."""
    pgo = "PGO build" if ref["python_optimized_build"] else "no PGO"
    return (f"host: {ref['cpu']} ({ref['machine']}, {ref['cores']} cores), Python {ref['python']} ({pgo}); "
            f"reference: Python loop {ref['python_loop_ns']:.0f} ns/iteration, NumPy 24x24 matmul "
            f"{ref['numpy_matmul_24_us']:.2f} us, matchTemplate 121x73/19x19 (no IPP) "
            f"{ref['match_template_us']:.0f} us")
