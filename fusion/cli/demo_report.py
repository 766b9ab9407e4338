"""What ``armfusion demo`` shows of a run (:mod:`armfusion.fusion.cli.demo`): the self-contained
HTML report (the tracking plots against the truth, the workbench's verdict and error ladder)
and the summary table for the terminal, both from the evaluation's document."""

from __future__ import annotations

import html
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from armfusion.fusion.cli.common import console, png_img
from armfusion.fusion.tracking.tracker import truth_at
from armfusion.models.rotations import wrap_angle


def score_combinations(reported: list, t: np.ndarray, q_true: np.ndarray, tilt_true: np.ndarray,
                       names: list[str]) -> list[dict[str, Any]]:
    """What gravity reads together (the joint states' ``combinations``, per estimate a tuple of
    ``{name, coefficients, angle_rad, sigma_rad}`` or None), each combination ever reported
    scored against the same combination of the truth (the joints' ``q_true (T, n)`` and the
    base's ``tilt_true (T, 2)``, roll and pitch, rad) over the estimates it was reported at:
    its share of estimates, its last value and sigma (deg), RMS error and share within 3 sigma
    (None where no truth)."""
    from armfusion.fusion.startup.solve import TILT_NAMES

    series: dict[str, dict[str, Any]] = {}
    for i, cs in enumerate(reported):
        for c in cs or ():
            row = series.setdefault(c["name"], {"coefficients": dict(c["coefficients"]), "i": [], "v": [],
                                                "s": []})
            row["i"].append(i)
            row["v"].append(float(c["angle_rad"]))
            row["s"].append(float(c["sigma_rad"]))
    truth_cols = {**{n: q_true[:, k] for k, n in enumerate(names)},
                  **{n: tilt_true[:, k] for k, n in enumerate(TILT_NAMES)}}
    out = []
    for name, row in series.items():
        idx, v, sg = np.array(row["i"]), np.array(row["v"]), np.array(row["s"])
        true = sum(c * truth_cols.get(term, np.full(len(t), np.nan))[idx]
                   for term, c in row["coefficients"].items())
        err = np.degrees(v - true)
        have = np.isfinite(err)
        out.append({"name": name, "coefficients": row["coefficients"],
                    "reported_share": float(len(idx) / max(len(t), 1)),
                    "angle_deg": float(np.degrees(v[-1])), "sigma_deg": float(np.degrees(sg[-1])),
                    "rms_error_deg": float(np.sqrt(np.mean(err[have] ** 2))) if have.any() else None,
                    "within_3_sigma": (float(np.mean(np.abs(err[have]) <= 3.0 * np.degrees(sg[have])))
                                       if have.any() else None)})
    return out


def joint_scores(names: list[str], t: np.ndarray, err_deg: np.ndarray, sig: np.ndarray,
                 flags: np.ndarray) -> dict[str, dict]:
    """Each joint's startup error, tracking RMS, worst error, share within 3 sigma, flags seen,
    and the same from its first ``ok`` estimate on (``err_deg``: estimate - truth per instant)."""
    first = 0
    startup = {n: {"error_deg": float(err_deg[first, k]), "sigma_deg": float(np.degrees(sig[first, k])),
                   "flag": str(flags[first, k])} for k, n in enumerate(names)}
    scored = np.isfinite(err_deg).all(axis=1)  # (an estimate past the truth's end is not scored)
    err_deg, sig_deg, t_scored = err_deg[scored], np.degrees(sig[scored]), t[scored]
    rms = {n: float(np.sqrt(np.mean(err_deg[:, k] ** 2))) for k, n in enumerate(names)}
    # from each joint's first `ok` estimate on: a joint gravity cannot read at the park pose
    # (j3, j6 at gimbal lock) is held at its prior, with a sigma that says so, until the arm
    # first reaches; its RMS over the whole run is mostly that wait
    once_ok: dict[str, dict[str, float] | None] = {}
    for k, n in enumerate(names):
        ok = np.flatnonzero(flags[scored][:, k] == "ok")
        once_ok[n] = None if not len(ok) else {
            "t_s": float(t_scored[ok[0]]), "rms_error_deg": float(np.sqrt(np.mean(err_deg[ok[0]:, k] ** 2))),
            "within_3_sigma": float(np.mean(np.abs(err_deg[ok[0]:, k]) <= 3 * sig_deg[ok[0]:, k]))}
    worst = {n: float(np.max(np.abs(err_deg[:, k]))) for k, n in enumerate(names)}
    inside = np.abs(err_deg) <= 3 * sig_deg
    within = {n: float(np.mean(inside[:, k])) for k, n in enumerate(names)}
    seen = {n: dict(Counter(flags[:, k].tolist()).most_common()) for k, n in enumerate(names)}
    return {"startup": startup, "rms": rms, "once_ok": once_ok, "worst": worst, "within": within,
            "seen": seen}


