"""No wrong pose marked successful (issue 17): the goodness-of-fit and observability gates
of every estimate (jaxloc._model.gates), P3P ambiguity, missing and invalid inputs.

Each test is a case of the issue that was `successful` and wrong (or crashed) at 5ebd322.
One jitted pipeline per strategy (simulate -> corrupt -> closed forms -> refinement),
vmapped over a fixed batch, keeps compilation to one program per strategy."""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxloc
import numpy as np
import pytest
from jaxloc._core.results import RESULTS


BATCH = 32
SUCCESSFUL = RESULTS.successful._value


KINDS = (
    "clean", "swap_overhead", "overhead_first_step_only", "nan_overhead_pixel",
    "bearings_only", "negative_odometry", "zero_sigma",
)  # fmt: skip


def _corrupt(obs, kind: int):
    """Observations with one realistic defect, `KINDS[kind]` (traced: one program)."""
    return jax.lax.switch(kind, [ft.partial(_corrupt_as, kind=k) for k in KINDS], obs)


def _corrupt_as(obs, kind: str):
    """Observations with the defect `kind`."""
    if kind == "clean":
        return obs
    if kind == "swap_overhead":  # two overhead images swapped between steps
        last = obs.overhead.shape[0] - 1
        order = jnp.array([last] + list(range(1, last)) + [0])
        return eqx.tree_at(
            lambda o: (o.overhead, o.overhead_pixels, o.overhead_visible),
            obs,
            (obs.overhead[order], obs.overhead_pixels[order], obs.overhead_visible[order]),
        )
    if kind == "overhead_first_step_only":  # C saw the robots at step 0 only: 3 points
        seen = jnp.zeros_like(obs.overhead_visible).at[0].set(True)
        nan = jnp.where(seen[..., None], obs.overhead, jnp.nan)
        nan_px = jnp.where(seen[..., None], obs.overhead_pixels, jnp.nan)
        return eqx.tree_at(
            lambda o: (o.overhead, o.overhead_pixels, o.overhead_visible),
            obs,
            (nan, nan_px, seen),
        )
    if kind == "nan_overhead_pixel":  # a missed overhead detection, as a NaN pixel
        bearing = jaxloc.paper_overhead_camera().unproject(jnp.full(2, jnp.nan))
        return eqx.tree_at(
            lambda o: (o.overhead, o.overhead_pixels),
            obs,
            (obs.overhead.at[1, 1].set(bearing), obs.overhead_pixels.at[1, 1].set(jnp.nan)),
        )
    if kind == "bearings_only":  # the README's own-data path: no pixels at all
        return eqx.tree_at(
            lambda o: (o.mutual_pixels, o.overhead_pixels),
            obs,
            (
                jnp.full_like(obs.mutual_pixels, jnp.nan),
                jnp.full_like(obs.overhead_pixels, jnp.nan),
            ),
        )
    if kind == "negative_odometry":
        return eqx.tree_at(lambda o: o.odometry, obs, obs.odometry.at[1].multiply(-1.0))
    if kind == "zero_sigma":
        return eqx.tree_at(lambda o: o.odometry_sigma, obs, obs.odometry_sigma.at[0].set(0.0))
    raise ValueError(kind)


@ft.partial(jax.jit, static_argnames="strategy")
def _pipeline(keys, strategy, kind):
    scenario = jaxloc.Scenario.paper(strategy)

    def one(key):
        truth, obs, visible = jaxloc.simulate_cycle(scenario, key)
        obs = _corrupt(obs, kind)
        closed = jaxloc.localize_cycle(obs, scenario.rig, throw=False)
        refined = jaxloc.refine_cycle(obs, scenario.rig, closed, throw=False)
        c_true = truth.poses.T_world_overhead.translation()

        def c_error(e):
            return jnp.linalg.norm(e.poses.T_world_overhead.translation() - c_true)

        def c_nees(e):
            d = e.poses.T_world_overhead.translation() - c_true
            return d @ jnp.linalg.solve(e.covariance.position[0], d)

        return {
            "visible": visible,
            "closed": closed.result._value,
            "closed_error": c_error(closed),
            "closed_nees": c_nees(closed),
            "refined": refined.result._value,
            "refined_error": c_error(refined),
            "refined_nees": c_nees(refined),
            "dof": refined.checks.dof,
            "chi2": refined.checks.chi2,
            "alternatives": closed.alternatives.ok if closed.alternatives is not None else None,
        }

    return jax.vmap(one)(keys)


