"""The measurement side of :class:`armfusion.fusion.tracking.ukf.BatchedUKF`: measurement groups
(one sensor's rows, gated as a whole on its normalised innovation squared, NIS), a plan
of them prepared once for updates of the same shape (:class:`GroupPlan`, with the compiled
innovation that reads it), the chi-square gate
(:func:`nis_bound`) and an update's :class:`Innovation`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from armfusion.fusion.tracking.ukf_kernels import innovation_into
from scipy.stats import chi2


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
    names, rows and gates, and the index arrays the compiled innovation reads
    (:meth:`innovation`): every group's rows one after the other, where each group starts
    there, and where each group's diagonal block of ``S`` goes in one flat array (laid out
    batch by batch, a batch being the groups of one size, in order)."""

    def __init__(self, groups: Sequence[MeasurementGroup]):
        self.groups = tuple(groups)
        self.names = tuple(g.name for g in groups)
        self.rows = tuple(np.asarray(g.rows, dtype=int).reshape(-1) for g in groups)
        self.gates = np.ascontiguousarray([g.gate for g in groups], dtype=float)
        sizes = np.array([len(r) for r in self.rows], dtype=np.int64)
        self._group_rows = np.ascontiguousarray(np.concatenate([np.zeros(0, int), *self.rows]),
                                                dtype=np.int64)
        if len(self._group_rows) and self._group_rows.min() < 0:
            raise ValueError(f"a group's rows must be indices from 0, got {self._group_rows.min()}")
        self._rows_end = int(self._group_rows.max()) + 1 if len(self._group_rows) else 0  # rows needed
        self._group_start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self._block_start = np.zeros(len(self.rows), dtype=np.int64)
        self._block_spans = []
        start = 0
        for k in np.unique(sizes):
            which = np.flatnonzero(sizes == k)
            g = len(which)
            self._block_start[which] = start + k * k * np.arange(g)
            self._block_spans.append((int(k), which, slice(start, start + g * k * k), (g, int(k), int(k))))
            start += g * k * k
        self._block_size = int(start)
        self.last_blocks: dict | None = None

    def gate_ok(self, nis: np.ndarray) -> np.ndarray:
        """Whether each group's NIS passes its gate (a NaN NIS fails any gate; an infinite
        one fails every gate, an infinite gate too)."""
        return np.isfinite(nis) & (nis <= self.gates)

    def innovation(self, z: np.ndarray, Z: np.ndarray, R: np.ndarray, weights: np.ndarray,
                   z_weights: np.ndarray | None, angle_rows: np.ndarray, DXW: np.ndarray) -> Innovation:
        """The innovation of ``z (m,)`` against the sigma points' measurements ``Z (N, m)``
        from the compiled kernel: ``R`` the noise ``(m, m)`` or its diagonal ``(m,)``,
        ``weights`` the points' mean and covariance weights ``(2, N)``, ``z_weights`` those
        the prediction is taken with (None: the mean's), ``angle_rows (int64)`` the rows that
        are angles (in ``[0, m)``), ``DXW`` the weighted state residuals ``(n, N)``."""
        m = z.shape[0]
        Zc = np.ascontiguousarray(Z, dtype=np.float64)
        N, n = weights.shape[1], DXW.shape[0]
        if Zc.shape != (N, m):
            raise ValueError(f"hx returned shape {Zc.shape}, expected ({N}, {m}): one row of the "
                             f"measurement's size per sigma point")
        R2 = np.ascontiguousarray(R[None] if R.ndim == 1 else R, dtype=np.float64)
        if R2.shape not in ((1, m), (m, m)):
            raise ValueError(f"R must be ({m}, {m}) or ({m},) for a measurement of size {m}, got {R.shape}")
        if self._rows_end > m:
            raise ValueError(f"a group's rows lie outside the measurement's {m} rows")
        G = len(self.rows)
        z_pred, nu, S, Pxz = np.empty(m), np.empty(m), np.empty((m, m)), np.empty((n, m))
        flat, nis, ok = np.empty(self._block_size), np.empty(G), np.empty(G, dtype=np.bool_)
        wz = weights[0] if z_weights is None else np.ascontiguousarray(z_weights, dtype=np.float64)
        innovation_into(Zc, weights, wz, angle_rows, np.ascontiguousarray(z, dtype=np.float64), R2,
                        np.ascontiguousarray(DXW), self._group_rows, self._group_start, self._block_start,
                        self.gates, z_pred, nu, S, Pxz, flat, nis, ok)
        blocks = self.last_blocks = self._blocks_from(flat)
        return Innovation(self.names, self.rows, nu, S, Pxz, nis, ok, z_pred, blocks)

    def _blocks_from(self, flat: np.ndarray) -> dict:
        """The diagonal blocks of ``S`` by group size, size -> (group indices, blocks
        ``(g, k, k)``), as views on ``flat`` (where the compiled innovation lays them out)."""
        return {k: (which, flat[span].reshape(shape)) for k, which, span, shape in self._block_spans}


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
