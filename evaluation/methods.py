"""Experiments "methods" (Allegro on the Panda, GD2P against its baselines) and "leap" (LEAP on the xArm7).

Both follow the protocol of `push_protocol.py` in an execution world (`--world real|exact`) and report
like the paper's appendix table: per object and direction, the successful trials out of the trial
count for each method ("–": no trial had a kinematically feasible plan), and the averages over the
procedural ("3D") objects, the everyday ("DO") objects and all 14, each with its 95% interval
clustered by object (`stats.py`). Results go to `<out>/<experiment>-<world>[-cameraN][-split][-tag]/`; a
`real` report shows the same methods' `exact` rates beside its own when `<out>` holds the `exact` run of the
same name (objects, perception, tag) made with the same pose models.
"""
from __future__ import annotations

import json
import math
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from evaluation import push_protocol as protocol
from evaluation.report import SUMMARY_FILE, markdown_table, write_experiment
from evaluation.stats import difference_interval, mean_interval, success_interval
from evaluation.store import SETTINGS_FILE, ResultStore
from evaluation.tasks import NEIGHBOUR_MOVED_M, SHAPE_TASK_OBJECTS, SHAPE_TASKS, TASK_CRITERIA
from shared.execution.robots import TrackingMode
from shared.world.push_outcome import rollout_predicts_success
from shared.world.sim.world import WorldLevel

QUICK_OBJECTS = ("proc-box-001", "pb-mug")
# For tuning (`--split val`): two val objects of each procedural family and two random shapes, as many
# as the test objects. Settings are chosen on these; the test objects only report.
VAL_OBJECTS = ("proc-box-010", "proc-box-017", "proc-cylinder-006", "proc-cylinder-013", "proc-cone-006",
               "proc-cone-007", "proc-ellipsoid-011", "proc-ellipsoid-019", "proc-capsule-016", "proc-capsule-017",
               "proc-hull-006", "proc-hull-012", "rnd-002", "rnd-004")
# A whole shape family that no model trains on (`--split unseen`, reported beside the 14): the first
# procedural mugs of the test split (catalog.UNSEEN_FAMILIES; pb-mug, one of the 14, is of it too).
UNSEEN_OBJECTS = ("proc-mug-000", "proc-mug-001", "proc-mug-002", "proc-mug-003", "proc-mug-004", "proc-mug-005")
OBJECT_SETS = ("test", "val", "unseen", "final")  # "test": the development split (`--split dev`)
# The records of the committed `exact` runs made before execution worlds existed (results/methods, results/leap):
# the same trials, under the methods' earlier names.
LEGACY_EXACT_NAMES = {"gd2p-no-ranking": "gd2p-random"}
# Compared in the report's differences: GD2P against each baseline with the same pipeline stages.
COMPARISONS = (("gd2p", "nearest"), ("gd2p", "fixed"), ("gd2p", "gd2p-unranked"), ("gd2p", "nearest-ranked"),
               ("gd2p-random", "nearest"), ("gd2p-robust", "gd2p"), ("gd2p-corrected", "gd2p"),
               ("gd2p-a30", "gd2p"), ("gd2p-corrected", "nearest-corrected"), ("gd2p-corrected", "fixed-corrected"),
               ("gd2p-closed", "gd2p"), ("gd2p-closed", "gd2p-corrected"), ("gd2p-closed-tight", "gd2p-corrected"),
               ("gd2p-closed-3cm", "gd2p-corrected"), ("gd2p-closed-loose", "gd2p-corrected"),
               ("gd2p-closed-looser", "gd2p-corrected"), ("gd2p-closed", "fixed-corrected"),
               ("gd2p-closed", "nearest-corrected"), ("gd2p-closed-critic-p24", "gd2p-closed"))
