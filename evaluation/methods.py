"""Experiments "methods" (Allegro on the Panda, GD2P against its baselines) and "leap" (LEAP on the xArm7).

Both follow the protocol of `push_protocol.py` and report like the paper's appendix table: per
object and direction, the successful trials out of 5 for each method ("–": no trial had a
kinematically feasible plan), and the averages over the procedural ("3D") objects, the everyday
("DO") objects and all 14.
"""
from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evaluation import push_protocol as protocol
from evaluation.report import markdown_table, write_experiment
from evaluation.store import ResultStore

METHOD_LABELS = {"gd2p": "GD2P", "gd2p-no-ranking": "GD2P w/o ranking", "nearest": "Nearest Neighbor",
                 "fixed": "Fixed spatula", "grasp": "Grasp pose"}
QUICK_OBJECTS = ("proc-box-001", "pb-mug")


@dataclass(frozen=True)
class Protocol:
    name: str
    title: str
    hand: str
    methods: tuple[str, ...]
    objects: tuple[str, ...]
    directions: tuple[float, ...]
    trials: int

    def settings(self) -> dict[str, Any]:
        """What a resumed run must share with the records on disk. Not the trial count: trial k is the
        same episode whatever the count, so a run with fewer trials can later be extended."""
        return {"hand": self.hand, "arm": protocol.ROBOTS[self.hand], "methods": list(self.methods),
                "objects": list(self.objects), "directions_deg": list(self.directions),
                "object_xy": list(protocol.OBJECT_XY), "placement_noise_m": protocol.PLACEMENT_NOISE_M,
                "placement_noise_deg": protocol.PLACEMENT_NOISE_DEG, "push_distance_m": protocol.PUSH_DISTANCE_M}


def protocol_for(name: str, quick: bool, trials: int | None = None) -> Protocol:
    objects = QUICK_OBJECTS if quick else protocol.PROCEDURAL_OBJECTS + protocol.EVERYDAY_OBJECTS
    trials = trials or (1 if quick else protocol.TRIALS)
    if name == "methods":
        return Protocol(name, "Methods × objects × directions (Allegro + Panda)", "allegro", protocol.METHODS,
                        objects, protocol.DIRECTIONS_DEG, trials)
    if name == "leap":
        return Protocol(name, "Hand morphology: LEAP + xArm7", "leap", ("gd2p",), objects,
                        protocol.DIRECTIONS_DEG, trials)
    raise ValueError(f"unknown protocol {name!r}")


def run_protocol(name: str, out: Path, quick: bool, workers: int, trials: int | None = None) -> Path:
    spec = protocol_for(name, quick, trials)
    directory = Path(out) / name
    store = ResultStore(directory, spec.settings())
    started = time.perf_counter()
    todo = protocol.episodes(spec.methods, spec.hand, spec.objects, spec.directions, spec.trials)
    pending = [e for e in todo if not store.done(e.key)]
    protocol.run_in_workers(pending, protocol.run_episode, store, workers, Path(out) / "grasp_poses", label=name)
    records = [store.records[e.key] for e in todo]
    summary = summarise(records, spec)
    body = report_body(records, spec, summary)
    _plot(records, spec, directory / "success_by_direction.png")
    body += "\n![success by method and direction](success_by_direction.png)\n"
    return write_experiment(directory, spec.title, body, {"settings": {**spec.settings(), "trials": spec.trials},
                                                          **summary}, time.perf_counter() - started, quick)


def run_methods(out: Path, quick: bool = False, workers: int = 2, trials: int | None = None) -> Path:
    return run_protocol("methods", out, quick, workers, trials)


def run_leap(out: Path, quick: bool = False, workers: int = 2, trials: int | None = None) -> Path:
    return run_protocol("leap", out, quick, workers, trials)


# ------------------------------------------------------------------------------------------ tables

def _rate(records: Sequence[dict[str, Any]]) -> float:
    return sum(r["success"] for r in records) / len(records) if records else float("nan")


