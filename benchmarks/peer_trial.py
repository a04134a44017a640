"""A peer for the whole Monte Carlo trial (issue 19, item 3): jaxloc's study vs NumPy/OpenCV/scipy.

    python benchmarks/peer_trial.py [--trials N] [--strategies sequential,concurrent] [--quick]
                                    [--out benchmarks/results/peer_trial.json]

The peer is the trial written the way a robotics researcher would write it without JAX:

- **NumPy, vectorized over trials**: the simulation of a cycle (placement on the saddle ground
  and the sinusoid ceiling, moves with branch-free resampling of `move_candidates` candidates
  until every required sighting is in view, projection through the camera models, pixel
  noise, odometry), the unprojection of the pixels, the three-robot mutual localization (law
  of sines + SVD Kabsch with the determinant fix, DESIGN §3), the sequential chain and its
  scale fit, and the concurrent scale fit (see `concurrent_scales`: simpler than jaxloc's).
- **`cv2.solvePnP(..., flags=cv2.SOLVEPNP_SQPNP)`** in a Python loop for the overhead camera
  (object points: the distinct placements in the world frame; image points: the overhead
  pixels, averaged over the sightings of a placement; K of the overhead camera; no
  distortion).
- **`scipy.optimize.least_squares`** in a Python loop for the joint refinement of a cycle:
  the residuals of jaxloc's `refine_cycle` (every mutual pixel, every overhead pixel, every
  odometry distance, each divided by its sigma), written in NumPy and vectorized within the
  cycle; unknowns: every distinct placement's pose but the first (the gauge) and the
  overhead camera's pose, each as `(t0 + v, R0 Exp(w))`; analytic Jacobian (the timed
  one) and scipy's finite differences (timed on a subset).

Measured, for each strategy:

- speed: the peer's whole trial (its own simulation + estimators + scoring), trials/s, in one
  process and in one process per core; the peer's estimators alone on jaxloc's
  observations; jaxloc's `run_study(methods=("robust",))` and `("robust", "refined")`
  trials/s after a warm-up chunk (compilation excluded), on every local core (one host
  device per core);
- accuracy on the same seeded trials: jaxloc's simulator produces the observations of trials
  `jaxloc.trial_key(seed, i)`, which the peer's estimators consume (as pixels and odometry,
  converted to NumPy); jaxloc's own errors on those trials come from the timed
  `run_study(..., methods=("robust", "refined"))`. Position / rotation error median, RMSE,
  p90 of C, C1, C2, C3; per-trial agreement of the two refinements (same minimum).

Checks (assertions): the peer's camera models agree with jaxloc's `project` to 1e-9 px (and
`unproject` to 1e-12) on the same points; the peer's strategy tables equal jaxloc's; the
peer's analytic Jacobian agrees with finite differences; the peer's noise-free pixels at
jaxloc's true poses differ from jaxloc's noisy pixels by the noise alone (RMS ~ sigma).

Every jaxloc call is in the section marked "JAXLOC SIDE" (one function, `jaxloc_side`).
"""

import argparse
import json
import math
import multiprocessing
import os
import subprocess
import sys
import time


# One BLAS thread: OpenBLAS's threads make a 58 x 42 SVD inside `least_squares` take 6-36 ms
# instead of 0.4 ms on this 2-core machine (measured). A Monte Carlo of tiny problems runs
# single-threaded BLAS; set before NumPy loads OpenBLAS (also in the spawned workers).
# jaxloc's trial programs make no LAPACK call on their hot path (DESIGN §8).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import cv2
import numpy as np
import scipy
import scipy.optimize


HERE = os.path.dirname(os.path.abspath(__file__))
CAMERAS = ("C", "C1", "C2", "C3")
#: Move lengths are clipped to at least this (m): the `Scenario` docstring's model.
MIN_MOVE_LENGTH = 0.05
#: Move candidates checked at once per trial in the simulation (see `simulate`).
CANDIDATE_BLOCK = 2
#: Smallest triangle angle (rad) the mutual localization accepts (as jaxloc's default).
MIN_ANGLE = math.radians(0.5)
#: Two concurrent scale candidates are the same when no scale differs by more than this
#: (log ratio); at most `MAX_SCALE_CANDIDATES` distinct ones are checked with solvePnP.
DISTINCT_LOG_SCALE = 0.1
MAX_SCALE_CANDIDATES = 4
#: A concurrent candidate whose odometry chi-square exceeds the best one's by more than
#: this is not checked with solvePnP (it cannot win on the combined score anyway unless
#: the overhead pixels overturn a 7-sigma odometry misfit).
ODOMETRY_GATE = 50.0
#: Two refined solutions whose every position differs by less than this (m) are the same
#: minimum. The two solvers' tolerances leave ~2e-5 m typically and up to a few mm along
#: weakly observed directions of the concurrent cycle (same cost to 0.1 chi-square
#: units, checked), while distinct minima of the paper's geometry are 1-4 m apart.
SAME_MINIMUM_M = 1e-2

#: Load-average snapshots around every timed section: `(label, seconds since start, 1-min
#: load, 5-min load)`. The machine is shared: a row measured under load says so.
LOAD_LOG = []
_T0 = time.perf_counter()


def mark(label):
    one, five, _ = os.getloadavg()
    LOAD_LOG.append((label, round(time.perf_counter() - _T0, 1), one, five))


#: The strategies as the paper (and DESIGN §3) describe them: steps, moving robot and start
#: step of each move, distinct placement of each (step, robot), reference robot of each
#: step's mutual localization (sequential: the robot that moved the earliest).
STRATEGIES = {
    "sequential": {
        "steps": 4,
        "movers": np.array([1, 2, 0]),
        "starts": np.array([0, 1, 2]),
        "ids": np.array([[0, 1, 2], [0, 3, 2], [0, 3, 4], [5, 3, 4]]),
        "refs": (0, 2, 0, 1),
    },
    "concurrent": {
        "steps": 3,
        "movers": np.array([1, 2, 1, 2]),
        "starts": np.array([0, 0, 1, 1]),
        "ids": np.array([[0, 1, 2], [0, 3, 4], [0, 5, 6]]),
        "refs": (0, 0, 0),
    },
}


# ======================================================================================
# Peer: small rotation helpers (NumPy, batched over leading axes).


def skew(w):
    z = np.zeros_like(w[..., 0])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w):
    """Rodrigues' formula, batched; Taylor series below 1e-4 rad."""
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-8
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = skew(w)
    return np.eye(3) + a * K + b * (K @ K)


def so3_right_jacobian(w):
    """`Jr(w)`: `Exp(w + d) = Exp(w) Exp(Jr(w) d)` to first order."""
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    small = th2 < 1e-8
    safe = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    b = np.where(small, 1.0 / 6.0 - th2 / 120.0, (safe - np.sin(safe)) / (safe**3))
    K = skew(w)
    return np.eye(3) - a * K + b * (K @ K)


def rotation_angle(R):
    """Geodesic angle of rotation matrices (rad), accurate near 0 and pi."""
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], -1)  # fmt: skip
    return np.arctan2(0.5 * np.linalg.norm(v, axis=-1), c)


def quat_to_matrix(q):
    """`wxyz` unit quaternions to rotation matrices, batched."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ======================================================================================
# Peer: camera models (NumPy). Points are batched `(..., 3)`, pixels `(..., 2)`.


class Pinhole:
    """Pinhole without distortion (the overhead camera, and the PTZ camera at pan = tilt = 0,
    whose base frame is then its optical frame: x right, y down, z forward)."""

    def __init__(self, fx, fy, cx, cy, image_size):
        self.fx, self.fy, self.cx, self.cy = fx, fy, cx, cy
        self.w, self.h = image_size

    @property
    def K(self):
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, P):
        return np.stack(
            [self.fx * P[..., 0] / P[..., 2] + self.cx, self.fy * P[..., 1] / P[..., 2] + self.cy],
            -1,
        )

    def project_jacobian(self, P):
        """Pixels `(..., 2)` and `d pixel / d P` `(..., 2, 3)`."""
        X, Y, Z = P[..., 0], P[..., 1], P[..., 2]
        iz = 1.0 / Z
        zero = np.zeros_like(X)
        uv = np.stack([self.fx * X * iz + self.cx, self.fy * Y * iz + self.cy], -1)
        J = np.stack(
            [
                np.stack([self.fx * iz, zero, -self.fx * X * iz * iz], -1),
                np.stack([zero, self.fy * iz, -self.fy * Y * iz * iz], -1),
            ],
            -2,
        )
        return uv, J

    def unproject(self, uv):
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        return normalize(np.stack([x, y, np.ones_like(x)], -1))

    def in_view(self, P):
        X, Y, Z = P[..., 0], P[..., 1], P[..., 2]
        front = (Z > 0) & (Z * 1e4 > np.abs(X) + np.abs(Y))
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * X / Z + self.cx
            v = self.fy * Y / Z + self.cy
        inside = (u >= -0.5) & (u <= self.w - 0.5) & (v >= -0.5) & (v <= self.h - 0.5)
        return front & inside


class Omni:
    """Mei's unified model without distortion: `m = (X, Y) / (Z + xi |P|)`, then the
    generalized pinhole `u = fx m_x + skew m_y + cx`, `v = fy m_y + cy`. Parameters may be
    arrays broadcasting against the points' batch shape (several cameras at once)."""

    def __init__(self, xi, fx, fy, cx, cy, skew, elevation_min, elevation_max, image_size):
        self.xi, self.fx, self.fy, self.cx, self.cy, self.s = xi, fx, fy, cx, cy, skew
        self.emin, self.emax = elevation_min, elevation_max
        self.w, self.h = image_size

    def project(self, P):
        D = P[..., 2] + self.xi * np.linalg.norm(P, axis=-1)
        mx, my = P[..., 0] / D, P[..., 1] / D
        return np.stack([self.fx * mx + self.s * my + self.cx, self.fy * my + self.cy], -1)

    def project_jacobian(self, P):
        X, Y, Z = P[..., 0], P[..., 1], P[..., 2]
        rho = np.sqrt(X * X + Y * Y + Z * Z)
        D = Z + self.xi * rho
        iD = 1.0 / D
        mx, my = X * iD, Y * iD
        # dD/dP = xi P / rho + e_z
        dD = np.asarray(self.xi)[..., None] * P / rho[..., None]
        dD[..., 2] += 1.0
        dmx = -mx[..., None] * iD[..., None] * dD
        dmx[..., 0] += iD
        dmy = -my[..., None] * iD[..., None] * dD
        dmy[..., 1] += iD
        fx, fy, s = (np.asarray(a)[..., None] for a in (self.fx, self.fy, self.s))
        uv = np.stack([self.fx * mx + self.s * my + self.cx, self.fy * my + self.cy], -1)
        J = np.stack([fx * dmx + s * dmy, fy * dmy], -2)
        return uv, J

    def unproject(self, uv):
        my = (uv[..., 1] - self.cy) / self.fy
        mx = (uv[..., 0] - self.cx - self.s * my) / self.fx
        r2 = mx * mx + my * my
        lam = (self.xi + np.sqrt(1.0 + (1.0 - self.xi * self.xi) * r2)) / (r2 + 1.0)
        return normalize(np.stack([lam * mx, lam * my, lam - self.xi], -1))

    def in_view(self, P):
        n = np.linalg.norm(P, axis=-1)
        safe = np.where(n > 0, n, 1.0)
        zs = P[..., 2] / safe
        xi = np.asarray(self.xi)
        w = np.where(xi > 1.0, 1.0 / np.maximum(xi, 1.0), xi)
        elevation = np.arctan2(P[..., 2], np.hypot(P[..., 0], P[..., 1]))
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = np.moveaxis(self.project(P), -1, 0)
        inside = (u >= -0.5) & (u <= self.w - 0.5) & (v >= -0.5) & (v <= self.h - 0.5)
        return (
            (n > 0) & (zs > -w) & (elevation >= self.emin) & (elevation <= self.emax) & inside
        )


