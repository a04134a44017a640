"""Maximum-likelihood refinement of a whole cycle and of one camera pose. Imports `_core`,
`_cameras`, `_cycle`, `_model`, `_solvers`.
"""
