"""Peer orientation filters of the package index on the one-joint IMU rig: the shaft's angle
as the relative angle between the shaft IMU and the frame IMU, each IMU's orientation
estimated by a 6-axis filter (gyroscope + accelerometer, no magnetometer), scored against
the encoder, as Song, Pei and Hsiao-Wecksler (2022) did with seven methods.

The peers, each with its documented defaults (one parameter set for every trial; nothing
is tuned to a file):

- ``vqf``: ``vqf.VQF(Ts)`` (VQF 6D, its default time constants, rest and motion bias
  estimation on), ``updateBatch`` -> ``quat6D``; gyroscope rad/s, accelerometer m/s².
- ``imufusion``: ``imufusion.Ahrs()`` with the settings it is constructed with (x-io's
  defaults: gain 0.5, NWU, its start-up ramp), ``set_sample_period(Ts)``,
  ``update_no_magnetometer`` each sample; gyroscope deg/s, accelerometer g.
- ``ahrs Madgwick`` (default IMU gain 0.033), ``ahrs Mahony`` (k_P 1, k_I 0.3),
  ``ahrs EKF`` (its default noise variances), ``ahrs Complementary`` (gain 0.9) and
  ``ahrs AQUA`` (its defaults): the ``ahrs`` package's filters that take a gyroscope and
  an accelerometer without a magnetometer, run in its batch mode (``gyr=``, ``acc=``,
  ``frequency=``); gyroscope rad/s, accelerometer m/s²; AQUA's quaternion is the world's
  orientation relative to the sensor and is conjugated. (Its other estimators are
  accelerometer/magnetometer attitude solvers, a gyro-only integrator, or need a
  magnetometer.)

The angle: each filter gives each IMU's orientation in its own world (``R_WF`` frame IMU,
``R_WS`` shaft IMU). A 6-axis filter's heading is arbitrary and drifts, so for a shaft
that is not vertical the shaft filter's world is first turned about the vertical until
the shaft axis (the config's, in each IMU's axes) points the same way in both worlds
(:func:`shared_heading`; without it the roll trial's peers measured 19-31 deg RMSE, the
frame filter's heading drifting away over 25 minutes). The relative orientation
``R_FS = R_WF^T R_WS`` is decomposed into a swing and a twist about the shaft axis in the
shaft IMU's axes ``a_S`` (from the config: joint 1's axis at q = 0 seen from the shaft
sensor's mount ``R_LS``, signed so that the encoder counts up as the shaft turns positively
about it). If ``R_FS(q) = R_FS(0)·Rot(a_S, q)`` the twist is exactly ``q`` plus a constant,
whatever ``R_FS(0)`` is; one constant (the circular mean of encoder minus twist on the
calibration stretch only) aligns its zero to the encoder, and the rest of the recording is
scored with it held fixed.
For a vertical shaft no heading is shared: the twist is the two filters' heading
difference, gyroscopes only, and drifts.

Time: the samples' stamps have jitter and the import drops some rows; every stream is
interpolated linearly onto one uniform grid at the recording's median rate (the shaft
accelerometer's stamps) spanning the samples all four streams share, and every peer runs
on that grid with its constant period (vqf takes only a fixed period). The grid's facts
(rate, stretches longer than 1.5 periods with no sample) are returned with the results.

    python tools/rig_peers.py TRIAL.mat... [--config imu_rig_roll] [--calibrate-s 300] [--json OUT]

needs the optional ``[bench]`` extra (``pip install -e '.[bench]'``).
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from importlib.metadata import version  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.models.arm import ArmModel  # noqa: E402
from armfusion.models.kinematics import chain_poses, sensor_poses  # noqa: E402
from armfusion.models.rotations import GRAVITY_MPS2, wrap_angle  # noqa: E402
from armfusion.models.sensor_models import stream_models  # noqa: E402
from armfusion.sensors.samples import LINK_GYRO_SUFFIX, Recording  # noqa: E402

GAP_PERIODS = 1.5
"""A stretch between two samples longer than this many grid periods counts as a gap."""


@dataclass(frozen=True)
class Grid:
    """The uniform grid every peer runs on: ``t_s (N,)``, its ``rate_hz``; ``gaps`` the
    stretches longer than :data:`GAP_PERIODS` periods with no sample in the shaft stream,
    ``longest_gap_s`` the longest of them (0 when none)."""

    t_s: np.ndarray
    rate_hz: float
    gaps: int
    longest_gap_s: float


@dataclass(frozen=True)
class RigInputs:
    """The two IMUs' readings on the grid: gyroscopes rad/s, accelerometers g ``(N, 3)``,
    the encoder's joint angle rad ``(N,)``."""

    grid: Grid
    shaft_gyro_rad_s: np.ndarray
    shaft_acc_g: np.ndarray
    frame_gyro_rad_s: np.ndarray
    frame_acc_g: np.ndarray
    encoder_rad: np.ndarray


