"""`HandModel`: batched torch kinematics, collision geometry and contact candidates of a dexterous hand.

Pose vector (docs/architecture.md §Frames): `[p(3), r6(6), q(16)]` - position and rotation of the hand's base link in some
frame (the direction frame D during generation, the world at serve time), r6 = the first two columns of
the rotation matrix, q = joint angles in `joint_names` order. Everything a `HandState` holds is in that
same frame. Kinematics use pytorch_kinematics (chain built once, float32, CPU) and are differentiable with
respect to the whole pose.

PyBullet's base pose is the base link's centre of mass, not its URDF frame (docs/architecture.md §Simulation);
`urdf_base_to_pybullet` / `pybullet_to_urdf_base` convert between the two.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pytorch_kinematics as pk
import torch
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from shared.frames import POSE_DIM, matrix_to_r6, pose25_to_matrix
from shared.robots.hands.config import HAND_SPECS, ContactRegion, HandSpec
from shared.robots.hands.primitives import (
    PenetrationKeypoints,
    PrimitiveSet,
    build_keypoints,
    farthest_point_indices,
    primitives_from_urdf,
    surface_samples,
)
from shared.robots.hands.urdf import RobotAssetError, read_urdf

_CANDIDATE_SEED = 20240531  # fixed: candidates are part of the model and must not change between runs
_DENSE_SAMPLES_PER_CANDIDATE = 60
_EXPOSED_TOLERANCE_M = 1e-5
_EXPOSURE_STEP_M = 1e-3
_PAIR_PRUNING_SEED = 7
_PAIR_PRUNING_SAMPLES = 4096
_PAIR_MARGIN_M = 0.01


class HandModelError(ValueError):
    """Bad input to a hand model (unknown hand, wrong pose shape, ...)."""


@dataclass(frozen=True)
class HandState:
    """Result of `HandModel.forward`: all transforms in the frame the pose was given in."""

    pose: torch.Tensor  # [B,25]
    base: torch.Tensor  # [B,4,4] base link frame
    links: torch.Tensor  # [B,L,4,4] every link frame, in HandModel.link_names order

    @property
    def batch_size(self) -> int:
        return self.pose.shape[0]


@dataclass(frozen=True)
class ContactCandidates:
    """Candidate contact points: link index, point and outward unit normal in that link's frame."""

    link_index: torch.Tensor  # [C] long
    points: torch.Tensor  # [C,3]
    normals: torch.Tensor  # [C,3]
    region_names: tuple[str, ...]  # one per region, e.g. "tip:link_3.0_tip"
    region_links: tuple[str, ...]  # the link each region lies on
    region_index: torch.Tensor  # [C] long, index into region_names

    def __len__(self) -> int:
        return int(self.link_index.shape[0])

    def indices_by_region(self) -> dict[str, torch.Tensor]:
        """Candidate indices of each region ("tip:...", "finger:...", "palm:...")."""
        return {name: torch.nonzero(self.region_index == i).flatten() for i, name in enumerate(self.region_names)}

    def indices_by_link(self) -> dict[str, torch.Tensor]:
        """Candidate indices on each link that carries candidates."""
        grouped: dict[str, list[int]] = {}
        for i, link in enumerate(self.region_links):
            grouped.setdefault(link, []).append(i)
        return {link: torch.nonzero(torch.isin(self.region_index, torch.tensor(ids))).flatten()
                for link, ids in grouped.items()}


