"""Follow a pushed object through depth images alone: segment its points, register the model, or say "lost".

    tracker = ObjectTracker.from_mesh(model_mesh)          # the model the system has, in its frame O
    tracker.reset(T_world_O)                               # where the system was told / perceived it is
    seen = tracker.update(frames, robot_masks)             # per frame: DepthFrame + robot self-filter mask
    seen.T_world_O if not seen.lost else seen.reason

Each update (depth frames of the same instant from one or more cameras, with the robot's self-filter
mask for each: the pixels its model covers at its measured joints):

1. Segmentation. Per frame only the pixels inside the projection of a search sphere are back-projected:
   centred on the predicted model centre (the last tracked one moved on by the last frame's shift), radius
   the model's radius + a search margin (wider after each lost frame). Pixels under the robot mask, dilated
   by `robot_padding_px` as real self-filters pad the robot model, are dropped; so are points within
   `table_margin_m` of the table plane z = 0 and points outside the sphere. The rest is voxel-downsampled
   (even density whatever the camera distance) and isolated points (stereo noise of the table above the
   margin, flying pixels) are dropped.
2. Registration. Point-to-plane ICP of the segmented points onto the model, from the predicted pose, coarse
   (wide correspondence gate) then fine. After a loss a second start, the model moved onto the segmented
   centroid, is tried too, and the better fit is kept.
3. Degenerate views. The point-to-plane Hessian at the solution says which motions the points pin down
   (rotations about the model centre, scaled by its radius so they compare with translations). The change
   from the predicted pose is damped along each eigen-direction as a prior term weighted `degenerate_ratio`
   times the strongest would: the spin of a standing cylinder or a sphere, sliding along a single visible
   plane keep (nearly) the prior's value instead of whatever the ICP drifted to; well observed directions
   keep the ICP's.
4. Checks. Fitness (the share of segmented points within `inlier_m` of the model surface), RMSE of those
   points' point-to-plane distances, and the step from the last tracked pose against what an object
   pushed at `max_speed_mps` / `max_turn_deg_s` can do in the frames since: a failed check reports
   lost with the reason, never a pose. A registration that turned faster than an object can is tried once more
   with the last tracked orientation at the registered centre (`hold_orientation_on_spin`): ICP spins a
   near-round or near-square body about an axis the points barely pin while the object itself barely turned
   (measured: docs/architecture.md "Tracking from images only"); the held pose stands if it passes the same
   checks, and an object that truly turned that fast fails them and is lost.

Registration library: Open3D's point-to-plane ICP with the model's own normals, chosen by measurement against
small_gicp (bench/tracking.py; the figures and why: docs/architecture.md "Tracking from images only").
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from shared.contracts.messages import Obstacle
from shared.world.obstacles import off_obstacles

from .cloud import voxel_downsample
from .depth import DepthFrame, Intrinsics, transform_points_no_blas
from .errors import PerceptionError


@dataclass(frozen=True)
class TrackingConfig:
    rate_hz: float = 10.0  # frames per second of robot time (users of the tracker read it)
    image_size: tuple[int, int] = (424, 240)  # the D435's 424x240 depth mode, what tracking renders at
    # A mesh is sampled this densely: ~5 mm between samples on a 20 cm box, well under the fine ICP gate.
    model_points: int = 4000
    # Self-filter padding: TinyRenderer silhouettes are exact, a real robot model is not (cables, calibration);
    # 2 px is ~9 mm at 1 m in the 424 x 240 mode.
    robot_padding_px: int = 2
    # The table's stereo noise at the head camera (~1 m, 7 mm sigma along the ray in this mode, about half of
    # it vertical) mostly stays under 1 cm; the survivors are isolated and dropped by the density filter.
    table_margin_m: float = 0.010
    # Search sphere: model radius + this around the last model centre; an object pushed at 0.3 m/s moves 3 cm
    # between two frames at 10 Hz.
    search_margin_m: float = 0.04
    lost_margin_growth_m: float = 0.03  # per lost frame: the object keeps moving while it is not seen
    max_search_margin_m: float = 0.15
    # Voxel of the segmented cloud: about the pixel footprint at 1 m (4.5 mm) so near cameras do not outweigh far ones.
    voxel_m: float = 0.005
    # Density filter: a point needs this many others within 2.5 voxels; a surface seen at 1 m has ~10 there.
    min_neighbours: int = 3
    min_points: int = 30  # fewer segmented points than this cannot pin 6 degrees of freedom against noise
    coarse_correspondence_m: float = 0.03  # first ICP pass: the motion between two frames
    fine_correspondence_m: float = 0.012  # second pass: noise (7 mm sigma at 1 m) plus model sampling
    icp_iterations: int = 30  # per pass, an upper bound: Open3D stops once the fit changes by under 1e-6
    # The prior term's weight, relative to the point-to-plane Hessian's strongest direction (step 3 above): a
    # direction with eigenvalue l keeps l / (l + 0.01 max l) of the ICP's change per frame, so a standing
    # cylinder's unobservable spin stays near the prior while a box's rotation follows the points (the measured
    # eigenvalue ratios: docs/architecture.md "Tracking from images only").
    degenerate_ratio: float = 0.01
    # Below this share of the strongest eigenvalue a direction is not observed and keeps the prior outright: above the
    # spin of every body of revolution measured (standing and lying cylinders, round small objects); a near-round
    # ellipsoid's spin falls under it too (bench/tracking.py's `weakest_direction`; docs/architecture.md "Tracking
    # from images only").
    unobserved_ratio: float = 0.005
    # Fitness: the share of segmented points within `inlier_m` of the model surface. On the bench's pushes (robot
    # in view) the right model explains nearly all of them and a wrong model far fewer; one of nearly the same
    # shape (a sphere for a near-round ellipsoid) can pass: shape is all depth can tell (figures:
    # docs/architecture.md "Tracking from images only").
    inlier_m: float = 0.007
    min_fitness: float = 0.75
    max_rmse_m: float = 0.005  # the explained points of the right pose sit at 2-3.5 mm RMSE at 0.5-1 m
    # The fastest a pushed object moves: pushes run at up to 0.3 m/s, the rest is room for the noise of the two
    # poses compared; a fast turn. One bound for every size: a small object may truly turn faster, but letting it
    # (the rim at max_speed_mps) let registration flip near-square small objects by 90 degrees (docs/architecture.md
    # "Tracking from images only").
    max_speed_mps: float = 0.5
    max_turn_deg_s: float = 180.0
    hold_orientation_on_spin: bool = True
    # Small objects (a model radius under `small_radius_m`: dice, erasers, caps, most under 1.7 cm tall) are tracked in
    # the D435's 848 x 480 mode (twice the focal length in pixels: four times the pixels on the object, half the depth
    # noise), on a finer voxel and a lower table cut: in the default mode the 1 cm cut leaves an 8 mm tall object only
    # its noisiest top points (measured: docs/architecture.md "Tracking from images only"). A search window around a
    # small object is small, so the finer mode costs little.
    small_radius_m: float = 0.03
    small_image_size: tuple[int, int] = (848, 480)
    small_voxel_m: float = 0.0025
    small_table_margin_m: float = 0.005

    def for_model(self, radius_m: float) -> TrackingConfig:
        """The settings that track a model of this radius (centre to farthest point): the small-object mode under
        `small_radius_m`, these settings otherwise."""
        if radius_m >= self.small_radius_m:
            return self
        return replace(self, image_size=self.small_image_size, voxel_m=self.small_voxel_m,
                                   table_margin_m=self.small_table_margin_m)

    def __post_init__(self) -> None:
        if not 0 < self.rate_hz <= 1000:
            raise PerceptionError(f"tracking rate_hz must be in (0, 1000], got {self.rate_hz}")
        if min(self.image_size) < 1 or self.model_points < 10 or self.min_points < 6:
            raise PerceptionError("tracking needs an image, at least 10 model points and at least 6 object points")
        if not 0.0 <= self.min_fitness <= 1.0:
            raise PerceptionError(f"min_fitness must be in [0, 1], got {self.min_fitness}")


@dataclass(frozen=True)
class TrackedPose:
    """What one tracking frame saw: the pose, or None and why it is lost."""

    T_world_O: np.ndarray | None  # None when lost
    fitness: float  # fraction of segmented points the model explains after registration (0..1)
    rmse_m: float  # point-to-plane RMSE of the explained points (NaN when nothing was registered)
    points: int  # segmented object points used
    reason: str | None  # why the track is lost (None when tracked)

    @property
    def lost(self) -> bool:
        return self.T_world_O is None


class Registration(Protocol):
    """Rigid registration of world points onto the model: from `T_init` (model <- world), the refined
    transform, with correspondences farther than `max_distance_m` ignored."""

    def __call__(self, source: np.ndarray, T_init: np.ndarray, max_distance_m: float, iterations: int) -> np.ndarray: ...


class Open3dPointToPlane:
    """Open3D's point-to-plane ICP onto the model, with the model's own normals (the faces' for a mesh)."""

    def __init__(self, model_points: np.ndarray, model_normals: np.ndarray) -> None:
        import open3d  # here, not at the top: its import takes a second, reading a cloud file should not

        self._o3d = open3d
        self._target = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(model_points))
        self._target.normals = open3d.utility.Vector3dVector(model_normals)
        self._estimation = open3d.pipelines.registration.TransformationEstimationPointToPlane()

    def __call__(self, source: np.ndarray, T_init: np.ndarray, max_distance_m: float, iterations: int) -> np.ndarray:
        registration, utility = self._o3d.pipelines.registration, self._o3d.utility
        cloud = self._o3d.geometry.PointCloud(utility.Vector3dVector(np.asarray(source, dtype=np.float64)))
        # One thread: Open3D's TBB threads sum the normal equations in a varying order, so a near-degenerate fit
        # (a cylinder's spin) came out degrees apart from one run to the next; a trial must repeat. A fit of
        # ~1000 points gains nothing from threads on a shared 2-core machine either. (OMP_NUM_THREADS does not
        # reach TBB; the limit is process-wide, so the caller's is restored.)
        threads = utility.get_max_threads()
        utility.set_max_threads(1)
        try:
            result = registration.registration_icp(cloud, self._target, max_distance_m, T_init, self._estimation,
                                                   registration.ICPConvergenceCriteria(max_iteration=iterations))
        finally:
            utility.set_max_threads(threads)
        return np.array(result.transformation, dtype=np.float64)