@dataclass(frozen=True)
class PeerResult:
    """One peer on one recording: the shaft angle it gives (``angle_rad (N,)`` on
    ``t_s``, zero aligned to the encoder on the calibration stretch by ``offset_deg``),
    and on the scored rest (``n_scored`` samples): RMSE and largest error against the
    encoder, deg; ``seconds``: wall time of its two filters (both IMUs);
    ``heading_shared``: the two filters' headings were reconciled through the shaft axis
    (:func:`shared_heading`; False for a vertical shaft: gyroscopes only)."""

    name: str
    library: str
    t_s: np.ndarray
    angle_rad: np.ndarray
    offset_deg: float
    rmse_deg: float
    max_deg: float
    n_scored: int
    seconds: float
    heading_shared: bool


# ------------------------------------------------------------------------ geometry from the config
def shaft_sensors(arm: ArmModel) -> tuple[str, str]:
    """The shaft IMU (the link sensor with a gyroscope on the first joint's link) and the
    frame IMU (the base IMU) of a one-joint rig config."""
    frame = arm.imu
    shafts = [s.name for s in arm.sensors if s.has_link_gyro and s.link == 1]
    if frame is None or not frame.description.has("gyroscope") or len(shafts) != 1:
        raise ValueError(
            f"config {arm.name!r} is not a two-IMU rig: needs a base IMU with a gyroscope and one "
            f"sensor with a gyroscope on link 1 (found {len(shafts)})")
    return shafts[0], frame.name


def shaft_axes(arm: ArmModel) -> tuple[np.ndarray, np.ndarray]:
    """Joint 1's axis at q = 0 in the shaft IMU's axes and in the frame IMU's axes (unit):
    the encoder counts up as the shaft turns positively about it (the config's mounts
    ``R_LS`` and the joint's z axis)."""
    shaft, frame = shaft_sensors(arm)
    q0 = np.zeros((1, arm.n_joints))
    axis_0 = chain_poses(arm, q0).axis_0[0, 0]
    R_0S, _ = sensor_poses(arm, q0, (shaft, frame))
    return R_0S[0, 0].T @ axis_0, R_0S[0, 1].T @ axis_0


