"""What the fusion node lets through to its estimator: every raw batch checked against the arm.

:mod:`armfusion.fusion.service.payloads` checks that a payload is a well-formed ``raw`` batch; this
module checks that it could have come from *this* robot's sensors, now. A batch that fails
is dropped whole, counted under its reason, and logged (at most one line a second per
reason); nothing in it reaches the estimator or the counters of what was received.

=================  =====================================================================
reason             the batch…
=================  =====================================================================
``unknown_sensor`` names a stream the arm's config does not have
``wrong_kind``     has a kind other than the config's for that stream (``accel``…)
``wrong_channels`` has channels other than the config's (e.g. 3 encoder channels of 7)
``out_of_range``   holds a count beyond the device's register range (an ADXL345 axis
                   -512…511, the MPU-9150's int16, the AK8975's 13 bits, the encoder
                   feed's int32): the rule and the words every reader of a file uses
                   (:mod:`armfusion.models.sample_admission`)
``encoder_jump``   moves a joint's encoder further than the joint can turn in the time
                   since the last sample (``max_joint_rate_rad_s`` plus
                   ``jump_slack_rad``)
``time_ahead``     is stamped more than ``ahead_s`` ahead of the sensors' clock
``time_behind``    is stamped more than ``clock_window_s`` behind it
``too_dense``      holds more samples than the stream's budget allows: a token bucket
                   per stream, sample by sample, that fills at ``max_rate_hz`` of sample
                   time and holds ``burst_samples`` (a real driver that fell behind
                   reads its whole FIFO at once, its stamps squeezed together; a peer
                   cannot hand the tracker 15,000 instants in one 1 MiB payload, nor a
                   steady stream faster than any sensor)
=================  =====================================================================

**The sensors' clock.** A recording's time has any origin (a replay, a rig powered up a
week ago), so the node's wall clock cannot judge a stamp by itself; what it can judge is
how a stream's time moves against the others' and against wall time. The reference is a
consensus of the *other* streams (a stream does not vote on itself): each stream the node
accepted a batch of in the last ``vote_fresh_s`` of wall time votes with the sensors' time
its batches say it is at this one's arrival (``arrived_s``: when Zenoh handed the message
over, not when a node that fell behind got to it): this arrival less the stream's least
delivery delay (arrival less last sample's time) over its batches whose last samples are
within ``ahead_s`` of its newest (and arrived in the last ``stall_memory_s``), and never
less than its newest accepted time; the reference is the median of the votes (the lower
of the middle two). The least delay, not the newest batch's: after a stall (a starved
node whose receive thread stamps a backlog on arrival, all at once; a driver that read
some sensors before it and sent them after it) a stream's newest batch may have arrived
seconds after it was read, and carrying its time forward from that late arrival would put
the clock seconds behind the genuine samples of the same burst, one stream's backlog
taken before another's. Only the last ``ahead_s`` of the stream's own time: a stream
whose time stood still while wall time went on (a replay paused, then live) has a larger
delay from then on, and its clock follows it once its samples have moved on that far. A
batch whose last sample is more than ``ahead_s`` ahead of the reference is refused
(``time_ahead``): one peer's sample stamped 1.9 s ahead can neither move the clock nor
make the node wait for it. A genuine stream leads the others only by the difference of
their latencies (a batch period and the delivery's jitter: ``ahead_s`` 0.25 s covers
batches of up to 200 ms, ten times the drivers' default); a stream that resumes after its
driver stalled is behind, not ahead, and the others' votes move on with wall time while they are
silent. A replay faster than real time moves every stream together, so the others' newest
times keep up with it. A batch whose first sample is more than ``clock_window_s`` behind
the median of the others' newest times (not carried forward: a driver catching up after
a stall sends seconds-old samples) and behind the stream's own newest (its backlog taken
after the others' is as old as the stall, and follows its own stream) is refused
(``time_behind``). With no other stream
voting, a stream is held to its own vote; the very first batch sets the clock. Should a
bogus batch be the first of all, the other streams are refused until its vote goes stale
(``vote_fresh_s``) and the stream that sent it is then reset (:attr:`Verdict.reset`: the
node discards what it kept of it). :meth:`Admission.clock` is the same consensus over
every voting stream: the node's reorder stage and its lateness measure take it (one
stream running ahead does not move either). The limits: a consensus of streams can be
moved by whoever sends for most of them; after a stall, a stream whose backlog has been
taken more than ``ahead_s`` of the way, not to its end, votes from its late arrivals, so
a stream whose backlog is taken further than most others' at once (not the order of one
publisher's messages, which interleaves them) may be refused as ahead; and a stream's very
first batch, taken after the others' backlogs and more than ``clock_window_s`` older than
their newest samples, is refused as ``time_behind`` (it has no sample of its own to follow).

**Encoders.** Counts are relative (any value at power-up) within the feed's int32. A
sample is compared with the last accepted one; a board that really restarted (its
counts start again elsewhere) would be refused for ever, so after
``encoder_rebase_after_s`` of sample time in which every encoder sample was refused as a
jump while agreeing with the previous refused one (and none was accepted) the new counts
are taken as a new baseline, counted in ``encoder_rebases`` (what the tracker makes of
the jump is its own slip handling). A publisher interleaving bogus counts with the real
ones never gets there: every real sample is accepted and restarts the wait.

**Batch numbers.** ``seq`` counts the batches of one sensor from one publisher (an integer
0…2⁶⁴ − 1: the payload's decoder refuses any other). Only an accepted batch moves it. A
gap counts as missed batches only as far as the batch's time leaves room: each missing
batch held at least one sample, taken after the last accepted one and before this one,
and no sensor samples faster than ``max_rate_hz``. A counter that wraps (from 2³² − 1,
2⁶³ − 1 or 2⁶⁴ − 1 to 0) goes on, gaps across the wrap counted the same way. A number that
goes back, or jumps further than the time allows, does not move the count by itself: it is
a new publisher session (``seq_resets``, the count going on from it) only when the next
batch of the stream follows it; when the next follows the old count instead, the odd one
was one peer's number and counted nothing. So a peer cannot make ``missed_batches`` grow
faster than real time allows, nor by sending one batch numbered -1, 0 or 10⁹. The batches
the node shed unread while it was behind (:meth:`Admission.shed`) are not counted as
missed either.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.service.inbox import DropLog
from armfusion.fusion.service.payloads import RawBatch
from armfusion.models.arm import ArmModel
from armfusion.models.sample_admission import (
    ENCODER_REBASE_AFTER_S,
    JUMP_SLACK_RAD,
    MAX_JOINT_RATE_RAD_S,
    jump_words,
)
from armfusion.models.sensor_models import ENCODER_STREAM, stream_models
from armfusion.sensors.adxl345 import FIFO_DEPTH
from armfusion.sensors.sample_checks import FEED_MAX, FEED_MIN, range_words

INT32_MIN, INT32_MAX = FEED_MIN, FEED_MAX
"""The encoder feed's counts (sensors/encoders.py: int32 per joint)."""
REASONS: tuple[str, ...] = ("unknown_sensor", "wrong_kind", "wrong_channels", "out_of_range",
                            "time_ahead", "time_behind", "too_dense", "encoder_jump")
