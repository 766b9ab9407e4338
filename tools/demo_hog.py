"""The README's demo beside a CPU hog: ``armfusion demo`` (the live part: router, fake
drivers, fusion node and recorder as processes over Zenoh on 127.0.0.1) while one spinning
process per core (:class:`tools.soak.CpuHog`) keeps every core busy, as on a machine whose
cores other work takes. Records what a user of the demo sees: the sample -> joint state
latency (the demo's own figure: a sample's read time on the drivers' clock to the joint
state's arrival at its consumer), the samples the fusion node refused, and what its
lateness policy did (degraded periods, instants folded, the largest lag), from the fusion
node's own report. The sensor calibration step is left out (``--no-calibrate``: the node
serves with the shipped config), as is the workbench, so that the hog covers the live run::

    nice python tools/demo_hog.py --duration 60 --write

``--write`` replaces the ``demo-cpu-hog`` section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tools.benchdoc import machine_line, write_section  # noqa: E402
from tools.soak import HOG_GRACE_S, CpuHog, _commit  # noqa: E402

DEMO_START_S = 900.0
"""The demo's nodes start (the fusion node compiles its kernels on a cold cache) within this."""
TARGET_P99_MS = 100.0
"""The latency target with every core busy (p99)."""


def run(duration_s: float, seed: int, batch_ms: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="armfusion-demo-hog-") as tmp:
        out = Path(tmp) / "demo"
        hog = CpuHog(DEMO_START_S + duration_s + HOG_GRACE_S)
        hog.start()
        t0 = time.monotonic()
        try:
            proc = subprocess.run(
                [sys.executable, "-m", "armfusion.fusion.cli", "demo", "--no-calibrate", "--no-workbench",
                 "--duration", str(duration_s), "--seed", str(seed), "--batch-ms", str(batch_ms),
                 "--out", str(out), "--json"],
                cwd=ROOT, capture_output=True, text=True, timeout=DEMO_START_S + 4 * duration_s + 120)
        finally:
            hog.stop()
        wall_s = time.monotonic() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"armfusion demo failed ({proc.returncode}): {proc.stderr[-2000:]}")
        doc = json.loads((out / "summary.json").read_text())
        serve = json.loads((out / "nodes" / "serve.out").read_text())
    ev = doc.get("evaluation", doc)
    return {"duration_s": duration_s, "seed": seed, "batch_ms": batch_ms, "wall_s": wall_s,
            "cpu_hog_processes": os.cpu_count() or 1, "load_average_1min": os.getloadavg()[0],
            "latency": ev.get("latency"), "samples": ev.get("samples"),
            "machine": ev.get("machine"), "tracking": {k: ev.get("tracking", {}).get(k) for k in
                                                      ("estimates", "rms_error_deg", "within_3_sigma")},
            "serve": {k: serve.get(k) for k in ("samples", "estimates", "dropped", "refused_samples",
                                               "degraded_periods", "folded_instants", "lag_max_ms",
                                               "shed_samples", "stalls", "errors", "message")},
            "commit": _commit()}


def markdown(r: dict) -> str:
    lat, srv, smp, m = r["latency"] or {}, r["serve"], r["samples"] or {}, r.get("machine") or {}
    p99 = lat.get("p99_after_settle_ms", lat.get("p99_ms"))
    verdict = ("none: no joint state arrived" if p99 is None else
               "this run meets it" if p99 <= TARGET_P99_MS else "this run misses it")
    refused = srv.get("refused_samples") or {}
    dropped = srv.get("dropped") or {}
    rows = [
        ("latency a sample's read time -> joint state, p50 / p99 / max (every joint state)",
         f"{lat.get('p50_ms', float('nan')):.1f} / {lat.get('p99_ms', float('nan')):.1f} / "
         f"{lat.get('max_ms', float('nan')):.1f} ms (n = {lat.get('count')})"),
        (f"the same after the first {lat.get('settle_s', 10):g} s of tracking, p50 / p99",
         f"{lat.get('p50_after_settle_ms', float('nan')):.1f} / {p99:.1f} ms" if p99 is not None else "none"),
        ("samples published by the drivers / accepted by the node / shed unread while it was behind",
         f"{smp.get('published')} / {srv.get('samples')} / {srv.get('shed_samples') or 0}"),
        ("samples the node refused (genuine: the drivers are the only publishers), by reason",
         ", ".join(f"{k} {v}" for k, v in sorted(refused.items())) or "none"),
        ("batches (payloads) the node refused or dropped, by reason",
         ", ".join(f"{k} {v}" for k, v in sorted(dropped.items())) or "none"),
        ("the node degraded (periods) / instants folded / largest lag",
         f"{srv.get('degraded_periods')} / {srv.get('folded_instants')} / {srv.get('lag_max_ms')} ms"),
        ("joint states received by the demo's consumer", f"{r['tracking']['estimates']}"),
        ("the fusion node's CPU / wall time from its start (share of one core)",
         f"{m.get('serve_cpu_s')} s / {m.get('serve_wall_s')} s"
         + (f" ({100 * m['serve_cpu_s'] / m['serve_wall_s']:.0f} %)"
            if m.get("serve_cpu_s") and m.get("serve_wall_s") else "")),
        ("stalls / errors in the node", f"{srv.get('stalls')} / {srv.get('errors')}"),
        ("the node's last message", (srv.get("message") or "")[:160].replace("|", "/")),
    ]
    table = "| figure | value |\n| --- | --- |\n" + "\n".join(f"| {a} | {b} |" for a, b in rows)
    return f"""## The demo beside a CPU hog (`tools/demo_hog.py`)

{machine_line()}; commit {r['commit']}; load average {r['load_average_1min']:.1f} at the end
(a shared machine: other processes took CPU too). `armfusion demo --no-calibrate --no-workbench
--duration {r['duration_s']:.0f} --batch-ms {r['batch_ms']:.0f}` (router, fake drivers, fusion
node and recorder as processes over Zenoh on 127.0.0.1) while {r['cpu_hog_processes']} processes
spin beside it, one per core, from before the nodes start until the demo ends
({r['wall_s']:.0f} s of wall time).

{table}

The p99 latency target with every core busy is {TARGET_P99_MS:.0f} ms (after the settling):
{verdict}. The demo publishes at the node's default 50 joint states a second, so a folded
instant (docs/service-node.md, "When the node falls behind") rarely leaves a gap a
consumer sees. Every refusal here is of a genuine batch: the fake drivers are the only
publishers.
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0, help="Seconds of the live run.")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--batch-ms", type=float, default=20.0, help="The drivers' batch, ms.")
    ap.add_argument("--write", action="store_true", help="Write its section of docs/benchmarks.md.")
    ap.add_argument("--json", action="store_true", help="Print the figures as JSON.")
    ap.add_argument("--from-json", type=Path, help="Render an earlier --json run instead of running again.")
    args = ap.parse_args(argv)
    r = json.loads(args.from_json.read_text()) if args.from_json else run(args.duration, args.seed,
                                                                          args.batch_ms)
    print(json.dumps(r, indent=2) if args.json else markdown(r))
    if args.write:
        print(f"wrote {write_section('demo-cpu-hog', markdown(r))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
