"""The object library: stable ids, where each object's mesh comes from, and the fixed splits.

Ids
- `rnd-000` .. `rnd-999`: pybullet_data's `random_urdfs` (their OBJ with the URDF's mesh scale;
  rnd-168 is excluded, see EXCLUDED_RANDOM_URDFS).
- `pb-<name>`: pybullet_data's named objects that a robot hand can push (see PYBULLET_OBJECTS).
- `proc-<family>-<NNN>`: procedural shapes with exact meshes (procedural.py).
- `mesh-<sha256[:12]>`: a user mesh file, named by its content.
- `final-<family>-<NN>`: the final split (final_split.py): not library ids, never listed, and loaded only
  inside the final-split evaluation (any other load is refused with FinalSplitAccessError).

An id is never a path: `resolve_library_id` (what every id from the bus goes through) accepts the
forms above only. `resolve_source` also takes a mesh file path, for local callers (CLI, benchmarks).

Splits are fixed by id: the named pybullet objects and the first HELD_OUT_PER_FAMILY objects of
each procedural family are always test (the everyday-like and 3D-printed-like evaluation sets of
the paper's protocol), and so is every object of the UNSEEN_FAMILIES (a shape family no model is
ever trained or tuned on); every other id falls in train / val / test 80 / 10 / 10 by a hash of
the id.

The library grew in generations: 0 is the library before the everyday procedural families, 1 adds
them (`library_generation`). Selections that take the first N ids of a split in a fixed order
(the data engine's build order, the data-size experiment's subset) rank generation 0 first, so a
command that named a count before the new families existed still picks the same objects.
"""
from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import pybullet_data
import trimesh

from . import meshio
from .errors import ObjectLoadError, SplitError, UnknownObjectError
from .final_split import FINAL_VERSION, check_final_access, checked_mesh, final_spec, is_final_id, read_manifest
from .procedural import (
    FAMILIES,
    PER_FAMILY,
    generator_version,
    is_everyday_id,
    is_procedural_id,
    parse_procedural_id,
    procedural_ids,
    procedural_mesh,
    procedural_spec,
)

SPLITS = ("train", "val", "test")
SPLIT_FRACTIONS = {"train": 0.8, "val": 0.1, "test": 0.1}
HELD_OUT_PER_FAMILY = 3  # proc-<family>-000..002: one of each shape class the family has
# Whole families kept out of training and tuning: the unseen-family test. "mug": the only family with
# a handle and a cavity (no other family, primitive or everyday, has either), at sizes and masses
# well inside those trained on, so what it measures is generalisation to a new shape, not to a new
# size; and pb-mug, a scanned mug, is already an everyday test object to compare with. (A bottle
# would be a weaker test: the lying family trains on bottles, and cylinders and cones on its parts.)
UNSEEN_FAMILIES = ("mug",)
assert set(UNSEEN_FAMILIES) <= set(FAMILIES)
RANDOM_URDF_COUNT = 1000

# Named pybullet_data objects of pushable size: (URDF or mesh path in pybullet_data, rotation
# (roll, pitch, yaw in rad) that stands the model upright in our z-up world).
# Left out: lego (3.2 cm, under a hand's 4 cm floor), domino (6 mm thin), sphere_small and
# soccerball (they roll; the ball is 1 m), tray / table / shape_sorter / teddy_large (0.4–3 m),
# bunny, torus, samurai, stone (no object scale given).
PYBULLET_OBJECTS: dict[str, tuple[str, tuple[float, float, float]]] = {
    "duck": ("duck_vhacd.urdf", (math.pi / 2, 0.0, 0.0)),  # the Collada duck is modelled +Y up
    "teddy": ("teddy_vhacd.urdf", (0.0, 0.0, 0.0)),
    "mug": ("objects/mug.urdf", (0.0, 0.0, 0.0)),  # an open surface: exercises the scan path
    "jenga": ("jenga/jenga.urdf", (0.0, 0.0, 0.0)),
    "cube-small": ("cube_small.urdf", (0.0, 0.0, 0.0)),
    "toy-cube": ("toys/cube.obj", (0.0, 0.0, 0.0)),
    "toy-cylinder": ("toys/cylinder.obj", (0.0, 0.0, 0.0)),
    "toy-prism": ("toys/prism.obj", (0.0, 0.0, 0.0)),
}

# random_urdfs entries that cannot be objects (checked by loading all 1000); their ids stay unused.
EXCLUDED_RANDOM_URDFS = {"rnd-168": "pybullet_data's random_urdfs/168/168.obj has only NaN vertices"}

_RND_PATTERN = re.compile(r"^rnd-(\d{3})$")
_MESH_ID_PATTERN = re.compile(r"^mesh-[0-9a-f]{12}$")


