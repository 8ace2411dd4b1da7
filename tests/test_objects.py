"""Object library: ids, splits, geometry, SDF, user meshes (incl. open scans), errors, cache, physics."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pybullet
import pytest
import torch
import trimesh

from shared.contracts.messages import MeshBlob, ObjectRef
from shared.world.bps import BasisPointSet
from shared.world.object_refs import load_object_ref, uploaded_mesh_path
from shared.world.objects import (
    FAMILIES,
    HELD_OUT_PER_FAMILY,
    PER_FAMILY,
    PRIMITIVE_FAMILIES,
    PYBULLET_OBJECTS,
    ObjectLoadError,
    SplitError,
    UnknownObjectError,
    assert_split,
    list_object_ids,
    load_in_pybullet,
    load_object,
    split_of,
    write_object_urdf,
)
from shared.world.objects.cache import cache_root
from shared.world.objects.model import load_library_object
from shared.world.objects.procedural import procedural_spec

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("gd2p-cache")


def box_sdf(points: np.ndarray, extents) -> np.ndarray:
    q = np.abs(points) - np.asarray(extents) / 2
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def open_box_mesh(extents=(0.10, 0.08, 0.06), edge=0.0028) -> trimesh.Trimesh:
    """A box without its top face, subdivided like a scan (10k+ vertices): not watertight."""
    box = trimesh.creation.box(extents=extents).subdivide_to_size(edge)
    keep = box.triangles_center[:, 2] < extents[2] / 2 - 1e-9
    mesh = trimesh.Trimesh(box.vertices, box.faces[keep], process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


# ----------------------------------------------------------------------------- ids and splits
def test_library_ids_are_stable_and_complete():
    ids = list_object_ids()
    assert len(ids) == len(set(ids)) == 999 + len(PYBULLET_OBJECTS) + len(FAMILIES) * PER_FAMILY
    assert "rnd-000" in ids and "rnd-999" in ids and "rnd-168" not in ids  # 168's OBJ is all NaN
    assert {"pb-duck", "pb-mug", "pb-teddy", "pb-jenga"} <= set(ids)
    assert "proc-box-000" in ids and f"proc-hull-{PER_FAMILY - 1:03d}" in ids


def test_split_is_deterministic_disjoint_and_holds_out_the_evaluation_objects():
    splits = {name: set(list_object_ids(name)) for name in ("train", "val", "test")}
    assert splits["train"].isdisjoint(splits["val"]) and splits["train"].isdisjoint(splits["test"]) and splits["val"].isdisjoint(splits["test"])
    assert set().union(*splits.values()) == set(list_object_ids())
    assert splits == {name: set(list_object_ids(name)) for name in ("train", "val", "test")}
    assert all(f"pb-{name}" in splits["test"] for name in PYBULLET_OBJECTS)
    assert all(f"proc-{family}-{i:03d}" in splits["test"] for family in FAMILIES for i in range(HELD_OUT_PER_FAMILY))
    random_ids = [i for i in list_object_ids() if i.startswith("rnd-")]
    train_fraction = np.mean([split_of(i) == "train" for i in random_ids])
    assert 0.75 < train_fraction < 0.85
    assert_split("pb-duck", "test")
    with pytest.raises(SplitError, match="never used for training"):
        assert_split("pb-duck", "train")
    with pytest.raises(ValueError, match="unknown split"):
        list_object_ids("holdout")


def test_procedural_dimensions_are_pushable_and_classes_match_the_geometry(cache):
    """The primitive families (the everyday ones: tests/test_families.py)."""
    for object_id in list_object_ids():
        if object_id.startswith("proc-") and procedural_spec(object_id).family in PRIMITIVE_FAMILIES:
            a, b, height = procedural_spec(object_id).dims
            assert 0.04 <= a <= 0.25 and 0.015 <= b <= a and 0.015 <= height <= 0.25, object_id
    for family in PRIMITIVE_FAMILIES:
        for index in range(3):
            obj = load_object(f"proc-{family}-{index:03d}", cache_dir=cache)
            assert obj.info.shape_class == procedural_spec(obj.id).shape_class, obj
            assert obj.default_pose.native, obj  # designed upright and stable
            assert obj.convex_parts is not None and len(obj.convex_parts) == 1  # convex: its own decomposition


def test_same_id_gives_the_same_mesh_across_runs(cache, tmp_path):
    ids = ["proc-hull-005", "rnd-003", "pb-duck"]
    here = {i: load_object(i, cache_dir=cache).mesh_hash for i in ids}
    assert here == {i: load_object(i, cache_dir=tmp_path / "fresh").mesh_hash for i in ids}
    script = f"from shared.world.objects import load_object\nfor i in {ids!r}: print(load_object(i, cache_dir={str(tmp_path / 'other')!r}).mesh_hash)"
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == [here[i] for i in ids]


# ----------------------------------------------------------------------------- geometry
def test_box_rests_on_the_table_with_its_centre_over_d(cache):
    obj = load_object("proc-box-001", cache_dir=cache)
    a, b, height = procedural_spec(obj.id).dims
    assert obj.watertight and not obj.mass_from_voxels
    assert obj.default_pose.height == pytest.approx(height / 2, abs=1e-9)
    for index in range(len(obj.resting_poses)):
        mesh = obj.mesh_in_d(index, yaw_rad=0.7)
        assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)  # lowest point on the table
        np.testing.assert_allclose(mesh.center_mass[:2], 0.0, atol=1e-9)  # centroid over D's origin
    probabilities = [pose.probability for pose in obj.resting_poses]
    assert probabilities == sorted(probabilities, reverse=True)
    np.testing.assert_allclose(sorted(obj.mesh_in_d().extents), sorted((a, b, height)), atol=1e-9)


def test_mass_and_inertia_follow_density_and_are_clamped(cache):
    obj = load_object("proc-box-001", cache_dir=cache)
    a, b, c = procedural_spec(obj.id).dims
    mass = float(np.clip(500.0 * a * b * c, 0.05, 1.5))
    assert obj.mass == pytest.approx(mass)
    expected = mass / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(np.sort(np.diag(obj.inertia)), np.sort(expected), rtol=1e-9)
    assert np.abs(obj.inertia - np.diag(np.diag(obj.inertia))).max() < 1e-12  # O is a principal frame
    assert load_object("proc-box-001", density=1e-3, cache_dir=cache).mass == 0.05
    assert load_object("proc-box-001", density=1e6, cache_dir=cache).mass == 1.5


def test_box_sdf_is_exact_to_the_grid_and_points_outward(cache):
    obj = load_object("proc-box-001", cache_dir=cache)  # default 64³ grid
    extents = procedural_spec(obj.id).dims
    grid = obj.sdf
    assert grid.resolution == (64, 64, 64)
    points = np.random.default_rng(0).uniform(grid.lower, grid.upper, (20000, 3))
    exact = box_sdf(points, extents)
    distance, gradient = grid.query_numpy(points)
    assert np.abs(distance - exact).max() < 2e-3
    clear = np.abs(exact) > 2e-3
    assert np.all(np.sign(distance[clear]) == np.sign(exact[clear]))
    # 4 mm outside each face (off its centre) the distance is 4 mm and the gradient is the face normal
    for axis in range(3):
        for sign in (-1.0, 1.0):
            probe = 0.3 * np.asarray(extents) / 2 * np.array([1.0, -1.0, 1.0])
            probe[axis] = sign * (extents[axis] / 2 + 0.004)
            d, g = grid.query_numpy(probe[None])
            assert d[0] == pytest.approx(0.004, abs=5e-4)
            assert g[0][axis] * sign > 0.99
    # beyond the grid the distance stays conservative (never above the truth beyond interpolation error)
    far = np.random.default_rng(1).uniform(-0.4, 0.4, (2000, 3))
    assert np.all(grid.query_numpy(far)[0] <= box_sdf(far, extents) + 1.5e-3)


def test_signed_distance_in_d_is_differentiable_and_batched(cache):
    obj = load_object("proc-box-001", cache_dir=cache)
    T = obj.T_D_O(yaw_rad=0.4)
    height = obj.default_pose.height
    points = torch.tensor([[0.0, 0.0, height], [0.0, 0.0, 2 * height + 0.02]], dtype=torch.float64, requires_grad=True)
    distance, gradient = obj.signed_distance(points, T)
    assert distance[0] < 0 < distance[1]
    np.testing.assert_allclose(gradient[1].detach().numpy(), [0, 0, 1], atol=1e-3)  # above the top: up, in D
    distance.sum().backward()
    np.testing.assert_allclose(points.grad.numpy(), gradient.detach().numpy())
    batched, _ = obj.signed_distance(torch.stack([points.detach(), points.detach()]), np.stack([T, obj.T_D_O(yaw_rad=1.0)]))
    assert batched.shape == (2, 2)
    np.testing.assert_allclose(batched[0].numpy(), distance.detach().numpy(), atol=1e-6)


def test_surface_samples_are_seeded_on_the_surface_and_fit_the_bps_ball(cache):
    obj = load_object("proc-cylinder-002", cache_dir=cache)  # a tall one
    points, normals = obj.surface_points(2048, seed=3)
    again, _ = obj.surface_points(2048, seed=3)
    np.testing.assert_array_equal(points, again)
    assert not np.array_equal(points, obj.surface_points(2048, seed=4)[0])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    assert np.abs(obj.sdf.query_numpy(points)[0]).max() < 2e-3
    in_d, _ = obj.surface_points(2048, seed=3, T_D_O=obj.T_D_O(yaw_rad=1.1))
    assert in_d[:, 2].min() >= -1e-9
    assert BasisPointSet().encode(in_d).shape == (4096,)


# ----------------------------------------------------------------------------- user meshes
def test_open_scan_like_mesh_loads_with_a_sensible_inside(cache, tmp_path):
    mesh = open_box_mesh()
    assert len(mesh.vertices) >= 10_000 and not mesh.is_watertight
    path = tmp_path / "scan.ply"
    mesh.export(path)
    obj = load_object(path, sdf_resolution=32, cache_dir=cache)
    assert obj.id.startswith("mesh-") and len(obj.id) == len("mesh-") + 12
    assert not obj.watertight and obj.mass_from_voxels
    assert obj.volume == pytest.approx(0.10 * 0.08 * 0.06, rel=0.15)
    assert obj.default_pose.native  # standing on its bottom, open side up
    probes = torch.tensor(
        [[0, 0, 0.03], [0, 0, 0.05], [0, 0, 0.09], [0.08, 0, 0.03], [0, 0, -0.02]], dtype=torch.float64
    )  # centre, just under the open top, above it, beside, under the table
    distance, _ = obj.signed_distance(probes, obj.T_D_O())
    assert distance[0] < 0 and distance[1] < 0
    assert distance[2] > 0 and distance[3] > 0 and distance[4] > 0
    assert distance[0].item() == pytest.approx(-0.03, abs=0.004)


def test_glb_is_read_y_up(cache, tmp_path):
    path = tmp_path / "tall.glb"
    trimesh.creation.box(extents=(0.05, 0.20, 0.04)).export(path)  # glTF: +Y is up
    obj = load_object(path, sdf_resolution=16, cache_dir=cache)
    assert obj.info.size_m[2] == pytest.approx(0.20, abs=1e-6)
    assert obj.info.shape_class == "tall"


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("broken.stl", b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 1 2\nendsolid", "broken.stl"),
        ("noise.ply", bytes(range(256)) * 8, "noise.ply"),
        ("model.fbx", b"Kaydara FBX Binary", "unsupported mesh type '.fbx'"),
        ("points.obj", b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\n", "no triangles"),
        ("zero.obj", b"", "empty"),
        ("sheet.obj", b"v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n", "encloses no volume"),
    ],
)
def test_unusable_files_raise_an_error_naming_file_and_problem(cache, tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ObjectLoadError) as error:
        load_object(path, cache_dir=cache)
    assert message in str(error.value) and name in str(error.value)


def test_wrong_units_missing_files_and_unknown_ids(cache, tmp_path):
    millimetres = tmp_path / "mm.stl"
    trimesh.creation.box(extents=(100.0, 60.0, 40.0)).export(millimetres)
    with pytest.raises(ObjectLoadError, match="millimetres"):
        load_object(millimetres, cache_dir=cache)
    with pytest.raises(ObjectLoadError, match="no such file"):
        load_object(tmp_path / "missing.obj", cache_dir=cache)
    for bad in ("banana", "proc-box-999", "proc-sphere-001", "rnd-1000", "mesh-0123456789ab"):
        with pytest.raises(UnknownObjectError):
            load_object(bad, cache_dir=cache)
    with pytest.raises(ObjectLoadError, match="NaN"):
        load_object("rnd-168", cache_dir=cache)


def test_sdf_cache_is_hit_on_second_load(cache, tmp_path, monkeypatch):
    path = tmp_path / "pebble.obj"
    trimesh.creation.icosphere(subdivisions=2, radius=0.04).export(path)
    first = load_object(path, sdf_resolution=20, cache_dir=cache)
    values = first.sdf.values.copy()
    assert first.provenance == {"geometry": "computed", "sdf": "computed"}

    def no_recompute(*args, **kwargs):
        raise AssertionError("SDF recomputed despite the cache")

    monkeypatch.setattr("shared.world.objects.model.compute_sdf_grid", no_recompute)
    second = load_object(path, sdf_resolution=20, cache_dir=cache)
    np.testing.assert_array_equal(second.sdf.values, values)
    assert second.provenance == {"geometry": "cache", "sdf": "cache"}
    assert load_object(first.id, sdf_resolution=20, cache_dir=cache).mesh_hash == first.mesh_hash  # by content id


# ----------------------------------------------------------------------------- objects named by the bus
def _pebble(path: Path) -> Path:
    trimesh.creation.icosphere(subdivisions=2, radius=0.04).export(path)
    return path


def test_a_library_id_is_never_read_as_a_path(cache, tmp_path, monkeypatch):
    monkeypatch.setenv("GD2P_CACHE_DIR", str(cache))
    pebble = _pebble(tmp_path / "x.obj")
    monkeypatch.chdir(tmp_path)  # relative names resolve here: "x.obj" names a loadable mesh
    mesh_id = load_object(pebble, cache_dir=cache).id  # local callers may still load a file by path
    for bad in ("../../etc/passwd", "/tmp/x.obj", str(pebble), "x.obj", "proc-box-000/../x", "proc-box-000/../x.obj"):
        with pytest.raises(UnknownObjectError):
            load_library_object(bad, cache_dir=cache)
        with pytest.raises(UnknownObjectError):  # what services load (the message's own check is bypassed here)
            load_object_ref(ObjectRef.model_construct(library_id=bad))
    assert load_library_object("proc-box-001", cache_dir=cache).id == "proc-box-001"
    assert load_object_ref(ObjectRef(library_id=mesh_id)).id == mesh_id  # a mesh loaded before, by its id


def test_a_rejected_upload_leaves_nothing_in_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GD2P_CACHE_DIR", str(tmp_path / "cache"))
    sheet = MeshBlob.from_bytes(b"v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n", "obj")
    with pytest.raises(ObjectLoadError, match="encloses no volume"):
        load_object_ref(ObjectRef(mesh=sheet))
    with pytest.raises(ObjectLoadError, match="encloses no volume"):
        uploaded_mesh_path(sheet)  # what the sampler caches
    assert [p for p in (tmp_path / "cache").rglob("*") if p.is_file()] == []
    stale = cache_root() / "uploads" / f"{sheet.sha256}.obj"  # cached before uploads were checked
    stale.parent.mkdir(parents=True, exist_ok=True)
    stale.write_bytes(sheet.data)
    with pytest.raises(ObjectLoadError):
        load_object_ref(ObjectRef(mesh=sheet))
    assert not stale.exists()
    good = MeshBlob.from_file(str(_pebble(tmp_path / "pebble.obj")))
    obj = load_object_ref(ObjectRef(mesh=good))
    assert obj.source_path == uploaded_mesh_path(good) and obj.source_path.read_bytes() == good.data
    assert [p.name for p in (cache_root() / "uploads").iterdir()] == [f"{good.sha256}.obj"]


# ----------------------------------------------------------------------------- physics
def test_urdf_carries_mass_inertia_and_rests_where_placed(cache):
    client = pybullet.connect(pybullet.DIRECT)
    try:
        pybullet.setGravity(0, 0, -9.81, physicsClientId=client)
        pybullet.createMultiBody(0, pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client), physicsClientId=client)
        for object_id in ("proc-box-001", "rnd-000"):
            obj = load_object(object_id, cache_dir=cache)
            T = obj.T_D_O(yaw_rad=0.3)
            body = load_in_pybullet(obj, T, client)
            mass, _, inertia = pybullet.getDynamicsInfo(body, -1, physicsClientId=client)[:3]
            assert mass == pytest.approx(obj.mass)
            np.testing.assert_allclose(inertia, np.diag(obj.inertia), rtol=1e-5)
            for _ in range(240):
                pybullet.stepSimulation(physicsClientId=client)
            position, _ = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)
            np.testing.assert_allclose(position, T[:3, 3], atol=3e-3)  # base frame = O: it stays put
        collision = (write_object_urdf(obj).parent / "collision.obj").read_text()
        assert collision.count("\no ") + collision.startswith("o ") == len(obj.convex_parts) > 1  # rnd-000's own pieces
    finally:
        pybullet.disconnect(client)


def test_vhacd_decomposition_keeps_the_mug_hollow(cache):
    obj = load_object("pb-mug", cache_dir=cache)
    assert not obj.watertight and obj.convex_parts is None
    client = pybullet.connect(pybullet.DIRECT)
    try:
        T = obj.T_D_O()
        load_in_pybullet(obj, T, client)
        rim = obj.mesh_in_d().bounds[1, 2]
        points, _ = obj.surface_points(4000, seed=0, T_D_O=T)
        # a vertical ray at the middle of the opening (centre of the top rim points) reaches the inside bottom
        top = points[points[:, 2] > rim - 0.005]
        centre = (top.min(axis=0) + top.max(axis=0)) / 2
        hit = pybullet.rayTest([centre[0], centre[1], rim + 0.1], [centre[0], centre[1], -0.1], physicsClientId=client)[0]
        assert hit[0] >= 0 and hit[3][2] < 0.5 * rim
    finally:
        pybullet.disconnect(client)


def test_cli_lists_objects_as_json(cache, monkeypatch, capsys):
    from cli.main import main

    monkeypatch.setenv("GD2P_CACHE_DIR", str(cache.parent / "cli-cache"))
    assert main(["objects", "list", "--split", "test", "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    assert listing["count"] == len(list_object_ids("test")) == len(listing["objects"])
    entries = {entry["id"]: entry for entry in listing["objects"]}
    assert entries["pb-duck"]["split"] == "test" and entries["pb-duck"]["shape_class"] == "volumetric"
    assert entries["proc-box-002"]["shape_class"] == "tall"
    assert set(entries["pb-mug"]) == {"id", "shape_class", "source", "family", "size_m", "split"}