# ------------------------------------------------------------------------------------ the grid
def rig_inputs(rec: Recording, arm: ArmModel) -> RigInputs:
    """The shaft and frame IMUs' readings and the encoder (``true_q``) on one uniform grid
    (module docstring), in the units the peers take, converted with the config's sensor
    descriptions."""
    shaft, _ = shaft_sensors(arm)
    names = (shaft, shaft + LINK_GYRO_SUFFIX, "imu_acc", "imu_gyro", "true_q")
    missing = [n for n in names if rec.get(n) is None or len(rec.get(n).t_s) < 2]
    if missing:
        raise ValueError(f"the recording lacks stream(s) {', '.join(missing)} (of {', '.join(names)})")
    streams = {n: rec.get(n) for n in names}
    t_ref = streams[shaft].t_s
    period_s = float(np.median(np.diff(t_ref)))
    t0 = max(float(s.t_s[0]) for s in streams.values())
    t1 = min(float(s.t_s[-1]) for s in streams.values())
    if not period_s > 0 or t1 - t0 < 10 * period_s:
        raise ValueError(f"the streams {', '.join(names)} share less than 10 samples of time")
    t = t0 + period_s * np.arange(int(np.floor((t1 - t0) / period_s)) + 1)
    dt = np.diff(t_ref)
    long = dt > GAP_PERIODS * period_s
    grid = Grid(t, 1.0 / period_s, int(long.sum()), float(dt[long].max()) if long.any() else 0.0)
    models = stream_models(arm, 1.0 / period_s)

    def on_grid(name: str) -> np.ndarray:
        s = streams[name]
        v = s.values if name == "true_q" else models[name].from_counts(s.values)
        return np.column_stack([np.interp(t, s.t_s, v[:, k]) for k in range(v.shape[1])])

    return RigInputs(grid, on_grid(shaft + LINK_GYRO_SUFFIX), on_grid(shaft), on_grid("imu_gyro"),
                     on_grid("imu_acc"), on_grid("true_q")[:, 0])


# ------------------------------------------------------------------------------------ the peers
# Each peer: (gyroscope rad/s (N, 3), accelerometer g (N, 3), period s) -> the sensor's
# orientation in the filter's world, unit quaternions w, x, y, z (N, 4), R_WS.
PeerFilter = Callable[[np.ndarray, np.ndarray, float], np.ndarray]


def _vqf(gyr_rad_s, acc_g, period_s):
    from vqf import VQF

    out = VQF(period_s).updateBatch(np.ascontiguousarray(gyr_rad_s, dtype=float),
                                    np.ascontiguousarray(acc_g * GRAVITY_MPS2, dtype=float))
    return out["quat6D"]


def _imufusion(gyr_rad_s, acc_g, period_s):
    import imufusion

    ahrs = imufusion.Ahrs()
    ahrs.set_sample_period(period_s)
    gyr_deg_s = np.degrees(gyr_rad_s)
    q = np.empty((len(gyr_deg_s), 4))
    for i in range(len(q)):
        ahrs.update_no_magnetometer(gyr_deg_s[i], acc_g[i])
        q[i] = ahrs.get_quaternion()
    return q


def _ahrs(cls_name: str, world_in_sensor: bool = False) -> PeerFilter:
    """An ``ahrs`` filter in batch mode; ``world_in_sensor``: its quaternion is the world's
    orientation relative to the sensor (AQUA, after Valenti et al.), conjugated here."""
    def run(gyr_rad_s, acc_g, period_s):
        import ahrs.filters

        cls = getattr(ahrs.filters, cls_name)
        q = cls(gyr=np.asarray(gyr_rad_s, float), acc=np.asarray(acc_g, float) * GRAVITY_MPS2,
                frequency=1.0 / period_s).Q
        return q * np.array([1.0, -1.0, -1.0, -1.0]) if world_in_sensor else q
    return run


PEERS: dict[str, tuple[str, PeerFilter]] = {
    "vqf 6D": ("vqf", _vqf),
    "imufusion": ("imufusion", _imufusion),
    "ahrs Madgwick": ("ahrs", _ahrs("Madgwick")),
    "ahrs Mahony": ("ahrs", _ahrs("Mahony")),
    "ahrs EKF": ("ahrs", _ahrs("EKF")),
    "ahrs Complementary": ("ahrs", _ahrs("Complementary")),
    "ahrs AQUA": ("ahrs", _ahrs("AQUA", world_in_sensor=True)),
}
"""Every peer filter, by the name it is reported under: (its package, how it is run)."""


