"""Allegro hand V5 CAN protocol: message ids, frame ids and payload encodings.

Source: Wonik Robotics' V5 ROS 2 driver (github.com/Wonikrobotics-git/allegro_hand_ros2_V5_Sense,
src/allegro_hand_driver/src/candrv/candef.h, socket_can.cpp and AllegroHandDrv.cpp):
- the wire CAN id is the message id shifted left by 2 (standard 11-bit frames, `can_id = id << 2`);
- payloads are little-endian int16, four joints per finger; fingers 0..3 = index, middle, ring, thumb;
- joint positions are reported in counts of 0.088 degree (`pos * (M_PI / 180.0) * 0.088`).

| message            | id        | wire id        | payload                                                  |
| ------------------ | --------- | -------------- | -------------------------------------------------------- |
| SYSTEM_ON / OFF    | 0x40/0x41 | 0x100 / 0x104  | none: servo power on / off                               |
| SET_PERIOD         | 0x81      | 0x204          | int16 x3: position, IMU, temperature report period (ms)  |
| SET_POSE finger f  | 0xE0 + f  | 0x380 + 4f     | int16 x4: joint position targets (0.088 deg counts)      |
| SET_TORQUE f       | 0x60 + f  | 0x180 + 4f     | H-inf firmware: int16 x4 position targets, as SET_POSE   |
| FINGER_CURRENT f   | 0x00 + f  | 0x000 + 4f     | int16 x4: joint currents (hand -> host)                  |
| FINGER_POSE f      | 0x20 + f  | 0x080 + 4f     | int16 x4: joint positions (hand -> host, every period)   |
| HAND_INFO          | 0x80      | 0x200 (RTR)    | hw version(2), fw version(2), type, temperature, status  |

Firmware variants: Wonik's driver notes that the V5 "H-inf" firmware takes position targets on the
SET_TORQUE ids (0x60 + f, wire 0x180 + 4f; `command_set_pose_direct`), disambiguated by its control
mode. The robot sends SET_POSE by default and the SET_TORQUE ids when told the hand runs that firmware.

HAND_INFO status bits (Wonik's v4_spec.hpp `data_info_t`, kept in V5): bit 0 servo on, bit 1
high-temperature fault, bit 2 internal communication fault.
Assumption, stated because no public V5 document gives it: SET_POSE targets use the same 0.088-degree
counts the hand reports its positions in.
"""
from __future__ import annotations

import math
import struct

import numpy as np

ID_CMD_SYSTEM_ON, ID_CMD_SYSTEM_OFF = 0x40, 0x41
ID_CMD_SET_PERIOD = 0x81
ID_CMD_SET_POSE = 0xE0
ID_CMD_SET_TORQUE = 0x60  # position targets on H-inf firmware (see the module docstring)
ID_RTR_FINGER_CURRENT = 0x00
ID_RTR_FINGER_POSE = 0x20
ID_RTR_HAND_INFO = 0x80
FINGERS, JOINTS_PER_FINGER = 4, 4
RAD_PER_COUNT = 0.088 * math.pi / 180.0
STATUS_SERVO_ON, STATUS_OVER_TEMPERATURE, STATUS_COMM_FAULT = 0x01, 0x02, 0x04


def wire_id(message_id: int) -> int:
    return message_id << 2


def message_id(arbitration_id: int) -> int:
    return arbitration_id >> 2


def encode_joints(values_rad: np.ndarray) -> bytes:
    counts = np.clip(np.round(np.asarray(values_rad, dtype=np.float64) / RAD_PER_COUNT), -32768, 32767).astype(int)
    return struct.pack("<4h", *counts)


def decode_joints(data: bytes | bytearray) -> np.ndarray:
    return np.array(struct.unpack("<4h", bytes(data[:8])), dtype=np.float64) * RAD_PER_COUNT


def decode_counts(data: bytes | bytearray) -> np.ndarray:
    return np.array(struct.unpack("<4h", bytes(data[:8])), dtype=np.float64)


def encode_period(position_ms: int, imu_ms: int = 0, temperature_ms: int = 0) -> bytes:
    return struct.pack("<3h", position_ms, imu_ms, temperature_ms)


def encode_hand_info(hardware: int, firmware: int, right_hand: bool, temperature_c: int, status: int) -> bytes:
    return struct.pack("<HHBBB", hardware, firmware, 0 if right_hand else 1, temperature_c, status)
