"""The tracker's measurement models and its per-step bookkeeping, compiled (numba), for
every sigma point (the process model: :mod:`armfusion.fusion.tracking.process_kernels`).

A tracker step evaluates its models at 2n + 1 = 39 sigma points of a 19-state filter: a
few thousand floating-point operations, which as NumPy array calls cost far more in
interpreter overhead than in arithmetic. These kernels do the same arithmetic in one
compiled loop per call. :mod:`armfusion.fusion.tracking.tracker` calls them. The accelerometer's and the
compass's equations are :mod:`armfusion.models.sensor_kernels`' (written once there, for the batch
models too). The tests hold the kernels to the motion model computed from scratch
(:func:`armfusion.models.motion.specific_force`, tests/fusion/test_tracker.py) and to the same
equations written in NumPy (``tools/bench_track_numpy.py``, the filterpy baseline of
``tools/bench_track.py``, tests/fusion/test_tracker_kernels.py).

The state layout (see :class:`armfusion.fusion.tracking.tracker.StateLayout`): joint offsets ``0 … n-1``,
roll, pitch, the base's linear acceleration (3), yaw, the gyro bias (3), the IMU
accelerometer's bias (3), and where the base's speed is bounded its velocity (3). Kernels
take the first index of each block.

Compiled once per machine and cached next to this file (``__pycache__``).
"""

from __future__ import annotations

import math

import numpy as np
from armfusion.models.chain_kernels import cross3
from armfusion.models.rotations import TWO_PI
from armfusion.models.sensor_kernels import gravity_plus, magnetic_heading_one, tilt_up, to_sensor_axes
from numba import njit


@njit(cache=True, nogil=True)
def measurement_points(X, sel, links, axes, offset_ref, motion_mps2, R_0S, imu_index, roll, accel, yaw,
                       imu_bias, g_mps2, still, m_B, heading_shift):  # pragma: no cover - compiled
    """Every measurement of one update at every sigma point ``X (N, n)`` -> ``(N, m)``.

    Columns: the accelerometers ``sel`` (indices into the tracker's accelerometers; three
    columns each, specific force in g, in ``sel``'s order), then with ``still`` the base's
    acceleration (three columns: a parked chair's is zero), then, when ``m_B`` (the
    magnetometer's mean field, base axes, µT) is finite, the heading residual
    ``yaw - tilt-compensated heading`` wrapped to [-pi, pi) (``heading_shift``:
    declination - pi).

    The accelerometers (the model of :mod:`armfusion.models.sensor_kernels`, ``f = R_0S^T (a + g up)``):
    each point's base-axis specific force is the frame's motion acceleration (at the mean
    pose) plus the point's base acceleration plus gravity turned by its roll and pitch (``g
    up``, :func:`armfusion.models.sensor_kernels.tilt_up`), carried to the sensor by the joints
    between the base and its link. The point's joint angles
    differ from the frame's by ``d_j = offset_j - offset_ref_j``, so its rotation is the
    frame's times ``exp([a_j]x d_j)`` for each joint ``j`` below the link (product of
    exponentials about the base-axis joint axes ``axes`` of the frame): in row form
    ``f^T = v^T E_0 … E_(link-1) R_0S / g``, each ``v^T E_j`` being
    ``v - sin d (a x v) + (1 - cos d) a x (a x v)``. The IMU (``imu_index``) adds its bias.
    The heading is :func:`armfusion.models.sensor_kernels.magnetic_heading_one` at the point's roll and
    pitch: the residual ``yaw - heading - heading_shift``, wrapped.
    """
    N = X.shape[0]
    k = sel.shape[0]
    n_joints = axes.shape[0]
    have_mag = math.isfinite(m_B[0]) and math.isfinite(m_B[1]) and math.isfinite(m_B[2])
    m = 3 * k + (3 if still else 0) + (1 if have_mag else 0)
    Z = np.empty((N, m))
    sd = np.empty(n_joints)
    omc = np.empty(n_joints)
    for i in range(N):
        sr, cr = math.sin(X[i, roll]), math.cos(X[i, roll])
        sp, cp = math.sin(X[i, roll + 1]), math.cos(X[i, roll + 1])
        u0, u1, u2 = tilt_up(sr, cr, sp, cp)
        # the base's specific force: its acceleration plus g up
        b0, b1, b2 = gravity_plus(X[i, accel], X[i, accel + 1], X[i, accel + 2], u0, u1, u2, g_mps2)
        for j in range(n_joints):
            d = X[i, j] - offset_ref[j]
            sd[j] = math.sin(d)
            omc[j] = 1.0 - math.cos(d)
        for c in range(k):
            s = sel[c]
            v0 = motion_mps2[s, 0] + b0
            v1 = motion_mps2[s, 1] + b1
            v2 = motion_mps2[s, 2] + b2
            for j in range(links[s]):
                a0, a1, a2 = axes[j, 0], axes[j, 1], axes[j, 2]
                c0, c1, c2 = cross3(a0, a1, a2, v0, v1, v2)  # a x v
                e0, e1, e2 = cross3(a0, a1, a2, c0, c1, c2)  # a x (a x v)
                v0 = v0 - sd[j] * c0 + omc[j] * e0
                v1 = v1 - sd[j] * c1 + omc[j] * e1
                v2 = v2 - sd[j] * c2 + omc[j] * e2
            f0, f1, f2 = to_sensor_axes(R_0S[s], v0, v1, v2)
            Z[i, 3 * c], Z[i, 3 * c + 1], Z[i, 3 * c + 2] = f0 / g_mps2, f1 / g_mps2, f2 / g_mps2
            if s == imu_index:
                for r in range(3):
                    Z[i, 3 * c + r] += X[i, imu_bias + r]
        col = 3 * k
        if still:
            for r in range(3):
                Z[i, col + r] = X[i, accel + r]
            col += 3
        if have_mag:
            d = X[i, yaw] - magnetic_heading_one(m_B[0], m_B[1], m_B[2], sr, cr, sp, cp) - heading_shift
            Z[i, col] = (d % TWO_PI) - math.pi
    return Z


