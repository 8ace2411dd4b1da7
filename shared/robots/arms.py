"""Robot arms (Franka Panda, UFactory xArm7), the arm-hand mount and combined arm+hand URDFs.

Both arms come from the `example-robot-data` wheel and are loaded from resolved copies (absolute mesh paths;
see shared/robots/hands/urdf.py). The Panda's Franka gripper is pruned: the dexterous hand takes its place on the
flange (`panda_link8`); the xArm7's flange is `link_eef` (= link7's frame).

Mount (flange -> hand base link), the same rule for every arm/hand pair: the hand is bolted by the back of
its palm to a flat adapter on the flange, so
- the palm normal points along the flange's +z axis (away from the arm): the arm is always behind the palm,
  which is what the energy's E_arm = max(0, v_palm.z) assumes (a palm facing up puts the arm below it);
- the fingers point along the flange's +x axis;
- the centre of the back of the palm sits `ADAPTER_THICKNESS_M` (20 mm, an aluminium plate plus the ISO
  9409 flange spigot) in front of the flange.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytorch_kinematics as pk
import torch

from shared.atomic import atomic_write_text
from shared.robots.hands import HandModel, load_hand
from shared.robots.hands.urdf import (
    RobotAssetError,
    cache_dir,
    content_key,
    example_robot_data_file,
    merge_urdf,
    read_urdf,
    resolved_urdf,
)

ADAPTER_THICKNESS_M = 0.02


class ArmModelError(ValueError):
    """Bad input to an arm model (unknown arm, wrong joint vector shape, ...)."""


@dataclass(frozen=True)
class ArmSpec:
    name: str
    source: str  # file inside example-robot-data's robots/
    flange_link: str
    joint_names: tuple[str, ...]
    home: tuple[float, ...]
    prune_below_link: str | None = None


ARM_SPECS: dict[str, ArmSpec] = {
    "panda": ArmSpec(
        name="panda",
        source="panda_description/urdf/panda.urdf",
        flange_link="panda_link8",
        joint_names=tuple(f"panda_joint{i}" for i in range(1, 8)),
        # Franka's "ready" pose (the SRDF's default state): flange 0.59 m above the base, pointing down.
        home=(0.0, -0.785398, 0.0, -2.356194, 0.0, 1.570796, 0.785398),
        prune_below_link="panda_link8",
    ),
    "xarm7": ArmSpec(
        name="xarm7",
        source="xarm_description/urdf/xarm7.urdf",
        flange_link="link_eef",
        joint_names=tuple(f"joint{i}" for i in range(1, 8)),
        # The SRDF's "home" (all zeros) is the arm standing straight up, a singular configuration. This is a
        # bent-elbow ready pose: flange 0.36 m in front of the base, 0.44 m up, pointing down.
        home=(0.0, -0.4, 0.0, 0.9, 0.0, 1.3, 0.0),
    ),
}


class ArmModel:
    """Kinematics and limits of one arm. Build with `load_arm(name)` (cached)."""

    def __init__(self, spec: ArmSpec):
        self.spec = spec
        self.name = spec.name
        self.urdf_path: Path = resolved_urdf(example_robot_data_file(spec.source), f"{spec.name}_arm",
                                             spec.prune_below_link)
        self.robot = read_urdf(self.urdf_path)
        self.chain = pk.build_chain_from_urdf(self.urdf_path.read_text()).to(dtype=torch.float32)
        if tuple(self.chain.get_joint_parameter_names()) != spec.joint_names:
            raise RobotAssetError(f"{self.name}: URDF joints {self.chain.get_joint_parameter_names()} "
                                  f"differ from the spec {spec.joint_names}")
        self.joint_names = spec.joint_names
        self.dof = len(self.joint_names)
        joints = [self.robot.joint(name) for name in self.joint_names]
        self.joint_lower = torch.tensor([j.lower for j in joints], dtype=torch.float32)
        self.joint_upper = torch.tensor([j.upper for j in joints], dtype=torch.float32)
        self.velocity_limits = torch.tensor([j.velocity for j in joints], dtype=torch.float32)
        self.effort_limits = torch.tensor([j.effort for j in joints], dtype=torch.float32)
        self.home = torch.tensor(spec.home, dtype=torch.float32)
        self.base_link = self.robot.root_link
        self.flange_link = spec.flange_link
        frames = self.chain.idx_to_frame
        self.link_names: tuple[str, ...] = tuple(frames[i] for i in range(len(frames)))  # pytorch_kinematics' order
        self._flange_index = self.link_names.index(self.flange_link)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """All link frames [B,L,4,4] (link_names order) in the arm's base frame, for joints q [B,dof]."""
        if q.ndim != 2 or q.shape[1] != self.dof:
            raise ArmModelError(f"{self.name}: joints must have shape [B, {self.dof}], got {tuple(q.shape)}")
        frames: torch.Tensor = self.chain.forward_kinematics_tensor(q).transpose(0, 1)
        return frames

    def flange_pose(self, q: torch.Tensor) -> torch.Tensor:
        """Flange frame [B,4,4] in the arm's base frame."""
        return self.forward(q)[:, self._flange_index]

    def serial_chain(self) -> pk.SerialChain:
        """Base -> flange serial chain (for pytorch_kinematics' Jacobian and IK solvers)."""
        return pk.SerialChain(self.chain, self.flange_link).to(dtype=torch.float32)

    def within_limits(self, q: torch.Tensor) -> torch.Tensor:
        """[B] bool: every joint inside its position limits."""
        return ((q >= self.joint_lower) & (q <= self.joint_upper)).all(-1)


