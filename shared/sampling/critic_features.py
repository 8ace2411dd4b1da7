"""Where the hand meets the object: the contact features the success critic reads beside BPS and pose.

A push fails by turning the object (the hand meets it off its centre line), toppling it (too high up a
tall object) or missing it; all three depend on where the hand touches the object relative to the
object's own extent. The critic's BPS embedding describes the shape and the pose places the hand, but
a small MLP trained on ~13 k pushes learns their relation poorly, so it is computed here: the hand's
signed distance (`HandModel.signed_distance`) to a thinned set of the object's surface points in D,
summarised per pose as

- the closest distance, and the share of points within 1 and 2 cm of the hand;
- the contact centroid (points weighted by exp(-distance / 5 mm)) and its spread per axis, and a
  sharper centroid (2 mm): where on the object the push acts;
- the lowest link origin's height (a hand scraping the table);
- the object's extent in D (lowest and highest point per axis).

D is the direction frame (origin under the object's centroid on the table, +x along the push), so the
centroid's y is the push's lateral offset and its z its height.
"""
from __future__ import annotations

import torch

from shared.robots.hands.model import HandModel

CONTACT_FEATURES = 19  # the width of `contact_features`' rows
CONTACT_POINTS = 512  # surface points the distances are taken to: 2,048 cost 0.2-0.4 s per 200 poses, 512 ~0.04 s
_SOFT_M = 0.005
_SHARP_M = 0.002
_CHUNK = 64  # poses per signed-distance batch: [64, 512] distances per primitive


def thin_points(points_d: torch.Tensor, count: int = CONTACT_POINTS) -> torch.Tensor:
    """Every n-th of the points [N, 3] so that at most `count` remain (surface samples are in random order)."""
    stride = max(1, -(-len(points_d) // count))
    return points_d[::stride]


def contact_features(hand: HandModel, poses_d: torch.Tensor, points_d: torch.Tensor,
                     differentiable: bool = False) -> torch.Tensor:
    """[B, CONTACT_FEATURES] for poses [B, 25] in D against the object's surface points [N, 3] in D.

    `differentiable`: keep the autograd graph back to the poses (critic guidance differentiates the critic
    through them; the two share-within-distance features are step functions and pass no gradient)."""
    if points_d.ndim != 2 or points_d.shape[1] != 3 or len(points_d) == 0:
        raise ValueError(f"object points must have shape [N > 0, 3], got {tuple(points_d.shape)}")
    with torch.set_grad_enabled(differentiable):
        points = thin_points(points_d.to(torch.float32))
        extent = torch.cat([points.min(0).values, points.max(0).values])
        rows = [_pose_rows(hand, chunk, points) for chunk in torch.split(poses_d.to(torch.float32), _CHUNK)]
        per_pose = torch.cat(rows) if rows else torch.zeros(0, CONTACT_FEATURES - 6)
        return torch.cat([per_pose, extent.expand(len(per_pose), -1)], dim=1)


def _pose_rows(hand: HandModel, poses: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    state = hand.forward(poses)
    batch = points.unsqueeze(0).expand(len(poses), -1, -1)
    distance = hand.signed_distance(batch, state)  # [B, N]
    soft = torch.softmax(-distance / _SOFT_M, dim=1).unsqueeze(-1)
    centroid = (soft * batch).sum(1)
    spread = (soft * (batch - centroid.unsqueeze(1)) ** 2).sum(1).clamp_min(0.0).sqrt()
    sharp = (torch.softmax(-distance / _SHARP_M, dim=1).unsqueeze(-1) * batch).sum(1)
    closest = distance.min(1, keepdim=True).values
    near = torch.stack([(distance < 0.01).float().mean(1), (distance < 0.02).float().mean(1)], dim=1)
    lowest = state.links[:, :, 2, 3].min(1, keepdim=True).values
    return torch.cat([centroid, closest, near, spread, sharp, lowest], dim=1)
