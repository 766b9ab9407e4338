"""The fusion node's settings: one frozen record with every default in one place, read by the
node (:class:`~armfusion.fusion.service.serve.FusionNode`) and its tracking
(:class:`~armfusion.fusion.service.serve_tracking.NodeTracking`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from armfusion.fusion.service.admission import AdmissionSettings
from armfusion.fusion.service.lateness import Lateness
from armfusion.fusion.service.node import DEFAULT_QUEUE_SIZE
from armfusion.fusion.tracking.tracker import TrackerSettings


@dataclass(frozen=True)
class NodeSettings:
    """How the fusion node runs; every field has its default.

    ``tracker``: the tracker's settings (``None``: its own defaults). ``publish_hz``: most
    estimates published per second of sample time. ``min_data_s``: samples collected before
    the first search for a still stretch, then one every ``retry_s``; ``startup_keep_s``: until
    the tracker starts, how much of the latest samples the node keeps for its startup
    calibration (older batches are let go: a node waiting for a still arm holds, and searches
    on each retry, at most that much, however long it waits), at least twice ``min_data_s``.
    ``max_lag_s``: how long the merge of the sensors in time waits for a late sensor.
    ``recent_s``: how much of the latest samples the node keeps for a calibration on request;
    ``still_tolerance_s``: how far before the newest sample a still stretch may end and still
    be the arm's "now". ``assume_parked``: the ready pose as evidence for the startup's branches
    (``serve --assume-parked``); by default nothing but the data chooses them.

    ``state_path``: the saved state (see :mod:`armfusion.fusion.service.state_file`), written
    every ``save_period_s`` of wall time and at stop, and resumed from at start when it is no
    older than ``max_state_age_s`` and the encoders moved no faster than
    ``max_joint_rate_rad_s`` in between.

    ``silent_after_s``: a sensor none of whose batches arrived for that long (wall time) is
    ``stale`` in the status, also when every sensor stops and the tracker, which judges
    staleness in sample time, hears nothing. ``queue_size``: the receive channel's depth in
    messages. ``admission``: the bounds every raw batch is checked against
    (:mod:`armfusion.fusion.service.admission`; ``None``: its defaults). ``stall_after_s``:
    while tracking, no estimate for that long (wall time) while raw batches arrive is a stall,
    reported in the status. ``lateness``: when the node is degraded and what it does then
    (:class:`~armfusion.fusion.service.lateness.Lateness`).
    """

    tracker: TrackerSettings | None = None
    publish_hz: float = 50.0
    min_data_s: float = 2.0
    retry_s: float = 0.5
    startup_keep_s: float = 60.0
    max_lag_s: float = 0.1
    recent_s: float = 5.0
    still_tolerance_s: float = 0.3
    assume_parked: bool = False
    state_path: Path | None = None
    save_period_s: float = 1.0
    max_state_age_s: float = 60.0
    max_joint_rate_rad_s: float = 1.5
    silent_after_s: float = 0.5
    queue_size: int = DEFAULT_QUEUE_SIZE
    admission: AdmissionSettings | None = None
    stall_after_s: float = 1.0
    lateness: Lateness = field(default_factory=Lateness)

    def __post_init__(self) -> None:
        if not self.startup_keep_s >= 2.0 * self.min_data_s:
            raise ValueError(f"startup_keep_s must be at least twice min_data_s "
                             f"({2.0 * self.min_data_s:g} s), not {self.startup_keep_s!r}")
        if self.state_path is not None and not isinstance(self.state_path, Path):
            object.__setattr__(self, "state_path", Path(self.state_path))

    @property
    def publish_period_s(self) -> float:
        """The least sample time between two published estimates (s)."""
        return 1.0 / self.publish_hz
