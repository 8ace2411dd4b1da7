"""The live view: a browser view of what the system perceives, considers, chooses and does.

`LiveView` serves a viser scene (viser ships its own web client, so it works with no internet) and is fed
messages — it knows nothing of Zenoh: `cli/view.py` subscribes to the bus and hands them on, an
in-process evaluation calls it directly, `gd2p replay --view` plays a recording into it:

- `show_decision(PushDecision)`: the captured point cloud and its reconstruction (or the library object),
  the candidate hand poses coloured by the critic's score (red: low P(success), green: high; grey when
  unscored), the rolled-out plans' predicted object paths (the chosen one thick and green, the rest thin
  and coloured by L_goal), the chosen plan's palm path, the target and the obstacles;
- `show_state(ExecutionState)`: the robot's joint state (the arm + hand URDF, posed by PyBullet forward
  kinematics) and the object where the robot bridge sees it, with the execution status (stopped, refused);
- `show_track(ObjectTrack)`: the tracked object during execution (its trail);
- `show_held(PlanHeld)`: a plan the bridge holds (`gd2p up --confirm`), with a Confirm button that calls
  `on_confirm(command_id)` (the bus adapter's `client.confirm.confirm`).

Every input is queued and drawn by one thread at most `RATE_HZ` times a second: robot states arrive at the
robot's rate (hundreds a second), so only the latest one is drawn; no caller ever waits for a browser. Any
number of browsers may watch; one that disconnects mid-push changes nothing for the others.
`counts()` (also shown on the page, "Scene" panel) says what is drawn: the browser test reads it there.
"""
from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
import viser

from shared.contracts.messages import (
    ExecutionState,
    ObjectPose,
    ObjectTrack,
    PlanConfirmReply,
    PlanHeld,
    PushDecision,
    PushResponse,
)
from shared.world.obstacles import obstacle_mesh

log = logging.getLogger("gd2p.view")

DEFAULT_PORT = 8090
RATE_HZ = 30.0  # drawing rate: above the tracker's 20 Hz, below a browser's 60 fps
TRAIL_POINTS = 400  # the tracked object's trail (points kept)
CLOUD_RGB = (40, 120, 255)
OBJECT_RGB = (230, 130, 30)
CHOSEN_RGB = (20, 200, 60)
TARGET_RGB = (255, 215, 0)
OBSTACLE_RGB = (200, 30, 30)
ROBOT_RGB = (190, 190, 200)

OnConfirm = Callable[[str], PlanConfirmReply]


def score_colors(scores: np.ndarray | None, n: int) -> np.ndarray:
    """[n, 3] uint8: red (0) to green (1) by score; grey without scores."""
    if scores is None:
        return np.tile(np.array([[150, 150, 150]], dtype=np.uint8), (n, 1))
    s = np.clip(np.nan_to_num(np.asarray(scores, dtype=np.float64)), 0.0, 1.0)[:, None]
    low, high = np.array([[220.0, 40.0, 40.0]]), np.array([[40.0, 220.0, 60.0]])
    colors: np.ndarray = (low * (1 - s) + high * s).astype(np.uint8)
    return colors


def _wxyz(quat_xyzw: Any) -> np.ndarray:
    x, y, z, w = (float(v) for v in quat_xyzw)
    return np.array([w, x, y, z])


@dataclass
class _Inputs:
    """What waits to be drawn: decisions and holds in order, only the latest state and track."""

    events: list[Any] = field(default_factory=list)
    state: ExecutionState | None = None
    tracks: list[ObjectTrack] = field(default_factory=list)


