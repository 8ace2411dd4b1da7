"""Sampler quality on the test split (the sampler's benchmark): `gd2p eval sampler-quality`.

For every test object (never trained on) and each method — the shipped Allegro checkpoint with the
paper's DDPM-100, the same checkpoint with the DDIM-10 fast path, and the paper's Nearest Neighbor
baseline — 200 candidate poses are drawn and pushed in the floating-hand validator (see
evaluation/coverage.py for the protocol and its exact early stopping). Reported per method: the
fraction of sampled poses that validate (over each object's first 50 poses; mean over objects and
pooled over all pushes) and the number of objects with >= 1 validated pose out of 200. The paper's
anchor: 169 of 300 unseen objects (56%); the target: >= 75%.
"""
from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.coverage import (
    DEFAULT_DATASET,
    HAND,
    TARGET_COVERED_PCT,
    CoverageError,
    CoveragePool,
    CoverageSettings,
    DiffusionSource,
    NearestNeighborSource,
    PoseSource,
    summarize,
)
from evaluation.report import markdown_table, write_experiment
from evaluation.store import ResultStore

NAME = "sampler-quality"
TITLE = "Sampler quality on the test split"
QUICK_OBJECTS = 8
PAPER_COVERED, PAPER_OBJECTS = 169.33, 300


def shipped_checkpoint() -> Path:
    from services.sampler.checkpoint import SHIPPED_DIR

    return SHIPPED_DIR / f"{HAND}.pt"


def shipped_nn_index() -> Path:
    from services.sampler.checkpoint import SHIPPED_DIR

    return SHIPPED_DIR / f"{HAND}_nn.npz"


def nearest_neighbor_index(cache_dir: Path, dataset_dir: Path = DEFAULT_DATASET, checkpoint: Path | None = None) -> Path:
    """The NN index to evaluate: the shipped `allegro_nn.npz` if present, else built once from the training store.

    A built index uses the checkpoint's BPS basis (the same encoding the model sees) and is saved
    in `cache_dir`, so a resumed run and the spawn workers load the file instead of rebuilding it.
    """
    if shipped_nn_index().is_file():
        return shipped_nn_index()
    built = Path(cache_dir) / f"{HAND}_nn.npz"
    if built.is_file():
        return built
    if not Path(dataset_dir).is_dir():
        raise CoverageError(f"no nearest-neighbour index at {shipped_nn_index()} and no training store at {dataset_dir} "
                            f"to build one from (`gd2p dataset build --split train --hand {HAND} ... --out {dataset_dir}`)")
    from services.sampler.checkpoint import load_checkpoint
    from services.sampler.nearest_neighbor import NearestNeighborBaseline

    bps = load_checkpoint(checkpoint or shipped_checkpoint()).bps
    return NearestNeighborBaseline.from_directory(dataset_dir, HAND, bps=bps, progress=True).save(built)


def quality_objects(quick: bool = False) -> list[str]:
    """The test split's object ids (the first QUICK_OBJECTS with `quick`)."""
    from shared.world.objects import list_object_ids

    ids = list_object_ids("test")
    return ids[:QUICK_OBJECTS] if quick else ids


def methods(checkpoint: Path, nn_index: Path) -> dict[str, PoseSource]:
    """Record-key prefix -> pose source, in table order."""
    return {
        "ddpm100": DiffusionSource(str(checkpoint), "ddpm"),
        "ddim10": DiffusionSource(str(checkpoint), "ddim"),
        "nn": NearestNeighborSource(str(nn_index)),
    }


def settings_of(object_ids: Sequence[str], checkpoint: Path, nn_index: Path, coverage: CoverageSettings) -> dict[str, Any]:
    """What the store pins: the objects, the exact weights and index, and the protocol."""
    from services.sampler.checkpoint import checkpoint_id

    return {"objects": list(object_ids), "checkpoint_id": checkpoint_id(checkpoint), "nn_index": index_fingerprint(nn_index),
            "methods": ["ddpm100", "ddim10", "nn"], "coverage": coverage.to_dict()}


def index_fingerprint(path: Path) -> str:
    """SHA-256 (16 hex digits) of an NN index's contents — not of the file, whose zip timestamps vary."""
    digest = hashlib.sha256()
    with np.load(path, allow_pickle=False) as data:
        for name in sorted(data.files):
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(data[name]).tobytes())
    return digest.hexdigest()[:16]


