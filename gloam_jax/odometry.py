"""LiDAR odometry: deskew, constant-velocity prediction, GICP to a local map of keyframes.

The register-frame loop reads in order: clean and crop the scan, deskew it with the current
velocity, prepare it (voxel grid, covariances), predict its pose with constant velocity,
register it (to the previous frame, or to the local map), check the solution's conditioning,
update the velocity and, past a distance or angle, add it to the map as a keyframe.
A run can stop and continue exactly: :meth:`Odometry.state` and :meth:`Odometry.restore`.

Poses are ``T_world_lidar`` at each frame's reference time (mid-sweep, see the simulator), the
world being the first frame's LiDAR frame. The velocity is the last frame-to-frame motion,
``xi = log(inv(T_prev) @ T_curr)`` over that frame's interval (geometry's tangent order); the
next frame's prediction and deskew scale it by the real time step, so a dropped scan (a gap in
the times) is predicted over its whole gap.
"""

from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import ClassVar, Literal

import numpy as np
from threadpoolctl import ThreadpoolController

from gloam_jax import geometry as geo
from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError, check_setting, is_int, is_positive
from gloam_jax.gicp import GICPConfig, increment, retract_host
from gloam_jax.learned import METHODS, without_gicp_constants
from gloam_jax.local_map import LocalMap
from gloam_jax.models import GLOAMModel, learned_parts, load_model
from gloam_jax.neighbors import KdTree
from gloam_jax.preprocess import (
    GridFeatures,
    PreprocessConfig,
    VoxelCentres,
    deskew_centres,
    on_grid,
    voxel_centres,
)
from gloam_jax.registration import PreparedCloud, align_prepared, build_cloud
from gloam_jax.sensor import SensorSignature, try_measure
from gloam_jax.timing import StageTimer


@dataclass(frozen=True)
class OdometryConfig:
    """Odometry settings; ``preprocess`` holds the scan preparation, ``gicp`` the
    registration."""

    mode: Literal["frame_to_model", "frame_to_frame"] = "frame_to_model"
    method: Literal["gicp", "gicp_da", "gicp_ce", "gloam"] = "gicp"  # see learned.METHODS
    model: str | None = None  # model file (learned parts) for the methods that need one
    # What runs instead of the learned parts where no shipped model (model: default) was
    # trained on the scans' sensor, or the model's features lie outside its training region:
    # plain GICP, GICP with the model's learned association, or the model all the same
    # (off). A model file named in model: always runs, with a warning (gloam_jax/guard.py).
    guard: Literal["gicp", "gicp_da", "off"] = "gicp"
    keyframe_distance: float = 2.0  # m between keyframes
    keyframe_angle_deg: float = 15.0
    max_keyframes: int = 10  # local map size
    # m; per voxel of this size the local map keeps only the newest keyframe's points (0:
    # every keyframe's points; see LocalMap); auto: by the scans' measured sensor
    # (resolve_map_resolution). 0.5 runs gicp 19 % faster, better on HDL-64 but worse on
    # VLP-16 and HDL-32 (experiments/map_voxels, map_voxels_by_sensor)
    map_resolution: float | Literal["auto"] = 0.0
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    gicp: GICPConfig = field(default_factory=GICPConfig)

    # Keys that moved into sections, for the error that old YAML files get.
    MOVED: ClassVar[dict[str, str]] = {
        **{k: f"preprocess.{k}" for k in (*PreprocessConfig.SCAN_FIELDS, "regularizer")},
        "degeneracy_threshold": "gicp.degeneracy_threshold",
        "lever_arm": "gicp.lever_arm",
    }
    # Keys that no longer do anything, with why: old files, and the config.yaml of old run
    # folders that --resume reads, still load (the key is ignored).
    RETIRED: ClassVar[dict[str, str]] = {
        "warmup_frames": "every scan is padded to a size bucket that holds it, nothing is thinned",
    }

    def __post_init__(self) -> None:
        for name in ("keyframe_distance", "keyframe_angle_deg"):
            check_setting(is_positive(v := getattr(self, name)), name, "positive", v)
        check_setting(is_int(self.max_keyframes, 1), "max_keyframes", "an integer >= 1",
                      self.max_keyframes)  # fmt: skip
        r = self.map_resolution
        ok = r == "auto" or (not isinstance(r, str | bool) and (r == 0 or is_positive(r)))
        check_setting(ok, "map_resolution", "0, positive (m) or auto", r)


