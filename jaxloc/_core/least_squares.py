"""The one least-squares kernel: a batched Levenberg--Marquardt on a manifold, its
Gauss--Newton special case, and the implicit-function derivative of its minimum.

Every nonlinear least-squares problem jaxloc solves goes through
[`levenberg_marquardt`][]: the joint refinement of a cycle (~40 unknowns), the
refinement of one camera pose and the robust overhead solver's polish (6 unknowns), the
concurrent strategy's small scale fits. The caller supplies the model (residuals and
their Jacobian with respect to a local perturbation, by the chain rule: cheaper than
differentiating the model) and the retraction that applies a step; the loop is the same.
Its derivatives are never those of the unrolled loop: [`implicit_step`][] gives the
minimum's derivative by the implicit function theorem. The lineax solver
[`NormalCholesky`][] lets `optx.least_squares` take its steps through the same
LAPACK-free normal equations (the `"optx-lm"` / `"optx-gn"` solvers).
"""

import functools as ft
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.flatten_util
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Bool, Float, Int, PyTree

from .linalg import cholesky, cholesky_solve, gauss_jordan_solve, gram, spd_inverse


#: Largest number of unknowns solved by Gauss--Jordan elimination; larger systems (a
#: cycle's 30-42 unknowns) use the `fori_loop` Cholesky: at that size, batched, the
#: elimination's update of the whole augmented matrix at every pivot ran several times
#: slower than the Cholesky loop (session 25's measurements, in the issue notes).
SMALL_SYSTEM_MAX = 8
#: Damping of the first step and its clip range.
_LAM_MIN, _LAM_MAX = 1e-9, 1e12


def solve_spd(
    H: Float[Array, "n n"], g: Float[Array, " n"]
) -> tuple[Float[Array, " n"], Bool[Array, ""]]:
    """Solve `H x = g` for SPD `H`, LAPACK-free: Gauss--Jordan elimination for a few
    unknowns, a `fori_loop` Cholesky beyond `SMALL_SYSTEM_MAX`. Returns `(x, ok)`; `x` is 0
    where not `ok`."""
    if H.shape[0] <= SMALL_SYSTEM_MAX:
        x, ok = gauss_jordan_solve(H, g)
    else:
        x = cholesky_solve(cholesky(H), g)
        ok = jnp.array(True)
    ok = ok & jnp.all(jnp.isfinite(x))
    return jnp.where(ok, x, 0.0), ok


class NormalEquations(NamedTuple):
    """A least-squares model linearized at an iterate: the cost `r^T r`, the Gauss--Newton
    matrix `H = J^T J` `(n, n)` and the gradient `g = J^T r` `(n,)`. Every model of the
    kernel returns these: a sparse model (a cycle: each residual touches two poses)
    builds them without a dense Jacobian."""

    cost: Float[Array, ""]
    H: Float[Array, "n n"]
    g: Float[Array, " n"]


def normal_equations(
    r: Float[Array, " m"], J: Float[Array, "m n"], gram_fn: Callable[[Array], Array] = gram
) -> NormalEquations:
    """The [`NormalEquations`][] of residuals `r` and their dense Jacobian `J`. `gram_fn`
    forms `J^T J`: [`gram`][] (element-wise, best for a few dozen unknowns or fewer) or
    `jaxloc._core.linalg.gram_dot` (one `dot`, for larger problems such as the tracking
    smoother's window)."""
    return NormalEquations(jnp.sum(r * r), gram_fn(J), jnp.sum(J * r[:, None], axis=0))


class LMSettings(NamedTuple):
    """The static settings of [`levenberg_marquardt`][] (see its arguments)."""

    rtol: float
    atol: float
    damped: bool = True
    decrease_tol: Any = None
    final_gauss_newton: bool = False


