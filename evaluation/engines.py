"""The same trials executed in two engines: `python -m evaluation.engines REAL_RUN MUJOCO_RUN [--out FILE]`.

Both runs are `gd2p eval methods|closed-loop` results directories of the same protocol, one `--world real` (PyBullet)
and one `--world mujoco`: the same requests and the same drawn quantities (a seed draws both worlds alike), the
planner predicting in PyBullet in both. For every method both ran, on the trials both finished, the report gives

- success in each engine with its 95% interval clustered by object, and the engine gap (MuJoCo − PyBullet) paired
  by object (`evaluation.stats`);
- why trials failed (`failure_cause`): perception (the cameras' cloud could not be reconstructed), planning (no
  feasible plan), tracking (the image tracker lost the object, or the push was stopped on a lost track) or the
  push itself (executed, and the object did not end where it should: physics, or a pose the tracker had wrong);
- success against the tolerance in each engine (`evaluation.tolerance`: 1-5 cm, 10-45 degrees), drawn beside the
  report when it is written to a file;
- the image tracker's error against the truth: the per-push median and worst position (mm) and rotation (degrees),
  pooled as percentiles, and the share of frames lost. Rotation errors of a body of revolution (a standing can)
  are its unobservable spin, reported as measured.
"""
from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.compare import load_run, request_key
from evaluation.methods import DEFAULT_METHOD, lost_track
from evaluation.report import markdown_table
from evaluation.stats import difference_interval, success_interval
from evaluation.store import RECORDS_FILE, read_records
from evaluation.tolerance import Curves, curves, plot, table

CAUSES = ("perception", "planning", "tracking", "push", "other error")


def failure_cause(record: dict[str, Any]) -> str | None:
    """Why a trial failed (None: it succeeded); see the module docstring."""
    if record["success"]:
        return None
    code = record.get("error_code")
    if code == "bad_request":
        return "perception"
    if code == "infeasible":
        return "planning"
    if lost_track(record):
        return "tracking"
    if record.get("outcome") == "failure":
        return "push"
    return "other error"


def tracker_errors(records: list[dict[str, Any]]) -> dict[str, float]:
    """Percentiles of the per-push tracker errors over `records`, and the share of frames lost."""
    pushes = [p for r in records for p in (r.get("tracker") or {}).get("pushes", [])]
    out: dict[str, float] = {"pushes": float(len(pushes))}
    if not pushes:
        return out
    frames = sum(p["frames"] for p in pushes)
    out["lost_frames"] = sum(p["lost"] for p in pushes) / frames if frames else float("nan")
    for key in ("median_mm", "worst_mm", "median_deg", "worst_deg"):
        values = np.array([p[key] for p in pushes if key in p], dtype=np.float64)
        if len(values):
            out[f"{key}_p50"], out[f"{key}_p95"] = (float(v) for v in np.percentile(values, [50, 95]))
    return out


