"""Where `localize_cycle`'s batch time goes: the closed forms against the gates, and the
gates' pieces (issue 19).

    python benchmarks/gate_stages.py [--strategy sequential] [--batch 1024] [--out FILE]

On `--batch` simulated cycles of the paper's scenario (seed 1), each stage is compiled as
its own `jit(vmap(...))` program on the previous stage's outputs: the robust closed form,
the whole gating of it (`gate_all` with its rivals, as `localize_cycle` calls it), and
the pieces one Gauss--Newton iteration of the gates is made of (whitened residuals and
their blocks, the normal equations from the blocks, the `fori_loop` Cholesky and the
solve, the Jacobi-scaled inverse, the row-equilibrated Gram matrix), then the gates' two
loops alone: polish and evaluation, and the second minima (which take no step in a batch
where no estimate lacks a sighting). Prints, per stage, the fused
kernels of its compiled program and the run time per problem (best of 3 calls); writes
JSON with `--out`.
"""

import argparse
import os
import sys

import jax


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", None)

import jax.random as jr  # noqa: E402
import jaxloc  # noqa: E402
from jaxloc._core.least_squares import solve_spd  # noqa: E402
from jaxloc._core.linalg import cholesky, row_equilibrated_gram, spd_inverse  # noqa: E402
from jaxloc._model.gates import (  # noqa: E402
    _polished,
    _second_minimum,
    gate_all,
    gate_point,
    gate_rivals,
    POLISH_STEPS,
)
from jaxloc._model.measurements import (  # noqa: E402
    cycle_data,
    normal_equations_of_blocks,
    unknowns_jacobian,
    whitened_blocks,
)
from jaxloc._solvers.localize import closed_forms  # noqa: E402


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from programs import _fusions, _timed  # noqa: E402
from run import machine_info  # noqa: E402


def timed_stage(name, f, args, batch, rows):
    """Compile `jit(vmap(f))`, run it on `args` (batched) and record one row."""
    program = jax.jit(jax.vmap(f)).lower(*args).compile()
    out = jax.block_until_ready(program(*args))
    best = min(_timed(program, args) for _ in range(3))
    row = {"stage": name, "fusions": _fusions(program), "per_problem_us": 1e6 * best / batch}
    print(f"{name:34s} {row['fusions']:5d} fusions  {row['per_problem_us']:9.1f} us/problem")
    rows.append(row)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--strategy", default="sequential")
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--out")
    args = parser.parse_args(argv)
    strategy, batch = args.strategy, args.batch
    scenario = jaxloc.Scenario.paper(strategy)
    rig = scenario.rig
    keys = jr.split(jr.key(1), batch)
    obs = jax.jit(jax.vmap(lambda k: jaxloc.simulate_cycle(scenario, k)))(keys)[1]
    rows: list[dict] = []

    (estimate,) = timed_stage("closed form (robust)", lambda o: closed_forms(o, ("robust",)),
                              (obs,), batch, rows)  # fmt: skip

    def gates(o, e):
        point = gate_point(e, cycle_data(o, rig), strategy)
        rivals = gate_rivals(e, point, strategy)
        return gate_all([point], rig, strategy, polish=True, rivals=[rivals])

    timed_stage("gates (gate_all, with rivals)", gates, (obs, estimate), batch, rows)
    points = jax.jit(jax.vmap(lambda o, e: gate_point(e, cycle_data(o, rig), strategy)))(
        obs, estimate
    )
    r, B = timed_stage(
        "whitened_blocks",
        lambda p: whitened_blocks(p.T_place, p.T_over, p.data, rig, strategy),
        (points,), batch, rows,
    )  # fmt: skip
    _, H, g = timed_stage(
        "normal_equations_of_blocks",
        lambda r, B: normal_equations_of_blocks(r, B, strategy),
        (r, B), batch, rows,
    )  # fmt: skip
    timed_stage("solve_spd (Cholesky + solves)", solve_spd, (H, -g), batch, rows)
    timed_stage("cholesky (fori_loop)", cholesky, (H,), batch, rows)
    timed_stage("spd_inverse", spd_inverse, (H,), batch, rows)
    J = timed_stage("unknowns_jacobian", lambda B: unknowns_jacobian(B, strategy), (B,), batch,
                    rows)  # fmt: skip
    timed_stage("row_equilibrated_gram", row_equilibrated_gram, (J,), batch, rows)
    P, O, _, _ = timed_stage(
        "polish and evaluation loop",
        lambda p: _polished(p.T_place, p.T_over, p.data, rig, strategy, True, POLISH_STEPS),
        (points,), batch, rows,
    )  # fmt: skip
    timed_stage(
        "second-minimum loop",
        lambda P, O, p: _second_minimum(P, O, p.data, rig, strategy),
        (P, O, points), batch, rows,
    )  # fmt: skip
    print(f"unknowns {H.shape[-1]}, whitened rows {r.shape[-1]}")
    if args.out:
        from jaxloc._core.files import atomic_write_json

        report = {"command": " ".join(["python", "benchmarks/gate_stages.py", *sys.argv[1:]]),
                  "machine": machine_info(), "strategy": strategy, "batch": batch,
                  "unknowns": int(H.shape[-1]), "rows": rows}  # fmt: skip
        atomic_write_json(args.out, report)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
