"""Automatic model discovery: the error ladder walked without a person.

``discover(model, data)`` diagnoses the model (:func:`armfusion.fusion.workbench.diagnose.diagnose`),
adds the best significant candidate, refits, diagnoses again, and stops when nothing is
significant (the corrected score test and ΔBIC < 0, as ``diagnose`` decides) or after
``max_rungs``. Every rung keeps what it added, the added block's estimate ± σ from that
rung's fit, and the residual RMS over the noise.

**The revisit.** When the forward walk stops, each effect it added (but the last, found with
all the others in already) is taken out again and the model diagnosed without it: an early
rung may have taken a larger effect for what a later one explains (acc3's six axis angles
for its board turned by three, while j2's sag was still missing). The best significant
candidate then is the same effect (kept), another one (swapped in where the BIC is lower: a
rung "A -> B"), or none, the others explaining it (taken out where the BIC is lower: a rung
"- A"). If the revisit changed the model and something is significant again, the forward
walk goes on once more.

**Judged on held-out data.** With ``held_out`` (the recording's last 30 %, or a second
recording: :mod:`armfusion.fusion.workbench.heldout`) each rung tries the first ``tries`` significant
candidates, each added and judged there, and keeps the one with the lowest held-out error,
if it is below the rung before's; the others are listed as refused with their reason, and
when none is kept the ladder stops. The revisit's swaps and removals are refused alike. The
held-out part so chooses among the candidates the fit part found significant (a
validation set); it is never fitted.

**Indistinguishable effects.** At each rung the significant refitted candidates whose whole
recording χ² after their quick refit is within ``tie_chi2`` of the best one's are a *tie*:
the recording fits them equally well (a likelihood ratio below ``exp(tie_chi2 / 2)``), so
they are reported together as one :class:`Finding` ("one of these"), with the motion that
would separate them (:func:`armfusion.fusion.identification.identifiability.suggestion_for` of each
member). The ladder goes on with the first of them in the ranking (the best ΔBIC: on equal
fits, the one with fewer parameters) as the group's stand-in, so that what remains can be
found; the finding says it is a stand-in.

**Where it stops above the noise** :attr:`Discovery.remaining` says what the remaining
residual follows: the worst sensors, the residual against the noise the recording itself
shows (:meth:`Diagnosis.measured_noise_ratios`: near 1 means noise the sensor model does not
know, such as vibration), the inputs it follows beyond the corrected band (with their lag),
the axes that are not white.

Parked recordings only: the fit takes the chair as still. On a moving recording the
command runs the tracker's innovations analysis instead (``armfusion diagnose --discover``
on a moving recording), which says what the innovations follow but ranks no effect.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from armfusion.fusion.identification.data import FitData
from armfusion.fusion.identification.identifiability import suggestion_for
from armfusion.fusion.workbench.candidates import Candidate, params_words
from armfusion.fusion.workbench.diagnose import DiagnoseSettings, Diagnosis, add_effects, diagnose
from armfusion.fusion.workbench.heldout import HeldOut
from armfusion.models.effects import Model, build_effect
from armfusion.models.effects.library import AccelAxes, MountRotation

STOP_NOISE = "fits to noise"
STOP_NOTHING = "nothing significant is left, above the noise: no effect of the library explains the rest"
STOP_RUNGS = "rung limit reached"
STOP_NO_GAIN = "the last effect added did not lower the residual"
STOP_HELD_OUT = "none of the significant candidates tried lowered the held-out error"

SAME_IN_EVERY_MOTION = {
    frozenset({MountRotation.name, AccelAxes.name}): "a board turned is its three axes turned together: no "
    "motion separates them",
}
"""Pairs of effects on one sensor one of which contains the other in every recording
(docs/effects.md, "What the data can and cannot separate"): no motion tells them apart."""


@dataclass(frozen=True)
class DiscoverSettings:
    diagnose: DiagnoseSettings = field(default_factory=DiagnoseSettings)
    """Each rung's diagnosis (significance level, refits, noise tolerance)."""
    max_rungs: int = 10
    """Effects added at most."""
    tie_chi2: float = 10.0
    """Candidates whose χ² after their refit is within this of the best's are reported
    together (the recording cannot tell them apart: likelihood ratio below e^5)."""
    tries: int = 3
    """With held-out data: the significant candidates (best first in sample) each added and
    judged there at a rung; the one with the lowest held-out error is kept."""


