"""Success against the tolerance: how many trials would succeed under a tighter or looser criterion.

    python -m evaluation.tolerance RUN [RUN ...] [--out FILE.md]    # a table per run and method, and FILE.png

A trial's record keeps where the object truly ended (`position_error_m` from the target, `rotation_deg` turned,
`toppled`), so the same trials answer the question at every tolerance: within 1-5 cm of the target (turned at
most 45 degrees), and turned at most 10-45 degrees (within 3 cm), upright in both. A trial that ended in an error
(no plan, a refused cloud, a lost track) fails at every tolerance. The system was asked for the paper's task
(3 cm, 45 degrees) and its closed loop stops correcting once inside it, so a curve below 3 cm says how precise
its pushes are, not how precise it could be if asked for more. A body of revolution's turn is judged as the
evaluation's judge reads it (the true turn, which no camera sees): its rotation curve says little. A pose goal's
trials are read by their yaw miss, and an object that rolls by its position alone (as `judge_push` does).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evaluation.report import markdown_table
from evaluation.stats import Interval, mean_interval
from evaluation.store import RECORDS_FILE, read_records

POSITION_TOLERANCES_M = (0.01, 0.02, 0.03, 0.04, 0.05)
ROTATION_TOLERANCES_DEG = (10.0, 15.0, 20.0, 30.0, 45.0)
PAPER_POSITION_M, PAPER_ROTATION_DEG = 0.03, 45.0  # the other axis is held at the paper's bound


@dataclass(frozen=True)
class Curves:
    """Success (with its interval clustered by object) at each position and each rotation tolerance."""

    trials: int
    by_position: tuple[Interval, ...]  # at POSITION_TOLERANCES_M, turned <= PAPER_ROTATION_DEG
    by_rotation: tuple[Interval, ...]  # at ROTATION_TOLERANCES_DEG, within PAPER_POSITION_M


def within(record: dict[str, Any], position_m: float, rotation_deg: float) -> bool:
    """Whether the trial ended within `position_m` of its target, turned at most `rotation_deg`, upright. The turn
    is the one its task judges: a pose goal's yaw miss (`yaw_error_deg`) rather than the turn from the start; an
    object that rolls (`shape` "round") is judged on its position alone, as the judge does."""
    error = record.get("position_error_m")
    turned = record.get("yaw_error_deg", record.get("rotation_deg"))
    if record.get("outcome") not in ("success", "failure") or error is None or turned is None:
        return False  # no final pose: an error before or during the push
    if record.get("shape") == "round":
        return bool(error <= position_m)
    return bool(error <= position_m and turned <= rotation_deg and not record.get("toppled", False))


def curves(records: Sequence[dict[str, Any]]) -> Curves:
    def at(position_m: float, rotation_deg: float) -> Interval:
        return mean_interval(records, lambda r: float(within(r, position_m, rotation_deg)))

    return Curves(len(records), tuple(at(p, PAPER_ROTATION_DEG) for p in POSITION_TOLERANCES_M),
                  tuple(at(PAPER_POSITION_M, r) for r in ROTATION_TOLERANCES_DEG))


def table(labelled: dict[str, Curves]) -> str:
    """Markdown: a row per label (run and method), a column per tolerance."""
    head = (["run / method", "trials"] + [f"≤ {p * 100:g} cm" for p in POSITION_TOLERANCES_M]
            + [f"≤ {r:g}°" for r in ROTATION_TOLERANCES_DEG])
    rows = [[label, c.trials] + [f"{i.value:.0%} [{i.low:.0%}, {i.high:.0%}]" for i in (*c.by_position, *c.by_rotation)]
            for label, c in labelled.items()]
    return markdown_table(head, rows)


def plot(labelled: dict[str, Curves], path: Path) -> Path:
    """Two panels (position, rotation tolerance), a line with its interval band per label; written to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_position, by_rotation) = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for label, c in labelled.items():
        for ax, xs, intervals in ((by_position, [100 * p for p in POSITION_TOLERANCES_M], c.by_position),
                                  (by_rotation, list(ROTATION_TOLERANCES_DEG), c.by_rotation)):
            line, = ax.plot(xs, [100 * i.value for i in intervals], marker="o", label=label)
            ax.fill_between(xs, [100 * i.low for i in intervals], [100 * i.high for i in intervals],
                            color=line.get_color(), alpha=0.15)
    by_position.set(xlabel=f"position tolerance, cm (turned ≤ {PAPER_ROTATION_DEG:g}°)", ylabel="success, %",
                    ylim=(0, 100))
    by_rotation.set(xlabel=f"rotation tolerance, ° (within {PAPER_POSITION_M * 100:g} cm)")
    for ax in (by_position, by_rotation):
        ax.axvline(100 * PAPER_POSITION_M if ax is by_position else PAPER_ROTATION_DEG, color="grey", lw=0.8, ls=":")
        ax.grid(alpha=0.3)
    by_rotation.legend(fontsize=8, loc="lower right")
    fig.suptitle("Success against the tolerance (95% intervals clustered by object; dotted: the paper's task)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run_curves(directory: Path) -> dict[str, Curves]:
    """Per method of a `gd2p eval` run: its curves, labelled `<run> / <method>`."""
    path = directory / RECORDS_FILE
    if not path.is_file():
        raise ValueError(f"{directory}: no {RECORDS_FILE} (not a `gd2p eval` run)")
    records = list(read_records(path).values())
    methods = sorted({str(r["method"]) for r in records})
    return {f"{directory.name} / {m}": curves([r for r in records if r["method"] == m]) for m in methods}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="`gd2p eval` run directories")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown here and the plot beside it (.png)")
    args = parser.parse_args(argv)
    try:
        labelled = {label: c for run in args.runs for label, c in run_curves(run).items()}
    except ValueError as exc:
        print(f"evaluation.tolerance: {exc}", file=sys.stderr)
        return 2
    command = " ".join(["python -m evaluation.tolerance", *(argv if argv is not None else sys.argv[1:])])
    text = f"# Success against the tolerance\n\n- command: `{command}`\n\n{table(labelled)}"
    if args.out is None:
        print(text)
        return 0
    image = plot(labelled, args.out.with_suffix(".png"))
    args.out.write_text(text + f"\n![success against the tolerance]({image.name})\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