def _run(strategy, kind, seed=0):
    keys = jr.split(jr.key(seed), BATCH)
    out = jax.tree.map(np.asarray, _pipeline(keys, strategy, KINDS.index(kind)))
    return {k: v[out["visible"]] for k, v in out.items() if v is not None}


#: 99.99% quantile of chi-square with 3 degrees of freedom.
NEES_LIMIT = 21.108


def _assert_never_wrong_and_successful(out):
    """Every `successful` estimate of the overhead camera is consistent with its own
    covariance: NEES of its position below the 99.99% quantile."""
    for stage in ("closed", "refined"):
        ok = out[stage] == SUCCESSFUL
        nees = out[f"{stage}_nees"][ok]
        assert np.all(nees < NEES_LIMIT), (stage, nees, out[f"{stage}_error"][ok])


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_swapped_overhead_images_are_inconsistent(strategy):
    """Issue 17.3: with two overhead images swapped between steps, the closed forms
    reported `successful` with C 1.8-3 m off. Now the chi-square gate flags them."""
    out = _run(strategy, "swap_overhead")
    _assert_never_wrong_and_successful(out)
    inconsistent = RESULTS.inconsistent_fit._value
    assert np.mean(out["closed"] != SUCCESSFUL) > 0.9, out["closed"]
    assert np.mean(out["refined"] != SUCCESSFUL) > 0.9, out["refined"]
    assert np.any(out["closed"] == inconsistent)


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_overhead_sighted_once_is_ambiguous_or_right(strategy):
    """Issue 17.2: with the overhead camera seeing only step 0's three robots, P3P has up
    to four exact roots; the closed form reported one of them `successful`, often the
    wrong one. Now several valid roots give `ambiguous`, and a `successful` pose (one
    valid root) is the right one."""
    out = _run(strategy, "overhead_first_step_only")
    _assert_never_wrong_and_successful(out)
    assert np.any(out["closed"] == RESULTS.ambiguous._value)


@pytest.mark.parametrize("strategy", ["sequential"])
def test_missed_overhead_detection_is_missing_data(strategy):
    """Issue 17.1: a NaN pixel unprojected to the optical axis turned a missed detection
    into a confident wrong pose. A NaN bearing is missing data: the other sightings give
    the pose."""
    out = _run(strategy, "nan_overhead_pixel")
    _assert_never_wrong_and_successful(out)


def test_bearings_only_observations_refine_with_positive_dof():
    """Issue 17.4: `refine_cycle` on observations without pixels reported `successful`
    with dof -33 and chi-square 2.5e-25. Bearings are now projected through the rig's
    cameras: the refinement has its full degrees of freedom and a chi-square of them."""
    out = _run("sequential", "bearings_only")
    ok = out["refined"] == SUCCESSFUL
    assert ok.mean() > 0.9
    assert np.all(out["dof"] == 39)  # 2 x 36 pixel sightings + 3 distances - 36 unknowns
    assert 20 < np.mean(out["chi2"][ok]) < 60
    _assert_never_wrong_and_successful(out)


def test_negative_odometry_is_invalid_under_jit():
    """Issue 17.5: negative odometry was `successful` for the concurrent strategy."""
    out = _run("concurrent", "negative_odometry")
    assert np.all(out["closed"] == RESULTS.invalid_observation._value)
    assert np.all(out["refined"] == RESULTS.invalid_observation._value)


