"""The camera models' single import point for the rest of jaxloc.

The models live one per module: the interface and shared validation in `base.py`, the
distortion models in `distortion.py`, and [`jaxloc.PinholeCamera`][] (`pinhole.py`),
[`jaxloc.PTZCamera`][] with [`jaxloc.ZoomTable`][] (`ptz.py`) and
[`jaxloc.OmniCamera`][] (`omni.py`). Code outside `jaxloc._cameras` imports them from
here, so that moving a model between those modules never touches its users.
"""

from .base import (
    AbstractCamera as AbstractCamera,
    project_with_jacobian_autodiff as project_with_jacobian_autodiff,
)
from .distortion import DISTORTION_MODELS as DISTORTION_MODELS
from .omni import OmniCamera as OmniCamera
from .pinhole import PinholeCamera as PinholeCamera
from .ptz import PTZCamera as PTZCamera, ZoomTable as ZoomTable
