"""Depth images with their intrinsics and camera poses, and their back-projection to a world cloud.

Camera frame convention (OpenCV, what RealSense / Azure Kinect SDKs report): x right, y down,
z forward along the optical axis; depth is the z coordinate in that frame (not the ray length).
Pixel (row v, column u) has its centre at image coordinates (u, v), so a centred principal point
is cx = (width - 1) / 2. Invalid pixels hold 0 (the RealSense convention) or NaN.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import PerceptionError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth image, in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> Intrinsics:
        """Square pixels, centred principal point, horizontal field of view `hfov_deg`."""
        if width < 1 or height < 1 or not 0.0 < hfov_deg < 180.0:
            raise PerceptionError(f"bad intrinsics: {width}x{height} px, horizontal FOV {hfov_deg} deg")
        focal = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, focal, focal, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan((self.height / 2.0) / self.fy))


@dataclass(frozen=True, eq=False)
class DepthFrame:
    """One depth image: metric depth [H, W] (0 / NaN invalid), intrinsics, camera pose in the world."""

    depth_m: np.ndarray
    intrinsics: Intrinsics
    T_world_camera: np.ndarray  # 4x4, OpenCV camera frame -> world

    def __post_init__(self) -> None:
        shape = (self.intrinsics.height, self.intrinsics.width)
        if np.shape(self.depth_m) != shape:
            raise PerceptionError(f"depth image has shape {np.shape(self.depth_m)}, intrinsics say {shape}")
        if np.shape(self.T_world_camera) != (4, 4) or not np.all(np.isfinite(self.T_world_camera)):
            raise PerceptionError("T_world_camera must be a finite 4x4 transform")

    @property
    def valid(self) -> np.ndarray:
        """[H, W] bool: pixels with a depth measurement."""
        depth = np.asarray(self.depth_m, dtype=np.float64)
        return np.asarray(np.isfinite(depth) & (depth > 0.0), dtype=bool)

    @property
    def camera_position(self) -> np.ndarray:
        return np.array(np.asarray(self.T_world_camera, dtype=np.float64)[:3, 3])

    def points_camera(self) -> np.ndarray:
        """[M, 3] valid pixels back-projected into the camera frame (row-major pixel order)."""
        k = self.intrinsics
        rows, cols = np.nonzero(self.valid)
        z = np.asarray(self.depth_m, dtype=np.float64)[rows, cols]
        return np.stack([(cols - k.cx) * z / k.fx, (rows - k.cy) * z / k.fy, z], axis=1)

    def points_world(self) -> np.ndarray:
        """[M, 3] valid pixels back-projected into the world frame."""
        return transform_points_no_blas(np.asarray(self.T_world_camera, dtype=np.float64), self.points_camera())


def transform_points_no_blas(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`points @ T[:3, :3].T + T[:3, 3]` as three broadcast multiply-adds.

    A [N, 3] x [3, 3] product goes through BLAS, whose threads spin against any other busy process:
    measured 80-90 ms for 140k points on a loaded 2-core machine, against 15 ms this way.
    """
    rotation = T[:3, :3]
    moved = points[:, 0:1] * rotation[:, 0] + points[:, 1:2] * rotation[:, 1] + points[:, 2:3] * rotation[:, 2] + T[:3, 3]
    return np.asarray(moved, dtype=np.float64)


def frames_to_cloud(frames: Sequence[DepthFrame]) -> np.ndarray:
    """The world-frame cloud of several depth frames (their valid pixels, concatenated)."""
    if not frames:
        raise PerceptionError("no depth frames given")
    return np.concatenate([frame.points_world() for frame in frames], axis=0)