@dataclass(frozen=True)
class Finding:
    """What one rung found: one effect, or a group the recording cannot tell apart."""

    members: tuple[str, ...]
    """``effect:target`` of each; the first is the one added (the group's stand-in)."""
    rms_after: tuple[float | None, ...]
    """Each member's whole-model RMS over the noise after its quick refit."""
    separate_by: str
    """For a group: the motion that would separate them ("" for one effect)."""

    @property
    def added(self) -> str:
        return self.members[0]

    @property
    def added_block(self) -> str:
        """The added effect's block name (``acc3.mount_rotation``)."""
        effect, _, target = self.added.partition(":")
        return f"{target}.{effect}"

    @property
    def is_group(self) -> bool:
        return len(self.members) > 1

    def words(self) -> str:
        if not self.is_group:
            return self.added
        return (f"one of {', '.join(self.members)} (the recording cannot tell them apart; "
                f"{self.added} stands in): {self.separate_by}")

    def as_dict(self) -> dict[str, Any]:
        return {"members": list(self.members), "added": self.added,
                "rms_after": [None if r is None else round(r, 4) for r in self.rms_after],
                "separate_by": self.separate_by or None}


@dataclass(frozen=True)
class Rung:
    """One model version of the ladder."""

    label: str
    finding: Finding | None
    """What this rung added (None: rung 0, the config as it is)."""
    estimate: dict[str, tuple[float, float]]
    """The added block's elements -> (estimate, σ) from this rung's fit, in ``units``."""
    units: str
    diagnosis: Diagnosis

    @property
    def rms_ratio(self) -> float:
        return self.diagnosis.rms_ratio

    @property
    def verdict(self) -> str:
        return self.diagnosis.verdict

    @property
    def per_stream(self) -> dict[str, float]:
        return self.diagnosis.stream_ratios()

    @property
    def measured_ratio(self) -> float:
        """RMS over the noise the recording shows (:meth:`Diagnosis.measured_noise_ratios`)."""
        return self.diagnosis.measured_noise_ratios()[0]

    def estimate_words(self) -> str:
        return params_words(self.estimate, self.units) if self.estimate else ""

    @property
    def held_out_ratio(self) -> float | None:
        return self.diagnosis.held_out_ratio

    def as_dict(self) -> dict[str, Any]:
        h = self.held_out_ratio
        return {"label": self.label, "rms_ratio": round(self.rms_ratio, 4), "verdict": self.verdict,
                "held_out_rms_ratio": None if h is None else round(h, 4),
                "finding": None if self.finding is None else self.finding.as_dict(),
                "units": self.units or None,
                "estimate": {k: {"value": v, "sigma": s} for k, (v, s) in self.estimate.items()},
                "streams": {s: round(r, 4) for s, r in self.per_stream.items()}}


@dataclass(frozen=True)
class Discovery:
    """The result of :func:`discover`: the ladder, why it stopped, what is left."""

    rungs: tuple[Rung, ...]
    stop: str
    remaining: tuple[str, ...]
    """Where it stops above the noise: what the residual follows (empty at the noise)."""
    seconds: float
    findings: tuple[Finding, ...]
    """What the final model added, in the order found (after the revisit)."""
    refused: tuple[tuple[str, str], ...] = ()
    """Model versions refused, and why (``(label, reason)``): their held-out error rose."""

    @property
    def first(self) -> Diagnosis:
        return self.rungs[0].diagnosis

    @property
    def final(self) -> Diagnosis:
        return self.rungs[-1].diagnosis

    def as_dict(self) -> dict[str, Any]:
        return {"stop": self.stop, "rms_ratio": round(self.final.rms_ratio, 4),
                "findings": [f.as_dict() for f in self.findings],
                "rungs": [r.as_dict() for r in self.rungs],
                "remaining": list(self.remaining), "seconds": round(self.seconds, 3),
                "refused": [{"label": a, "reason": b} for a, b in self.refused]}


