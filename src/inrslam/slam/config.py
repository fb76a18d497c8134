"""Options of the SLAM loop (defaults = the paper's settings, supplementary §1 / docs/spec.md §7)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field


class PoseParam(str, enum.Enum):
    """How a pose is optimised."""

    QUAT = "quat"  # unnormalised quaternion + translation (the paper)
    SE3 = "se3"  # left-multiplied se(3) twist around the initial pose (smooth at zero)


class PoseInit(str, enum.Enum):
    """Where tracking starts from."""

    CONST_VELOCITY = "const_velocity"  # constant-velocity prediction (the paper)
    GICP = "gicp"  # GICP of the frame's depth onto the previous frame's, checked; constant velocity when it fails


class GicpTarget(str, enum.Enum):
    """What a frame's depth is registered onto."""

    PREVIOUS = "previous"  # the previous frame (frame-to-frame odometry)
    KEYFRAME = "keyframe"  # the last GICP keyframe, renewed on motion / overlap loss (drift per keyframe, not frame)
    LOCAL_MAP = "local_map"  # the last `local_map_keyframes` GICP keyframes merged in the world (frame-to-model)


@dataclass
class GicpConfig:
    """GICP initialiser settings (`slam.gicp.*`)."""

    downsample: float = 0.02  # voxel size of the point clouds, metres
    max_corr: float = 0.1  # maximum correspondence distance, metres
    neighbors: int = 10  # neighbours for the per-point covariances
    max_iterations: int = 30  # Gauss-Newton iterations
    eps_trans: float = 1e-5  # stop when an update moves less than this, metres ...
    eps_rot: float = 1e-5  # ... and rotates less than this, radians (small_gicp's default, 1 mm / 0.1 deg, stops early)
    pixel_stride: int = 2  # back-project every N-th pixel in u and v
    depth_filter: int = 0  # bilateral filter of the depth before back-projection: window radius in pixels (0 = off)
    depth_noise: float = 0.0  # depth noise std at 1 m (grows with depth^2), metres; 0 = estimated from each frame
    filter_min_noise: float = 0.002  # filter only depth whose noise at 1 m is at least this, metres (Kinect: ~0.001)
    max_depth: float = 6.0  # ignore depth beyond this, metres
    min_fitness: float = 0.6  # minimum inlier fraction of the source points
    degeneracy_ratio: float = 0.005  # minimum lambda_min / lambda_max of the rotation and translation Hessian blocks
    max_step: float = 0.3  # metres; a relative motion larger than this from the prediction is rejected
    threads: int = 1  # small_gicp threads (1 keeps results independent of the thread count)
    target: GicpTarget = GicpTarget.PREVIOUS  # register onto the previous frame, or onto a GICP keyframe
    kf_dist: float = 0.15  # target = keyframe: a new GICP keyframe after this much motion from it, metres ...
    kf_angle: float = 10.0  # ... or this much rotation, degrees ...
    kf_fitness: float = 0.85  # ... or when the inlier fraction drops below this
    local_map_keyframes: int = 5  # target = local_map: GICP keyframes merged into the target
    rigid_init: bool = True  # GICP starts from the nearest rigid pose to its prediction (small_gicp keeps any
    # scale / shear of its start, and constant-velocity predictions compound it: off, poses drift from orthonormal)



@dataclass
class SdfTrackConfig:
    """Point-to-surface tracking against the map (`slam.sdf_track.*`): Gauss-Newton on the SDF of the frame's
    back-projected depth points, r_i = SDF(T p_i) (metres), robust (Huber) weights, stop on a small step."""

    iters: int = 0  # maximum Gauss-Newton iterations per frame (0 = off)
    only_on_init_failure: bool = False  # run only when the geometric initialiser failed its checks (wall views);
    # every frame when there is none (slam.init=const_velocity)
    points: int = 8192  # depth points per frame (drawn once per frame)
    huber: float = 0.01  # Huber threshold, metres
    band: float = 0.5  # use points with |SDF| < band x truncation (where the field was trained as a distance)
    min_points: int = 200  # fewer usable points: skip (keep the pose it was given) and log it
    tol_trans: float = 2e-5  # stop when the step is below this, metres ...
    tol_rot: float = 2e-5  # ... and below this, radians
    damping: float = 1e-4  # Levenberg-Marquardt damping, relative to the Hessian's mean diagonal
    max_step: float = 0.1  # metres; a total correction larger than this is rejected (pose kept)