def heading_scores(headings: list, truth_base) -> tuple[float | None, float | None, dict[str, float]]:
    """The heading's RMS error (deg), its share within 3 sigma and its statuses' shares, from
    the ``(arrival, Heading)`` pairs received (``None``, ``None``, ``{}`` without any)."""
    if not headings:
        return None, None, {}
    th = np.array([h.t_s for _, h in headings])
    yaw = np.array([h.heading_rad for _, h in headings])
    yaw_true = truth_at(truth_base, th, angles=True)[:, 2]
    yaw_err = np.abs(wrap_angle(yaw - yaw_true))
    heading_rms = float(np.degrees(np.sqrt(np.mean(yaw_err**2))))
    heading_within = float(np.mean(yaw_err <= 3 * np.array([h.heading_sigma_rad for _, h in headings])))
    heading_status = {s: n / len(headings) for s, n in
                      Counter(h.heading_status for _, h in headings).most_common()}
    return heading_rms, heading_within, heading_status


def latency_figures(arrived: np.ndarray, t: np.ndarray, epoch: float | None, settle_s: float) -> dict | None:
    """The sample->estimate latency (ms) from each estimate's arrival and its sample time on the
    drivers' clock (``epoch``: that clock's zero on this machine's monotonic clock), and the
    same after ``settle_s`` of tracking; ``None`` without the epoch."""
    if epoch is None:
        return None
    lat_ms = 1e3 * (arrived - (epoch + t))
    latency = {"p50_ms": float(np.percentile(lat_ms, 50)), "p99_ms": float(np.percentile(lat_ms, 99)),
               "max_ms": float(np.max(lat_ms)), "count": int(len(lat_ms))}
    # the node buffers while it calibrates on the still stretch, then works off the
    # backlog: the latency once it runs, apart
    later = lat_ms[t >= t[0] + settle_s]
    if len(later):
        latency.update({"settle_s": settle_s,
                        "p50_after_settle_ms": float(np.percentile(later, 50)),
                        "p99_after_settle_ms": float(np.percentile(later, 99))})
    return latency


def shed_words(s: dict) -> str:
    """`` (N more shed unread while it was behind)`` when the node shed samples, else ``""``."""
    n = s.get("shed_by_serve", 0)
    return f" ({n} more shed unread while it was behind)" if n else ""