def run(out: Path, quick: bool = False, workers: int = 2) -> Path:
    """Measure the three methods on the test split into `out/sampler-quality/`; returns the report path."""
    started = time.perf_counter()
    directory = Path(out) / NAME
    directory.mkdir(parents=True, exist_ok=True)
    checkpoint = shipped_checkpoint()
    if not checkpoint.is_file():
        raise CoverageError(f"no shipped {HAND} checkpoint at {checkpoint}")
    nn_index = nearest_neighbor_index(directory)
    objects = quality_objects(quick)
    coverage = CoverageSettings(hand=HAND)
    store = ResultStore(directory, settings_of(objects, checkpoint, nn_index, coverage))
    results: dict[str, list[dict[str, Any]]] = {}
    sources = methods(checkpoint, nn_index)
    with CoveragePool(workers) as pool:
        for key, source in sources.items():
            results[key] = pool.measure(source, objects, store, key, coverage, desc=source.label())
    summaries = {key: summarize(records) for key, records in results.items()}
    plot = plot_validated_fractions(results, sources, directory / "validated_fraction.png")
    body = report_body(summaries, sources, results, objects, nn_index, plot.name)
    summary = {"objects": len(objects), "methods": {sources[k].label(): v for k, v in summaries.items()},
               "paper_anchor": {"covered": PAPER_COVERED, "objects": PAPER_OBJECTS}, "target_covered_pct": TARGET_COVERED_PCT}
    return write_experiment(directory, TITLE, body, summary, time.perf_counter() - started, quick)


# ----------------------------------------------------------------------------- report
def report_body(summaries: dict[str, dict[str, Any]], sources: dict[str, PoseSource], results: dict[str, list[dict[str, Any]]],
                objects: Sequence[str], nn_index: Path, plot_name: str) -> str:
    rows = [[sources[k].label(), f"{s['mean_validated_fraction']:.1%}", f"{s['pooled_validated_fraction']:.1%}",
             f"{s['covered']} / {s['objects']}", f"{s['covered_pct']:.1f}%", s["pushes"], f"{s['seconds']:.0f}"]
            for k, s in summaries.items()]
    table = markdown_table(["method", "validated fraction (mean over objects)", "validated fraction (pooled)",
                            "objects with >= 1 validated pose", "% of objects", "pushes", "worker-seconds"], rows)
    nn_counts = [r["n_poses"] for r in results["nn"]]
    return (f"{len(objects)} objects of the test split (never trained on), the shipped `{HAND}` checkpoint; "
            f"each object rests in its default pose and is pushed 0.20 m along +x by the floating hand "
            f"(validator default physics, the data engine's criterion).\n\n{table}\n"
            f"{verdict(summaries)}\n\n"
            "Protocol: 200 poses per object (seeded per object); the first 50 are all pushed (validated fraction); "
            "then 25 at a time until one succeeds (>= 1 validated pose of 200 — early stopping gives exactly the "
            "count that pushing all 200 would). The Nearest Neighbor baseline returns the stored poses of the training "
            f"frame nearest in BPS: {np.mean(nn_counts):.0f} per object on average (min {min(nn_counts)}, max "
            f"{max(nn_counts)}), fewer than 200; its index: `{nn_index.name}`. \"worker-seconds\" sums the per-object "
            "time (sampling + pushes) over the worker processes.\n\n"
            f"![validated fraction per object]({plot_name})\n")


def verdict(summaries: dict[str, dict[str, Any]]) -> str:
    """Sentences comparing DDPM-100 with the paper's anchor, the target, DDIM-10 and the NN baseline."""
    ddpm, ddim, nn = summaries["ddpm100"], summaries["ddim10"], summaries["nn"]
    paper_pct = 100.0 * PAPER_COVERED / PAPER_OBJECTS
    gap = ddpm["covered_pct"] - TARGET_COVERED_PCT
    target = (f"meets the >= {TARGET_COVERED_PCT:.0f}% target" if gap >= 0
              else f"misses the >= {TARGET_COVERED_PCT:.0f}% target by {-gap:.1f} points")
    return (f"DDPM-100 has >= 1 validated pose on {ddpm['covered_pct']:.1f}% of the test objects (paper: "
            f"{PAPER_COVERED:.0f} of {PAPER_OBJECTS}, {paper_pct:.0f}%), which {target}. "
            f"DDIM-10 validates {ddim['pooled_validated_fraction']:.1%} of its poses against DDPM-100's "
            f"{ddpm['pooled_validated_fraction']:.1%} and covers {ddim['covered']} objects against {ddpm['covered']}; "
            f"Nearest Neighbor validates {nn['pooled_validated_fraction']:.1%} and covers {nn['covered']}.")


def plot_validated_fractions(results: dict[str, list[dict[str, Any]]], sources: dict[str, PoseSource], path: Path) -> Path:
    """Histogram of the per-object validated fraction, one outline per method."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 4), dpi=110)
    bins = np.linspace(0.0, 1.0, 21)
    for key, records in results.items():
        axis.hist([r["validated_fraction"] for r in records], bins=bins, histtype="step", linewidth=1.6,
                  label=sources[key].label())
    axis.set_xlabel("validated fraction of the object's first 50 poses")
    axis.set_ylabel("test objects")
    axis.legend()
    axis.grid(True, alpha=0.3)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
    return path
