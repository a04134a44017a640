r"""Formation design: objectives, gradient-based search, and fresh Monte Carlo checks
(DESIGN §5, §9).

- Objectives, each differentiable in a [`jaxloc.Formation`][]:
  [`jaxloc.crlb_objective`][] (the Cramér–Rao bound of the overhead camera's position:
  A-optimal trace or D-optimal log-det, averaged over fixed draws of the random moves:
  common random numbers) and [`jaxloc.mc_objective`][] (the mean squared error of the
  refined estimator over fixed noise draws, differentiated through the solver by
  optimistix's implicit adjoint).
- [`jaxloc.design_formation`][]: BFGS (optimistix) on objective + smooth constraint
  penalty, from the given formation and many random starts at once (`vmap`), keeping the
  best feasible result. A start runner decides where the starts run: all in one `vmap`
  here ([`local_starts`][], the default), or in groups, each a Ray task
  (`jaxloc._design.cluster.ray_starts`).
- [`jaxloc.evaluate_formation`][] and [`jaxloc.rmse_table`][]: fresh Monte Carlo of the
  refined estimator (new seed) with bootstrap confidence intervals.
"""

import functools as ft
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, PRNGKeyArray, Scalar

from .._core.compiler import compiler_options
from .._core.linalg import logdet3
from .._core.programs import cached_program, describe
from .._core.results import RESULTS
from .._cycle.layout import CAMERAS
from .._model.covariance import cycle_crlb
from .._refine.cycle import refine_cycle
from .._sim.scenario import Scenario
from .._sim.simulate import camera_points, sightings_in_view
from .._solvers.localize import localize_cycle_methods
from .._study.engine import run_study
from .._study.trial import REFINE_MAX_STEPS, score
from .formation import (
    constraint_penalty,
    constraint_values,
    Formation,
    formation_filter,
    Limits,
    place_fixed,
    Placement,
    placement_from_truth,
)


OBJECTIVES = ("crlb", "mc")
#: Solver of the Monte Carlo objective's refinement: optimistix's Levenberg--Marquardt,
#: differentiated by optimistix's implicit adjoint, where `refine_cycle` offers it (its
#: default fast path is used for plain evaluation).
_MC_SOLVER = "optx-lm"
CRITERIA = ("A", "D")


# --------------------------------------------------------------------------------------
# One cycle of a formation.


def simulate_formation(formation: Formation, scenario: Scenario, key: PRNGKeyArray):
    """Simulate one cycle of `formation` in `scenario`'s world: exactly
    [`jaxloc.simulate_cycle`][] on `formation.apply(scenario)` (random moves drawn and
    resampled as the simulator does; fixed moves applied as given, the scenario's `moves`
    field), so that what a design optimizes is what `jaxloc simulate` of its scenario
    file runs.

    **Returns:** `(poses, observations, placement, all_visible)`: the true
    [`jaxloc.CyclePoses`][] in `W`, the [`jaxloc.CycleObservations`][], the
    [`jaxloc.Placement`][] in `E` (for fixed moves from [`jaxloc.place_fixed`][], which places the
    robots exactly where the simulator does, as plain matrices), and whether every
    required sighting exists (and the robots keep `min_separation`).
    """
    from .._sim.simulate import simulate_cycle

    scn = formation.apply(scenario)
    truth, obs, ok = simulate_cycle(scn, key)
    pl = place_fixed(formation, scn) if formation.fixed_moves else placement_from_truth(truth)
    return truth.poses, obs, pl, ok


def _all_visible(scn: Scenario, pl: Placement):
    cams = camera_points(scn, pl.R_body, pl.p_body, pl.R_overhead, pl.p_overhead)
    ok, _, _ = sightings_in_view(scn, *cams)
    return jnp.all(ok)


# --------------------------------------------------------------------------------------
# Objectives.


def _weights(weights, dtype):
    w = jnp.asarray(weights, dtype)
    if w.shape != (4,):
        raise ValueError(f"`weights` must have 4 entries (C, C1, C2, C3); got {weights!r}.")
    return w


