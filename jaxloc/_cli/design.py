"""`jaxloc design`: gradient-based formation design from the command line (DESIGN §9).

Wire with `register(sub)` on the `jaxloc` sub-parsers.
"""

import argparse
import json
import time

import numpy as np


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `design` subcommand to `jaxloc`'s sub-parsers."""
    p = sub.add_parser(
        "design",
        help="search for a formation that minimizes the expected localization error",
        description=(
            "Optimize the formation (triangle, headings, overhead camera placement, PTZ "
            "setting, moves) with BFGS from the scenario's formation and random starts, "
            "write the best feasible one as a scenario file, and optionally check it by "
            "fresh Monte Carlo against the starting formation."
        ),
    )
    p.add_argument("--scenario", metavar="FILE",
                   help="starting scenario (YAML/JSON); default: the paper's simulation")
    p.add_argument("--strategy", choices=("sequential", "concurrent"),
                   help="override the scenario's strategy (default sequential for the paper)")
    p.add_argument("--objective", choices=("crlb", "mc"), default="crlb",
                   help="crlb: Cramér–Rao bound (fast, smooth); mc: refined Monte Carlo MSE")
    p.add_argument("--criterion", choices=("A", "D"), default="A",
                   help="A: trace (expected squared error); D: log-det (crlb only)")
    p.add_argument("--free", default="all", metavar="LIST",
                   help="comma-separated free parameters (base, side, initial_xy, headings, "
                        "overhead_xy, overhead_heading, pan, tilt, zoom, move_mean, moves) or "
                        "'all'")
    p.add_argument("--triangle", choices=("isosceles", "general"),
                   help="isosceles: design `base` and `side`; general: the three initial "
                        "positions (`initial_xy`). Default: general if the scenario has "
                        "`initial_xy`, else isosceles")
    p.add_argument("--moves", choices=("random", "fixed"), default="random",
                   help="random: the scenario's random moves, N(move_mean, move_std); fixed: "
                        "design each move's length and direction (written as the scenario's "
                        "`moves`; starts from the scenario's fixed moves if it has them, else "
                        "0.8 m straight ahead)")
    p.add_argument("--weights", default="1,0,0,0", metavar="C,C1,C2,C3",
                   help="per-camera weights of the position error (default: overhead camera)")
    p.add_argument("--starts", type=int, default=8, help="parallel starts (first = scenario's)")
    p.add_argument("--draws", type=int, default=32,
                   help="common random draws (moves and, for mc, noise) per evaluation")
    p.add_argument("--iterations", type=int, default=80, help="BFGS iterations per start")
    p.add_argument("--seed", type=int, default=0, help="seed of the draws and random starts")
    p.add_argument("--image-margin", type=float, default=10.0, metavar="PX",
                   help="required margin of every sighting inside a perspective image")
    p.add_argument("--strict-moves", action="store_true",
                   help="random moves: require the margins after every drawn move too, not "
                        "only in the initial formation (fixed moves: always)")
    p.add_argument("--out", metavar="FILE", help="write the optimized scenario (YAML/JSON)")
    p.add_argument("--formation-json", metavar="FILE",
                   help="write the initial and optimized formation parameters as JSON")
    p.add_argument("--plot", metavar="FILE", help="3D plot of the formation before and after")
    p.add_argument("--verify-trials", type=int, default=0, metavar="N",
                   help="fresh Monte Carlo check with N trials each (0: skip; e.g. 10000)")
    p.add_argument("--verify-seed", type=int, default=12345,
                   help="seed of the fresh Monte Carlo check (differs from --seed)")
    p.add_argument("--json", metavar="FILE", help="write every number as JSON")
    p.set_defaults(func=_cmd_design)


def _parse_free(text: str):
    from .._design.formation import FORMATION_FIELDS

    if text.strip() == "all":
        return "all"
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in FORMATION_FIELDS]
    if bad or not names:
        raise ValueError(
            f"--free must be 'all' or a comma-separated subset of {FORMATION_FIELDS}; "
            f"got {text!r}."
        )
    return names


