"""What the fusion node says of itself: its status (counters, each sensor's status and a
message) every second on ``armfusion/<robot>/status``, and its report when it stops
(:class:`ServeReport`, ``serve --json``)."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field

from armfusion.fusion.service.admission import Admission
from armfusion.fusion.service.lateness import LagWatch
from armfusion.fusion.service.node import StallWatch


@dataclass(frozen=True)
class ServeReport:
    robot: str
    state: str
    samples: int
    estimates: int
    out_of_order: int
    dropped: dict[str, int]
    startup_t_s: float | None
    message: str
    resumed: bool = False
    resume_message: str = ""
    calibrations: int = 0
    missed_batches: int = 0
    seq_resets: int = 0
    encoder_rebases: int = 0
    stalls: int = 0
    errors: int = 0
    refused_samples: dict[str, int] | None = None
    """The samples of the raw batches the admission refused, by reason (``dropped`` counts
    payloads and batches)."""
    degraded_periods: int = 0
    folded_instants: int = 0
    lag_max_ms: int = 0
    shed_batches: int = 0
    shed_samples: int = 0

    def as_dict(self) -> dict:
        return {"robot": self.robot, "state": self.state, "samples": self.samples,
                "estimates": self.estimates, "out_of_order": self.out_of_order,
                "dropped": self.dropped, "startup_t_s": self.startup_t_s, "message": self.message,
                "resumed": self.resumed, "resume_message": self.resume_message,
                "calibrations": self.calibrations, "missed_batches": self.missed_batches,
                "seq_resets": self.seq_resets, "encoder_rebases": self.encoder_rebases,
                "stalls": self.stalls, "errors": self.errors,
                "refused_samples": dict(self.refused_samples or {}),
                "degraded_periods": self.degraded_periods, "folded_instants": self.folded_instants,
                "lag_max_ms": self.lag_max_ms, "shed_batches": self.shed_batches,
                "shed_samples": self.shed_samples}


@dataclass
class NodeBoard:
    """What the fusion node's parts say for its status: its ``state`` (``starting``,
    ``calibrating``, ``tracking``, ``stopping``), its ``message``, whether a status is ``due``
    before the next second's (a sensor's status changed, an alarm, a new start), and its own
    ``counts`` (see :class:`NodeCounts`)."""

    state: str = "starting"
    message: str = "waiting for samples"
    due: bool = False
    counts: Counter[str] = field(default_factory=Counter)


@dataclass(frozen=True)
class NodeCounts:
    """What the node's status and report count, from where each is kept: ``counts`` the node's
    own (``samples``, ``estimates``, ``out_of_order``, ``errors``, ``calibrations``,
    ``alarms``, ``shed_batches``, ``shed_samples``), the admission's, the stall watch's and
    the lag watch's; ``dropped`` the payloads and batches dropped, by reason."""

    counts: Counter[str]
    admission: Admission
    stall: StallWatch
    lag: LagWatch
    dropped: dict[str, int]

    def status_counters(self) -> dict[str, int]:
        """The status's counters, in the order they are published."""
        c, adm, lag = self.counts, self.admission, self.lag
        counters = {"samples": c["samples"], "estimates": c["estimates"], "out_of_order": c["out_of_order"],
                    "missed_batches": adm.missed_batches, "seq_resets": adm.seq_resets,
                    "encoder_rebases": adm.encoder_rebases,
                    "stalled": int(self.stall.since_s is not None), "stalls": self.stall.stalls,
                    "errors": c["errors"], "calibrations": c["calibrations"], "model_alarms": c["alarms"],
                    "degraded": int(lag.degraded), "lag_ms": int(round(1e3 * lag.lag_s)),
                    "degraded_periods": lag.periods, "folded_instants": lag.folded,
                    "shed_batches": c["shed_batches"]}
        counters.update({f"dropped.{k}": v for k, v in self.dropped.items()})
        return counters

    def report(self, robot: str, state: str, startup_t_s: float | None, message: str, resumed: bool,
               resume_message: str) -> ServeReport:
        """The node's report when it stops."""
        c, adm, lag = self.counts, self.admission, self.lag
        return ServeReport(robot, state, c["samples"], c["estimates"], c["out_of_order"], self.dropped,
                           startup_t_s, message, resumed, resume_message, c["calibrations"],
                           adm.missed_batches, adm.seq_resets, adm.encoder_rebases, self.stall.stalls,
                           c["errors"], dict(adm.rejected_samples), lag.periods, lag.folded,
                           int(round(1e3 * lag.lag_max_s)), c["shed_batches"], c["shed_samples"])


def status_message(message: str, *, maneuver, tracker, lag: LagWatch, every_sensor_quiet_s: float | None,
                   stall: StallWatch) -> str:
    """The status's message: the node's own ``message``, led by what a reader must see first
    (a stall, every sensor quiet for ``every_sensor_quiet_s``, being degraded, a model-change
    alarm, a sensor the gate rejects more than its share, a maneuver under way)."""
    if maneuver is not None and maneuver.state in ("recording", "fitting", "failed"):
        message = f"maneuver {maneuver.state}: {maneuver.message}; {message}"
    if tracker is not None and tracker.t_s is not None:
        # a sensor the gate rejects (or the screen leaves out) more than its share, and why
        warnings = tracker.sensor_warnings()
        if warnings:
            message = "; ".join(warnings) + f"; {message}"
    if tracker is not None and tracker.alarm.active:
        message = "model changed: " + "; ".join(a.line() for a in tracker.alarm.alarms) + f"; {message}"
    if lag.degraded:
        held = ("" if lag.lag_s > lag.lateness.degrade_after_s else
                f" (held for {lag.lateness.hold_s:g} s after it was last behind)")
        message = (f"degraded: {1e3 * lag.lag_s:.0f} ms behind the sensors{held}; folding the backlog "
                   f"({1.0 / lag.lateness.fold_period_s:.0f} instants a second of it); {message}")
    if every_sensor_quiet_s is not None:
        message = f"no samples for {every_sensor_quiet_s:.1f} s: every sensor stale; {message}"
    if stall.since_s is not None:
        message = (f"stalled: no estimate for {time.monotonic() - stall.since_s:.1f} s while raw "
                   f"batches arrived; {message}")
    return message
