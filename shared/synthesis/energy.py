"""The push-pose energy (paper Eq. 1 plus the get_a_grip terms), batched over poses in torch.

    E = w_fc E_fc + w_dis E_dis + w_pen E_pen + w_spen E_spen + w_joints E_j + w_ff E_ff + w_fp E_fp
        + w_tpen E_tpen + w_dir E_dir + w_arm E_arm

Everything is expressed in the direction frame D (docs/architecture.md §Frames): table z = 0, push along +x.
Notation: B poses, K selected contacts per pose with points x_i and the object's outward surface
normal n_i at x_i (the unit gradient of the object SDF d), object surface points o_j, hand surface
samples h_s, the hand's signed distance sd_hand (negative inside), palm normal v (unit, in D),
joints q within [l, u]. E_pen = E_pen,obj + E_pen,hand counts penetration both ways.

Each term is its own function returning a [B] tensor; `evaluate_energy` computes them all for one
state. Term functions take plain tensors (plus the hand model where the hand's geometry is needed),
so each can be tested on constructed cases.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, cast

import numpy as np
import torch

from shared.robots.hands import HandModel, HandState
from shared.robots.hands.primitives import Primitive, surface_samples
from shared.synthesis.config import TERMS, GenerationConfig

_FAR_AWAY_M = 1.0e3  # distance reported for points that no primitive's bounding sphere reaches
_SURFACE_SAMPLE_SEED = 1234
_KINDS = ("box", "sphere", "cylinder")  # the primitive kinds shared.robots.hands.primitives produces


class ObjectField(Protocol):
    """The object as the energy sees it, in D (see `shared.synthesis.scene.PushScene`). Read-only properties, so
    that a frozen dataclass matches."""

    @property
    def surface_points(self) -> torch.Tensor:
        """[N,3] on the object surface."""

    @property
    def centroid(self) -> torch.Tensor:
        """[3] reference point for contact torques."""

    @property
    def distance_error_m(self) -> float:
        """How much `distance` may over-estimate the true distance (grid interpolation)."""

    def distance(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance [...] (negative inside, differentiable) and unit outward normal [..., 3]."""


# ------------------------------------------------------------------------------------ the terms