def _parse_weights(text: str):
    try:
        w = tuple(float(x) for x in text.split(","))
    except ValueError:
        w = ()
    if len(w) != 4 or any(x < 0 for x in w) or not any(x > 0 for x in w):
        raise ValueError(f"--weights must be 4 nonnegative numbers, not all 0; got {text!r}.")
    return w


def formation_to_dict(formation) -> dict:
    """JSON-ready dict of a [`jaxloc.Formation`][] (metres, radians)."""
    from .._design.formation import FORMATION_FIELDS

    out = {}
    for n in FORMATION_FIELDS:
        v = getattr(formation, n)
        out[n] = None if v is None else np.asarray(v, np.float64).tolist()
    return out


def _cmd_design(args) -> int:
    import equinox as eqx
    import jax.random as jr

    from .._design.formation import Formation, Limits, paper_fixed_moves
    from .._design.search import design_formation, evaluate_formation, objective_value, rmse_table
    from .._sim.scenario import Scenario
    from .._sim.scenario_file import load_scenario, save_scenario

    for name in ("starts", "draws", "iterations"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name} must be positive; got {getattr(args, name)}.")
    if args.verify_trials < 0:
        raise ValueError(f"--verify-trials must be >= 0; got {args.verify_trials}.")
    if args.image_margin < 0:
        raise ValueError(f"--image-margin must be >= 0; got {args.image_margin}.")
    if args.objective == "mc" and args.criterion != "A":
        raise ValueError("--criterion D applies to --objective crlb only.")
    free = _parse_free(args.free)
    weights = _parse_weights(args.weights)
    fixed = args.moves == "fixed"
    if args.scenario:
        scenario = load_scenario(args.scenario)
        if args.strategy and args.strategy != scenario.strategy:
            from .._sim.scenario_file import scenario_from_dict, scenario_to_dict

            d = scenario_to_dict(scenario)
            d["strategy"] = args.strategy
            scenario = scenario_from_dict(d)
    else:
        scenario = Scenario.paper(args.strategy or "sequential")
    strategy = scenario.strategy
    if not fixed:
        start_moves = None
    elif scenario.moves is not None:
        start_moves = scenario.moves
    else:
        start_moves = paper_fixed_moves(strategy)
    formation = Formation.from_scenario(scenario, start_moves)
    general = args.triangle == "general" or (
        args.triangle is None and scenario.initial_xy is not None
    )
    formation = eqx.tree_at(
        lambda f: f.initial_xy,
        formation,
        scenario.formation_xy() if general else None,
        is_leaf=lambda x: x is None,
    )
    limits = Limits(image_margin_px=float(args.image_margin))
    key = jr.key(args.seed)
    print(
        f"jaxloc design — {strategy} strategy, objective {args.objective} "
        f"({'trace' if args.criterion == 'A' else 'log-det'}), weights {weights}, "
        f"{args.moves} moves, free: {free if free == 'all' else ','.join(free)}"
    )
    print(
        f"Assumptions: pixel noise sigma = {scenario.rig.sigma_text()} px "
        f"({scenario.rig.noise_model} model); odometry sigma = "
        f"{100 * float(scenario.odometry_sigma_rel):g}% of the distance; {args.starts} starts "
        f"x {args.iterations} BFGS iterations, {args.draws} common draws, seed {args.seed}; "
        f"image margin {args.image_margin:g} px; {scenario.base.dtype}."
    )
    t0 = time.perf_counter()
    res = design_formation(
        formation, scenario, key=key, objective=args.objective, criterion=args.criterion,
        free=free, weights=weights, num_starts=args.starts, num_draws=args.draws,
        iterations=args.iterations, limits=limits, strict_steps=True if args.strict_moves else None,
    )
    elapsed = time.perf_counter() - t0
    best = res.formation
    report: dict = {
        "strategy": strategy,
        "objective": args.objective,
        "criterion": args.criterion,
        "weights": list(weights),
        "moves": args.moves,
        "free": free if free == "all" else list(free),
        "seconds": elapsed,
        "initial": formation_to_dict(res.initial),
        "optimized": formation_to_dict(best),
    }
    # Compare both formations on fresh draws (not the ones optimized on).
    k_fresh = jr.key(args.seed + 1_000_003)
    baseline = Formation.from_scenario(scenario)  # the scenario's own formation and moves
    vals = {}
    runs = [("initial", res.initial), ("optimized", best)]
    if fixed != baseline.fixed_moves:
        runs.append(("scenario", baseline))
    for name, f in runs:
        vals[name] = float(objective_value(
            f, scenario, key=k_fresh, objective=args.objective, criterion=args.criterion,
            weights=weights, num_draws=max(args.draws, 64),
        ))  # fmt: skip
    unit = "cm (RMSE)" if args.criterion == "A" else "(mean log det, m^6)"

    def show(v):
        return f"{100 * np.sqrt(v):.2f}" if args.criterion == "A" else f"{v:.3f}"

    print(f"\nSearch: {elapsed:.1f} s; best start {int(res.best)} of {args.starts}; "
          f"BFGS steps per start {np.asarray(res.steps).tolist()}")
    print(f"Objective {unit}, on the design draws: {show(float(res.objective_initial))} -> "
          f"{show(float(res.objective))}")
    print(f"Objective {unit}, on fresh draws:      {show(vals['initial'])} -> "
          f"{show(vals['optimized'])}")
    if "scenario" in vals:
        kind = "fixed" if baseline.fixed_moves else "random"
        print(f"Objective {unit} of the scenario's own formation ({kind} moves, fresh draws): "
              f"{show(vals['scenario'])}")
    margins, in_view = _margins(best, scenario, limits, args.seed, fixed or args.strict_moves)
    report["objective"] = {
        "design_draws": [float(res.objective_initial), float(res.objective)],
        "fresh_draws": [vals["initial"], vals["optimized"]],
        "scenario_formation_fresh_draws": vals.get("scenario"),
        "penalty": float(res.penalty),
    }
    report["constraint_margins"] = margins
    report["in_view_fraction"] = in_view
    print(f"Constraint penalty {float(res.penalty):.3g} (0 = all margins met); smallest "
          "margin per constraint (>= 0: satisfied with the required margin):")
    for k, v in margins.items():
        print(f"  {k:<16} {v: .4g}")
    print(f"Cycles with every required sighting in view (64 fresh draws): {100 * in_view:.1f}%")
    print("\nOptimized formation:")
    for k, v in formation_to_dict(best).items():
        if v is not None:
            print(f"  {k:<17} {np.round(np.asarray(v), 4).tolist()}")
    designed = best.to_scenario(scenario)
    if args.out:
        save_scenario(designed, args.out)
        designed = load_scenario(args.out)  # verify what the file says
        print(f"\nwrote {args.out} (run it with: jaxloc simulate --scenario {args.out})")
    if args.formation_json:
        with open(args.formation_json, "w") as f:
            json.dump({"initial": report["initial"], "optimized": report["optimized"]}, f,
                      indent=2)
        print(f"wrote {args.formation_json}")
    if args.plot:
        plot_formations(baseline, best, scenario, args.plot, seed=args.seed)
        print(f"wrote {args.plot}")
    if args.verify_trials:
        n = args.verify_trials
        kind = "fixed" if baseline.fixed_moves else "random"
        print(
            f"\nFresh Monte Carlo (run_study, as `jaxloc simulate --methods refined`): {n} "
            f"trials each, seed {args.verify_seed}, refined estimator; before = the "
            f"scenario's own formation ({kind} moves), after = the optimized one "
            f"({args.moves} moves"
            + (f", as read back from {args.out})" if args.out else ")")
        )
        before = evaluate_formation(baseline, scenario, n, seed=args.verify_seed)
        after = evaluate_formation(
            Formation.from_scenario(designed), designed, n, seed=args.verify_seed
        )
        table = rmse_table(before, after)
        report["verification"] = {"trials": n, "seed": args.verify_seed, **table}
        print(format_verification(table))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
        print(f"wrote {args.json}")
    return 0


