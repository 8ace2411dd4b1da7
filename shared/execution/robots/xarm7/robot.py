"""The arm `xarm7`: a UFactory xArm7 over xarm-python-sdk, streaming joint targets in servo mode (mode 1, `set_servo_angle_j`).

Connect: XArmAPI(ip, is_radian=True) -> connect -> refuse if the controller reports an error code ->
clean warnings -> motion enable -> mode 1 (servo) -> state 0 (ready).
Motion: `set_servo_angle_j` of the interpolated trajectory each command period (the controller's own
servo loop follows). State: `get_joint_states(num=3)` -> positions (rad), velocities (rad/s),
efforts (Nm), monitored against the effort limits. Stop: state 4 (the controller decelerates and
holds). Recover: clean error and warning, motion enable, mode 1, state 0.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from shared.execution.robot import DeviceRefused, DeviceUnavailable, Observation, StreamingRobot
from shared.execution.robots.xarm7.config import XArm7Config, limits

SERVO_MODE, STATE_READY, STATE_STOP = 1, 0, 4
# Return codes that mean the link failed, not that the controller refused (xarm.x3.code.APIState):
# NOT_CONNECTED -1, reply timeout 3, reply length/number/protocol/function mismatch 4-7, send error 8.
# Every other non-zero code (an uncleared error 1, not ready -2/9, joint limit -7, e-stop -9, ...) is a refusal.
LINK_ERROR_CODES = frozenset({-1, 3, 4, 5, 6, 7, 8})


def _default_api(ip: str) -> Any:
    try:
        from xarm.wrapper import XArmAPI
    except ImportError:
        raise DeviceUnavailable("xArm: xarm-python-sdk is not installed (pip install 'gd2p-zenoh[xarm]')") from None
    return XArmAPI(ip, is_radian=True, do_not_open=True)


class XArm7Robot(StreamingRobot):
    """The xArm7 controller of `config`. `api_factory(ip)` returns an unopened XArmAPI (tests pass a fake,
    robots/xarm7/fake.py)."""

    name = "xarm7"
    reports_effort = True

    def __init__(self, config: XArm7Config, *, api_factory: Callable[[str], Any] = _default_api):
        device_limits = limits()
        super().__init__(device_limits.joint_names, device_limits, config.command_rate_hz,
                         config.settle_tolerance_rad, config.settle_timeout_s)
        self.config = config
        self.ip = config.ip
        self._api_factory = api_factory
        self._api: Any = None
        self._io = threading.Lock()
        # effort_cap stays None: the controller enforces its own torque limits; measured torques are monitored

    @property
    def connected(self) -> bool:
        return self._api is not None and bool(self._api.connected)

    def connect(self) -> None:
        if self.connected:
            return
        api = self._api_factory(self.ip)
        try:
            api.connect()
        except Exception as exc:  # the SDK raises bare Exception('connect socket failed')
            raise DeviceUnavailable(f"xArm at {self.ip}: cannot connect: {exc}") from None
        if not api.connected:
            raise DeviceUnavailable(f"xArm at {self.ip}: not reachable")
        self._api = api
        try:
            self._check_no_error()
            self._enable()
        except Exception:
            self._api.disconnect()
            self._api = None
            raise

    def _call(self, what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        with self._io:
            result = fn(*args, **kwargs)
        code = result[0] if isinstance(result, (tuple, list)) else result
        if code != 0:
            if code in LINK_ERROR_CODES:
                raise DeviceUnavailable(f"xArm at {self.ip}: {what} failed with code {code} (link to the controller)")
            raise DeviceRefused(f"xArm at {self.ip}: {what} refused with code {code}; "
                                f"controller error/warn {self._api.error_code}/{self._api.warn_code}")
        return result

    def _check_no_error(self) -> None:
        _, (error, warn) = self._call("get_err_warn_code", self._api.get_err_warn_code)
        if error:
            raise DeviceRefused(f"xArm at {self.ip}: controller error {error} (see the xArm error table); "
                                f"clear the cause, then recover()")

    def _enable(self) -> None:
        self._call("clean_warn", self._api.clean_warn)
        self._call("motion_enable", self._api.motion_enable, enable=True)
        self._call("set_mode", self._api.set_mode, SERVO_MODE)
        self._call("set_state", self._api.set_state, STATE_READY)

    def disconnect(self) -> None:
        if self._api is None:
            return
        try:
            with self._io:
                self._api.set_state(STATE_STOP)
        finally:
            with self._io:
                self._api.disconnect()
            self._api = None

    def _send_positions(self, q: np.ndarray) -> None:
        self.require_connected()
        self._call("set_servo_angle_j", self._api.set_servo_angle_j, [float(v) for v in q], is_radian=True)

    def _halt(self) -> None:
        with self._io:
            self._api.set_state(STATE_STOP)

    def observe(self) -> Observation:
        self.require_connected()
        _, (positions, velocities, efforts) = self._call("get_joint_states", self._api.get_joint_states,
                                                         is_radian=True, num=3)
        return Observation(time.time(), self.joint_names, np.asarray(positions[:7], dtype=np.float64),
                          np.asarray(velocities[:7], dtype=np.float64), np.asarray(efforts[:7], dtype=np.float64))

    def recover(self) -> None:
        super().recover()
        self.require_connected()
        self._call("clean_error", self._api.clean_error)
        self._enable()