def test_zero_sigma_is_invalid_under_jit():
    """Issue 17.5: a zero odometry sigma was silently floored (an over-confident fit)."""
    out = _run("sequential", "zero_sigma")
    assert np.all(out["closed"] == RESULTS.invalid_observation._value)


def test_clean_cycles_pass_the_gates():
    out = _run("sequential", "clean")
    assert np.mean(out["refined"] == SUCCESSFUL) > 0.9
    _assert_never_wrong_and_successful(out)


def _clean_observations(strategy="sequential"):
    scenario = jaxloc.Scenario.paper(strategy)
    _, obs, _ = jax.jit(jaxloc.simulate_cycle)(scenario, jr.key(3))
    return scenario, obs


def test_observations_are_floating_and_validated():
    """Issue 17.5: integer odometry became an int64 sigma of zeros; negative odometry and
    non-positive sigmas were accepted. Wrong lengths raised a broadcasting error."""
    _, obs = _clean_observations()
    ints = jaxloc.CycleObservations(obs.mutual, obs.overhead, [1, 2, 1], 0.01, "sequential")
    assert ints.odometry.dtype == obs.mutual.dtype == ints.odometry_sigma.dtype
    np.testing.assert_allclose(ints.odometry_sigma, 0.01)
    for name, odometry, sigma in [
        ("odometry", [1.0, -2.0, 1.0], 0.01),
        ("odometry", [1.0, 0.0, 1.0], 0.01),
        ("odometry", [1.0, np.nan, 1.0], 0.01),
        ("odometry_sigma", [1.0, 2.0, 1.0], 0.0),
        ("odometry_sigma", [1.0, 2.0, 1.0], [0.01, -0.01, 0.01]),
    ]:
        with pytest.raises(ValueError, match=rf"`CycleObservations\({name}=...\)` must be finite"):
            jaxloc.CycleObservations(obs.mutual, obs.overhead, odometry, sigma, "sequential")
    with pytest.raises(ValueError, match=r"odometry=.*must have shape \(3,\)"):
        jaxloc.CycleObservations(obs.mutual, obs.overhead, [1.0, 2.0], 0.01, "sequential")


def test_float32_stays_float32():
    """Issue 17.15: float32 inputs came back float64 with a FutureWarning."""
    scenario = jaxloc.astype(jaxloc.Scenario.paper("sequential"), jnp.float32)
    _, obs, _ = jax.jit(jaxloc.simulate_cycle)(scenario, jr.key(3))
    closed = jax.jit(lambda o, r: jaxloc.localize_cycle(o, r, throw=False))(obs, scenario.rig)
    refined = jax.jit(lambda o, r, e: jaxloc.refine_cycle(o, r, e, throw=False))(
        obs, scenario.rig, closed
    )
    for estimate in (closed, refined):
        for leaf in jax.tree.leaves((estimate.poses, estimate.checks.chi2, estimate.scales)):
            assert leaf.dtype == jnp.float32
    assert refined.result == RESULTS.successful