# -- the innovation tests' per-instant sums (the slip detector's, the model-change alarm's) ---
@njit(cache=True, nogil=True)
def add_normalised_innovations(which, nu, Su, sums, counts):  # pragma: no cover - compiled
    """The slip detector's per-instant sums (:meth:`armfusion.fusion.tracking.slips.SlipDetector.listen`):
    for each accelerometer ``which[i]``, ``sums[which[i]] += nu[i] / sqrt(diag(Su[i]))`` (its
    innovation ``nu (k, 3)``, g, over each axis's sigma) and ``counts[which[i]] += 1``."""
    for i in range(which.shape[0]):
        s = which[i]
        for a in range(3):
            sums[s, a] += nu[i, a] / math.sqrt(Su[i, a, a])
        counts[s] += 1


@njit(cache=True, nogil=True)
def add_block_sums(which, nu, Su, z_pred, var, rows, sum_nu, sum_g, sum_r, sum_var,
                   counts):  # pragma: no cover - compiled
    """The model-change alarm's per-instant sums
    (:meth:`armfusion.fusion.tracking.alarm.ModelChangeAlarm.listen`): for each accelerometer
    ``which[i]`` with innovation ``nu[i] (3,)`` and its covariance ``Su[i] (3, 3)``, whose
    update rows are ``rows[i] (3,)`` (its predicted force in ``z_pred``, its measurement
    variances in ``var``): the innovation, the prediction, the noise ``r`` (the mean of its
    three variances) and the filter's own share ``max(trace(Su) / 3 - r, 0)`` added to the
    sums, the count by one. (Summed in the order NumPy's ``mean`` and ``trace`` sum, so the
    figures are the same to the bit.)"""
    for i in range(which.shape[0]):
        s = which[i]
        r0, r1, r2 = rows[i, 0], rows[i, 1], rows[i, 2]
        r = (var[r0] + var[r1] + var[r2]) / 3.0
        sum_nu[s, 0] += nu[i, 0]
        sum_nu[s, 1] += nu[i, 1]
        sum_nu[s, 2] += nu[i, 2]
        sum_g[s, 0] += z_pred[r0]
        sum_g[s, 1] += z_pred[r1]
        sum_g[s, 2] += z_pred[r2]
        sum_r[s] += r
        own = (Su[i, 0, 0] + Su[i, 1, 1] + Su[i, 2, 2]) / 3.0 - r
        if own <= 0.0:  # (as np.maximum(own, 0): NaN stays, -0 becomes 0)
            own = 0.0
        sum_var[s] += own
        counts[s] += 1


# -- the accelerometers' health screening (armfusion.fusion.tracking.health.SensorHealth.accel) ----------
@njit(cache=True, nogil=True)
def screen_accelerometers(sel, counts, f, z_pred, last_counts, tol_g, same,
                          implausible):  # pragma: no cover - compiled
    """For the accelerometers ``sel (k,)`` of one update, whose raw ``counts (k, 3)`` read
    ``f (k, 3)`` (g) where ``z_pred`` (their three rows each, in ``sel``'s order, first)
    predicted the specific force: ``same[i]``, the counts identical to the sensor's last
    (``last_counts (Sa, 3)``, then set to these; NaN: none yet), and ``implausible[i]``, the
    reading's magnitude further than ``tol_g`` from the prediction's (a dead sensor). Returns
    whether any sample is either."""
    flagged = False
    for i in range(sel.shape[0]):
        s = sel[i]
        c0, c1, c2 = counts[i, 0], counts[i, 1], counts[i, 2]
        same[i] = c0 == last_counts[s, 0] and c1 == last_counts[s, 1] and c2 == last_counts[s, 2]
        last_counts[s, 0], last_counts[s, 1], last_counts[s, 2] = c0, c1, c2
        a, b, c = f[i, 0], f[i, 1], f[i, 2]
        u, v, w = z_pred[3 * i], z_pred[3 * i + 1], z_pred[3 * i + 2]
        implausible[i] = abs(math.sqrt(a * a + b * b + c * c) - math.sqrt(u * u + v * v + w * w)) > tol_g
        flagged = flagged or same[i] or implausible[i]
    return flagged


