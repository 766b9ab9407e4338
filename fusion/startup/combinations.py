"""What gravity reads where it cannot read single joints: the observable combinations.

Joints whose axes are parallel (a UR5's shoulder, elbow and wrist 1) turn the links beyond
them about the same direction, so the link accelerometers read only their sum: each alone
is unknown (``ill_conditioned``, its sigma large) while the sum is known to the readings'
degree. The same holds for a joint and the base's tilt about a parallel axis. Such a
combination is a direction of the covariance that is well determined although no single
variable is: :func:`observable_combinations` finds them from the covariance itself (the
joint block, with the base's roll and pitch where given, and any consider or systematic
term the caller adds), not from a list of known pairs, names them readably
(``shoulder + elbow``) and gives each its value and sigma, the sigma of exactly the
combination named (``c^T P c``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COEFFICIENT_STEP = 0.5
"""A combination's coefficients are read to this step first (parallel axes give 1 and -1)."""
FINE_STEP = 0.01
"""Where the coarse step's combination is not well determined, the coefficients to this step."""
LEAST_COEFFICIENT = 0.05
"""A coefficient smaller than this (the largest is 1) is left out of the combination."""
LEAST_CORRELATION = 0.1
"""A variable whose correlation with every other is below this takes part in no combination:
a sum with an uncorrelated term is known no better than that term."""


@dataclass(frozen=True)
class Combination:
    """A weighted sum of joint angles (and the base's tilt) that is known though its terms
    are not: ``name`` (``"shoulder + elbow"``), ``coefficients`` (variable name to
    coefficient, the largest 1), ``angle_rad`` (the sum at the estimate) and ``sigma_rad``."""

    name: str
    coefficients: tuple[tuple[str, float], ...]
    angle_rad: float
    sigma_rad: float

    def as_dict(self) -> dict:
        return {"name": self.name, "coefficients": dict(self.coefficients),
                "angle_rad": float(self.angle_rad), "sigma_rad": float(self.sigma_rad)}

    def vector(self, names: list[str] | tuple[str, ...]) -> np.ndarray:
        """The coefficients over ``names`` (zero for a variable not in the combination)."""
        c = dict(self.coefficients)
        return np.array([c.get(n, 0.0) for n in names])


def combination_name(terms: list[tuple[str, float]]) -> str:
    """``shoulder + elbow``, ``shoulder - base pitch``, ``0.5 elbow + wrist1``."""
    out = ""
    for i, (name, c) in enumerate(terms):
        mag = abs(c)
        word = name if abs(mag - 1.0) < 1e-9 else f"{mag:g} {name}"
        if i == 0:
            out = ("-" if c < 0 else "") + word
        else:
            out += (" - " if c < 0 else " + ") + word
    return out


def _readable(v: np.ndarray, step: float) -> np.ndarray:
    """``v`` scaled so that its largest coefficient is 1 (the first of them positive),
    rounded to ``step``, the smallest left out."""
    v = v / v[np.argmax(np.abs(v))]
    c = np.round(v / step) * step
    c[np.abs(c) < LEAST_COEFFICIENT] = 0.0
    nz = np.flatnonzero(c)
    if len(nz) and c[nz[0]] < 0:
        c = -c
    return c


def observable_combinations(cov: np.ndarray, x: np.ndarray, names: list[str] | tuple[str, ...],
                            limit_rad: float,
                            candidates: np.ndarray | None = None) -> tuple[Combination, ...]:
    """The combinations of the ``candidates`` (a mask over ``names``: the variables the caller
    does not call known, e.g. the joints not ``ok``; default: every variable whose own sigma
    is above ``limit_rad``) that the covariance ``cov`` (of the variables ``x``) knows within
    ``limit_rad`` and better than any of their terms alone.

    The well-determined directions are the eigenvectors of the candidates' block of ``cov``
    whose sigma is within ``limit_rad``; their span is written in reduced row echelon form
    (each direction on as few variables as it can be), each row scaled to a largest
    coefficient of 1 and read to :data:`COEFFICIENT_STEP` (else :data:`FINE_STEP`). A
    combination is reported only where the combination as named is within ``limit_rad``
    (its sigma is ``sqrt(c^T cov c)`` for exactly those coefficients), below each of its
    terms' own sigma, and has two terms or more; the best known first."""
    cov = np.asarray(cov, float)
    x = np.asarray(x, float)
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    finite = np.isfinite(sig) & np.isfinite(x)
    cand = (sig > limit_rad) if candidates is None else np.asarray(candidates, bool).copy()
    cand &= finite & (sig > 0.0)
    idx = np.flatnonzero(cand)
    if len(idx) < 2:
        return ()
    C = cov[np.ix_(idx, idx)]
    C = 0.5 * (C + C.T)
    # a variable correlated with none of the others is known (or not) alone; left out, the
    # block's small eigenvalues keep their precision beside a joint at millions of degrees
    rho = np.abs(C / np.outer(sig[idx], sig[idx]))
    np.fill_diagonal(rho, 0.0)
    keep = rho.max(axis=1) >= LEAST_CORRELATION
    idx, C = idx[keep], C[np.ix_(keep, keep)]
    if len(idx) < 2:
        return ()
    lam, V = np.linalg.eigh(C)
    good = V[:, lam <= limit_rad**2]
    if not good.shape[1]:
        return ()
    basis = _rref(good.T)
    out, seen = [], set()
    for row in basis:
        for step in (COEFFICIENT_STEP, FINE_STEP):
            c = _readable(row, step)
            if np.count_nonzero(c) < 2:
                break
            s = float(np.sqrt(max(c @ C @ c, 0.0)))
            if s <= limit_rad and s < float(np.min(sig[idx][c != 0])):
                key = tuple(np.round(c, 6))
                if key not in seen:
                    seen.add(key)
                    terms = [(names[idx[k]], float(c[k])) for k in np.flatnonzero(c)]
                    out.append(Combination(combination_name(terms), tuple(terms),
                                           float(c @ x[idx]), s))
                break
    return tuple(sorted(out, key=lambda cb: cb.sigma_rad))


def _rref(A: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """The reduced row echelon form of ``A`` (k, m), partial pivoting: k rows that span the
    same space, each with a leading 1 in a column no other row has."""
    A = np.array(A, float)
    k, m = A.shape
    r = 0
    for col in range(m):
        if r == k:
            break
        p = r + int(np.argmax(np.abs(A[r:, col])))
        if abs(A[p, col]) < tol:
            continue
        A[[r, p]] = A[[p, r]]
        A[r] /= A[r, col]
        for i in range(k):
            if i != r:
                A[i] -= A[i, col] * A[r]
        r += 1
    return A[:r]
