"""The final split: objects drawn once for the release measurement, frozen by id and content hash, and
readable by one path only.

Objects. `final-<family>-<NN>`: FINAL_PER_FAMILY fresh draws of every procedural family (the primitives and
the everyday families, from seeds of their own: none is a library object) and ROUND_COUNT objects of
`round`, a family no model, index or critic trains on (it is not in the library at all): small round
objects that roll, which the development split lacks (balls and fruit-like ellipsoids).

Frozen. `final_split.json` beside this file is the committed manifest: each id with the SHA-256 of its mesh
as generated (`mesh_sha256`). Loading the split (`load_final_split`) and reading any final object's mesh
check it: a changed generator raises FinalSplitChangedError naming the object, never a silently different
object. (A deliberate new final split is a new FINAL_VERSION and a new manifest, `python -m
shared.world.objects.final_split --write`, not an edit of this one.)

Guarded. Every library load of a final id (`catalog.resolve_library_id`, which every load by id goes
through: `gd2p push`, `gd2p objects`, the data engine, the sampler's retrieval, training) is refused with
FinalSplitAccessError unless the process holds the final-split access (`final_split_access()`), which only
the final-split evaluation (`evaluation/final_run.py`, `gd2p eval EXPERIMENT --split final`) opens, after
refusing a dirty tree (tests/test_final_split.py checks no other module opens it). Final ids are not in
`catalog.library_ids()`, so no listing, dataset or index ever names them.
"""
from __future__ import annotations

import argparse
import functools
import hashlib
import json
import math
import re
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import trimesh

from .errors import ObjectLoadError, SplitError, UnknownObjectError
from .procedural import FAMILIES, ProceduralSpec, draw_spec, procedural_mesh

FINAL_VERSION = 1  # the draw; a new final split is a new version and a new manifest
FINAL_PER_FAMILY = 5  # fresh draws of each library family
ROUND_COUNT = 12  # objects of the new family
NEW_FAMILIES = ("round",)  # no model, index or critic trains on these: they are not library families
FINAL_FAMILIES = FAMILIES + NEW_FAMILIES
MANIFEST_PATH = Path(__file__).with_name("final_split.json")
_ID_PATTERN = re.compile(r"^final-([a-z]+)-(\d{2})$")

# ----------------------------------------------------------------------------- the round family
# Balls and fruit, index % 3: a ball, a fruit standing (apple- or orange-like, a little oblate), a fruit lying
# (lemon- or plum-like, a little prolate, its long axis on the table). Regulation balls: a golf ball at least
# 42.67 mm across and at most 45.93 g (the Rules of Golf), a tennis ball 6.54-6.86 cm and 56.0-59.4 g (the ITF's
# rules); a baseball about 7.3-7.5 cm and 142-149 g. Chosen, not cited: toy and sports balls 4.3-7.5 cm and
# 0.04-0.15 kg, fruit 5-9 cm with densities 800-1000 kg/m^3 (an apple floats, an orange barely) and 0.05-0.30 kg.
# Each has a small flat where it rests (BALL_FLAT / FRUIT_FLAT of its height cut off, 1-3 mm): placed still,
# it stands; pushed, it rolls.
_ROUND_KINDS = ("ball", "fruit", "fruit-lying")
BALL_DIAMETER_M = (0.043, 0.075)
BALL_MASS_KG = (0.04, 0.15)
FRUIT_DIAMETER_M = (0.05, 0.09)
FRUIT_DENSITY_KG_M3 = (800.0, 1000.0)
FRUIT_MASS_KG = (0.05, 0.30)
BALL_FLAT = 0.01
FRUIT_FLAT = 0.03


class FinalSplitAccessError(ObjectLoadError, SplitError):
    """A final-split object asked for outside the final-split evaluation."""


class FinalSplitChangedError(ObjectLoadError):
    """A final-split object whose mesh is no longer the one frozen in the manifest (or a manifest that is off)."""


def is_final_id(text: str) -> bool:
    """True for anything of the final split's id form (`final-...`): such ids are never library or user ids."""
    return text.startswith("final-")


def final_ids() -> list[str]:
    """The final split's ids: each library family's fresh draws, then the new families'."""
    return [f"final-{family}-{index:02d}" for family in FINAL_FAMILIES for index in range(_count(family))]


