"""The live view, tested as a person would use it: the system runs (sampler, validator, planner,
simulated robot bridge, as tests/test_push.py's `system`, plus the view's bus adapter), the view is opened in
headless Chromium (Debian's `chromium` and `chromium-driver`: `make install`), a push runs, and the page itself
shows the cloud, the candidates and the robot (the counts the view prints in its "Scene" panel, and the pixels
of a screenshot). The bridge runs with preview and confirm (`gd2p up --confirm`): the robot does not move until
the page's Confirm button is clicked. A second viewer and a viewer that disconnects mid-push change nothing
for the push or the others. Without Chromium the browser tests are skipped.
"""
from __future__ import annotations

import os
import re
import shutil
import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from client.push_client import push
from conftest import TRUTH_TRACKED as TRUTH
from shared.bus import BusConfig, live_workers, open_session
from shared.contracts.messages import ObjectRef, PlannerOptions, PushRequest

BOX = "proc-box-013"
ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT = ROOT / "docs" / "img" / "live_view.png"
# A system with the sampler and a browser on 2 shared cores: start-up alone can take minutes under load.
BROWSER_TIMEOUT_S = 900
CHROME_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1280,800")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _chromium() -> tuple[str, str] | None:
    binary = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver") or "/usr/bin/chromedriver"
    return (binary, driver) if binary and os.path.exists(driver) else None