class HandModel:
    """Kinematics and geometry of one hand. Build with `load_hand(name)` (cached)."""

    def __init__(self, spec: HandSpec):
        self.spec = spec
        self.name = spec.name
        self.urdf_path = spec.urdf_path()
        self.robot = read_urdf(self.urdf_path)
        self._chain = pk.build_chain_from_urdf(self.urdf_path.read_text()).to(dtype=torch.float32)
        frames = self._chain.idx_to_frame
        self.link_names: tuple[str, ...] = tuple(frames[i] for i in range(len(frames)))  # pytorch_kinematics' order
        self._link_index = {name: i for i, name in enumerate(self.link_names)}
        self.joint_names = spec.joint_names
        self.dof = len(self.joint_names)
        self._chain_order = self._joint_permutation()
        joints = [self.robot.joint(name) for name in self.joint_names]
        self.joint_lower = torch.tensor([j.lower for j in joints], dtype=torch.float32)
        self.joint_upper = torch.tensor([j.upper for j in joints], dtype=torch.float32)
        self.open_joint_positions = torch.tensor(
            [spec.open_joints.get(name, 0.0) for name in self.joint_names], dtype=torch.float32)
        self.palm_normal_base = _unit(spec.palm_normal_base)
        self.finger_direction_base = _unit(spec.finger_direction_base)
        self.mount_point_base = torch.tensor(spec.mount_point_base, dtype=torch.float32)
        self.pybullet_base_com_offset = self.robot.inertial_origins.get(self.robot.root_link, np.eye(4))
        self.primitives = PrimitiveSet(primitives_from_urdf(self.robot, self.link_names))
        self.keypoints: PenetrationKeypoints = self._prune_far_pairs(build_keypoints(
            self.primitives.prims, self.link_names, self.robot, spec.self_collision_exclusions))
        self.contact_candidates = self._sample_contact_candidates()

    # ------------------------------------------------------------------------------------------ kinematics

    def forward(self, pose: torch.Tensor) -> HandState:
        """Link frames for a batch of pose vectors [B,25] (differentiable)."""
        if pose.ndim != 2 or pose.shape[1] != POSE_DIM:
            raise HandModelError(f"{self.name}: pose must have shape [B, {POSE_DIM}], got {tuple(pose.shape)}")
        base, joints = pose25_to_matrix(pose)
        in_base = self._chain.forward_kinematics_tensor(joints[:, self._chain_order])  # [L,B,4,4]
        links = base.unsqueeze(1) @ in_base.transpose(0, 1)
        return HandState(pose, base, links)

    def link_index(self, name: str) -> int:
        try:
            return self._link_index[name]
        except KeyError:
            raise HandModelError(f"{self.name} has no link {name!r}; links: {self.link_names}") from None

    def palm_normal(self, state: HandState) -> torch.Tensor:
        """Unit palm normal [B,3] in the pose's frame."""
        return state.base[:, :3, :3] @ self.palm_normal_base

    # ---------------------------------------------------------------------------------- contact candidates

    def contact_candidates_world(self, state: HandState) -> tuple[torch.Tensor, torch.Tensor]:
        """All candidates as points [B,C,3] and outward normals [B,C,3] in the pose's frame."""
        cands = self.contact_candidates
        frames = state.links[:, cands.link_index]  # [B,C,4,4]
        return _apply(frames, cands.points), (frames[..., :3, :3] @ cands.normals.unsqueeze(-1)).squeeze(-1)

    def contact_points(self, state: HandState, indices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Selected candidates: indices [B,K] -> points [B,K,3], normals [B,K,3] in the pose's frame."""
        cands = self.contact_candidates
        if indices.ndim != 2 or indices.shape[0] != state.batch_size:
            raise HandModelError(f"indices must have shape [B={state.batch_size}, K], got {tuple(indices.shape)}")
        batch = torch.arange(state.batch_size).unsqueeze(1)
        frames = state.links[batch, cands.link_index[indices]]  # [B,K,4,4]
        points = _apply(frames, cands.points[indices])
        normals = (frames[..., :3, :3] @ cands.normals[indices].unsqueeze(-1)).squeeze(-1)
        return points, normals

    # --------------------------------------------------------------------------------------------- geometry

    def signed_distance(self, points: torch.Tensor, state: HandState) -> torch.Tensor:
        """Signed distance [B,N] from points [B,N,3] (pose's frame) to the hand; negative inside."""
        if points.ndim != 3 or points.shape[0] != state.batch_size or points.shape[2] != 3:
            raise HandModelError(f"points must have shape [B={state.batch_size}, N, 3], got {tuple(points.shape)}")
        return self.primitives.signed_distance(points, state.links)

    def self_penetration(self, state: HandState) -> torch.Tensor:
        """Sum of keypoint-sphere overlaps between non-adjacent links [B] (0 when the hand is collision free)."""
        return self.keypoints.penetration(state.links)

    # ------------------------------------------------------------------------------------------------ poses

    def open_pose(self, batch_size: int = 1) -> torch.Tensor:
        """Pose vectors [B,25]: base at the origin with identity rotation, joints at the open configuration."""
        pose = torch.zeros(batch_size, POSE_DIM)
        pose[:, 3:9] = matrix_to_r6(torch.eye(3))
        pose[:, 9:] = self.open_joint_positions
        return pose

    def urdf_base_to_pybullet(self, position: ArrayLike, quaternion_xyzw: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """URDF base frame pose -> pose of the base's centre-of-mass frame (what PyBullet resets/reports)."""
        return _compose(position, quaternion_xyzw, self.pybullet_base_com_offset)

    def pybullet_to_urdf_base(self, com_position: ArrayLike,
                              com_quaternion_xyzw: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """PyBullet base (centre-of-mass) pose -> URDF base frame pose."""
        return _compose(com_position, com_quaternion_xyzw, np.linalg.inv(self.pybullet_base_com_offset))

    # ------------------------------------------------------------------------------------------- internals

    def _joint_permutation(self) -> torch.Tensor:
        chain_joints = self._chain.get_joint_parameter_names()
        if sorted(chain_joints) != sorted(self.joint_names):
            raise RobotAssetError(f"{self.name}: URDF joints {chain_joints} differ from the spec {self.joint_names}")
        return torch.tensor([self.joint_names.index(name) for name in chain_joints], dtype=torch.long)

    def _prune_far_pairs(self, keypoints: PenetrationKeypoints) -> PenetrationKeypoints:
        """Drop keypoint pairs that stay > _PAIR_MARGIN_M apart over random joint configurations.

        The same sampling test MoveIt's setup assistant uses for its "never in collision" matrix; the
        margin keeps pairs that come close without touching in the samples. It cuts the pairs ~4x.
        """
        generator = torch.Generator().manual_seed(_PAIR_PRUNING_SEED)
        closest = torch.full((keypoints.pairs.shape[0],), float("inf"))
        with torch.no_grad():
            for _ in range(_PAIR_PRUNING_SAMPLES // 512):
                pose = self.open_pose(512)
                pose[:, 9:] = self.joint_lower + (self.joint_upper - self.joint_lower) * torch.rand(
                    512, self.dof, generator=generator)
                closest = torch.minimum(closest, keypoints.closest_separation(self.forward(pose).links))
        return keypoints.keep_pairs(closest < _PAIR_MARGIN_M)

    def _sample_contact_candidates(self) -> ContactCandidates:
        open_state = self.forward(self.open_pose())
        links, points, normals, regions = [], [], [], []
        for region_id, region in enumerate(self.spec.contact_regions):
            p, n = self._sample_region(region, open_state, np.random.default_rng(_CANDIDATE_SEED + region_id))
            links += [self.link_index(region.link)] * len(p)
            points.append(p)
            normals.append(n)
            regions += [region_id] * len(p)
        return ContactCandidates(
            torch.tensor(links, dtype=torch.long),
            torch.tensor(np.concatenate(points), dtype=torch.float32),
            torch.tensor(np.concatenate(normals), dtype=torch.float32),
            tuple(r.name for r in self.spec.contact_regions),
            tuple(r.link for r in self.spec.contact_regions),
            torch.tensor(regions, dtype=torch.long),
        )

    def _sample_region(self, region: ContactRegion, open_state: HandState,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Dense area-uniform samples on the link's facing, exposed surface, thinned by farthest-point sampling."""
        link = self.link_index(region.link)
        prims = [p for p in self.primitives.prims if p.link_index == link]
        if not prims:
            raise RobotAssetError(f"{self.name}: contact region {region.name} is on a link without collision shapes")
        dense = _DENSE_SAMPLES_PER_CANDIDATE * region.count
        areas = np.array([p.area() for p in prims])
        per_prim = rng.multinomial(dense, areas / areas.sum())
        samples = [surface_samples(p, int(k), rng) for p, k in zip(prims, per_prim, strict=True)]
        points = np.concatenate([s[0] for s in samples])
        normals = np.concatenate([s[1] for s in samples])
        facing = normals @ np.asarray(region.facing) > region.min_cos
        points, normals = points[facing], normals[facing]
        exposed = self._exposed(points, normals, link, open_state)
        points, normals = points[exposed], normals[exposed]
        if len(points) < region.count:
            raise RobotAssetError(
                f"{self.name}: region {region.name} has too little exposed surface for {region.count} candidates")
        keep = farthest_point_indices(points, region.count)
        return points[keep], normals[keep]

    def _exposed(self, local_points: np.ndarray, local_normals: np.ndarray, link: int,
                 open_state: HandState) -> np.ndarray:
        """Surface points (link frame) with free space in front of them at the open pose.

        A point must lie outside every primitive and stepping _EXPOSURE_STEP_M along its normal must leave the
        hand by at least half that step: this drops faces covered by, or flush against, another shape.
        """
        frame = open_state.links[0, link].double().numpy()
        world = local_points @ frame[:3, :3].T + frame[:3, 3]
        ahead = world + _EXPOSURE_STEP_M * (local_normals @ frame[:3, :3].T)
        queries = torch.tensor(np.stack((world, ahead)), dtype=torch.float32).reshape(1, -1, 3)
        sdf = self.signed_distance(queries, open_state)[0].reshape(2, -1)
        return ((sdf[0] > -_EXPOSED_TOLERANCE_M) & (sdf[1] > 0.5 * _EXPOSURE_STEP_M)).numpy()


@functools.cache
def load_hand(name: str) -> HandModel:
    """The hand model for 'allegro' or 'leap' (built once per process)."""
    try:
        spec = HAND_SPECS[name]
    except KeyError:
        raise HandModelError(f"unknown hand {name!r}; known hands: {sorted(HAND_SPECS)}") from None
    return HandModel(spec)


# ------------------------------------------------------------------------------------------------- helpers


def _apply(frames: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """frames [...,4,4] applied to points [...,3] (broadcast) -> [...,3]."""
    return (frames[..., :3, :3] @ points.unsqueeze(-1)).squeeze(-1) + frames[..., :3, 3]


def _unit(vector: tuple[float, float, float]) -> torch.Tensor:
    v = torch.tensor(vector, dtype=torch.float32)
    unit: torch.Tensor = v / v.norm()
    return unit


def _compose(position: ArrayLike, quaternion_xyzw: ArrayLike, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_quat(quaternion_xyzw).as_matrix()
    frame[:3, 3] = position
    result = frame @ offset
    quaternion: np.ndarray = Rotation.from_matrix(result[:3, :3]).as_quat()
    return result[:3, 3], quaternion
