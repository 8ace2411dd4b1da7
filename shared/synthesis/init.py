"""Starting poses and contact choices for the optimiser (after DexGraspNet's `initialize_convex_hull`).

Every random draw goes through the caller's `torch.Generator`, so a seed fixes the whole start.

Pose: the palm centre is placed on the object's convex hull inflated by a few centimetres (a point
drawn area-uniformly), backed off further along the hull's outward normal; the palm normal points
into the object (the inward hull normal) tilted by a random angle up to `jitter_max_rad`, with a
uniformly random roll about it. For pushes only the back of the object is used (inward hull normal
within `push_side_min_cos` of +x; config.py has the measurement behind it); grasps start all around.
Joints come from a normal around the hand's open pose truncated to the joint limits.

Contacts: K distinct candidate indices per pose, uniform over all of the hand's candidates (the
paper's per-region candidate counts set how often each region is picked).
"""
from __future__ import annotations

import numpy as np
import torch
import trimesh

from shared.robots.hands import HandModel
from shared.synthesis.config import InitSettings

_POOL_FACTOR = 4  # hull points drawn per pose before the push-side / height filter
_MAX_DRAWS = 16


class InitialisationError(RuntimeError):
    """No admissible start point on the object's hull (e.g. an object entirely below the start height)."""


def palm_center_base(hand: HandModel) -> torch.Tensor:
    """Centre of the palm's contact face in the hand base frame [3] (mean of the palm-region candidates)."""
    cands = hand.contact_candidates
    palm_regions = [i for i, name in enumerate(cands.region_names) if name.startswith("palm:")]
    if not palm_regions:
        raise InitialisationError(f"{hand.name}: no palm contact region to aim with")
    mask = torch.isin(cands.region_index, torch.tensor(palm_regions))
    state = hand.forward(hand.open_pose())
    frames = state.links[0, cands.link_index[mask]]  # open pose: base = identity
    points = (frames[:, :3, :3] @ cands.points[mask].unsqueeze(-1)).squeeze(-1) + frames[:, :3, 3]
    return points.mean(0)


def inflated_hull(vertices_d: np.ndarray, inflation_m: float) -> trimesh.Trimesh:
    """Convex hull of the object (vertices in D) grown outward by about `inflation_m`."""
    hull = trimesh.Trimesh(vertices=np.asarray(vertices_d, dtype=np.float64)).convex_hull
    grown = hull.vertices + inflation_m * hull.vertex_normals
    hull_grown: trimesh.Trimesh = trimesh.Trimesh(vertices=grown).convex_hull  # trimesh's cached property is untyped
    return hull_grown


