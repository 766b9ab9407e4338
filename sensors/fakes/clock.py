"""A fake monotonic clock: time moves only when someone sleeps or a bus transfers."""

from __future__ import annotations

import random


class FakeClock:
    """``monotonic()`` / ``sleep()`` / ``advance()`` on simulated time (seconds).

    ``sleep_jitter_s`` adds a seeded uniform oversleep in ``[0, sleep_jitter_s]`` to
    every ``sleep`` with a positive duration, the way a Linux process oversleeps.
    The fake buses advance it by each transfer's wire time, so read times are real
    numbers in tests. Pass ``clock.monotonic`` and ``clock.sleep`` to the drivers
    and the sampling loop.
    """

    def __init__(self, start_s: float = 1000.0, *, sleep_jitter_s: float = 0.0, seed: int = 0):
        self._t = float(start_s)
        self.sleep_jitter_s = sleep_jitter_s
        self._rng = random.Random(seed)
        self.slept_s = 0.0

    def monotonic(self) -> float:
        return self._t

    __call__ = monotonic

    def advance(self, dt_s: float) -> None:
        if dt_s < 0:
            raise ValueError(f"time does not go backwards (advance {dt_s!r} s)")
        self._t += dt_s

    def sleep(self, dt_s: float) -> None:
        if dt_s <= 0:
            return
        extra = self._rng.uniform(0.0, self.sleep_jitter_s) if self.sleep_jitter_s else 0.0
        self.slept_s += dt_s + extra
        self._t += dt_s + extra
