"""`gd2p eval` building blocks: resumable records, the push protocol, the grasp baseline's frames, reports."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from evaluation import push_protocol as protocol
from evaluation.grasp_baseline import GraspPoseSource
from evaluation.methods import failure_cause
from evaluation.report import markdown_table, write_experiment, write_index
from evaluation.store import ResultStore, ResultStoreError
from shared.contracts.messages import DirectionFrame, ObjectRef, SampleRequest
from shared.frames import direction_frame, direction_xy, invert_transform, pose25_to_matrix
from shared.world.objects import load_object
from shared.world.push_outcome import object_pose, pose_matrix


def test_store_resumes_and_survives_a_torn_line(tmp_path):
    store = ResultStore(tmp_path, {"trials": 5})
    store.add("a", {"success": True})
    with store.path.open("a") as f:
        f.write('{"key": "b", "succ')  # killed mid-write
    again = ResultStore(tmp_path, {"trials": 5})
    assert again.done("a") and not again.done("b")
    assert again.pending(["a", "b", "c"]) == ["b", "c"]
    again.add("b", {"success": False})
    assert set(ResultStore(tmp_path, {"trials": 5}).records) == {"a", "b"}


def test_store_refuses_other_settings(tmp_path):
    ResultStore(tmp_path, {"trials": 5, "objects": ["x"]})
    with pytest.raises(ResultStoreError, match="trials"):
        ResultStore(tmp_path, {"trials": 3, "objects": ["x"]})


def test_episodes_use_test_objects_only_and_known_methods():
    with pytest.raises(ValueError, match="train split"):
        protocol.episodes(["gd2p"], "allegro", ["proc-box-050"], [60.0], 1)
    with pytest.raises(ValueError, match="unknown method"):
        protocol.episodes(["magic"], "allegro", ["proc-box-001"], [60.0], 1)
    eps = protocol.episodes(["gd2p", "fixed"], "allegro", ["proc-box-001", "pb-mug"], protocol.DIRECTIONS_DEG, 5)
    assert len(eps) == 2 * 2 * 3 * 5 and len({e.key for e in eps}) == len(eps)


def test_unseen_objects_are_a_whole_never_trained_family_of_the_test_split():
    from evaluation.methods import UNSEEN_OBJECTS, protocol_for
    from shared.world.objects import UNSEEN_FAMILIES, list_object_ids
    from shared.world.objects.catalog import resolve_library_id

    spec = protocol_for("methods", quick=False, split="unseen")
    assert spec.objects == UNSEEN_OBJECTS and spec.directory_name == "methods-real-unseen"
    assert {resolve_library_id(o).family for o in spec.objects} <= set(UNSEEN_FAMILIES)
    # no object of the family is anywhere but the test split, so no model ever trained on one
    assert not [i for s in ("train", "val") for i in list_object_ids(s) if resolve_library_id(i).family in UNSEEN_FAMILIES]
    assert len(protocol.episodes(["gd2p"], "allegro", spec.objects, [60.0], 1, split="unseen")) == len(UNSEEN_OBJECTS)
    with pytest.raises(ValueError, match="which models train on"):
        protocol.episodes(["gd2p"], "allegro", ["proc-box-001"], [60.0], 1, split="unseen")


def test_every_method_faces_the_same_placement():
    a = protocol.Episode("gd2p", "allegro", "pb-mug", 180.0, 3)
    b = protocol.Episode("fixed", "allegro", "pb-mug", 180.0, 3)
    other_trial = protocol.Episode("gd2p", "allegro", "pb-mug", 180.0, 4)
    assert np.allclose(protocol.placement(a), protocol.placement(b))
    assert not np.allclose(protocol.placement(a), protocol.placement(other_trial))
    offset = protocol.placement(a)[:2, 3] - np.array(protocol.OBJECT_XY)
    assert np.all(np.abs(offset) <= protocol.PLACEMENT_NOISE_M + 1e-9)
    request = protocol.push_request(a, protocol.placement(a))
    assert request.options.choice == "ranked" and request.options.method == "gd2p" and request.distance_m == pytest.approx(0.20)
    ablation, random_nn = (protocol.push_request(e, protocol.placement(e)) for e in
                           (protocol.Episode("gd2p-unranked", "allegro", "pb-mug", 180.0, 3),
                            protocol.Episode("nearest", "allegro", "pb-mug", 180.0, 3)))
    assert (ablation.options.method, ablation.options.choice) == ("gd2p", "unranked")
    assert (random_nn.options.method, random_nn.options.choice) == ("nearest", "random")


def test_every_method_faces_the_same_execution_world_and_trials_differ():
    a, b = (protocol.Episode(m, "allegro", "pb-mug", 180.0, 3) for m in ("gd2p", "fixed"))
    other_trial = protocol.Episode("gd2p", "allegro", "pb-mug", 180.0, 4)
    world_a, world_b, world_c = (protocol.execution_world(e) for e in (a, b, other_trial))
    assert world_a == world_b and world_a != world_c
    assert world_a.level == "real" and world_a.pose_error != protocol.execution_world(
        protocol.Episode("gd2p", "allegro", "pb-mug", 180.0, 3, world="exact")).pose_error


def test_with_cameras_the_system_gets_a_capture_and_the_robot_the_true_object():
    from evaluation.local_system import true_world
    from shared.contracts.messages import SimWorld
    from shared.world.sim.world import PoseError

    episode = protocol.Episode("gd2p", "allegro", "proc-box-001", 60.0, 0, cameras=1)
    world = protocol.execution_world(episode)
    T_start = protocol.put_down(episode, world)
    request = protocol.push_request(episode, T_start)
    assert request.object.point_cloud is not None and request.object_pose is None
    assert np.array_equal(protocol.captured_cloud(episode, T_start), request.object.point_cloud.to_numpy())  # seeded
    assert world.cameras == 1 and world.pose_error == PoseError()  # perception brings its own pose error
    true_object = (ObjectRef(library_id="proc-box-001"), protocol.placement(episode))
    told = SimWorld(object=request.object, object_pose=object_pose(np.eye(4)))
    truth = true_world(told, world, true_object)
    assert truth.obj.library_id == "proc-box-001"
    assert np.allclose(truth.T_world_O, protocol.placement(episode))
    assert truth.physics == world.physics


def test_with_cameras_the_tracker_follows_the_reconstruction_the_planner_plans_around():
    """The reconstruction's frame O (principal axes of what the cameras saw) can be the mug's own frame
    turned upside down. The robot's tracker reports the reconstruction's frame, rigidly attached to the
    true mug: a correction or the next push then sees an upright object that has moved with the push,
    where the library frame would read "toppled" before anything moved."""
    from dataclasses import replace

    from evaluation.local_system import true_world
    from shared.contracts.messages import SimWorld
    from shared.execution.robots.sim.config import SimConfig
    from shared.execution.robots.sim.robot import SimRobot
    from shared.frames import make_transform, yaw_rotation
    from shared.world.object_refs import captured_object
    from shared.world.push_outcome import judge_push

    episode = protocol.Episode("gd2p", "allegro", "pb-mug", 180.0, 0, cameras=3)
    T_true = protocol.put_down(episode, protocol.execution_world(episode))
    request = protocol.push_request(episode, T_true)
    seen = captured_object(request.object).T_world_O
    assert (seen[:3, 2] @ T_true[:3, 2]) < -0.9  # what makes this case: the two frames' z axes are opposite
    told = SimWorld(object=request.object, object_pose=object_pose(seen))
    truth = true_world(told, protocol.execution_world(episode), (ObjectRef(library_id="pb-mug"), T_true))
    target = seen[:2, 3] + 0.2 * direction_xy(180.0)
    # The truth tracker: the frame it reports is the one the judge compares the image tracker with, and the mug
    # is teleported 20 cm below (a new world), which no image tracker follows.
    with SimRobot(SimConfig("panda", "allegro", tracking="truth")) as robot:
        robot.reset_world(truth)
        tracked = pose_matrix(robot.observe().object_pose)
        assert np.linalg.norm(tracked[:2, 3] - seen[:2, 3]) < 0.01 and tracked[:3, 2] @ seen[:3, 2] > 0.99
        assert np.allclose(pose_matrix(robot.true_object_pose()), T_true, atol=1e-3)  # the truth is unchanged
        moved = make_transform(yaw_rotation(math.radians(30.0)) @ T_true[:3, :3], T_true[:3, 3] + [-0.2, 0.0, 0.0])
        robot.reset_world(replace(truth, T_world_O=moved))  # the mug pushed 20 cm and turned 30 degrees
        after = pose_matrix(robot.observe().object_pose)
    judged = judge_push(seen, target, object_pose(after), max_rotation_deg=None)
    assert not judged.toppled and judged.position_error_m < 0.03


def test_a_trial_is_judged_from_where_the_object_truly_started():
    """Told pose off by 2 cm: an object pushed exactly 0.20 m from its true start succeeds, although it
    ends 2 cm from the target the planner computed from the told pose."""
    from dataclasses import replace

    from shared.world.sim.world import PoseError

    episode = protocol.Episode("gd2p", "allegro", "proc-box-001", 60.0, 0)
    world = replace(protocol.execution_world(episode), pose_error=PoseError(0.02, 0.0, 0.0))
    T_true = protocol.put_down(episode, world)
    T_end = T_true.copy()
    T_end[:2, 3] += 0.20 * direction_xy(60.0)
    assert protocol.judged_from(episode, T_true, object_pose(T_end)).success
    T_told_end = protocol.placement(episode)
    T_told_end[:2, 3] += 0.20 * direction_xy(60.0) + np.array([0.0, 0.035])
    assert not protocol.judged_from(episode, T_true, object_pose(T_told_end)).success


def test_grasp_poses_move_with_the_object(tmp_path):
    """A cached grasp pose keeps its place on the object whatever the object's yaw and the push direction."""
    obj = load_object("proc-box-001")
    T_D0_O = obj.T_D_O()
    pose = np.zeros(25)
    pose[:3] = (-0.12, 0.02, 0.05)
    pose[3:9] = (1, 0, 0, 0, 1, 0)
    cache = tmp_path / "allegro" / "proc-box-001_4.npz"
    cache.parent.mkdir(parents=True)
    np.savez(cache, poses=pose[None], T_D_O=T_D0_O)
    source = GraspPoseSource(tmp_path, generated=4, offered=1)

    T_world_O = pose_matrix(object_pose(np.array([[math.cos(0.4), -math.sin(0.4), 0, 0.45],
                                                   [math.sin(0.4), math.cos(0.4), 0, 0.05],
                                                   [0, 0, 1, 0], [0, 0, 0, 1]]) @ T_D0_O))
    frame = DirectionFrame(object_pose=object_pose(T_world_O), direction_xy=tuple(direction_xy(130.0)))
    reply = source(SampleRequest(object=ObjectRef(library_id="proc-box-001"), hand="allegro", frame=frame, k=1))
    T_world_hand, _ = pose25_to_matrix(reply.poses_world.to_numpy()[0])
    T_O_hand_expected = invert_transform(T_D0_O) @ pose25_to_matrix(pose)[0]
    assert np.allclose(invert_transform(T_world_O) @ T_world_hand, T_O_hand_expected, atol=1e-9)
    T_world_D = direction_frame(T_world_O[:3, 3], direction_xy(130.0))
    assert np.allclose(T_world_D @ pose25_to_matrix(reply.poses_d.to_numpy()[0])[0], T_world_hand, atol=1e-9)


