"""The success critic: P(a push from this pose succeeds) and its predicted position error, from the
object's BPS and a hand pose in D.

    BPS (4096) -> standardise -> Linear -> SiLU -> Linear -> object embedding (object_dim)
    pose (25), contact features (contact_dim) -> standardise
        -> [pose, contact, object embedding] -> [Linear -> LayerNorm -> SiLU] x num_layers
        -> Linear -> (success logit, log position error)

The contact features (`critic_features.py`: where the hand meets the object) are computed from the
pose and the object's surface points; critics trained before them have contact_dim 0.

The target is what the planner's prescreen measures: the validator's floating-hand push of the pose
(20 cm, judged by the one push judge). The object embedding is computed once per request and
broadcast over its poses, so scoring K = 200 poses costs one small MLP pass. Training is in
`critic_train.py`; the standardisation statistics are buffers and travel in the state dict.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

ERROR_FLOOR_M = 0.005  # the error head predicts log(error + floor): millimetre misses all count as "on target"


@dataclass(frozen=True)
class CriticConfig:
    """Architecture of the critic; stored in its checkpoint."""

    # Chosen on val objects (ROC AUC of 60 val objects' 1,920 labelled samples; 12,800 training samples): this
    # tiny net 0.756, object 16 / hidden 128 0.742, object 64 / hidden 256 x 3 0.723 (larger ones overfit).
    pose_dim: int = 25
    bps_dim: int = 4096
    object_dim: int = 8
    hidden_dim: int = 64
    num_layers: int = 2
    contact_dim: int = 0  # critic_features.CONTACT_FEATURES when trained with them

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            lowest = 0 if name == "contact_dim" else 1
            if not isinstance(value, int) or value < lowest:
                raise ValueError(f"CriticConfig.{name} must be an integer >= {lowest}, got {value!r}")

    def to_dict(self) -> dict[str, int]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CriticConfig:
        return cls(**{k: int(v) for k, v in data.items() if k in cls.__dataclass_fields__})


class SuccessCritic(nn.Module):
    """Scores poses [B, 25] of one or more objects (BPS [R, bps_dim], `group` [B] mapping poses to objects),
    with the poses' contact features [B, contact_dim] when the config has them."""

    bps_mean: torch.Tensor  # buffers (register_buffer), declared for the type checker
    bps_std: torch.Tensor
    pose_mean: torch.Tensor
    pose_std: torch.Tensor
    contact_mean: torch.Tensor  # only with contact features
    contact_std: torch.Tensor

    def __init__(self, config: CriticConfig | None = None):
        super().__init__()
        self.config = config = config or CriticConfig()
        self.register_buffer("bps_mean", torch.zeros(config.bps_dim))
        self.register_buffer("bps_std", torch.ones(config.bps_dim))
        self.register_buffer("pose_mean", torch.zeros(config.pose_dim))
        self.register_buffer("pose_std", torch.ones(config.pose_dim))
        if config.contact_dim:
            self.register_buffer("contact_mean", torch.zeros(config.contact_dim))
            self.register_buffer("contact_std", torch.ones(config.contact_dim))
        self.object_encoder = nn.Sequential(
            nn.Linear(config.bps_dim, config.object_dim), nn.SiLU(), nn.Linear(config.object_dim, config.object_dim))
        layers: list[nn.Module] = []
        width = config.pose_dim + config.contact_dim + config.object_dim
        for _ in range(config.num_layers):
            layers += [nn.Linear(width, config.hidden_dim), nn.LayerNorm(config.hidden_dim), nn.SiLU()]
            width = config.hidden_dim
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Linear(width, 2)

    @property
    def uses_contact(self) -> bool:
        return self.config.contact_dim > 0

    def set_statistics(self, bps: torch.Tensor, poses: torch.Tensor, contact: torch.Tensor | None = None,
                       min_std: float = 1e-3) -> None:
        """Standardise inputs with the training set's per-feature mean and std."""
        self.bps_mean.copy_(bps.mean(0))
        self.bps_std.copy_(bps.std(0).clamp_min(min_std))
        self.pose_mean.copy_(poses.mean(0))
        self.pose_std.copy_(poses.std(0).clamp_min(min_std))
        if self.uses_contact:
            if contact is None:
                raise ValueError("a critic with contact features needs their training statistics")
            self.contact_mean.copy_(contact.mean(0))
            self.contact_std.copy_(contact.std(0).clamp_min(min_std))

    def encode_object(self, bps: torch.Tensor) -> torch.Tensor:
        """[R, bps_dim] raw BPS distances -> [R, object_dim]."""
        embedding: torch.Tensor = self.object_encoder((bps - self.bps_mean) / self.bps_std)
        return embedding

    def forward(self, poses: torch.Tensor, bps: torch.Tensor, group: torch.Tensor | None = None,
                contact: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(success logits [B], predicted log(position error + ERROR_FLOOR_M) [B])."""
        embedding = self.encode_object(bps)
        if group is not None:
            embedding = embedding.index_select(0, group)
        elif embedding.shape[0] == 1:
            embedding = embedding.expand(poses.shape[0], -1)
        inputs = [(poses - self.pose_mean) / self.pose_std]
        if self.uses_contact:
            if contact is None or contact.shape != (poses.shape[0], self.config.contact_dim):
                raise ValueError(f"this critic reads contact features [{poses.shape[0]}, {self.config.contact_dim}], "
                                 f"got {None if contact is None else tuple(contact.shape)}")
            inputs.append((contact - self.contact_mean) / self.contact_std)
        out = self.head(self.trunk(torch.cat([*inputs, embedding], dim=-1)))
        return out[:, 0], out[:, 1]