@njit(cache=True, nogil=True)
def close_slip_block(t, sums, counts, n_links, taus, thresholds, shift_t, shift, stat, heard, a_out,
                     var_w_out):  # pragma: no cover - compiled
    """The slip detector's block at ``t`` (:meth:`armfusion.fusion.tracking.slips.SlipDetector.listen`):
    every link accelerometer ``s < n_links`` heard in it (``counts[s] > 0``; ``heard[s]``
    says which) gets its mean normalised innovation ``sums[s] / counts[s]`` into its
    averages on each time scale (``shift[s] (2, 3)``, weight ``a = min(1, dt / taus)``,
    ``dt`` since its last block ``shift_t[s]``, 0 the first time), and its test statistic
    ``|shift|² / var_w / thresholds`` (``var_w = a / (2 - a) / count``: the average of unit
    white noise; 0 where ``a`` is 0), the worst of the two in ``stat[s]``; ``a_out`` and
    ``var_w_out (n_links, 2)`` keep ``a`` and ``var_w`` for the caller. The sums and counts
    of every sensor start again. Returns how many link accelerometers were heard, -1 (with
    nothing done) when no sensor was summed at all."""
    if not (counts != 0).any():
        return -1
    k = 0
    for s in range(n_links):
        c = counts[s]
        heard[s] = c > 0
        if c <= 0:
            continue
        k += 1
        last = shift_t[s]
        dt = 0.0 if math.isnan(last) else t - last
        shift_t[s] = t
        worst = 0.0
        for j in range(2):
            a = min(1.0, dt / taus[j])
            e2 = 0.0
            for ax in range(3):
                e = shift[s, j, ax]
                e = e + a * (sums[s, ax] / c - e)
                shift[s, j, ax] = e
                e2 = e * e if ax == 0 else e2 + e * e
            pos = a > 0
            var_w = (a if pos else 1.0) / ((2.0 - a) * c)
            st = e2 / var_w if pos else 0.0
            st /= thresholds[j]
            a_out[s, j], var_w_out[s, j] = a, var_w
            # the larger of the two, NaN if either is (np.max's)
            if j == 0 or (not math.isnan(worst) and (st > worst or math.isnan(st))):
                worst = st
        stat[s] = worst
    sums[:] = 0.0
    counts[:] = 0
    return k


# -- rows kept per instant (copies: the accelerometers' innovation ring, a run's arrays) --------
@njit(cache=True, nogil=True)
def ring_row_into(i, t, nu, S, nis, ok, ring_t, ring_nu, ring_S, ring_nis, ring_ok, present, nis_sum,
                  count_nis):  # pragma: no cover - compiled
    """Row ``i`` of the accelerometers' innovation ring (:class:`armfusion.fusion.tracking.innovations.AccelRing`)
    set to one update's with every accelerometer, in order: time ``t``, innovations ``nu (Sa, 3)``,
    their covariances ``S (Sa, 3, 3)``, NIS and acceptance ``(Sa,)``, every sensor present; with
    ``count_nis`` each NIS added to ``nis_sum``."""
    ring_t[i] = t
    for s in range(nu.shape[0]):
        present[i, s] = True
        ring_nis[i, s] = nis[s]
        ring_ok[i, s] = ok[s]
        for a in range(3):
            ring_nu[i, s, a] = nu[s, a]
            for b in range(3):
                ring_S[i, s, a, b] = S[s, a, b]
        if count_nis:
            nis_sum[s] += nis[s]


@njit(cache=True, nogil=True)
def state_row_into(i, x, P, att_rows, att_cols, nees_rows, nees_cols, x_out, var_out, att_out,
                   P_out):  # pragma: no cover - compiled
    """Row ``i`` of a run's arrays (:class:`armfusion.fusion.tracking.run.RunArrays`) from the state ``x``
    and its covariance ``P``: ``x``, ``diag(P)``, the attitude's covariance entries
    ``P[att_rows, att_cols]`` and, when ``P_out`` has rows, the NEES states' ``P[nees_rows,
    nees_cols]`` (flattened)."""
    for j in range(x.shape[0]):
        x_out[i, j] = x[j]
        var_out[i, j] = P[j, j]
    for j in range(att_rows.shape[0]):
        att_out[i, j] = P[att_rows[j], att_cols[j]]
    if P_out.shape[0]:
        for j in range(nees_rows.shape[0]):
            P_out[i, j] = P[nees_rows[j], nees_cols[j]]
