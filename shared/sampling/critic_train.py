"""Training the success critic (`critic.py`) on labelled samples (`evaluation/critic_data.py` builds them).

    gd2p critic train --data data/critic-allegro-train --val data/critic-allegro-val --out ckpt.pt

Each record is one object in one push frame (a yaw in D), the diffusion samples pushed there and their
outcomes. The object's BPS is computed here by the sampler checkpoint's own encoder from (object, yaw),
as the sampler service computes it for a request, so the critic sees the same features in training and
in use. The checkpoint kept is the one with the best ROC AUC on the val records (held-out objects of
the val split), checked every `eval_every` steps; the test split is never touched here.

Checkpoint: a `torch.save` dict of tensors and plain values (`weights_only` loadable) with the format,
hand, config, weights, the sampler checkpoint id whose BPS basis it was trained with, and a manifest
(data, steps, val metrics), also written beside it as `<file>.manifest.json`.
"""
from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.stats import rankdata
from torch.nn import functional as F

from shared.contracts.messages import DirectionFrame
from shared.sampling.capture_bps import CaptureSettings, FrameCaptures, build_captures, capture_store_spec
from shared.sampling.checkpoint import SHIPPED_DIR, atomic_torch_save, verify_file, write_manifest
from shared.sampling.critic import ERROR_FLOOR_M, CriticConfig, SuccessCritic
from shared.sampling.critic_features import CONTACT_FEATURES, contact_features
from shared.sampling.dataset import DEFAULT_POSE_INDEX, Frame
from shared.sampling.sampling import PoseSampler

CRITIC_FORMAT = "gd2p-critic-v1"
CRITIC_ENV = "GD2P_CRITIC_CHECKPOINT_{hand}"  # e.g. GD2P_CRITIC_CHECKPOINT_ALLEGRO=/path/to.pt; "none": no critic
CAPTURES_DIR = "captures"  # a critic data directory's camera captures (`record_captures`)
TOP_K = 6  # the plans a request rolls out (PipelineSettings.max_plans): the precision that matters


class CriticError(ValueError):
    """Critic data or checkpoint that cannot be used (missing, empty, wrong format or hand)."""


def critic_frame(object_id: str, yaw_deg: float) -> DirectionFrame:
    """The push frame of a labelled object: resting at the origin, turned by `yaw_deg`, pushed along world +x."""
    from shared.world.objects import load_object
    from shared.world.push_outcome import object_pose

    obj = load_object(object_id)
    return DirectionFrame(object_pose=object_pose(obj.T_D_O(None, math.radians(yaw_deg))), yaw_deg=0.0)


@dataclass(frozen=True)
class CriticData:
    """Labelled poses of many objects: poses [N, 25] and their contact features [N, CONTACT_FEATURES],
    `group` [N] into bps [R, n_basis] (one row per object view: its mesh, or one camera capture of it),
    outcomes [N]; `captured` [N] marks the rows whose view is a capture."""

    poses: torch.Tensor
    group: torch.Tensor
    bps: torch.Tensor
    success: torch.Tensor
    error_m: torch.Tensor
    object_ids: list[str]  # per BPS row
    contact: torch.Tensor
    captured: torch.Tensor | None = None  # None: mesh views only

    def __len__(self) -> int:
        return len(self.poses)

    def captured_rows(self) -> torch.Tensor:
        return torch.zeros(len(self), dtype=torch.bool) if self.captured is None else self.captured

    @staticmethod
    def concat(parts: list[CriticData]) -> CriticData:
        """One data set of several (each part's groups renumbered past the previous parts' BPS rows)."""
        if len(parts) == 1:
            return parts[0]
        offsets = np.cumsum([0] + [len(p.bps) for p in parts[:-1]]).tolist()
        return CriticData(torch.cat([p.poses for p in parts]),
                          torch.cat([p.group + offset for p, offset in zip(parts, offsets, strict=True)]),
                          torch.cat([p.bps for p in parts]), torch.cat([p.success for p in parts]),
                          torch.cat([p.error_m for p in parts]), [i for p in parts for i in p.object_ids],
                          torch.cat([p.contact for p in parts]),
                          torch.cat([p.captured_rows() for p in parts]) if any(p.captured is not None for p in parts)
                          else None)

    def subset(self, rows: torch.Tensor) -> CriticData:
        """The poses `rows` (a bool mask or indices), keeping every BPS row."""
        return CriticData(self.poses[rows], self.group[rows], self.bps, self.success[rows], self.error_m[rows],
                          self.object_ids, self.contact[rows], self.captured_rows()[rows])


