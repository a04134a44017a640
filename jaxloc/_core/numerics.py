"""Small numerical helpers shared by every module: finite values and finite gradients.

Each guards its singular point with a double `where`, so both the value and the gradient
stay finite there (the gradient at the singular point is 0).
"""

import jax.numpy as jnp
from jaxtyping import Array, Float


def safe_sqrt(x: Array) -> Array:
    """`sqrt(x)` for `x > 0`, else 0; gradient 0 (not inf/NaN) at `x <= 0`."""
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_norm(x: Float[Array, "... n"]) -> Float[Array, "..."]:
    """Euclidean norm over the last axis, with a zero (not NaN) gradient at `x = 0`."""
    return safe_sqrt(jnp.sum(x * x, axis=-1))


def safe_normalize(x: Float[Array, "... n"]) -> Float[Array, "... n"]:
    """`x / |x|` over the last axis; 0 where `x = 0`."""
    sq = jnp.sum(x * x, axis=-1, keepdims=True)
    ok = sq > 0
    return jnp.where(ok, x / jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def as_floating(x, dtype=None) -> Array:
    """`x` as a floating-point array: float arrays keep their dtype (float32 stays
    float32); anything else (lists, Python numbers, integer or bool arrays) becomes
    `dtype`, by default JAX's default float."""
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.floating):
        return x
    return x.astype(jnp.result_type(float) if dtype is None else dtype)