def test_fixed_pose_pull_toward_the_robot_succeeds_with_the_arm(tmp_path):
    """One full protocol trial in physics: the spatula pose pulls the box 0.20 m toward the robot."""
    protocol._init_worker(str(tmp_path))
    record = protocol.run_episode(protocol.Episode("fixed", "allegro", "proc-box-001", 180.0, 0, world="exact"))
    assert record["outcome"] == "success", record
    assert record["world_draw"]["level"] == "exact"
    assert record["position_error_m"] <= 0.03 and not record["toppled"]
    assert record["pose_model"] is None  # the fixed pose comes from no model or index


def test_a_failed_plan_is_replayed_to_tell_perception_from_physics(tmp_path):
    """The spatula pull planned for the told pose: replayed in nominal physics it succeeds where the planner
    was told the box stood; on the true box 15 cm to the side it misses (perception), on the true box
    where it was told to be it succeeds (so a failure there was the physics')."""
    from dataclasses import replace

    from shared.world.sim.world import PoseError

    protocol._init_worker(str(tmp_path))
    protocol._system.robot.tracking_mode = "truth"  # physics replayed, not tracking: the quicker tracker
    episode = protocol.Episode("fixed", "allegro", "proc-box-001", 180.0, 0, world="exact")
    request = protocol.push_request(episode, protocol.placement(episode))
    response = protocol._system.pipeline("sampler").run(request).response
    exact = protocol.execution_world(episode)
    for error, on_true_object in ((PoseError(0.0, 0.15, 0.0), False), (PoseError(), True)):
        world = replace(exact, pose_error=error)
        truth = (ObjectRef(library_id="proc-box-001"), protocol.put_down(episode, world))
        protocol._system.robot.true_object = truth
        replayed = protocol.replay_failure(episode, truth[1], request, response.plan)
        assert replayed == {"planner_world": True, "true_object": on_true_object}
        assert protocol._system.robot.true_object is truth and protocol._system.robot.execution_world is None


