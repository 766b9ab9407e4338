"""Writing a calibrated config: the config with the fit's estimates and σ as its effects,
the accelerometer floor lowered to what the fit leaves, the covariance of each
accelerometer's still-reading correction, and what the fit could not tell (its holds, the
joint-zero conventions, the references' checks)."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.identification.result import Identification
from armfusion.models.effects import entries_from_model
from armfusion.models.effects.base import SensorEffect


def joint_zero_conventions(result: Identification) -> list[str]:
    """Held elements that the data cannot tell from a joint's zero (the last sensor's mount
    rotation about the last joint's axis…): with relative encoders the startup defines the
    zeros with them at their priors, so they are a convention, not an error of the startup."""
    return [h.element for h in result.holds
            if any(p.split("[")[0].endswith(".joint_offset") for p, _ in h.partners)]


def correction_covariance(result: Identification) -> dict[str, dict]:
    """Per accelerometer stream, the covariance of the elements its still-reading correction
    uses (mount, axes, scale, bias, temperature drift), correlations included (a held axis
    angle and the mount rotation that carries it are known together far better than
    alone). The joint-zero conventions are in it too: a sensor's mount about the last
    joint's axis that no calibration can tell from that joint's zero is an uncertainty of
    the joint's real angle, which the startup's and the tracker's σ must carry
    (``StartupCorrection``)."""
    m = result.model
    conv: set[str] = set()
    arm = m.arm
    streams = [s.name for s in arm.link_accelerometers] + (["imu_acc"] if arm.imu is not None else [])
    out = {}
    for s in streams:
        idx = []
        for e in m.effects:
            if isinstance(e, SensorEffect) and s in e.streams:
                sl = m.index[e.block_name]
                idx += [i for i in range(sl.start, sl.stop) if result.names[i] not in conv]
        if idx:
            C = result.covariance[np.ix_(idx, idx)]
            out[s] = {"elements": [result.names[i] for i in idx],
                      "matrix": [[float(f"{v:.6g}") for v in row] for row in C]}
    return out


def config_with_estimates(config_data: dict, result: Identification,
                          include_joint_offsets: bool = False) -> dict:
    """A config dict (as loaded from YAML) with the effects replaced by the estimates and
    their σ, and ``calibration.accel_unmodelled_g`` lowered to what the fit leaves beyond
    the noise (per sensor in ``accel_unmodelled_g_per_sensor``).

    Joint offsets are left out unless asked: with relative encoders they are the
    recording's encoder zeros, not a property of the arm.
    """
    cm = result.calibrated_model()
    entries = entries_from_model(cm, cm.x0)
    if not include_joint_offsets:
        entries = [e for e in entries if e["effect"] != "joint_offset"]
    for e in entries:
        b = cm.block(f"{e['target']}.{e['effect']}")
        sl = cm.index[b.name]
        held = result.held[sl]
        e["note"] = (e["note"] + (" (held at its prior: the calibration data could not tell it)"
                                  if held.all() else ""))
    out = dict(config_data)
    out["effects"] = entries
    cal = dict(out.get("calibration") or {})
    un = result.unmodelled_g()
    if un:
        floor = max(un.values())
        cal["accel_unmodelled_g"] = round(max(floor, 1e-4), 6)
        cal["accel_unmodelled_g_per_sensor"] = {k: round(max(v, 1e-4), 6) for k, v in un.items()}
    cal["correction_covariance"] = correction_covariance(result)
    cal["identified"] = {"mode": result.mode, "samples": result.n_samples,
                         "chi2_red": round(result.chi2_red, 3),
                         "held": [h.element for h in result.holds],
                         "joint_zero_conventions": joint_zero_conventions(result),
                         "references": [c.as_dict() for c in result.reference_checks]}
    out["calibration"] = cal
    return out
