"""Property-based fuzzing of the public cycle API (issue 17): random formations x random
corruptions (`jaxloc.DEFECTS`: NaN, infinite, zero, negated, swapped, outlier and missing
sightings, scaled and negative odometry). Invariant: whenever an estimate is
`successful`, it is not wrong: no end-of-cycle position is ten of its own standard
deviations off (NEES below `WRONG_POSE_NEES`; the 99.99% chi-square quantile is too
strict for the first-order covariance in random near-degenerate formations, see there).

Examples are derandomized (the same every run), so the test is deterministic; one jitted
program per strategy serves every example (the defect is data)."""

import functools as ft

import jax
import jax.numpy as jnp
import jax.random as jr
import jaxloc
import numpy as np
from hypothesis import given, HealthCheck, settings, strategies as st
from jaxloc._core.results import RESULTS
from jaxloc._study.robustness import corrupted_trial, WRONG_POSE_NEES


@ft.partial(jax.jit, static_argnames="strategy")
def _trial(strategy, key, defect, spread, turn):
    return corrupted_trial(jaxloc.Scenario.paper(strategy), key, defect, spread, turn)


@settings(
    max_examples=40, deadline=None, derandomize=True, database=None,
    suppress_health_check=[HealthCheck.too_slow],
)  # fmt: skip
@given(
    seed=st.integers(0, 2**31 - 1),
    strategy=st.sampled_from(["sequential", "concurrent"]),
    defect=st.integers(0, len(jaxloc.DEFECTS) - 1),
    spread=st.floats(0.0, 0.6),
    turn=st.floats(0.0, 1.0),
)
def test_successful_estimates_are_consistent(seed, strategy, defect, spread, turn):
    out = _trial(strategy, jr.key(seed), defect, jnp.asarray(spread), jnp.asarray(turn))
    out = jax.tree.map(np.asarray, out)
    if not out["visible"]:
        return
    for stage in ("closed", "refined"):
        if out[stage] == RESULTS.successful._value:
            nees = out[f"{stage}_nees"]
            assert np.all(nees < WRONG_POSE_NEES), (jaxloc.DEFECTS[defect], stage, nees)
