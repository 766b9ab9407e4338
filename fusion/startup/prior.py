"""What is known of the pose before a still window, and how it may choose a branch.

A :class:`StartupPrior` is either checked (a saved pose, an earlier window carried through
the encoder counts: a claim the data must confirm, by a chi-square test) or assumed (the
caller asserts the arm is parked). :class:`BranchChooser` applies it to the branches that
fit the still data: which the result may not rule out, which it reports first, and what
chose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import DEG, wrap_angle


@dataclass(frozen=True)
class StartupPrior:
    """What is known of the pose before a still window, and how far it may be used.

    ``kind``:

    - ``"checked"``: candidate poses (the pose saved at the last clean shutdown, or an
      earlier window's answers carried through the encoder counts). They choose between
      branches only where a branch that fits the data lies within their sigma (a chi-square
      test over the joints both know); when none does, the prior is ignored and the result
      says so. Relative encoders lose their count with the power, and a person may move the
      arm by hand: a saved pose is a claim to check, not evidence.
    - ``"assumed"``: the caller asserts where the arm stands (``--assume-parked``): the pose
      picks among the branches as a Gaussian prior, and the result says it rests on that.

    ``sigma_rad`` is per joint; ``inf`` where the prior knows nothing of a joint.
    """

    candidates_rad: np.ndarray  # (C, n)
    sigma_rad: np.ndarray  # (n,)
    kind: str = "checked"
    source: str = "a saved pose"
    covariance_rad2: np.ndarray | None = None
    """(n, n), or (C, n, n) one per candidate: the candidates' covariance where it is known
    (an earlier window's answer: near a singular pair its joints are strongly correlated);
    default ``diag(sigma_rad**2)``."""

    def __post_init__(self):
        c = np.atleast_2d(np.asarray(self.candidates_rad, float))
        object.__setattr__(self, "candidates_rad", c)
        sig = np.broadcast_to(np.asarray(self.sigma_rad, float), (c.shape[1],)).copy()
        object.__setattr__(self, "sigma_rad", sig)
        known = np.isfinite(sig)
        cov = (np.diag(np.where(known, sig, 0.0) ** 2) if self.covariance_rad2 is None
               else np.array(self.covariance_rad2, float))
        cov[..., ~known, :] = 0.0
        cov[..., :, ~known] = 0.0
        object.__setattr__(self, "covariance_rad2", np.where(np.isfinite(cov), cov, 0.0))
        if self.kind not in ("checked", "assumed"):
            raise ValueError(f"prior kind must be 'checked' or 'assumed', not {self.kind!r}")

    @classmethod
    def saved_pose(cls, q_rad: np.ndarray, sigma_deg: float = StartupSettings.saved_pose_sigma_deg,
                   source: str = "the saved pose") -> StartupPrior:
        return cls(np.asarray(q_rad, float)[None], np.full(len(q_rad), sigma_deg * DEG), "checked", source)

    @classmethod
    def assume_parked(cls, arm: ArmModel, sigma_deg: float = StartupSettings.prior_sigma_deg) -> StartupPrior:
        return cls(arm.ready_pose_rad[None], np.full(arm.n_joints, sigma_deg * DEG), "assumed",
                   "the arm assumed parked at its ready pose")



@dataclass
class BranchChooser:
    """Which of the fitting branches the result may not rule out, and which to report.

    ``keep`` (B,): the branches in the pool; ``rank`` (B,): lower is reported first;
    ``admits``: whether a further minimum found later joins the pool; ``used``: what chose.
    """

    keep: np.ndarray
    rank: np.ndarray
    used: str
    prior: StartupPrior | None
    threshold: float
    settings: StartupSettings

    @classmethod
    def make(cls, prior: StartupPrior | None, st: StartupSettings, q: np.ndarray,
             locked: np.ndarray, cov: np.ndarray, notes: list[str]) -> BranchChooser:
        """The chooser of ``prior`` over branches ``q (B, n)`` ordered by cost (their locked
        joints and covariances ``(B, n, n)``); what it did is appended to ``notes``."""
        B = len(q)
        by_cost = np.arange(B, dtype=float)  # q comes ordered by cost
        if prior is None:
            return cls(np.ones(B, bool), by_cost, "none", None, np.inf, st)
        if prior.kind == "assumed":
            d2 = _prior_d2(prior, q, locked, np.zeros_like(cov))
            notes.append(f"the branch rests on an assumption: {prior.source} (--assume-parked); "
                         f"without it every branch that fits would be reported")
            return cls(d2 - d2.min() < st.prior_decisive_chi2, d2, prior.source, prior,
                       float(d2.min() + st.prior_decisive_chi2), st)
        d2, k = _prior_d2(prior, q, locked, cov, with_dof=True)
        thr = _chi2_quantile(k, st.prior_fit_p)
        fits = d2 <= thr
        if not fits.any():
            i = int(np.argmin(d2 / np.maximum(thr, 1e-9)))
            notes.append(f"{prior.source} does not fit the still data (chi-square {d2[i]:.0f} "
                         f"over {int(k[i])} joints at the nearest branch, above {thr[i]:.0f}): "
                         f"ignored; the arm was moved since, or its count lost")
            return cls(np.ones(B, bool), by_cost, "none", None, np.inf, st)
        # it fits: it chooses, as evidence, among the branches that agree with it (those it
        # does not prefer by a chi-square of prior_decisive_chi2 stay rivals)
        best = float(d2[fits].min())
        keep = fits & (d2 - best < st.prior_decisive_chi2)
        notes.append(f"{prior.source} fits the still data (chi-square {best:.1f} over "
                     f"{int(k[fits].max())} joints); it chose among {B} fitting branch"
                     f"{'es' if B != 1 else ''}")
        return cls(keep, d2, prior.source, prior, best + st.prior_decisive_chi2, st)

    def admits(self, q: np.ndarray, locked: np.ndarray, cov: np.ndarray) -> np.ndarray:
        """Whether each further minimum ``q (R, n)`` found later joins the pool ``(R,)``."""
        if self.prior is None:
            return np.ones(len(q), bool)
        if self.prior.kind == "assumed":
            return _prior_d2(self.prior, q, locked, np.zeros_like(cov)) < self.threshold
        d2, k = _prior_d2(self.prior, q, locked, cov, with_dof=True)
        return (d2 <= _chi2_quantile(k, self.settings.prior_fit_p)) & (d2 < self.threshold)


def _prior_d2(prior: StartupPrior, q: np.ndarray, locked: np.ndarray, cov: np.ndarray,
              with_dof: bool = False):
    """Per branch ``q (B, n)``: the chi-square of its nearest prior candidate over the joints
    both know (readable in the branch, known to the prior), with the branch's own covariance
    ``cov (B, n, n)`` added to the prior's (full matrices: along a valley the joints move
    together, and a rival that is many sigmas away as a whole may be within each joint's
    own sigma); and the number of those joints."""
    known = ~locked & np.isfinite(prior.sigma_rad)  # (B, n)
    C = len(prior.candidates_rad)
    Cp = np.broadcast_to(prior.covariance_rad2, (C, *prior.covariance_rad2.shape[-2:]))
    S = cov[:, None] + Cp[None]  # (B, C, n, n)
    both = (known[:, :, None] & known[:, None, :])[:, None]
    S = np.where(both, S, 0.0) + np.eye(q.shape[1]) * np.where(known, 0.0, 1.0)[:, None, None]
    dq = wrap_angle(q[:, None, :] - prior.candidates_rad[None]) * known[:, None]  # (B, C, n)
    w = np.linalg.solve(S, dq[..., None])[..., 0]
    d2 = np.sum(dq * w, -1).min(1)
    return (d2, known.sum(1)) if with_dof else d2


def _chi2_quantile(k, p: float) -> np.ndarray:
    """The chi-square value exceeded with probability ``p`` at ``k`` degrees of freedom."""
    from scipy.special import chdtri

    k = np.maximum(np.asarray(k, float), 1.0)
    return chdtri(k, p)
