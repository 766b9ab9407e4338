"""Soak test of the fusion node: four link accelerometers, the IMU and the encoders at 200 Hz,
in real time through Zenoh on 127.0.0.1, to ``armfusion serve`` running as its own process.

Measures what a deployment cares about: samples lost (published but never received, or
dropped), joint states missing (an instant after the startup calibration without one), the
sample -> estimate latency (from the moment the last sensor's message of an instant is put
to the moment its joint state arrives back: Zenoh both ways, decoding, the reorder stage
and the tracker), and the node's CPU use. The scenario is the WMRA's daily use (still
for 15 s, then reaching while the chair drives). Run it niced on a shared machine::

    nice python tools/soak.py --duration 60 --write

``--write`` replaces the ``soak-<rate>hz-<batch>ms`` section of docs/benchmarks.md; ``--json`` prints the
figures, which ``--from-json FILE --write`` renders later without running again.

``--cpu-hog`` keeps every core busy beside the node while the stream is published: one
process per core spinning, started with the publishing and stopped with it by the tool (and
each ends by itself after the stream's duration and 30 s, whatever happens to the tool).
The figures then add what the node's lateness policy did (its status's ``degraded`` and
``lag_ms`` as they came, the instants it folded) and the genuine batches it refused; the
section is ``soak-<rate>hz-<batch>ms-cpu-hog``.

``--hostile HZ`` runs a second publisher beside the real one, in its own process and Zenoh session:
``HZ`` times a second it sends one payload of each hostile case and the earlier hostile
input (:data:`HOSTILE_CASES`: garbage bytes, another schema version, NaN, another robot,
deep nesting, an oversized payload, 3 encoder channels, a batch 10⁶ s ahead, counts of
2⁶³ − 1, a 174° encoder jump, an unknown sensor, a plausible accelerometer sample with
an invented ``seq``, 2,000 plausible samples 0.1 ms apart, one accelerometer sample stamped
1.9 s ahead of the real stream (inside the 2 s window the sensors' clock once allowed), and
one numbered -1) on the node's raw keys. The figures then add what the node refused by
reason, how far every joint state is from the truth in its own sigma, and the share of the
real instants whose joint state came on time (within :data:`ON_TIME_S` of its samples being
put); the section is ``soak-<rate>hz-<batch>ms-hostile``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.fusion.service import payloads as pl  # noqa: E402
from armfusion.fusion.service.zenoh_config import ZenohSettings, open_session  # noqa: E402
from armfusion.models.simulator import angle_truth, simulate  # noqa: E402
from armfusion.sensors.samples import Stream  # noqa: E402

from tools.benchdoc import machine_line, write_section  # noqa: E402

ROBOT = "soak"
BASELINE_ROBOT = "soak-baseline"
"""The robot name the baseline's node serves (``--baseline``): its own keys, the same stream."""
CAUGHT_UP_S = 0.05
"""A joint state this soon after its samples were put: the node has caught up with the stream."""
ON_TIME_S = 0.1
"""A joint state this soon after its samples were put is on time (the latency target's p99)."""
START_S = 900.0
"""A node subscribes within this (it first readies its tracker kernels: minutes on a busy
machine with a cold cache)."""
STOP_S = 600.0
"""A node stops within this (it first drains its receive channel: a node far behind takes long)."""
HOG_GRACE_S = 30.0
"""A CPU hog ends by itself this long after the stream's duration, whatever the tool does."""


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _commit(root: Path = ROOT) -> str:
    """The commit measured, marked ``+changes`` when fusion/ or models/ differ from it; a
    folder that is no git checkout (an exported tree) is named by its path."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "fusion", "models"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown" if root == ROOT else str(root)
    return head + (" +changes" if dirty else "")


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Joints:
    """Arrival time (monotonic), sample time, angles and sigmas of every joint state."""

    def __init__(self, session: zenoh.Session, robot: str = ROBOT):
        self.lock = threading.Lock()
        self.t_s: list[float] = []
        self.wall_s: list[float] = []
        self.q_rad: list[tuple[float, ...]] = []
        self.sigma_rad: list[tuple[float, ...]] = []
        self.sub = session.declare_subscriber(pl.joints_key(robot), self)

    def __call__(self, sample: zenoh.Sample) -> None:
        now = time.monotonic()
        js = pl.decode(str(sample.key_expr), sample.payload.to_bytes())
        with self.lock:
            self.t_s.append(js.t_s)
            self.wall_s.append(now)
            self.q_rad.append(js.q_rad)
            self.sigma_rad.append(js.sigma_rad)

    def last_t(self) -> float:
        with self.lock:
            return self.t_s[-1] if self.t_s else -np.inf


HOSTILE_CASES = ("garbage", "version_3", "nan", "other_robot", "nested", "oversized", "enc_3_channels",
                 "acc_1e6_s_ahead", "enc_2_63", "enc_jump_174_deg", "unknown_sensor", "invented_seq", "dense",
                 "acc_1_9_s_ahead", "seq_minus_1")
"""What the hostile publisher sends, one of each per cycle; ``invented_seq`` is a plausible
sample (the node accepts it: it could be real) whose ``seq`` jumps by 10⁹;
``acc_1_9_s_ahead`` one acc1 sample 1.9 s ahead of the real stream's latest."""


