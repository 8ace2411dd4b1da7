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

Dataset v2 (`--dataset data/allegro-v2 --yaw random --train-steps N --seeds 0`): every test object is
turned by a seeded yaw, as the v2 data is, and the subset is taken one shape family after another
(`sampler_quality.quality_objects`), so it holds the never-trained family too; its main column is the
validated fraction with its interval clustered by object.
"""
from __future__ import annotations

import dataclasses
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
    pose_trials,
    summarize,
    world_markdown,
    world_rows,
    world_text,
)
from evaluation.report import markdown_table, write_experiment
from evaluation.stats import success_interval
from evaluation.store import ResultStore
from shared.world.objects import UNSEEN_FAMILIES
from shared.world.objects.catalog import resolve_library_id

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
    lr: float = 1e-4  # the paper's; dataset v2's model was chosen on val at 1e-3
    batch_size: int = 256
    test_objects: int = 40  # of the 185 test objects: the 12 models must fit a 2-core session
    subset_seed: int = SUBSET_SEED
    samples: int = 200
    yaw: str = "zero"  # "random": each test object turned by a seeded yaw, the subset taken family by family
    world: str = "exact"  # "real": each object pushed in a drawn execution world (evaluation/coverage.py)
    cameras: int = 0  # 1-3: the model samples for what that many cameras see of the object

    def __post_init__(self) -> None:
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise CoverageError(f"give one or more distinct seeds, got {list(self.seeds)}")
        if self.train_steps < 1 or self.test_objects < 1:
            raise CoverageError(f"training steps and test objects must be >= 1, got {self.train_steps} and {self.test_objects}")
        if not self.lr > 0:
            raise CoverageError(f"the learning rate must be > 0, got {self.lr}")

    def coverage(self) -> CoverageSettings:
        return CoverageSettings(samples=self.samples, fraction_poses=min(50, self.samples), hand=HAND, yaw=self.yaw,
                                world=self.world, cameras=self.cameras)

    def to_dict(self) -> dict[str, Any]:
        # coverage().to_dict() carries the yaw only when it is random, and the learning rate appears only when it
        # is not the paper's: the pin of the first runs stays the same
        lr = {} if self.lr == DataSizeSettings.lr else {"lr": self.lr}
        return {"fractions": list(self.fractions), "seeds": list(self.seeds), "train_steps": self.train_steps, **lr,
                "batch_size": self.batch_size, "test_objects": self.test_objects, "subset_seed": self.subset_seed,
                "coverage": self.coverage().to_dict()}


FULL = DataSizeSettings()
QUICK = DataSizeSettings(fractions=(0.2, 1.0), seeds=(0,), train_steps=200, test_objects=4, samples=50)


def test_objects(settings: DataSizeSettings) -> list[str]:
    """The measured objects: the first protocol's seeded subset, or at a random yaw one family after another."""
    if settings.yaw == "random":
        from evaluation.sampler_quality import quality_objects

        return quality_objects(split="test", count=settings.test_objects)
    return object_subset(settings.test_objects, settings.subset_seed)


