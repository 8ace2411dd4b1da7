"""Re-decide from a recording (issue 52, `gd2p replay FILE.mcap --resim`): a push recorded through the system
carries what its decision needed (request and capture, models, commit, seeds, settings), and planning it again
in process gives the same plan, bit for bit. Unusable and altered recordings get a clear answer."""
from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from conftest import TRUTH_TRACKED as TRUTH
from shared.bus import BusConfig, live_workers, open_session
from shared.contracts.messages import ObjectRef, Plan, PlannerOptions, PushRequest
from shared.planning.decision import METADATA_NAME, compare_plans
from visualisation.recording import McapWriter, read_metadata, read_records

BOX = "proc-box-013"


@pytest.fixture(scope="module")
def recorded_push(module_router, tmp_path_factory):
    """A "fixed" push served by the planner, a validator and the simulated bridge on the router: its MCAP."""
    from client.push_client import push
    from services.planner import service as planner
    from services.robot_bridge import service as bridge
    from shared.bus import run_worker
    from shared.validation import jobs as validator

    cfg = BusConfig(mode="client", connect=[module_router], connect_timeout_ms=5000)
    record_dir = tmp_path_factory.mktemp("pushes")
    stop = threading.Event()
    workers = [
        threading.Thread(target=bridge.run, args=(cfg, "bridge-r", stop), kwargs=TRUTH, daemon=True),
        threading.Thread(target=run_worker, args=(validator.SERVICE, validator.handlers(), cfg, "validator-r"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=planner.run, args=(cfg, "planner-r", stop, str(record_dir)), daemon=True),
    ]
    for w in workers:
        w.start()
    try:
        with open_session(cfg) as session:
            deadline = time.monotonic() + 30.0
            while not all(live_workers(session).get(s) for s in ("planner", "validator", "robot_bridge")):
                assert time.monotonic() < deadline, "workers did not register"
                time.sleep(0.2)
        response = push(PushRequest(object=ObjectRef(library_id=BOX), direction_deg=90.0, seed=7, options=PlannerOptions(method="fixed")),
                        cfg, timeout_s=240.0)
    finally:
        stop.set()
        for w in workers:
            w.join(timeout=15.0)
    assert response.recording_path
    return response


def test_a_push_recording_carries_what_its_decision_needed(recorded_push):
    decision = read_metadata(recorded_push.recording_path)[METADATA_NAME]
    assert set(json.loads(decision["models"])) == {"diffusion", "critic", "nn_index"}
    assert all(v.startswith("sha256:") for v in json.loads(decision["models"]).values())
    assert json.loads(decision["seeds"]) == {"request": 7, "motion_planner": 0, "ik": 0}
    assert decision["commit"] not in ("", "unknown") and decision["settings"].startswith("PipelineSettings(")
    assert decision["method"] == "fixed" and decision["capture"] == f"library object {BOX}"


def test_resim_of_a_recorded_push_gives_the_same_plan_bit_for_bit(recorded_push, capsys):
    from cli.main import main

    assert main(["replay", recorded_push.recording_path, "--resim"]) == 0
    out = capsys.readouterr()
    assert "identical: the same plan comes out" in out.out, out
    assert "warning" not in out.err, out.err


def test_a_plan_that_differs_is_named_with_where_and_by_how_much(recorded_push):
    plan = recorded_push.plan
    positions = plan.positions.to_numpy().copy()
    positions[3, 2] += 1e-9
    changed = Plan(arm=plan.arm, hand=plan.hand, joint_names=plan.joint_names, positions=positions,
                   times_s=plan.times_s.to_numpy(), segments=plan.segments)
    assert compare_plans(plan, plan) == []
    [difference] = compare_plans(plan, changed)
    assert "waypoints: 1 of" in difference and "at most 1e-09" in difference
    assert f"waypoint 3, joint {plan.joint_names[2]}" in difference


def _rewrite(source: str, target, metadata: dict[str, str] | None, keys=None) -> str:
    """A copy of `source` with only the bus messages on `keys` (default all) and the given decision metadata."""
    with McapWriter(str(target)) as writer:
        for record in read_records(source):
            if record.encoding.startswith("application/msgpack") and (keys is None or record.key in keys):
                writer.write(record.key, record.payload, record.encoding, record.log_time_ns)
        if metadata is not None:
            writer.add_metadata(METADATA_NAME, metadata)
    return str(target)


def test_resim_warns_of_another_commit_or_model_and_still_plans(recorded_push, tmp_path, capsys):
    from cli.main import main

    decision = dict(read_metadata(recorded_push.recording_path)[METADATA_NAME])
    models = json.loads(decision["models"]) | {"diffusion": "sha256:" + "0" * 64}
    other = _rewrite(recorded_push.recording_path, tmp_path / "other.mcap",
                     decision | {"commit": "0" * 40, "models": json.dumps(models)})
    assert main(["replay", other, "--resim"]) == 0  # "fixed" uses no model: the same plan still comes out
    err = capsys.readouterr().err
    assert f"other commit: recorded {'0' * 40}" in err and "other model diffusion" in err


@pytest.mark.parametrize("what", ["missing file", "not mcap", "no request", "no metadata"])
def test_an_unusable_recording_exits_2_with_a_clear_message(recorded_push, tmp_path, capsys, what):
    from cli.main import main

    path = {"missing file": lambda: str(tmp_path / "nothing.mcap"),
            "not mcap": lambda: (tmp_path / "text.mcap").write_text("hello") and str(tmp_path / "text.mcap"),
            "no request": lambda: _rewrite(recorded_push.recording_path, tmp_path / "bare.mcap", None,
                                           keys={"gd2p/planner/response"}),
            "no metadata": lambda: _rewrite(recorded_push.recording_path, tmp_path / "old.mcap", None)}[what]()
    code = main(["replay", path, "--resim"])
    err = capsys.readouterr().err
    if what == "no metadata":  # an older recording: said, and planned anyway
        assert code == 0 and f"no {METADATA_NAME} metadata" in err
        return
    assert code == 2 and "unusable recording" in err
    assert {"missing file": "no such recording", "not mcap": "not a readable MCAP",
            "no request": "no PushRequest"}[what] in err


def test_the_recorded_capture_is_the_requests_cloud():
    """A point-cloud request's capture travels inside the recorded request (nothing else to store)."""
    from shared.planning.decision import decision_metadata

    cloud = np.zeros((100, 3), dtype=np.float32)
    cloud[:, 0] = np.linspace(0.5, 0.6, 100)
    request = PushRequest(object=ObjectRef(point_cloud=cloud), direction_deg=0.0)
    assert decision_metadata(request, None, {})["capture"] == "point cloud of 100 points (in the request)"



def test_a_recording_whose_plan_differs_from_the_replanned_one_exits_1_naming_the_difference(recorded_push, tmp_path,
                                                                                            capsys):
    from cli.main import main
    from shared.contracts.codec import encode

    plan = recorded_push.plan
    positions = plan.positions.to_numpy().copy()
    positions[5, 0] += 0.01  # as if another decision had been recorded
    other_plan = Plan(arm=plan.arm, hand=plan.hand, joint_names=plan.joint_names, positions=positions,
                      times_s=plan.times_s.to_numpy(), segments=plan.segments)
    steps = [step.model_copy(update={"plan": other_plan}) for step in recorded_push.steps[:1]] + recorded_push.steps[1:]
    response = recorded_push.model_copy(update={"plan": other_plan, "steps": steps})
    target = tmp_path / "altered.mcap"
    decision = read_metadata(recorded_push.recording_path)[METADATA_NAME]
    with McapWriter(str(target)) as writer:
        for record in read_records(recorded_push.recording_path):
            if record.key == "gd2p/planner/request":
                writer.write(record.key, record.payload, record.encoding, record.log_time_ns)
        payload, encoding = encode(response)
        writer.write("gd2p/planner/response", payload, encoding)
        writer.add_metadata(METADATA_NAME, decision)
    assert main(["replay", str(target), "--resim"]) == 1
    out = capsys.readouterr().out
    assert "DIFFERENT" in out and "push 1: waypoints: 1 of" in out and "at most 0.01" in out
    assert f"(waypoint 5, joint {plan.joint_names[0]})" in out


def test_with_view_a_decision_that_differs_is_shown_beside_the_recorded_one(recorded_push, tmp_path, capsys,
                                                                            monkeypatch):
    """`--resim --view`: the recorded decision and the one made again, switched by the view's Decision selector."""
    import socket
    import time

    from cli.main import main
    from shared.contracts.codec import encode
    from visualisation.live import LiveView

    plan = recorded_push.plan
    positions = plan.positions.to_numpy().copy()
    positions[5, 0] += 0.01
    other_plan = Plan(arm=plan.arm, hand=plan.hand, joint_names=plan.joint_names, positions=positions,
                      times_s=plan.times_s.to_numpy(), segments=plan.segments)
    target = tmp_path / "altered-decision.mcap"
    with McapWriter(str(target)) as writer:
        for record in read_records(recorded_push.recording_path):
            if record.key == "gd2p/planner/decision":  # as if the planner had chosen the other plan
                decision = record.decode().model_copy(update={"plan": other_plan})
                writer.write(record.key, *encode(decision), record.log_time_ns)
            elif record.key == "gd2p/planner/request":
                writer.write(record.key, record.payload, record.encoding, record.log_time_ns)
        steps = [step.model_copy(update={"plan": other_plan}) for step in recorded_push.steps[:1]]
        writer.write("gd2p/planner/response", *encode(recorded_push.model_copy(update={"plan": other_plan,
                                                                                        "steps": steps})))
        writer.add_metadata(METADATA_NAME, read_metadata(recorded_push.recording_path)[METADATA_NAME])
    shown: list[tuple[tuple[str, ...], dict[str, int]]] = []
    compare = LiveView.show_comparison

    def watched(view, decisions):
        selector = compare(view, decisions)
        deadline = time.monotonic() + 30.0
        while view.counts()["decisions"] < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        selector.value = list(decisions)[1]  # what picking the other one in the panel does
        while view.counts()["decisions"] < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        shown.append((tuple(selector.options), dict(view.counts())))
        return selector

    monkeypatch.setattr(LiveView, "show_comparison", watched)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(["replay", str(target), "--resim", "--view", "--exit", "--port", str(port)]) == 1
    out = capsys.readouterr().out
    assert "DIFFERENT" in out and "the Decision selector switches between them" in out
    [(options, counts)] = shown
    assert options == ("altered-decision.mcap push 1: recorded", "altered-decision.mcap push 1: decided again")
    assert counts["decisions"] == 2 and counts["rollouts"] > 0
