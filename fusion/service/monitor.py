"""``armfusion monitor``: what every robot on the Zenoh network is doing, live.

A :class:`Monitor` subscribes to ``armfusion/*/state/joints``, ``armfusion/*/state/heading``
and ``armfusion/*/status``, and to the liveliness tokens on ``armfusion/*/status`` (with
their history, so robots already running are seen at once): a robot appears with its first
message or token and is marked gone when its fusion node's token vanishes. Every payload is
checked on receipt (:class:`~armfusion.fusion.service.inbox.Inbox`: a bad one is counted and
dropped). :meth:`Monitor.snapshot` gives, per robot, the last joint state (angles, sigma,
flags), the heading, each node's state and counters, and the age of the last update;
:func:`render` draws it as a rich table and :func:`snapshot_json` as one JSON document.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.inbox import Inbox

ALL_JOINTS = f"{pl.ROOT}/*/state/joints"
ALL_HEADINGS = f"{pl.ROOT}/*/state/heading"
ALL_STATUS = f"{pl.ROOT}/*/status"


@dataclass
class RobotView:
    """What the monitor knows of one robot (times on this process's monotonic clock)."""

    robot: str
    alive: bool | None = None
    """The fusion node's liveliness token: True while it lives, False once it vanished,
    None while none was seen."""
    joints: pl.JointState | None = None
    heading: pl.Heading | None = None
    nodes: dict[str, pl.Status] = field(default_factory=dict)
    joint_messages: int = 0
    last_update_s: float | None = None

    def age_s(self, now_s: float) -> float | None:
        return None if self.last_update_s is None else now_s - self.last_update_s


class Monitor:
    """Subscribes on ``session`` until :meth:`close`; thread-safe snapshots."""

    def __init__(self, session: zenoh.Session, robots: tuple[str, ...] = ()):
        self.session = session
        self.robots = tuple(pl.check_name(r, "robot") for r in robots)
        self._lock = threading.Lock()
        self._views: dict[str, RobotView] = {}
        self._inbox = Inbox("monitor")
        self._subs = [session.declare_subscriber(k, self._on_sample)
                      for k in (ALL_JOINTS, ALL_HEADINGS, ALL_STATUS)]
        self._subs.append(session.liveliness().declare_subscriber(ALL_STATUS, self._on_token,
                                                                   history=True))

    def _view(self, robot: str) -> RobotView | None:
        if self.robots and robot not in self.robots:
            return None
        return self._views.setdefault(robot, RobotView(robot))

    def _on_sample(self, sample: zenoh.Sample) -> None:
        payload = self._inbox.decode(str(sample.key_expr), sample.payload.to_bytes())
        if payload is None:
            return
        now = time.monotonic()
        with self._lock:
            v = self._view(payload.robot)
            if v is None:
                return
            v.last_update_s = now
            if isinstance(payload, pl.JointState):
                v.joints = payload
                v.joint_messages += 1
            elif isinstance(payload, pl.Heading):
                v.heading = payload
            elif isinstance(payload, pl.Status):
                v.nodes[payload.node] = payload

    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            robot, kind, _ = pl.parse_key(str(sample.key_expr))
        except pl.PayloadError:
            return
        if kind != "status":
            return
        with self._lock:
            v = self._view(robot)
            if v is not None:
                v.alive = sample.kind == zenoh.SampleKind.PUT
                v.last_update_s = time.monotonic()

    def snapshot(self) -> dict[str, RobotView]:
        """A copy of every robot's view, by name."""
        with self._lock:
            return {k: RobotView(v.robot, v.alive, v.joints, v.heading, dict(v.nodes),
                                 v.joint_messages, v.last_update_s)
                    for k, v in sorted(self._views.items())}

    def with_joints(self) -> int:
        """Robots from which a joint state has come."""
        with self._lock:
            return sum(1 for v in self._views.values() if v.joints is not None)

    def with_state(self) -> int:
        """Robots from which both halves of an estimate have come: a joint state and a heading
        (a node publishes them one after the other)."""
        with self._lock:
            return sum(1 for v in self._views.values() if v.joints is not None and v.heading is not None)

    @property
    def dropped(self) -> dict[str, int]:
        return self._inbox.dropped

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


# --- output -----------------------------------------------------------------------------------


def _deg(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(math.degrees(x), 4)


def view_json(v: RobotView, now_s: float) -> dict[str, Any]:
    j, h = v.joints, v.heading
    age = v.age_s(now_s)
    return {
        "alive": v.alive,
        "age_s": None if age is None else round(age, 3),
        "joint_messages": v.joint_messages,
        "joints": None if j is None else {
            "t_s": j.t_s,
            **{n: {"deg": _deg(q), "sigma_deg": _deg(s), "flag": f}
               for n, q, s, f in zip(j.joint_names, j.q_rad, j.sigma_rad, j.flags, strict=True)}},
        "sensors": {} if j is None else dict(j.sensors),
        "heading": None if h is None else {"t_s": h.t_s, "deg": _deg(h.heading_rad),
                                           "sigma_deg": _deg(h.heading_sigma_rad),
                                           "magnetic_disturbance": h.magnetic_disturbance,
                                           "status": h.heading_status},
        "nodes": {n: {"state": s.state, "message": s.message, "counters": dict(s.counters)}
                  for n, s in sorted(v.nodes.items())},
    }


def snapshot_json(monitor: Monitor) -> dict[str, Any]:
    now = time.monotonic()
    return {"robots": {k: view_json(v, now) for k, v in monitor.snapshot().items()},
            "dropped": monitor.dropped}


def _counters(v: RobotView) -> str:
    """Samples published (drivers) / received (serve), and what was dropped."""
    out = []
    drv = v.nodes.get("drivers") or v.nodes.get("replay")
    if drv is not None:
        out.append(f"out {sum(n for k, n in drv.counters if k.startswith('samples.'))}")
    srv = v.nodes.get("serve")
    if srv is not None:
        c = dict(srv.counters)
        out.append(f"in {c.get('samples', 0)}")
        drops = sum(n for k, n in c.items() if k.startswith("dropped.")) + c.get("out_of_order", 0)
        out.append(f"dropped {drops}")
    return "\n".join(out) or "-"


def render(monitor: Monitor):
    """The monitor's table (a rich renderable)."""
    from rich.table import Table

    now = time.monotonic()
    views = monitor.snapshot()
    t = Table(title=f"armfusion monitor: {len(views)} robot{'s' if len(views) != 1 else ''}",
              title_justify="left", show_lines=True)
    for col in ("robot", "joints [deg ± sigma, flag]", "heading [deg]", "nodes", "samples",
                "age [s]"):
        t.add_column(col, justify="right" if col in ("age [s]",) else "left",
                     no_wrap=col.startswith("joints"))
    for name, v in views.items():
        label = name + ("" if v.alive is None else ("\n[green]alive[/]" if v.alive else "\n[red]gone[/]"))
        joints = "-"
        if v.joints is not None:
            rows = []
            for n, q, s, f in zip(v.joints.joint_names, v.joints.q_rad, v.joints.sigma_rad,
                                  v.joints.flags, strict=True):
                colour = "green" if f == "ok" else "yellow"
                rows.append(f"{n} {math.degrees(q):7.2f}±{math.degrees(s):<5.2f} [{colour}]{f}[/]")
            joints = "\n".join(rows)
        heading = "-"
        if v.heading is not None:
            h = v.heading
            heading = f"{math.degrees(h.heading_rad):7.2f} ± {math.degrees(h.heading_sigma_rad):.2f}"
            if h.heading_status != "compass_fused":
                heading += f"\n[yellow]{h.heading_status.replace('_', ' ')}[/]"
        nodes = "\n".join(f"{n}: {s.state}" + (" [red]stalled[/]" if dict(s.counters).get("stalled") else "")
                          for n, s in sorted(v.nodes.items())) or "-"
        age = v.age_s(now)
        t.add_row(label, joints, heading, nodes, _counters(v), "-" if age is None else f"{age:.1f}")
    if monitor.dropped:
        t.caption = "dropped payloads: " + ", ".join(f"{k} {n}" for k, n in monitor.dropped.items())
    return t