class Hostile:
    """A second publisher on the node's raw keys, in a process and a Zenoh session of its own
    (as an attacker would be: its work and its blocking puts do not hold up the real publisher
    or the soak's clock): every ``1/hz`` s one payload of each of :data:`HOSTILE_CASES`, made
    from the real stream's latest samples (:meth:`saw` tells it, through shared memory),
    seeded. :attr:`sent` counts what it put, by case."""

    def __init__(self, endpoint: str, streams: dict[str, Stream], hz: float, seed: int,
                 counts_per_rad: np.ndarray):
        ctx = multiprocessing.get_context("spawn")
        self._latest = {k: ctx.Array("d", 1 + streams[k].values.shape[1]) for k in ("enc", "acc1")}
        for a in self._latest.values():
            a[0] = np.nan
        self._sent = ctx.Array("q", len(HOSTILE_CASES))
        self._stop = ctx.Event()
        meta = {k: (s.kind, s.channels) for k, s in streams.items()}
        cpr = np.asarray(counts_per_rad, float)
        self._proc = ctx.Process(target=_hostile_main, daemon=True, args=(
            endpoint, meta, hz, seed, cpr, self._latest, self._sent, self._stop))

    def saw(self, name: str, t_s: float, counts: np.ndarray) -> None:
        a = self._latest.get(name)
        if a is not None:
            with a.get_lock():
                a[1:] = [float(c) for c in counts]
                a[0] = t_s

    def start(self) -> None:
        self._proc.start()

    def stop(self) -> None:
        self._stop.set()
        self._proc.join(30.0)
        if self._proc.is_alive():
            self._proc.kill()

    @property
    def sent(self) -> dict[str, int]:
        return dict(zip(HOSTILE_CASES, self._sent[:], strict=True))


def _hostile_main(endpoint, meta, hz, seed, cpr, latest, sent, stop) -> None:
    settings = ZenohSettings(listen=["tcp/127.0.0.1:0"], connect=[endpoint])
    with open_session(settings) as session:
        _HostileLoop(session, meta, hz, seed, cpr, latest, sent, stop).run()


class _HostileLoop:
    """The hostile process's loop (see :class:`Hostile`)."""

    def __init__(self, session, meta, hz, seed, cpr, latest, sent, stop):
        self.session, self.meta, self.period_s = session, meta, 1.0 / hz
        self.rng = np.random.default_rng(seed)
        self.cpr, self.latest, self.sent, self.stop = cpr, latest, sent, stop

    def _last(self, name: str) -> tuple[float, np.ndarray]:
        a = self.latest[name]
        with a.get_lock():
            values = a[:]
        return values[0], np.array(values[1:], dtype=np.int64)

    def _batch(self, name: str, t_s: float, counts, seq: int, channels=None) -> dict:
        kind, all_channels = self.meta[name]
        part = Stream(name, kind, np.atleast_1d(np.asarray(t_s, float)),
                      np.atleast_2d(np.asarray(counts, dtype=np.int64)),
                      channels or all_channels)
        return pl.RawBatch(ROBOT, part, seq).to_json()

    def _payloads(self, k: int) -> list[tuple[str, str, bytes]]:
        t_enc, enc = self._last("enc")
        t_acc, acc = self._last("acc1")
        if not (np.isfinite(t_enc) and np.isfinite(t_acc)):
            return []
        enc_ch = self.meta["enc"][1]
        jumped = enc.copy()
        jumped[0] += int(np.radians(174.0) * self.cpr[0])
        v3 = self._batch("acc1", t_acc + 1e-3, acc, k)
        v3["v"] = 3
        other = self._batch("acc1", t_acc + 1e-3, acc, k)
        other["robot"] = "chair9"
        nan = self._batch("acc1", t_acc + 1e-3, acc, k)
        nan["values"][0][0] = float("nan")
        unknown = self._batch("acc1", t_acc + 1e-3, acc, k)
        unknown["sensor"], unknown["channels"] = "acc9", ["acc9_x", "acc9_y", "acc9_z"]
        cases = {
            "garbage": ("acc1", self.rng.bytes(int(self.rng.integers(1, 400)))),
            "version_3": ("acc1", json.dumps(v3).encode()),
            "nan": ("acc1", json.dumps(nan).encode()),  # (Python writes NaN)
            "other_robot": ("acc1", json.dumps(other).encode()),
            "nested": ("enc", b'{"v":2,"type":"raw","values":' + b"[" * 20000 + b"]" * 20000 + b"}"),
            "oversized": ("imu_acc", b" " * (pl.MAX_PAYLOAD_BYTES + 1)),
            "enc_3_channels": ("enc", json.dumps(self._batch("enc", t_enc + 1e-3, enc[:3], 10**9,
                                                             enc_ch[:3])).encode()),
            "acc_1e6_s_ahead": ("acc1", json.dumps(self._batch("acc1", t_acc + 1e6, acc, k)).encode()),
            "enc_2_63": ("enc", json.dumps(self._batch("enc", t_enc + 1e-3, np.full(len(enc), 2**63 - 1),
                                                       10**9)).encode()),
            "enc_jump_174_deg": ("enc", json.dumps(self._batch("enc", t_enc + 1e-3, jumped, 10**9)).encode()),
            "unknown_sensor": ("acc9", json.dumps(unknown).encode()),
            "invented_seq": ("acc1", json.dumps(self._batch("acc1", t_acc + 1e-3, acc, 10**9 + k)).encode()),
            "dense": ("acc1", json.dumps(self._batch(
                "acc1", t_acc + 1e-3 + 1e-4 * np.arange(2000), np.tile(acc, (2000, 1)), k)).encode()),
            "acc_1_9_s_ahead": ("acc1", json.dumps(self._batch("acc1", t_acc + 1.9, acc, k)).encode()),
            "seq_minus_1": ("acc1", json.dumps(self._batch("acc1", t_acc + 1e-3, acc, -1)).encode()),
        }
        return [(case, name, data) for case, (name, data) in cases.items()]

    def run(self) -> None:
        k, next_t = 0, time.monotonic()
        while not self.stop.wait(max(0.0, next_t - time.monotonic())):
            next_t += self.period_s
            for case, name, data in self._payloads(k):
                # blocking, as the real publisher: a dropped hostile payload would blur the count
                self.session.put(pl.raw_key(ROBOT, name), data,
                                 congestion_control=zenoh.CongestionControl.BLOCK)
                self.sent[HOSTILE_CASES.index(case)] += 1
            k += 1


