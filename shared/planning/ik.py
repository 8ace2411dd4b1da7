"""Batched arm inverse kinematics for hand poses (pytorch_kinematics' damped least squares).

A hand pose is reachable when the arm can put its flange at `T_world_hand · mount⁻¹` (the hand base
pose in the world composed with the inverse flange -> hand mount, `shared.robots.arms.mount`). All K targets
are solved at once: pytorch_kinematics' `PseudoInverseIK` runs every target from `num_seeds` start
configurations in one batch (the arm's home plus uniform samples inside the joint limits, the same
for every target so results are reproducible for a seed), with joint limits enforced. Among the
converged seeds of a target the one closest to `prefer` (default: home) and away from the joint
stops is returned, so the motion planner gets a configuration that needs little travel and leaves
room for the Cartesian push that follows.

    solver = ArmIK(load_arm("panda"), hand="allegro")
    result = solver.solve_hand_poses(T_world_hand)      # [K,4,4] hand base poses in the world
    result.q[result.success]                            # [k,7] joint solutions
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytorch_kinematics as pk
import torch

from shared.robots.arms import ArmModel, load_arm, mount
from shared.robots.hands import HandModel

POSITION_TOLERANCE_M = 0.002
ROTATION_TOLERANCE_RAD = np.deg2rad(1.0)
LIMIT_MARGIN = 0.1  # fraction of a joint's range counted as "near the stop"
LIMIT_PENALTY_RAD = 3.0  # a joint at its stop costs as much as 3 rad of extra travel


class IKError(ValueError):
    """Bad input to the IK solver (wrong target shape, non-finite targets, bad seed count)."""


@dataclass(frozen=True)
class IKResult:
    """Per-target IK outcome. `q` rows of failed targets hold the best (non-converged) attempt."""

    q: np.ndarray  # [K, dof] joint angles
    success: np.ndarray  # [K] bool: converged within tolerance and inside the joint limits
    position_error_m: np.ndarray  # [K] flange position error of `q`
    rotation_error_rad: np.ndarray  # [K] flange rotation error of `q` (axis-angle magnitude)

    def __len__(self) -> int:
        return len(self.success)


class ArmIK:
    """IK for one arm (+ mounted hand). Build once and reuse: the seed set is fixed at construction."""

    def __init__(
        self,
        arm: ArmModel | str,
        hand: HandModel | str | None = None,
        *,
        T_world_base: np.ndarray | None = None,
        num_seeds: int = 16,
        max_iterations: int = 30,  # 60 solved the same 172 of bench/motion.py's 200 poses, in 1.7x the time
        position_tolerance_m: float = POSITION_TOLERANCE_M,
        rotation_tolerance_rad: float = ROTATION_TOLERANCE_RAD,
        seed: int = 0,
    ):
        if num_seeds < 1:
            raise IKError(f"num_seeds must be >= 1, got {num_seeds}")
        self.arm = load_arm(arm) if isinstance(arm, str) else arm
        self.T_flange_hand = mount(self.arm, hand) if hand is not None else np.eye(4)
        self.T_world_base = np.eye(4) if T_world_base is None else np.asarray(T_world_base, dtype=np.float64)
        self.position_tolerance_m = position_tolerance_m
        self.rotation_tolerance_rad = rotation_tolerance_rad
        limits = torch.stack((self.arm.joint_lower, self.arm.joint_upper), dim=1)
        # pytorch_kinematics' default (1e-9) vanishes in float32: a converged step (no LM damping left) at a
        # singular arm configuration then fails the whole batch's solve ("input matrix is singular").
        regularisation = 1e-5
        self.seeds = self._seed_configs(num_seeds, seed)
        self._solver = pk.PseudoInverseIK(
            self.arm.serial_chain(), pos_tolerance=position_tolerance_m, rot_tolerance=rotation_tolerance_rad,
            retry_configs=self.seeds, joint_limits=limits, max_iterations=max_iterations,
            early_stopping_any_converged=False, early_stopping_no_improvement=None,
            enforce_joint_limits=True, lr=0.5, regularlization=regularisation)
        # One seed, replaced before every solve: `track` starts each waypoint from the previous solution.
        # pytorch_kinematics' limit enforcement runs 10 extra iterations on every solve (most of a
        # waypoint's time); the tracker skips it and only a waypoint that leaves the limits is re-solved with it.
        self._trackers = {enforce: pk.PseudoInverseIK(
            self.arm.serial_chain(), pos_tolerance=position_tolerance_m / 2, rot_tolerance=rotation_tolerance_rad / 2,
            retry_configs=self.arm.home[None].clone(), joint_limits=limits, max_iterations=2 * max_iterations,
            early_stopping_any_converged=True, early_stopping_no_improvement=None, enforce_joint_limits=enforce, lr=1.0,
            regularlization=regularisation)
            for enforce in (False, True)}

    def _seed_configs(self, num_seeds: int, seed: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(seed)
        lower, upper = self.arm.joint_lower, self.arm.joint_upper
        # Random seeds stay a twentieth of each joint's range inside the limits: DLS steps from a seed on a stop are mostly clipped away.
        margin = 0.05 * (upper - lower)
        unit = torch.rand(num_seeds - 1, self.arm.dof, generator=generator)
        random = lower + margin + unit * (upper - lower - 2 * margin)
        return torch.cat((self.arm.home[None], random), dim=0)

    # ------------------------------------------------------------------------------------ solving

    def flange_targets(self, T_world_hand: np.ndarray) -> np.ndarray:
        """Hand base poses [K,4,4] in the world -> flange poses [K,4,4] in the arm's base frame."""
        T_world_hand = _check_transforms(T_world_hand)
        T_base_world = np.linalg.inv(self.T_world_base)
        targets: np.ndarray = T_base_world @ T_world_hand @ np.linalg.inv(self.T_flange_hand)
        return targets

    def solve_hand_poses(self, T_world_hand: np.ndarray, prefer: np.ndarray | None = None) -> IKResult:
        """Arm joints that put the hand base at each of `T_world_hand` [K,4,4] (or one [4,4])."""
        return self.solve_flange_poses(self.flange_targets(T_world_hand), prefer)

    def solve_flange_poses(self, T_base_flange: np.ndarray, prefer: np.ndarray | None = None) -> IKResult:
        """Arm joints for flange poses [K,4,4] in the arm's base frame."""
        targets = _check_transforms(T_base_flange)
        q, converged, pos_err, rot_err = self._solve_all_seeds(targets)
        best = self._scores(q, converged, pos_err, rot_err, prefer).argmin(axis=1)
        rows = np.arange(len(targets))
        return IKResult(q=q[rows, best], success=converged[rows, best],
                        position_error_m=pos_err[rows, best], rotation_error_rad=rot_err[rows, best])

    def distinct_solutions(self, T_world_hand: np.ndarray, prefer: np.ndarray | None = None,
                           min_difference_rad: float = 0.2, limit: int | None = None) -> list[np.ndarray]:
        """Per hand pose of `T_world_hand` [K,4,4] (or one [4,4]): its converged solutions [n, dof], best
        first, no two closer than `min_difference_rad`, at most `limit` of them (n = 0: unreachable).

        When the best solution is blocked (the elbow in an obstacle, a joint running into its stop along
        the push) the next may not be: they differ in elbow / wrist configuration, not in the last digits.
        """
        targets = self.flange_targets(T_world_hand)
        q, converged, pos_err, rot_err = self._solve_all_seeds(targets)
        order = np.argsort(self._scores(q, converged, pos_err, rot_err, prefer), axis=1)
        solutions = []
        for q_k, converged_k, order_k in zip(q, converged, order, strict=True):
            kept: list[np.ndarray] = []
            for candidate in q_k[order_k][converged_k[order_k]]:
                if len(kept) == limit:
                    break
                if all(np.abs(candidate - other).max() >= min_difference_rad for other in kept):
                    kept.append(candidate)
            solutions.append(np.array(kept).reshape(-1, self.arm.dof))
        return solutions

    def _solve_all_seeds(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Solutions [K, seeds, dof], converged [K, seeds], position and rotation errors [K, seeds]."""
        solution = self._solver.solve(pk.Transform3d(matrix=torch.as_tensor(targets, dtype=torch.float32)))
        q_all = solution.solutions
        shape = q_all.shape[:2]
        flat = q_all.reshape(-1, self.arm.dof)
        # pytorch_kinematics reports the error of the iterate *before* its last step; measure the returned q.
        pos_err, rot_err = self._errors(flat, np.repeat(targets, shape[1], axis=0))
        pos_err, rot_err = pos_err.reshape(shape), rot_err.reshape(shape)
        inside = self.arm.within_limits(flat).reshape(shape).numpy()
        converged = (pos_err < self.position_tolerance_m) & (rot_err < self.rotation_tolerance_rad) & inside
        return q_all.numpy().astype(np.float64), converged, pos_err, rot_err

    def _scores(self, q: np.ndarray, converged: np.ndarray, pos_err: np.ndarray, rot_err: np.ndarray,
                prefer: np.ndarray | None) -> np.ndarray:
        """Rank [K, seeds] of solutions q [K, seeds, dof]: lower is better.

        Converged seeds rank by travel (max joint change) from `prefer` (default home) plus a penalty
        growing inside the outer LIMIT_MARGIN of each joint's range: a joint near its stop leaves no
        room for the Cartesian push that follows. Non-converged seeds come after, by error.
        """
        reference = self.arm.home.numpy() if prefer is None else np.asarray(prefer, dtype=np.float64)
        travel = np.abs(q - reference).max(axis=-1)
        lower, upper = self.arm.joint_lower.numpy(), self.arm.joint_upper.numpy()
        margin = (np.minimum(q - lower, upper - q) / (upper - lower)).min(axis=-1)
        crowding = np.maximum(0.0, LIMIT_MARGIN - margin) / LIMIT_MARGIN
        return np.where(converged, travel + LIMIT_PENALTY_RAD * crowding,
                        1e6 + pos_err / self.position_tolerance_m + rot_err / self.rotation_tolerance_rad)

    def track(self, T_world_hand: np.ndarray, q_start: np.ndarray) -> IKResult:
        """IK along a path of nearby hand poses [N,4,4], each solved from the previous solution (from `q_start`).

        Meant for Cartesian segments: staying on one IK branch keeps the joint motion continuous. The
        caller checks the joint steps (a branch switch shows up as a jump).
        """
        paths = _check_transforms(T_world_hand)[None]
        result = self.track_many(paths, np.asarray(q_start, dtype=np.float64).reshape(1, -1))
        return IKResult(q=result.q[0], success=result.success[0], position_error_m=result.position_error_m[0],
                        rotation_error_rad=result.rotation_error_rad[0])

    def track_many(self, T_world_hand: np.ndarray, q_start: np.ndarray) -> IKResult:
        """`track` for K paths at once: hand poses [K,N,4,4] from arm joints [K,dof] -> fields [K,N(,dof)].

        Waypoint n of every path is solved in one batch from each path's solution at n - 1, so a
        planner can check K straight lines for the cost of about one. A path stops at its first
        waypoint that fails (the rest of it is reported failed, its q held): an unreachable waypoint
        costs the solver's every iteration, and every waypoint after it would too.
        """
        paths = np.asarray(T_world_hand, dtype=np.float64)
        if paths.ndim != 4 or paths.shape[2:] != (4, 4):
            raise IKError(f"paths must be [K,N,4,4], got shape {paths.shape}")
        k, n = paths.shape[:2]
        targets = self.flange_targets(paths.reshape(-1, 4, 4)).reshape(k, n, 4, 4)
        q = torch.as_tensor(np.asarray(q_start, dtype=np.float64), dtype=torch.float32).reshape(k, self.arm.dof)
        q_all = np.repeat(q.double().numpy()[:, None], n, axis=1)
        success = np.zeros((k, n), dtype=bool)
        pos_err, rot_err = np.full((k, n), np.inf), np.full((k, n), np.inf)
        alive = np.arange(k)
        for step in range(n):
            if alive.size == 0:
                break
            step_targets = targets[alive, step]
            q_alive = self._track_step(q[alive], pk.Transform3d(matrix=torch.as_tensor(step_targets, dtype=torch.float32)))
            q[alive] = q_alive
            p_err, r_err = self._errors(q_alive, step_targets)
            ok = (p_err < self.position_tolerance_m) & (r_err < self.rotation_tolerance_rad) & \
                self.arm.within_limits(q_alive).numpy()
            q_all[alive, step:] = q_alive.double().numpy()[:, None]
            pos_err[alive, step], rot_err[alive, step], success[alive, step] = p_err, r_err, ok
            alive = alive[ok]
        return IKResult(q=q_all, success=success, position_error_m=pos_err, rotation_error_rad=rot_err)

    def _track_step(self, q: torch.Tensor, target: pk.Transform3d) -> torch.Tensor:
        """IK for one waypoint per row from q [K,dof]; limits enforced only for rows whose plain solution leaves them."""
        free = self._trackers[False]
        free.initial_config = q
        solution: torch.Tensor = free.solve(target).solutions[:, 0].clone()
        outside = ~self.arm.within_limits(solution)
        if bool(outside.any()):
            # A joint a hair past its stop is usually still on target once clamped; only the rest pay for
            # pytorch_kinematics' limit enforcement (about 12 ms a call, most of a screen's tracking time).
            rows = torch.nonzero(outside).flatten()
            clamped = torch.clamp(solution[rows], self.arm.joint_lower, self.arm.joint_upper)
            p_err, r_err = self._errors(clamped, target.get_matrix()[rows].double().numpy())
            on_target = torch.as_tensor((p_err < self.position_tolerance_m / 2) & (r_err < self.rotation_tolerance_rad / 2))
            solution[rows[on_target]] = clamped[on_target]
            outside[rows[on_target]] = False
        if bool(outside.any()):
            enforced = self._trackers[True]
            enforced.initial_config = q[outside]
            rows = torch.nonzero(outside).flatten()
            solution[rows] = enforced.solve(_select(target, rows)).solutions[:, 0]
        return solution

    def _errors(self, q: torch.Tensor, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        reached = self.arm.flange_pose(q.to(torch.float32)).double().numpy()
        return pose_errors(reached, targets)

    def hand_pose(self, q: np.ndarray) -> np.ndarray:
        """Forward kinematics: hand base pose(s) in the world for arm joints q [dof] or [B,dof]."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        flange = self.arm.flange_pose(torch.as_tensor(q, dtype=torch.float32)).double().numpy()
        out: np.ndarray = self.T_world_base @ flange @ self.T_flange_hand
        return out[0] if out.shape[0] == 1 else out


def _select(transforms: pk.Transform3d, rows: torch.Tensor) -> pk.Transform3d:
    return pk.Transform3d(matrix=transforms.get_matrix()[rows])


def pose_errors(reached: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error [K] (m) and rotation error [K] (rad, angle of R_reachedᵀ R_target) between transforms."""
    position = np.linalg.norm(reached[..., :3, 3] - targets[..., :3, 3], axis=-1)
    relative = np.swapaxes(reached[..., :3, :3], -1, -2) @ targets[..., :3, :3]
    cos = (np.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0
    return position, np.arccos(np.clip(cos, -1.0, 1.0))


def _check_transforms(transforms: np.ndarray) -> np.ndarray:
    out = np.asarray(transforms, dtype=np.float64)
    if out.shape == (4, 4):
        out = out[None]
    if out.ndim != 3 or out.shape[1:] != (4, 4) or len(out) == 0:
        raise IKError(f"targets must be [K,4,4] (K >= 1) or [4,4], got shape {out.shape}")
    if not np.isfinite(out).all():
        raise IKError("targets contain NaN or infinity")
    return out