def discover(model: Model, data: FitData, settings: DiscoverSettings | None = None,
             attitude0_rad: np.ndarray | None = None,
             progress: Callable[[str, float], None] | None = None,
             held_out: HeldOut | None = None) -> Discovery:
    """Walk the error ladder from ``model`` on ``data`` (module docstring); with ``held_out``
    every rung is judged there and one whose held-out error rises is refused."""
    st = settings or DiscoverSettings()
    t0 = time.perf_counter()
    say = progress or (lambda _m, _f: None)
    total = 2 * st.max_rungs + 1
    count = [0]

    def stage():
        k = count[0]
        count[0] += 1
        return lambda msg, f: say(f"rung {k}: {msg}", min((k + f) / total, 1.0))

    d = diagnose(model, data, st.diagnose, attitude0_rad=attitude0_rad, progress=stage(), held_out=held_out)
    rungs = [Rung("the config as it is", None, {}, "", d)]
    findings: list[Finding] = []
    refused: list[tuple[str, str]] = []
    stop = STOP_RUNGS
    for _round in range(2):  # forward, revisit; once more forward if the revisit changed the model
        d, stop = _forward(d, data, model.arm, st, rungs, findings, stage, refused)
        if stop in (STOP_NO_GAIN, STOP_HELD_OUT) or len(findings) < 2:
            break
        d, changed = _revisit(d, data, model.arm, st, rungs, findings, stage, refused)
        if not changed or not d.significant:
            if not d.significant:
                stop = STOP_NOISE if d.fits_to_noise else STOP_NOTHING
            break
    say("done", 1.0)
    return Discovery(tuple(rungs), stop, remaining_words(d, st.diagnose.noise_tolerance),
                     time.perf_counter() - t0, tuple(findings), tuple(refused))


def held_out_worse(before: Diagnosis, after: Diagnosis) -> str | None:
    """Why ``after`` is refused against ``before`` (None: it is not): its held-out error is
    higher. Without held-out data nothing is refused."""
    a, b = before.held_out_ratio, after.held_out_ratio
    if a is None or b is None or b <= a:
        return None
    return f"the held-out error rose from {a:.3f} to {b:.3f}x the noise ({after.held_out.label})"


def _rung(label: str, finding: Finding, c: Candidate, d: Diagnosis) -> Rung:
    """A rung that added candidate ``c`` (the finding's stand-in), with its estimate from ``d``."""
    block = f"{c.target}.{c.effect}"
    sl = d.fit.model.index[block]
    names = [n.split("[")[-1].rstrip("]") for n in d.fit.names[sl]]
    est = {f"{block}[{n}]": (float(v), float(s))
           for n, v, s in zip(names, d.fit.x[sl], d.fit.sigma[sl], strict=True)}
    return Rung(label, finding, est, c.units, d)


def _forward(d: Diagnosis, data: FitData, arm, st: DiscoverSettings, rungs: list[Rung],
             findings: list[Finding], stage, refused: list[tuple[str, str]]) -> tuple[Diagnosis, str]:
    """Add the best significant candidate until nothing is significant (or the rung limit, or
    an addition that does not lower the residual, or none that does not raise the held-out
    error). Appends to ``rungs``, ``findings`` and ``refused``."""
    while len(findings) < st.max_rungs:
        sig = d.significant
        if not sig:
            return d, STOP_NOISE if d.fits_to_noise else STOP_NOTHING
        nxt = None
        if d.held_out_ratio is None:  # nothing to judge on: the best in sample
            c = sig[0]
            nxt, chosen = add_effects(d, [build_effect(arm, c.effect, c.target)], st.diagnose,
                                      progress=stage()), c
        else:
            # the first few significant candidates, each added and judged on the held-out data:
            # the one that fits it best, if any fits it better than the rung before (in sample
            # a bias can fit a hair better than the scale it stands in for, and tilt the angles)
            trials = []
            for c in sig[:st.tries]:
                trial = add_effects(d, [build_effect(arm, c.effect, c.target)], st.diagnose, progress=stage())
                why = held_out_worse(d, trial)
                if why is None:
                    trials.append((trial.held_out_ratio, len(trials), trial, c))
                else:
                    refused.append((f"+ {c.name}", why))
            if trials:
                _, _, nxt, chosen = min(trials, key=lambda t: (t[0], t[1]))
        if nxt is None:
            return d, STOP_HELD_OUT
        finding = _finding((chosen, *[o for o in sig if o is not chosen]), d.fit.n_residuals, st.tie_chi2)
        rungs.append(_rung(f"+ {finding.added}", finding, chosen, nxt))
        findings.append(finding)
        gained = nxt.rms_ratio < d.rms_ratio * (1.0 - 1e-9)
        d = nxt
        if not gained:
            return d, STOP_NO_GAIN
    return d, STOP_RUNGS if d.significant else (STOP_NOISE if d.fits_to_noise else STOP_NOTHING)


def _bic(d: Diagnosis) -> float:
    """χ² of the whole recording plus BIC's price of every free element."""
    return d.rms_ratio**2 * d.fit.n_residuals + int((~d.fit.held).sum()) * np.log(d.fit.n_residuals)


