"""``armfusion router``, ``armfusion fleet`` and ``armfusion monitor``.

``router``: a Zenoh session in router mode (listening on loopback only, no scouting: on
``--listen``, else on its ``--zenoh-config`` file's endpoints, by default
tcp/127.0.0.1:7447) that
the nodes of several chairs connect to; with gossip off, peers do not find each other
through a third peer, so a fleet needs one.

``fleet``: N simulated chairs, each two processes (``armfusion drivers --fake --realtime
--robot chairK`` → ``armfusion serve --robot chairK``), every one connected to a router
(its own, started as a process, or ``--connect``'s); stops them all on SIGINT or SIGTERM
(or after ``--duration``), and leaves no child behind.

``monitor``: a live table of every robot it hears (:mod:`armfusion.fusion.service.monitor`).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Annotated

import typer
from armfusion.fusion.cli.common import console, emit_json, err_console, fail
from armfusion.fusion.cli.nodes import session_or_exit, zenoh_settings
from armfusion.fusion.cli.options import (
    ConfigOpt,
    ConnectOpt,
    JsonOpt,
    ListenOpt,
    ModeOpt,
    RealisticOpt,
    ScenarioOpt,
    StopAfterOpt,
    ZenohConfigOpt,
)
from armfusion.fusion.service.node import stop_on_signals
from armfusion.fusion.service.processes import free_loopback_port
from armfusion.fusion.service.zenoh_config import (
    ZenohConfigError,
    check_loopback,
    endpoints_line,
    load_config,
)


def router_command(
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    zenoh_config: ZenohConfigOpt = None,
    duration_s: StopAfterOpt = None,
) -> None:
    """A Zenoh router on loopback for the nodes of several robots: it listens where --listen
    says, else where --zenoh-config's file says (default tcp/127.0.0.1:7447), and connects
    where its file says (or --connect); runs until SIGINT or SIGTERM."""
    settings = zenoh_settings(zenoh_config, listen, connect, "router")
    stop = threading.Event()
    with session_or_exit(settings, say_endpoints=False) as session, stop_on_signals(stop):
        where = endpoints_line(load_config(settings), settings).split(": ", 1)[1]
        err_console.print(f"router {session.zid()} {where}; Ctrl-C (SIGINT) or SIGTERM stops",
                          highlight=False, soft_wrap=True)
        stop.wait(duration_s)
    err_console.print("router stopped", highlight=False)

def fleet_command(
    chairs: Annotated[int, typer.Option("--chairs", "-n", help="How many simulated chairs.")] = 3,
    duration_s: Annotated[float, typer.Option(
        "--duration", help="Seconds each chair's fake drivers run.")] = 60.0,
    scenario: ScenarioOpt = "daily-use",
    realistic: RealisticOpt = False,
    seed: Annotated[int, typer.Option("--seed", help="Chair k simulates with seed + k.")] = 0,
    prefix: Annotated[str, typer.Option("--prefix", help="Chair k is <prefix><k>.")] = "chair",
    rate_hz: Annotated[float, typer.Option("--rate", help="Each chair's sampling rate, Hz.")] = 100.0,
    config: ConfigOpt = "wmra",
    router_listen: Annotated[str | None, typer.Option(
        "--router-listen", help="Start a router listening here (default: a free loopback port).")] = None,
    connect: Annotated[str | None, typer.Option(
        "--connect", help="Use this running router instead of starting one.")] = None,
    workdir: Annotated[Path | None, typer.Option(
        "--workdir", help="Where the nodes' outputs go (default: a temporary directory).")] = None,
) -> None:
    """N simulated chairs as separate processes (fake drivers → serve each), connected
    through one Zenoh router; watch them with `armfusion monitor --connect <router>`."""
    import tempfile

    from armfusion.fusion.service.payloads import check_name
    from armfusion.fusion.service.processes import Children

    if not 1 <= chairs <= 50:
        fail(f"--chairs {chairs}: expected 1 to 50")
    if not duration_s > 0:
        fail(f"--duration {duration_s!r}: expected > 0")
    try:
        names = [check_name(f"{prefix}{k}", "--prefix") for k in range(1, chairs + 1)]
        for ep in [e for e in (router_listen, connect) if e]:
            check_loopback([ep], "fleet")
    except (ValueError, ZenohConfigError) as e:
        fail(str(e))
    wd = workdir or Path(tempfile.mkdtemp(prefix="armfusion-fleet-"))
    router = connect or router_listen or f"tcp/127.0.0.1:{free_loopback_port()}"
    stop = threading.Event()
    with Children(wd) as ch, stop_on_signals(stop):
        if connect is None:
            r = ch.start("router", ["router", "--listen", router], stdout=False)
            if not r.wait_for_line("listening", 30.0):
                fail(f"the router did not start on {router}: {r.stderr_tail()}")
        # every node at once: the drivers wait (--wait) until their fusion node subscribes
        serves = [ch.start(f"serve-{n}", ["serve", "--config", config, "--robot", n, "--mode", "client",
                                          "--connect", router, "--json"]) for n in names]
        drivers = [ch.start(f"drivers-{n}", [
            "drivers", "--fake", "--realtime", "--config", config, "--scenario", scenario,
            "--seed", str(seed + k), "--duration", str(duration_s), "--rate", str(rate_hz), "--robot", n,
            "--mode", "client", "--connect", router, "--wait", "120", "--json",
            *(["--realistic"] if realistic else [])])
            for k, n in enumerate(names, 1)]
        for n, s in zip(names, serves, strict=True):
            if not s.wait_for_line("serving", 120.0):
                fail(f"{n}'s fusion node did not start: {s.stderr_tail()}")
        err_console.print(f"fleet of {chairs} chairs ({', '.join(names)}) through the router at "
                          f"{router}; watch: armfusion monitor --connect {router}; Ctrl-C stops",
                          highlight=False)
        while not stop.is_set() and any(d.running for d in drivers):
            stop.wait(0.2)
        ch.stop_all(children=drivers)
        time.sleep(0.5)  # the fusion nodes take the last batches
        ch.stop_all(children=serves)
    console.print(f"fleet stopped; outputs in {wd}", highlight=False)

def monitor_command(
    robot: Annotated[list[str] | None, typer.Option(
        "--robot", help="Show only this robot (repeatable; default: every robot heard).")] = None,
    duration_s: Annotated[float | None, typer.Option(
        "--duration", help="Stop after this long, in s (default: at SIGINT; with --once: 3 s).")] = None,
    once: Annotated[bool, typer.Option("--once", help="Listen for --duration (or until --expect "
                                       "robots have sent their state), print one table, exit.")] = False,
    expect: Annotated[int | None, typer.Option(
        "--expect", help="Stop as soon as this many robots have sent their state (a joint state "
                         "and a heading).")] = None,
    refresh_hz: Annotated[float, typer.Option("--refresh-hz", help="Live table refreshes per s.")] = 4.0,
    zenoh_config: ZenohConfigOpt = None,
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """A live table of every robot: joints (deg, sigma, flags), heading, node states,
    samples and drops, age of the last update. Subscribes armfusion/*/state/*, status and
    the liveliness tokens."""
    from armfusion.fusion.service.monitor import Monitor, render, snapshot_json
    from rich.live import Live

    if duration_s is not None and not duration_s > 0:
        fail(f"--duration {duration_s!r}: expected > 0")
    if expect is not None and expect < 1:
        fail(f"--expect {expect!r}: expected >= 1")
    if not refresh_hz > 0:
        fail(f"--refresh-hz {refresh_hz!r}: expected > 0")
    if once and duration_s is None:
        duration_s = 3.0
    if connect and mode is None:
        mode = "client"  # a consumer attached to a router (or to a node): routers forward to clients
    live_view = not (once or json_out)
    stop = threading.Event()
    with session_or_exit(zenoh_settings(zenoh_config, listen, connect, mode)) as session, \
            stop_on_signals(stop):
        try:
            mon = Monitor(session, tuple(robot or ()))
        except ValueError as e:
            fail(str(e))
        deadline = None if duration_s is None else time.monotonic() + duration_s

        def done() -> bool:
            return stop.is_set() or (deadline is not None and time.monotonic() >= deadline) or \
                (expect is not None and mon.with_state() >= expect)

        if live_view:
            with Live(render(mon), console=console, refresh_per_second=refresh_hz) as live:
                while not done():
                    stop.wait(1.0 / refresh_hz)
                    live.update(render(mon))
        else:
            while not done():
                stop.wait(0.05)
        doc = snapshot_json(mon)
        mon.close()
    if json_out:
        emit_json(doc)
    elif once:
        console.print(render(mon))


COMMAND_TABLE = (
    ("router", router_command),
    ("fleet", fleet_command),
    ("monitor", monitor_command),
)
"""The fleet's commands: each command's name and its function."""


def register(app: typer.Typer) -> None:
    """Add the commands of :data:`COMMAND_TABLE` to ``app``."""
    for name, command in COMMAND_TABLE:
        app.command(name)(command)