def sample_counts(drv: dict, srv: dict, rec: dict, received: int) -> dict:
    """Samples and estimates published, received, refused, recorded and dropped, from the
    drivers', the fusion node's and the recorder's reports (``received``: estimates here)."""
    published = int(sum(drv.get("published", {}).get("samples", {}).values()))
    dropped = {f"serve.{k}": v for k, v in srv.get("dropped", {}).items()}
    if srv.get("out_of_order"):
        dropped["serve.out_of_order"] = srv["out_of_order"]
    dropped.update({f"record.{k}": v for k, v in rec.get("dropped", {}).items()})
    return {"published": published, "received_by_serve": int(srv.get("samples", 0)),
            # refused by the node's admission, by reason (a driver that fell behind on a
            # loaded machine reads a burst, refused as too dense): counted, never lost
            "refused_by_serve": {k: int(v) for k, v in srv.get("refused_samples", {}).items()},
            # shed unread while the node was behind (its lateness policy): counted, not fused
            "shed_by_serve": int(srv.get("shed_samples", 0)),
            "recorded": int(sum(rec.get("samples", {}).values())), "dropped": dropped,
            "estimates_published": int(srv.get("estimates", 0)),
            # messages whose handling raised in the fusion node (logged, the node going on)
            "serve_errors": int(srv.get("errors", 0)),
            "estimates_received": int(received),
            "estimates_recorded": int(sum(rec.get("estimates", {}).values()))}


def heading_detail(tr: dict) -> str:
    """The heading's share within 3 sigma and its statuses (``compass_fused``…) over the run."""
    within, status = tr.get("heading_within_3_sigma"), tr.get("heading_status") or {}
    if within is None:
        return ""
    shares = ", ".join(f"{k.replace('_', ' ')} {100 * v:.0f} %" for k, v in status.items())
    return f", within 3σ {100 * within:.0f} %" + (f" ({shares})" if shares else "")


def settled_latency(lat: dict) -> str:
    if "p99_after_settle_ms" not in lat:
        return ""
    return (f"; after the first {lat['settle_s']:g} s of tracking p50 {lat['p50_after_settle_ms']:.1f} ms, "
            f"p99 {lat['p99_after_settle_ms']:.1f} ms")


def combinations_html(combos: list[dict[str, Any]]) -> str:
    """The table of what gravity reads together (:func:`score_combinations`):
    name, last value, σ, error against the truth, share within 3σ and of estimates reported."""
    if not combos:
        return ("<p>Every joint the sensors read was read alone: no combination of joints (or of a "
                "joint and the base's tilt) was reported.</p>")

    def pct(x) -> str:
        return "—" if x is None else f"{100 * x:.0f} %"

    rows = "".join(
        f"<tr><td>{html.escape(c['name'])}</td><td>{c['angle_deg']:+.2f}</td><td>{c['sigma_deg']:.2f}</td>"
        f"<td>{'—' if c['rms_error_deg'] is None else format(c['rms_error_deg'], '.2f')}</td>"
        f"<td>{pct(c['within_3_sigma'])}</td><td>{pct(c['reported_share'])}</td></tr>"
        for c in combos)
    return ("<table><tr><th>combination</th><th>value (last) [deg]</th><th>σ (last) [deg]</th>"
            "<th>RMS error [deg]</th><th>within 3σ</th><th>estimates reported at</th></tr>"
            f"{rows}</table>")


