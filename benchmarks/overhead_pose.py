"""Overhead-camera pose: jaxloc's solvers under jit(vmap) vs cv2.solvePnP in a loop.

    python benchmarks/overhead_pose.py [--batch 100000] [--loop 2000]

Same seeded problems for every method: the paper's geometry (camera 3.5 m above six
robot positions spread like the sequential strategy's, 656 px focal length), 2 px pixel
noise (paper model). Prints problems/s and the median / p90 camera-position error, so no
method wins by being wrong.
"""

import argparse
import json
import time

import cv2
import jax
import jax.numpy as jnp
import jaxloc
import numpy as np


F = 656.1  # px, the paper's 52 deg overhead camera at 640 px


def problems(n: int, rng: np.random.Generator):
    h = np.sqrt(1.5**2 - 1.0**2)
    base = np.array([[-h, 0, 0], [0, 1, 0], [0, -1, 0]])
    pts = np.concatenate([base, base + rng.normal(scale=0.5, size=(3, 3)) * [1, 1, 0]])
    pts = np.broadcast_to(pts, (n, 6, 3)) + rng.normal(scale=[0.2, 0.2, 0.05], size=(n, 6, 3))
    cam = np.stack([rng.normal(0, 0.2, n), rng.normal(0, 0.2, n), 3.5 + rng.normal(0, 0.1, n)], -1)
    # Camera looking down: optical z = -world z.
    R = np.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, -1]])
    p_cam = np.einsum("ij,nkj->nki", R, pts - cam[:, None, :])
    uv = F * p_cam[..., :2] / p_cam[..., 2:]
    radius = rng.normal(0, 2.0, size=uv.shape[:2])
    angle = rng.uniform(0, 2 * np.pi, size=uv.shape[:2])
    uv_noisy = uv + radius[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    bearings = np.concatenate([uv_noisy / F, np.ones(uv.shape[:2] + (1,))], -1)
    bearings /= np.linalg.norm(bearings, axis=-1, keepdims=True)
    return pts, bearings, uv_noisy / F, cam


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--batch", type=int, default=100_000)
    parser.add_argument("--loop", type=int, default=2000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    pts, bearings, xy, cam = problems(args.batch, rng)
    rows = {}

    for method in ("robust", "paper"):
        solve = jax.jit(
            jax.vmap(lambda p, b: jaxloc.solve_overhead_pose(p, b, method=method, throw=False))
        )
        t0 = time.perf_counter()
        jax.block_until_ready(solve(jnp.asarray(pts[:256]), jnp.asarray(bearings[:256])))
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        sol = solve(jnp.asarray(pts), jnp.asarray(bearings))
        jax.block_until_ready(sol)
        dt = time.perf_counter() - t0
        err = np.linalg.norm(np.asarray(sol.pose.inverse().translation()) - cam, axis=-1)
        rows[f"jaxloc {method} jit(vmap) x{args.batch}"] = (args.batch / dt, err, compile_s)

    n = args.loop
    for name, flag in (
        ("SQPNP", cv2.SOLVEPNP_SQPNP),
        ("EPNP", cv2.SOLVEPNP_EPNP),
        ("ITERATIVE", cv2.SOLVEPNP_ITERATIVE),
    ):
        K = np.eye(3)
        errs = []
        t0 = time.perf_counter()
        for i in range(n):
            ok, rvec, tvec = cv2.solvePnP(pts[i], xy[i], K, None, flags=flag)
            errs.append((rvec, tvec))
        dt = time.perf_counter() - t0
        err = np.array(
            [
                np.linalg.norm(-cv2.Rodrigues(r)[0].T @ t.ravel() - cam[i])
                for i, (r, t) in enumerate(errs)
            ]
        )
        rows[f"cv2.solvePnP {name} loop x{n}"] = (n / dt, err, 0.0)

    print(
        f"{'method':<40}{'problems/s':>12}{'median err (cm)':>17}{'p90 (cm)':>10}"
        f"{'compile (s)':>12}"
    )
    report = {}
    for name, (rate, err, comp) in rows.items():
        print(
            f"{name:<40}{rate:>12,.0f}{100 * np.median(err):>17.2f}"
            f"{100 * np.percentile(err, 90):>10.2f}{comp:>12.1f}"
        )
        report[name] = {
            "per_second": rate,
            "median_m": float(np.median(err)),
            "p90_m": float(np.percentile(err, 90)),
            "compile_s": comp,
        }
    print(
        json.dumps(
            {
                "command": "python benchmarks/overhead_pose.py "
                f"--batch {args.batch} --loop {args.loop}"
            }
        )
    )


if __name__ == "__main__":
    main()
