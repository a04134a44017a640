"""Formation design (issue 8): parameters, constraints, objectives, search, CLI."""

import argparse
import json
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from jaxloc._design.formation import (
    constraint_margins,
    constraint_values,
    Formation,
    formation_filter,
    Limits,
    paper_fixed_moves,
    place_fixed,
)
from jaxloc._design.search import (
    crlb_objective,
    mc_objective,
    rmse_ci,
    rmse_table,
)
from jaxloc._sim.scenario import Scenario
from jaxloc._sim.scenario_file import load_scenario, save_scenario
from jaxloc._sim.simulate import simulate_cycle


SEQ = Scenario.paper("sequential")
FIXED = Formation.from_scenario(SEQ, paper_fixed_moves("sequential"))
RANDOM = Formation.from_scenario(SEQ)
KEYS = jr.split(jr.key(0), 2)


@eqx.filter_jit
def _crlb_a(f):
    return crlb_objective(f, SEQ, KEYS)[0]


def test_formation_round_trips_through_a_scenario_file(tmp_path):
    f = Formation(base=2.3, side=1.8, headings=(0.1, -0.2, 0.05), overhead_xy=(-0.3, 0.2),
                  overhead_heading=1.2, pan=0.05, tilt=-0.02, zoom=0.1, move_mean=0.9)
    path = tmp_path / "designed.yaml"
    save_scenario(f.to_scenario(SEQ), path)
    back = Formation.from_scenario(load_scenario(path))
    for name in ("base", "side", "headings", "overhead_xy", "overhead_heading", "pan", "tilt",
                 "zoom", "move_mean"):
        np.testing.assert_array_equal(getattr(back, name), getattr(f, name))
    with pytest.raises(ValueError, match="zoom"):
        Formation(zoom=1.5).to_scenario(SEQ)


TRIANGLE = np.array([[-1.2, 0.05], [0.05, 1.05], [-0.05, -0.95]])


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_fixed_moves_and_general_triangle_round_trip_through_a_file(tmp_path, suffix):
    # Issue 8: a designed formation with fixed moves and a general triangle is written as a
    # scenario file (Scenario.moves, Scenario.initial_xy) and read back unchanged.
    moves = np.array([[0.7, 0.1], [0.9, -0.2], [0.6, 0.15]])
    f = eqx.tree_at(lambda x: (x.moves, x.initial_xy), FIXED, (jnp.asarray(moves),
                    jnp.asarray(TRIANGLE)), is_leaf=lambda x: x is None)  # fmt: skip
    path = tmp_path / f"designed{suffix}"
    save_scenario(f.to_scenario(SEQ), path)
    loaded = load_scenario(path)
    np.testing.assert_array_equal(loaded.moves, moves)
    np.testing.assert_array_equal(loaded.formation_xy(), TRIANGLE)
    back = Formation.from_scenario(loaded)
    assert bool(eqx.tree_equal(back, f, typematch=True))
    # `moves=None` asks for random moves whatever the scenario holds.
    assert Formation.from_scenario(loaded, None).moves is None
    with pytest.raises(ValueError, match=r"Scenario\(moves=...\)` lengths"):
        eqx.tree_at(lambda x: x.moves, f, f.moves.at[1, 0].set(-0.2)).to_scenario(SEQ)


def test_general_triangle_places_like_the_isosceles_one():
    iso = jax.jit(place_fixed)(FIXED, SEQ)
    xy = np.asarray(FIXED.triangle_xy())
    gen = eqx.tree_at(lambda x: x.initial_xy, FIXED, jnp.asarray(xy), is_leaf=lambda x: x is None)
    assert gen.general_triangle and not FIXED.general_triangle
    assert bool(eqx.tree_equal(jax.jit(place_fixed)(gen, SEQ), iso))
    # Free fields: the triangle's positions replace base and side.
    spec = formation_filter(gen)
    assert spec.initial_xy is True or bool(jnp.all(spec.initial_xy))
    assert spec.base is False and spec.side is False and spec.move_mean is False
    assert "triangle" not in jax.eval_shape(constraint_values, gen, SEQ, iso)
    assert "triangle" in jax.eval_shape(constraint_values, FIXED, SEQ, iso)
    with pytest.raises(ValueError, match="initial_xy"):
        formation_filter(FIXED, ("initial_xy",))


_simulate_single = eqx.filter_jit(simulate_cycle)


