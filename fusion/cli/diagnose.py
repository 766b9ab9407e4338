"""``armfusion diagnose``: where the model fails, which effect is missing; add it, refit.

    armfusion diagnose --config C REC [--json] [--add EFFECT[:TARGET] …] [--write C2.yaml]
        [--window 10] [--history H.json] [--report out.html]

Fits the config's model to the recording (``fusion.workbench.diagnose``), shows every sensor axis's
residual RMS against its noise floor, the verdict and the ranked missing effects. ``--add``
refits with the named effects starting from the estimates and shows before and after;
``--write`` saves the config with the (last) estimates. Every run appends each model
version's residual RMS to a history (the error ladder). See docs/workbench.md.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
import yaml
from rich.table import Table

from fusion.cli.common import (
    ConfigOpt,
    JsonOpt,
    check_output_path,
    console,
    emit_json,
    err_console,
    fail,
    load_arm_or_exit,
    progress_bar,
    read_recording_or_exit,
    screen_or_exit,
)
from fusion.configfile import resolve_config_path
from fusion.identification.identify import config_with_estimates, data_from_recording, fit_streams
from fusion.workbench.diagnose import (
    Diagnosis,
    add_effects,
    chair_moves,
    diagnose,
    innovation_diagnosis,
    params_words,
    parse_add,
)
from models.effects import TargetError, model_from_arm

HISTORY_FORMAT = "armfusion.workbench-history/1"


def register(app: typer.Typer) -> None:
    """Add ``diagnose`` to the ``armfusion`` app (once)."""
    if any(c.name == "diagnose" for c in app.registered_commands):
        return
    app.command("diagnose")(diagnose_command)


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
        "streams": {s: round(float(np.sqrt(np.mean([a.ratio**2 for a in diag.axes if a.stream == s]))), 5)
                    for s in dict.fromkeys(a.stream for a in diag.axes)},
        "verdict": diag.verdict,
        "top_candidate": None if top is None else top.name,
    }


def append_history(path: Path, entries: list[dict]) -> list[dict]:
    """Append ``entries`` to the history file at ``path``; returns the whole ladder."""
    runs: list[dict] = []
    if path.exists():
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            runs = list(doc.get("runs", []))
        except (ValueError, AttributeError):
            err_console.print(f"[yellow]warning:[/] {path} is not a workbench history; starting a new one")
    runs += entries
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"format": HISTORY_FORMAT, "runs": runs}, indent=2) + "\n", encoding="utf-8")
    return runs


def diagnose_command(
    recording: Annotated[Path, typer.Argument(help="Recording (.csv or .mcap); the arm still for its "
                                              "first second, then moving through many orientations.")],
    config: ConfigOpt = "wmra",
    add: Annotated[list[str] | None, typer.Option(
        "--add", help="Add this effect and refit (EFFECT or EFFECT:TARGET, e.g. accel_bias:acc2); repeatable.")] = None,
    write: Annotated[Path | None, typer.Option(help="Write the config with the (last) estimates here.")] = None,
    window: Annotated[int, typer.Option(help="Average this many samples per fit point (small enough that "
                                        "the motion within a window stays below the noise).")] = 10,
    history: Annotated[Path | None, typer.Option(help="The error ladder's history file (default: "
                                                 "CONFIG.workbench.json beside the config).")] = None,
    report: Annotated[Path | None, typer.Option(help="Write an HTML report (one file, plots embedded).")] = None,
    top: Annotated[int, typer.Option(help="Candidates to show.")] = 8,
    innovations: Annotated[bool, typer.Option(
        "--innovations", help="Also run the tracker over the recording and analyse its normalised "
        "innovations (whiteness, correlation with the inputs); automatic when the chair moves.")] = False,
    json_out: JsonOpt = False,
) -> None:
    """Compare the model with a recording: where it fails, which physical effect is missing."""
    for path, option in ((write, "--write"), (report, "--report"), (history, "--history")):
        if path is not None:
            check_output_path(path, option)
    if write is not None and history is None:
        check_output_path(write.with_name(write.stem + ".workbench.json"), "--write (its history)")
    arm = load_arm_or_exit(config)
    rec = read_recording_or_exit(recording, arm)
    screen = screen_or_exit(arm, rec, recording, fit_streams(arm), "diagnose fits (the encoders and "
                            f"every sensor stream of {arm.source})", json_out)
    try:
        added = parse_add(arm, add or [])
    except (KeyError, TargetError) as e:
        fail(f"--add: {e.args[0] if e.args else e}")
    if chair_moves(arm, rec):
        if added or write is not None:
            fail("the chair moves in this recording: the fit (and so --add and --write) takes it as parked; "
                 "record with the chair parked to find and add effects")
        _innovations_only(arm, rec, recording, config, report, json_out, screen)
        return
    try:
        data = data_from_recording(arm, rec, window=window)
    except ValueError as e:
        fail(str(e))
    if data.saturated_windows and not json_out:
        err_console.print(f"[yellow]{data.saturated_windows:,} fit windows left out: they hold saturated "
                          "samples[/]", highlight=False)

    runs = 2 if added else 1
    with progress_bar("diagnose", json_out) as advance:

        def stage(k: int):
            def progress(msg: str, frac: float) -> None:
                advance((k + frac) / runs, msg)
            return progress

        before = diagnose(model_from_arm(arm), data, progress=stage(0))
        after = add_effects(before, added, progress=stage(1)) if added else None
    inn = _run_innovations(arm, rec, json_out) if innovations else None
    final = after or before
    hpath = history or history_path(config)
    entries = [history_entry(before, recording, config, Path(config).stem)]
    if after is not None:
        entries.append(history_entry(after, recording, config, "+ " + ", ".join(e.block_name for e in added)))
    ladder = append_history(hpath, entries)
    if write is not None and history is None:  # the written config carries the ladder on
        nxt = write.with_name(write.stem + ".workbench.json")  # beside it (it is not written yet)
        if nxt.resolve() != hpath.resolve():
            nxt.parent.mkdir(parents=True, exist_ok=True)
            nxt.write_text(json.dumps({"format": HISTORY_FORMAT, "runs": ladder}, indent=2) + "\n",
                           encoding="utf-8")
    if write is not None:
        src = resolve_config_path(config)
        cfg = yaml.safe_load(src.read_text(encoding="utf-8"))
        out = config_with_estimates(cfg, final.fit)
        write.parent.mkdir(parents=True, exist_ok=True)
        write.write_text(f"# armfusion diagnose: rms_ratio {final.rms_ratio:.3f} ({final.verdict})\n"
                         f"# from {recording}, config {src.name}\n"
                         + yaml.safe_dump(out, sort_keys=False, width=110), encoding="utf-8")
    if report is not None:
        write_report(report, before, after, ladder, recording, config)
    if json_out:
        d = final.as_dict(top)
        d["added"] = [e.block_name for e in added]
        d["before"] = None if after is None else before.as_dict(top)
        d["history"] = str(hpath)
        d["ladder"] = [{"label": r["label"], "rms_ratio": r["rms_ratio"], "effects": r["effects"]}
                       for r in ladder]
        d["written"] = str(write) if write else None
        d["report"] = str(report) if report else None
        d["innovations"] = None if inn is None else inn.as_dict()
        d["saturated_left_out"] = {"samples": screen.as_dict()["saturated"],
                                   "windows": data.saturated_windows}
        emit_json(d)
        return
    _print(before, after, top)
    if inn is not None:
        _print_innovations(inn)
    console.print(f"History (error ladder, {len(ladder)} model versions): {hpath}")
    if write:
        console.print(f"Wrote {write}")
    if report:
        console.print(f"Report: {report}")


def _verdict_line(d: Diagnosis) -> str:
    colour = "green" if d.fits_to_noise else "yellow"
    return (f"[bold {colour}]{d.verdict}[/]: residual RMS {d.rms_ratio:.2f}× the noise floor "
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


def _innovations_only(arm, rec, recording: Path, config: str, report: Path | None, json_out: bool,
                      screen) -> None:
    """A moving chair: the fit (parked) does not apply; the tracker's innovations do."""
    inn = _run_innovations(arm, rec, json_out)
    note = ("the chair moves in this recording: the model fit takes the chair as parked, so the analysis "
            "runs on the tracker's normalised innovations")
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
                    f"{int(a._tested().sum()) * (2 * a.max_lag + 1):,} tests (|r| > {a.band_flag:.3f}; "
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


