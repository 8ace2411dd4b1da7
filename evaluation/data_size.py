"""Data size (the paper's table of objects with >= 1 feasible pose): `gd2p eval data-size`.

The sampler is trained on 2%, 20%, 50% and 100% of the training objects (`gd2p train --fraction F
--seed S`, whole objects kept or dropped, 3 seeds each) with the settings of the shipped checkpoint
(2000 steps, batch 256, default model, the Allegro dataset), and each model's coverage is measured
on a fixed, seeded subset of the test split: 200 DDPM-100 samples per object pushed in the
floating-hand validator until one succeeds (evaluation/coverage.py). The paper reports 41.7, 102.7,
110.3 and 169.3 of 300 unseen objects; the target is a monotone curve with 100% >= 75%.

One model is trained at a time with `workers` torch threads when the cores are idle (training is
what parallelises there; on a busy machine 1 thread, see `training_threads`);
its coverage is then measured over `workers` spawn processes. Trained models land in
`models/f{F}_s{S}.pt` (resumable by the training code), every finished unit — a model, an object's
coverage — is a record in the experiment's store, so a killed run resumes where it stopped.

Budget (2 idle cores): training ~45 s per model at 2 threads (data loading included); pushes ~25/s
over 2 processes. An object costs 50 pushes when one of its first 50 poses validates and up to 200
when none does. Measured here, even a 2% model (4 training objects) had a validated pose among the
first 50 on 12 of 12 test objects, so a model costs ~40 x 50 pushes ~ 1.5 min: 12 models ~ 27 min
for FULL's 40 objects (more if many objects go uncovered: +6 s each).
"""
from __future__ import annotations

import hashlib
import itertools
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
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
    summarize,
)
from evaluation.report import markdown_table, write_experiment
from evaluation.store import ResultStore

NAME = "data-size"
TITLE = "Data size: test objects with >= 1 validated pose"
SUBSET_SEED = 0
PAPER_OBJECTS = 300
PAPER_COVERED = {0.02: (41.67, 10.21), 0.2: (102.67, 5.85), 0.5: (110.33, 29.67), 1.0: (169.33, 15.18)}


@dataclass(frozen=True)
class DataSizeSettings:
    """The protocol of one data-size run (pinned in the store)."""

    fractions: tuple[float, ...] = (0.02, 0.2, 0.5, 1.0)
    seeds: tuple[int, ...] = (0, 1, 2)
    train_steps: int = 2000  # the shipped checkpoint's budget
    batch_size: int = 256
    test_objects: int = 40  # of the 185 test objects: the 12 models must fit a 2-core session
    subset_seed: int = SUBSET_SEED
    samples: int = 200

    def coverage(self) -> CoverageSettings:
        return CoverageSettings(samples=self.samples, fraction_poses=min(50, self.samples), hand=HAND)

    def to_dict(self) -> dict[str, Any]:
        return {"fractions": list(self.fractions), "seeds": list(self.seeds), "train_steps": self.train_steps,
                "batch_size": self.batch_size, "test_objects": self.test_objects, "subset_seed": self.subset_seed,
                "coverage": self.coverage().to_dict()}


FULL = DataSizeSettings()
QUICK = DataSizeSettings(fractions=(0.2, 1.0), seeds=(0,), train_steps=200, test_objects=4, samples=50)


def object_subset(count: int, seed: int = SUBSET_SEED) -> list[str]:
    """A fixed, seeded subset of `count` test-split objects (a larger count extends a smaller one;
    the everyday procedural families rank after the rest of the library, so the subsets chosen
    before they existed stay the same)."""
    from shared.world.objects import library_generation, list_object_ids

    ids = list_object_ids("test")
    if not 1 <= count <= len(ids):
        raise CoverageError(f"the test split has {len(ids)} objects; cannot take {count}")
    rank = {i: (library_generation(i), hashlib.sha256(f"gd2p-data-size:{seed}:{i}".encode()).hexdigest()) for i in ids}
    return sorted(ids, key=lambda i: rank[i])[:count]


def model_name(fraction: float, seed: int) -> str:
    return f"f{fraction:g}_s{seed}"


# ----------------------------------------------------------------------------- training
def idle_cores(interval_s: float = 0.5) -> float | None:
    """Cores left idle by every process on the machine over `interval_s` (from /proc/stat; None elsewhere)."""
    def sample() -> tuple[int, int]:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return sum(fields), fields[3] + fields[4]  # total and idle + iowait jiffies

    try:
        total_0, idle_0 = sample()
        time.sleep(interval_s)
        total_1, idle_1 = sample()
    except (OSError, ValueError, IndexError):
        return None
    cores = os.cpu_count() or 1
    return cores * (idle_1 - idle_0) / max(1, total_1 - total_0)


def training_threads(workers: int) -> int:
    """`workers` torch threads when that many cores are idle, else 1.

    Training is the parallel part here, but torch threads on a busy machine stall at their OpenMP
    barriers whenever one is pre-empted (DESIGN.md §6; measured here with other jobs running:
    200 steps 21/s at 1 thread, 2.6/s at 2), so extra threads are used only on idle cores.
    """
    spare = idle_cores()
    if workers <= 1 or spare is None:
        return max(1, workers)
    return workers if spare >= workers - 0.25 else 1


