"""Judged on data the fit did not see: the recording split in time (the fit on its first
``1 - share``, judged on the rest), or a second recording of the same arm.

A model version's **held-out error** is its residual RMS over the noise on the held-out part,
at the estimates the fit part gave. Within one recording the encoder zeros and the base
attitude carry over (the same joints, the same stance); a second recording has its own, so
they alone are fitted there (every effect held at the fit part's estimate) before it is
judged. A rung of the ladder, an ``--add`` or a written config whose held-out error is above
the one before it is refused (:mod:`armfusion.fusion.workbench.discover`, ``armfusion.fusion.cli.diagnose``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from armfusion.fusion.identification.data import FitData
from armfusion.fusion.identification.identify import identify
from armfusion.fusion.identification.problem import FitProblem
from armfusion.fusion.identification.result import Identification
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.workbench.gauges import held_elements, structural_gauges
from armfusion.fusion.workbench.residuals import fit_model
from armfusion.models.effects import Model
from armfusion.models.effects.library import JointOffset

HELD_OUT_SHARE = 0.3
"""The share of a recording (its end) judged, not fitted."""
MIN_HELD_OUT_POINTS = 20
"""Fewer held-out fit points than this and nothing is judged (the split is refused)."""


@dataclass(frozen=True)
class HeldOut:
    """The data a fit is judged on."""

    data: FitData
    same_recording: bool
    """True: the end of the fitted recording (its encoder zeros and attitude carry over)."""
    label: str

    def aligned(self, fitted: FitData) -> FitData:
        """The held-out part with the start pose the fit ended up using (a rival branch of the
        still start moves it: the same shift here)."""
        if not self.same_recording:
            return self.data
        dq = fitted.q_ref_rad - self.data.q_ref_rad
        return self.data.shifted(dq) if np.any(dq) else self.data


def split_in_time(data: FitData, share: float = HELD_OUT_SHARE) -> tuple[FitData, HeldOut]:
    """The first ``1 - share`` of the fit points to fit, the rest held out."""
    if not 0.0 < share < 1.0:
        raise ValueError(f"held-out share must be between 0 and 1, not {share}")
    k = int(round(data.n * (1.0 - share)))
    if data.n - k < MIN_HELD_OUT_POINTS or k < MIN_HELD_OUT_POINTS:
        raise ValueError(f"the recording has {data.n} fit points: too few to fit on "
                         f"{100 * (1 - share):.0f} % and judge on the rest (at least "
                         f"{MIN_HELD_OUT_POINTS} each)")
    fit_part = data.subset(slice(0, k))
    held = data.subset(slice(k, None))
    t0, t1 = float(held.state.t_s[0]), float(held.state.t_s[-1])
    return fit_part, HeldOut(held, True, f"the recording's last {100 * share:.0f} % ({t0:.1f}-{t1:.1f} s)")


@dataclass(frozen=True)
class HeldOutFit:
    """A fit judged on held-out data."""

    rms_ratio: float
    """Residual RMS over the noise there."""
    stream_rms: dict[str, np.ndarray]
    """Per stream, each axis's residual RMS there (physical units)."""
    stream_noise: dict[str, np.ndarray]
    stream_units: dict[str, str]

    def unmodelled(self, unit: str = "g") -> dict[str, float]:
        """Per stream in ``unit``, the worst axis's residual beyond the noise there."""
        return {s: float(np.max(np.sqrt(np.clip(r**2 - self.stream_noise[s] ** 2, 0, None))))
                for s, r in self.stream_rms.items() if self.stream_units[s] == unit}


def judge(fit: Identification, fitted: FitData, held: HeldOut, streams: Sequence[str],
          settings: IdentifySettings) -> HeldOutFit | None:
    """``fit`` (made on ``fitted``) on the held-out data; None where it cannot be judged there
    (the held-out part has a stance of the chair the fit never saw)."""
    data = held.aligned(fitted)
    model = fit.model.with_values(fit.model_x)
    att = fit.attitude_rad if fit.attitude_rad is not None else np.zeros(3)
    if held.same_recording:
        if data.n_stances > fitted.n_stances:
            return None
        z = np.concatenate([fit.model_x, fit.x[model.size:]]) if fit.attitude_rad is not None else fit.model_x
        pb = FitProblem(model, data, streams, fit.attitude_rad is not None, att,
                        encoder_scale=settings.encoder_scale)
    else:
        # another recording: its own encoder zeros and attitude, every effect at the fit's estimate
        effects = [b.name for b in model.blocks if b.effect != JointOffset.name]
        hold = [*effects, *held_elements(structural_gauges(model, data))]
        res = identify(model, data, streams, settings, hold=hold, attitude0_rad=fit.attitude_rad)
        pb = FitProblem(res.model.with_values(res.model_x), data, streams, res.attitude_rad is not None,
                        res.attitude_rad if res.attitude_rad is not None else np.zeros(3),
                        encoder_scale=settings.encoder_scale)
        z = res.x
    pred = pb.predict(z)
    r = (pred - pb.meas) * pb.w
    n = max(int(np.count_nonzero(pb.w)), 1)
    sm = model.stream_models()
    rms, noise = {}, {}
    i = 0
    for s in pb.streams:
        shape = data.counts[s].shape
        size = data.counts[s].size
        d = (pred[i:i + size] - pb.meas[i:i + size]).reshape(shape)
        i += size
        g = np.abs(sm[s].gain)
        rms[s] = np.sqrt(np.mean(d**2, 0)) / g
        noise[s] = np.broadcast_to(data.sigma_counts[s], (shape[1],)) / g
    return HeldOutFit(float(np.sqrt(float(r @ r) / n)), rms, noise, {s: sm[s].unit for s in pb.streams})


