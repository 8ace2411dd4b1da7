"""The hand `allegro`: an Allegro hand V5 over python-can (the V5 CAN protocol: see protocol.py for ids and sources).

Connect: open the bus -> SYSTEM_OFF -> HAND_INFO request -> SET_PERIOD (position reports every
`report_period_ms`) -> wait for the hand's info and all four fingers' positions (DeviceUnavailable if
nothing answers, DeviceRefused if it reports a fault) -> SET_POSE to where the fingers are (holding,
so servo-on does not jump) -> SYSTEM_ON.
Motion: four SET_POSE frames (one per finger) each command period; the hand's firmware servoes.
State: the latest FINGER_POSE reports; velocities are finite differences of consecutive reports through a
30 Hz low-pass (the V5 reports no velocity); efforts are the FINGER_CURRENT reports, monitored against the effort limit.
Stop: SET_POSE to the measured positions (hold). Recover: SYSTEM_OFF, re-read HAND_INFO (DeviceRefused
while a fault persists), hold in place, SYSTEM_ON confirmed by HAND_INFO's servo bit. Disconnect: reports off, SYSTEM_OFF.
"""
from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from shared.execution.robot import DeviceRefused, DeviceUnavailable, Observation, StreamingRobot
from shared.execution.robots.allegro import protocol as proto
from shared.execution.robots.allegro.config import AllegroConfig, limits

VELOCITY_FILTER_HZ = 30.0  # the cut-off Wonik's driver uses for its joint-velocity low-pass (v4_spec.hpp)


def _can() -> Any:
    try:
        import can
    except ImportError:
        raise DeviceUnavailable("Allegro hand: python-can is not installed (pip install 'gd2p-zenoh[allegro]')") from None
    return can


