"""The simulated robot's object tracker: the true pose, seen late and with noise, at a camera-like rate.

A real bridge learns the object's pose from a tracker (an RGB-D pose tracker, markers, motion capture)
publishing on the object-track key (docs/interfaces.md); the simulated robot stands in for one, so that
what the planner sees of the object, during a push and after it, is never the exact truth.

The defaults are a deliberately modest RGB-D tracker, chosen rather than measured: 20 Hz (a 30 Hz depth
camera with a tracker that keeps up on most frames), one frame of latency, noise of σ 2 mm per axis in
position and σ 1° in yaw — the order of the errors of fiducial-marker and model-based RGB-D pose
estimates of a tabletop object at 0.5–1 m. `gd2p eval` runs with them; a user who knows their tracker
sets their own (SimConfig.tracker).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.contracts.messages import ObjectPose
from shared.frames import yaw_rotation
from shared.world.push_outcome import object_pose


@dataclass(frozen=True)
class TrackerConfig:
    rate_hz: float = 20.0  # poses per second of robot time
    position_sigma_m: float = 0.002  # per axis
    yaw_sigma_deg: float = 1.0
    latency_frames: int = 1  # a pose reported at a frame is the one seen this many frames earlier

    def __post_init__(self) -> None:
        if not 0 < self.rate_hz <= 1000:
            raise ValueError(f"tracker rate_hz must be in (0, 1000], got {self.rate_hz}")
        if self.position_sigma_m < 0 or self.yaw_sigma_deg < 0 or self.latency_frames < 0:
            raise ValueError("tracker noise and latency must be non-negative")


class SimTracker:
    """Sees the true object pose at its frames: `frame(T_true)` is the (late, noisy) pose reported then."""

    source = "sim-tracker"

    def __init__(self, config: TrackerConfig = TrackerConfig(), seed: int = 0):
        self.config = config
        self.reset(seed)

    def reset(self, seed: int) -> None:
        """Forget what was seen; draw the noise from `seed` from now on."""
        self._rng = np.random.default_rng(seed)
        self.forget()

    def forget(self) -> None:
        """Forget the frames seen (a new command's first frame reports the pose now, not one from before)."""
        self._seen: list[np.ndarray] = []

    def frame(self, T_true: np.ndarray) -> ObjectPose:
        """One tracker frame now, the object truly at T_true: the pose reported (seen `latency_frames` ago)."""
        self._seen.append(np.array(T_true, dtype=np.float64))
        del self._seen[:-(self.config.latency_frames + 1)]
        return self.noisy(self._seen[0])

    def noisy(self, T: np.ndarray) -> ObjectPose:
        """T as the tracker reports it: translated and turned (about the vertical) by its noise."""
        c = self.config
        seen = np.array(T, dtype=np.float64)
        seen[:3, 3] += self._rng.normal(0.0, c.position_sigma_m, 3)
        seen[:3, :3] = yaw_rotation(math.radians(self._rng.normal(0.0, c.yaw_sigma_deg))) @ seen[:3, :3]
        return object_pose(seen)

    def steps_per_frame(self, time_step_s: float) -> int:
        """Physics steps between two frames."""
        return max(1, round(1.0 / (self.config.rate_hz * time_step_s)))