# ------------------------------------------------------------------------------------ the angle
def _qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions w, x, y, z ``(N, 4)``."""
    pw, pv, qw, qv = p[:, :1], p[:, 1:], q[:, :1], q[:, 1:]
    return np.column_stack([pw[:, 0] * qw[:, 0] - np.sum(pv * qv, axis=1),
                            pw * qv + qw * pv + np.cross(pv, qv)])


def _qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R(q) v`` for each row of ``q`` ``(N, 4)`` and one vector ``v`` ``(3,)``."""
    p = np.column_stack([np.zeros(len(q)), np.broadcast_to(v, (len(q), 3))])
    return _qmul(_qmul(q, p), _qconj(q))[:, 1:]


def twist_angle_rad(q_WF: np.ndarray, q_WS: np.ndarray, axis_S: np.ndarray) -> np.ndarray:
    """The twist about ``axis_S`` (shaft IMU axes) of ``R_FS = R_WF^T R_WS``, unwrapped,
    rad ``(N,)``; quaternions w, x, y, z ``(N, 4)``."""
    a = np.asarray(axis_S, float) / np.linalg.norm(axis_S)
    q_FS = _qmul(_qconj(q_WF), q_WS)
    return np.unwrap(2.0 * np.arctan2(q_FS[:, 1:] @ a, q_FS[:, 0]))


HORIZONTAL_SHARE = 0.5
"""The shaft counts as horizontal enough to carry a heading when its axis's horizontal part
(in the frame filter's world) is at least this (30 deg or more from the vertical)."""


def shared_heading(q_WF: np.ndarray, q_WS: np.ndarray, axis_F: np.ndarray,
                   axis_S: np.ndarray) -> tuple[np.ndarray, bool]:
    """The shaft filter's orientation turned about its world's vertical (z) so that the
    shaft axis points the same way in both filters' worlds, and whether that was done.

    A 6-axis filter's heading is its own (each starts anywhere about the vertical and
    drifts with its gyroscope's bias there): the two IMUs' worlds differ by a turn about the
    vertical that the relative orientation would take for joint motion. The shaft axis is
    the one direction both IMUs share; where it is horizontal enough (median over the
    recording, :data:`HORIZONTAL_SHARE`) its heading in each world gives that turn, sample
    by sample. A vertical shaft carries no heading: the relative orientation is left as the
    filters give it (the angle is then their gyroscopes' alone)."""
    u_F = _rotate(q_WF, np.asarray(axis_F, float))
    u_S = _rotate(q_WS, np.asarray(axis_S, float))
    if np.median(np.hypot(u_F[:, 0], u_F[:, 1])) < HORIZONTAL_SHARE:
        return q_WS, False
    turn = np.arctan2(u_F[:, 1], u_F[:, 0]) - np.arctan2(u_S[:, 1], u_S[:, 0])
    q_turn = np.column_stack([np.cos(turn / 2), np.zeros((len(turn), 2)), np.sin(turn / 2)])
    return _qmul(q_turn, q_WS), True


