"""Requests to a fusion node (``armfusion serve``) over Zenoh queries, answered with a payload:

- ``armfusion/<robot>/calibrate`` (``armfusion recalibrate``): re-run the startup calibration
  now; the reply is a :class:`~armfusion.fusion.service.payloads.Calibration` (accepted with the result,
  or refused with the reason);
- ``armfusion/<robot>/maneuver`` and ``maneuver/start``, ``/done``, ``/abort``
  (``armfusion maneuver``): the planned calibration maneuver the node serves, and its run;
  the reply is a :class:`~armfusion.fusion.service.payloads.Maneuver`.
"""

from __future__ import annotations

import zenoh
from armfusion.fusion.service import payloads as pl


class NoReplyError(RuntimeError):
    """No fusion node answered (none runs for that robot, or it is not reachable)."""


def ask(session: zenoh.Session, key: str, expected: type, timeout_s: float):
    """The first reply to a query on ``key``, which must be an ``expected`` payload.

    Raises :class:`NoReplyError` when no node answers within ``timeout_s`` (or answers with an
    error), and :class:`~armfusion.fusion.service.payloads.PayloadError` when the reply is not a valid
    payload of that type.
    """
    for reply in session.get(key, timeout=timeout_s):
        if reply.ok is not None:
            sample = reply.ok
            payload = pl.decode(str(sample.key_expr), sample.payload.to_bytes())
            if not isinstance(payload, expected):
                raise pl.PayloadError("malformed", f"a {type(payload).__name__} in reply on {key}")
            return payload
        raise NoReplyError(f"{key}: the node answered with an error: {reply.err.payload.to_string()[:300]}")
    raise NoReplyError(f"{key}: no fusion node answered within {timeout_s:g} s (is `armfusion serve "
                       f"--robot {key.split('/')[1]}` running and connected?)")


def request_calibration(session: zenoh.Session, robot: str, timeout_s: float = 10.0) -> pl.Calibration:
    """The reply of ``robot``'s fusion node to a calibration request."""
    return ask(session, pl.calibrate_key(robot), pl.Calibration, timeout_s)


def request_maneuver(session: zenoh.Session, robot: str, action: str | None = None,
                     timeout_s: float = 10.0) -> pl.Maneuver:
    """The planned maneuver ``robot``'s fusion node serves (``action`` ``None``), or its reply
    to a ``start``, ``done`` or ``abort`` request (``accepted`` False: refused, saying why)."""
    return ask(session, pl.maneuver_key(robot, action), pl.Maneuver, timeout_s)