class Statuses:
    """Arrival time (monotonic), ``degraded`` and ``lag_ms`` of every status of the node."""

    def __init__(self, session: zenoh.Session, robot: str = ROBOT):
        self.lock = threading.Lock()
        self.seen: list[tuple[float, int, int]] = []
        self.sub = session.declare_subscriber(pl.status_key(robot), self)

    def __call__(self, sample: zenoh.Sample) -> None:
        now = time.monotonic()
        try:
            st = pl.decode(str(sample.key_expr), sample.payload.to_bytes())
        except pl.PayloadError:
            return
        c = dict(st.counters)
        with self.lock:
            self.seen.append((now, int(c.get("degraded", 0)), int(c.get("lag_ms", 0))))

    def summary(self, t0: float, t1: float) -> dict:
        """Statuses between wall times ``t0`` and ``t1``: how many said degraded, the
        largest lag they gave, and the wall time from the first saying so to the last."""
        with self.lock:
            seen = [x for x in self.seen if t0 <= x[0] <= t1]
        bad = [x for x in seen if x[1]]
        return {"statuses": len(seen), "degraded": len(bad),
                "lag_ms_max": max((x[2] for x in bad), default=0),
                "first_degraded_s": bad[0][0] - t0 if bad else None,
                "last_degraded_s": bad[-1][0] - t0 if bad else None}


def _spin(until_monotonic: float, stop) -> None:
    """A CPU hog: spin until ``stop`` is set or the monotonic clock passes ``until_monotonic``."""
    n = 0
    while not stop.is_set() and time.monotonic() < until_monotonic:
        for _ in range(10_000):
            n += 1


class CpuHog:
    """One spinning process per core (see the module's docstring), bounded in time."""

    def __init__(self, lasts_s: float):
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        until = time.monotonic() + lasts_s
        self._procs = [ctx.Process(target=_spin, args=(until, self._stop), daemon=True)
                       for _ in range(os.cpu_count() or 1)]

    def start(self) -> None:
        for p in self._procs:
            p.start()

    def stop(self) -> None:
        self._stop.set()
        for p in self._procs:
            p.join(10.0)
            if p.is_alive():
                p.kill()


def _z_scores(joints: Joints, truth: Stream, after_t_s: float) -> np.ndarray:
    """|estimate - truth| / sigma, per joint state (rows) and joint, for states after ``after_t_s``."""
    with joints.lock:
        t = np.array(joints.t_s)
        q, sig = np.array(joints.q_rad), np.array(joints.sigma_rad)
    if not t.size:
        return np.zeros((0, 1))
    keep = t > after_t_s
    t, q, sig = t[keep], q[keep], sig[keep]
    k = np.clip(np.searchsorted(truth.t_s, t + 1e-9) - 1, 0, len(truth) - 1)
    err = np.abs(np.angle(np.exp(1j * (q - truth.values[k]))))
    return err / sig


CHECKOUT_BOOT = """
import importlib.abc, importlib.machinery, importlib.util, os, runpy, sys
root = sys.argv.pop(1)
dirs = {"armfusion": "armfusion", "armfusion.fusion": "fusion", "armfusion.models": "models",
        "armfusion.sensors": "sensors", "armfusion.config": "config"}
class Checkout(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name not in dirs:
            return None
        d = os.path.join(root, dirs[name])
        init = os.path.join(d, "__init__.py")
        if os.path.exists(init):
            return importlib.util.spec_from_file_location(name, init, submodule_search_locations=[d])
        spec = importlib.machinery.ModuleSpec(name, None, is_package=True)
        spec.submodule_search_locations = [d]
        return spec
sys.meta_path.insert(0, Checkout())
runpy.run_module("armfusion.fusion.cli", run_name="__main__", alter_sys=True)
"""
"""Runs ``armfusion`` from the checkout given as its first argument: the layers' packages
mapped to that folder's ``fusion``, ``models``… ahead of any install (an editable install
of this checkout would otherwise be imported whatever the folder)."""


