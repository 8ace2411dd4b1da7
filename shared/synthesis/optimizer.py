"""Annealing optimiser: RMSProp-style proposals accepted or rejected by the Metropolis rule.

One step (paper §"Dataset Generation", appendix "Optimization hyperparameters"; the scheme of
DexGraspNet's `Annealing`):

1. propose   pose' = pose - s_t * g / (sqrt(v_t) + 1e-6),   v_t = mu * mean_b(g^2) + (1 - mu) * v_{t-1}
             with s_t = s_0 * decay^floor(t / step_size_period); each contact index is replaced with
             probability `switch_probability` by a fresh candidate (one the pose does not use yet);
2. evaluate  E(pose') and its gradient;
3. accept    pose' with probability min(1, exp((E - E') / T_t)),  T_t = T_0 * decay^floor(t / annealing_period);
             a rejected pose keeps its old pose, contacts, energy and gradient.

`mu` weighs the *current* squared gradient (DexGraspNet's convention, where mu = "1 - decay rate"):
with mu = 0.98 the normaliser follows the batch's current gradient scale per parameter, so every
parameter (metres, r6 entries, radians) moves by about s_t per step whatever its energy units.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from shared.synthesis.config import AnnealingSettings
from shared.synthesis.init import sample_contacts

_RMS_EPS = 1e-6


@dataclass
class Proposal:
    """A candidate update for every pose of the batch."""

    pose: torch.Tensor  # [B,25]
    contacts: torch.Tensor  # [B,K]


class AnnealingOptimizer:
    """Stateful proposal/acceptance rule for a batch of poses; all randomness from `generator`."""

    def __init__(self, settings: AnnealingSettings, num_candidates: int, generator: torch.Generator):
        self.settings = settings
        self.num_candidates = num_candidates
        self.generator = generator
        self.step = 0
        self._mean_square: torch.Tensor | None = None

    def step_size(self) -> float:
        s = self.settings
        return s.step_size * s.temperature_decay ** (self.step // s.step_size_period)

    def temperature(self) -> float:
        s = self.settings
        return s.starting_temperature * s.temperature_decay ** (self.step // s.annealing_period)

    def propose(self, pose: torch.Tensor, gradient: torch.Tensor, contacts: torch.Tensor) -> Proposal:
        """RMSProp step on the pose and random contact switches (advances the step counter)."""
        mu = self.settings.mu
        # One pose's NaN gradient must not poison the batch-shared RMS normaliser; its step is then 0.
        gradient = torch.nan_to_num(gradient, nan=0.0, posinf=0.0, neginf=0.0)
        square = gradient.square().mean(0)
        previous = torch.zeros_like(square) if self._mean_square is None else self._mean_square
        self._mean_square = mu * square + (1.0 - mu) * previous
        new_pose = pose - self.step_size() * gradient / (self._mean_square.sqrt() + _RMS_EPS)
        new_contacts = self._switch_contacts(contacts)
        self.step += 1
        return Proposal(new_pose, new_contacts)

    def accept(self, energy: torch.Tensor, new_energy: torch.Tensor) -> torch.Tensor:
        """Metropolis rule at the current temperature: [B] bool, True where the proposal is kept."""
        alpha = torch.rand(energy.shape[0], generator=self.generator)
        return alpha < torch.exp((energy - new_energy) / self.temperature())

    def _switch_contacts(self, contacts: torch.Tensor) -> torch.Tensor:
        switch = torch.rand(contacts.shape, generator=self.generator) < self.settings.switch_probability
        fresh = sample_contacts(self.num_candidates, contacts.shape[0], contacts.shape[1], self.generator,
                                exclude=contacts)
        return torch.where(switch, fresh, contacts)