# The closed-loop experiment (`gd2p eval closed-loop`): open loop, corrective pushes after a push, and
# pushes watched and stopped mid-way, run together on one commit; the last in the critic's order (the planner's default).
WORLD_TEXT = {  # how a report describes the world its trials executed in
    "real": "each trial executes in physics the planner does not know",
    "mujoco": "each trial executes in MuJoCo, whose contact model and drawn physics (the hand's included) the planner "
              "does not know: it predicts in PyBullet",
    "exact": "each trial executes in the planner's own world",
}
DEFAULT_METHOD = "gd2p-closed-critic-p24"  # the planner's default (methods.yaml: it changes nothing)
CLOSED_LOOP_METHODS = ("gd2p", "gd2p-corrected", "gd2p-closed", "gd2p-closed-critic-p24")


@dataclass(frozen=True)
class Protocol:
    name: str
    title: str
    hand: str
    methods: tuple[str, ...]
    objects: tuple[str, ...]
    directions: tuple[float, ...]
    trials: int
    world: WorldLevel = "real"
    cameras: int = 0  # 0: the system is told the mesh; 1-3: it sees the object with that many depth cameras
    # "test": the development split's 14 (`--split dev`); "val": the tuning objects; "unseen": a whole never-trained
    # family of the test split; "final": the final split (evaluation/final_run.py, once per release)
    split: str = "test"
    tag: str | None = None  # names a run of the same protocol with other models or code (`--tag`)
    tracking: TrackingMode = "image"  # how the robot sees the object while it pushes: rendered images, or "truth"
    task: str = "paper"  # what each trial asks (push_protocol.TASKS)

    @property
    def directory_name(self) -> str:
        return (f"{self.name}-{self.world}" + (f"-camera{self.cameras}" if self.cameras else "")
                + ("-truthtrack" if self.tracking == "truth" else "")
                + (f"-{self.split}" if self.split != "test" else "") + (f"-{self.task}" if self.task != "paper" else "")
                + (f"-{self.tag}" if self.tag else ""))

    def episodes(self, methods: Sequence[str] | None = None) -> list[protocol.Episode]:
        """The protocol's trials (of `methods`, default its own)."""
        return protocol.episodes(self.methods if methods is None else methods, self.hand, self.objects,
                                 self.directions, self.trials, self.world, self.cameras, self.split, self.tracking,
                                 self.task)

    def settings(self) -> dict[str, Any]:
        """What a resumed run must share with the records on disk. Not the trial count nor the methods:
        trial k of a method is the same episode whatever else runs, so a run can later be extended."""
        settings: dict[str, Any] = {"hand": self.hand, "arm": protocol.ROBOTS[self.hand], "world": self.world,
                    "objects": list(self.objects), "directions_deg": list(self.directions),
                    "object_xy": list(protocol.OBJECT_XY), "placement_noise_m": protocol.PLACEMENT_NOISE_M,
                    "placement_noise_deg": protocol.PLACEMENT_NOISE_DEG, "push_distance_m": protocol.PUSH_DISTANCE_M,
                    # the robot's tracker, and cameras off their calibration by the world's draw: records made before
                    # either (truth-plus-noise tracking, exact cameras) do not mix with these
                    "tracking": self.tracking, "camera_calibration_errors": True,
                    # the poses' models: a run resumed after the shipped checkpoint or index changed is refused
                    "pose_models": protocol.pose_model_ids(self.hand)}
        if self.task != "paper":  # the paper's runs were made before tasks, and keep their settings
            settings["task"] = self.task
        if self.split == "final":  # the frozen objects the run measured, and that they are the final split's
            from shared.world.objects.final_split import manifest_sha256

            settings.update(split="final", final_manifest_sha256=manifest_sha256())
        return {**settings, "cameras": self.cameras} if self.cameras else settings


DEFAULT_CAMERAS: dict[str, int] = {
    # `real`, the evaluation's default, hands the system what a robot has: the object as depth cameras
    # capture it, three views as the paper's test geometry came from multi-view captures. `exact` keeps
    # the behaviour before execution worlds: told the true mesh where it truly stands.
    "real": 3,
    "mujoco": 3,
    "exact": 0,
}


