"""Training the pose diffusion model on the data engine's store (`gd2p train`).

Hyper-parameters are the paper's (appendix table): Adam, lr 1e-4, weight decay 1e-6, beta1 0.9,
eps 1e-8, gradient clipping at 1.0, cosine learning-rate schedule with 500 warm-up steps, EMA with
power 0.75, DDPM-100 epsilon loss. Two CPU-driven departures, both configurable: batch 256
instead of 16 (per-step overhead dominates a small model on CPU; 256 is where throughput was
measured, docs/architecture.md §Compute) and a budget counted in optimiser steps (`--steps`, or `--epochs` over the
training poses) instead of 200 epochs of 1.3 M poses.

Data: poses of one hand; objects are split, not poses — a seeded ~10% of the objects is held out
for the validation loss, so the val curve measures generalisation to unseen shapes. `--fraction`
keeps a seeded subset of the remaining training objects (the data-size experiment).

Outputs for `--out CKPT`: CKPT (EMA weights only, optionally fp16, with the pose normaliser, the
BPS basis and a manifest), CKPT.manifest.json, CKPT.loss.png (train / val loss curves) and
CKPT.train.pt (full training state). Re-running the same command resumes from CKPT.train.pt; the
run continues bit-for-bit as if it had not stopped (same batches, same noise).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import diffusers
import numpy as np
import torch
from diffusers.optimization import get_cosine_schedule_with_warmup
from tqdm import tqdm

from shared.sampling.capture_bps import CaptureSettings, FrameCaptures, build_captures, capture_store_spec
from shared.sampling.checkpoint import (
    SamplerCheckpoint,
    load_training_state,
    save_checkpoint,
    save_training_state,
)
from shared.sampling.dataset import (
    SURFACE_POINTS,
    SURFACE_SEED,
    PoseDataset,
    choose_fraction,
    frame_bps,
    load_pose_dataset,
    split_objects,
)
from shared.sampling.diffusion import (
    DiffusionConfigError,
    PoseNormalizer,
    check_guidance_scale,
    denoising_loss,
    make_ema,
    make_noise_scheduler,
)
from shared.sampling.model import DenoiserConfig, PoseDenoiser, parameter_count
from shared.world.bps import BasisPointSet

log = logging.getLogger(__name__)

DEFAULT_STEPS = 20_000
BALANCES = ("poses", "objects")  # TrainConfig.balance
LOG_EVERY = 50  # steps per point of the training-loss curve


class TrainingError(ValueError):
    """A training run that cannot start or resume (bad settings, changed data, mismatched resume)."""


@dataclass
class TrainConfig:
    """Everything that determines a training run's result (stored with it; a resume must match)."""

    steps: int | None = None  # total optimiser steps; None: from `epochs`, else DEFAULT_STEPS
    epochs: float | None = None  # passes over the training poses (sampled with replacement)
    batch_size: int = 256
    lr: float = 1e-4
    weight_decay: float = 1e-6
    beta1: float = 0.9
    beta2: float = 0.999
    adam_eps: float = 1e-8
    grad_clip: float = 1.0
    warmup_steps: int = 500
    val_fraction: float = 0.1
    fraction: float = 1.0
    seed: int = 0
    model: DenoiserConfig = field(default_factory=DenoiserConfig)
    # How a batch draws its poses: "poses", uniformly over the training poses (objects with many valid poses
    # dominate), or "objects", an object uniformly then one of its poses (every object weighs the same, as in
    # the evaluation, which pushes the same number of samples per object).
    balance: str = "poses"
    # Rows of a batch trained without their object (the model's "no object" embedding), so the checkpoint can
    # sample with classifier-free guidance; > 0 needs `model.unconditional`.
    condition_dropout: float = 0.0
    # Rows of a batch conditioned on a camera capture of their frame instead of its mesh BPS, the pose moved into
    # the reconstruction's frame (shared/sampling/capture_bps.py); > 0 needs `captures`, the capture store.
    capture_fraction: float = 0.0
    captures: str | None = None

    def check(self) -> None:
        if self.balance not in BALANCES:
            raise TrainingError(f"--balance must be one of {', '.join(BALANCES)}, got {self.balance!r}")
        if not 0.0 <= self.condition_dropout < 1.0:
            raise TrainingError(f"--condition-dropout must be in [0, 1), got {self.condition_dropout}")
        if not 0.0 <= self.capture_fraction <= 1.0:
            raise TrainingError(f"--capture-fraction must be in [0, 1], got {self.capture_fraction}")
        if (self.capture_fraction > 0) != (self.captures is not None):
            raise TrainingError("--capture-fraction and --captures go together")
        if (self.condition_dropout > 0) != self.model.unconditional:
            raise TrainingError("condition dropout and the model's unconditional embedding go together "
                                f"(dropout {self.condition_dropout}, unconditional {self.model.unconditional})")
        if self.steps is not None and self.epochs is not None:
            raise TrainingError("give --steps or --epochs, not both")
        if self.steps is not None and self.steps < 1:
            raise TrainingError(f"--steps must be >= 1, got {self.steps}")
        if self.epochs is not None and not self.epochs > 0:
            raise TrainingError(f"--epochs must be > 0, got {self.epochs}")
        if self.batch_size < 1 or not self.lr > 0 or self.warmup_steps < 0 or not self.grad_clip > 0:
            raise TrainingError(f"invalid optimiser settings: batch {self.batch_size}, lr {self.lr}, "
                                f"warm-up {self.warmup_steps}, grad clip {self.grad_clip}")

    def total_steps(self, train_poses: int) -> int:
        if self.steps is not None:
            return self.steps
        if self.epochs is not None:
            return max(1, math.ceil(self.epochs * train_poses / self.batch_size))
        return DEFAULT_STEPS

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["model"] = self.model.to_dict()
        if self.balance == "poses":  # the setting every run had before it existed: states saved then still resume
            del out["balance"]
        for name in ("condition_dropout", "capture_fraction", "captures"):  # likewise
            if not out[name]:
                del out[name]
        return out