# map_resolution: auto. Dense sensors get the voxel map: on HDL-64 worlds it made GICP better
# and faster; on VLP-16 and HDL-32 worlds worse, where the overlapping, differently placed ring
# points of several keyframes are what the pairing lives on (experiments/map_voxels, chosen on
# new worlds in experiments/map_voxels_by_sensor). Dense: at least 40 rings measured, more than
# a 32-beam sensor shows (at most 37, gloam_jax.sensor's tolerance); a 64-beam one whose top
# rings see only sky still shows 46-64 (the presets on highways, experiments/sensor_guard).
DENSE_RINGS = 40
DENSE_MAP_RESOLUTION = 0.5  # m


def resolve_map_resolution(
    setting: float | str, sensor: SensorSignature | None
) -> tuple[float, str]:
    """The local map's resolution (m) for ``setting`` (a number, or ``auto``) and the scans'
    measured ``sensor`` (None: not measurable), and why."""
    if setting != "auto":
        return float(setting), "set"
    if sensor is None:
        return 0.0, "auto: the sensor could not be measured, so every keyframe's points"
    if sensor.rings >= DENSE_RINGS:
        return DENSE_MAP_RESOLUTION, (
            f"auto: {sensor.rings} rings measured (at least {DENSE_RINGS}), so one keyframe's "
            f"points per {DENSE_MAP_RESOLUTION:g} m voxel"
        )
    return 0.0, (
        f"auto: {sensor.rings} rings measured (fewer than {DENSE_RINGS}), so every keyframe's "
        "points"
    )


@dataclass
class FrameStatus:
    """What happened to one frame, for the run's report."""

    num_points: int = 0  # after cleaning, cropping and downsampling
    num_dropped: int = 0  # NaN / inf points removed
    # Points left out to fit a padded size: always 0, as each scan's bucket holds it; kept
    # for the reports that count it (metrics.json thinned_points) and older frames.json files.
    num_thinned: int = 0
    iterations: int = 0
    queries: int = 0  # the target's k-d tree queried (rounds that found new candidates, rows)
    num_inliers: int = 0
    # GICP's cost per inlier at the solution (mean squared whitened residual): how well the
    # scan fits its target; comparable between settings on the same scans, not across scans
    residual: float = float("nan")
    converged: bool = False
    degenerate: bool = False  # some directions were unconstrained and kept the motion prior
    # the scene's weakest constraint over its strongest (registration.conditioning), the
    # planar points facing that direction, and the weak directions, each (rho, lever_arm *
    # phi) of unit length
    condition: float = float("nan")
    support: float = float("nan")
    weak_directions: list[list[float]] = field(default_factory=list)
    error: str = ""  # bad input that made the frame fall back on the motion prior
    # Wall-clock ms per stage spent on this frame (gloam_jax.timing.STAGES): a measurement,
    # not a result. Frame 1's include redoing frames 0 and 1 (Odometry._redo_start).
    stage_ms: dict[str, float] = field(default_factory=dict)


def _needs_keyframe(last: np.ndarray | None, T: np.ndarray, config: OdometryConfig) -> bool:
    if last is None:
        return True
    delta = np.linalg.inv(last) @ T
    angle = np.rad2deg(np.linalg.norm(np.asarray(geo.se3_log_jit(delta), dtype=np.float64)[3:]))
    return (
        np.linalg.norm(delta[:3, 3]) > config.keyframe_distance or angle > config.keyframe_angle_deg
    )