def result_directory(out: Path, yaw: str = "zero", tag: str | None = None, world: str = "exact", cameras: int = 0) -> Path:
    """`<out>/data-size[-<world>[-cameraN]][-random-yaw][-TAG]/`: one store per world, protocol and training store
    (the exact world told the mesh keeps the name of the runs made before worlds existed)."""
    name = NAME + CoverageSettings(world=world, cameras=cameras).world_suffix + ("-random-yaw" if yaw == "random" else "")
    return Path(out) / (f"{name}-{tag}" if tag else name)


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
    barriers whenever one is pre-empted (docs/architecture.md §Compute; measured here with other jobs running:
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

    from shared.sampling.checkpoint import load_checkpoint
    from shared.sampling.train import RunOptions, TrainConfig, train

    previous = torch.get_num_threads()
    torch.set_num_threads(max(1, threads))
    started = time.perf_counter()
    try:
        config = TrainConfig(steps=settings.train_steps, batch_size=settings.batch_size, fraction=fraction, seed=seed,
                             lr=settings.lr)
        command = (f"gd2p train --dataset {dataset_dir} --hand {HAND} --out {path} --steps {settings.train_steps} "
                   f"--lr {settings.lr:g} --fraction {fraction:g} --seed {seed} --threads {threads}")
        result = train(dataset_dir, HAND, path, config, RunOptions(command=command))
    finally:
        torch.set_num_threads(previous)
    manifest = load_checkpoint(path).manifest
    return {"fraction": fraction, "seed": seed, "checkpoint": path.name,
            "train_objects": manifest["dataset"]["train_objects"], "train_poses": manifest["dataset"]["train_poses"],
            "final_train_loss": result.final_train_loss, "final_val_loss": result.final_val_loss,
            "train_seconds": round(time.perf_counter() - started, 1), "train_threads": threads}


# ----------------------------------------------------------------------------- the experiment
def run(out: Path, quick: bool = False, workers: int = 2, dataset_dir: Path = DEFAULT_DATASET, yaw: str = "zero",
        train_steps: int | None = None, seeds: Sequence[int] | None = None, objects: int | None = None,
        lr: float | None = None, tag: str | None = None, world: str = "exact", cameras: int = 0) -> Path:
    """Train and measure every (fraction, seed) into `result_directory(out, yaw, tag, world, cameras)`; returns the
    report path.

    `train_steps`, `lr`, `seeds`, `objects` and `yaw` replace the protocol's (FULL, or QUICK with `quick`). A run of
    another world than exact-told-the-mesh measures each model in the exact world too, so the two stand side by side
    for the same models (a model is the expensive part and is not kept between runs).
    """
    started = time.perf_counter()
    base = QUICK if quick else FULL
    settings = dataclasses.replace(
        base, yaw=yaw, train_steps=train_steps or base.train_steps, lr=lr or base.lr, seeds=tuple(seeds) if seeds else base.seeds,
        test_objects=objects or base.test_objects, world=world, cameras=cameras)
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise CoverageError(f"no {HAND} training store at {dataset_dir}; build it with "
                            f"`gd2p dataset build --split train --hand {HAND} ... --out {dataset_dir}`")
    directory = result_directory(out, yaw, tag, world, cameras)
    object_ids = test_objects(settings)
    from shared.sampling.dataset import load_pose_dataset

    fingerprint = load_pose_dataset(dataset_dir, HAND).fingerprint
    store = ResultStore(directory, {**settings.to_dict(), "objects": object_ids, "dataset_sha256": fingerprint})
    models, coverage, exact = {}, {}, {}
    exact_settings = dataclasses.replace(settings.coverage(), world="exact", cameras=0)
    with CoveragePool(workers) as pool:
        for fraction in settings.fractions:
            for seed in settings.seeds:
                name = model_name(fraction, seed)
                models[name] = _trained(store, dataset_dir, directory / "models" / f"{name}.pt", fraction, seed, settings,
                                        workers)
                source = DiffusionSource(str(directory / "models" / f"{name}.pt"), "ddpm")
                coverage[name] = pool.measure(source, object_ids, store, f"coverage/{name}", settings.coverage(), desc=f"coverage {name}")
                if settings.coverage().perceived:
                    exact[name] = pool.measure(source, object_ids, store, f"coverage-exact/{name}", exact_settings,
                                               desc=f"coverage {name}, exact")
    rows = table_rows(settings, models, coverage)
    plot = plot_coverage(settings, rows, len(object_ids), directory / "coverage_vs_fraction.png")
    worlds = world_rows(*(_by_fraction(settings, records) for records in (coverage, exact))) if exact else []
    body = (report_body(settings, object_ids, rows, models, plot.name)
            + world_markdown(worlds, settings.coverage(), "the same models, measured in this run"))
    summary = {"objects": object_ids, "settings": settings.to_dict(), "per_fraction": rows, "exact_beside": worlds,
               "models": {name: {**models[name], **summarize(coverage[name])} for name in models}}
    return write_experiment(directory, TITLE, body, summary, time.perf_counter() - started, quick)


def _by_fraction(settings: DataSizeSettings, coverage: dict[str, list[dict[str, Any]]]) -> dict[str, list[dict[str, Any]]]:
    """Each data fraction's records pooled over its seeds, labelled by the fraction."""
    return {f"{fraction:.0%} of the data": [r for seed in settings.seeds for r in coverage[model_name(fraction, seed)]]
            for fraction in settings.fractions}


def _trained(store: ResultStore, dataset_dir: Path, path: Path, fraction: float, seed: int, settings: DataSizeSettings,
             workers: int) -> dict[str, Any]:
    key = f"model/{model_name(fraction, seed)}"
    if not (store.done(key) and path.is_file()):
        store.add(key, train_model(dataset_dir, path, fraction, seed, settings, training_threads(workers)))
    return store.records[key]


# ----------------------------------------------------------------------------- tables and plots
def table_rows(settings: DataSizeSettings, models: dict[str, dict[str, Any]],
               coverage: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per fraction: the validated fraction (pooled over seeds, 95% interval clustered by object), the
    never-trained family's, objects covered per seed with mean and std, training sizes and losses."""
    rows = []
    for fraction in settings.fractions:
        names = [model_name(fraction, seed) for seed in settings.seeds]
        covered = [summarize(coverage[n])["covered"] for n in names]
        records = [r for n in names for r in coverage[n]]
        validated = success_interval(pose_trials(records))
        unseen = [r for r in records if resolve_library_id(r["object"]).family in UNSEEN_FAMILIES]
        rows.append({
            "fraction": fraction, "covered_per_seed": covered,
            "covered_mean": float(np.mean(covered)), "covered_std": float(np.std(covered, ddof=1)) if len(covered) > 1 else 0.0,
            "validated_fraction_mean": float(np.mean([summarize(coverage[n])["mean_validated_fraction"] for n in names])),
            "validated_fraction": validated.as_dict(),
            "unseen_family": ({"objects": len({r["object"] for r in unseen}), **success_interval(pose_trials(unseen)).as_dict()}
                              if unseen else None),
            "train_objects": [models[n]["train_objects"] for n in names], "train_poses": [models[n]["train_poses"] for n in names],
            "final_val_loss": [models[n]["final_val_loss"] for n in names],
        })
    return rows


def _validated_cell(row: dict[str, Any]) -> str:
    v = row["validated_fraction"]
    return f"**{v['value']:.1%}** [{v['low']:.1%}, {v['high']:.1%}]"


def _unseen_cell(row: dict[str, Any]) -> str:
    u = row.get("unseen_family")
    return "–" if not u else f"{u['value']:.1%} [{u['low']:.1%}, {u['high']:.1%}] ({u['objects']} objects)"


def report_body(settings: DataSizeSettings, objects: Sequence[str], rows: list[dict[str, Any]],
                models: dict[str, dict[str, Any]], plot_name: str) -> str:
    n = len(objects)
    unseen = ", ".join(UNSEEN_FAMILIES)
    table = markdown_table(
        ["data size", "train objects", "train poses", "validated fraction (pooled, 95% CI by object)",
         f"never-trained family ({unseen})", f"objects with >= 1 validated pose (of {n})", "% of objects",
         "per seed", f"paper (of {PAPER_OBJECTS})"],
        [[f"{r['fraction']:.0%}", _span(r["train_objects"]), _span(r["train_poses"]), _validated_cell(r), _unseen_cell(r),
          f"{r['covered_mean']:.2f} ± {r['covered_std']:.2f}", f"{100 * r['covered_mean'] / n:.1f}%",
          ", ".join(map(str, r["covered_per_seed"])), _paper(r["fraction"])]
         for r in rows])
    model_table = markdown_table(
        ["model", "train objects", "train poses", "final train loss", "final val loss", "train seconds", "torch threads"],
        [[name, m["train_objects"], m["train_poses"], _loss(m["final_train_loss"]), _loss(m["final_val_loss"]),
          f"{m['train_seconds']:.0f}", m.get("train_threads", "–")]
         for name, m in models.items()])
    placement = ("each turned about z by a seeded yaw, taken one shape family after another"
                 if settings.yaw == "random" else "seeded hash order, subset seed " + str(settings.subset_seed))
    return (f"Each model: `gd2p train --fraction F --seed S --steps {settings.train_steps} --lr {settings.lr:g}` "
            f"(batch {settings.batch_size}, "
            f"default model, the {HAND} training store), then {settings.samples} DDPM-100 samples per object on a fixed "
            f"subset of **{n} test-split objects** ({placement}; the paper used 300), the first "
            f"{settings.coverage().fraction_poses} pushed 0.20 m along +x by the floating hand in "
            f"{world_text(settings.coverage())} (validated fraction), then more until one succeeds. Seeds {', '.join(map(str, settings.seeds))}: the validated "
            f"fraction pools them, the coverage is mean ± std over them.\n\n{table}\n{verdict(rows, n)}\n\n"
            f"![validated fraction and objects covered vs data fraction]({plot_name})\n\n### Models\n\n{model_table}\n"
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
    fractions = [r["validated_fraction"]["value"] for r in rows]
    trend = " → ".join(f"{v:.1%}" for v in fractions)
    quality = ("rises monotonically" if all(b >= a for a, b in itertools.pairwise(fractions)) else "is not monotone")
    return (f"The fraction of sampled poses that validate {quality} with the data size ({trend}). {monotone} At "
            f"{last['fraction']:.0%} of the data, {last['covered_mean']:.1f} of {n_objects} test objects ({pct:.1f}%) "
            f"have >= 1 validated pose, which {target} (paper: {100 * PAPER_COVERED[1.0][0] / PAPER_OBJECTS:.0f}% at 100%).")


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
    """Left: the validated fraction vs data fraction with its interval; right: objects covered (every
    seed a point, the mean a line, the paper's means scaled to N)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, (quality, covered) = plt.subplots(1, 2, figsize=(11, 4), dpi=110)
    fractions = [r["fraction"] for r in rows]
    values = np.array([[r["validated_fraction"][k] for k in ("value", "low", "high")] for r in rows]) * 100
    quality.errorbar(fractions, values[:, 0], yerr=[values[:, 0] - values[:, 1], values[:, 2] - values[:, 0]], fmt="-o",
                     color="tab:green", capsize=4, label="validated fraction (95% CI by object)")
    unseen = [(r["fraction"], 100 * r["unseen_family"]["value"]) for r in rows if r.get("unseen_family")]
    if unseen:
        quality.plot(*zip(*unseen, strict=True), ":^", color="tab:purple", label=f"never-trained family ({', '.join(UNSEEN_FAMILIES)})")
    quality.set_ylim(0, 100)
    quality.set_ylabel("validated fraction of DDPM-100 samples (%)")
    for r in rows:
        covered.scatter([r["fraction"]] * len(r["covered_per_seed"]), r["covered_per_seed"], color="tab:blue", alpha=0.6, s=22)
    covered.plot(fractions, [r["covered_mean"] for r in rows], "-o", color="tab:blue", label="this run (mean over seeds)")
    paper = [(f, PAPER_COVERED[f][0] * n_objects / PAPER_OBJECTS) for f in fractions if f in PAPER_COVERED]
    if paper:
        covered.plot(*zip(*paper, strict=True), "--s", color="tab:gray", label=f"paper, scaled to {n_objects} objects")
    covered.axhline(TARGET_COVERED_PCT / 100 * n_objects, color="tab:red", linestyle=":", label=f"target {TARGET_COVERED_PCT:.0f}%")
    covered.set_ylim(0, n_objects * 1.05)
    covered.set_ylabel(f"test objects with >= 1 validated pose (of {n_objects})")
    for axis in (quality, covered):
        axis.set_xscale("log")
        axis.minorticks_off()
        axis.set_xticks(fractions, [f"{f:.0%}" for f in fractions])
        axis.set_xlabel("training data (fraction of the training objects)")
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
    return path
