"""``armfusion diagnose``: where the model fails, which effect is missing; add it, refit.

    armfusion diagnose --config C REC [--json] [--add EFFECT[:TARGET] … | --discover [--rungs 10]]
        [--write C2.yaml] [--window 10] [--history H.json] [--report out.html]

Fits the config's model to the recording (``armfusion.fusion.workbench.diagnose``), shows every sensor axis's
residual RMS against its noise floor, the verdict and the ranked missing effects. ``--add``
refits with the named effects starting from the estimates and shows before and after;
``--discover`` walks the ladder by itself (``armfusion.fusion.workbench.discover``: add the best
significant candidate, refit, until nothing is significant) and shows every rung;
``--write`` saves the config with the (last) estimates. Every run appends each model
version's residual RMS to a history (the error ladder). See docs/workbench.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from armfusion.fusion.cli.common import (
    arm_and_recording_or_exit,
    check_output_path,
    config_file,
    console,
    emit_json,
    err_console,
    fail,
    progress_bar,
    read_recording_or_exit,
    screen_or_exit,
)
from armfusion.fusion.cli.diagnose_report import write_innovation_report, write_report
from armfusion.fusion.cli.diagnose_write import (
    Fits,
    HeldOutCheck,
    extend_ladder,
    history_path,
    history_problem,
    without_bound,
    write_config,
    write_refusal,
)
from armfusion.fusion.cli.options import ConfigOpt, JsonOpt, WriteConfigOpt, count_at_least
from armfusion.fusion.identification.identify import data_from_recording, fit_streams
from armfusion.fusion.workbench.diagnose import (
    DiagnoseSettings,
    Diagnosis,
    add_effects,
    chair_moves,
    diagnose,
    innovation_diagnosis,
    params_words,
    parse_add,
)
from armfusion.fusion.workbench.discover import DiscoverSettings, Discovery, discover, held_out_worse
from armfusion.fusion.workbench.heldout import HeldOut, as_it_is, judge, split_in_time
from armfusion.fusion.workbench.resampling import resampled_streams
from armfusion.models.effects import TargetError, model_from_arm
from rich.table import Table


def register(app: typer.Typer) -> None:
    """Add ``diagnose`` to the ``armfusion`` app (once)."""
    if any(c.name == "diagnose" for c in app.registered_commands):
        return
    app.command("diagnose")(diagnose_command)


def diagnose_command(
    recording: Annotated[Path, typer.Argument(help="Recording (.csv or .mcap); the arm still for its "
                                              "first second, then moving through many orientations.")],
    config: ConfigOpt = "wmra",
    add: Annotated[list[str] | None, typer.Option(
        "--add", help="Add this effect and refit (EFFECT or EFFECT:TARGET, e.g. accel_bias:acc2); repeatable.")] = None,
    write: WriteConfigOpt = None,
    window: Annotated[int, typer.Option(help="Average this many samples per fit point (small enough that "
                                        "the motion within a window stays below the noise).",
                                        callback=count_at_least("--window", 1, "samples per fit point"))] = 10,
    history: Annotated[Path | None, typer.Option(help="The error ladder's history file (default: "
                                                 "CONFIG.workbench.json beside the config).")] = None,
    report: Annotated[Path | None, typer.Option(help="Write an HTML report (one file, plots embedded).")] = None,
    top: Annotated[int, typer.Option(help="Candidates to show.",
                                     callback=count_at_least("--top", 0, "a number of candidates"))] = 8,
    innovations: Annotated[bool, typer.Option(
        "--innovations", help="Also run the tracker over the recording and analyse its normalised "
        "innovations (whiteness, correlation with the inputs); automatic when the chair moves.")] = False,
    discover_: Annotated[bool, typer.Option(
        "--discover", help="Find the missing effects by itself: add the most significant, refit, until "
        "nothing is significant; every rung shown (with --write: the last rung's config).")] = False,
    rungs: Annotated[int, typer.Option(help="With --discover: effects added at most.", min=1, max=50)] = 10,
    validate: Annotated[Path | None, typer.Option(
        "--validate", help="Judge every fit on this second recording of the same arm (default: the "
        "recording's last 30 %, which the fit then does not see).")] = None,
    json_out: JsonOpt = False,
) -> None:
    """Compare the model with a recording: where it fails, which physical effect is missing."""
    _check_outputs(recording, config, add, write, report, history, discover_)
    arm, rec, screen = arm_and_recording_or_exit(
        config, recording, fit_streams,
        "diagnose fits (the encoders and every sensor stream of {source})", json_out, encoder_steps=True)
    try:
        added = parse_add(arm, add or [])
    except (KeyError, TargetError) as e:
        fail(f"--add: {e.args[0] if e.args else e}")
    if chair_moves(arm, rec):
        if added or write is not None:
            fail("the chair moves in this recording: the fit (and so --add and --write) takes it as parked; "
                 "record with the chair parked to find and add effects")
        _innovations_only(arm, rec, recording, config, report, json_out, screen, discover_)
        return
    data, held, judged_rec = _data_and_held_out(arm, rec, recording, validate, window, write, json_out)
    if data.saturated_windows and not json_out:
        err_console.print(f"[yellow]{data.saturated_windows:,} fit windows left out: they hold saturated "
                          "samples[/]", highlight=False)
    fits = _fits(arm, data, held, added, discover_, rungs, write is not None, json_out)
    out = _Outputs(inn=_run_innovations(arm, rec, json_out) if innovations else None,
                   resampled=resampled_streams(rec, [s for s in fit_streams(arm) if s != "enc"]),
                   hpath=history or history_path(config), write=write, report=report)
    out.ladder = extend_ladder(out.hpath, fits, recording, config, write, history)
    if write is not None:
        out.written_held = _written_held_out(fits.final)
        out.write_refused = fits.refused_add or write_refusal(fits.final, fits.as_is, out.written_held)
        if out.write_refused is None:
            check = HeldOutCheck(judged_rec, held, out.written_held)
            out.consistency, out.write_refused = write_config(arm, fits, recording, config, write, check,
                                                               json_out)
    if report is not None:
        write_report(report, fits.before, fits.after, out.ladder, recording, config, fits.disc)
    if json_out:
        emit_json(_json_doc(fits, out, top, screen, data))
        if out.write_refused is not None:
            raise typer.Exit(1)
        return
    _say(fits, out, top)


def _written_held_out(final: Diagnosis):
    """Where elements of the fit ended at their bound, what is written (those at their prior)
    judged on the held-out data; None where nothing ended at a bound or nothing is held out."""
    if not final.at_bound or final.held_out is None:
        return None
    return judge(without_bound(final), final.data, final.held_out,
                 list(dict.fromkeys(a.stream for a in final.axes)), DiagnoseSettings().identify)


@dataclass
class _Outputs:
    """What ``diagnose`` reports beside the fits, and what it wrote or refused to."""

    inn: object | None
    resampled: list
    hpath: Path
    write: Path | None
    report: Path | None
    ladder: list = field(default_factory=list)
    write_refused: str | None = None
    consistency: dict | None = None
    written_held: object | None = None  # what is written, judged on the held-out data (elements at a bound)


def _check_outputs(recording: Path, config: str, add, write: Path | None, report: Path | None,
                   history: Path | None, discover_: bool) -> None:
    """Exit 2 before any work when the options clash or an output cannot be written."""
    if discover_ and add:
        fail("--discover chooses the effects itself: give --discover or --add, not both")
    inputs = (recording, config_file(config))  # (--history is read and extended: not among them)
    for path, option in ((write, "--write"), (report, "--report"), (history, "--history")):
        if path is not None:
            check_output_path(path, option, inputs=inputs)
    if write is not None and history is None:
        check_output_path(write.with_name(write.stem + ".workbench.json"), "--write (its history)",
                          inputs=inputs)
    hpath = history or history_path(config)
    why = history_problem(hpath)  # (read, then replaced: checked before the work)
    if why is not None:
        fail(f"{'--history ' if history is not None else 'the history '}{hpath}: {why}")


def _data_and_held_out(arm, rec, recording: Path, validate: Path | None, window: int, write: Path | None,
                       json_out: bool):
    """The fit's data, the held-out data (``--validate``'s recording, else the recording's last
    part; ``None`` when it is too short to hold a part out) and the recording it comes from."""
    try:
        data = data_from_recording(arm, rec, window=window)
    except ValueError as e:
        fail(str(e))
    if validate is not None:
        vrec = read_recording_or_exit(validate, arm)
        screen_or_exit(arm, vrec, validate, (), "", json_out, encoder_steps=True)  # (the same door)
        if chair_moves(arm, vrec):
            fail(f"--validate: the chair moves in {validate}: a fit is judged on a parked recording")
        try:
            held = HeldOut(data_from_recording(arm, vrec, window=window), False, f"the recording {validate}")
        except ValueError as e:
            fail(f"--validate {validate}: {e}")
        return data, held, vrec
    try:
        data, held = split_in_time(data)
    except ValueError as e:
        # too short to hold a part out: diagnosed on itself, nothing written from it
        held, no_held_out = None, f"{recording}: {e}"
        if write is not None:
            fail(f"{no_held_out}; --write needs a part the fit does not see (or --validate REC)")
        if not json_out:
            err_console.print(f"[yellow]warning:[/] {no_held_out}: judged on nothing but itself",
                              highlight=False)
    return data, held, rec


def _fits(arm, data, held, added: list, discover_: bool, rungs: int, writing: bool, json_out: bool) -> Fits:
    """The config's fit, then the discovered or the added effects', with a progress bar."""
    runs = 2 if added else 1
    disc: Discovery | None = None
    with progress_bar("diagnose", json_out) as advance:

        def stage(k: int):
            def progress(msg: str, frac: float) -> None:
                advance((k + frac) / runs, msg)
            return progress

        if discover_:
            disc = discover(model_from_arm(arm), data, DiscoverSettings(max_rungs=rungs), progress=stage(0),
                            held_out=held)
            before = disc.first
            after = disc.final if len(disc.rungs) > 1 else None
        else:
            before = diagnose(model_from_arm(arm), data, progress=stage(0), held_out=held)
            after = add_effects(before, added, progress=stage(1)) if added else None
        refused_add = held_out_worse(before, after) if after is not None and disc is None else None
        as_is = (as_it_is(model_from_arm(arm), data, held, list(dict.fromkeys(a.stream for a in before.axes)),
                          DiagnoseSettings().identify, before.fit.attitude_rad)
                 if writing and held is not None else None)
    return Fits(before, after, disc, added, refused_add, as_is)


def _json_doc(fits: Fits, out: _Outputs, top: int, screen, data) -> dict:
    """``diagnose --json``'s document."""
    before, after, disc, as_is = fits.before, fits.after, fits.disc, fits.as_is
    d = fits.final.as_dict(top)
    d["added"] = ([f.added_block for f in disc.findings]
                  if disc is not None else [e.block_name for e in fits.added])
    d["discovery"] = None if disc is None else disc.as_dict()
    d["before"] = None if after is None else before.as_dict(top)
    d["history"] = str(out.hpath)
    d["ladder"] = [{"label": r["label"], "rms_ratio": r["rms_ratio"],
                    "held_out_rms_ratio": r.get("held_out_rms_ratio"), "effects": r["effects"]}
                   for r in out.ladder]
    d["written"] = str(out.write) if out.write and out.write_refused is None else None
    d["write_refused"] = out.write_refused
    d["add_refused"] = fits.refused_add
    d["as_it_was_held_out_rms_ratio"] = None if as_is is None else round(as_is.rms_ratio, 4)
    d["written_held_out_rms_ratio"] = (None if out.written_held is None
                                       else round(out.written_held.rms_ratio, 4))
    d["tracked_held_out"] = out.consistency
    d["report"] = str(out.report) if out.report else None
    d["innovations"] = None if out.inn is None else out.inn.as_dict()
    d["resampled_streams"] = [r.as_dict() for r in out.resampled]
    d["saturated_left_out"] = {"samples": screen.as_dict()["saturated"],
                               "windows": data.saturated_windows}
    return d


