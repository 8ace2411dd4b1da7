"""Perception: table removal, the object's cluster, the watertight reconstruction, its ObjectModel and
BPS, and point-cloud files (.ply / .pcd / .npy), on simulated captures of library objects."""
from __future__ import annotations

import math
import types

import numpy as np
import pytest
import trimesh

from shared.frames import direction_frame, make_transform
from shared.world.bps import BasisPointSet
from shared.world.objects import load_object
from shared.world.perception import (
    Cloud,
    CloudFileError,
    PerceptionError,
    Region,
    bps_from_cloud,
    load_cloud,
    object_from_cloud,
    reconstruct,
    save_cloud,
)
from shared.world.perception.decompose import OVERLAP_M, convex_pieces
from shared.world.perception.reconstruct import ReconstructionSettings, remove_table
from shared.world.sim.camera import capture_object

POSITION = (0.55, 0.0)
SIZE = (424, 240)  # half the capture default (848 x 480), a quarter of its render time; dense enough for a box


def _placed(object_id: str, xy=POSITION, yaw: float = 0.3):
    obj = load_object(object_id)
    return obj, make_transform(np.eye(3), np.array([xy[0], xy[1], 0.0])) @ obj.T_D_O(yaw_rad=yaw)


@pytest.fixture(scope="module")
def box():
    """proc-box-001 (19.2 x 11.0 x 8.1 cm) captured by 3 noisy cameras, its true mesh in the world."""
    obj, T_world_O = _placed("proc-box-001")
    capture = capture_object(obj, T_world_O, n_cameras=3, seed=0, size=SIZE)
    truth = obj.mesh.copy()
    truth.apply_transform(T_world_O)
    return obj, T_world_O, capture, truth


@pytest.fixture(scope="module")
def box_reconstruction(box):
    return reconstruct(box[2].cloud)


def _footprint(mesh: trimesh.Trimesh) -> np.ndarray:
    """Sides (a >= b) of the smallest rectangle around the mesh seen from above."""
    _, extents = trimesh.bounds.oriented_bounds_2D(mesh.convex_hull.vertices[:, :2])
    return np.sort(extents)[::-1]


# ----------------------------------------------------------------------------- reconstruction
def test_captured_box_reconstructs_to_a_watertight_mesh_of_its_size(box, box_reconstruction):
    """Volume within 20 %, footprint sides within 1.6 cm and height within 8 mm of the true box.

    Measured over seeds 0-2: volume +9 to +10 %, sides +1.2 / +0.9 cm, height +4 to +5 mm. The growth
    is the head camera's depth noise (3.6 mm at 1 m, along its rays) on the walls and top (+4 % of
    it is the 3 mm columns' half-cell rounding, present with ideal depth too)."""
    _, _, _, truth = box
    mesh = box_reconstruction.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert abs(mesh.volume / truth.volume - 1.0) < 0.20
    assert np.all(np.abs(_footprint(mesh) - _footprint(truth)) < 0.016)
    assert abs(mesh.bounds[1, 2] - truth.bounds[1, 2]) < 0.008
    assert abs(mesh.bounds[0, 2]) < 1e-3  # closed down to the table
    assert np.linalg.norm(box_reconstruction.center_of_mass[:2] - truth.center_mass[:2]) < 0.01


