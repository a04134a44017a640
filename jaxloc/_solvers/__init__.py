"""Closed-form solvers: mutual localization, P3P, the overhead pose (paper Eq. 6 and
robust), the moving strategies. Imports `_core`, `_cameras`, `_cycle`, `_model` (the
gates).
"""
