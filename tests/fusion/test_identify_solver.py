"""The fit's solver: it stops at the optimum (a Gauss-Newton step from its answer moves
nothing), along the curved valley of a compass's heading and hard iron too, and the coarse
start on a subset of a long recording's points ends at the same optimum as the whole
recording's fit alone."""

import numpy as np
import pytest
from armfusion.fusion.configfile import load_arm
from armfusion.fusion.identification.data import data_from_recording
from armfusion.fusion.identification.problem import CHUNK_POINTS, FitProblem
from armfusion.fusion.identification.solver import (
    COARSE_BLOCK,
    COARSE_FACTOR,
    COARSE_MIN_POINTS,
    coarse_points,
    levenberg_marquardt,
    solve,
)
from armfusion.models.effects import Model, build_effect
from armfusion.models.simulator import simulate


@pytest.fixture(scope="module")
def compass_problem():
    """The compass alone, 270 s of renk-maneuver (1,080 points: long enough for a coarse
    start): its hard and soft iron and every link's dipole drawn (seeded) and estimated
    with the heading, which trade along curved valleys (a rotation of the Earth's field
    against a constant offset) where a plain Levenberg-Marquardt step creeps."""
    arm = load_arm("wmra")
    rng = np.random.default_rng(5)
    targets = [("mag_hard_iron", "imu"), ("mag_soft_iron", "imu")] + [
        ("mag_arm_disturbance", j) for j in arm.joint_names]
    effects = [build_effect(arm, e, t) for e, t in targets]
    entries = [{"effect": e, "target": t, "params": {fx.key: fx.draw(rng).tolist()}}
               for (e, t), fx in zip(targets, effects, strict=True)]
    rec, _ = simulate(arm, "renk-maneuver", 270.0, seed=1, effects=entries)
    data = data_from_recording(arm, rec, 25, nodes=2)
    pb = FitProblem(Model(arm, effects), data, ["imu_mag"], True, np.zeros(3))
    pb.x0[pb.P + 2] = np.radians(100.0)  # a heading start far from the truth's
    return pb


def gauss_newton_step_in_sigma(pb: FitProblem, z: np.ndarray, fcols: np.ndarray) -> np.ndarray:
    """Each free element's full Gauss-Newton step from ``z`` (priors included), in its σ."""
    H, g, _ = pb.normal_equations(z, fcols)
    sd = pb.sigma0[fcols]
    H = H + np.diag(1.0 / sd**2)
    g = g + (z[fcols] - pb.x0[fcols]) / sd**2
    C = np.linalg.inv(H)
    return np.abs(np.linalg.solve(H, g)) / np.sqrt(np.diag(C))


def test_the_coarse_subset_is_runs_of_neighbours_one_in_four():
    idx = coarse_points(1200, None)
    assert abs(len(idx) - 1200 / COARSE_FACTOR) <= COARSE_BLOCK
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    assert all(len(r) == COARSE_BLOCK for r in runs)
    assert idx[0] == 0 and idx[-1] > 1200 - COARSE_FACTOR * COARSE_BLOCK


def test_no_coarse_start_for_a_short_recording_or_one_that_would_miss_a_stance():
    assert coarse_points(COARSE_FACTOR * COARSE_MIN_POINTS - 1, None) is None
    n = 2000
    stance = np.zeros(n, int)
    stance[9:15] = 1  # a stance that falls between two runs of the subset
    assert coarse_points(n, stance) is None
    stance[:] = np.arange(n) // 500  # four long stances: each is in the subset
    assert coarse_points(n, stance) is not None
    used = np.ones(n, bool)
    used[500:1000] = np.arange(500, 1000) % (COARSE_FACTOR * COARSE_BLOCK) >= COARSE_BLOCK  # between the runs
    assert coarse_points(n, stance, used) is None


def test_a_long_recording_s_coarse_subset_stays_one_chunk():
    idx = coarse_points(20 * CHUNK_POINTS, None)
    assert CHUNK_POINTS // 2 <= len(idx) <= CHUNK_POINTS


@pytest.fixture(scope="module")
def whole_fit(compass_problem):
    """The whole recording's solve alone, from the prior: estimate, converged, Jacobians."""
    pb = compass_problem
    return levenberg_marquardt(pb, pb.x0.copy(), np.arange(pb.size), {s: 1.0 for s in pb.streams}, 100,
                               lambda k, c: None)


def test_the_solver_stops_at_the_optimum_of_a_curved_valley(compass_problem, whole_fit):
    pb = compass_problem
    fcols = np.arange(pb.size)
    z, converged, n, _ = whole_fit
    assert converged, n
    step = gauss_newton_step_in_sigma(pb, z, fcols)
    worst = int(np.argmax(step))
    assert step[worst] < 0.05, (pb.names[worst], step[worst])


def test_the_coarse_start_ends_at_the_whole_recording_s_optimum(compass_problem, whole_fit):
    pb = compass_problem
    fcols = np.arange(pb.size)
    w = {s: 1.0 for s in pb.streams}
    idx = coarse_points(pb.data.n, pb.data.stance)
    assert idx is not None
    coarse = FitProblem(pb.model, pb.data.subset(idx), pb.streams, True, np.zeros(3))
    coarse.x0 = pb.x0
    seen = []
    z, converged, n_coarse = solve(pb, coarse, pb.x0.copy(), fcols, w, 100, lambda k, c: seen.append(c))
    assert converged and n_coarse > 0
    alone = whole_fit[0]
    H, _, _ = pb.normal_equations(alone, fcols)
    sd = pb.sigma0
    sigma = np.sqrt(np.diag(np.linalg.inv(H + np.diag(1.0 / sd**2))))
    moved = np.abs(z - alone) / sigma
    worst = int(np.argmax(moved))
    assert moved[worst] < 0.05, (pb.names[worst], moved[worst])
    # the progress the user sees: the coarse solve's cost scaled to the whole recording, so
    # the last coarse cost and the first whole-recording cost are alike
    assert 0.5 < seen[n_coarse] / seen[n_coarse - 1] < 2.0, seen[n_coarse - 2:n_coarse + 2]