def tracking_figures(ev: dict[str, Any]) -> dict[str, bytes]:
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = ev["_series"]
    t, q, sig = s["t"], s["q"], s["sigma"]
    tq = s["truth_q"]
    names = ev["joint_names"]
    figs: dict[str, bytes] = {}

    def png(fig) -> bytes:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
        plt.close(fig)
        return buf.getvalue()

    n = len(names)
    fig, axs = plt.subplots(n, 2, figsize=(12, 1.9 * n), squeeze=False, layout="constrained")
    span = (tq.t_s >= t[0] - 1.0) & (tq.t_s <= t[-1])
    q_true = truth_at(tq, t)
    for k, name in enumerate(names):
        a, b = axs[k]
        a.plot(tq.t_s[span], np.degrees(tq.values[span, k]), "-", color="0.5", lw=2, label="truth")
        a.plot(t, np.degrees(q[:, k]), "-", color="C0", lw=1, label="estimate")
        a.set_ylabel(f"{name} [deg]")
        e = np.degrees(q[:, k] - q_true[:, k])
        s2 = 2 * np.degrees(sig[:, k])
        b.fill_between(t, -s2, s2, color="C0", alpha=0.2, label="±2σ")
        b.plot(t, e, "-", color="C3", lw=1, label="error")
        lim = max(1.0, float(np.percentile(np.abs(e), 99)) * 1.5)
        b.set_ylim(-lim, lim)
        b.set_ylabel("error [deg]")
    axs[0][0].legend(fontsize=8, loc="upper right")
    axs[0][1].legend(fontsize=8, loc="upper right")
    axs[-1][0].set_xlabel("t [s]")
    axs[-1][1].set_xlabel("t [s]")
    figs["joints"] = png(fig)
    if s["headings"]:
        tb = s["truth_base"]
        th, yaw, ysig = (np.array(v) for v in zip(*s["headings"], strict=True))
        yaw_true = truth_at(tb, th, angles=True)[:, 2]
        fig, (a, b) = plt.subplots(1, 2, figsize=(12, 2.8), layout="constrained")
        a.plot(th, np.degrees(yaw_true), "-", color="0.5", lw=2, label="truth")
        a.plot(th, np.degrees(yaw), "-", color="C0", lw=1, label="estimate")
        a.set_ylabel("heading [deg]")
        a.set_xlabel("t [s]")
        a.legend(fontsize=8)
        e = np.degrees(wrap_angle(yaw - yaw_true))
        b.fill_between(th, -2 * np.degrees(ysig), 2 * np.degrees(ysig), color="C0", alpha=0.2, label="±2σ")
        b.plot(th, e, "-", color="C3", lw=1, label="error")
        b.set_ylabel("heading error [deg]")
        b.set_xlabel("t [s]")
        b.legend(fontsize=8)
        figs["heading"] = png(fig)
    return figs


def _esc(x) -> str:
    """``x`` as text, escaped for HTML."""
    return html.escape(str(x))


def _joint_rows(ev: dict[str, Any]) -> str:
    """The accuracy table's rows: per joint, the startup's error, σ and flag, the tracking's
    errors, the share within 3σ, the first ok estimate and the flags seen."""
    tr, esc = ev["tracking"], _esc
    return "".join(
        f"<tr><td>{esc(n)}</td><td>{ev['startup']['joints'][n]['error_deg']:+.3f}</td>"
        f"<td>{ev['startup']['joints'][n]['sigma_deg']:.3f}</td><td>{esc(ev['startup']['joints'][n]['flag'])}</td>"
        f"<td>{tr['rms_error_deg'][n]:.3f}</td><td>{tr['max_error_deg'][n]:.3f}</td>"
        f"<td>{100 * tr['within_3_sigma'][n]:.0f} %</td>"
        + ("<td>never ok</td><td>—</td>" if tr["from_first_ok"][n] is None else
           f"<td>{tr['from_first_ok'][n]['t_s']:.1f}</td><td>{tr['from_first_ok'][n]['rms_error_deg']:.3f}</td>")
        + f"<td>{esc(', '.join(f'{k} {v}' for k, v in ev['flags_seen'][n].items()))}</td></tr>"
        for n in ev["joint_names"])


def _workbench_section(doc: dict[str, Any], diag, ladder, figs: dict[str, bytes]) -> str:
    """What the workbench said of the calibration recording (the shipped model's residual, the
    best candidate's evidence, the identified model's residual) with its figures; or that it
    was not run."""
    if diag is None:
        return "<p>The workbench was not run (--no-workbench).</p>"
    esc = _esc
    best = diag.candidates[0] if diag.candidates and diag.candidates[0].significant else None
    return (f"<p>On the calibration recording (<code>{esc(doc['calibration']['recording'])}"
            f"</code>), the shipped model (no sensor errors) leaves a residual of "
            f"<b>{diag.rms_ratio:.1f}×</b> the sensors' noise: <b>{esc(diag.verdict)}</b>."
            + (f" {esc(best.evidence)}." if best else "")
            + " With the identified effects the fit's residual is "
            f"<b>{ladder[-1]['rms_ratio']:.2f}×</b> the noise (the identification's fit on the "
            "same window means).</p>"
            + png_img(figs, "wb_ladder") + png_img(figs, "wb_candidates"))