class ObjectTracker:
    """Tracks one object model (points in its frame O, normals optional) through depth frames."""

    def __init__(self, model_points_O: np.ndarray, config: TrackingConfig = TrackingConfig(),
                 model_normals_O: np.ndarray | None = None) -> None:
        points = _check_model(model_points_O)
        self.model_points = points
        self.model_normals = _estimate_normals(points) if model_normals_O is None else _check_normals(model_normals_O, len(points))
        self.centre_O = points.mean(axis=0)
        self.radius_m = max(float(np.max(np.linalg.norm(points - self.centre_O, axis=1))), 1e-3)
        self.config = config.for_model(self.radius_m)  # a small model's own mode (the frames' size follows it)
        self._tree = cKDTree(points)
        self.registration = self._registration()
        self._T_good: np.ndarray | None = None  # last tracked pose (world <- O)
        self._obstacles: tuple[Obstacle, ...] = ()  # known obstacles and walls near the object
        self._since_good = 0  # frames since it (1 on the frame after a tracked one)
        self._velocity = np.zeros(3)  # the model centre's shift between the last two tracked frames, if consecutive

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, config: TrackingConfig = TrackingConfig()) -> ObjectTracker:
        """Track `mesh` (in its frame O): its surface sampled area-uniformly, with the faces' normals."""
        if len(mesh.faces) == 0 or not mesh.area > 0.0:
            raise PerceptionError("cannot track an empty mesh: the model has no faces")
        points, faces = trimesh.sample.sample_surface(mesh, config.model_points, seed=0)
        normals = np.asarray(mesh.face_normals, dtype=np.float64)[faces]
        return cls(np.asarray(points, dtype=np.float64), config, normals)

    def _registration(self) -> Registration:
        """The registration library (chosen by bench/tracking.py; a bench overrides this to compare others)."""
        return Open3dPointToPlane(self.model_points, self.model_normals)

    # ------------------------------------------------------------------------------------------ state

    def reset(self, T_world_O: np.ndarray, obstacles: Sequence[Obstacle] = ()) -> None:
        """Start from this pose (the pose the system was told or perceived), among the known `obstacles` (cylinders
        and walls: their points are never the object's)."""
        self._obstacles = tuple(obstacles)
        self._T_good = _check_pose(T_world_O)
        self._since_good = 1
        self._velocity = np.zeros(3)

    @property
    def pose(self) -> np.ndarray | None:
        """The last tracked pose (None before reset)."""
        return None if self._T_good is None else np.array(self._T_good, dtype=np.float64)

    def update(self, frames: Sequence[DepthFrame], robot_masks: Sequence[np.ndarray | None]) -> TrackedPose:
        """One tracking frame: `frames` of one instant and the robot's self-filter mask of each (None: no robot)."""
        _check_frames(frames, robot_masks)
        if self._T_good is None:
            raise PerceptionError("tracker updated before reset: call reset(T_world_O) with the object's pose first")
        predicted = self._predicted()
        centre = self.centre(predicted)
        points = self.segment(frames, robot_masks, centre, self.radius_m + self._search_margin())
        if len(points) < self.config.min_points:
            return self._lose(f"too few object points ({len(points)} < {self.config.min_points})", len(points))
        T_world_O = self._register(points, predicted, centre)
        fitness, rmse = self.score(points, T_world_O)
        reason = self._implausible(fitness, rmse, T_world_O)
        if reason is not None and self.config.hold_orientation_on_spin and self._too_fast_turn_deg(T_world_O) is not None:
            held = self._orientation_held(T_world_O)
            held_fitness, held_rmse = self.score(points, held)
            if self._implausible(held_fitness, held_rmse, held) is None:
                T_world_O, fitness, rmse, reason = held, held_fitness, held_rmse, None
        if reason is not None:
            return self._lose(reason, len(points), fitness, rmse)
        self._accept(T_world_O)
        return TrackedPose(T_world_O.copy(), fitness, rmse, len(points), None)

    def search_window(self, intrinsics: Intrinsics, T_world_camera: np.ndarray) -> tuple[slice, slice]:
        """(rows, columns) of the only pixels the next `update` reads from a camera at T_world_camera: a renderer may
        draw just these (a simulated camera's cost is per pixel drawn)."""
        if self._T_good is None:
            raise PerceptionError("tracker asked for its search window before reset")
        return sphere_window(intrinsics, np.asarray(T_world_camera, dtype=np.float64), self.centre(self._predicted()),
                             self.radius_m + self._search_margin())

    def centre(self, T_world_O: np.ndarray) -> np.ndarray:
        """[3] the model centre (the mean of its points) in the world with the model at T_world_O."""
        return np.asarray(T_world_O[:3, :3] @ self.centre_O + T_world_O[:3, 3], dtype=np.float64)

    def _accept(self, T_world_O: np.ndarray) -> None:
        """T_world_O becomes the last tracked pose; the centre's shift from the previous one is the velocity
        when the two were consecutive frames."""
        assert self._T_good is not None
        consecutive = self._since_good == 1
        self._velocity = self.centre(T_world_O) - self.centre(self._T_good) if consecutive else np.zeros(3)
        self._T_good, self._since_good = T_world_O, 1

    def _predicted(self) -> np.ndarray:
        """Where the object should be now: the last tracked pose, its centre moved on by the last frame's shift.
        Only the centre: a rotation carried on would also carry on an unobserved spin."""
        assert self._T_good is not None
        out = np.array(self._T_good, dtype=np.float64)
        out[:3, 3] += self._velocity
        return out

    def _search_margin(self) -> float:
        c = self.config
        return min(c.search_margin_m + (self._since_good - 1) * c.lost_margin_growth_m, c.max_search_margin_m)

    def _lose(self, reason: str, points: int, fitness: float = 0.0, rmse: float = math.nan) -> TrackedPose:
        self._since_good += 1
        self._velocity = np.zeros(3)  # the search widens instead: where it went while unseen is unknown
        return TrackedPose(None, fitness, rmse, points, reason)

    # ----------------------------------------------------------------------------------- segmentation

    def segment(self, frames: Sequence[DepthFrame], robot_masks: Sequence[np.ndarray | None], centre: np.ndarray,
                radius_m: float) -> np.ndarray:
        """[N, 3] world points of the object: within `radius_m` of `centre`, off the robot, the table and the known
        obstacles, voxel-downsampled, isolated points dropped."""
        parts = [self._frame_points(frame, mask, centre, radius_m) for frame, mask in zip(frames, robot_masks, strict=True)]
        points = off_obstacles(np.concatenate(parts, axis=0), self._obstacles)
        if len(points) == 0:
            return points
        points = voxel_downsample(points, self.config.voxel_m)
        return _drop_isolated(points, 2.5 * self.config.voxel_m, self.config.min_neighbours)

    def _frame_points(self, frame: DepthFrame, robot_mask: np.ndarray | None, centre: np.ndarray,
                      radius_m: float) -> np.ndarray:
        keep = frame.valid & _sphere_window(frame, centre, radius_m)
        if robot_mask is not None and robot_mask.any():
            padding = self.config.robot_padding_px
            robot = ndimage.binary_dilation(robot_mask, iterations=padding) if padding > 0 else robot_mask
            keep &= ~robot
        kept = DepthFrame(np.where(keep, np.asarray(frame.depth_m, dtype=np.float64), 0.0), frame.intrinsics,
                          frame.T_world_camera)
        points = kept.points_world()
        near = np.sum((points - centre) ** 2, axis=1) <= radius_m * radius_m
        return np.asarray(points[near & (points[:, 2] > self.config.table_margin_m)], dtype=np.float64)

    # ----------------------------------------------------------------------------------- registration

    def _register(self, points: np.ndarray, predicted: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """World <- O of the model registered onto `points`, from the predicted pose (and, after a loss, also
        from the model moved onto the points' centroid; the better fit wins)."""
        starts = [predicted]
        if self._since_good > 1:
            shifted = predicted.copy()
            shifted[:3, 3] += points.mean(axis=0) - centre
            starts.append(shifted)
        best: tuple[float, np.ndarray] | None = None
        for start in starts:
            T_world_O = self._refine(points, start)
            fitness, _ = self.score(points, T_world_O)
            if best is None or fitness > best[0]:
                best = (fitness, T_world_O)
        assert best is not None
        return best[1]

    def _refine(self, points: np.ndarray, T_start: np.ndarray) -> np.ndarray:
        c = self.config
        T = self.registration(points, _inverse(T_start), c.coarse_correspondence_m, c.icp_iterations)
        T = self.registration(points, T, c.fine_correspondence_m, c.icp_iterations)
        return self._keep_unobserved(points, _inverse(T), T_start)

    def _keep_unobserved(self, points: np.ndarray, T_world_O: np.ndarray, T_prior: np.ndarray) -> np.ndarray:
        """T_world_O with its change from T_prior damped along the directions the points barely constrain.

        A pose is taken as its rotation and the world position of the model centre; the change (a rotation
        about the centre, scaled by the model radius, and the centre's shift) is split along the eigenvectors
        of the point-to-plane Hessian H in the same terms (eigenvalues l), and each part scaled by
        l / (l + mu), mu = degenerate_ratio * max(l): the solution with a prior term mu |change|^2 added. A well
        observed direction keeps its change, an unobserved one (a cylinder's spin) keeps the prior."""
        observed = self.observability(points, T_world_O)
        if observed is None:
            return T_world_O
        eigenvalues, eigenvectors = observed
        damping = self.config.degenerate_ratio * eigenvalues[-1]
        turn = Rotation.from_matrix(T_world_O[:3, :3] @ T_prior[:3, :3].T).as_rotvec()
        change = np.concatenate([self.radius_m * turn, self.centre(T_world_O) - self.centre(T_prior)])
        keep = eigenvalues / (eigenvalues + damping)
        # A direction the points hardly see at all (a round object's spin) keeps the prior outright: a fraction of
        # an arbitrary turn each frame adds up to tens of degrees over a push.
        keep[eigenvalues < self.config.unobserved_ratio * eigenvalues[-1]] = 0.0
        kept = eigenvectors @ (keep * (eigenvectors.T @ change))
        out = np.eye(4)
        out[:3, :3] = Rotation.from_rotvec(kept[:3] / self.radius_m).as_matrix() @ T_prior[:3, :3]
        out[:3, 3] = self.centre(T_prior) + kept[3:] - out[:3, :3] @ self.centre_O
        return out

    def observability(self, points: np.ndarray, T_world_O: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """How well `points` pin the pose T_world_O down: the point-to-plane Hessian's eigenvalues (ascending, the
        weakest first; compare them with the last, the strongest) and its eigenvectors (columns; radius * rotation
        about the model centre, then centre shift); None with too few matches or nothing observed."""
        hessian = self._hessian(points, T_world_O)
        if hessian is None:
            return None
        eigenvalues, eigenvectors = np.linalg.eigh(hessian)
        eigenvalues = np.maximum(eigenvalues, 0.0)
        if eigenvalues[-1] <= 0.0:
            return None
        return eigenvalues, eigenvectors

    def _hessian(self, points: np.ndarray, T_world_O: np.ndarray) -> np.ndarray | None:
        """[6, 6] point-to-plane Gauss-Newton Hessian per matched point at T_world_O, in (radius * rotation about
        the model centre, centre shift), world axes; None with under 6 matches."""
        in_O = transform_points_no_blas(_inverse(T_world_O), points)
        distance, index = self._tree.query(in_O, distance_upper_bound=self.config.fine_correspondence_m)
        matched = np.isfinite(distance)
        if np.count_nonzero(matched) < 6:
            return None
        normals = self.model_normals[index[matched]] @ T_world_O[:3, :3].T
        arm = (points[matched] - self.centre(T_world_O)) / self.radius_m
        jacobian = np.concatenate([np.cross(arm, normals), normals], axis=1)
        return np.asarray(jacobian.T @ jacobian / len(jacobian), dtype=np.float64)

    # ------------------------------------------------------------------------------------------ checks

    def score(self, points: np.ndarray, T_world_O: np.ndarray) -> tuple[float, float]:
        """(fitness, RMSE): the share of `points` (world) within `inlier_m` of the model at T_world_O, and the
        RMSE of their point-to-plane distances (NaN when none is)."""
        in_O = transform_points_no_blas(_inverse(T_world_O), points)
        distance, index = self._tree.query(in_O, distance_upper_bound=self.config.fine_correspondence_m)
        matched = np.isfinite(distance)
        plane = np.abs(np.sum((in_O[matched] - self.model_points[index[matched]]) * self.model_normals[index[matched]], axis=1))
        inliers = plane[plane <= self.config.inlier_m]
        fitness = len(inliers) / max(len(points), 1)
        rmse = float(np.sqrt(np.mean(inliers**2))) if len(inliers) else math.nan
        return float(fitness), rmse

    def _too_fast_turn_deg(self, T_world_O: np.ndarray) -> float | None:
        """How far T_world_O turned from the last tracked pose, if faster than `max_turn_deg_s` allows (else None)."""
        assert self._T_good is not None
        turn_deg = _angle_deg(self._T_good[:3, :3].T @ T_world_O[:3, :3])
        return turn_deg if turn_deg > self.config.max_turn_deg_s * self._since_good / self.config.rate_hz else None

    def _orientation_held(self, T_world_O: np.ndarray) -> np.ndarray:
        """The last tracked orientation with the model centre where T_world_O puts it."""
        assert self._T_good is not None
        held = np.array(self._T_good, dtype=np.float64)
        held[:3, 3] += self.centre(T_world_O) - self.centre(held)
        return held

    def _implausible(self, fitness: float, rmse: float, T_world_O: np.ndarray) -> str | None:
        """Why the registered pose is not to be believed (None: it is)."""
        assert self._T_good is not None
        c = self.config
        if fitness < c.min_fitness:
            return f"fitness {fitness:.2f} below {c.min_fitness:.2f}: the model does not explain the segmented points"
        if not rmse <= c.max_rmse_m:
            return f"registration RMSE {rmse * 1000:.1f} mm above {c.max_rmse_m * 1000:.1f} mm"
        seconds = self._since_good / c.rate_hz
        step_m = float(np.linalg.norm(self.centre(T_world_O) - self.centre(self._T_good)))
        if step_m > c.max_speed_mps * seconds:
            return f"implausible jump: {step_m * 1000:.0f} mm in {self._since_good} frame(s)"
        turn_deg = self._too_fast_turn_deg(T_world_O)
        if turn_deg is not None:
            return f"implausible turn: {turn_deg:.0f} deg in {self._since_good} frame(s)"
        return None


# ------------------------------------------------------------------------------------------- helpers


def _check_model(model_points_O: np.ndarray) -> np.ndarray:
    points = np.asarray(model_points_O, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PerceptionError(f"model points must be an [N, 3] array, got shape {points.shape}")
    if len(points) < 10:
        raise PerceptionError(f"the model has {len(points)} points: at least 10 are needed to track it")
    if not np.all(np.isfinite(points)):
        raise PerceptionError("the model points contain NaN or infinite values")
    return points


def _check_normals(model_normals_O: np.ndarray, count: int) -> np.ndarray:
    normals = np.asarray(model_normals_O, dtype=np.float64)
    if normals.shape != (count, 3) or not np.all(np.isfinite(normals)):
        raise PerceptionError(f"model normals must be a finite [{count}, 3] array, got shape {normals.shape}")
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if np.any(length < 1e-9):
        raise PerceptionError("model normals contain zero vectors")
    return np.asarray(normals / length, dtype=np.float64)


def _estimate_normals(points: np.ndarray, neighbours: int = 16) -> np.ndarray:
    """Unoriented normals of a point model: the least-variance axis of each point's neighbourhood
    (point-to-plane distances ignore the sign)."""
    _, index = cKDTree(points).query(points, k=min(neighbours, len(points)))
    local = points[index] - points[index].mean(axis=1, keepdims=True)
    _, _, axes = np.linalg.svd(local, full_matrices=False)
    return np.asarray(axes[:, -1, :], dtype=np.float64)


def _check_pose(T_world_O: np.ndarray) -> np.ndarray:
    T = np.asarray(T_world_O, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise PerceptionError(f"the pose to track from must be a finite 4x4 transform, got shape {T.shape}"
                              + ("" if T.shape != (4, 4) else " with NaN or infinite values"))
    if not np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-4) or np.linalg.det(T[:3, :3]) <= 0:
        raise PerceptionError("the pose to track from has no rotation in its upper-left 3x3 block")
    return np.array(T, dtype=np.float64)


def _check_frames(frames: Sequence[DepthFrame], robot_masks: Sequence[np.ndarray | None]) -> None:
    if len(frames) == 0:
        raise PerceptionError("no depth frames given to the tracker")
    if len(robot_masks) != len(frames):
        raise PerceptionError(f"{len(frames)} depth frames but {len(robot_masks)} robot masks: give one per frame "
                              "(None for a frame without the robot)")
    for number, (frame, mask) in enumerate(zip(frames, robot_masks, strict=True)):
        shape = (frame.intrinsics.height, frame.intrinsics.width)
        if mask is not None and (np.shape(mask) != shape or np.asarray(mask).dtype != np.bool_):
            raise PerceptionError(f"robot mask {number} must be a bool array of the frame's shape {shape}, "
                                  f"got {np.asarray(mask).dtype} {np.shape(mask)}")


def _sphere_window(frame: DepthFrame, centre: np.ndarray, radius_m: float) -> np.ndarray:
    """[H, W] bool: the pixels the sphere can project to (a box around it; the whole image when the
    camera is inside or next to the sphere)."""
    k = frame.intrinsics
    window = np.zeros((k.height, k.width), dtype=bool)
    rows, columns = sphere_window(k, np.asarray(frame.T_world_camera, dtype=np.float64), centre, radius_m)
    window[rows, columns] = True
    return window


def sphere_window(k: Intrinsics, T_world_camera: np.ndarray, centre: np.ndarray, radius_m: float) -> tuple[slice, slice]:
    """(rows, columns) of the image box a sphere can project to, clipped to the image (the whole image when the
    camera is inside or next to the sphere; empty slices when it is out of view)."""
    in_camera = transform_points_no_blas(_inverse(T_world_camera), np.asarray(centre, dtype=np.float64)[None])[0]
    depth = in_camera[2] - radius_m
    if depth <= 1e-3:
        return slice(0, k.height), slice(0, k.width)
    u, v = k.cx + k.fx * in_camera[0] / in_camera[2], k.cy + k.fy * in_camera[1] / in_camera[2]
    # The sphere's image is inside the circle of radius f * r / (z - r) around the projected centre, plus the
    # shift of that centre across the sphere's depth (x / z varies up to |x| r / (z (z - r))).
    half_u = k.fx * (radius_m + abs(in_camera[0]) * radius_m / in_camera[2]) / depth + 1.0
    half_v = k.fy * (radius_m + abs(in_camera[1]) * radius_m / in_camera[2]) / depth + 1.0
    columns = slice(min(max(int(math.floor(u - half_u)), 0), k.width), min(max(int(math.ceil(u + half_u)) + 1, 0), k.width))
    rows = slice(min(max(int(math.floor(v - half_v)), 0), k.height), min(max(int(math.ceil(v + half_v)) + 1, 0), k.height))
    return rows, columns


def _drop_isolated(points: np.ndarray, radius_m: float, min_neighbours: int) -> np.ndarray:
    """The points with at least `min_neighbours` others within `radius_m`."""
    if min_neighbours <= 0 or len(points) == 0:
        return points
    counts = cKDTree(points).query_ball_point(points, radius_m, return_length=True)
    return np.asarray(points[np.asarray(counts) > min_neighbours], dtype=np.float64)


def _inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _angle_deg(rotation: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))