SEQ_WRAPS = (1 << 32, 1 << 63, 1 << 64)
"""Where a publisher's batch counter may wrap to 0: an unsigned 32-bit, a signed or an
unsigned 64-bit integer."""
SHOWN = 40
"""Characters of a peer's text (a name, a value) a message repeats at most."""


def _shown(value, quoted: bool = True) -> str:
    text = repr(value) if quoted else str(value)
    return text if len(text) <= SHOWN else text[:SHOWN - 1] + "…"


@dataclass(frozen=True)
class AdmissionSettings:
    """Bounds of :class:`Admission` (see the module's docstring); units in the names."""

    clock_window_s: float = 2.0
    ahead_s: float = 0.25
    vote_fresh_s: float = 2.0
    stall_memory_s: float = 60.0
    """How long (arrival time) at most a stream's least delivery delay is remembered while
    its time does not move on: the longest stall of a starved node or driver after which
    the genuine samples of a burst are still judged by the wall time that passed (beside a
    CPU hog the demo's node lagged 43 s)."""
    max_joint_rate_rad_s: float = MAX_JOINT_RATE_RAD_S  # (with the files: armfusion.models.sample_admission)
    jump_slack_rad: float = JUMP_SLACK_RAD
    encoder_rebase_after_s: float = ENCODER_REBASE_AFTER_S
    max_rate_hz: float = 1000.0
    burst_samples: int = 2 * (FIFO_DEPTH + 1) + 1
    """The sample before and two whole ADXL345 FIFO reads (32 entries and the output
    registers each): the most a driver that fell behind hands on at once, its stamps
    squeezed together onto the last one."""


