"""The simulated world: surfaces, scenarios and their files, one simulated cycle.
Imports `_core`, `_cameras`, `_cycle`.
"""