class LMState(NamedTuple):
    """The loop state of [`levenberg_marquardt`][], resumable with [`lm_continue`][]:
    `k` iterations run (iteration `k >= 1` decided on step `k`), the current iterate `x`
    with its normal equations, the damping `lam` the proposed step `x_try` was solved
    with, and whether that step is finite, small enough to stop and how much it
    promises (`predicted`, the decrease of the linearized cost)."""

    k: Int[Array, ""]
    x: PyTree
    normal: NormalEquations
    lam: Float[Array, ""]
    nu: Float[Array, ""]
    done: Bool[Array, ""]
    converged: Bool[Array, ""]
    x_try: PyTree
    finite: Bool[Array, ""]
    small: Bool[Array, ""]
    predicted: Float[Array, ""]


class LMResult(NamedTuple):
    """Outcome of [`levenberg_marquardt`][]: the last accepted iterate `x`, the number of
    steps decided (`num_steps`), whether it `converged`, and the normal equations at
    `x`."""

    x: PyTree
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]
    normal: NormalEquations


def lm_start(
    x0: PyTree, num_unknowns: int, *, active: Bool[Array, ""] | bool = True, lam0: float = 1e-2
) -> LMState:
    """The state before the first iteration: nothing evaluated yet (iteration 0
    evaluates `x0`)."""
    dtype = jnp.result_type(*jax.tree.leaves(x0))
    false = jnp.array(False)
    n = num_unknowns
    return LMState(
        k=jnp.array(0, jnp.int32), x=x0,
        normal=NormalEquations(jnp.zeros((), dtype), jnp.zeros((n, n), dtype), jnp.zeros(n, dtype)),
        lam=jnp.array(lam0, dtype), nu=jnp.array(2.0, dtype), done=~jnp.asarray(active),
        converged=false, x_try=x0, finite=jnp.array(True), small=false,
        predicted=jnp.array(0.0, dtype),
    )  # fmt: skip


def lm_iteration(
    model: Callable[[PyTree], NormalEquations],
    retract: Callable[[PyTree, Array], PyTree],
    scale: Callable[[PyTree], Array],
    settings: LMSettings,
) -> Callable[[LMState], LMState]:
    """One iteration of [`levenberg_marquardt`][] as a function `state -> state`: it
    evaluates the model at the proposed step, accepts or rejects it, updates the damping
    and proposes the next step (iteration 0 evaluates the start)."""
    rtol, atol, damped, decrease_tol, _ = settings

    def propose(x, normal, lam):
        H, g = normal.H, normal.g
        delta, finite = solve_spd(H + lam * jnp.eye(g.shape[0], dtype=g.dtype), -g)
        small = jnp.max(jnp.abs(delta)) <= atol + rtol * scale(x)
        if decrease_tol is not None:
            small = small | (-jnp.sum(g * delta) <= decrease_tol)
        predicted = -2.0 * jnp.sum(g * delta) - jnp.sum(delta * (H @ delta))
        return retract(x, delta), finite, small, predicted

    def body(s: LMState):
        dtype = s.lam.dtype
        new = model(s.x_try)
        first = s.k == 0
        cost, cost_new = s.normal.cost, new.cost
        ok_new = s.finite & jnp.isfinite(cost_new)
        accept = first | (ok_new & (cost_new <= cost) if damped else ok_new)
        # A rejected step that is already negligible: the minimum within rounding.
        done = ~first & (accept | (s.lam < 1e-3)) & s.finite & s.small
        pick = ft.partial(jax.tree.map, lambda a, b: jnp.where(accept, a, b))
        if damped:
            gain = (cost - cost_new) / jnp.where(s.predicted > 0, s.predicted, 1.0)
            shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            lam = jnp.clip(jnp.where(accept, s.lam * shrink, s.lam * s.nu), _LAM_MIN, _LAM_MAX)
            lam = jnp.where(first, s.lam, lam).astype(dtype)
            nu = jnp.where(first | accept, 2.0, 2.0 * s.nu).astype(dtype)
        else:
            lam, nu = s.lam, s.nu
        x, normal = pick(s.x_try, s.x), pick(new, s.normal)
        x_try, finite, small, predicted = propose(x, normal, lam)
        return LMState(s.k + 1, x, normal, lam, nu, done, done, x_try, finite, small, predicted)

    return body


