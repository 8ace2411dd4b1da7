"""Scrambled-Halton augmentation of successful push poses (paper appendix: 10 copies per success).

Each copy perturbs the pose within the paper's bounds:
- translation of the base: a vector of norm <= `MAX_TRANSLATION_M` (5 mm);
- rotation of the base: an axis-angle vector of norm <= `MAX_ROTATION_DEG` (2.5 deg), applied in
  the base's own frame (R' = R exp([w]x)), so the copy differs from its parent by at most 2.5 deg;
- joints: each angle moved by at most `MAX_JOINT_RAD` (0.05 rad), then clipped to the joint limits.

The 22 noise coordinates (3 + 3 + 16) come from one scrambled Halton sequence
(`scipy.stats.qmc.Halton(d=22, scramble=True, seed=seed)`): low-discrepancy, so ten copies cover the
neighbourhood more evenly than ten random draws, and deterministic for a seed. A point of the unit
cube becomes a vector in the ball by the radial map v * |v|_inf / |v|_2 (the cube's shell of
inf-norm r goes to the sphere of radius r), which keeps the bound exact.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from shared.frames import make_transform, matrix_to_pose25, pose25_to_matrix

MAX_TRANSLATION_M = 0.005
MAX_ROTATION_DEG = 2.5
MAX_JOINT_RAD = 0.05
COPIES_PER_SUCCESS = 10
_NOISE_DIM = 3 + 3 + 16


class AugmentError(ValueError):
    """Bad input to the augmentation (wrong pose shape, bad count or limits)."""


def halton_perturbations(pose: np.ndarray, n: int = COPIES_PER_SUCCESS, seed: int = 0,
                         joint_lower: np.ndarray | None = None,
                         joint_upper: np.ndarray | None = None) -> np.ndarray:
    """`n` perturbed copies [n, 25] of one pose [25] (in D), deterministic for `seed`."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (25,) or not np.all(np.isfinite(pose)):
        raise AugmentError(f"pose must be 25 finite values [p(3), r6(6), q(16)], got shape {pose.shape}")
    if n < 1:
        raise AugmentError(f"the number of copies must be >= 1, got {n}")
    unit = qmc.Halton(d=_NOISE_DIM, scramble=True, seed=seed).random(n) * 2.0 - 1.0  # [n, 22] in [-1, 1)
    translation = _cube_to_ball(unit[:, 0:3]) * MAX_TRANSLATION_M
    rotation_vectors = _cube_to_ball(unit[:, 3:6]) * np.radians(MAX_ROTATION_DEG)
    joint_noise = unit[:, 6:] * MAX_JOINT_RAD

    base, joints = pose25_to_matrix(pose)
    rotations = base[:3, :3] @ Rotation.from_rotvec(rotation_vectors).as_matrix()  # [n, 3, 3]
    positions = base[:3, 3] + translation
    new_joints = joints + joint_noise
    if joint_lower is not None or joint_upper is not None:
        new_joints = np.clip(new_joints, joint_lower, joint_upper)
    return matrix_to_pose25(make_transform(rotations, positions), new_joints)


def _cube_to_ball(v: np.ndarray) -> np.ndarray:
    """Radial map [-1, 1]^3 -> unit ball: scales each vector by |v|_inf / |v|_2."""
    norm2 = np.linalg.norm(v, axis=1, keepdims=True)
    norm_inf = np.abs(v).max(axis=1, keepdims=True)
    return np.where(norm2 > 0.0, v * norm_inf / np.maximum(norm2, 1e-300), 0.0)