def _margins(formation, scenario, limits, seed: int, strict: bool):
    """Smallest constraint margin over 64 fresh draws of the formation's cycles (full
    margins on every step if `strict`, else on the initial formation and "in view" after
    the moves) and the fraction of draws with every sighting in view."""
    import jax
    import jax.random as jr

    from .._design.formation import constraint_margins, constraint_values
    from .._design.search import simulate_formation

    scn = formation.apply(scenario)
    keys = jr.split(jr.key(seed + 7), 64)

    @jax.jit
    def values(keys):
        def one(k):
            _, _, pl, visible = simulate_formation(formation, scenario, k)
            return constraint_values(formation, scn, pl, limits, strict_steps=strict), visible

        return jax.vmap(one)(keys)

    vals, visible = values(keys)
    return constraint_margins(vals), float(np.mean(np.asarray(visible)))


def format_verification(table: dict) -> str:
    from .._cycle.layout import CAMERAS

    lines = [
        f"trials ok: before {table['n_ok'][0]}, after {table['n_ok'][1]} "
        f"(failures skipped: {table['failures'][0]}, {table['failures'][1]})",
        "Position RMSE (cm) with 95% bootstrap CI; ratio after/before (paired bootstrap CI)",
        f"{'Camera':<8}{'before':>26}{'after':>26}{'ratio':>26}",
    ]
    for cam in CAMERAS:
        r = table[cam]

        def fmt(x, scale=100.0):
            v, lo, hi = (scale * t for t in x)
            return f"{v:7.2f} [{lo:6.2f}, {hi:6.2f}]"

        lines.append(f"{cam:<8}{fmt(r['before']):>26}{fmt(r['after']):>26}"
                     f"{fmt(r['ratio'], 1.0):>26}")
    return "\n".join(lines)