def _draws(formation: Formation, keys):
    """The CRN keys a formation needs: one geometry for fixed moves, all for random."""
    return keys[:1] if formation.fixed_moves else keys


def crlb_objective(
    formation: Formation,
    scenario: Scenario,
    keys: PRNGKeyArray,
    *,
    criterion: str = "A",
    weights=(1.0, 0.0, 0.0, 0.0),
) -> tuple[Scalar, dict[str, Array]]:
    r"""Cramér–Rao objective of a formation (DESIGN §9), differentiable.

    For each draw `k` of `keys` (common random numbers: the same moves for every
    formation evaluated with the same keys; a fixed-moves formation has one geometry and
    uses only `keys[0]`), the bound $P_c$ of each camera's final position
    ([`jaxloc.cycle_crlb`][], m^2) is computed at the true poses.

    - `criterion="A"`: $\frac{1}{K}\sum_k \sum_c w_c\,\mathrm{tr}\,P_c$ (m^2): the
      predicted mean squared error. Its square root is the predicted RMSE.
    - `criterion="D"`: $\frac{1}{K}\sum_k \sum_c w_c \log\det P_c$ (log of m^6).

    **Arguments:**

    - `formation`: a [`jaxloc.Formation`][].
    - `scenario`: the world, cameras, noise (its formation fields are replaced).
    - `keys`: PRNG keys, shape `(K,)`.
    - `criterion`: `"A"` or `"D"`. Keyword only.
    - `weights`: per camera (C, C1, C2, C3); default the overhead camera only.

    **Returns:** `(value, aux)` with `aux` holding `"trace"` `(K, 4)` (m^2),
    `"feasible"` `(K,)` (every required sighting exists), and `"penalty_inputs"`, the
    placements `(K, ...)`, for [`jaxloc.design_penalty`][].
    """
    if criterion not in CRITERIA:
        raise ValueError(f"`criterion` must be one of {CRITERIA}; got {criterion!r}.")
    dtype = scenario.base.dtype
    w = _weights(weights, dtype)

    def one(key):
        scn = formation.apply(scenario)
        if formation.fixed_moves:
            pl = place_fixed(formation, scn)
            poses, ok = pl.poses(), _all_visible(scn, pl)
        else:
            poses, _, pl, ok = simulate_formation(formation, scenario, key)
        P = cycle_crlb(scn.rig, poses, odometry_sigma_rel=scn.odometry_sigma_rel).position
        tr = jnp.trace(P, axis1=-2, axis2=-1)
        if criterion == "A":
            v = jnp.sum(w * tr)
        else:
            v = jnp.sum(jnp.where(w > 0, w * jax.vmap(logdet3)(P), 0.0))
        return v, tr, ok, pl

    v, tr, ok, pl = jax.vmap(one)(_draws(formation, keys))
    return jnp.mean(v), {"trace": tr, "feasible": ok, "placements": pl}


