"""The weighted least-squares problem of one still window, and its Levenberg-Marquardt.

:class:`StillWindowProblem` holds the measured directions of gravity and their sigmas; its
unknowns are every joint angle, then the base roll and pitch (``x (B, n + 2)``). It gives
weighted residuals and their Jacobian for any batch of states, and the layout of one kind
of solve (which sensors, with or without the base accelerometer: :class:`SolveLayout`) as
the compiled kernels take it (:mod:`armfusion.fusion.startup.kernels`, on the gravity chain's core
:mod:`armfusion.models.gravity_kernels`). :func:`batched_lm` polishes many starts at once;
:func:`expected_covariance` and :func:`axis_to_vertical` read a state's geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from armfusion.fusion.startup.kernels import augmented, lm_solve
from armfusion.fusion.startup.readings import StillReadings
from armfusion.fusion.startup.results import StartupInputError
from armfusion.models.arm import ArmModel
from armfusion.models.kinematics import gravity_chain
from armfusion.models.rotations import DEG, up_from_tilt


class SolveLayout(NamedTuple):
    """The chain and the rows of one kind of solve, as the compiled kernels take them
    (:mod:`armfusion.fusion.startup.kernels`; passed as ``*layout``)."""

    step_in: np.ndarray  # (n, 3, 3) the gravity chain's constant steps
    offset: np.ndarray  # (n,) rad, the joints' zero offsets
    read_W: np.ndarray  # (R, 3, 3) each row block's read-out, weighted and negated
    read_row: np.ndarray  # (R,) its first row
    read_link: np.ndarray  # (R,) the link it reads (V after joint link - 1)
    meas_w: np.ndarray  # (m,) measured / sigma; 0 on the tilt prior's rows
    n_sensor_rows: int  # the link accelerometers' rows
    imu: bool  # the base accelerometer's rows follow (else the level-chair prior's two)
    tilt_prior: float  # rad, the level-chair prior's sigma
    last: int  # the last joint any row needs


@dataclass
class StillWindowProblem:
    """The weighted least-squares problem of one still window."""

    arm: ArmModel
    names: list[str]
    meas: np.ndarray  # (S, 3) unit directions measured by the link accelerometers
    sigma: np.ndarray  # (S, 3) sigma of each axis, in g (on the unit direction)
    imu_meas: np.ndarray | None
    imu_sigma: np.ndarray | None
    R_0I: np.ndarray = field(default_factory=lambda: np.eye(3))
    tilt_prior_rad: float = 5.0 * DEG

    def __post_init__(self):
        self._chain = gravity_chain(self.arm, self.names)
        # every row's read-out, weighted and negated: rows = -(D_s v) / sigma = r - meas / sigma
        self._read_w = -self._chain.read_out / self.sigma[:, :, None]  # (S, 3, 3)
        self._layouts: dict = {}

    @property
    def n(self) -> int:
        return self.arm.n_joints

    def layout(self, active: np.ndarray | None, use_imu: bool) -> SolveLayout:
        """The rows of one kind of solve (the sensors used, the IMU or the level-chair
        prior), built once."""
        key = (None if active is None else np.asarray(active, bool).tobytes(), use_imu)
        hit = self._layouts.get(key)
        if hit is None:
            S = len(self.names)
            used = np.arange(S) if active is None else np.flatnonzero(active)
            imu = use_imu and self.imu_meas is not None
            m = 3 * len(used) + (3 if imu else 2)
            meas_w = np.zeros(m)  # measured / sigma; 0 on the tilt prior's rows
            meas_w[: 3 * len(used)] = (self.meas[used] / self.sigma[used]).reshape(-1)
            reads = [(3 * i, int(self._chain.links[s]), self._read_w[s]) for i, s in enumerate(used)]
            if imu:
                meas_w[3 * len(used):] = self.imu_meas / self.imu_sigma
                reads.append((3 * len(used), 0, -self.R_0I.T / self.imu_sigma[:, None]))
            last = max([k for _, k, _ in reads], default=0) - 1  # the last joint any row needs
            hit = SolveLayout(
                self._chain.step_in, np.ascontiguousarray(self._chain.offset_rad, dtype=float),
                np.ascontiguousarray(np.stack([W for _, _, W in reads]) if reads
                                     else np.zeros((0, 3, 3))),
                np.array([row for row, _, _ in reads], dtype=np.int64),
                np.array([k for _, k, _ in reads], dtype=np.int64),
                np.ascontiguousarray(meas_w), int(3 * len(used)), bool(imu),
                float(self.tilt_prior_rad), int(last))
            self._layouts[key] = hit
        return hit

    def residuals_and_jacobian(self, x: np.ndarray, active: np.ndarray | None = None,
                               use_imu: bool = True):
        """Weighted residuals ``(B, m)`` and Jacobian ``(B, m, n + 2)`` for states ``x (B, n+2)``.

        ``active`` (S,) bool selects the sensors used (sequential solves); ``use_imu=False``
        leaves the base accelerometer out (the level-chair prior takes its place).
        Rows: 3 per sensor used (in config order), then the IMU's 3 or the prior's 2.
        Computed by the compiled kernel the Levenberg-Marquardt runs on
        (:func:`armfusion.fusion.startup.kernels.augmented`).
        """
        rJ = augmented(np.ascontiguousarray(x, dtype=float), *self.layout(active, use_imu))
        return rJ[:, :, 0], rJ[:, :, 1:]


def make_problem(arm: ArmModel, readings: StillReadings) -> StillWindowProblem:
    """The problem of the window ``readings`` averaged: every link accelerometer read (in
    config order) and the base accelerometer when there is one, each as a unit direction
    with its sigmas scaled alike."""
    names = [s.name for s in arm.link_accelerometers if s.name in readings.accel_mean_g]
    if not names:
        raise StartupInputError("no link accelerometer readings: nothing to solve from")
    meas, sig = [], []
    for nm in names:
        m = np.asarray(readings.accel_mean_g[nm], float)
        norm = float(np.linalg.norm(m))
        meas.append(m / norm)
        sig.append(np.asarray(readings.accel_sigma_g[nm], float) / norm)
    imu_m = imu_s = None
    R_0I = np.eye(3)
    if readings.imu_mean_g is not None and arm.imu is not None:
        m = np.asarray(readings.imu_mean_g, float)
        norm = float(np.linalg.norm(m))
        imu_m, imu_s = m / norm, np.asarray(readings.imu_sigma_g, float) / norm
        R_0I = arm.imu.R_LS
    problem = StillWindowProblem(arm, names, np.array(meas), np.array(sig), imu_m, imu_s, R_0I)
    if arm.fixed_base is not None:  # a bolted base: level to its tilt's sigma, not a chair's 5°
        problem.tilt_prior_rad = fixed_base_tilt_prior_rad(arm.fixed_base)
    return problem


def fixed_base_tilt_prior_rad(fixed) -> float:
    """The level-base prior's sigma for a bolted base (:class:`armfusion.models.arm.FixedBase`): its
    tilt's sigma; where an installer's level gave a tilt, wide enough to hold it (three
    sigmas past it: the prior is centred on level, the tracker starts from the tilt given)."""
    if fixed.roll_rad is None:
        return float(fixed.tilt_sigma_rad)
    return float(np.hypot(fixed.roll_rad, fixed.pitch_rad) + 3.0 * fixed.tilt_sigma_rad)


def batched_lm(problem: StillWindowProblem, x0: np.ndarray, free: np.ndarray, iters,
               active: np.ndarray | None = None, use_imu: bool = True,
               ) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every start, compiled (:func:`armfusion.fusion.startup.kernels.lm_solve`):
    the same arithmetic as ``batched_lm_numpy`` in tests/fusion/test_startup_kernels.py."""
    # fresh writable C arrays of one type each: a single compiled signature
    x = np.array(x0, dtype=float, order="C")
    B, p = x.shape
    free_f = np.array(np.broadcast_to(np.asarray(free, bool), (B, p)), dtype=float, order="C")
    left = np.array(np.broadcast_to(np.asarray(iters), (B,)), dtype=np.int64, order="C")
    return lm_solve(x, free_f, left, *problem.layout(active, use_imu))


