"""What the startup solve gives: a value, sigma and flag per joint, the base tilt, every
candidate it cannot rule out, and the moves it proposes.

:class:`StartupResult` holds :class:`JointEstimate` per joint, an :class:`UnlockMove` (blind
joints: a move that makes them readable) and a :class:`DisambiguatingMove` (rival branches:
a move after which they read apart); :func:`summary` is the line a person reads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FLAGS = ("ok", "ill_conditioned", "gimbal_lock", "ambiguous", "out_of_limits")


class StartupInputError(ValueError):
    """The readings cannot give joint angles (NaN, saturated, dead sensor...)."""


@dataclass(frozen=True)
class JointEstimate:
    """One joint: its angle and sigma (None where it has no number), its flag, and for an
    ambiguous joint every candidate value."""

    name: str
    angle_rad: float | None
    sigma_rad: float | None
    flag: str
    alternatives_rad: tuple[float, ...] = ()
    axis_to_vertical_deg: float = 90.0
    thesis_detector_locked: bool | None = None
    range_rad: tuple[float, float] | None = None
    """Where a joint with no number may be: its limits (the data do not narrow it)."""
    turns_rad: tuple[float, ...] = ()
    """The turn branches of a joint with a number whose limits hold it on more than one turn
    (a UR's ±360°): every angle inside the limits a whole number of turns from
    ``angle_rad`` (that one included), ascending. Gravity reads a revolute joint's angle only
    modulo a turn, so the still data fit each of them equally; ``angle_rad`` is the one nearest
    the middle of the limits, and the encoders' turn count decides between them (the tracker
    reports the encoders' turn). Empty where one turn alone fits inside the limits."""

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "angle_rad": self.angle_rad,
            "sigma_rad": self.sigma_rad,
            "flag": self.flag,
            "alternatives_rad": list(self.alternatives_rad),
            "range_rad": None if self.range_rad is None else list(self.range_rad),
            "turns_rad": list(self.turns_rad),
            "axis_to_vertical_deg": self.axis_to_vertical_deg,
            "thesis_detector_locked": self.thesis_detector_locked,
        }


@dataclass(frozen=True)
class UnlockMove:
    """A small, safe move of joints already known well, after which the blind joints read."""

    joints: tuple[str, ...]
    delta_rad: tuple[float, ...]
    target_rad: tuple[float, ...]
    expected_sigma_rad: tuple[float, ...]
    unlocks: tuple[str, ...]

    def as_dict(self) -> dict:
        return {
            "moves": [{"joint": j, "delta_rad": d, "target_rad": t}
                      for j, d, t in zip(self.joints, self.delta_rad, self.target_rad, strict=True)],
            "expected_sigma_rad": list(self.expected_sigma_rad),
            "unlocks": list(self.unlocks),
        }

    def describe(self) -> str:
        moves = " and ".join(f"{j} by {np.degrees(d):+.1f} deg (to {np.degrees(t):.1f})"
                             for j, d, t in zip(self.joints, self.delta_rad, self.target_rad,
                                                strict=True))
        return (f"move {moves}, then calibrate again: {', '.join(self.unlocks)} become "
                f"readable, worst expected sigma {np.degrees(max(self.expected_sigma_rad)):.3f} deg")


@dataclass(frozen=True)
class DisambiguatingMove:
    """A small, safe move after which branches that fit the still data equally well predict
    readings far apart: after it and a second still window, the encoders (which counted
    the move) carry each branch forward and only the true one fits."""

    joints: tuple[str, ...]
    delta_rad: tuple[float, ...]
    separation_sigma: float
    """The closest any two rival branches then come, in the sensors' noise (sqrt chi-square)."""
    resolves: tuple[str, ...]

    def as_dict(self) -> dict:
        return {"moves": [{"joint": j, "delta_rad": d}
                          for j, d in zip(self.joints, self.delta_rad, strict=True)],
                "separation_sigma": self.separation_sigma, "resolves": list(self.resolves)}

    def describe(self) -> str:
        moves = " and ".join(f"{j} by {np.degrees(d):+.1f} deg"
                             for j, d in zip(self.joints, self.delta_rad, strict=True))
        return (f"move {moves} (every candidate stays inside the limits), hold still, and "
                f"calibrate again: the candidates of {', '.join(self.resolves)} then read "
                f"{self.separation_sigma:.0f} sigma apart")


