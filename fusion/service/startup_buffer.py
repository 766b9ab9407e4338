"""What the fusion node keeps for its startup calibration until the tracker starts: each
sensor's accepted batches of the latest ``keep_s`` of sample time, and their span, known
without merging them (a node that merged its growing buffer on every batch fell further
behind the longer it collected)."""

from __future__ import annotations

from armfusion.fusion.service.reorder import merge_batches
from armfusion.sensors.samples import Recording, Stream


class StartupBuffer:
    """The batches kept for the startup calibration, at most ``keep_s`` of sample time (a
    quarter more before the oldest are let go, so a batch's cost stays bounded)."""

    def __init__(self, keep_s: float):
        self.keep_s = keep_s
        self._parts: dict[str, list[Stream]] = {}
        self._span: tuple[float, float] | None = None  # the kept batches' first and last time

    @property
    def span_s(self) -> float:
        """The span of sample time kept (s; 0 when nothing is)."""
        return 0.0 if self._span is None else self._span[1] - self._span[0]

    def keep(self, s: Stream) -> None:
        """An accepted batch kept; the oldest let go once the span passes 1.25 ``keep_s``."""
        self._parts.setdefault(s.name, []).append(s)
        t0, t1 = float(s.t_s[0]), float(s.t_s[-1])
        b = self._span
        self._span = (t0, t1) if b is None else (min(b[0], t0), max(b[1], t1))
        if self._span[1] - self._span[0] > 1.25 * self.keep_s:
            self._let_go_before(self._span[1] - self.keep_s)

    def forget(self, name: str) -> None:
        """What was kept of stream ``name`` dropped (its clock refuted)."""
        if self._parts.pop(name, None) is not None:
            self._span = self._measured()

    def merged(self) -> Recording:
        """The kept batches as one recording."""
        return merge_batches(self._parts)

    def clear(self) -> None:
        self._parts.clear()
        self._span = None

    def _let_go_before(self, t_from_s: float) -> None:
        for name in list(self._parts):
            kept = [b for b in self._parts[name] if float(b.t_s[-1]) >= t_from_s]
            if kept:
                self._parts[name] = kept
            else:
                del self._parts[name]
        self._span = self._measured()

    def _measured(self) -> tuple[float, float] | None:
        """The first and last time of the kept batches, or None."""
        ends = [(float(p.t_s[0]), float(p.t_s[-1])) for ps in self._parts.values() for p in ps]
        return None if not ends else (min(e[0] for e in ends), max(e[1] for e in ends))