def test_nan_overhead_bearing_marked_visible_is_nonfinite():
    """Issue 17.15: a NaN overhead bearing that `overhead_visible` says was seen reported
    `no_valid_solution`; it is `nonfinite_observation` (a NaN bearing left to the default
    visibility is missing data)."""
    scenario, obs = _clean_observations()
    bad = eqx.tree_at(lambda o: o.overhead, obs, obs.overhead.at[1, 1].set(jnp.nan))
    est = jaxloc.localize_cycle(bad, scenario.rig, throw=False)
    assert est.result == RESULTS.nonfinite_observation
    missing = jaxloc.CycleObservations(
        bad.mutual, bad.overhead, bad.odometry, bad.odometry_sigma, "sequential"
    )
    assert not bool(missing.overhead_visible[1, 1])


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_information_singular_to_rounding_is_not_observable(dtype):
    """Issue 17 (missing sightings): the Cholesky of an information matrix that is
    singular to rounding can succeed (its pivot a tiny positive number), and the gates
    took it as observable. `nonsingular_information` rejects it, however its rows are
    weighed, and keeps an observable information whose rows are weighed 1e6 apart (a
    noiseless cycle's pixels at the 1e-6 px floor beside its odometry), which the
    Jacobi-scaled `J^T J` alone puts at rounding level too."""
    from jaxloc._core.linalg import spd_inverse
    from jaxloc._model.gates import nonsingular_information
    from jaxloc._study.robustness import nonsingular

    eps = float(jnp.finfo(dtype).eps)
    # Direction (1, -1, 0) touched only by rounding.
    singular = jnp.asarray([[1e3, 1e3, 0.0], [1.0, 1.0 + 2 * eps, 0.0], [0.0, 0.0, 1e-2]],
                           dtype)  # fmt: skip
    assert not bool(nonsingular_information(singular))
    # Observable: (1, -1, 0) seen by one row weighed 1e6 below the others.
    weighed = jnp.asarray([[1e6, 1e6, 0.0], [1.0, -1.0, 0.0], [0.0, 0.0, 1e6]], dtype)
    assert bool(nonsingular_information(weighed))
    if dtype == jnp.float64:
        H = weighed.T @ weighed
        d = 1 / jnp.sqrt(jnp.diag(H))
        assert float(jnp.linalg.eigvalsh(H * d[:, None] * d[None])[0]) < 1e-10  # Jacobi alone
        _, ok = spd_inverse(singular.T @ singular)
        assert bool(ok)  # the Cholesky alone passes the singular one
        assert not bool(nonsingular(singular)) and bool(nonsingular(weighed))
    assert not bool(nonsingular_information(jnp.zeros((4, 3), dtype)))


def test_a_rival_minimum_makes_the_closed_form_ambiguous():
    """The closed form's rival start (its other local minimum, polished in the gates' own
    Gauss--Newton loop beside the point) is what makes these clean concurrent cycles
    `ambiguous`: trials 178 and 364 of `split(key(0), 4096)` in the paper's scenario.
    Gated without the rival, or with it marked inactive, the same estimates are
    `successful`."""
    from jaxloc._model.gates import gate_all, gate_point, gate_rivals
    from jaxloc._model.measurements import cycle_data
    from jaxloc._solvers.localize import closed_forms

    scenario = jaxloc.Scenario.paper("concurrent")
    rig = scenario.rig

    def results(key):
        _, obs, _ = jaxloc.simulate_cycle(scenario, key)
        (estimate,) = closed_forms(obs, ("robust",))
        point = gate_point(estimate, cycle_data(obs, rig), "concurrent")
        rival = gate_rivals(estimate, point, "concurrent")
        inactive = (rival[0], rival[1], jnp.zeros_like(rival[2]))
        gates = gate_all([point] * 3, rig, "concurrent", polish=True,
                         rivals=[rival, None, inactive])  # fmt: skip
        return jnp.stack([g[0]._value for g in gates])

    keys = jr.split(jr.key(0), 4096)[jnp.array([178, 364])]
    codes = np.asarray(jax.jit(jax.vmap(results))(keys))
    assert np.all(codes[:, 0] == RESULTS.ambiguous._value), codes
    assert np.all(codes[:, 1:] == SUCCESSFUL), codes