def train_model(dataset_dir: Path, path: Path, fraction: float, seed: int, settings: DataSizeSettings,
                threads: int) -> dict[str, Any]:
    """Train (or finish training) one model with the project's training code; its record."""
    import torch

    from services.sampler.checkpoint import load_checkpoint
    from services.sampler.train import RunOptions, TrainConfig, train

    previous = torch.get_num_threads()
    torch.set_num_threads(max(1, threads))
    started = time.perf_counter()
    try:
        config = TrainConfig(steps=settings.train_steps, batch_size=settings.batch_size, fraction=fraction, seed=seed)
        command = (f"gd2p train --dataset {dataset_dir} --hand {HAND} --out {path} --steps {settings.train_steps} "
                   f"--fraction {fraction:g} --seed {seed} --threads {threads}")
        result = train(dataset_dir, HAND, path, config, RunOptions(command=command))
    finally:
        torch.set_num_threads(previous)
    manifest = load_checkpoint(path).manifest
    return {"fraction": fraction, "seed": seed, "checkpoint": path.name,
            "train_objects": manifest["dataset"]["train_objects"], "train_poses": manifest["dataset"]["train_poses"],
            "final_train_loss": result.final_train_loss, "final_val_loss": result.final_val_loss,
            "train_seconds": round(time.perf_counter() - started, 1), "train_threads": threads}


# ----------------------------------------------------------------------------- the experiment
def run(out: Path, quick: bool = False, workers: int = 2, dataset_dir: Path = DEFAULT_DATASET) -> Path:
    """Train and measure every (fraction, seed) into `out/data-size/`; returns the report path."""
    started = time.perf_counter()
    settings = QUICK if quick else FULL
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise CoverageError(f"no {HAND} training store at {dataset_dir}; build it with "
                            f"`gd2p dataset build --split train --hand {HAND} ... --out {dataset_dir}`")
    directory = Path(out) / NAME
    objects = object_subset(settings.test_objects, settings.subset_seed)
    from services.sampler.dataset import load_pose_dataset

    fingerprint = load_pose_dataset(dataset_dir, HAND).fingerprint
    store = ResultStore(directory, {**settings.to_dict(), "objects": objects, "dataset_sha256": fingerprint})
    models, coverage = {}, {}
    with CoveragePool(workers) as pool:
        for fraction in settings.fractions:
            for seed in settings.seeds:
                name = model_name(fraction, seed)
                models[name] = _trained(store, dataset_dir, directory / "models" / f"{name}.pt", fraction, seed, settings,
                                        workers)
                source = DiffusionSource(str(directory / "models" / f"{name}.pt"), "ddpm")
                coverage[name] = pool.measure(source, objects, store, f"coverage/{name}", settings.coverage(), desc=f"coverage {name}")
    rows = table_rows(settings, models, coverage)
    plot = plot_coverage(settings, rows, len(objects), directory / "coverage_vs_fraction.png")
    body = report_body(settings, objects, rows, models, plot.name)
    summary = {"objects": objects, "settings": settings.to_dict(), "per_fraction": rows,
               "models": {name: {**models[name], **summarize(coverage[name])} for name in models}}
    return write_experiment(directory, TITLE, body, summary, time.perf_counter() - started, quick)


def _trained(store: ResultStore, dataset_dir: Path, path: Path, fraction: float, seed: int, settings: DataSizeSettings,
             workers: int) -> dict[str, Any]:
    key = f"model/{model_name(fraction, seed)}"
    if not (store.done(key) and path.is_file()):
        store.add(key, train_model(dataset_dir, path, fraction, seed, settings, training_threads(workers)))
    return store.records[key]


