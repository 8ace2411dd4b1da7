"""Critic guidance: the success critic's gradient steers the diffusion sampler's last denoising steps.

Ordering samples by the critic (the planner's default) only chooses among what the model drew; the model
itself places poses less precisely than retrieval does (CHANGELOG.md, "Why the samples fail"), while the critic
reads exactly what the denoiser sees only through its BPS: where the hand meets the object
(`critic_features`). Guidance hands that knowledge to the draws: in the last denoising steps each
predicted clean pose climbs log P(success) by the critic (`diffusion.GradientGuidance`), and the
remaining steps denoise from there, so the pose stays on the model's manifold instead of drifting where
the critic was never trained (as gradient ascent on a finished pose would).
"""
from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

from shared.frames import ROTATION_6D, matrix_to_r6, r6_to_matrix
from shared.robots.hands.model import HandModel
from shared.sampling.critic import SuccessCritic
from shared.sampling.critic_features import contact_features, thin_points
from shared.sampling.diffusion import PoseNormalizer


class CriticGuide:
    """The gradient of log P(success) by `critic` for one object, over poses in the sampler's normalised space.

    The critic scores poses as the sampler returns them (an orthonormal rotation block), so the gradient is
    taken through that clean-up too."""

    def __init__(self, critic: SuccessCritic, hand: HandModel, bps: np.ndarray | torch.Tensor,
                 points_d: np.ndarray | torch.Tensor, normalizer: PoseNormalizer):
        self.critic = critic
        self.hand = hand
        self.bps = torch.as_tensor(np.asarray(bps, dtype=np.float32)).reshape(1, -1)
        self.points = thin_points(torch.as_tensor(np.asarray(points_d, dtype=np.float32)))
        self.normalizer = normalizer

    def __call__(self, normalized: torch.Tensor) -> torch.Tensor:
        # The sampler denoises in inference mode; its tensors carry no graph, so a fresh leaf is made outside it.
        with torch.inference_mode(False), torch.enable_grad():
            leaf = normalized.detach().clone().float().requires_grad_(True)
            poses = self.normalizer.unnormalize(leaf)
            rotation = matrix_to_r6(r6_to_matrix(poses[:, ROTATION_6D]))
            poses = torch.cat([poses[:, :ROTATION_6D.start], rotation, poses[:, ROTATION_6D.stop:]], dim=1)
            contact = contact_features(self.hand, poses, self.points, differentiable=True) if self.critic.uses_contact else None
            logits, _ = self.critic(poses, self.bps, None, contact)
            (gradient,) = torch.autograd.grad(F.logsigmoid(logits).sum(), leaf)
        return gradient.to(normalized)