def test_simulating_the_written_scenario_reproduces_the_design(tmp_path):
    # What `jaxloc simulate --scenario FILE` runs: simulate_cycle of the loaded scenario puts
    # the robots exactly where the design placed them (place_fixed, used by the objectives)
    # in every trial. (simulate_formation, of the Monte Carlo objective, is that simulation.)
    moves = np.array([[0.7, 0.1], [0.9, -0.2], [0.6, 0.15]])
    f = Formation(headings=(0.02, -0.1, 0.1), overhead_xy=(0.1, -0.05), moves=moves,
                  initial_xy=TRIANGLE)
    path = tmp_path / "designed.yaml"
    save_scenario(f.to_scenario(SEQ), path)
    scenario = load_scenario(path)
    pl = jax.jit(place_fixed)(f, SEQ)
    for seed in (0, 1):
        truth, _, ok = _simulate_single(scenario, jr.key(seed))
        assert bool(ok)
        np.testing.assert_allclose(truth.T_env_body.translation(), pl.p_body, atol=1e-13)
        np.testing.assert_allclose(truth.T_env_overhead.translation(), pl.p_overhead,
                                   atol=1e-13)


def test_filter_freezes_the_other_fields():
    spec = formation_filter(FIXED, ("overhead_xy", "moves"))
    free, frozen = eqx.partition(FIXED, spec)
    assert free.base is None and free.headings is None
    assert free.overhead_xy.shape == (2,) and free.moves.shape == (3, 2)
    assert frozen.overhead_xy is None and frozen.base is not None
    with pytest.raises(ValueError, match="Unknown formation parameter"):
        formation_filter(FIXED, ("height",))
    with pytest.raises(ValueError, match="random"):
        formation_filter(RANDOM, ("moves",))
    grads = eqx.filter_grad(lambda fr: jnp.sum(eqx.combine(fr, frozen).overhead_xy ** 2))(free)
    assert grads.base is None


def test_paper_formation_constraints():
    # The paper's formation keeps every sighting in view, but C1's PTZ sees C2 and C3 at
    # +-41.8 deg of its +-42.5 deg half field of view: ~5 px from the image edge, less than
    # the default 10 px margin.
    pl = jax.jit(place_fixed)(FIXED, SEQ)
    g = constraint_margins(constraint_values(FIXED, SEQ, pl))
    assert g["overhead_image"] > 0 and g["omni_elevation"] > 0 and g["separation"] > 0
    assert g["triangle_angle"] > 0 and g["move_length"] > 0
    assert -0.02 < g["ptz_image"] < 0
    g0 = constraint_margins(constraint_values(FIXED, SEQ, pl, Limits(image_margin_px=0.0)))
    assert all(v >= 0 for v in g0.values()), g0


def test_crlb_objective_gradient_matches_finite_differences():
    f = FIXED
    g = eqx.filter_jit(eqx.filter_grad(_crlb_a))(f)
    h = 1e-5
    for name, index in (("base", ()), ("overhead_xy", (0,)), ("moves", (1, 1)), ("pan", ())):
        def shifted(d):
            return eqx.tree_at(lambda x: getattr(x, name), f,
                               getattr(f, name).at[index].add(d))

        fd = (_crlb_a(shifted(h)) - _crlb_a(shifted(-h))) / (2 * h)
        an = getattr(g, name)[index]
        assert abs(an - fd) <= 1e-4 * abs(fd) + 1e-9, (name, an, fd)


_crlb_grad = eqx.filter_jit(eqx.filter_grad(_crlb_a))


def test_a_gradient_step_reduces_the_crlb_objective():
    spec = formation_filter(FIXED, ("overhead_xy", "moves", "base", "side"))
    g, _ = eqx.partition(_crlb_grad(FIXED), spec)
    norm2 = sum(jnp.sum(x * x) for x in jax.tree.leaves(g))
    step = jax.tree.map(lambda x: -0.01 * x / jnp.sqrt(norm2), g)  # 1 cm / 0.01 rad
    f1 = eqx.apply_updates(FIXED, step)
    before, after = float(_crlb_a(FIXED)), float(_crlb_a(f1))
    assert after < before
    # First order: the decrease matches the directional derivative.
    predicted = -0.01 * float(jnp.sqrt(norm2))
    assert after - before == pytest.approx(predicted, rel=0.2)


def test_rmse_confidence_intervals():
    rng = np.random.default_rng(0)
    e = np.abs(rng.normal(0.0, 0.1, 4000))
    rmse, lo, hi = rmse_ci(e, n_boot=400)
    assert lo < rmse < hi and lo < 0.1 < hi and hi - lo < 0.01
    n = 4000
    status = np.zeros((n, 1), np.int32)
    status[:10] = 3
    pos_b = np.abs(rng.normal(0.0, 0.1, (n, 1, 4)))
    before = {"status": status, "position": pos_b, "rotation": pos_b}
    after = {"status": np.zeros((n, 1), np.int32), "position": 0.5 * pos_b, "rotation": pos_b}
    table = rmse_table(before, after, n_boot=400)
    assert table["n_ok"] == [n - 10, n] and table["failures"] == [10, 0]
    r, lo, hi = table["C"]["ratio"]
    assert r == pytest.approx(0.5) and lo <= 0.5 <= hi