# ----------------------------------------------------------------------------- tables and plots
def table_rows(settings: DataSizeSettings, models: dict[str, dict[str, Any]],
               coverage: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per fraction: objects covered per seed, their mean and std, mean validated fraction, training size."""
    rows = []
    for fraction in settings.fractions:
        names = [model_name(fraction, seed) for seed in settings.seeds]
        covered = [summarize(coverage[n])["covered"] for n in names]
        rows.append({
            "fraction": fraction, "covered_per_seed": covered,
            "covered_mean": float(np.mean(covered)), "covered_std": float(np.std(covered, ddof=1)) if len(covered) > 1 else 0.0,
            "validated_fraction_mean": float(np.mean([summarize(coverage[n])["mean_validated_fraction"] for n in names])),
            "train_objects": [models[n]["train_objects"] for n in names], "train_poses": [models[n]["train_poses"] for n in names],
            "final_val_loss": [models[n]["final_val_loss"] for n in names],
        })
    return rows


def report_body(settings: DataSizeSettings, objects: Sequence[str], rows: list[dict[str, Any]],
                models: dict[str, dict[str, Any]], plot_name: str) -> str:
    n = len(objects)
    table = markdown_table(
        ["data size", "train objects", "train poses", f"objects with >= 1 validated pose (of {n})", "% of objects",
         "per seed", "validated fraction", f"paper (of {PAPER_OBJECTS})"],
        [[f"{r['fraction']:.0%}", _span(r["train_objects"]), _span(r["train_poses"]),
          f"{r['covered_mean']:.2f} ± {r['covered_std']:.2f}", f"{100 * r['covered_mean'] / n:.1f}%",
          ", ".join(map(str, r["covered_per_seed"])), f"{r['validated_fraction_mean']:.1%}", _paper(r["fraction"])]
         for r in rows])
    model_table = markdown_table(
        ["model", "train objects", "train poses", "final train loss", "final val loss", "train seconds", "torch threads"],
        [[name, m["train_objects"], m["train_poses"], _loss(m["final_train_loss"]), _loss(m["final_val_loss"]),
          f"{m['train_seconds']:.0f}", m.get("train_threads", "–")]
         for name, m in models.items()])
    return (f"Each model: `gd2p train --fraction F --seed S --steps {settings.train_steps}` (batch {settings.batch_size}, "
            f"default model, the {HAND} training store), then {settings.samples} DDPM-100 samples per object on a fixed "
            f"subset of **{n} test-split objects** (seeded hash order, subset seed {settings.subset_seed}; the paper used "
            f"300), each pushed 0.20 m along +x in the floating-hand validator until one succeeds. Mean ± std over seeds "
            f"{', '.join(map(str, settings.seeds))}.\n\n{table}\n{verdict(rows, n)}\n\n"
            f"![objects covered vs data fraction]({plot_name})\n\n### Models\n\n{model_table}\n"
            f"Test objects: {', '.join(objects)}.\n")


def verdict(rows: list[dict[str, Any]], n_objects: int) -> str:
    """Whether coverage grows monotonically with data, and how the largest fraction compares with the target."""
    steps = [f"{a['fraction']:.0%}→{b['fraction']:.0%}" for a, b in itertools.pairwise(rows) if b["covered_mean"] < a["covered_mean"]]
    monotone = ("Coverage grows monotonically with the data size." if not steps
                else f"Coverage is not monotone: it falls at {', '.join(steps)}.")
    last = rows[-1]
    pct = 100.0 * last["covered_mean"] / n_objects
    gap = pct - TARGET_COVERED_PCT
    target = (f"meets the >= {TARGET_COVERED_PCT:.0f}% target" if gap >= 0
              else f"misses the >= {TARGET_COVERED_PCT:.0f}% target by {-gap:.1f} points")
    fractions = [r["validated_fraction_mean"] for r in rows]
    trend = " → ".join(f"{v:.1%}" for v in fractions)
    quality = ("rises monotonically" if all(b >= a for a, b in itertools.pairwise(fractions)) else "is not monotone")
    return (f"{monotone} At {last['fraction']:.0%} of the data, {last['covered_mean']:.1f} of {n_objects} test "
            f"objects ({pct:.1f}%) have >= 1 validated pose, which {target} (paper: "
            f"{100 * PAPER_COVERED[1.0][0] / PAPER_OBJECTS:.0f}% at 100%). The fraction of sampled poses that "
            f"validate {quality} with the data size ({trend}).")


def _span(values: Sequence[int]) -> str:
    return str(values[0]) if min(values) == max(values) else f"{min(values)}–{max(values)}"


def _paper(fraction: float) -> str:
    if fraction not in PAPER_COVERED:
        return "–"
    mean, std = PAPER_COVERED[fraction]
    return f"{mean:.2f} ± {std:.2f} ({100 * mean / PAPER_OBJECTS:.0f}%)"


def _loss(value: float | None) -> str:
    return "–" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.4f}"


def plot_coverage(settings: DataSizeSettings, rows: list[dict[str, Any]], n_objects: int, path: Path) -> Path:
    """Objects covered vs data fraction: every seed as a point, the mean as a line, the paper's means scaled to N."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 4), dpi=110)
    fractions = [r["fraction"] for r in rows]
    for r in rows:
        axis.scatter([r["fraction"]] * len(r["covered_per_seed"]), r["covered_per_seed"], color="tab:blue", alpha=0.6, s=22)
    axis.plot(fractions, [r["covered_mean"] for r in rows], "-o", color="tab:blue", label="this run (mean over seeds)")
    paper = [(f, PAPER_COVERED[f][0] * n_objects / PAPER_OBJECTS) for f in fractions if f in PAPER_COVERED]
    if paper:
        axis.plot(*zip(*paper, strict=True), "--s", color="tab:gray", label=f"paper, scaled to {n_objects} objects")
    axis.axhline(TARGET_COVERED_PCT / 100 * n_objects, color="tab:red", linestyle=":", label=f"target {TARGET_COVERED_PCT:.0f}%")
    axis.set_xscale("log")
    axis.minorticks_off()
    axis.set_xticks(fractions, [f"{f:.0%}" for f in fractions])
    axis.set_ylim(0, n_objects * 1.05)
    axis.set_xlabel("training data (fraction of the training objects)")
    axis.set_ylabel(f"test objects with >= 1 validated pose (of {n_objects})")
    axis.grid(True, alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
    return path
