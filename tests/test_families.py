"""The everyday procedural families: designs within their cited ranges, loading, physics, splits, and
the library as it was before them (ids, splits, meshes and selections unchanged)."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math

import numpy as np
import pybullet
import pytest
import torch

from shared.world.objects import (
    EVERYDAY_FAMILIES,
    FAMILIES,
    HELD_OUT_PER_FAMILY,
    PER_FAMILY,
    PRIMITIVE_FAMILIES,
    UNSEEN_FAMILIES,
    SplitError,
    UnknownObjectError,
    assert_split,
    library_generation,
    list_object_ids,
    load_object,
    split_of,
    write_object_urdf,
)
from shared.world.objects import everyday as ev
from shared.world.objects.catalog import resolve_library_id, source_fingerprint
from shared.world.objects.procedural import procedural_spec
from shared.world.sim.params import PhysicsParams
from shared.world.sim.scene import SimScene

# Measured on the library before the everyday families (commit 679668e), and unchanged since.
EXISTING_MESH_HASHES = {
    "proc-box-013": "02324947dba842195df87b42b467645a6671215aee4c320d75bffe1a14fad8d4",
    "proc-cylinder-001": "d478d4b62f4b7cd3bf5cc8f50171e8ea7f50f596a6d577f6cc13bbe3df089657",
    "proc-hull-012": "aac0df0952218cd1a2d698fb4181aa4be55616cf7bfc8eb80ebc053bc028c2c8",
    "rnd-002": "866bf8a95080b231b9d8cc4ea6b7a15c780bfb6e9add7b32cc69c917af77c35a",
}
EXISTING_SPLITS = {"proc-box-013": "train", "proc-cylinder-001": "test", "proc-hull-012": "val", "rnd-002": "val"}
EXISTING_LIBRARY = (1607, "6a48fa76b61d129e")  # ids, digest of every id's split and generator fingerprint
EXISTING_SELECTIONS = {"train230": "a7fc065a9b865c44", "subset40": "ba72dee89627ba99"}
PIECES = {"spatula": 3, "small": 1, "bottle": 3, "mug": 58, "banana": 12}  # lying: 1 (can) or 3 (bottle)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("gd2p-families-cache")


def _ids(family: str) -> list[str]:
    return [f"proc-{family}-{index:03d}" for index in range(PER_FAMILY)]


def _within(value: float, bounds: tuple[float, float], rel: float = 0.0) -> bool:
    return bounds[0] * (1 - rel) - 1e-9 <= value <= bounds[1] * (1 + rel) + 1e-9


def _library_digest(ids: list[str]) -> str:
    digest = hashlib.sha256()
    for object_id in ids:
        digest.update(f"{object_id}:{split_of(object_id)}\n".encode())
        if object_id.startswith("proc-"):
            digest.update(source_fingerprint(resolve_library_id(object_id)))
    return digest.hexdigest()[:16]


# ----------------------------------------------------------------------------- designs
def test_every_design_is_within_its_family_ranges():
    """Sizes and masses of all 600 designs within the ranges everyday.py cites (or chose)."""
    round_tolerance = 0.01  # a 32- or 48-gon's smallest rectangle is within 1% of its diameter
    for family in EVERYDAY_FAMILIES:
        classes = ev.EVERYDAY_FAMILY_CLASSES[family]
        for index, object_id in enumerate(_ids(family)):
            spec = procedural_spec(object_id)
            p, (a, b, height) = spec.params, spec.dims
            assert spec.shape_class == classes[index % len(classes)], object_id
            assert spec.mass_kg is not None and _within(spec.mass_kg, ev.MASS_RANGES_KG[family]), object_id
            if family == "spatula":
                assert _within(a, ev.SPATULA_LENGTH_M) and _within(b, ev.SPATULA_BLADE_WIDTH_M), object_id
                assert _within(height, ev.SPATULA_HANDLE_THICKNESS_M), object_id
                assert _within(p["blade_thickness"], ev.SPATULA_BLADE_THICKNESS_M) and p["blade_thickness"] < height
                assert _within(p["blade_length"], ev.SPATULA_BLADE_LENGTH_M), object_id
            elif family == "small":
                assert max(a, b, height) < ev.SMALL_MAX_EXTENT_M, object_id
                kind = ("die", "eraser", "cap")[index % 3]
                if kind == "die":
                    assert a == b == height and _within(a, ev.DIE_SIDE_M), object_id
                if kind == "cap":
                    assert _within(a, ev.CAP_DIAMETER_M, round_tolerance), object_id
            elif family == "bottle":
                assert _within(b, ev.BOTTLE_DIAMETER_M, round_tolerance) and _within(height, ev.BOTTLE_HEIGHT_M), object_id
                assert _within(p["neck_diameter"], ev.BOTTLE_NECK_DIAMETER_M) or p["neck_diameter"] == 0.6 * p["diameter"]
            elif family == "mug":
                assert _within(b, ev.MUG_DIAMETER_M, round_tolerance) and _within(height, ev.MUG_HEIGHT_M), object_id
                assert a > b  # the handle stands out
            elif family == "banana":
                assert _within(p["length"], ev.BANANA_LENGTH_M) and a < ev.BANANA_LENGTH_M[1], object_id
                assert 0.03 < height < 0.045 and b < a, object_id
            else:  # lying: as long as it is, as wide and high as its diameter
                diameters = (min(ev.CAN_DIAMETER_M[0], ev.BOTTLE_DIAMETER_M[0]), max(ev.CAN_DIAMETER_M[1], ev.BOTTLE_DIAMETER_M[1]))
                assert _within(b, diameters, round_tolerance) and height == pytest.approx(b, rel=round_tolerance), object_id
                assert a <= max(ev.CAN_LENGTH_MAX_M, ev.BOTTLE_HEIGHT_M[1]) + 1e-9, object_id


# ----------------------------------------------------------------------------- loading
@pytest.mark.parametrize("family", EVERYDAY_FAMILIES)
def test_family_loads_watertight_with_its_designed_size_mass_and_exact_convex_pieces(cache, family):
    for index in range(HELD_OUT_PER_FAMILY):  # one of each kind for small (die, eraser, cap) and lying (can, bottle)
        spec = procedural_spec(f"proc-{family}-{index:03d}")
        obj = load_object(spec.object_id, cache_dir=cache)
        assert obj.family == family and obj.watertight and not obj.mass_from_voxels, obj
        assert obj.mass == pytest.approx(spec.mass_kg) and 100 < obj.density < 3000, obj  # not the 500 kg/m^3 guess
        assert obj.default_pose.native and obj.info.shape_class == spec.shape_class, obj  # rests as designed
        np.testing.assert_allclose(obj.info.size_m, spec.dims, atol=1e-6)
        parts = obj.convex_parts
        expected = PIECES.get(family, 1 + 2 * (index % 2))
        assert parts is not None and len(parts) == expected, obj  # its own pieces: no V-HACD
        assert len(obj.mesh.faces) < 5000, obj
    assert load_object(spec.object_id, cache_dir=cache).provenance["geometry"] == "cache"


def test_a_mug_is_hollow_and_open_at_the_top(cache):
    obj = load_object("proc-mug-000", cache_dir=cache)
    p = procedural_spec(obj.id).params
    T = obj.T_D_O()
    mesh = obj.mesh_in_d()
    top = mesh.bounds[1, 2]
    centre = np.asarray(mesh.vertices)[np.asarray(mesh.vertices)[:, 2] < 1e-6].mean(axis=0)  # under the cup's axis
    probes = torch.tensor([[centre[0], centre[1], z] for z in (p["bottom"] / 2, p["bottom"] + 0.01, top - 0.005)], dtype=torch.float64)
    distance, _ = obj.signed_distance(probes, T)
    assert distance[0] < 0 < distance[1] and distance[2] > 0  # solid floor, then the cavity up to the rim
    assert obj.volume < 0.5 * math.pi * (p["diameter"] / 2) ** 2 * p["height"]


def test_each_family_rests_still_on_the_table_in_pybullet(cache):
    params = PhysicsParams()
    for object_id in [f"proc-{family}-000" for family in EVERYDAY_FAMILIES] + ["proc-lying-001"]:
        obj = load_object(object_id, cache_dir=cache)
        with SimScene(params) as scene:
            T = obj.T_D_O(yaw_rad=0.3)
            body = scene.add_object(write_object_urdf(obj), T)
            mass = pybullet.getDynamicsInfo(body.id, -1, physicsClientId=scene.client)[0]
            assert mass == pytest.approx(obj.mass)
            for _ in range(240):
                scene.step()
            pose = body.pose()
            turned = math.degrees(math.acos(np.clip((np.trace(pose[:3, :3].T @ T[:3, :3]) - 1) / 2, -1.0, 1.0)))
            assert np.linalg.norm(pose[:3, 3] - T[:3, 3]) < 2e-3 and turned < 0.5, object_id


def _roll(obj, rolling_friction: float, seconds: float) -> tuple[float, float | None]:
    """Roll a lying object across its axis at the push speed; (distance, time it came to rest or None)."""
    params = dataclasses.replace(PhysicsParams(), object_rolling_friction=rolling_friction)
    with SimScene(params) as scene:
        T = obj.T_D_O()
        body = scene.add_object(write_object_urdf(obj), T)
        axis = T[:3, :3] @ np.array([1.0, 0.0, 0.0])
        across = np.cross([0.0, 0.0, 1.0], axis)
        across /= np.linalg.norm(across)
        pybullet.resetBaseVelocity(body.id, (params.push_speed_mps * across).tolist(), [0, 0, 0], physicsClientId=scene.client)
        still = 0
        for step in range(1, int(seconds / params.time_step_s) + 1):
            scene.step()
            velocity, spin = pybullet.getBaseVelocity(body.id, physicsClientId=scene.client)
            still = still + 1 if np.linalg.norm(velocity) < 2e-3 and np.linalg.norm(spin) < 5e-2 else 0
            if still == 24:
                return float(np.linalg.norm(body.pose()[:2, 3] - T[:2, 3])), step * params.time_step_s
        return float(np.linalg.norm(body.pose()[:2, 3] - T[:2, 3])), None


def test_a_lying_can_rolls_and_comes_to_rest_with_rolling_resistance(cache):
    obj = load_object("proc-lying-000", cache_dir=cache)  # a can
    assert obj.default_pose.native and procedural_spec(obj.id).params["kind"] == 0
    distance, rest = _roll(obj, 0.0, 1.0)
    assert distance > 0.05 and rest is None  # nominal physics (no rolling resistance): it rolls on (~7 cm in 1 s)
    distance, rest = _roll(obj, 0.002, 3.0)  # the execution worlds' largest rolling friction
    assert rest is not None and rest < 2.0 and distance < 0.05


# ----------------------------------------------------------------------------- splits
def test_the_unseen_family_is_all_test_and_the_others_split_as_before():
    assert UNSEEN_FAMILIES == ("mug",) and set(UNSEEN_FAMILIES) <= set(EVERYDAY_FAMILIES)
    splits = {name: set(list_object_ids(name)) for name in ("train", "val", "test")}
    for family in EVERYDAY_FAMILIES:
        ids = _ids(family)
        assert set(ids) <= set(list_object_ids())
        if family in UNSEEN_FAMILIES:
            assert set(ids) <= splits["test"]
            with pytest.raises(SplitError, match="never used for training"):
                assert_split(ids[50], "train")
            continue
        assert set(ids[:HELD_OUT_PER_FAMILY]) <= splits["test"]
        counts = {name: len(set(ids[HELD_OUT_PER_FAMILY:]) & splits[name]) for name in splits}
        assert counts["train"] > 0.7 * PER_FAMILY and counts["val"] > 0 and counts["test"] > 0, (family, counts)
    assert FAMILIES == PRIMITIVE_FAMILIES + EVERYDAY_FAMILIES  # appended: ids and listings keep their order
    assert all(library_generation(i) == (i.split("-")[1] in EVERYDAY_FAMILIES if i.startswith("proc-") else False)
               for i in list_object_ids())


def test_unknown_family_or_index_is_rejected_naming_the_families():
    for bad in ("proc-spoon-001", "proc-mug-100", "proc-Mug-001", "proc-bottle-7"):
        with pytest.raises(UnknownObjectError) as error:
            load_object(bad)
        message = str(error.value)
        assert bad in message and "family one of" in message and "mug" in message and "spatula" in message


# ----------------------------------------------------------------------------- the library before them
def test_existing_objects_keep_their_ids_splits_meshes_and_selections(cache):
    from evaluation.data_size import object_subset
    from shared.data_engine import select_objects

    before = [i for i in list_object_ids() if library_generation(i) == 0]
    assert list_object_ids()[:len(before)] == before  # the new ids come after all of them
    assert (len(before), _library_digest(before)) == EXISTING_LIBRARY
    for object_id, mesh_hash in EXISTING_MESH_HASHES.items():
        assert load_object(object_id, cache_dir=cache).mesh_hash == mesh_hash, object_id
        assert split_of(object_id) == EXISTING_SPLITS[object_id]
    selections = {"train230": select_objects("train", 230), "subset40": object_subset(40)}
    assert {k: hashlib.sha256(json.dumps(v).encode()).hexdigest()[:16] for k, v in selections.items()} == EXISTING_SELECTIONS
    assert '"procedural": 1' in source_fingerprint(resolve_library_id("proc-box-013")).decode()
    assert '"everyday": 1' in source_fingerprint(resolve_library_id("proc-bottle-013")).decode()
    assert any(library_generation(i) for i in select_objects("train"))  # a whole-split build has the new families
