"""The xArm7's protocol fake: a controller at the xarm-python-sdk transport boundary (there is no xArm simulator).

`fake_xarm_api(controller)` builds a real `XArmAPI(ip, do_not_open=True)` and replaces its transport:
the link (`_stream`, reporting connected) and the command layer (`arm_cmd`, the SDK's UxbusCmd that
would serialise each call onto TCP port 502) by `FakeXArmController`. Everything above that boundary
— argument handling, radian/degree conversion, return-code checks, the ready/connected decorators —
is the SDK's own code. The controller records every command and models the controller's state
machine (motion enable, mode, state 0 ready / 4 stopped, error codes) and a first-order joint response
to servo-mode (`set_servo_angle_j`) targets.

Return conventions follow the SDK's UxbusCmd: a list whose first item is the code (0 = ok), e.g.
`get_joint_states(num=3)` -> [0, q1..q7, dq1..dq7, tau1..tau7] in radians.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

ERR_CONTROLLER = 1  # code returned by a command the controller rejects while it has an error


class _ConnectedStream:
    """Stands in for the SDK's SocketPort: only `connected` and `close()` are used above the boundary."""

    def __init__(self) -> None:
        self.connected = True

    def close(self) -> None:
        self.connected = False


class FakeXArmController:
    """Records commands; tracks servo targets with a first-order response while enabled, mode 1, state 0."""

    def __init__(self, initial_rad: Sequence[float] = (0.0, -0.4, 0.0, 0.9, 0.0, 1.3, 0.0),
                 time_constant_s: float = 0.02, max_speed_rad_s: float = 3.14, torque_per_rad: float = 20.0) -> None:
        self.positions = np.asarray(initial_rad, dtype=np.float64).copy()
        self.targets = self.positions.copy()
        self.velocities = np.zeros(7)
        self.torques = np.zeros(7)
        self.external_torques = np.zeros(7)  # tests: a contact loading the joints (Nm), added to the reports
        self.tau, self.max_speed, self.torque_per_rad = time_constant_s, max_speed_rad_s, torque_per_rad
        self.enabled = False
        self.mode = 0
        self.state = 4  # stopped until set_state(0)
        self.error_code = 0
        self.warn_code = 0
        self.commands: list[tuple[Any, ...]] = []
        self._lock = threading.Lock()
        self._last = time.monotonic()
        self.state_is_ready = True  # read by XArmAPI._check_code for motion commands
        self.version = "7,7,XI1300000000,AC1300000000,v2.5.5"  # axis, type, robot SN, control box SN, firmware
        self._sdk_arm: Any = None  # the SDK's XArm (untyped)

    def attach(self, sdk_arm: Any) -> None:
        """Mirror mode/state/error codes into the SDK object, as the controller's report socket does."""
        self._sdk_arm = sdk_arm
        self._report()

    def _report(self) -> None:
        if self._sdk_arm is not None:
            self._sdk_arm._mode, self._sdk_arm._state = self.mode, self.state
            self._sdk_arm._error_code, self._sdk_arm._warn_code = self.error_code, self.warn_code

    # ---- fault injection (tests)
    def fault(self, error_code: int = 22) -> None:
        """Controller error (22: self-collision in the xArm error table): motion stops, state 4."""
        with self._lock:
            self._integrate()
            self.error_code, self.state = error_code, 4
            self.targets = self.positions.copy()
            self._report()

    # ---- the UxbusCmd methods the SDK calls
    def set_debug(self, debug: bool) -> None:
        pass

    def get_version(self) -> list[int]:
        return [0, *self.version.encode(), 0]

    def motion_en(self, axis_id: int, enable: int) -> list[int]:
        with self._lock:
            self.commands.append(("motion_en", axis_id, enable))
            self.enabled = bool(enable)
            self._report()
            return [0]

    def set_mode(self, mode: int, detection_param: int = -1) -> list[int]:
        with self._lock:
            self.commands.append(("set_mode", mode))
            self.mode = mode
            self._report()
            return [0]

    def set_state(self, value: int) -> list[int]:
        with self._lock:
            self.commands.append(("set_state", value))
            self._integrate()
            if value == 0 and (self.error_code or not self.enabled):
                return [ERR_CONTROLLER]
            if value == 4:
                self.targets = self.positions.copy()
            self.state = value
            self._report()
            return [0]

    def get_state(self) -> list[int]:
        with self._lock:
            return [0, self.state]

    def get_err_code(self) -> list[int]:
        with self._lock:
            return [0, self.error_code, self.warn_code]

    def clean_err(self) -> list[int]:
        with self._lock:
            self.commands.append(("clean_err",))
            self.error_code = 0
            self._report()
            return [0]

    def clean_war(self) -> list[int]:
        with self._lock:
            self.commands.append(("clean_war",))
            self.warn_code = 0
            return [0]

    def move_servoj(self, mvjoint: Sequence[float], mvvelo: float, mvacc: float, mvtime: float) -> list[int]:
        with self._lock:
            self.commands.append(("move_servoj", tuple(mvjoint)))
            self._integrate()
            if self.error_code or self.state != 0 or self.mode != 1 or not self.enabled:
                return [ERR_CONTROLLER]
            self.targets = np.asarray(mvjoint[:7], dtype=np.float64)
            return [0]

    def get_joint_pos(self) -> list[float]:
        with self._lock:
            self._integrate()
            return [0, *self.positions.tolist()]

    def get_joint_states(self, num: int = 3) -> list[float]:
        with self._lock:
            self._integrate()
            return [0, *self.positions.tolist(), *self.velocities.tolist(), *self.torques.tolist()]

    def _integrate(self) -> None:
        now = time.monotonic()
        dt, self._last = now - self._last, now
        moving = self.enabled and self.state == 0 and not self.error_code
        error = self.targets - self.positions if moving else np.zeros(7)
        speed = np.clip(error / self.tau, -self.max_speed, self.max_speed)
        step = speed * dt
        self.positions = np.where(np.abs(step) >= np.abs(error), self.positions + error, self.positions + step)
        self.velocities = np.where(np.abs(step) >= np.abs(error), 0.0, speed)
        self.torques = self.torque_per_rad * error + self.external_torques


def fake_xarm_api(controller: FakeXArmController, ip: str = "192.168.1.201") -> Any:
    """A real XArmAPI whose transport is `controller` (see the module docstring)."""
    from xarm.wrapper import XArmAPI

    api = XArmAPI(ip, is_radian=True, do_not_open=True)
    arm = api._arm  # the SDK's XArm instance behind the API facade
    arm._stream = _ConnectedStream()
    arm.arm_cmd = controller
    controller.attach(arm)
    return api
