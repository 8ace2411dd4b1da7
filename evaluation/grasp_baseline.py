"""The grasp-pose baseline's pose source: the project's optimiser with grasp terms only.

The paper's baseline is a pre-trained grasp model (Lum et al.) run on the test objects; its poses
are not conditioned on the push direction. Here the stand-in is the generator with `grasp_only`
(no E_dir, no E_arm; initialised all around the object, not behind it): the same optimiser,
none of the push-specific terms. Poses are optimised once per (object, hand) with the object in
its default placement, cached in the output directory, and moved with the object into each
request's direction frame — grasp poses belong to the object, not to the direction.

As the paper executes "the best actions from [the grasp model's] output", the source offers the
`offered` lowest-energy poses of the `generated` ones; the pipeline then executes a feasible one of
them (no rollout ranking).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.atomic import atomic_writer
from shared.contracts.messages import SampleRequest, SampleResponse
from shared.frames import direction_frame, direction_xy, invert_transform, poses_d_to_world, transform_poses
from shared.synthesis.config import GenerationConfig
from shared.synthesis.synthesis import generate
from shared.world.objects import load_object
from shared.world.push_outcome import pose_matrix

GENERATED = 64
OFFERED = 16
SEED = 0


class GraspPoseSource:
    """A PoseSource serving cached grasp-only poses of library objects."""

    def __init__(self, cache_dir: str | Path, generated: int = GENERATED, offered: int = OFFERED):
        self.cache_dir = Path(cache_dir)
        self.generated, self.offered = generated, offered
        self._memory: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}

    def poses_in_default_d(self, object_id: str, hand: str) -> tuple[np.ndarray, np.ndarray]:
        """([offered, 25] lowest-energy grasp poses in the default placement's D, T_D_O of that placement)."""
        key = (object_id, hand)
        if key not in self._memory:
            path = self.cache_dir / hand / f"{object_id}_{self.generated}.npz"
            if not path.exists():
                output = generate(load_object(object_id), hand, self.generated, SEED, GenerationConfig(grasp_only=True))
                best = np.argsort(output.energies["total"], kind="stable")[: self.offered]
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_writer(path) as f:
                    np.savez(f, poses=output.poses[best], T_D_O=output.object_transform_d)
            with np.load(path) as data:
                self._memory[key] = (data["poses"], data["T_D_O"])
        return self._memory[key]

    def __call__(self, request: SampleRequest) -> SampleResponse:
        if request.object.library_id is None:
            raise ValueError("the grasp baseline serves library objects only")
        poses, T_D0_O = self.poses_in_default_d(request.object.library_id, request.hand)
        frame = request.frame
        T_world_O = pose_matrix(frame.object_pose)
        T_world_D = direction_frame(T_world_O[:3, 3], direction_xy(np.degrees(frame.yaw_rad())))
        T_D_O = invert_transform(T_world_D) @ T_world_O
        poses_d = transform_poses(poses, T_D_O @ invert_transform(T_D0_O))  # the hand moves with the object
        return SampleResponse(request_id=request.id, hand=request.hand, poses_d=poses_d,
                              poses_world=poses_d_to_world(poses_d, T_world_D), latency_s=0.0,
                              checkpoint_id=f"grasp-only-optimiser:{self.generated}:{self.offered}")
