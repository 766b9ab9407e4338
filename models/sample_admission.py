"""The one admission of raw samples, at every door: a recording file read by a command, an
import, a batch over the wire (``armfusion.fusion.service.admission``). The rules that need no config
(a finite time within any clock's reach, values within the feed's 32-bit range) are
:mod:`armfusion.sensors.sample_checks`; here the one that needs the sensor's description: every value
within the range its device can deliver (:attr:`armfusion.models.sensor_models.StreamModel.admissible_range`:
the register's limits of the config's description, or the feed's range for a stream without
them, the encoders).

The encoders' counts are relative, so their range says little: a spike, a sample that moves
a joint further than any joint turns since the one before (:data:`SPIKE_RATE_RAD_S`, plus
:data:`JUMP_SLACK_RAD`) with the next sample moving it back, is refused too
(:func:`encoder_jump_problem`; the wire, which cannot wait for the next sample, refuses
every such step: ``armfusion.fusion.service.admission``).

A value *at* a limit is saturated, not refused (:meth:`StreamModel.saturated`: the commands
leave such samples out); a value *past* it cannot come from the sensor, so the sample is
refused, said in the same words wherever it came in (:func:`armfusion.sensors.sample_checks.range_words`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.sensor_models import ENCODER_STREAM, StreamModel, stream_models
from armfusion.sensors.sample_checks import SampleProblem, feed_problems, range_problem, sample_place
from armfusion.sensors.samples import Recording, Stream

MAX_JOINT_RATE_RAD_S = 3.0
"""The fastest a joint turns (the WMRA's joints at most about 1 rad/s; a margin of three)."""
JUMP_SLACK_RAD = math.radians(0.5)
"""A step of the encoders taken whatever the time since the last sample (stamps' jitter)."""
SPIKE_RATE_RAD_S = 10 * MAX_JOINT_RATE_RAD_S
"""A file's encoder spike goes out and back faster than this (30 rad/s, 1700°/s): ten times
the node's bound, as files hold rigs faster than an arm (the imu-rig's medium trials turn
back and forth at up to 5.1 rad/s between samples, with stamps' jitter)."""
ENCODER_REBASE_AFTER_S = 1.0
"""The wire's: sample time for which counts after a jump must stay on their course to be
taken as a new baseline (a board that restarted)."""


def jump_words(channel: str, deg: float, dt_s: float, t_s: float, rate_rad_s: float) -> str:
    """How an encoder jump is said, at every door (the wire's ``encoder_jump``)."""
    return (f"{channel} moved {deg:.3g}° in {dt_s:.3g} s at t = {t_s:.6g} s, more than the joint can "
            f"turn ({rate_rad_s:g} rad/s)")


def encoder_jump_problem(arm: ArmModel, stream: Stream) -> SampleProblem | None:
    """The first encoder sample that is a spike: it moves a joint further than
    :data:`SPIKE_RATE_RAD_S` allows since the sample before (plus :data:`JUMP_SLACK_RAD`),
    and the sample after moves it back as far, to where the joint could have gone from the
    one before; ``None`` when there is none.

    A file shows the sample after, which the wire does not: so a step that the counts go on
    from (a board that restarted) is not a spike, only a value that comes and goes."""
    if len(stream) < 3 or stream.values.shape[1] != arm.n_joints:
        return None
    cpr = np.asarray(arm.counts_per_rad, float)
    t = stream.t_s
    c = np.asarray(stream.values, float)
    dt = np.diff(t)[:, None]
    step = np.diff(c, axis=0)
    limit = dt * cpr * SPIKE_RATE_RAD_S + cpr * JUMP_SLACK_RAD
    too_far = np.abs(step) > limit
    across = (np.abs(c[2:] - c[:-2])
              <= (t[2:] - t[:-2])[:, None] * cpr * SPIKE_RATE_RAD_S + cpr * JUMP_SLACK_RAD)
    spike = too_far[:-1] & too_far[1:] & (np.sign(step[:-1]) != np.sign(step[1:])) & across
    hits = np.flatnonzero(spike.any(axis=1))
    if not hits.size:
        return None
    k = int(hits[0]) + 1  # the spike's sample
    j = int(np.argmax(spike[k - 1]))
    deg = math.degrees(abs(step[k - 1, j]) / cpr[j])
    return SampleProblem(stream.name, k, "encoder_jump",
                         jump_words(stream.channels[j], deg, float(dt[k - 1, 0]), float(t[k]),
                                    SPIKE_RATE_RAD_S))


def encoder_step_problem(arm: ArmModel, stream: Stream) -> SampleProblem | None:
    """The first encoder sample that moves a joint further than :data:`SPIKE_RATE_RAD_S`
    allows since the sample before (plus :data:`JUMP_SLACK_RAD`), whether or not the counts go
    on from it: a spike, or a board that restarted (its counts from a new zero). The tracker
    takes such a step as a slip; a fit over the whole recording (``calibrate sensors``,
    ``diagnose``) reads the angles from the counts, which do not carry across it."""
    if len(stream) < 2 or stream.values.shape[1] != arm.n_joints:
        return None
    cpr = np.asarray(arm.counts_per_rad, float)
    dt = np.diff(stream.t_s)[:, None]
    step = np.diff(np.asarray(stream.values, float), axis=0)
    too_far = np.abs(step) > dt * cpr * SPIKE_RATE_RAD_S + cpr * JUMP_SLACK_RAD
    hits = np.flatnonzero(too_far.any(axis=1))
    if not hits.size:
        return None
    k = int(hits[0]) + 1
    j = int(np.argmax(too_far[k - 1]))
    deg = math.degrees(abs(step[k - 1, j]) / cpr[j])
    return SampleProblem(stream.name, k, "encoder_step",
                         jump_words(stream.channels[j], deg, float(dt[k - 1, 0]), float(stream.t_s[k]),
                                    SPIKE_RATE_RAD_S))


def stream_problem(model: StreamModel, stream: Stream) -> SampleProblem | None:
    """The first sample of ``stream`` (``model``'s) with a value past its device's range."""
    return range_problem(stream, *model.admissible_range)


def admission_problems(arm: ArmModel, rec: Recording) -> list[SampleProblem]:
    """Every stream's first refused sample: the config-free rules
    (:func:`armfusion.sensors.sample_checks.feed_problems`), then each config sensor's range and the
    encoders' jumps; streams the config does not describe (truth, other sensors) meet the
    first only."""
    out = feed_problems(rec)
    seen = {p.stream for p in out}
    for name, model in stream_models(arm).items():
        s = rec.get(name)
        if s is None or name in seen or not len(s) or s.values.shape[1] != model.size:
            continue
        p = stream_problem(model, s)
        if p is None and name == ENCODER_STREAM:
            p = encoder_jump_problem(arm, s)
        if p is not None:
            out.append(p)
    return out


# --------------------------------------------------------------------------------------
# what every command that reads samples does with range and saturation
class OutOfRangeError(ValueError):
    """A recording holds a value its device cannot output (past its register range)."""


class MissingSensorError(ValueError):
    """A recording lacks a stream that the config and the command require."""


@dataclass(frozen=True)
class SampleScreen:
    """What :func:`screen_samples` found: per stream with a count model, its samples and
    those saturated (a channel at its register limit); the commands leave those out."""

    samples: dict[str, int]
    saturated: dict[str, int]

    @property
    def any_saturated(self) -> bool:
        return any(self.saturated.values())

    def words(self) -> str:
        """One line for a person: which streams had saturated samples, how many of how many."""
        parts = [f"{s} {n:,} of {self.samples[s]:,} ({100.0 * n / self.samples[s]:.2g} %)"
                 for s, n in self.saturated.items() if n]
        return ("saturated samples (a channel at its register limit), left out: " + ", ".join(parts)
                if parts else "no saturated sample")

    def as_dict(self) -> dict:
        return {"samples": dict(self.samples), "saturated": {s: n for s, n in self.saturated.items() if n}}


_REFUSED_BECAUSE = {
    "out_of_range": "; no such sensor can read that",
    "encoder_jump": ", and the next sample moves it back: a spike no joint makes",
    "encoder_step": ("; the counts do not carry across such a step (a board that restarted?), and a fit "
                     "over the whole recording cannot span it (cut the recording there)"),
}


def screen_samples(arm: ArmModel, rec, required: Iterable[str] = (), needed_by: str = "",
                   encoder_steps: bool = False) -> SampleScreen:
    """Every command's check of a recording's samples against the config's sensors.

    Raises :class:`MissingSensorError` when a stream of ``required`` has no sample (naming
    them and ``needed_by``), :class:`OutOfRangeError` at the first value past its device's
    range (:attr:`StreamModel.admissible_range`: the encoders' is the feed's int32), naming
    the place in the file, the channel, the value and the time in the words the fusion node
    uses (:func:`armfusion.sensors.sample_checks.range_words`), and likewise at the first encoder jump
    (:func:`encoder_jump_problem`), and with ``encoder_steps`` at the first encoder step no
    joint makes (:func:`encoder_step_problem`: the commands that fit over the whole recording);
    otherwise it counts the
    saturated samples per stream (:meth:`StreamModel.saturated`), which the commands leave out.
    Streams the config does not describe (truth, unknown sensors) are not looked at.
    """
    missing = [s for s in required if rec.get(s) is None or len(rec.get(s)) == 0]
    if missing:
        raise MissingSensorError(
            f"the recording has no samples of {', '.join(missing)}"
            + (f", which {needed_by}" if needed_by else "")
            + f" (it has: {', '.join(s for s in rec.raw() if len(rec.get(s))) or 'no sensor stream'})")
    samples, saturated = {}, {}
    for name, model in stream_models(arm).items():
        st = rec.get(name)
        if st is None or len(st) == 0 or st.values.shape[1] != model.size:
            continue
        problem = range_problem(st, *model.admissible_range)
        if problem is None and name == ENCODER_STREAM:
            problem = encoder_jump_problem(arm, st)
            if problem is None and encoder_steps:
                problem = encoder_step_problem(arm, st)
        if problem is not None:
            raise OutOfRangeError(f"{sample_place(rec, name, problem.index)}: {problem.words}"
                                  f"{_REFUSED_BECAUSE[problem.reason]}, so the recording is refused")
        samples[name] = len(st)
        saturated[name] = int(model.saturated(st.values).any(axis=1).sum())
    return SampleScreen(samples, saturated)