def protocol_for(name: str, quick: bool, trials: int | None = None, world: WorldLevel = "real",
                 methods: Sequence[str] | None = None, cameras: int = 0, split: str = "test",
                 tag: str | None = None, task: str = "paper") -> Protocol:
    if split not in OBJECT_SETS:
        raise ValueError(f"unknown split {split!r}; known: {', '.join(OBJECT_SETS)}")
    objects: tuple[str, ...]
    if split == "val":
        objects = VAL_OBJECTS[:2] if quick else VAL_OBJECTS
    elif split == "unseen":
        objects = UNSEEN_OBJECTS[:2] if quick else UNSEEN_OBJECTS
    elif split == "final":  # every final object, hash-checked against the committed manifest
        from shared.world.objects.final_split import load_final_split

        final = tuple(load_final_split())
        objects = (final[0], final[-1]) if quick else final
    else:
        objects = QUICK_OBJECTS if quick else protocol.PROCEDURAL_OBJECTS + protocol.EVERYDAY_OBJECTS
    trials = trials or (1 if quick else protocol.TRIALS)
    on_val = {"val": ", val objects (tuning)", "unseen": ", a never-trained shape family (mugs)",
              "final": ", the final split"}.get(split, "")
    on_val += f" ({tag})" if tag else ""
    if name == "methods":
        return Protocol(name, f"Methods × objects × directions (Allegro + Panda), world `{world}`{on_val}", "allegro",
                        tuple(methods or protocol.DEFAULT_METHODS), objects, protocol.DIRECTIONS_DEG, trials, world, cameras,
                        split, tag)
    if name == "leap":
        return Protocol(name, f"Hand morphology: LEAP + xArm7, world `{world}`{on_val}", "leap",
                        tuple(methods or ("gd2p",)), objects, protocol.DIRECTIONS_DEG, trials, world, cameras, split,
                        tag)
    if name == "closed-loop":
        title = f"Closed loop (Allegro + Panda), world `{world}`{on_val}"
        if task != "paper":
            title = f"Task `{task}`: " + title
        if task in SHAPE_TASKS:
            # the final split measures every object of the class it holds (5 small ones, more of the others)
            count = 2 if quick else None if split == "final" else SHAPE_TASK_OBJECTS
            objects = protocol.shape_task_objects(task, split, count)
        return Protocol(name, title, "allegro", tuple(methods or CLOSED_LOOP_METHODS), protocol.task_objects(task, objects),
                        protocol.DIRECTIONS_DEG, trials, world, cameras, split, tag, task=task)
    if task != "paper":
        raise ValueError(f"the {name} experiment asks the paper's task; tasks are measured by closed-loop (and suite)")
    raise ValueError(f"unknown protocol {name!r}")


def run_protocol(name: str, out: Path, quick: bool, workers: int, trials: int | None = None,
                 world: WorldLevel = "real", methods: Sequence[str] | None = None, cameras: int = 0,
                 split: str = "test", tag: str | None = None,
                 worker_init: Callable[[str], None] | None = None, tracking: TrackingMode = "image",
                 task: str = "paper") -> Path:
    """One run of a trial protocol into `<out>/<directory_name>/`; `worker_init` replaces the workers' initializer
    (the final split's, evaluation/final_run.py, opens its access in every worker)."""
    spec = replace(protocol_for(name, quick, trials, world, methods, cameras, split, tag, task), tracking=tracking)
    directory = Path(out) / spec.directory_name
    settings = spec.settings()  # hashes the pose models' files: once per run
    store = ResultStore(directory, settings)
    started = time.perf_counter()
    todo = spec.episodes()
    pending = [e for e in todo if not store.done(e.key)]
    protocol.run_in_workers(pending, protocol.run_episode, store, workers, Path(out) / "grasp_poses", label=name,
                            initializer=worker_init)
    spec = with_stored_methods(spec, store)
    records = [store.records[e.key] for e in spec.episodes()]
    summary = summarise(records, spec)
    body = report_body(records, spec, summary, exact_rates(Path(out), spec, settings["pose_models"]))
    _plot(records, spec, directory / "success_by_direction.png")
    body += "\n![success by method and direction](success_by_direction.png)\n"
    return write_experiment(directory, spec.title, body, {"settings": {**settings, "trials": spec.trials,
                                                                       "methods": list(spec.methods)},
                                                          **summary}, time.perf_counter() - started, quick, records)


