"""The measurement side of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`: measurement groups
(one sensor's rows, gated as a whole on its normalised innovation squared, NIS), a plan
of them prepared once for updates of the same shape (:class:`GroupPlan`: the NIS of every
group from one Cholesky factor when they tile the rows), the chi-square gate
(:func:`nis_bound`) and an update's :class:`Innovation`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.ukf_kernels import OK, innovation_into
from scipy.linalg import lapack
from scipy.stats import chi2


def group_nis(nu: np.ndarray, S: np.ndarray, rows: Sequence[np.ndarray]) -> np.ndarray:
    """Normalised innovation squared of each group of rows (inf where S is singular).

    Groups of the same size are solved together in one batched call.
    """
    G = len(rows)
    out = np.empty(G)
    sizes = np.array([len(r) for r in rows])
    for k in np.unique(sizes):
        which = np.flatnonzero(sizes == k)
        idx = np.stack([rows[i] for i in which])  # (g, k)
        Sg = S[idx[:, :, None], idx[:, None, :]]  # (g, k, k)
        v = nu[idx]  # (g, k)
        try:
            out[which] = np.einsum("gi,gi->g", v, np.linalg.solve(Sg, v[..., None])[..., 0])
        except np.linalg.LinAlgError:
            out[which] = _nis_each(v, Sg)
    return out


def _nis_each(v: np.ndarray, Sg: np.ndarray) -> np.ndarray:
    """``v[i]^T Sg[i]^-1 v[i]`` group by group (inf where a block is singular)."""
    out = np.empty(len(v))
    for i in range(len(v)):
        try:
            out[i] = v[i] @ np.linalg.solve(Sg[i], v[i])
        except np.linalg.LinAlgError:
            out[i] = np.inf
    return out


def nis_bound(dof: int | np.ndarray, significance: float) -> np.ndarray:
    """The chi-square gate: NIS above this is an outlier at ``significance``."""
    return chi2.ppf(1.0 - significance, dof)


@dataclass(frozen=True)
class MeasurementGroup:
    """A named block of measurement rows (one sensor), gated as a whole."""

    name: str
    rows: np.ndarray  # indices into the stacked measurement vector
    gate: float = np.inf  # NIS above this is rejected (np.inf: never)


class GroupPlan:
    """Measurement groups prepared once for repeated updates of the same shape: their
    names, rows, gates, and the index arrays that batch the NIS of equal-sized groups
    (and, when the groups tile the rows, those the compiled innovation reads:
    :meth:`innovation_compiled`)."""

    def __init__(self, groups: Sequence[MeasurementGroup]):
        self.groups = tuple(groups)
        self.names = tuple(g.name for g in groups)
        self.rows = tuple(np.asarray(g.rows, dtype=int) for g in groups)
        self.gates = np.array([g.gate for g in groups], dtype=float)
        sizes = np.array([len(r) for r in self.rows])
        self.batches = []
        for k in np.unique(sizes):
            which = np.flatnonzero(sizes == k)
            idx = np.stack([self.rows[i] for i in which])
            # groups that tile consecutive rows: their diagonal blocks of S are a view
            r0 = int(idx[0, 0])
            tiles = np.array_equal(idx.reshape(-1), np.arange(r0, r0 + idx.size))
            tile = (r0, len(which), int(k)) if tiles else None
            self.batches.append((which, idx, idx[:, :, None], idx[:, None, :], tile))
        self._finite_gates = bool(np.all(np.isfinite(self.gates)))
        m = int(sum(sizes))
        self.m = m
        # the block diagonal of S (one block per group) and which rows make each group: the
        # NIS of every group from one Cholesky factor, when the groups tile the rows
        self._tiled = m > 0 and np.array_equal(np.sort(np.concatenate(self.rows)), np.arange(m))
        if self._tiled:
            self._block_mask = np.zeros((m, m))
            self._member = np.zeros((m, len(self.rows)))
            for g, r in enumerate(self.rows):
                self._block_mask[np.ix_(r, r)] = 1.0
                self._member[r, g] = 1.0
            # for the compiled innovation: every group's rows one after the other, and where
            # each group's start (group g is group_rows[group_start[g]:group_start[g + 1]])
            self._group_rows = np.ascontiguousarray(np.concatenate(self.rows), dtype=np.int64)
            self._group_start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
            self._gates_c = np.ascontiguousarray(self.gates)
            # the diagonal blocks of S, batch by batch (groups of one size, in order), one
            # after the other in one flat array: where each group's block starts, and each
            # batch's span and shape there
            self._block_start = np.zeros(len(self.rows), dtype=np.int64)
            self._block_spans = []
            start = 0
            for which, idx, _, _, _ in self.batches:
                g, k = idx.shape
                self._block_start[which] = start + k * k * np.arange(g)
                self._block_spans.append((k, which, slice(start, start + g * k * k), (g, k, k)))
                start += g * k * k
            self._block_size = start

    @property
    def tiled(self) -> bool:
        """Whether the groups tile the measurement rows (each row in exactly one group): the
        NIS of every group from one Cholesky factor, and the compiled innovation."""
        return self._tiled

    def gate_ok(self, nis: np.ndarray) -> np.ndarray:
        """Whether each group's NIS passes its gate (a NaN NIS fails any gate; an infinite
        one fails every finite gate)."""
        return nis <= self.gates if self._finite_gates else np.isfinite(nis) & (nis <= self.gates)

    def innovation_compiled(self, z: np.ndarray, Z: np.ndarray, R: np.ndarray, weights: np.ndarray,
                            z_weights: np.ndarray | None, angle_row: int | None,
                            DXW: np.ndarray) -> Innovation | None:
        """The innovation of ``z (m,)`` against the sigma points' measurements ``Z (N, m)``
        from the compiled kernel, for a tiled plan: ``R`` diagonal ``(m,)``, ``weights``
        the points' mean and covariance weights ``(2, N)``, ``z_weights`` those the
        prediction is taken with (None: the mean's), at most one ``angle_row``, ``DXW`` the
        weighted state residuals ``(n, N)``. None when the shapes are not those of the
        common case (the caller's NumPy path takes over)."""
        Zc = np.ascontiguousarray(Z, dtype=np.float64)
        N, n = weights.shape[1], DXW.shape[0]
        m = self.m
        if Zc.shape != (N, m) or z.shape[0] != m or R.shape[0] != m or DXW.shape != (n, N):
            return None
        if angle_row is None:
            angle_row = -1
        elif -m <= angle_row < m:
            angle_row %= m
        else:
            return None
        G = len(self.rows)
        z_pred, nu, S, Pxz = np.empty(m), np.empty(m), np.empty((m, m)), np.empty((n, m))
        flat, nis, ok = np.empty(self._block_size), np.empty(G), np.empty(G, dtype=np.bool_)
        wz = weights[0] if z_weights is None else np.ascontiguousarray(z_weights, dtype=np.float64)
        status = innovation_into(Zc, weights, wz, angle_row, np.ascontiguousarray(z),
                                 np.ascontiguousarray(R), np.ascontiguousarray(DXW), self._group_rows,
                                 self._group_start, self._block_start, self._gates_c,
                                 z_pred, nu, S, Pxz, flat, nis, ok)
        blocks = self.last_blocks = self._blocks_from(flat)
        if status != OK:  # a block of S is not positive definite: NumPy, block by block
            nis = self._nis_blocks(nu)
            ok = self.gate_ok(nis)
        return Innovation(self.names, self.rows, nu, S, Pxz, nis, ok, z_pred, blocks)

    def _blocks_of(self, S: np.ndarray) -> dict:
        """The diagonal blocks of S by group size: size -> (group indices, blocks (g, k, k))."""
        return {idx.shape[1]: (which, S[ii, jj] if tile is None else _diagonal_blocks(S, *tile))
                for which, idx, ii, jj, tile in self.batches}

    def _blocks_from(self, flat: np.ndarray) -> dict:
        """:meth:`_blocks_of` from the blocks laid out one after the other in ``flat`` (as
        ``_block_start`` says; the compiled innovation copies them there): views on it."""
        return {k: (which, flat[span].reshape(shape)) for k, which, span, shape in self._block_spans}

    def nis(self, nu: np.ndarray, S: np.ndarray) -> np.ndarray:
        """Each group's NIS; the diagonal blocks of S are kept in ``last_blocks`` (size ->
        (group indices, blocks)) for whoever wants them."""
        self.last_blocks = self._blocks_of(S)
        if self._tiled and nu.shape[0] == self.m:
            c, info = lapack.dpotrf(S * self._block_mask, lower=1, clean=0)
            if info == 0:
                w, info = lapack.dtrtrs(c, nu, lower=1)
                if info == 0:
                    return (w * w) @ self._member
        return self._nis_blocks(nu)

    def _nis_blocks(self, nu: np.ndarray) -> np.ndarray:
        """The NIS block by block (a group whose block is singular gets inf)."""
        out = np.empty(len(self.rows))
        for which, idx, _, _, _ in self.batches:
            k = idx.shape[1]
            Sg = self.last_blocks[k][1]
            v = nu[idx]
            if k == 1:
                with np.errstate(divide="ignore", invalid="ignore"):
                    r = v[:, 0] ** 2 / Sg[:, 0, 0]
                out[which] = np.where(Sg[:, 0, 0] > 0, r, np.inf)
            else:
                out[which] = _nis_each(v, Sg)
        return out


def _diagonal_blocks(S: np.ndarray, r0: int, g: int, k: int) -> np.ndarray:
    """The ``g`` diagonal ``(k, k)`` blocks of ``S`` that tile its rows from ``r0`` on, as a
    read-only view ``(g, k, k)``."""
    Sv = S[r0:r0 + g * k, r0:r0 + g * k].reshape(g, k, g, k)
    return Sv.diagonal(axis1=0, axis2=2).transpose(2, 0, 1)


class Innovation(NamedTuple):
    """One measurement's prediction against the current state, before it is applied
    (immutable: a named tuple, cheap to make once per step).

    ``innovation (m,)`` and ``S (m, m)`` are the full stacked vectors (every group);
    ``nis (G,)`` is each group's normalised innovation squared, ``gate_ok (G,)`` whether
    it passed its own gate. ``Pxz (n, m)`` is the state-measurement cross covariance.
    """

    names: tuple[str, ...]
    rows: tuple[np.ndarray, ...]
    innovation: np.ndarray
    S: np.ndarray
    Pxz: np.ndarray
    nis: np.ndarray
    gate_ok: np.ndarray
    z_pred: np.ndarray
    blocks: dict | None = None  # group size -> (group indices, their diagonal blocks of S)

    def group(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Innovation and covariance of one group."""
        r = self.rows[self.names.index(name)]
        return self.innovation[r], self.S[np.ix_(r, r)]
