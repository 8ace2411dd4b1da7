"""The Allegro hand's protocol fake: a simulated V5 hand on a python-can bus (the V5 CAN protocol of protocol.py).

    hand = SimAllegroHand(interface="virtual", channel="allegro-test")
    ... AllegroRobot(AllegroConfig(interface="virtual", channel="allegro-test")) talks to it ...
    hand.close()

It answers HAND_INFO requests, streams FINGER_POSE and FINGER_CURRENT frames every SET_PERIOD ms,
and while its servos are on (SYSTEM_ON) each joint tracks its last SET_POSE target with a first-order
response limited to `max_speed_rad_s`; the current is proportional to the tracking error.
"""
from __future__ import annotations

import threading
import time

import can
import numpy as np

from shared.execution.robots.allegro import protocol as proto


class SimAllegroHand:
    def __init__(self, interface: str = "virtual", channel: str = "allegro", initial_rad: np.ndarray | None = None,
                 max_speed_rad_s: float = 7.0, time_constant_s: float = 0.02, current_per_rad: float = 400.0,
                 h_inf_firmware: bool = False):
        self.bus = can.Bus(interface=interface, channel=channel)
        self.positions = np.zeros(16) if initial_rad is None else np.asarray(initial_rad, dtype=np.float64).copy()
        self.targets = self.positions.copy()
        self.currents = np.zeros(16)
        self.servo_on = False
        self.status_faults = 0
        self.max_speed, self.tau, self.current_per_rad = max_speed_rad_s, time_constant_s, current_per_rad
        self.period_s = 0.0
        self.pose_message_id = proto.ID_CMD_SET_TORQUE if h_inf_firmware else proto.ID_CMD_SET_POSE
        self.received: list[int] = []  # message ids, for tests
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._last = time.monotonic()
        self._threads = [threading.Thread(target=self._receive, daemon=True, name="allegro-rx"),
                         threading.Thread(target=self._report, daemon=True, name="allegro-tx")]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self.bus.shutdown()

    def __enter__(self) -> SimAllegroHand:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def fault(self, status_bits: int = proto.STATUS_OVER_TEMPERATURE) -> None:
        """Simulate a fault: servos switch off and HAND_INFO reports the fault bits."""
        with self._lock:
            self.status_faults = status_bits
            self.servo_on = False

    def clear_fault(self) -> None:
        """The cause is gone (e.g. the motors cooled down): HAND_INFO stops reporting it."""
        with self._lock:
            self.status_faults = 0

    def _receive(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.05)
            if msg is None or msg.is_error_frame:
                continue
            with self._lock:
                self._handle(msg)

    def _handle(self, msg: can.Message) -> None:
        mid = proto.message_id(msg.arbitration_id)
        self.received.append(mid)
        if mid == proto.ID_RTR_HAND_INFO and msg.is_remote_frame:
            status = (proto.STATUS_SERVO_ON if self.servo_on else 0) | self.status_faults
            self._send(proto.ID_RTR_HAND_INFO, proto.encode_hand_info(0x0500, 0x0500, True, 35, status))
        elif mid == proto.ID_CMD_SYSTEM_ON:
            self._integrate()
            self.servo_on = not self.status_faults
        elif mid == proto.ID_CMD_SYSTEM_OFF:
            self._integrate()
            self.servo_on = False
        elif mid == proto.ID_CMD_SET_PERIOD:
            position_ms = int.from_bytes(bytes(msg.data[:2]), "little", signed=True)
            self.period_s = position_ms / 1000.0
        elif self.pose_message_id <= mid < self.pose_message_id + proto.FINGERS:
            finger = mid - self.pose_message_id
            self._integrate()
            self.targets[4 * finger:4 * finger + 4] = proto.decode_joints(msg.data)

    def _integrate(self) -> None:
        now = time.monotonic()
        dt, self._last = now - self._last, now
        if not self.servo_on:
            self.currents[:] = 0.0
            return
        error = self.targets - self.positions
        speed = np.clip(error / self.tau, -self.max_speed, self.max_speed)
        step = speed * dt
        self.positions = np.where(np.abs(step) >= np.abs(error), self.targets, self.positions + step)
        self.currents = self.current_per_rad * (self.targets - self.positions)

    def _report(self) -> None:
        while not self._stop.is_set():
            period = self.period_s
            if period <= 0:
                time.sleep(0.01)
                continue
            with self._lock:
                self._integrate()
                for finger in range(proto.FINGERS):
                    joints = slice(4 * finger, 4 * finger + 4)
                    self._send(proto.ID_RTR_FINGER_POSE + finger, proto.encode_joints(self.positions[joints]))
                    counts = np.clip(np.round(self.currents[joints]), -32768, 32767).astype(int)
                    self._send(proto.ID_RTR_FINGER_CURRENT + finger, np.asarray(counts, dtype="<i2").tobytes())
            time.sleep(period)

    def _send(self, message_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=proto.wire_id(message_id), data=data, is_extended_id=False))
