"""Fault injection for the fake buses and devices: failed transactions on demand."""

from __future__ import annotations

import errno as errno_mod
import os
import random


def os_error(code: int) -> OSError:
    """The OSError the kernel's i2c-dev / spidev would hand to Python for ``code``."""
    return OSError(code, os.strerror(code))


class FaultInjector:
    """Decides, per transaction, whether it fails and with which errno.

    * :meth:`fail_next` — the next ``k`` transactions fail (a NACK burst);
    * :meth:`fail_randomly` — each transaction fails with a probability (seeded);
    * :meth:`stick` — every transaction fails until :meth:`clear` (a stuck bus).

    ``injected`` counts the failures it caused.
    """

    def __init__(self, seed: int = 0):
        self._rng = random.Random(seed)
        self._next: list[int] = []
        self._p = 0.0
        self._p_errno = errno_mod.EIO
        self._stuck: int | None = None
        self.injected = 0

    def fail_next(self, k: int = 1, errno: int = errno_mod.EIO) -> None:
        self._next.extend([errno] * k)

    def fail_randomly(self, probability: float, errno: int = errno_mod.EIO) -> None:
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"probability must be in [0, 1], got {probability!r}")
        self._p = probability
        self._p_errno = errno

    def stick(self, errno: int = errno_mod.ETIMEDOUT) -> None:
        self._stuck = errno

    def clear(self) -> None:
        self._next.clear()
        self._p = 0.0
        self._stuck = None

    @property
    def active(self) -> bool:
        return bool(self._next) or self._p > 0 or self._stuck is not None

    def check(self) -> None:
        """Raise the OSError for this transaction, if it is to fail."""
        code: int | None = None
        if self._stuck is not None:
            code = self._stuck
        elif self._next:
            code = self._next.pop(0)
        elif self._p > 0 and self._rng.random() < self._p:
            code = self._p_errno
        if code is not None:
            self.injected += 1
            raise os_error(code)