@dataclass(frozen=True)
class Verdict:
    """What :meth:`Admission.check` decided about one batch.

    ``reason`` is ``None`` when it is accepted. ``reset``: the stream's earlier samples were
    on a clock the others refute: drop what was kept of it. ``missed``: batches counted as
    lost before this one; ``seq_reset``: a new publisher session; ``rebased``: the encoder
    counts were taken as a new baseline.
    """

    reason: str | None
    message: str = ""
    reset: bool = False
    missed: int = 0
    seq_reset: bool = False
    rebased: bool = False

    @property
    def ok(self) -> bool:
        return self.reason is None


_OK = Verdict(None)


class Admission:
    """Checks raw batches against ``arm``'s sensors and the sensors' own clock.

    Not thread-safe: the node's loop calls it. ``now_s`` is a monotonic wall clock, used only
    to tell which streams still vote on the clock.
    """

    def __init__(self, arm: ArmModel, settings: AdmissionSettings | None = None):
        self.settings = settings or AdmissionSettings()
        self.arm_name = arm.name
        self._models = stream_models(arm)
        self._range = {}
        for name, m in self._models.items():  # register counts, or values in the declared unit
            self._range[name] = m.admissible_range  # (the encoders: the feed's int32)
        st = self.settings
        self._cpr = arm.counts_per_rad
        self._enc_step = self._cpr * st.max_joint_rate_rad_s  # counts per second
        self._enc_slack = self._cpr * st.jump_slack_rad
        self._newest: dict[str, float] = {}
        self._budget: dict[str, tuple[float, float]] = {}  # stream -> (samples left, at time)
        self._voted_at: dict[str, float] = {}  # stream -> when the node took its newest (freshness)
        self._leads: dict[str, deque[tuple[float, float, float]]] = {}  # stream -> (t, arrived, t - arrived)
        self._seq: dict[str, tuple[int, float]] = {}
        self._seq_odd: dict[str, tuple[int, float]] = {}  # a number that did not follow, until the next
        self._enc_last: tuple[float, np.ndarray] | None = None
        self._jump_since: float | None = None
        self._jump_last: tuple[float, np.ndarray] | None = None
        self.rejected: Counter[str] = Counter()
        self.rejected_samples: Counter[str] = Counter()
        """The samples of the batches refused, by reason (:attr:`rejected` counts batches)."""
        self.missed_batches = 0
        self._shed: Counter[str] = Counter()  # stream -> batches the node shed since its last accepted
        self.seq_resets = 0
        self.encoder_rebases = 0
        self._log = DropLog()

    # -- the checks --------------------------------------------------------------------------
    def check(self, batch: RawBatch, now_s: float | None = None, arrived_s: float | None = None) -> Verdict:
        """Accept ``batch`` (and note it) or say why not (counted in :attr:`rejected`).
        ``now_s``: the wall time (monotonic) the node takes it, ``arrived_s``: when it
        arrived (by default ``now_s``; earlier when the node is behind)."""
        now_s = time.monotonic() if now_s is None else now_s
        arrived_s = now_s if arrived_s is None else arrived_s
        verdict = self._check(batch, now_s, arrived_s)
        if not verdict.ok:
            self.rejected[verdict.reason] += 1
            self.rejected_samples[verdict.reason] += len(batch.stream)
            self._warn(batch, verdict)
        return verdict

    def _check(self, batch: RawBatch, now_s: float, arrived_s: float) -> Verdict:
        s = batch.stream
        model = self._models.get(s.name)
        if model is None:
            return Verdict("unknown_sensor", f"sensor {_shown(s.name)} is not one of {self.arm_name}'s "
                                             f"({', '.join(self._models)})")
        if s.kind != model.kind:
            return Verdict("wrong_kind", f"kind {_shown(s.kind)}, expected {model.kind!r}")
        if tuple(s.channels) != model.channels:
            got = _shown(", ".join(c[:SHOWN] for c in s.channels[:8]), quoted=False)
            return Verdict("wrong_channels", f"{len(s.channels)} channels ({got}), expected "
                                             f"{model.size} ({', '.join(model.channels)})")
        lo, hi = self._range[s.name]
        flat = s.values.ravel().tolist() if s.values.size <= 64 else None  # (numpy's min/max: 3 us each)
        if (min(flat) < lo or max(flat) > hi) if flat is not None else (
                s.values.min().item() < lo or s.values.max().item() > hi):
            i, j = (int(x) for x in np.argwhere((s.values < lo) | (s.values > hi))[0])
            return Verdict("out_of_range",
                           range_words(s.channels[j], s.values[i, j].item(), s.t_s[i], lo, hi))
        verdict = self._check_time(s.name, float(s.t_s[0]), float(s.t_s[-1]), now_s, arrived_s)
        if not verdict.ok:
            return verdict
        if verdict.reset:  # its earlier times were on a refuted clock: so was its budget
            self._budget.pop(s.name, None)
        bucket = self._bucket_after(s.name, s.t_s)
        if bucket is None:
            return self._too_dense(s.t_s)
        rebased = False
        if s.name == ENCODER_STREAM:
            jump, rebased = self._check_encoder(s.t_s, s.values)
            if jump is not None:
                return jump
        missed, seq_reset = self._note(batch, now_s, arrived_s, rebased, bucket)
        if not (verdict.reset or missed or seq_reset or rebased):
            return _OK  # (the common case: no object to make)
        return Verdict(None, reset=verdict.reset, missed=missed, seq_reset=seq_reset, rebased=rebased)

    def _votes(self, now_s: float, arrived_s: float, but: str | None = None) -> list[float]:
        """The fresh streams' newest times carried forward to ``arrived_s``, sorted (``but``:
        leave that stream out). Fresh: taken by the node in the last ``vote_fresh_s`` before
        ``now_s``."""
        fresh = now_s - self.settings.vote_fresh_s
        votes = [max(t, arrived_s + self._leads[k][0][2]) for k, t in self._newest.items()
                 if k != but and self._voted_at[k] >= fresh]
        votes.sort()  # (np.median costs 20x more on a handful of streams)
        return votes

    def clock(self, now_s: float, arrived_s: float | None = None) -> float | None:
        """The sensors' time at wall time ``arrived_s`` (monotonic; by default ``now_s``, when
        the node asks): the median of every fresh stream's newest accepted time carried
        forward by the wall time since it arrived (see the module's docstring); ``None``
        before any batch was accepted or once every stream fell silent."""
        votes = self._votes(now_s, now_s if arrived_s is None else arrived_s)
        return votes[(len(votes) - 1) // 2] if votes else None

    def _check_time(self, name: str, t0: float, t1: float, now_s: float, arrived_s: float) -> Verdict:
        st = self.settings
        w = st.clock_window_s
        fresh = now_s - st.vote_fresh_s
        newest, votes = [], []
        for k, t in self._newest.items():  # (one pass: this runs for every batch)
            if k != name and self._voted_at[k] >= fresh:
                newest.append(t)
                carried = arrived_s + self._leads[k][0][2]
                votes.append(carried if carried > t else t)
        if votes:
            votes.sort()
            newest.sort()
            ahead_ref = votes[(len(votes) - 1) // 2]
            behind_ref = newest[(len(newest) - 1) // 2]
            own = self._newest.get(name)
            if own is not None and own < behind_ref:  # its backlog, taken after the others'
                behind_ref = own
            whose = f"the other sensors' clock ({len(votes)} streams)"
        elif name in self._newest and self._voted_at[name] >= fresh:
            behind_ref = self._newest[name]
            ahead_ref = max(behind_ref, arrived_s + self._leads[name][0][2])
            whose = "this sensor's last sample"
        else:
            ahead_ref = behind_ref = None
        if ahead_ref is not None:
            if t1 > ahead_ref + st.ahead_s:
                return Verdict("time_ahead", f"t = {t1:.6g} s is {t1 - ahead_ref:.6g} s ahead of {whose} "
                                             f"(t = {ahead_ref:.6g} s; at most {st.ahead_s:g} s)")
            if t0 < behind_ref - w:
                return Verdict("time_behind", f"t = {t0:.6g} s is {behind_ref - t0:.6g} s behind {whose} "
                                              f"(t = {behind_ref:.6g} s; at most {w:g} s)")
        reset = name in self._newest and self._newest[name] > t1 + w
        return Verdict(None, reset=True) if reset else _OK

    def _bucket_after(self, name: str, t_s: np.ndarray) -> tuple[float, float] | None:
        """The stream's token bucket after ``t_s``'s samples, drawn one by one (each takes a
        token; the bucket fills at ``max_rate_hz`` for the sample time gained since the
        sample before, up to ``burst_samples``): ``(tokens left, last sample's time)``, or
        ``None`` when it runs dry on one of them."""
        st = self.settings
        cap, rate = float(st.burst_samples), st.max_rate_hz
        left, at = self._budget.get(name, (cap, float(t_s[0])))
        if len(t_s) <= 64:  # (plain Python: NumPy's per-call cost is larger on a driver's few samples)
            for t in t_s.tolist():
                left = min(cap, left + max(t - at, 0.0) * rate) - 1.0
                if left < 0.0:
                    return None
                at = t
            return left, at
        # the same, at once: with g_i the time gained up to sample i, the tokens after it are
        # the least of the run from the start, left + g_i * rate - (i + 1), and of the runs
        # from a bucket full just before sample j <= i, cap + (g_i - g_j) * rate - (i - j + 1)
        t = np.asarray(t_s, float)
        g = np.cumsum(np.maximum(np.diff(t, prepend=at), 0.0))
        i = np.arange(len(t), dtype=float)
        c = g * rate - i
        level = np.minimum(left + c - 1.0, cap + c - np.maximum.accumulate(c) - 1.0)
        if level.min() < 0.0:
            return None
        return float(level[-1]), float(t[-1])

    def _too_dense(self, t_s: np.ndarray) -> Verdict:
        """The refusal of a batch one of whose samples finds the stream's bucket dry (see the
        module's docstring); the bucket is drawn on only when the batch is accepted
        (:meth:`_note`)."""
        span_ms = (float(t_s[-1]) - float(t_s[0])) * 1e3
        return Verdict("too_dense", f"{len(t_s)} samples in {span_ms:.3g} ms: denser than any sensor "
                                    f"samples (at most {self.settings.max_rate_hz:g} Hz, bursts of "
                                    f"{self.settings.burst_samples})")

    def _check_encoder(self, t_s: np.ndarray, counts: np.ndarray) -> tuple[Verdict | None, bool]:
        """``(None, rebased)`` when every step of ``counts`` is one the joints can make, or a
        rebase is due; else ``(the refusal, False)``."""
        if self._enc_last is not None:
            prev_t = np.concatenate([[self._enc_last[0]], t_s[:-1]])
            prev_c = np.vstack([self._enc_last[1], counts[:-1]])
            now_t, now_c = t_s, counts
        else:
            prev_t, prev_c, now_t, now_c = t_s[:-1], counts[:-1], t_s[1:], counts[1:]
        bad = self._jumps(prev_t, prev_c, now_t, now_c)
        if bad is None:
            self._jump_since = self._jump_last = None
            return None, False
        # refused; but a board that restarted sends counts that agree with each other
        own = self._jumps(t_s[:-1], counts[:-1], t_s[1:], counts[1:]) is None
        run_goes_on = own and self._jump_last is not None and self._jumps(
            np.array([self._jump_last[0]]), self._jump_last[1][None, :], t_s[:1], counts[:1]) is None
        if run_goes_on:
            if float(t_s[-1]) - self._jump_since >= self.settings.encoder_rebase_after_s:
                self._jump_since = self._jump_last = None
                return None, True
        else:
            self._jump_since = float(t_s[0]) if own else None
        self._jump_last = (float(t_s[-1]), counts[-1].copy()) if own else None
        i, j = bad
        deg = math.degrees(abs(int(now_c[i, j]) - int(prev_c[i, j])) / self._cpr[j])
        dt = abs(float(now_t[i]) - float(prev_t[i]))
        return Verdict("encoder_jump", jump_words(self._models[ENCODER_STREAM].channels[j], deg, dt,
                                                  float(now_t[i]), self.settings.max_joint_rate_rad_s)), False

    def _jumps(self, t0, c0, t1, c1) -> tuple[int, int] | None:
        """The first ``(sample, joint)`` whose step from ``c0`` to ``c1`` is too large, or ``None``."""
        if len(t1) == 0:
            return None
        dt = np.abs(np.asarray(t1, float) - np.asarray(t0, float))[:, None]
        step = np.abs(np.asarray(c1, float) - np.asarray(c0, float))
        bad = step > dt * self._enc_step + self._enc_slack
        if not bad.any():
            return None
        i, j = np.argwhere(bad)[0]
        return int(i), int(j)

    def _note(self, batch: RawBatch, now_s: float, arrived_s: float, rebased: bool,
              bucket: tuple[float, float]) -> tuple[int, bool]:
        """An accepted batch: the clock, the stream's token bucket after it (``bucket``), the
        encoders' last sample, the batch numbers."""
        s = batch.stream
        t0, t1 = float(s.t_s[0]), float(s.t_s[-1])
        w = self.settings.clock_window_s
        newest = self._newest.get(s.name)
        if newest is None or newest > t1 + w:  # (a new clock: what was remembered of the old goes)
            newest = None
            self._leads[s.name] = leads = deque()
        else:
            leads = self._leads[s.name]
        if newest is None or t1 >= newest:  # the sliding maximum of the stream's lead, t - arrival
            self._newest[s.name] = t1
            lead = t1 - arrived_s
            while leads and leads[-1][2] <= lead:
                leads.pop()
            leads.append((t1, arrived_s, lead))
            st = self.settings
            since_t, since_arrived = t1 - st.ahead_s, arrived_s - st.stall_memory_s
            while leads[0][0] < since_t or leads[0][1] < since_arrived:
                leads.popleft()
        self._budget[s.name] = bucket
        self._voted_at[s.name] = now_s
        if s.name == ENCODER_STREAM and (self._enc_last is None or t1 >= self._enc_last[0]):
            self._enc_last = (t1, s.values[-1].copy())
        missed, reset = self._count_seq(s.name, batch.seq, t0, t1)
        if rebased:
            self.encoder_rebases += 1
        return missed, reset

    def _gap(self, last_seq: int, last_t: float, seq: int, t0: float) -> int | None:
        """Batches missing between ``last_seq`` at ``last_t`` and ``seq`` at ``t0`` (across a
        counter's wrap too), or ``None`` when ``seq`` does not follow: it goes back, or jumps
        further than the time between them leaves room for."""
        room = math.ceil(max(t0 - last_t, 0.0) * self.settings.max_rate_hz)
        gaps = [seq - last_seq - 1] + [seq + wrap - last_seq - 1 for wrap in SEQ_WRAPS
                                       if seq < last_seq < wrap]
        return next((g for g in gaps if 0 <= g <= room), None)

    def shed(self, name: str) -> None:
        """The node shed a batch on ``name``'s key unread (its lateness policy): the gap it
        leaves in the stream's batch numbers is not counted as missed batches."""
        if name in self._models:  # (a peer's invented names are not remembered)
            self._shed[name] += 1

    def _count_seq(self, name: str, seq: int, t0: float, t1: float) -> tuple[int, bool]:
        """``(batches missed, a new publisher session)`` for an accepted batch numbered ``seq``
        (see the module's docstring; the batches the node shed since the stream's last
        accepted one are not missed)."""
        shed = self._shed.pop(name, 0) if self._shed else 0
        last = self._seq.get(name)
        if last is None:
            self._seq[name] = (seq, t1)
            return 0, False
        last_seq, last_t = last
        gap = self._gap(last_seq, last_t, seq, t0)
        if gap is not None:
            self._seq_odd.pop(name, None)
            self._seq[name] = (seq, max(t1, last_t))
            gap = max(gap - shed, 0)
            self.missed_batches += gap
            return gap, False
        odd = self._seq_odd.pop(name, None)
        if odd is not None and self._gap(odd[0], odd[1], seq, t0) is not None:
            self._seq[name] = (seq, t1)  # the odd one began a new session: this one follows it
            self.seq_resets += 1
            return 0, True
        self._seq_odd[name] = (seq, t1)
        return 0, False

    def _warn(self, batch: RawBatch, v: Verdict) -> None:
        self._log.warn(v.reason, "serve: refused a batch of %s (%s): %s", _shown(batch.stream.name),
                       v.reason, v.message)