def sample_hull_points(hull: trimesh.Trimesh, count: int, generator: torch.Generator,
                       min_inward_x: float | None, min_height_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """`count` area-uniform points on `hull` and their outward normals [count,3] each.

    Keeps only points at least `min_height_m` above the table and, when `min_inward_x` is given,
    whose inward normal has an x component >= it (the side of the object a +x push starts from).
    """
    triangles = torch.tensor(hull.triangles, dtype=torch.float32)
    normals = torch.tensor(hull.face_normals, dtype=torch.float32)
    area = torch.tensor(hull.area_faces, dtype=torch.float32)
    kept_points, kept_normals, have = [], [], 0
    for _ in range(_MAX_DRAWS):
        faces = torch.multinomial(area, _POOL_FACTOR * count, replacement=True, generator=generator)
        points = _uniform_in_triangles(triangles[faces], generator)
        outward = normals[faces]
        ok = points[:, 2] >= min_height_m
        if min_inward_x is not None:
            ok &= -outward[:, 0] >= min_inward_x
        kept_points.append(points[ok])
        kept_normals.append(outward[ok])
        have += int(ok.sum())
        if have >= count:
            return torch.cat(kept_points)[:count], torch.cat(kept_normals)[:count]
    # The push side is a small part of this hull (thin or pointed objects): draw from its faces only.
    # (A fallback, not the first strategy, so objects that sampled fine keep their seeded results.)
    eligible = torch.tensor(hull.triangles[:, :, 2].max(axis=1) >= min_height_m)
    if min_inward_x is not None:
        eligible &= -normals[:, 0] >= min_inward_x
    if bool(eligible.any()):
        for _ in range(_MAX_DRAWS):
            faces = torch.multinomial(area * eligible, _POOL_FACTOR * count, replacement=True, generator=generator)
            points = _uniform_in_triangles(triangles[faces], generator)
            ok = points[:, 2] >= min_height_m
            kept_points.append(points[ok])
            kept_normals.append(normals[faces][ok])
            have += int(ok.sum())
            if have >= count:
                return torch.cat(kept_points)[:count], torch.cat(kept_normals)[:count]
    raise InitialisationError(
        f"only {have} of {count} start points found on the inflated hull above {min_height_m} m"
        + ("" if min_inward_x is None else f" facing +x by >= {min_inward_x}"))


def _uniform_in_triangles(triangles: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """One uniform point per triangle [N,3,3] -> [N,3] (folded barycentric coordinates)."""
    u, v = torch.rand(2, triangles.shape[0], 1, generator=generator)
    fold = (u + v) > 1.0
    u, v = torch.where(fold, 1.0 - u, u), torch.where(fold, 1.0 - v, v)
    a, b, c = triangles.unbind(1)
    return a + u * (b - a) + v * (c - a)


def random_unit_perpendicular(axis: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """A uniformly random unit vector orthogonal to each unit axis [N,3]."""
    for _ in range(_MAX_DRAWS):
        u = torch.randn(axis.shape, generator=generator)
        u = u - (u * axis).sum(-1, keepdim=True) * axis
        norm = torch.linalg.vector_norm(u, dim=-1, keepdim=True)
        if bool((norm > 1e-6).all()):
            result: torch.Tensor = u / norm
            return result
    raise InitialisationError("could not draw a vector perpendicular to the palm axis")  # pragma: no cover


def aim_rotations(inward: torch.Tensor, hand: HandModel, jitter_max_rad: float,
                  generator: torch.Generator) -> torch.Tensor:
    """Base rotations [N,3,3] whose palm normal is `inward` tilted by U[0, jitter] with a random roll."""
    tilt = jitter_max_rad * torch.rand(inward.shape[0], 1, generator=generator)
    sideways = random_unit_perpendicular(inward, generator)
    palm = torch.cos(tilt) * inward + torch.sin(tilt) * sideways
    fingers = random_unit_perpendicular(palm, generator)
    target = torch.stack((palm, fingers, torch.linalg.cross(palm, fingers, dim=-1)), dim=-1)  # columns
    n_b, f_b = hand.palm_normal_base, hand.finger_direction_base
    source = torch.stack((n_b, f_b, torch.linalg.cross(n_b, f_b, dim=-1)), dim=-1)
    return target @ source.T


def truncated_normal_joints(hand: HandModel, count: int, jitter: float, generator: torch.Generator) -> torch.Tensor:
    """Joints [count,J] ~ N(open pose, (jitter (u - l))^2) truncated to [l, u] (inverse-CDF sampling)."""
    lower, upper = hand.joint_lower, hand.joint_upper
    mean = hand.open_joint_positions.clamp(lower, upper)
    sigma = (jitter * (upper - lower)).clamp_min(1e-6)
    normal = torch.distributions.Normal(0.0, 1.0)
    cdf_low, cdf_high = normal.cdf((lower - mean) / sigma), normal.cdf((upper - mean) / sigma)
    u = cdf_low + (cdf_high - cdf_low) * torch.rand(count, hand.dof, generator=generator)
    result: torch.Tensor = (mean + sigma * torch.special.ndtri(u.clamp(1e-7, 1 - 1e-7))).clamp(lower, upper)
    return result


def initial_poses(hand: HandModel, hull_vertices_d: np.ndarray, count: int, settings: InitSettings,
                  generator: torch.Generator, push: bool = True) -> torch.Tensor:
    """`count` starting poses [count,25] in D around an object with convex-hull vertices in D."""
    hull = inflated_hull(hull_vertices_d, settings.hull_inflation_m)
    points, outward = sample_hull_points(
        hull, count, generator, settings.push_side_min_cos if push else None, settings.min_height_m)
    rotation = aim_rotations(-outward, hand, settings.jitter_max_rad, generator)
    backoff = settings.backoff_min_m + (settings.backoff_max_m - settings.backoff_min_m) * torch.rand(
        count, 1, generator=generator)
    palm_target = points + backoff * outward
    position = palm_target - rotation @ palm_center_base(hand)
    joints = truncated_normal_joints(hand, count, settings.joint_jitter, generator)
    return torch.cat((position, rotation[:, :, 0], rotation[:, :, 1], joints), dim=1)


def sample_contacts(num_candidates: int, count: int, per_pose: int, generator: torch.Generator,
                    exclude: torch.Tensor | None = None) -> torch.Tensor:
    """[count, per_pose] distinct candidate indices per row, uniform; never one of `exclude`'s row.

    Rejection sampling: draw uniformly, redraw the entries that repeat an earlier entry of their row
    or an excluded index. With K << C collisions are rare, so this is ~10x cheaper per step than
    `torch.multinomial` without replacement over all C candidates (which sorts C exponentials per row).
    """
    available = num_candidates - (0 if exclude is None else exclude.shape[1])
    if per_pose > available:
        raise ValueError(f"cannot pick {per_pose} distinct contacts from {available} candidates")
    chosen = torch.randint(num_candidates, (count, per_pose), generator=generator)
    while True:
        clash = _repeats_earlier(chosen)
        if exclude is not None:
            clash |= (chosen.unsqueeze(-1) == exclude.unsqueeze(1)).any(-1)
        redraw = int(clash.sum())
        if redraw == 0:
            return chosen
        chosen[clash] = torch.randint(num_candidates, (redraw,), generator=generator)


def _repeats_earlier(indices: torch.Tensor) -> torch.Tensor:
    """[B,K] True where an entry equals an entry to its left in the same row."""
    same = indices.unsqueeze(-1) == indices.unsqueeze(1)  # [B,K,K]: same[b,i,j] = (x_i == x_j)
    return torch.tril(same, diagonal=-1).any(-1)