def mc_objective(
    formation: Formation,
    scenario: Scenario,
    keys: PRNGKeyArray,
    *,
    weights=(1.0, 0.0, 0.0, 0.0),
) -> tuple[Scalar, dict[str, Array]]:
    r"""Monte Carlo objective: mean over fixed noise draws (common random numbers) of the
    refined estimator's squared final-position error, $\frac{1}{K_\mathrm{ok}}
    \sum_k \sum_c w_c \|\hat p_{c,k} - p_{c,k}\|^2$ (m^2), differentiable.

    Each draw simulates the cycle ([`jaxloc.simulate_formation`][]; the key sets the moves, if
    random, and every noise sample), starts from the closed-form `"robust"` estimate
    (treated as a constant: the optimum does not depend on the start) and refines with
    [`jaxloc.refine_cycle`][]; gradients go through the solver by optimistix's implicit
    adjoint (never unrolled). Trials that fail (not visible, solver failure, chi-square
    gate) are left out of the mean; their count is in `aux`.

    **Returns:** `(value, aux)`, `aux`: `"sq_error"` `(K, 4)` (m^2), `"ok"` `(K,)`,
    `"feasible"` `(K,)`, `"placements"`.
    """
    dtype = scenario.base.dtype
    w = _weights(weights, dtype)

    def one(key):
        scn = formation.apply(scenario)
        poses, obs, pl, visible = simulate_formation(formation, scenario, key)
        (start,) = localize_cycle_methods(obs, scn.rig, ("robust",))
        start = jax.lax.stop_gradient(start)
        est = refine_cycle(
            obs, scn.rig, start, solver=_MC_SOLVER, max_steps=REFINE_MAX_STEPS, throw=False
        )
        pos, _, _, diff = score(est.poses, poses, scn.rig)
        ok = visible & (est.result == RESULTS.successful)
        sq = jnp.sum(diff * diff, axis=-1)
        return jnp.where(ok, jnp.sum(w * sq), 0.0), sq, ok, visible, pl

    v, sq, ok, visible, pl = jax.vmap(one)(keys)
    n_ok = jnp.maximum(jnp.sum(ok), 1).astype(dtype)
    return jnp.sum(v) / n_ok, {"sq_error": sq, "ok": ok, "feasible": visible, "placements": pl}


def design_penalty(
    formation: Formation,
    scenario: Scenario,
    placements: Placement,
    limits: Limits = Limits(),
    strict_steps: bool = True,
) -> Scalar:
    """Mean over draws of [`jaxloc.constraint_penalty`][] of each drawn placement
    (batched `Placement`, leading axis = draws). With `strict_steps` every step of the
    cycle gets the full margins; otherwise only the initial formation does and later
    steps need only be in view (for random moves: the simulator's resampling keeps them
    there when it can; full margins on the drawn moves make a design robust to draws it
    has not seen)."""
    scn = formation.apply(scenario)
    strict = strict_steps

    def one(pl):
        values = constraint_values(formation, scn, pl, limits, strict_steps=strict)
        return constraint_penalty(values)

    return jnp.mean(jax.vmap(one)(placements))


# --------------------------------------------------------------------------------------
# Search.

#: Scale (natural units) of each formation field in the optimizer's normalized
#: coordinates and in the random starts.
FIELD_SCALES = {
    "base": 0.1, "side": 0.1, "headings": 0.1, "overhead_xy": 0.1, "overhead_heading": 0.1,
    "pan": 0.1, "tilt": 0.1, "zoom": 0.05, "move_mean": 0.1, "moves": 0.1, "initial_xy": 0.1,
}  # fmt: skip
#: Half-width (natural units) of the uniform perturbation of each field for random starts.
START_SPREAD = {
    "base": 0.2, "side": 0.15, "headings": 0.1, "overhead_xy": 0.3,
    "overhead_heading": 0.5 * math.pi, "pan": 0.1, "tilt": 0.05, "zoom": 0.0,
    "move_mean": 0.2, "moves": 0.3, "initial_xy": 0.15,
}  # fmt: skip


def _field_tree(formation: Formation, table: dict[str, float]) -> Formation:
    """A formation-shaped tree holding `table[field]` at every leaf of each field."""
    return Formation(
        **{
            n: (None if getattr(formation, n) is None
                else jnp.full_like(getattr(formation, n), table[n]))
            for n in table
        }
    )  # fmt: skip


class DesignResult(eqx.Module):
    """Outcome of [`jaxloc.design_formation`][].

    **Fields:**

    - `formation`: the best feasible formation found (or the least infeasible if none).
    - `initial`: the formation the search started from.
    - `objective`, `objective_initial`: the unpenalized objective (m^2 for A/MC, log m^6
      for D) at `formation` and at `initial`, on the design's own draws.
    - `penalty`: its constraint penalty (0 = every constraint satisfied).
    - `history`: penalized, normalized objective per BFGS iteration for every start,
      shape `(starts, iterations)` (frozen once a start has converged).
    - `final`: penalized normalized objective of every start, `(starts,)`.
    - `penalties`: constraint penalty of every start's result, `(starts,)`.
    - `best`: index of the chosen start.
    - `steps`: BFGS iterations each start ran, `(starts,)`.
    """

    formation: Formation
    initial: Formation
    objective: Array
    objective_initial: Array
    penalty: Array
    history: Array
    final: Array
    penalties: Array
    best: Array
    steps: Array