def lm_continue(
    model: Callable[[PyTree], NormalEquations],
    retract: Callable[[PyTree, Array], PyTree],
    scale: Callable[[PyTree], Array],
    state: LMState,
    settings: LMSettings,
    max_steps: int | Array,
) -> LMState:
    """Iterate from `state` until converged or until `max_steps` steps are decided (the
    step count includes those of earlier calls). See [`levenberg_marquardt`][]."""

    def cond(s: LMState):
        return (s.k <= max_steps) & ~s.done

    return jax.lax.while_loop(cond, lm_iteration(model, retract, scale, settings), state)


def lm_result(state: LMState, retract, settings: LMSettings) -> LMResult:
    """The [`LMResult`][] of a final state (with the closing Gauss--Newton step of
    `settings.final_gauss_newton`)."""
    x = state.x
    if settings.final_gauss_newton:
        delta, ok = solve_spd(state.normal.H, -state.normal.g)
        polished = retract(x, delta)
        x = jax.tree.map(lambda a, b: jnp.where(ok & state.converged, a, b), polished, x)
    return LMResult(x, jnp.maximum(state.k - 1, 0), state.converged, state.normal)


def levenberg_marquardt(
    model: Callable[[PyTree], NormalEquations],
    retract: Callable[[PyTree, Array], PyTree],
    scale: Callable[[PyTree], Array],
    x0: PyTree,
    *,
    num_unknowns: int,
    max_steps: int | Array,
    rtol: float,
    atol: float,
    active: Bool[Array, ""] | bool = True,
    damped: bool = True,
    lam0: float = 1e-2,
    decrease_tol: float | None = None,
    final_gauss_newton: bool = False,
) -> LMResult:
    r"""Levenberg--Marquardt re-linearized at the current iterate every step.

    **Arguments:**

    - `model(x) -> NormalEquations`: the cost, `J^T J` and `J^T r` at `x`, `J` the
      Jacobian of the residuals with respect to the local perturbation `delta` of
      `retract(x, delta)` at `delta = 0` (a dense model: [`normal_equations`][]).
    - `retract(x, delta) -> x'`: applies a step (e.g. `T exp(delta)` per pose).
    - `scale(x)`: the size of `x` the relative tolerance refers to (e.g. the largest
      position, m).
    - `x0`: the start (any pytree of arrays).
    - `num_unknowns`: the length of `delta`.
    - `max_steps`: steps decided at most (each one model evaluation).
    - `rtol`, `atol`: converged when a step (accepted, or rejected at negligible damping:
      the minimum within rounding) has `max |delta| <= atol + rtol * scale(x)`.
    - `active`: an inactive problem (e.g. a failed start) takes no step, so under `vmap`
      it does not prolong its batch's loop.
    - `damped`: `False` gives Gauss--Newton: every finite step is taken and the damping
      stays `lam0` (0 for plain Gauss--Newton; a tiny value regularizes directions no
      residual touches).
    - `lam0`: the first step's damping. Damping is isotropic, `H + lambda I`: on whitened
      residuals `lambda` is a prior precision on the unknowns (Marquardt's `diag(J^T J)`
      scaling over-damps every translation a precise odometry distance touches). It is
      updated by Nielsen's rule: by the gain ratio (actual over predicted decrease) after
      an accepted step, by doubling factors after rejected ones (fixed factors of 10
      oscillate between acceptance and rejection along a curved, weakly observed valley).
    - `decrease_tol`: also converged when a step's predicted cost decrease `-g . delta` is
      below it (the residuals must be whitened: it is then in chi-square units, about the
      squared step in standard deviations). Gauss--Newton converges only linearly along
      weakly observed directions (a flat floor), where the step test alone takes
      hundreds of iterations. `None`: the step test only.
    - `final_gauss_newton`: after convergence, one more Gauss--Newton step from the
      normal equations at hand (no model evaluation) takes the remaining error to
      rounding.

    One model evaluation per iteration, at the top of the loop body, so the model is
    traced and compiled once: iteration 0 evaluates the start, iteration `k >= 1`
    evaluates step `k` proposed by iteration `k - 1` and accepts or rejects it. The loop
    is [`lm_start`][], [`lm_continue`][] and [`lm_result`][], which a batched caller
    may interleave (e.g. to go on with the unconverged problems of a batch only). Steps
    are solved by a LAPACK-free Cholesky ([`solve_spd`][]). Not meant to be
    differentiated: see [`implicit_step`][].
    """
    settings = LMSettings(rtol, atol, damped, decrease_tol, final_gauss_newton)
    state = lm_start(x0, num_unknowns, active=active, lam0=lam0)
    state = lm_continue(model, retract, scale, state, settings, max_steps)
    return lm_result(state, retract, settings)


