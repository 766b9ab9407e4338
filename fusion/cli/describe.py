"""Plain summaries of an arm and of a recording, as JSON-ready dicts (for `info`, `inspect`)."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.startup.static import StaticDetectionSettings, find_static_segments
from armfusion.models.arm import ArmModel
from armfusion.models.kinematics import joint_axis_angle_to_vertical
from armfusion.sensors.samples import Recording, stream_gaps


def describe_arm(arm: ArmModel) -> dict:
    vertical = np.degrees(joint_axis_angle_to_vertical(arm, arm.ready_pose_rad))[0] < 1e-6
    joints = []
    for i, j in enumerate(arm.joints):
        row = {
            "name": j.name,
            "min_deg": float(np.degrees(j.min_rad)),
            "max_deg": float(np.degrees(j.max_rad)),
            "ready_deg": float(np.degrees(arm.ready_pose_rad[i])),
            "counts_per_rev": j.counts_per_rev,
            "vertical_at_ready": bool(vertical[i]),
        }
        if arm.dh is not None:
            row.update(
                alpha_deg=float(np.degrees(arm.dh.alpha_rad[i])),
                a_mm=float(arm.dh.a_m[i] * 1000),
                d_mm=float(arm.dh.d_m[i] * 1000),
                offset_deg=float(np.degrees(arm.dh.offset_rad[i])),
            )
        joints.append(row)
    sensors = []
    for s in arm.sensors:
        bus = ""
        if s.bus:
            b = s.bus
            bus = (f"I2C bus {b['bus']} at 0x{b['address']:02X}" if b["kind"] == "i2c"
                   else f"SPI bus {b['bus']} CS {b['chip_select']}")
        floor = (arm.calibration.imu_accel_floor_g if s.is_base_imu else
                 arm.calibration.accel_floor_g(s.name) if s.is_link_accelerometer else None)
        sensors.append({
            "name": s.name,
            "type": s.type,
            "link": s.link,
            "unmodelled_g": floor,
            "unmodelled_from": ("class" if (("imu_acc" if s.is_base_imu else s.name)
                                            in arm.calibration.floors_by_default) else "config"),
            "position_mm": (s.p_L_m * 1000).tolist(),
            "rotation": s.R_LS.tolist(),
            "bus": bus,
            "sees_joints": [arm.joints[k].name for k in arm.joints_seen_by(s.name)],
        })
    return {
        "name": arm.name,
        "source": arm.source,
        "dh_convention": arm.convention,
        "n_joints": arm.n_joints,
        "joints": joints,
        "sensors": sensors,
        "effects": [{"effect": e.effect, "target": e.target} for e in arm.effects],
        "base": ("moving" if arm.fixed_base is None else
                 {"mount": "fixed", "tilt_sigma_deg": float(np.degrees(arm.fixed_base.tilt_sigma_rad)),
                  "roll_deg": None if arm.fixed_base.roll_rad is None else float(np.degrees(arm.fixed_base.roll_rad)),
                  "pitch_deg": None if arm.fixed_base.pitch_rad is None
                  else float(np.degrees(arm.fixed_base.pitch_rad))}),
    }


def describe_recording(rec: Recording, settings: StaticDetectionSettings | None = None) -> dict:
    streams = []
    for s in rec.streams.values():
        n_gaps, longest, missing = stream_gaps(s)
        streams.append({
            "name": s.name,
            "kind": s.kind,
            "channels": list(s.channels),
            "samples": len(s),
            "rate_hz": s.rate_hz,
            "t_start_s": float(s.t_s[0]) if len(s) else None,
            "t_end_s": float(s.t_s[-1]) if len(s) else None,
            "gaps": n_gaps,
            "missing_samples": missing,
            "missing_percent": 100.0 * missing / (len(s) + missing) if len(s) else 0.0,
            "longest_gap_s": longest,
        })
    segs = find_static_segments(rec, settings) if rec.raw() else []
    report = rec.meta.get("read_report")
    return {
        "t_start_s": rec.t_start_s,
        "t_end_s": rec.t_end_s,
        "duration_s": rec.duration_s,
        "streams": streams,
        "has_truth": bool(rec.truth()),
        "static_segments": [
            {"t_start_s": g.t_start_s, "t_end_s": g.t_end_s, "duration_s": g.duration_s}
            for g in segs
        ],
        "read_report": None if report is None else getattr(report, "message", str(report)),
    }