def remap(T_prior: np.ndarray, T_est: np.ndarray, weak: np.ndarray, lever_arm: float):
    """``T_est`` with its weak directions (6, m) taken from ``T_prior`` instead: the solution
    remapping of Zhang, Kaess and Singh (2016), so the well-constrained directions keep the
    registration's answer. Returns (4, 4)."""
    scale = np.array([1.0, 1.0, 1.0, lever_arm, lever_arm, lever_arm])
    z = increment(T_prior, T_est) * scale
    z -= weak @ (weak.T @ z)
    return retract_host(z / scale, T_prior)


class Odometry:
    """Frame-by-frame pose estimation; call :meth:`register_frame` with each scan in order."""

    def __init__(
        self, config: OdometryConfig = OdometryConfig(), model: GLOAMModel | None = None
    ) -> None:
        """``model`` (default: loaded from ``config.model``) holds the learned parts that
        ``config.method`` uses; those methods then need per-point features in register_frame,
        unless the model's backbone runs on the voxel grid (:attr:`grid_backbone`)."""
        if model is None and config.model is not None:
            model = load_model(config.model)
        self.model = model
        self.learned = without_gicp_constants(
            learned_parts(model, config.method), config.preprocess.regularizer
        )
        if METHODS[config.method][0] and self.learned.conversion is None:
            # The candidates are there for the learned association to choose among; without
            # it (a fall-back model), GICP's single nearest neighbour, as gicp.yaml has it.
            config = replace(config, gicp=replace(config.gicp, num_candidates=1))
        self.config = config
        self.needs_features = self.learned.conversion is not None or (
            self.learned.eigenvalue is not None
        )
        self._threads = ThreadpoolController()
        # The stages of the frame in progress; a caller adds its own (load, features) before
        # register_frame, which files them with the frame's status.
        self.timer = StageTimer()
        self.poses: list[np.ndarray] = []
        self.status: list[FrameStatus] = []
        self.velocity = np.zeros(6)  # se(3) motion over the last frame interval
        self.velocity_dt = 1.0  # s, that interval
        self.previous: PreparedCloud | None = None
        self.buckets = pc.StickyBuckets()
        # map_resolution: auto waits for the first raw scan's sensor (_resolve_map)
        resolution = 0.0 if config.map_resolution == "auto" else float(config.map_resolution)
        self.map = LocalMap(config.max_keyframes, self.buckets, resolution)
        # The first two frames' inputs, kept until the first velocity redoes them (_redo_start).
        self._start: list[tuple] = []

    def _velocity(self, frame_dt: float) -> np.ndarray:
        """The motion (6,) over a frame interval of ``frame_dt`` s, at constant velocity."""
        return self.velocity * (frame_dt / self.velocity_dt)

    def _predict(self, frame_dt: float) -> np.ndarray:
        if not self.poses:
            return np.eye(4)
        step = geo.se3_exp_jit(self._velocity(frame_dt))
        return self.poses[-1] @ np.asarray(step, dtype=np.float64)

    @cached_property
    def grid_backbone(self) -> GridFeatures | None:
        """The model's backbone where it runs on the preprocessing's own voxel grid (the
        features then come with :meth:`voxel_centres`, none need be given), else None."""
        if not self.needs_features:
            return None
        return on_grid(self.model.backbone(), self.config.preprocess)

    def voxel_centres(
        self,
        scan: np.ndarray,
        times: np.ndarray | None = None,
        source: str | None = None,
        features: np.ndarray | None = None,
        timer: StageTimer | None = None,
    ) -> VoxelCentres:
        """A frame's preprocessing up to the deskew (:func:`gloam_jax.preprocess.voxel_centres`
        with this odometry's settings and PCA), which needs no pose: run it ahead of
        :meth:`register_frame` (``gloam run`` does, on its prefetch thread) and pass the result
        as the scan. Without ``features``, a learned method's come from :attr:`grid_backbone`.
        ``timer`` gets stages ``voxels`` and ``features`` (the latter within the former, moved
        out). Raises InputError for a scan it cannot prepare."""
        self._check_features(features, source)
        pca = self.model.pca if self.needs_features else None
        backbone = self.grid_backbone if features is None else None
        inner = StageTimer()
        with nullcontext() if timer is None else timer("voxels"):
            centres = voxel_centres(scan, times, self.config.preprocess, pca=pca,
                                    features=features, backbone=backbone, source=source,
                                    timer=inner)  # fmt: skip
        if timer is not None:
            timer.split("voxels", inner.ms)
        return centres

    def _check_features(self, features: np.ndarray | None, source: str | None) -> None:
        if self.needs_features and features is None and self.grid_backbone is None:
            raise InputError(source, f"method '{self.config.method}' needs per-point features")

    def register_frame(
        self,
        scan: np.ndarray | VoxelCentres | None,
        times: np.ndarray | None = None,
        frame_dt: float = 0.1,
        source: str | None = None,
        features: np.ndarray | None = None,
    ) -> np.ndarray:
        """Estimate the pose of ``scan`` (N, 3+), with optional per-point times (N,) in seconds
        from its reference time; ``frame_dt`` is the time since the previous frame;
        ``features`` (N, D): the backbone's, for the learned methods (not needed where
        :attr:`grid_backbone` makes them). ``scan`` may also be
        its :meth:`voxel_centres`, prepared ahead (``times`` and ``features`` then unused).
        Returns ``T_world_lidar`` (4, 4). Bad scans fall back on the motion prior; so does
        ``scan`` None, a scan that could not be read (``source`` then says why)."""
        start = time.perf_counter()
        self.timer.begin()
        if not is_positive(frame_dt):
            self.timer.take()
            raise InputError(source, f"frame_dt must be a positive time step (s), not {frame_dt!r}")
        # A frame's NumPy products are thin ((N, 3) @ (3, 3), (N, D) @ (D, 6)): threaded BLAS
        # only fights XLA's and the k-d tree's threads for the cores.
        try:
            if self.config.map_resolution == "auto":
                self._resolve_map(scan, source)
            with self._threads.limit(limits=1, user_api="blas"):
                inputs = (scan, times, frame_dt, source, features)
                if len(self.poses) < 2 and self.config.preprocess.deskew != "off":
                    self._start.append(inputs)
                T = self._register(*inputs)
                if len(self.poses) == 2 and self._start:
                    T = self._redo_start()
        finally:  # a frame that raised leaves no stages to the next
            stage_ms = self.timer.take(1e3 * (time.perf_counter() - start))
        self.status[-1].stage_ms = stage_ms
        return T

    def _resolve_map(self, scan: np.ndarray | VoxelCentres | None, source: str | None) -> None:
        """``map_resolution: auto`` made a number from the first scan's measured sensor
        (``gloam run`` resolves it before, from its first three scans)."""
        if isinstance(scan, VoxelCentres):
            raise InputError(
                source,
                "map_resolution: auto measures the sensor on the first raw scan, not on voxel "
                "centres; give it raw, or set a number",
            )
        if scan is None:  # an unreadable scan: the next one decides
            return
        resolution, _ = resolve_map_resolution("auto", try_measure([scan]))
        self.config = replace(self.config, map_resolution=resolution)
        self.map.resolution = resolution

    # The columns of a prepared cloud that a state keeps (the k-d tree is rebuilt from them).
    _COLUMNS: ClassVar[tuple[str, ...]] = ("points", "covs", "features", "normals", "planarity")

    @property
    def resumable(self) -> bool:
        """Whether :meth:`state` holds all there is: not while the first two frames wait to be
        redone with the first velocity (:meth:`_redo_start`)."""
        return not self._start

    def state(self) -> dict[str, np.ndarray]:
        """Everything the next frame depends on, as named arrays (for ``np.savez``): poses
        (F, 4, 4), velocity, padded sizes and the local map's keyframes (frame_to_model) or the
        previous scan (frame_to_frame), bit for bit; not the frames' statuses, a report. An
        :class:`Odometry` of the same settings and model that :meth:`restore` s it registers the
        next frames exactly as this one would."""
        if not self.poses or not self.resumable:
            raise ValueError("no frames, or the first frames are not final yet (see resumable)")
        floors = self.buckets.state()
        state = {
            "poses": np.stack(self.poses),
            "velocity": self.velocity,
            "velocity_dt": np.float64(self.velocity_dt),
            "bucket_roles": np.array(list(floors), dtype=str),
            "bucket_sizes": np.array(list(floors.values()), dtype=np.int64),
        }
        clouds = {f"keyframe{j}": k for j, k in enumerate(self.map.keyframes)}
        if self.previous is not None and self.config.mode == "frame_to_frame":
            clouds["previous"] = {c: getattr(self.previous, c) for c in self._COLUMNS}
        if self.map.last_pose is not None:
            state["map_last_pose"] = self.map.last_pose
        for name, columns in clouds.items():
            state |= {f"{name}_{c}": v for c, v in columns.items() if v is not None}
        return state

    def restore(self, state: dict[str, np.ndarray], status: list[FrameStatus]) -> None:
        """Continue from a :meth:`state` (of a run with these settings and this model), with
        the statuses of its frames."""
        if self.config.map_resolution == "auto":
            raise InputError(None, "map_resolution: auto must be resolved (as gloam run does, "
                             "resolve_map_resolution) before a state is restored")  # fmt: skip
        self.poses = list(np.asarray(state["poses"], np.float64))
        if len(status) != len(self.poses):
            raise ValueError(f"{len(status)} statuses for {len(self.poses)} frames")
        self.status = list(status)
        self.velocity = np.asarray(state["velocity"], np.float64)
        self.velocity_dt = float(state["velocity_dt"])
        roles, sizes = state["bucket_roles"].tolist(), state["bucket_sizes"].tolist()
        floors = dict(zip(roles, sizes, strict=True))
        # Older states also say "buckets_frozen": ignored, as sizes now grow all run long.
        self.buckets.restore(floors)
        self._start = []

        def columns(name: str) -> dict[str, np.ndarray | None]:
            return {c: state.get(f"{name}_{c}") for c in self._COLUMNS}

        keyframes = [columns(f"keyframe{j}") for j in range(self.config.max_keyframes)]
        keyframes = [k for k in keyframes if k["points"] is not None]
        if keyframes:
            self.map.restore(keyframes, np.asarray(state["map_last_pose"]))
        if "previous_points" in state:
            previous = columns("previous")
            self.previous = PreparedCloud(tree=KdTree(previous["points"], "previous scan"),
                                          **previous)  # fmt: skip

    def _redo_start(self) -> np.ndarray:
        """Frames 0 and 1 again, both deskewed with the motion between them (the first
        velocity). Before it was known they were not deskewed; left so, they would be the map
        that the next, deskewed, scans register to, which biases those registrations (a jump
        of 19 cm at 8.5 m/s on a simulated urban drive, experiments/startup_deskew). Returns
        frame 1's pose."""
        start, velocity = self._start, self.velocity
        self._start = []
        stage_ms = [s.stage_ms for s in self.status]  # as first measured; frame 1's is pending
        # As at the first pass but for the deskew: the same motion prior (none) for frame 1.
        self.poses, self.status, self.previous, self.velocity = [], [], None, np.zeros(6)
        self.velocity_dt = 1.0
        self.map.clear()
        for inputs in start:
            T = self._register(*inputs, velocity=velocity)
        for status, ms in zip(self.status, stage_ms, strict=True):
            status.stage_ms = ms
        return T

    def _register(
        self, scan, times, frame_dt, source, features, velocity: np.ndarray | None = None
    ) -> np.ndarray:
        """One frame, deskewed with ``velocity`` (default: the current one; none for the
        first frame)."""
        cfg, status, timer = self.config, FrameStatus(), self.timer
        T_pred = self._predict(frame_dt)
        if scan is None:
            status.error = source
            return self._accept(T_pred, None, status, frame_dt)
        prepared = isinstance(scan, VoxelCentres)
        if not prepared:  # raised to the caller, not filed as a bad scan
            self._check_features(features, source)
        try:
            if prepared:
                centres = scan
            else:
                centres = self.voxel_centres(scan, times, source, features, timer)
            if velocity is None and self.poses:
                velocity = self._velocity(frame_dt)
            with timer("deskew"):
                points = deskew_centres(centres, velocity, frame_dt)
            status.num_dropped, pca = centres.dropped, centres.features
            # Padded to its own bucket (one compilation each), not to the largest scan seen:
            # 1.09x the rows instead of 1.46-1.49x on long drives (experiments/scan_buckets).
            # The map's slots keep the sticky size, so the map's shape changes only with it.
            scan_size = pc.bucket_size(len(points))
            prep = cfg.preprocess
            cloud = build_cloud(points, prep.num_neighbors, prep.regularizer, source, scan_size,
                                pca, self.learned, timer, centres.neighbours)  # fmt: skip
        except InputError as err:
            status.error = str(err)
            return self._accept(T_pred, None, status, frame_dt)
        status.num_points = len(cloud.points)
        # Taken only now: the map's merge ran beside this frame's preprocessing.
        with timer("map"):
            target = self.previous if cfg.mode == "frame_to_frame" else self.map.cloud
        if target is None:  # first usable scan (earlier ones, if any, were bad): it anchors
            return self._accept(T_pred, cloud, status, frame_dt)
        # Registration in the target's frame: the previous scan's, or the world (local map).
        if cfg.mode == "frame_to_frame":
            T_world_target = self.poses[-1]
            sizes = (scan_size, pc.bucket_size(len(target.points)))
            prior = np.asarray(geo.se3_exp_jit(self._velocity(frame_dt)), dtype=np.float64)
        else:
            T_world_target, sizes, prior = np.eye(4), (scan_size, self.map.size), T_pred
        result = align_prepared(target, cloud, prior, cfg.gicp, sizes, timer=timer)
        status.iterations, status.num_inliers = result.iterations, result.num_inliers
        status.queries = result.queries
        if result.num_inliers:  # without inliers the fit is unknown, not perfect
            status.residual = result.error / result.num_inliers
        status.converged = result.converged
        T, weak = result.T_target_source, result.weak_directions
        status.condition, status.support = result.condition, round(result.support, 2)
        status.weak_directions = weak.T.round(4).tolist()
        if result.degenerate:
            status.degenerate = True
            T = prior if result.num_inliers == 0 else remap(prior, T, weak, cfg.gicp.lever_arm)
        T = T_world_target @ T
        return self._accept(T, cloud, status, frame_dt)

    def _accept(
        self, T: np.ndarray, cloud: PreparedCloud | None, status: FrameStatus, frame_dt: float
    ) -> np.ndarray:
        if self.poses:
            xi = geo.se3_log_jit(np.linalg.inv(self.poses[-1]) @ T)
            self.velocity, self.velocity_dt = np.asarray(xi, dtype=np.float64), frame_dt
        self.poses.append(T)
        self.status.append(status)
        if cloud is not None:
            self.previous = cloud
            with self.timer("map"):
                if self.config.mode == "frame_to_model" and _needs_keyframe(
                    self.map.last_pose, T, self.config
                ):
                    self.map.add(cloud, T)
        return T
