"""What the fusion node lets through to its estimator: every raw batch checked against the arm.

:mod:`fusion.service.payloads` checks that a payload is a well-formed ``raw`` batch; this
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
                   (:mod:`models.sample_admission`)
``encoder_jump``   moves a joint's encoder further than the joint can turn in the time
                   since the last sample (``max_joint_rate_rad_s`` plus
                   ``jump_slack_rad``)
``time_ahead``     is stamped more than ``clock_window_s`` ahead of the sensors' clock
``time_behind``    is stamped more than ``clock_window_s`` behind it
``too_dense``      holds more samples than the stream's budget allows: a token bucket
                   per stream that fills at ``max_rate_hz`` of sample time and holds
                   ``burst_samples`` (a real driver that fell behind reads a few samples
                   in quick succession; a peer cannot hand the tracker 15,000 instants
                   in one 1 MiB payload, nor a steady stream faster than any sensor)
=================  =====================================================================

**The sensors' clock.** A recording's time has any origin (a replay, a rig powered up a
week ago), so the node's wall clock cannot judge a stamp. The reference is the sensors'
own: the median (the lower of the middle two) of the newest accepted times of the *other*
streams that were accepted in the last ``vote_fresh_s`` of wall time (a stream does not
vote on itself, and a stream that fell silent stops voting). With no other stream voting,
a stream is held to its own newest time; the very first batch sets the clock. So one batch stamped 10⁶ s ahead
is refused whether the node tracks or not, and the clock does not move. Should a bogus
batch be the first of all, the other streams are refused until its vote goes stale
(``vote_fresh_s``) and the stream that sent it is then reset (:attr:`Verdict.reset`:
the node discards what it kept of it).

**Encoders.** Counts are relative (any value at power-up) within the feed's int32. A
sample is compared with the last accepted one; a board that really restarted (its
counts start again elsewhere) would be refused for ever, so after
``encoder_rebase_after_s`` of sample time in which every encoder sample was refused as a
jump while agreeing with the previous refused one (and none was accepted) the new counts
are taken as a new baseline, counted in ``encoder_rebases`` (what the tracker makes of
the jump is its own slip handling). A publisher interleaving bogus counts with the real
ones never gets there: every real sample is accepted and restarts the wait.

**Batch numbers.** ``seq`` counts the batches of one sensor from one publisher. Only an
accepted batch moves it. A gap counts as missed batches only as far as the batch's time
leaves room: each missing batch held at least one sample, taken after the last accepted
one and before this one, and no sensor samples faster than ``max_rate_hz``; a larger
jump, or a number that goes back, is a new publisher session (``seq_resets``) and counts
nothing. So a peer cannot make ``missed_batches`` grow faster than real time allows.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from fusion.service.inbox import DropLog
from fusion.service.payloads import RawBatch
from models.arm import ArmModel
from models.sample_admission import ENCODER_REBASE_AFTER_S, JUMP_SLACK_RAD, MAX_JOINT_RATE_RAD_S, jump_words
from models.sensor_models import ENCODER_STREAM, stream_models
from sensors.sample_checks import FEED_MAX, FEED_MIN, range_words

INT32_MIN, INT32_MAX = FEED_MIN, FEED_MAX
"""The encoder feed's counts (sensors/encoders.py: int32 per joint)."""
REASONS: tuple[str, ...] = ("unknown_sensor", "wrong_kind", "wrong_channels", "out_of_range",
                            "time_ahead", "time_behind", "too_dense", "encoder_jump")
SHOWN = 40
"""Characters of a peer's text (a name, a value) a message repeats at most."""


def _shown(value, quoted: bool = True) -> str:
    text = repr(value) if quoted else str(value)
    return text if len(text) <= SHOWN else text[:SHOWN - 1] + "…"


