"""What ``armfusion diagnose`` keeps and writes: the error ladder's history, and the config
with the fit's estimates, written only when the fit is judged no worse on the held-out data
than the config it replaces, by the fit and by the tracker."""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml
from armfusion.fusion.cli.common import progress_bar
from armfusion.fusion.configfile import load_arm, resolve_config_path
from armfusion.fusion.identification.identify import config_with_estimates
from armfusion.fusion.workbench.diagnose import Diagnosis
from armfusion.fusion.workbench.discover import Discovery
from armfusion.fusion.workbench.heldout import HeldOut, Tracked, tracked, tracked_worse
from armfusion.fusion.workbench.zeros import turns_from_encoder_zeros
from armfusion.sensors.output_files import write_text_replacing
from armfusion.sensors.samples import Recording

HISTORY_FORMAT = "armfusion.workbench-history/1"


def history_path(config: str) -> Path:
    """Beside the config when it is a file the user named; in the current directory for a
    shipped config (``wmra``), so the repository's configs stay untouched."""
    p = Path(config)
    if p.exists():
        return p.with_name(p.stem + ".workbench.json")
    return Path.cwd() / f"{Path(config).stem}.workbench.json"


def history_entry(diag: Diagnosis, recording: Path, config: str, label: str) -> dict:
    top = diag.candidates[0] if diag.candidates else None
    return {
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "recording": str(recording), "config": str(config), "label": label,
        "effects": [e for e in diag.effects() if not e.endswith(".joint_offset")],
        "rms_ratio": round(diag.rms_ratio, 5),
        "held_out_rms_ratio": None if diag.held_out_ratio is None else round(diag.held_out_ratio, 5),
        "streams": {s: round(r, 5) for s, r in diag.stream_ratios().items()},
        "verdict": diag.verdict,
        "top_candidate": None if top is None else top.name,
    }


MAX_HISTORY_BYTES = 64 << 20
"""A history file larger than this is not read (a run adds about a kilobyte)."""


def _history_doc(path: Path) -> dict | None:
    from armfusion.fusion.configfile import read_bounded

    try:
        doc = json.loads(read_bounded(path, MAX_HISTORY_BYTES, "a workbench history"))
    except (OSError, ValueError):
        return None
    ok = (isinstance(doc, dict) and str(doc.get("format", "")).startswith(HISTORY_FORMAT.split("/")[0])
          and isinstance(doc.get("runs", []), list))
    return doc if ok else None


def history_problem(path: Path) -> str | None:
    """Why the history file ``path``, which ``diagnose`` reads and then replaces, must not be
    (a device, a FIFO: read without end or blocking; a file that is no workbench history: a
    recording or a report would be replaced), or ``None`` (absent, or a history)."""
    if not path.exists():
        return None
    if not path.is_file():
        return "not a regular file (a device, a FIFO); diagnose would replace it"
    if _history_doc(path) is None:
        return ("holds something other than a workbench history; diagnose would replace it: give "
                "another path, or remove the file")
    return None


def append_history(path: Path, entries: list[dict]) -> list[dict]:
    """Append ``entries`` to the history file at ``path`` (absent, or a history:
    :func:`history_problem`); returns the whole ladder."""
    doc = _history_doc(path) if path.exists() else None
    runs: list[dict] = list(doc.get("runs", [])) if doc else []
    runs += entries
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_replacing(path, json.dumps({"format": HISTORY_FORMAT, "runs": runs}, indent=2) + "\n")
    return runs


@dataclass
class Fits:
    """What ``diagnose`` fitted: the config as it is (``before``), with the added or discovered
    effects (``after``), the discovery, the added effects, why they are refused, and the config
    as it is judged on the held-out data (``as_is``, when a config is to be written)."""

    before: Diagnosis
    after: Diagnosis | None
    disc: Discovery | None
    added: list
    refused_add: str | None
    as_is: object | None

    @property
    def final(self) -> Diagnosis:
        return self.after or self.before