def _say(fits: Fits, out: _Outputs, top: int) -> None:
    """``diagnose``'s report on the console; exit 1 when the config was not written."""
    if fits.disc is not None:
        _print_discovery(fits.disc)
    _print(fits.before, fits.after, top)
    if fits.refused_add is not None:
        console.print(f"[bold yellow]The added effects are refused:[/] {fits.refused_add}.", highlight=False)
    if out.inn is not None:
        _print_innovations(out.inn)
    for r in out.resampled:
        console.print(f"[yellow]Resampled stream:[/] {r.words()}.", highlight=False)
    console.print(f"History (error ladder, {len(out.ladder)} model versions): {out.hpath}")
    if out.write and out.write_refused is None:
        console.print(f"Wrote {out.write}")
    if out.report:
        console.print(f"Report: {out.report}")
    if out.write_refused is not None:
        err_console.print(f"[bold red]Not written[/] ({out.write}): {out.write_refused}", highlight=False)
        raise typer.Exit(1)


def _print_discovery(disc: Discovery) -> None:
    n = len(disc.findings)
    t = Table(title=f"Discovery: the error ladder ({n} effect{'' if n == 1 else 's'} found in "
                    f"{len(disc.rungs) - 1} rung{'' if len(disc.rungs) == 2 else 's'}; stopped: {disc.stop})")
    for c in ("#", "added", "its estimate ± σ", "RMS / noise (fitted)", "held out"):
        t.add_column(c, justify="left" if c in ("added", "its estimate ± σ") else "right")
    for k, r in enumerate(disc.rungs):
        h = r.held_out_ratio
        t.add_row(str(k), r.label, r.estimate_words() or "—", f"{r.rms_ratio:.3f}",
                  "—" if h is None else f"{h:.3f}")
    if disc.rungs[0].diagnosis.held_out is not None:
        t.caption = f"held out: {disc.rungs[0].diagnosis.held_out.label}, not fitted"
    console.print(t)
    for label, why in disc.refused:
        console.print(f"[yellow]refused:[/] {label}: {why}", highlight=False)
    for f in disc.findings:
        if f.is_group:
            console.print(f"[bold]One finding, one of these:[/] {f.words()}.", highlight=False)
    if disc.remaining:
        console.print("[yellow]The ladder stopped above the noise; no effect of the library explains the rest. "
                      "The remaining residual:[/] " + "; ".join(disc.remaining) + ".", highlight=False)


