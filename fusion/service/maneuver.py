"""The planned self-calibration maneuver, served: ``armfusion serve --maneuver M.yaml``.

armfusion never moves the arm. The fusion node publishes the plan (``armfusion plan-maneuver``'s
file, checked against the arm's limits and the unlock move's safety bounds when the node
starts) on ``armfusion/<robot>/maneuver`` for the arm's controller, and answers four
requests there (:class:`ManeuverEndpoint`, the Zenoh side):

- ``maneuver/start``: the controller is about to play it. From then on the node keeps every
  raw sample it accepts (the tracker goes on as before), at most the plan's duration and a
  half plus ``overrun_s`` of sample time: a run that goes on longer is dropped, saying so.
- ``maneuver/done``: the controller has played it. The node writes the kept samples as an
  armfusion MCAP recording, counts the plan's poses the encoders saw held (the encoders are
  relative, so a pose counts when the joints' moves between the still stretches are the
  plan's, within ``pose_tolerance_deg``), and, when at least half were, runs
  ``armfusion calibrate sensors`` on the recording in a child process at a lower priority
  (the tracker keeps its core), with the installer's one-time references if the node was
  given them. The fit's result comes as the next state on ``armfusion/<robot>/maneuver``:
  ``calibrated`` with the written config, or ``failed`` with the fit's own message.
- ``maneuver/abort``: drop what was kept (or stop the fit).
- ``maneuver/apply``: track with the calibrated config from now on. The written config is
  not applied by itself: a person reviews a calibration before the arm relies on it
  (``armfusion diagnose`` on the same recording shows what the fit left), then asks. The
  node checks that the config is this arm's (:func:`same_arm_problem`) and runs a startup
  calibration with it on the still arm (refused while the arm moves), and the tracker
  goes on from it (``applied``). Restarting the node with ``serve --config`` does the same.

Every state change is published; the status's message carries the state too.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.service import payloads as pl
from armfusion.fusion.service.processes import armfusion_argv
from armfusion.fusion.service.reorder import merge_batches
from armfusion.fusion.startup.static import StaticDetectionSettings, find_static_segments
from armfusion.models.arm import ArmModel
from armfusion.models.arm_config import ConfigError
from armfusion.models.sensor_models import ENCODER_STREAM, stream_models
from armfusion.models.trajectories.planned import PlannedManeuver
from armfusion.sensors.recording_mcap import write_mcap
from armfusion.sensors.samples import Recording, Stream

log = logging.getLogger("armfusion.service")

MAX_KEPT_SAMPLES = 2_000_000
"""At most this many samples are kept for one run, whatever the sensors' rates (a 60 s plan
at 200 Hz of nine sensors is about 110,000)."""


@dataclass(frozen=True)
class ManeuverSettings:
    """How the node serves a planned maneuver.

    ``out_dir``: where the kept recording and the calibrated config are written;
    ``effects`` and ``references``: ``calibrate sensors``' ``--effects`` and ``--reference``
    (``None``: the config's effects, else all); ``overrun_s``: how much longer than a plan and
    a half a run may go on; ``pose_tolerance_deg``: how far a held pose may be from the
    plan's; ``still_s``: how long the encoders must hold for a pose to count;
    ``fit_timeout_s``: a fit still running after this long (wall time) is stopped."""

    out_dir: Path
    effects: str | None = None
    references: tuple[str, ...] = ()
    overrun_s: float = 30.0
    pose_tolerance_deg: float = 1.0
    still_s: float = 0.5
    fit_timeout_s: float = 1800.0

    def __post_init__(self):
        for name in ("overrun_s", "pose_tolerance_deg", "still_s", "fit_timeout_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v > 0):
                raise ValueError(f"ManeuverSettings.{name}: expected a positive number, got {v!r}")


def still_poses_rad(arm: ArmModel, rec: Recording, still_s: float) -> np.ndarray:
    """The joint angles (relative to the encoders' first sample, rad) held over each still
    stretch of at least ``still_s`` seconds (the startup's still detector,
    :func:`armfusion.fusion.startup.static.find_static_segments`, over that window): ``(S, n)``."""
    enc = rec.get(ENCODER_STREAM)
    segs = find_static_segments(rec, StaticDetectionSettings(window_s=still_s, min_duration_s=still_s),
                                stream_models(arm))
    held = [enc.between(g.t_start_s, g.t_end_s).values for g in segs]
    held = [np.mean(v, axis=0) for v in held if len(v)]
    if not held:
        return np.zeros((0, arm.n_joints))
    return (np.array(held) - np.asarray(enc.values[0], float)) / arm.counts_per_rad


def poses_reached(plan: PlannedManeuver, held_rad: np.ndarray, tolerance_rad: float) -> int:
    """How many of ``plan``'s poses are among the ``held_rad`` stretches (angles relative to an
    unknown start, as incremental encoders give them): the most poses matched by one offset,
    each offset tried being a held stretch less a planned pose."""
    best = 0
    P = plan.poses_rad
    for h in held_rad:
        for p in P:
            offset = h - p  # the angle the encoders count from, if stretch h is pose p
            d = np.abs((held_rad - offset)[:, None, :] - P[None, :, :]).max(axis=2)  # (S, K)
            best = max(best, int(np.sum(np.any(d <= tolerance_rad, axis=0))))
    return best


class ServedManeuver:
    """One planned maneuver served by one fusion node: the plan, the run's kept samples and the
    fit's child process. Called from the node's loop only (not thread-safe)."""

    def __init__(self, arm: ArmModel, robot: str, plan: PlannedManeuver, config_path: Path,
                 settings: ManeuverSettings):
        self.arm, self.robot, self.plan = arm, robot, plan
        self.config_path = Path(config_path)
        self.settings = settings
        self.state = "ready"
        self.message = (f"the plan ({len(plan.poses_rad)} poses, {plan.duration_s:.1f} s) waits for the "
                        f"arm's controller: query {pl.maneuver_key(robot, 'start')} before playing it")
        self._kept: dict[str, list[Stream]] = {}
        self._n_kept = 0
        self._t0: float | None = None
        self._t1: float | None = None
        self._reached: int | None = None
        self._recording = ""
        self._config = ""
        self._fit: subprocess.Popen | None = None
        self._fit_started = 0.0
        self._fit_out: Path | None = None
        self._cfg_path: Path | None = None
        self._fit_err: Path | None = None
        self.version = 0  # bumped on every state change: the node publishes then

    @property
    def max_run_s(self) -> float:
        return 1.5 * self.plan.duration_s + self.settings.overrun_s

    def payload(self, accepted: bool = True, message: str | None = None) -> pl.Maneuver:
        return pl.Maneuver(self.robot, self.state, accepted, self.message if message is None else message,
                           self.plan, self._t0, self._t1, self._reached, self._recording, self._config)

    def _set(self, state: str, message: str) -> None:
        self.state, self.message = state, message
        self.version += 1
        log.info("serve: maneuver %s: %s", state, message)

    # -- the requests ----------------------------------------------------------------------------
    def request(self, action: str | None, joints_note: str = "") -> pl.Maneuver:
        """The reply to a query on the maneuver's key (``None``: what it is now) or on one of
        its requests (``start``, ``done``, ``abort``; ``apply`` is the node's:
        :class:`ManeuverEndpoint`)."""
        if action is None:
            return self.payload()
        if action == "start":
            if self.state in ("recording", "fitting"):
                return self.payload(False, f"refused: the maneuver is {self.state} already; abort it first")
            self._clear()
            self._set("recording", "keeping every sample until the controller queries "
                                   f"{pl.maneuver_key(self.robot, 'done')} (at most {self.max_run_s:.0f} s)"
                      + (f"; {joints_note}" if joints_note else ""))
            return self.payload()
        if action == "done":
            if self.state != "recording":
                return self.payload(False, "refused: nothing is being recorded (the maneuver is "
                                           f"{self.state})")
            self._finish_run()
            return self.payload()
        if action == "abort":
            if self.state not in ("recording", "fitting"):
                return self.payload(False, f"refused: nothing to abort (the maneuver is {self.state})")
            was = self.state
            self._stop_fit()
            self._clear()
            self._set("ready", f"aborted while {was}: nothing kept; the plan waits again")
            return self.payload()
        return self.payload(False, f"refused: unknown request {action[:20]!r}")

    @property
    def config_written(self) -> str:
        """The calibrated config's path, once the fit wrote it (else empty)."""
        return self._config

    def applied(self, message: str) -> pl.Maneuver:
        """The node tracks with the written config now (``maneuver/apply`` done)."""
        self._set("applied", message)
        return self.payload()

    def _clear(self) -> None:
        self._kept, self._n_kept = {}, 0
        self._t0 = self._t1 = None
        self._reached = None
        self._recording = self._config = ""

    # -- the run ---------------------------------------------------------------------------------
    def keep(self, stream: Stream) -> None:
        """An accepted raw batch: kept while recording, within the run's bounds."""
        if self.state != "recording" or not len(stream):
            return
        t_first, t_last = float(stream.t_s[0]), float(stream.t_s[-1])
        self._t0 = t_first if self._t0 is None else min(self._t0, t_first)
        self._t1 = t_last if self._t1 is None else max(self._t1, t_last)
        self._n_kept += len(stream)
        if self._t1 - self._t0 > self.max_run_s or self._n_kept > MAX_KEPT_SAMPLES:
            span = self._t1 - self._t0
            self._clear()
            self._set("failed", f"the run went on for {span:.0f} s of sample time, more than the "
                                f"{self.max_run_s:.0f} s a {self.plan.duration_s:.0f} s plan may take "
                                f"(or more than {MAX_KEPT_SAMPLES:,} samples): nothing kept; start again")
            return
        self._kept.setdefault(stream.name, []).append(stream)

    def clock_reset(self, sensor: str) -> None:
        """A sensor's clock restarted (the admission said so): a run's kept samples would mix
        two clocks, so the run is dropped."""
        if self.state == "recording":
            self._clear()
            self._set("failed", f"{sensor}'s clock restarted during the run: nothing kept; start again")

    def _finish_run(self) -> None:
        rec = merge_batches(self._kept)
        self._kept = {}
        enc = rec.streams.get(ENCODER_STREAM)
        if enc is None or len(enc) < 2:
            self._set("failed", "no encoder samples were kept between start and done: nothing to fit")
            return
        held = still_poses_rad(self.arm, rec, self.settings.still_s)
        self._reached = reached = poses_reached(self.plan, held, np.radians(self.settings.pose_tolerance_deg))
        k = len(self.plan.poses_rad)
        if 2 * reached < k:
            self._set("failed", f"the encoders saw {reached} of the plan's {k} poses held (within "
                                f"{self.settings.pose_tolerance_deg:g}°, {len(held)} still stretches): "
                                "not this plan played; nothing fitted")
            return
        out = self.settings.out_dir
        stamp = time.strftime("%Y%m%dT%H%M%S")
        rec_path = out / f"maneuver-{self.robot}-{stamp}.mcap"
        cfg_path = out / f"calibrated-{self.robot}-{stamp}.yaml"
        argv = ["calibrate", "sensors", str(rec_path), "--config", str(self.config_path),
                "--write", str(cfg_path), "--json"]
        if self.settings.effects:
            argv += ["--effects", self.settings.effects]
        for r in self.settings.references:
            argv += ["--reference", r]
        self._fit_out, self._fit_err = out / f"{rec_path.stem}.fit.json", out / f"{rec_path.stem}.fit.log"
        try:
            out.mkdir(parents=True, exist_ok=True)
            write_mcap(rec, rec_path, arm_config=self.config_path.name)
            self._recording = str(rec_path)
            with open(self._fit_out, "wb") as so, open(self._fit_err, "wb") as se:
                self._fit = subprocess.Popen(armfusion_argv(*argv), stdout=so, stderr=se,
                                             stdin=subprocess.DEVNULL, preexec_fn=_lower_priority)
        except OSError as e:
            self._set("failed", f"cannot write the run or start its fit in {out}: {str(e)[:200]}")
            return
        self._fit_started = time.monotonic()
        self._cfg_path = cfg_path
        self._set("fitting", f"{reached} of {k} poses held; {rec.duration_s:.1f} s kept in {rec_path}; "
                             f"armfusion calibrate sensors runs on it (pid {self._fit.pid})")

    def poll(self) -> None:
        """The fit's end, when it has ended (or its time is up)."""
        if self.state != "fitting" or self._fit is None:
            return
        rc = self._fit.poll()
        if rc is None:
            if time.monotonic() - self._fit_started > self.settings.fit_timeout_s:
                self._stop_fit()
                self._set("failed", f"the sensor fit ran past {self.settings.fit_timeout_s:.0f} s and was "
                                    f"stopped; the recording is kept: {self._recording}")
            return
        self._fit = None
        if rc == 0 and self._cfg_path is not None and self._cfg_path.is_file():
            self._config = str(self._cfg_path)
            self._set("calibrated", f"{_fit_summary(self._fit_out)}; wrote {self._cfg_path}: once reviewed, "
                                    f"query {pl.maneuver_key(self.robot, 'apply')} (or restart serve with "
                                    f"--config {self._cfg_path}) to track with it")
        else:
            self._set("failed", f"the sensor fit failed (exit {rc}): {_last_line(self._fit_err)}; "
                                f"the recording is kept: {self._recording}")

    def _stop_fit(self) -> None:
        if self._fit is not None and self._fit.poll() is None:
            self._fit.kill()
            self._fit.wait(10.0)
        self._fit = None

    def close(self) -> None:
        """The node stops: a running fit is stopped (its recording stays)."""
        if self.state == "fitting":
            self._stop_fit()
            self._set("failed", f"the fusion node stopped during the fit; the recording is kept: "
                                f"{self._recording}")


class ManeuverEndpoint:
    """A :class:`ServedManeuver` on the node's Zenoh session: a publisher of its state on
    ``armfusion/<robot>/maneuver`` and one queryable for that key and its requests. Queries
    are queued by Zenoh's thread and answered in the node's loop (:meth:`serve`), where
    ``apply()`` (the node's ``maneuver/apply``) and ``joints_note()`` (what the controller
    must know of the pose, for ``start``) run; a request that fails gets an error reply."""

    def __init__(self, session, maneuver: ServedManeuver, apply: Callable[[], pl.Maneuver],
                 joints_note: Callable[[], str]):
        self.maneuver, self._apply, self._joints_note = maneuver, apply, joints_note
        key = pl.maneuver_key(maneuver.robot)
        self._queries: queue.Queue = queue.Queue()
        self._published = -1  # the state's version last published
        self._pub = session.declare_publisher(key)
        self._queryable = session.declare_queryable(f"{key}/**", self._queries.put)

    def serve(self) -> bool:
        """Answer the queued queries, look at the fit, publish the state if it changed; True
        when it did (the status is due)."""
        m = self.maneuver
        for query in self._drain():
            self._answer(query)
        m.poll()
        if m.version == self._published:
            return False
        self._published = m.version
        self._pub.put(pl.encode(m.payload()))
        return True

    def _drain(self):
        while True:
            try:
                yield self._queries.get_nowait()
            except queue.Empty:
                return

    def _answer(self, query) -> None:
        m, key = self.maneuver, str(query.key_expr)
        base = pl.maneuver_key(m.robot)
        try:
            if key == base:
                reply = m.payload()
            elif key == pl.maneuver_key(m.robot, "apply"):
                reply = self._apply()
            elif key in {pl.maneuver_key(m.robot, a) for a in pl.MANEUVER_ACTIONS}:
                reply = m.request(key.rsplit("/", 1)[1], self._joints_note())
            else:
                query.reply_err(f"{key[:100]}: ask {base} or {base}/<{'|'.join(pl.MANEUVER_ACTIONS)}>")
                return
            query.reply(key, pl.encode(reply))
        except Exception as e:  # noqa: BLE001 - a request must never stop the node
            log.exception("serve: a maneuver request on %s failed", key[:100])
            query.reply_err(f"the request failed in the node: {type(e).__name__}: {str(e)[:200]}")
        finally:
            query.drop()

    def close(self) -> None:
        """The node stops: queued queries refused, a running fit stopped, the last state said."""
        self._queryable.undeclare()
        for query in self._drain():
            query.reply_err("the fusion node is stopping")
            query.drop()
        self.maneuver.close()
        self._pub.put(pl.encode(self.maneuver.payload()))
        self._pub.undeclare()


def same_arm_problem(arm: ArmModel, other: ArmModel) -> str:
    """Why ``other`` is not a config of ``arm`` (another arm, other joints or encoders, other
    sensors where they were), or empty: what a sensor calibration may change is the effects,
    not which arm and sensors there are."""
    if other.name != arm.name:
        return f"it describes {other.name[:40]!r}, not {arm.name!r}"
    if tuple(other.joint_names) != tuple(arm.joint_names):
        return f"its joints {list(other.joint_names)[:10]} are not {list(arm.joint_names)}"
    if not np.array_equal(other.counts_per_rad, arm.counts_per_rad):
        return "its encoders count otherwise"
    mine = [(s.name, s.description.device, s.link) for s in arm.sensors]
    theirs = [(s.name, s.description.device, s.link) for s in other.sensors]
    if mine != theirs:
        return f"its sensors {theirs[:8]} are not {mine[:8]}"
    return ""


def apply_fitted_config(maneuver: ServedManeuver, arm: ArmModel,
                        calibrate: Callable[[ArmModel, str], pl.Calibration]) -> pl.Maneuver:
    """``maneuver/apply``: track from now on with the config the maneuver's fit wrote (of the
    same ``arm``), by ``calibrate(new_arm, why)``: the fusion node's startup calibration on
    the still arm, the running tracker's pose carried; or refuse, saying why."""
    m = maneuver
    if m.state != "calibrated":
        return m.payload(False, f"refused: no calibration to apply (the maneuver is {m.state})")
    try:
        new_arm = load_arm(m.config_written)
    except (ConfigError, OSError, ValueError) as e:
        return m.payload(False, f"refused: {m.config_written} does not load: {str(e)[:200]}")
    differs = same_arm_problem(arm, new_arm)
    if differs:
        return m.payload(False, f"refused: {m.config_written} is not this arm's config: {differs}")
    what = f"the calibration of {Path(m.config_written).name} applied"
    result = calibrate(new_arm, what)
    if not result.ok:
        return m.payload(False, f"refused: {result.message}")
    return m.applied(f"{what}; the startup with it: {result.message}")


def joints_note(estimate, plan: PlannedManeuver) -> str:
    """What the controller must know of the arm's pose (the tracker's last ``estimate``, or
    ``None``) before it plays ``plan``."""
    e = estimate
    if e is None:
        return ("the node has no joint estimate yet: the controller must take the arm to the plan's "
                "first pose by its own means")
    unknown = [f"{j} ({f})" for j, f in zip(e.joint_names, e.flags, strict=True) if f != "ok"]
    if unknown:
        return (f"not known to the tracker now: {', '.join(unknown)}: the controller must not rely on "
                "their estimates to reach the plan's first pose")
    d = np.degrees(np.abs(np.asarray(e.q_rad) - plan.poses_rad[0]))
    j = int(np.argmax(d))
    return f"the plan's first pose is {d[j]:.1f}° away ({e.joint_names[j]}) from the estimate now"


def _lower_priority() -> None:  # in the child, before exec: the tracker keeps its core
    os.nice(10)


def _fit_summary(path: Path | None) -> str:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        ratio = max(float(np.max(np.asarray(f["rms"]) / np.asarray(f["noise"]))) for f in doc["fit"])
        est = sum(not p["held"] for p in doc["parameters"])
        return (f"{est} parameters estimated, {len(doc['parameters']) - est} held at their priors, "
                f"worst stream's RMS {ratio:.2f}x its noise")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        return f"fitted (its JSON unread: {type(e).__name__})"


def _last_line(path: Path | None) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(encoding="utf-8", errors="replace").splitlines()
                 if ln.strip()]
        return lines[-1][:300] if lines else "no message"
    except OSError:
        return "no message"