def extend_ladder(hpath: Path, fits: Fits, recording: Path, config: str, write: Path | None,
                   history: Path | None) -> list:
    """The error ladder with this run's model versions appended (in ``hpath``, and beside the
    config to be written when no ``--history`` is given)."""
    if fits.disc is not None:
        entries = [history_entry(r.diagnosis, recording, config, Path(config).stem if k == 0 else r.label)
                   for k, r in enumerate(fits.disc.rungs)]
    else:
        entries = [history_entry(fits.before, recording, config, Path(config).stem)]
        if fits.after is not None:
            entries.append(history_entry(fits.after, recording, config,
                                         "+ " + ", ".join(e.block_name for e in fits.added)))
    ladder = append_history(hpath, entries)
    if write is not None and history is None:  # the written config carries the ladder on
        nxt = write.with_name(write.stem + ".workbench.json")  # beside it (it is not written yet)
        if nxt.resolve() != hpath.resolve():
            nxt.parent.mkdir(parents=True, exist_ok=True)
            write_text_replacing(nxt, json.dumps({"format": HISTORY_FORMAT, "runs": ladder}, indent=2) + "\n")
    return ladder


@dataclass(frozen=True)
class HeldOutCheck:
    """What a config is judged on before it is written: the recording the tracker runs over
    (``rec``), the held-out part of the fit's data (``held``), and, where elements of the fit
    ended at their bound, what is written judged on that part (``written_held``; ``None``:
    none did)."""

    rec: Recording
    held: HeldOut
    written_held: object | None = None


def write_config(arm, fits: Fits, recording: Path, config: str, write: Path, check: HeldOutCheck,
                 json_out: bool) -> tuple[dict | None, str | None]:
    """Write the config with the final fit's estimates to ``write`` when the tracker over the
    held-out part (``check``) does not refuse it: the tracker's figures, and the refusal's
    reason (None: written). ``recording`` and ``config``: what the fit ran on, for the header."""
    final, disc, as_is = fits.final, fits.disc, fits.as_is
    held, written_held = check.held, check.written_held
    src = resolve_config_path(config)
    cfg = yaml.safe_load(src.read_text(encoding="utf-8"))
    judge = TrackedJudge(arm, check.rec, held, json_out, convention_groups(final))
    before, failed = judge.as_it_is()
    if failed is not None:
        return None, failed
    fit = without_bound(final)
    moved = turns_from_encoder_zeros(fit, final.data, final.gauges, tuple(before.encoder_rms_deg))
    out = config_with_estimates(cfg, fit if moved is None else moved.fit)
    raise_floors(out, final, arm)
    consistency, refused = judge.against(before, out)
    if refused is not None:
        return consistency, refused
    write.parent.mkdir(parents=True, exist_ok=True)
    stand_ins = "".join(f"# {f.added} stands in for one of {', '.join(f.members)} (equal fits)\n"
                        for f in (disc.findings if disc is not None else ()) if f.is_group)
    bound = "".join(f"# {n}: its fit ended at the parameter's bound; written at its prior\n"
                    for n in final.at_bound)
    turns = ("".join(f"# {n}: {np.degrees(v):+.3f}° ± {np.degrees(sg):.3f}°, from the encoders' zeros "
                     f"({', '.join(moved.joints)} read their own angles)\n" for n, (v, sg) in moved.turns.items())
             if moved is not None else "")
    held_ratio = final.held_out_ratio if written_held is None else written_held.rms_ratio
    judged = (f"# held out: {final.held_out.label}: {held_ratio:.3f}x the noise "
              f"(the config as it was: {as_is.rms_ratio:.3f}x)\n"
              if held_ratio is not None and as_is is not None else "")
    write_text_replacing(write, f"# armfusion diagnose: rms_ratio {final.rms_ratio:.3f} ({final.verdict})\n"
                         f"# from {recording}, config {src.name}\n" + judged + stand_ins + bound + turns
                         + yaml.safe_dump(out, sort_keys=False, width=110))
    return consistency, None


def convention_groups(final: Diagnosis) -> tuple[tuple[str, ...], ...]:
    """Per structural gauge of the fit (a held turn of a mount about a joint's axis), the
    joints whose zeros take it (parallel axes: the turn is their sum's): the written config
    takes the turn for their zeros."""
    return tuple(dict.fromkeys(
        tuple(sorted(p.removesuffix(".joint_offset") for p in g.partners if p.endswith(".joint_offset")))
        for g in final.gauges if g.structural))


