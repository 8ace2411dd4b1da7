"""The denoiser: a FiLM-conditioned residual MLP over the 25-d hand pose, conditioned on the BPS.

Why not diffusion_policy's ConditionalUnet1D as is: GD2P's "horizon" is one pose, and a 1-long
sequence breaks the U-Net's down-sampling (https://github.com/real-stanford/diffusion_policy/issues/32). What survives of the U-Net
at horizon 1 is its residual blocks with FiLM conditioning, which is what this model is:

    pose (25) -> Linear -> [ResidualFiLMBlock] x num_blocks -> Linear -> epsilon (25)
    BPS (4096) -> standardise -> Linear -> SiLU -> Linear -> object embedding (object_dim)
    timestep -> sinusoidal -> Linear -> SiLU -> Linear -> time embedding (time_dim)
    [time, object] -> SiLU -> Linear -> FiLM scale and bias of every block

Each block mirrors diffusion_policy's ConditionalResidualBlock1D with Linear for Conv1d(k=1)
(30-40% faster at horizon 1, docs/architecture.md §Compute), LayerNorm for GroupNorm and SiLU for Mish (Mish
measured ~20x slower than SiLU on this CPU for a [200, 256] activation: it was the largest cost
of a denoising step):
    h = SiLU(LN(W1 x)); h = scale * h + bias; h = SiLU(LN(W2 h)); out = x + h

Size (the default `DenoiserConfig`): 1.51 M parameters, chosen for CPU. The BPS is compressed to
128-d before FiLM (feeding the 4096-d condition straight into FiLM is what makes the paper-scale
U-Net 76 M parameters); hidden width 256, 4 blocks. A model of this size trains at ~8-9k
samples/s on one thread (batch 256) and converges in minutes, where a 76 M U-Net is far from
converged after the same time (docs/architecture.md §Compute); 200 poses take ~0.3 s with DDPM-100 and ~30 ms with
DDIM-10 on one core (bench/sampler.py).

Sampling cost: the object embedding depends only on the request and the FiLM parameters only on
(request, timestep), so `encode_object` runs once per request and `film` once per denoising step
per request; `denoise` broadcasts them over the request's samples (`group` maps rows to requests
when several requests share a batch).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

FLAGS = ("unconditional", "outcome")  # DenoiserConfig's bool fields


@dataclass(frozen=True)
class DenoiserConfig:
    """Architecture of the denoiser; stored in every checkpoint."""

    pose_dim: int = 25
    bps_dim: int = 4096
    object_dim: int = 128  # the BPS compressed to this before FiLM
    time_dim: int = 64
    hidden_dim: int = 256
    num_blocks: int = 4
    # A learned "no object" embedding (trained with condition dropout), so the model also predicts the noise
    # without the object and can sample with classifier-free guidance (`sample_normalized`).
    unconditional: bool = False
    # A learned "failed push" embedding added to the object's (trained on the store's failures beside its
    # successes), so guidance can steer the samples away from what failed on this object (`sample_normalized`).
    outcome: bool = False

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if name in FLAGS:
                if not isinstance(value, bool):
                    raise ValueError(f"DenoiserConfig.{name} must be a bool, got {value!r}")
            elif not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"DenoiserConfig.{name} must be a positive integer, got {value!r}")
        if self.time_dim % 2:
            raise ValueError(f"DenoiserConfig.time_dim must be even (sin/cos pairs), got {self.time_dim}")
        if self.unconditional and self.outcome:
            raise ValueError("DenoiserConfig: guidance from the unconditional or from the failure embedding, not both")

    @property
    def guidable(self) -> bool:
        """Whether the model has a second condition to guide against (classifier-free guidance)."""
        return self.unconditional or self.outcome

    def to_dict(self) -> dict[str, int | bool]:
        out = asdict(self)
        for flag in FLAGS:  # unset flags are left out: the config of every checkpoint made before they existed
            if not out[flag]:
                del out[flag]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DenoiserConfig:
        known: dict[str, Any] = {k: (bool(v) if k in FLAGS else int(v)) for k, v in data.items() if k in cls.__dataclass_fields__}
        return cls(**known)


def sinusoidal_embedding(timesteps: torch.Tensor, dim: int) -> torch.Tensor:
    """[N] diffusion steps -> [N, dim] sin/cos features (the Transformer / DDPM position encoding)."""
    half = dim // 2
    frequencies = torch.exp(torch.arange(half, device=timesteps.device, dtype=torch.float32) * (-math.log(10000.0) / max(half - 1, 1)))
    angles = timesteps.float()[:, None] * frequencies[None, :]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class ResidualFiLMBlock(nn.Module):
    """Two Linear-LayerNorm-SiLU layers with FiLM after the first, plus a skip connection."""

    def __init__(self, width: int):
        super().__init__()
        self.linear1 = nn.Linear(width, width)
        self.norm1 = nn.LayerNorm(width)
        self.linear2 = nn.Linear(width, width)
        self.norm2 = nn.LayerNorm(width)

    def forward(self, x: torch.Tensor, scale: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        h = F.silu(self.norm1(self.linear1(x)))
        h = h * scale + bias
        h = F.silu(self.norm2(self.linear2(h)))
        return x + h


class PoseDenoiser(nn.Module):
    """Predicts the noise in a normalised 25-d pose given the diffusion step and the object's BPS.

    The BPS standardisation statistics are buffers, so they travel in the state dict.
    """

    bps_mean: torch.Tensor  # buffers (register_buffer), declared for the type checker
    bps_std: torch.Tensor

    def __init__(self, config: DenoiserConfig | None = None):
        super().__init__()
        self.config = config = config or DenoiserConfig()
        self.register_buffer("bps_mean", torch.zeros(config.bps_dim))
        self.register_buffer("bps_std", torch.ones(config.bps_dim))
        self.object_encoder = nn.Sequential(
            nn.Linear(config.bps_dim, config.object_dim), nn.SiLU(), nn.Linear(config.object_dim, config.object_dim))
        self.time_encoder = nn.Sequential(
            nn.Linear(config.time_dim, config.time_dim * 4), nn.SiLU(), nn.Linear(config.time_dim * 4, config.time_dim))
        cond_dim = config.time_dim + config.object_dim
        self.film_generator = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 2 * config.hidden_dim * config.num_blocks))
        self.input_layer = nn.Linear(config.pose_dim, config.hidden_dim)
        self.blocks = nn.ModuleList(ResidualFiLMBlock(config.hidden_dim) for _ in range(config.num_blocks))
        self.output_layer = nn.Linear(config.hidden_dim, config.pose_dim)
        if config.unconditional:
            self.null_object = nn.Parameter(torch.zeros(config.object_dim))
        if config.outcome:  # random, not zero: from zero the two conditions barely part (tests/test_sampler.py)
            self.failure_offset = nn.Parameter(torch.randn(config.object_dim))

    def set_bps_statistics(self, mean: torch.Tensor, std: torch.Tensor, min_std: float = 1e-3) -> None:
        """Standardise BPS features with the training set's per-feature mean and std."""
        self.bps_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.bps_std.copy_(torch.as_tensor(std, dtype=torch.float32).clamp_min(min_std))

    def encode_object(self, bps: torch.Tensor) -> torch.Tensor:
        """[R, bps_dim] raw BPS distances -> [R, object_dim]; once per request."""
        embedding: torch.Tensor = self.object_encoder((bps - self.bps_mean) / self.bps_std)
        return embedding

    def film(self, object_embedding: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """[R, object_dim] + [R] (or scalar) steps -> [R, num_blocks, 2, hidden] FiLM scale and bias."""
        timesteps = torch.as_tensor(timesteps, device=object_embedding.device).reshape(-1)
        time_embedding = self.time_encoder(sinusoidal_embedding(timesteps, self.config.time_dim))
        time_embedding = time_embedding.expand(object_embedding.shape[0], -1)
        params: torch.Tensor = self.film_generator(torch.cat([time_embedding, object_embedding], dim=-1))
        return params.view(-1, self.config.num_blocks, 2, self.config.hidden_dim)

    def denoise(self, noisy_pose: torch.Tensor, film: torch.Tensor, group: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 25] noisy poses -> [B, 25] predicted noise.

        `film` is [R, num_blocks, 2, hidden]; row b uses film[group[b]], or film[b] when `group` is
        None and R == B, or film[0] for every row when R == 1.
        """
        if group is not None:
            film = film.index_select(0, group)
        elif film.shape[0] not in (1, noisy_pose.shape[0]):
            raise ValueError(f"FiLM parameters for {film.shape[0]} requests cannot broadcast over {noisy_pose.shape[0]} poses")
        h = self.input_layer(noisy_pose)
        for index, block in enumerate(self.blocks):
            h = block(h, film[:, index, 0], film[:, index, 1])
        noise: torch.Tensor = self.output_layer(h)
        return noise

    def null_embedding(self, rows: int) -> torch.Tensor:
        """[rows, object_dim] copies of the learned "no object" embedding (an `unconditional` model only)."""
        if not self.config.unconditional:
            raise ValueError("this denoiser has no unconditional embedding: train it with condition dropout")
        return self.null_object.expand(rows, -1)

    def failed_embedding(self, object_embedding: torch.Tensor) -> torch.Tensor:
        """[R, object_dim] the objects' embeddings as for a failed push (an `outcome` model only)."""
        if not self.config.outcome:
            raise ValueError("this denoiser has no failure embedding: train it with --learn-failures")
        return object_embedding + self.failure_offset

    def guidance_embedding(self, object_embedding: torch.Tensor) -> torch.Tensor:
        """[R, object_dim] what guidance steers away from: each object's failures (`outcome`), else "no object"
        (`unconditional`)."""
        if self.config.outcome:
            return self.failed_embedding(object_embedding)
        return self.null_embedding(object_embedding.shape[0])

    def forward(self, noisy_pose: torch.Tensor, timesteps: torch.Tensor, bps: torch.Tensor,
                drop_object: torch.Tensor | None = None, failed: torch.Tensor | None = None) -> torch.Tensor:
        """Training path: one timestep and one BPS per row ([B, 25], [B], [B, bps_dim]) -> [B, 25]; rows where
        `drop_object` [B] is true see the "no object" embedding instead (condition dropout), rows where `failed`
        [B] is true the object's failure embedding (a failed push of the store)."""
        embedding = self.encode_object(bps)
        if drop_object is not None:
            embedding = torch.where(drop_object[:, None], self.null_embedding(embedding.shape[0]), embedding)
        if failed is not None:
            embedding = torch.where(failed[:, None], self.failed_embedding(embedding), embedding)
        return self.denoise(noisy_pose, self.film(embedding, timesteps))


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
