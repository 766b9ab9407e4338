"""A simulated twin of a UR5 with two IMUs, as a generic logger writes it: one CSV of time,
the controller's joint angles and each IMU's accelerometer and gyroscope.

The arm is ``config/ur5_two_imu.yaml`` (bolted to a table, IMUs on the forearm and on wrist
link 1). What the simulator draws on it, beyond each IMU's datasheet noise:

- **The IMUs' own errors** (effects of the library, ``docs/effects.md``): each
  accelerometer's scale 3.5-4.4 % low on every axis (``accel_scale``; a MEMS part's factory
  trim lost to the board's supply or a range set in the wrong register), each mount turned
  about 1° off its nominal axes (``mount_rotation``, a rotation vector of 0.6° per axis).
- **The logger's clock** (:func:`logged_and_resampled`): each IMU's samples are stamped
  ``o(t)`` late, ``o`` starting between -13 and +3 ms and drifting by 5-10 ms over the
  recording, kept within ±13 ms (two clocks that are not disciplined to each other);
  logged at 100 Hz, then linearly interpolated onto the controller's 125 Hz instants, as a
  user merging the two logs by time does.
- **The motion**: a table a few tenths of a degree off level; a start with under a second
  still (0.6-0.9 s), then slow repeated shapes (minimum-jerk moves, at most 25 °/s, between
  four poses, one with wrist 1 past -180°), held 3 s at one of them each round.

The joint columns are the controller's angles (deg), which are also the truth: a twin's
recording, imported with ``config/imports/ur5-csv.yaml``, carries them as the encoders and
as ``true_q``. Every draw is seeded (``--seed``).

    python tools/twin_ur5.py --seed 0 --out twin.csv [--duration 45]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armfusion.fusion.configfile import load_arm  # noqa: E402
from armfusion.models.arm import ArmModel  # noqa: E402
from armfusion.models.rotations import DEG  # noqa: E402
from armfusion.models.simulator import SimulationOptions, simulate  # noqa: E402
from armfusion.models.trajectories.paths import ParkedBase, StepsBuilder, WaypointPath, min_jerk_duration  # noqa: E402
from armfusion.models.trajectories.scenario import Scenario, warm_up  # noqa: E402
from armfusion.sensors.samples import link_gyro_stream  # noqa: E402

CONFIG = ROOT / "config" / "ur5_two_imu.yaml"
IMU_RATE_HZ = 100.0
"""The IMUs' logger's rate."""
CONTROLLER_RATE_HZ = 125.0
"""The UR controller's real-time interface's rate: the instants the merged CSV holds."""
SHAPE_POSES_DEG = np.array([
    [0, -90, 90, -90, -90, 0],
    [25, -60, 70, -120, -70, 30],
    [-20, -110, 120, -190, -100, -40],
    [10, -75, 40, -60, -80, 60],
])
"""The four poses of the repeated shape, deg: the ready pose, a reach, a fold with wrist 1
past -180° (where an angle wrapped to ±180° would jump to +170°), a lift."""
PEAK_RATE_DEG_S = 25.0
HOLD_S = 3.0
TABLE_TILT_SIGMA_DEG = 0.3
ACCEL_SCALE_LOW = (0.035, 0.044)
"""Each accelerometer axis reads this fraction low (uniform between)."""
MOUNT_SIGMA_DEG = 0.6
"""Each mount's rotation vector, per axis (about 1° in all)."""
OFFSET_START_MS = (-13.0, 3.0)
OFFSET_DRIFT_MS = (5.0, 10.0)
OFFSET_BOUND_MS = 13.0


@dataclass(frozen=True)
class Twin:
    """One twin recording: the CSV's columns, and what was drawn."""

    columns: dict[str, np.ndarray]
    effects: list[dict]
    offsets_ms: dict[str, tuple[float, float]]
    table_tilt_deg: tuple[float, float]
    still_start_s: float


def twin_scenario(arm: ArmModel, duration_s: float,
                  rng: np.random.Generator) -> tuple[Scenario, float, tuple]:
    """The table's tilt, a short still start, then the shape repeated until ``duration_s``."""
    roll, pitch = rng.normal(0.0, TABLE_TILT_SIGMA_DEG * DEG, 2)
    still_s = float(rng.uniform(0.6, 0.9))
    poses = SHAPE_POSES_DEG * DEG
    b = StepsBuilder(poses[0]).hold(still_s)
    k = 0
    while b.t < duration_s:
        k = (k + 1) % len(poses)
        q = poses[k]
        b.move(q, min_jerk_duration(q - b.level, PEAK_RATE_DEG_S * DEG, min_s=1.0))
        b.hold(HOLD_S if k == 1 else 0.2)
    path = WaypointPath(b.build())
    sc = Scenario("ur5-twin", arm, duration_s, path, ParkedBase(float(roll), float(pitch), 0.0), warm_up())
    return sc, still_s, (float(roll / DEG), float(pitch / DEG))


