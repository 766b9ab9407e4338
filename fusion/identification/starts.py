"""Where a fit starts: the joint angles at a recording's first sample (:func:`start_pose`)
and their rivals (:func:`start_poses`), from the startup solved on the recording's still
stretches. The encoders are relative: a fit's joint angles are ``q_ref + encoder angle``,
and these are the ``q_ref`` it may take (:func:`~armfusion.fusion.identification.data.data_from_recording`
takes the first and keeps the others as its rivals).
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import wrap_angle
from armfusion.models.sensor_models import stream_models


def start_pose(arm: ArmModel, rec, window_s: float = 1.0) -> np.ndarray:
    """The joint angles at the recording's first sample: the startup calibration on its first
    ``window_s`` (the arm must be still), the ready pose for joints it cannot tell."""
    return start_poses(arm, rec, window_s)[0]


def start_poses(arm: ArmModel, rec, window_s: float = 1.0) -> list[np.ndarray]:
    """:func:`start_pose`, then its rivals: where the fit may start. First the startup's
    branches on the first still ``window_s`` (its candidates, nearest the ready pose first),
    joints it cannot tell (gimbal lock) at the ready pose: a calibration maneuver starts from
    the ready pose, so that comes first and is right there. Then, where a joint was untold,
    the same branches with it taken from the later still stretches
    (:func:`_later_still_angles`): for a recording that starts elsewhere (random still poses).
    Which one is right the fit's residuals say (:func:`armfusion.fusion.workbench.diagnose.diagnose`
    tries the rivals when the first does not fit the noise).

    Those first starts come from the startup with the config's unmodelled-error floors,
    which leave a branch the data barely prefer open (nearest the ready pose first: right
    for a maneuver that starts there, with effects still to be found). The same starts
    solved with the floors left out (:func:`_nominal`: the pose the nominal model fits best,
    however unsure the config is of it) follow as rivals: with the shipped WMRA's 45 mg every
    joint is ``ill_conditioned``, some with no angle, and a recording that starts at a
    random pose was left in a wrong basin (a clean 60 s ``static-poses`` recording at 3e5
    times its noise). Then, where the still start cannot settle the pose, each later still
    pose's own answer (:func:`_later_still_starts`); at most :data:`MAX_STARTS` in all."""
    q = np.array(arm.ready_pose_rad, float)
    enc = rec.get("enc")
    models = stream_models(arm)
    e = models["enc"].from_counts(enc.values[:1])[0] if enc is not None and len(enc) else 0.0
    nominal = _nominal(arm)
    segments = functools.cache(lambda: _still_segments(rec))  # found once, where needed
    out: list[np.ndarray] = []
    unsettled = False
    # an untold joint starts at the ready pose (as the tracker's startup takes it): its q_ref is
    # the ready angle less the encoder's first reading, which an absolute encoder (a UR's
    # controller angles) does not give as zero
    ready_ref = q - e
    for solver_arm in (arm, nominal):
        found = _still_start_branches(solver_arm, rec, window_s, q, e, models, segments)
        if found is None:
            continue
        branches, settled = found
        unsettled |= not settled
        for b in branches:
            qb = np.where(np.isfinite(b), b - e, ready_ref)
            _add_start(out, qb)
    if not out:  # no still start: the ready pose
        return [ready_ref]
    if enc is not None and len(enc) and unsettled:
        # a start the still start cannot settle: each later still pose's own answer too
        for qb in _later_still_starts(nominal, rec, out[0], window_s, models, segments):
            _add_start(out, qb)
    return out


def _add_start(out: list[np.ndarray], q_ref_rad: np.ndarray) -> None:
    """``q_ref_rad`` appended to the starts ``out`` unless one is there already or they are full."""
    if len(out) < MAX_STARTS and not any(np.allclose(q_ref_rad, o) for o in out):
        out.append(q_ref_rad)


def _still_start_branches(solver_arm: ArmModel, rec, window_s: float, q_ready_rad: np.ndarray,
                          enc0_rad, models, segments) -> tuple[list[np.ndarray], bool] | None:
    """The startup on the recording's first still ``window_s`` solved for ``solver_arm``: its
    branches as geometric angles (NaN where untold; ambiguous joints each way, nearest the
    ready pose first, untold joints filled from later stretches where those tell them), and
    whether it settled the pose (no joint untold, one branch). None without a still start."""
    res = _solve_still_at(solver_arm, rec, rec.t_start_s, window_s)
    if res is None:
        return None
    enc = rec.get("enc")
    geo, branches = _branches(res, q_ready_rad)
    settled = not np.isnan(geo).any() and len(branches) == 1
    if np.isnan(geo).any() and enc is not None and len(enc):
        told = _later_still_angles(solver_arm, rec, geo, enc0_rad, window_s, models, segments)
        untold = np.isnan(geo) & np.isfinite(told)
        if untold.any():
            branches += [np.where(untold, told, b) for b in branches]
    return branches, settled