class ServeProcess:
    """``armfusion serve`` as its own process for ``robot``, listening on a port of its own,
    run from the checkout ``root`` (this one, or a baseline's: its packages imported from
    that folder, :data:`CHECKOUT_BOOT`)."""

    def __init__(self, robot: str, root: Path):
        self.robot, self.root, self.port = robot, root, _free_port()
        self.err_lines: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-c", CHECKOUT_BOOT, str(Path(root).resolve()), "serve", "--robot", robot,
             "--listen", f"tcp/127.0.0.1:{self.port}", "--publish-hz", "1000", "--json"],
            cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def wait_serving(self) -> None:
        """Keep reading its stderr (a full pipe would stall it); whether it serves is told by
        its subscriber (the publishers' matching status), however long its start takes."""
        threading.Thread(target=lambda: self.err_lines.extend(self.proc.stderr), daemon=True).start()

    def interrupt(self) -> None:
        self.proc.send_signal(signal.SIGINT)

    def report(self, timeout_s: float = STOP_S) -> dict:
        """Its summary once it stopped (a node behind drains what it received first)."""
        out, _ = self.proc.communicate(timeout=timeout_s)
        return json.loads(out)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()


def soak(duration_s: float, rate_hz: float, batch_s: float, seed: int, hostile_hz: float = 0.0,
         cpu_hog: bool = False, baseline: Path | None = None) -> dict:
    """The soak's figures; with ``baseline`` (a checkout of other code), a second node run
    from it beside this one on the same stream, its figures under ``"baseline"``: both
    nodes get the same samples at the same moments and share the machine (and the hog)."""
    arm = load_arm("wmra")
    rec, sim_truth = simulate(arm, "daily-use", duration_s, rate_hz, seed=seed)
    truth = angle_truth(rec.get("true_q"), sim_truth, arm.joint_names)
    streams = {k: s for k, s in rec.raw().items() if len(s)}
    nodes = [ServeProcess(ROBOT, ROOT)]
    if baseline is not None:
        nodes.append(ServeProcess(BASELINE_ROBOT, Path(baseline).resolve()))
    port = nodes[0].port
    try:
        for node in nodes:
            node.wait_serving()
        settings = ZenohSettings(listen=["tcp/127.0.0.1:0"],
                                 connect=[f"tcp/127.0.0.1:{n.port}" for n in nodes])
        with open_session(settings) as session:
            joints = [Joints(session, n.robot) for n in nodes]
            statuses = [Statuses(session, n.robot) for n in nodes]
            hog = CpuHog(duration_s + HOG_GRACE_S) if cpu_hog else None
            hostile = (Hostile(f"tcp/127.0.0.1:{port}", streams, hostile_hz, seed, arm.counts_per_rad)
                       if hostile_hz > 0 else None)
            if hostile is not None:  # (its process starts while the node waits for samples)
                hostile.start()
            pubs = [{k: session.declare_publisher(pl.raw_key(n.robot, k),
                                                  congestion_control=zenoh.CongestionControl.BLOCK)
                     for k in streams} for n in nodes]
            deadline = time.monotonic() + START_S
            while not all(p.matching_status.matching for ps in pubs for p in ps.values()):
                if time.monotonic() > deadline or any(n.proc.poll() is not None for n in nodes):
                    raise RuntimeError("armfusion serve did not subscribe: "
                                       + "".join(nodes[0].err_lines)[-2000:])
                time.sleep(0.05)
            # windows of batch_s: every sensor's samples in it go out as one message each
            t0 = min(s.t_s[0] for s in streams.values())
            edges = t0 + batch_s * np.arange(1, int(np.ceil(duration_s / batch_s)) + 2)
            cuts = {k: np.searchsorted(s.t_s, edges, side="left") for k, s in streams.items()}
            enc_t = streams["enc"].t_s
            put_wall = np.full(len(enc_t), np.nan)  # when the last message of its window went out
            enc_window = np.searchsorted(edges, enc_t, side="right")
            seq = dict.fromkeys(streams, 0)
            published = 0
            if hog is not None:
                hog.start()
            cpu0, wall0 = [_cpu_s(n.proc.pid) for n in nodes], time.monotonic()
            for w in range(len(edges)):
                delay = wall0 + (edges[w] - t0) - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                for k, s in streams.items():
                    i0 = int(cuts[k][w - 1]) if w else 0
                    i1 = int(cuts[k][w])
                    if i1 > i0:
                        part = Stream(k, s.kind, s.t_s[i0:i1], s.values[i0:i1], s.channels)
                        # (the nodes take turns to be sent to first)
                        for j in (range(len(nodes)) if w % 2 == 0 else reversed(range(len(nodes)))):
                            pubs[j][k].put(pl.encode(pl.RawBatch(nodes[j].robot, part, seq[k])))
                        seq[k] += 1
                        published += i1 - i0
                        if hostile is not None:
                            hostile.saw(k, float(s.t_s[i1 - 1]), s.values[i1 - 1])
                put_wall[enc_window == w] = time.monotonic()
            wall_pub = time.monotonic() - wall0
            cpu_pub = [_cpu_s(n.proc.pid) - c for n, c in zip(nodes, cpu0, strict=True)]
            if hog is not None:
                hog.stop()
            if hostile is not None:
                hostile.stop()
            # let the nodes finish (the reorder stage holds the newest 0.1 s until the stop)
            done_by = time.monotonic() + max(30.0, 2.0 * duration_s)
            walls_all, cpus_all = [], []
            for n, js, c in zip(nodes, joints, cpu0, strict=True):
                while js.last_t() < enc_t[-1] - 0.11 and time.monotonic() < done_by:
                    time.sleep(0.05)
                walls_all.append(time.monotonic() - wall0)
                cpus_all.append(_cpu_s(n.proc.pid) - c)
            time.sleep(0.2)
            status_seen = [st.summary(wall0, wall0 + wall_pub) for st in statuses]
        for n in nodes:
            n.interrupt()
        reports = [n.report() for n in nodes]
    finally:
        for n in nodes:
            n.kill()
    hostile_sent = hostile.sent if hostile is not None else {}
    common = {
        "hostile_hz": hostile_hz, "hostile_sent": hostile_sent, "cpu_hog": cpu_hog,
        "cpu_hog_processes": (os.cpu_count() or 1) if cpu_hog else 0,
        "duration_s": duration_s, "rate_hz": rate_hz, "batch_ms": 1e3 * batch_s,
        "sensors": sorted(streams), "published": published, "wall_publish_s": wall_pub,
        "load_average_1min": os.getloadavg()[0], "cores": os.cpu_count(),
        "tracker_instants_per_cpu_s": tracker_alone(rec),
    }
    read_wall = wall0 + (enc_t - t0)  # when each instant was sampled, on this clock (real time)
    figures = [{**common, **_node_figures(rep, js, st, truth, enc_t, put_wall, read_wall, published,
                                          hostile_sent, wall_pub, cp, wa, ca)}
               for rep, js, st, cp, wa, ca in zip(reports, joints, status_seen, cpu_pub, walls_all,
                                                   cpus_all, strict=True)]
    figures[0]["commit"] = _commit()
    if baseline is not None:
        figures[1]["commit"] = _commit(Path(baseline).resolve())
        figures[0]["baseline"] = figures[1]
    return figures[0]


