"""The object as the optimiser sees it: resting on the table in the direction frame D.

The object library gives the mesh and a voxel SDF in the object frame O (centre of mass, principal
axes) and its resting poses; a resting pose and a yaw give T_D_O (the object on the table, centre
of mass above D's origin - the same placement the validator uses). Queries arrive in D and are
mapped to O for the SDF lookup; normals are rotated back.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from shared.objects.sdf import SdfGrid

SURFACE_SAMPLE_SEED = 0


@dataclass(frozen=True, eq=False)
class PushScene:
    """Object geometry in D: SDF queries, surface samples, convex hull and the torque reference point."""

    object_id: str
    transform_d: np.ndarray  # 4x4 T_D_O
    sdf: SdfGrid  # in O
    surface_points: torch.Tensor  # [N,3] in D, for E_pen
    check_points: torch.Tensor  # [M,3] in D, denser, for the reported max penetration
    hull_vertices: np.ndarray  # [V,3] convex hull vertices in D, for the initialisation
    centroid: torch.Tensor  # [3] centre of mass in D (= O's origin), for E_fc torques
    rotation: torch.Tensor  # [3,3] R_D_O

    @classmethod
    def build(cls, object_id: str, mesh_o: trimesh.Trimesh, sdf: SdfGrid, transform_d: np.ndarray,
              surface_points: int, check_points: int) -> "PushScene":
        """Place an object (mesh and SDF in O) at T_D_O and sample its surface (fixed seed)."""
        transform_d = np.asarray(transform_d, dtype=np.float64)
        mesh_d = mesh_o.copy()
        mesh_d.apply_transform(transform_d)
        samples, _ = trimesh.sample.sample_surface(mesh_d, max(surface_points, check_points), seed=SURFACE_SAMPLE_SEED)
        samples = torch.tensor(samples, dtype=torch.float32)
        return cls(
            object_id=object_id,
            transform_d=transform_d,
            sdf=sdf,
            surface_points=samples[:surface_points].contiguous(),
            check_points=samples[:check_points].contiguous(),
            hull_vertices=np.asarray(mesh_d.convex_hull.vertices),
            centroid=torch.tensor(transform_d[:3, 3], dtype=torch.float32),
            rotation=torch.tensor(transform_d[:3, :3], dtype=torch.float32),
        )

    def distance(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance [...] (negative inside; differentiable) and unit outward normal [..., 3] at points in D."""
        local = (points - self.centroid) @ self.rotation  # R^T (p - t), row-vector form
        distance, gradient = self.sdf.query(local)
        return distance, gradient @ self.rotation.T

    def height(self) -> float:
        """Top of the object above the table (m)."""
        return float(self.hull_vertices[:, 2].max())
