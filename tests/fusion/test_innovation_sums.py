"""The per-instant bookkeeping compiled in :mod:`armfusion.fusion.tracking.tracker_kernels` (the slip
detector's and the model-change alarm's sums, the slip test's block, the sensor health's
screen, the innovation ring's rows) does what the NumPy and Python forms it replaced did, to
the bit: the tests' averages, hence their verdicts (a slip re-acquired, an alarm raised, a
sensor stuck or dead), are the same as before the kernels. Summed over many instants, any
difference in the order of the additions would show in the last bits."""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.alarm import AccelRows, ModelChangeAlarm
from armfusion.fusion.tracking.tracker_kernels import add_block_sums, add_normalised_innovations


def _instants(rng, steps: int, k: int):
    """Innovations ``(k, 3)``, their covariances ``(k, 3, 3)`` (symmetric, positive), the
    update's predictions and variances (``3k`` rows, then a heading row)."""
    for _ in range(steps):
        nu = rng.normal(0.0, 0.01, (k, 3)) * rng.choice([1e-3, 1.0, 30.0], (k, 1))
        A = rng.normal(0.0, 0.01, (k, 3, 3))
        Su = A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(3)
        z_pred = rng.normal(0.0, 1.0, 3 * k + 1)
        var = rng.uniform(1e-7, 1e-4, 3 * k + 1)
        yield nu, Su, z_pred, var


def test_the_slip_sums_equal_numpys_over_many_instants_any_subset():
    rng = np.random.default_rng(3)
    k = 5
    ref_sum, ref_n = np.zeros((k, 3)), np.zeros(k, dtype=np.int64)
    got_sum, got_n = np.zeros((k, 3)), np.zeros(k, dtype=np.int64)
    for step, (nu, Su, _, _) in enumerate(_instants(rng, 400, k)):
        u = np.arange(k) if step % 3 else np.array([0, 2, 4])  # every sensor, or some
        nu, Su = nu[: len(u)], Su[: len(u)]
        ref_sum[u] += nu / np.sqrt(np.diagonal(Su, axis1=1, axis2=2))  # the replaced form
        ref_n[u] += 1
        add_normalised_innovations(u.astype(np.int64), nu, Su, got_sum, got_n)
    assert np.array_equal(got_sum, ref_sum)
    assert np.array_equal(got_n, ref_n)


def test_the_alarm_sums_equal_numpys_including_a_negative_and_a_nan_share():
    rng = np.random.default_rng(4)
    k = 4
    rows = np.arange(3 * k).reshape(k, 3)
    ref = [np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k), np.zeros(k), np.zeros(k, dtype=np.int64)]
    got = [np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k), np.zeros(k), np.zeros(k, dtype=np.int64)]
    for step, (nu, Su, z_pred, var) in enumerate(_instants(rng, 400, k)):
        if step == 7:
            Su[1] *= 1e-6  # the filter's own share below the noise: clipped at zero
        if step == 399:
            Su[2, 0, 0] = np.nan  # a NaN share stays NaN (np.maximum's)
        idx = np.arange(k) if step % 4 else np.array([1, 3])
        pos = rows[idx]
        n_, S_ = nu[idx], Su[idx]
        # the replaced NumPy form (alarm.listen before the kernel)
        r = var[pos].mean(1)
        ref[0][idx] += n_
        ref[1][idx] += z_pred[pos]
        ref[2][idx] += r
        ref[3][idx] += np.maximum(np.trace(S_, axis1=1, axis2=2) / 3.0 - r, 0.0)
        ref[4][idx] += 1
        add_block_sums(idx.astype(np.int64), n_, S_, z_pred, var, pos, *got)
    for a, b in zip(got, ref, strict=True):
        assert np.array_equal(a, b, equal_nan=True)
    assert np.isnan(got[3][2]) and np.isfinite(got[3][[0, 1, 3]]).all()


