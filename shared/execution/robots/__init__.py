"""The robots of the bridge, one folder each (config + robot + protocol fake), and their one vocabulary.

Messages, flags, folders, self-test entries and limits all name an arm `panda` or `xarm7` and a hand
`allegro` or `leap` (`shared.contracts.messages.ARMS` / `HANDS`). `DEVICES` is the one place that says which
hardware and driver stand behind each name — e.g. the arm `panda` is a Franka Research 3 (FR3) driven
through franky-control: plans use the Panda model, which has the FR3's kinematic chain.

    sim/       the simulated arm + hand (PyBullet), the default robot
    mujoco/    the simulated arm + hand in MuJoCo, a second engine
    panda/     Franka Research 3 over franky-control (protocol fake: franky-sim, an optional package)
    xarm7/     UFactory xArm7 over xarm-python-sdk (fake: a controller at the SDK's transport boundary)
    leap/      LEAP hand over dynamixel-sdk (fake: a Dynamixel Protocol 2.0 bus on a pty)
    allegro/   Allegro hand V5 over python-can (fake: a V5 hand on a python-can bus)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

# The simulated robot's engines (`--robot`, `gd2p up --robot`): sim/ (PyBullet, the planner's own) and mujoco/.
SIM_ROBOTS: tuple[str, ...] = ("sim", "mujoco")
# How a simulated robot sees the object while a plan runs (`--tracking`): "image" registers its model in the depth
# frames the engine renders (a real robot's view), "truth" reads the simulator's pose plus noise (quicker).
TrackingMode = Literal["image", "truth"]
TRACKING_MODES: tuple[TrackingMode, ...] = ("image", "truth")


@dataclass(frozen=True)
class Device:
    """What stands behind one arm or hand name on real hardware."""

    name: str  # the name in messages, flags and folders
    kind: Literal["arm", "hand"]
    hardware: str  # what is on the bench
    driver: str  # the vendor package the robot imports (an optional extra)
    extra: str  # pip install 'gd2p-zenoh[<extra>]'


DEVICES: dict[str, Device] = {d.name: d for d in (
    Device("panda", "arm", "Franka Research 3 (FR3; plans use the Panda model, the same kinematic chain)",
           "franky-control", "franka"),
    Device("xarm7", "arm", "UFactory xArm7", "xarm-python-sdk", "xarm"),
    Device("leap", "hand", "LEAP hand (16 Dynamixel X-series motors)", "dynamixel-sdk", "leap"),
    Device("allegro", "hand", "Allegro hand V5 (CAN)", "python-can", "allegro"),
)}
