"""The fusion node's keys on a Zenoh session: the raw batches it subscribes to, the joint
state, heading, status and health it publishes, the liveliness token it holds while it
runs, and the ``calibrate`` queryable whose requests wait in a queue for the node's loop."""

from __future__ import annotations

import queue

import zenoh
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.node import BoundedReceiver


class NodeEndpoints:
    """Declared on ``session`` for ``robot`` in this order: the publishers (``state/joints``,
    ``state/heading``, ``status``, ``health``), the liveliness token on ``status``, the
    subscriber to ``raw/*`` feeding ``receiver``, and the ``calibrate`` queryable."""

    def __init__(self, session: zenoh.Session, robot: str, receiver: BoundedReceiver):
        self.robot = robot
        self._queries: queue.Queue = queue.Queue()
        self._joints = session.declare_publisher(pl.joints_key(robot))
        self._heading = session.declare_publisher(pl.heading_key(robot))
        self._status = session.declare_publisher(pl.status_key(robot))
        self._health = session.declare_publisher(pl.health_key(robot))
        self._token = session.liveliness().declare_token(pl.status_key(robot))
        self._sub = session.declare_subscriber(pl.raw_keys(robot), receiver)
        self._queryable = session.declare_queryable(pl.calibrate_key(robot), self._queries.put)

    def estimate(self, e) -> None:
        """An estimate's two records, on ``state/joints`` and ``state/heading``."""
        self._joints.put(pl.encode(pl.JointState.of(self.robot, e)))
        self._heading.put(pl.encode(pl.Heading.of(self.robot, e)))

    def health(self, t_s: float, alarms) -> None:
        """The tracker's active model-change ``alarms`` at sample time ``t_s``."""
        self._health.put(pl.encode(pl.Health.of(self.robot, t_s, alarms)))

    def status(self, status: pl.Status) -> None:
        self._status.put(pl.encode(status))

    def next_query(self):
        """The oldest ``calibrate`` request waiting, or ``None``."""
        try:
            return self._queries.get_nowait()
        except queue.Empty:
            return None

    def reply(self, query, result: pl.Calibration) -> None:
        try:
            query.reply(pl.calibrate_key(self.robot), pl.encode(result))
        finally:
            query.drop()

    def close_queries(self, why: str) -> None:
        """No more ``calibrate`` requests: the queryable undeclared, those waiting refused
        with ``why``."""
        self._queryable.undeclare()
        while (query := self.next_query()) is not None:
            self.reply(query, pl.Calibration(self.robot, False, why))

    def close(self) -> None:
        """The subscriber, the token and the publishers undeclared (after :meth:`close_queries`)."""
        self._sub.undeclare()
        self._token.undeclare()
        for p in (self._joints, self._heading, self._status, self._health):
            p.undeclare()