def test_table_plane_is_removed(box, box_reconstruction):
    """Every point kept as the object lies on the box (within 1 cm), and most of the cloud was table."""
    _, _, capture, truth = box
    kept = box_reconstruction.object_points
    distance = np.abs(trimesh.proximity.signed_distance(truth, kept[:: max(1, len(kept) // 2000)]))
    assert np.quantile(distance, 0.99) < 0.01
    assert kept[:, 2].min() > 0.003
    assert box_reconstruction.table_points > 0.8 * len(capture.cloud)


def test_object_cluster_is_kept_beside_a_distractor(box):
    """A small cluster elsewhere (a stray blob) is ignored and reported; a comparable second object
    needs a region, and with one the object in the region is taken."""
    _, _, capture, truth = box
    rng = np.random.default_rng(1)
    blob = np.array([0.85, 0.25, 0.03]) + rng.normal(0.0, 0.008, (300, 3))
    recon = reconstruct(np.concatenate([capture.cloud, blob]))
    assert np.all(np.abs(recon.mesh.bounds[:, :2] - truth.bounds[:, :2]) < 0.02)
    assert any(np.linalg.norm(c[:2] - blob[:, :2].mean(axis=0)) < 0.02 for c in recon.other_clusters)

    twin = capture.cloud[capture.cloud[:, 2] > 0.01] + np.array([0.0, 0.5, 0.0])
    scene = np.concatenate([capture.cloud, twin])
    with pytest.raises(PerceptionError, match="two separate objects"):
        reconstruct(scene)
    chosen = reconstruct(scene, region=Region((0.55, 0.5), 0.15))
    assert abs(chosen.mesh.centroid[1] - (truth.centroid[1] + 0.5)) < 0.02


def test_a_patch_of_table_a_miscalibrated_camera_sees_high_is_not_a_second_object(box):
    """A camera off its calibration by tenths of a degree sees far table a few mm above z = 0: a wide, dense,
    flat sheet above the cut. It is table, not an object to choose between; a box of its width is not."""
    _, _, capture, truth = box
    rng = np.random.default_rng(2)
    sheet = np.column_stack([rng.uniform(0.70, 1.10, 6000), rng.uniform(-0.35, -0.05, 6000),
                             rng.normal(0.009, 0.001, 6000)])  # 40 x 30 cm, 9 mm up
    recon = reconstruct(np.concatenate([capture.cloud, sheet]))
    assert np.all(np.abs(recon.mesh.bounds[:, :2] - truth.bounds[:, :2]) < 0.02)
    block = sheet + np.array([0.0, 0.0, 0.04])  # the same footprint standing 5 cm high: an object
    with pytest.raises(PerceptionError, match="two separate objects"):
        reconstruct(np.concatenate([capture.cloud, block, block - np.array([0.0, 0.0, 0.04])]))


def test_one_object_seen_sparsely_stays_one_cluster():
    """pb-mug where the evaluation puts it, seen by the head camera alone at 424 x 240 (~1 m away): rim,
    handle and interior are 4-5 mm apart on average and the rim's sides are lost to edge dropouts. The gap
    follows the cloud's spacing (6 x 4.6 mm = 2.8 cm) and the mug stays one object; the former fixed 2 cm
    gap split it in two (149 and 129 points)."""
    obj, T_world_O = _placed("pb-mug", (0.40, 0.0), yaw=0.0)
    cloud = capture_object(obj, T_world_O, n_cameras=1, seed=5, size=(424, 240)).cloud
    recon = reconstruct(cloud)
    assert recon.cluster_gap_m > 0.025 and recon.point_spacing_m > 0.004
    truth = obj.mesh.copy()
    truth.apply_transform(T_world_O)
    assert np.all(np.abs(recon.mesh.bounds[:, :2] - truth.bounds[:, :2]) < 0.02)  # the whole mug, handle included
    with pytest.raises(PerceptionError, match="two separate objects"):
        reconstruct(cloud, settings=ReconstructionSettings(max_cluster_gap_m=0.02))


@pytest.mark.parametrize("axis", [0, 1])
def test_two_objects_5cm_apart_stay_two_however_sparse(axis):
    """Two 6 cm cubes 5 cm apart (along the view and across it), seen as sparsely as above (320 x 180: the
    gap is at its 2.8 cm bound): still two objects, refused without a region, each found with one."""
    offset = np.zeros(3)
    offset[axis] = 0.055
    cubes = [trimesh.creation.box((0.06, 0.06, 0.06)) for _ in range(2)]
    cubes[0].apply_translation(np.array([0.0, 0.0, 0.03]) - offset)
    cubes[1].apply_translation(np.array([0.0, 0.0, 0.03]) + offset)
    scene = types.SimpleNamespace(mesh=trimesh.util.concatenate(cubes))
    T_world_O = make_transform(np.eye(3), np.array([0.40, 0.0, 0.0]))
    cloud = capture_object(scene, T_world_O, n_cameras=1, seed=5, size=(320, 180)).cloud
    settings = ReconstructionSettings(min_object_points=100)  # ~130 points per cube at this resolution
    with pytest.raises(PerceptionError, match="two separate objects"):
        reconstruct(cloud, settings=settings)
    for sign in (-1.0, 1.0):
        center = np.array([0.40, 0.0]) + sign * offset[:2]
        recon = reconstruct(cloud, region=Region((float(center[0]), float(center[1])), 0.03), settings=settings)
        assert recon.cluster_gap_m == pytest.approx(0.028)
        assert np.linalg.norm(recon.mesh.centroid[:2] - center) < 0.015
        assert np.ptp(recon.mesh.vertices[:, axis]) < 0.08  # one cube, not both


def test_hull_method_is_also_watertight(box):
    recon = reconstruct(box[2].cloud, settings=ReconstructionSettings(method="hull"))
    assert recon.mesh.is_watertight and recon.method == "hull"


def test_depth_frames_reconstruct_like_their_cloud(box, box_reconstruction):
    recon = reconstruct(box[2].frames)  # the frames' cloud is not cropped: the rest of the table goes too
    assert recon.mesh.is_watertight
    assert abs(recon.mesh.volume / box_reconstruction.mesh.volume - 1.0) < 0.05


def test_unusable_clouds_are_refused_with_the_reason(box):
    cloud = box[2].cloud
    with pytest.raises(PerceptionError, match="empty"):
        reconstruct(np.zeros((0, 3)))
    with pytest.raises(PerceptionError, match="NaN"):
        reconstruct(np.vstack([cloud, [np.nan, 0.0, 0.0]]))
    with pytest.raises(PerceptionError, match="millimetres"):
        reconstruct(cloud * 1000.0)
    with pytest.raises(PerceptionError, match="too few"):
        reconstruct(cloud[cloud[:, 2] < 0.004])  # the table alone
    with pytest.raises(PerceptionError, match="not at 0"):
        reconstruct(cloud + np.array([0.0, 0.0, 0.012]))  # a cloud whose table is 12 mm up
    with pytest.raises(PerceptionError, match="not at 0"):
        reconstruct(cloud - np.array([0.0, 0.0, 0.012]))  # everything 12 mm below the table
    with pytest.raises(PerceptionError, match=r"within 0\.1 m"):
        reconstruct(cloud, region=Region((0.0, 0.6), 0.1))


def test_a_small_die_seen_by_the_three_cameras_is_perceived_where_it_stands():
    """A 1.7 cm die leaves ~80 points in the evaluation's 3 captures: enough to find and place it (a 200-point
    minimum refused 7 of the 9 small test objects before; bench/results/perception_small.md)."""
    from shared.world.perception import cloud_for_request

    obj = load_object("proc-small-000")
    T_world_O = direction_frame(np.array([0.40, 0.0, 0.0]), 0.0) @ obj.T_D_O(None, 0.0)
    cloud = cloud_for_request(capture_object(obj, T_world_O, n_cameras=3, seed=0).cloud)
    recon = reconstruct(cloud)
    assert len(recon.object_points) < 200 and recon.mesh.is_watertight
    assert np.linalg.norm(recon.mesh.centroid[:2] - T_world_O[:2, 3]) < 0.005
    assert np.all(np.ptp(recon.mesh.vertices, axis=0) < 0.035)  # a die, not the table


def test_sparse_noise_above_an_empty_table_is_no_object():
    """Table noise that passes the cut is sparse: refused as no object, whatever its count (it used to fail an
    assertion once it passed the point minimum)."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.3, 0.3, (20000, 2))
    table = np.column_stack([xy, rng.normal(0.0, 0.001, 20000)])
    specks = np.column_stack([rng.uniform(-0.3, 0.3, (80, 2)), rng.uniform(0.01, 0.03, 80)])  # far apart
    with pytest.raises(PerceptionError, match="no object above the table"):
        reconstruct(np.vstack([table, specks]))


def test_a_five_million_point_scan_is_thinned_before_it_travels(box):
    """A dense scan is voxel-thinned to a bounded message; what is left still reconstructs the box."""
    from shared.world.perception import cloud_for_request
    from shared.world.perception.cloud import MAX_REQUEST_POINTS

    cloud = box[2].cloud
    rng = np.random.default_rng(0)
    dense = np.repeat(cloud, 5_000_000 // len(cloud) + 1, axis=0)[:5_000_000]
    dense += rng.normal(0.0, 0.0005, dense.shape)
    sent = cloud_for_request(dense)
    assert len(sent) <= MAX_REQUEST_POINTS and sent.dtype == np.float32
    assert reconstruct(sent).mesh.is_watertight


def test_remove_table_tolerance_follows_the_noise():
    """The cut adapts: a noisier table is cut higher (within the 5 mm .. 2 cm bounds)."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.3, 0.3, (20000, 2))
    quiet = np.column_stack([xy, rng.normal(0.0, 0.001, 20000)])
    noisy = np.column_stack([xy, rng.normal(0.0, 0.004, 20000)])
    assert remove_table(quiet)[1] == pytest.approx(0.005)
    assert 0.008 < remove_table(noisy)[1] < 0.012  # the 99th percentile of |noise| below: 2.6 sigma


# ----------------------------------------------------------------------------- convex pieces
def _pieces_of(heights: np.ndarray, pitch: float = 0.003) -> tuple[list[trimesh.Trimesh], trimesh.Trimesh]:
    pieces = convex_pieces(heights, np.zeros(2), pitch)
    union = trimesh.boolean.union(pieces, engine="manifold") if len(pieces) > 1 else pieces[0]
    return pieces, union


def _columns_solid(heights: np.ndarray, pitch: float = 0.003) -> trimesh.Trimesh:
    boxes = []
    for i, j in np.argwhere(heights > 0):
        column = trimesh.creation.box((pitch, pitch, heights[i, j]))
        column.apply_translation([i * pitch, j * pitch, heights[i, j] / 2.0])
        boxes.append(column)
    return trimesh.boolean.union(boxes, engine="manifold")


def test_convex_pieces_of_a_convex_height_map_are_one_piece():
    heights = np.zeros((30, 20))
    heights[5:25, 5:15] = 0.05
    pieces, union = _pieces_of(heights)
    assert len(pieces) == 1 and union.is_watertight and union.is_convex
    assert union.volume == pytest.approx(0.06 * 0.03 * 0.05, rel=0.02)
    assert abs(union.bounds[0, 2]) < 1e-9  # stands on the table


def test_convex_pieces_keep_concavities_and_share_no_vertex():
    """An L-shaped block and a cup (a ring on a floor): the pieces cover the solid, keep the L's inner corner
    (2 pieces, 1 % over its volume) and the cup's opening (16 pieces; the ring's arcs add 13 %); each piece is
    a closed convex solid; no two share a vertex, so the object library reads them as separate convex
    bodies (its collision decomposition)."""
    ell = np.zeros((34, 34))
    ell[2:32, 2:12] = 0.04
    ell[2:12, 2:32] = 0.04
    x, y = np.meshgrid(np.arange(34), np.arange(34), indexing="ij")
    radius = np.hypot(x - 16.5, y - 16.5)
    cup = np.where(radius < 14, np.where(radius > 10, 0.08, 0.01), 0.0)
    for heights, excess in ((ell, 0.02), (cup, 0.15)):
        pieces, union = _pieces_of(heights)
        truth = _columns_solid(heights)
        assert 2 <= len(pieces) <= 16
        assert all(p.is_watertight and p.is_convex and p.volume > 0 for p in pieces)
        assert union.intersection(truth, engine="manifold").volume > 0.999 * truth.volume  # covers it
        assert union.volume < (1.0 + excess) * truth.volume
        merged = trimesh.util.concatenate(pieces)
        merged.merge_vertices()
        assert len(merged.split(only_watertight=False)) == len(pieces)
    assert not union.contains([[16.5 * 0.003, 16.5 * 0.003, 0.05]])[0]  # the cup is open: its inside is not filled
    assert OVERLAP_M < 0.001


# ----------------------------------------------------------------------------- object model and BPS
def test_cloud_becomes_an_object_model_where_the_object_stands(box, tmp_path):
    obj, T_world_O, capture, _ = box
    captured = object_from_cloud(capture.cloud, cache_dir=tmp_path)
    assert captured.model.watertight and not captured.from_cache
    assert captured.model.id.startswith("mesh-")
    parts = captured.model.convex_parts  # the reconstruction's pieces are the collision shape: no V-HACD
    assert parts is not None and len(parts) == captured.meta["convex_parts"]
    assert np.linalg.norm(captured.T_world_O[:3, 3] - T_world_O[:3, 3]) < 0.01
    assert captured.T_world_O[2, 2] > math.cos(math.radians(3))  # upright, as captured
    assert captured.model.default_pose.native
    assert abs(captured.model.mass / obj.mass - 1.0) < 0.2
    again = object_from_cloud(capture.cloud, cache_dir=tmp_path)  # the same cloud: the cached reconstruction
    assert again.from_cache and again.model.mesh_hash == captured.model.mesh_hash
    np.testing.assert_allclose(again.T_world_O, captured.T_world_O)


def test_bps_from_cloud_is_close_to_the_mesh_bps(box, box_reconstruction):
    """Same frame D, basis and scale as the mesh BPS (2048 surface samples): from a 3-camera capture the
    features differ by 4.3 mm on average (median 2.4 mm; the basis points' distances average 14 cm), the
    difference being what the cameras did not see (the underside)."""
    obj, T_world_O, _, _ = box
    bps = BasisPointSet()
    T_world_D = direction_frame(box_reconstruction.center_of_mass, 30.0)
    from_cloud = bps_from_cloud(box_reconstruction.object_points, T_world_D, bps)
    surface, _ = obj.surface_points(2048, seed=0, T_D_O=np.linalg.inv(direction_frame(T_world_O[:3, 3], 30.0)) @ T_world_O)
    from_mesh = bps.encode(surface)
    difference = np.abs(from_cloud - from_mesh)
    assert from_cloud.shape == (bps.n,) and from_cloud.dtype == np.float32
    assert difference.mean() < 0.007 and np.median(difference) < 0.004
    unrelated = bps.encode(load_object("proc-cylinder-000").surface_points(2048, seed=0, T_D_O=load_object("proc-cylinder-000").T_D_O())[0])
    assert np.abs(unrelated - from_mesh).mean() > 3 * difference.mean()


# ----------------------------------------------------------------------------- files
@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".npy"])
def test_cloud_files_round_trip(tmp_path, suffix):
    points = np.random.default_rng(0).uniform(-0.2, 0.2, (500, 3))
    path = save_cloud(tmp_path / f"cloud{suffix}", points)
    loaded = load_cloud(path)
    tolerance = 1e-6 if suffix == ".pcd" else 0.0  # PCD stores float32
    np.testing.assert_allclose(loaded.points, points, atol=tolerance)


def test_cloud_file_keeps_colours(tmp_path):
    points = np.random.default_rng(0).uniform(-0.2, 0.2, (50, 3))
    colors = np.random.default_rng(1).integers(0, 256, (50, 3)).astype(np.uint8)
    for suffix in (".ply", ".pcd"):
        loaded = load_cloud(save_cloud(tmp_path / f"c{suffix}", Cloud(points, colors=colors)))
        np.testing.assert_array_equal(loaded.colors, colors)


def test_malformed_cloud_files_are_rejected_clearly(tmp_path):
    text = tmp_path / "notes.ply"
    text.write_text("this is not a point cloud\n")
    with pytest.raises(CloudFileError, match=r"notes\.ply: cannot parse as PLY"):
        load_cloud(text)
    mesh = tmp_path / "mesh.ply"
    trimesh.creation.box((0.1, 0.1, 0.1)).export(str(mesh))
    with pytest.raises(CloudFileError, match="holds a triangle mesh"):
        load_cloud(mesh)
    bad_pcd = tmp_path / "bad.pcd"
    bad_pcd.write_text("VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n")
    with pytest.raises(CloudFileError, match=r"bad\.pcd"):
        load_cloud(bad_pcd)
    wrong_shape = tmp_path / "flat.npy"
    np.save(wrong_shape, np.zeros((10, 2)))
    with pytest.raises(CloudFileError, match=r"\[N, 3\]"):
        load_cloud(wrong_shape)
    pickled = tmp_path / "objects.npy"
    np.save(pickled, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(CloudFileError, match="pickled objects are refused"):
        load_cloud(pickled)
    nan = tmp_path / "nan.npy"
    np.save(nan, np.array([[0.0, 0.0, np.nan], [0.1, 0.1, 0.1]]))
    with pytest.raises(CloudFileError, match="NaN"):
        load_cloud(nan)
    empty = tmp_path / "empty.pcd"
    empty.write_bytes(b"")
    with pytest.raises(CloudFileError, match="empty"):
        load_cloud(empty)
    with pytest.raises(CloudFileError, match="no such file"):
        load_cloud(tmp_path / "missing.ply")
    with pytest.raises(CloudFileError, match=r"unsupported point-cloud type '\.xyz'"):
        load_cloud(tmp_path / "cloud.xyz")
    millimetres = tmp_path / "mm.npy"
    np.save(millimetres, np.random.default_rng(0).uniform(0, 600, (100, 3)))
    with pytest.raises(CloudFileError, match="millimetres"):
        load_cloud(millimetres)