@pytest.fixture(scope="module")
def view_system(module_router, tmp_path_factory):
    """Sampler, validator, planner and simulated bridge on the router, and the live view attached to it."""
    from cli import view as view_cli
    from services.planner import service as planner
    from services.robot_bridge import service as bridge
    from shared.bus import run_worker
    from shared.sampling import server as sampler
    from shared.validation import jobs as validator

    cfg = BusConfig(mode="client", connect=[module_router], connect_timeout_ms=5000)
    record_dir = tmp_path_factory.mktemp("pushes")
    stop = threading.Event()
    workers = [
        threading.Thread(target=bridge.run, args=(cfg, "bridge-v", stop), kwargs={"confirm_timeout_s": 60.0, **TRUTH},
                         daemon=True),
        threading.Thread(target=run_worker, args=(validator.SERVICE, validator.handlers(), cfg, "validator-v"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=run_worker, args=(sampler.SERVICE, sampler.handlers(), cfg, "sampler-v"),
                         kwargs={"stop": stop}, daemon=True),
        threading.Thread(target=planner.run, args=(cfg, "planner-v", stop, str(record_dir)), daemon=True),
    ]
    views: list = []
    ready = threading.Event()
    workers.append(threading.Thread(target=view_cli.serve, args=(cfg, _free_port()),
                                    kwargs={"stop": stop, "ready": lambda v: (views.append(v), ready.set())},
                                    daemon=True))
    for w in workers:
        w.start()
    assert ready.wait(60), "the view did not start"
    with open_session(cfg) as session:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            live = live_workers(session)
            if all(live.get(s) for s in ("planner", "validator", "robot_bridge", "sampler")):
                break
            time.sleep(0.2)
        else:
            pytest.fail(f"workers did not register: {live}")
    yield cfg, views[0], record_dir
    stop.set()
    for w in workers:
        w.join(timeout=15.0)


def _browser():
    found = _chromium()
    if found is None:
        pytest.skip("no chromium / chromedriver (make install installs them)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = found[0]
    for flag in (*CHROME_FLAGS, f"--user-data-dir={tempfile.mkdtemp(prefix='gd2p-chromium-')}"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(found[1]), options=options)


@pytest.fixture
def browser():
    driver = _browser()
    yield driver
    driver.quit()


def _page_counts(driver) -> dict[str, int]:
    """The view's "Scene" panel as the page shows it: {"cloud points": n, "candidates": n, ...}."""
    text = driver.find_element("tag name", "body").text
    return {name.strip(): int(n) for name, n in re.findall(r"([a-z][a-z -]+): (\d+)", text)}


def _wait_page(driver, condition, timeout_s: float = 240.0) -> dict[str, int]:
    deadline = time.monotonic() + timeout_s
    counts: dict[str, int] = {}
    while time.monotonic() < deadline:
        counts = _page_counts(driver)
        if condition(counts):
            return counts
        time.sleep(0.5)
    raise AssertionError(f"the page never showed it; it shows {counts}")


def _cloud_request(**overrides) -> PushRequest:
    from shared.world.objects import load_object
    from shared.world.perception import cloud_for_request
    from shared.world.sim.camera import capture_object

    box = load_object(BOX)
    T_world_O = box.T_D_O()
    T_world_O[:2, 3] = (0.55, 0.0)
    cloud = cloud_for_request(capture_object(box, T_world_O, n_cameras=3, seed=1, size=(212, 120)).cloud)
    options = dict(sampler="ddim", k=64, prescreen=False, corrections=0) | overrides
    return PushRequest(object=ObjectRef(point_cloud=cloud), direction_deg=90.0, options=PlannerOptions(**options))


# ------------------------------------------------------------------------------ without a system

def _plan(n: int = 5, offset: float = 0.0):
    from shared.contracts.messages import Plan, PlanSegment

    positions = np.linspace(0.0, 1.0, n)[:, None] * np.ones((n, 2)) + offset
    return Plan(arm="panda", hand="allegro", joint_names=["a", "b"], positions=positions,
                times_s=np.arange(n, dtype=float), segments=[PlanSegment(label="push", start=0, stop=n)])


def test_the_decision_tap_reports_candidates_scores_rollouts_and_the_chosen_plan():
    """What crosses the pipeline's service boundary is enough: the sampler's reply, the arm rollouts, the plan."""
    from concurrent.futures import Future

    from shared.contracts.messages import (
        DirectionFrame,
        ExecutionState,
        ObjectPath,
        ObjectPose,
        SampleRequest,
        SampleResponse,
        ValidationJob,
        ValidationResult,
    )
    from shared.planning.decision_tap import DecisionTap
    from shared.planning.outcome import Execution
    from shared.planning.pipeline import PushServices

    frame = DirectionFrame(object_pose=ObjectPose(position=(0.55, 0.0, 0.04)), yaw_deg=90.0)
    poses = np.zeros((3, 25))
    poses[:, 3], poses[:, 7] = 1.0, 1.0  # r6: identity
    poses[:, 0] = [-0.1, -0.2, -0.3]  # behind the object in D (x along the push)
    ref = ObjectRef(library_id=BOX)

    def sample(request):
        return SampleResponse(request_id=request.id, hand="allegro", poses_d=poses, poses_world=poses, latency_s=0.1,
                              checkpoint_id="c", success_probability=np.array([0.1, 0.9, 0.5]))

    def validate(job):
        f: Future = Future()
        ok = np.array([True])
        path = ObjectPath(times_s=np.array([0.0, 1.0]), positions=np.array([[0.55, 0.0, 0.04], [0.55, 0.2, 0.04]]),
                          quaternions_xyzw=np.array([[0, 0, 0, 1.0], [0, 0, 0, 1.0]]))
        zeros = np.zeros(1)
        f.set_result(ValidationResult(job_id=job.id, hand="allegro", object_id=BOX, success=ok, position_error_m=zeros,
                                      rotation_deg=zeros, max_tilt_deg=zeros, contact_kept=ok, hand_table_contact=~ok,
                                      initial_penetration_m=zeros, goal_error_m=np.array([0.01]),
                                      collision_cost=zeros, obstacle_contact=~ok, object_paths=[path]))
        return f

    final = ExecutionState(stamp=0.0, joint_names=["a", "b"], positions=np.zeros(2), velocities=np.zeros(2), status="done")
    seen = []
    tap = DecisionTap(PushServices(sample=sample, validate=validate, execute=lambda *a: Execution(final=final)),
                      seen.append)
    services = tap.services()
    tap.begin("r1")
    services.sample(SampleRequest(object=ref, hand="allegro", frame=frame, k=3))
    rolled = [_plan(5, 0.0), _plan(5, 0.5)]
    for plan in rolled:
        services.validate(ValidationJob(object=ref, hand="allegro", poses=poses[:1], with_arm=True, arm="panda",
                                        plan=plan, frame=frame))
    chosen = rolled[1].model_validate(rolled[1].model_dump() | {  # the rolled-out plan with its way back
        "positions": np.vstack([rolled[1].positions.to_numpy(), [[2.0, 2.0]]]), "times_s": np.arange(6, dtype=float)})
    services.execute(chosen, None, None, None)
    (decision,) = seen
    assert decision.request_id == "r1" and decision.push_index == 0 and decision.chosen == 1
    assert list(decision.candidates_world.shape) == [3, 25] and list(decision.critic_scores.shape) == [3]
    world = decision.candidates_world.to_numpy()
    assert np.allclose(world[:, :2], [[0.55, -0.1], [0.55, -0.2], [0.55, -0.3]])  # D turned 90 deg onto the world
    assert [r.goal_error_m for r in decision.rollouts] == [0.01, 0.01] and decision.rollouts[1].object_path is not None
    assert tap.decisions == [decision]


def test_the_view_keeps_up_with_a_tracker_at_20_hz():
    from shared.contracts.messages import ObjectPose, ObjectTrack
    from visualisation.live import LiveView

    view = LiveView(port=_free_port())
    try:
        started = time.monotonic()
        for i in range(60):  # 3 s at 20 Hz
            view.show_track(ObjectTrack(stamp=time.time(), pose=ObjectPose(position=(0.5, 0.001 * i, 0.04)), source="t"))
            time.sleep(max(0.0, started + (i + 1) / 20.0 - time.monotonic()))
        time.sleep(0.2)
        stats = view.track_stats()
    finally:
        view.close()
    assert stats["tracks"] == 60
    assert stats["rate_hz"] >= 18.0, stats  # every tracked pose drawn in its own frame, or nearly
    assert stats["lag_max_s"] < 0.2, stats


@pytest.mark.timeout(BROWSER_TIMEOUT_S)
def test_the_browser_shows_the_cloud_the_candidates_and_the_robot_of_a_push(view_system, browser):
    cfg, view, _ = view_system
    browser.get(view.url)
    _wait_page(browser, lambda c: "candidates" in c, 60)  # the page is up and connected
    request = _cloud_request()
    done: dict = {}
    pushing = threading.Thread(target=lambda: done.update(response=push(request, cfg, timeout_s=300.0)))
    pushing.start()
    button = _wait_confirmable(browser)
    held = _page_counts(browser)
    assert held["candidates"] == 64 and held["robot states drawn"] == 0  # shown before the robot may move
    assert "A plan waits for your confirmation" in browser.find_element("tag name", "body").text
    for close in browser.find_elements("css selector", "[class*='Notification'] button"):
        try:  # headless Chromium renders WebGL in software, and the page says so in a notice
            close.click()
        except Exception:
            pass
    time.sleep(1.0)
    png = browser.get_screenshot_as_png()  # the view as an operator sees it before confirming
    if os.environ.get("GD2P_VIEW_SCREENSHOT"):
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        SCREENSHOT.write_bytes(png)
    button.click()
    pushing.join(timeout=300)
    assert done["response"].result is not None
    page = browser.find_element("tag name", "body").text
    assert re.search(r"Held plan \S+ (confirmed|: confirmed)", page) and "not confirmed" not in page, page[-400:]
    counts = _wait_page(browser, lambda c: c.get("robot states drawn", 0) > 0 and c.get("candidates", 0) > 0)
    assert counts["cloud points"] == request.object.point_cloud.shape[0]  # the captured cloud, every point
    assert counts["candidates"] == 64  # every sampled pose of the push, coloured by the critic
    assert counts["rolled-out plans"] >= 1
    assert counts["robot links"] >= 20  # the panda + allegro link meshes
    assert counts["decisions"] >= 1
    from io import BytesIO

    from PIL import Image

    pixels = np.asarray(Image.open(BytesIO(png)).convert("RGB")).reshape(-1, 3).astype(int)
    blue = ((pixels[:, 2] > 200) & (pixels[:, 0] < 90) & (pixels[:, 1] > 90) & (pixels[:, 1] < 160)).sum()
    orange = ((pixels[:, 0] > 200) & (pixels[:, 1] > 100) & (pixels[:, 1] < 170) & (pixels[:, 2] < 90)).sum()
    assert blue > 50, "no point-cloud blue on the page"
    assert orange > 50, "no object orange on the page"
    green = ((pixels[:, 1] > 180) & (pixels[:, 0] < 110) & (pixels[:, 2] < 120)).sum()
    assert green > 5, "no well-scored (green) candidate or chosen path on the page"


def _wait_confirmable(driver, timeout_s: float = 240.0):
    """The page's Confirm button once it is enabled (a plan is held)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for button in driver.find_elements("xpath", "//button[contains(., 'Confirm held plan')]"):
            if button.is_enabled():
                return button
        time.sleep(0.3)
    raise AssertionError("the Confirm button was never enabled")


class _AutoConfirm:
    """Confirms every held plan from the bus (`client.confirm`), for tests about something else."""

    def __init__(self, cfg: BusConfig):
        from client.confirm import confirm
        from shared.bus.keys import ROBOT_HELD_KEY
        from shared.contracts.codec import decode
        from shared.contracts.messages import PlanHeld

        self.session = open_session(cfg)
        self.confirmed: set[str] = set()

        def on_held(sample) -> None:
            held = decode(sample.payload.to_bytes(), str(sample.encoding), PlanHeld)
            if held.reason is None and held.command_id not in self.confirmed:
                self.confirmed.add(held.command_id)
                threading.Thread(target=confirm, args=(self.session, held.command_id), daemon=True).start()

        self.subscriber = self.session.declare_subscriber(ROBOT_HELD_KEY, on_held)

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()


@pytest.mark.timeout(BROWSER_TIMEOUT_S)
def test_a_second_viewer_and_one_that_leaves_mid_push_change_nothing(view_system, browser):
    cfg, view, _ = view_system
    confirmer = _AutoConfirm(cfg)
    browser.get(view.url)
    leaving = _browser()
    leaving.get(view.url)
    _wait_page(browser, lambda c: "candidates" in c, 60)
    _wait_page(leaving, lambda c: "candidates" in c, 60)
    assert view.clients() >= 2
    before = view.counts()["decisions"]
    done: dict = {}
    pushing = threading.Thread(target=lambda: done.update(response=push(
        PushRequest(object=ObjectRef(library_id=BOX), direction_deg=-90.0, options=PlannerOptions(method="fixed")), cfg, timeout_s=300.0)))
    pushing.start()
    deadline = time.monotonic() + 120
    while view.counts()["decisions"] == before and time.monotonic() < deadline:
        time.sleep(0.05)
    leaving.quit()  # the browser goes away while the plan waits and the robot moves
    pushing.join(timeout=300)
    confirmer.close()
    assert done["response"].success and confirmer.confirmed
    counts = _wait_page(browser, lambda c: c.get("decisions", 0) > before)
    assert counts["candidates"] == 1  # the fixed pose
    deadline = time.monotonic() + 10
    while view.clients() > 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert view.clients() == 1


@pytest.mark.timeout(BROWSER_TIMEOUT_S)
def test_gd2p_replay_view_plays_a_push_recording_in_the_view(view_system, capsys):
    """The pushes above were recorded with their decisions: `gd2p replay FILE --view` plays one in a view."""
    from cli.main import main
    from visualisation.live import LiveView
    from visualisation.live_replay import ReplayPlayer

    _, _, record_dir = view_system
    recordings = sorted(Path(record_dir).glob("push-*.mcap"), key=lambda p: p.stat().st_mtime)
    if not recordings:
        pytest.skip("no push was recorded (the browser tests did not run)")
    view = LiveView(port=_free_port())
    try:
        player = ReplayPlayer(view, [str(recordings[0])], speed=10.0)
        shown = player.play()
        deadline = time.monotonic() + 20
        while view.counts()["robot_states"] == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        counts = view.counts()
    finally:
        view.close()
    assert shown > 2 and counts["decisions"] >= 1 and counts["candidates"] >= 1 and counts["robot_states"] >= 1
    assert main(["replay", str(recordings[-1]), "--view", "--port", str(_free_port()), "--rate", "10", "--exit"]) == 0
    assert "played" in capsys.readouterr().out


def test_gd2p_up_view_starts_the_view_beside_the_services(zenoh_router, tmp_path):
    """The launcher's view process (`gd2p up --view PORT`) serves the page on its port, and stops with it."""
    import urllib.request

    from deploy.launcher import Launcher

    port = _free_port()
    launcher = Launcher(validators=0, listen=zenoh_router, log_dir=tmp_path, view_port=port)
    launcher._start_view(port)
    assert launcher._view is not None and launcher.view_url == f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        page = b""
        while time.monotonic() < deadline:
            try:
                page = urllib.request.urlopen(launcher.view_url, timeout=2).read()
                break
            except OSError:
                assert launcher._view.poll() is None, (tmp_path / "view.log").read_text()
                time.sleep(0.5)
        assert b"<html" in page.lower(), (tmp_path / "view.log").read_text()
    finally:
        launcher._view.terminate()
        assert launcher._view.wait(timeout=20) is not None


def test_gd2p_eval_view_feeds_the_in_process_system(monkeypatch):
    """`gd2p eval --view`: the evaluation's in-process system hands its decisions and robot states to the view."""
    from evaluation import local_system
    from shared.planning.decision_tap import DecisionTap

    class Sink:
        def __init__(self):
            self.decisions, self.states = [], []

        def show_decision(self, decision):
            self.decisions.append(decision)

        def show_state(self, state):
            self.states.append(state)

    sink = Sink()
    monkeypatch.setattr(local_system, "_view", None)
    local_system.set_view(sink)
    system = local_system.LocalSystem()
    try:
        pipeline = system.pipeline("fake", source=lambda request: None)
        assert isinstance(pipeline.services.sample.__self__, DecisionTap)
        assert pipeline.services.sample.__self__.on_decision == sink.show_decision
        assert system.robot.view is sink
    finally:
        local_system.set_view(None)
        system.close()
    other = local_system.LocalSystem()
    assert other.robot.view is None
    other.close()