def with_stored_methods(spec: Protocol, store: ResultStore) -> Protocol:
    """`spec` reporting every method the run's store holds all of `spec`'s trials of, not only those asked this
    time: a run extended by another method (`--methods nearest` into a finished run) keeps the others in its report."""
    def complete(method: str) -> bool:
        return all(store.done(e.key) for e in spec.episodes((method,)))
    stored = {record["method"] for record in store.records.values()}
    extra = [m for m in protocol.METHODS if m in stored and m not in spec.methods and complete(m)]
    return replace(spec, methods=(*spec.methods, *extra))


def run_methods(out: Path, quick: bool = False, workers: int = 2, trials: int | None = None,
                world: WorldLevel = "real", methods: Sequence[str] | None = None, cameras: int = 0,
                split: str = "test", tag: str | None = None, worker_init: Callable[[str], None] | None = None,
                tracking: TrackingMode = "image") -> Path:
    return run_protocol("methods", out, quick, workers, trials, world, methods, cameras, split, tag, worker_init, tracking)


def run_leap(out: Path, quick: bool = False, workers: int = 2, trials: int | None = None,
             world: WorldLevel = "real", methods: Sequence[str] | None = None, cameras: int = 0,
             split: str = "test", tag: str | None = None, worker_init: Callable[[str], None] | None = None,
             tracking: TrackingMode = "image") -> Path:
    return run_protocol("leap", out, quick, workers, trials, world, methods, cameras, split, tag, worker_init, tracking)


def run_closed_loop(out: Path, quick: bool = False, workers: int = 2, trials: int | None = None,
                    world: WorldLevel = "real", methods: Sequence[str] | None = None, cameras: int = 0,
                    split: str = "test", tag: str | None = None, worker_init: Callable[[str], None] | None = None,
                    tracking: TrackingMode = "image", tasks: Sequence[str] = ("paper",)) -> Path:
    """The closed-loop run of one task (`tasks`: one of TASKS; the suite runs them all and reports them together)."""
    if len(tasks) != 1:
        raise ValueError(f"closed-loop runs one task at a time, not {', '.join(tasks) or 'none'}; the suite runs several")
    return run_protocol("closed-loop", out, quick, workers, trials, world, methods, cameras, split, tag, worker_init,
                        tracking, task=tasks[0])


def exact_rates(out: Path, spec: Protocol, pose_models: dict[str, str]) -> dict[str, dict[str, Any]]:
    """Per method, the success rate of the same protocol under `exact` found in `out` (for a `real` report):
    the run named as this one with `exact` for `real` and told the mesh (`exact` is the planner's own world:
    its object and pose, so a camera run's `exact` is the mesh-told one) if its trials used the same pose
    models, else, for an untagged mesh-told run on the test objects, the run made before execution worlds
    existed (`<name>`, the models then shipped)."""
    if spec.world == "exact":
        return {}
    candidates: list[tuple[Path, dict[str, str]]] = [(out / replace(spec, world="exact", cameras=0).directory_name, {})]
    if not spec.cameras and spec.split == "test" and not spec.tag:
        candidates.append((out / spec.name, LEGACY_EXACT_NAMES))
    for directory, names in candidates:
        path = directory / SUMMARY_FILE
        if not path.is_file() or _other_pose_models(directory, pose_models):
            continue
        summary = json.loads(path.read_text())
        methods = {names.get(m, m): v for m, v in summary.get("methods", {}).items()}
        code = summary.get("code", "code before commit ids were recorded")
        return {m: {"rate": v["success_rate"],
                    "source": f"results/{directory.name}, {v['trials']} trials per method, {code}"}
                for m, v in methods.items()}
    return {}


