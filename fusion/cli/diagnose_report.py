"""The HTML report of ``armfusion diagnose``: one self-contained file a person reads top to
bottom (verdict, error ladder, ranked candidates, plots embedded as PNG), and its moving
twin, the tracker's innovations (:func:`write_innovation_report`).

Imports matplotlib (the Agg backend) only when a figure is drawn.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from armfusion.fusion.cli.common import png_img
from armfusion.fusion.workbench.diagnose import Diagnosis, params_words
from armfusion.sensors.output_files import write_text_replacing


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png_bytes(fig) -> bytes:
    """``fig`` as PNG bytes (90 dpi, tight), and closed."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    _pyplot().close(fig)
    return buf.getvalue()


def ladder_figure(ladder: list[dict]) -> bytes:
    """The error ladder: the residual RMS over the noise per model version (a re-run of the
    same model is the same rung), fitted and, where judged, on the held-out data."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2))
    steps = [r for k, r in enumerate(ladder)  # a re-run of the same model is the same rung
             if k == 0 or (r["effects"], r["rms_ratio"]) != (ladder[k - 1]["effects"], ladder[k - 1]["rms_ratio"])]
    vals = [r["rms_ratio"] for r in steps]
    labels = [f"{k + 1}: {r['label']}" for k, r in enumerate(steps)]
    ax.plot(range(len(vals)), vals, "o-", color="C0", label="fitted")
    held = [r.get("held_out_rms_ratio") for r in steps]
    if any(h is not None for h in held):
        ax.plot(range(len(vals)), [np.nan if h is None else h for h in held], "s--", color="C1",
                label="held out (not fitted)")
    ax.axhline(1.0, color="k", ls="--", lw=1, label="noise floor")
    ax.axhspan(0, 1.1, color="green", alpha=0.08)
    ax.set_yscale("log")
    ax.set_xticks(range(len(vals)), labels, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("residual RMS / noise")
    ax.set_title("The error ladder")
    ax.legend(fontsize=8)
    return png_bytes(fig)


def candidates_figure(top: list) -> bytes:
    """The ranked candidates ``top`` by their -ΔBIC, the significant ones in red."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(top) + 1))
    y = np.arange(len(top))[::-1]
    v = [-c.delta_bic for c in top]
    ax.barh(y, np.maximum(v, 1e-1), color=["C3" if c.significant else "0.6" for c in top])
    ax.set_yticks(y, [c.name for c in top], fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("-ΔBIC (red: significant)")
    ax.set_title("Which effect is missing")
    return png_bytes(fig)


def compare_figure(pm: dict, worst: list) -> bytes:
    """Predicted against measured on the ``worst`` axes (of ``pm``, the diagnosis's
    :func:`~armfusion.fusion.workbench.diagnose.predicted_and_measured`), the residual beside
    each with its ±1σ band."""
    plt = _pyplot()
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
    return png_bytes(fig)


def before_after_figure(pm: dict, pm_after: dict, worst: list) -> bytes:
    """The ``worst`` axes' residual before (``pm``) and after (``pm_after``) the effects were
    added, with the ±1σ band."""
    plt = _pyplot()
    fig, axs = plt.subplots(len(worst), 1, figsize=(10, 1.8 * len(worst)), squeeze=False,
                            layout="constrained")
    for (axx,), a in zip(axs, worst, strict=True):
        t, ym, yp, unit, ch = pm[a.stream]
        t2, ym2, yp2, _, _ = pm_after[a.stream]
        k = ch.index(a.axis)
        axx.plot(t, ym[:, k] - yp[:, k], ".", ms=2, color="C3", label="before")
        axx.plot(t2, ym2[:, k] - yp2[:, k], ".", ms=2, color="C2", label="after")
        axx.axhspan(-a.noise, a.noise, color="green", alpha=0.15)
        axx.set_title(f"{a.axis} residual before and after ({unit})", fontsize=9)
    axs[0][0].legend(fontsize=8)
    return png_bytes(fig)


def report_figures(before: Diagnosis, after: Diagnosis | None, ladder: list[dict]) -> dict[str, bytes]:
    """The report's figures as PNG bytes: ``ladder``, ``candidates``, ``compare`` (predicted
    against measured, the worst axes), ``after`` (their residual before and after, given
    ``after``) and, with the diagnosis's analysis, ``inputs`` and ``correlation``."""
    from armfusion.fusion.workbench.diagnose import predicted_and_measured

    figs: dict[str, bytes] = {"ladder": ladder_figure(ladder)}
    # the ranked candidates (of the diagnosis before adding: what suggested the step)
    top = before.candidates[:10]
    if top:
        figs["candidates"] = candidates_figure(top)
    pm = predicted_and_measured(before)
    worst = sorted(before.axes, key=lambda a: -a.ratio)[:4]
    figs["compare"] = compare_figure(pm, worst)
    if after is not None:
        figs["after"] = before_after_figure(pm, predicted_and_measured(after), worst)
    if before.analysis is not None:
        figs.update(analysis_figures(before))
    return figs


def analysis_figures(d: Diagnosis) -> dict[str, bytes]:
    """``inputs``: the worst axis's residual against every input (binned means over the
    points); ``correlation``: the worst axes' autocorrelation and the worst axis's
    cross-correlation with the inputs it follows most, with the 99 % band (MATLAB's ``resid``)."""
    plt = _pyplot()

    a = d.analysis
    figs: dict[str, bytes] = {}
    worst = sorted(range(len(d.axes)), key=lambda k: -d.axes[k].ratio)[:3]
    w = worst[0]
    ax0 = d.axes[w]
    from armfusion.fusion.workbench.diagnose import fit_inputs

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
    figs["inputs"] = png_bytes(fig)
    figs["correlation"] = correlation_figure(a, [(d.axes[k].stream, d.axes[k].axis) for k in worst])
    return figs


def correlation_figure(a, worst: list[tuple[str, str]]) -> bytes:
    """The ``worst`` axes' autocorrelation and the first one's cross-correlation with the four
    inputs it follows most, with the 99 % band ±2.58/√N (as MATLAB's ``resid``)."""
    plt = _pyplot()

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
        score = np.where(a.tested()[w], np.max(np.abs(a.xcorr[w]), 1), -1.0)
        for i in np.argsort(-score)[:4]:
            p2.plot(xl, a.xcorr[w, i], "-", label=a.inputs[i])
        p2.axhspan(-a.band, a.band, color="0.85", label="99 % band")
        p2.legend(fontsize=7)
    p2.set_title(f"Cross-correlation of {a.axes[w][1]} with the inputs", fontsize=9)
    p2.set_xlabel(f"lag [{a.dt_s:.2g} s] (positive: it follows later)")
    return png_bytes(fig)


def write_innovation_report(path: Path, inn, recording: Path, config: str, note: str) -> Path:
    """The report of a moving recording: the tracker's innovations, whiteness and correlations."""
    import base64
    import html

    imgs = []
    for a in inn.analyses:
        order = sorted(range(len(a.axes)), key=lambda k: -float(np.max(np.abs(a.autocorr[k, 1:]), initial=0.0)))
        b = correlation_figure(a, [a.axes[k] for k in order[:3]])
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
    write_text_replacing(path, doc)
    return path


def _residual_of_axis(d: Diagnosis, k: int) -> np.ndarray:
    """Axis ``k``'s residual in units of its noise σ (measured minus model)."""
    from armfusion.fusion.workbench.diagnose import predicted_and_measured

    a = d.axes[k]
    t, ym, yp, unit, ch = predicted_and_measured(d)[a.stream]
    c = ch.index(a.axis)
    return (ym[:, c] - yp[:, c]) / a.noise


def discovery_html(disc) -> str:
    """The discovery's ladder as an HTML table (what each rung added, its estimate ± σ, the RMS
    over the noise), its grouped findings, why it stopped and what the residual follows."""
    import html

    rows = "".join(
        f"<tr><td>{k}</td><td style='text-align:left'>{html.escape(r.label)}</td>"
        f"<td style='text-align:left'>{html.escape(r.estimate_words() or '—')}</td><td>{r.rms_ratio:.3f}</td>"
        f"<td>{'—' if r.held_out_ratio is None else f'{r.held_out_ratio:.3f}'}</td></tr>"
        for k, r in enumerate(disc.rungs))
    refused = "".join(f"<li>refused: {html.escape(a)}: {html.escape(b)}</li>" for a, b in disc.refused)
    groups = "".join(f"<li>One finding, one of these: {html.escape(f.words())}.</li>"
                     for f in disc.findings if f.is_group)
    rest = ("<p>The ladder stopped above the noise, and no effect of the library explains the rest. "
            "The remaining residual:</p><ul>" + "".join(f"<li>{html.escape(x)}</li>" for x in disc.remaining)
            + "</ul>") if disc.remaining else ""
    n = len(disc.findings)
    return (f"<h2>Discovery: {n} effect{'' if n == 1 else 's'} found in {len(disc.rungs) - 1} rung{'' if len(disc.rungs) == 2 else 's'} "
            f"({html.escape(disc.stop)})</h2>"
            "<table><tr><th>rung</th><th>added</th><th>its estimate ± σ</th><th>RMS / noise, fitted</th>"
            "<th>held out</th></tr>"
            f"{rows}</table>" + (f"<ul>{refused}</ul>" if refused else "")
            + (f"<ul>{groups}</ul>" if groups else "") + rest)


def _esc(x) -> str:
    """``x`` as text, escaped for HTML."""
    import html

    return html.escape(str(x))


def _candidate_rows(before: Diagnosis) -> str:
    """The ranked candidates' table rows (the first ten): effect, target, ΔBIC, RMS after,
    what they explain, significance and the refitted estimate."""
    esc = _esc
    return "".join(
        f"<tr><td>{i}</td><td>{esc(c.effect)}</td><td>{esc(c.target)}</td><td>{c.delta_bic:.1f}</td>"
        f"<td>{'' if c.rms_after is None else f'{c.rms_after:.2f}'}</td><td>{100 * c.explained:.0f} %</td>"
        f"<td>{'yes' if c.significant else 'no'}</td>"
        f"<td>{esc(params_words(c.params, c.units)) if c.refitted else ''}</td></tr>"
        for i, c in enumerate(before.candidates[:10], 1))


def _axis_rows(d: Diagnosis) -> str:
    """Per sensor axis of ``d``, a table row: its residual RMS, noise, their ratio (marked over
    1.1) and the fit percentage."""
    esc = _esc
    return "".join(
        f"<tr><td>{esc(a.axis)}</td><td>{a.rms:.3g} {esc(a.unit)}</td><td>{a.noise:.3g}</td>"
        f"<td{' class=bad' if a.ratio > 1.1 else ''}>{a.ratio:.2f}</td>"
        f"<td>{'—' if a.fit_percent is None else f'{a.fit_percent:.2f}'}</td></tr>" for a in d.axes)


def _most_likely_missing(before: Diagnosis) -> str:
    """The significant top candidate, its explanation and evidence; or that none is."""
    esc = _esc
    best = before.candidates[0] if before.candidates and before.candidates[0].significant else None
    return (f"<h2>Most likely missing: {esc(best.effect)} on {esc(best.target)}</h2>"
            f"<p>{esc(best.explanation)}</p><p><b>Evidence:</b> {esc(best.evidence)}.</p>") if best else \
        "<p>No effect of the library is significant: nothing to add.</p>"


def _correlation_words(before: Diagnosis) -> str:
    """The residuals' correlations beyond the corrected 99 % band, in a sentence; nothing
    without the diagnosis's analysis."""
    if before.analysis is None:
        return ""
    an = before.analysis
    fl = an.flagged()[:5]
    return (f"Correlations beyond the 99 % band ±{an.band:.3f}, corrected for the number of "
            f"tests (|r| > {an.band_flag:.3f}): "
            + ("; ".join(f"{c.axis} with {c.input} (r = {c.r:+.2f} at lag {c.lag:+d})" for c in fl)
               if fl else "none: the residuals are white and follow no input") + ".")


def write_report(path: Path, before: Diagnosis, after: Diagnosis | None, ladder: list[dict],
                 recording: Path, config: str, discovery=None) -> Path:
    """One HTML file a person reads top to bottom: verdict, ladder, ranked candidates, plots;
    with ``discovery`` (:class:`armfusion.fusion.workbench.discover.Discovery`) its rungs under the ladder."""
    figs = report_figures(before, after, ladder)
    fin = after or before
    held_words = ("" if fin.held_out_ratio is None else
                  f"; {fin.held_out_ratio:.2f}× on the held-out data ({_esc(fin.held_out.label)}), "
                  "which the fit did not see")
    d = after or before

    def img(name: str) -> str:
        return png_img(figs, name)

    esc = _esc
    rows, axes, why = _candidate_rows(before), _axis_rows(d), _most_likely_missing(before)
    step = ""
    if after is not None:
        step = (f"<h2>After adding {esc(', '.join(b for b in after.effects() if b not in before.effects()))}</h2>"
                f"<p>Residual RMS {before.rms_ratio:.2f}× → {after.rms_ratio:.2f}× the noise floor: "
                f"<b>{esc(after.verdict)}</b>.</p>{img('after')}")
    corr_words = _correlation_words(before)
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>armfusion diagnose</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}}
table{{border-collapse:collapse;font-size:90%}}td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}
td:nth-child(2),td:nth-child(3){{text-align:left}}.bad{{color:#b00;font-weight:bold}}img{{max-width:100%}}</style>
</head><body>
<h1>armfusion diagnose</h1>
<p>Recording <code>{esc(recording)}</code>, config <code>{esc(config)}</code>; {d.fit.n_samples:,} fit points.</p>
<h2>Verdict: {esc(d.verdict)}</h2>
<p>Residual RMS {d.rms_ratio:.2f}× the sensors' noise floor (1.0: the model fits to noise){held_words}.
Model effects: {esc(', '.join(e for e in d.effects() if not e.endswith('.joint_offset')) or 'none')}.</p>
{img('ladder')}
{'' if discovery is None else discovery_html(discovery)}
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
    write_text_replacing(path, doc)
    return path