@functools.cache
def load_arm(name: str) -> ArmModel:
    """The arm model for 'panda' or 'xarm7' (built once per process)."""
    try:
        spec = ARM_SPECS[name]
    except KeyError:
        raise ArmModelError(f"unknown arm {name!r}; known arms: {sorted(ARM_SPECS)}") from None
    return ArmModel(spec)


def mount(arm: ArmModel | str, hand: HandModel | str) -> np.ndarray:
    """Flange -> hand base link transform (4x4, float64); see the module docstring for the convention."""
    hand = load_hand(hand) if isinstance(hand, str) else hand
    arm_name = arm if isinstance(arm, str) else arm.name
    if arm_name not in ARM_SPECS:  # the adapter is the same for every arm; the name is still checked
        raise ArmModelError(f"unknown arm {arm_name!r}; known arms: {sorted(ARM_SPECS)}")
    normal = hand.palm_normal_base.double().numpy()
    fingers = hand.finger_direction_base.double().numpy()
    if abs(normal @ fingers) > 1e-6:
        raise RobotAssetError(f"{hand.name}: finger direction is not orthogonal to the palm normal")
    hand_axes = np.stack((fingers, np.cross(normal, fingers), normal), axis=1)  # flange x, y, z in the hand frame
    transform = np.eye(4)
    transform[:3, :3] = hand_axes.T
    transform[:3, 3] = np.array([0.0, 0.0, ADAPTER_THICKNESS_M]) - hand_axes.T @ hand.mount_point_base.double().numpy()
    return transform


def combined_urdf(arm: ArmModel | str, hand: HandModel | str) -> Path:
    """A URDF of the arm with the hand fixed to its flange by `mount` (cached on disk); joints: arm then hand."""
    arm = load_arm(arm) if isinstance(arm, str) else arm
    hand = load_hand(hand) if isinstance(hand, str) else hand
    transform = mount(arm, hand)
    key = content_key(arm.urdf_path.read_text(), hand.urdf_path.read_text(), np.array2string(transform, precision=12))
    target = cache_dir() / f"{arm.name}_{hand.name}-{key}.urdf"
    if not target.is_file():
        text = merge_urdf(arm.urdf_path, hand.urdf_path, arm.flange_link, transform,
                          joint_name=mount_joint_name(arm.name, hand.name), robot_name=f"{arm.name}_{hand.name}")
        atomic_write_text(target, text)
    return target


def mount_joint_name(arm: str, hand: str) -> str:
    """Name of the fixed flange -> hand joint in `combined_urdf`."""
    return f"{arm}_{hand}_mount"
