"""Issue 21's targets, measured (tracking over many cycles, one-step localization).

    python benchmarks/track_targets.py [--only study,one_step,scaling] [--runs N]
        [--cycles K] [--one-step-trials N] [--scaling-runs N] [--seed S] [--chunks DIR]
        [--out benchmarks/results/track_targets.json]

Sections (paper scenario, sequential, 2 px paper noise, 1 % odometry; the tracking
section's defaults: climbing robot's odometry 1 % of its step and 0.01 rad per axis):

- `study`: `jaxloc.run_track_study` of `--runs` runs of `--cycles` cycles (default 20);
  per cycle and robot, RMSE / bound for chaining (chained bound) and the smoother (its
  window bound), the worst ratio over every cycle and robot, and how far the smoother's
  RMSE of C at the last cycle is below chaining's (`jaxloc._cli.track.targets`).
- `one_step`: `jaxloc.localize_one_step` on the first formation of independent simulated
  cycles, with a pose prior of sigma 20 cm / 5 deg per axis (its mean drawn from that
  Gaussian about the true pose, so the Bayesian bound applies) and the formation's
  perimeter from "the last full cycle" (its mean drawn with sigma `--scale-sigma`, default
  2 cm). Correct-root rate (the P3P root nearest the truth is the one refined), the
  efficiency of C's position (bound RMSE / RMSE over the successful estimates, bound:
  `jaxloc.one_step_bound` at the truth with the same prior), and the latency of one jitted
  update (`localize_one_step(..., throw=False)` on one snapshot, median of 2000 calls after
  warm-up; the same with the rig closed over and compiled ahead of time, as a robot's code
  would call it; and per update under `jit(vmap)` at batch 1024).
- `scaling`: seconds per cycle of `jit(vmap(jaxloc.track_cycles))` (chaining, one-step,
  smoother, the cycle's refinement) on `--scaling-runs` runs that stay feasible for 100
  cycles (drawn from 4 times as many) at K = 10 and K = 100 cycles
  (the same simulated observations, the first 10 cycles for K = 10), best of 3 interleaved
  timings each, compilation excluded.

The machine is shared (2 cores): the load average is recorded at start and end.
"""

import argparse
import json
import math
import os
import sys
import time


def _setup():
    os.environ.setdefault(
        "XLA_FLAGS", f"--xla_force_host_platform_device_count={os.cpu_count() or 1}"
    )
    import jax

    jax.config.update("jax_enable_x64", True)
    cache = os.environ.get("JAXLOC_COMPILE_CACHE", os.path.expanduser("~/.cache/jaxloc/xla"))
    if cache != "off":
        jax.config.update("jax_compilation_cache_dir", cache)


def study_section(args) -> dict:
    import numpy as np
    from jaxloc._cli.track import targets
    from jaxloc._cycle.layout import CAMERAS
    from jaxloc._track.scenario import TrackScenario
    from jaxloc._track.study import run_track_study, summarize_track

    track = TrackScenario()
    t0 = time.perf_counter()
    study = run_track_study(track, args.runs, args.cycles, seed=args.seed,
                            chunk_size=min(args.runs, 256), out_dir=args.chunks,
                            progress=False)  # fmt: skip
    seconds = time.perf_counter() - t0
    summary = summarize_track(study)
    measured = targets(summary)
    ratios = {
        m: [{cam: summary["methods"][m][k]["robots"][cam]["ratio"] for cam in CAMERAS}
            for k in range(args.cycles)]
        for m in ("chain", "smoother")
    }  # fmt: skip
    rmse_c = {m: [summary["methods"][m][k]["robots"]["C"]["position_m"]["rmse"]
                  for k in range(args.cycles)] for m in ("chain", "smoother")}  # fmt: skip
    n_ok = {m: [summary["methods"][m][k]["n_ok"] for k in range(args.cycles)]
            for m in summary["methods"]}  # fmt: skip
    print(f"study: {args.runs} runs x {args.cycles} cycles in {seconds:.0f} s")
    for m in ("chain", "smoother"):
        worst = [max((r for r in ratios[m][k].values() if np.isfinite(r)), default=float("nan"))
                 for k in range(args.cycles)]  # fmt: skip
        print(f"  {m:9s} worst RMSE/bound per cycle: " + " ".join(f"{w:.2f}" for w in worst))
        print(f"  {m:9s} runs successful per cycle: " + " ".join(map(str, n_ok[m])))
    print(f"  RMSE of C at cycle {args.cycles}: chain {100 * rmse_c['chain'][-1]:.2f} cm, "
          f"smoother {100 * rmse_c['smoother'][-1]:.2f} cm "
          f"({100 * measured['smoother_vs_chain_C_last']:.0f}% below)")  # fmt: skip
    print(f"  targets: {measured}")
    return {"runs": args.runs, "cycles": args.cycles, "seconds": seconds, "targets": measured,
            "ratios": ratios, "rmse_C": rmse_c, "n_ok": n_ok,
            "one_step_in_study": summary["one_step"]}  # fmt: skip