@dataclass(frozen=True)
class TrackedJudge:
    """The tracker over the held-out part of ``rec``: with the config it would replace
    (:meth:`as_it_is`), then with the one it would write (:meth:`against`); ``groups``: the
    joints whose zeros a held gauge makes the same as a turn, :func:`convention_groups`, whose
    sums are judged against the encoders beside each joint."""

    arm: object
    rec: object
    held: HeldOut
    json_out: bool
    groups: tuple[tuple[str, ...], ...] = ()

    @property
    def t_from_s(self) -> float:
        return float(self.held.data.state.t_s[0]) if self.held.same_recording else -np.inf

    def as_it_is(self) -> tuple[Tracked | None, str | None]:
        """The config as it is tracked; or why the tracker could not run."""
        with progress_bar("tracking the held-out part", self.json_out) as advance:
            try:
                advance(0.0, "with the config as it is")
                return tracked(self.arm, self.rec, self.t_from_s, self.groups), None
            except (ValueError, RuntimeError) as e:
                return None, f"the tracker could not run over the held-out part to judge it: {e}"

    def against(self, before: Tracked, out: dict) -> tuple[dict | None, str | None]:
        """The config ``out`` (a dict, as written) tracked and judged against ``before``
        (:func:`armfusion.fusion.workbench.heldout.tracked_worse`): both runs' figures, and the
        refusal's reason (None: no worse)."""
        with progress_bar("tracking the held-out part", self.json_out) as advance:
            try:
                with tempfile.TemporaryDirectory() as d:
                    path = Path(d) / "candidate.yaml"
                    path.write_text(yaml.safe_dump(out, sort_keys=False), encoding="utf-8")
                    new_arm = load_arm(str(path))
                advance(0.5, "with the config to write")
                after = tracked(new_arm, self.rec, self.t_from_s, self.groups)
            except (ValueError, RuntimeError) as e:
                return None, f"the tracker could not run over the held-out part to judge it: {e}"
        return {"as_it_is": before.as_dict(), "written": after.as_dict()}, tracked_worse(before, after)


def write_refusal(final: Diagnosis, as_is, written=None) -> str | None:
    """Why the fit ``final`` is not written (None: it may be): judged on the held-out data it
    fits worse than the config it would replace (``as_is``: that config's held-out fit).
    ``written``: where elements ended at their bound, what is written (those at their prior:
    :func:`without_bound`) judged there, which is what must not be worse."""
    ratio = final.held_out_ratio if written is None else written.rms_ratio
    if ratio is None or as_is is None:
        return None
    if ratio > as_is.rms_ratio:
        what = "it" if written is None else "what it would write (the elements at their bound at their prior)"
        return (f"on the held-out data ({final.held_out.label}) {what} fits worse than the config it would "
                f"replace: {ratio:.3f} against {as_is.rms_ratio:.3f}x the noise")
    return None


def without_bound(d: Diagnosis):
    """The fit with every element that ended at its bound back at its prior (value and σ, its
    covariance with every other element none: the fit told nothing of it)."""
    if not d.at_bound:
        return d.fit
    f = d.fit
    x, sig, cov = f.x.copy(), f.sigma.copy(), f.covariance.copy()
    for n in d.at_bound:
        i = list(f.names).index(n)
        x[i], sig[i] = f.x0[i], f.prior_sigma[i]
        cov[i, :] = 0.0
        cov[:, i] = 0.0
        cov[i, i] = f.prior_sigma[i] ** 2
    return replace(f, x=x, sigma=sig, covariance=cov)


def raise_floors(cfg: dict, d: Diagnosis, arm=None) -> None:
    """The written accelerometer floors (the unmodelled error, what stays): at least what the
    fit leaves on the held-out data (the in-sample residual is smaller by the parameters
    fitted to it), and, with ``arm`` (the config it replaces), never below that config's own
    floor. The fit's residual is of window means: it does not see what a tracker reading
    every sample meets (a clock's offset while moving, a resampled stream's shared samples);
    a lower floor made the UR5 twin's tracked forearm pitch 0.87° RMS on its held-out part
    against 0.23°. The fast error the fit measured (``accel_fast_error_g_per_sensor``, one
    sample's excess) is kept as written: it only adds to a reading's noise."""
    cal = cfg.get("calibration") or {}
    per = dict(cal.get("accel_unmodelled_g_per_sensor") or {})
    model_arm = d.fit.model.arm
    if d.held_out_fit is not None:
        for s, g in d.held_out_fit.unmodelled("g").items():
            name = model_arm.imu.name if s == "imu_acc" and model_arm.imu is not None else s
            per[name] = max(float(per.get(name, 0.0)), g)
    if arm is not None:
        for s in arm.link_accelerometers:
            per[s.name] = max(float(per.get(s.name, 0.0)), arm.calibration.accel_floor_g(s.name))
    per = {k: round(max(v, 1e-4), 6) for k, v in per.items()}
    if per:
        cal["accel_unmodelled_g_per_sensor"] = per
        cal["accel_unmodelled_g"] = max(per.values())
        cfg["calibration"] = cal