def gauss_newton(model, retract, x0: PyTree, *, steps: int, lam: float) -> PyTree:
    """`steps` Gauss--Newton steps with the fixed isotropic damping `lam` (`H + lam I`; a
    tiny value regularizes directions no residual touches), no convergence test: the
    kernel's undamped case as a `fori_loop` with static bounds, so reverse-mode
    differentiation applies. A step to a point where the model is not finite is not
    taken. `model(x) -> (r, J)` and `retract(x, delta)` as in [`levenberg_marquardt`][]."""
    r0, J0 = model(x0)
    eye = jnp.eye(J0.shape[1], dtype=J0.dtype)

    def body(_, carry):
        x, r, J = carry
        delta, finite = solve_spd(gram(J) + lam * eye, -jnp.sum(J * r[:, None], axis=0))
        x_new = retract(x, delta)
        r_new, J_new = model(x_new)
        ok = finite & jnp.isfinite(jnp.sum(r_new * r_new))
        return jax.tree.map(lambda a, b: jnp.where(ok, a, b), (x_new, r_new, J_new), carry)

    return jax.lax.fori_loop(0, steps, body, (x0, r0, J0))[0]


def jvp_nonzero(f, primals, tangents):
    """`jax.jvp(f, primals, tangents)[1]` over the pytree `primals`, differentiating only
    the leaves whose tangent is not a `SymbolicZero`; `None` if every tangent is zero."""
    leaves, tree = jax.tree.flatten(primals)
    dots = tree.flatten_up_to(tangents)
    live = [i for i, t in enumerate(dots) if not isinstance(t, SymbolicZero)]
    if not live:
        return None

    def of_live(*values):
        full = list(leaves)
        for i, v in zip(live, values):
            full[i] = v
        return f(tree.unflatten(full))

    return jax.jvp(of_live, [leaves[i] for i in live], [dots[i] for i in live])[1]


def _zero_step(num_unknowns: int, x) -> Array:
    # Derived from an input so that under `vmap` it is batched like its tangent.
    leaf = jax.tree.leaves(x)[0]
    return jnp.zeros(num_unknowns, leaf.dtype) + 0.0 * leaf.reshape(-1)[0]


@ft.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def implicit_step(residuals: Callable, num_unknowns: int, static: Any, x: PyTree, args: PyTree):
    """Zero tangent step at a converged minimum `x`, whose derivative is that of the
    minimizer of `|residuals(x, delta, args, static)|^2` over `delta` with respect to
    `args` (the implicit function theorem on the gradient of the cost; full Hessian).

    `retract(x, implicit_step(...))` is the solution with correct derivatives; it does
    not depend on the start. `residuals` and `static` are hashable and not
    differentiated; `residuals(x, delta, args, static)` gives the residuals at the
    perturbed iterate."""
    return _zero_step(num_unknowns, x)


@ft.partial(implicit_step.defjvp, symbolic_zeros=True)
def _implicit_step_jvp(residuals, num_unknowns, static, primals, tangents):
    x, args = primals
    _, args_dot = tangents
    zero = _zero_step(num_unknowns, x)

    def gradient(delta, args):
        def cost(d):
            r = residuals(x, d, args, static)
            return 0.5 * jnp.sum(r * r)

        return jax.grad(cost)(delta)

    H = jax.jacfwd(gradient)(zero, args)
    H_inv, _ = spd_inverse(0.5 * (H + H.T))
    g_dot = jvp_nonzero(lambda a: gradient(zero, a), args, args_dot)
    return zero, jnp.zeros_like(zero) if g_dot is None else -H_inv @ g_dot


