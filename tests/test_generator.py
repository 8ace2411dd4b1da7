"""Generator (issue 4): energy terms on constructed cases, initialisation, optimiser, synthesis, service, CLI."""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import trimesh

from shared.robots.hands import load_hand
from shared.synthesis import energy as E
from shared.synthesis.config import GenerationConfig, GenerationConfigError
from shared.synthesis.init import initial_poses, palm_center_base, sample_contacts
from shared.synthesis.optimizer import AnnealingOptimizer
from shared.synthesis.scene import PushScene
from shared.synthesis.synthesis import generate, hand_geometry

pytestmark = pytest.mark.timeout(120)

BOX_SIZE = (0.06, 0.10, 0.12)
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("gd2p-cache")


@pytest.fixture(scope="module")
def box_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("meshes") / "box.stl"
    trimesh.creation.box(extents=BOX_SIZE).export(path)
    return path


@pytest.fixture(scope="module")
def box(box_file, cache_dir):
    from shared.world.objects import load_object

    return PushScene.from_object(load_object(box_file, cache_dir=cache_dir))


@pytest.fixture(scope="module")
def hand():
    return load_hand("allegro")


@pytest.fixture(scope="module")
def geometry(hand):
    return hand_geometry(hand)


def rotation_to(palm_direction, hand) -> torch.Tensor:
    """A base rotation whose palm normal points along `palm_direction` (fingers any orthogonal way)."""
    palm = torch.tensor(palm_direction, dtype=torch.float32)
    palm = palm / palm.norm()
    helper = torch.tensor([0.0, 0.0, 1.0]) if abs(float(palm[2])) < 0.9 else torch.tensor([1.0, 0.0, 0.0])
    fingers = torch.linalg.cross(palm, helper)
    fingers = fingers / fingers.norm()
    target = torch.stack((palm, fingers, torch.linalg.cross(palm, fingers)), dim=-1)
    n_b, f_b = hand.palm_normal_base, hand.finger_direction_base
    source = torch.stack((n_b, f_b, torch.linalg.cross(n_b, f_b)), dim=-1)
    return target @ source.T


def make_pose(hand, position, palm_direction=(1.0, 0.0, 0.0), joints=None) -> torch.Tensor:
    rotation = rotation_to(palm_direction, hand)
    q = hand.open_joint_positions if joints is None else torch.as_tensor(joints, dtype=torch.float32)
    return torch.cat((torch.as_tensor(position, dtype=torch.float32), rotation[:, 0], rotation[:, 1], q)).unsqueeze(0)


def palm_at(hand, point, palm_direction=(1.0, 0.0, 0.0)) -> torch.Tensor:
    """Pose with the palm centre at `point`."""
    rotation = rotation_to(palm_direction, hand)
    return make_pose(hand, torch.as_tensor(point) - rotation @ palm_center_base(hand), palm_direction)


# ------------------------------------------------------------------------------------ energy terms


def test_hand_overlapping_the_object_raises_e_pen_and_far_away_is_zero(hand, geometry, box):
    inside = palm_at(hand, box.centroid.tolist())
    far = palm_at(hand, (box.centroid + torch.tensor([1.0, 0.0, 0.0])).tolist())
    assert float(E.object_penetration(geometry, hand.forward(inside), box)[0]) > 0.01
    assert float(E.object_penetration(geometry, hand.forward(far), box)[0]) == 0.0