def as_it_is(model: Model, fitted: FitData, held: HeldOut, streams: Sequence[str],
             settings: IdentifySettings, attitude0_rad: np.ndarray | None = None) -> HeldOutFit | None:
    """The config as it is (every effect at its value), judged on ``held``: only the
    recording's encoder zeros and the base attitude fitted, on ``fitted``. What a written
    config must not be worse than."""
    effects = [b.name for b in model.blocks if b.effect != JointOffset.name]
    fit = fit_model(model, fitted, streams, settings, attitude0_rad, hold=effects)
    return judge(fit, fitted, held, streams, settings)


TRACKED_SLACK = 0.01
"""A written config may keep up to this share fewer held-out innovations within 3σ than the
config it replaces, or its innovations' RMS or mean NIS be up to this share larger (chance
between two runs of one recording), and still be written."""
CHANCE_Z = 3.0
"""A tracked angle's RMS off its encoder must rise by more than this many of its chance
spreads (:func:`chance_deg`) to count as worse: the 3σ used everywhere else (a config no
different refused by chance 0.13 % of the time, one-sided)."""
NIS_3SIGMA = {1: 9.0, 2: 11.83, 3: 14.16}
"""χ² of the 99.73 % (3σ) quantile by degrees of freedom."""


@dataclass(frozen=True)
class Tracked:
    """The tracker over the held-out part of a recording (from ``t_from_s`` on), judged
    without the truth: each link accelerometer's innovations, and each joint's angle against
    its encoder.

    With relative encoders the tracker's angle is the encoder's reading plus an offset it
    estimates; where the model is right that offset stays put as the arm moves, and where it
    is wrong (a scale, a mount, a clock) gravity pulls it one way in one pose and another way
    in the next. Its wander over the held-out part (RMS about its median) is the part of the
    angles' error the recording itself shows; its constant part is the gauge no recording
    shows (a joint's zero against its sensors' mounts about that joint's axis)."""

    within_3_sigma: dict[str, float]
    """Per accelerometer, the share of its innovations inside the 3σ ellipsoid (NIS below the
    χ² 99.73 % quantile): 99.7 % when the filter's σ are right, less when it is too sure."""
    mean_nis_per_dof: dict[str, float]
    """Per accelerometer, the mean NIS over its dof: 1 when right, below when cautious."""
    innovation_rms: dict[str, float] = field(default_factory=dict)
    """Per accelerometer, the RMS of its innovations (the readings' units, every axis): what
    the tracked model leaves of the readings."""
    offset_wander_deg: dict[str, float] = field(default_factory=dict)
    """Per joint, the RMS of (tracked angle - encoder angle) about its median, deg."""
    encoder_step_deg: float = 0.0
    """One encoder count, deg: differences below it are the encoders' rounding."""
    encoder_rms_deg: dict[str, float] = field(default_factory=dict)
    """Per joint whose encoder reads its own angle (:func:`reads_its_own_angle`), the RMS of
    (tracked angle - encoder angle), its constant part included: what a user with absolute
    encoders (an industrial arm's controller angles) sees of the tracked angle's error."""
    chance_deg: dict[str, float] = field(default_factory=dict)
    """Per joint (and group), the spread (1σ, deg) by which two configs' RMS figures of it
    over the part judged differ by chance: the readings' noise, not the model
    (:func:`chance_deg`)."""

    @property
    def worst(self) -> float:
        return min(self.within_3_sigma.values(), default=1.0)

    def as_dict(self) -> dict[str, Any]:
        return {"within_3_sigma": {k: round(v, 4) for k, v in self.within_3_sigma.items()},
                "mean_nis_per_dof": {k: round(v, 3) for k, v in self.mean_nis_per_dof.items()},
                "innovation_rms": {k: float(f"{v:.4g}") for k, v in self.innovation_rms.items()},
                "offset_wander_deg": {k: round(v, 4) for k, v in self.offset_wander_deg.items()},
                "encoder_rms_deg": {k: round(v, 4) for k, v in self.encoder_rms_deg.items()},
                "chance_deg": {k: float(f"{v:.3g}") for k, v in self.chance_deg.items()}}


