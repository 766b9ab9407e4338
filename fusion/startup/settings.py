"""What the startup solve may assume and where it draws its lines: :class:`StartupSettings`.

Every threshold of :func:`armfusion.fusion.startup.solve.solve_still` and its moves, in one frozen
struct with its unit in the name and its reason beside it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StartupSettings:
    """Every threshold of the still solve and its moves (angles in deg, chi-squares
    unitless); the defaults are the ones the benchmarks run."""

    gimbal_lock_deg: float = 2.5
    """A joint whose axis is within this angle of vertical is gravity-blind: no number."""
    sigma_limit_deg: float = 0.5
    """A joint with a larger sigma is ``ill_conditioned``."""
    prior_sigma_deg: float = 30.0
    """How far the arm may have moved since the prior pose was saved (1 sigma)."""
    prior_decisive_chi2: float = 9.0
    """The prior decides between branches when it prefers one by this much (chi-square)."""
    thesis_detector_g: float = 0.95
    """The thesis's detector: the sensor axis along the joint reads above this (in g)."""
    max_iterations: int = 30
    sigma_safety_factor: float = 1.25
    """Reported sigmas are the statistical ones times this. With exact sigmas, Gaussian tails
    alone put about 4 of 70,000 joint estimates beyond 4 sigma; the factor makes a "within
    4 sigma" claim hold over 10,000 poses (at the price of slightly wider, honest bars)."""
    profile_above_deg: float = 0.08
    """Joints with a linear sigma above this get the profile (non-quadratic) check."""
    limit_margin_deg: float = 0.5
    """Readings are noisy: a branch this close outside a limit is still feasible."""
    limit_zero_sigmas: float = 3.0
    """A joint's limits are stated in its numbering, the branches are solved in the geometric
    angle, and the two differ by the joint's zero offset, known to the config's
    ``joint_offset`` sigma (the effect's datasheet-typical 1 deg where the config has none): a
    branch within this many of those sigmas (plus ``limit_margin_deg``) outside a limit is
    still feasible. (With 0.5 deg alone, a pose 0.8 deg inside j4's limit whose zero was 1 deg
    off lost its true branch, and its rival's j3 and j4, 160-190 deg away, were reported
    ``ok``.)"""
    limit_reach_deg: float = 45.0
    """A branch at most this far outside a limit is also tried held at the limit."""
    fit_chi2: float = 9.0
    """A branch fits the data when its chi-square is within this of the best branch's."""
    prior_fit_p: float = 1e-3
    """A checked prior (saved pose, encoder carry) fits a branch unless the branch lies
    this improbably far from it (chi-square test over the joints both know)."""
    saved_pose_sigma_deg: float = 3.0
    """How far a joint may have settled since its pose was saved at a clean shutdown
    (1 sigma): brakes taking the load, gear play. A pose moved further is stale."""
    ill_grow_max_deg: float = 30.0
    """An ill-conditioned joint's sigma grows to cover a rival minimum up to this far away
    (one valley); a rival further away makes it ``ambiguous``."""
    combination_sigma_max_deg: float = 5.0
    """A combination of joints not ``ok`` (parallel axes' sum; a joint and the base's tilt)
    known within this, and better than each of its terms, is reported
    (:mod:`armfusion.fusion.startup.combinations`): the tracker's line between a joint it knows and one
    it holds (``TrackerSettings.mean_state_held_sigma_deg``)."""
    numbered_sigma_max_deg: float = 45.0
    """A joint whose sigma would exceed this is not given a number: the data do not see it
    (its angle is null and its range the limits)."""
    encoder_carry_sigma_deg: float = 0.1
    """What the encoders add to a pose they carry from one still window to the next (1
    sigma): they count the motor, and the gears between it and the link have play."""
    separation_chi2: float = 100.0
    """A disambiguating move must make every pair of rival branches predict readings this
    far apart (chi-square over the sensors' noise: 10 sigma)."""

