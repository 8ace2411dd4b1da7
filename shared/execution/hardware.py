"""The bridge's hardware robot from flags: which arm and hand, and the config of each.

    spec = HardwareSpec.from_args(args)   # --hardware xarm7+leap --xarm7-ip ... --leap-port ...
    robots = spec.robots()                # the arm's and the hand's robots (not yet connected)
    connect_all(robots)                   # all connected, or none (DeviceUnavailable / DeviceRefused)
    executor = Executor(spec.arm, spec.hand, robots, estop)

Names are the one vocabulary of robots/__init__.py: arm `panda` (a Franka Research 3) or `xarm7`,
hand `leap` or `allegro`; every flag of a device starts with its name. Each robot's vendor package
is an optional extra, imported only when its device connects.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass

from shared.contracts.messages import HAND_ARM_PAIRS
from shared.execution.robot import Robot, RobotError
from shared.execution.robots.allegro.config import AllegroConfig
from shared.execution.robots.allegro.robot import AllegroRobot
from shared.execution.robots.leap.config import LeapConfig
from shared.execution.robots.leap.robot import LeapRobot
from shared.execution.robots.panda.config import PandaConfig
from shared.execution.robots.panda.robot import PandaRobot
from shared.execution.robots.xarm7.config import XArm7Config
from shared.execution.robots.xarm7.robot import XArm7Robot

ArmConfig = PandaConfig | XArm7Config
HandConfig = LeapConfig | AllegroConfig


class HardwareConfigError(ValueError):
    """The hardware flags do not describe a robot the bridge can drive."""


@dataclass(frozen=True)
class HardwareSpec:
    arm: str
    hand: str
    arm_config: ArmConfig
    hand_config: HandConfig

    def __post_init__(self) -> None:
        _check_pairing(self.arm, self.hand)

    @staticmethod
    def add_cli_args(parser: argparse.ArgumentParser) -> None:
        group = parser.add_argument_group("hardware robot (default: the simulated robot)")
        group.add_argument("--hardware", metavar="ARM+HAND", default=None,
                           help="drive real devices: panda+allegro (Franka FR3 + Allegro V5) or xarm7+leap")
        group.add_argument("--panda-host", default=None, help="the panda arm's (Franka FR3's) FCI address")
        group.add_argument("--panda-no-realtime", action="store_true",
                           help="do not require a real-time kernel (simulators only)")
        group.add_argument("--xarm7-ip", default=None, help="the xArm7 controller's address")
        group.add_argument("--leap-port", default=None, help="the LEAP hand's serial port, e.g. /dev/ttyUSB0")
        group.add_argument("--leap-baudrate", type=int, default=4_000_000)
        group.add_argument("--leap-current-limit-ma", type=float, default=550.0,
                           help="Dynamixel current cap (mA) of the LEAP motors (at most the device limit)")
        group.add_argument("--allegro-interface", default="socketcan", help="python-can interface (default %(default)s)")
        group.add_argument("--allegro-channel", default="can0", help="CAN channel (default %(default)s)")
        group.add_argument("--allegro-h-inf", action="store_true",
                           help="the Allegro runs H-inf firmware (position targets on the SET_TORQUE ids)")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> HardwareSpec | None:
        """None when --hardware is not given (the simulated robot); HardwareConfigError if an address is missing."""
        if not getattr(args, "hardware", None):
            return None
        arm, sep, hand = args.hardware.partition("+")
        if not sep:
            raise HardwareConfigError(f"--hardware takes ARM+HAND (e.g. xarm7+leap), got {args.hardware!r}")
        _check_pairing(arm, hand)  # before asking for the addresses of devices it cannot drive
        return cls(arm, hand, _arm_config(arm, args), _hand_config(hand, args))

    def robots(self) -> list[Robot]:
        """The arm's and the hand's robots, not connected (each imports its vendor package on connect)."""
        return [_robot(self.arm_config), _robot(self.hand_config)]


def _check_pairing(arm: str, hand: str) -> None:
    if (hand, arm) not in HAND_ARM_PAIRS:
        pairs = ", ".join(f"{a}+{h}" for h, a in sorted(HAND_ARM_PAIRS))
        raise HardwareConfigError(f"no hardware pairing {arm}+{hand}; supported: {pairs}")


def _arm_config(arm: str, args: argparse.Namespace) -> ArmConfig:
    if arm == "panda":
        return PandaConfig(_need(args.panda_host, "--panda-host"), realtime=not args.panda_no_realtime)
    return XArm7Config(_need(args.xarm7_ip, "--xarm7-ip"))


def _hand_config(hand: str, args: argparse.Namespace) -> HandConfig:
    if hand == "leap":
        return LeapConfig(_need(args.leap_port, "--leap-port"), baudrate=args.leap_baudrate,
                          current_limit_ma=args.leap_current_limit_ma)
    return AllegroConfig(args.allegro_interface, args.allegro_channel, h_inf_firmware=args.allegro_h_inf)


def _robot(config: ArmConfig | HandConfig) -> Robot:
    if isinstance(config, PandaConfig):
        return PandaRobot(config)
    if isinstance(config, XArm7Config):
        return XArm7Robot(config)
    if isinstance(config, LeapConfig):
        return LeapRobot(config)
    return AllegroRobot(config)


def _need(value: str | None, flag: str) -> str:
    if not value:
        raise HardwareConfigError(f"{flag} is required for this robot")
    return value


def connect_all(robots: list[Robot]) -> None:
    """Connect every robot, or none: if one fails, the ones already connected are disconnected again."""
    connected: list[Robot] = []
    try:
        for robot in robots:
            robot.connect()
            connected.append(robot)
    except RobotError:
        for robot in reversed(connected):
            robot.disconnect()
        raise