@dataclass
class PhotoConfig:
    """Photometric refinement after the geometric initialiser (`slam.photo.*`, `inrslam.slam.photometric`): direct
    alignment of the frame's grey image onto a photometric keyframe (its colour and filtered depth), coarse to fine."""

    enabled: bool = False  # refine every frame's pose photometrically (after GICP; also where GICP failed)
    rescue: bool = True  # where GICP failed its checks, a successful refinement stands (no neural tracking)
    min_depth_noise: float = 0.0005  # only on depth at least this noisy (std at 1 m, metres, estimated per frame)
    levels: int = 3  # pyramid levels (each halves the image)
    iters: int = 10  # Gauss-Newton iterations per level (cap; stops on a step below tol)
    tol: float = 1e-6  # stop when the twist's norm is below this
    grad_threshold: float = 0.01  # reference pixels need an intensity gradient above this (grey in [0, 1] per px)
    max_points: int = 30000  # reference pixels per level (a random subset beyond)
    min_points: int = 300  # fewer valid residuals at the finest level (a quarter per coarser level): keep the pose
    huber: float = 0.05  # Huber threshold on the intensity residual
    max_step: float = 0.01  # metres; a refinement moving a well-conditioned GICP pose further than this and ...
    jump_factor: float = 4.0  # ... this times the median move of the last `jump_window` accepted refinements is
    jump_window: int = 20  # rejected (real sensors: colour and depth disagree by millimetres on every frame) ...
    weak_degeneracy: float = 0.05  # ... where GICP's degeneracy is below this (a near-degenerate view) or GICP
    weak_max_step: float = 0.05  # failed its checks, the bound is this, metres
    jump_rms_factor: float = 0.0  # a refinement beyond the bound stands when its residual RMS is at most this x
    # the first one onto its keyframe (the image is explained as well as usual: GICP is the one off; 0 = off)
    kf_dist: float = 0.3  # a new photometric keyframe after this much motion from it, metres ...
    kf_angle: float = 25.0  # ... or this much rotation, degrees, ...
    kf_rms_factor: float = 0.0  # ... or once the residual RMS exceeds this x the first one onto it (0 = off)
    kf_refs: int = 1  # a new photometric keyframe's pose: the mean of its alignments onto the last kf_refs
    # keyframes (1 = only the one it was aligned onto; more: off in every preset, docs/accurate.md)
    track_refs: int = 1  # each frame is aligned onto the last track_refs photometric keyframes at once (their
    # residuals in one Gauss-Newton; 1 = the current one only; `accurate`: 2, docs/accurate.md)
    affine_light: bool = False  # also fit an affine brightness change (1 + a) I + b of the reference (exposure)
    depth_weight: float = 0.0  # weight of a depth residual per reference point beside its intensity residual (the
    # current frame's depth where the point lands against the point's depth; 1 = as an intensity residual of the
    # same robust standard score; 0 = off; docs/accurate.md)
    gicp_prior: float = 0.0  # weight of GICP's pose and Hessian as a prior of the alignment (0 = off; 1 = each
    # residual's own variance; docs/accurate.md)
    skip_stale: bool = False  # a frame whose colour or depth is bit-identical to the previous frame's (a dropped
    # sensor frame repeated: colour and depth from different times; 7-Scenes) is not refined nor made a photometric
    # keyframe; its pose is GICP of its depth onto the previous frame's (logged as `stale`; docs/accurate.md)


@dataclass
class LostConfig:
    """Lost-tracking detection and recovery (rendered tracking only; docs/reliability.md)."""

    factor: float = 5.0  # a frame is lost when its tracking loss exceeds factor x the median of recent frames
    window: int = 20  # recent frames whose median loss is the running level (init's final loss seeds it)
    recover: bool = False  # re-track a lost frame from GICP onto the previous frame and from the previous pose
    recover_max_corr: float = 0.3  # metres, GICP correspondence distance of the recovery (wide: large motion)
    stop_after: int = 0  # stop the run after this many consecutive lost frames (0 = never: log and go on)