MAX_STARTS = 16
"""At most this many starts (the first and its rivals) from :func:`start_poses`: each rival
costs the diagnosis a short trial fit (about 0.2 s) where the first does not reach the noise."""


def _later_still_starts(nominal: ArmModel, rec, fallback_ref_rad: np.ndarray, window_s: float, models,
                        segments) -> list[np.ndarray]:
    """Starts (``q_ref``, rad) from the later still stretches, each on its own: the startup's
    angles there (each of its branches where it has several) less the encoder angles there,
    joints it cannot tell from ``fallback_ref_rad``. Where the still start leaves the arm's
    middle joints to a twin or untold (a shoulder at gimbal lock: the elbow and the forearm
    read alike either way), a later pose that tells them all gives a start in the right
    basin, which filling the untold joints one by one (:func:`_later_still_angles`) cannot."""
    out = []
    for res, e in _later_still_solutions(nominal, rec, window_s, models, segments):
        _, sets = _branches(res)
        out += [np.where(np.isfinite(g), g - e, fallback_ref_rad) for g in sets]
    return out


def _still_segments(rec) -> list:
    """The recording's still stretches (:func:`armfusion.fusion.startup.static.find_static_segments`);
    none where it finds none."""
    from armfusion.fusion.startup.static import find_static_segments

    try:
        return list(find_static_segments(rec))
    except Exception:  # noqa: BLE001 - no stretch found
        return []


def _solve_still_at(arm: ArmModel, rec, t0_s: float, window_s: float):
    """The startup's answer on ``rec``'s still ``window_s`` from ``t0_s``; None where it has none."""
    from armfusion.fusion.startup.solve import readings_from_recording, solve_still

    try:
        readings, _ = readings_from_recording(arm, rec, t0_s, t0_s + window_s, window_s)
        return solve_still(arm, readings, propose_unlock=False)
    except Exception:  # noqa: BLE001 - this stretch tells nothing
        return None


def _branches(res, q_near_rad: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """A startup answer's angles (NaN where untold) and its branches: the ambiguous joints
    taken from each candidate (nearest ``q_near_rad`` first, where given)."""
    geo = np.array([je.angle_rad if je.angle_rad is not None else np.nan for je in res.joints])
    if res.candidates_rad is None or len(res.candidates_rad) <= 1:
        return geo, [geo]
    cands = np.asarray(res.candidates_rad, float)
    amb = np.array([je.flag == "ambiguous" for je in res.joints])
    order = (np.argsort(np.abs(wrap_angle(cands - q_near_rad))[:, amb].sum(1), kind="stable")
             if q_near_rad is not None else range(len(cands)))
    return geo, [np.where(amb, cands[int(k)], geo) for k in order]


def _later_still_solutions(arm: ArmModel, rec, window_s: float, models, segments, max_segments: int = 8):
    """For each later still stretch (after the first, up to ``max_segments``) long enough and
    with an answer: the startup's answer there and the encoder angles at its start (rad)."""
    enc = rec.get("enc")
    t_enc = np.asarray(enc.t_s, float)
    for seg in segments()[1:max_segments + 1]:
        if seg.t_end_s - seg.t_start_s < window_s:
            continue
        res = _solve_still_at(arm, rec, seg.t_start_s, window_s)
        if res is None:
            continue
        i = int(np.searchsorted(t_enc, seg.t_start_s))
        yield res, models["enc"].from_counts(enc.values[min(i, len(enc) - 1):][:1])[0]


def _nominal(arm: ArmModel) -> ArmModel:
    """``arm`` with nothing unmodelled (its calibration's floors left out): where a fit starts
    (:func:`start_poses`), not how sure anything is."""
    return replace(arm, calibration=arm.calibration.as_exact())


def _later_still_angles(arm: ArmModel, rec, geo: np.ndarray, enc0_rad: np.ndarray, window_s: float,
                        models, segments) -> np.ndarray:
    """Joints the still start cannot tell (a joint at gimbal lock, a wrist whose roll gravity
    does not see there): their angle at the start from the first later still stretch that
    tells them, carried back through the encoders (``angle there - encoder there + encoder at
    the start``). Joints no stretch tells stay NaN. ``segments``: the recording's still
    stretches, a call (found once per recording: :func:`start_poses`)."""
    geo = geo.copy()
    for res, e in _later_still_solutions(arm, rec, window_s, models, segments):
        for j, je in enumerate(res.joints):
            if np.isnan(geo[j]) and je.angle_rad is not None and je.flag != "ambiguous":
                geo[j] = je.angle_rad - e[j] + enc0_rad[j]
        if not np.isnan(geo).any():
            break
    return geo