@dataclass(frozen=True)
class ObjectSource:
    """Where an object's mesh comes from and how to read it (no geometry loaded yet)."""

    object_id: str
    source: str  # "random_urdfs" | "pybullet_data" | "procedural" | "final" | "mesh"
    family: str  # "random", the pybullet name, the procedural family, or "user"
    native_upright: bool  # the mesh's own +z is "up" as the object is normally placed
    path: Path | None = None
    mass_kg: float | None = None  # a designed mass (everyday procedural families), else None: uniform density

    @property
    def label(self) -> str:
        """How error messages name the object."""
        return str(self.path) if self.source == "mesh" and self.path else self.object_id


@dataclass(frozen=True)
class ObjectInfo:
    """What `gd2p objects list` shows for one object."""

    id: str
    shape_class: str  # flat | volumetric | tall, in the default resting pose
    source: str
    family: str
    size_m: tuple[float, float, float]  # footprint a >= b, height H in the default resting pose
    split: str

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["size_m"] = [round(v, 4) for v in self.size_m]
        return out


# ----------------------------------------------------------------------------- ids and sources
def pybullet_data_dir() -> Path:
    return Path(pybullet_data.getDataPath())


def library_ids() -> list[str]:
    """Every library id (user meshes are not in the library)."""
    random_ids = [f"rnd-{i:03d}" for i in range(RANDOM_URDF_COUNT)]
    return [i for i in random_ids if i not in EXCLUDED_RANDOM_URDFS] + [f"pb-{name}" for name in PYBULLET_OBJECTS] + procedural_ids()


def user_mesh_id(path: Path) -> str:
    return "mesh-" + hashlib.sha256(path.read_bytes()).hexdigest()[:12]


def is_user_mesh_id(text: str) -> bool:
    """`mesh-<sha256[:12]>`: the id of a user mesh file loaded before."""
    return _MESH_ID_PATTERN.fullmatch(text) is not None


def resolve_source(id_or_path: str | Path) -> ObjectSource:
    """Map a library id or a mesh file path to its ObjectSource (UnknownObjectError otherwise).

    A `Path`, or a string that is not a library id and looks like a file (a separator, a suffix, an
    existing file), is read as a mesh file. Ids from the bus go through `resolve_library_id` instead.
    """
    text = str(id_or_path)
    if isinstance(id_or_path, Path) or (not _is_library_id(text) and _looks_like_path(text)):
        return _mesh_file_source(Path(text).expanduser())
    try:
        return resolve_library_id(text)
    except UnknownObjectError as exc:
        raise UnknownObjectError(f"{exc}, or a path to an OBJ/STL/PLY/GLB file") from None


def _is_library_id(text: str) -> bool:
    """One of the library's ids (a file of that name in the working directory does not shadow it)."""
    return bool(_RND_PATTERN.fullmatch(text)) or (text.startswith("pb-") and text[3:] in PYBULLET_OBJECTS) \
        or text in procedural_ids() or is_final_id(text)


def _looks_like_path(text: str) -> bool:
    return "/" in text or "\\" in text or bool(Path(text).suffix) or Path(text).is_file()


def _mesh_file_source(path: Path) -> ObjectSource:
    meshio.check_suffix(path)
    if not path.is_file():
        raise ObjectLoadError(f"{path}: no such file")
    return ObjectSource(user_mesh_id(path), "mesh", "user", True, path)


def resolve_library_id(text: str) -> ObjectSource:
    """The ObjectSource of a library id; never reads `text` as a path (UnknownObjectError otherwise).

    `mesh-<hash>` ids are not library objects: `model.load_library_object` looks them up in the cache.
    """
    match = _RND_PATTERN.fullmatch(text)
    if text in EXCLUDED_RANDOM_URDFS:
        raise ObjectLoadError(f"{text}: excluded from the library: {EXCLUDED_RANDOM_URDFS[text]}")
    if match:
        return ObjectSource(text, "random_urdfs", "random", False, pybullet_data_dir() / "random_urdfs" / match.group(1) / f"{match.group(1)}.urdf")
    if text.startswith("pb-") and text[3:] in PYBULLET_OBJECTS:
        return ObjectSource(text, "pybullet_data", text[3:], True, pybullet_data_dir() / PYBULLET_OBJECTS[text[3:]][0])
    if is_procedural_id(text):
        spec = procedural_spec(text)
        return ObjectSource(text, "procedural", spec.family, True, mass_kg=spec.mass_kg)
    if is_final_id(text):
        check_final_access(text)  # the final split's objects: only inside the final-split evaluation
        spec = final_spec(text)
        return ObjectSource(text, "final", spec.family, True, mass_kg=spec.mass_kg)
    raise UnknownObjectError(
        f"{text!r}: unknown object; expected rnd-000..rnd-{RANDOM_URDF_COUNT - 1}, pb-<{'|'.join(PYBULLET_OBJECTS)}>, "
        f"proc-<family>-000..{PER_FAMILY - 1:03d}, mesh-<hash> (a mesh loaded before)"
    )


