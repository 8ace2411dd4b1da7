"""The bridge's hardware robot from flags: which arm and hand, and where each one is connected.

    spec = HardwareSpec.from_args(args)         # --hardware xarm7+leap --xarm-ip ... --leap-port ...
    devices = spec.devices()                    # adapters (not yet connected) with their device limits
    connect_all(devices)                        # all connected, or none (DeviceUnavailable / DeviceRefused)
    executor = SafeExecutor(session, spec.arm, spec.hand, devices)

Arm "panda" is the Franka Research 3 (plans use the Panda model's joint names; franky-control), arm
"xarm7" the UFactory xArm7; hands "leap" (Dynamixel bus) and "allegro" (CAN). Each adapter's vendor
package is an optional extra, imported only when its device connects.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass

from services.robot_bridge.backend import Backend, BackendError
from services.robot_bridge.safety import ALLEGRO_LIMITS, FR3_LIMITS, LEAP_LIMITS, XARM7_LIMITS, Device
from shared.messages import HAND_ARM_PAIRS


class HardwareConfigError(ValueError):
    """The hardware flags do not describe a robot the bridge can drive."""


@dataclass(frozen=True)
class HardwareSpec:
    arm: str
    hand: str
    franka_host: str | None = None
    franka_realtime: bool = True
    xarm_ip: str | None = None
    leap_port: str | None = None
    leap_baudrate: int = 4_000_000
    leap_current_limit_ma: float = 550.0
    allegro_interface: str = "socketcan"
    allegro_channel: str = "can0"
    allegro_h_inf_firmware: bool = False

    def __post_init__(self) -> None:
        if (self.hand, self.arm) not in HAND_ARM_PAIRS:
            pairs = ", ".join(f"{a}+{h}" for h, a in sorted(HAND_ARM_PAIRS))
            raise HardwareConfigError(f"no hardware pairing {self.arm}+{self.hand}; supported: {pairs}")

    @staticmethod
    def add_cli_args(parser: argparse.ArgumentParser) -> None:
        group = parser.add_argument_group("hardware robot (default: the simulated robot)")
        group.add_argument("--hardware", metavar="ARM+HAND", default=None,
                           help="drive real devices: panda+allegro (Franka FR3 + Allegro V5) or xarm7+leap")
        group.add_argument("--franka-host", default=None, help="the FR3's FCI address")
        group.add_argument("--franka-no-realtime", action="store_true",
                           help="do not require a real-time kernel (simulators only)")
        group.add_argument("--xarm-ip", default=None, help="the xArm controller's address")
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
        """None when --hardware is not given (the simulated robot)."""
        if not getattr(args, "hardware", None):
            return None
        arm, sep, hand = args.hardware.partition("+")
        if not sep:
            raise HardwareConfigError(f"--hardware takes ARM+HAND (e.g. xarm7+leap), got {args.hardware!r}")
        return cls(arm=arm, hand=hand, franka_host=args.franka_host, franka_realtime=not args.franka_no_realtime,
                   xarm_ip=args.xarm_ip, leap_port=args.leap_port, leap_baudrate=args.leap_baudrate,
                   leap_current_limit_ma=args.leap_current_limit_ma, allegro_interface=args.allegro_interface,
                   allegro_channel=args.allegro_channel, allegro_h_inf_firmware=args.allegro_h_inf)

    def devices(self) -> list[Device]:
        """The arm's and the hand's adapters with their limits (HardwareConfigError if an address is missing)."""
        return [self._arm(), self._hand()]

    def _arm(self) -> Device:
        if self.arm == "panda":
            from services.robot_bridge.adapters.franka import FrankaBackend

            return Device(FrankaBackend(_need(self.franka_host, "--franka-host"), realtime=self.franka_realtime),
                          FR3_LIMITS)
        from services.robot_bridge.adapters.xarm import XArmBackend

        return Device(XArmBackend(_need(self.xarm_ip, "--xarm-ip")), XARM7_LIMITS)

    def _hand(self) -> Device:
        if self.hand == "leap":
            from services.robot_bridge.adapters.leap import LeapBackend

            return Device(LeapBackend(_need(self.leap_port, "--leap-port"), baudrate=self.leap_baudrate,
                                      current_limit_ma=self.leap_current_limit_ma), LEAP_LIMITS)
        from services.robot_bridge.adapters.allegro import AllegroBackend

        return Device(AllegroBackend(self.allegro_interface, self.allegro_channel,
                                     h_inf_firmware=self.allegro_h_inf_firmware), ALLEGRO_LIMITS)


def _need(value: str | None, flag: str) -> str:
    if not value:
        raise HardwareConfigError(f"{flag} is required for this robot")
    return value


def connect_all(devices: list[Device]) -> None:
    """Connect every device, or none: if one fails, the ones already connected are disconnected again."""
    connected: list[Backend] = []
    try:
        for device in devices:
            device.backend.connect()
            connected.append(device.backend)
    except BackendError:
        for backend in reversed(connected):
            backend.disconnect()
        raise
