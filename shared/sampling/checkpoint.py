"""Sampler checkpoints: the shipped file (EMA weights + everything sampling needs) and training state.

Shipped checkpoint (`save_checkpoint` / `load_checkpoint`), a `torch.save` dict of tensors and
plain values, loaded with `weights_only=True` (no pickled code runs on load):
    format, hand, model_config, state_dict (EMA weights and BPS statistics; fp32 or fp16),
    pose_normalizer {low, high}, joint_limits {lower, upper}, bps {n, radius, seed, basis},
    surface {points, seed}, manifest {dataset hash, command, final losses, ...}
The manifest is also written beside it as `<file>.manifest.json` for people and tools, with the file's SHA-256:
every model loader (checkpoint, critic, NN index) checks the file against it (`verify_file`).

Training state (`save_training_state` / `load_training_state`): the live model, EMA, optimiser,
learning-rate schedule, random-generator state, loss history and the object split — what `gd2p
train` needs to resume. It stays next to the run (`<out>.train.pt`) and is never shipped.

Every write is atomic (temporary file in the same directory, fsync, rename): a crash mid-save
leaves the previous file intact.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from shared.atomic import atomic_write_text, atomic_writer
from shared.sampling.diffusion import PoseNormalizer
from shared.sampling.model import DenoiserConfig, PoseDenoiser
from shared.world.bps import BasisPointSet

CHECKPOINT_FORMAT = "gd2p-sampler-v1"
TRAINING_STATE_FORMAT = "gd2p-sampler-train-v1"


class CheckpointError(ValueError):
    """A checkpoint file that is missing, unreadable, or not a sampler checkpoint."""


@dataclass
class SamplerCheckpoint:
    """Everything needed to sample poses for one hand."""

    hand: str
    model_config: DenoiserConfig
    state_dict: dict[str, torch.Tensor]
    normalizer: PoseNormalizer
    joint_lower: torch.Tensor  # [16]
    joint_upper: torch.Tensor  # [16]
    bps: BasisPointSet
    surface_points: int
    surface_seed: int
    manifest: dict[str, Any] = field(default_factory=dict)
    # Classifier-free guidance weight the sampler uses (`sample_normalized`); != 1 needs an unconditional model.
    guidance_scale: float = 1.0

    def build_model(self) -> PoseDenoiser:
        """The denoiser with these weights, in fp32 and eval mode."""
        model = PoseDenoiser(self.model_config)
        model.load_state_dict({k: v.float() for k, v in self.state_dict.items()})
        return model.eval()

    def to_dict(self, half: bool = False) -> dict[str, Any]:
        weights = {k: (v.half() if half and v.is_floating_point() else v.float()).detach().cpu().clone() for k, v in self.state_dict.items()}
        bps = self.bps.to_dict()
        return {
            "format": CHECKPOINT_FORMAT,
            "hand": self.hand,
            "model_config": self.model_config.to_dict(),
            "state_dict": weights,
            "weights_dtype": "float16" if half else "float32",
            "pose_normalizer": self.normalizer.to_dict(),
            "joint_limits": {"lower": self.joint_lower.float().clone(), "upper": self.joint_upper.float().clone()},
            "bps": {"n": bps["n"], "radius": bps["radius"], "seed": bps["seed"], "basis": torch.from_numpy(bps["basis"])},
            "surface": {"points": int(self.surface_points), "seed": int(self.surface_seed)},
            "manifest": json.loads(json.dumps(self.manifest)),  # plain JSON values only
            **({} if self.guidance_scale == 1.0 else {"guidance_scale": float(self.guidance_scale)}),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "checkpoint") -> SamplerCheckpoint:
        if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
            found = data.get("format") if isinstance(data, dict) else type(data).__name__
            raise CheckpointError(f"{source}: not a GD2P sampler checkpoint (format {found!r}, expected {CHECKPOINT_FORMAT!r})")
        try:
            bps = data["bps"]
            return cls(
                hand=str(data["hand"]),
                model_config=DenoiserConfig.from_dict(data["model_config"]),
                state_dict=dict(data["state_dict"]),
                normalizer=PoseNormalizer.from_dict(data["pose_normalizer"]),
                joint_lower=torch.as_tensor(data["joint_limits"]["lower"], dtype=torch.float32),
                joint_upper=torch.as_tensor(data["joint_limits"]["upper"], dtype=torch.float32),
                bps=BasisPointSet.from_dict({"n": bps["n"], "radius": bps["radius"], "seed": bps["seed"], "basis": bps["basis"].numpy()}),
                surface_points=int(data["surface"]["points"]),
                surface_seed=int(data["surface"]["seed"]),
                manifest=dict(data.get("manifest") or {}),
                guidance_scale=float(data.get("guidance_scale", 1.0)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{source}: incomplete sampler checkpoint: {exc!r}") from exc


# ----------------------------------------------------------------------------- files
def atomic_torch_save(obj: Any, path: str | Path) -> Path:
    """torch.save through an atomic, durable write: a crash never leaves a half checkpoint."""
    with atomic_writer(path, "wb", durable=True) as handle:
        torch.save(obj, handle)
    return Path(path)


def manifest_path(checkpoint_path: str | Path) -> Path:
    path = Path(checkpoint_path)
    return path.with_name(path.name + ".manifest.json")


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_manifest(path: str | Path, manifest: dict[str, Any], indent: int = 2, sort_keys: bool = True) -> Path:
    """Write `<path>.manifest.json` beside a model file (checkpoint, critic, NN index) with the file's SHA-256,
    which every loader checks (`verify_file`)."""
    return atomic_write_text(manifest_path(path), json.dumps({**manifest, "sha256": file_sha256(path)}, indent=indent,
                                                             sort_keys=sort_keys) + "\n")


def verify_file(path: str | Path, error: type[Exception] = ValueError) -> None:
    """Raise `error` naming the file when the manifest beside a model file records a SHA-256 the file does not have
    (a file replaced, truncated or changed after its manifest was written). A file without a manifest, or with
    one from before hashes were recorded, loads as it is."""
    path = Path(path)
    try:
        recorded = json.loads(manifest_path(path).read_text()).get("sha256")
    except (OSError, ValueError, AttributeError):
        return
    if recorded and (actual := file_sha256(path)) != recorded:
        raise error(f"{path}: its SHA-256 is {actual[:16]}..., but its manifest {manifest_path(path).name} records "
                    f"{str(recorded)[:16]}...: the file is not the one the manifest describes (restore it, or rewrite "
                    "the manifest if it was replaced on purpose)")


def save_checkpoint(checkpoint: SamplerCheckpoint, path: str | Path, half: bool = False) -> Path:
    """Write the shipped checkpoint (fp16 weights with `half`) and its manifest JSON (with the file's SHA-256)
    beside it."""
    path = atomic_torch_save(checkpoint.to_dict(half=half), path)
    write_manifest(path, checkpoint.manifest)
    return path


def _torch_load(path: Path) -> Any:
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a corrupt or foreign file
        raise CheckpointError(f"{path}: unreadable checkpoint: {exc}") from exc


def load_checkpoint(path: str | Path) -> SamplerCheckpoint:
    """Load a shipped checkpoint (CheckpointError if it is not one, or not the file its manifest describes)."""
    path = Path(path)
    data = _torch_load(path)
    verify_file(path, CheckpointError)
    return SamplerCheckpoint.from_dict(data, str(path))


def checkpoint_id(path: str | Path) -> str:
    """First 16 hex digits of the file's SHA-256: names the exact weights that produced a sample."""
    return file_sha256(path)[:16]


def save_training_state(state: dict[str, Any], path: str | Path) -> Path:
    return atomic_torch_save({"format": TRAINING_STATE_FORMAT, **state}, path)


def load_training_state(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    state = _torch_load(path)
    if not isinstance(state, dict) or state.get("format") != TRAINING_STATE_FORMAT:
        raise CheckpointError(f"{path}: not a GD2P sampler training state")
    return state


# ----------------------------------------------------------------------------- shipped checkpoints
SHIPPED_DIR = Path(__file__).resolve().parent / "checkpoints"
CHECKPOINT_ENV = "GD2P_SAMPLER_CHECKPOINT_{hand}"  # e.g. GD2P_SAMPLER_CHECKPOINT_ALLEGRO=/path/to.pt


def default_checkpoint_path(hand: str) -> Path:
    """Where the sampler looks for `hand`'s checkpoint: $GD2P_SAMPLER_CHECKPOINT_<HAND>, else the shipped file."""
    override = os.environ.get(CHECKPOINT_ENV.format(hand=hand.upper()))
    return Path(override).expanduser() if override else SHIPPED_DIR / f"{hand}.pt"
