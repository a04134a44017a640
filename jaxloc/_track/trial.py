r"""One Monte Carlo run of a tracking study: simulate K cycles, track them, score every
estimate against the truth and against its bound ([`jaxloc.run_track_trial`][]).

Methods, in the order of every per-method array: `"chain"` (each cycle alone, chained into
`W_0`), `"smoother"` (the fixed-lag smoother, in `W_0`), `"one_step"` (the climbing
robot from each cycle's first formation and its prior, and that formation at the prior's
scale, in the cycle's own frame `W_k`: its errors do not accumulate a frame's).

Bounds, per method: the *chained bound* (each cycle's Cramér–Rao bound at the true poses,
chained as the estimates are: `jaxloc._track.chain`), the smoother's bound (the Fisher
information of every cycle so far at the true poses, marginalized: `jaxloc._track.smoother`),
and the one-step bound (the Bayesian bound of one formation and the prior the estimator
used: `jaxloc._track.one_step`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from .._core.compiler import jit
from .._core.numerics import safe_norm
from .._core.poses import compose, inverse, rotation_error
from .._core.results import RESULTS, status_code
from .._cycle.layout import first_sighting
from .._model.covariance import covariance_at, crlb_inputs
from .._study.trial import final_poses, position_nees
from .chain import chain_start, chain_step
from .frames import body_of_overhead, end_covariance, position_covariance, rotation_covariance
from .one_step import one_step_bound
from .scenario import TrackScenario
from .simulate import CLIMBER_SIGMA_FLOOR, simulate_track, TrackTruth
from .smoother import bound_update, smoother_start, WindowLayout
from .tracker import DEFAULT_WINDOW, track_cycles, TrackEstimates


TRACK_METHODS = ("chain", "smoother", "one_step")
"""The methods of a tracking study, in the order of every per-method array: "chain" (each
cycle alone, chained into the first cycle's frame), "smoother" (the fixed-lag smoother),
"one_step" (the climbing robot from each cycle's first formation and its prior)."""


class TrackErrors(eqx.Module):
    """Errors of one tracked run, per cycle (leading axis K), method (`TRACK_METHODS`)
    and robot (`jaxloc.CAMERAS`: C, C1, C2, C3).

    **Fields:**

    - `status` `(K, 3)`: int32 status per method (0 = successful; `not_visible` where
      the simulation lost a required sighting).
    - `position` `(K, 3, 4)` (m), `rotation` `(K, 3, 4)` (rad, geodesic),
      `position_vector` `(K, 3, 4, 3)` (estimate minus truth): chain and smoother at the
      end of cycle `k` in `W_0`; one-step at the cycle's first step in `W_k`.
    - `bound_position_var`, `bound_rotation_var` `(K, 3, 4)`: trace of each method's bound
      (m^2, rad^2) at the same poses.
    - `nees` `(K, 3, 4)`: each position's error squared under the method's own covariance
      (NaN where that covariance is singular, e.g. C1 in one-step: the frame's origin).
    - `root_correct` `(K,)`: the one-step estimate refined the P3P root nearest the truth;
      `root_count` `(K,)`: valid roots.
    - `truth_position` `(K, 4, 3)`: the true end-of-cycle positions in `W_0` (plots).
    - `covariance_xy` `(K, 3, 4, 3)`: each method's own position covariance in its frame,
      its x-y block as `(xx, xy, yy)` (m^2; uncertainty ellipses of a top view).
    """

    status: Int[Array, "K 3"]
    position: Float[Array, "K 3 4"]
    rotation: Float[Array, "K 3 4"]
    position_vector: Float[Array, "K 3 4 3"]
    bound_position_var: Float[Array, "K 3 4"]
    bound_rotation_var: Float[Array, "K 3 4"]
    nees: Float[Array, "K 3 4"]
    root_correct: Bool[Array, " K"]
    root_count: Int[Array, " K"]
    truth_position: Float[Array, "K 4 3"]
    covariance_xy: Float[Array, "K 3 4 3"]


def truth_end(truth: TrackTruth) -> Float[Array, "K 4 7"]:
    """True end-of-cycle body poses of (C, C1, C2, C3) in `W_0`, `(K, 4, 7)`."""
    ground = truth.T_world_body.wxyz_xyz[:, -1]
    return jnp.concatenate([truth.T_world_climber.wxyz_xyz[:, None], ground], axis=1)


def _errors(est: Float[Array, "4 7"], tru: Float[Array, "4 7"]):
    def one(e, t):
        diff = e[4:] - t[4:]
        rot = rotation_error(jaxlie.SO3(e[:4]), jaxlie.SO3(t[:4]))
        return safe_norm(diff), rot, diff

    return jax.vmap(one)(est, tru)


def climber_truth(track: TrackScenario, truth: TrackTruth):
    """The climbing robot's true motion into every cycle and its odometry sigma,
    `(K, 7)`, `(K, 6)` (row 0 unused)."""
    T = truth.T_world_climber.wxyz_xyz
    dtype = T.dtype
    Z = jax.vmap(lambda a, b: compose(inverse(jaxlie.SE3(a)), jaxlie.SE3(b)).wxyz_xyz)(
        jnp.concatenate([T[:1], T[:-1]]), T
    )
    dist = safe_norm(Z[:, 4:])
    s_v = jnp.maximum(track.climber_odometry_sigma_rel.astype(dtype) * dist, CLIMBER_SIGMA_FLOOR)
    s_r = jnp.maximum(track.climber_odometry_rotation_sigma.astype(dtype), CLIMBER_SIGMA_FLOOR)
    sigma = jnp.concatenate(
        [jnp.broadcast_to(s_v[:, None], (T.shape[0], 3)), jnp.full((T.shape[0], 3), s_r)], 1
    )
    return Z, sigma.at[0].set(1.0)


def track_bounds(track: TrackScenario, truth: TrackTruth, estimates: TrackEstimates):
    """Every method's bound at the true poses of every cycle: `(position (K, 3, 4, 3, 3),
    rotation (K, 3, 4, 3, 3))` covariances (m^2, rad^2) for chain, smoother, one-step."""
    rig, strategy = track.rig, track.strategy
    dtype = truth.height.dtype
    sigma_rel = track.scenario.odometry_sigma_rel
    layout = WindowLayout(strategy, 1)
    Z, Z_sigma = climber_truth(track, truth)
    ks, rs = first_sighting(strategy)
    ends = truth_end(truth)

    def one_cycle(carry, inputs):
        chain, bound = carry
        poses_k, T_place0, T_over0, z, z_sigma, prior, end0 = inputs
        T_place, T_over, data = crlb_inputs(rig, poses_k, sigma_rel, strategy)
        crlb = covariance_at(T_place, T_over, data, rig, strategy)
        end_k = final_poses(poses_k, rig).wxyz_xyz
        chain, _, chain_cov = chain_step(
            chain, end_k, end_covariance(crlb.tangent, strategy, rig.mounts[0]), jnp.array(True)
        )
        bound, _, joint = bound_update(layout, bound, data, z, z_sigma, T_place0, T_over0, rig)
        smooth_cov = jnp.stack([joint[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(4)])
        one = one_step_bound(T_place, T_over, data, rig, strategy, prior)  # C2, C3, C body
        one_cov = jnp.stack([jnp.zeros((6, 6), dtype), jnp.zeros((6, 6), dtype),
                             one[:6, :6], one[6:12, 6:12]])  # fmt: skip
        one_cov = one_cov.at[0].set(one[12:, 12:])
        # One-step poses in W_k: C's body, C1 (origin), C2, C3 at the first step.
        one_poses = jnp.concatenate([
            body_of_overhead(T_over, rig.mounts[0])[None], T_place[:3]
        ])  # fmt: skip

        def world(poses, covs):
            return (jax.vmap(position_covariance)(poses, covs),
                    jax.vmap(rotation_covariance)(covs))  # fmt: skip

        pos, rot = zip(world(end0, chain_cov), world(end0, smooth_cov), world(one_poses, one_cov))
        return (chain, bound), (jnp.stack(pos), jnp.stack(rot))

    T_place0 = truth.T_world_body.wxyz_xyz[:, ks, rs]  # (K, P, 7) in W_0
    T_over0 = truth.T_world_overhead.wxyz_xyz
    init = (chain_start(dtype), smoother_start(layout, dtype))
    _, (pos, rot) = jax.lax.scan(
        one_cycle, init,
        (truth.cycles.poses, T_place0, T_over0, Z, Z_sigma, estimates.one_step_prior, ends),
    )  # fmt: skip
    return pos, rot


def _trace(P):
    return jnp.trace(P, axis1=-2, axis2=-1)


@jit(inline=True)
def run_track_trial(
    track: TrackScenario, key: PRNGKeyArray, cycles: int, window: int = DEFAULT_WINDOW
) -> TrackErrors:
    """Simulate `cycles` cycles of `track`, track them ([`jaxloc.track_cycles`][]), score
    every method against the truth and its bound. Pure and branch-free, for one run: batch
    with `jax.vmap`."""
    truth, obs, feasible = simulate_track(track, key, cycles)
    rig = track.rig
    est = track_cycles(obs, rig, window=window)
    tru = truth_end(truth)
    mount = rig.mounts[0]
    # One-step truth in each cycle's frame W_k: C's body, C1, C2, C3 at the first step.
    cyc = truth.cycles.poses
    one_truth = jnp.concatenate([
        jax.vmap(lambda T: body_of_overhead(T, mount))(cyc.T_world_overhead.wxyz_xyz)[:, None],
        cyc.T_world_body.wxyz_xyz[:, 0],
    ], axis=1)  # fmt: skip
    one_est = jnp.concatenate([est.one_step.T_world_climber[:, None], est.one_step.T_world_body],
                              axis=1)  # fmt: skip
    pos_c, rot_c, vec_c = jax.vmap(_errors)(est.chain_poses, tru)
    pos_s, rot_s, vec_s = jax.vmap(_errors)(est.smoother_poses, tru)
    pos_o, rot_o, vec_o = jax.vmap(_errors)(one_est, one_truth)
    # Covariances in world position terms.
    smooth_blocks = jnp.stack(
        [est.smoother_covariance[:, 6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(4)], 1
    )
    pc = jax.vmap(jax.vmap(position_covariance))(est.chain_poses, est.chain_covariance)
    ps = jax.vmap(jax.vmap(position_covariance))(est.smoother_poses, smooth_blocks)
    po = jnp.zeros_like(ps).at[:, 0].set(jax.vmap(lambda e: e.position_covariance)(est.one_step))
    nees = jnp.stack([jax.vmap(position_nees)(v, P) for v, P in
                      ((vec_c, pc), (vec_s, ps), (vec_o, po))], 1)  # fmt: skip
    b_pos, b_rot = track_bounds(track, truth, est)
    # The root nearest the truth (C's body position) is the one refined?
    near = jnp.argmin(
        jnp.where(est.one_step.roots_ok,
                  jnp.sum((est.one_step.roots[..., 4:] - one_truth[:, None, 0, 4:]) ** 2, -1),
                  jnp.inf), axis=-1,
    )  # fmt: skip
    status = jnp.stack([est.chain_status, est.smoother_status, est.one_step_status], 1)
    status = jnp.where(feasible[:, None], status, status_code(RESULTS.not_visible))
    return TrackErrors(
        status=status,
        position=jnp.stack([pos_c, pos_s, pos_o], 1),
        rotation=jnp.stack([rot_c, rot_s, rot_o], 1),
        position_vector=jnp.stack([vec_c, vec_s, vec_o], 1),
        bound_position_var=_trace(b_pos),
        bound_rotation_var=_trace(b_rot),
        nees=nees,
        root_correct=near == est.one_step.chosen,
        root_count=jnp.sum(est.one_step.roots_ok, -1).astype(jnp.int32),
        truth_position=tru[..., 4:],
        covariance_xy=jnp.stack([_xy(pc), _xy(ps), _xy(po)], 1),
    )


def _xy(P):
    return jnp.stack([P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]], -1)