def read_source_mesh(source: ObjectSource) -> trimesh.Trimesh:
    """The raw mesh in metres, in the source's own frame (upright rotation applied)."""
    if source.source == "procedural":
        return procedural_mesh(procedural_spec(source.object_id))
    if source.source == "final":
        check_final_access(source.object_id)
        return checked_mesh(source.object_id)  # refused if it is not the mesh frozen in the manifest
    assert source.path is not None
    if source.source == "mesh":
        return meshio.read_mesh_file(source.path)
    if not source.path.is_file():
        raise ObjectLoadError(f"{source.object_id}: asset file {source.path} is missing (is pybullet installed completely?)")
    if source.path.suffix == ".urdf":
        visual = meshio.read_urdf_visual(source.path)
        mesh = meshio.read_asset_mesh(visual.mesh_path, visual.scale, visual.origin)
    else:
        mesh = meshio.read_asset_mesh(source.path)
    if source.source == "pybullet_data":
        mesh.apply_transform(trimesh.transformations.euler_matrix(*PYBULLET_OBJECTS[source.family][1], axes="sxyz"))
    return mesh


def source_fingerprint(source: ObjectSource) -> bytes:
    """Bytes that change iff the source geometry changes (file contents, scale, generator)."""
    if source.source == "procedural":
        spec = procedural_spec(source.object_id)
        return json.dumps({**generator_version(spec.family), "family": spec.family, "params": spec.params}, sort_keys=True).encode()
    if source.source == "final":  # keyed by the frozen content: a cached final object is the one in the manifest
        sha256 = read_manifest().get(source.object_id)
        return json.dumps({"final": FINAL_VERSION, "id": source.object_id, "sha256": sha256}, sort_keys=True).encode()
    assert source.path is not None
    parts = [source.path.read_bytes()]
    if source.path.suffix == ".urdf":
        parts.append(meshio.read_urdf_visual(source.path).mesh_path.read_bytes())
    if source.source == "pybullet_data":
        parts.append(json.dumps(PYBULLET_OBJECTS[source.family][1]).encode())
    if source.source == "mesh":
        parts.append(source.path.suffix.lower().encode())  # the same bytes as GLB are read Y-up
    return b"\0".join(parts)


# ----------------------------------------------------------------------------- splits
def split_of(object_id: str) -> str:
    """The fixed split of an id: train / val / test, or final for the final split's ids (see the module docstring)."""
    if is_final_id(object_id):
        return "final"
    if object_id.startswith("pb-"):
        return "test"
    if is_procedural_id(object_id):
        family, index = parse_procedural_id(object_id)
        if family in UNSEEN_FAMILIES or index < HELD_OUT_PER_FAMILY:
            return "test"
    digest = hashlib.sha256(f"gd2p-split-v1:{object_id}".encode()).digest()
    u = int.from_bytes(digest[:8], "little") / 2.0**64
    if u < SPLIT_FRACTIONS["train"]:
        return "train"
    if u < SPLIT_FRACTIONS["train"] + SPLIT_FRACTIONS["val"]:
        return "val"
    return "test"


def library_generation(object_id: str) -> int:
    """0 for the library before the everyday procedural families, 1 for their objects (see the module docstring)."""
    return 1 if is_everyday_id(object_id) else 0


def assert_split(object_id: str, split: str) -> None:
    """Raise SplitError unless `object_id` belongs to `split` (guards training against test data)."""
    check_split_name(split)
    actual = split_of(object_id)
    if actual != split:
        raise SplitError(f"{object_id} belongs to the {actual} split, not {split}" + ("; test objects are never used for training" if actual == "test" else ""))


def check_split_name(split: str | None) -> None:
    if split is not None and split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")


def list_object_ids(split: str | None = None) -> list[str]:
    """Library ids, optionally of one split (cheap: no geometry is loaded)."""
    check_split_name(split)
    return [i for i in library_ids() if split is None or split_of(i) == split]


def procedural_info(object_id: str) -> ObjectInfo:
    """Info of a procedural object straight from its designed dimensions (no mesh needed)."""
    spec = procedural_spec(object_id)
    return ObjectInfo(object_id, spec.shape_class, "procedural", spec.family, spec.dims, split_of(object_id))