def force_closure(points: torch.Tensor, normals: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """E_fc = || G n ||^2 = || sum_i [ n_i ; (x_i - c) x n_i ] ||^2   (DexGraspNet's DFC estimate).

    G = [I_3 ... I_3 ; [x_1 - c]_x ... [x_K - c]_x] is the 6 x 3K grasp matrix and n the stacked
    contact normals: the net wrench of unit forces along the normals. It is 0 when the contact
    forces can cancel (force closure) and grows as they pile up on one side. Torques are taken
    about the object's centroid c. points, normals [B,K,3] -> [B].
    """
    arms = points - center
    wrench = torch.cat((normals.sum(1), torch.linalg.cross(arms, normals, dim=-1).sum(1)), dim=-1)
    return wrench.square().sum(-1)


def contact_distance(distance: torch.Tensor, offset_m: float) -> torch.Tensor:
    """E_dis = sum_i | d(x_i) - delta |: contacts pulled to a pre-contact offset delta outside the surface.

    DexGraspNet uses delta = 0 (contacts on the surface). A push starts from rest, so the hand is
    placed delta (default 5 mm) off the surface: PyBullet then starts without penetration, at the
    cost of delta of final position error (config.py). distance [B,K] -> [B].
    """
    return (distance - offset_m).abs().sum(-1)


def object_penetration(geometry: HandGeometry, state: HandState, scene: ObjectField, margin_m: float = 0.0,
                       clearance: torch.Tensor | None = None) -> torch.Tensor:
    """E_pen,obj = sum_j max(0, m - sd_hand(o_j)): object surface points inside (or within m of) the hand.

    DexGraspNet's penetration term, the first half of E_pen (see `hand_in_object`).

    Sparse gradient (docs/architecture.md §Compute): a no-grad pass finds the (pose, point) pairs with sd_hand < m
    (`HandGeometry.signed_distance_upper_bound`); only those pairs are evaluated again with
    gradients. Every other pair contributes exactly 0, so energy and gradient equal the dense sum's.
    Uses the scene's `surface_points` o_j [N,3]; `clearance` = `HandGeometry.primitive_clearance`
    when the caller already has it. -> [B].
    """
    points = scene.surface_points
    with torch.no_grad():
        bound = geometry.signed_distance_upper_bound(state, points, margin_m, scene, clearance)
        batch, point = torch.nonzero(bound < margin_m, as_tuple=True)
    depth = torch.relu(margin_m - geometry.signed_distance_pairs(state, batch, points[point]))
    return state.pose.new_zeros(state.batch_size).index_add(0, batch, depth)


def hand_in_object(geometry: HandGeometry, state: HandState, scene: ObjectField, margin_m: float = 0.0,
                   clearance: torch.Tensor | None = None) -> torch.Tensor:
    """E_pen,hand = sum_s max(0, m - d(h_s)): hand surface samples inside (or within m of) the object.

    The second half of E_pen. Object points inside a thin finger link push it towards the link's
    nearest face, which can lie deeper in the object; the object SDF gradient at the hand's own
    samples h_s (the first `penetration_samples`) always points out of the object, so a fingertip poking
    into a face between object samples is pulled out. Sparse like E_pen,obj: a sample on primitive p
    is within R_p of its centre c_p, so d(h_s) >= d(c_p) - R_p up to the grid's error (counted once
    in `clearance` and once here, as d is the interpolated grid on both sides); only samples of
    primitives within reach are looked up - exactly the same energy and gradient. -> [B].
    """
    with torch.no_grad():
        if clearance is None:
            clearance = geometry.primitive_clearance(state, scene)
        reachable = clearance - scene.distance_error_m < geometry.bound_radius + margin_m  # [B,P]
        batch, sample = torch.nonzero(reachable[:, geometry.sample_primitive[: geometry.penetration_samples]],
                                      as_tuple=True)
    depth = torch.relu(margin_m - scene.distance(geometry.sample_points_at(state, batch, sample))[0])
    return state.pose.new_zeros(state.batch_size).index_add(0, batch, depth)


def self_penetration(hand: HandModel, state: HandState) -> torch.Tensor:
    """E_spen = sum_{(a,b)} max(0, r_a + r_b - |c_a - c_b|) over keypoint spheres of non-adjacent links [B]."""
    return hand.self_penetration(state)


def joint_limits(joints: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """E_j = sum_k max(0, q_k - u_k) + max(0, l_k - q_k): joint-limit violation in radians. [B,J] -> [B]."""
    return (torch.relu(joints - upper) + torch.relu(lower - joints)).sum(-1)


def contact_spread(points: torch.Tensor, min_distance_m: float) -> torch.Tensor:
    """E_ff = sum_{i<j} max(0, delta_ff - |x_i - x_j|): selected contacts closer than delta_ff.

    get_a_grip rewards spread without bound (-sum |x_i - x_j|); this hinge only keeps contacts from
    collapsing onto one spot (re-sampling can pick neighbouring candidates), so a flat-palm push
    with legitimately close contacts is not pushed apart. points [B,K,3] -> [B].
    """
    k = points.shape[1]
    first, second = torch.triu_indices(k, k, offset=1)
    gaps = torch.linalg.vector_norm(points[:, first] - points[:, second], dim=-1)
    return torch.relu(min_distance_m - gaps).sum(-1)


def finger_palm(points: torch.Tensor, base_position: torch.Tensor) -> torch.Tensor:
    """E_fp = -sum_i |x_i - p_base|: get_a_grip's "finger palm distance" (weight 0 in the paper). [B,K,3] -> [B]."""
    result: torch.Tensor = -torch.linalg.vector_norm(points - base_position.unsqueeze(1), dim=-1).sum(-1)
    return result


def table_penetration(heights: torch.Tensor, clearance_m: float = 0.0) -> torch.Tensor:
    """E_tpen = sum_s max(0, h - z_s): hand surface samples below the table (z = 0) plus a clearance h.

    get_a_grip's table term: the samples (`HandGeometry.sample_heights`) are area-uniform on the
    hand's collision primitives, so the cost grows with how much of the hand is under the table, not
    only with how deep its lowest point is - strong enough to beat E_dis pulling contacts down a low
    object. heights z_s [B,S] -> [B].
    """
    return torch.relu(clearance_m - heights).sum(-1)


def palm_direction(palm_normal: torch.Tensor) -> torch.Tensor:
    """E_dir = -cos(v_palm, +x) = -v_x / |v|: lowest when the palm faces the push direction. [B,3] -> [B]."""
    result: torch.Tensor = -palm_normal[:, 0] / torch.linalg.vector_norm(palm_normal, dim=-1)
    return result


def arm_feasibility(palm_normal: torch.Tensor) -> torch.Tensor:
    """E_arm = max(0, v_z / |v|): a palm facing up puts the arm under the hand (paper's E_kinematics). [B]."""
    return torch.relu(palm_normal[:, 2] / torch.linalg.vector_norm(palm_normal, dim=-1))


# ------------------------------------------------------------------------------- total energy


@dataclass(frozen=True)
class EnergyTerms:
    """Unweighted terms [B] by short name (config.TERMS) and the weighted total [B]."""

    terms: dict[str, torch.Tensor]
    total: torch.Tensor


def evaluate_energy(hand: HandModel, geometry: HandGeometry, scene: ObjectField, pose: torch.Tensor,
                    contact_indices: torch.Tensor, config: GenerationConfig) -> EnergyTerms:
    """All terms of E for poses [B,25] (in D) with selected contact candidate indices [B,K]."""
    state = hand.forward(pose)
    points, _ = hand.contact_points(state, contact_indices)
    distance, normals = scene.distance(points)
    palm = hand.palm_normal(state)
    with torch.no_grad():
        clearance = geometry.primitive_clearance(state, scene)  # shared by both halves of E_pen
    margin = config.penetration_margin_m
    terms = {
        "fc": force_closure(points, normals, scene.centroid),
        "dis": contact_distance(distance, config.contact_offset_m),
        "pen": (object_penetration(geometry, state, scene, margin, clearance)
                + hand_in_object(geometry, state, scene, margin, clearance)),
        "spen": self_penetration(hand, state),
        "joints": joint_limits(pose[:, 9:], hand.joint_lower, hand.joint_upper),
        "ff": contact_spread(points, config.ff_min_distance_m),
        "fp": finger_palm(points, pose[:, :3]),
        "tpen": table_penetration(geometry.sample_heights(state), config.table_clearance_m),
        "dir": palm_direction(palm),
        "arm": arm_feasibility(palm),
    }
    weights = config.effective_weights()
    total = cast(torch.Tensor, sum(weights[name] * terms[name] for name in TERMS))  # TERMS is not empty: not 0
    return EnergyTerms(terms, total)


def max_penetration(hand: HandModel, geometry: HandGeometry, scene: ObjectField, pose: torch.Tensor,
                    object_points: torch.Tensor) -> torch.Tensor:
    """Deepest hand-object interpenetration per pose [B] (m, >= 0), checked both ways.

    max( max_j -sd_hand(o_j) over object surface points, max_s -d(h_s) over hand surface samples ):
    the first catches object edges inside the hand, the second fingertips inside the object.
    """
    with torch.no_grad():
        state = hand.forward(pose)
        object_in_hand = torch.zeros(state.batch_size)
        for chunk in object_points.split(1024):
            depth = -geometry.signed_distance_upper_bound(state, chunk, 0.0, scene)
            object_in_hand = torch.maximum(object_in_hand, depth.amax(1))
        hand_points = geometry.surface_points(state)
        hand_in_object = (-scene.distance(hand_points)[0]).amax(1)
        return torch.maximum(object_in_hand, hand_in_object).clamp_min(0.0)


# --------------------------------------------------------------------- per-hand precomputed geometry


class HandGeometry:
    """What the energy needs from the hand's collision primitives beyond `HandModel`'s own API.

    Built once per hand from the public primitive list: bounding spheres and per-primitive
    parameters (for the sparse penetration pass) and area-uniform surface samples in shuffled
    order, so any prefix is area-uniform too: the first `penetration_samples` for the hand-side
    half of E_pen (an object-SDF lookup each, the costly part), the first `table_samples` for E_tpen
    (a dot product each), all of them for the reported penetration depth.
    """

    def __init__(self, hand: HandModel, surface_samples_total: int = 2048, penetration_samples: int = 256,
                 table_samples: int = 512):
        prims = hand.primitives.prims
        self.link_index = torch.tensor([p.link_index for p in prims], dtype=torch.long)
        self.kind = torch.tensor([_KINDS.index(p.kind) for p in prims], dtype=torch.long)
        self.origin = torch.tensor(np.array([p.origin for p in prims]), dtype=torch.float32)  # [P,4,4]
        self.bound_radius = torch.tensor([_bounding_radius(p) for p in prims], dtype=torch.float32)
        self.box_half = torch.tensor([[s / 2 for s in p.size] if p.kind == "box" else [0.0] * 3 for p in prims],
                                     dtype=torch.float32)
        self.sphere_radius = torch.tensor([p.radius if p.kind == "sphere" else 0.0 for p in prims])
        self.cylinder_radius = torch.tensor([p.radius if p.kind == "cylinder" else 0.0 for p in prims])
        self.cylinder_half_length = torch.tensor([p.length / 2 if p.kind == "cylinder" else 0.0 for p in prims])
        self.sample_primitive, self._sample_points = _hand_surface_samples(prims, surface_samples_total)
        self._sample_link = self.link_index[self.sample_primitive]
        self._sample_points_h = torch.cat((self._sample_points, torch.ones(len(self._sample_points), 1)), dim=1)
        self.penetration_samples = min(penetration_samples, len(self._sample_points))
        self.table_samples = min(table_samples, len(self._sample_points))

    def primitive_frames(self, state: HandState) -> torch.Tensor:
        """Every primitive's frame in the pose's frame [B,P,4,4]."""
        return state.links[:, self.link_index] @ self.origin

    def signed_distance_upper_bound(self, state: HandState, points: torch.Tensor, margin_m: float,
                                    scene: ObjectField, clearance: torch.Tensor | None = None) -> torch.Tensor:
        """[B,N]: the hand's exact signed distance to object points where it is < margin, else >= margin (no grad).

        Three culls, each exact: (1) a primitive whose centre c is farther from the object than its
        bounding radius R + m (object SDF at c, minus the grid's error bound) holds no surface point;
        (2) for the remaining (pose, primitive) pairs, |o - c|^2 < (R + m)^2 for all points in one
        matmul ([o, |o|^2, 1] . [-2c, 1, |c|^2 - (R + m)^2] < 0); (3) the primitive's own distance
        on the (pose, point, primitive) triples that survive.
        """
        frames = self.primitive_frames(state)  # [B,P,4,4]
        centers = frames[..., :3, 3]
        reach = self.bound_radius + margin_m
        if clearance is None:
            clearance = self.primitive_clearance(state, scene)
        pose_index, prim_index = torch.nonzero(clearance < reach, as_tuple=True)
        best = points.new_full((state.batch_size * points.shape[0],), _FAR_AWAY_M)
        if pose_index.numel() == 0:
            return best.view(state.batch_size, -1)
        active = centers[pose_index, prim_index]  # [A,3]
        lifted = torch.cat((points, points.square().sum(-1, keepdim=True), torch.ones_like(points[:, :1])), dim=1)
        planes = torch.cat((-2.0 * active, torch.ones_like(active[:, :1]),
                            (active.square().sum(-1) - reach[prim_index].square()).unsqueeze(-1)), dim=1)  # [A,5]
        pair, point = torch.nonzero(planes @ lifted.T < 0.0, as_tuple=True)
        batch, prim = pose_index[pair], prim_index[pair]
        if batch.numel():
            rotation = frames[batch, prim, :3, :3]
            local = ((points[point] - centers[batch, prim]).unsqueeze(-2) @ rotation).squeeze(-2)
            best.scatter_reduce_(0, batch * points.shape[0] + point, self._primitive_distance(local, prim), "amin")
        return best.view(state.batch_size, points.shape[0])

    def primitive_clearance(self, state: HandState, scene: ObjectField) -> torch.Tensor:
        """[B,P] lower bound on the distance from each primitive's centre to the object (no grad)."""
        centers = self.primitive_frames(state)[..., :3, 3]
        return scene.distance(centers)[0] - scene.distance_error_m

    def signed_distance_pairs(self, state: HandState, batch: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Signed distance [T] of points [T,3] to the hand of pose `batch` [T] (differentiable, exact)."""
        frames = self.primitive_frames(state)[batch]  # [T,P,4,4]
        local = ((points.unsqueeze(1) - frames[..., :3, 3]).unsqueeze(-2) @ frames[..., :3, :3]).squeeze(-2)
        prims = torch.arange(len(self.kind)).expand(local.shape[:2])
        return self._primitive_distance(local.reshape(-1, 3), prims.reshape(-1)).view(prims.shape).amin(1)

    def _primitive_distance(self, local: torch.Tensor, prim: torch.Tensor) -> torch.Tensor:
        """Signed distance of points [T,3] given in the frames of primitives `prim` [T]."""
        out = local.new_empty(local.shape[0])
        for code, distance in enumerate((self._box_distance, self._sphere_distance, self._cylinder_distance)):
            mask = self.kind[prim] == code
            if bool(mask.any()):
                out[mask] = distance(local[mask], prim[mask])
        return out

    # The standard primitive SDFs (the formulas of HandModel.signed_distance; tests pin the agreement).
    def _box_distance(self, local: torch.Tensor, prim: torch.Tensor) -> torch.Tensor:
        q = local.abs() - self.box_half[prim]
        result: torch.Tensor = torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1) + q.amax(-1).clamp_max(0.0)
        return result

    def _sphere_distance(self, local: torch.Tensor, prim: torch.Tensor) -> torch.Tensor:
        result: torch.Tensor = torch.linalg.vector_norm(local, dim=-1) - self.sphere_radius[prim]
        return result

    def _cylinder_distance(self, local: torch.Tensor, prim: torch.Tensor) -> torch.Tensor:
        radial = torch.linalg.vector_norm(local[:, :2], dim=-1) - self.cylinder_radius[prim]
        axial = local[:, 2].abs() - self.cylinder_half_length[prim]
        q = torch.stack((radial, axial), dim=-1)
        result: torch.Tensor = torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1) + q.amax(-1).clamp_max(0.0)
        return result

    def surface_points(self, state: HandState, count: int | None = None) -> torch.Tensor:
        """The first `count` (default all) area-uniform samples on the hand's surface [B,S,3], pose's frame."""
        count = len(self._sample_link) if count is None else count
        rows = state.links[:, self._sample_link[:count], :3, :]  # [B,S,3,4]
        return (rows * self._sample_points_h[:count, None, :]).sum(-1)

    def sample_heights(self, state: HandState) -> torch.Tensor:
        """z of the first `table_samples` surface samples [B,S] (only the z row of each link frame is needed)."""
        z_rows = state.links[:, self._sample_link[: self.table_samples], 2, :]  # [B,S,4]
        return (z_rows * self._sample_points_h[: self.table_samples]).sum(-1)

    def sample_points_at(self, state: HandState, batch: torch.Tensor, sample: torch.Tensor) -> torch.Tensor:
        """Surface sample `sample` [T] of pose `batch` [T] in the pose's frame [T,3] (differentiable)."""
        rows = state.links[batch, self._sample_link[sample], :3, :]  # [T,3,4]
        return (rows * self._sample_points_h[sample, None, :]).sum(-1)


def _bounding_radius(prim: Primitive) -> float:
    if prim.kind == "box":
        return 0.5 * float(np.linalg.norm(prim.size))
    if prim.kind == "sphere":
        return float(prim.radius)
    return float(np.hypot(prim.radius, prim.length / 2))


def _hand_surface_samples(prims: Sequence[Primitive], total: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples spread over primitives by area: primitive index [S] and point in its link frame [S,3].

    Fixed seed (the samples are part of the model) and shuffled, so any prefix is area-uniform too.
    """
    rng = np.random.default_rng(_SURFACE_SAMPLE_SEED)
    areas = np.array([p.area() for p in prims])
    counts = np.maximum(1, np.round(total * areas / areas.sum()).astype(int))
    owners, points = [], []
    for index, (prim, count) in enumerate(zip(prims, counts, strict=True)):
        local, _ = surface_samples(prim, int(count), rng)
        owners += [index] * len(local)
        points.append(local)
    order = rng.permutation(len(owners))
    return (torch.tensor(np.asarray(owners)[order], dtype=torch.long),
            torch.tensor(np.concatenate(points)[order], dtype=torch.float32))