# ======================================================================================
# Peer: the world (height fields) and the robots' body frames.


class Surface:
    """`saddle`: z = z0 + x^2 / (2 rx) + y^2 / (2 ry); `sinusoid`: z = z0 + A (cos(2 pi x / P
    + phase) - cos(phase)); `flat`: z = z0."""

    def __init__(self, kind, **p):
        self.kind, self.p = kind, p

    def height(self, xy):
        x, y, p = xy[..., 0], xy[..., 1], self.p
        if self.kind == "saddle":
            return p["z0"] + x * x / (2 * p["radius_x"]) + y * y / (2 * p["radius_y"])
        if self.kind == "sinusoid":
            w = 2 * math.pi / p["period"]
            return p["z0"] + p["amplitude"] * (np.cos(w * x + p["phase"]) - math.cos(p["phase"]))
        return np.full(x.shape, p["z0"])

    def gradient(self, xy):
        x, y, p = xy[..., 0], xy[..., 1], self.p
        if self.kind == "saddle":
            return np.stack([x / p["radius_x"], y / p["radius_y"]], -1)
        if self.kind == "sinusoid":
            w = 2 * math.pi / p["period"]
            return np.stack([-p["amplitude"] * w * np.sin(w * x + p["phase"]), 0 * y], -1)
        return np.zeros(xy.shape)


def body_frames(surface, xy, heading):
    """Body frames on a height field (x = heading projected vertically into the tangent
    plane, z = upward normal, y = z x x): `R (..., 3, 3)` (columns), `p (..., 3)`."""
    g = surface.gradient(xy)
    n = normalize(np.stack([-g[..., 0], -g[..., 1], np.ones(xy.shape[:-1])], -1))
    c, s = np.cos(heading), np.sin(heading)
    c, s = c + 0 * g[..., 0], s + 0 * g[..., 0]
    x = normalize(np.stack([c, s, g[..., 0] * c + g[..., 1] * s], -1))
    y = np.cross(n, x)
    p = np.concatenate([xy, surface.height(xy)[..., None]], -1)
    return np.stack([x, y, n], -1), p


class World:
    """Everything the peer's simulator and estimators need, from a parameter dict of plain
    numbers and arrays (built by the jaxloc side from a `jaxloc.Scenario`; picklable)."""

    def __init__(self, params):
        self.params = params
        P = params
        self.strategy = P["strategy"]
        self.tables = STRATEGIES[self.strategy]
        self.ground = Surface(P["ground"][0], **P["ground"][1])
        self.ceiling = Surface(P["ceiling"][0], **P["ceiling"][1])
        self.overhead = Pinhole(**P["overhead"])
        self.K = self.overhead.K
        self.ptz = Pinhole(**P["ptz"])
        self.omni = [Omni(**P["omni2"]), Omni(**P["omni3"])]
        o2, o3 = P["omni2"], P["omni3"]
        # omni2 and omni3 as one camera with per-robot parameters, shape (2, 1): the mutual
        # sightings of robots 1 and 2 are projected in one call.
        self.omni_pair = Omni(
            **{k: np.array([[o2[k]], [o3[k]]]) for k in o2 if k != "image_size"},
            image_size=o2["image_size"],
        )
        assert o2["image_size"] == o3["image_size"]
        self.M_ptz = np.asarray(P["R_BODY_PTZ"])
        self.M_omni = np.asarray(P["R_BODY_OMNI"])
        R_climber, self.t_over = body_frames(
            self.ceiling, np.asarray(P["overhead_xy"]), np.asarray(P["overhead_heading"])
        )
        self.R_over = R_climber @ np.asarray(P["R_BODY_OVERHEAD"])
        self.xy0 = np.asarray(P["formation_xy"])
        self.headings = np.asarray(P["headings"])
        sigma = P["pixel_sigma"]
        self.sigma_px = sigma / math.sqrt(2.0) if P["noise_model"] == "paper" else sigma
        ids = self.tables["ids"]
        self.n_place = int(ids.max()) + 1
        # First (step, robot) of each placement, and the averaging matrix of its sightings.
        self.first = np.array([np.argwhere(ids == p)[0] for p in range(self.n_place)])
        A = (ids.reshape(-1)[None, :] == np.arange(self.n_place)[:, None]).astype(float)
        self.average = A / A.sum(axis=1, keepdims=True)


# ======================================================================================
# Peer: simulation of a batch of cycles (NumPy, vectorized over trials and candidates).


def relative_points(R, p):
    """`rel[..., i, j] = R_i^T (p_j - p_i)`; the diagonal set to (1, 0, 0) (unused).
    Written as three broadcast products (2x faster than `np.einsum` here)."""
    d = p[..., None, :, :] - p[..., :, None, :]
    Rc = R[..., :, None, :, :]  # rows of R_i: R_i^T d = sum_b R[b, :] d_b
    rel = Rc[..., 0, :] * d[..., 0:1] + Rc[..., 1, :] * d[..., 1:2] + Rc[..., 2, :] * d[..., 2:3]
    rel[..., [0, 1, 2], [0, 1, 2], :] = (1.0, 0.0, 0.0)
    return rel


def formations_ok(world, xy):
    """Required sightings and separation of formations `xy (..., 3, 2)`: bool `(...)`."""
    P = world.params
    R, p = body_frames(world.ground, xy, world.headings)
    rel = relative_points(R, p)
    ok = np.ones(xy.shape[:-2], bool)
    if P["require_overhead"]:
        p_over = np.einsum("ba,...jb->...ja", world.R_over, p - world.t_over)
        ok &= np.all(world.overhead.in_view(p_over), axis=-1)
    if P["require_ptz"]:
        vis = world.ptz.in_view(np.einsum("ba,...jb->...ja", world.M_ptz, rel[..., 0, :, :]))
        ok &= vis[..., 1] & vis[..., 2]
    if P["require_omni"]:
        pts = np.einsum("ba,...ijb->...ija", world.M_omni, rel[..., 1:, :, :])
        vis = world.omni_pair.in_view(pts)  # (..., 2, 3)
        ok &= vis[..., 0, 0] & vis[..., 0, 2] & vis[..., 1, 0] & vis[..., 1, 1]
    d2 = np.sum((p[..., :, None, :] - p[..., None, :, :]) ** 2, axis=-1)
    sep2 = P["min_separation"] ** 2
    return ok & (d2[..., 0, 1] >= sep2) & (d2[..., 0, 2] >= sep2) & (d2[..., 1, 2] >= sep2)


def pixel_noise(world, rng, shape):
    sigma = world.params["pixel_sigma"]
    if world.params["noise_model"] == "paper":
        # Radius ~ N(0, sigma), direction ~ U[0, 2 pi) (the paper's Sec. IV.A).
        r = sigma * rng.standard_normal(shape)
        a = rng.uniform(0.0, 2 * math.pi, shape)
        return np.stack([r * np.cos(a), r * np.sin(a)], -1)
    return sigma * rng.standard_normal(shape + (2,))


def observe(world, R_b, p_b, R_cam, t_cam):
    """Noise-free pixels of every sighting of a batch of cycles whose ground robots have
    body frames `R_b (..., steps, 3, 3, 3)`, `p_b (..., steps, 3, 3)` and whose overhead
    camera has the pose `R_cam (..., 3, 3)`, `t_cam (..., 3)` (same frame): mutual
    `(..., steps, 3, 3, 2)` (diagonal: a dummy pixel), overhead `(..., steps, 3, 2)`."""
    rel = relative_points(R_b, p_b)
    uv_ptz = world.ptz.project(rel[..., 0, :, :] @ world.M_ptz)  # M^T rel
    uv_omni = world.omni_pair.project(rel[..., 1:, :, :] @ world.M_omni)
    mutual = np.concatenate([uv_ptz[..., None, :, :], uv_omni], axis=-3)
    d = p_b - t_cam[..., None, None, :]
    over = world.overhead.project(d @ R_cam[..., None, :, :])  # R_cam^T d
    return mutual, over