def _objective_fn(objective: str, criterion: str, weights):
    if objective == "crlb":
        return lambda f, s, k: crlb_objective(f, s, k, criterion=criterion, weights=weights)
    if objective == "mc":
        if criterion != "A":
            raise ValueError('The "mc" objective is a mean squared error: use criterion "A".')
        return lambda f, s, k: mc_objective(f, s, k, weights=weights)
    raise ValueError(f"`objective` must be one of {OBJECTIVES}; got {objective!r}.")


def _normalizer(criterion: str, value0):
    """Map the raw objective to an O(10) quantity for BFGS: RMSE relative to the start
    (A) or log-det difference (D)."""
    if criterion == "A":
        return lambda v: 10.0 * jnp.sqrt(jnp.maximum(v, 0.0) / value0)
    return lambda v: v - value0


def _fixed_length_minimise(solver, f, z0, dtype, iterations: int):
    """Minimise `f(z, args) -> (value, aux)` from `z0` with `solver` (optimistix) in a
    `lax.scan` of exactly `iterations` steps that stops moving once the solver
    terminates (a fixed-length loop, reverse-differentiable and vmappable).

    Returns `(z, num_steps, history)`: the minimiser, the steps taken before termination
    and the objective `f` after every scan step, shape `(iterations,)`."""
    f_struct = jax.ShapeDtypeStruct((), dtype)
    aux_struct = jax.eval_shape(lambda: f(z0, None)[1])
    state = solver.init(f, z0, None, {}, f_struct, aux_struct, frozenset())

    def body(carry, _):
        z, state, done, n = carry
        z_new, state_new, _ = solver.step(f, z, None, {}, state, frozenset())
        stop, _ = solver.terminate(f, z_new, None, {}, state_new, frozenset())
        z = jax.tree.map(lambda a, b: jnp.where(done, a, b), z, z_new)
        state = jax.tree.map(
            lambda a, b: jnp.where(done, a, b) if eqx.is_array(a) else b, state, state_new
        )
        n = n + jnp.where(done, 0, 1)
        done = done | stop
        return (z, state, done, n), state.f_info.f

    (z, state, _, n), hist = jax.lax.scan(
        body, (z0, state, jnp.array(False), jnp.array(0)), None, length=iterations
    )
    return z, n, hist


def _search(
    formation0: Formation,
    starts: Formation,
    scenario: Scenario,
    keys,
    spec,
    *,
    objective: str,
    criterion: str,
    weights: tuple,
    limits: Limits,
    strict_steps: bool,
    penalty_weight: float,
    iterations: int,
    rtol: float,
    atol: float,
):
    fn = _objective_fn(objective, criterion, weights)
    value0, _ = fn(formation0, scenario, keys)
    value0 = jax.lax.stop_gradient(value0)
    norm = _normalizer(criterion, value0)
    scales = _field_tree(formation0, FIELD_SCALES)
    free0, frozen = eqx.partition(formation0, spec)
    free_scales, _ = eqx.partition(scales, spec)

    def unscale(z, base):
        return jax.tree.map(lambda zi, s, b: b + s * zi, z, free_scales, base)

    def penalized(z, base):
        f = eqx.combine(unscale(z, base), frozen)
        value, aux = fn(f, scenario, keys)
        pen = design_penalty(f, scenario, aux["placements"], limits, strict_steps)
        return norm(value) + penalty_weight * pen, (value, pen)

    solver = optx.BFGS(rtol=rtol, atol=atol)

    def run(start: Formation):
        base, _ = eqx.partition(start, spec)
        z0 = jax.tree.map(jnp.zeros_like, base)
        f = lambda z, args: penalized(z, base)  # noqa: E731
        z, n, hist = _fixed_length_minimise(solver, f, z0, scenario.base.dtype, iterations)
        value, pen = penalized(z, base)[1]
        total, _ = penalized(z, base)
        return eqx.combine(unscale(z, base), frozen), total, value, pen, hist, n

    out = jax.vmap(run)(starts)
    return value0, out


