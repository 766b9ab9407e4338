"""Writing a calibrated config: the config with the fit's estimates and σ as its effects,
the accelerometer floor lowered to what the fit leaves, the covariance of each
accelerometer's still-reading correction, and what the fit could not tell (its holds, the
joint-zero conventions, the references' checks)."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.identification.result import Identification
from armfusion.models.effects import entries_from_model
from armfusion.models.effects.base import SensorEffect
from armfusion.models.effects.library import JointOffset

CONVENTION_SHARE = 0.1
"""A held element whose prior carries at least this share of a joint zero's variance (its
squared correlation with the zero) is that zero's convention: the zero is known only
relative to it, as a board's axes turned about the joint it rides on are that joint's zero
turned back. Several held elements can share one zero's doubt (a still frame's bias along
the shaft's horizontal normal, and the shaft board's turn about the shaft): each that carries
a tenth of it or more is a convention of the zero."""


def joint_zero_conventions(result: Identification) -> list[str]:
    """Held elements that the data cannot tell from a joint's zero (the last sensor's mount
    rotation about the last joint's axis…): with relative encoders the startup defines the
    zeros with them at their priors, so they are a convention, not an error of the startup.
    Each such element is found either by the fit's own identifiability analysis (a hold whose
    partners are a joint's zero) or, where the model's structure held it before the fit (a
    gauge of the workbench's), by its covariance: its prior carries at least
    :data:`CONVENTION_SHARE` of a joint zero's variance."""
    out = [h.element for h in result.holds
           if any(p.split("[")[0].endswith(".joint_offset") for p, _ in h.partners)]
    zeros = [i for i, n in enumerate(result.names) if n.split("[")[0].endswith(".joint_offset")
             and not result.held[i]]
    if zeros:
        C = result.correlation()
        for i in np.flatnonzero(result.held):
            if result.names[i] not in out and np.max(C[i, zeros] ** 2) >= CONVENTION_SHARE:
                out.append(result.names[i])
    return out


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
    their σ, ``calibration.accel_unmodelled_g`` lowered to what the fit's window means leave
    beyond the noise (per sensor in ``accel_unmodelled_g_per_sensor``: an error that stays),
    and each sensor's fast error beyond its noise in ``accel_fast_error_g_per_sensor`` (one
    sample's excess, vibration: it averages away, so it joins the readings' noise only).

    Joint offsets are left out unless asked: with relative encoders they are the
    recording's encoder zeros, not a property of the arm.
    """
    cm = result.calibrated_model()
    entries = entries_from_model(cm, cm.x0)
    if not include_joint_offsets:
        entries = [e for e in entries if e["effect"] != JointOffset.name]
    for e in entries:
        b = cm.block(f"{e['target']}.{e['effect']}")
        sl = cm.index[b.name]
        held = result.held[sl]
        e["note"] = (e["note"] + (" (held at its prior: the calibration data could not tell it)"
                                  if held.all() else ""))
    out = dict(config_data)
    out["effects"] = entries
    cal = dict(out.get("calibration") or {})
    un = result.unmodelled_g("lasting")
    if un:
        floor = max(un.values())
        cal["accel_unmodelled_g"] = round(max(floor, 1e-4), 6)
        cal["accel_unmodelled_g_per_sensor"] = {k: round(max(v, 1e-4), 6) for k, v in un.items()}
    fast = {k: round(v, 6) for k, v in result.unmodelled_g("fast").items() if v > 0.0}
    if fast:
        cal["accel_fast_error_g_per_sensor"] = fast
    cal["correction_covariance"] = correction_covariance(result)
    cal["identified"] = {"mode": result.mode, "samples": result.n_samples,
                         "chi2_red": round(result.chi2_red, 3),
                         "held": [h.element for h in result.holds],
                         "joint_zero_conventions": joint_zero_conventions(result),
                         "references": [c.as_dict() for c in result.reference_checks]}
    out["calibration"] = cal
    return out
