"""Ask a fusion node to re-run its startup calibration: a Zenoh query on
``armfusion/<robot>/calibrate`` (``armfusion recalibrate``), answered by ``armfusion serve``
with a :class:`~fusion.service.payloads.Calibration` (accepted with the result, or refused
with the reason)."""

from __future__ import annotations

import zenoh

from fusion.service import payloads as pl


class NoReplyError(RuntimeError):
    """No fusion node answered (none runs for that robot, or it is not reachable)."""


def request_calibration(session: zenoh.Session, robot: str, timeout_s: float = 10.0) -> pl.Calibration:
    """The reply of ``robot``'s fusion node to a calibration request.

    Raises :class:`NoReplyError` when no node answers within ``timeout_s``, and
    :class:`~fusion.service.payloads.PayloadError` when the reply is not a valid payload.
    """
    key = pl.calibrate_key(robot)
    replies = session.get(key, timeout=timeout_s)
    for reply in replies:
        if reply.ok is not None:
            sample = reply.ok
            payload = pl.decode(str(sample.key_expr), sample.payload.to_bytes())
            if not isinstance(payload, pl.Calibration):
                raise pl.PayloadError("malformed", f"a {type(payload).__name__} in reply on {key}")
            return payload
        err = reply.err
        raise NoReplyError(f"{key}: the node answered with an error: {err.payload.to_string()}")
    raise NoReplyError(f"{key}: no fusion node answered within {timeout_s:g} s (is `armfusion serve "
                       f"--robot {robot}` running and connected?)")