class RobotModel:
    """The arm + hand in the view: one scene frame per link, posed by PyBullet forward kinematics."""

    def __init__(self, server: viser.ViserServer, arm: str, hand: str):
        import pybullet as pb

        from shared.robots.arms import combined_urdf

        self.pb = pb
        self.client = pb.connect(pb.DIRECT)
        self.robot = pb.loadURDF(str(combined_urdf(arm, hand)), useFixedBase=True, physicsClientId=self.client)
        n = pb.getNumJoints(self.robot, physicsClientId=self.client)
        self.joint_index: dict[str, int] = {}
        self.link_names: dict[int, str] = {-1: "base"}
        for j in range(n):
            info = pb.getJointInfo(self.robot, j, physicsClientId=self.client)
            self.joint_index[info[1].decode()] = j
            self.link_names[j] = info[12].decode()
        self.frames: dict[int, Any] = {}
        meshes = 0
        for shape in pb.getVisualShapeData(self.robot, physicsClientId=self.client):
            link, geom, dims, filename, local_pos, local_orn, rgba = shape[1], shape[2], shape[3], shape[4], shape[5], shape[6], shape[7]
            if link not in self.frames:
                self.frames[link] = server.scene.add_frame(f"/robot/{self.link_names[link]}", show_axes=False)
            mesh = _visual_mesh(geom, dims, filename.decode() if isinstance(filename, bytes) else str(filename))
            if mesh is None:
                continue
            color = (int(255 * rgba[0]), int(255 * rgba[1]), int(255 * rgba[2])) if rgba[:3] != (1.0, 1.0, 1.0) else ROBOT_RGB
            server.scene.add_mesh_simple(f"/robot/{self.link_names[link]}/visual{meshes}", mesh.vertices.astype(np.float32),
                                         mesh.faces.astype(np.uint32), color=color, position=tuple(local_pos),
                                         wxyz=_wxyz(local_orn))
            meshes += 1
        self.meshes = meshes

    def pose(self, joint_names: list[str], positions: np.ndarray) -> None:
        pb = self.pb
        for name, q in zip(joint_names, positions, strict=False):
            j = self.joint_index.get(name)
            if j is not None:
                pb.resetJointState(self.robot, j, float(q), physicsClientId=self.client)
        links = [k for k in self.frames if k >= 0]
        states = pb.getLinkStates(self.robot, links, computeForwardKinematics=True, physicsClientId=self.client)
        for k, st in zip(links, states, strict=True):
            frame = self.frames[k]
            frame.position = np.asarray(st[4])
            frame.wxyz = _wxyz(st[5])

    def hand_path(self, joint_names: list[str], positions: np.ndarray, max_points: int = 120) -> np.ndarray:
        """[T, 3] world positions of the hand's base link (the palm) along a joint trajectory."""
        palm = next((j for j, name in self.link_names.items() if "palm" in name), max(self.link_names))
        rows = positions[np.unique(np.linspace(0, len(positions) - 1, min(max_points, len(positions))).astype(int))]
        path = []
        for q in rows:
            for name, value in zip(joint_names, q, strict=False):
                j = self.joint_index.get(name)
                if j is not None:
                    self.pb.resetJointState(self.robot, j, float(value), physicsClientId=self.client)
            state = self.pb.getLinkState(self.robot, palm, computeForwardKinematics=True, physicsClientId=self.client)
            path.append(state[4])
        return np.asarray(path, dtype=np.float64)

    def close(self) -> None:
        try:
            self.pb.disconnect(self.client)
        except Exception:
            pass


def _visual_mesh(geom: int, dims: Any, filename: str) -> trimesh.Trimesh | None:
    """A link's visual mesh (a COLLADA mesh is drawn from its collision STL: trimesh reads no .dae here)."""
    import pybullet as pb

    try:
        if geom == pb.GEOM_MESH:
            path = Path(filename)
            if path.suffix.lower() == ".dae":
                stl = path.parent.parent / "collision" / f"{path.stem}.stl"
                if not stl.exists():
                    return None
                path = stl
            mesh = trimesh.load(str(path), force="mesh")
            mesh.apply_scale(np.asarray(dims[:3], dtype=np.float64))
            return mesh if isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) else None
        shape: trimesh.Trimesh | None = None
        if geom == pb.GEOM_BOX:
            shape = trimesh.creation.box(np.asarray(dims[:3]))
        elif geom == pb.GEOM_SPHERE:
            shape = trimesh.creation.icosphere(2, float(dims[0]))
        elif geom in (pb.GEOM_CYLINDER, pb.GEOM_CAPSULE):
            shape = trimesh.creation.cylinder(float(dims[1]), float(dims[0]))
        return shape
    except Exception as exc:  # a missing asset: the link is drawn without it
        log.debug("no visual mesh for %s: %s", filename, exc)
    return None


