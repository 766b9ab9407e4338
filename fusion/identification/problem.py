"""The fit problem: the noise-weighted residuals of every reading (prediction minus
measurement) and their Jacobian over the model's elements and the base attitude.

:class:`FitProblem` holds a model, the data (:class:`~armfusion.fusion.identification.data.FitData`)
and the streams fitted. The model's columns are analytic (:meth:`Model.predict_with_jacobian`);
the base attitude's (one roll, pitch, yaw per parked stance) and the encoder scales' without
a joint offset beside them are forward differences of the model. One-time joint references
are pseudo-measurements of a joint's geometric angle. :meth:`FitProblem.normal_equations`
accumulates ``JᵀJ``, ``Jᵀr`` and ``rᵀr`` chunk by chunk, so memory stays bounded whatever
the recording's length.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from armfusion.fusion.identification.data import FitData
from armfusion.fusion.identification.references import ReferenceRows
from armfusion.models.effects import Model
from armfusion.models.effects.library import EncoderScale
from armfusion.models.motion import MotionState
from armfusion.models.rotations import DEG, R_from_rpy

ATTITUDE = "base.attitude"
ATTITUDE_LABELS = ("roll", "pitch", "yaw")
ATTITUDE_SIGMA_RAD = np.array([10 * DEG, 10 * DEG, 180 * DEG])
CHUNK_POINTS = 1500
"""Points per chunk of :meth:`FitProblem.normal_equations` (its memory bound)."""


def attitude_names(n_stances: int) -> tuple[str, ...]:
    """The base attitude's element names: ``base.attitude[roll]``… for one stance,
    ``base.attitude[2.roll]``… (stance 2 of K, from 1) for several."""
    if n_stances == 1:
        return tuple(f"{ATTITUDE}[{k}]" for k in ATTITUDE_LABELS)
    return tuple(f"{ATTITUDE}[{i + 1}.{k}]" for i in range(n_stances) for k in ATTITUDE_LABELS)


def scaled_joints(st: MotionState, z: np.ndarray, enc_scale: Sequence[tuple[int, int, str | None]],
                  q_ref_rad: np.ndarray, n_joints: int) -> MotionState:
    """The motion ``st`` with the encoder scale errors at ``z`` taken out: a joint whose encoder
    counts too fast by ``s`` (``z[c]``, for each ``(c, joint, _)`` of ``enc_scale``) stands at
    ``q_ref + (encoder angle)/(1 + s)``, its rate and acceleration scaled alike."""
    if not enc_scale:
        return st
    f = np.ones(n_joints)
    for c, j, _ in enc_scale:
        f[j] = 1.0 / (1.0 + z[c])
    if np.all(f == 1.0):
        return st
    return st.replace(q_rad=q_ref_rad + (st.q_rad - q_ref_rad) * f, qd_rad_s=st.qd_rad_s * f,
                      qdd_rad_s2=st.qdd_rad_s2 * f)


class FitProblem:
    """The weighted least-squares problem of one fit. Its unknowns ``z`` are the model's
    elements (``P`` of them) then, with ``attitude``, a roll, pitch and yaw per parked stance
    (``K``); ``x0``, ``sigma0``, ``lower``, ``upper`` are their priors and bounds, ``names``
    their element names. ``encoder_scale``: the model's ``encoder_scale`` effects act on the
    fit's joint angles."""

    def __init__(self, model: Model, data: FitData, streams: Sequence[str], attitude: bool,
                 attitude0: np.ndarray, encoder_scale: bool = False):
        self.model = model
        self.data = data
        self.streams = [s for s in streams if s in data.counts]
        if not self.streams:
            raise ValueError("no measured stream to fit (streams: " + ", ".join(streams) + ")")
        self.attitude = attitude
        self.P = model.size
        # one attitude per parked stance (the chair tilted differently in each)
        self.K = data.n_stances
        K = self.K if attitude else 0
        self.size = model.size + 3 * K
        self.names = tuple(model.element_names()) + attitude_names(K)
        att0 = np.broadcast_to(np.asarray(attitude0, float).reshape(-1, 3)
                               if np.size(attitude0) else np.zeros((1, 3)), (max(K, 1), 3))
        self.x0 = np.concatenate([model.x0, att0[:K].ravel()])
        self.sigma0 = np.concatenate([model.prior_sigma, np.tile(ATTITUDE_SIGMA_RAD, K)])
        self.lower = np.concatenate([model.lower, np.tile([-np.pi / 2, -np.pi / 2, -4 * np.pi], K)])
        self.upper = np.concatenate([model.upper, np.tile([np.pi / 2, np.pi / 2, 4 * np.pi], K)])
        ref = data.base_tilt_reference
        if K and ref is not None:  # an independent measurement of the first stance's tilt
            tilt, sig = np.asarray(ref[0], float).reshape(2), float(ref[1])
            if not sig > 0 or not np.all(np.abs(tilt) < np.pi / 2):
                raise ValueError(f"base tilt reference: roll and pitch within ±90° and a positive σ, "
                                 f"got {np.degrees(tilt)} deg ± {np.degrees(sig)} deg")
            self.x0[self.P:self.P + 2] = tilt
            self.sigma0[self.P:self.P + 2] = sig
        self.meas = np.concatenate([data.counts[s].ravel() for s in self.streams])
        self.w = self.measurements(None, None)[1]
        self.base_rpy = np.zeros(3)
        self._R0 = data.state.R_WB
        # encoder scale errors: the fit's joint angles come from the encoders, so a joint whose
        # encoder counts too fast stands at q_ref + (encoder angle)/(1 + s); its column is the
        # joint's sensitivity (its joint_offset column, where the model has one) times
        # -(encoder angle)/(1 + s)²
        self.enc_scale: list[tuple[int, int, str | None]] = []
        for e in model.effects:
            if encoder_scale and e.name == EncoderScale.name:
                off = f"{e.target}.joint_offset"
                self.enc_scale.append((model.index[e.block_name].start, e.j,
                                       off if off in model.index else None))
        self.refs = tuple(data.joint_references)
        self._references = ReferenceRows.of(model, data, self.size, encoder_scale)

    def reference_angles(self, z: np.ndarray) -> np.ndarray:
        """Each reference's joint's geometric angle at the reference, as the fit at ``z`` has it."""
        ref = self._references
        st = self._scaled_joints(MotionState.static(self.data.q_ref_rad + ref.encoder_rad), z)
        if self.attitude:
            a = z[self.P:].reshape(-1, 3)[ref.stance]
            st = st.replace(R_WB=R_from_rpy(a[:, 0], a[:, 1], a[:, 2]))
        else:
            st = st.replace(R_WB=np.asarray(self._R0)[ref.point * self.data.nodes])
        ctx = self.model.context(st, z[: self.P], (ref.stream,))
        return np.asarray(ctx.q_geom, float)[np.arange(len(self.refs)), ref.joint]

    def reference_residual(self, z: np.ndarray) -> np.ndarray:
        """The references' weighted residuals at ``z`` (none without references)."""
        if not self.refs:
            return np.zeros(0)
        return self._references.residual(self.reference_angles(z))

    def reference_rows(self, z: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The references' weighted residuals and their Jacobian over columns ``cols`` (forward
        differences: one still instant per reference, only the columns that can move it)."""
        r = self.reference_residual(z)
        J = np.zeros((len(r), len(cols)))
        if not len(r):
            return r, J
        moving = set(self._references.cols.tolist())
        for i, c in enumerate(cols):
            if int(c) in moving:
                h = 1e-3 * self.sigma0[c]
                zz = np.array(z, float)
                zz[c] += h
                J[:, i] = (self.reference_residual(zz) - r) / h
        return r, J

    def _scaled_joints(self, st: MotionState, z: np.ndarray) -> MotionState:
        return scaled_joints(st, z, self.enc_scale, self.data.q_ref_rad, self.model.arm.n_joints)

    def state(self, z: np.ndarray, rows: slice | None = None) -> MotionState:
        return self._state_of(self.data if rows is None else self.data.subset(rows), z)

    def _state_of(self, d: FitData, z: np.ndarray) -> MotionState:
        st = self._scaled_joints(d.state, z)
        if not self.attitude:
            return st
        a = z[self.P:].reshape(-1, 3)
        R = R_from_rpy(a[:, 0], a[:, 1], a[:, 2])
        if len(a) == 1:
            return st.replace(R_WB=np.broadcast_to(R[0], st.R_WB.shape).copy())
        return st.replace(R_WB=R[d.stance_of_instants()])

    def _mean_nodes(self, a: np.ndarray) -> np.ndarray:
        k = self.data.nodes
        if k == 2:  # the usual two Gauss nodes: the same sum and halving as mean(), without its overhead
            return (a[0::2] + a[1::2]) * 0.5
        return a if k == 1 else a.reshape(a.shape[0] // k, k, *a.shape[1:]).mean(1)

    def predict(self, z: np.ndarray) -> np.ndarray:
        p = self.model.predict(self.state(z), z[: self.P], self.streams)
        return np.concatenate([self._mean_nodes(p[s]).ravel() for s in self.streams])

    def residual(self, z: np.ndarray) -> np.ndarray:
        return (self.predict(z) - self.meas) * self.w

    def jacobian(self, z: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted residual and Jacobian columns ``cols`` (indices into z)."""
        return self._jacobian_rows(z, cols, None, None, self.w)

    def measurements(self, rows: slice | None, keep: slice | None, w_stream: dict[str, float] | None = None):
        """Measurements and weights of the points ``rows`` (then ``keep`` of them), stream-major."""
        d = self.data
        meas, w = [], []
        used = None
        if d.used is not None:
            used = d.used if rows is None else d.used[rows]
            if keep is not None:
                used = used[keep]
        for s in self.streams:
            c = d.counts[s] if rows is None else d.counts[s][rows]
            if keep is not None:
                c = c[keep]
            ws = np.broadcast_to(1.0 / d.sigma_counts[s], c.shape) * (1.0 if w_stream is None
                                                                      else w_stream[s])
            if used is not None:  # points while the chair moves weigh nothing
                ws = ws * used[:, None]
            meas.append(c.ravel())
            w.append(ws.ravel())
        return np.concatenate(meas), np.concatenate(w)

    def _predicted(self, z, cols, rows, keep):
        """The model's prediction at ``z`` of the points ``rows`` (then ``keep`` of them), per
        stream and node-averaged, with the block Jacobians that columns ``cols`` need; the
        state it was evaluated at; and the encoder-scale columns among ``cols`` (column ->
        its joint and the joint offset block beside it, or None)."""
        m = self.model
        mcols = cols[cols < self.P]
        want = set(b.name for b in m.blocks
                   if np.any((mcols >= m.index[b.name].start) & (mcols < m.index[b.name].stop)))
        enc_cols = {c: (j, off) for c, j, off in self.enc_scale if c in set(mcols.tolist())}
        want |= {off for _, off in enc_cols.values() if off is not None}
        blocks = [b.name for b in m.blocks if b.name in want]
        st = self.state(z, rows)
        pred, jac = m.predict_with_jacobian(st, z[: self.P], self.streams, blocks=blocks)
        if self.data.nodes > 1:
            pred = {s: self._mean_nodes(pred[s]) for s in self.streams}
            jac = {s: {b: self._mean_nodes(v) for b, v in jac.get(s, {}).items()} for s in self.streams}
        if keep is not None:
            pred = {s: pred[s][keep] for s in self.streams}
            jac = {s: {b: v[keep] for b, v in jac.get(s, {}).items()} for s in self.streams}
        else:
            pred = {s: pred[s] for s in self.streams}
        return st, pred, jac, enc_cols

    def _model_columns(self, J, cols, enc_cols, pred, jac, w) -> dict[str, slice]:
        """Fill ``J``'s columns of the model's own elements straight from each stream's block
        Jacobians, weighted; returns each stream's rows."""
        at = {int(c): i for i, c in enumerate(cols) if c < self.P and c not in enc_cols}
        span: dict[str, slice] = {}
        o = 0
        for s in self.streams:
            n_s = pred[s].size
            span[s] = slice(o, o + n_s)
            for b, v in jac.get(s, {}).items():
                first = self.model.index[b].start
                src = [jj for jj in range(v.shape[-1]) if first + jj in at]
                if src:
                    J[span[s], [at[first + jj] for jj in src]] = v.reshape(n_s, -1)[:, src] * w[span[s], None]
            o += n_s
        return span

    def _jacobian_rows(self, z, cols, rows, keep, w, meas=None):
        """Weighted residuals of the points ``rows`` (then ``keep`` of them) and their Jacobian
        over columns ``cols``: the model's own columns analytic (:meth:`_model_columns`), an
        encoder scale's from its joint offset's column where the model has one, the rest
        (the base attitude, an encoder scale alone) forward differences."""
        st, pred, jac, enc_cols = self._predicted(z, cols, rows, keep)
        y = np.concatenate([pred[s].ravel() for s in self.streams])
        if meas is None:
            meas = self.meas
        r = (y - meas) * w
        J = np.zeros((len(r), len(cols)))
        span = self._model_columns(J, cols, enc_cols, pred, jac, w)

        def offset_column(block: str) -> np.ndarray:  # a joint offset's column, unweighted
            col = np.zeros(len(r))
            for s in self.streams:
                if block in jac.get(s, {}):
                    col[span[s]] = jac[s][block].reshape(pred[s].size, -1)[:, 0]
            return col
        enc = None
        for i, c in enumerate(cols):
            if c < self.P and c not in enc_cols:
                continue
            if c in enc_cols:
                j, off = enc_cols[c]
                if enc is None:  # each point's encoder angle, repeated over the stream's axes
                    q_pts = self._mean_nodes(st.q_rad)
                    q = q_pts if keep is None else q_pts[keep]
                    enc = (q - self.data.q_ref_rad)
                    enc = np.concatenate([np.repeat(enc, pred[s].shape[1], axis=0).reshape(
                        len(q), pred[s].shape[1], -1).reshape(-1, enc.shape[1]) for s in self.streams])
                if off is not None:
                    J[:, i] = offset_column(off) * w * (-enc[:, j] / (1.0 + z[c]))
                else:
                    J[:, i] = self._numeric_column(z, c, y, w, rows, keep)
            elif self.K == 1:  # base attitude: forward differences of the model
                J[:, i] = self._numeric_column(z, c, y, w, rows, keep)
            else:  # one stance's attitude: forward differences on that stance's points only
                J[:, i] = self._stance_column(z, c, y, w, rows, keep, {s: pred[s].shape[1]
                                                                      for s in self.streams})
        return r, J

    def _stance_column(self, z, c, y, w, rows, keep, dims, h=1e-6):
        """An attitude column of stance k: only its points change. The model is evaluated on
        them with two points either side (so a time derivative there uses the same
        neighbours as the whole chunk's) and the column is zero elsewhere."""
        d = self.data if rows is None else self.data.subset(rows)
        pts = np.arange(d.n) if keep is None else np.arange(d.n)[keep]
        k = (c - self.P) // 3
        sel = np.flatnonzero(d.stance[pts] == k)  # positions among the kept points
        col = np.zeros(len(y))
        if not len(sel):
            return col
        a, b = max(0, pts[sel[0]] - 2), min(d.n, pts[sel[-1]] + 3)
        zz = np.array(z, float)
        zz[c] += h
        sub = d.subset(slice(a, b))
        p = self.model.predict(self._state_of(sub, zz), zz[: self.P], self.streams)
        at = pts[sel] - a
        off = 0
        for s in self.streams:
            m = dims[s]
            ps = self._mean_nodes(p[s])[at]
            idx = off + (sel[:, None] * m + np.arange(m)).ravel()
            col[idx] = (ps.ravel() - y[idx]) * w[idx] / h
            off += len(pts) * m
        return col

    def _numeric_column(self, z, c, y, w, rows, keep, h=1e-6):
        zz = np.array(z, float)
        zz[c] += h
        p = self.model.predict(self.state(zz, rows), zz[: self.P], self.streams)
        p = {s: self._mean_nodes(p[s]) for s in self.streams}
        if keep is not None:
            p = {s: p[s][keep] for s in self.streams}
        return (np.concatenate([p[s].ravel() for s in self.streams]) - y) * w / h

    def normal_equations(self, z: np.ndarray, cols: np.ndarray, w_stream: dict[str, float] | None = None,
                         chunk: int = CHUNK_POINTS, rows_out: list | None = None
                         ) -> tuple[np.ndarray, np.ndarray, float]:
        """``JᵀJ``, ``Jᵀr`` and ``rᵀr`` over columns ``cols``, accumulated ``chunk`` points at a
        time (memory stays bounded whatever the recording's length). Chunks overlap by two
        points on each side so the time derivatives of the time offsets are those of the
        whole series; ``w_stream`` scales each stream's weights. ``rows_out``: a list that
        receives each chunk's ``(r, J)`` (the references' last); on a problem of at most
        ``chunk`` points, stacked they are the rows of :meth:`residual_rows`."""
        n = self.data.n
        H = np.zeros((len(cols), len(cols)))
        g = np.zeros(len(cols))
        rr = 0.0
        pad = 2
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            lo, hi = max(0, a - pad), min(n, b + pad)
            keep = slice(a - lo, a - lo + (b - a))
            meas, w = self.measurements(slice(lo, hi), keep, w_stream)
            r, J = self._jacobian_rows(z, cols, slice(lo, hi), keep, w, meas)
            H += J.T @ J
            g += J.T @ r
            rr += float(r @ r)
            if rows_out is not None:
                rows_out.append((r, J))
        if self.refs:
            r, J = self.reference_rows(z, np.asarray(cols))
            H += J.T @ J
            g += J.T @ r
            rr += float(r @ r)
            if rows_out is not None:
                rows_out.append((r, J))
        return H, g, rr

    def residual_rows(self, z: np.ndarray, w_stream: dict[str, float] | None = None) -> np.ndarray:
        """Every weighted residual at ``z``, stream by stream, then the references': the rows
        of :meth:`normal_equations` when the problem has at most one chunk of points."""
        meas, w = self.measurements(None, None, w_stream)
        return np.concatenate([(self.predict(z) - meas) * w, self.reference_residual(z)])