def _machine_words(ev: dict[str, Any]) -> str:
    """The fusion node's CPU time and the machine's load, with what the node does when short
    of CPU; nothing when not measured."""
    m = ev.get("machine") or {}
    return "" if m.get("serve_cpu_s") is None else (
        f"<p>The fusion node used {m['serve_cpu_s']:.0f} CPU-s in {m['serve_wall_s']:.0f} s of wall time; "
        f"load average {m['load_average_1min']:.1f} on {m['cpus']} CPUs. With too little CPU the fusion "
        "node degrades rather than lag: it folds late instants into fewer updates, publishes fewer "
        "estimates and says <code>degraded</code> with its lag in its status.</p>")


def write_report(path: Path, doc: dict[str, Any], ev: dict[str, Any], diag, ladder) -> Path:
    """One self-contained HTML file: the summary, the tracking plots, the workbench."""
    figs = tracking_figures(ev)
    if diag is not None:
        from armfusion.fusion.cli.diagnose_report import report_figures

        wb = report_figures(diag, None, ladder)
        figs.update({f"wb_{k}": v for k, v in wb.items() if k in ("ladder", "candidates")})

    def img(name: str) -> str:
        return png_img(figs, name)

    esc = _esc
    tr = ev["tracking"]
    rows = _joint_rows(ev)
    wb_html = _workbench_section(doc, diag, ladder, figs)
    s = ev["samples"]
    lat = ev["latency"]
    machine = _machine_words(ev)
    heading_html = (("—" if tr["heading_rms_deg"] is None else f"{tr['heading_rms_deg']:.2f}°")
                    + esc(heading_detail(tr)))
    doc_html = f"""<!doctype html><html><head><meta charset="utf-8"><title>armfusion demo</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}}
table{{border-collapse:collapse;font-size:90%}}td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}
td:first-child,td:last-child{{text-align:left}}img{{max-width:100%}}</style></head><body>
<h1>armfusion demo</h1>
<p>The WMRA simulated with {'datasheet-typical' if doc['realistic'] else 'no'} sensor errors
(seed {doc['seed']}), scenario <code>{esc(doc['scenario'])}</code> for {doc['duration_s']:g} s on the
wall clock: fake-device drivers → fusion node (config <code>{esc(doc['config'])}</code>) → recorder,
separate processes over Zenoh on 127.0.0.1.</p>
<h2>Startup calibration</h2><p>{esc(ev['startup']['message'])} (t = {ev['startup']['t_s']:.2f} s)</p>
<h2>Accuracy against the simulator's truth</h2>
<table><tr><th>joint</th><th>startup error [deg]</th><th>startup σ [deg]</th><th>startup flag</th>
<th>tracking RMS [deg]</th><th>max [deg]</th><th>within 3σ</th>
<th>first ok [s]</th><th>RMS from first ok [deg]</th><th>flags seen (estimates)</th></tr>
{rows}</table>
<p>Heading RMS error: {heading_html}.
{tr['estimates']} joint states from t = {tr['t_start_s']:.2f} to {tr['t_end_s']:.2f} s.</p>
<p>Samples: {s['published']} published, {s['received_by_serve']} received by the fusion node{shed_words(s)}, {s['recorded']}
recorded; dropped: {esc(', '.join(f'{k} {v}' for k, v in s['dropped'].items()) or 'none')}.
Sample→estimate latency: {'—' if lat is None else
    f"p50 {lat['p50_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms" + settled_latency(lat)}.</p>
{machine}
<h2>What gravity reads together</h2>
<p>Where single joints are not read, the combinations the tracker reports with their σ
(the joint states' <code>combinations</code>), scored against the same combination of the truth.</p>
{combinations_html(tr.get('combinations') or [])}
<h2>Tracking: estimate against truth, and the error with its ±2σ band</h2>{img('joints')}
<h2>Heading</h2>{img('heading')}
<h2>The workbench: what the sensor calibration fixed</h2>{wb_html}
</body></html>
"""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(doc_html, encoding="utf-8")
    return path