class LiveView:
    """A browser view served on `host:port` (see the module docstring)."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", on_confirm: OnConfirm | None = None,
                 title: str = "GD2P live view", preload: tuple[tuple[str, str], ...] = (("panda", "allegro"),)):
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.port = self.server.get_port()
        self.on_confirm = on_confirm
        scene = self.server.scene
        scene.set_up_direction("+z")
        scene.add_grid("/table", width=1.6, height=1.6, cell_size=0.1, section_size=0.5, position=(0.5, 0.0, 0.0))
        self.server.initial_camera.position = (1.25, -0.75, 0.75)
        self.server.initial_camera.look_at = (0.45, 0.0, 0.1)
        gui = self.server.gui
        self._status = gui.add_markdown("**Waiting for a push…**")
        self._held_md = gui.add_markdown("")
        self._confirm = gui.add_button("Confirm held plan", disabled=True, color="green",
                                       hint="Let the robot bridge run the plan it holds (gd2p up --confirm)")
        self._confirm.on_click(lambda _event: self._confirm_clicked())
        with gui.add_folder("Scene"):
            self._counts_md = gui.add_markdown("")
        with gui.add_folder("Decision"):
            self._decision_md = gui.add_markdown("")
        self._controls: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._inputs = _Inputs()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._robots: dict[tuple[str, str], RobotModel] = {}
        self._robot: RobotModel | None = None
        self._object: Any = None
        self._object_key: str | None = None
        self._held: PlanHeld | None = None
        self._trail: list[np.ndarray] = []
        self._counts: dict[str, int] = {"cloud_points": 0, "candidates": 0, "rollouts": 0, "robot_links": 0,
                                         "robot_states": 0, "tracks": 0, "decisions": 0, "obstacles": 0}
        self._confirmations: queue.Queue[str] = queue.Queue()
        self._track_frames: list[tuple[float, float]] = []  # (when drawn, lag behind the newest track's stamp)
        self.server.on_client_connect(lambda _client: self._show_counts())
        # Robots loaded when the view starts (link meshes: a second or two of CPU), not during a push.
        self._preload = preload
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()
        self._confirmer = threading.Thread(target=self._run_confirmations, name="live-view-confirm", daemon=True)
        self._confirmer.start()

    # ------------------------------------------------------------------------------ inputs (any thread)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def show_decision(self, decision: PushDecision) -> None:
        self._put_event(decision)

    def show_held(self, held: PlanHeld) -> None:
        self._put_event(held)

    def show_response(self, response: PushResponse) -> None:
        self._put_event(response)

    def show_state(self, state: ExecutionState) -> None:
        with self._lock:
            self._inputs.state = state
        self._wake.set()

    def show_track(self, track: ObjectTrack) -> None:
        with self._lock:
            self._inputs.tracks.append(track)
            del self._inputs.tracks[:-TRAIL_POINTS]
        self._wake.set()

    def counts(self) -> dict[str, int]:
        """What is drawn now: cloud points, candidate poses, rolled-out plans, robot link meshes, ..."""
        with self._lock:
            return dict(self._counts)

    def track_stats(self) -> dict[str, float]:
        """How the view kept up with the tracker: frames drawn with new tracked poses, their rate over the span
        of those frames (Hz), and the lag from a pose's stamp to its drawing (median and max, s)."""
        with self._lock:
            frames = list(self._track_frames)
            received = self._counts["tracks"]
        if len(frames) < 2:
            return {"frames": float(len(frames)), "tracks": float(received)}
        span = frames[-1][0] - frames[0][0]
        lags = sorted(lag for _, lag in frames)
        return {"frames": float(len(frames)), "tracks": float(received), "rate_hz": (len(frames) - 1) / max(span, 1e-9),
                "lag_median_s": lags[len(lags) // 2], "lag_max_s": lags[-1]}

    def reset_track_stats(self) -> None:
        with self._lock:
            self._track_frames = []

    def clients(self) -> int:
        return len(self.server.get_clients())

    def show_comparison(self, decisions: dict[str, PushDecision]) -> Any:
        """Two or more decisions of the same push (e.g. `gd2p replay --resim --view`: as recorded, and decided
        again): a selector in the panel switches which one is drawn; the first is drawn now. The selector."""
        if not decisions:
            raise ValueError("show_comparison needs at least one decision")
        names = tuple(decisions)
        selector = self.server.gui.add_dropdown("Decision", options=names, initial_value=names[0])
        selector.on_update(lambda _event: self.show_decision(decisions[str(selector.value)]))
        self.show_decision(decisions[names[0]])
        return selector

    def add_markdown(self, text: str) -> Any:
        """A panel of the caller's own (e.g. the replay's clock)."""
        return self.server.gui.add_markdown(text)

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._confirmations.put("")
        self._thread.join(timeout=5)
        for robot in self._robots.values():
            robot.close()
        self.server.stop()

    def _put_event(self, event: Any) -> None:
        with self._lock:
            self._inputs.events.append(event)
        self._wake.set()

    # ------------------------------------------------------------------------------ drawing (one thread)

    def _run(self) -> None:
        period = 1.0 / RATE_HZ
        for arm, hand in self._preload:
            try:
                self._robot_for(arm, hand)
            except Exception:
                log.exception("live view: could not load the %s + %s", arm, hand)
        while not self._stop.is_set():
            self._wake.wait(timeout=0.5)
            self._wake.clear()
            with self._lock:
                inputs, self._inputs = self._inputs, _Inputs()
            try:
                self._draw(inputs)
            except Exception:
                log.exception("live view: could not draw")
            self._stop.wait(period)

    def _draw(self, inputs: _Inputs) -> None:
        for event in inputs.events:
            if isinstance(event, PushDecision):
                self._draw_decision(event)
            elif isinstance(event, PlanHeld):
                self._draw_held(event)
            elif isinstance(event, PushResponse):
                self._draw_response(event)
        if inputs.tracks:
            self._draw_tracks(inputs.tracks)
        if inputs.state is not None:
            self._draw_state(inputs.state)
        self._show_counts()

    def _set_count(self, **values: int) -> None:
        with self._lock:
            self._counts.update(values)

    def _show_counts(self) -> None:
        c = self.counts()
        self._counts_md.content = (
            f"cloud points: **{c['cloud_points']}**  \ncandidates: **{c['candidates']}**  \n"
            f"rolled-out plans: **{c['rollouts']}**  \nrobot links: **{c['robot_links']}**  \n"
            f"robot states drawn: **{c['robot_states']}**  \ntracked poses: **{c['tracks']}**  \n"
            f"decisions: **{c['decisions']}**  \nobstacles: **{c['obstacles']}**")

    def _robot_for(self, arm: str, hand: str) -> RobotModel:
        key = (arm, hand)
        if key not in self._robots:
            for other in self._robots.values():
                for frame in other.frames.values():
                    frame.visible = False
            self._robots[key] = RobotModel(self.server, arm, hand)
        robot = self._robots[key]
        for frame in robot.frames.values():
            frame.visible = True
        self._robot = robot
        self._set_count(robot_links=robot.meshes)
        return robot

    def _draw_decision(self, d: PushDecision) -> None:
        scene = self.server.scene
        T_pos = np.asarray(d.frame.object_pose.position)
        obj_key = d.object.object_id
        if obj_key != self._object_key:
            self._object_key = obj_key
            self._draw_object(d)
        self._place_object(d.frame.object_pose)
        self._trail = []
        scene.add_point_cloud("/track", np.zeros((1, 3), np.float32), (255, 120, 0), point_size=0.004, visible=False)
        # Candidates: palm positions coloured by the critic, with a short tick along the palm's normal.
        poses = d.candidates_world.to_numpy().astype(np.float64)
        scores = None if d.critic_scores is None else d.critic_scores.to_numpy()
        colors = score_colors(scores, len(poses))
        if len(poses):
            scene.add_point_cloud("/candidates/palms", poses[:, :3].astype(np.float32), colors, point_size=0.008,
                                  point_shape="circle")
            normals = _palm_normals(poses)
            segments = np.stack([poses[:, :3], poses[:, :3] + 0.03 * normals], axis=1)
            scene.add_line_segments("/candidates/normals", segments.astype(np.float32),
                                    np.repeat(colors[:, None, :], 2, axis=1), thickness=1.5, thickness_units="screen")
        # Rollouts: each plan's predicted object path; the chosen one thick and green.
        for name in list(self._controls.get("rollout_nodes", [])):
            name.remove()
        nodes = []
        goals = [r.goal_error_m for r in d.rollouts if r.goal_error_m is not None]
        worst = max(goals) if goals else 1.0
        for i, r in enumerate(d.rollouts):
            if r.object_path is None or r.object_path.positions.shape[0] < 2:
                continue
            path = r.object_path.positions.to_numpy().astype(np.float32)
            chosen = i == d.chosen
            if chosen:
                color = CHOSEN_RGB
            else:
                g = (r.goal_error_m or worst) / max(worst, 1e-6)
                color = (int(80 + 150 * g), 80, int(230 - 150 * g))
            nodes.append(scene.add_spline_catmull_rom(f"/rollouts/{i}", path, color=color,
                                                      thickness=6.0 if chosen else 2.0, thickness_units="screen"))
        self._controls["rollout_nodes"] = nodes
        # Target and obstacles.
        yaw = d.frame.yaw_rad()
        if d.distance_m is not None:
            target = T_pos[:2] + d.distance_m * np.array([math.cos(yaw), math.sin(yaw)])
            scene.add_icosphere("/target", radius=0.015, color=TARGET_RGB, position=(float(target[0]), float(target[1]), 0.015))
            scene.add_line_segments("/direction", np.array([[[T_pos[0], T_pos[1], 0.002], [target[0], target[1], 0.002]]],
                                                           dtype=np.float32), TARGET_RGB, thickness=3.0,
                                    thickness_units="screen")
        for node in self._controls.get("obstacle_nodes", []):
            node.remove()
        self._controls["obstacle_nodes"] = [
            scene.add_mesh_simple(f"/obstacles/{k}", obstacle.vertices.astype(np.float32), obstacle.faces.astype(np.uint32),
                                  color=OBSTACLE_RGB, opacity=0.8)
            for k, obstacle in enumerate(map(obstacle_mesh, d.obstacles))]
        # The chosen plan: the robot at its first waypoint (it moves with the states).
        robot = self._robot_for(d.arm, d.hand)
        waypoints = d.plan.positions.to_numpy()
        palm = robot.hand_path(d.plan.joint_names, waypoints)
        if len(palm) >= 2:
            scene.add_spline_catmull_rom("/chosen/hand_path", palm.astype(np.float32), color=CHOSEN_RGB, thickness=2.5,
                                         thickness_units="screen")
        robot.pose(d.plan.joint_names, waypoints[0])
        chosen_score = ""
        if d.chosen is not None:
            r = d.rollouts[d.chosen]
            chosen_score = (f"; chosen plan {d.chosen + 1}: L_goal {r.goal_error_m * 100:.1f} cm"
                            if r.goal_error_m is not None else f"; chosen plan {d.chosen + 1}")
        best = f", best critic score {float(np.max(scores)):.2f}" if scores is not None and len(scores) else ""
        self._decision_md.content = (
            f"request `{(d.request_id or '-')[:12]}`, push {d.push_index + 1} ({d.hand} + {d.arm})  \n"
            f"{len(poses)} candidates{best}  \n{len(d.rollouts)} plans rolled out{chosen_score}")
        kind = "correction / next push" if d.push_index else "push"
        self._status.content = f"**Planned {kind} {d.push_index + 1}**: sending the chosen plan to the robot"
        with self._lock:
            decisions = self._counts["decisions"] + 1
        self._set_count(candidates=len(poses), rollouts=len(d.rollouts), obstacles=len(d.obstacles),
                        decisions=decisions)

    def _draw_object(self, d: PushDecision) -> None:
        from shared.world.object_refs import captured_object, load_object_ref

        scene = self.server.scene
        cloud = d.object.point_cloud
        if cloud is not None:
            points = cloud.to_numpy().astype(np.float32)
            scene.add_point_cloud("/cloud", points, CLOUD_RGB, point_size=0.0018, point_shape="circle")
            self._set_count(cloud_points=len(points))
            mesh = captured_object(d.object).model.mesh
        else:
            scene.add_point_cloud("/cloud", np.zeros((1, 3), np.float32), CLOUD_RGB, visible=False)
            self._set_count(cloud_points=0)
            mesh = load_object_ref(d.object).mesh
        self._object = scene.add_mesh_simple("/object", mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32),
                                             color=OBJECT_RGB)

    def _place_object(self, pose: ObjectPose) -> None:
        if self._object is not None:
            self._object.position = np.asarray(pose.position)
            self._object.wxyz = _wxyz(pose.quaternion_xyzw)

    def _draw_tracks(self, tracks: list[ObjectTrack]) -> None:
        self._place_object(tracks[-1].pose)
        self._trail += [np.asarray(t.pose.position) for t in tracks]
        self._trail = self._trail[-TRAIL_POINTS:]
        self.server.scene.add_point_cloud("/track", np.array(self._trail, dtype=np.float32), (255, 120, 0),
                                          point_size=0.004, point_shape="circle")
        now = time.time()
        with self._lock:
            self._counts["tracks"] += len(tracks)
            self._track_frames.append((now, now - tracks[-1].stamp))
            del self._track_frames[:-10_000]

    def _draw_state(self, state: ExecutionState) -> None:
        if self._robot is None:
            return
        self._robot.pose(state.joint_names, state.positions.to_numpy())
        if state.object_pose is not None:
            self._place_object(state.object_pose)
        with self._lock:
            self._counts["robot_states"] += 1
        verdict = {"executing": "Executing", "done": "Done", "stopped": "**Stopped**", "refused": "**Refused**",
                   "error": "**Error**"}.get(state.status)
        if verdict is not None:
            message = f": {state.message}" if state.message else ""
            timing = f" (t = {state.plan_time_s:.2f} s)" if state.plan_time_s is not None else ""
            self._status.content = f"{verdict}{timing}{message}"

    def _draw_held(self, held: PlanHeld) -> None:
        if held.reason is not None:  # the hold ended
            if self._held is not None and self._held.command_id == held.command_id:
                self._held = None
                self._confirm.disabled = True
            self._held_md.content = f"Held plan `{held.command_id[:12]}`: {held.reason}"
            return
        self._held = held
        left = max(0.0, held.expires_at - time.time())
        self._held_md.content = (f"**A plan waits for your confirmation** (`{held.command_id[:12]}`, "
                                 f"{held.plan.positions.shape[0]} waypoints, {left:.0f} s left)")
        self._confirm.disabled = self.on_confirm is None
        self._status.content = "**Held**: the robot waits for an operator's confirmation"
        robot = self._robot_for(held.plan.arm, held.plan.hand)
        robot.pose(held.plan.joint_names, held.plan.positions.to_numpy()[0])

    def _draw_response(self, response: PushResponse) -> None:
        r = response.result
        steps = len(response.steps)
        stopped = sum(1 for s in response.steps if s.stopped)
        corrected = sum(1 for s in response.steps if s.reason)
        self._status.content = (f"**{'Success' if response.success else 'Missed'}**: {steps} push(es), "
                                f"{corrected} correction(s), {stopped} stopped; {r.position_error_m * 100:.1f} cm "
                                f"from the target")

    # ------------------------------------------------------------------------------ confirm

    def _confirm_clicked(self) -> None:
        held = self._held
        if held is None or self.on_confirm is None:
            return
        self._confirm.disabled = True
        self._confirmations.put(held.command_id)

    def _run_confirmations(self) -> None:
        while not self._stop.is_set():
            command_id = self._confirmations.get()
            if not command_id or self.on_confirm is None:
                continue
            try:
                reply = self.on_confirm(command_id)
                text = "confirmed: the robot runs it" if reply.accepted else f"not confirmed: {reply.reason}"
            except Exception as exc:  # no bridge answered, ...
                text = f"not confirmed: {exc}"
            self._held_md.content = f"Held plan `{command_id[:12]}` {text}"
            if self._held is not None and self._held.command_id == command_id:
                self._held = None


def _palm_normals(poses: np.ndarray) -> np.ndarray:
    """The third column of each pose's rotation (r6: the first two columns): the palm's normal direction."""
    a, b = poses[:, 3:6], poses[:, 6:9]
    a = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-9)
    b = b - (a * b).sum(1, keepdims=True) * a
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-9)
    normals: np.ndarray = np.cross(a, b)
    return normals