def test_the_alarm_counts_every_sensor_alike_given_all_of_them_or_their_indices():
    """The update with every accelerometer in order (a slice) and the same update named
    sensor by sensor (indices, the IMU last and left out) give the alarm the same sums."""
    rng = np.random.default_rng(5)
    names = ("acc1", "acc2", "acc3", "acc4")
    a_all = ModelChangeAlarm(names, None, 0.0)
    a_idx = ModelChangeAlarm(names, None, 0.0)
    rows = np.arange(15).reshape(5, 3)
    sel = np.arange(5)
    for i, (nu, Su, z_pred, var) in enumerate(_instants(rng, 60, 5)):
        t = 0.01 * (i + 1)
        a_all.listen(t, slice(0, 5), nu, Su, AccelRows(z_pred, var, rows, sel), True)
        a_idx.listen(t, sel, nu, Su, AccelRows(z_pred, var, rows, sel), True)
    for name in ("_sum_nu", "_sum_g", "_sum_r", "_sum_var", "_n", "_ema"):
        assert np.array_equal(getattr(a_all, name), getattr(a_idx, name)), name
    # a block closed at 0.5 s (its means in the test's average), ten instants summed since
    assert a_all._n.tolist() == [10, 10, 10, 10]
    assert np.abs(a_all._ema).min() > 0.0


def test_the_health_screen_flags_the_samples_the_plain_python_form_flagged():
    """Stuck (identical counts in a row) and implausible (magnitude off the prediction by
    more than the tolerance) as the sensor-by-sensor Python form had them, any subset."""
    from armfusion.fusion.tracking.tracker_kernels import screen_accelerometers

    rng = np.random.default_rng(6)
    Sa, tol = 5, 0.35
    last = np.full((Sa, 3), np.nan)
    ref_last: list = [None] * Sa
    seen_same = seen_implausible = 0
    for step in range(300):
        sel = np.arange(Sa) if step % 2 else np.sort(rng.choice(Sa, 3, replace=False))
        k = len(sel)
        counts = rng.integers(-3, 4, (k, 3)).astype(float)  # few values: repeats happen
        f = rng.normal(0.0, 0.6, (k, 3))
        z_pred = np.r_[rng.normal(0.0, 0.6, 3 * k), 0.1]
        same, implausible = np.empty(k, bool), np.empty(k, bool)
        flagged = screen_accelerometers(sel.astype(np.int64), counts, f, z_pred, last, tol, same, implausible)
        cl = counts.tolist()
        want_same = [c == ref_last[s] for c, s in zip(cl, sel.tolist(), strict=True)]
        for c, s in zip(cl, sel.tolist(), strict=True):
            ref_last[s] = c
        want_imp = [abs(np.sqrt(a * a + b * b + c * c) - np.sqrt(u * u + v * v + w * w)) > tol
                    for (a, b, c), (u, v, w) in zip(f.tolist(), z_pred[:3 * k].reshape(k, 3).tolist(),
                                                    strict=True)]
        assert same.tolist() == want_same and implausible.tolist() == want_imp
        assert flagged == (any(want_same) or any(want_imp))
        seen_same += sum(want_same)
        seen_implausible += sum(want_imp)
    assert seen_same > 0 and seen_implausible > 0  # both verdicts were exercised


class _SlipTestBefore:
    """The slip detector's block test as NumPy computed it before the kernel (the reference)."""

    def __init__(self, det):
        self.d = det
        self.shift, self.shift_t = det.shift.copy(), det.shift_t.copy()
        self._stat, self._cool = det._stat.copy(), det._cool.copy()
        self._sum, self._n = np.zeros_like(det._sum), np.zeros_like(det._n)
        self._block_t = det._block_t

    def listen(self, t, u, nu, Su, calm, reacquire):
        if calm:
            self._sum[u] += nu / np.sqrt(np.diagonal(Su, axis1=1, axis2=2))
            self._n[u] += 1
        else:
            self.shift_t[u] = t
            self._sum[u] = 0.0
            self._n[u] = 0
        if t - self._block_t >= 0.05 and self._n.any():
            nl = self.d.n_links
            have = (self._n[:nl] > 0).nonzero()[0]
            if len(have):
                n_ = self._n[have]
                self._detect(t, slice(0, nl) if len(have) == nl else have, self._sum[have] / n_[:, None], n_,
                             reacquire)
            self._sum[:] = 0.0
            self._n[:] = 0
            self._block_t = t

    def _detect(self, t, which, nu_w, count, reacquire):
        d = self.d
        last = self.shift_t[which]
        dt = np.where(np.isnan(last), 0.0, t - last)
        self.shift_t[which] = t
        a = np.minimum(1.0, dt[:, None] / d._taus)
        ema = self.shift[which]
        ema += a[:, :, None] * (nu_w[:, None, :] - ema)
        self.shift[which] = ema
        pos = a > 0
        var_w = np.where(pos, a, 1.0) / ((2.0 - a) * count[:, None])
        stat = np.square(ema).sum(axis=2) / var_w
        stat[~pos] = 0.0
        stat /= d._thr
        self._stat[which] = worst = stat.max(axis=1)
        cal = d.calibration[which]
        if cal.any():
            M = cal[:, None] + var_w[:, :, None, None] * np.eye(3)
            stat = np.einsum("kti,kti->kt", ema, np.linalg.solve(M, ema[..., None])[..., 0])
            stat[~pos] = 0.0
            stat /= d._thr
            worst = stat.max(axis=1)
        hit = worst > 1.0
        if hit.any():
            ids = np.arange(len(self.shift_t))[which]
            for s in ids[hit & (t >= self._cool[which])]:
                reacquire(int(s), t)
                self.shift[s] = 0.0
                self._cool[s] = t + d.settings.reacquiring_flag_s


