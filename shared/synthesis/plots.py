"""Energy-per-iteration curves of a generation run (matplotlib, Agg backend: no display needed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.synthesis.config import TERMS

TOTAL = "total"


def plot_energy_history(history: dict[str, np.ndarray], path: str | Path, weights: dict[str, float],
                        title: str = "") -> Path:
    """Save the batch-mean total energy and each weighted term against the iteration to `path` (PNG).

    Left: the total. Right: w_t * E_t for every term with a non-zero weight (symlog y axis, since
    terms range from ~1e-3 to ~1e2 and E_dir / E_fp are negative).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if TOTAL not in history or len(history[TOTAL]) == 0:
        raise ValueError("no energy history recorded (was record_history off?)")
    iterations = np.arange(1, len(history[TOTAL]) + 1)
    figure, (left, right) = plt.subplots(1, 2, figsize=(13, 4.8))
    left.plot(iterations, history[TOTAL], color="black")
    left.set(xlabel="iteration", ylabel="batch-mean E", title="total energy")
    left.grid(alpha=0.3)
    for term in TERMS:
        if weights.get(term, 0.0) != 0.0 and term in history:
            right.plot(iterations, weights[term] * history[term], label=f"{weights[term]:g} E_{term}")
    right.set_yscale("symlog", linthresh=1e-2)
    right.set(xlabel="iteration", ylabel="batch-mean weighted term", title="weighted terms")
    right.grid(alpha=0.3)
    right.legend(fontsize=8, ncol=2)
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
