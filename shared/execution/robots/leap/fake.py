"""The LEAP hand's protocol fake: a Dynamixel Protocol 2.0 bus on a pseudo-terminal: X-series motors (XC330-M288, as in the LEAP hand).

    with DynamixelBus(motor_ids=range(16)) as bus:
        PortHandler(bus.port_name)   # dynamixel-sdk opens the pty's slave side like a USB2Dynamixel

The responder owns the pty's master side. It parses instruction packets (header FF FF FD 00, id,
length, instruction, parameters with byte stuffing, CRC-16) and answers status packets (instruction
0x55, error byte) for PING, READ, WRITE, REBOOT, SYNC READ (one status packet per listed id, in
order) and SYNC WRITE (no answer). Each motor has a control table with the X-series addresses the
LEAP robot uses; EEPROM items (address < 64) are writable only while torque is off (Access Error,
as on the real motors). With torque on, the motor tracks Goal Position with a first-order response
limited to `max_speed_rad_s`; its present current is proportional to the tracking error and clipped
at Goal Current in current-based position mode (operating mode 5).
"""
from __future__ import annotations

import math
import os
import select
import struct
import threading
import time
import tty
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

# Protocol 2.0 instruction codes and status error numbers (ROBOTIS e-Manual, "Protocol 2.0").
INST_PING, INST_READ, INST_WRITE, INST_REBOOT = 0x01, 0x02, 0x03, 0x08
INST_SYNC_READ, INST_SYNC_WRITE, INST_STATUS = 0x82, 0x83, 0x55
ERR_INSTRUCTION, ERR_CRC, ERR_DATA_LENGTH, ERR_ACCESS = 0x02, 0x03, 0x05, 0x07
ALERT_BIT = 0x80
BROADCAST_ID = 0xFE
HEADER = b"\xff\xff\xfd\x00"

# X-series control table (XC330/XL330 e-Manual): address -> (size, signed)
ADDR_MODEL_NUMBER, ADDR_FIRMWARE, ADDR_ID, ADDR_OPERATING_MODE, ADDR_CURRENT_LIMIT = 0, 6, 7, 11, 38
ADDR_TORQUE_ENABLE, ADDR_HARDWARE_ERROR = 64, 70
ADDR_D_GAIN, ADDR_I_GAIN, ADDR_P_GAIN = 80, 82, 84
ADDR_GOAL_CURRENT, ADDR_GOAL_POSITION = 102, 116
ADDR_PRESENT_CURRENT, ADDR_PRESENT_VELOCITY, ADDR_PRESENT_POSITION = 126, 128, 132
EEPROM_END = 64
XC330_M288_MODEL = 1240
TABLE_SIZE = 147

TICKS_PER_RAD = 4096 / (2 * math.pi)
VELOCITY_UNIT_RAD_S = 0.229 * 2 * math.pi / 60  # one Present Velocity count: 0.229 rev/min