def read_records(directory: str | Path) -> list[dict[str, Any]]:
    """The records of a critic data directory (JSON lines; a torn last line is skipped)."""
    path = Path(directory) / "records.jsonl"
    if not path.is_file():
        raise CriticError(f"no critic data at {path} (build it with `gd2p critic data`)")
    records = {}
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        records[row["key"]] = row  # a key recorded again replaces the earlier record, as the store reads it
    if not records:
        raise CriticError(f"{path} holds no records")
    return list(records.values())


def critic_frames(records: list[dict[str, Any]]) -> list[Frame]:
    """The training frames of records (as the sampler's data knows them): default resting pose, the record's yaw."""
    return [Frame(r["object_id"], DEFAULT_POSE_INDEX, math.radians(r["yaw_deg"])) for r in records]


def record_captures(directory: str | Path, records: list[dict[str, Any]], workers: int = 2,
                    progress: bool = True) -> FrameCaptures:
    """Camera captures of each record's object in its frame (`capture_bps`, the sampler's training captures:
    3 cameras, 2 captures per frame), stored with their points in `directory`/captures (resumable)."""
    fingerprint = "critic:" + ",".join(sorted({r["checkpoint_id"] for r in records}))
    return build_captures(critic_frames(records), Path(directory) / CAPTURES_DIR, CaptureSettings(), fingerprint,
                          workers=workers, progress=progress, keep_points=True, desc="captures of critic objects")


def encode_records(records: list[dict[str, Any]], sampler: PoseSampler, progress: Callable[[], object] | None = None,
                   captures: FrameCaptures | None = None) -> CriticData:
    """The records as tensors, each object's BPS computed by `sampler`'s encoder and the poses' contact
    features from the same surface points. With `captures` (of `records`' frames, in order) each record also
    comes as each of its reconstructed captures: BPS and contact features from the captured points in the
    reconstruction's D, the poses moved into that frame (p + shift), the outcomes the same physical pushes'."""
    from shared.robots.hands import load_hand

    bps: list[np.ndarray] = []
    poses: list[np.ndarray] = []
    group: list[np.ndarray] = []
    success: list[np.ndarray] = []
    error: list[np.ndarray] = []
    ids: list[str] = []
    contact: list[torch.Tensor] = []
    captured: list[np.ndarray] = []

    def add_view(points_d: np.ndarray, poses_d: np.ndarray, record: dict[str, Any], is_capture: bool) -> None:
        group.append(np.full(len(poses_d), len(bps)))
        bps.append(sampler.encode_points(points_d, record["object_id"]))
        poses.append(poses_d)
        contact.append(contact_features(load_hand(record["hand"]), torch.as_tensor(poses_d),
                                        torch.as_tensor(points_d, dtype=torch.float32)))
        success.append(np.asarray(record["success"], dtype=np.float32))
        error.append(np.asarray(record["position_error_m"], dtype=np.float32))
        ids.append(record["object_id"])
        captured.append(np.full(len(poses_d), is_capture))

    for index, record in enumerate(records):
        frame = critic_frame(record["object_id"], record["yaw_deg"])
        points_d, _, _ = sampler.points_in_d(record["object_id"], frame)
        poses_d = np.asarray(record["poses_d"], dtype=np.float32)
        add_view(points_d, poses_d, record, False)
        for variant in range(0 if captures is None else captures.ok.shape[1]):
            if captures is not None and captures.ok[index, variant]:
                moved = poses_d.copy()
                moved[:, :2] += captures.shift_xy[index, variant]
                add_view(captures.points(index, variant), moved, record, True)
        if progress is not None:
            progress()
    return CriticData(torch.as_tensor(np.concatenate(poses)), torch.as_tensor(np.concatenate(group)),
                      torch.as_tensor(np.stack(bps)), torch.as_tensor(np.concatenate(success)),
                      torch.as_tensor(np.concatenate(error)), ids, torch.cat(contact),
                      torch.as_tensor(np.concatenate(captured)) if captures is not None else None)