def one_step_section(args) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import jax.random as jr
    import jaxlie
    import numpy as np
    from jaxloc._core.poses import rplus
    from jaxloc._core.results import RESULTS
    from jaxloc._model.covariance import crlb_inputs
    from jaxloc._sim.scenario import Scenario
    from jaxloc._sim.simulate import simulate_cycle
    from jaxloc._track.frames import body_of_overhead, position_covariance
    from jaxloc._track.one_step import (
        localize_one_step,
        one_step_bound,
        OneStepPrior,
        perimeter,
        Snapshot,
    )

    scenario = Scenario.paper()
    rig, strategy = scenario.rig, scenario.strategy
    sigma_p, sigma_r = 0.2, math.radians(5.0)
    cov = jnp.diag(jnp.array([sigma_p] * 3 + [sigma_r] * 3) ** 2)

    def problem(key):
        k_sim, k_pose, k_scale = jr.split(key, 3)
        truth, obs, feasible = simulate_cycle(scenario, k_sim)
        mount = rig.mounts[0]
        T_body = body_of_overhead(truth.poses.T_world_overhead.wxyz_xyz, mount)
        noise = jnp.array([sigma_p] * 3 + [sigma_r] * 3) * jr.normal(k_pose, (6,))
        mean = rplus(jaxlie.SE3(T_body), noise).wxyz_xyz
        true_perimeter = perimeter(truth.poses.T_world_body.wxyz_xyz[0, :, 4:])
        measured = true_perimeter + args.scale_sigma * jr.normal(k_scale, ())
        prior = OneStepPrior.pose_prior(mean, cov).with_scale(measured, args.scale_sigma)
        return truth, obs, feasible, T_body, prior

    @jax.jit
    def batch(keys):
        def one(key):
            truth, obs, feasible, T_body, prior = problem(key)
            est = localize_one_step(Snapshot.of(obs, 0), rig, prior, throw=False)
            T_place, T_over, data = crlb_inputs(rig, truth.poses, scenario.odometry_sigma_rel,
                                                strategy)  # fmt: skip
            bound = one_step_bound(T_place, T_over, data, rig, strategy, prior)
            bound_pos = jnp.trace(position_covariance(T_body, bound[12:, 12:]))
            err = est.T_world_climber[4:] - T_body[4:]
            near = jnp.argmin(jnp.where(
                est.roots_ok, jnp.sum((est.roots[:, 4:] - T_body[4:]) ** 2, -1), jnp.inf
            ))  # fmt: skip
            return dict(
                feasible=feasible, ok=est.result == RESULTS.successful,
                ambiguous=est.result == RESULTS.ambiguous, has_root=jnp.any(est.roots_ok),
                correct=near == est.chosen, err2=jnp.sum(err * err), bound2=bound_pos,
                nees=err @ jnp.linalg.solve(est.position_covariance, err),
            )  # fmt: skip

        return jax.lax.map(one, keys, batch_size=256)

    n = args.one_step_trials
    keys = jr.split(jr.key(args.seed + 1), n)
    t0 = time.perf_counter()
    out = {k: np.asarray(v) for k, v in batch(keys).items()}
    seconds = time.perf_counter() - t0
    use = out["feasible"] & out["has_root"]
    ok = use & out["ok"]
    rmse = math.sqrt(out["err2"][ok].mean())
    bound = math.sqrt(out["bound2"][ok].mean())
    rmse_all = math.sqrt(out["err2"][use & np.isfinite(out["err2"])].mean())
    bound_all = math.sqrt(out["bound2"][use].mean())
    res = {
        "trials": n, "feasible": int(out["feasible"].sum()), "prior_sigma_m": sigma_p,
        "prior_sigma_deg": 5.0, "scale_sigma_m": args.scale_sigma,
        "correct_root_rate": float(out["correct"][use].mean()),
        "successful_rate": float(out["ok"][use].mean()),
        "ambiguous_rate": float(out["ambiguous"][use].mean()),
        "wrong_root_successful": int((ok & ~out["correct"]).sum()),
        "rmse_C_m": rmse, "bound_C_m": bound, "efficiency": bound / rmse,
        "rmse_C_all_m": rmse_all, "bound_C_all_m": bound_all,
        "efficiency_all": bound_all / rmse_all,
        "nees_mean": float(np.mean(out["nees"][ok])), "seconds_incl_compile": seconds,
    }  # fmt: skip
    # Latency: one snapshot, one jitted update.
    truth, obs, _, _, prior = jax.jit(problem)(keys[0])
    snap = Snapshot.of(obs, 0)
    jax.block_until_ready(localize_one_step(snap, rig, prior, throw=False))
    times = []
    for _ in range(2000):
        t = time.perf_counter()
        jax.block_until_ready(localize_one_step(snap, rig, prior, throw=False))
        times.append(time.perf_counter() - t)
    res["latency_median_us"] = 1e6 * float(np.median(times))
    res["latency_p90_us"] = 1e6 * float(np.percentile(times, 90))
    # The same update as a robot's code would call it: the rig closed over (constants),
    # compiled ahead of time, so a call flattens only the snapshot and the prior.
    compiled = jax.jit(lambda s, p: localize_one_step(s, rig, p, throw=False)).lower(
        snap, prior).compile()  # fmt: skip
    jax.block_until_ready(compiled(snap, prior))
    times = []
    for _ in range(2000):
        t = time.perf_counter()
        jax.block_until_ready(compiled(snap, prior))
        times.append(time.perf_counter() - t)
    res["latency_aot_median_us"] = 1e6 * float(np.median(times))
    res["latency_aot_p90_us"] = 1e6 * float(np.percentile(times, 90))
    # The same update under jit(vmap), per update.
    snaps, priors = jax.jit(jax.vmap(lambda k: (lambda p: (Snapshot.of(p[1], 0), p[4]))(
        problem(k))))(keys[:1024])  # fmt: skip
    vm = eqx.filter_jit(jax.vmap(lambda s, p: localize_one_step(s, rig, p, throw=False)))
    jax.block_until_ready(vm(snaps, priors))
    best = min(_timed(lambda: jax.block_until_ready(vm(snaps, priors))) for _ in range(5))
    res["batched_us_per_update"] = 1e6 * best / 1024
    print(f"one-step: {json.dumps(res, indent=1)}")
    return res