@dataclass
class LoopConfig:
    """Loop closure (`slam.loop.*`, on with `slam.loop_closure`; docs/loop_closure.md). At every new keyframe:
    detect keyframes seen long before whose view overlaps it, verify them by GICP (with a drift bound, a significance
    test and a colour check), add the verified loop edge to a pose graph of the keyframes (GTSAM; odometry edges as
    tracked), move the keyframes (their frames follow), and re-fit the map from the ray store once the corrections
    since the last re-fit add up to `refit_min_move`."""

    min_gap: int = 100  # frames between a keyframe and an older keyframe it may close a loop with
    max_dist: float = 0.8  # metres between their camera centres (current estimates) for a candidate ...
    max_angle: float = 45.0  # ... and degrees between their viewing directions
    min_overlap: float = 0.3  # fraction of the keyframe's depth points landing on the candidate's depth (reprojected)
    overlap_tol: float = 0.1  # metres: |reprojected depth - candidate's depth| within this counts as overlap
    candidates: int = 3  # the best candidates by overlap that are verified (each verified one is a loop edge)
    corr_stages: list[float] = field(default_factory=lambda: [0.25, 0.1, 0.05])  # metres, GICP correspondence
    # distance of each verification stage, coarse to fine (each starts where the previous ended)
    coarse_downsample: float = 0.05  # metres: voxel size of the clouds of the coarse stages (all but the last; the
    # last uses slam.gicp.downsample; 0 = that for every stage)
    epsilon: float = 1e-4  # a verification stage has converged once a GICP step moves less than this (metres and
    # radians)
    min_fitness: float = 0.45  # final-stage inlier fraction of the keyframe's points (earlier stages: 0.3)
    max_correction: float = 0.05  # metres a loop may move the keyframe, plus ...
    max_correction_per_m: float = 0.05  # ... this per metre travelled since the candidate (a drift bound)
    max_correction_angle: float = 10.0  # degrees a loop may turn the keyframe
    consistency: float = 0.05  # metres: verified candidates placing the keyframe further apart are ambiguous (rejected)
    min_correction: float = 0.005  # metres: a loop onto a place with no loop edge yet must move the keyframe at least
    # this much (smaller: within the verification's own error, the edge would only add it; 0 = off)
    color_check: bool = True  # a verified loop must explain the two views' colour better than the current estimate
    # does (the keyframe's pixels warped into the candidate: a cue independent of the depth registration)
    color_margin: float = 0.05  # a loop onto a place with no loop edge yet must lower that colour disagreement by at
    # least this fraction of the estimate's (a correction the colour cannot tell from the estimate is not confirmed;
    # further edges onto a closed place need only lower it; 0 = only lower)
    refit_min_move: float = 0.01  # metres: re-fit the map once the corrections since the last re-fit (the largest
    # keyframe move of each) add up to this
    refit_final_move: float = 0.001  # metres: the same rule after the last frame's graph (one re-fit per run, so a
    # smaller threshold: on `symmetric` 2 edges moved keyframes by <= 4 mm and left the map unfitted to them)
    odom_sigma_t: float = 0.01  # pose-graph std of an odometry edge (consecutive keyframes), metres ...
    odom_sigma_r: float = 0.005  # ... and radians
    loop_sigma_t: float = 0.01  # std of a loop edge, metres ...
    loop_sigma_r: float = 0.005  # ... and radians
    huber: float = 1.345  # Huber threshold of the loop edges, in standard deviations (0 = no robust kernel)
    refit_iters: int = 40  # map re-fit iterations after a closure (rays from every keyframe, at the new poses)
    refit_pixels: int = 2048  # rays per re-fit iteration


@dataclass
class RefineConfig:
    """A pose graph of every frame after the last one (`slam.refine.*`, on with `slam.refine.enabled`;
    `inrslam.slam.trajectory_graph`, docs/accurate.md "A final pose graph over photometric links"): each frame is
    aligned photometrically (slam.photo's settings) onto the frames `gaps` before it, from their tracked relative pose;
    those links and the tracked relative poses of consecutive frames are optimised together (GTSAM, frame 0 fixed) and
    replace the trajectory. The map is not re-fitted to the new poses; runs with given poses (slam.poses) track
    nothing and are not refined."""

    enabled: bool = False  # refine the whole trajectory once, after the last frame
    gaps: list[int] = field(default_factory=lambda: [8, 16])  # each frame is linked to the frames this many before it
    sigma_t: float = 0.005  # std of a photometric link, metres ...
    sigma_r: float = 0.005  # ... and radians
    odom_sigma_t: float = 0.002  # std of the tracked relative pose of consecutive frames, metres ...
    odom_sigma_r: float = 0.002  # ... and radians
    huber: float = 2.0  # Huber threshold of the links, in standard deviations (0 = no robust kernel)
    max_shift: float = 0.03  # metres; a link whose alignment moved the tracked relative pose further is left out