def _verdict_line(d: Diagnosis) -> str:
    colour = "green" if d.fits_to_noise else "yellow"
    held = ("" if d.held_out_ratio is None
            else f", {d.held_out_ratio:.2f}× on the held-out data ({d.held_out.label})")
    return (f"[bold {colour}]{d.verdict}[/]: residual RMS {d.rms_ratio:.2f}× the noise floor{held} "
            f"({d.fit.n_samples:,} fit points; model: "
            f"{', '.join(e for e in d.effects() if not e.endswith('.joint_offset')) or 'the config alone'})")


def _axes_table(d: Diagnosis, title: str, other: Diagnosis | None = None) -> Table:
    t = Table(title=title)
    for c in ("axis", "RMS", "noise", "RMS / noise", "fit %", "lag-1 autocorr."):
        t.add_column(c, justify="right" if c != "axis" else "left")
    if other is not None:
        t.add_column("before: RMS / noise", justify="right")
    prev = {(a.stream, a.axis): a for a in other.axes} if other is not None else {}
    band = 1.0 / np.sqrt(max(d.fit.n_samples, 1))  # white noise: lag-1 σ 1/√n; red beyond 3σ
    for a in d.axes:
        r = f"{a.ratio:.2f}"
        row = [a.axis, f"{a.rms:.3g} {a.unit}", f"{a.noise:.3g}",
               f"[red]{r}[/]" if a.ratio > 1.1 else r,
               "—" if a.fit_percent is None else f"{a.fit_percent:.2f}",
               f"[red]{a.autocorr1:.2f}[/]" if abs(a.autocorr1) > 3 * band else f"{a.autocorr1:.2f}"]
        if other is not None:
            row.append(f"{prev[(a.stream, a.axis)].ratio:.2f}" if (a.stream, a.axis) in prev else "")
        t.add_row(*row)
    return t


