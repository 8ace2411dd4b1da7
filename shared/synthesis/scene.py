"""The object as the optimiser sees it: resting on the table in the direction frame D.

The object library (`shared.world.objects`) gives the mesh and a voxel SDF in the object frame O and the
resting poses; a resting pose and a yaw give T_D_O - the object on the table with its centre of
mass above D's origin, the placement the validator uses too. Everything here is in D.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from shared.world.objects import ObjectModel

SURFACE_SAMPLE_SEED = 0


@dataclass(frozen=True, eq=False)
class PushScene:
    """One object at one placement: SDF queries, surface samples, convex hull and torque reference, in D."""

    object: ObjectModel
    pose_index: int  # which of the object's resting poses
    yaw_rad: float
    transform_d: np.ndarray  # 4x4 T_D_O
    surface_points: torch.Tensor  # [N,3] for E_pen
    check_points: torch.Tensor  # [M,3] denser, for the reported max penetration
    hull_vertices: np.ndarray  # [V,3] convex hull vertices, for the initialisation
    centroid: torch.Tensor  # [3] centre of mass (O's origin), the reference point of E_fc's torques

    @classmethod
    def from_object(cls, obj: ObjectModel, pose_index: int | None = None, yaw_rad: float = 0.0,
                    surface_points: int = 1024, check_points: int = 4096) -> PushScene:
        """Place `obj` resting in pose `pose_index` (its default pose if None), turned by `yaw_rad` about z."""
        index = obj.default_pose_index if pose_index is None else pose_index
        if not 0 <= index < len(obj.resting_poses):
            raise ValueError(f"{obj.id} has {len(obj.resting_poses)} resting poses; pose index {index} does not exist")
        transform = obj.T_D_O(index, yaw_rad)
        # One sample set: its first `surface_points` are themselves area-uniform (trimesh draws i.i.d.).
        points, _ = obj.surface_points(max(surface_points, check_points), seed=SURFACE_SAMPLE_SEED, T_D_O=transform)
        samples = torch.tensor(points, dtype=torch.float32)
        hull = obj.mesh.convex_hull.vertices @ transform[:3, :3].T + transform[:3, 3]
        return cls(
            object=obj, pose_index=index, yaw_rad=float(yaw_rad), transform_d=transform,
            surface_points=samples[:surface_points].contiguous(), check_points=samples[:check_points].contiguous(),
            hull_vertices=np.asarray(hull), centroid=torch.tensor(transform[:3, 3], dtype=torch.float32),
        )

    @property
    def object_id(self) -> str:
        return self.object.id

    @property
    def distance_error_m(self) -> float:
        """Bound on how far `distance` can exceed the true distance: one grid cell diagonal.

        Trilinear interpolation of a 1-Lipschitz field mixes node values each within a cell diagonal
        of the true value at the query point; outside the grid the lookup never over-estimates.
        """
        return float(np.linalg.norm(self.object.sdf.spacing))

    def distance(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance [...] (negative inside; differentiable) and unit outward normal [..., 3] at points in D."""
        return self.object.signed_distance(points, self._transform_t)

    @property
    def _transform_t(self) -> torch.Tensor:
        return torch.as_tensor(self.transform_d, dtype=torch.float32)
