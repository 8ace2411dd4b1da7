"""The hand `leap`: a LEAP hand over dynamixel-sdk (Protocol 2.0): 16 X-series motors in current-based position mode.

Connect sequence (per motor, ids 0..15 = LEAP joints '0'..'15'):
  ping (model number) -> torque off -> Operating Mode (addr 11) = 5, current-based position control
  -> Current Limit (addr 38, EEPROM) = the effort cap -> torque on -> Goal Current (addr 102) = effort cap.
Motion: GroupSyncWrite of Goal Position (addr 116, 4 bytes) for all 16 motors each command period.
State: GroupSyncRead of Present Current + Velocity + Position (addr 126, 10 bytes) in one transaction.

Angle convention (LEAP hand API): joint angle 0 is the motors' 180 deg, so motor = joint + pi, in
ticks of 2*pi/4096 rad. Present Velocity counts are 0.229 rev/min; Present Current counts are mA.
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from shared.execution.robot import (
    DeviceRefused,
    DeviceUnavailable,
    Observation,
    RobotError,
    StreamingRobot,
)
from shared.execution.robots.leap.config import LeapConfig, limits

ADDR_OPERATING_MODE, ADDR_CURRENT_LIMIT, ADDR_TORQUE_ENABLE, ADDR_HARDWARE_ERROR = 11, 38, 64, 70
ADDR_GOAL_CURRENT, ADDR_GOAL_POSITION = 102, 116
ADDR_PRESENT_CURRENT, ADDR_PRESENT_VELOCITY, ADDR_PRESENT_POSITION = 126, 128, 132
LEN_GOAL_POSITION, LEN_PRESENT_STATE = 4, 10  # present current(2) + velocity(4) + position(4)
CURRENT_BASED_POSITION_MODE = 5
TICKS_PER_RAD = 4096 / (2 * math.pi)
VELOCITY_UNIT_RAD_S = 0.229 * 2 * math.pi / 60
LEAP_ZERO_OFFSET_RAD = math.pi


def _sdk() -> Any:
    try:
        import dynamixel_sdk
    except ImportError:
        raise DeviceUnavailable("LEAP hand: dynamixel-sdk is not installed (pip install 'gd2p-zenoh[leap]')") from None
    return dynamixel_sdk


class LeapRobot(StreamingRobot):
    """The LEAP hand of `config` (joints '0'..'15' = limits.joint_names)."""

    name = "leap"
    reports_effort = True  # Present Current, mA

    def __init__(self, config: LeapConfig):
        device_limits = limits()
        super().__init__(device_limits.joint_names, device_limits, config.command_rate_hz,
                         config.settle_tolerance_rad, config.settle_timeout_s)
        self.config = config
        self.retries = config.retries
        if len(config.motor_ids) != len(self.joint_names):
            raise ValueError(f"LEAP: {len(config.motor_ids)} motor ids for {len(self.joint_names)} joints")
        self.port, self.baudrate = config.port, config.baudrate
        self.motor_ids = [int(i) for i in config.motor_ids]
        self.effort_cap = np.full(len(self.motor_ids), float(config.current_limit_ma))
        self._io = threading.Lock()  # one transaction on the half-duplex bus at a time
        self._port: Any = None
        self._packets: Any = None
        self._writer: Any = None
        self._reader: Any = None

    @property
    def connected(self) -> bool:
        return self._port is not None

    def connect(self) -> None:
        """Open the port and configure every motor; DeviceRefused if a motor reports a hardware error
        (overload, overheating, ...): recover() reboots such motors and connects."""
        if self.connected:
            return
        self._open_port()
        try:
            self._configure(_sdk())
        except RobotError:
            self._close_port()
            raise

    def _open_port(self) -> None:
        sdk = _sdk()
        port = sdk.PortHandler(self.port)
        try:
            opened = port.openPort() and port.setBaudRate(self.baudrate)
        except Exception as exc:  # pyserial raises SerialException (an OSError) for a missing device
            raise DeviceUnavailable(f"LEAP hand: cannot open serial port {self.port}: {exc}") from None
        if not opened:
            raise DeviceUnavailable(f"LEAP hand: cannot open {self.port} at {self.baudrate} baud")
        self._port, self._packets = port, sdk.PacketHandler(2.0)

    def _configure(self, sdk: Any) -> None:
        missing = [i for i in self.motor_ids if not self._ping(sdk, i)]
        if missing:
            raise DeviceUnavailable(f"LEAP hand: motors {missing} do not answer on {self.port} "
                                    f"(power, cabling, ids or baud rate {self.baudrate})")
        caps = [int(round(self.config.current_limit_ma))] * len(self.motor_ids)
        for motor, cap in zip(self.motor_ids, caps, strict=False):
            self._write(motor, ADDR_TORQUE_ENABLE, 1, 0)  # EEPROM items below are writable only with torque off
            self._write(motor, ADDR_OPERATING_MODE, 1, CURRENT_BASED_POSITION_MODE)
            self._write(motor, ADDR_CURRENT_LIMIT, 2, cap)
        self._hold_here()
        for motor, cap in zip(self.motor_ids, caps, strict=False):
            self._write(motor, ADDR_TORQUE_ENABLE, 1, 1)
            self._write(motor, ADDR_GOAL_CURRENT, 2, cap)
        self._writer = sdk.GroupSyncWrite(self._port, self._packets, ADDR_GOAL_POSITION, LEN_GOAL_POSITION)
        self._reader = sdk.GroupSyncRead(self._port, self._packets, ADDR_PRESENT_CURRENT, LEN_PRESENT_STATE)
        for motor in self.motor_ids:
            self._reader.addParam(motor)

    def _ping(self, sdk: Any, motor: int) -> bool:
        _, result, _ = self._transaction(self._packets.ping, motor)
        return bool(result == sdk.COMM_SUCCESS)

    def _hold_here(self) -> None:
        """Goal Position := present position before torque goes on, so enabling torque does not jump."""
        for motor in self.motor_ids:
            ticks, result, error = self._transaction(self._packets.read4ByteTxRx, motor, ADDR_PRESENT_POSITION)
            self._check(result, error, motor, "read present position")
            self._write(motor, ADDR_GOAL_POSITION, 4, ticks)

    def _transaction(self, fn: Callable[..., Any], *args: int) -> Any:
        """One instruction/status exchange; retried when the status packet is lost (writes and reads are
        idempotent), as a lost packet on a loaded host or a noisy RS-485 line is not a dead motor."""
        for _ in range(self.retries + 1):
            with self._io:
                answer = fn(self._port, *args)
            if answer[-2] == 0:  # (..., result, error): COMM_SUCCESS
                break
        return answer

    def _write(self, motor: int, address: int, size: int, value: int) -> None:
        write = {1: self._packets.write1ByteTxRx, 2: self._packets.write2ByteTxRx, 4: self._packets.write4ByteTxRx}[size]
        result, error = self._transaction(write, motor, address, int(value) & ((1 << (8 * size)) - 1))
        self._check(result, error, motor, f"write {value} to address {address}")

    def _check(self, result: int, error: int, motor: int, what: str) -> None:
        if result != 0:  # COMM_SUCCESS
            raise DeviceUnavailable(f"LEAP motor {motor}: {what}: {self._packets.getTxRxResult(result)}")
        if error:
            raise DeviceRefused(f"LEAP motor {motor}: {what}: {self._packets.getRxPacketError(error)}"
                                f"{' (hardware error: call recover())' if error & 0x80 else ''}")

    def disconnect(self) -> None:
        if not self.connected:
            return
        try:
            for motor in self.motor_ids:
                self._write(motor, ADDR_TORQUE_ENABLE, 1, 0)
        except RobotError:
            pass  # leaving anyway; the port closes below
        finally:
            self._close_port()

    def _close_port(self) -> None:
        try:
            self._port.closePort()
        finally:
            self._port = self._packets = self._writer = self._reader = None

    def _send_positions(self, q: np.ndarray) -> None:
        self.require_connected()
        ticks = np.round((np.asarray(q) + LEAP_ZERO_OFFSET_RAD) * TICKS_PER_RAD).astype(np.int64)
        with self._io:
            self._writer.clearParam()
            for motor, value in zip(self.motor_ids, ticks, strict=False):
                self._writer.addParam(motor, int(value).to_bytes(4, "little", signed=True))
            result = self._writer.txPacket()
        if result != 0:
            raise DeviceUnavailable(f"LEAP hand: goal-position sync write failed: {self._packets.getTxRxResult(result)}")

    def observe(self) -> Observation:
        self.require_connected()
        with self._io:
            for _ in range(self.retries + 1):  # a lost status packet is retried, as on a real USB-serial link
                result = self._reader.txRxPacket()
                if result == 0:
                    break
            if result != 0:
                raise DeviceUnavailable(f"LEAP hand: state sync read failed: {self._packets.getTxRxResult(result)}")
            raw = [(self._reader.getData(m, ADDR_PRESENT_CURRENT, 2), self._reader.getData(m, ADDR_PRESENT_VELOCITY, 4),
                    self._reader.getData(m, ADDR_PRESENT_POSITION, 4)) for m in self.motor_ids]
        current, velocity, position = (np.array([_signed(v[k], (2, 4, 4)[k]) for v in raw], dtype=np.float64)
                                       for k in range(3))
        return Observation(time.time(), self.joint_names, position / TICKS_PER_RAD - LEAP_ZERO_OFFSET_RAD,
                          velocity * VELOCITY_UNIT_RAD_S, current)

    def recover(self) -> None:
        """Reboot motors reporting a hardware error (overload, overheating...), then re-enable torque in place.

        Also usable when connect() was refused because of such an error: it opens the port first.
        """
        super().recover()
        opened_here = not self.connected
        if opened_here:
            self._open_port()
        try:
            sdk = _sdk()
            for motor in self._faulty():
                result, _ = self._transaction(self._packets.reboot, motor)
                if result != 0:
                    raise DeviceUnavailable(f"LEAP motor {motor}: reboot failed: {self._packets.getTxRxResult(result)}")
            self._configure(sdk)
        except RobotError:
            if opened_here:
                self._close_port()
            raise

    def _faulty(self) -> list[int]:
        faulty = []
        for motor in self.motor_ids:
            value, result, error = self._transaction(self._packets.read1ByteTxRx, motor, ADDR_HARDWARE_ERROR)
            if result == 0 and (value or error & 0x80):
                faulty.append(motor)
        return faulty


def _signed(value: int, size: int) -> int:
    bits = 8 * size
    return value - (1 << bits) if value >= 1 << (bits - 1) else value