def test_failure_causes_follow_the_replays():
    failed = {"success": False, "outcome": "failure", "predicted_l_goal": 0.01}
    assert failure_cause(failed) == "world gap"  # not replayed
    assert failure_cause({**failed, "replayed": {"planner_world": False, "true_object": False}}) == "prediction"
    assert failure_cause({**failed, "replayed": {"planner_world": True, "true_object": False}}) == "perception"
    assert failure_cause({**failed, "replayed": {"planner_world": True, "true_object": True}}) == "physics"
    assert failure_cause({**failed, "predicted_l_goal": 0.05}) == "pose quality"
    lost = {"success": False, "outcome": "error", "error_code": "lost", "message": "after the push the tracker had lost "
            "the object: too few object points (16 < 30)"}
    assert failure_cause(lost) == "tracking"  # the tracker's, not the planner's
    assert failure_cause({**lost, "error_code": "infeasible"}) == "planning"


def test_reports_and_index(tmp_path):
    table = markdown_table(["method", "rate"], [["GD2P", 0.8123], ["fixed", "–"]])
    assert table.splitlines()[2] == "| GD2P | 0.81 |"
    records = [{"code": "abc", "pose_model": "allegro:0123"}, {"code": "abc", "pose_model": None}]
    write_experiment(tmp_path / "methods", "Methods", table, {"success": 0.8}, wall_time_s=90.0, quick=True,
                     records=records)
    assert "pose models of the trials (diffusion checkpoint id, or nn:index@id): allegro:0123 (1)" in (
        tmp_path / "methods" / "report.md").read_text()
    summary = json.loads((tmp_path / "methods" / "summary.json").read_text())
    assert summary["success"] == 0.8 and summary["quick"] and "cores" in summary["machine"]
    assert summary["code"] not in ("", "unknown")  # the commit these results came from (tests run in the checkout)
    index = write_index(tmp_path).read_text()
    assert "[methods](methods/report.md)" in index and "| abc |" in index  # the commit its trials ran at