@dataclass(frozen=True)
class CriticTraining:
    steps: int = 2000
    batch_size: int = 512
    learning_rate: float = 1e-3
    weight_decay: float = 1e-2
    error_weight: float = 0.5  # the position-error head's share of the loss
    eval_every: int = 250
    seed: int = 0
    # The share of each batch drawn from camera-capture views (`encode_records(captures=...)`), the rest from
    # mesh views: the planner meets both (a mesh when told one, captures under the default perception).
    capture_fraction: float = 0.0
    config: CriticConfig = field(default_factory=lambda: CriticConfig(contact_dim=CONTACT_FEATURES))


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (the Mann-Whitney statistic, ties counted half); NaN without both classes."""
    labels = np.asarray(labels, dtype=bool)
    positives, negatives = int(labels.sum()), int((~labels).sum())
    if positives == 0 or negatives == 0:
        return float("nan")
    ranks = rankdata(scores)
    return float((ranks[labels].sum() - positives * (positives + 1) / 2) / (positives * negatives))


@torch.no_grad()
def evaluate(model: SuccessCritic, data: CriticData) -> dict[str, Any]:
    """ROC AUC, and the success rate of each view's TOP_K best-scored poses against all its poses (a view: an
    object seen as its mesh or as one capture, so "views" counts objects × views); with
    capture views, the same for the mesh and the capture views apart ("mesh", "captures")."""
    metrics = _metrics(model, data)
    captured = data.captured_rows()
    if captured.any():
        metrics["mesh"] = _metrics(model, data.subset(~captured))
        metrics["captures"] = _metrics(model, data.subset(captured))
    return metrics


def _metrics(model: SuccessCritic, data: CriticData) -> dict[str, Any]:
    model.eval()
    logits, _ = model(data.poses, data.bps, data.group, data.contact)
    scores, labels, groups = logits.numpy(), data.success.numpy() > 0.5, data.group.numpy()
    overall = [labels[groups == g].mean() for g in np.unique(groups)]
    return {"roc_auc": round(roc_auc(scores, labels), 4), f"top{TOP_K}_success": round(top_k_success(scores, labels, groups), 4),
            "all_success": round(float(np.mean(overall)), 4), "poses": len(labels),
            "objects": len({data.object_ids[g] for g in np.unique(groups)}), "views": len(np.unique(groups))}


def top_k_success(scores: np.ndarray, labels: np.ndarray, groups: np.ndarray, k: int = TOP_K) -> float:
    """The mean over objects (`groups`) of the success rate of each object's k best-scored poses."""
    rates = []
    for g in np.unique(groups):
        rows = np.flatnonzero(groups == g)
        rates.append(labels[rows[np.argsort(-scores[rows], kind="stable")[:k]]].mean())
    return float(np.mean(rates))


def train_critic(train: CriticData, val: CriticData, settings: CriticTraining = CriticTraining(),
                 progress: Callable[[dict[str, Any]], object] | None = None) -> tuple[SuccessCritic, dict[str, Any]]:
    """The critic with the best val ROC AUC seen during training, and the metrics history."""
    torch.manual_seed(settings.seed)
    model = SuccessCritic(settings.config)
    model.set_statistics(train.bps, train.poses, train.contact)
    optimiser = torch.optim.AdamW(model.parameters(), lr=settings.learning_rate, weight_decay=settings.weight_decay)
    generator = torch.Generator().manual_seed(settings.seed)
    target_error = torch.log(train.error_m + ERROR_FLOOR_M)
    best: tuple[float, dict[str, torch.Tensor], int] = (-1.0, {}, 0)
    history: list[dict[str, Any]] = []
    draw = _batch_rows(train, settings, generator)
    for step in range(1, settings.steps + 1):
        model.train()
        rows = draw()
        logits, log_error = model(train.poses[rows], train.bps, train.group[rows], train.contact[rows])
        loss = (F.binary_cross_entropy_with_logits(logits, train.success[rows])
                + settings.error_weight * F.smooth_l1_loss(log_error, target_error[rows]))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % settings.eval_every == 0 or step == settings.steps:
            metrics: dict[str, Any] = {"step": step, "loss": round(float(loss.detach()), 4), "val": evaluate(model, val)}
            history.append(metrics)
            if metrics["val"]["roc_auc"] > best[0]:
                best = (metrics["val"]["roc_auc"], {k: v.clone() for k, v in model.state_dict().items()}, step)
            if progress is not None:
                progress(metrics)
    model.load_state_dict(best[1])
    return model.eval(), {"best_step": best[2], "history": history}


def _batch_rows(train: CriticData, settings: CriticTraining, generator: torch.Generator) -> Callable[[], torch.Tensor]:
    """A function drawing a batch's rows: `capture_fraction` of them from the capture views, the rest from the
    mesh views (uniform over all rows without captures)."""
    captured = train.captured_rows()
    if settings.capture_fraction <= 0 or not captured.any():
        return lambda: torch.randint(len(train), (settings.batch_size,), generator=generator)
    if not 0 < settings.capture_fraction <= 1:
        raise CriticError(f"capture_fraction must be in [0, 1], got {settings.capture_fraction}")
    from_captures = round(settings.batch_size * settings.capture_fraction)
    capture_rows, mesh_rows = torch.nonzero(captured).squeeze(1), torch.nonzero(~captured).squeeze(1)
    if not len(mesh_rows):
        mesh_rows = capture_rows

    def draw() -> torch.Tensor:
        picked = [capture_rows[torch.randint(len(capture_rows), (from_captures,), generator=generator)],
                  mesh_rows[torch.randint(len(mesh_rows), (settings.batch_size - from_captures,), generator=generator)]]
        return torch.cat(picked)
    return draw


