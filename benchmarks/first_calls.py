"""What a user waits for: the first and later calls of jaxloc's entry points (issue 19).

    python benchmarks/first_calls.py [--only NAME,...] [--calls 20] [--out FILE]

Each case runs in a fresh Python process without a persistent compilation cache (so the
first call traces and compiles, as on a fresh machine), on one simulated cycle of the
paper's sequential scenario (`key(0)`; its simulation, and the estimate or the 2-cycle
track a case needs, are computed before the clock starts, except for the
`simulate_cycle` case). Prints, per case, the first call's seconds and the median of
`--calls` later calls (each `block_until_ready`). Cases: the eager entry points as a
user calls them (jaxloc compiles them with `jaxloc.compiler_options()`), and
`localize_cycle` inside the user's own `jax.jit`, without and with those options;
`localize_cycle` then `refine_cycle` on its estimate, called plainly and with both
programs compiled side by side first (`jaxloc.compiled_ahead`).
"""

import argparse
import json
import os
import subprocess
import sys
import textwrap


CASES = {
    "simulate_cycle": "lambda: jaxloc.simulate_cycle(sc, jr.key(1))",
    "localize_cycle": "lambda: jaxloc.localize_cycle(obs, sc.rig, throw=False)",
    "refine_cycle": "lambda: jaxloc.refine_cycle(obs, sc.rig, est, throw=False)",
    "cycle_crlb": "lambda: jaxloc.cycle_crlb(sc.rig, truth.poses, odometry_sigma_rel=0.01)",
    "cycle_covariance": "lambda: jaxloc.cycle_covariance(obs, sc.rig, est)",
    "run_trial": "lambda: jaxloc.run_trial(sc, jr.key(1))",
    "track_cycles (2 cycles)": "lambda: jaxloc.track_cycles(track_obs, sc.rig)",
    "run_track_trial (2 cycles)": "lambda: jaxloc.run_track_trial(track, jr.key(1), 2)",
    "p3p": "lambda: jaxloc.p3p(X[:3], b[:3])",
    "mutual_localization": "lambda: jaxloc.mutual_localization(obs.mutual[0], throw=False)",
    # A height prior of 3 +- 0.3 m, not the scene's: the update runs its whole path (P3P,
    # 7 LM steps, the gates, `inconsistent_fit`); only the time is measured here.
    "localize_one_step": (
        "(lambda s, p: lambda: jaxloc.localize_one_step(s, sc.rig, p, throw=False))("
        "jaxloc.Snapshot.of(obs, 0), jaxloc.OneStepPrior.height_prior(3.0, 0.3, 0.1))"
    ),
    "solve_overhead_pose": "lambda: jaxloc.solve_overhead_pose(X, b, throw=False)",
    "localize_cycle then refine_cycle": (
        "lambda: jaxloc.refine_cycle(obs, sc.rig, jaxloc.localize_cycle(obs, sc.rig, "
        "throw=False), throw=False)"
    ),
    "the same in compiled_ahead": (
        "compiled_ahead_once(lambda: jaxloc.refine_cycle(obs, sc.rig, "
        "jaxloc.localize_cycle(obs, sc.rig, throw=False), throw=False))"
    ),
    "jit(localize_cycle)": (
        "(lambda f: lambda: f(obs))(jax.jit(lambda o: jaxloc.localize_cycle(o, sc.rig, "
        "throw=False)))"
    ),
    "jit(localize_cycle) with options": (
        "(lambda f: lambda: f(obs))(jax.jit(lambda o: jaxloc.localize_cycle(o, sc.rig, "
        "throw=False), compiler_options=jaxloc.compiler_options()))"
    ),
}

#: The subprocesses run here, where no `jaxloc` folder shadows the one `PYTHONPATH` names.
HERE = os.path.dirname(os.path.abspath(__file__))
#: Settings that would let a case reuse another run's compilation.
NO_CACHE = ("JAX_COMPILATION_CACHE_DIR", "JAXLOC_COMPILE_CACHE")

SCRIPT = textwrap.dedent(
    """
    import json, sys, time
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, jax.random as jr, jaxloc, numpy as np
    sc = jaxloc.Scenario.paper("sequential")
    case, calls = sys.argv[1], int(sys.argv[2])
    if case != "simulate_cycle":
        truth, obs, _ = jaxloc.simulate_cycle(sc, jr.key(0))
        X = truth.poses.T_world_body.wxyz_xyz[:, :, 4:].reshape(-1, 3)  # every step's
        b = obs.overhead.reshape(-1, 3)  # robots, and the overhead camera's bearings
        if case in ("refine_cycle", "cycle_covariance"):
            est = jaxloc.localize_cycle(obs, sc.rig, throw=False)
        track = jaxloc.TrackScenario(sc)
        if case.startswith("track_cycles"):
            track_obs = jaxloc.simulate_track(track, jr.key(0), 2)[1]

    def compiled_ahead_once(f):
        # The first call compiles f's programs side by side (placeholders), then runs f.
        done = []
        def call():
            if not done:
                with jaxloc.compiled_ahead():
                    f()
                done.append(True)
            return f()
        return call

    f = eval(sys.argv[3])
    t = time.perf_counter()
    jax.block_until_ready(f())
    first = time.perf_counter() - t
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - t)
    print(json.dumps({"first_s": first, "later_median_ms": 1e3 * float(np.median(times))}))
    """
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(CASES))
    parser.add_argument("--calls", type=int, default=20)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    results = {}
    for name in args.only.split(","):
        env = {k: v for k, v in os.environ.items() if k not in NO_CACHE}
        run = subprocess.run(
            [sys.executable, "-c", SCRIPT, name, str(args.calls), CASES[name]],
            env=env, capture_output=True, text=True, check=True, cwd=HERE,
        )  # fmt: skip
        results[name] = json.loads(run.stdout.strip().splitlines()[-1])
        r = results[name]
        print(f"{name:32s} first call {r['first_s']:6.2f} s, later calls "
              f"{r['later_median_ms']:8.2f} ms (median)", flush=True)  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"load_average": os.getloadavg(), "cases": results}, f, indent=1)


if __name__ == "__main__":
    main()
