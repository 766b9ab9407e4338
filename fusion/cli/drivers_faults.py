"""Bus and device faults on the register-level fakes, for ``armfusion drivers --fake --fault``.

A fault is written ``TARGET:KIND[=VALUE][@T0[-T1]]`` (:func:`parse_fault`, the kinds in
:data:`FAULT_KINDS`); a :class:`FaultSchedule` applies the specs to a
:class:`~armfusion.sensors.fakes.FakeRig` as its simulated time passes. See docs/drivers.md.
"""

from __future__ import annotations

import errno as errno_mod
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from armfusion.sensors.fakes import FakeRig
from armfusion.sensors.fakes.faults import FaultInjector

FAULT_KINDS = {
    "nack": "the next K transactions fail with EIO (default K = 1), at T0",
    "random": "each transaction fails with probability P (EIO) from T0 to T1",
    "stuck": "every transaction times out (ETIMEDOUT) from T0 to T1",
    "unplug": "the device stops answering at T0 and is plugged back (power-cycled) at T1",
    "mag-overflow": "the IMU's AK8975 reports overflow (HOFL) from T0 to T1",
}
_FAULT_RE = re.compile(
    r"^(?P<target>[A-Za-z_][\w.]*):(?P<kind>[a-z-]+)(?:=(?P<value>[0-9.eE+-]+))?"
    r"(?:@(?P<t0>[0-9.]+)(?:-(?P<t1>[0-9.]+))?)?$")


@dataclass(frozen=True)
class FaultSpec:
    """``TARGET:KIND[=VALUE][@T0[-T1]]``: a device (``acc3``, ``imu``, ``imu.mag``) or a bus
    (``i2c1``, ``spi``), a kind of :data:`FAULT_KINDS`, times in seconds since power-up
    (default: from the first tick to the end)."""

    text: str
    target: str
    kind: str
    value: float | None = None
    t_start_s: float = 0.0
    t_end_s: float | None = None


def parse_fault(text: str) -> FaultSpec:
    m = _FAULT_RE.match(text.strip())
    if m is None:
        raise ValueError(f"--fault {text!r}: expected TARGET:KIND[=VALUE][@T0[-T1]], e.g. "
                         "acc3:unplug@2-3, i2c1:random=0.02, imu:nack=2@1")
    kind = m["kind"]
    if kind not in FAULT_KINDS:
        raise ValueError(f"--fault {text!r}: unknown kind {kind!r}; kinds: {', '.join(FAULT_KINDS)}")
    value = float(m["value"]) if m["value"] is not None else None
    if kind == "random" and (value is None or not 0.0 < value <= 1.0):
        raise ValueError(f"--fault {text!r}: random needs a probability in (0, 1], e.g. random=0.02")
    if kind == "nack" and value is not None and (value < 1 or value != int(value)):
        raise ValueError(f"--fault {text!r}: nack takes a whole number of transactions")
    t0 = float(m["t0"]) if m["t0"] is not None else 0.0
    t1 = float(m["t1"]) if m["t1"] is not None else None
    if t1 is not None and t1 <= t0:
        raise ValueError(f"--fault {text!r}: the end time must come after the start")
    return FaultSpec(text, m["target"], kind, value, t0, t1)


class FaultSchedule:
    """Applies fault specs to a rig as simulated time passes (:meth:`step` before each tick)."""

    def __init__(self, rig: FakeRig, specs: Sequence[FaultSpec]):
        self.rig = rig
        self._pending: list[tuple[float, Callable[[], None]]] = []
        self.injectors: dict[str, FaultInjector] = {}
        for spec in specs:
            start, stop = self._actions(spec)
            self._pending.append((spec.t_start_s, start))
            if spec.t_end_s is not None and stop is not None:
                self._pending.append((spec.t_end_s, stop))
        self._pending.sort(key=lambda p: p[0])

    def _injector(self, spec: FaultSpec) -> FaultInjector:
        rig, target = self.rig, spec.target
        if target == "spi":
            inj = rig.spi.faults
        elif re.fullmatch(r"i2c\d+", target):
            n = int(target[3:])
            if n not in rig.i2c:
                raise ValueError(f"--fault {spec.text!r}: no I2C bus {n} on the rig")
            inj = rig.i2c[n].faults
        elif target.endswith(".mag") and target[:-4] in rig.devices and \
                hasattr(rig.devices[target[:-4]], "ak8975"):
            inj = rig.devices[target[:-4]].ak8975.faults  # type: ignore[attr-defined]
        elif target in rig.devices:
            inj = rig.devices[target].faults
        else:
            raise ValueError(f"--fault {spec.text!r}: no device or bus {target!r}; targets: "
                             f"{', '.join([*rig.devices, 'imu.mag', *(f'i2c{n}' for n in rig.i2c), 'spi'])}")
        self.injectors[target] = inj
        return inj

    def _actions(self, spec: FaultSpec) -> tuple[Callable[[], None], Callable[[], None] | None]:
        if spec.kind == "unplug":
            dev = self.rig.devices.get(spec.target)
            if dev is None:
                raise ValueError(f"--fault {spec.text!r}: unplug takes a device "
                                 f"({', '.join(self.rig.devices)})")
            self.injectors.setdefault(spec.target, dev.faults)
            return dev.disappear, dev.reappear
        if spec.kind == "mag-overflow":
            dev = self.rig.devices.get(spec.target.removesuffix(".mag"))
            ak = getattr(dev, "ak8975", None)
            if ak is None:
                raise ValueError(f"--fault {spec.text!r}: mag-overflow takes the IMU")

            def on() -> None:
                ak.force_overflow = True

            def off() -> None:
                ak.force_overflow = False

            return on, off
        inj = self._injector(spec)
        if spec.kind == "nack":
            k = int(spec.value or 1)
            return (lambda: inj.fail_next(k, errno_mod.EIO)), None
        if spec.kind == "random":
            p = float(spec.value or 0.0)
            return (lambda: inj.fail_randomly(p, errno_mod.EIO)), inj.clear
        return (lambda: inj.stick(errno_mod.ETIMEDOUT)), inj.clear  # stuck

    def step(self, t_s: float) -> None:
        """Apply every action due at or before ``t_s`` (seconds since power-up)."""
        while self._pending and self._pending[0][0] <= t_s:
            _, action = self._pending.pop(0)
            action()

    def injected(self) -> int:
        """Failed transactions caused so far (unplugged devices NACK on their own)."""
        return sum(inj.injected for inj in self.injectors.values())