def test_sparse_penetration_equals_the_dense_sum_with_the_same_gradient(hand, geometry, box):
    config = GenerationConfig()
    start = initial_poses(hand, box.hull_vertices, 24, config.init, torch.Generator().manual_seed(5))
    pose = (start + 0.02 * torch.randn(start.shape, generator=torch.Generator().manual_seed(6))).requires_grad_(True)
    margin = 0.01
    sparse = E.object_penetration(geometry, hand.forward(pose), box, margin)
    (sparse_grad,) = torch.autograd.grad(sparse.sum(), pose)
    points = box.surface_points.expand(pose.shape[0], -1, -1)
    dense = torch.relu(margin - hand.signed_distance(points, hand.forward(pose))).sum(1)
    (dense_grad,) = torch.autograd.grad(dense.sum(), pose)
    assert float(dense.detach().max()) > 0.0, "the test poses must touch the object"
    torch.testing.assert_close(sparse, dense, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(sparse_grad, dense_grad, rtol=1e-3, atol=1e-5)


def test_hand_below_the_table_raises_e_tpen(hand, geometry):
    below = geometry.sample_heights(hand.forward(make_pose(hand, (0.0, 0.0, -0.05))))
    above = geometry.sample_heights(hand.forward(make_pose(hand, (0.0, 0.0, 0.5))))
    assert float(E.table_penetration(below)[0]) > 0.1
    assert float(E.table_penetration(above)[0]) == 0.0
    assert float(E.table_penetration(above, clearance_m=1.0)[0]) > 0.0


def test_hand_inside_the_object_raises_the_hand_side_of_e_pen(hand, geometry, box):
    inside = hand.forward(palm_at(hand, box.centroid.tolist()))
    far = hand.forward(palm_at(hand, (box.centroid + torch.tensor([1.0, 0, 0])).tolist()))
    assert float(E.hand_in_object(geometry, inside, box)[0]) > 0.01
    assert float(E.hand_in_object(geometry, far, box)[0]) == 0.0


def test_sparse_hand_side_penetration_equals_the_dense_sum(hand, geometry, box):
    start = initial_poses(hand, box.hull_vertices, 24, GenerationConfig().init, torch.Generator().manual_seed(8))
    pose = (start + 0.02 * torch.randn(start.shape, generator=torch.Generator().manual_seed(9))).requires_grad_(True)
    sparse = E.hand_in_object(geometry, hand.forward(pose), box, 0.01)
    (sparse_grad,) = torch.autograd.grad(sparse.sum(), pose)
    samples = geometry.surface_points(hand.forward(pose), geometry.penetration_samples)
    dense = torch.relu(0.01 - box.distance(samples)[0]).sum(-1)
    (dense_grad,) = torch.autograd.grad(dense.sum(), pose)
    assert float(dense.detach().max()) > 0.0
    torch.testing.assert_close(sparse, dense, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(sparse_grad, dense_grad, rtol=1e-4, atol=1e-5)


def test_palm_facing_plus_x_minimises_e_dir_and_palm_up_raises_e_arm(hand):
    directions = {"+x": (1.0, 0, 0), "-x": (-1.0, 0, 0), "up": (0, 0, 1.0), "down": (0, 0, -1.0), "diag": (1.0, 1.0, 1.0)}
    palms = {name: hand.palm_normal(hand.forward(make_pose(hand, (0, 0, 0.3), d))) for name, d in directions.items()}
    e_dir = {name: float(E.palm_direction(p)[0]) for name, p in palms.items()}
    e_arm = {name: float(E.arm_feasibility(p)[0]) for name, p in palms.items()}
    assert e_dir["+x"] == pytest.approx(-1.0, abs=1e-6)
    assert min(e_dir.values()) == e_dir["+x"]
    assert e_dir["-x"] == pytest.approx(1.0, abs=1e-6)
    assert e_arm["up"] == pytest.approx(1.0, abs=1e-6)
    assert e_arm["diag"] == pytest.approx(1 / math.sqrt(3), abs=1e-6)
    assert e_arm["+x"] == pytest.approx(0.0, abs=1e-6) and e_arm["down"] == 0.0


def test_joint_limit_violation_is_its_size_in_radians(hand):
    inside = ((hand.joint_lower + hand.joint_upper) / 2).unsqueeze(0)
    beyond = inside.clone()
    beyond[0, 1] = hand.joint_upper[1] + 0.1
    beyond[0, 5] = hand.joint_lower[5] - 0.2
    assert float(E.joint_limits(inside, hand.joint_lower, hand.joint_upper)[0]) == 0.0
    assert float(E.joint_limits(beyond, hand.joint_lower, hand.joint_upper)[0]) == pytest.approx(0.3, abs=1e-5)


def test_force_closure_is_zero_for_opposed_contacts_and_large_for_one_sided_ones():
    points = torch.tensor([[[-0.03, 0.0, 0.0], [0.03, 0.0, 0.0]]])
    opposed = torch.tensor([[[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    same_side = torch.tensor([[[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]])
    center = torch.zeros(3)
    assert float(E.force_closure(points, opposed, center)[0]) == pytest.approx(0.0, abs=1e-9)
    assert float(E.force_closure(points, same_side, center)[0]) == pytest.approx(4.0)


def test_contact_distance_spread_and_finger_palm_terms():
    assert float(E.contact_distance(torch.tensor([[0.005, 0.007]]), 0.005)[0]) == pytest.approx(0.002)
    points = torch.tensor([[[0.0, 0.0, 0.0], [0.005, 0.0, 0.0], [0.1, 0.0, 0.0]]])
    assert float(E.contact_spread(points, 0.02)[0]) == pytest.approx(0.015)  # only the close pair counts
    assert float(E.finger_palm(points, torch.zeros(1, 3))[0]) == pytest.approx(-0.105)


def test_hand_geometry_distances_agree_with_the_hand_model(hand, geometry, box):
    pose = initial_poses(hand, box.hull_vertices, 8, GenerationConfig().init, torch.Generator().manual_seed(1))
    state = hand.forward(pose)
    points = box.check_points[:1500]
    exact = hand.signed_distance(points.expand(8, -1, -1), state)
    bound = geometry.signed_distance_upper_bound(state, points, 0.02, box)
    close = exact < 0.02
    assert bool(close.any())
    torch.testing.assert_close(bound[close], exact[close], rtol=0, atol=1e-6)
    assert bool((bound[~close] >= 0.02 - 1e-6).all())


def test_every_term_has_finite_gradients(hand, geometry, box):
    config = GenerationConfig()
    generator = torch.Generator().manual_seed(2)
    pose = initial_poses(hand, box.hull_vertices, 16, config.init, generator).requires_grad_(True)
    contacts = sample_contacts(len(hand.contact_candidates), 16, config.contacts_per_pose, generator)
    energy = E.evaluate_energy(hand, geometry, box, pose, contacts, config)
    assert set(energy.terms) == set(config.weights.as_dict())
    for name, value in energy.terms.items():
        (gradient,) = torch.autograd.grad(value.sum(), pose, retain_graph=True, allow_unused=True)
        assert gradient is None or bool(torch.isfinite(gradient).all()), name
    assert bool(torch.isfinite(energy.total).all())


def test_grasp_only_drops_the_push_terms():
    config = GenerationConfig(grasp_only=True)
    weights = config.effective_weights()
    assert weights["dir"] == 0.0 and weights["arm"] == 0.0 and weights["dis"] == 500.0
    with pytest.raises(GenerationConfigError):
        GenerationConfig(iterations=0)


# ------------------------------------------------------------------------------ init and optimiser


def test_initial_palms_aim_into_the_object_from_the_push_side(hand, box):
    config = GenerationConfig()
    pose = initial_poses(hand, box.hull_vertices, 64, config.init, torch.Generator().manual_seed(3))
    state = hand.forward(pose)
    palm = hand.palm_normal(state)
    centre = (state.base[:, :3, :3] @ palm_center_base(hand)) + pose[:, :3]
    to_object = box.centroid - centre
    cos = (palm * to_object).sum(-1) / to_object.norm(dim=-1)
    assert float(cos.min()) > 0.0, "every palm starts facing the object"
    assert float((box.distance(centre)[0]).min()) > 0.0, "no palm centre starts inside the object"
    assert float(palm[:, 0].min()) > -0.6, "starts are on the side a +x push comes from (within the jitter)"
    limits_ok = (pose[:, 9:] >= hand.joint_lower) & (pose[:, 9:] <= hand.joint_upper)
    assert bool(limits_ok.all())


def test_contact_sampling_is_distinct_and_avoids_excluded_indices():
    generator = torch.Generator().manual_seed(0)
    current = sample_contacts(10, 500, 4, generator)
    fresh = sample_contacts(10, 500, 4, generator, exclude=current)
    for row, old in zip(fresh.tolist(), current.tolist(), strict=True):
        assert len(set(row)) == 4 and not set(row) & set(old)
    with pytest.raises(ValueError):
        sample_contacts(6, 1, 4, generator, exclude=current[:1])


def test_annealing_schedule_and_metropolis_rule():
    from shared.synthesis.config import AnnealingSettings

    optimizer = AnnealingOptimizer(AnnealingSettings(), 100, torch.Generator().manual_seed(0))
    assert optimizer.step_size() == 0.005 and optimizer.temperature() == 18.0
    optimizer.step = 60
    assert optimizer.step_size() == pytest.approx(0.005 * 0.95)
    assert optimizer.temperature() == pytest.approx(18.0 * 0.95**2)
    energy = torch.zeros(1000)
    assert bool(optimizer.accept(energy, energy - 1.0).all()), "downhill moves are always accepted"
    uphill = optimizer.accept(energy, energy + optimizer.temperature()).float().mean()
    assert 0.3 < float(uphill) < 0.44, "uphill by T is accepted with probability 1/e"


# ------------------------------------------------------------------------------------- synthesis


def test_generation_is_deterministic_for_a_seed(box):
    config = GenerationConfig(iterations=12, batch_size=4)
    first = generate(box, "allegro", 6, 3, config)
    again = generate(box, "allegro", 6, 3, config)
    other = generate(box, "allegro", 6, 4, config)
    np.testing.assert_array_equal(first.poses, again.poses)
    np.testing.assert_array_equal(first.energies["total"], again.energies["total"])
    assert not np.allclose(first.poses, other.poses)
    assert first.poses.shape == (6, 25) and first.history["total"].shape == (12,)


def test_optimising_a_box_gives_low_energy_push_poses(box, hand):
    config = GenerationConfig(iterations=900, batch_size=32)
    out = generate(box, hand, 32, 0, config)
    total = out.history["total"]
    assert total[-1] < total[0] - 150.0, f"energy fell only from {total[0]:.1f} to {total[-1]:.1f}"
    facing = out.palm_normals[:, 0] >= 0.7
    shallow = out.max_penetration_m <= 0.005
    assert (facing & shallow).mean() >= 0.7, f"{facing.mean():.0%} face +x, {shallow.mean():.0%} penetrate <= 5 mm"
    assert np.all(out.poses[:, 9:] >= hand.joint_lower.numpy()) and np.all(out.poses[:, 9:] <= hand.joint_upper.numpy())
    rotation = np.stack((out.poses[:, 3:6], out.poses[:, 6:9]), axis=-1)
    np.testing.assert_allclose(np.einsum("bki,bkj->bij", rotation, rotation), np.broadcast_to(np.eye(2), (32, 2, 2)),
                               atol=1e-5)


# ------------------------------------------------------------------------------------ service, CLI


def _job(box_file, **changes):
    from shared.contracts.messages import GenerationJob, MeshBlob, ObjectRef

    fields = dict(object=ObjectRef(mesh=MeshBlob.from_file(str(box_file))), hand="allegro", batch_size=3, seed=7,
                  iterations=10)
    fields.update(changes)
    return GenerationJob(**fields)


def test_service_answers_a_job_deterministically(box_file, cache_dir, monkeypatch):
    from services.generator.service import handlers
    from shared.contracts.messages import GenerationJob, GenerationResult

    monkeypatch.setenv("GD2P_CACHE_DIR", str(cache_dir))
    handle = handlers()[GenerationJob]
    job = _job(box_file)
    result = handle(job)
    assert isinstance(result, GenerationResult)
    assert result.poses.shape == [3, 25] and result.job_id == job.id
    assert {"total", "dir", "pen"} <= set(result.energies) and result.energy_history["total"].shape == [10]
    np.testing.assert_array_equal(handle(_job(box_file)).poses.to_numpy(), result.poses.to_numpy())


def test_service_rejects_a_point_cloud_with_a_clear_error():
    from services.generator.service import run_job
    from shared.contracts.errors import ServiceError
    from shared.contracts.messages import GenerationJob, ObjectRef

    job = GenerationJob(object=ObjectRef(point_cloud=np.zeros((5, 3), np.float32)), hand="allegro", batch_size=2)
    with pytest.raises(ServiceError, match="point cloud"):
        run_job(job)


@pytest.mark.slow
def test_generation_job_through_the_dispatcher(zenoh_router, box_file, cache_dir, box):
    from shared.bus import BusConfig, Dispatcher, open_session
    from shared.contracts.messages import GenerationResult

    env = dict(os.environ, GD2P_CACHE_DIR=str(cache_dir), PYTHONPATH=REPO)
    worker = subprocess.Popen([sys.executable, "-m", "services.generator", "--connect", zenoh_router,
                               "--worker-id", "gen-test"], cwd=REPO, env=env)
    try:
        with open_session(BusConfig(connect=[zenoh_router], connect_timeout_ms=5000)) as session, \
                Dispatcher(session, "generator", timeout_s=60.0) as dispatcher:
            dispatcher.wait_for_workers(1, timeout=60)
            result = dispatcher.call(_job(box_file, batch_size=2), timeout=90)
        assert isinstance(result, GenerationResult) and result.poses.shape == [2, 25]
    finally:
        worker.terminate()
        worker.wait(20)


def test_cli_writes_the_documented_json_and_plot(box_file, cache_dir, tmp_path, monkeypatch):
    import cli.generate

    monkeypatch.setenv("GD2P_CACHE_DIR", str(cache_dir))
    parser = argparse.ArgumentParser()
    cli.generate.register(parser.add_subparsers())
    out, plot = tmp_path / "poses.json", tmp_path / "energy.png"
    args = parser.parse_args(["generate", "--object", str(box_file), "--hand", "allegro", "--n", "3", "--seed", "1",
                              "--out", str(out), "--iterations", "8", "--plot", str(plot)])
    assert args.func(args) == 0
    document = json.loads(out.read_text())
    assert len(document["poses"]) == 3
    entry = document["poses"][0]
    assert len(entry["pose"]) == 25 and len(entry["palm_normal"]) == 3 and entry["max_penetration_m"] >= 0.0
    assert {"fc", "dis", "pen", "spen", "joints", "ff", "fp", "tpen", "dir", "arm", "total"} == set(entry["energy"])
    assert plot.stat().st_size > 10_000


def test_initialisation_starts_behind_objects_whose_push_side_is_a_sliver(hand):
    """rnd-648's push side is a sliver of its inflated hull (1 of 8 start points by plain rejection,
    which failed its dataset build): start poses are still found, all behind the object."""
    from shared.world.objects import load_object

    scene = PushScene.from_object(load_object("rnd-648"))
    for seed in (1, 3, 8):  # seeds on which plain rejection sampling found too few start points
        start = initial_poses(hand, scene.hull_vertices, 8, GenerationConfig().init, torch.Generator().manual_seed(seed))
        assert start.shape == (8, 25) and bool(torch.isfinite(start).all())
        assert float(start[:, 0].max()) < float(scene.hull_vertices[:, 0].max())