def test_the_slip_test_re_acquires_as_its_numpy_form_did_with_and_without_the_calibrations_error():
    from armfusion.fusion.tracking.settings import StateLayout, TrackerSettings
    from armfusion.fusion.tracking.slips import SlipDetector

    st, n, Sa, nl = TrackerSettings(), 7, 5, 4
    names = ("acc1", "acc2", "acc3", "acc4", "imu_acc", "imu_gyro", "imu_mag", "enc")
    sees = np.array([2, 4, 6, 7, 0])[:, None] > np.arange(n)[None, :]
    for with_cal in (False, True):
        rng = np.random.default_rng(8 + with_cal)
        det = SlipDetector(st, StateLayout(n), names, nl, Sa, sees, 0.0)
        if with_cal:
            A = rng.normal(0.0, 0.3, (nl, 3, 3))
            det.calibration[:] = A @ A.transpose(0, 2, 1)
        ref = _SlipTestBefore(det)
        got_calls, ref_calls = [], []
        for i in range(1500):
            t = 0.01 * (i + 1)
            u = slice(0, Sa) if i % 7 else np.array([0, 2, 4])
            k = Sa if type(u) is slice else 3
            nu = rng.normal(0.0, 0.01, (k, 3))
            if 500 <= i < 900:
                nu[1 if k == Sa else 0] += 0.2  # a lasting shift on one sensor: a slip
            A = rng.normal(0.0, 0.01, (k, 3, 3))
            Su = A @ A.transpose(0, 2, 1) + 1e-4 * np.eye(3)
            calm = i % 50 != 0
            det.listen(t, u, nu, Su, calm, lambda s, tt, calls=got_calls: calls.append((s, tt)))
            ref.listen(t, u, nu, Su, calm, lambda s, tt, calls=ref_calls: calls.append((s, tt)))
        assert got_calls == ref_calls and len(got_calls) >= 1
        for name in ("shift", "shift_t", "_stat", "_cool"):
            assert np.array_equal(getattr(det, name), getattr(ref, name), equal_nan=True), name


def test_the_innovation_ring_keeps_whole_rows_as_it_keeps_rows_sensor_by_sensor():
    """A row of every accelerometer (written compiled) reads back, in each sensor's log and
    its NIS statistics, as the same row given sensor by sensor; a non-finite NIS is kept
    but not counted."""
    from armfusion.fusion.tracking.innovations import AccelRing

    rng = np.random.default_rng(9)
    names = ("acc1", "acc2", "acc3")
    whole, by_sensor = AccelRing(names, 50), AccelRing(names, 150)  # (three rows an instant)
    for i, (nu, Su, _, _) in enumerate(_instants(rng, 80, 3)):  # more rows than the ring holds
        nis = rng.chisquare(3, 3)
        if i == 70:
            nis[1] = np.inf
        ok = nis < 7.8
        whole.add(0.01 * i, np.arange(3), nu, Su, nis, ok)
        for s in range(3):
            by_sensor.add(0.01 * i, np.array([s]), nu[s:s + 1], Su[s:s + 1], nis[s:s + 1], ok[s:s + 1])
    for name in names:
        a, b = whole.log(name), by_sensor.log(name)
        assert len(a.t_s) == 50  # the last 50 rows
        for field in ("t_s", "innovation", "S", "nis", "accepted"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), (name, field)
    assert whole.counts.tolist() == [80, 79, 80]
    np.testing.assert_allclose(whole.nis_sum, by_sensor.nis_sum, rtol=1e-15)
