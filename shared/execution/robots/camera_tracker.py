"""The simulated robots' image tracker: the object's pose only from depth frames the engine renders.

A real robot learns where the object is from its cameras, with its own arm and hand in view; so do the simulated
ones by default. At each tracking frame the engine renders depth from every camera of the rig as it truly stands
(`CameraRig.true_poses`: a calibration is never exact), the D435-class noise of `shared.world.sim.camera` is added, and
the frames go to `shared.world.perception.tracking.ObjectTracker` stamped with the poses the system *believes*
(`CameraRig.believed`, levelled to the table once per rig as the capture's frames are), together with the robot's
self-filter mask (the pixels its model covers at its measured joints) and the known obstacles and walls (their points
are left out, as the planner leaves them out of a cloud). The tracker segments the object, registers
the model the system has (the told mesh, or the reconstruction it planned around) and reports a pose with a
fitness, or "lost". Nothing here reads the simulator's object pose: the engine only draws pictures.

Engines provide `render(T_world_cameras, intrinsics) -> [(ideal depth, robot mask)]` (PyBullet's TinyRenderer in
`sim/robot.py`, MuJoCo's renderer in `mujoco/cameras.py`).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from shared.contracts.messages import Obstacle
from shared.world.perception.depth import DepthFrame, Intrinsics, level_to_table
from shared.world.perception.tracking import ObjectTracker, TrackedPose, TrackingConfig
from shared.world.sim.camera import (
    DEFAULT_SIZE,
    CameraPose,
    StereoDepthNoise,
    default_cameras,
    renderer_intrinsics,
    true_camera_pose,
)
from shared.world.sim.world import CameraError

Window = tuple[slice, slice]  # (rows, columns) of an image
Renderer = Callable[[Sequence[np.ndarray], Intrinsics, Sequence[Window]], list[tuple[np.ndarray, np.ndarray]]]
"""What an engine renders for the tracker from cameras at T_world_camera (OpenCV): per camera, ideal metric depth
[H, W] (0: nothing) and the robot's self-filter mask [H, W] bool. Only each camera's window need be drawn."""

EDGE_MARGIN_PX = 2  # drawn around the tracker's window: the noise model's edge test looks one pixel beyond it


@dataclass(frozen=True)
class CameraRig:
    """The depth cameras around the table: where the system believes each stands (its calibration) and, with
    `errors`, how far off that belief is (an execution world's drawn calibration errors; none: exact)."""

    believed: tuple[CameraPose, ...]
    errors: tuple[CameraError, ...] = ()

    def __post_init__(self) -> None:
        if not self.believed:
            raise ValueError("a camera rig needs at least one camera")
        if len(self.errors) not in (0, len(self.believed)):
            raise ValueError(f"a camera rig of {len(self.believed)} cameras needs one calibration error each or "
                             f"none, got {len(self.errors)}")

    def true_poses(self) -> list[np.ndarray]:
        """T_world_camera of each camera as it truly stands."""
        errors: Sequence[CameraError | None] = self.errors or [None] * len(self.believed)
        return [true_camera_pose(camera, error) for camera, error in zip(self.believed, errors, strict=True)]

    @classmethod
    def calibrated(cls, cameras: Sequence[CameraPose]) -> CameraRig:
        return cls(tuple(cameras))

    @classmethod
    def around(cls, T_world_O: np.ndarray, mesh: trimesh.Trimesh, count: int = 3,
               errors: Sequence[CameraError] = ()) -> CameraRig:
        """The default rig (shared.world.sim.camera.default_cameras: as the capture aims them) at an object at
        T_world_O; `errors`: the first `count` of them are the cameras' calibration errors."""
        T = np.asarray(T_world_O, dtype=np.float64)
        height = float(np.ptp((np.asarray(mesh.vertices) @ T[:3, :3].T)[:, 2]))
        cameras = default_cameras((float(T[0, 3]), float(T[1, 3])), count, height)
        return cls(tuple(cameras), tuple(errors[:count]) if errors else ())


def tracking_noise(size: tuple[int, int]) -> StereoDepthNoise:
    """The D435's noise in a mode of `size`: its disparity is measured on a sensor binned to that width, so the
    focal length in pixels, and with it the depth precision, scale with the width."""
    nominal = StereoDepthNoise()
    return StereoDepthNoise(focal_px=nominal.focal_px * size[0] / DEFAULT_SIZE[0])


class CameraTracker:
    """Tracks the object from what `render` draws of the scene (see the module docstring)."""

    source = "image-tracker"

    def __init__(self, render: Renderer, config: TrackingConfig = TrackingConfig()):
        self.render = render
        self.config = config
        self.intrinsics = renderer_intrinsics(config.image_size)
        self.noise = tracking_noise(config.image_size)
        self._tracker: ObjectTracker | None = None
        self._rig: CameraRig | None = None
        self._believed: list[np.ndarray] = []  # the rig's poses as calibrated, then levelled to the table
        self._rng = np.random.default_rng(0)

    def reset(self, model: trimesh.Trimesh, T_world_O: np.ndarray, rig: CameraRig, seed: int,
              obstacles: Sequence[Obstacle] = ()) -> None:
        """Track `model` (the system's, in its frame O), which the system was told stands at `T_world_O`, through
        `rig`, among the known `obstacles`; the depth noise drawn from `seed`. A new rig is first levelled to the
        table (`_level`)."""
        self._tracker = ObjectTracker.from_mesh(model, self.config)
        self._tracker.reset(np.asarray(T_world_O, dtype=np.float64), obstacles)
        self._rng = np.random.default_rng(seed)
        size = self._tracker.config.image_size  # the camera mode of this model (a small one's is finer)
        if size != (self.intrinsics.width, self.intrinsics.height):
            self.intrinsics, self.noise = renderer_intrinsics(size), tracking_noise(size)
            self._rig = None  # levelled in the other mode
        if rig != self._rig:
            self._believed = self._level(rig)
        self._rig = rig

    def _level(self, rig: CameraRig) -> list[np.ndarray]:
        """Each camera's pose refined against the table in one whole frame of it (`level_to_table`), as the
        capture's frames are: the tracker and the model it registers see the table at the same height."""
        calibrated = [camera.T_world_camera() for camera in rig.believed]
        whole = (slice(0, self.intrinsics.height), slice(0, self.intrinsics.width))
        seen = self.render(rig.true_poses(), self.intrinsics, [whole] * len(calibrated))
        rng = np.random.default_rng(0)  # its own: a trial's noise must not depend on whether its rig was new
        return [level_to_table(DepthFrame(self.noise.apply(depth, rng).astype(np.float32), self.intrinsics,
                                          T)).T_world_camera for (depth, _), T in zip(seen, calibrated, strict=True)]

    @property
    def ready(self) -> bool:
        return self._tracker is not None

    def frame(self) -> TrackedPose:
        """One tracking frame now: render, add the sensor's noise, segment and register."""
        if self._tracker is None or self._rig is None:
            raise RuntimeError("the image tracker has no object to track: reset it with the object's model first")
        believed = self._believed
        # Only the pixels the tracker will read are drawn and made noisy (a camera's simulation costs per pixel).
        windows = [self._window(T) for T in believed]
        frames, masks = [], []
        seen = self.render(self._rig.true_poses(), self.intrinsics, windows)
        for (depth, robot_mask), T_world_camera, (rows, columns) in zip(seen, believed, windows, strict=True):
            noisy = np.zeros(depth.shape, dtype=np.float32)
            noisy[rows, columns] = self.noise.apply(depth[rows, columns], self._rng)
            frames.append(DepthFrame(noisy, self.intrinsics, T_world_camera))
            masks.append(robot_mask)
        return self._tracker.update(frames, masks)

    def _window(self, T_world_camera: np.ndarray) -> Window:
        assert self._tracker is not None
        rows, columns = self._tracker.search_window(self.intrinsics, T_world_camera)
        k, margin = self.intrinsics, EDGE_MARGIN_PX
        return (slice(max(rows.start - margin, 0), min(rows.stop + margin, k.height)),
                slice(max(columns.start - margin, 0), min(columns.stop + margin, k.width)))

    def steps_per_frame(self, time_step_s: float) -> int:
        """Physics steps between two frames."""
        return max(1, round(1.0 / (self.config.rate_hz * time_step_s)))
