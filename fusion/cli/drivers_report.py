"""The report of ``armfusion drivers``: a run (:class:`~armfusion.fusion.cli.drivers_run.DriversRun`)
as one JSON document (:func:`summary`, documented in docs/reference/drivers.md) and as the tables a
person reads (:func:`print_report`): per device the samples, read time, jitter, bus
errors, retries and the drivers' other counters."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from armfusion.fusion.cli.drivers_run import ENCODER_READER, DriversRun
from armfusion.sensors.sampling import Wiring


def _valid_count(name: str, results: list[Any]) -> int:
    if name == ENCODER_READER:
        return len(results)
    n = 0
    for s in results:
        n += bool(getattr(s, "valid", False))
    return n


def _ms(seconds: float) -> float:
    return round(1e3 * seconds, 4)


def _bus(w: Wiring) -> str:
    return f"spi{w.bus_number}.{w.address}" if w.bus == "spi" else f"i2c{w.bus_number} 0x{w.address:02X}"


def summary(run: DriversRun) -> dict[str, Any]:
    """The run as one JSON-ready document (documented in docs/reference/drivers.md)."""
    rep = run.loop
    bus = {w.name: _bus(w) for w in run.wiring}
    devices: dict[str, Any] = {}
    for name, timing in rep.readers.items():
        results = run.samples.get(name, [])
        d: dict[str, Any] = {
            "bus": bus.get(name, "simulated feed" if run.mode == "fake" else "-"),
            "samples": _valid_count(name, results),
            "read_time_ms": {"mean": _ms(timing.read_time_mean_s), "std": _ms(timing.read_time_std_s),
                             "max": _ms(timing.read_time_max_s)},
            "jitter_ms": {"std": _ms(timing.jitter_std_s), "max_abs": _ms(timing.jitter_max_abs_s)},
            "loop_errors": timing.errors,
        }
        h = run.health.get(name)
        if h is not None:
            d.update({"where": h.where, "online": h.online, "counters": dict(h.counters),
                      "errors": h["bus_errors"], "retries": h["retries"], "last_error": h.last_error})
        elif name == ENCODER_READER and run.encoder_stats is not None:
            st = run.encoder_stats
            d.update({"where": "simulated encoder feed", "online": True,
                      "counters": dict(st.__dict__), "errors": st.malformed, "retries": 0,
                      "last_error": ""})
        devices[name] = d
        mag = run.health.get(f"{name}.mag")
        if mag is not None:
            w = next(w for w in run.wiring if w.name == name)
            devices[f"{name}.mag"] = {
                "bus": f"i2c{w.bus_number} 0x0C",
                "samples": sum(1 for s in results if getattr(s, "mag_valid", False)),
                "where": mag.where, "online": mag.online, "counters": dict(mag.counters),
                "errors": mag["bus_errors"], "retries": mag["retries"], "last_error": mag.last_error,
            }
    return {
        "mode": run.mode,
        "config": run.arm.source,
        "arm": run.arm.name,
        **({k: run.settings[k] for k in ("scenario", "seed", "realistic", "noise", "realtime",
                                         "epoch_monotonic_s") if k in run.settings}),
        "rate_hz": run.rate_hz,
        "duration_s": round(rep.duration_s, 6),
        "ticks": rep.ticks,
        "missed_ticks": rep.missed_ticks,
        "lateness_ms": {"mean": _ms(rep.lateness_mean_s), "max": _ms(rep.lateness_max_s)},
        "devices": devices,
        "streams": {k: len(s) for k, s in run.recording.streams.items()},
        "faults": [{"spec": f.text, "target": f.target, "kind": f.kind} for f in run.faults],
        "faults_injected": run.faults_injected,
        "notes": list(run.notes),
    }


_QUIET = frozenset({"reads", "ok", "bus_errors", "retries", "received", "accepted"})


def _events(counters: Mapping[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counters.items()) if v and k not in _QUIET) or "-"


def print_report(doc: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    con = Console()
    head = f"[bold]{doc['arm']}[/] ({doc['mode']}"
    if doc["mode"] == "fake":
        head += f": {doc['scenario']}, seed {doc['seed']}" + (", realistic" if doc["realistic"] else "")
        head += ", wall clock" if doc["realtime"] else ", simulated clock"
    con.print(head + f"): {doc['ticks']} ticks at {doc['rate_hz']:g} Hz over {doc['duration_s']:.2f} s, "
              f"{doc['missed_ticks']} missed; tick lateness {doc['lateness_ms']['mean']:.3f} ms mean / "
              f"{doc['lateness_ms']['max']:.3f} ms max", highlight=False)
    t = Table(title="Devices", title_justify="left")
    for col in ("device", "bus", "samples", "read (ms) mean/max", "jitter (ms) std/max",
                "errors", "retries", "other events"):
        t.add_column(col, justify="right" if col in ("samples", "errors", "retries") else "left")
    for name, d in doc["devices"].items():
        timing = "-"
        jitter = "-"
        if "read_time_ms" in d:
            timing = f"{d['read_time_ms']['mean']:.2f}/{d['read_time_ms']['max']:.2f}"
            jitter = f"{d['jitter_ms']['std']:.2f}/{d['jitter_ms']['max_abs']:.2f}"
        errors = d.get("errors", 0) + d.get("loop_errors", 0)
        events = _events(d.get("counters", {}))
        if not d.get("online", True):
            events = "[red]OFFLINE[/]" + ("" if events == "-" else f", {events}")
        t.add_row(name, d["bus"], str(d["samples"]), timing, jitter,
                  f"[red]{errors}[/]" if errors else "0", str(d.get("retries", 0)), events)
    con.print(t)
    for f in doc["faults"]:
        con.print(f"fault injected: {escape(f['spec'])}", highlight=False)
    if doc["faults"]:
        con.print(f"{doc['faults_injected']} transactions failed by injection", highlight=False)
    for name, d in doc["devices"].items():
        if d.get("last_error"):
            con.print(f"[yellow]{name}[/] last error: {escape(d['last_error'])}", highlight=False)
    for n in doc["notes"]:
        con.print(f"note: {escape(n)}", highlight=False)
    if doc.get("out"):
        con.print(f"Wrote {doc['out']}" + (f" and {doc['truth']}" if doc.get("truth") else ""),
                  highlight=False)