def _other_pose_models(directory: Path, pose_models: dict[str, str]) -> bool:
    """Whether the run in `directory` recorded pose models other than `pose_models` (a run made before the
    models were recorded is taken as it stands)."""
    path = directory / SETTINGS_FILE
    recorded = json.loads(path.read_text()).get("pose_models") if path.is_file() else None
    return recorded is not None and recorded != pose_models


# ------------------------------------------------------------------------------------------ tables

def _rate(records: Sequence[dict[str, Any]]) -> float:
    return sum(r["success"] for r in records) / len(records) if records else float("nan")


def lost_track(record: dict[str, Any]) -> bool:
    """Whether the trial ended on the image tracker losing the object (the push stopped on a lost track, or no pose
    of the object after it)."""
    return record.get("error_code") == "lost" or any("lost the object" in note for note in record.get("notes") or [])


def failure_cause(record: dict[str, Any]) -> str | None:
    """Why a trial failed: "tracking" (the image tracker lost the object), "planning" (no feasible plan, or another
    error), "pose quality" (the chosen plan's
    own rollout predicted the failure: nothing better was found), "unpredicted" (a random choice has no
    rollout to tell); a plan predicted to succeed is split by its replays (`push_protocol.replay_failure`)
    into "prediction" (it fails in the planner's own world too: rollout and robot parted), "perception"
    (it fails on the true object where it truly stood, in nominal physics: the told pose or the
    reconstruction) and "physics" (it succeeds there: the execution world's physics), or is "world gap"
    where no replay was made (trials before replays existed, and requests of several pushes). None for
    a success; "wall contact" when the robot touched a wall (the wall and corner tasks), "neighbour moved" when the clutter task's
    neighbour was moved."""
    if record["success"]:
        return None
    if lost_track(record):
        return "tracking"
    if record["outcome"] != "failure":
        return "planning"
    if record.get("robot_touched_wall"):
        return "wall contact"
    if max(record.get("neighbours_moved_m") or [0.0]) > NEIGHBOUR_MOVED_M:
        return "neighbour moved"
    predicted = record.get("predicted_l_goal")
    if predicted is None:
        return "unpredicted"
    if not rollout_predicts_success(predicted):
        return "pose quality"
    replayed = record.get("replayed")
    if replayed is None:
        return "world gap"
    if not replayed["planner_world"]:
        return "prediction"
    return "physics" if replayed["true_object"] else "perception"


FAILURE_CAUSES = {
    "tracking": "the image tracker lost the object: the push was stopped and backed out, or it gave no pose after it",
    "planning": "no feasible plan (or another error)",
    "wall contact": "the robot touched a wall (the wall and corner tasks)",
    "neighbour moved": "a neighbour was moved more than 1 cm (the clutter task)",
    "pose quality": "the executed plan's own rollout predicted the failure",
    "prediction": "predicted to succeed, and the same plan fails in the planner's own world too (rollout and robot parted)",
    "perception": "predicted to succeed, and the same plan fails on the true object where it truly stood, in nominal "
                  "physics (the told pose or the reconstruction was off)",
    "physics": "predicted to succeed, and the same plan succeeds on the true object in nominal physics (the execution "
               "world's friction, mass, centre of mass or controller made it fail)",
    "world gap": "predicted to succeed in the planner's world, failed in the execution world, not replayed (perception "
                 "or physics; trials before replays, requests of several pushes)",
    "unpredicted": "a random choice, no rollout",
}