def reads_its_own_angle(offset_deg: np.ndarray, sigma_deg: np.ndarray) -> bool:
    """Does a joint's encoder read the joint's own angle (an absolute encoder, its zero the
    joint's)? Where the tracker's angle keeps within its own 3σ of the encoder's over the part
    judged (its offsets ``offset_deg``, its σ ``sigma_deg``), the encoder's zero is the one
    gravity reads; a relative encoder counts from where the arm stood at power-up, and the
    tracker's offset is that pose's angle, well outside its σ."""
    return bool(np.median(np.abs(offset_deg)) <= 3.0 * np.median(sigma_deg))


def tracked(arm, rec, t_from_s: float, groups: Sequence[Sequence[str]] = ()) -> Tracked:
    """Run the tracker over ``rec`` with ``arm`` (a config) and read, from ``t_from_s`` on, its
    link accelerometers' innovations and each joint's tracked angle against its encoder: with
    no truth at hand, whether the filter's σ hold there and how far the angles wander off the
    encoders (:class:`Tracked`). ``groups``: joints whose sum is also read so (keyed
    ``"a + b"``: the angle of the link after them, where their axes are parallel), where
    each of them reads its own angle."""
    from armfusion.fusion.tracking.settings import ENC
    from armfusion.fusion.tracking.tracker import start_from_recording
    from armfusion.models.rotations import wrap_angle

    tr, _start = start_from_recording(arm, rec)
    run = tr.run(rec, truth=False)
    within, nis, rms = {}, {}, {}
    for s in (a.name for a in arm.link_accelerometers):
        try:
            lg = tr.innovations(s)
        except KeyError:
            continue
        k = lg.innovation.shape[1]
        ok = np.isfinite(lg.nis) & (lg.t_s >= t_from_s)
        if ok.sum() < 10:
            continue
        within[s] = float(np.mean(lg.nis[ok] <= NIS_3SIGMA.get(k, 14.16)))
        nis[s] = float(np.mean(lg.nis[ok]) / k)
        inn = lg.innovation[ok]
        rms[s] = float(np.sqrt(np.mean(inn[np.all(np.isfinite(inn), axis=1)] ** 2)))
    wander: dict[str, float] = {}
    absolute: dict[str, float] = {}
    enc = rec.streams.get(ENC)
    late = (run.t_s >= t_from_s) & np.all(np.isfinite(run.q_rad), axis=1)
    if enc is not None and len(enc) and late.sum() >= 10:
        q_enc = enc.values / tr.counts_per_rad
        offs = {}
        for j, name in enumerate(arm.joint_names):
            e = np.interp(run.t_s[late], enc.t_s, q_enc[:, j])
            offs[name] = off = np.degrees(wrap_angle(run.q_rad[late, j] - e))
            wander[name] = float(np.sqrt(np.mean((off - np.median(off)) ** 2)))
            if reads_its_own_angle(off, np.degrees(run.sigma_rad[late, j])):
                absolute[name] = float(np.sqrt(np.mean(off**2)))
        for g in groups:
            if len(g) > 1 and all(j in absolute for j in g):
                off = np.sum([offs[j] for j in g], axis=0)
                wander[" + ".join(g)] = float(np.sqrt(np.mean((off - np.median(off)) ** 2)))
                absolute[" + ".join(g)] = float(np.sqrt(np.mean(off**2)))
    step = float(np.degrees(1.0 / np.max(np.atleast_1d(tr.counts_per_rad))))
    return Tracked(within, nis, rms, wander, step, absolute, chance_deg(arm, rec, t_from_s, groups))