def report(real_dir: Path, mujoco_dir: Path, command: str | None = None, plot_path: Path | None = None,
           only: Sequence[str] | None = None) -> str:
    """The markdown report; with `plot_path`, the tolerance curves are drawn there and linked; `only`: these
    methods (e.g. leaving out one whose trials are still running)."""
    methods = [m for m in _methods(real_dir) if m in _methods(mujoco_dir) and (only is None or m in only)]
    if not methods:
        raise ValueError(f"{real_dir} and {mujoco_dir} share no method" + (f" of {', '.join(only)}" if only else ""))
    rows, causes, tracking, against = [], [], [], []
    tolerance: dict[str, Curves] = {}
    paired: dict[str, tuple[list[dict[str, Any]], list[dict[str, Any]]]] = {}
    for method in methods:
        real, mujoco = load_run(real_dir, method).records, load_run(mujoco_dir, method).records
        by_request = {request_key(r): r for r in mujoco}
        pairs = [(r, by_request[request_key(r)]) for r in real if request_key(r) in by_request]
        if not pairs:
            continue
        a, b = [p[0] for p in pairs], [p[1] for p in pairs]
        paired[method] = (a, b)
        rows.append([method, len(pairs), len({r["object_id"] for r in a}), str(success_interval(a)),
                     str(success_interval(b)), difference_interval(b, a).points()])
        for engine, records in (("PyBullet (`real`)", a), ("MuJoCo", b)):
            tolerance[f"{method} / {engine.split()[0]}"] = curves(records)
            counted = Counter(failure_cause(r) for r in records)
            causes.append([method, engine] + [counted.get(c, 0) for c in CAUSES])
            t = tracker_errors(records)
            tracking.append([method, engine, int(t["pushes"])] + [_fmt(t, k) for k in (
                "median_mm_p50", "median_mm_p95", "worst_mm_p95", "median_deg_p50", "worst_deg_p95")]
                + [f"{100 * t['lost_frames']:.1f}%" if "lost_frames" in t else "–"])
    if DEFAULT_METHOD in paired:  # the default minus each baseline in each engine, paired by object
        for method, (a, b) in paired.items():
            if method != DEFAULT_METHOD:
                against.append([method, len(a), difference_interval(paired[DEFAULT_METHOD][0], a).points(),
                                difference_interval(paired[DEFAULT_METHOD][1], b).points()])
    versus = ("" if not against else f"\n## The default ({DEFAULT_METHOD}) minus each method, in each engine\n\n"
              "Points, paired by object on the objects both ran (its trials as above).\n\n"
              + markdown_table(["method", "trials", "PyBullet", "MuJoCo"], against))
    head = "# The same trials in PyBullet and MuJoCo\n\n" + (f"- command: `{command}`\n" if command else "")
    return (head + f"- runs: `{real_dir}` (PyBullet) and `{mujoco_dir}` (MuJoCo), matched by request\n"
            f"- code: {_codes(real_dir)} / {_codes(mujoco_dir)}\n\n"
            "Intervals: 95%, bootstrap clustered by object; the gap is MuJoCo − PyBullet, paired by object.\n\n"
            + markdown_table(["method", "trials", "objects", "PyBullet", "MuJoCo", "gap, points"], rows) + versus
            + "\n## Why trials failed\n\n" + markdown_table(["method", "engine", *CAUSES], causes)
            + "\n## The image tracker against the truth (per push)\n\n"
            + markdown_table(["method", "engine", "pushes", "median mm (p50)", "median mm (p95)", "worst mm (p95)",
                              "median ° (p50)", "worst ° (p95)", "frames lost"], tracking)
            + "\n## Success against the tolerance (the same trials; `evaluation.tolerance`)\n\n" + table(tolerance)
            + (f"\n![success against the tolerance]({plot(tolerance, plot_path).name})\n" if plot_path else ""))


def _fmt(values: dict[str, float], key: str) -> str:
    return f"{values[key]:.1f}" if key in values else "–"


def _methods(directory: Path) -> list[str]:
    path = directory / RECORDS_FILE
    if not path.is_file():
        raise ValueError(f"{directory}: no {RECORDS_FILE} (not a `gd2p eval` run)")
    return sorted({str(r["method"]) for r in read_records(path).values()})


def _codes(directory: Path) -> str:
    return ", ".join(sorted({str(r.get("code")) for r in read_records(directory / RECORDS_FILE).values()}))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("real", type=Path, help="the `--world real` run's directory")
    parser.add_argument("mujoco", type=Path, help="the `--world mujoco` run's directory")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown here (default: print it)")
    parser.add_argument("--methods", default=None, help="comma-separated methods to report (default: every one both ran)")
    args = parser.parse_args(argv)
    only = None if args.methods is None else [m.strip() for m in args.methods.split(",") if m.strip()]
    try:
        command = " ".join(["python -m evaluation.engines", *(argv or sys.argv[1:])])
        text = report(args.real, args.mujoco, command, args.out.with_suffix(".png") if args.out else None, only)
    except ValueError as exc:
        print(f"evaluation.engines: {exc}", file=sys.stderr)
        return 2
    if args.out is None:
        print(text)
    else:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
