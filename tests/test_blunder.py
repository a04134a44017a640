"""Baarda's external reliability (`FitCheck.blunder_nees`): a blunder that the sighting
gate lets through moves the estimate by what the figure predicts."""

import jax.random as jr
import jaxloc
import numpy as np
import pytest
from jaxloc._core.results import RESULTS
from jaxloc._model.covariance import estimate_placements, final_position_jacobian
from jaxloc._model.gates import blunder_shifts, MIN_REDUNDANCY, sighting_limits
from jaxloc._model.measurements import cycle_data, OBSERVER, TARGET, whitened_with_jacobian
from jaxloc._sim.defects import _moved


def _hidden_blunder(obs, rig, estimate, share):
    """The pixel offset `(step, observer, target, offset (2,))` of the mutual sighting
    whose blunder moves an end-of-cycle position most while its normalized residual's
    noise-free part is `share` of the gate's limit, and the NEES it predicts."""
    strategy = obs.strategy
    data = cycle_data(obs, rig)
    T_place, T_over = estimate_placements(estimate.poses, strategy)
    _, Jd = whitened_with_jacobian(T_place, T_over, data, rig, strategy)
    J = np.asarray(Jd[:, 1:].reshape(Jd.shape[0], -1))
    C = np.linalg.inv(J.T @ J)
    G = np.asarray(final_position_jacobian(T_place, T_over, strategy))
    Sigma = np.asarray(estimate.covariance.position)
    pairs = (J.shape[0] - data.odometry.shape[-1]) // 2
    num = data.num_sightings + data.num_odometry
    pixel, single = blunder_shifts(J, C, G, Sigma, pairs, num, rig.noise_model)
    figure = max(float(np.max(pixel)), float(np.max(single)))
    steps = obs.mutual.shape[0]
    s = int(np.argmax(np.asarray(pixel)[: 6 * steps]))  # the worst mutual sighting
    Js = J[2 * s : 2 * s + 2]
    R = np.eye(2) * (1.0 + MIN_REDUNDANCY) - Js @ C @ Js.T
    best = (0.0, None)
    for q in range(4):
        if np.trace(Sigma[q]) <= 0:
            continue
        W = G[q] @ C @ Js.T  # (3, 2)
        M = W.T @ np.linalg.inv(Sigma[q]) @ W
        w, V = np.linalg.eig(np.linalg.solve(R, M))
        i = int(np.argmax(w.real))
        if w[i].real > best[0]:
            best = (w[i].real, V[:, i].real)
    limit = float(sighting_limits(num, rig.noise_model, J.dtype)[0])
    v = best[1]
    b = v * np.sqrt(share * limit / (v @ R @ v))
    k, p = divmod(s, 6)
    i, j = int(OBSERVER[p]), int(TARGET[p])
    weight = float(data.mutual_weight[k, i, j])
    return (k, i, j, -b / weight), share * limit * best[0], figure


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_a_hidden_blunder_moves_the_estimate_as_blunder_nees_predicts(strategy):
    scenario = jaxloc.Scenario.paper(strategy)
    rig = scenario.rig
    _, obs, _ = jaxloc.simulate_cycle(scenario, jr.key(3))
    closed = jaxloc.localize_cycle(obs, rig, throw=False)
    refined = jaxloc.refine_cycle(obs, rig, closed, throw=False)
    assert refined.result == RESULTS.successful
    (k, i, j, offset), predicted, figure = _hidden_blunder(obs, rig, refined, share=0.5)
    # The figure the gates report is the largest of the per-measurement shifts.
    np.testing.assert_allclose(float(refined.checks.blunder_nees), figure, rtol=1e-6)
    mask = np.zeros(obs.mutual.shape[:3], bool)
    mask[k, i, j] = True
    bad = _moved(obs, rig, (mask, np.zeros(obs.overhead.shape[:2], bool)), (offset, offset))
    blundered = jaxloc.refine_cycle(bad, rig, closed, throw=False)
    # Half the gate's limit: the sighting test lets it through...
    assert blundered.result == RESULTS.successful
    # ... and an end-of-cycle position moves by the predicted NEES (to first order).
    dp = np.asarray(blundered.poses.T_world_body.wxyz_xyz[-1, :, 4:]) - np.asarray(
        refined.poses.T_world_body.wxyz_xyz[-1, :, 4:]
    )
    dc = np.asarray(blundered.poses.T_world_overhead.wxyz_xyz[4:]) - np.asarray(
        refined.poses.T_world_overhead.wxyz_xyz[4:]
    )
    d = np.concatenate([dc[None], dp])
    Sigma = np.asarray(refined.covariance.position)
    nees = [d[q] @ np.linalg.solve(Sigma[q], d[q]) for q in range(4) if np.trace(Sigma[q]) > 0]
    # Shown with `pytest -s` (the README quotes it).
    print(f"{strategy}: blunder {offset} px on step {k}'s sighting of robot {j} by robot {i}: "
          f"position NEES moved {max(nees):.2f}, predicted {predicted:.2f}")  # fmt: skip
    assert max(nees) == pytest.approx(predicted, rel=0.15)