def save_critic(model: SuccessCritic, path: str | Path, hand: str, sampler_checkpoint_id: str,
                manifest: dict[str, Any]) -> Path:
    data = {"format": CRITIC_FORMAT, "hand": hand, "config": model.config.to_dict(),
            "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
            "sampler_checkpoint_id": sampler_checkpoint_id, "manifest": manifest}
    out = atomic_torch_save(data, path)
    write_manifest(out, {**manifest, "hand": hand, "format": CRITIC_FORMAT, "sampler_checkpoint_id": sampler_checkpoint_id},
                   indent=1, sort_keys=False)
    return out


@dataclass(frozen=True)
class LoadedCritic:
    hand: str
    model: SuccessCritic
    sampler_checkpoint_id: str
    manifest: dict[str, Any]


def default_critic_path(hand: str) -> Path | None:
    """Where the sampler looks for `hand`'s critic: $GD2P_CRITIC_CHECKPOINT_<HAND> ("none": no critic), else the
    shipped file."""
    override = os.environ.get(CRITIC_ENV.format(hand=hand.upper()))
    if override is not None:
        return None if override.lower() == "none" else Path(override).expanduser()
    return SHIPPED_DIR / f"{hand}_critic.pt"


@torch.no_grad()
def success_probabilities(critic: SuccessCritic, hand: str, bps: np.ndarray, points_d: np.ndarray,
                          poses_d: np.ndarray) -> np.ndarray:
    """[K] P(success) of a floating-hand push by `hand` from each pose [K, 25] in D of the object with
    BPS [n_basis] of its surface points [N, 3] in D."""
    from shared.robots.hands import load_hand

    poses = torch.as_tensor(np.asarray(poses_d, dtype=np.float32))
    contact = (contact_features(load_hand(hand), poses, torch.as_tensor(np.asarray(points_d, dtype=np.float32)))
               if critic.uses_contact else None)
    logits, _ = critic(poses, torch.as_tensor(np.asarray(bps, dtype=np.float32)).reshape(1, -1), None, contact)
    return torch.sigmoid(logits).double().numpy()


def success_probabilities_for(critic: SuccessCritic, hand: str, sampler: PoseSampler, obj: Any,
                              frame: DirectionFrame | None, poses_d: np.ndarray) -> np.ndarray:
    """[K] P(success) of poses [K, 25] in `frame`'s D, whatever they came from, read from `obj` as `sampler` encodes
    it (the encoding the critic was trained on); SamplerInputError when the object cannot be encoded."""
    points_d, _, label = sampler.points_in_d(obj, frame)
    return success_probabilities(critic, hand, sampler.encode_points(points_d, label), points_d, poses_d)


def load_critic(path: str | Path) -> LoadedCritic:
    path = Path(path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, ValueError) as exc:
        raise CriticError(f"cannot read critic checkpoint {path}: {exc}") from exc
    if not isinstance(data, dict) or data.get("format") != CRITIC_FORMAT:
        raise CriticError(f"{path} is not a {CRITIC_FORMAT} checkpoint")
    verify_file(path, CriticError)
    model = SuccessCritic(CriticConfig.from_dict(data["config"]))
    model.load_state_dict(data["state_dict"])
    return LoadedCritic(data["hand"], model.eval(), data["sampler_checkpoint_id"], data.get("manifest", {}))


def manifest_for(train_dirs: list[str], val_dir: str | Path, settings: CriticTraining, train: CriticData,
                 val: CriticData, result: dict[str, Any], started: float, command: str) -> dict[str, Any]:
    train_data = train_dirs[0] if len(train_dirs) == 1 else train_dirs  # a single one as before
    captures = ({"captures": {str(d): capture_store_spec(Path(d) / CAPTURES_DIR) for d in [*train_dirs, str(val_dir)]}}
                if train.captured is not None else {})
    return {"command": command, "train_data": train_data, "val_data": str(val_dir), **captures,
            "train_poses": len(train), "train_objects": len(set(train.object_ids)), "val_poses": len(val),
            "val_objects": len(set(val.object_ids)), "settings": {**asdict(settings), "config": settings.config.to_dict()},
            "best_step": result["best_step"], "val": result["history"][-1]["val"] if result["history"] else None,
            "best_val": next((h["val"] for h in result["history"] if h["step"] == result["best_step"]), None),
            "train_s": round(time.time() - started, 1)}
