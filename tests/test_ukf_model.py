"""The spring-mass model pushes rods apart and holds a resting robot; the filter is
consistent on a resting robot over seeded runs (the rest of the UKF: test_ukf.py)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from agents.runs import record_run
from estimation.ukf import SpringMassModel, UkfEstimator
from tensegrity_gym.model.description import load_robot

RNG = np.random.default_rng(0)  # the UKF ignores it: it is deterministic given its samples


@pytest.mark.parametrize("robot", ["three_bar", "three_bar_large", "superball"])
def test_compiled_model_matches_the_numpy_model(robot: str) -> None:
    d = load_robot(robot)
    model = SpringMassModel(d)
    rng = np.random.default_rng(1)
    x0 = np.concatenate([d.initial_positions.ravel(), np.zeros(3 * d.n_nodes)])
    states = x0 + 0.03 * d.characteristic_length * rng.standard_normal((6, x0.size))
    states[0, 2] -= 0.02  # a node under the ground
    rest = d.rest_lengths[d.actuated]
    states[1, : 3 * d.n_nodes] *= 0.9  # cables slack
    # Two rods pressed together: move rod 1's centre onto rod 0's.
    nodes = states[2, : 3 * d.n_nodes].reshape(-1, 3)
    (a0, a1), (b0, b1) = d.rod_nodes[0], d.rod_nodes[1]
    shift = 0.5 * (nodes[a0] + nodes[a1]) - 0.5 * (nodes[b0] + nodes[b1])
    nodes[[b0, b1]] += shift + np.array([0.0, 0.0, 0.5 * d.rods[0].endcap_radius])
    fast = model.propagate(states, 0.1, rest, 0.95 * rest)
    slow = model.propagate(states, 0.1, rest, 0.95 * rest, compiled=False)
    assert np.all(np.isfinite(fast))
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-9)

    # The pressed rods were pushed apart.
    def centre_gap(nodes: np.ndarray) -> float:
        return float(np.linalg.norm(0.5 * (nodes[a0] + nodes[a1] - nodes[b0] - nodes[b1])))

    moved = fast[2, : 3 * d.n_nodes].reshape(-1, 3)
    assert centre_gap(moved) > 2.0 * centre_gap(nodes)


def test_model_holds_a_resting_robot_still() -> None:
    d = load_robot("three_bar")
    model = SpringMassModel(d)
    x0 = np.concatenate([d.initial_positions.ravel(), np.zeros(3 * d.n_nodes)])
    x = model.propagate(x0, 5.0, d.rest_lengths[d.actuated])
    drift = np.linalg.norm((x[: x.size // 2] - x0[: x.size // 2]).reshape(-1, 3), axis=1)
    assert drift.max() < 0.02  # metres: it settles, it does not bounce or fly off
    assert np.abs(x[x.size // 2 :]).max() < 1e-3


def test_consistency_on_a_quiet_trajectory() -> None:
    """NEES of the node positions over seeded runs of a resting robot, in its band.

    Within a run the errors are correlated in time, so each run's average counts as
    one chi-square sample of 3 n degrees of freedom: the band is that of 5 x 18 dof.
    """

    def hold(env, obs, step):  # type: ignore[no-untyped-def]
        d = env.backend.description
        return env.targets_to_action(d.rest_lengths[d.actuated])

    nees, nis = [], []
    for seed in range(5):
        run = record_run("tensegrity_gym/ThreeBarRoll-v0", hold, 30, seed=seed)
        est = UkfEstimator()
        estimates = [
            est.reset(run.description, run.calibration, run.start.samples, run.start.command, RNG)
        ]
        estimates += [est.update(s.samples, s.command) for s in run.steps]
        n = run.description.n_nodes
        for e, step in zip(estimates[11:], run.steps[10:], strict=True):
            assert step.truth is not None and e.covariance is not None
            err = (e.node_positions - step.truth.node_positions).ravel()
            nees.append(err @ np.linalg.solve(e.covariance[: 3 * n, : 3 * n], err) / (3 * n))
        nis += list(est.diagnostics.nis_history)[10:]
        # A first fit from one UWB round may be re-done once the filter has more.
        assert est.diagnostics.reinitialisations <= 1
    dof = 5 * 3 * 6
    low, high = scipy.stats.chi2.ppf([0.025, 0.975], dof) / dof
    assert low < float(np.mean(nees)) < high, (low, float(np.mean(nees)), high)
    assert 0.3 < float(np.mean(nis)) < 2.0