class AllegroRobot(StreamingRobot):
    """The Allegro hand V5 of `config` (joints 'joint_0.0'..'joint_15.0' = limits.joint_names)."""

    name = "allegro"
    reports_effort = True

    def __init__(self, config: AllegroConfig):
        device_limits = limits()
        super().__init__(device_limits.joint_names, device_limits, config.command_rate_hz,
                         config.settle_tolerance_rad, config.settle_timeout_s)
        self.config = config
        self.interface, self.channel, self.bitrate = config.interface, config.channel, config.bitrate
        self.report_period_ms = config.report_period_ms
        self.connect_timeout_s, self.stale_after_s = config.connect_timeout_s, config.stale_after_s
        # Which message carries position targets: SET_POSE, or SET_TORQUE's ids on H-inf firmware.
        self.pose_message_id = proto.ID_CMD_SET_TORQUE if config.h_inf_firmware else proto.ID_CMD_SET_POSE
        # effort_cap stays None: position mode, the firmware's own current limit applies; measured current is monitored
        self._bus: Any = None
        self._notifier: Any = None
        self._lock = threading.Lock()
        self._positions = np.zeros(16)
        self._velocities = np.zeros(16)
        self._currents = np.zeros(16)
        self._stamp = np.zeros(proto.FINGERS)  # monotonic time of each finger's last report
        self._info: bytes | None = None
        self._info_event = threading.Event()

    @property
    def connected(self) -> bool:
        return self._bus is not None

    # ---------------------------------------------------------------- link
    def connect(self) -> None:
        if self.connected:
            return
        can = _can()
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.bitrate and self.interface not in ("virtual", "socketcan"):
            kwargs["bitrate"] = self.bitrate  # socketcan's bitrate is set on the link (ip link set can0 ...)
        try:
            self._bus = can.Bus(**kwargs)
        except (can.CanError, OSError, ValueError) as exc:
            raise DeviceUnavailable(f"Allegro hand: cannot open CAN {self.interface}:{self.channel}: {exc}") from None
        self._notifier = can.Notifier(self._bus, [self._on_frame], timeout=0.05)
        try:
            self._start()
        except Exception:
            self._close_bus()
            raise

    def _start(self) -> None:
        self._send(proto.ID_CMD_SYSTEM_OFF)
        status = self._request_info()
        self._check_status(status)
        self._send(proto.ID_CMD_SET_PERIOD, proto.encode_period(self.report_period_ms))
        deadline = time.monotonic() + self.connect_timeout_s
        while (self._stamp == 0).any():
            if time.monotonic() > deadline:
                raise DeviceUnavailable(f"Allegro hand on {self.interface}:{self.channel} sends no joint positions")
            time.sleep(0.005)
        self._send_positions(self.observe().positions)  # hold here: servo-on must not jump to a stale target
        self._servo_on()

    def _servo_on(self) -> None:
        self._send(proto.ID_CMD_SYSTEM_ON)
        status = self._request_info()
        self._check_status(status)
        if not status & proto.STATUS_SERVO_ON:
            raise DeviceRefused("Allegro hand did not switch its servos on (HAND_INFO status shows servo off)")

    def _request_info(self) -> int:
        self._info_event.clear()
        self._send(proto.ID_RTR_HAND_INFO, remote=True)
        if not self._info_event.wait(self.connect_timeout_s):
            raise DeviceUnavailable(f"no Allegro hand answers on {self.interface}:{self.channel} "
                                    f"(power, CAN wiring, bitrate)")
        assert self._info is not None  # set before the event
        return self._info[6]

    def _check_status(self, status: int) -> None:
        faults = []
        if status & proto.STATUS_OVER_TEMPERATURE:
            faults.append("over-temperature")
        if status & proto.STATUS_COMM_FAULT:
            faults.append("internal communication fault")
        if faults:
            raise DeviceRefused(f"Allegro hand reports {', '.join(faults)}; let it cool / check it, then recover()")

    def disconnect(self) -> None:
        if not self.connected:
            return
        try:
            self._send(proto.ID_CMD_SET_PERIOD, proto.encode_period(0))
            self._send(proto.ID_CMD_SYSTEM_OFF)
        finally:
            self._close_bus()

    def _close_bus(self) -> None:
        if self._notifier is not None:
            self._notifier.stop()
        if self._bus is not None:
            self._bus.shutdown()
        self._bus = self._notifier = None
        self._stamp[:] = 0

    def _send(self, message_id: int, data: bytes = b"", remote: bool = False) -> None:
        can = _can()
        frame = can.Message(arbitration_id=proto.wire_id(message_id), data=data, is_extended_id=False,
                            is_remote_frame=remote, dlc=0 if remote else len(data))
        try:
            self._bus.send(frame, timeout=0.05)
        except can.CanError as exc:
            raise DeviceUnavailable(f"Allegro hand: CAN send failed: {exc}") from None

    # ---------------------------------------------------------------- frames from the hand
    def _on_frame(self, msg: Any) -> None:  # a can.Message
        if msg.is_error_frame or msg.is_remote_frame:
            return
        mid = proto.message_id(msg.arbitration_id)
        if proto.ID_RTR_FINGER_POSE <= mid < proto.ID_RTR_FINGER_POSE + proto.FINGERS:
            self._on_pose(mid - proto.ID_RTR_FINGER_POSE, proto.decode_joints(msg.data))
        elif proto.ID_RTR_FINGER_CURRENT <= mid < proto.ID_RTR_FINGER_CURRENT + proto.FINGERS:
            finger = mid - proto.ID_RTR_FINGER_CURRENT
            with self._lock:
                self._currents[4 * finger:4 * finger + 4] = proto.decode_counts(msg.data)
        elif mid == proto.ID_RTR_HAND_INFO and len(msg.data) >= 7:
            self._info = bytes(msg.data)
            self._info_event.set()

    def _on_pose(self, finger: int, q: np.ndarray) -> None:
        joints = slice(4 * finger, 4 * finger + 4)
        now = time.monotonic()
        with self._lock:
            previous = self._stamp[finger]
            if previous:
                dt = now - previous
                if dt > 1e-4:  # finite difference through a first-order low-pass (quantisation: 0.088 deg/count)
                    raw = (q - self._positions[joints]) / dt
                    alpha = dt / (dt + 1.0 / (2 * np.pi * VELOCITY_FILTER_HZ))
                    self._velocities[joints] += alpha * (raw - self._velocities[joints])
            self._positions[joints] = q
            self._stamp[finger] = now

    # ---------------------------------------------------------------- contract
    def observe(self) -> Observation:
        self.require_connected()
        with self._lock:
            age = time.monotonic() - self._stamp.min()
            if age > self.stale_after_s:
                raise DeviceUnavailable(f"Allegro hand: no joint positions for {age:.2f} s (CAN link lost?)")
            return Observation(time.time(), self.joint_names, self._positions.copy(), self._velocities.copy(),
                               self._currents.copy())

    def _send_positions(self, q: np.ndarray) -> None:
        self.require_connected()
        q = np.asarray(q, dtype=np.float64)
        for finger in range(proto.FINGERS):
            self._send(self.pose_message_id + finger, proto.encode_joints(q[4 * finger:4 * finger + 4]))

    def recover(self) -> None:
        """Servos off, re-read HAND_INFO (refused while a fault persists), hold in place, servos on."""
        super().recover()
        self.require_connected()
        self._send(proto.ID_CMD_SYSTEM_OFF)
        self._check_status(self._request_info())
        self._send_positions(self.observe().positions)
        self._servo_on()
