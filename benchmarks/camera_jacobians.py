"""Closed-form projection Jacobians against `jax.jacfwd`, per camera model (issue 19).

    python benchmarks/camera_jacobians.py                 # batch 10^4, float64
    python benchmarks/camera_jacobians.py --dtype float32 --batch 100000 --json out.json

For each camera model and distortion, three programs map a batch of points in view to
pixels and `d pixels / d point` `(batch, 2, 3)`: `jit(vmap(camera.project_with_jacobian))`
("closed", the closed form written element-wise, one point per vmapped call), the same
method called once on the whole batch ("batched": it broadcasts over leading axes), and
`jit(vmap(jacfwd))` of `camera.project` ("jacfwd", `jaxloc.project_with_jacobian_autodiff`,
what the refinement did before). The camera is an argument (its parameters traced, as the
refinement passes it). Printed per program: the seconds to trace and lower, to compile
(median of 3 fresh compilations), the number of fused kernels, the run time (best of 50
calls) and the largest relative difference of the closed form and jacfwd Jacobians. No
persistent compilation cache.
"""

import argparse
import json
import re
import statistics
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=10_000)
    parser.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = parser.parse_args()

    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import jaxloc
    import numpy as np
    from jaxloc._cameras.models import (
        OmniCamera,
        PinholeCamera,
        project_with_jacobian_autodiff,
        PTZCamera,
        ZoomTable,
    )

    jax.config.update("jax_enable_compilation_cache", False)
    dtype = jnp.float32 if args.dtype == "float32" else jnp.float64
    table = ZoomTable(
        [0.0, 0.4, 1.0], [420.0, 700.0, 1500.0], [421.5, 702.0, 1504.0],
        [321.0, 318.5, 316.0], [238.0, 240.5, 243.0],
        [[-0.2, 0.05, 1e-3, -5e-4, 0.0], [-0.1, 0.02, 5e-4, 0.0, 0.0],
         [-0.02, 0.0, 0.0, 1e-4, 0.0]],
    )  # fmt: skip
    left = (-0.266, -0.0386, 0.00178, -0.00028, 0.238)
    cameras = {
        "pinhole (paper overhead)": jaxloc.paper_overhead_camera(),
        "pinhole radtan5": PinholeCamera(535.9, 535.9, 342.3, 235.6, left),
        "pinhole rational8": PinholeCamera(
            400.0, 402.0, 320.0, 240.0, (1.8, 0.9, 1e-3, -5e-4, 0.05, 2.1, 1.3, 0.2)
        ),
        "pinhole equidistant": PinholeCamera(
            280.0, 281.0, 322.0, 238.0, (-0.013, 0.02, -0.015, 0.004), distortion="equidistant"
        ),
        "ptz (paper, pan/tilt)": jaxloc.paper_ptz_camera(pan=0.3, tilt=-0.2, zoom=0.4),
        "ptz zoom table": PTZCamera(pan=-0.4, tilt=0.25, zoom=0.7, zoom_table=table),
        "omni (paper)": jaxloc.paper_omni_camera(),
        "omni radtan": OmniCamera(
            0.9, 180.0, 182.0, 320.0, 240.0, skew=0.5, dist=(-0.02, 0.003, 1e-3, -1e-3)
        ),
        "omni equidistant": OmniCamera(
            0.9, 180.0, 182.0, 320.0, 240.0, skew=0.5, dist=(-0.02, 0.003, 1e-3, -1e-3),
            distortion="equidistant",
        ),  # fmt: skip
    }

    def closed(camera, p):
        return jax.vmap(camera.project_with_jacobian)(p)

    def batched(camera, p):
        return camera.project_with_jacobian(p)

    def autodiff(camera, p):
        return project_with_jacobian_autodiff(camera, p)

    rng = np.random.default_rng(0)
    rows = []
    print(f"batch {args.batch}, {args.dtype}, jax {jax.__version__}, "
          f"{jax.devices()[0].platform}", flush=True)  # fmt: skip
    header = (f"{'camera':<26} {'program':<9} {'trace s':>8} {'compile s':>10} "
              f"{'fusions':>8} {'run ms':>8} {'Mpts/s':>7}")  # fmt: skip
    print(header)
    for name, cam in cameras.items():
        cam = jax.tree.map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, cam)
        w, h = cam.image_size
        uv = rng.uniform([0.0, 0.0], [w - 1.0, h - 1.0], size=(4 * args.batch, 2))
        b = np.asarray(jax.jit(lambda c, x: c.unproject(x))(cam, jnp.asarray(uv, dtype)))
        p = b * rng.uniform(0.5, 5.0, size=(len(b), 1))
        ok = np.asarray(jax.jit(lambda c, x: c.in_view(x))(cam, jnp.asarray(p, dtype)))
        p = jnp.asarray(p[ok][: args.batch], dtype)
        results = {}
        for prog_name, fn in (("closed", closed), ("batched", batched), ("jacfwd", autodiff)):
            compile_s, trace_s = [], []
            for _ in range(3):
                jitted = jax.jit(lambda c, x, fn=fn: fn(c, x))
                t0 = time.perf_counter()
                lowered = jitted.lower(cam, p)
                t1 = time.perf_counter()
                compiled = lowered.compile()
                t2 = time.perf_counter()
                trace_s.append(t1 - t0)
                compile_s.append(t2 - t1)
            fusions = len(re.findall(r" fusion[.\d]*\(", compiled.as_text()))
            jax.block_until_ready(compiled(cam, p))
            runs = []
            for _ in range(50):
                t0 = time.perf_counter()
                out = jax.block_until_ready(compiled(cam, p))
                runs.append(time.perf_counter() - t0)
            results[prog_name] = out
            row = dict(camera=name, program=prog_name, batch=int(p.shape[0]), dtype=args.dtype,
                       trace_s=statistics.median(trace_s),
                       compile_s=statistics.median(compile_s), fusions=fusions,
                       run_s=min(runs))  # fmt: skip
            rows.append(row)
            print(f"{name:<26} {prog_name:<9} {row['trace_s']:8.3f} {row['compile_s']:10.3f} "
                  f"{fusions:8d} {1e3 * row['run_s']:8.3f} "
                  f"{p.shape[0] / row['run_s'] / 1e6:7.2f}", flush=True)  # fmt: skip
        J, J_ref = np.asarray(results["closed"][1]), np.asarray(results["jacfwd"][1])
        scale = np.abs(J_ref).max(axis=(-1, -2))
        rel = float((np.abs(J - J_ref).max(axis=(-1, -2)) / scale).max())
        for row in rows[-3:]:
            row["max_rel_diff"] = rel
        c, bt, a = rows[-3:]
        print(f"{'':<26} jacfwd / closed: compile x{a['compile_s'] / c['compile_s']:.2f}, run "
              f"x{a['run_s'] / c['run_s']:.2f} (batched x{a['run_s'] / bt['run_s']:.2f}); max "
              f"rel. diff {rel:.1e}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