def final_index(object_id: str) -> int:
    """A final id's place in the split's order (`final_ids`): what spreads the final trials' directions and cases."""
    return _final_indices()[object_id]


@functools.cache
def _final_indices() -> dict[str, int]:
    return {object_id: index for index, object_id in enumerate(final_ids())}


def _count(family: str) -> int:
    return ROUND_COUNT if family == "round" else FINAL_PER_FAMILY


def parse_final_id(object_id: str) -> tuple[str, int]:
    match = _ID_PATTERN.fullmatch(object_id)
    if not match or match.group(1) not in FINAL_FAMILIES or int(match.group(2)) >= _count(match.group(1)):
        raise UnknownObjectError(f"{object_id!r}: not a final-split object id (final-<family>-NN: "
                                 f"{FINAL_PER_FAMILY} of each of {', '.join(FAMILIES)}, {ROUND_COUNT} of round)")
    return match.group(1), int(match.group(2))


def _seed(object_id: str) -> int:
    digest = hashlib.sha256(f"gd2p-final-v{FINAL_VERSION}:{object_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


@functools.lru_cache(maxsize=256)
def final_spec(object_id: str) -> ProceduralSpec:
    """The family, designed class, dimensions and mass of a final id (no access needed: it names no mesh)."""
    family, index = parse_final_id(object_id)
    if family == "round":
        return _round_spec(object_id, index, np.random.default_rng(_seed(object_id)))
    return draw_spec(object_id, family, index, _seed(object_id))


def _round_spec(object_id: str, index: int, rng: np.random.Generator) -> ProceduralSpec:
    kind = index % len(_ROUND_KINDS)
    for _ in range(10_000):
        if _ROUND_KINDS[kind] == "ball":
            diameter = float(rng.uniform(*BALL_DIAMETER_M))
            a = b = c = diameter
            mass, (low, high) = float(rng.uniform(*BALL_MASS_KG)), BALL_MASS_KG
            flat = BALL_FLAT
        else:
            a = float(rng.uniform(*FRUIT_DIAMETER_M))
            if _ROUND_KINDS[kind] == "fruit":
                b, c = a * float(rng.uniform(0.95, 1.0)), a * float(rng.uniform(0.8, 0.95))  # a little oblate
            else:
                b = c = a * float(rng.uniform(0.7, 0.85))  # lying: the long axis along x
            mass = float(rng.uniform(*FRUIT_DENSITY_KG_M3)) * math.pi * a * b * c / 6.0
            (low, high), flat = FRUIT_MASS_KG, FRUIT_FLAT
        if low <= mass <= high:
            params = {"kind": float(kind), "a": a, "b": b, "c": c, "flat": flat, "mass_kg": mass}
            return ProceduralSpec(object_id, "round", index, "volumetric", params, (max(a, b), min(a, b), c * (1.0 - flat)))
    raise RuntimeError(f"{object_id}: no round object within its mass range")  # cannot happen with these ranges


def _round_mesh(p: dict[str, float]) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.apply_scale([p["a"] / 2, p["b"] / 2, p["c"] / 2])
    lower, upper = sphere.bounds
    keep_lower = lower - 1.0
    keep_lower[2] = lower[2] + p["flat"] * p["c"]
    keep = trimesh.creation.box(bounds=[keep_lower, upper + 1.0])
    cut: trimesh.Trimesh = trimesh.boolean.intersection([sphere, keep], engine="manifold")
    return cut


def mesh_as_generated(object_id: str) -> trimesh.Trimesh:
    """The final object's mesh straight from its generator (not checked against the manifest)."""
    spec = final_spec(object_id)
    return _round_mesh(spec.params) if spec.family == "round" else procedural_mesh(spec)


def mesh_sha256(mesh: trimesh.Trimesh) -> str:
    """The content hash of a mesh as generated: its vertices to 0.1 µm and its faces, in order."""
    vertices = np.round(np.asarray(mesh.vertices, dtype=np.float64) * 1e7).astype("<i8")
    faces = np.asarray(mesh.faces, dtype="<i8")
    return hashlib.sha256(vertices.tobytes() + b"\0" + faces.tobytes()).hexdigest()


# ----------------------------------------------------------------------------- the manifest
def read_manifest(path: Path = MANIFEST_PATH) -> dict[str, str]:
    """id -> SHA-256 of the mesh, as committed."""
    try:
        data = json.loads(path.read_text())
        objects = data["objects"]
        if data.get("version") != FINAL_VERSION or not isinstance(objects, dict):
            raise ValueError(f"version {data.get('version')!r}, expected {FINAL_VERSION}")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FinalSplitChangedError(f"the final split's manifest {path} is missing or unreadable: {exc}") from None
    return {str(k): str(v) for k, v in objects.items()}


def manifest_sha256(path: Path = MANIFEST_PATH) -> str:
    """The manifest file's own hash (a final run records it)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def checked_mesh(object_id: str, manifest: dict[str, str] | None = None) -> trimesh.Trimesh:
    """The final object's mesh, refused unless it hashes to the manifest's (FinalSplitChangedError naming it)."""
    frozen = (manifest if manifest is not None else read_manifest()).get(object_id)
    if frozen is None:
        raise FinalSplitChangedError(f"{object_id}: not in the final split's manifest {MANIFEST_PATH.name}")
    mesh = mesh_as_generated(object_id)
    actual = mesh_sha256(mesh)
    if actual != frozen:
        raise FinalSplitChangedError(
            f"{object_id}: its generator now makes a different mesh (SHA-256 {actual[:12]}…, frozen {frozen[:12]}…): "
            "the final split's objects must not change; restore the generator (procedural.py / everyday.py / "
            "final_split.py), or draw a new final split (FINAL_VERSION) deliberately")
    return mesh


def load_final_split(path: Path = MANIFEST_PATH) -> list[str]:
    """The final split's ids, after checking the manifest names exactly them and every mesh hashes as frozen."""
    manifest = read_manifest(path)
    ids = final_ids()
    if sorted(manifest) != sorted(ids):
        extra, missing = sorted(set(manifest) - set(ids)), sorted(set(ids) - set(manifest))
        raise FinalSplitChangedError(f"the final split's manifest {path.name} does not list its objects: "
                                     f"extra {extra or 'none'}, missing {missing or 'none'}")
    for object_id in ids:
        checked_mesh(object_id, manifest)
    return ids


def write_manifest(path: Path = MANIFEST_PATH) -> Path:
    """Freeze the current draw (only for a new FINAL_VERSION: a committed manifest is never rewritten)."""
    objects = {object_id: mesh_sha256(mesh_as_generated(object_id)) for object_id in final_ids()}
    families = {family: _count(family) for family in FINAL_FAMILIES}
    path.write_text(json.dumps({"version": FINAL_VERSION, "families": families, "objects": objects}, indent=1) + "\n")
    return path


# ----------------------------------------------------------------------------- the guard
_lock = threading.Lock()
_holders = 0  # process-wide: the evaluation's worker threads and processes load under the access it opened


@contextmanager
def final_split_access() -> Iterator[None]:
    """Allow final-split loads in this process while open. Only `evaluation/final_run.py` opens it (a test
    enforces that): everything else that asks for a final id gets FinalSplitAccessError."""
    global _holders
    with _lock:
        _holders += 1
    try:
        yield
    finally:
        with _lock:
            _holders -= 1


def final_access_open() -> bool:
    return _holders > 0


def check_final_access(object_id: str) -> None:
    """Raise FinalSplitAccessError unless the final-split access is open in this process."""
    if not final_access_open():
        raise FinalSplitAccessError(
            f"{object_id} is an object of the final split: it is measured once per release by `gd2p eval EXPERIMENT "
            "--split final` only (from a clean tree, logged in results/final/LOG.md), and nothing else may load it "
            "(docs/evaluation.md#final-split)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="check (default) or write the final split's manifest")
    parser.add_argument("--write", action="store_true", help="freeze the current draw (a new FINAL_VERSION only)")
    args = parser.parse_args(argv)
    if args.write:
        print(write_manifest())
        return 0
    print(f"{len(load_final_split())} final objects hash as frozen in {MANIFEST_PATH}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