def summary_table(doc: dict[str, Any], ev: dict[str, Any]):
    from rich.table import Table

    tr = ev["tracking"]
    t = Table(title="armfusion demo: accuracy against the simulator's truth", title_justify="left")
    for col in ("joint", "startup error [deg]", "startup flag", "tracking RMS [deg]", "max [deg]",
                "within 3σ", "from first ok: t [s], RMS [deg]", "flags seen"):
        t.add_column(col, justify="left" if col in ("joint", "startup flag", "flags seen") else "right")
    for n in ev["joint_names"]:
        st = ev["startup"]["joints"][n]
        seen = ev["flags_seen"][n]
        total = sum(seen.values())
        colour = "green" if st["flag"] == "ok" else "yellow"
        t.add_row(n, f"{st['error_deg']:+.2f} ± {st['sigma_deg']:.2f}", f"[{colour}]{st['flag']}[/]",
                  f"{tr['rms_error_deg'][n]:.2f}", f"{tr['max_error_deg'][n]:.2f}",
                  f"{100 * tr['within_3_sigma'][n]:.0f} %",
                  "never ok" if tr["from_first_ok"][n] is None else
                  f"{tr['from_first_ok'][n]['t_s']:.1f}, {tr['from_first_ok'][n]['rms_error_deg']:.2f}",
                  ", ".join(f"{k} {100 * v / total:.0f} %" for k, v in seen.items()))
    s = ev["samples"]
    lat = ev["latency"]
    lines = [
        "heading RMS error: " + ("—" if tr["heading_rms_deg"] is None else f"{tr['heading_rms_deg']:.2f}°")
        + heading_detail(tr),
        f"samples: {s['published']} published by the drivers, {s['received_by_serve']} received by the "
        f"fusion node{shed_words(s)}, {s['recorded']} recorded; dropped: "
        + (", ".join(f"{k} {v}" for k, v in s["dropped"].items()) or "none"),
        f"estimates: {s['estimates_published']} published, {s['estimates_received']} received here, "
        f"{s['estimates_recorded']} recorded"
        + (f"; [red]the fusion node raised on {s['serve_errors']} messages[/] (its log says where)"
           if s.get("serve_errors") else ""),
        "sample→estimate latency: " + ("—" if lat is None else
                                       f"p50 {lat['p50_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms "
                                       f"(max {lat['max_ms']:.1f} ms, {lat['count']} estimates)"
                                       + settled_latency(lat)),
    ]
    m = ev.get("machine")
    if m and m.get("serve_cpu_s") is not None:
        lines.append(f"the fusion node used {m['serve_cpu_s']:.0f} CPU-s in {m['serve_wall_s']:.0f} s; load "
                     f"average {m['load_average_1min']:.1f} on {m['cpus']} CPUs (with too little CPU the "
                     "fusion node degrades rather than lag: it folds late instants into fewer updates, "
                     "publishes fewer estimates and says `degraded` with its lag in its status; "
                     "docs/service-node.md)")
    return t, lines


def say_summary(doc: dict, ev: dict, diag, ladder, last_line: str) -> None:
    """The summary on the console: the startup, the table, the workbench's verdict, the report."""
    table, lines = summary_table(doc, ev)
    console.print(f"startup: {ev['startup']['message']}", highlight=False)
    console.print(table)
    for ln in lines:
        console.print(ln, highlight=False)
    if diag is not None:
        console.print(f"workbench on the calibration recording: shipped model {diag.rms_ratio:.1f}× "
                      f"the noise ({diag.verdict}); with the identified effects "
                      f"{ladder[-1]['rms_ratio']:.2f}×", highlight=False)
    console.print(last_line, highlight=False)