def _node_figures(report: dict, joints: Joints, status_seen: dict, truth: Stream, enc_t: np.ndarray,
                  put_wall: np.ndarray, read_wall: np.ndarray, published: int, hostile_sent: dict,
                  wall_pub: float, cpu_pub: float, wall_all: float, cpu_all: float) -> dict:
    """One node's figures from what it reported and what its subscribers saw. ``put_wall``:
    when each instant's last message went out; ``read_wall``: when it was sampled (the
    stream runs in real time: the driver's batch wait is in the latency)."""
    if report["startup_t_s"] is None:
        raise RuntimeError(f"armfusion serve did not start tracking: {report['message']}")
    with joints.lock:
        got_t, got_wall = np.array(joints.t_s), np.array(joints.wall_s)
    startup_t = report["startup_t_s"]
    # (a node that published no joint state at all while the tool listened: every instant
    # after its startup is missing)
    last_t = got_t.max() if got_t.size else enc_t[-1]
    expected = enc_t[(enc_t > startup_t + 1e-9) & (enc_t <= last_t + 1e-9)]
    missing = int(len(np.setdiff1d(expected, got_t)))
    # latency in the steady state: from the moment a joint state first arrives within
    # CAUGHT_UP_S of its samples being put (before, the node waited for its startup
    # calibration, then fused the samples it had kept), for every instant put after it
    k = np.clip(np.searchsorted(enc_t, got_t), 0, len(enc_t) - 1)
    matched = np.abs(enc_t[k] - got_t) < 1e-9
    arrive, put = got_wall[matched], put_wall[k[matched]]
    lat = arrive - put
    up = np.flatnonzero(lat <= CAUGHT_UP_S)
    t_up = float(arrive[up[0]]) if up.size else np.inf
    lat_ms = 1e3 * (arrive - read_wall[k[matched]])[put >= t_up]  # sample time -> joint state
    first_put = float(np.nanmin(put_wall[enc_t >= startup_t]))
    catch_up_s = t_up - first_put if up.size else None
    in_time = np.zeros(len(enc_t), bool)  # instants whose joint state came within ON_TIME_S
    in_time[k[matched][lat <= ON_TIME_S]] = True
    after_up = (enc_t > startup_t + 1e-9) & (put_wall >= t_up)
    on_time_percent = float(100.0 * in_time[after_up].mean()) if after_up.any() else None
    # what a user meets: every instant after the catch-up, a joint state on time or not (a
    # folded instant has none: the user's latest is then the previous one); the age of the
    # newest joint state at each instant's put, plus the wait for the next
    fresh_ms = _staleness_ms(got_t, got_wall, enc_t, put_wall, read_wall, t_up)
    z = _z_scores(joints, truth, startup_t)
    accepted_hostile = hostile_sent.get("invented_seq", 0)
    return {
        "on_time_percent": on_time_percent, "status_seen": status_seen,
        "degraded_periods": report.get("degraded_periods"), "folded_instants": report.get("folded_instants"),
        "lag_max_ms": report.get("lag_max_ms"),
        "hostile_accepted": accepted_hostile,
        "sigma": {"n": int(z.shape[0]), "max_z": float(z.max()) if z.size else None,
                  "beyond_4_sigma": int((z > 4.0).any(axis=1).sum()),
                  "within_3_sigma_percent_worst_joint":
                      float(100.0 * (z <= 3.0).mean(axis=0).min()) if z.size else None},
        "seq_resets": report.get("seq_resets"), "stalls": report.get("stalls"),
        "errors": report.get("errors"),
        "received": report["samples"],
        "shed_batches": report.get("shed_batches", 0), "shed_samples": report.get("shed_samples", 0),
        "lost": published + accepted_hostile - report["samples"] - report.get("shed_samples", 0),
        "dropped": report["dropped"],
        "out_of_order": report["out_of_order"], "missed_batches": report["missed_batches"],
        "startup_t_s": startup_t,
        "estimates_expected": int(len(expected)), "estimates_received": int(len(np.unique(got_t))),
        "estimates_missing": missing, "catch_up_s": catch_up_s,
        "latency_ms": {"n": int(lat_ms.size), **({
            "p50": float(np.percentile(lat_ms, 50)), "p99": float(np.percentile(lat_ms, 99)),
            "max": float(lat_ms.max())} if lat_ms.size else {"p50": None, "p99": None, "max": None})},
        "staleness_ms": fresh_ms,
        "wall_total_s": wall_all,
        "serve_cpu_percent_while_publishing": 100.0 * cpu_pub / wall_pub,
        "serve_cpu_percent_overall": 100.0 * cpu_all / wall_all,
        "instants_per_serve_cpu_s": float(len(enc_t) / cpu_all) if cpu_all > 0 else None,
    }