def peer_joint_angles(rec: Recording, arm: ArmModel, calibrate_s: float,
                      axis_shaft: np.ndarray | None = None,
                      peers: tuple[str, ...] | None = None) -> tuple[Grid, dict[str, PeerResult]]:
    """Run every peer (``peers``: names of :data:`PEERS`, default all) on both IMUs of the
    rig recording ``rec`` (config ``arm``), form the shaft angle (module docstring), align
    its zero to the encoder on the first ``calibrate_s`` seconds, and score the rest.

    ``axis_shaft``: the shaft axis in the shaft IMU's axes (default: from the config).
    """
    names = tuple(PEERS) if peers is None else tuple(peers)
    unknown = [n for n in names if n not in PEERS]
    if unknown:
        raise ValueError(f"unknown peer filter(s) {', '.join(repr(n[:40]) for n in unknown)}; "
                         f"known: {', '.join(PEERS)}")
    if not np.isfinite(calibrate_s) or calibrate_s <= 0:
        raise ValueError(f"calibrate_s must be a positive number of seconds, got {calibrate_s!r}")
    axis_S, axis_F = shaft_axes(arm)
    axis = axis_S if axis_shaft is None else np.asarray(axis_shaft, float)
    if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) < 1e-9:
        raise ValueError(f"axis_shaft must be a non-zero 3-vector, got shape {axis.shape}")
    x = rig_inputs(rec, arm)
    t = x.grid.t_s
    cal = t < t[0] + calibrate_s
    if cal.all() or cal.sum() < 2:
        raise ValueError(f"calibrate_s {calibrate_s:g} s leaves nothing to calibrate on or to score "
                         f"(the streams share {t[-1] - t[0]:.1f} s)")
    period_s = 1.0 / x.grid.rate_hz
    out = {}
    for name in names:
        package, run = PEERS[name]
        t_wall = time.perf_counter()
        q_S = run(x.shaft_gyro_rad_s, x.shaft_acc_g, period_s)
        q_F = run(x.frame_gyro_rad_s, x.frame_acc_g, period_s)
        seconds = time.perf_counter() - t_wall
        q_S, heading_shared = shared_heading(q_F, q_S, axis_F, axis)
        twist = twist_angle_rad(q_F, q_S, axis)
        offset = float(np.angle(np.mean(np.exp(1j * (x.encoder_rad[cal] - twist[cal])))))
        angle = twist + offset
        err = np.degrees(wrap_angle(angle[~cal] - x.encoder_rad[~cal]))
        out[name] = PeerResult(name, f"{package} {version(package)}", t, angle, float(np.degrees(offset)),
                               float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err))),
                               int(err.size), seconds, heading_shared)
    return x.grid, out


# ------------------------------------------------------------------------------------ command line
def main(argv=None) -> int:
    from armfusion.fusion.configfile import load_arm
    from armfusion.fusion.importing.column_map import load_column_map
    from armfusion.fusion.importing.run import import_recording

    from tools.rig_configs import RIG_CONFIGS, choose_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", type=Path, nargs="+", help="the rig's .mat trials")
    ap.add_argument("--config", default=None,
                    help="rig config (default: the one whose model fits the first minute best, "
                         "as tools/bench_real_rig.py chooses)")
    ap.add_argument("--calibrate-s", type=float, default=300.0)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    a = ap.parse_args(argv)
    table = {}
    for path in a.trials:
        first = RIG_CONFIGS[0]
        rec = import_recording(path, load_column_map("imu-rig"), load_arm(first), first).recording
        config = a.config or choose_config(rec, 60.0)[0]
        arm = load_arm(config)
        grid, res = peer_joint_angles(rec, arm, a.calibrate_s)
        print(f"{path.name} ({config}): {len(grid.t_s):,} samples at {grid.rate_hz:.2f} Hz, "
              f"{grid.gaps} gaps (longest {grid.longest_gap_s:.3f} s); calibrated on {a.calibrate_s:g} s")
        for r in res.values():
            print(f"  {r.name:20s} RMSE {r.rmse_deg:7.2f} deg  max {r.max_deg:7.2f} deg  "
                  f"({r.library}, {r.seconds:.1f} s)", flush=True)
        table[path.stem] = {
            "config": config, "calibrate_s": a.calibrate_s, "samples": len(grid.t_s),
            "rate_hz": grid.rate_hz, "gaps": grid.gaps, "longest_gap_s": grid.longest_gap_s,
            "peers": {r.name: {"library": r.library, "rmse_deg": r.rmse_deg, "max_deg": r.max_deg,
                               "scored_samples": r.n_scored, "zero_offset_deg": r.offset_deg,
                               "heading_shared": r.heading_shared, "seconds": r.seconds}
                      for r in res.values()}}
    if a.json is not None:
        a.json.write_text(json.dumps(table, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