def summarise(records: Sequence[dict[str, Any]], spec: Protocol) -> dict[str, Any]:
    """Per method: success rates (all objects with the clustered interval, procedural, everyday, per
    direction), outcome and failure-cause counts; GD2P's differences to its baselines."""
    by_method: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        by_method[r["method"]].append(r)
    methods = {}
    for method in spec.methods:
        rs = by_method[method]
        outcomes: dict[str, int] = defaultdict(int)
        causes: dict[str, int] = defaultdict(int)
        for r in rs:
            outcomes[r["outcome"]] += 1
            cause = failure_cause(r)
            if cause is not None:
                causes[cause] += 1
        feasible = [r for r in rs if r["outcome"] != "infeasible"]
        methods[method] = {
            "success_rate": _rate(rs),
            "interval_95": success_interval(rs).as_dict(),
            "feasible_success_rate": _rate(feasible),  # pose quality apart from the arm's reach
            "procedural_success_rate": _rate([r for r in rs if r["object_id"].startswith("proc-")]),
            "everyday_success_rate": _rate([r for r in rs if r["object_id"].startswith("pb-")]),
            "by_direction": {f"{d:g}": _rate([r for r in rs if r["direction_deg"] == d]) for d in spec.directions},
            "outcomes": dict(outcomes),
            "failure_causes": dict(causes),
            "trials": len(rs),
            "median_seconds": sorted(r["seconds"] for r in rs)[len(rs) // 2] if rs else None,
            "corrections_per_trial": mean_interval(rs, corrections).as_dict(),
            "stopped_per_trial": mean_interval(rs, lambda r: len(r.get("stopped_pushes", ()))).as_dict(),
        }
    differences = {f"{a} - {b}": difference_interval(by_method[a], by_method[b]).as_dict()
                   for a, b in COMPARISONS if a in spec.methods and b in spec.methods}
    return {"methods": methods, "differences_95": differences}


def corrections(record: dict[str, Any]) -> float:
    """Pushes made after the first (corrective pushes) in a trial."""
    return float(record.get("pushes", 1) - 1) if record["outcome"] in ("success", "failure") else 0.0


def _corrects(spec: Protocol) -> bool:
    """Whether any method of `spec` may push more than once (the report then counts the pushes)."""
    return any(protocol.METHODS[m].options.corrections for m in spec.methods)


def _cell(records: Sequence[dict[str, Any]]) -> str:
    if all(r["outcome"] == "infeasible" for r in records):
        return "–"
    return str(sum(r["success"] for r in records))


def _share(rate: float, spec: str = ".1%") -> str:
    """A rate as text; "–" when there was nothing to count (e.g. no everyday object among val objects)."""
    return "–" if math.isnan(rate) else format(rate, spec)


def _per_trial(interval: dict[str, float]) -> str:
    return f"{interval['value']:.2f} [{interval['low']:.2f}, {interval['high']:.2f}]"


def method_label(method: str) -> str:
    return protocol.METHODS[method].label


def report_body(records: Sequence[dict[str, Any]], spec: Protocol, summary: dict[str, Any],
                exact: dict[str, dict[str, Any]] | None = None) -> str:
    cells: dict[tuple[str, str, float], list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        cells[(r["method"], r["object_id"], r["direction_deg"])].append(r)
    headers = ["object"] + [f"{method_label(m)} {d:g}°" for m in spec.methods for d in spec.directions]
    rows = [[o] + [_cell(cells[(m, o, d)]) for m in spec.methods for d in spec.directions] for o in spec.objects]
    averages = summary["methods"]
    for label, key in (("3D avg.", "procedural_success_rate"), ("DO avg.", "everyday_success_rate"),
                       ("All avg.", "success_rate")):
        rows.append([f"**{label}**"] + [_share(averages[m][key], ".2f") if d == spec.directions[0] else ""
                                        for m in spec.methods for d in spec.directions])
    text = (f"World `{spec.world}` (`shared.world.sim.world`): "
            + (WORLD_TEXT[spec.world] + ("" if spec.cameras or spec.world == "exact" else ", with the object off the told pose")
               + ". ")
            + (f"Task `{spec.task}`: {TASK_CRITERIA[spec.task]}. " if spec.task != "paper" else "")
            + (f"The system never sees the object's mesh: it receives the point cloud {spec.cameras} simulated depth "
               "camera(s) capture of it and plans around its own reconstruction; the robot pushes the true object. "
               if spec.cameras else "The system is told the object's mesh. ")
            + f"{spec.hand} hand on the {protocol.ROBOTS[spec.hand]}; objects resting at "
            f"({protocol.OBJECT_XY[0]:.2f}, {protocol.OBJECT_XY[1]:.2f}) m, re-placed for each trial (±"
            f"{protocol.PLACEMENT_NOISE_M * 100:.0f} cm, ±{protocol.PLACEMENT_NOISE_DEG:.0f}°); directions "
            f"{', '.join(f'{d:g}°' for d in spec.directions)} (180° pulls toward the robot); a "
            f"{protocol.PUSH_DISTANCE_M:.2f} m push; {spec.trials} trial(s) per cell. Cells: successful trials out of "
            f"{spec.trials}; – : no kinematically feasible plan in any trial (counted as failures).\n\n")
    text += markdown_table(headers, rows)
    text += "\n### Averages\n\nAll: the pooled rate and its 95% interval clustered by object (bootstrap over objects)"
    text += (f"; exact: the same protocol in the planner's own world{', told the mesh' if spec.cameras else ''} "
             f"({next(iter(exact.values()))['source']})" if exact else "") + ".\n\n"
    summary_rows = []
    for m in spec.methods:
        s = averages[m]
        o = s["outcomes"]
        interval = s["interval_95"]
        exact_rate = f"{exact[m]['rate']:.1%}" if exact and m in exact else "–"
        summary_rows.append([method_label(m), f"{s['success_rate']:.1%} [{interval['low']:.1%}, {interval['high']:.1%}]"]
                            + ([exact_rate] if exact else [])
                            + [_share(s['procedural_success_rate']), _share(s['everyday_success_rate']),
                               _share(s['feasible_success_rate'])]
                            + [f"{s['by_direction'][f'{d:g}']:.1%}" for d in spec.directions]
                            + [o.get("infeasible", 0), o.get("error", 0), s["trials"], s["median_seconds"]]
                            + ([_per_trial(s["corrections_per_trial"]), _per_trial(s["stopped_per_trial"])]
                               if _corrects(spec) else []))
    text += markdown_table(["method", "all [95% CI]"] + (["exact"] if exact else []) + ["3D", "DO", "when feasible"]
                           + [f"{d:g}°" for d in spec.directions]
                           + ["infeasible", "errors", "trials", "median s/trial"]
                           + (["corrections/trial [95% CI]", "pushes stopped/trial [95% CI]"] if _corrects(spec) else []),
                           summary_rows)
    if summary["differences_95"]:
        text += "\n### Differences (percentage points, paired by object, 95% interval)\n\n"
        text += markdown_table(["comparison", "difference"],
                               [[" − ".join(method_label(m) for m in key.split(" - ")),
                                 f"{d['value'] * 100:+.1f} [{d['low'] * 100:+.1f}, {d['high'] * 100:+.1f}]"]
                                for key, d in summary["differences_95"].items()])
    counts = {m: averages[m]["failure_causes"] for m in spec.methods}
    causes = [c for c in FAILURE_CAUSES if c in ("planning", "pose quality") or any(c in n for n in counts.values())]
    text += "\n### Failures by cause\n\n" + "".join(f"- {c}: {FAILURE_CAUSES[c]}\n" for c in causes) + "\n"
    text += markdown_table(["method"] + causes, [[method_label(m)] + [counts[m].get(c, 0) for c in causes]
                                                 for m in spec.methods])
    return text


def _plot(records: Sequence[dict[str, Any]], spec: Protocol, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    width = 0.8 / len(spec.methods)
    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(spec.directions) + 1)
    for i, method in enumerate(spec.methods):
        rs = [r for r in records if r["method"] == method]
        rates = [_rate([r for r in rs if r["direction_deg"] == d]) for d in spec.directions] + [_rate(rs)]
        ax.bar(x + (i - (len(spec.methods) - 1) / 2) * width, rates, width, label=method_label(method))
    ax.set_xticks(x, [f"{d:g}°" for d in spec.directions] + ["all"])
    ax.set_ylim(0, 1)
    ax.set_ylabel("success rate")
    ax.set_title(spec.title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
