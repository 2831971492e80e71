"""Waiting in tests that talk to other threads or processes over a link: until a condition holds, or gathering what
arrives for a while (one copy for every link test)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import TypeVar

T = TypeVar("T")


def wait_for(cond: Callable[[], object], timeout_s: float = 5.0) -> bool:
    """Whether ``cond()`` became true within ``timeout_s`` (asked every 50 ms)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return False


def gather(poll: Callable[[], Iterable[T]], seconds: float = 0.5) -> list[T]:
    """Everything ``poll()`` returns, called every 10 ms for ``seconds`` (e.g. an endpoint's received messages)."""
    out: list[T] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out += poll()
        time.sleep(0.01)
    return out
