"""jaxloc: cooperative localization of a heterogeneous robot team in unknown 3D space.

Importing jaxloc enables JAX's 64-bit mode (`jax_enable_x64`): solvers and statistics
run in float64 by default. Pass float32 arrays (or cast a scenario with
`jaxloc.astype`) to run in float32.
"""

import jax


jax.config.update("jax_enable_x64", True)

from ._pose import (
    kabsch as kabsch,
    pose_from_opencv as pose_from_opencv,
    pose_to_opencv as pose_to_opencv,
    position_error as position_error,
    project_to_so3 as project_to_so3,
    rotation_angle as rotation_angle,
    rotation_error as rotation_error,
    rotation_from_ypr as rotation_from_ypr,
    ypr_from_rotation as ypr_from_rotation,
)
from ._results import (
    RESULTS as RESULTS,
    status_code as status_code,
    status_messages as status_messages,
    status_names as status_names,
)


__version__ = "0.1.0"
