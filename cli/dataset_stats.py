"""`gd2p dataset stats`: what a pose store holds, as a text table, JSON and PNG plots.

Successes are what training sees (`DatasetStore.rows()`); a version-2 store also keeps its failures,
so success rates per family, per resting pose and against the yaw are counted over every validated
raw candidate (augmented copies exist only for successful candidates, so their rate is reported
apart). A version-1 store has no failures and every pose at yaw 0: its rates come from the manifest's
per-stage counts and its yaw coverage is one bin.

    coverage      successful poses and raw candidates per 30-degree yaw bin
    by_family     objects, successes, failures, raw and augmented success rates per family
    by_resting_pose  rows and successes per resting-pose index (0 = an object's most stable pose)
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

YAW_BIN_DEG = 30
STAT_COLUMNS = ("object_id", "hand", "stage", "yaw_rad", "pose_index", "success")


def run_stats(args: argparse.Namespace) -> int:
    from shared.data.dataset_store import DatasetStore, StoreError

    try:
        store = DatasetStore.open(args.directory)
        store.verify()
        stats = store_statistics(store)
        if args.plot is not None:
            plot_joint_histograms(store, args.plot)
            coverage = coverage_plot_path(args.plot)
            plot_coverage(stats, coverage)
            stats["plot"] = str(args.plot)
            stats["coverage_plot"] = str(coverage)
    except StoreError as exc:
        print(f"gd2p dataset stats: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(stats))
    else:
        print_stats(stats)
    return 0


def coverage_plot_path(plot: Path) -> Path:
    """joints.png -> joints-coverage.png: the second figure of `--plot`."""
    return plot.with_name(f"{plot.stem}-coverage{plot.suffix or '.png'}")


# ============================================================================= figures
def store_statistics(store) -> dict:
    """Counts per object, hand, stage, family and resting pose; success rates; yaw coverage."""
    rows = _stat_rows(store)
    succeeded = [r for r in rows if r["success"]]
    totals = store.totals(family_of=library_family)
    stages = {k: totals[k] for k in ("generated", "raw_successes", "augmented_validated", "augmented_successes")}
    return {
        "directory": str(store.directory),
        "version": store.version,
        "hand": store.manifest["hand"],
        "split": store.manifest["split"],
        "objects": totals["objects"],
        "poses": len(succeeded),
        "failures": len(rows) - len(succeeded),
        "by_hand": _count(succeeded, "hand"),
        "by_stage": {stage: sum(r["stage"] == stage for r in succeeded) for stage in ("raw", "augmented")},
        "stages": stages,
        "success_rates": {"raw": _rate(stages["raw_successes"], stages["generated"]),
                          "augmented": _rate(stages["augmented_successes"], stages["augmented_validated"])},
        "placements": len({(r["object_id"], r["pose_index"], round(r["yaw_rad"], 6)) for r in succeeded}),
        "by_family": _family_table(totals["by_family"]),
        "by_resting_pose": {pose: {**c, "success_rate": _rate(c["successes"], c["rows"])}
                            for pose, c in totals["by_resting_pose"].items()},
        "yaw": yaw_coverage(rows, has_failures=store.version >= 2),
        "objects_with_at_least": _objects_with_at_least(store),
        "build_wall_s": round(sum(run.get("wall_s", 0.0) for run in store.manifest["runs"]), 1),
        "runs": len(store.manifest["runs"]),
        "content_hash": store.content_hash(),
        "per_object": _per_object(store, succeeded),
    }


def _stat_rows(store) -> list[dict[str, Any]]:
    """Every row's object, hand, stage, yaw, resting pose and outcome (absent columns: yaw 0, default pose)."""
    table = store.rows(columns=STAT_COLUMNS, outcome="all")
    rows: list[dict[str, Any]] = table.to_pylist() if table.num_columns else []
    for row in rows:
        row["yaw_rad"] = row["yaw_rad"] or 0.0
        row["success"] = row["success"] is not False  # absent or null: a success (version 1)
    return rows


def yaw_coverage(rows: list[dict[str, Any]], has_failures: bool) -> dict[str, Any]:
    """Per 30-degree yaw bin: successful poses, raw candidates and (version 2) their success rate."""
    bins = 360 // YAW_BIN_DEG
    successes, candidates, candidate_ok = [0] * bins, [0] * bins, [0] * bins
    for row in rows:
        b = yaw_bin(row["yaw_rad"], bins)
        successes[b] += row["success"]
        if row["stage"] == "raw":
            candidates[b] += 1
            candidate_ok[b] += row["success"]
    return {"bin_start_deg": [-180 + YAW_BIN_DEG * b for b in range(bins)], "successes": successes,
            "raw_candidates": candidates,
            "raw_success_rate": [_rate(ok, n) if has_failures and n else None for ok, n in zip(candidate_ok, candidates,
                                                                                               strict=True)]}


