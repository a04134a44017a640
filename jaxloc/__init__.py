"""jaxloc: cooperative localization of a heterogeneous robot team in unknown 3D space.

jaxloc computes in the dtype of its inputs and never changes JAX's configuration.
Solvers and statistics are meant to run in float64: turn on JAX's 64-bit mode before
creating any array, `jax.config.update("jax_enable_x64", True)` (the `jaxloc` command
does). Without it, JAX's default float is float32 and so is everything jaxloc builds
(scenarios, rigs, studies); float32 inputs stay float32 either way.

One exception, for the CPU backend only: with jaxlib 0.10.2 or 0.11.0, importing jaxloc
before JAX's backend starts adds `--xla_cpu_experimental_ynn_fusion_type=` to `XLA_FLAGS`
(unless `XLA_FLAGS` already sets it), turning off XLA:CPU's YNN fusions, which crash those
releases at random on x86-64 (jax-ml/jax#39257, #40412).
"""

from ._core.xla_workaround import avoid_ynn_crash as _avoid_ynn_crash


_avoid_ynn_crash()

from ._cameras.files import (
    Camchain as Camchain,
    camchain_from_kalibr as camchain_from_kalibr,
    camera_from_dict as camera_from_dict,
    camera_from_kalibr as camera_from_kalibr,
    camera_to_dict as camera_to_dict,
    camera_to_kalibr as camera_to_kalibr,
    load_camchain as load_camchain,
    load_camera as load_camera,
    save_camchain as save_camchain,
    save_camera as save_camera,
)
from ._cameras.models import (
    AbstractCamera as AbstractCamera,
    OmniCamera as OmniCamera,
    PinholeCamera as PinholeCamera,
    project_with_jacobian_autodiff as project_with_jacobian_autodiff,
    PTZCamera as PTZCamera,
    ZoomTable as ZoomTable,
)
from ._cameras.presets import (
    field_of_view as field_of_view,
    paper_omni_camera as paper_omni_camera,
    paper_overhead_camera as paper_overhead_camera,
    paper_ptz_camera as paper_ptz_camera,
    R_BODY_OMNI as R_BODY_OMNI,
    R_BODY_OVERHEAD as R_BODY_OVERHEAD,
    R_BODY_PTZ as R_BODY_PTZ,
)
from ._core.batching import map_problems as map_problems
from ._core.compiler import compiled_ahead as compiled_ahead, compiler_options as compiler_options
from ._core.poses import (
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
from ._core.results import (
    RESULTS as RESULTS,
    status_code as status_code,
    status_messages as status_messages,
    status_names as status_names,
)
from ._cycle.estimate import (
    CycleCovariance as CycleCovariance,
    CycleEstimate as CycleEstimate,
    CycleStarts as CycleStarts,
    FitCheck as FitCheck,
    rejected_sightings as rejected_sightings,
    RejectedSightings as RejectedSightings,
)
from ._cycle.layout import (
    CAMERAS as CAMERAS,
    move_start_step as move_start_step,
    moving_robot as moving_robot,
    num_moves as num_moves,
    num_placements as num_placements,
    num_steps as num_steps,
    placement_ids as placement_ids,
)
from ._cycle.observations import (
    CycleObservations as CycleObservations,
    CyclePoses as CyclePoses,
)
from ._cycle.rig import Rig as Rig
from ._design.formation import (
    constraint_margins as constraint_margins,
    constraint_penalty as constraint_penalty,
    constraint_values as constraint_values,
    Formation as Formation,
    FORMATION_FIELDS as FORMATION_FIELDS,
    formation_filter as formation_filter,
    Limits as Limits,
    paper_fixed_moves as paper_fixed_moves,
    place_fixed as place_fixed,
    Placement as Placement,
)
from ._design.search import (
    crlb_objective as crlb_objective,
    design_formation as design_formation,
    design_penalty as design_penalty,
    DesignResult as DesignResult,
    evaluate_formation as evaluate_formation,
    mc_objective as mc_objective,
    objective_value as objective_value,
    rmse_ci as rmse_ci,
    rmse_table as rmse_table,
    simulate_formation as simulate_formation,
)
from ._model.covariance import (
    crlb_rmse as crlb_rmse,
    cycle_covariance as cycle_covariance,
    cycle_crlb as cycle_crlb,
)
from ._refine.cycle import refine_cycle as refine_cycle
from ._refine.pose import POSE_SOLVERS as POSE_SOLVERS, refine_overhead_pose as refine_overhead_pose
from ._sim.defects import (
    add_outliers as add_outliers,
    corrupt_observations as corrupt_observations,
    DEFECTS as DEFECTS,
    drop_sightings as drop_sightings,
)
from ._sim.scenario import astype as astype, Scenario as Scenario
from ._sim.scenario_file import (
    load_scenario as load_scenario,
    save_scenario as save_scenario,
    scenario_from_dict as scenario_from_dict,
    scenario_to_dict as scenario_to_dict,
)
from ._sim.simulate import (
    CycleTruth as CycleTruth,
    noiseless as noiseless,
    simulate_cycle as simulate_cycle,
)
from ._sim.world import (
    AbstractSurface as AbstractSurface,
    body_frame_on_surface as body_frame_on_surface,
    body_pose_on_surface as body_pose_on_surface,
    FlatSurface as FlatSurface,
    formation_xy as formation_xy,
    FunctionSurface as FunctionSurface,
    SaddleSurface as SaddleSurface,
    SinusoidSurface as SinusoidSurface,
)
from ._solvers.dlt import paper_linear_pose as paper_linear_pose
from ._solvers.localize import localize_cycle as localize_cycle
from ._solvers.mutual import (
    mutual_localization as mutual_localization,
    MutualSolution as MutualSolution,
)
from ._solvers.overhead import solve_overhead_pose as solve_overhead_pose
from ._solvers.p3p import p3p as p3p, P3PSolution as P3PSolution
from ._solvers.pose_problem import PoseSolution as PoseSolution
from ._study.cluster import (
    run_study_on_ray as run_study_on_ray,
    stream_study_on_ray as stream_study_on_ray,
)
from ._study.engine import (
    balanced_chunk_size as balanced_chunk_size,
    MICRO_BATCH as MICRO_BATCH,
    precompile as precompile,
    run_chunk as run_chunk,
    run_study as run_study,
    stream_study as stream_study,
    trial_key as trial_key,
)
from ._study.stats import (
    describe as describe,
    StreamingSummary as StreamingSummary,
    summarize as summarize,
)
from ._study.trial import (
    METHODS as METHODS,
    run_trial as run_trial,
    TrialErrors as TrialErrors,
)
from ._track.chain import chain_estimates as chain_estimates
from ._track.one_step import (
    localize_one_step as localize_one_step,
    one_step_bound as one_step_bound,
    OneStepEstimate as OneStepEstimate,
    OneStepPrior as OneStepPrior,
    Snapshot as Snapshot,
)
from ._track.scenario import (
    load_track_scenario as load_track_scenario,
    save_track_scenario as save_track_scenario,
    track_scenario_from_dict as track_scenario_from_dict,
    track_scenario_to_dict as track_scenario_to_dict,
    TrackScenario as TrackScenario,
)
from ._track.simulate import (
    simulate_track as simulate_track,
    TrackObservations as TrackObservations,
    TrackTruth as TrackTruth,
)
from ._track.smoother import SmootherEstimate as SmootherEstimate
from ._track.study import (
    run_track_chunk as run_track_chunk,
    run_track_study as run_track_study,
    summarize_track as summarize_track,
)
from ._track.tracker import track_cycles as track_cycles, TrackEstimates as TrackEstimates
from ._track.trial import (
    run_track_trial as run_track_trial,
    TRACK_METHODS as TRACK_METHODS,
    TrackErrors as TrackErrors,
)
from ._vision.calibrate import (
    calibrate_omni as calibrate_omni,
    calibrate_omni_corners as calibrate_omni_corners,
    calibrate_pinhole as calibrate_pinhole,
    calibrate_ptz as calibrate_ptz,
    Calibration as Calibration,
    find_corners as find_corners,
    object_points as object_points,
    omni_initial_guess as omni_initial_guess,
    parse_board as parse_board,
    ZoomCalibration as ZoomCalibration,
)
from ._vision.localize import (
    detect_team_images as detect_team_images,
    ImageLocalization as ImageLocalization,
    localize_images as localize_images,
    observations_from_detections as observations_from_detections,
    rig_for as rig_for,
    team_from_rendered as team_from_rendered,
)
from ._vision.markers import (
    annulus_mask as annulus_mask,
    DEFAULT_MARKER_COLORS as DEFAULT_MARKER_COLORS,
    detect_markers as detect_markers,
    MarkerColor as MarkerColor,
    MarkerDetection as MarkerDetection,
    read_image as read_image,
)
from ._vision.render import (
    annulus_of as annulus_of,
    DEFAULT_MARKER_BGR as DEFAULT_MARKER_BGR,
    render_chessboard as render_chessboard,
    render_cycle as render_cycle,
    render_markers as render_markers,
    sphere_center_pixel as sphere_center_pixel,
)
from ._vision.team import load_team as load_team, save_team as save_team, Team as Team


def _package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("jaxloc")
    except PackageNotFoundError:  # a source tree that is not installed
        return "0.0.0+unknown"


__version__ = _package_version()
"""jaxloc's version, from the installed package's metadata."""