@dataclass
class SlamConfig:
    """Tracking, mapping and keyframe settings."""

    init_iters: int = 500  # optimisation iterations on the first frame
    init_pixels: int = 2048  # rays per initialisation iteration
    init_stop_window: int = 0  # end initialisation early once the mean loss of the last this-many iterations is less
    # than init_stop_tol below the mean of the window before it (0 = off: all init_iters; docs/speed.md)
    init_stop_tol: float = 0.01  # relative fall of the windowed mean loss below which initialisation ends
    track_iters: int = 20  # pose iterations per frame
    track_pixels: int = 1024  # rays per tracking iteration (drawn once per frame)
    track_lr: float = 1e-3  # Adam learning rate of the pose
    track_only_on_init_failure: bool = False  # rendered tracking only when the geometric initialiser failed (every
    # frame without one: slam.init=const_velocity)
    track_edge: int = 20  # pixels ignored at the image border during tracking
    keep_best_pose: bool = True  # keep the lowest-loss evaluated pose (False: the last evaluated pose)
    eval_final_pose: bool = True  # also evaluate the pose after the final update (the original never did)
    faithful_relative: bool = False  # trajectory_relative.txt as the original (Co-SLAM) composes it, c2w_t c2w_k^-1
    # c2w'_k, not c2w'_k c2w_k^-1 c2w_t (the frame held rigid to its bundle-adjusted keyframe; docs/differences.md)
    pose_param: PoseParam = PoseParam.QUAT  # pose parameterisation for tracking and BA
    const_velocity: bool = True  # constant-velocity motion prediction
    init: PoseInit = PoseInit.CONST_VELOCITY  # tracking's starting pose: prediction, or GICP onto the previous frame
    gicp: GicpConfig = field(default_factory=GicpConfig)  # init = gicp; its depth filter serves map_filtered_depth
    photo: PhotoConfig = field(default_factory=PhotoConfig)  # photometric refinement (after the initialiser)
    sdf_track: SdfTrackConfig = field(default_factory=SdfTrackConfig)  # point-to-surface refinement (before Adam)
    lost: LostConfig = field(default_factory=LostConfig)  # lost-tracking detection / recovery
    map_every: int = 5  # mapping + keyframe every N frames
    map_iters: int = 20  # mapping iterations per call
    map_pixels: int = 2048  # rays per mapping iteration drawn from the keyframe store
    map_current_min: int = 100  # min current-frame rays per mapping iteration (max(map_pixels/#KF, this))
    map_lr: float = 0.01  # Adam learning rate of the scene parameters
    map_filtered_depth: bool = False  # map noisy depth after slam.gicp's bilateral filter (needs gicp.depth_filter>0)
    # depth below slam.gicp.filter_min_noise is mapped as measured; tracking still registers the raw depth
    bundle_adjust: bool = True  # optimise keyframe poses (first keyframe fixed) during mapping
    ba_lr: float = 1e-3  # Adam learning rate of keyframe poses
    ba_pose_every: int = 5  # pose step every N mapping iterations (gradients accumulate in between)
    keyframe_fraction: float = 0.05  # fraction of each keyframe's pixels kept for global sampling (Table 3: 0.005)
    keyframe_edge_fraction: float = 0.0  # and up to this fraction of its pixels from depth edges (silhouettes) ...
    keyframe_edge_jump: float = 0.05  # ... pixels whose depth differs from a 4-neighbour's by more, metres
    keyframe_edge_near_only: bool = False  # ... only the near side of each edge (a pixel whose 8-neighbour is farther)
    max_pose_jump: float = 0.5  # metres; a tracked pose moving more than this from the prediction is rejected (0 =
    # never, as the original: docs/differences.md row 24)
    loop_closure: bool = False  # detect revisits, optimise the keyframe pose graph, re-fit the map (slam.loop)
    loop: LoopConfig = field(default_factory=LoopConfig)  # settings of loop closure
    refine: RefineConfig = field(default_factory=RefineConfig)  # a final pose graph of every frame (off)
    poses: str = ""  # mapping only, with given poses: "gt" (the dataset's) or a TUM file; "" = track (SLAM)
    poses_tolerance: float = 0.02  # seconds; each frame takes the pose file's pose nearest in time, at most this far
    poses_anchor: bool = True  # move a pose file's trajectory so frame 0 sits at the dataset's frame-0 pose
    checkpoint_every: int = 50  # frames between checkpoints (0 = only at the end)
    mesh_every: int = 0  # extract an intermediate mesh every N frames (0 = only at the end)


@dataclass
class MeshConfig:
    """Marching cubes on the SDF inside the scene bounds."""

    enabled: bool = True  # extract mesh.ply at the end
    resolution: float = 0.02  # grid spacing in metres
    chunk: int = 65536  # points per field query
    color: bool = True  # query vertex colours from the colour decoder


@dataclass
class OutputConfig:
    """What a run writes besides the mandatory outputs."""

    tensorboard: bool = True  # TensorBoard scalars when tensorboard is installed
    keep_checkpoint: bool = True  # keep checkpoints/ of a finished run (false: delete it once the run is complete)
    renders: bool = True  # renders/ (held-out frames: observed, rendered, depth, error), trajectory.png, mesh.png

