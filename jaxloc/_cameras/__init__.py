"""Camera models and the paper's nominal cameras and mounts. Imports only `_core`.

`base` (the interface, validation, shared element-wise kernels) <- `distortion` <-
`pinhole` <- `ptz`; `omni` on `base` and `distortion`; `models` re-exports the models for
the rest of jaxloc; `presets` the paper's cameras; `files` the camera file formats.
"""