def plot_formations(before, after, scenario, path: str, *, seed: int = 0, draws: int = 6):
    """3D plot of two formations in the environment frame: the overhead camera (with its
    viewing axis), the robots' initial triangle and, for random moves, the moved robots of
    a few draws (fixed moves: the one path). Saves a PNG to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(12, 5.5))
    titles = ("before (the scenario's formation)", "after (optimized)")
    for col, (title, f) in enumerate(zip(titles, (before, after))):
        ax = fig.add_subplot(1, 2, col + 1, projection="3d")
        draw_formation(ax, f, scenario, seed=seed, draws=draws)
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def draw_formation(ax, formation, scenario, *, seed: int = 0, draws: int = 6):
    """Draw one formation on a 3D matplotlib axis (environment frame, m)."""
    import jax
    import jax.random as jr

    from .._design.search import simulate_formation

    keys = jr.split(jr.key(seed), 1 if formation.fixed_moves else draws)
    pls = jax.vmap(lambda k: simulate_formation(formation, scenario, k)[2])(keys)
    p = np.asarray(pls.p_body)  # (draws, steps, 3, 3)
    colors = ("tab:red", "tab:green", "tab:blue")
    for r, name in enumerate(("C1", "C2", "C3")):
        for d in range(p.shape[0]):
            ax.plot(p[d, :, r, 0], p[d, :, r, 1], p[d, :, r, 2], "-", color=colors[r],
                    alpha=0.35, lw=1)
            ax.scatter(p[d, 1:, r, 0], p[d, 1:, r, 1], p[d, 1:, r, 2], color=colors[r], s=8,
                       alpha=0.5)
        ax.scatter(*p[0, 0, r], color=colors[r], s=40, label=name)
    tri = np.concatenate([p[0, 0], p[0, 0, :1]])
    ax.plot(tri[:, 0], tri[:, 1], tri[:, 2], "k-", lw=1.5)
    c = np.asarray(pls.p_overhead[0])
    axis = np.asarray(pls.R_overhead[0])[:, 2]
    ax.scatter(*c, color="k", marker="s", s=50, label="C (overhead)")
    ax.plot(*np.stack([c, c + 1.0 * axis]).T, "k--", lw=1)
    for r in range(3):
        ax.plot(*np.stack([c, p[0, 0, r]]).T, color="0.6", lw=0.5)
    every = np.concatenate([p.reshape(-1, 3), c[None]])
    ax.set_box_aspect(np.maximum(np.ptp(every, axis=0), 0.5))  # metric proportions
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.legend(fontsize=7, loc="upper left")
