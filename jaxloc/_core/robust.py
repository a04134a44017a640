r"""Robust losses of whitened residual blocks, for iteratively reweighted least squares.

A robust loss replaces a block's squared whitened norm `s = |r_i|^2` (a pixel sighting:
two residuals, chi-square units) by `rho(s)`, growing more slowly than `s` for large
residuals. The least-squares kernel (`jaxloc._core.least_squares`) minimises
`sum_i rho(s_i)` unchanged: at each iterate the model weighs block `i` by `w_i =
rho'(s_i)` (iteratively reweighted least squares), which gives the exact gradient
`2 sum_i w_i J_i^T r_i` and the Gauss--Newton matrix `sum_i w_i J_i^T J_i` (Triggs et
al., "Bundle adjustment -- a modern synthesis", 2000, §4.3, without the second-order
correction: it keeps the matrix positive semi-definite). `rho(s) = s` for small `s`,
so near the minimum the cost reads in chi-square units as the plain one.

The losses act on the block's norm `e = sqrt(s)` with the scale `k` in whitened units
(standard deviations): Huber `rho = s` for `e <= k`, `2 k e - k^2` beyond; Cauchy
`rho = k^2 log(1 + s / k^2)`. The defaults are the usual 95%-efficiency constants of a
one-dimensional residual (1.345 Huber, 2.3849 Cauchy); jaxloc uses the loss only to
find the outliers and then re-solves on the inliers by plain least squares
([`jaxloc.refine_cycle`][]), so the loss's own efficiency does not reach the estimate.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


#: The robust losses by name.
LOSSES = ("huber", "cauchy")
#: Default `loss_scale` of each loss (whitened units, standard deviations).
DEFAULT_LOSS_SCALE = {"huber": 1.345, "cauchy": 2.3849}


class RobustLoss(eqx.Module):
    """A robust loss of squared whitened block norms (see the module docstring).

    **Fields:** `kind` (static), one of `LOSSES`; `scale`, the scale `k` (standard
    deviations), an array leaf (so a study may vary it under `vmap`)."""

    kind: str = eqx.field(static=True)
    scale: Float[Array, ""]

    def rho(self, s: Float[Array, "*b"]) -> Float[Array, "*b"]:
        """The loss of squared norms `s` (chi-square units)."""
        k = self.scale.astype(s.dtype)
        if self.kind == "huber":
            e = jnp.sqrt(jnp.where(s > k * k, s, 1.0))
            return jnp.where(s > k * k, 2.0 * k * e - k * k, s)
        k2 = jnp.where(jnp.isfinite(k), k * k, 1.0)
        return jnp.where(jnp.isfinite(k), k2 * jnp.log1p(s / k2), s)

    def weight(self, s: Float[Array, "*b"]) -> Float[Array, "*b"]:
        """`rho'(s)`, the weight of each block in the reweighted least squares (in
        `(0, 1]`). An infinite `scale` gives plain least squares (weights 1)."""
        k = self.scale.astype(s.dtype)
        if self.kind == "huber":
            e = jnp.sqrt(jnp.where(s > k * k, s, 1.0))
            return jnp.where(s > k * k, k / e, 1.0)
        return 1.0 / (1.0 + s / (k * k))


def robust_loss(loss: str | None, loss_scale: Float[ArrayLike, ""] | None) -> RobustLoss | None:
    """The [`RobustLoss`][] of `loss` (`None`: plain least squares) and `loss_scale`
    (`None`: the loss's default), validated: a `ValueError` naming the argument and its
    value for an unknown loss, a scale without a loss, or a scale that is not a positive
    finite number (checked when it is concrete; a traced scale is taken as it is)."""
    if loss is not None and loss not in LOSSES:
        raise ValueError(f'`loss` must be None, "huber" or "cauchy"; got {loss!r}.')
    if loss is None:
        if loss_scale is not None:
            raise ValueError(
                f"`loss_scale` ({loss_scale!r}) needs a robust `loss` (\"huber\" or "
                '"cauchy"); with `loss=None` the refinement is plain least squares.'
            )
        return None
    if loss_scale is None:
        loss_scale = DEFAULT_LOSS_SCALE[loss]
    if isinstance(loss_scale, bool | str):
        raise ValueError(f"`loss_scale` must be a positive number; got {loss_scale!r}.")
    if not isinstance(loss_scale, jax.core.Tracer):
        try:
            value = float(np.asarray(loss_scale))  # numpy: no tracer under an outer jit
        except (TypeError, ValueError):
            raise ValueError(
                f"`loss_scale` must be a positive number (a scalar); got {loss_scale!r}."
            ) from None
        if not (math.isfinite(value) and value > 0):
            raise ValueError(
                f"`loss_scale` must be a positive finite number of standard deviations "
                f"(default {DEFAULT_LOSS_SCALE[loss]} for {loss!r}); got {loss_scale!r}."
            )
    scale = jnp.asarray(loss_scale)
    if not jnp.issubdtype(scale.dtype, jnp.floating):
        scale = scale.astype(float)
    return RobustLoss(loss, scale)