def _candidates_table(d: Diagnosis, top: int) -> Table:
    t = Table(title="Missing effects, ranked (significant: a score test beyond chance and ΔBIC < 0)")
    for c in ("#", "effect", "target", "ΔBIC", "RMS after", "explains", "signif.", "estimate (refitted)"):
        t.add_column(c, justify="right" if c in ("#", "ΔBIC", "RMS after", "explains") else "left")
    for i, c in enumerate(d.candidates[:top], 1):
        est = params_words(dict(list(c.params.items())), c.units) if c.refitted else ""
        t.add_row(str(i), c.effect, c.target, f"{c.delta_bic:.1f}",
                  "" if c.rms_after is None else f"{c.rms_after:.2f}", f"{100 * c.explained:.0f} %",
                  "[bold]yes[/]" if c.significant else "no", est)
    return t


def _run_innovations(arm, rec, json_out: bool):
    with progress_bar("tracker", json_out) as advance:
        try:
            return innovation_diagnosis(arm, rec, progress=lambda m, f: advance(f, m))
        except (ValueError, RuntimeError) as e:
            fail(f"--innovations: {e}")


def _print_innovations(inn) -> None:
    colour = "green" if inn.white else "yellow"
    console.print(f"Tracker innovations ({inn.steps:,} fused instants): [bold {colour}]{inn.verdict}[/]")
    t = Table(title="Normalised innovation squared per sensor (its mean is the dof when the noise is right)")
    for c in ("sensor", "mean NIS", "dof", "samples"):
        t.add_column(c, justify="left" if c == "sensor" else "right")
    for s, (m, n, k) in inn.nis.items():
        t.add_row(s, f"{m:.3g}", str(k), f"{n:,}")
    console.print(t)
    for a in inn.analyses:
        ct = _correlation_table(a)
        if ct is not None:
            console.print(ct)
    if inn.compass is not None:
        console.print("The compass's heading innovations (not in the verdict: its iron and the arm's steel are "
                      "biases that last a heading visit, coloured by design; its mean NIS above says whether "
                      f"their size is right): {'white' if inn.compass.white else 'coloured'}")