def simulate(world, rng, n):
    """`n` cycles: `(obs, truth, feasible)` as NumPy arrays. `obs`: mutual and overhead
    pixels, odometry and its sigma; `truth`: the end-of-cycle poses of C (camera frame)
    and of C1, C2, C3 in the world frame W (C1's body frame at the start)."""
    P, tb = world.params, world.tables
    steps, movers, starts = tb["steps"], tb["movers"], tb["starts"]
    mover_mask = np.zeros((steps - 1, 3), bool)
    mover_mask[starts, movers] = True
    K = P["move_candidates"]
    xy = np.broadcast_to(world.xy0, (n, 3, 2)).copy()
    feasible = formations_ok(world, xy)
    rows = np.arange(n)
    xys = [xy]
    for s in range(steps - 1):
        R, _ = body_frames(world.ground, xy, world.headings)  # (n, 3, 3, 3)
        length = np.maximum(
            P["move_mean"] + P["move_std"] * rng.standard_normal((n, K, 3)), MIN_MOVE_LENGTH
        )
        phi = rng.uniform(-math.pi, math.pi, (n, K, 3))
        d = np.cos(phi)[..., None] * R[:, None, :, :, 0]
        d += np.sin(phi)[..., None] * R[:, None, :, :, 1]
        cands = np.where(
            mover_mask[s][None, None, :, None], xy[:, None] + length[..., None] * d[..., :2],
            xy[:, None],
        )
        # The first feasible candidate, else the first (and the cycle is infeasible): the
        # candidates are checked in blocks, each block only for the trials that have none
        # yet (the same choice as checking all K at once, most trials need one block).
        best = np.zeros(n, int)
        found = np.zeros(n, bool)
        for b0 in range(0, K, CANDIDATE_BLOCK):
            todo = np.flatnonzero(~found)
            if todo.size == 0:
                break
            ok = formations_ok(world, cands[todo, b0 : b0 + CANDIDATE_BLOCK])
            has = ok.any(axis=1)
            best[todo[has]] = b0 + np.argmax(ok[has], axis=1)
            found[todo[has]] = True
        xy = cands[rows, best]
        feasible &= found
        xys.append(xy)
    xy_all = np.stack(xys, axis=1)  # (n, steps, 3, 2)
    R_b, p_b = body_frames(world.ground, xy_all, world.headings)
    mutual, over = observe(world, R_b, p_b, world.R_over, world.t_over)
    mutual = mutual + pixel_noise(world, rng, mutual.shape[:-1])
    over = over + pixel_noise(world, rng, over.shape[:-1])
    mutual[..., [0, 1, 2], [0, 1, 2], :] = np.nan
    dist = np.linalg.norm(p_b[:, starts + 1, movers] - p_b[:, starts, movers], axis=-1)
    odometry = dist * (1.0 + P["odometry_sigma_rel"] * rng.standard_normal(dist.shape))
    obs = {
        "mutual_pixels": mutual,
        "overhead_pixels": over,
        "odometry": odometry,
        "odometry_sigma": P["odometry_sigma_rel"] * odometry,
    }
    R0, p0 = R_b[:, 0, 0], p_b[:, 0, 0]
    truth = {
        "R_body": np.einsum("nba,nibc->niac", R0, R_b[:, -1]),
        "t_body": np.einsum("nba,nib->nia", R0, p_b[:, -1] - p0[:, None]),
        "R_cam": np.einsum("nba,bc->nac", R0, world.R_over),
        "t_cam": np.einsum("nba,nb->na", R0, world.t_over - p0),
    }
    return obs, truth, feasible


# ======================================================================================
# Peer: closed-form estimators.


def unproject_mutual(world, mutual_pixels):
    """Unit bearings `(..., steps, 3, 3, 3)` in the observers' body frames."""
    b_ptz = world.ptz.unproject(mutual_pixels[..., 0, :, :]) @ world.M_ptz.T
    b_omni = world.omni_pair.unproject(mutual_pixels[..., 1:, :, :]) @ world.M_omni.T
    return np.concatenate([b_ptz[..., None, :, :], b_omni], axis=-3)


def kabsch(a, b):
    """Rotations `R` minimizing `sum_i |R a_i - b_i|^2`, batched: `a`, `b` of shape
    `(..., pairs, 3)`; SVD with the determinant fix (proper rotations)."""
    H = np.einsum("...ia,...ib->...ab", a, b)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.swapaxes(-1, -2) @ U.swapaxes(-1, -2)))
    D = np.ones(U.shape[:-1])
    D[..., 2] = d
    return (Vt.swapaxes(-1, -2) * D[..., None, :]) @ U.swapaxes(-1, -2)


def angle(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def mutual_localization(u):
    """Three robots from their six bearings `u (..., 3, 3, 3)` (`u[i, j]`: i sees j, in i's
    body frame), in robot 0's frame, circumdiameter 1 (DESIGN §3, errata fixed): the side
    opposite vertex k is `sin psi_k`; each other robot's rotation by Kabsch on its two
    bearing pairs. Returns `R (..., 3, 3, 3)`, `p (..., 3, 3)`, `ok (...)`."""
    u = normalize(np.where(np.isfinite(u), u, 1.0))
    u01, u02, u10, u12, u20, u21 = (u[..., i, j, :] for i, j in
                                    ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)))  # fmt: skip
    psi = np.stack([angle(u01, u02), angle(u10, u12), angle(u20, u21)], -1)
    ok = (psi.min(-1) >= MIN_ANGLE) & (psi.max(-1) <= math.pi - MIN_ANGLE)
    s = np.sin(psi)
    p1 = s[..., 2, None] * u01  # |C1 C2| is opposite C3
    p2 = s[..., 1, None] * u02
    e12 = normalize(p2 - p1)
    # 1R2 maps 2T1 -> -1T2 and 2T3 -> 1T3 - 1T2 (Eq. 2); likewise 1R3.
    R1 = kabsch(np.stack([u10, u12], -2), np.stack([-u01, e12], -2))
    R2 = kabsch(np.stack([u20, u21], -2), np.stack([-u02, -e12], -2))
    R0 = np.broadcast_to(np.eye(3), R1.shape)
    p = np.stack([np.zeros_like(p1), p1, p2], -2)
    return np.stack([R0, R1, R2], -3), p, ok


def mutual_steps(world, bearings):
    """Mutual localization of every step about its reference robot: `R (n, steps, 3, 3, 3)`,
    `p (n, steps, 3, 3)` (robot order restored), `ok (n,)`."""
    refs = world.tables["refs"]
    perms = np.array([(r,) + tuple(i for i in range(3) if i != r) for r in refs])
    k = np.arange(len(refs))
    permuted = bearings[:, k[:, None, None], perms[:, :, None], perms[:, None, :]]
    R, p, ok = mutual_localization(permuted)
    back = np.argsort(perms, axis=1)
    return R[:, k[:, None], back], p[:, k[:, None], back], np.all(ok, axis=1)


def odometry_weights(obs):
    d, sigma = obs["odometry"], obs["odometry_sigma"]
    floor = 1e-9 + 1e-6 * np.max(np.abs(d), axis=-1, keepdims=True)
    return 1.0 / np.maximum(sigma, floor) ** 2


def sequential_chain(world, R_s, p_s, obs):
    """The sequential strategy: each formation joined to the previous one through its
    reference robot, the ratio of the shared pair's distances fixing its scale; one
    global scale by weighted least squares on the odometry. Returns metric
    `R (n, steps, 3, 3, 3)`, `p (n, steps, 3, 3)`, `ok (n,)`."""
    tb = world.tables
    R, p = [R_s[:, 0]], [p_s[:, 0]]
    for k in range(1, tb["steps"]):
        ref, mover = tb["refs"][k], int(tb["movers"][k - 1])
        shared = 3 - ref - mover
        chain = np.linalg.norm(p[-1][:, ref] - p[-1][:, shared], axis=-1)
        local = np.linalg.norm(p_s[:, k, ref] - p_s[:, k, shared], axis=-1)
        ratio = chain / np.where(local > 0, local, 1.0)
        R_ref, p_ref = R[-1][:, ref], p[-1][:, ref]
        R.append(R_ref[:, None] @ R_s[:, k])
        p.append(p_ref[:, None] + ratio[:, None, None] * (p_s[:, k] @ R_ref.swapaxes(-1, -2)))
    R, p = np.stack(R, 1), np.stack(p, 1)
    rows = np.arange(p.shape[0])[:, None]
    lengths = np.linalg.norm(
        p[rows, tb["starts"] + 1, tb["movers"]] - p[rows, tb["starts"], tb["movers"]], axis=-1
    )
    w, d = odometry_weights(obs), obs["odometry"]
    den = np.sum(w * lengths**2, axis=1)
    ok = den > 1e-12 * np.sum(w * d**2, axis=1)
    scale = np.sum(w * d * lengths, axis=1) / np.where(ok, den, 1.0)
    ok &= scale > 0
    return R, p * np.where(ok, scale, 1.0)[:, None, None, None], ok


