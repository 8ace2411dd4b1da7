"""DDPM training objective, DDPM / DDIM sampling loops, EMA and pose normalisation.

The noise schedule is the paper's (appendix, "Training Details"): DDPM with 100 training steps,
`squaredcos_cap_v2` betas, `clip_sample=True` and epsilon prediction, from diffusers. Sampling
offers the paper's DDPM-100 and a DDIM fast path over the same trained model (DDIM with eta 0
reuses the DDPM's training schedule; only the reverse process differs).

`clip_sample` clips the predicted clean sample to [-1, 1], so poses are normalised per dimension
to [-1, 1] by the training set's min / max (`PoseNormalizer`, as diffusion_policy's
LinearNormalizer) — any other normalisation would make the clip cut valid poses.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
from diffusers import DDIMScheduler, DDPMScheduler
from diffusers.training_utils import EMAModel
from torch.nn import functional as F

from shared.sampling.model import DenoiserConfig, PoseDenoiser

SamplerKind = Literal["ddpm", "ddim"]
SAMPLERS: tuple[str, ...] = ("ddpm", "ddim")

TRAIN_TIMESTEPS = 100
BETA_SCHEDULE = "squaredcos_cap_v2"
DEFAULT_DDIM_STEPS = 10
EMA_POWER = 0.75
EMA_MAX_DECAY = 0.9999  # diffusion_policy's EMAModel max_value
DEFAULT_NOISE_SCALE = 1.0  # the sampling temperature when a request names none
MAX_GUIDANCE_SCALE = 10.0  # classifier-free guidance weights above this only over-saturate
NOISE_SCALE_ENV = "GD2P_SAMPLER_NOISE_SCALE"  # overrides DEFAULT_NOISE_SCALE, as GD2P_SAMPLER_CHECKPOINT_<HAND> the weights


class DiffusionConfigError(ValueError):
    """A sampler name or step count that cannot be used."""


Guide = Callable[[torch.Tensor], torch.Tensor]  # normalised clean poses [n, 25] -> the direction to move them [n, 25]


@dataclass(frozen=True)
class GradientGuidance:
    """How a `Guide` steers the reverse process: in each of the last `steps` denoising steps the predicted clean
    poses move by `scale` x the guide's gradient (normalised pose units; each row's move capped at `max_step`),
    and the step continues from the moved prediction (universal guidance's forward step, Bansal et al. 2023)."""

    scale: float
    steps: int = 10
    max_step: float = 0.2

    def __post_init__(self) -> None:
        if not float(self.scale) > 0.0:
            raise DiffusionConfigError(f"the guidance step scale must be > 0, got {self.scale}")
        if not 1 <= int(self.steps) <= TRAIN_TIMESTEPS:
            raise DiffusionConfigError(f"guided steps must be in 1..{TRAIN_TIMESTEPS}, got {self.steps}")
        if not float(self.max_step) > 0.0:
            raise DiffusionConfigError(f"the largest guided move must be > 0, got {self.max_step}")

    @classmethod
    def of(cls, scale: float, steps: int | None = None) -> GradientGuidance:
        """The guidance a command line asks for: `steps` None is the default number of guided steps."""
        return cls(scale) if steps is None else cls(scale, steps=steps)

    def applies_at(self, timestep: int) -> bool:
        """True for the last `steps` of the training schedule's timesteps (whatever the sampler's stride)."""
        return int(timestep) < self.steps

    def move(self, normalized: torch.Tensor, guide: Guide) -> torch.Tensor:
        """The normalised poses [n, 25] moved one guided step along `guide`, kept inside [-1, 1]."""
        move = self.scale * guide(normalized)
        move = move * (self.max_step / move.norm(dim=1, keepdim=True).clamp_min(self.max_step))  # long moves shortened
        moved: torch.Tensor = (normalized + move).clamp(-1.0, 1.0)
        return moved


def make_noise_scheduler() -> DDPMScheduler:
    """The paper's training (and DDPM sampling) schedule."""
    return DDPMScheduler(
        num_train_timesteps=TRAIN_TIMESTEPS, beta_schedule=BETA_SCHEDULE, clip_sample=True, prediction_type="epsilon")


def resolve_steps(kind: str, steps: int | None = None) -> int:
    """The number of denoising steps a sampler runs (DDPM: all 100; DDIM: `steps`, default 10)."""
    if kind not in SAMPLERS:
        raise DiffusionConfigError(f"unknown sampler {kind!r}; expected one of {', '.join(SAMPLERS)}")
    if kind == "ddpm":
        if steps not in (None, TRAIN_TIMESTEPS):
            raise DiffusionConfigError(f"the DDPM sampler runs all {TRAIN_TIMESTEPS} steps; use sampler='ddim' for {steps} steps")
        return TRAIN_TIMESTEPS
    steps = DEFAULT_DDIM_STEPS if steps is None else int(steps)
    if not 1 <= steps <= TRAIN_TIMESTEPS:
        raise DiffusionConfigError(f"DDIM steps must be in 1..{TRAIN_TIMESTEPS}, got {steps}")
    return steps


def make_sampling_scheduler(kind: str, steps: int | None = None) -> DDPMScheduler | DDIMScheduler:
    """A scheduler ready to sample: DDPM over all 100 steps, or DDIM over `steps` (default 10)."""
    count = resolve_steps(kind, steps)
    ddpm = make_noise_scheduler()
    scheduler = ddpm if kind == "ddpm" else DDIMScheduler.from_config(ddpm.config)
    scheduler.set_timesteps(count)
    return scheduler


def make_ema(model: PoseDenoiser) -> EMAModel:
    """diffusers' EMA with diffusion_policy's warm-up: decay = 1 - (1 + step)^-0.75, capped at 0.9999."""
    return EMAModel(model.parameters(), decay=EMA_MAX_DECAY, min_decay=0.0, update_after_step=0,
                    use_ema_warmup=True, inv_gamma=1.0, power=EMA_POWER, foreach=True)


# ----------------------------------------------------------------------------- normalisation
@dataclass
class PoseNormalizer:
    """Per-dimension affine map of poses onto [-1, 1] (the training set's min -> -1, max -> +1)."""

    low: torch.Tensor  # [25]
    high: torch.Tensor  # [25]

    MIN_RANGE = 1e-4  # a constant dimension (e.g. a joint never moved) maps to 0 instead of dividing by 0

    @classmethod
    def fit(cls, poses: torch.Tensor) -> PoseNormalizer:
        if poses.ndim != 2 or poses.shape[0] == 0:
            raise ValueError(f"need a non-empty [N, D] pose tensor to fit the normaliser, got {tuple(poses.shape)}")
        return cls(poses.min(dim=0).values.float(), poses.max(dim=0).values.float())

    @property
    def centre_and_half_range(self) -> tuple[torch.Tensor, torch.Tensor]:
        centre = (self.high + self.low) / 2
        half = ((self.high - self.low) / 2).clamp_min(self.MIN_RANGE / 2)
        return centre, half

    def normalize(self, poses: torch.Tensor) -> torch.Tensor:
        centre, half = self.centre_and_half_range
        return (poses - centre.to(poses)) / half.to(poses)

    def unnormalize(self, normalized: torch.Tensor) -> torch.Tensor:
        centre, half = self.centre_and_half_range
        return normalized * half.to(normalized) + centre.to(normalized)

    def to_dict(self) -> dict[str, torch.Tensor]:
        return {"low": self.low.clone(), "high": self.high.clone()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PoseNormalizer:
        return cls(torch.as_tensor(data["low"], dtype=torch.float32), torch.as_tensor(data["high"], dtype=torch.float32))


# ----------------------------------------------------------------------------- training objective
def denoising_loss(model: PoseDenoiser, scheduler: DDPMScheduler, poses: torch.Tensor, bps: torch.Tensor,
                   generator: torch.Generator | None = None, condition_dropout: float = 0.0,
                   failed: torch.Tensor | None = None) -> torch.Tensor:
    """DDPM epsilon loss: noise normalised poses at random steps, predict the noise, mean squared error.

    With `condition_dropout` p > 0 each row sees the "no object" embedding with probability p, so the
    model learns the unconditional noise too (classifier-free guidance, Ho & Salimans 2022). Rows where
    `failed` [B] is true are failed pushes, learned under the object's failure embedding (an `outcome` model)."""
    noise = torch.randn(poses.shape, generator=generator, device=poses.device, dtype=poses.dtype)
    timesteps = torch.randint(0, scheduler.config.num_train_timesteps, (poses.shape[0],), generator=generator, device=poses.device)
    noisy = scheduler.add_noise(poses, noise, timesteps)
    drop = None
    if condition_dropout > 0:
        drop = torch.rand(poses.shape[0], generator=generator, device=poses.device) < condition_dropout
    return F.mse_loss(model(noisy, timesteps, bps, drop, failed), noise)


# ----------------------------------------------------------------------------- sampling
@torch.inference_mode()
def sample_normalized(
    model: PoseDenoiser,
    bps: torch.Tensor,
    counts: Sequence[int],
    generators: Sequence[torch.Generator],
    kind: str = "ddpm",
    steps: int | None = None,
    noise_scale: float = 1.0,
    guidance_scale: float = 1.0,
    guides: Sequence[Guide | None] | None = None,
    gradient_guidance: GradientGuidance | None = None,
) -> list[torch.Tensor]:
    """Reverse diffusion for R requests at once: R BPS rows, `counts[r]` poses each, one generator each.

    `noise_scale` (the sampling temperature, in (0, 1]) multiplies the initial noise and every DDPM
    step's noise (DDIM with eta 0 adds none): below 1 the samples concentrate on the model's modes,
    trading diversity for validity; 1 is the plain reverse process.

    `guidance_scale` w != 1 (a model with `config.guidable`) is classifier-free guidance: the noise is
    eps(base) + w (eps(object) - eps(base)), where base is "no object" for an `unconditional` model
    (pushing the samples toward what is particular to this object) and this object's failed pushes for
    an `outcome` model (pushing them away from what failed on it, a negative prompt); each step runs the
    network on twice as many rows.

    `guides` (one per request, or None) with `gradient_guidance` steer the last denoising steps of those
    requests up a gradient (`GradientGuidance`; e.g. the success critic's, `guidance.CriticGuide`).

    The object embedding is computed once per request and the FiLM parameters once per step per
    request; the network runs on all rows together. Each request draws its initial noise and its
    DDPM step noise from its own generator, so its samples do not depend on what it was batched with.
    Returns R tensors [counts[r], 25] of normalised poses.
    """
    if len(counts) != bps.shape[0] or len(generators) != bps.shape[0]:
        raise ValueError(f"{bps.shape[0]} BPS rows need as many counts and generators, got {len(counts)} and {len(generators)}")
    if guides is not None and (gradient_guidance is None or len(guides) != len(counts)):
        raise ValueError("guides need one entry per request and a GradientGuidance")
    check_noise_scale(noise_scale)
    check_guidance_scale(guidance_scale, model.config)
    scheduler = make_sampling_scheduler(kind, steps)
    device = bps.device
    pose_dim = model.config.pose_dim
    samples = [noise_scale * torch.randn((n, pose_dim), generator=g, device=device) for n, g in zip(counts, generators, strict=True)]
    x = torch.cat(samples)
    bounds = _row_bounds(counts)
    request_of_row = torch.repeat_interleave(torch.arange(len(counts), device=device), torch.as_tensor(counts, device=device))
    group = None if len(counts) == 1 else request_of_row
    object_embedding = model.encode_object(bps)
    guided = guidance_scale != 1.0
    if guided:  # the second copy of every row sees its request's guidance base, FiLM rows R..2R-1
        group = torch.cat([request_of_row, request_of_row + len(counts)])
        object_embedding = torch.cat([object_embedding, model.guidance_embedding(object_embedding)])
    for t in scheduler.timesteps:
        film = model.film(object_embedding, t.to(device))
        if guided:  # both predictions in one pass: the rows twice, the second half with the guidance base
            conditional, base_epsilon = model.denoise(torch.cat([x, x]), film, group).chunk(2)
            epsilon = base_epsilon + guidance_scale * (conditional - base_epsilon)
        else:
            epsilon = model.denoise(x, film, group)
        if guides is not None and gradient_guidance is not None and gradient_guidance.applies_at(int(t)):
            epsilon = _steered(scheduler, int(t), x, epsilon, bounds, guides, gradient_guidance)
        x = torch.cat([_step(scheduler, epsilon[a:b], t, x[a:b], g, noise_scale)
                       for (a, b), g in zip(bounds, generators, strict=True)])
    return [x[a:b] for a, b in bounds]


def check_noise_scale(noise_scale: float) -> None:
    """DiffusionConfigError unless 0 < noise_scale <= 1."""
    if not 0.0 < float(noise_scale) <= 1.0:
        raise DiffusionConfigError(f"the noise scale must be in (0, 1], got {noise_scale}")


def check_guidance_scale(guidance_scale: float, config: DenoiserConfig | None = None) -> None:
    """DiffusionConfigError unless 1 <= guidance_scale <= MAX_GUIDANCE_SCALE, and guidance (!= 1) has a model
    trained for it."""
    if not 1.0 <= float(guidance_scale) <= MAX_GUIDANCE_SCALE:
        raise DiffusionConfigError(f"the guidance scale must be in [1, {MAX_GUIDANCE_SCALE:g}], got {guidance_scale}")
    if guidance_scale != 1.0 and config is not None and not config.guidable:
        raise DiffusionConfigError("classifier-free guidance needs a model trained with condition dropout or on "
                                   "failures (gd2p train --condition-dropout or --learn-failures)")


def default_noise_scale() -> float:
    """The temperature of a request that names none: $GD2P_SAMPLER_NOISE_SCALE, else DEFAULT_NOISE_SCALE."""
    override = os.environ.get(NOISE_SCALE_ENV)
    if not override:
        return DEFAULT_NOISE_SCALE
    try:
        value = float(override)
        check_noise_scale(value)
    except (ValueError, DiffusionConfigError) as exc:
        raise DiffusionConfigError(f"${NOISE_SCALE_ENV}={override!r}: must be a number in (0, 1]") from exc
    return value


def _step(scheduler: DDPMScheduler | DDIMScheduler, epsilon: torch.Tensor, t: torch.Tensor, x: torch.Tensor,
          generator: torch.Generator, noise_scale: float = 1.0) -> torch.Tensor:
    sample: torch.Tensor  # diffusers is not analysed (pyproject.toml): its results are Any
    if noise_scale == 1.0 or not isinstance(scheduler, DDPMScheduler) or int(t) == 0:
        sample = scheduler.step(epsilon, t, x, generator=generator).prev_sample
        return sample
    # diffusers' DDPM step draws its noise z from `generator` and returns mean + sigma_t z; replaying the
    # generator gives the same z, so the step with sigma_t scaled is the returned sample minus (1 - scale) sigma_t z.
    state = generator.get_state()
    prev_sample = scheduler.step(epsilon, t, x, generator=generator).prev_sample
    z = torch.randn(epsilon.shape, generator=torch.Generator(device=generator.device).set_state(state),
                    device=epsilon.device, dtype=epsilon.dtype)
    sigma = scheduler._get_variance(t) ** 0.5  # the step's "fixed_small" posterior standard deviation
    sample = prev_sample - (1.0 - noise_scale) * sigma * z
    return sample


def _steered(scheduler: DDPMScheduler | DDIMScheduler, t: int, x: torch.Tensor, epsilon: torch.Tensor,
             bounds: list[tuple[int, int]], guides: Sequence[Guide | None], guidance: GradientGuidance) -> torch.Tensor:
    """The noise prediction whose clean pose is the predicted one moved along each request's guide."""
    alpha_bar = scheduler.alphas_cumprod[t].to(x)
    clean = ((x - (1 - alpha_bar).sqrt() * epsilon) / alpha_bar.sqrt()).clamp(-1.0, 1.0)  # the scheduler's clip_sample
    moved = clean.clone()
    for (a, b), guide in zip(bounds, guides, strict=True):
        if guide is not None:
            moved[a:b] = guidance.move(clean[a:b], guide)
    steered: torch.Tensor = (x - alpha_bar.sqrt() * moved) / (1 - alpha_bar).sqrt()
    return steered


def _row_bounds(counts: Iterable[int]) -> list[tuple[int, int]]:
    bounds, start = [], 0
    for n in counts:
        if n < 1:
            raise ValueError(f"every request needs at least one sample, got {n}")
        bounds.append((start, start + n))
        start += n
    return bounds
