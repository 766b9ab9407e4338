"""The one admission of raw samples, at every door: a recording file read by a command, an
import, a batch over the wire (``fusion.service.admission``). The rules that need no config
(a finite time within any clock's reach, values within the feed's 32-bit range) are
:mod:`sensors.sample_checks`; here the one that needs the sensor's description: every value
within the range its device can deliver (:attr:`models.sensor_models.StreamModel.admissible_range`:
the register's limits of the config's description, or the feed's range for a stream without
them, the encoders).

A value *at* a limit is saturated, not refused (:meth:`StreamModel.saturated`: the commands
leave such samples out); a value *past* it cannot come from the sensor, so the sample is
refused, said in the same words wherever it came in (:func:`sensors.sample_checks.range_words`).
"""

from __future__ import annotations

from models.arm import ArmModel
from models.sensor_models import StreamModel, stream_models
from sensors.sample_checks import SampleProblem, feed_problems, range_problem
from sensors.samples import Recording, Stream


def stream_problem(model: StreamModel, stream: Stream) -> SampleProblem | None:
    """The first sample of ``stream`` (``model``'s) with a value past its device's range."""
    return range_problem(stream, *model.admissible_range)


def admission_problems(arm: ArmModel, rec: Recording) -> list[SampleProblem]:
    """Every stream's first refused sample: the config-free rules
    (:func:`sensors.sample_checks.feed_problems`), then each config sensor's range; streams the
    config does not describe (truth, other sensors) meet the first only."""
    out = feed_problems(rec)
    seen = {p.stream for p in out}
    for name, model in stream_models(arm).items():
        s = rec.get(name)
        if s is None or name in seen or not len(s) or s.values.shape[1] != model.size:
            continue
        p = stream_problem(model, s)
        if p is not None:
            out.append(p)
    return out
