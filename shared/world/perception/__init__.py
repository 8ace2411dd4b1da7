"""Perception: objects as a camera sees them (algorithms only, no bus code).

    from shared.world.perception import load_cloud, reconstruct, object_from_cloud, bps_from_cloud, Region
    recon = reconstruct(load_cloud("cloud.ply").points, region=Region((0.55, 0.0)))   # mesh in the world
    captured = object_from_cloud(points_world)     # ObjectModel + T_world_O, cached by content hash

cloud.py (Cloud, load_cloud / save_cloud for .ply .pcd .npy, input checks), depth.py (DepthFrame,
Intrinsics, back-projection), reconstruct.py (table, cluster, watertight solid; the method choice
and its measurement), decompose.py (the solid's convex pieces: the collision shape, found in the
height map instead of by V-HACD), object_model.py (ObjectModel of a capture, BPS from the cloud).
The simulated camera that produces clouds is shared.world.sim.camera.

object_model imports the object library (torch): its names load on first use, so reading a cloud
file stays cheap for a command-line client.
"""
from typing import Any

from .cloud import CLOUD_SUFFIXES, Cloud, check_points, cloud_for_request, load_cloud, save_cloud, voxel_downsample
from .depth import DepthFrame, Intrinsics, frames_to_cloud
from .errors import CloudFileError, PerceptionError
from .reconstruct import METHODS, Reconstruction, ReconstructionSettings, Region, reconstruct

_LAZY = {"CloudObject", "bps_from_cloud", "bps_points", "cloud_key", "object_from_cloud", "object_from_reconstruction"}

__all__ = [
    "CLOUD_SUFFIXES", "METHODS", "Cloud", "CloudFileError", "DepthFrame", "Intrinsics", "PerceptionError",
    "Reconstruction", "ReconstructionSettings", "Region", "check_points", "cloud_for_request", "frames_to_cloud", "load_cloud",
    "reconstruct", "save_cloud", "voxel_downsample",
    "CloudObject", "bps_from_cloud", "bps_points", "cloud_key", "object_from_cloud", "object_from_reconstruction",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from . import object_model

        return getattr(object_model, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