def summarise(records: Sequence[dict[str, Any]], spec: Protocol) -> dict[str, Any]:
    """Success rates per method: all objects, procedural, everyday, per direction; outcome counts."""
    by_method: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        by_method[r["method"]].append(r)
    methods = {}
    for method in spec.methods:
        rs = by_method[method]
        outcomes = defaultdict(int)
        for r in rs:
            outcomes[r["outcome"]] += 1
        feasible = [r for r in rs if r["outcome"] != "infeasible"]
        methods[method] = {
            "success_rate": _rate(rs),
            "feasible_success_rate": _rate(feasible),  # pose quality apart from the arm's reach
            "procedural_success_rate": _rate([r for r in rs if r["object_id"] in protocol.PROCEDURAL_OBJECTS]),
            "everyday_success_rate": _rate([r for r in rs if r["object_id"] in protocol.EVERYDAY_OBJECTS]),
            "by_direction": {f"{d:g}": _rate([r for r in rs if r["direction_deg"] == d]) for d in spec.directions},
            "outcomes": dict(outcomes),
            "trials": len(rs),
            "median_seconds": sorted(r["seconds"] for r in rs)[len(rs) // 2] if rs else None,
        }
    return {"methods": methods}


def _cell(records: Sequence[dict[str, Any]]) -> str:
    if all(r["outcome"] == "infeasible" for r in records):
        return "–"
    return str(sum(r["success"] for r in records))


def report_body(records: Sequence[dict[str, Any]], spec: Protocol, summary: dict[str, Any]) -> str:
    cells: dict[tuple[str, str, float], list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        cells[(r["method"], r["object_id"], r["direction_deg"])].append(r)
    headers = ["object"] + [f"{METHOD_LABELS[m]} {d:g}°" for m in spec.methods for d in spec.directions]
    rows = [[o] + [_cell(cells[(m, o, d)]) for m in spec.methods for d in spec.directions] for o in spec.objects]
    averages = summary["methods"]
    for label, key in (("3D avg.", "procedural_success_rate"), ("DO avg.", "everyday_success_rate"),
                       ("All avg.", "success_rate")):
        rows.append([f"**{label}**"] + [f"{averages[m][key]:.2f}" if d == spec.directions[0] else ""
                                        for m in spec.methods for d in spec.directions])
    text = (f"{spec.hand} hand on the {protocol.ROBOTS[spec.hand]}; objects resting at "
            f"({protocol.OBJECT_XY[0]:.2f}, {protocol.OBJECT_XY[1]:.2f}) m, re-placed for each trial (±"
            f"{protocol.PLACEMENT_NOISE_M * 100:.0f} cm, ±{protocol.PLACEMENT_NOISE_DEG:.0f}°); directions "
            f"{', '.join(f'{d:g}°' for d in spec.directions)} (180° pulls toward the robot); a "
            f"{protocol.PUSH_DISTANCE_M:.2f} m push; {spec.trials} trial(s) per cell. Cells: successful trials out of "
            f"{spec.trials}; – : no kinematically feasible plan in any trial (counted as failures).\n\n")
    text += markdown_table(headers, rows)
    text += "\n### Averages\n\n"
    summary_rows = []
    for m in spec.methods:
        s = averages[m]
        o = s["outcomes"]
        summary_rows.append([METHOD_LABELS[m], f"{s['success_rate']:.1%}", f"{s['procedural_success_rate']:.1%}",
                             f"{s['everyday_success_rate']:.1%}", f"{s['feasible_success_rate']:.1%}"]
                            + [f"{s['by_direction'][f'{d:g}']:.1%}" for d in spec.directions]
                            + [o.get("infeasible", 0), o.get("error", 0), s["trials"], s["median_seconds"]])
    text += markdown_table(["method", "all", "3D", "DO", "when feasible"] + [f"{d:g}°" for d in spec.directions]
                           + ["infeasible", "errors", "trials", "median s/trial"], summary_rows)
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
        ax.bar(x + (i - (len(spec.methods) - 1) / 2) * width, rates, width, label=METHOD_LABELS[method])
    ax.set_xticks(x, [f"{d:g}°" for d in spec.directions] + ["all"])
    ax.set_ylim(0, 1)
    ax.set_ylabel("success rate")
    ax.set_title(spec.title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