def test_a_multistep_run_that_fails_after_some_pushes_records_how_far_the_object_got(monkeypatch):
    """The failed request's PushError carries the executed pushes: their count and the object's path are recorded."""
    from types import SimpleNamespace

    from evaluation import multistep
    from evaluation.local_system import Contacts
    from shared.contracts.messages import ObjectPose
    from shared.planning.outcome import PushError

    moved = [SimpleNamespace(step=SimpleNamespace(result=SimpleNamespace(final_object_pose=ObjectPose(position=p))))
             for p in [(0.45, 0.0, 0.04), (0.47, 0.1, 0.04)]]

    class StuckPipeline:
        def run(self, request):
            raise PushError("infeasible", "push 3, ... after 2 push(es): no plan", records=moved)

    system = SimpleNamespace(robot=SimpleNamespace(contacts=Contacts()), pipeline=lambda _name: StuckPipeline())
    monkeypatch.setattr(protocol, "_system", system)
    run = multistep.Run(multistep.SCENARIOS[0], "proc-cylinder-001", 0)
    record = multistep.run_one(run)
    assert record["outcome"] == "infeasible" and record["pushes"] == 2 and not record["success"]
    start = multistep.true_start(run, run.execution_world())[:2, 3]  # where it truly stood, not where it was told
    assert np.linalg.norm(start - pose_matrix(multistep.request(run).object_pose)[:2, 3]) > 1e-3
    assert record["path_xy"] == [[round(float(v), 4) for v in start], [0.45, 0.0], [0.47, 0.1]]


