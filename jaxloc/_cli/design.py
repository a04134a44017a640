"""`jaxloc design`: gradient-based formation design from the command line (DESIGN §9).

Wire with `register(sub)` on the `jaxloc` sub-parsers.
"""

import argparse
import time

import numpy as np

from .common import (
    chatter,
    check_outputs,
    check_ray_arg,
    check_seed_arg,
    EXIT_CODES_HELP,
    EXIT_NO_RESULT,
    EXIT_OK,
    HelpFormatter,
    quiet_option,
    ray_cluster,
    ray_option,
    write_report,
)


def register(sub: argparse._SubParsersAction, parents=None) -> None:
    """Add the `design` subcommand to `jaxloc`'s sub-parsers (with the options of the
    `parents` parsers; default: `--quiet`)."""
    parents = [quiet_option()] if parents is None else list(parents)
    p = sub.add_parser(
        "design", parents=parents, epilog=EXIT_CODES_HELP,
        formatter_class=HelpFormatter,
        help="search for a formation that minimizes the expected localization error",
        description=(
            "Optimize the formation (triangle, headings, overhead camera placement, PTZ "
            "setting, moves) with BFGS from the scenario's formation and random starts, "
            "write the best feasible one as a scenario file, and optionally check it by "
            "fresh Monte Carlo against the starting formation. When no start ends feasible, "
            "says so, writes no scenario file and exits with code 1."
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
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the draws and random starts, in [0, 4294967295]")
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
                   help="seed of the fresh Monte Carlo check (differs from --seed), in "
                        "[0, 4294967295]")
    ray_option(p, tasks="every group of starts (one group per cluster CPU)",
               same="the same draws, the same chosen start and formation")
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


#: Largest constraint penalty of a formation counted as feasible, passed to
#: [`jaxloc.design_formation`][] (its default) and used to report the result.
FEASIBILITY_TOL = 0.05


def _feasible(res) -> bool:
    """Whether the search's result is feasible by [`jaxloc.design_formation`][]'s own
    rule (penalty within the tolerance, finite objective)."""
    penalty, total = float(res.penalty), float(res.final[int(res.best)])
    return bool(penalty <= FEASIBILITY_TOL and np.isfinite(total))


def _check_design_args(args) -> tuple:
    """Every check that needs no computation, before anything is compiled. Returns the
    free fields and the weights."""
    for name in ("starts", "draws", "iterations"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name} must be positive; got {getattr(args, name)}.")
    if args.verify_trials < 0:
        raise ValueError(f"--verify-trials must be >= 0; got {args.verify_trials}.")
    if not args.image_margin >= 0:
        raise ValueError(f"--image-margin must be >= 0; got {args.image_margin}.")
    if args.objective == "mc" and args.criterion != "A":
        raise ValueError("--criterion D applies to --objective crlb only.")
    check_seed_arg("--seed", args.seed)
    check_seed_arg("--verify-seed", args.verify_seed)
    check_ray_arg(args)
    check_outputs(args, files=("out", "formation_json", "json"))
    return _parse_free(args.free), _parse_weights(args.weights)


def _start(args):
    """The scenario (with --strategy applied), the starting formation, and whether the
    moves are designed as fixed moves."""
    import equinox as eqx

    from .._design.formation import Formation, paper_fixed_moves
    from .._sim.scenario import Scenario
    from .._sim.scenario_file import load_scenario, scenario_from_dict, scenario_to_dict

    if args.scenario:
        scenario = load_scenario(args.scenario)
        if args.strategy and args.strategy != scenario.strategy:
            scenario = scenario_from_dict({**scenario_to_dict(scenario), "strategy": args.strategy})
    else:
        scenario = Scenario.paper(args.strategy or "sequential")
    fixed = args.moves == "fixed"
    if not fixed:
        start_moves = None
    elif scenario.moves is not None:
        start_moves = scenario.moves
    else:
        start_moves = paper_fixed_moves(scenario.strategy)
    formation = Formation.from_scenario(scenario, start_moves)
    general = args.triangle == "general" or (
        args.triangle is None and scenario.initial_xy is not None
    )
    formation = eqx.tree_at(
        lambda f: f.initial_xy, formation, scenario.formation_xy() if general else None,
        is_leaf=lambda x: x is None,
    )  # fmt: skip
    return scenario, formation, fixed


def _print_header(args, scenario, free, weights) -> None:
    print(
        f"jaxloc design — {scenario.strategy} strategy, objective {args.objective} "
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


def _fresh_objectives(args, res, scenario, fixed, weights) -> tuple[dict, object]:
    """The objective of the initial and optimized formations (and the scenario's own,
    when its kind of moves differs) on fresh draws, not the ones optimized on."""
    import jax.random as jr

    from .._design.formation import Formation
    from .._design.search import objective_value

    k_fresh = jr.key(args.seed + 1_000_003)
    baseline = Formation.from_scenario(scenario)  # the scenario's own formation and moves
    runs = [("initial", res.initial), ("optimized", res.formation)]
    if fixed != baseline.fixed_moves:
        runs.append(("scenario", baseline))
    vals = {
        name: float(objective_value(
            f, scenario, key=k_fresh, objective=args.objective, criterion=args.criterion,
            weights=weights, num_draws=max(args.draws, 64),
        ))  # fmt: skip
        for name, f in runs
    }
    return vals, baseline


def _print_objectives(args, res, elapsed, vals, baseline) -> None:
    unit = "cm (RMSE)" if args.criterion == "A" else "(mean log det, m^6)"

    def show(v):
        return f"{100 * np.sqrt(v):.2f}" if args.criterion == "A" else f"{v:.3f}"

    print(f"\nSearch: {elapsed:.1f} s; best start {int(res.best)} of {args.starts}; "
          f"BFGS steps per start {np.asarray(res.steps).tolist()}")  # fmt: skip
    print(f"Objective {unit}, on the design draws: {show(float(res.objective_initial))} -> "
          f"{show(float(res.objective))}")  # fmt: skip
    print(f"Objective {unit}, on fresh draws:      {show(vals['initial'])} -> "
          f"{show(vals['optimized'])}")  # fmt: skip
    if "scenario" in vals:
        kind = "fixed" if baseline.fixed_moves else "random"
        print(f"Objective {unit} of the scenario's own formation ({kind} moves, fresh draws): "
              f"{show(vals['scenario'])}")  # fmt: skip


def _print_result(res, feasible: bool, margins: dict, in_view: float, starts: int) -> None:
    print(f"Constraint penalty {float(res.penalty):.3g} (0 = all margins met); smallest "
          "margin per constraint (>= 0: satisfied with the required margin):")  # fmt: skip
    for k, v in margins.items():
        print(f"  {k:<16} {v: .4g}")
    print(f"Cycles with every required sighting in view (64 fresh draws): {100 * in_view:.1f}%")
    if feasible:
        print("\nOptimized formation:")
    else:
        print(
            f"\nNo feasible formation found: none of the {starts} starts ends with its "
            f"constraint penalty within {FEASIBILITY_TOL:g} (best: {float(res.penalty):.3g}). "
            "The least infeasible formation below violates the margins above (< 0); it is "
            "not written as a scenario. Relax the limits (e.g. --image-margin) or free more "
            "parameters."
        )
        print("\nLeast infeasible formation (NOT feasible):")
    for k, v in formation_to_dict(res.formation).items():
        if v is not None:
            print(f"  {k:<17} {np.round(np.asarray(v), 4).tolist()}")


def _verify(args, scenario, baseline, designed) -> dict:
    """Fresh Monte Carlo of the scenario's own formation (`baseline`) and of the designed
    scenario (as read back from --out if written); prints and returns the RMSE table."""
    from .._design.formation import Formation
    from .._design.search import evaluate_formation, rmse_table

    n = args.verify_trials
    kind = "fixed" if baseline.fixed_moves else "random"
    print(
        f"\nFresh Monte Carlo (run_study, as `jaxloc simulate --methods refined`): {n} "
        f"trials each, seed {args.verify_seed}, refined estimator; before = the "
        f"scenario's own formation ({kind} moves), after = the optimized one "
        f"({args.moves} moves" + (f", as read back from {args.out})" if args.out else ")")
    )
    before = evaluate_formation(baseline, scenario, n, seed=args.verify_seed)
    after = evaluate_formation(
        Formation.from_scenario(designed), designed, n, seed=args.verify_seed
    )
    table = rmse_table(before, after)
    print(format_verification(table))
    return {"trials": n, "seed": args.verify_seed, **table}


def _design_report(args, res, strategy, free, weights, elapsed, vals, margins, in_view):
    """The --json report: settings, both formations, objectives, constraint margins."""
    feasible = _feasible(res)
    return {
        "strategy": strategy, "objective_kind": args.objective, "criterion": args.criterion,
        "weights": list(weights), "moves": args.moves,
        "free": free if free == "all" else list(free), "seconds": elapsed, "feasible": feasible,
        "initial": formation_to_dict(res.initial), "optimized": formation_to_dict(res.formation),
        "objective": {
            "design_draws": [float(res.objective_initial), float(res.objective)],
            "fresh_draws": [vals["initial"], vals["optimized"]],
            "scenario_formation_fresh_draws": vals.get("scenario"),
            "penalty": float(res.penalty),
        },
        "constraint_margins": margins,
        "in_view_fraction": in_view,
    }  # fmt: skip


def _write_outputs(args, res, report, scenario, baseline, feasible):
    """--out (only a feasible formation), --formation-json and --plot; returns the
    designed scenario (as read back from --out if written)."""
    from .._sim.scenario_file import load_scenario, save_scenario

    designed = res.formation.to_scenario(scenario)
    if args.out and feasible:
        save_scenario(designed, args.out)
        designed = load_scenario(args.out)  # verify what the file says
        chatter(args)(f"\nwrote {args.out} (run it with: jaxloc simulate --scenario {args.out})")
    if args.formation_json:
        keys = ("initial", "optimized", "feasible")
        write_report(args.formation_json, {k: report[k] for k in keys}, quiet=args.quiet)
    if args.plot:
        plot_formations(baseline, res.formation, scenario, args.plot, seed=args.seed)
        chatter(args)(f"wrote {args.plot}")
    return designed


def _cmd_design(args) -> int:
    import jax.random as jr

    from .._design.formation import Limits
    from .._design.search import design_formation

    free, weights = _check_design_args(args)
    scenario, formation, fixed = _start(args)
    limits = Limits(image_margin_px=float(args.image_margin))
    _print_header(args, scenario, free, weights)
    with ray_cluster(args) as where:
        if where:
            chatter(args)(f"({where}; every group of starts one task, retried if its worker "
                          "is lost)")  # fmt: skip
        t0 = time.perf_counter()
        res = design_formation(
            formation, scenario, key=jr.key(args.seed), objective=args.objective,
            criterion=args.criterion, free=free, weights=weights, num_starts=args.starts,
            num_draws=args.draws, iterations=args.iterations, limits=limits,
            strict_steps=True if args.strict_moves else None, feasibility_tol=FEASIBILITY_TOL,
            runner=_runner(args),
        )  # fmt: skip
        elapsed = time.perf_counter() - t0
    feasible = _feasible(res)
    vals, baseline = _fresh_objectives(args, res, scenario, fixed, weights)
    _print_objectives(args, res, elapsed, vals, baseline)
    strict = fixed or args.strict_moves
    margins, in_view = _margins(res.formation, scenario, limits, args.seed, strict)
    _print_result(res, feasible, margins, in_view, args.starts)
    report = _design_report(args, res, scenario.strategy, free, weights, elapsed, vals, margins,
                            in_view)  # fmt: skip
    if where:
        report["ray"] = where
    designed = _write_outputs(args, res, report, scenario, baseline, feasible)
    if args.verify_trials and feasible:
        report["verification"] = _verify(args, scenario, baseline, designed)
    elif args.verify_trials:
        print("\nFresh Monte Carlo skipped: no feasible formation to verify.")
    if args.json:
        write_report(args.json, report, quiet=args.quiet)
    return EXIT_OK if feasible else EXIT_NO_RESULT


def _runner(args):
    """The start runner of --ray (`jaxloc._design.cluster.ray_starts`), else `None`
    (every start in this process)."""
    if args.ray is None:
        return None
    from .._design.cluster import ray_starts

    return ray_starts()


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