def crc16(data: bytes) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, initial 0, not reflected)."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def stuff(params: bytes) -> bytes:
    """Insert 0xFD after every FF FF FD inside a packet body, so it cannot look like a header."""
    out = bytearray()
    for byte in params:
        out.append(byte)
        if len(out) >= 3 and out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(params: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(params):
        out.append(params[i])
        if len(out) >= 3 and out[-3:] == b"\xff\xff\xfd" and i + 1 < len(params) and params[i + 1] == 0xFD:
            i += 1  # drop the stuffing byte
        i += 1
    return bytes(out)


def packet(motor_id: int, instruction: int, params: bytes) -> bytes:
    body = stuff(params)
    frame = HEADER + bytes([motor_id]) + struct.pack("<H", len(body) + 3) + bytes([instruction]) + body
    return frame + struct.pack("<H", crc16(frame))


@dataclass
class SimMotor:
    """One X-series motor: its control table and a first-order position response."""

    motor_id: int
    initial_rad: float = math.pi  # LEAP's zero pose is the motors' 180 deg (2048 ticks)
    max_speed_rad_s: float = 8.48
    time_constant_s: float = 0.02
    amps_per_rad: float = 3000.0  # mA of present current per rad of tracking error (before the cap)
    table: bytearray = field(default_factory=lambda: bytearray(TABLE_SIZE))
    position_rad: float = 0.0
    velocity_rad_s: float = 0.0
    last_update: float = field(default_factory=time.monotonic)

    def __post_init__(self) -> None:
        self.position_rad = self.initial_rad
        self.write_item(ADDR_MODEL_NUMBER, 2, XC330_M288_MODEL)
        self.write_item(ADDR_FIRMWARE, 1, 52)
        self.write_item(ADDR_ID, 1, self.motor_id)
        self.write_item(ADDR_OPERATING_MODE, 1, 3)
        self.write_item(ADDR_CURRENT_LIMIT, 2, 1750)
        self.write_item(ADDR_GOAL_CURRENT, 2, 1750)
        self.write_item(ADDR_GOAL_POSITION, 4, round(self.position_rad * TICKS_PER_RAD))
        self._publish(0.0)

    def read_item(self, address: int, size: int, signed: bool = False) -> int:
        return int.from_bytes(self.table[address:address + size], "little", signed=signed)

    def write_item(self, address: int, size: int, value: int) -> None:
        self.table[address:address + size] = int(value).to_bytes(size, "little", signed=value < 0)

    @property
    def torque_on(self) -> bool:
        return self.table[ADDR_TORQUE_ENABLE] == 1

    def step(self) -> None:
        now = time.monotonic()
        dt, self.last_update = now - self.last_update, now
        if not self.torque_on:
            self.velocity_rad_s = 0.0
            self._publish(0.0)
            return
        goal = self.read_item(ADDR_GOAL_POSITION, 4, signed=True) / TICKS_PER_RAD
        error = goal - self.position_rad
        speed = max(-self.max_speed_rad_s, min(self.max_speed_rad_s, error / self.time_constant_s))
        move = speed * dt
        self.position_rad = goal if abs(move) >= abs(error) else self.position_rad + move
        self.velocity_rad_s = speed if self.position_rad != goal else 0.0
        current = self.amps_per_rad * (goal - self.position_rad)
        if self.table[ADDR_OPERATING_MODE] == 5:
            cap = min(self.read_item(ADDR_GOAL_CURRENT, 2), self.read_item(ADDR_CURRENT_LIMIT, 2))
            current = max(-cap, min(cap, current))
        self._publish(current)

    def _publish(self, current_ma: float) -> None:
        self.write_item(ADDR_PRESENT_CURRENT, 2, int(round(current_ma)))
        self.write_item(ADDR_PRESENT_VELOCITY, 4, int(round(self.velocity_rad_s / VELOCITY_UNIT_RAD_S)))
        self.write_item(ADDR_PRESENT_POSITION, 4, int(round(self.position_rad * TICKS_PER_RAD)))

    def write(self, address: int, data: bytes) -> int:
        """Apply a WRITE; returns the status error number (0 = ok)."""
        if address + len(data) > TABLE_SIZE:
            return ERR_DATA_LENGTH
        if address < EEPROM_END and self.torque_on:
            return ERR_ACCESS
        if address <= ADDR_TORQUE_ENABLE < address + len(data) and self.hardware_error and data[ADDR_TORQUE_ENABLE - address]:
            return ERR_ACCESS  # a motor in shutdown does not enable torque until rebooted
        self.step()
        self.table[address:address + len(data)] = data
        return 0

    @property
    def hardware_error(self) -> int:
        return self.table[ADDR_HARDWARE_ERROR]

    def fault(self, bits: int) -> None:
        """Simulate a shutdown (e.g. 0x20 overload): hardware error set, torque off."""
        self.table[ADDR_HARDWARE_ERROR] = bits
        self.table[ADDR_TORQUE_ENABLE] = 0

    def reboot(self) -> None:
        self.step()
        self.table[ADDR_HARDWARE_ERROR] = 0
        self.table[ADDR_TORQUE_ENABLE] = 0


class DynamixelBus:
    """The responder thread on a pty's master side; `port_name` is the slave device path."""

    def __init__(self, motor_ids: Iterable[int] = range(16), initial_rad: float = math.pi,
                 **motor_kwargs: Any) -> None:  # SimMotor fields
        self.motors = {int(i): SimMotor(int(i), initial_rad, **motor_kwargs) for i in motor_ids}
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes pass through as on a USB serial port
        self.port_name = os.ttyname(self._slave)
        self._buffer = bytearray()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.instructions: list[tuple[int, int]] = []  # (instruction, id) in arrival order, for tests
        self.crc_errors = 0
        self._thread = threading.Thread(target=self._serve, name="dynamixel-bus", daemon=True)
        self._thread.start()

    def __enter__(self) -> DynamixelBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def motor(self, motor_id: int) -> SimMotor:
        with self._lock:
            self.motors[motor_id].step()
            return self.motors[motor_id]

    def positions_rad(self) -> list[float]:
        with self._lock:
            for m in self.motors.values():
                m.step()
            return [m.position_rad for m in self.motors.values()]

    # ---------------------------------------------------------------- protocol
    def _serve(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.05)
            if not ready:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except OSError:
                return
            self._buffer.extend(chunk)
            for frame in self._frames():
                reply = self._handle(frame)
                if reply:
                    os.write(self._master, reply)

    def _frames(self) -> Iterator[bytes]:
        while True:
            start = self._buffer.find(HEADER)
            if start < 0:
                del self._buffer[:-3]
                return
            del self._buffer[:start]
            if len(self._buffer) < 7:
                return
            length = struct.unpack_from("<H", self._buffer, 5)[0]
            total = 7 + length
            if len(self._buffer) < total:
                return
            frame = bytes(self._buffer[:total])
            del self._buffer[:total]
            if crc16(frame[:-2]) != struct.unpack_from("<H", frame, total - 2)[0]:
                self.crc_errors += 1
                continue  # a real motor answers a CRC error only if the id is readable; the SDK then times out
            yield frame

    def _handle(self, frame: bytes) -> bytes:
        motor_id, instruction = frame[4], frame[7]
        params = unstuff(frame[8:-2])
        with self._lock:
            self.instructions.append((instruction, motor_id))
            if instruction == INST_SYNC_READ:
                return self._sync_read(params)
            if instruction == INST_SYNC_WRITE:
                self._sync_write(params)
                return b""
            motor = self.motors.get(motor_id)
            if motor is None:
                return b""  # nobody on the bus with that id: silence, the SDK times out
            if instruction == INST_PING:
                return self._status(motor, 0, struct.pack("<HB", motor.read_item(ADDR_MODEL_NUMBER, 2), motor.table[ADDR_FIRMWARE]))
            if instruction == INST_READ:
                address, size = struct.unpack_from("<HH", params)
                motor.step()
                if address + size > TABLE_SIZE:
                    return self._status(motor, ERR_DATA_LENGTH, b"")
                return self._status(motor, 0, bytes(motor.table[address:address + size]))
            if instruction == INST_WRITE:
                address = struct.unpack_from("<H", params)[0]
                return self._status(motor, motor.write(address, params[2:]), b"")
            if instruction == INST_REBOOT:
                motor.reboot()
                return self._status(motor, 0, b"")
            return self._status(motor, ERR_INSTRUCTION, b"")

    def _status(self, motor: SimMotor, error: int, data: bytes) -> bytes:
        alert = ALERT_BIT if motor.hardware_error else 0
        return packet(motor.motor_id, INST_STATUS, bytes([error | alert]) + data)

    def _sync_read(self, params: bytes) -> bytes:
        address, size = struct.unpack_from("<HH", params)
        replies = []
        for motor_id in params[4:]:
            motor = self.motors.get(motor_id)
            if motor is None:
                break  # the SDK waits for this id and times out, as on a real bus
            motor.step()
            replies.append(self._status(motor, 0, bytes(motor.table[address:address + size])))
        return b"".join(replies)

    def _sync_write(self, params: bytes) -> None:
        address, size = struct.unpack_from("<HH", params)
        body = params[4:]
        entry = 1 + size  # id, then `size` data bytes
        for offset in range(0, len(body) - entry + 1, entry):
            motor = self.motors.get(body[offset])
            if motor is not None:
                motor.write(address, body[offset + 1:offset + entry])
