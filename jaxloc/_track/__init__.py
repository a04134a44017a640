"""Tracking the team over many cycles (issue 21): multi-cycle scenarios and their
simulation, chaining cycles into the first cycle's frame, the fixed-lag smoother with its
bound, one-step localization of the climbing robot, and the tracking study.

Modules, in the order data flows: `scenario` (a [`jaxloc.TrackScenario`][]: a cycle's
scenario plus the climbing robot's motion and odometry, and its file section) <- `simulate`
(K cycles) ; `frames` (SE(3) covariance helpers) <- `chain`, `smoother`, `one_step` <-
`tracker` (one run: every estimator over K cycles) <- `trial` (one scored Monte Carlo run
with its bounds) <- `study` (chunked, resumable study and per-cycle statistics).

Imports everything below the studies (`_core`, `_cameras`, `_cycle`, `_model`, `_solvers`,
`_refine`, `_sim`) and `_study` (the chunk files, the trial's scoring); never `_cli`.
"""