def _revisit(d: Diagnosis, data: FitData, arm, st: DiscoverSettings, rungs: list[Rung],
             findings: list[Finding], stage, refused: list[tuple[str, str]]) -> tuple[Diagnosis, bool]:
    """Each effect added, taken out again with all the others in: an early rung may have taken
    a larger effect for what a later one explains (acc3's axes for its board turned, while
    j2's sag was still missing). Diagnosed without it, the best significant candidate is it
    again (kept; its group of equal fits as they stand now), another one (swapped in where the
    BIC is lower) or none (the others explain it: taken out)."""
    changed = False
    for f in findings[:-1]:  # the last was found with all the others in already
        if f.added_block not in d.fit.model.index:
            continue
        wo = diagnose(d.model.without([f.added_block]), d.data, st.diagnose, attitude0_rad=d.fit.attitude_rad,
                      progress=stage(), held_out=d.held_out)
        sig = wo.significant
        i = findings.index(f)
        if not sig:
            why = held_out_worse(d, wo)
            if why is not None:
                refused.append((f"- {f.added}", why))
            elif _bic(wo) <= _bic(d):
                rungs.append(Rung(f"- {f.added} (the others explain it)", None, {}, "", wo))
                findings.pop(i)
                d, changed = wo, True
            continue
        g = _finding(sig, wo.fit.n_residuals, st.tie_chi2)
        if g.added == f.added:
            findings[i] = g
            continue
        nxt = add_effects(wo, [build_effect(arm, sig[0].effect, sig[0].target)], st.diagnose,
                          progress=stage())
        why = held_out_worse(d, nxt)
        if why is not None:
            refused.append((f"{f.added} -> {g.added}", why))
        elif _bic(nxt) < _bic(d):
            rungs.append(_rung(f"{f.added} -> {g.added}", g, sig[0], nxt))
            findings[i] = g
            d, changed = nxt, True
    return d, changed


def _finding(sig: tuple[Candidate, ...], n_residuals: int, tie_chi2: float) -> Finding:
    """The best significant candidate and those the recording fits as well (within
    ``tie_chi2`` of its χ² after the refit)."""
    best = sig[0]
    members = [best]
    if best.rms_after is not None:
        chi2_best = best.rms_after**2 * n_residuals
        members += [c for c in sig[1:] if c.refitted and c.rms_after is not None
                    and c.rms_after**2 * n_residuals - chi2_best <= tie_chi2]
    separate = ""
    parts: list[str] = []
    for c in members[1:]:
        same = SAME_IN_EVERY_MOTION.get(frozenset({best.effect, c.effect}))
        if same is not None and c.target == best.target:
            parts.append(same)
        else:  # the motion that makes each one's own parameters known
            parts += [suggestion_for(f"{best.target}.{best.effect}[0]"),
                      suggestion_for(f"{c.target}.{c.effect}[0]")]
    separate = "; or ".join(dict.fromkeys(parts))
    return Finding(tuple(c.name for c in members), tuple(c.rms_after for c in members), separate)


def remaining_words(d: Diagnosis, noise_tolerance: float, n_inputs: int = 4,
                    n_axes: int = 3) -> tuple[str, ...]:
    """What the residual of ``d`` follows, in words, where it is above the noise: the worst
    sensors, the input correlations beyond the corrected band (with their lag) and the axes
    that are not white. Empty at the noise."""
    if d.rms_ratio <= noise_tolerance:
        return ()
    out = []
    worst = sorted(d.stream_ratios().items(), key=lambda kv: -kv[1])
    out.append("worst sensors: " + ", ".join(f"{s} {r:.2f}× the noise" for s, r in worst[:3]))
    measured, per = d.measured_noise_ratios()
    out.append(f"against the noise the recording itself shows (the sensor model's with the single-sample "
               f"excess the fit measured, e.g. vibration): {measured:.2f}× overall ("
               + ", ".join(f"{s} {per[s]:.2f}×" for s, _ in worst[:3]) + ")")
    a = d.analysis
    if a is not None:
        for fc in a.flagged()[:n_inputs]:
            out.append(f"{fc.axis} follows {fc.input} (r {fc.r:+.2f} at lag {fc.lag:+d}, "
                       f"{abs(fc.lag) * a.dt_s:.2g} s)")
        for _s, ax, m in a.not_white()[:n_axes]:
            out.append(f"{ax} is not white (autocorrelation up to {m:.2f})")
        if a.white:
            out.append("the residual is white and follows no input: noise the sensor model does not know")
    return tuple(out)
