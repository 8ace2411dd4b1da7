"""Object library: stable ids, meshes, mass, resting poses, SDF, splits, physics assets.

    from shared.world.objects import load_object, list_objects, assert_split, write_object_urdf
    obj = load_object("proc-box-017")          # or "proc-mug-004", "rnd-042", "pb-mug", "path/to/scan.ply"
    T_D_O = obj.T_D_O(yaw_rad=0.3)              # resting on the table, centre of mass over D's origin
    dist, grad = obj.signed_distance(points_d, T_D_O)   # torch, differentiable
    urdf = write_object_urdf(obj)               # PyBullet: base pose == T_world_O

See catalog.py (ids, splits), procedural.py and everyday.py (the procedural families), model.py
(ObjectModel), geometry.py (frame O, resting poses, shape classes), sdf.py (grid and lookup),
physics.py (convex decomposition, URDF).
"""
from .catalog import (
    HELD_OUT_PER_FAMILY,
    PYBULLET_OBJECTS,
    SPLITS,
    UNSEEN_FAMILIES,
    ObjectInfo,
    assert_split,
    library_generation,
    list_object_ids,
    split_of,
)
from .errors import ObjectLoadError, SplitError, UnknownObjectError
from .everyday import EVERYDAY_FAMILIES
from .geometry import SHAPE_CLASSES, RestingPose, shape_class
from .model import DEFAULT_DENSITY, MASS_LIMITS_KG, ObjectModel, list_objects, load_object
from .physics import convex_decomposition, load_in_pybullet, write_object_urdf
from .procedural import FAMILIES, PER_FAMILY, PRIMITIVE_FAMILIES
from .sdf import DEFAULT_RESOLUTION, SdfGrid, compute_sdf_grid

__all__ = [
    "DEFAULT_DENSITY",
    "DEFAULT_RESOLUTION",
    "EVERYDAY_FAMILIES",
    "FAMILIES",
    "HELD_OUT_PER_FAMILY",
    "MASS_LIMITS_KG",
    "PER_FAMILY",
    "PRIMITIVE_FAMILIES",
    "PYBULLET_OBJECTS",
    "SHAPE_CLASSES",
    "SPLITS",
    "UNSEEN_FAMILIES",
    "ObjectInfo",
    "ObjectLoadError",
    "ObjectModel",
    "RestingPose",
    "SdfGrid",
    "SplitError",
    "UnknownObjectError",
    "assert_split",
    "compute_sdf_grid",
    "convex_decomposition",
    "library_generation",
    "list_object_ids",
    "list_objects",
    "load_in_pybullet",
    "load_object",
    "shape_class",
    "split_of",
    "write_object_urdf",
]