def imu_effects(arm: ArmModel, rng: np.random.Generator) -> list[dict]:
    """The IMUs' scale and mount errors, as config entries."""
    out = []
    for s in arm.link_accelerometers:
        out.append({"effect": "accel_scale", "target": s.name,
                    "params": {"scale_error": (-rng.uniform(*ACCEL_SCALE_LOW, 3)).tolist()}})
        out.append({"effect": "mount_rotation", "target": s.name,
                    "params": {"rotvec_rad": rng.normal(0.0, MOUNT_SIGMA_DEG * DEG, 3).tolist()}})
    return out


def logged_and_resampled(t_true_s: np.ndarray, values: np.ndarray, offset_s,
                         t_out_s: np.ndarray) -> np.ndarray:
    """A logger's view of samples taken at ``t_true_s``: the sample stamped ``t`` holds the
    value at ``t - offset_s(t)`` (both linear in time between samples), then the stamped
    series read at ``t_out_s`` by linear interpolation (NaN outside it)."""
    stamped_true = t_true_s - offset_s(t_true_s)
    logged = np.column_stack([np.interp(stamped_true, t_true_s, v) for v in values.T])
    inside = (t_out_s >= t_true_s[0]) & (t_out_s <= t_true_s[-1])
    out = np.full((len(t_out_s), values.shape[1]), np.nan)
    for c in range(values.shape[1]):
        out[inside, c] = np.interp(t_out_s[inside], t_true_s, logged[:, c])
    return out


def make_twin(seed: int = 0, duration_s: float = 45.0, arm: ArmModel | None = None) -> Twin:
    arm = load_arm(str(CONFIG)) if arm is None else arm
    rng = np.random.default_rng([int(seed), 0x7A1])
    sc, still_s, tilt = twin_scenario(arm, duration_s, rng)
    effects = imu_effects(arm, rng)
    rates = {s.name: IMU_RATE_HZ for s in arm.link_accelerometers}
    rec, _ = simulate(arm, sc, rate_hz=CONTROLLER_RATE_HZ, seed=seed, effects=effects,
                      options=SimulationOptions(rates_hz=rates))
    q_true = rec.streams["true_q"]
    t_out = q_true.t_s
    cols: dict[str, np.ndarray] = {"time_s": t_out}
    for i in range(arm.n_joints):
        cols[f"q{i + 1}_deg"] = q_true.values[:, i] / DEG
    offsets = {}
    for s in arm.link_accelerometers:
        start = rng.uniform(*OFFSET_START_MS)
        end = np.clip(start + rng.choice([-1.0, 1.0]) * rng.uniform(*OFFSET_DRIFT_MS), -OFFSET_BOUND_MS,
                      OFFSET_BOUND_MS)
        offsets[s.name] = (float(start), float(end))

        def offset_s(t, a=start, b=end):
            return 1e-3 * (a + (b - a) * np.asarray(t) / duration_s)

        for stream, suffix in ((s.name, ("ax", "ay", "az")), (link_gyro_stream(s.name), ("gx", "gy", "gz"))):
            st = rec.streams[stream]
            v = logged_and_resampled(st.t_s, st.values.astype(float), offset_s, t_out)
            for c, name in enumerate(suffix):
                cols[f"{s.name}_{name}"] = v[:, c]
    return Twin(cols, effects, offsets, tilt, still_s)


def write_csv(twin: Twin, path: Path) -> Path:
    """The twin as a generic CSV: a header row, then one row per controller instant (an IMU
    column is empty where its log has not begun or has ended)."""
    names = list(twin.columns)
    data = np.column_stack([twin.columns[n] for n in names])
    with open(path, "w") as f:
        f.write(",".join(names) + "\n")
        for row in data:
            f.write(",".join("" if not np.isfinite(v) else f"{v:.9g}" for v in row) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=45.0, help="seconds (default 45)")
    ap.add_argument("--out", type=Path, required=True, help="the CSV to write")
    a = ap.parse_args(argv)
    twin = make_twin(a.seed, a.duration)
    write_csv(twin, a.out)
    print(f"wrote {a.out}: {len(twin.columns['time_s'])} rows at {CONTROLLER_RATE_HZ:g} Hz, "
          f"still for the first {twin.still_start_s:.2f} s; table tilt roll {twin.table_tilt_deg[0]:+.2f}°, "
          f"pitch {twin.table_tilt_deg[1]:+.2f}°")
    for name, (a0, a1) in twin.offsets_ms.items():
        print(f"  {name}: time offset {a0:+.1f} -> {a1:+.1f} ms")
    for e in twin.effects:
        print(f"  {e['target']}.{e['effect']}: {np.round(list(e['params'].values())[0], 4).tolist()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
