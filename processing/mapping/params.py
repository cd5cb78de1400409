"""Parameters of the map pipeline, one class per stage (:class:`MapParams` holds them all)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class SelectParams:
    """Selection: which returns are kept, how the depth image is filtered, voxel size."""

    voxel_m: float = 0.02
    max_range_m: float = 4.0
    depth_median_px: int = 5  # median filter of an organised depth image (0: off)
    pixel_stride: int = 2  # ... then averaged in blocks of this many pixels squared


@dataclass(frozen=True)
class TrackingParams:
    """Tracking: each cloud registered to the map of all earlier ones, held by the odometry
    as far as the data show the odometry to be right (:mod:`processing.mapping.tracking`)."""

    enabled: bool = True
    # the odometry's error per step until ``warm_up`` steps measured it: generous
    initial_sigma_m: float = 0.05
    initial_sigma_deg: float = 5.0
    warm_up: int = 5
    min_sigma_m: float = 0.002  # the measured error is not trusted below these
    min_sigma_deg: float = 0.2
    max_distance_m: float = 0.3  # the widest correspondence search (3 sigma of the motion error)
    final_distance_voxels: float = 1.5  # the last search distance, in voxels of the selection
    max_iterations: int = 15
    # an iteration's step (rad, m) below this ends a search distance: coarse ones only bring
    # the cloud near (a millimetre a metre out), the last one refines to a tenth of that,
    # far below any ToF camera's range noise
    coarse_tolerance: float = 1e-3
    final_tolerance: float = 1e-4
    min_normal_cos: float = 0.7  # a match's normals (cloud's and map's) agree this well
    # directions the geometry fixes less than this share of the strongest half do: prior only
    degenerate_ratio: float = 0.001
    min_points: int = 50  # fewer points (cloud or map in view): the prediction is used
    # effective error of one point-to-plane residual in the graph's tracked edge (neighbouring
    # residuals are correlated: far above the noise)
    icp_sigma_m: float = 0.06


@dataclass(frozen=True)
class IcpParams:
    """Matching, rejection and alignment of one pair of clouds, and the stopping rules."""

    use_fpfh: bool = False  # FPFH refinement of the odometry guess (ambiguous on repeating beams)
    fpfh_radius_m: float = 0.1
    metric: Literal["point_to_plane", "point_to_point", "generalized"] = "point_to_plane"
    max_correspondence_m: float = 0.06
    tukey_m: float = 0.03
    relative_fitness: float = 1e-4
    relative_rmse: float = 1e-4
    # from the odometry or the current estimate ICP converges in a few (more: no better, measured)
    max_iterations: int = 10
    max_correction_m: float = 0.10
    max_correction_deg: float = 10.0
    # below it (mid-turn views that barely overlap) ICP lands centimetres off: odometry instead
    min_fitness: float = 0.6
    min_points: int = 10  # clouds with fewer points (after selection) are placed by odometry
    degenerate_ratio: float = 0.1
    # effective error of one point-to-plane residual (neighbouring residuals are correlated: > the
    # noise)
    icp_sigma_m: float = 0.06


@dataclass(frozen=True)
class LoopParams:
    """Loop closures: which earlier clouds are candidates and when a closure is kept."""

    radius_m: float = 0.25  # earlier clouds this close (sensor positions) are loop candidates ...
    min_gap: int = 12  # ... at least this many clouds back ...
    max_view_angle_deg: float = 45.0  # ... whose optical axes are this close
    per_cloud: int = 2
    # coarse correspondence distances tried before a loop's ICP
    search_m: tuple[float, ...] = (
        0.3,
        0.15,
    )
    max_correction_m: float = 0.3  # a loop closure may correct this much accumulated drift ...
    max_correction_deg: float = 15.0  # ... and this much heading
    min_fitness: float = 0.5  # it is kept when this share of its points matched ...
    min_structure_fitness: float = 0.8  # ... and this share of its structure (not the plate)
    min_structure_points: int = 50
    # ... and this share of each cloud lies within loop_overlap_m of the other (both ways)
    min_overlap: float = 0.6
    overlap_m: float = 0.02
    # from optimised poses a candidate must overlap this well before it is searched
    prefilter_m: float = 0.05
    preference: float = 1.0  # Open3D's line process: lower prunes disagreeing loop closures sooner


@dataclass(frozen=True)
class OdometryParams:
    """The odometry edges' errors (per step, random walks in distance) and their calibration."""

    sigma_frac: float = 0.05  # odometry error per step: this fraction of its length ...
    sigma_deg_per_m: float = 15.0  # ... and this heading error per metre driven
    sigma_floor_m: float = 0.002
    # raise the odometry's errors (heading and distance) to the heading error measured against ICP
    calibrate: bool = True


@dataclass(frozen=True)
class PlaneParams:
    """Plane landmarks: association of a cloud's planes to landmarks and their weight."""

    # large planes (deck plate, web, stiffener faces) as landmarks of the pose graph
    enabled: bool = True
    max_angle_deg: float = 5.0  # a cloud's plane is a landmark's when this close in angle ...
    max_offset_m: float = 0.03  # ... and in distance (current estimate)
    sigma_m: float = 0.06  # effective error of one inlier's distance to its landmark
    min_sightings: int = 3  # a landmark seen fewer times ties nothing


@dataclass(frozen=True)
class MapParams:
    """Options of the whole pipeline: each stage's parameters and the pose graph's own."""

    select: SelectParams = field(default_factory=SelectParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)
    icp: IcpParams = field(default_factory=IcpParams)
    loops: LoopParams = field(default_factory=LoopParams)
    odometry: OdometryParams = field(default_factory=OdometryParams)
    planes: PlaneParams = field(default_factory=PlaneParams)
    neighbours: int = 2  # edges from each cloud to the next few (tracked clouds: the next one)
    pose_graph: bool = True
    # tracked steps tied to the robot's wheel model fitted to them (processing.mapping.wheels)
    wheels: bool = True
    # False: the initial poses are better than ICP can do (visual odometry); only fuse
    refine: bool = True
    map_voxel_m: float = 0.01