def chance_deg(arm, rec, t_from_s: float, groups: Sequence[Sequence[str]] = ()) -> dict[str, float]:
    """Per joint (and per group of ``groups``, keyed as :func:`tracked` keys it), the spread
    (1σ, deg) by which two configs' RMS of the tracked angle off its encoder, over ``rec``
    from ``t_from_s`` on, differ by chance: from the config's noise figures and the part's
    length alone, not from the model.

    A tracked angle's error there is a part the model makes, ``s(t)``, and the part the
    readings' noise makes through the filter, ``n(t)``. The mean square over ``N`` readings
    carries ``2·mean(s·n)`` by chance: as an RMS, a spread of ``σ_n / √N_eff``, whatever the
    filter's bandwidth (a filter averaging ``k`` readings has ``σ_n² = σ²/k`` and ``N/k``
    independent values, so ``σ_n² / N_eff = σ² / N``). ``σ``: one reading's tilt noise, its
    accelerometer's datasheet noise and rounding at the rate it delivers independent readings
    (the config's ``rate_hz``: a stream resampled to a higher rate adds none), with the
    config's fast error, read as a tilt (1 g ≙ 1 rad); ``N``: its readings in the part. Each
    accelerometer on a link the joint moves reads the joint's angle, their information adds
    (``1 / Σ N_i/σ_i²``); two configs' figures each carry it (``√2``). A joint no
    accelerometer reads: 0 (its encoder's count is the only floor)."""
    from armfusion.models.sensor_models import stream_models

    info = []
    for s in arm.link_accelerometers:
        st = rec.get(s.name)
        if st is None or len(st) < 2:
            continue
        n = int(np.count_nonzero(st.t_s >= t_from_s))
        own = s.description.part("accelerometer").rate_hz
        rate = min(st.rate_hz, own) if own else st.rate_hz
        n = n * min(1.0, rate / st.rate_hz)
        sm = stream_models(arm, {s.name: rate})[s.name]
        noise_g = float(np.max(sm.sigma_counts / np.abs(sm.gain)))
        sigma = float(np.hypot(noise_g, arm.calibration.accel_fast_error_g(s.name)))
        if n >= 1 and sigma > 0:
            info.append((s.link, n / sigma**2))
    index = {name: j for j, name in enumerate(arm.joint_names)}
    keys = {name: (j,) for name, j in index.items()}
    keys.update({" + ".join(g): tuple(index[j] for j in g) for g in groups if len(g) > 1})
    out = {}
    for key, joints in keys.items():
        total = sum(w for link, w in info if link >= max(joints) + 1)  # link k moves with joints 1..k
        out[key] = float(np.degrees(np.sqrt(2.0 / total))) if total > 0 else 0.0
    return out


def tracked_worse(before: Tracked, after: Tracked) -> str | None:
    """Why ``after`` tracks the held-out part worse than ``before`` (None: it does not): a
    sensor with fewer innovations within 3σ, a larger innovation RMS, or a mean NIS per dof
    above 1 and above ``before``'s (too sure), each beyond :data:`TRACKED_SLACK`; or a joint
    (or group's sum) whose tracked angle is further off its encoder by more than chance
    (:data:`CHANCE_Z` times ``before``'s :attr:`Tracked.chance_deg`, at least one encoder
    count). Where the encoder reads the joint's own angle (:func:`reads_its_own_angle`, in
    both) the figure is the whole RMS off it, its constant part included (what a user with
    a controller's angles sees: a config that takes a mount's turn about the joint's axis
    for its zero is further off); elsewhere (a relative encoder, its zero the power-up
    pose's) its wander about the median."""
    why = []
    for s, w in after.within_3_sigma.items():
        if w < before.within_3_sigma.get(s, 0.0) - TRACKED_SLACK:
            why.append(f"{s} keeps {100 * w:.1f} % of its innovations within 3σ against "
                       f"{100 * before.within_3_sigma[s]:.1f} %")
    for s, r in after.innovation_rms.items():
        if s in before.innovation_rms and r > before.innovation_rms[s] * (1.0 + TRACKED_SLACK):
            why.append(f"{s}'s innovations are {r:.4g} RMS against {before.innovation_rms[s]:.4g}")
    for s, v in after.mean_nis_per_dof.items():
        b = before.mean_nis_per_dof.get(s)
        if b is not None and v > 1.0 and v > max(b, 1.0) * (1.0 + TRACKED_SLACK):
            why.append(f"{s}'s mean NIS per dof is {v:.2f} against {b:.2f} (too sure)")
    why += _angles_worse(before, after)
    if not why:
        return None
    return ("tracked over the held-out part it does worse than the config it replaces: " + "; ".join(why))


def _angles_worse(before: Tracked, after: Tracked) -> list[str]:
    """The joints (and groups) :func:`tracked_worse` finds further off their encoders."""
    step = max(before.encoder_step_deg, after.encoder_step_deg)
    why = []
    for j in dict.fromkeys([*after.encoder_rms_deg, *after.offset_wander_deg]):
        floor = max(CHANCE_Z * before.chance_deg.get(j, 0.0), step)
        a, b = after.encoder_rms_deg.get(j), before.encoder_rms_deg.get(j)
        if a is not None and b is not None:
            if a - b > floor:
                why.append(f"{j}'s tracked angle is {a:.3f}° RMS off its encoder, which reads the joint's "
                           f"own angle (its constant part included), against {b:.3f}° (chance {floor:.4f}°)")
            continue
        a, b = after.offset_wander_deg.get(j), before.offset_wander_deg.get(j)
        if a is not None and b is not None and a - b > floor:
            why.append(f"{j}'s tracked angle wanders {a:.3f}° RMS off its encoder against {b:.3f}° "
                       f"(chance {floor:.4f}°)")
    return why