@dataclass
class RunOptions:
    """How a run is carried out; does not change its result."""

    device: str = "auto"  # "auto" | "cpu" | "cuda" | "cuda:N"
    val_every: int = 500
    val_max_poses: int = 4096  # validation loss over at most this many held-out poses (fixed noise)
    checkpoint_every: int = 1000
    snapshot_every: int = 0  # > 0: also ship the EMA weights every this many steps (CKPT.stepN.pt) to choose among on val
    half: bool = False  # ship fp16 weights
    progress: bool = True
    resume: bool = True
    command: str | None = None  # recorded in the manifest
    guidance_scale: float = 1.0  # written into the shipped checkpoint: its classifier-free guidance weight
    should_stop: Callable[[int], bool] | None = None  # polled after every step: save and return early
    capture_workers: int = 2  # processes capturing the training frames when the capture store is not finished


@dataclass
class TrainResult:
    checkpoint_path: Path | None  # None when the run stopped early
    state_path: Path
    plot_path: Path | None
    start_step: int
    step: int
    total_steps: int
    stopped: bool
    final_train_loss: float | None
    final_val_loss: float | None
    samples_per_s: float
    parameters: int
    history: dict[str, list[list[float]]]


@dataclass
class TrainingTensors:
    """Tensors on the training device: normalised poses, their frame rows, the frames' BPS."""

    poses: torch.Tensor
    frame_index: torch.Tensor
    bps: torch.Tensor
    pose_weights: torch.Tensor | None = None  # [N] a pose's chance to be drawn; None: uniform
    failed: torch.Tensor | None = None  # [N] bool: a failed push (a model that learns from failures); None: none

    def batch(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The rows' normalised poses, their BPS and whether each push failed (None: all succeeded)."""
        failed = None if self.failed is None else self.failed[rows]
        return self.poses[rows], self.bps[self.frame_index[rows]], failed

    def draw(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """`count` pose rows, with replacement."""
        if self.pose_weights is None:
            return torch.randint(0, len(self.poses), (count,), generator=generator, device=self.poses.device)
        return torch.multinomial(self.pose_weights, count, replacement=True, generator=generator)


@dataclass
class CaptureTensors:
    """The training frames' camera captures on the device (shared/sampling/capture_bps.py)."""

    bps: torch.Tensor  # [F, V, n]
    shift: torch.Tensor  # [F, V, 25] added to a normalised pose conditioned on the capture (only x, y non-zero)
    ok: torch.Tensor  # [F, V] bool: reconstructed

    @classmethod
    def from_captures(cls, captures: FrameCaptures, normalizer: PoseNormalizer, device: torch.device) -> CaptureTensors:
        _, half = normalizer.centre_and_half_range
        shift = torch.zeros(*captures.shift_xy.shape[:2], len(half))
        shift[..., :2] = torch.from_numpy(captures.shift_xy) / half[:2]
        return cls(torch.from_numpy(captures.bps).to(device), shift.to(device), torch.from_numpy(captures.ok).to(device))

    def swap(self, frame_rows: torch.Tensor, poses: torch.Tensor, bps: torch.Tensor, fraction: float,
             generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """A `fraction` of the rows conditioned on one of their frame's captures instead of the mesh BPS,
        each such pose moved into its capture's reconstructed frame."""
        count = len(frame_rows)
        variant = torch.randint(0, self.ok.shape[1], (count,), generator=generator, device=frame_rows.device)
        use = (torch.rand(count, generator=generator, device=frame_rows.device) < fraction) & self.ok[frame_rows, variant]
        bps = torch.where(use[:, None], self.bps[frame_rows, variant], bps)
        poses = poses + use[:, None] * self.shift[frame_rows, variant]
        return poses, bps


def object_balanced_weights(object_ids: np.ndarray) -> torch.Tensor:
    """[N] 1 / (poses of the pose's object): every object is drawn equally often, each of its poses equally."""
    _, inverse, counts = np.unique(object_ids, return_inverse=True, return_counts=True)
    return torch.from_numpy(1.0 / counts[inverse]).float()


def output_paths(out: Path) -> dict[str, Path]:
    return {"state": out.with_name(out.name + ".train.pt"), "plot": out.with_name(out.name + ".loss.png")}


def snapshot_path(out: Path, step: int) -> Path:
    """Where `--snapshot-every` writes the checkpoint of `step` (CKPT.stepN.pt beside CKPT)."""
    return out.with_name(f"{out.stem}.step{step}{out.suffix}")


def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    resolved = torch.device(device)
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise TrainingError(f"device {device!r} requested but CUDA is not available")
    return resolved


# ----------------------------------------------------------------------------- the run
def train(dataset_dir: str | Path, hand: str, out: str | Path, config: TrainConfig | None = None,
          options: RunOptions | None = None) -> TrainResult:
    """Train (or resume training) a sampler for `hand` on the store at `dataset_dir`; see module doc."""
    config, options = config or TrainConfig(), options or RunOptions()
    config.check()
    try:
        check_guidance_scale(options.guidance_scale, config.model)
    except DiffusionConfigError as exc:
        raise TrainingError(f"--guidance-scale: {exc}") from exc
    out = Path(out)
    paths = output_paths(out)
    device = resolve_device(options.device)
    dataset = load_pose_dataset(dataset_dir, hand, with_failures=config.model.outcome)
    train_set, val_set = _split(dataset, config)
    resumed = _load_resume_state(paths["state"], config, dataset, train_set, val_set) if options.resume else None
    return _Run(config, options, dataset, train_set, val_set, device, resumed).fit(paths, out, Path(dataset_dir))


def _split(dataset: PoseDataset, config: TrainConfig) -> tuple[PoseDataset, PoseDataset]:
    train_ids, val_ids = split_object_ids(dataset.objects(), config.val_fraction, config.fraction, config.seed)
    return dataset.subset(train_ids), dataset.subset(val_ids)


def split_object_ids(object_ids: list[str], val_fraction: float, fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """(trained on, held out for the validation loss): the objects of a run with these settings
    (a checkpoint's manifest has them under "config"), as `train` splits them."""
    train_ids, val_ids = split_objects(object_ids, val_fraction, seed)
    return choose_fraction(train_ids, fraction, seed), val_ids


def _load_resume_state(path: Path, config: TrainConfig, dataset: PoseDataset, train_set: PoseDataset,
                       val_set: PoseDataset) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    state = load_training_state(path)
    if state["dataset_sha256"] != dataset.fingerprint:
        raise TrainingError(f"{path}: the dataset changed since this run started; delete the file or pass --restart")
    differing = sorted(k for k, v in config.to_dict().items() if state["config"].get(k) != v)
    if differing:
        raise TrainingError(f"{path}: cannot resume with different settings ({', '.join(differing)}); "
                            "use the original ones or pass --restart")
    if state["train_objects"] != train_set.objects() or state["val_objects"] != val_set.objects():
        raise TrainingError(f"{path}: the object split differs from the saved run's")
    return state


class _Run:
    """One training session: builds everything, restores a saved state, loops, saves."""

    def __init__(self, config: TrainConfig, options: RunOptions, dataset: PoseDataset, train_set: PoseDataset,
                 val_set: PoseDataset, device: torch.device, resumed: dict[str, Any] | None):
        self.config, self.options, self.device = config, options, device
        self.dataset, self.train_set, self.val_set = dataset, train_set, val_set
        self.total_steps = config.total_steps(len(train_set))
        self.bps = BasisPointSet()
        train_bps = torch.from_numpy(frame_bps(train_set.frames, self.bps, progress=options.progress))
        val_bps = torch.from_numpy(frame_bps(val_set.frames, self.bps, progress=options.progress))
        # The range of the successful poses, failures or not: a failure far outside it must not squeeze it.
        self.normalizer = PoseNormalizer.fit(torch.from_numpy(train_set.successes().poses))
        self.train_data = self._device_data(train_set, train_bps)
        self.capture_summary: dict[str, Any] = {}
        self.captures = self._captures(train_set) if config.capture_fraction > 0 else None
        if self.captures is not None:  # the model's BPS statistics over both kinds of input it trains on
            train_bps = torch.cat([train_bps, self.captures.bps[self.captures.ok].cpu()])
        if config.balance == "objects":
            self.train_data.pose_weights = object_balanced_weights(train_set.object_ids).to(device)
        # The validation loss is over successes only, comparable between models that learn failures and not.
        val_successes = val_set.successes()
        self.val_data = self._device_data(val_successes, val_bps) if len(val_successes) else None
        with torch.random.fork_rng(devices=[]):  # seeded initial weights, global RNG untouched
            torch.manual_seed(config.seed)
            self.model = PoseDenoiser(config.model).to(device)
        self.model.set_bps_statistics(train_bps.mean(0), train_bps.std(0, unbiased=False))
        self.scheduler = make_noise_scheduler()
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr, betas=(config.beta1, config.beta2),
                                          eps=config.adam_eps, weight_decay=config.weight_decay, amsgrad=False, fused=True)
        self.lr_schedule = get_cosine_schedule_with_warmup(self.optimizer, config.warmup_steps, self.total_steps)
        self.ema = make_ema(self.model)
        self.generator = torch.Generator(device=device).manual_seed(config.seed)
        self.step = 0
        self.loss_sum, self.loss_count = 0.0, 0
        self.history: dict[str, list[list[float]]] = {"train": [], "val": []}
        self.wall_time_s = 0.0
        if resumed is not None:
            self._restore(resumed)
        self.start_step = self.step

    def _device_data(self, subset: PoseDataset, frame_features: torch.Tensor) -> TrainingTensors:
        poses = self.normalizer.normalize(torch.from_numpy(subset.poses))
        failed = None if subset.failed is None else torch.from_numpy(subset.failed).to(self.device)
        return TrainingTensors(poses.to(self.device), torch.from_numpy(subset.frame_index).to(self.device),
                               frame_features.to(self.device), failed=failed)

    def _captures(self, train_set: PoseDataset) -> CaptureTensors:
        assert self.config.captures is not None
        captures = build_captures(train_set.frames, self.config.captures, CaptureSettings(), self.dataset.fingerprint,
                                  workers=self.options.capture_workers, progress=self.options.progress)
        self.capture_summary = captures.summary()  # for the manifest
        log.info("captures: %s", self.capture_summary)
        return CaptureTensors.from_captures(captures.for_frames(train_set.frames), self.normalizer, self.device)

    # ------------------------------------------------------------------ loop
    def fit(self, paths: dict[str, Path], out: Path, dataset_dir: Path) -> TrainResult:
        log.info("training %s sampler: %d poses / %d objects (val %d / %d), %d params, steps %d..%d on %s",
                 self.dataset.hand, len(self.train_set), len(self.train_set.objects()), len(self.val_set),
                 len(self.val_set.objects()), parameter_count(self.model), self.step, self.total_steps, self.device)
        started, stopped = time.perf_counter(), False
        self.out, self.dataset_dir = out, dataset_dir
        with tqdm(total=self.total_steps, initial=self.step, desc=f"train {self.dataset.hand}", unit="step",
                  disable=not self.options.progress, dynamic_ncols=True) as bar:
            while self.step < self.total_steps:
                self._train_step()
                self._after_step(bar, paths)
                if self.options.should_stop is not None and self.step < self.total_steps and self.options.should_stop(self.step):
                    stopped = True
                    break
        session_s = time.perf_counter() - started
        self.wall_time_s += session_s
        samples_per_s = (self.step - self.start_step) * self.config.batch_size / max(session_s, 1e-9)
        if not stopped and (not self.history["val"] or self.history["val"][-1][0] != self.step):
            self._validate()
        self._save_state(paths["state"])
        checkpoint_path = plot_path = None
        if not stopped:
            plot_path = plot_loss_curves(self.history, paths["plot"], title=self._plot_title())
            checkpoint_path = save_checkpoint(self._shipped(dataset_dir, samples_per_s), out, half=self.options.half)
        return TrainResult(checkpoint_path, paths["state"], plot_path, self.start_step, self.step, self.total_steps, stopped,
                           _last(self.history["train"]), _last(self.history["val"]), samples_per_s,
                           parameter_count(self.model), self.history)

    def _train_step(self) -> None:
        self.model.train()
        rows = self.train_data.draw(self.config.batch_size, self.generator)
        poses, bps, failed = self.train_data.batch(rows)
        if self.captures is not None:
            poses, bps = self.captures.swap(self.train_data.frame_index[rows], poses, bps, self.config.capture_fraction,
                                            self.generator)
        loss = denoising_loss(self.model, self.scheduler, poses, bps, self.generator, self.config.condition_dropout, failed)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip, foreach=True)
        self.optimizer.step()
        self.lr_schedule.step()
        self.ema.step(self.model.parameters())
        self.step += 1
        self.loss_sum += float(loss.detach())
        self.loss_count += 1

    def _after_step(self, bar: tqdm, paths: dict[str, Path]) -> None:
        bar.update(1)
        if self.step % LOG_EVERY == 0 or self.step == self.total_steps:
            self.history["train"].append([self.step, self.loss_sum / self.loss_count])
            self.loss_sum, self.loss_count = 0.0, 0
            postfix = {"loss": f"{self.history['train'][-1][1]:.4f}", "lr": f"{self.lr_schedule.get_last_lr()[0]:.2e}"}
            if self.history["val"]:
                postfix["val"] = f"{self.history['val'][-1][1]:.4f}"
            bar.set_postfix(postfix, refresh=False)
        if self.step % self.options.val_every == 0:
            self._validate()
        if self.step % self.options.checkpoint_every == 0 and self.step < self.total_steps:
            self._save_state(paths["state"])
        if self.options.snapshot_every > 0 and self.step % self.options.snapshot_every == 0 and self.step < self.total_steps:
            save_checkpoint(self._shipped(self.dataset_dir, 0.0), snapshot_path(self.out, self.step), half=self.options.half)

    @torch.no_grad()
    def _validate(self) -> None:
        """Loss of the EMA weights on the held-out objects, with the same noise every time."""
        if self.val_data is None:
            return
        generator = torch.Generator(device=self.device).manual_seed(self.config.seed + 1)
        count = min(len(self.val_data.poses), self.options.val_max_poses)
        rows = torch.randperm(len(self.val_data.poses), generator=generator, device=self.device)[:count]
        self.ema.store(self.model.parameters())
        self.ema.copy_to(self.model.parameters())
        self.model.eval()
        total = 0.0
        for chunk in rows.split(1024):
            poses, bps, _ = self.val_data.batch(chunk)
            total += float(denoising_loss(self.model, self.scheduler, poses, bps, generator)) * len(chunk)
        self.ema.restore(self.model.parameters())
        self.history["val"].append([self.step, total / count])

    # ------------------------------------------------------------------ state
    def _save_state(self, path: Path) -> None:
        save_training_state({
            "step": self.step,
            "total_steps": self.total_steps,
            "config": self.config.to_dict(),
            "dataset_sha256": self.dataset.fingerprint,
            "train_objects": self.train_set.objects(),
            "val_objects": self.val_set.objects(),
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "lr_schedule": self.lr_schedule.state_dict(),
            "ema": self.ema.state_dict(),
            "generator": self.generator.get_state(),
            "loss_accumulator": [self.loss_sum, self.loss_count],
            "history": self.history,
            "wall_time_s": self.wall_time_s,
        }, path)

    def _restore(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.lr_schedule.load_state_dict(state["lr_schedule"])
        self.ema.load_state_dict(state["ema"])
        self.ema.to(self.device)
        self.generator.set_state(state["generator"])
        self.step = int(state["step"])
        self.loss_sum, self.loss_count = float(state["loss_accumulator"][0]), int(state["loss_accumulator"][1])
        self.history = {k: [list(p) for p in v] for k, v in state["history"].items()}
        self.wall_time_s = float(state.get("wall_time_s", 0.0))
        log.info("resuming at step %d of %d", self.step, self.total_steps)

    def _shipped(self, dataset_dir: Path, samples_per_s: float) -> SamplerCheckpoint:
        joint_lower, joint_upper = hand_joint_limits(self.dataset.hand)
        ema_model = PoseDenoiser(self.config.model)
        ema_model.load_state_dict(self.model.state_dict())
        self.ema.copy_to(ema_model.parameters())
        return SamplerCheckpoint(
            hand=self.dataset.hand, model_config=self.config.model,
            state_dict={k: v.detach().cpu() for k, v in ema_model.state_dict().items()},
            normalizer=self.normalizer, joint_lower=joint_lower, joint_upper=joint_upper,
            bps=self.bps, surface_points=SURFACE_POINTS, surface_seed=SURFACE_SEED,
            manifest=self._manifest(dataset_dir, samples_per_s), guidance_scale=self.options.guidance_scale)

    def _manifest(self, dataset_dir: Path, samples_per_s: float) -> dict[str, Any]:
        return {
            "hand": self.dataset.hand,
            "dataset": {"path": str(dataset_dir), "sha256": self.dataset.fingerprint, "poses_total": len(self.dataset),
                        "train_poses": len(self.train_set), "train_objects": len(self.train_set.objects()),
                        "val_poses": len(self.val_set), "val_objects": len(self.val_set.objects()),
                        "failed_poses_trained": _count(self.train_set.failed),
                        "frames": len(self.dataset.frames), "frames_skipped": self.dataset.skipped_summary()},
            "command": self.options.command,
            "config": self.config.to_dict(),
            **({"captures": {**capture_store_spec(self.config.captures), **self.capture_summary}}
               if self.config.captures is not None else {}),
            "steps": self.step,
            "final_train_loss": _last(self.history["train"]),
            "final_val_loss": _last(self.history["val"]),
            "parameters": parameter_count(self.model),
            "weights_dtype": "float16" if self.options.half else "float32",
            "train_samples_per_s_last_session": round(samples_per_s, 1),
            "wall_time_s": round(self.wall_time_s, 1),
            "device": str(self.device),
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "versions": {"torch": torch.__version__, "diffusers": diffusers.__version__},
        }

    def _plot_title(self) -> str:
        return (f"{self.dataset.hand}: {len(self.train_set)} train poses / {len(self.train_set.objects())} objects, "
                f"val {len(self.val_set.objects())} held-out objects")


def hand_joint_limits(hand: str) -> tuple[torch.Tensor, torch.Tensor]:
    """[16] lower and upper joint limits of `hand` from its URDF, in the pose vector's joint order."""
    from shared.robots.hands import HAND_SPECS
    from shared.robots.hands.urdf import read_urdf

    if hand not in HAND_SPECS:
        raise TrainingError(f"unknown hand {hand!r}; known hands: {sorted(HAND_SPECS)}")
    spec = HAND_SPECS[hand]
    robot = read_urdf(spec.urdf_path())
    joints = [robot.joint(name) for name in spec.joint_names]
    return (torch.tensor([j.lower for j in joints], dtype=torch.float32),
            torch.tensor([j.upper for j in joints], dtype=torch.float32))


def _count(flags: np.ndarray | None) -> int:
    return 0 if flags is None else int(flags.sum())


def _last(points: list[list[float]]) -> float | None:
    return float(points[-1][1]) if points else None


def plot_loss_curves(history: dict[str, list[list[float]]], path: Path, title: str = "") -> Path:
    """Train (running mean per LOG_EVERY steps) and validation loss per step, log scale, as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 4), dpi=110)
    for name, style in (("train", "-"), ("val", "o-")):
        points = np.asarray(history.get(name) or [], dtype=np.float64).reshape(-1, 2)
        if len(points):
            axis.plot(points[:, 0], points[:, 1], style, label=f"{name} loss", markersize=3)
    axis.set_xlabel("optimiser step")
    axis.set_ylabel("denoising MSE (epsilon)")
    axis.set_yscale("log")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend()
    axis.set_title(title, fontsize=9)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    figure.savefig(tmp)
    plt.close(figure)
    tmp.replace(path)
    return path
