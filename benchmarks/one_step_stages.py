"""Where a single one-step update's latency goes (issue 21's <= 100 us target).

    python benchmarks/one_step_stages.py [--calls 1000] [--rounds 3]

One snapshot of the paper's scenario with a 20 cm / 5 deg pose prior and the perimeter
(as `benchmarks/track_targets.py --only one_step` draws them, seed 1). Each stage of
`jaxloc._track.one_step` is compiled ahead of time as its own program, cumulatively
(formation; + P3P roots and their prior misfits; + the MAP refinement), beside the whole
update, `mutual_localization` and `p3p` alone and an empty program (the floor of one
call), all with `jaxloc.compiler_options()` (the options of jaxloc's own entry points),
the team's `Rig` a constant of the program; then the whole update with the `Rig` as an
argument, and the public `localize_one_step` called eagerly (its jit's dispatch
included). Prints the best of `--rounds` medians of `--calls` calls of each, and the
fused kernels and while loops of the whole update's compiled program.
"""

import argparse
import math
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import jaxlie  # noqa: E402
import numpy as np  # noqa: E402
from jaxloc._core.compiler import compiler_options  # noqa: E402
from jaxloc._core.poses import rplus  # noqa: E402
from jaxloc._sim.scenario import Scenario  # noqa: E402
from jaxloc._sim.simulate import simulate_cycle  # noqa: E402
from jaxloc._solvers.mutual import mutual_localization  # noqa: E402
from jaxloc._solvers.p3p import p3p  # noqa: E402
from jaxloc._track import one_step  # noqa: E402
from jaxloc._track.frames import body_of_overhead  # noqa: E402


def snapshot_and_prior(scenario: Scenario, key):
    """A snapshot (the cycle's first step) and a pose prior 20 cm / 5 deg off, with the
    perimeter to 2 cm."""
    sigma = jnp.array([0.2] * 3 + [math.radians(5.0)] * 3)
    k_sim, k_pose, k_scale = jr.split(key, 3)
    truth, obs, _ = simulate_cycle(scenario, k_sim)
    T_body = body_of_overhead(truth.poses.T_world_overhead.wxyz_xyz, scenario.rig.mounts[0])
    mean = rplus(jaxlie.SE3(T_body), sigma * jr.normal(k_pose, (6,))).wxyz_xyz
    true_perimeter = one_step.perimeter(truth.poses.T_world_body.wxyz_xyz[0, :, 4:])
    prior = one_step.OneStepPrior.pose_prior(mean, jnp.diag(sigma**2)).with_scale(
        true_perimeter + 0.02 * jr.normal(k_scale, ()), 0.02
    )
    return one_step.Snapshot.of(obs, 0), prior


def median_latency_us(f, args, calls: int, rounds: int, compiled: bool = True) -> float:
    """The best of `rounds` medians of `calls` calls of `f` (compiled ahead of time with
    jaxloc's options when `compiled`, else called as it is)."""
    if compiled:
        f = jax.jit(f, compiler_options=compiler_options()).lower(*args).compile()
    jax.block_until_ready(f(*args))
    medians = []
    for _ in range(rounds):
        times = []
        for _ in range(calls):
            t = time.perf_counter()
            jax.block_until_ready(f(*args))
            times.append(time.perf_counter() - t)
        medians.append(float(np.median(times)))
    return 1e6 * min(medians)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    scenario = Scenario.paper()
    rig = scenario.rig
    mount = rig.mounts[0]
    snap, prior = jax.jit(lambda key: snapshot_and_prior(scenario, key))(jr.key(1))

    def whole(s, p):
        return one_step.localize_one_step(s, rig, p, throw=False)

    def formation(s, p):
        return one_step._formation(s)

    def roots(s, p):
        _, _, u, _, up = one_step._formation(s)
        return one_step._choose_root(s, u, up, mount, p)

    def refined(s, p):
        _, _, u, R_robots, up = one_step._formation(s)
        r = one_step._choose_root(s, u, up, mount, p)
        return one_step._refine_root(s, rig, p, r, u, R_robots, up, mount)

    stages = {
        "whole update": (whole, (snap, prior)),
        "formation (mutual localization)": (formation, (snap, prior)),
        "+ P3P roots, prior misfits": (roots, (snap, prior)),
        "+ MAP refinement (LM)": (refined, (snap, prior)),
        "mutual_localization alone": (lambda s: mutual_localization(s.mutual, 0, throw=False),
                                      (snap,)),  # fmt: skip
        "p3p alone": (p3p, (jnp.eye(3), jnp.eye(3))),
        "empty program (x + 1)": (lambda x: x + 1, (jnp.ones(3),)),
        "whole update, Rig an argument": (
            lambda s, r, p: one_step.localize_one_step(s, r, p, throw=False), (snap, rig, prior)),
    }
    for name, (f, f_args) in stages.items():
        print(f"{name:<34}{median_latency_us(f, f_args, args.calls, args.rounds):8.0f} us")
    eager = median_latency_us(stages["whole update, Rig an argument"][0], (snap, rig, prior),
                              args.calls, args.rounds, compiled=False)  # fmt: skip
    print(f"{'localize_one_step called eagerly':<34}{eager:8.0f} us")
    options = compiler_options()
    text = jax.jit(whole, compiler_options=options).lower(snap, prior).compile().as_text()
    print(f"whole update: {text.count('fusion(')} fused kernels, "
          f"{text.count(' while(')} while loops")  # fmt: skip


if __name__ == "__main__":
    main()