# --------------------------------------------------------------------------------------
# the HTML report: one self-contained file, the plots embedded as PNG
def report_figures(before: Diagnosis, after: Diagnosis | None, ladder: list[dict]) -> dict[str, bytes]:
    """The report's figures as PNG bytes: ``ladder``, ``candidates``, ``compare`` (predicted
    against measured, the worst axes) and ``residuals`` (the worst axis against the input the
    top candidate's evidence names)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fusion.workbench.diagnose import predicted_and_measured

    figs: dict[str, bytes] = {}

    def png(fig) -> bytes:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
        plt.close(fig)
        return buf.getvalue()

    # the error ladder: residual RMS per model version
    fig, ax = plt.subplots(figsize=(7, 3.2))
    steps = [r for k, r in enumerate(ladder)  # a re-run of the same model is the same rung
             if k == 0 or (r["effects"], r["rms_ratio"]) != (ladder[k - 1]["effects"], ladder[k - 1]["rms_ratio"])]
    vals = [r["rms_ratio"] for r in steps]
    labels = [f"{k + 1}: {r['label']}" for k, r in enumerate(steps)]
    ax.plot(range(len(vals)), vals, "o-", color="C0")
    ax.axhline(1.0, color="k", ls="--", lw=1, label="noise floor")
    ax.axhspan(0, 1.1, color="green", alpha=0.08)
    ax.set_yscale("log")
    ax.set_xticks(range(len(vals)), labels, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("residual RMS / noise")
    ax.set_title("The error ladder")
    ax.legend(fontsize=8)
    figs["ladder"] = png(fig)
    # the ranked candidates (of the diagnosis before adding: what suggested the step)
    src = before
    top = [c for c in src.candidates[:10]]
    if top:
        fig, ax = plt.subplots(figsize=(7, 0.35 * len(top) + 1))
        y = np.arange(len(top))[::-1]
        v = [-c.delta_bic for c in top]
        ax.barh(y, np.maximum(v, 1e-1), color=["C3" if c.significant else "0.6" for c in top])
        ax.set_yticks(y, [c.name for c in top], fontsize=8)
        ax.set_xscale("log")
        ax.set_xlabel("-ΔBIC (red: significant)")
        ax.set_title("Which effect is missing")
        figs["candidates"] = png(fig)
    # predicted against measured on the worst axes, residual underneath
    pm = predicted_and_measured(src)
    worst = sorted(src.axes, key=lambda a: -a.ratio)[:4]
    fig, axs = plt.subplots(len(worst), 2, figsize=(10, 2.2 * len(worst)), squeeze=False,
                            layout="constrained")
    for row, a in zip(axs, worst, strict=True):
        t, ym, yp, unit, ch = pm[a.stream]
        k = ch.index(a.axis)
        row[0].plot(t, ym[:, k], ".", ms=2, color="0.4", label="measured")
        row[0].plot(t, yp[:, k], "-", lw=1, color="C0", label="model")
        fit = "" if a.fit_percent is None else f", fit {a.fit_percent:.1f} %"
        row[0].set_title(f"{a.axis}{fit}", fontsize=9)
        row[0].set_ylabel(unit)
        row[1].plot(t, ym[:, k] - yp[:, k], ".", ms=2, color="C3")
        row[1].axhspan(-a.noise, a.noise, color="green", alpha=0.15)
        row[1].set_title(f"{a.axis} residual: RMS {a.ratio:.2f}× the noise (band: ±1σ)", fontsize=9)
    axs[0][0].legend(fontsize=8)
    axs[-1][0].set_xlabel("t [s]")
    axs[-1][1].set_xlabel("t [s]")
    figs["compare"] = png(fig)
    if after is not None:
        pm2 = predicted_and_measured(after)
        fig, axs = plt.subplots(len(worst), 1, figsize=(10, 1.8 * len(worst)), squeeze=False,
                            layout="constrained")
        for (axx,), a in zip(axs, worst, strict=True):
            t, ym, yp, unit, ch = pm[a.stream]
            t2, ym2, yp2, _, _ = pm2[a.stream]
            k = ch.index(a.axis)
            axx.plot(t, ym[:, k] - yp[:, k], ".", ms=2, color="C3", label="before")
            axx.plot(t2, ym2[:, k] - yp2[:, k], ".", ms=2, color="C2", label="after")
            axx.axhspan(-a.noise, a.noise, color="green", alpha=0.15)
            axx.set_title(f"{a.axis} residual before and after ({unit})", fontsize=9)
        axs[0][0].legend(fontsize=8)
        figs["after"] = png(fig)
    if src.analysis is not None:
        figs.update(analysis_figures(src, png))
    return figs


def analysis_figures(d: Diagnosis, png) -> dict[str, bytes]:
    """``inputs``: the worst axis's residual against every input (binned means over the
    points); ``correlation``: the worst axes' autocorrelation and the worst axis's
    cross-correlation with the inputs it follows most, with the 99 % band (MATLAB's ``resid``)."""
    import matplotlib.pyplot as plt

    a = d.analysis
    figs: dict[str, bytes] = {}
    worst = sorted(range(len(d.axes)), key=lambda k: -d.axes[k].ratio)[:3]
    w = worst[0]
    ax0 = d.axes[w]
    from fusion.workbench.diagnose import fit_inputs

    inputs = fit_inputs(d.data.state, d.fit.model.arm.joint_names)
    shown = [k for k in inputs if k not in a.constant_inputs]
    res = _residual_of_axis(d, w)
    ncol = 7
    nrow = -(-len(shown) // ncol)
    fig, axs = plt.subplots(nrow, ncol, figsize=(14, 1.9 * nrow), squeeze=False, sharey=True,
                            layout="constrained")
    step = max(1, len(res) // 3000)
    for k, lab in enumerate(shown):
        axx = axs[k // ncol][k % ncol]
        u = inputs[lab]
        axx.plot(u[::step], res[::step], ".", ms=1, color="0.6")
        bins = np.linspace(u.min(), u.max(), 21)
        idx = np.clip(np.digitize(u, bins) - 1, 0, 19)
        cnt = np.bincount(idx, minlength=20)
        mean = np.bincount(idx, res, minlength=20) / np.maximum(cnt, 1)
        ok = cnt > 5
        axx.plot(0.5 * (bins[1:] + bins[:-1])[ok], mean[ok], "-", color="C3", lw=1.5)
        axx.axhspan(-1, 1, color="green", alpha=0.12)
        axx.set_title(lab, fontsize=8)
        axx.tick_params(labelsize=6)
    for k in range(len(shown), nrow * ncol):
        axs[k // ncol][k % ncol].axis("off")
    fig.suptitle(f"{ax0.axis} residual (in noise σ) against each input; red: binned mean, "
                 "band ±1σ", fontsize=10)
    figs["inputs"] = png(fig)
    figs["correlation"] = correlation_figure(a, [(d.axes[k].stream, d.axes[k].axis) for k in worst], png)
    return figs


def correlation_figure(a, worst: list[tuple[str, str]], png) -> bytes:
    """The ``worst`` axes' autocorrelation and the first one's cross-correlation with the four
    inputs it follows most, with the 99 % band ±2.58/√N (as MATLAB's ``resid``)."""
    import matplotlib.pyplot as plt

    fig, (p1, p2) = plt.subplots(1, 2, figsize=(11, 3.2), layout="constrained")
    lags = np.arange(a.max_lag + 1)
    idx = [a.axes.index(w) for w in worst]
    for k in idx:
        p1.plot(lags[1:], a.autocorr[k, 1:], "o-", ms=3, label=a.axes[k][1])
    p1.axhspan(-a.band, a.band, color="0.85", label="99 % band")
    p1.set_title(f"Autocorrelation ({a.source}): whiteness", fontsize=9)
    p1.set_xlabel(f"lag [{a.dt_s:.2g} s]")
    p1.legend(fontsize=7)
    w = idx[0]
    if a.inputs:
        xl = np.arange(-a.max_lag, a.max_lag + 1)
        score = np.where(a._tested()[w], np.max(np.abs(a.xcorr[w]), 1), -1.0)
        for i in np.argsort(-score)[:4]:
            p2.plot(xl, a.xcorr[w, i], "-", label=a.inputs[i])
        p2.axhspan(-a.band, a.band, color="0.85", label="99 % band")
        p2.legend(fontsize=7)
    p2.set_title(f"Cross-correlation of {a.axes[w][1]} with the inputs", fontsize=9)
    p2.set_xlabel(f"lag [{a.dt_s:.2g} s] (positive: it follows later)")
    return png(fig)


def write_innovation_report(path: Path, inn, recording: Path, config: str, note: str) -> Path:
    """The report of a moving recording: the tracker's innovations, whiteness and correlations."""
    import base64
    import html
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def png(fig) -> bytes:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
        plt.close(fig)
        return buf.getvalue()

    imgs = []
    for a in inn.analyses:
        order = sorted(range(len(a.axes)), key=lambda k: -float(np.max(np.abs(a.autocorr[k, 1:]), initial=0.0)))
        b = correlation_figure(a, [a.axes[k] for k in order[:3]], png)
        imgs.append(f'<img alt="correlation" src="data:image/png;base64,{base64.b64encode(b).decode()}">')
    fl = inn.flagged()[:8]
    words = "; ".join(f"{html.escape(c.axis)} with {html.escape(c.input)} (r = {c.r:+.2f} at lag {c.lag:+d})"
                      for c in fl) or "none"
    nis = "".join(f"<tr><td>{html.escape(s)}</td><td>{m:.3g}</td><td>{k}</td><td>{n:,}</td></tr>"
                  for s, (m, n, k) in inn.nis.items())
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>armfusion diagnose (moving)</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}}
table{{border-collapse:collapse;font-size:90%}}td,th{{border:1px solid #ccc;padding:2px 6px}}img{{max-width:100%}}</style>
</head><body><h1>armfusion diagnose: the tracker's innovations</h1>
<p>Recording <code>{html.escape(str(recording))}</code>, config <code>{html.escape(str(config))}</code>;
{inn.steps:,} fused instants. {html.escape(note)}.</p>
<h2>Verdict: {html.escape(inn.verdict)}</h2>
<p>Correlations beyond the corrected 99 % band: {words}.</p>
{''.join(imgs)}
<h2>Normalised innovation squared</h2>
<table><tr><th>sensor</th><th>mean NIS</th><th>dof</th><th>samples</th></tr>{nis}</table>
</body></html>
"""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(doc, encoding="utf-8")
    return path


def _residual_of_axis(d: Diagnosis, k: int) -> np.ndarray:
    """Axis ``k``'s residual in units of its noise σ (measured minus model)."""
    from fusion.workbench.diagnose import predicted_and_measured

    a = d.axes[k]
    t, ym, yp, unit, ch = predicted_and_measured(d)[a.stream]
    c = ch.index(a.axis)
    return (ym[:, c] - yp[:, c]) / a.noise


def write_report(path: Path, before: Diagnosis, after: Diagnosis | None, ladder: list[dict],
                 recording: Path, config: str) -> Path:
    """One HTML file a person reads top to bottom: verdict, ladder, ranked candidates, plots."""
    import base64
    import html

    figs = report_figures(before, after, ladder)
    d = after or before

    def img(name: str) -> str:
        if name not in figs:
            return ""
        return (f'<img alt="{name}" src="data:image/png;base64,'
                f'{base64.b64encode(figs[name]).decode()}">')

    def esc(x) -> str:
        return html.escape(str(x))

    rows = "".join(
        f"<tr><td>{i}</td><td>{esc(c.effect)}</td><td>{esc(c.target)}</td><td>{c.delta_bic:.1f}</td>"
        f"<td>{'' if c.rms_after is None else f'{c.rms_after:.2f}'}</td><td>{100 * c.explained:.0f} %</td>"
        f"<td>{'yes' if c.significant else 'no'}</td>"
        f"<td>{esc(params_words(c.params, c.units)) if c.refitted else ''}</td></tr>"
        for i, c in enumerate(before.candidates[:10], 1))
    axes = "".join(
        f"<tr><td>{esc(a.axis)}</td><td>{a.rms:.3g} {esc(a.unit)}</td><td>{a.noise:.3g}</td>"
        f"<td{' class=bad' if a.ratio > 1.1 else ''}>{a.ratio:.2f}</td>"
        f"<td>{'—' if a.fit_percent is None else f'{a.fit_percent:.2f}'}</td></tr>" for a in d.axes)
    best = before.candidates[0] if before.candidates and before.candidates[0].significant else None
    why = (f"<h2>Most likely missing: {esc(best.effect)} on {esc(best.target)}</h2>"
           f"<p>{esc(best.explanation)}</p><p><b>Evidence:</b> {esc(best.evidence)}.</p>") if best else \
        "<p>No effect of the library is significant: nothing to add.</p>"
    step = ""
    if after is not None:
        step = (f"<h2>After adding {esc(', '.join(b for b in after.effects() if b not in before.effects()))}</h2>"
                f"<p>Residual RMS {before.rms_ratio:.2f}× → {after.rms_ratio:.2f}× the noise floor: "
                f"<b>{esc(after.verdict)}</b>.</p>{img('after')}")
    corr_words = ""
    if before.analysis is not None:
        an = before.analysis
        fl = an.flagged()[:5]
        corr_words = (f"Correlations beyond the 99 % band ±{an.band:.3f}, corrected for the number of "
                      f"tests (|r| > {an.band_flag:.3f}): "
                      + ("; ".join(f"{c.axis} with {c.input} (r = {c.r:+.2f} at lag {c.lag:+d})" for c in fl)
                         if fl else "none: the residuals are white and follow no input") + ".")
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>armfusion diagnose</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}}
table{{border-collapse:collapse;font-size:90%}}td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}
td:nth-child(2),td:nth-child(3){{text-align:left}}.bad{{color:#b00;font-weight:bold}}img{{max-width:100%}}</style>
</head><body>
<h1>armfusion diagnose</h1>
<p>Recording <code>{esc(recording)}</code>, config <code>{esc(config)}</code>; {d.fit.n_samples:,} fit points.</p>
<h2>Verdict: {esc(d.verdict)}</h2>
<p>Residual RMS {d.rms_ratio:.2f}× the sensors' noise floor (1.0: the model fits to noise).
Model effects: {esc(', '.join(e for e in d.effects() if not e.endswith('.joint_offset')) or 'none')}.</p>
{img('ladder')}
{why}
<h2>Missing effects, ranked</h2>
<table><tr><th>#</th><th>effect</th><th>target</th><th>ΔBIC</th><th>RMS after</th><th>explains</th>
<th>significant</th><th>estimate</th></tr>{rows}</table>
{img('candidates')}
{step}
<h2>Model against measurements (the worst axes)</h2>
{img('compare')}
<h2>Where it fails: residuals against the inputs</h2>
<p>{esc(corr_words)}</p>
{img('inputs')}
{img('correlation')}
<h2>Residual RMS per sensor axis</h2>
<table><tr><th>axis</th><th>RMS</th><th>noise</th><th>RMS / noise</th><th>fit %</th></tr>{axes}</table>
</body></html>
"""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(doc, encoding="utf-8")
    return path
