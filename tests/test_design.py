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
from jaxloc._design import (
    crlb_objective,
    design_formation,
    design_penalty,
    mc_objective,
    rmse_ci,
    rmse_table,
)
from jaxloc._formation import (
    constraint_margins,
    constraint_values,
    Formation,
    formation_filter,
    Limits,
    paper_fixed_moves,
    place_fixed,
)
from jaxloc._scenario import load_scenario, save_scenario, Scenario


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
    with pytest.raises(ValueError, match="fixed `moves`"):
        FIXED.to_scenario(SEQ)
    with pytest.raises(ValueError, match="zoom"):
        Formation(zoom=1.5).to_scenario(SEQ)


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
