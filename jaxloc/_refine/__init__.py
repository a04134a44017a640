"""Maximum-likelihood refinement, covariance and Cramér–Rao bound of a cycle and of one
camera pose. Imports `_core`, `_cameras`, `_cycle`, `_solvers`.
"""