def search_starts(formation0, scenario, keys, spec, options: dict, starts: Formation):
    """The search of [`jaxloc.design_formation`][] from `starts` (a batched
    [`jaxloc.Formation`][], leading axis: start; any number of them), every start on the
    draws `keys` and normalized by the objective of `formation0` on them. `options`: the
    keyword arguments of `_search` (objective, limits, iterations, ...).

    **Returns:** `(value0, (formations, total, value, penalty, history, steps))` as numpy
    arrays (cheap to send back from a worker): the objective of `formation0`, then per
    start its result, penalized normalized objective, objective, constraint penalty,
    objective per iteration `(starts, iterations)` and BFGS steps.
    """
    program, args = _search_program(formation0, starts, scenario, keys, spec, options)
    value0, form_leaves, *per_start = program(args)
    forms = jax.tree.unflatten(jax.tree.structure(starts), form_leaves)
    return jax.device_get((value0, (forms, *per_start)))


def _search_program(formation0, starts, scenario, keys, spec, options: dict):
    """The search as a program kept traced on disk (`jaxloc._core.programs`; a later
    process loads it instead of tracing it), on the default device, with its arguments:
    the arrays of the formations and the scenario, and the draws' key data. The large
    program XLA options (classic emitters, LLVM -O1): on a sequential design of 4 starts
    x 8 draws x 30 iterations, compile 54 -> 43 s; the search runs as fast (0.6 s) and
    ends at the same objective (to 1e-13 relative)."""
    dynamic, rest = eqx.partition((formation0, starts, scenario), eqx.is_array)
    arrays, tree = jax.tree.flatten(dynamic)
    impl = jr.key_impl(keys)

    def make_fn():
        def search(args):
            arrays, key_data = args
            f0, st, sc = eqx.combine(jax.tree.unflatten(tree, arrays), rest)
            draws = jr.wrap_key_data(key_data, impl=impl)
            value0, (forms, *per_start) = _search(f0, st, sc, draws, spec, **options)
            return value0, jax.tree.leaves(forms), *per_start

        return search

    static = describe((rest, spec, sorted(options.items()), str(tree), str(impl)))
    args = (arrays, jr.key_data(keys))
    program = cached_program(
        "design_search", make_fn, static, args,
        compiler_options=compiler_options(), replicated=False,
    )  # fmt: skip
    return program, args


#: Where a design's starts run: `runner(search, starts)` splits `starts` (a batched
#: [`jaxloc.Formation`][], leading axis: start) into consecutive groups ([`split_starts`][])
#: and returns `[search(group) for group in groups]`, in order. `search` is a picklable
#: [`search_starts`][] with everything but the starts bound.
StartRunner = Callable[[Callable[[Formation], tuple], Formation], list]


def local_starts(search: Callable[[Formation], tuple], starts: Formation) -> list:
    """The default [`StartRunner`][]: every start in one group, in this process (one
    `vmap`)."""
    return [search(starts)]


def num_starts(starts: Formation) -> int:
    """The number of starts of a batched formation (its leaves' leading axis)."""
    return int(jax.tree.leaves(starts)[0].shape[0])