def yaw_bin(yaw_rad: float, bins: int) -> int:
    """The bin of a yaw wrapped to [-180, 180) degrees."""
    degrees = (math.degrees(yaw_rad) + 180.0) % 360.0
    return min(bins - 1, int(degrees // (360 / bins)))


def library_family(object_id: str) -> str:
    """The library family of an id ("random", "box", "bottle", ...), "user" for other ids."""
    from shared.world.objects import ObjectLoadError
    from shared.world.objects.catalog import resolve_library_id

    try:
        return resolve_library_id(object_id).family
    except ObjectLoadError:
        return "user"


def _family_table(by_family: dict[str, dict[str, int]]) -> dict[str, dict[str, Any]]:
    return {name: {"objects": c["objects"], "successes": c["successes"], "failures": c["failures"],
                   "raw_success_rate": _rate(c["raw_successes"], c["generated"]),
                   "augmented_success_rate": _rate(c["augmented_successes"], c["augmented_validated"])}
            for name, c in by_family.items()}


def _per_object(store, succeeded: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    per_object: dict[str, dict[str, Any]] = {}
    for object_id, status in store.completed_objects().items():
        per_object[object_id] = {**status.counts, "poses": status.successes, "failures": status.rows - status.successes,
                                 "raw": 0, "augmented": 0}
    for row in succeeded:
        per_object[row["object_id"]][row["stage"]] += 1
    return per_object


def _objects_with_at_least(store) -> dict[str, int]:
    poses = [status.successes for status in store.completed_objects().values()]
    return {str(k): sum(p >= k for p in poses) for k in (1, 10, 20)}


def _count(rows: list[dict[str, Any]], key: str) -> dict[str, int]:
    counts: dict[str, int] = {}
    for row in rows:
        counts[row[key]] = counts.get(row[key], 0) + 1
    return counts


def _rate(part: int, whole: int) -> float:
    return part / whole if whole else 0.0


# ============================================================================= text
def print_stats(s: dict) -> None:
    print(f"{s['directory']}: version {s['version']}, hand {s['hand']}, split {s['split']}, {s['objects']} objects, "
          f"{s['poses']} poses ({s['by_stage']['raw']} raw, {s['by_stage']['augmented']} augmented), "
          f"{s['failures']} failed pushes kept, {s['placements']} placements with a success")
    st = s["stages"]
    print(f"  generated {st['generated']} -> raw successes {st['raw_successes']} ({100 * s['success_rates']['raw']:.1f}%); "
          f"augmented {st['augmented_validated']} -> successes {st['augmented_successes']} "
          f"({100 * s['success_rates']['augmented']:.1f}%)")
    print(f"  built in {s['runs']} run(s), {s['build_wall_s']:.0f} s of wall time")
    print("  objects with >= 1 / 10 / 20 poses: " + " / ".join(str(v) for v in s["objects_with_at_least"].values()))
    _print_families(s["by_family"])
    _print_yaw(s["yaw"])
    _print_resting_poses(s["by_resting_pose"])
    print(f"  {'OBJECT':<18} {'GENERATED':>9} {'RAW OK':>7} {'AUG':>6} {'AUG OK':>7} {'POSES':>6} {'FAILED':>7}")
    for object_id, c in s["per_object"].items():
        print(f"  {object_id:<18} {c['generated']:>9} {c['raw_successes']:>7} {c['augmented_validated']:>6} "
              f"{c['augmented_successes']:>7} {c['poses']:>6} {c['failures']:>7}")


def _print_families(by_family: dict[str, dict[str, Any]]) -> None:
    print(f"  {'FAMILY':<12} {'OBJECTS':>7} {'POSES':>7} {'FAILED':>7} {'RAW OK':>7} {'AUG OK':>7}")
    for name, c in by_family.items():
        print(f"  {name:<12} {c['objects']:>7} {c['successes']:>7} {c['failures']:>7} "
              f"{100 * c['raw_success_rate']:>6.1f}% {100 * c['augmented_success_rate']:>6.1f}%")


def _print_yaw(yaw: dict[str, Any]) -> None:
    print(f"  {'YAW (DEG)':<12} {'POSES':>7} {'RAW':>7} {'RAW OK':>7}")
    for start, poses, raw, rate in zip(yaw["bin_start_deg"], yaw["successes"], yaw["raw_candidates"],
                                       yaw["raw_success_rate"], strict=True):
        shown = "-" if rate is None else f"{100 * rate:.1f}%"
        print(f"  {f'{start}..{start + YAW_BIN_DEG}':<12} {poses:>7} {raw:>7} {shown:>7}")


def _print_resting_poses(by_pose: dict[str, dict[str, Any]]) -> None:
    print(f"  {'RESTING POSE':<12} {'ROWS':>7} {'POSES':>7} {'OK':>7}")
    for pose, c in by_pose.items():
        print(f"  {pose:<12} {c['rows']:>7} {c['successes']:>7} {100 * c['success_rate']:>6.1f}%")


# ============================================================================= plots
def plot_coverage(stats: dict, path: Path) -> None:
    """Yaw coverage, poses per family, success rate per family and against the yaw (2 x 2 panels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    yaw, families = stats["yaw"], stats["by_family"]
    centres = [start + YAW_BIN_DEG / 2 for start in yaw["bin_start_deg"]]
    fig, ((ax_yaw, ax_fam), (ax_fam_rate, ax_yaw_rate)) = plt.subplots(2, 2, figsize=(13, 9))
    ax_yaw.bar(centres, yaw["successes"], width=YAW_BIN_DEG * 0.9, color="tab:blue", label="successful poses")
    ax_yaw.bar(centres, yaw["raw_candidates"], width=YAW_BIN_DEG * 0.45, color="tab:orange", label="raw candidates")
    _axes(ax_yaw, "yaw coverage", "object yaw in D (deg)", "poses")
    names = list(families)
    ax_fam.bar(names, [families[n]["successes"] for n in names], color="tab:blue", label="successes")
    ax_fam.bar(names, [families[n]["failures"] for n in names], bottom=[families[n]["successes"] for n in names],
               color="tab:red", label="failures")
    _axes(ax_fam, "poses per family", None, "rows")
    positions = range(len(names))
    ax_fam_rate.bar([p - 0.2 for p in positions], [families[n]["raw_success_rate"] for n in names], width=0.4,
                    color="tab:orange", label="raw candidates")
    ax_fam_rate.bar([p + 0.2 for p in positions], [families[n]["augmented_success_rate"] for n in names], width=0.4,
                    color="tab:blue", label="augmented copies")
    ax_fam_rate.set_xticks(list(positions), names)
    ax_fam_rate.set_ylim(0, 1)
    _axes(ax_fam_rate, "success rate per family", None, "success rate")
    rates = [math.nan if r is None else r for r in yaw["raw_success_rate"]]
    ax_yaw_rate.plot(centres, rates, marker="o", color="tab:orange", label="raw candidates")
    ax_yaw_rate.set_ylim(0, 1)
    _axes(ax_yaw_rate, "success rate vs yaw" + ("" if stats["version"] >= 2 else " (version 1: no failures kept)"),
          "object yaw in D (deg)", "success rate")
    for ax in (ax_fam, ax_fam_rate):
        ax.tick_params(axis="x", labelrotation=45)
    fig.suptitle(f"{stats['poses']} successful and {stats['failures']} failed {stats['hand']} pushes, "
                 f"{stats['objects']} objects ({Path(stats['directory']).name})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _axes(ax, title: str, xlabel: str | None, ylabel: str) -> None:
    ax.set_title(title)
    if xlabel:
        ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)


def plot_joint_histograms(store, path: Path) -> None:
    """The paper's appendix figure: one histogram per joint of the successful poses, joint limits as green dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from shared.robots.hands import load_hand

    table = store.rows(columns=["pose"])
    poses = (np.asarray(table.column("pose").combine_chunks().flatten().to_numpy(zero_copy_only=False),
                        dtype=np.float64).reshape(-1, 25) if table.num_columns else np.zeros((0, 25)))
    hand = load_hand(store.hand)
    lower, upper = hand.joint_lower.numpy(), hand.joint_upper.numpy()
    joints = poses[:, 9:]
    fig, axes = plt.subplots(4, 4, figsize=(14, 11))
    for j, ax in enumerate(axes.flat):
        ax.hist(joints[:, j], bins=40, range=(lower[j] - 0.1, upper[j] + 0.1), color="tab:blue")
        for limit in (lower[j], upper[j]):
            ax.axvline(limit, color="green", linestyle="--", linewidth=1.2)
        ax.text(0.97, 0.93, str(j), transform=ax.transAxes, ha="right", va="top", fontsize=11, weight="bold")
        ax.set_xlabel("rad", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.suptitle(f"Joint angles of {len(poses)} validated {store.hand} poses ({store.directory.name})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