def _innovations_only(arm, rec, recording: Path, config: str, report: Path | None, json_out: bool,
                      screen, discovering: bool = False) -> None:
    """A moving chair: the fit (parked) does not apply; the tracker's innovations do."""
    inn = _run_innovations(arm, rec, json_out)
    note = ("the chair moves in this recording: the model fit takes the chair as parked, so the analysis "
            "runs on the tracker's normalised innovations")
    if discovering:
        note += ("; discovery on the innovations says what they follow but names no effect (no score test "
                 "on innovations yet): record with the chair parked for the ladder")
    if report is not None:
        write_innovation_report(report, inn, recording, config, note)
    if json_out:
        emit_json({"mode": "innovations", "verdict": inn.verdict, "note": note,
                   "innovations": inn.as_dict(), "report": str(report) if report else None,
                   "saturated_left_out": {"samples": screen.as_dict()["saturated"]}})
        return
    console.print(f"[dim]{note}[/]")
    _print_innovations(inn)
    if report:
        console.print(f"Report: {report}")


def _correlation_table(a, rows: int = 8, per_axis: int = 3) -> Table | None:
    """The axes whose residual is not white or follows an input beyond the band (None if none)."""
    flagged = a.flagged()
    nw = {(s, ax): m for s, ax, m in a.not_white()}
    keys = list(dict.fromkeys([(c.stream, c.axis) for c in flagged] + list(nw)))
    if not keys:
        return None
    t = Table(title=f"Where it fails ({a.source}): correlations beyond the 99 % band, corrected for "
                    f"{a.n_tests:,} tests (|r| > {a.band_flag:.3f}; "
                    f"lags in units of {a.dt_s:.2g} s)")
    t.add_column("axis")
    t.add_column("max |autocorr.|", justify="right")
    t.add_column("follows (r at lag)")
    for s, ax in keys[:rows]:
        cs = [c for c in flagged if (c.stream, c.axis) == (s, ax)][:per_axis]
        k = a.axes.index((s, ax))
        m = float(np.max(np.abs(a.autocorr[k, 1:]))) if a.max_lag else 0.0
        t.add_row(ax, f"[red]{m:.2f}[/]" if (s, ax) in nw else f"{m:.2f}",
                  ", ".join(f"{c.input} ({c.r:+.2f} at {c.lag:+d})" for c in cs) or "—")
    if len(keys) > rows:
        t.caption = f"… and {len(keys) - rows} more axes (--json has them all)"
    return t


def _print(before: Diagnosis, after: Diagnosis | None, top: int) -> None:
    d = after or before
    if after is not None:
        console.print(f"Before: {_verdict_line(before)}")
        console.print(f"After:  {_verdict_line(after)}")
        console.print(_axes_table(after, "Residual RMS per sensor axis, after adding", before))
    else:
        console.print(_verdict_line(d))
        console.print(_axes_table(d, "Residual RMS per sensor axis (window means)"))
    if d.worst and not d.fits_to_noise:
        console.print("Worst stretches: " + "; ".join(f"{a:.1f}-{b:.1f} s ({r:.1f}× the noise)"
                                                      for a, b, r in d.worst))
    if d.analysis is not None:
        t = _correlation_table(d.analysis)
        if t is not None:
            console.print(t)
    if d.candidates and d.candidates[0].significant:
        console.print(_candidates_table(d, top))
        c = d.candidates[0]
        console.print(f"[bold]Most likely missing: {c.effect} on {c.target}.[/] {c.explanation}")
        console.print(f"Evidence: {c.evidence}.")
        console.print(f"Try: armfusion diagnose … --add {c.effect}:{c.target}")
    else:
        console.print("No effect of the library is significant: nothing to add.")
    for h in d.fit.holds:
        console.print(f"[dim]held: {h.message}[/]")
    for g in d.gauges:
        console.print(f"[dim]gauge held: {g.message}[/]", highlight=False)
    for n in d.at_bound:
        console.print(f"[yellow]{n} ended at its parameter's bound: the model does not explain what pulled it "
                      "there; it is not written[/]", highlight=False)