def _staleness_ms(got_t, got_wall, enc_t, put_wall, read_wall, t_up: float) -> dict:
    """For every instant put after ``t_up``: how long from its sampling until a joint state
    of it or of a later instant arrived (a folded instant gets none of its own: the user
    waits for the next one). p50 / p99 / max in ms, over the instants that got one."""
    if not np.isfinite(t_up) or not len(got_t):
        return {"n": 0, "p50": None, "p99": None, "max": None}
    order = np.argsort(got_t, kind="stable")
    t_sorted, wall_sorted = got_t[order], got_wall[order]
    # the earliest arrival of a joint state of this instant or a later one
    first_after = np.minimum.accumulate(wall_sorted[::-1])[::-1]
    pick = (put_wall >= t_up) & np.isfinite(put_wall)
    idx = np.searchsorted(t_sorted, enc_t[pick] - 1e-9)
    ok = idx < len(t_sorted)
    wait = 1e3 * (first_after[idx[ok]] - read_wall[pick][ok])
    if not wait.size:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    return {"n": int(wait.size), "p50": float(np.percentile(wait, 50)),
            "p99": float(np.percentile(wait, 99)), "max": float(wait.max())}


def tracker_alone(rec, n_instants: int = 1000) -> float:
    """Instants per CPU-second of the tracker by itself (no Zenoh, no decoding), on the
    first ``n_instants`` after a startup calibration on the recording's first 3 s."""
    from armfusion.fusion.tracking.tracker import start_from_recording

    arm = load_arm("wmra")
    head = rec.between(-np.inf, rec.t_start_s + 3.0)
    tr, _ = start_from_recording(arm, head)
    names = [k for k in tr.sensor_names if rec.get(k) is not None]
    t = rec.get("enc").t_s
    idx = np.flatnonzero(t > tr.t_s + 1e-9)[:n_instants]
    values = {k: rec.get(k).values for k in names}
    c0 = time.process_time()
    for i in idx.tolist():
        tr.update_instant(t[i], {k: v[i] for k, v in values.items()})
    return float(len(idx) / (time.process_time() - c0))


def _side_by_side(r: dict) -> str:
    """This code's figures beside the baseline's (``--baseline``), same stream, same moments."""
    b = r["baseline"]

    def p(d: dict, key: str) -> float | None:
        return (d.get(key) or {}).get("p99")

    def refused(d: dict) -> int:
        return sum(v for k, v in d["dropped"].items() if k != "overflow")

    rows = [
        ("wait p99, every instant (ms)", p(r, "staleness_ms"), p(b, "staleness_ms")),
        ("latency p99 of the joint states (ms)", p(r, "latency_ms"), p(b, "latency_ms")),
        ("latency p50 of the joint states (ms)", r["latency_ms"]["p50"], b["latency_ms"]["p50"]),
        ("caught up after (s of wall time)", r["catch_up_s"], b["catch_up_s"]),
        ("largest lag (ms)", r["lag_max_ms"], b["lag_max_ms"]),
        ("degraded periods", r["degraded_periods"], b["degraded_periods"]),
        ("instants folded", r["folded_instants"], b["folded_instants"]),
        ("samples shed unread", r.get("shed_samples", 0), b.get("shed_samples", 0)),
        ("joint states missing", r["estimates_missing"], b["estimates_missing"]),
        ("instants per CPU-second of serve", r["instants_per_serve_cpu_s"], b["instants_per_serve_cpu_s"]),
        ("serve CPU while publishing (% of one core)", r["serve_cpu_percent_while_publishing"],
         b["serve_cpu_percent_while_publishing"]),
        ("genuine batches refused", refused(r), refused(b)),
    ]

    def cell(v) -> str:
        if v is None:
            return "none (never caught up)"
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    def ratio(a, c) -> str:
        return f"{a / c:.2f}" if isinstance(a, int | float) and isinstance(c, int | float) and c else "-"

    lines = "\n".join(f"| {name} | {cell(a)} | {cell(c)} | {ratio(a, c)} |" for name, a, c in rows)
    return (f"Side by side, in the same run: this code (commit {r.get('commit', 'unknown')}, robot "
            f"`{ROBOT}`) and the baseline (commit {b.get('commit', 'unknown')}, robot `{BASELINE_ROBOT}`), "
            "each a node of its own, sent the same batches at the same moments (taking turns to be "
            "first), sharing the machine and the hog.\n\n"
            f"| figure | this code | baseline | ratio |\n| --- | --- | --- | --- |\n{lines}\n\n"
            "The table above is this code's.\n\n")


