"""Result codes shared by every jaxloc solver and by the Monte Carlo studies."""

import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Int


class RESULTS(optx.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Per-solve status. `RESULTS.successful` is the only good outcome.

    Extends `optimistix.RESULTS`, so a refinement's own result can be promoted into it
    with `RESULTS.promote(sol.result)`. Inside `jit`/`vmap` a status is an array; use
    [`jaxloc.status_code`][] to get plain integers for storage and statistics.
    """

    degenerate_configuration = (
        "The robots are (nearly) collinear or coincident; the geometry does not fix the pose."
    )
    rank_deficient = (
        "The linear system is rank deficient (e.g. the paper's Eq. 6 on coplanar points)."
    )
    too_few_points = "Fewer points than the solver needs."
    nonfinite_observation = "An observation (bearing, pixel or odometry) is NaN or infinite."
    no_valid_solution = "No candidate pose puts every point in front of the camera."
    not_visible = "A required robot was outside a camera's field of view."
    scale_unobservable = "The odometry does not fix the metric scale (zero-length moves)."
    inconsistent_fit = (
        "The estimate's chi-square is implausibly large for the noise model "
        "(99.9% quantile): a wrong local minimum or branch, or an outlier measurement."
    )
    ambiguous = (
        "Another distinct pose fits the measurements about as well or better (a minimum "
        "less than chi-square 4 above the estimate's, or several exact P3P roots): the data "
        "do not tell which is the pose; the returned one is a candidate, not the answer."
    )
    unobservable = (
        "The measurements do not determine the pose: the Fisher information is singular, "
        "the bound is absurd for the formation's size, or there are no more measurements "
        "than unknowns (too few distinct placements seen, a robot no camera sees, a "
        "degenerate formation)."
    )
    invalid_observation = (
        "An observation is outside its domain (a zero or negative odometry distance or "
        "standard deviation)."
    )


def status_code(result: RESULTS) -> Int[Array, "..."]:
    """Plain `int32` code of a [`jaxloc.RESULTS`][] item (0 = successful). Works inside jit."""
    return jnp.asarray(result._value, dtype=jnp.int32)


def status_names() -> dict[int, str]:
    """Map from integer status code to the item's name, e.g. `{0: "successful", ...}`."""
    return {int(item._value): name for name, item in RESULTS._name_to_item.items()}


def status_messages() -> dict[int, str]:
    """Map from integer status code to the item's human-readable message."""
    return {int(item._value): RESULTS[item] for item in RESULTS._name_to_item.values()}


def raise_if_failed(obj, result: RESULTS, throw: bool):
    """Attach a runtime error to `obj` if `throw` and `result` is not successful."""
    if throw:
        return result.error_if(obj, result != RESULTS.successful)
    return obj