def _timed(f) -> float:
    t = time.perf_counter()
    f()
    return time.perf_counter() - t


def scaling_section(args) -> dict:
    import jax
    import jax.random as jr
    import numpy as np
    from jaxloc._track.scenario import TrackScenario
    from jaxloc._track.simulate import simulate_track
    from jaxloc._track.tracker import track_cycles

    track = TrackScenario()
    rig = track.rig
    K_long, K_short = 100, 10
    # Runs that keep every required sighting for all K_long cycles (a run that loses the
    # team keeps being tracked on missing data, its solvers at their iteration caps, and
    # under `vmap` the batch waits for its slowest run): the same runs for both K.
    keys = jr.split(jr.key(args.seed + 2), 4 * args.scaling_runs)
    _, obs, feasible = jax.jit(jax.vmap(lambda k: simulate_track(track, k, K_long)))(keys)
    order = np.argsort(~np.asarray(feasible[:, -1]), kind="stable")[: args.scaling_runs]
    obs = jax.tree.map(lambda a: a[order] if a.ndim >= 1 else a, obs)
    feasible = feasible[order]
    obs_short = jax.tree.map(
        lambda a: a[:, :K_short] if a.ndim >= 2 and a.shape[1] == K_long else a, obs
    )
    run = jax.jit(jax.vmap(lambda o: track_cycles(o, rig)))
    for o in (obs_short, obs):
        t = time.perf_counter()
        jax.block_until_ready(run(o))
        print(f"scaling: compiled and ran K={o.climber_odometry.shape[1]} in "
              f"{time.perf_counter() - t:.0f} s")  # fmt: skip
    best = {K_short: math.inf, K_long: math.inf}
    for _ in range(3):
        for K, o in ((K_short, obs_short), (K_long, obs)):
            best[K] = min(best[K], _timed(lambda: jax.block_until_ready(run(o))))
    per = {K: best[K] / K for K in best}
    res = {
        "runs": args.scaling_runs, "seconds_K10": best[K_short], "seconds_K100": best[K_long],
        "per_cycle_K10_s": per[K_short], "per_cycle_K100_s": per[K_long],
        "ratio_K100_over_K10": per[K_long] / per[K_short],
        "feasible_runs_at_K100": int(feasible[:, -1].sum()),
    }  # fmt: skip
    print(f"scaling: {json.dumps(res, indent=1)}")
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", default="study,one_step,scaling")
    p.add_argument("--runs", type=int, default=1024)
    p.add_argument("--cycles", type=int, default=20)
    p.add_argument("--one-step-trials", type=int, default=10000)
    p.add_argument("--scale-sigma", type=float, default=0.02)
    p.add_argument("--scaling-runs", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunks", default=None, metavar="DIR",
                   help="stream the study's chunks to DIR (resumable: run again to go on)")
    p.add_argument("--out", default="benchmarks/results/track_targets.json")
    args = p.parse_args(argv)
    _setup()
    import jax

    sections = {"study": study_section, "one_step": one_step_section,
                "scaling": scaling_section}  # fmt: skip
    report = {"command": " ".join(sys.argv), "load_start": os.getloadavg(),
              "devices": jax.device_count(), "jax": jax.__version__}  # fmt: skip
    for name in args.only.split(","):
        report[name] = sections[name](args)
    report["load_end"] = os.getloadavg()
    from jaxloc._core.files import atomic_write_json

    atomic_write_json(args.out, report)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