def test_a_multistep_run_with_cameras_sends_a_capture_and_the_robot_pushes_the_true_object(monkeypatch):
    from types import SimpleNamespace

    from evaluation import multistep
    from evaluation.local_system import Contacts
    from shared.planning.outcome import PushError

    run = multistep.Run(multistep.SCENARIOS[0], "proc-cylinder-001", 0, cameras=3)
    request = multistep.request(run)
    assert request.object.point_cloud is not None and request.object_pose is None and request.goal_xy is not None
    assert np.array_equal(request.object.point_cloud.to_numpy(), multistep.request(run).object.point_cloud.to_numpy())
    cloud_centre = request.object.point_cloud.to_numpy()[:, :2].mean(axis=0)
    world = run.execution_world()
    assert np.linalg.norm(cloud_centre - multistep.true_start(run, world)[:2, 3]) < 0.02  # captured where it stands

    class NoPlan:
        def run(self, request):
            raise PushError("infeasible", "no plan", records=[])

    system = SimpleNamespace(robot=SimpleNamespace(contacts=Contacts()), pipeline=lambda _name: NoPlan())
    monkeypatch.setattr(protocol, "_system", system)
    multistep.run_one(run)
    true_ref, T_true = system.robot.true_object
    assert true_ref.library_id == "proc-cylinder-001" and np.allclose(T_true, multistep.true_start(run, world))


def test_a_real_report_compares_with_the_exact_run_of_the_same_perception_and_models(tmp_path):
    from evaluation.methods import exact_rates, protocol_for

    def committed(name: str, method: str, rate: float, pose_models: dict | None = None) -> None:
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps(
            {"code": "abc1234", "methods": {method: {"success_rate": rate, "trials": 210}}}))
        if pose_models is not None:
            (tmp_path / name / "settings.json").write_text(json.dumps({"pose_models": pose_models}))

    shipped, other = {"diffusion": "d1", "nearest": "n1"}, {"diffusion": "d0", "nearest": "n1"}
    committed("methods", "gd2p-no-ranking", 0.3)  # made before execution worlds (and model ids) were recorded
    told_mesh = exact_rates(tmp_path, protocol_for("methods", False, 3, "real", ("gd2p-random",)), shipped)
    assert told_mesh["gd2p-random"]["rate"] == 0.3 and "results/methods, 210 trials" in told_mesh["gd2p-random"]["source"]
    assert exact_rates(tmp_path, protocol_for("methods", False, 3, "real", ("gd2p",), cameras=1), shipped) == {}
    assert exact_rates(tmp_path, protocol_for("methods", False, 3, "exact", ("gd2p",)), shipped) == {}

    tagged = protocol_for("methods", False, 3, "real", ("gd2p",), tag="v2")
    assert exact_rates(tmp_path, tagged, shipped) == {}  # never the run of the models shipped before
    committed("methods-exact-v2", "gd2p", 0.97, other)
    assert exact_rates(tmp_path, tagged, shipped) == {}  # an exact run of other models compares nothing
    assert exact_rates(tmp_path, tagged, other)["gd2p"] == {
        "rate": 0.97, "source": "results/methods-exact-v2, 210 trials per method, abc1234"}
    seen = protocol_for("methods", False, 3, "real", ("gd2p",), cameras=3, tag="v2")  # its `exact`: told the mesh
    assert exact_rates(tmp_path, seen, other)["gd2p"]["source"].startswith("results/methods-exact-v2,")