def markdown(r: dict) -> str:
    lat = r["latency_ms"]
    wait = r.get("staleness_ms") or {"n": 0}
    target_ms = 100.0 if r.get("cpu_hog") else 10.0
    if lat["n"]:
        judged = wait if wait["n"] else lat
        ok_lat = "this run meets it" if judged["p99"] <= target_ms else "this run misses it"
        lat_text = f"{lat['p50']:.1f} / {lat['p99']:.1f} / {lat['max']:.1f} ms (n = {lat['n']})"
    else:
        ok_lat = "this run never caught up, so it has no figure"
        lat_text = "none: the node never caught up with the stream"
    wait_text = (f"{wait['p50']:.1f} / {wait['p99']:.1f} / {wait['max']:.1f} ms (n = {wait['n']})"
                 if wait["n"] else "none")
    rows = [
        ("samples published / received / shed unread while behind (batches)",
         f"{r['published']} / {r['received']} / {r.get('shed_samples', 0)} ({r.get('shed_batches', 0)})"),
        ("samples lost / dropped / late",
         f"{r['lost']} / {sum(r['dropped'].values())} / {r['out_of_order']}"),
        ("batches the node saw missing (seq gaps)", f"{r.get('missed_batches', 'not counted')}"),
        ("joint states expected / missing", f"{r['estimates_expected']} / {r['estimates_missing']}"),
        ("startup calibration at (sample time)", f"{r['startup_t_s']:.2f} s"),
        ("caught up (a joint state within 50 ms of its samples) after",
         "never" if r["catch_up_s"] is None else f"{r['catch_up_s']:.2f} s of wall time"),
        ("latency, a sample's time -> its joint state, once caught up, p50 / p99 / max", lat_text),
        ("wait, a sample's time -> a joint state of it or a later instant (every instant, folded "
         "ones too), p50 / p99 / max", wait_text),
        ("serve CPU while publishing / overall",
         f"{r['serve_cpu_percent_while_publishing']:.0f} % / "
         f"{r['serve_cpu_percent_overall']:.0f} % of one core"),
        ("instants per CPU-second of serve", f"{r['instants_per_serve_cpu_s']:.0f}"),
        ("wall time: publishing / until the last joint state",
         f"{r['wall_publish_s']:.1f} s / {r['wall_total_s']:.1f} s"),
    ]
    if r.get("degraded_periods") is not None:
        st = r.get("status_seen") or {}
        said = (f"{st['degraded']} of {st['statuses']}, lag up to {st['lag_ms_max']} ms, from "
                f"{st['first_degraded_s']:.1f} s to {st['last_degraded_s']:.1f} s"
                if st.get("degraded") else f"none of {st.get('statuses', 0)}")
        on_time = r.get("on_time_percent")
        rows += [
            ("the node degraded (periods) / instants folded / largest lag",
             f"{r['degraded_periods']} / {r['folded_instants']} / {r['lag_max_ms']} ms"),
            ("statuses saying degraded while publishing (wall time after the start)", said),
            (f"instants whose joint state came within {1e3 * ON_TIME_S:.0f} ms, once caught up",
             "none caught up" if on_time is None else f"{on_time:.1f} %"),
        ]
    if r.get("cpu_hog"):
        rows += [("processes spinning beside the node (one per core)", f"{r['cpu_hog_processes']}"),
                 ("genuine batches refused (no hostile publisher: every refusal)",
                  f"{sum(v for k, v in r['dropped'].items() if k != 'overflow')}"
                  + (f" ({', '.join(f'{k} {v}' for k, v in sorted(r['dropped'].items()))})"
                     if r["dropped"] else ""))]
    sig = r.get("sigma")
    if sig and sig["n"]:
        rows += [
            ("joint states beyond 4 sigma of the truth (any joint) / largest error in sigmas",
             f"{sig['beyond_4_sigma']} of {sig['n']} / {sig['max_z']:.2f}"),
            ("joint states within 3 sigma, the worst joint",
             f"{sig['within_3_sigma_percent_worst_joint']:.1f} %"),
            ("stalls / errors in the node", f"{r.get('stalls')} / {r.get('errors')}"),
        ]
    if r.get("hostile_hz"):
        sent = r["hostile_sent"]
        rows += [
            ("hostile payloads sent (one of each case per cycle)",
             f"{sum(sent.values())} ({r['hostile_hz']:g} cycles a second; {len(sent)} cases)"),
            ("refused by the node, by reason",
             ", ".join(f"{k} {v}" for k, v in sorted(r["dropped"].items()))),
            ("hostile samples accepted (plausible, invented seq) / publisher sessions seen (seq_resets)",
             f"{r['hostile_accepted']} / {r.get('seq_resets')}"),
        ]
    need = 100.0 * r["rate_hz"] / r["instants_per_serve_cpu_s"]
    msgs_per_s = len(r["sensors"]) * min(r["rate_hz"], 1000.0 / r["batch_ms"])
    per_msg = max(1.0, r["rate_hz"] * r["batch_ms"] / 1000.0)
    tracker_share = 100.0 * r["instants_per_serve_cpu_s"] / r["tracker_instants_per_cpu_s"]
    folded = (f"; here {r['folded_instants']} instants, so the tracker's share above counts updates it "
              "did not all make" if r.get("folded_instants") else "")
    table = "| figure | value |\n| --- | --- |\n" + "\n".join(f"| {a} | {b} |" for a, b in rows)
    busy = " with every core busy" if r.get("cpu_hog") else ""
    title = f"Soak: the fusion node at {r['rate_hz']:.0f} Hz, {r['batch_ms']:.0f} ms batches, through Zenoh"
    if r.get("hostile_hz"):
        title += ", a hostile publisher beside the real one"
    if r.get("cpu_hog"):
        title += ", every core kept busy beside it"
    side = _side_by_side(r) if r.get("baseline") else ""
    return f"""## {title} (`tools/soak.py`)

{machine_line()}; commit {r.get('commit', 'unknown')}; load average
{r['load_average_1min']:.1f} during the run (a shared machine: other processes took CPU too).
`armfusion serve` as its own process on 127.0.0.1; the WMRA's daily use
({r['duration_s']:.0f} s: still for 15 s, then reaching while the chair drives);
{', '.join(r['sensors'])} at {r['rate_hz']:.0f} Hz, every sensor's samples of each
{r['batch_ms']:.0f} ms sent as one message (about {per_msg:.0f} sample(s) each), in real time.

{table}

{side}The p99 target (on the wait, every instant counted) is {target_ms:.0f} ms{busy}: {ok_lat}.
To keep up, the node needs
{need:.0f} % of one core ({r['rate_hz']:.0f} instants a second at {r['instants_per_serve_cpu_s']:.0f}
per CPU-second); it got {r['serve_cpu_percent_while_publishing']:.0f} % on this shared machine. The
tracker alone does {r['tracker_instants_per_cpu_s']:.0f} instants per CPU-second on the same
samples, so it takes {tracker_share:.0f} % of the node's CPU; Zenoh's receive threads (about
{msgs_per_s:.0f} messages a second), decoding, the reorder stage, publishing and the startup
calibration take the rest. Latency runs from an instant's sample time (the stream is sent in
real time: a sample first waits up to one batch, {r['batch_ms']:.0f} ms, in the driver) to its joint
state's arrival at a subscriber, over the instants sent after the node caught up (before, it waits
for its startup calibration, then fuses the samples it kept); the wait counts every instant, also
one the node folded (it has no joint state of its own: a user waits for the next). A node that
needs more than one CPU-second per
{r['rate_hz']:.0f} instants cannot keep up one instant at a time: it degrades (docs/service-node.md,
"When the node falls behind": it folds the instants more than 50 ms behind, one update per
20 ms of them{folded}). If taking the messages in alone costs more than it gets, it sheds
unread, of what waited more than 0.5 s in its receive channel, all but each sensor's newest
(counted: `shed_samples`), so that its lag stays bounded; what it cannot even receive (Zenoh's
own threads starved) waits in Zenoh and counts in its lag.
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0, help="Seconds of data (real time).")
    ap.add_argument("--rate", type=float, default=200.0, help="Every sensor's rate, Hz.")
    ap.add_argument("--batch-ms", type=float, default=5.0, help="Sample time per message, ms.")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--hostile", type=float, default=0.0, metavar="HZ",
                    help="Cycles a second of a hostile publisher beside the real one (0: none).")
    ap.add_argument("--cpu-hog", action="store_true",
                    help="Keep every core busy beside the node while publishing (one spinning process each).")
    ap.add_argument("--baseline", type=Path, metavar="DIR",
                    help="A checkout of other code (e.g. main's HEAD) whose node runs beside this one's "
                         "on the same stream; the section then shows both, side by side.")
    ap.add_argument("--write", action="store_true", help="Write the soak section of docs/benchmarks.md.")
    ap.add_argument("--json", action="store_true", help="Print the figures as JSON.")
    ap.add_argument("--from-json", type=Path, help="Render the figures of an earlier --json run "
                                                     "instead of running again.")
    args = ap.parse_args(argv)
    if args.from_json is not None:
        r = json.loads(args.from_json.read_text())
    else:
        r = soak(args.duration, args.rate, args.batch_ms / 1000.0, args.seed, args.hostile, args.cpu_hog,
                 args.baseline)
    print(json.dumps(r, indent=2) if args.json else markdown(r))
    if args.write:
        section = "soak-{:.0f}hz-{:.0f}ms".format(r["rate_hz"], r["batch_ms"])
        if r.get("hostile_hz"):
            section += "-hostile"
        if r.get("cpu_hog"):
            section += "-cpu-hog"
        print(f"wrote {write_section(section, markdown(r))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