def _parser():
    from jaxloc._cli.design import register

    parser = argparse.ArgumentParser(prog="jaxloc")
    register(parser.add_subparsers(dest="command", required=True))
    return parser


@pytest.mark.parametrize(
    "argv, match",
    [
        (["design", "--free", "base,height"], "--free"),
        (["design", "--weights", "1,0"], "--weights"),
        (["design", "--objective", "mc", "--criterion", "D"], "crlb only"),
        (["design", "--starts", "0"], "--starts"),
        (["design", "--ray", " "], "--ray ADDRESS must not be empty"),
    ],
)
def test_cli_rejects_bad_arguments(argv, match):
    args = _parser().parse_args(argv)
    with pytest.raises(ValueError, match=match):
        args.func(args)


# --------------------------------------------------------------------------------------
# Slow: the Monte Carlo objective's gradient and a whole search through the CLI.


@pytest.mark.slow
def test_mc_objective_gradient_matches_finite_differences():
    keys = jr.split(jr.key(5), 2)

    @eqx.filter_jit
    def mc(f):
        value, aux = mc_objective(f, SEQ, keys)
        return value, aux["ok"]

    value, ok = mc(FIXED)
    assert bool(jnp.all(ok)) and float(value) > 0
    g = eqx.filter_jit(eqx.filter_grad(lambda f: mc(f)[0]))(FIXED)
    h = 1e-4
    for name, index in (("overhead_xy", (1,)), ("base", ()), ("moves", (0, 0))):
        def shifted(d):
            return eqx.tree_at(lambda x: getattr(x, name), FIXED,
                               getattr(FIXED, name).at[index].add(d))

        fd = (mc(shifted(h))[0] - mc(shifted(-h))[0]) / (2 * h)
        an = getattr(g, name)[index]
        assert abs(an - fd) <= 2e-3 * abs(fd) + 1e-7, (name, an, fd)


@pytest.mark.slow
def test_cli_design_round_trips_through_a_scenario_file(tmp_path):
    # design (fixed moves, general triangle) -> scenario file -> `jaxloc simulate`: the file
    # holds the optimized formation, moves included, and the simulation runs it.
    from jaxloc._cli.main import main
    from jaxloc._design.formation import CONSTRAINT_SCALES

    out, report_path = tmp_path / "designed.yaml", tmp_path / "report.json"
    argv = ["design", "--strategy", "sequential", "--moves", "fixed", "--triangle", "general",
            "--free", "initial_xy,overhead_xy,moves", "--starts", "2", "--draws", "1",
            "--iterations", "4", "--image-margin", "4", "--out", str(out),
            "--json", str(report_path), "--plot", str(tmp_path / "f.png")]
    args = _parser().parse_args(argv)
    assert args.func(args) == 0
    report = json.loads(report_path.read_text())
    scenario = load_scenario(out)
    loaded = Formation.from_scenario(scenario)
    assert loaded.fixed_moves and loaded.general_triangle
    for name, value in report["optimized"].items():
        if value is not None:
            np.testing.assert_allclose(getattr(loaded, name), value, rtol=1e-12)
    # Frozen parameters kept, free ones moved; the objective went down on the design draws.
    assert report["optimized"]["headings"] == report["initial"]["headings"]
    assert report["optimized"]["moves"] != report["initial"]["moves"]
    before, after = report["objective"]["design_draws"]
    assert after < before
    # Constraints hold at the optimum (up to the penalty's tolerance, a fraction of a scale).
    for k, v in report["constraint_margins"].items():
        assert v >= -0.25 * CONSTRAINT_SCALES[k], (k, v)
    assert os.path.getsize(tmp_path / "f.png") > 0
    # The simulated robots stand where the design placed them.
    truth, _, _ = simulate_cycle(scenario, jr.key(3))
    pl = place_fixed(loaded, scenario)
    np.testing.assert_allclose(truth.T_env_body.translation(), pl.p_body, atol=1e-12)
    # `jaxloc simulate` accepts the written scenario.
    assert main(["simulate", "--scenario", str(out), "--trials", "8", "--chunk-size", "8",
                 "--methods", "robust", "--no-progress"]) == 0