def expected_covariance(problem: StillWindowProblem, x: np.ndarray) -> np.ndarray:
    """Covariance of every unknown at states ``x (B, n+2)`` from the Jacobian alone (with the
    solve's flat prior): ``(B, n+2, n+2)``."""
    _, J = problem.residuals_and_jacobian(x)
    A = np.einsum("bmi,bmj->bij", J, J) + np.eye(J.shape[-1]) / np.pi**2  # as in the solve
    return np.linalg.inv(A)


def expected_sigma(problem: StillWindowProblem, x: np.ndarray) -> np.ndarray:
    """Sigma of every unknown at states ``x (B, n+2)`` from the Jacobian alone."""
    return np.sqrt(np.clip(np.einsum("bii->bi", expected_covariance(problem, x)), 0, None))


def axis_to_vertical(arm: ArmModel, q: np.ndarray, roll, pitch) -> np.ndarray:
    """The angle between every joint's axis and vertical at poses ``q (B, n)`` on a base at
    (``roll``, ``pitch``) ``(B,)``: ``(B, n)`` rad (near 0: the joint is gravity-blind)."""
    c = np.abs(gravity_chain(arm).axis_up_cos(q, up_from_tilt(roll, pitch)))
    return np.arccos(np.clip(c, 0.0, 1.0))