def ratio_roots(pb, pa, d):
    """Candidate `s_after / s_before` for a concurrent move of C2 and C3 from `pb (n, 2, 3)`
    to `pa (n, 2, 3)` (unit-scale positions) over distances `d (n, 2)`: each robot gives
    `s_b^2 |pb|^2 - 2 s_b s_a pb.pa + s_a^2 |pa|^2 = d^2`; dividing by `d^2` and subtracting
    the two eliminates `s_b`: a quadratic in the ratio. Its two roots and 1 (the guess that
    the formation kept its size), `(n, 3)`, with a validity mask."""
    d2 = np.maximum(d**2, 1e-30)
    A = np.sum(pb * pb, -1) / d2
    B = np.sum(pb * pa, -1) / d2
    C = np.sum(pa * pa, -1) / d2
    a, b, c = C[:, 0] - C[:, 1], -2.0 * (B[:, 0] - B[:, 1]), A[:, 0] - A[:, 1]
    sq = np.sqrt(np.maximum(b * b - 4 * a * c, 0.0))
    q = -0.5 * (b + np.where(b >= 0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1, r2 = q / a, c / q
    roots = np.stack([r1, r2, np.ones_like(r1)], 1)
    valid = np.isfinite(roots) & (roots > 0.05) & (roots < 20.0)
    return np.where(valid, roots, 1.0), valid


def concurrent_lengths(s, P, tb):
    """Move lengths `(..., moves)` and the unit move directions for scales `s (..., 3)` of
    the three formations at unit-scale positions `P (..., 3, 3, 3)`."""
    a, r = tb["starts"], tb["movers"]
    end = s[..., a + 1, None] * P[..., a + 1, r, :]
    start = s[..., a, None] * P[..., a, r, :]
    diff = end - start
    length = np.linalg.norm(diff, axis=-1)
    return length, diff / np.maximum(length, 1e-300)[..., None]


def concurrent_scales(world, P, obs):
    """Scales of the three concurrent formations: candidates `(n, c, 3)` sorted by their
    odometry chi-square `(n, c)`, and a mask of the distinct ones worth checking.

    A simpler fit than jaxloc's (which also takes scale ratios from P3P poses of the
    overhead camera): every combination of the two moves' quadratic roots (and 1), the
    overall scale by weighted least squares, then 6 Gauss-Newton steps on the four odometry
    residuals (3 unknowns). The winner is picked later by odometry + overhead reprojection
    chi-square (`overhead_poses`)."""
    tb = world.tables
    d, w_abs = obs["odometry"], odometry_weights(obs)
    w = w_abs / w_abs.max(axis=1, keepdims=True)
    r01, ok01 = ratio_roots(P[:, 0, 1:], P[:, 1, 1:], d[:, :2])
    r12, ok12 = ratio_roots(P[:, 1, 1:], P[:, 2, 1:], d[:, 2:])
    i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    i, j = i.ravel(), j.ravel()
    rho = np.stack([np.ones((len(d), 9)), r01[:, i], r01[:, i] * r12[:, j]], -1)  # (n, 9, 3)
    valid = ok01[:, i] & ok12[:, j]
    Pc = P[:, None]
    q, _ = concurrent_lengths(rho, Pc, tb)
    s0 = np.sum(w[:, None] * d[:, None] * q, -1) / np.maximum(np.sum(w[:, None] * q * q, -1), 1e-30)
    s = rho * s0[..., None]
    a, r = tb["starts"], tb["movers"]
    sw = np.sqrt(w)[:, None]
    for _ in range(6):
        length, u = concurrent_lengths(s, Pc, tb)
        res = sw * (length - d[:, None])
        J = np.zeros(res.shape + (3,))
        m = np.arange(len(a))
        J[..., m, a + 1] = np.sum(u * Pc[..., a + 1, r, :], -1)
        J[..., m, a] = -np.sum(u * Pc[..., a, r, :], -1)
        J *= sw[..., None]
        H = np.einsum("...mi,...mj->...ij", J, J) + 1e-12 * np.eye(3)
        step = -np.linalg.solve(H, np.einsum("...mi,...m->...i", J, res)[..., None])[..., 0]
        s_new = s + step
        s = np.where(np.all(s_new > 0, -1, keepdims=True), s_new, s)
    length, _ = concurrent_lengths(s, Pc, tb)
    chi2 = np.sum(w_abs[:, None] * (length - d[:, None]) ** 2, -1)
    valid &= np.all(s > 0, -1) & np.isfinite(chi2)
    chi2 = np.where(valid, chi2, np.inf)
    order = np.argsort(chi2, axis=1)
    s, chi2, valid = (np.take_along_axis(x, order[..., None] if x.ndim == 3 else order, 1)
                      for x in (s, chi2, valid))  # fmt: skip
    # Distinct candidates, best first, within the odometry gate.
    keep = valid & (chi2 <= chi2[:, :1] + ODOMETRY_GATE)
    logs = np.log(np.where(valid[..., None], s, 1.0))
    for c in range(1, 9):
        gap = np.max(np.abs(logs[:, :c] - logs[:, c : c + 1]), -1)  # (n, c)
        keep[:, c] &= np.all((gap > DISTINCT_LOG_SCALE) | ~keep[:, :c], -1)
    keep &= np.cumsum(keep, 1) <= MAX_SCALE_CANDIDATES
    return s, chi2, keep


def solve_pnp(world, points, pixels):
    """`cv2.solvePnP` SQPnP on one problem: `(ok, rvec, tvec)` of `p_cam = R p + t`."""
    try:
        ok, rvec, tvec = cv2.solvePnP(points, pixels, world.K, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:  # degenerate input: a failed trial, not a crash
        ok = False
    if not ok or rvec is None or tvec is None:  # SQPnP found no solution
        return False, np.zeros(3), np.zeros(3)
    return True, rvec.reshape(3), tvec.reshape(3)


def overhead_poses(world, points, pixels, todo):
    """SQPnP for each problem `points (..., k, 3)`, `pixels (..., k, 2)` where `todo`: the
    camera's pose in the world `R_wc (..., 3, 3)`, `t_wc (..., 3)`, `ok (...)`, and the
    whitened reprojection chi-square `(...)`."""
    shape = todo.shape
    pts = np.ascontiguousarray(points.reshape((-1,) + points.shape[-2:]))
    pix = np.ascontiguousarray(pixels.reshape((-1,) + pixels.shape[-2:]))
    flat = todo.reshape(-1)
    rvec, tvec = np.zeros((flat.size, 3)), np.zeros((flat.size, 3))
    ok = np.zeros(flat.size, bool)
    idx = np.flatnonzero(flat)
    for i in idx:  # the Python loop a researcher would write
        ok[i], rvec[i], tvec[i] = solve_pnp(world, pts[i], pix[i])
    R_cw = so3_exp(rvec)
    # Reprojection chi-square of the solved problems only.
    p_cam = (pts[idx] @ R_cw[idx].swapaxes(-1, -2)) + tvec[idx, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (world.overhead.project(p_cam) - pix[idx]) / world.sigma_px
    chi2 = np.full(flat.size, np.inf)
    chi2[idx] = np.sum(r * r, axis=(-2, -1))
    ok[idx] &= np.all(p_cam[..., 2] > 0, -1)
    ok &= np.isfinite(chi2)
    R_wc = R_cw.swapaxes(-1, -2)
    t_wc = -(R_wc @ tvec[..., None])[..., 0]
    return (R_wc.reshape(shape + (3, 3)), t_wc.reshape(shape + (3,)), ok.reshape(shape),
            np.where(ok, chi2, np.inf).reshape(shape))  # fmt: skip


def placement_pixels(world, obs):
    """Overhead pixels of each distinct placement, averaged over its sightings."""
    over = obs["overhead_pixels"]
    return np.einsum("pk,nkc->npc", world.average, over.reshape(over.shape[0], -1, 2))


def closed_form(world, obs, todo):
    """The peer's closed-form estimate of every trial where `todo`: placements' poses
    `R (n, placements, 3, 3)`, `t (n, placements, 3)` (from each placement's first step:
    the overhead camera's points and the refinement's start), the ground robots' poses at
    the last step `R_end (n, 3, 3, 3)`, `t_end (n, 3, 3)` (what the cycle reports), and the
    overhead camera's `R_c`, `t_c`, in W, metric; `ok (n,)`."""
    n = obs["odometry"].shape[0]
    bearings = unproject_mutual(world, obs["mutual_pixels"])
    R_s, p_s, ok = mutual_steps(world, bearings)
    ok &= todo & np.all(np.isfinite(obs["odometry"]), 1)
    fk, fr = world.first[:, 0], world.first[:, 1]
    pixels = placement_pixels(world, obs)
    ok &= np.all(np.isfinite(pixels), axis=(1, 2))
    if world.strategy == "sequential":
        R, p, scale_ok = sequential_chain(world, R_s, p_s, obs)
        ok &= scale_ok
        R_pl, t_pl = R[:, fk, fr], p[:, fk, fr]
        R_end, t_end = R[:, -1], p[:, -1]
        R_c, t_c, pnp_ok, _ = overhead_poses(world, t_pl, pixels, ok)
        ok &= pnp_ok
    else:
        s, chi2_odo, keep = concurrent_scales(world, p_s, obs)
        keep &= ok[:, None]
        pts = s[:, :, fk, None] * p_s[:, None, fk, fr]  # (n, c, placements, 3)
        pix = np.broadcast_to(pixels[:, None], pts.shape[:-1] + (2,))
        R_cc, t_cc, pnp_ok, chi2_pix = overhead_poses(world, pts, pix, keep)
        score = np.where(keep & pnp_ok, chi2_odo + chi2_pix, np.inf)
        best = np.argmin(score, axis=1)
        rows = np.arange(n)
        ok &= np.isfinite(score[rows, best])
        R_pl, t_pl = R_s[:, fk, fr], pts[rows, best]
        last = world.tables["ids"][-1]
        R_end, t_end = R_pl[:, last], t_pl[:, last]
        R_c, t_c = R_cc[rows, best], t_cc[rows, best]
    return {"R": R_pl, "t": t_pl, "R_end": R_end, "t_end": t_end, "R_c": R_c, "t_c": t_c,
            "ok": ok}  # fmt: skip


# ======================================================================================
# Peer: joint refinement with scipy.optimize.least_squares (residuals vectorized per cycle).


class CycleModel:
    """Whitened residuals of one cycle and their analytic Jacobian, the measurement model
    of jaxloc's `refine_cycle`: every mutual pixel (in the observing camera, through its
    mount), every overhead pixel, every odometry distance, each divided by its sigma;
    missing (NaN) measurements get weight 0. Unknowns `x`: for placements 1, 2, ... and
    then the overhead camera, `(v, w)` with `t = t0 + v` and `R = R0 Exp(w)`; placement
    0 (C1 at the start) is the world frame."""

    def __init__(self, world):
        self.world = world
        ids = world.tables["ids"]
        steps = world.tables["steps"]
        k, i, j = (a.ravel() for a in np.meshgrid(np.arange(steps), np.arange(3), np.arange(3),
                                                  indexing="ij"))  # fmt: skip
        off = i != j
        self.mk, self.mi, self.mj = k[off], i[off], j[off]
        self.m_obs, self.m_tgt = ids[self.mk, self.mi], ids[self.mk, self.mj]
        self.is_ptz = self.mi == 0
        ko, jo = (a.ravel() for a in np.meshgrid(np.arange(steps), np.arange(3), indexing="ij"))
        self.ok_, self.oj = ko, jo
        self.o_tgt = ids[ko, jo]
        self.d_end = ids[world.tables["starts"] + 1, world.tables["movers"]]
        self.d_start = ids[world.tables["starts"], world.tables["movers"]]
        n_place = world.n_place
        self.n_x = 6 * n_place  # placements 1.. and the overhead camera
        # Column offset of each placement's block; placement 0 (the gauge) goes to a dummy
        # block past the end that is dropped.
        self.col = np.concatenate([[self.n_x], 6 * np.arange(n_place - 1)])
        self.col_over = 6 * (n_place - 1)
        nm, no = len(self.mk), len(ko)
        self.n_res = 2 * nm + 2 * no + len(self.d_end)
        omni = world.omni_pair
        sel = self.mi[~self.is_ptz] - 1
        self.omni_rows = Omni(
            *(np.asarray(getattr(omni, a))[sel, 0] for a in ("xi", "fx", "fy", "cx", "cy", "s")),
            omni.emin, omni.emax, (omni.w, omni.h),
        )
        self.M = np.where(self.is_ptz[:, None, None], world.M_ptz, world.M_omni)
        self._cache = None

    def data(self, obs, n):
        """Per-trial measurements and weights of trial `n` of a batch `obs`."""
        mp = obs["mutual_pixels"][n][self.mk, self.mi, self.mj]
        op = obs["overhead_pixels"][n][self.ok_, self.oj]
        d, sd = obs["odometry"][n], obs["odometry_sigma"][n]
        m_ok, o_ok = np.all(np.isfinite(mp), -1), np.all(np.isfinite(op), -1)
        d_ok = np.isfinite(d) & np.isfinite(sd)
        floor = 1e-9 + 1e-6 * np.max(np.abs(np.where(d_ok, d, 0.0)))
        s_px = max(self.world.sigma_px, 1e-6)
        return {
            "mp": np.where(m_ok[:, None], mp, 0.0), "mw": np.where(m_ok, 1.0 / s_px, 0.0),
            "op": np.where(o_ok[:, None], op, 0.0), "ow": np.where(o_ok, 1.0 / s_px, 0.0),
            "d": np.where(d_ok, d, 0.0),
            "dw": np.where(d_ok, 1.0 / np.maximum(np.where(d_ok, sd, 0.0), floor), 0.0),
        }  # fmt: skip

    def poses(self, x, start):
        R0, t0, Rc0, tc0 = start
        d = x[: self.col_over].reshape(-1, 6)
        R = np.concatenate([R0[:1], R0[1:] @ so3_exp(d[:, 3:])])
        t = np.concatenate([t0[:1], t0[1:] + d[:, :3]])
        return R, t, Rc0 @ so3_exp(x[-3:]), tc0 + x[-6:-3]

    def forward(self, x, start, data):
        """Residuals `(m,)` at `x` and what the Jacobian needs (cached by `x`: scipy asks
        for the residuals, then the Jacobian, at the same point)."""
        key = x.tobytes()
        if self._cache is not None and self._cache[0] == key and self._cache[1] is data:
            return self._cache[2]
        w = self.world
        R, t, Rc, tc = self.poses(x, start)
        # Mutual sightings: q = R_a^T (t_b - t_a) in the observer's body frame, then the
        # camera frame M^T q.
        Ra = R[self.m_obs]
        q = np.einsum("mba,mb->ma", Ra, t[self.m_tgt] - t[self.m_obs])
        cam = np.einsum("mba,mb->ma", self.M, q)
        uv = np.empty(q.shape[:-1] + (2,))
        uv[self.is_ptz] = w.ptz.project(cam[self.is_ptz])
        uv[~self.is_ptz] = self.omni_rows.project(cam[~self.is_ptz])
        r_m = data["mw"][:, None] * (uv - data["mp"])
        # Overhead sightings: q = Rc^T (t_b - tc).
        qo = (t[self.o_tgt] - tc) @ Rc
        r_o = data["ow"][:, None] * (w.overhead.project(qo) - data["op"])
        # Odometry.
        diff = t[self.d_end] - t[self.d_start]
        length = np.linalg.norm(diff, axis=-1)
        r_d = data["dw"] * (length - data["d"])
        r = np.concatenate([r_m.ravel(), r_o.ravel(), r_d])
        out = {"r": r, "Ra": Ra, "q": q, "cam": cam, "Rc": Rc, "qo": qo, "diff": diff,
               "length": length}  # fmt: skip
        self._cache = (key, data, out)
        return out

    def residuals(self, x, start, data):
        return self.forward(x, start, data)["r"]

    def jacobian(self, x, start, data):
        """Analytic Jacobian `(m, n_x)` at `x` (chain rule through each sighting's two
        poses, as jaxloc's `_cycle_model`)."""
        f = self.forward(x, start, data)
        w = self.world
        q, cam, Ra, Rc, qo = f["q"], f["cam"], f["Ra"], f["Rc"], f["qo"]
        Jc = np.empty(q.shape[:-1] + (2, 3))
        _, Jc[self.is_ptz] = w.ptz.project_jacobian(cam[self.is_ptz])
        _, Jc[~self.is_ptz] = self.omni_rows.project_jacobian(cam[~self.is_ptz])
        JqM = data["mw"][:, None, None] * (Jc @ self.M.swapaxes(-1, -2))  # d r / d q
        RaT = Ra.swapaxes(-1, -2)
        Jr_all = so3_right_jacobian(np.concatenate([x[: self.col_over].reshape(-1, 6)[:, 3:],
                                                    x[None, -3:]]))  # fmt: skip
        Jr_place = np.concatenate([np.eye(3)[None], Jr_all[:-1]])
        obs_v = -JqM @ RaT
        obs_w = JqM @ skew(q) @ Jr_place[self.m_obs]
        tgt_v = JqM @ RaT
        _, Jo = w.overhead.project_jacobian(qo)
        Jo = data["ow"][:, None, None] * Jo
        cam_v = -Jo @ Rc.T
        cam_w = Jo @ skew(qo) @ Jr_all[-1]
        pt_v = Jo @ Rc.T
        u = f["diff"] / np.maximum(f["length"], 1e-300)[:, None]
        # Assemble (one extra block of columns for the gauge, dropped at the end).
        nm, no = len(self.mk), len(self.o_tgt)
        J = np.zeros((self.n_res, self.n_x + 6))
        rows_m = np.arange(2 * nm).reshape(nm, 2)[:, :, None]
        c_obs = self.col[self.m_obs][:, None, None] + np.arange(3)
        c_tgt = self.col[self.m_tgt][:, None, None] + np.arange(3)
        J[rows_m, c_obs] = obs_v
        J[rows_m, c_obs + 3] = obs_w
        J[rows_m, c_tgt] = tgt_v
        rows_o = 2 * nm + np.arange(2 * no).reshape(no, 2)[:, :, None]
        J[rows_o, self.col_over + np.arange(3)] = cam_v
        J[rows_o, self.col_over + 3 + np.arange(3)] = cam_w
        J[rows_o, self.col[self.o_tgt][:, None, None] + np.arange(3)] = pt_v
        rows_d = (2 * nm + 2 * no + np.arange(len(self.d_end)))[:, None]
        dw = data["dw"][:, None]
        J[rows_d, self.col[self.d_end][:, None] + np.arange(3)] += dw * u
        J[rows_d, self.col[self.d_start][:, None] + np.arange(3)] -= dw * u
        return J[:, : self.n_x]


def refine(model, est, obs, todo, *, method, jac="analytic"):
    """`scipy.optimize.least_squares` on every trial where `todo`, from the closed form
    `est`; a Python loop over the trials. Returns the refined estimate (same layout)."""
    out = {k: v.copy() for k, v in est.items()}
    out["ok"] = np.zeros_like(est["ok"])
    out["nfev"] = np.zeros(len(todo), int)
    out["cost"] = np.full(len(todo), np.nan)
    x0 = np.zeros(model.n_x)
    for n in np.flatnonzero(todo):
        start = (est["R"][n], est["t"][n], est["R_c"][n], est["t_c"][n])
        data = model.data(obs, n)
        kw = {"jac": model.jacobian} if jac == "analytic" else {"jac": "2-point"}
        sol = scipy.optimize.least_squares(
            model.residuals, x0, method=method, args=(start, data), **kw
        )
        R, t, Rc, tc = model.poses(sol.x, start)
        out["R"][n], out["t"][n], out["R_c"][n], out["t_c"][n] = R, t, Rc, tc
        last = model.world.tables["ids"][-1]
        out["R_end"][n], out["t_end"][n] = R[last], t[last]
        out["ok"][n] = sol.status > 0 and np.all(np.isfinite(sol.x))
        out["nfev"][n], out["cost"][n] = sol.nfev, 2.0 * sol.cost
    return out


# ======================================================================================
# Peer: scoring and the whole trial.


def score(world, est, truth):
    """Errors of the end-of-cycle poses of (C, C1, C2, C3): position `(n, 4)` (m), rotation
    `(n, 4)` (rad), position vector estimate - truth `(n, 4, 3)` (m)."""
    R_e = np.concatenate([est["R_c"][:, None], est["R_end"]], 1)
    t_e = np.concatenate([est["t_c"][:, None], est["t_end"]], 1)
    R_t = np.concatenate([truth["R_cam"][:, None], truth["R_body"]], 1)
    t_t = np.concatenate([truth["t_cam"][:, None], truth["t_body"]], 1)
    vec = t_e - t_t
    rot = rotation_angle(R_e.swapaxes(-1, -2) @ R_t)
    return np.linalg.norm(vec, axis=-1), rot, vec


def whole_trial(params, n, seed, refined, method, batch=1024):
    """The peer's whole trial, `n` trials in batches: simulate, estimate, (refine), score.
    Returns the seconds and the errors (the peer's own accuracy on its own trials)."""
    cv2.setNumThreads(1)
    world = World(params)
    model = CycleModel(world)
    rng = np.random.default_rng(seed)
    errors = {"position": [], "rotation": [], "ok": [], "feasible": []}
    t0, c0 = time.perf_counter(), time.process_time()
    for start in range(0, n, batch):
        m = min(batch, n - start)
        obs, truth, feasible = simulate(world, rng, m)
        est = closed_form(world, obs, feasible)
        if refined:
            est = refine(model, est, obs, est["ok"], method=method)
        pos, rot, _ = score(world, est, truth)
        errors["position"].append(pos)
        errors["rotation"].append(rot)
        errors["ok"].append(est["ok"])
        errors["feasible"].append(feasible)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    return seconds, cpu, {k: np.concatenate(v) for k, v in errors.items()}


def _whole_trial_task(args):
    return whole_trial(*args)


def whole_trial_parallel(pool, processes, params, n, seed, refined, method):
    """The same, `n` trials split over `processes` worker processes (one per core): the
    Monte Carlo a researcher would run with `multiprocessing`. Wall-clock seconds and the
    workers' CPU seconds."""
    share = [n // processes + (i < n % processes) for i in range(processes)]
    tasks = [(params, share[i], seed + 1000 * (i + 1), refined, method) for i in range(processes)]
    t0 = time.perf_counter()
    results = pool.map(_whole_trial_task, tasks)
    seconds = time.perf_counter() - t0
    errors = {k: np.concatenate([r[2][k] for r in results]) for k in results[0][2]}
    return seconds, sum(r[1] for r in results), errors


# ======================================================================================
# JAXLOC SIDE: every call into jaxloc is in this function. It reads the scenario's
# parameters for the peer, projects check points through jaxloc's cameras, simulates the
# shared trials, and times and scores jaxloc's studies. (When `refine_cycle` takes a
# `Rig`, only `run_study`'s internals change; nothing here calls `refine_cycle` directly.)


def jaxloc_side(strategy, seed, n_trials, check_seed=12345):
    import jax
    import jax.numpy as jnp
    import jaxloc

    sc = jaxloc.Scenario.paper(strategy)
    f = lambda x: float(np.asarray(x))  # noqa: E731
    assert type(sc.ground) is jaxloc.SaddleSurface and type(sc.ceiling) is jaxloc.SinusoidSurface
    assert sc.moves is None and sc.initial_xy is None
    for cam in (sc.overhead, sc.ptz):
        assert not np.any(np.asarray(cam.dist)), "the peer's pinhole has no distortion"
    assert f(sc.ptz.pan) == 0 and f(sc.ptz.tilt) == 0, "the peer's PTZ is at pan = tilt = 0"
    ptz = sc.ptz.pinhole()

    def omni(c):
        assert not np.any(np.asarray(c.dist)), "the peer's omni model has no distortion"
        return {
            "xi": f(c.xi), "fx": f(c.fx), "fy": f(c.fy), "cx": f(c.cx), "cy": f(c.cy),
            "skew": f(c.skew), "elevation_min": f(c.elevation_min),
            "elevation_max": f(c.elevation_max), "image_size": tuple(c.image_size),
        }  # fmt: skip

    def pinhole(c):
        return {"fx": f(c.fx), "fy": f(c.fy), "cx": f(c.cx), "cy": f(c.cy),
                "image_size": tuple(c.image_size)}  # fmt: skip

    g, c = sc.ground, sc.ceiling
    params = {
        "strategy": strategy,
        "ground": ("saddle", {"radius_x": f(g.radius_x), "radius_y": f(g.radius_y), "z0": f(g.z0)}),
        "ceiling": ("sinusoid", {"z0": f(c.z0), "amplitude": f(c.amplitude),
                                 "period": f(c.period), "phase": f(c.phase)}),  # fmt: skip
        "formation_xy": np.asarray(sc.formation_xy(), float),
        "headings": np.asarray(sc.headings, float),
        "overhead_xy": np.asarray(sc.overhead_xy, float),
        "overhead_heading": f(sc.overhead_heading),
        "overhead": pinhole(sc.overhead), "ptz": pinhole(ptz),
        "omni2": omni(sc.omni2), "omni3": omni(sc.omni3),
        "move_mean": f(sc.move_mean), "move_std": f(sc.move_std),
        "min_separation": f(sc.min_separation), "pixel_sigma": f(sc.pixel_sigma),
        "odometry_sigma_rel": f(sc.odometry_sigma_rel),
        "move_candidates": int(sc.move_candidates), "noise_model": sc.noise_model,
        "require_overhead": sc.require_overhead, "require_ptz": sc.require_ptz,
        "require_omni": sc.require_omni,
        "R_BODY_PTZ": np.asarray(jaxloc.R_BODY_PTZ), "R_BODY_OMNI": np.asarray(jaxloc.R_BODY_OMNI),
        "R_BODY_OVERHEAD": np.asarray(jaxloc.R_BODY_OVERHEAD),
    }  # fmt: skip
    tables = {
        "ids": np.asarray(jaxloc.placement_ids(strategy)),
        "movers": np.asarray(jaxloc.moving_robot(strategy)),
        "starts": np.asarray(jaxloc.move_start_step(strategy)),
        "steps": jaxloc.num_steps(strategy),
    }

    # Check points through jaxloc's cameras (points in each camera's frame, in its view).
    rng = np.random.default_rng(check_seed)
    m = 2000
    z = rng.uniform(0.3, 6.0, m)
    pin_pts = np.stack([rng.uniform(-0.45, 0.45, m) * z, rng.uniform(-0.35, 0.35, m) * z, z], -1)
    az = rng.uniform(-np.pi, np.pi, m)
    el = rng.uniform(np.radians(-12.0), np.radians(32.0), m)
    r = rng.uniform(0.3, 6.0, m)
    ce = np.cos(el)
    omni_pts = r[:, None] * np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], -1)
    checks = {}
    cams = (("overhead", sc.overhead, pin_pts), ("ptz", sc.ptz, pin_pts),
            ("omni2", sc.omni2, omni_pts), ("omni3", sc.omni3, omni_pts))  # fmt: skip
    for name, cam, pts in cams:
        uv = np.asarray(cam.project(jnp.asarray(pts)))
        checks[name] = (pts, uv, np.asarray(cam.unproject(jnp.asarray(uv))))

    # The shared trials: jaxloc's simulator, keys `trial_key(seed, i)` as in `run_study`.
    t0 = time.perf_counter()
    sim = jax.jit(jax.vmap(lambda i: jaxloc.simulate_cycle(sc, jaxloc.trial_key(seed, i))))
    truth, obs, feasible = sim(jnp.arange(n_trials))
    jax.block_until_ready(obs)
    sim_seconds = time.perf_counter() - t0
    wx = lambda T: np.asarray(T.wxyz_xyz, float)  # noqa: E731
    T_body, T_cam = wx(truth.poses.T_world_body), wx(truth.poses.T_world_overhead)
    shared = {
        "obs": {
            "mutual_pixels": np.asarray(obs.mutual_pixels, float),
            "overhead_pixels": np.asarray(obs.overhead_pixels, float),
            "odometry": np.asarray(obs.odometry, float),
            "odometry_sigma": np.asarray(obs.odometry_sigma, float),
        },
        "mutual_bearings": np.asarray(obs.mutual, float),
        "truth_all_steps": {"R": quat_to_matrix(T_body[..., :4]), "t": T_body[..., 4:]},
        "truth": {
            "R_body": quat_to_matrix(T_body[:, -1, :, :4]), "t_body": T_body[:, -1, :, 4:],
            "R_cam": quat_to_matrix(T_cam[:, :4]), "t_cam": T_cam[:, 4:],
        },
        "feasible": np.asarray(feasible, bool),
    }  # fmt: skip

    # Studies: a warm-up chunk of each compiles it (timed as "first chunk"); `study` then
    # runs the shared trials, timed (the caller repeats it; the numbers are the same).
    chunk = jaxloc.balanced_chunk_size(n_trials)
    first_chunk_s = {}
    for methods in (("robust",), ("robust", "refined")):
        t0 = time.perf_counter()
        jaxloc.run_chunk(sc, seed + 1, 0, chunk, methods)
        first_chunk_s["+".join(methods)] = time.perf_counter() - t0

    def study(methods):
        t0, c0 = time.perf_counter(), time.process_time()
        out = jaxloc.run_study(sc, n_trials, seed=seed, chunk_size=chunk, methods=methods,
                               progress=False)  # fmt: skip
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        keys = ("status", "position", "rotation", "position_vector")
        return seconds, cpu, {k: out[k] for k in keys}

    return {
        "study": study,
        "chunk_size": chunk,
        "first_chunk_s": first_chunk_s,
        "params": params,
        "tables": tables,
        "camera_checks": checks,
        "shared": shared,
        "simulate_compile_and_run_s": sim_seconds,
        "devices": jax.device_count(),
        "status_names": jaxloc.status_names(),
    }


# ======================================================================================
# Report.


def stats(x):
    x = np.asarray(x, float)
    if x.size == 0:
        return {"n": 0, "median": None, "rmse": None, "p90": None}
    return {
        "n": int(x.size),
        "median": float(np.median(x)),
        "rmse": float(np.sqrt(np.mean(x * x))),
        "p90": float(np.percentile(x, 90)),
    }


def accuracy(errors, sets):
    """Per method, per trial set, per camera: position (m) and rotation (rad) stats."""
    out = {}
    for method, e in errors.items():
        out[method] = {}
        for set_name, mask in sets.items():
            m = mask(method)
            out[method][set_name] = {
                "n_trials": int(m.sum()),
                "cameras": {
                    cam: {"position_m": stats(e["position"][m, ci]),
                          "rotation_rad": stats(e["rotation"][m, ci])}  # fmt: skip
                    for ci, cam in enumerate(CAMERAS)
                },
            }
    return out


def check_cameras(world, checks):
    """The peer's cameras vs jaxloc's on the same points: max pixel and bearing gaps."""
    cams = {"overhead": world.overhead, "ptz": world.ptz, "omni2": world.omni[0],
            "omni3": world.omni[1]}  # fmt: skip
    out = {}
    for name, (pts, uv, b) in checks.items():
        cam = cams[name]
        uv_peer = cam.project(pts)
        _, J = cam.project_jacobian(pts)
        du = np.max(np.abs(uv_peer - uv))
        db = np.max(np.abs(cam.unproject(uv) - b))
        # The analytic projection Jacobian vs central differences.
        h = 1e-6
        J_fd = np.stack([(cam.project(pts + h * e) - cam.project(pts - h * e)) / (2 * h)
                         for e in np.eye(3)], -1)  # fmt: skip
        dj = np.max(np.abs(J - J_fd) / (1.0 + np.abs(J_fd)))
        out[name] = {"max_pixel_gap_px": float(du), "max_bearing_gap": float(db),
                     "max_jacobian_gap_rel": float(dj), "points": int(len(pts))}  # fmt: skip
        assert du <= 1e-9, f"{name}: peer project differs from jaxloc's by {du:.3g} px"
        assert db <= 1e-12, f"{name}: peer unproject differs from jaxloc's by {db:.3g}"
        assert dj <= 1e-6, f"{name}: analytic projection Jacobian off by {dj:.3g}"
    return out


def check_model(world, model, shared, est):
    """The peer's measurement model at jaxloc's true poses vs jaxloc's noisy pixels (the
    gap must be the noise alone), and the cycle Jacobian vs finite differences."""
    obs, tr = shared["obs"], shared["truth_all_steps"]
    feas = shared["feasible"]
    # Every pose in W: the ground robots' true body frames at every step, the camera's.
    R_b, p_b = tr["R"][feas], tr["t"][feas]
    R_c, t_c = shared["truth"]["R_cam"][feas], shared["truth"]["t_cam"][feas]
    mutual, over = observe(world, R_b, p_b, R_c, t_c)
    gap_m = (mutual - obs["mutual_pixels"][feas])[..., ~np.eye(3, dtype=bool), :]
    gap_o = over - obs["overhead_pixels"][feas]
    gaps = np.concatenate([gap_m.reshape(-1, 2), gap_o.reshape(-1, 2)])
    rms = float(np.sqrt(np.mean(gaps**2)))
    # The unprojected pixels vs jaxloc's bearings.
    b = unproject_mutual(world, obs["mutual_pixels"])
    off = ~np.eye(3, dtype=bool)
    db = float(np.nanmax(np.abs(b - shared["mutual_bearings"])[..., off, :]))
    assert db <= 1e-12, f"peer bearings differ from jaxloc's by {db:.3g}"
    assert abs(rms / world.sigma_px - 1.0) < 0.1, f"pixel gap RMS {rms:.3f} px"
    # Jacobian vs central differences at a perturbed point, a few trials.
    rng = np.random.default_rng(0)
    worst = 0.0
    for n in np.flatnonzero(est["ok"])[:5]:
        start = (est["R"][n], est["t"][n], est["R_c"][n], est["t_c"][n])
        data = model.data(obs, n)
        x = 1e-2 * rng.standard_normal(model.n_x)
        J = model.jacobian(x, start, data).copy()
        h = 1e-6
        J_fd = np.stack([(model.residuals(x + h * e, start, data)
                          - model.residuals(x - h * e, start, data)) / (2 * h)
                         for e in np.eye(model.n_x)], -1)  # fmt: skip
        worst = max(worst, float(np.max(np.abs(J - J_fd)) / (1.0 + np.max(np.abs(J_fd)))))
    assert worst < 1e-6, f"analytic cycle Jacobian off by {worst:.3g}"
    return {
        "pixel_gap_rms_px": rms,
        "expected_rms_px": world.sigma_px,
        "max_bearing_gap": db,
        "cycle_jacobian_gap_rel": worst,
    }


def best_of(runs, n):
    """Rates of repeated runs `[(seconds, cpu_seconds), ...]` of `n` trials: the best (the
    machine is shared: other load only slows a run down) and all of them."""
    return {
        "trials_per_s": n / min(r[0] for r in runs),
        "trials_per_cpu_s": n / min(r[1] for r in runs),
        "all_trials_per_s": [n / r[0] for r in runs],
        "all_trials_per_cpu_s": [n / r[1] for r in runs],
    }


def timing_rounds(strategy, args, js, pool, processes):
    """Speed of both pipelines, jaxloc's study and the peer's whole trial (its own simulation
    + estimators + scoring; in one process and in `processes`), in `args.repeats` rounds
    that interleave them, so both sample the same load; the best run of each is kept.
    Returns `(studies, whole, jaxloc_errors)`: jaxloc's errors on the shared trials come
    from its first ("robust", "refined") study (every repeat computes the same numbers)."""
    params, n, seed = js["params"], args.trials, args.seed
    n_whole = {False: n, True: args.whole_refined_trials or max(256, n // 4)}
    runs = {(m, p): [] for m in ("closed form", "closed form + refinement")
            for p in ("jaxloc", "peer x1", "peer xP")}  # fmt: skip
    jaxloc_errors, own = None, {}
    for r in range(args.repeats):
        print(f"== {strategy}: timing round {r + 1} of {args.repeats}", flush=True)
        for refined, methods in ((False, ("robust",)), (True, ("robust", "refined"))):
            label = "closed form + refinement" if refined else "closed form"
            m = n_whole[refined]
            mark(f"{strategy}: round {r + 1}, {label}: jaxloc start")
            seconds, cpu, errors = js["study"](methods)
            runs[label, "jaxloc"].append((seconds, cpu))
            if refined and jaxloc_errors is None:
                jaxloc_errors = errors
            mark(f"{strategy}: round {r + 1}, {label}: peer x1 start")
            seconds, cpu, e = whole_trial(params, m, seed + 7, refined, args.scipy_method)
            runs[label, "peer x1"].append((seconds, cpu))
            own[label] = e
            if pool is not None:
                mark(f"{strategy}: round {r + 1}, {label}: peer x{processes} start")
                seconds, cpu, _ = whole_trial_parallel(pool, processes, params, m, seed + 11,
                                                       refined, args.scipy_method)  # fmt: skip
                runs[label, "peer xP"].append((seconds, cpu))
            mark(f"{strategy}: round {r + 1}, {label}: end")
            rates = [f"jaxloc {n / runs[label, 'jaxloc'][-1][0]:,.0f}/s"]
            rates += [f"{p} {m / runs[label, p][-1][0]:,.0f}/s" for p in ("peer x1", "peer xP")
                      if runs[label, p]]  # fmt: skip
            print(f"  {label}: " + ", ".join(rates), flush=True)
    studies, whole = {}, {}
    for refined, methods in ((False, ("robust",)), (True, ("robust", "refined"))):
        label = "closed form + refinement" if refined else "closed form"
        m = n_whole[refined]
        studies["+".join(methods)] = {
            "methods": list(methods), "trials": n, "chunk_size": js["chunk_size"],
            "first_chunk_s": js["first_chunk_s"]["+".join(methods)],
            **best_of(runs[label, "jaxloc"], n),
        }  # fmt: skip
        row = {"trials": m}
        for p, key in (("peer x1", "1_process"), ("peer xP", f"{processes}_processes")):
            if runs[label, p]:
                b = best_of(runs[label, p], m)
                row.update({f"trials_per_s_{key}": b["trials_per_s"],
                            f"trials_per_cpu_s_{key}": b["trials_per_cpu_s"],
                            f"all_trials_per_s_{key}": b["all_trials_per_s"],
                            f"all_trials_per_cpu_s_{key}": b["all_trials_per_cpu_s"]})  # fmt: skip
        e = own[label]
        ok = e["ok"] & e["feasible"]
        row["feasible_fraction"] = float(e["feasible"].mean())
        row["ok_fraction"] = float(ok.mean())
        row["own_accuracy"] = {cam: {"position_m": stats(e["position"][ok, ci]),
                                     "rotation_rad": stats(e["rotation"][ok, ci])}
                               for ci, cam in enumerate(CAMERAS)}  # fmt: skip
        whole[label] = row
    return studies, whole, jaxloc_errors


def run_strategy(strategy, args, pool, processes):
    seed = args.seed
    n = args.trials
    print(f"\n== {strategy}: jaxloc side ({n} trials, seed {seed})", flush=True)
    js = jaxloc_side(strategy, seed, n)
    params, shared = js["params"], js["shared"]
    world = World(params)
    for k in ("ids", "movers", "starts", "steps"):
        assert np.array_equal(world.tables[k], js["tables"][k]), f"strategy table {k} differs"
    camera_checks = check_cameras(world, js["camera_checks"])
    model = CycleModel(world)
    print(f"  jaxloc first chunks (compile + run): {js['first_chunk_s']}", flush=True)

    # Peer estimators alone on jaxloc's observations.
    print("== peer estimators on the shared observations", flush=True)
    obs, feas = shared["obs"], shared["feasible"]
    mark(f"{strategy}: peer estimators start")
    t0, c0 = time.perf_counter(), time.process_time()
    est = closed_form(world, obs, feas)
    t_closed, c_closed = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    ref = refine(model, est, obs, est["ok"], method=args.scipy_method)
    t_refine, c_refine = time.perf_counter() - t0, time.process_time() - c0
    model_check = check_model(world, model, shared, est)
    n_fd = min(n, args.fd_trials)
    sub = np.zeros(n, bool)
    sub[np.flatnonzero(est["ok"])[:n_fd]] = True
    t0 = time.perf_counter()
    ref_fd = refine(model, est, obs, sub, method=args.scipy_method, jac="2-point")
    t_fd = time.perf_counter() - t0
    n_sub = int(sub.sum())
    fd_gap = np.max(np.abs(ref_fd["t"][sub] - ref["t"][sub])) if n_sub else float("nan")
    # The other scipy method on the same subset, for the record.
    other = "lm" if args.scipy_method == "trf" else "trf"
    t0 = time.perf_counter()
    ref_other = refine(model, est, obs, sub, method=other)
    t_other = time.perf_counter() - t0
    other_gap = np.max(np.abs(ref_other["t"][sub] - ref["t"][sub])) if n_sub else float("nan")
    mark(f"{strategy}: peer estimators end")
    peer_alone = {
        "closed_form": {"seconds": t_closed, "trials_per_s": n / t_closed,
                        "trials_per_cpu_s": n / c_closed},
        "closed_form_plus_refinement": {
            "seconds": t_closed + t_refine, "trials_per_s": n / (t_closed + t_refine),
            "trials_per_cpu_s": n / (c_closed + c_refine),
            "refinement_only_cycles_per_s": int(est["ok"].sum()) / t_refine,
            "jacobian": "analytic", "method": args.scipy_method,
            "nfev_median": float(np.median(ref["nfev"][est["ok"]])),
            "nfev_max": int(ref["nfev"][est["ok"]].max()),
        },
        "refinement_finite_differences": {
            "cycles": n_sub, "cycles_per_s": n_sub / t_fd if n_sub else None,
            "jacobian": "'2-point'", "method": args.scipy_method,
            "max_position_gap_vs_analytic_m": float(fd_gap),
            "nfev_median": float(np.median(ref_fd["nfev"][sub])) if n_sub else None,
        },
        f"refinement_method_{other}": {
            "cycles": n_sub, "cycles_per_s": n_sub / t_other if n_sub else None,
            "jacobian": "analytic", "method": other,
            "max_position_gap_vs_main_m": float(other_gap),
        },
    }  # fmt: skip
    print(f"  peer closed form {n / t_closed:,.0f} trials/s; + refinement "
          f"{n / (t_closed + t_refine):,.0f} trials/s (scipy {args.scipy_method}, analytic "
          f"jac); FD jac {n_sub / t_fd:,.1f} cycles/s", flush=True)  # fmt: skip

    studies, whole, jx = timing_rounds(strategy, args, js, pool, processes)

    # Accuracy on the shared trials.
    errors = {}
    for name, e in (("peer closed form", est), ("peer refined", ref)):
        pos, rot, vec = score(world, e, shared["truth"])
        errors[name] = {"position": pos, "rotation": rot, "vector": vec, "ok": e["ok"] & feas}
    for mi, name in enumerate(("jaxloc robust", "jaxloc refined")):
        errors[name] = {
            "position": jx["position"][:, mi], "rotation": jx["rotation"][:, mi],
            "vector": jx["position_vector"][:, mi], "ok": (jx["status"][:, mi] == 0) & feas,
        }  # fmt: skip
    common = feas.copy()
    for e in errors.values():
        common &= e["ok"]
    sets = {
        "own_successes": lambda m: errors[m]["ok"],
        "common": lambda m: common,
    }
    acc = accuracy(errors, sets)
    names = js["status_names"]
    failures = {}
    for mi, name in enumerate(("jaxloc robust", "jaxloc refined")):
        codes, counts = np.unique(jx["status"][feas, mi], return_counts=True)
        failures[name] = {names.get(int(c), str(int(c))): int(k) for c, k in zip(codes, counts)
                          if c != 0}  # fmt: skip
    for name in ("peer closed form", "peer refined"):
        failures[name] = {"failed": int((feas & ~errors[name]["ok"]).sum())}

    def agreement(a, b):
        both = errors[a]["ok"] & errors[b]["ok"]
        gap = np.max(np.linalg.norm(errors[a]["vector"][both] - errors[b]["vector"][both],
                                    axis=-1), axis=-1)  # fmt: skip
        dpos = np.abs(errors[a]["position"][both] - errors[b]["position"][both])
        return {
            "trials": int(both.sum()),
            "max_position_gap_m": {"median": float(np.median(gap)) if gap.size else None,
                                   "p99": float(np.percentile(gap, 99)) if gap.size else None,
                                   "max": float(gap.max()) if gap.size else None},  # fmt: skip
            "fraction_same_minimum": float(np.mean(gap < SAME_MINIMUM_M)) if gap.size else None,
            "fraction_within_1mm": float(np.mean(gap < 1e-3)) if gap.size else None,
            "trials_different_minimum": int(np.sum(gap >= SAME_MINIMUM_M)),
            # Of those, where the first estimator's C is farther from the truth.
            "different_and_first_worse_on_C": int(np.sum(
                (gap >= SAME_MINIMUM_M)
                & (errors[a]["position"][both, 0] > errors[b]["position"][both, 0])
            )),
            "max_abs_error_difference_m": float(dpos.max()) if dpos.size else None,
        }

    agree = {
        "peer refined vs jaxloc refined": agreement("peer refined", "jaxloc refined"),
        "peer closed form vs jaxloc robust": agreement("peer closed form", "jaxloc robust"),
    }
    # The peer's chi-square (whitened cost) where the refinements agree and where they
    # differ: a wrong minimum shows in its cost (the peer runs no fit test; jaxloc flags a
    # chi-square above its 99.9% quantile as `inconsistent_fit`).
    both = errors["peer refined"]["ok"] & errors["jaxloc refined"]["ok"]
    diff = errors["peer refined"]["vector"] - errors["jaxloc refined"]["vector"]
    gap = np.max(np.linalg.norm(diff, axis=-1), axis=-1)
    chi2 = ref["cost"]
    same = gap < SAME_MINIMUM_M
    for label, sel in (("same", both & same), ("different", both & ~same)):
        agree["peer refined vs jaxloc refined"][f"peer_chi2_on_{label}_minimum"] = (
            {"median": float(np.median(chi2[sel])), "max": float(np.max(chi2[sel]))}
            if sel.any() else None
        )
    # The ground robots' closed forms are the same method (chain / mutual localization):
    # their positions should agree to rounding for the sequential strategy.
    both = errors["peer closed form"]["ok"] & errors["jaxloc robust"]["ok"]
    g = np.abs(errors["peer closed form"]["vector"][both, 1:]
               - errors["jaxloc robust"]["vector"][both, 1:])  # fmt: skip
    agree["ground robots, closed forms: max position gap m"] = float(g.max()) if g.size else None
    a = agree["peer refined vs jaxloc refined"]
    print(f"  refined agreement: {a['fraction_same_minimum']:.4f} of {a['trials']} trials "
          f"within {SAME_MINIMUM_M * 1e3:g} mm ({a['fraction_within_1mm']:.4f} within 1 mm); "
          f"median max gap {a['max_position_gap_m']['median']:.2e} m", flush=True)  # fmt: skip

    return {
        "strategy": strategy,
        "trials": n,
        "seed": seed,
        "jaxloc_devices": js["devices"],
        "feasible_fraction_shared": float(feas.mean()),
        "checks": {"cameras": camera_checks, "model": model_check},
        "jaxloc_run_study": studies,
        "jaxloc_simulate_compile_and_run_s": js["simulate_compile_and_run_s"],
        "peer_estimators_on_shared_observations": peer_alone,
        "peer_whole_trial": whole,
        "accuracy": acc,
        "failures_on_feasible_trials": failures,
        "agreement": agree,
    }


def print_report(report, processes):
    print("\n" + "=" * 100)
    print(f"Speed (trials/s; jaxloc on {report['jaxloc_devices']} host devices, compilation "
          f"excluded; peer in 1 process and in {processes})")  # fmt: skip
    px = f"x{processes}"
    print(f"{'strategy':<11} {'pipeline':<20} {'jaxloc':>9} {'peer x1':>9} {'peer ' + px:>9} "
          f"{'jaxloc/peer x1':>15} {'jaxloc/peer ' + px:>15}")  # fmt: skip
    for r in report["strategies"].values():
        for pipe, study, whole in (("closed form", "robust", "closed form"),
                                   ("+ joint refinement", "robust+refined",
                                    "closed form + refinement")):  # fmt: skip
            j = r["jaxloc_run_study"][study]["trials_per_s"]
            w = r["peer_whole_trial"][whole]
            p1 = w["trials_per_s_1_process"]
            pp = w.get(f"trials_per_s_{processes}_processes", float("nan"))
            print(f"{r['strategy']:<11} {pipe:<20} {j:>9,.0f} {p1:>9,.0f} {pp:>9,.0f} "
                  f"{j / p1:>15.2f} {j / pp:>15.2f}")  # fmt: skip
    print("\nPer CPU-second (trials per second of CPU time of the measuring process(es), all "
          "threads: less sensitive to other load; a per-core efficiency)")
    print(f"{'strategy':<11} {'pipeline':<20} {'jaxloc':>9} {'peer x1':>9} {'peer ' + px:>9} "
          f"{'jaxloc/peer x1':>15}")  # fmt: skip
    for r in report["strategies"].values():
        for pipe, study, whole in (("closed form", "robust", "closed form"),
                                   ("+ joint refinement", "robust+refined",
                                    "closed form + refinement")):  # fmt: skip
            j = r["jaxloc_run_study"][study]["trials_per_cpu_s"]
            w = r["peer_whole_trial"][whole]
            p1 = w["trials_per_cpu_s_1_process"]
            pp = w.get(f"trials_per_cpu_s_{processes}_processes", float("nan"))
            print(f"{r['strategy']:<11} {pipe:<20} {j:>9,.0f} {p1:>9,.0f} {pp:>9,.0f} "
                  f"{j / p1:>15.2f}")  # fmt: skip
    print("\nPeer estimators alone on jaxloc's observations (1 process):")
    for r in report["strategies"].values():
        pa = r["peer_estimators_on_shared_observations"]
        cf, pr = pa["closed_form"], pa["closed_form_plus_refinement"]
        fd = pa["refinement_finite_differences"]
        other = next(v for k, v in pa.items() if k.startswith("refinement_method_"))
        print(f"  {r['strategy']:<11} closed form {cf['trials_per_s']:,.0f}/s; + refinement "
              f"{pr['trials_per_s']:,.0f}/s (refinement alone "
              f"{pr['refinement_only_cycles_per_s']:,.0f} cycles/s, scipy {pr['method']!r}, "
              f"analytic jac)")
        print(f"  {'':<11} refinement alone, {fd['cycles']} cycles: finite-difference jac "
              f"{fd['cycles_per_s']:,.1f} cycles/s (max gap "
              f"{fd['max_position_gap_vs_analytic_m']:.1e} m); method {other['method']!r} "
              f"{other['cycles_per_s']:,.0f} cycles/s (max gap "
              f"{other['max_position_gap_vs_main_m']:.1e} m)")  # fmt: skip
    print("\nAccuracy on the same trials, trials where all four estimators succeed "
          "(position cm, rotation deg: median / RMSE / p90)")  # fmt: skip
    for r in report["strategies"].values():
        print(f"-- {r['strategy']}")
        for method, a in r["accuracy"].items():
            com = a["common"]
            fails = sum(r["failures_on_feasible_trials"][method].values())
            for cam in CAMERAS:
                p, q = com["cameras"][cam]["position_m"], com["cameras"][cam]["rotation_rad"]
                if p["n"] == 0:
                    continue
                print(f"  {method:<18} {cam:<3} pos {100 * p['median']:7.2f} {100 * p['rmse']:7.2f}"
                      f" {100 * p['p90']:7.2f}   rot {math.degrees(q['median']):6.3f} "
                      f"{math.degrees(q['rmse']):6.3f} {math.degrees(q['p90']):6.3f}"
                      + (f"   (n={com['n_trials']}, own failures {fails})" if cam == "C" else ""))
        ag = r["agreement"]["peer refined vs jaxloc refined"]
        gap = ag["max_position_gap_m"]
        print(f"  refined agreement (peer vs jaxloc, both successful): "
              f"{ag['trials_different_minimum']} of {ag['trials']} trials differ by >= "
              f"{SAME_MINIMUM_M * 1e3:g} mm (peer's C worse in "
              f"{ag['different_and_first_worse_on_C']}); max position gap per trial: median "
              f"{gap['median']:.1e} m, p99 {gap['p99']:.1e} m, max {gap['max']:.1e} m")
    la = report["machine"]["load_average_at_start"], report["load_average_at_end"]
    print(f"\nload average at start {la[0]}, at end {la[1]}; 1-min load around the timed "
          f"sections:")
    for label, _, one, _ in LOAD_LOG:
        print(f"  {one:5.2f}  {label}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=None,
                    help="trials per pipeline and strategy (default 8192; 256 with --quick)")
    ap.add_argument("--strategies", default="sequential,concurrent")
    ap.add_argument("--quick", action="store_true", help="small sizes")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scipy-method", default="lm", choices=("lm", "trf"),
                    help="least_squares method of the timed refinement (the other one is "
                    "timed on the --fd-trials subset)")
    ap.add_argument("--fd-trials", type=int, default=None,
                    help="cycles refined with finite differences (default 128; 32 with --quick)")
    ap.add_argument("--whole-refined-trials", type=int, default=None,
                    help="trials of the peer's whole trial with refinement, per timing run "
                    "(default: --trials / 4, at least 256)")
    ap.add_argument("--repeats", type=int, default=3,
                    help="timing rounds (interleaving jaxloc and the peer); best run kept")
    ap.add_argument("--processes", type=int, default=os.cpu_count() or 1,
                    help="worker processes of the parallel peer (default: the cores; 1: none)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "peer_trial.json"))
    args = ap.parse_args(argv)
    if args.trials is None:
        args.trials = 256 if args.quick else 8192
    if args.fd_trials is None:
        args.fd_trials = 32 if args.quick else 128
    # One host device per core for jaxloc, before JAX starts (run.py does the same).
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]  # fmt: skip
    os.environ["XLA_FLAGS"] = " ".join(
        flags + [f"--xla_force_host_platform_device_count={os.cpu_count() or 1}"]
    )
    sys.path.insert(0, HERE)
    from run import machine_info

    cv2.setNumThreads(1)  # as in the workers (solvePnP on 6-7 points is serial anyway)

    t_start = time.perf_counter()
    report = {
        "command": " ".join(["python", os.path.relpath(__file__)] + sys.argv[1:]),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine_info(),
        "git_commit": subprocess.run(["git", "-C", HERE, "rev-parse", "HEAD"],
                                     capture_output=True, text=True).stdout.strip(),
        "settings": {k: v for k, v in vars(args).items()},
        "peer": {
            "tools": {"numpy": np.__version__, "scipy": scipy.__version__,
                      "opencv": cv2.__version__},  # fmt: skip
            "overhead_pose": "cv2.solvePnP SOLVEPNP_SQPNP, Python loop, pixels averaged per "
            "placement",
            "refinement": f"scipy.optimize.least_squares method={args.scipy_method!r}, default "
            "tolerances, analytic Jacobian (finite differences on a subset)",
            "concurrent_scales": "quadratic ratio roots x overall LS scale x 6 Gauss-Newton "
            "steps on the odometry; up to 4 distinct candidates scored by odometry + SQPnP "
            "reprojection chi-square (jaxloc also uses P3P-derived ratios and a multi-start "
            "refinement; the peer does not)",
        },
        "same_minimum_threshold_m": SAME_MINIMUM_M,
    }
    print(f"load average at start: {report['machine']['load_average_at_start']}", flush=True)
    processes = max(1, args.processes)
    pool = None
    if processes > 1:
        # Spawned (not forked: the parent runs JAX's threads); started now, before JAX.
        pool = multiprocessing.get_context("spawn").Pool(processes)
        pool.map(int, range(processes))  # workers up and imported
    report["peer_processes"] = processes
    report["strategies"] = {}
    try:
        for strategy in [s for s in args.strategies.split(",") if s]:
            report["strategies"][strategy] = run_strategy(strategy, args, pool, processes)
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    report["jaxloc_devices"] = next(iter(report["strategies"].values()))["jaxloc_devices"]
    report["total_seconds"] = time.perf_counter() - t_start
    report["load_average_at_end"] = list(os.getloadavg())
    report["load_log"] = [dict(zip(("label", "t_s", "load_1min", "load_5min"), e))
                          for e in LOAD_LOG]  # fmt: skip
    print_report(report, processes)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=2, default=float)
    print(f"\nwrote {args.out} ({report['total_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
