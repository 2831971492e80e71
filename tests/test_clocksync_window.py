"""nav.link.ClockSync keeps the least-delayed offset of a sliding window: the O(1) sliding minimum gives what the
minimum over every sample in the window gives (receive times from the companion's monotonic clock)."""

from __future__ import annotations

import numpy as np

from nav.link import ClockSync


def test_sliding_minimum_equals_the_minimum_over_the_window():
    rng = np.random.default_rng(5)
    window_s = 0.5
    sync = ClockSync(window_s)
    seen: list[tuple[int, int]] = []
    recv = 0
    for k in range(3000):
        vehicle = k * 20_000 + int(rng.integers(-3_000, 3_000))          # jittery stamps at 50 Hz
        recv = max(recv, vehicle + int(rng.exponential(8_000)))          # delays, never back in time
        if rng.random() < 0.05:
            recv += int(rng.integers(0, 300_000))                        # a stall of the link
        got = sync.observe(vehicle, recv)
        seen.append((recv, recv - vehicle))
        best = min(d for r, d in seen[-200:] if r >= recv - window_s * 1e6)
        assert sync.offset_us == best and got == vehicle + best