def test_a_gross_error_in_a_weakly_controlled_odometry_is_inconsistent():
    """One odometry distance scaled by 0.72-1.14 in random sequential formations (cycles
    5378, 12408, 18798 and 25148 of `benchmarks/corrupted_cycles.py`'s seed 0): the
    others control it weakly (redundancy 0.1-0.35), so the refinement absorbs the error
    into the scale and its total chi-square stays under the limit, with C 10-26 of its
    own standard deviations off (position NEES 127-668). Only the test of each
    measurement against the rest (`worst_sighting`, Baarda's data snooping) sees it;
    these were `successful` before it."""
    from jaxloc._sim.defects import corrupt_observations, DEFECTS
    from jaxloc._study.robustness import final_positions, position_nees, random_formation

    base = jaxloc.Scenario.paper("sequential")

    def one(key):
        k_geo, k_sim, k_defect = jr.split(key, 3)
        scenario = random_formation(base, k_geo, 0.3, 0.5)
        truth, obs, visible = jaxloc.simulate_cycle(scenario, k_sim)
        obs = corrupt_observations(obs, scenario.rig, DEFECTS.index("scaled_odometry"),
                                   key=k_defect)  # fmt: skip
        closed = jaxloc.localize_cycle(obs, scenario.rig, throw=False)
        refined = jaxloc.refine_cycle(obs, scenario.rig, closed, throw=False)
        c = refined.checks
        nees = jnp.max(position_nees(refined, final_positions(truth.poses)))
        return visible, refined.result._value, c.chi2_min <= c.chi2_limit, c.worst_sighting, nees

    keys = jax.vmap(lambda i: jr.fold_in(jr.key(0), i))(jnp.array([5378, 12408, 18798, 25148]))
    visible, result, chi2_passes, worst, nees = map(np.asarray, jax.jit(jax.vmap(one))(keys))
    assert visible.all()
    assert np.all(nees > 100.0), nees  # wrong by 10 standard deviations or more
    assert chi2_passes.all()  # the total chi-square does not notice
    assert np.all(worst > 1.0), worst
    assert np.all(result == RESULTS.inconsistent_fit._value), result


@pytest.mark.slow
@pytest.mark.parametrize("late", [1, 2])
def test_mixed_polish_flags_gate_as_separate_calls(late):
    """A trial gates its closed form (polished) and its refinement and the
    true poses (not polished) in one `gate_all` call; each gate equals that of a call with
    only its own kind. `late=2` puts more unpolished points than polished lanes (one: the
    closed form, gated here without rivals), the branch that adds lanes with an
    evaluation only."""
    from jaxloc._model.covariance import crlb_inputs
    from jaxloc._model.gates import end_poses, gate_all, gate_point, GatePoint
    from jaxloc._model.measurements import cycle_data
    from jaxloc._refine.cycle import refine_solution
    from jaxloc._solvers.localize import closed_forms

    scenario = jaxloc.Scenario.paper("sequential")
    rig = scenario.rig

    @jax.jit
    def gates(key):
        truth, obs, _ = jaxloc.simulate_cycle(scenario, key)
        data = cycle_data(obs, rig)
        (closed,) = closed_forms(obs, ("robust",))
        refined, _ = refine_solution(obs, rig, closed, solver="lm", max_steps=50, rtol=1e-6,
                                     atol=1e-6)  # fmt: skip
        T_place, T_over, bound_data = crlb_inputs(rig, truth.poses, scenario.odometry_sigma_rel,
                                                  "sequential")  # fmt: skip
        true_point = GatePoint(T_place, T_over, end_poses(T_place, T_over, "sequential"),
                               bound_data, RESULTS.successful)  # fmt: skip
        polished = [gate_point(closed, data, "sequential")]
        unpolished = [gate_point(refined, data, "sequential"), true_point][:late]
        mixed = gate_all(polished + unpolished, rig, "sequential",
                         polish=[True] + [False] * late)  # fmt: skip
        apart = gate_all(polished, rig, "sequential", polish=True) + gate_all(
            unpolished, rig, "sequential", polish=False
        )
        return mixed, apart

    mixed, apart = gates(jr.key(3))
    assert len(mixed) == len(apart) == 1 + late
    for one, other in zip(mixed, apart):
        assert one[0] == other[0]
        for a, b in zip(jax.tree.leaves(one[1:]), jax.tree.leaves(other[1:])):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12)
    assert mixed[0][0] == RESULTS.successful and mixed[-1][0] == RESULTS.successful