def split_starts(starts: Formation, groups: int) -> list[Formation]:
    """`starts` (batched, leading axis: start) as `groups` consecutive groups whose
    sizes differ by at most one (the first ones larger), as `numpy.array_split`."""
    n = num_starts(starts)
    if not 1 <= groups <= n:
        raise ValueError(f"`groups` must be in [1, {n}] (the number of starts); got {groups}.")
    bounds = np.cumsum([0] + [n // groups + (g < n % groups) for g in range(groups)])
    return [jax.tree.map(lambda x: x[a:b], starts) for a, b in zip(bounds[:-1], bounds[1:])]


def _gather(outs: list) -> tuple:
    """The groups' results of [`search_starts`][] as one search's: `value0` of the first
    group (every group computes it from the same formation and draws; on other machines of
    a cluster it may differ in the last bits, as any other number) and every start's
    results concatenated in start order."""
    starts_out = jax.tree.map(lambda *xs: jnp.concatenate(xs), *(o[1] for o in outs))
    return jnp.asarray(outs[0][0]), starts_out


def random_starts(
    formation: Formation, spec: Formation, n: int, *, key: PRNGKeyArray
) -> Formation:
    """`n` starting formations (batched leaves): `formation` itself first, then uniform
    perturbations of its free fields (`spec`) by `START_SPREAD`. Random headings of the
    overhead camera cover the whole circle."""
    spread = _field_tree(formation, START_SPREAD)
    leaves, treedef = jax.tree.flatten(formation)
    spread_leaves = jax.tree.leaves(spread)
    spec_leaves = jax.tree.leaves(spec)
    keys = jr.split(key, len(leaves))
    out = []
    for x, s, free, k in zip(leaves, spread_leaves, spec_leaves, keys):
        u = jr.uniform(k, (n,) + x.shape, x.dtype, -1.0, 1.0) * jnp.asarray(s)[None]
        u = u.at[0].set(0.0)
        out.append(x[None] + (u if free else 0.0 * u))
    return jax.tree.unflatten(treedef, out)


def design_formation(
    formation: Formation,
    scenario: Scenario,
    *,
    key: PRNGKeyArray,
    objective: str = "crlb",
    criterion: str = "A",
    free: tuple[str, ...] | str = "all",
    weights=(1.0, 0.0, 0.0, 0.0),
    num_starts: int = 8,
    num_draws: int = 32,
    iterations: int = 60,
    limits: Limits = Limits(),
    strict_steps: bool | None = None,
    penalty_weight: float = 10.0,
    feasibility_tol: float = 0.05,
    rtol: float = 1e-5,
    atol: float = 1e-5,
    runner: StartRunner | None = None,
) -> DesignResult:
    r"""Search for the formation minimizing an objective under the design constraints.

    Minimizes `objective + penalty_weight * penalty` with `optx.BFGS` in normalized
    coordinates (each free field divided by `FIELD_SCALES`; the A objective as
    `10 * RMSE / RMSE_start`), for `iterations` steps (or until BFGS converges), from
    `formation` and `num_starts - 1` random perturbations of it, all at once under
    `jax.vmap`. Every start sees the same draws (common random numbers). The result is the
    start with the lowest objective among those whose constraint penalty is at most
    `feasibility_tol` (a violation of the margins by `sqrt(tol)` of a scale unit, e.g.
    2 px of a 10 px image margin at the default), or the least infeasible one.

    **Arguments:**

    - `formation`: the starting formation (e.g. `Formation.from_scenario(scenario)`);
      its `moves` (`None` or fixed) decide the kind of moves designed.
    - `scenario`: world, cameras, noise, strategy.
    - `key`: PRNG key for the draws and the random starts. Keyword only (as the rest).
    - `objective`: `"crlb"` ([`jaxloc.crlb_objective`][]) or `"mc"`
      ([`jaxloc.mc_objective`][]).
    - `criterion`: `"A"` (trace) or `"D"` (log-det), for `"crlb"`.
    - `free`: names of the free fields (others frozen), or `"all"`; see
      [`jaxloc.formation_filter`][].
    - `weights`: per-camera weights (C, C1, C2, C3).
    - `num_starts`, `num_draws`, `iterations`: sizes (static).
    - `limits`, `penalty_weight`, `feasibility_tol`: constraints (see [`jaxloc.Limits`][]).
    - `strict_steps`: apply the margins to every step of every drawn cycle, or only to the
      initial formation (later steps need only be in view); see [`jaxloc.design_penalty`][].
      Default (`None`): every step for fixed moves; the initial formation for random moves
      (the simulator's resampling accepts moves that end anywhere in view, so full margins
      on drawn moves over-constrain: measured, it shrank the moves to 0.3 m and doubled
      the Monte Carlo error of the overhead camera).
    - `rtol`, `atol`: BFGS tolerances (normalized units).
    - `runner`: where the starts run (a `jaxloc._design.search.StartRunner`). Default
      (`None`): all at once in this process, one `vmap`. On a Ray cluster:
      `jaxloc._design.cluster.ray_starts()` (connect first, e.g. with
      `jaxloc._study.cluster.connect(address)`) splits the starts into one group per
      cluster CPU, each group a Ray task running the same search on the same draws,
      retried if its worker is lost; the results are gathered in start order and the
      best start is chosen by the same rule. The result equals the local run's to
      round-off, not always bit for bit (a `vmap` over fewer starts is a different XLA
      program), so only starts tied to round-off could be chosen differently.

    **Returns:** a [`jaxloc.DesignResult`][].
    """
    if num_starts < 1 or num_draws < 1 or iterations < 1:
        raise ValueError(
            "`num_starts`, `num_draws` and `iterations` must be positive; got "
            f"{num_starts}, {num_draws}, {iterations}."
        )
    _objective_fn(objective, criterion, tuple(weights))  # validates
    spec = formation_filter(formation, free)
    if strict_steps is None:
        strict_steps = formation.fixed_moves
    k_draws, k_starts = jr.split(key)
    keys = jr.split(k_draws, num_draws)
    dtype = scenario.base.dtype
    formation = jax.tree.map(lambda x: jnp.asarray(x, dtype), formation)
    starts = random_starts(formation, spec, num_starts, key=k_starts)
    options = dict(
        objective=objective, criterion=criterion, weights=tuple(float(w) for w in weights),
        limits=limits, strict_steps=bool(strict_steps), penalty_weight=float(penalty_weight),
        iterations=int(iterations), rtol=rtol, atol=atol,
    )  # fmt: skip
    search = ft.partial(search_starts, formation, scenario, keys, spec, options)
    outs = (runner or local_starts)(search, starts)
    value0, (forms, total, value, pen, hist, n) = _gather(outs)
    ok = np.asarray(pen <= feasibility_tol) & np.isfinite(np.asarray(total))
    score_ = np.where(ok, np.asarray(value), np.inf)
    best = int(np.argmin(score_)) if ok.any() else int(np.argmin(np.asarray(pen)))
    pick = jax.tree.map(lambda x: x[best], forms)
    if "zoom" in (free if free != "all" else ("zoom",)):
        pick = eqx.tree_at(lambda f: f.zoom, pick, jnp.clip(pick.zoom, 0.0, 1.0))
    return DesignResult(
        formation=pick,
        initial=formation,
        objective=value[best],
        objective_initial=value0,
        penalty=pen[best],
        history=hist,
        final=total,
        penalties=pen,
        best=jnp.asarray(best),
        steps=n,
    )


# --------------------------------------------------------------------------------------
# Verification by fresh Monte Carlo.


def evaluate_formation(
    formation: Formation,
    scenario: Scenario,
    n_trials: int,
    *,
    seed: int,
    chunk_size: int = 2048,
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """Fresh Monte Carlo of the refined estimator on `formation` (DESIGN §9's check):
    [`jaxloc.run_study`][] of `formation.to_scenario(scenario)` (random or fixed moves)
    with `methods=("refined",)`, the study `jaxloc simulate --scenario FILE --seed SEED
    --methods refined` runs on the saved scenario.

    **Returns:** `{"status": (n, 1), "position": (n, 1, 4), "rotation": (n, 1, 4)}` as
    numpy arrays (cameras C, C1, C2, C3; metres, radians).
    """
    study = run_study(
        formation.to_scenario(scenario), n_trials, seed=seed, chunk_size=chunk_size,
        methods=("refined",), progress=progress,
    )
    return {k: study[k] for k in ("status", "position", "rotation")}


def rmse_ci(
    errors: np.ndarray, *, n_boot: int = 2000, level: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """RMSE of `errors` (1-D) with a percentile bootstrap confidence interval.

    **Returns:** `(rmse, low, high)`."""
    e2 = np.asarray(errors, np.float64) ** 2
    rng = np.random.default_rng(seed)
    n = e2.size
    means = np.empty(n_boot)
    for b in range(0, n_boot, 100):
        idx = rng.integers(0, n, size=(min(100, n_boot - b), n))
        means[b : b + idx.shape[0]] = e2[idx].mean(axis=1)
    a = (1.0 - level) / 2.0
    lo, hi = np.sqrt(np.quantile(means, [a, 1.0 - a]))
    return float(np.sqrt(e2.mean())), float(lo), float(hi)


def rmse_table(
    before: dict[str, np.ndarray], after: dict[str, np.ndarray], *, n_boot: int = 2000
) -> dict:
    """Per camera: RMSE of the final position before and after with 95% bootstrap CIs,
    and the ratio after/before with a paired bootstrap CI over the trials where both
    succeeded (same seed, so trial `i` shares its key in both studies).

    **Returns:** a JSON-ready dict `{camera: {"before": [rmse, lo, hi], "after": [...],
    "ratio": [r, lo, hi]}, "n_ok": [before, after], "failures": [before, after]}` (m)."""
    ok_b = before["status"][:, 0] == 0
    ok_a = after["status"][:, 0] == 0
    both = ok_b & ok_a
    rng = np.random.default_rng(1)
    out: dict = {
        "n_trials": int(ok_b.size),
        "n_ok": [int(ok_b.sum()), int(ok_a.sum())],
        "failures": [int((~ok_b).sum()), int((~ok_a).sum())],
    }
    for ci, cam in enumerate(CAMERAS):
        eb = before["position"][ok_b, 0, ci]
        ea = after["position"][ok_a, 0, ci]
        row = {
            "before": list(rmse_ci(eb, n_boot=n_boot)),
            "after": list(rmse_ci(ea, n_boot=n_boot)),
        }
        pb = before["position"][both, 0, ci] ** 2
        pa = after["position"][both, 0, ci] ** 2
        if pb.size and pb.mean() > 0:
            ratios = []
            for _ in range(n_boot // 100):
                idx = rng.integers(0, pb.size, size=(100, pb.size))
                ratios.append(np.sqrt(pa[idx].mean(1) / pb[idx].mean(1)))
            ratios = np.concatenate(ratios)
            r = math.sqrt(pa.mean() / pb.mean())
            row["ratio"] = [r, float(np.quantile(ratios, 0.025)), float(np.quantile(ratios, 0.975))]
        else:
            row["ratio"] = [float("nan")] * 3
        out[cam] = row
    return out


def objective_value(
    formation: Formation,
    scenario: Scenario,
    *,
    key: PRNGKeyArray,
    objective: str = "crlb",
    criterion: str = "A",
    weights=(1.0, 0.0, 0.0, 0.0),
    num_draws: int = 32,
) -> Float[Array, ""]:
    """The unpenalized objective of [`jaxloc.design_formation`][] at `formation` with the draws
    it would use for `key` (same split), e.g. to compare formations on common draws."""
    k_draws, _ = jr.split(key)
    weights = tuple(float(w) for w in weights)
    value, _ = _objective(
        formation, scenario, jr.split(k_draws, num_draws), objective=objective,
        criterion=criterion, weights=weights,
    )  # fmt: skip
    return value


@eqx.filter_jit
def _objective(formation, scenario, keys, *, objective: str, criterion: str, weights: tuple):
    # Compiled once per configuration (the keyword arguments are static) and formation
    # structure, shared by every call.
    return _objective_fn(objective, criterion, weights)(formation, scenario, keys)