def test_the_index_names_the_commits_that_ran_the_trials(tmp_path):
    import json

    from evaluation.report import write_index

    for name, summary in (("stamped", {"code": "bbb", "records_code": {"aaa": 3, "bbb": 1}}), ("old", {})):
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps({"title": name, **summary}))
        (tmp_path / name / "report.md").write_text(f"# {name}\n\n- header\n\nbody\n")
    index = write_index(tmp_path).read_text()
    assert "| aaa (3), bbb (1) |" in index  # the commits that ran its trials, not the one that wrote the report
    assert "| not recorded |" in index  # a run from before results were stamped


def test_a_tagged_run_has_its_own_directory_and_a_store_refuses_other_pose_models(tmp_path, monkeypatch):
    from evaluation.methods import protocol_for
    from shared.sampling.checkpoint import SHIPPED_DIR

    spec = protocol_for("methods", True, 1, "real", ("gd2p",), tag="v2")
    assert spec.directory_name == "methods-real-v2" and spec.title.endswith("(v2)")
    models = spec.settings()["pose_models"]
    assert models["diffusion"] and models["nearest"]  # the shipped checkpoint and index, by content
    ResultStore(tmp_path / spec.directory_name, spec.settings())
    monkeypatch.setenv("GD2P_SAMPLER_NOISE_SCALE", "0.5")  # the same weights drawn at another temperature
    assert spec.settings()["pose_models"]["diffusion_noise_scale"] == 0.5
    with pytest.raises(ResultStoreError, match="pose_models"):
        ResultStore(tmp_path / spec.directory_name, spec.settings())
    monkeypatch.delenv("GD2P_SAMPLER_NOISE_SCALE")
    monkeypatch.setenv("GD2P_SAMPLER_CHECKPOINT_ALLEGRO", str(SHIPPED_DIR / "leap.pt"))  # other weights
    with pytest.raises(ResultStoreError, match="pose_models"):
        ResultStore(tmp_path / spec.directory_name, spec.settings())


def test_a_run_extended_by_another_method_keeps_the_methods_it_ran_before_in_its_report(tmp_path):
    from evaluation.methods import protocol_for, with_stored_methods

    first = protocol_for("methods", True, 1, "real", ("gd2p", "fixed"))
    store = ResultStore(tmp_path, {"trials": 1})
    for episode in protocol.episodes(first.methods, first.hand, first.objects, first.directions, 1):
        store.add(episode.key, {"method": episode.method, "success": True})
    partial = protocol.episodes(("nearest-ranked",), first.hand, first.objects, first.directions, 1)[:1]
    store.add(partial[0].key, {"method": "nearest-ranked", "success": True})  # a method killed after one trial
    extended = with_stored_methods(protocol_for("methods", True, 1, "real", ("nearest",)), store)
    assert extended.methods == ("nearest", "gd2p", "fixed")  # asked first; an incomplete method is not reported
    more_trials = with_stored_methods(protocol_for("methods", True, 2, "real", ("nearest",)), store)
    assert more_trials.methods == ("nearest",)  # the earlier methods lack trial 1 of the longer run


def test_the_methods_are_data_and_the_planner_default_is_defined_once(tmp_path):
    """evaluation/methods.yaml lists each method's options; the default method changes none of PlannerOptions'."""
    from shared.contracts.messages import PlannerOptions

    assert protocol.METHODS["gd2p-closed-critic-p24"].options == PlannerOptions()
    assert protocol.METHODS["gd2p"].options == PlannerOptions(corrections=0, closed_loop=False, critic=False)
    assert protocol.METHODS["grasp"].source == "grasp" and protocol.METHODS["grasp"].options.method == "gd2p"
    assert "gd2p-a30" in protocol.TUNING_METHODS and "gd2p-a30" not in protocol.DEFAULT_METHODS
    bad = tmp_path / "methods.yaml"
    bad.write_text("mine:\n  label: Mine\n  options: {k: 0}\n")
    with pytest.raises(protocol.MethodsFileError, match=r"methods.yaml: method 'mine': .*k"):
        protocol.load_methods(bad)
    bad.write_text("mine:\n  label: Mine\n  options: {}\n  budgett: [1, 2]\n")
    with pytest.raises(protocol.MethodsFileError, match=r"method 'mine': .*budgett"):
        protocol.load_methods(bad)