class NormalCholesky(lx.AbstractLinearSolver):
    """Least-squares solve `min |A x - b|` through the normal equations `A^T A x = A^T b`
    with a `fori_loop` Cholesky: no LAPACK in `optx.least_squares`'s loop (lineax's
    default QR calls LAPACK once per problem under `vmap`). For the small, well-scaled
    systems of a pose refinement (6 or ~40 unknowns; Levenberg--Marquardt passes the
    damped augmented Jacobian) squaring the condition number costs nothing in float64."""

    def init(self, operator, options):
        del options
        A = operator.as_matrix()
        return A, cholesky(A.T @ A)

    def compute(self, state, vector, options):
        del options
        A, L = state
        flat, _ = jax.flatten_util.ravel_pytree(vector)
        x = cholesky_solve(L, A.T @ flat)
        ok = jnp.all(jnp.isfinite(x))
        x = jnp.where(ok, x, 0.0)
        result = lx.RESULTS.where(ok, lx.RESULTS.successful, lx.RESULTS.singular)
        _, unflatten_in = jax.flatten_util.ravel_pytree(jnp.zeros(A.shape[1], A.dtype))
        return unflatten_in(x), result, {}

    def transpose(self, state, options):
        raise NotImplementedError("`NormalCholesky` is only used inside the solver loop.")

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


def optx_solver(solver: str, rtol: float, atol: float):
    """optimistix's `"lm"` (Levenberg--Marquardt) or `"gn"` (Gauss--Newton) with the
    [`NormalCholesky`][] linear solver."""
    if solver == "lm":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=NormalCholesky())
    if solver == "gn":
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=NormalCholesky())
    raise ValueError(f'`solver` must be "lm" or "gn"; got {solver!r}.')


class KernelLevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """jaxloc's kernel ([`levenberg_marquardt`][]) as an optimistix least-squares solver,
    for `optx.least_squares` (its implicit adjoint, `RESULTS`, `max_steps` and `throw`).

    optimistix iterates `y` in a vector space, the kernel a point on a manifold (poses).
    `y` is the point's coordinates in a chart around a fixed base point carried in
    `args`: `point(y, args)` is the point (e.g. `T0 exp(y)` per pose) and
    `coordinates(x, args)` its inverse. The state keeps the point itself and the kernel
    re-linearizes there (`model(x, args)`: the normal equations with respect to the local
    perturbation of `retract`), exactly as [`levenberg_marquardt`][] does; each step
    returns the chart coordinates of the accepted point, which is what the adjoint
    differentiates through `fn(y, args)` (the residuals at `point(y, args)`).

    Options: `"active"` (a `bool` array; default `True`): an inactive problem takes no
    step. `max_steps` of `optx.least_squares` counts iterations as the kernel does, the
    start's evaluation included: pass the kernel's `max_steps + 1`.
    """

    model: Callable[[PyTree, PyTree], NormalEquations]
    retract: Callable[[PyTree, Array], PyTree]
    scale: Callable[[PyTree], Array]
    point: Callable[[Array, PyTree], PyTree]
    coordinates: Callable[[PyTree, PyTree], Array]
    num_unknowns: int
    rtol: float
    atol: float
    decrease_tol: Any = None
    lam0: float = 1e-2
    norm: Callable[[PyTree], Array] = optx.max_norm

    def _settings(self) -> LMSettings:
        return LMSettings(self.rtol, self.atol, True, self.decrease_tol)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, f_struct, aux_struct, tags
        active = options.get("active", True)
        return lm_start(self.point(y, args), self.num_unknowns, active=active, lam0=self.lam0)

    def step(self, fn, y, args, options, state, tags):
        del fn, y, options, tags
        iterate = lm_iteration(
            lambda x: self.model(x, args), self.retract, self.scale, self._settings()
        )
        state = iterate(state)
        return self.coordinates(state.x, args), state, None

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        return state.done, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, tags, result
        return y, aux, {"converged": state.converged}