@dataclass(frozen=True)
class StartupResult:
    """Everything one still solve found: every joint, the base tilt, the fit, every branch
    and candidate it cannot rule out, what chose, and the moves it proposes."""

    joints: tuple[JointEstimate, ...]
    roll_rad: float
    pitch_rad: float
    roll_sigma_rad: float
    pitch_sigma_rad: float
    residual_rms_g: float
    chi2_per_dof: float
    q_rad: np.ndarray  # the chosen branch, every joint (locked ones at an arbitrary value)
    covariance: np.ndarray  # (n + 2, n + 2): joints, roll, pitch
    branches_rad: np.ndarray  # (B, n) every feasible branch
    method: str
    t_start_s: float = 0.0
    t_end_s: float = 0.0
    unlock_move: UnlockMove | None = None
    summary: str = ""
    candidates_rad: np.ndarray | None = None
    """(R, n): every branch the result cannot rule out, the reported one first."""
    candidates_covariance: np.ndarray | None = None
    """(R, n + 2, n + 2): each candidate's covariance (the first is ``covariance``)."""
    prior_used: str = "none"
    """What chose the branch: "none" (the data alone), or the prior's source."""
    notes: tuple[str, ...] = ()
    disambiguating_move: DisambiguatingMove | None = None
    combinations: tuple = ()
    """What gravity reads where it cannot read single joints: the
    :class:`armfusion.fusion.startup.combinations.Combination` s of joints not ``ok`` (and the base's
    tilt) known within ``StartupSettings.combination_sigma_max_deg``, better than their terms."""

    @property
    def flags(self) -> tuple[str, ...]:
        return tuple(j.flag for j in self.joints)

    @property
    def all_ok(self) -> bool:
        return all(f == "ok" for f in self.flags)

    def as_dict(self) -> dict:
        return {
            "t_start": self.t_start_s,
            "t_end": self.t_end_s,
            "method": self.method,
            "base": {"roll_rad": self.roll_rad, "pitch_rad": self.pitch_rad,
                     "roll_sigma_rad": self.roll_sigma_rad, "pitch_sigma_rad": self.pitch_sigma_rad},
            "joints": [j.as_dict() for j in self.joints],
            "residual_rms_g": self.residual_rms_g,
            "chi2_per_dof": self.chi2_per_dof,
            "branches": len(self.branches_rad),
            "unlock_move": None if self.unlock_move is None else self.unlock_move.as_dict(),
            "disambiguating_move": (None if self.disambiguating_move is None
                                    else self.disambiguating_move.as_dict()),
            "prior": self.prior_used,
            "combinations": [c.as_dict() for c in self.combinations],
            "summary": self.summary,
            "notes": list(self.notes),
        }




def summary(res: StartupResult) -> str:
    """One line for a person: the joints that are not ok and the moves proposed."""
    bad = [f"{j.name} {j.flag}" for j in res.joints if j.flag != "ok"]
    if not bad and not any(len(j.turns_rad) > 1 for j in res.joints):
        worst = max(j.sigma_rad for j in res.joints)
        return f"all {len(res.joints)} joints ok; worst sigma {np.degrees(worst):.3f} deg"
    text = f"{len(res.joints) - len(bad)} of {len(res.joints)} joints ok; " + ", ".join(bad)
    if res.combinations:
        text += "; gravity reads together " + ", ".join(
            f"{c.name} = {np.degrees(c.angle_rad):.1f} ± {np.degrees(c.sigma_rad):.1f} deg"
            for c in res.combinations)
    turns = [j for j in res.joints if len(j.turns_rad) > 1]
    if turns:
        text += "; gravity reads a turn apart alike: " + ", ".join(
            f"{j.name} " + " or ".join(f"{np.degrees(a):.1f}" for a in j.turns_rad) for j in turns
        ) + " deg inside the limits (the encoders' turn count decides)"
    if res.unlock_move is not None:
        text += "; " + res.unlock_move.describe()
    if res.disambiguating_move is not None:
        text += "; to tell the branches apart: " + res.disambiguating_move.describe()
    elif any(j.flag == "ambiguous" for j in res.joints):
        text += "; no safe move of up to 45 deg separates the branches: a person must confirm the pose"
    return text