@dataclass(frozen=True)
class AdmissionSettings:
    """Bounds of :class:`Admission` (see the module's docstring); units in the names."""

    clock_window_s: float = 2.0
    vote_fresh_s: float = 2.0
    max_joint_rate_rad_s: float = MAX_JOINT_RATE_RAD_S  # (with the files: models.sample_admission)
    jump_slack_rad: float = JUMP_SLACK_RAD
    encoder_rebase_after_s: float = ENCODER_REBASE_AFTER_S
    max_rate_hz: float = 1000.0
    burst_samples: int = 16


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
        self._voted_at: dict[str, float] = {}
        self._seq: dict[str, tuple[int, float]] = {}
        self._enc_last: tuple[float, np.ndarray] | None = None
        self._jump_since: float | None = None
        self._jump_last: tuple[float, np.ndarray] | None = None
        self.rejected: Counter[str] = Counter()
        self.rejected_samples: Counter[str] = Counter()
        """The samples of the batches refused, by reason (:attr:`rejected` counts batches)."""
        self.missed_batches = 0
        self.seq_resets = 0
        self.encoder_rebases = 0
        self._log = DropLog()

    # -- the checks --------------------------------------------------------------------------
    def check(self, batch: RawBatch, now_s: float | None = None) -> Verdict:
        """Accept ``batch`` (and note it) or say why not (counted in :attr:`rejected`)."""
        now_s = time.monotonic() if now_s is None else now_s
        verdict = self._check(batch, now_s)
        if not verdict.ok:
            self.rejected[verdict.reason] += 1
            self.rejected_samples[verdict.reason] += len(batch.stream)
            self._warn(batch, verdict)
        return verdict

    def _check(self, batch: RawBatch, now_s: float) -> Verdict:
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
        verdict = self._check_time(s.name, float(s.t_s[0]), float(s.t_s[-1]), now_s)
        if not verdict.ok:
            return verdict
        dense = self._check_density(s.name, s.t_s)
        if dense is not None:
            return dense
        rebased = False
        if s.name == ENCODER_STREAM:
            jump, rebased = self._check_encoder(s.t_s, s.values)
            if jump is not None:
                return jump
        missed, seq_reset = self._note(batch, now_s, rebased)
        if not (verdict.reset or missed or seq_reset or rebased):
            return _OK  # (the common case: no object to make)
        return Verdict(None, reset=verdict.reset, missed=missed, seq_reset=seq_reset, rebased=rebased)

    def _check_time(self, name: str, t0: float, t1: float, now_s: float) -> Verdict:
        w = self.settings.clock_window_s
        fresh = now_s - self.settings.vote_fresh_s
        voters = [t for k, t in self._newest.items() if k != name and self._voted_at[k] >= fresh]
        if voters:
            voters.sort()  # the median (the lower of the middle two); np.median costs 20x more here
            ref = voters[(len(voters) - 1) // 2]
        elif name in self._newest and self._voted_at[name] >= fresh:
            ref = self._newest[name]
        else:
            ref = None
        if ref is not None and not ref - w <= t0 <= t1 <= ref + w:
            whose = (f"the other sensors' clock ({len(voters)} streams)" if voters
                     else "this sensor's last sample")
            if t1 > ref + w:
                return Verdict("time_ahead", f"t = {t1:.6g} s is {t1 - ref:.6g} s ahead of {whose} "
                                             f"(t = {ref:.6g} s; at most {w:g} s)")
            return Verdict("time_behind", f"t = {t0:.6g} s is {ref - t0:.6g} s behind {whose} "
                                          f"(t = {ref:.6g} s; at most {w:g} s)")
        reset = name in self._newest and self._newest[name] > t1 + w
        return Verdict(None, reset=True) if reset else _OK

    def _budget_left(self, name: str, t_s: np.ndarray) -> float:
        """Samples the stream may still deliver by its last sample's time: its bucket, filled
        at ``max_rate_hz`` of sample time since it was last drawn on, capped at the burst."""
        st = self.settings
        left, at = self._budget.get(name, (float(st.burst_samples), float(t_s[0])))
        return min(float(st.burst_samples), left + max(float(t_s[-1]) - at, 0.0) * st.max_rate_hz)

    def _check_density(self, name: str, t_s: np.ndarray) -> Verdict | None:
        """Refuse a batch with more samples than the stream's budget holds (see the module's
        docstring); the budget is drawn on only when the batch is accepted (:meth:`_note`)."""
        if len(t_s) <= self._budget_left(name, t_s):
            return None
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

    def _note(self, batch: RawBatch, now_s: float, rebased: bool) -> tuple[int, bool]:
        """An accepted batch: the clock, the encoders' last sample, the batch numbers."""
        s = batch.stream
        t0, t1 = float(s.t_s[0]), float(s.t_s[-1])
        w = self.settings.clock_window_s
        newest = self._newest.get(s.name)
        self._newest[s.name] = t1 if newest is None or newest > t1 + w else max(newest, t1)
        self._budget[s.name] = (self._budget_left(s.name, s.t_s) - len(s.t_s), max(t1, t0))
        self._voted_at[s.name] = now_s
        if s.name == ENCODER_STREAM and (self._enc_last is None or t1 >= self._enc_last[0]):
            self._enc_last = (t1, s.values[-1].copy())
        missed, reset = 0, False
        last = self._seq.get(s.name)
        if last is not None:
            last_seq, last_t = last
            gap = batch.seq - last_seq - 1
            room = math.ceil(max(t0 - last_t, 0.0) * self.settings.max_rate_hz)
            if gap < 0 or gap > room:
                reset = True
                self.seq_resets += 1
            else:
                missed = gap
                self.missed_batches += gap
        self._seq[s.name] = (batch.seq, t1 if last is None or reset else max(t1, last[1]))
        if rebased:
            self.encoder_rebases += 1
        return missed, reset

    def _warn(self, batch: RawBatch, v: Verdict) -> None:
        self._log.warn(v.reason, "serve: refused a batch of %s (%s): %s", _shown(batch.stream.name),
                       v.reason, v.message)
