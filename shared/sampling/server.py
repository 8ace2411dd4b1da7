"""Bus adapter of the sampler service: a SampleRequest in, a SampleResponse (K poses in D and world) out.

One `PoseSampler` per hand, loaded on the first request for that hand from its checkpoint
(`checkpoint.default_checkpoint_path`, or the paths given to `handlers`). Run the worker with a
concurrency above one (see `__main__`): concurrent requests then wait together in the sampler's
batching thread and share network passes.

`sampler="nearest"` is the paper's Nearest-Neighbour baseline: one index per hand
(`nearest_neighbor.default_nn_index_path`: the shipped `checkpoints/<hand>_nn.npz`, or the paths
given to `handlers`), loaded on first use; the reply holds the stored poses of the training frame
nearest to the object in BPS space, and its `checkpoint_id` names the index file and that object.

Objects: a library id (loaded as an id, never as a path), a mesh (cached by its hash once it
loaded, as the validator does: shared/world/object_refs.py) or a point cloud in the world frame. Scaled objects are refused, as by the validator: a pose
sampled for a scaled object could not be validated or executed on the same geometry.
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from shared.contracts.errors import ServiceError
from shared.contracts.messages import Message, ObjectRef, SampleRequest, SampleResponse
from shared.sampling.checkpoint import CheckpointError, default_checkpoint_path
from shared.sampling.critic import SuccessCritic
from shared.sampling.critic_train import (
    CriticError,
    default_critic_path,
    load_critic,
    success_probabilities,
    success_probabilities_for,
)
from shared.sampling.diffusion import GradientGuidance
from shared.sampling.nearest_neighbor import NearestNeighborError, NearestNeighborSampler, default_nn_index_path
from shared.sampling.sampling import ObjectInput, PoseSampler, SamplerInputError
from shared.world.object_refs import captured_object, load_uploaded_mesh
from shared.world.objects import ObjectLoadError
from shared.world.objects.model import load_library_object

SERVICE = "sampler"
# A request's deadline (Worker job_budget): its samples times the cost of their denoising steps and guided steps,
# with a margin. Measured: DDPM-100 draws 200 samples in about 0.3 s (bench/push.py), about 15 us a sample a
# step; a guided step costs about 0.2 s per 200 poses on one thread (shared/sampling/guidance.py).
SECONDS_PER_SAMPLE_STEP = 15e-6
SECONDS_PER_GUIDED_SAMPLE_STEP = 1e-3
DEFAULT_STEPS = 100  # DDPM-100, the most a request without `steps` runs
BUDGET_MARGIN = 4.0
BUDGET_BASE_S = 30.0  # loading a checkpoint, its critic or an index on first use
log = logging.getLogger("gd2p.sampler")


class SamplerService:
    """Serves SampleRequests for every hand it has (or can find) a checkpoint / NN index for."""

    def __init__(self, checkpoints: Mapping[str, str | Path] | None = None, device: str = "cpu",
                 nn_indexes: Mapping[str, str | Path] | None = None):
        self._paths = {hand: Path(path) for hand, path in (checkpoints or {}).items()}
        self._nn_paths = {hand: Path(path) for hand, path in (nn_indexes or {}).items()}
        self._device = device
        self._samplers: dict[str, PoseSampler] = {}
        self._nearest: dict[str, NearestNeighborSampler] = {}
        self._critics: dict[str, SuccessCritic | None] = {}
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            samplers, self._samplers = list(self._samplers.values()), {}
        for sampler in samplers:
            sampler.close()

    def sampler(self, hand: str) -> PoseSampler:
        """The loaded sampler for `hand`; ServiceError 'not_implemented' when this worker has no usable checkpoint.

        Not 'unavailable': the dispatcher reads that as "worker shutting down" and re-dispatches forever.
        """
        with self._lock:
            if hand not in self._samplers:
                path = self._paths.get(hand) or default_checkpoint_path(hand)
                try:
                    sampler = PoseSampler(path, device=self._device)
                except CheckpointError as exc:
                    raise ServiceError("not_implemented", f"sampler: no usable {hand} checkpoint: {exc} "
                                       f"(train one with `gd2p train --hand {hand} --out {path}`)") from exc
                if sampler.hand != hand:
                    raise ServiceError("not_implemented", f"sampler: {path} is a {sampler.hand} checkpoint, not {hand}")
                self._samplers[hand] = sampler
            return self._samplers[hand]

    def nearest(self, hand: str) -> NearestNeighborSampler:
        """The loaded NN index for `hand`; ServiceError 'not_implemented' (see `sampler`) when there is none."""
        with self._lock:
            if hand not in self._nearest:
                path = self._nn_paths.get(hand) or default_nn_index_path(hand)
                try:
                    nearest = NearestNeighborSampler.load(path)
                except NearestNeighborError as exc:
                    raise ServiceError("not_implemented", f"sampler: no usable {hand} nearest-neighbour index: {exc} "
                                       f"(build one with `gd2p sampler-nn build --dataset DIR --hand {hand} --out {path}`)") from exc
                if nearest.hand != hand:
                    raise ServiceError("not_implemented", f"sampler: {path} is a {nearest.hand} nearest-neighbour index, not {hand}")
                self._nearest[hand] = nearest
            return self._nearest[hand]

    def critic(self, hand: str, sampler: PoseSampler) -> SuccessCritic | None:
        """`hand`'s success critic, when one is installed and was trained with `sampler`'s BPS basis (else None:
        the samples go out unscored, with a warning in the log for a critic of another checkpoint)."""
        with self._lock:
            if hand not in self._critics:
                self._critics[hand] = _load_critic(hand, sampler)
            return self._critics[hand]

    def handle(self, request: SampleRequest) -> SampleResponse:
        """Sample `request.k` poses for `request.object` in `request.frame` (scored by the critic, if any)."""
        if request.sampler == "nearest":
            return self._handle_nearest(request)
        sampler = self.sampler(request.hand)
        guide_critic, guidance = self._guidance(request, sampler)
        try:
            result = sampler.sample(object_input(request.object), request.frame, k=request.k, sampler=request.sampler,
                                    steps=request.steps, seed=request.seed, noise_scale=request.noise_scale,
                                    critic=guide_critic, guidance=guidance)
        except SamplerInputError as exc:
            raise ServiceError("bad_request", f"sampler: object {request.object.object_id}: {exc}") from exc
        critic = self.critic(request.hand, sampler) if request.score else None
        scores = (None if critic is None or result.bps is None or result.points_d is None
                  else success_probabilities(critic, request.hand, result.bps, result.points_d, result.poses_d))
        return SampleResponse(
            request_id=request.id, hand=request.hand, poses_d=result.poses_d,
            poses_world=result.poses_world, latency_s=result.latency_s,
            checkpoint_id=sampler.checkpoint_id, sampler=request.sampler, noise_scale=result.noise_scale,
            success_probability=scores)

    def _guidance(self, request: SampleRequest, sampler: PoseSampler) -> tuple[SuccessCritic | None, GradientGuidance | None]:
        """The critic and settings that steer the request's samples (`critic_guidance`), or (None, None)."""
        if request.critic_guidance is None:
            return None, None
        critic = self.critic(request.hand, sampler)
        if critic is None:
            raise ServiceError("not_implemented", f"sampler: critic guidance needs a {request.hand} success critic made for "
                                                  f"the checkpoint {sampler.checkpoint_id}; none is installed")
        return critic, GradientGuidance(request.critic_guidance, steps=request.guided_steps)

    def _handle_nearest(self, request: SampleRequest) -> SampleResponse:
        """The nearest training frame's poses: `request.k` of them, seeded, or all when it has fewer."""
        if request.steps is not None or request.noise_scale is not None or request.critic_guidance is not None:
            raise ServiceError("bad_request", "sampler: `steps`, `noise_scale` and `critic_guidance` apply to the diffusion "
                                              "samplers, not 'nearest'")
        nearest = self.nearest(request.hand)
        try:
            reply = nearest.sample(object_input(request.object), request.frame, k=request.k, seed=request.seed)
        except SamplerInputError as exc:
            raise ServiceError("bad_request", f"sampler: object {request.object.object_id}: {exc}") from exc
        return SampleResponse(
            request_id=request.id, hand=request.hand, poses_d=reply.result.poses_d,
            poses_world=reply.result.poses_world, latency_s=reply.result.latency_s,
            checkpoint_id=reply.source_id, sampler="nearest",
            success_probability=self._score_retrieved(request, reply.result.poses_d) if request.score else None)

    def _score_retrieved(self, request: SampleRequest, poses_d: np.ndarray) -> np.ndarray | None:
        """The critic's P(success) of retrieved poses, from the object as the diffusion sampler encodes it (the
        encoding the critic was trained on), so a planner orders retrieval's candidates as it orders the model's:
        the same pipeline stages for the baseline. None (retrieval's poses go out unscored, in their own order) when
        the hand has no checkpoint or no critic for it, or the object cannot be encoded as the critic reads it."""
        try:
            sampler = self.sampler(request.hand)
        except ServiceError:
            return None  # no diffusion checkpoint: no critic either
        critic = self.critic(request.hand, sampler)
        if critic is None:
            return None
        try:
            return success_probabilities_for(critic, request.hand, sampler, object_input(request.object), request.frame,
                                             poses_d)
        except SamplerInputError as exc:  # the match itself is good: keep it, without the critic's order
            log.warning("sampler: retrieved poses left unscored: %s", exc)
            return None


def _load_critic(hand: str, sampler: PoseSampler) -> SuccessCritic | None:
    path = default_critic_path(hand)
    if path is None or not path.is_file():
        return None
    try:
        loaded = load_critic(path)
    except CriticError as exc:
        log.warning("sampler: ignoring the %s critic: %s", hand, exc)
        return None
    if loaded.hand != hand or loaded.sampler_checkpoint_id != sampler.checkpoint_id:
        log.warning("sampler: ignoring the critic %s: trained for the %s checkpoint %s, the sampler has %s %s",
                    path, loaded.hand, loaded.sampler_checkpoint_id, hand, sampler.checkpoint_id)
        return None
    return loaded.model


def object_input(ref: ObjectRef) -> ObjectInput:
    """What PoseSampler.sample takes for an ObjectRef: the loaded object, or, for a point cloud, the
    object's own points in the world (table removed, its cluster kept, thinned: `bps_points`), so the
    BPS is computed from the cloud itself as in the paper.

    SamplerInputError for an unknown id, a mesh that does not load or a cloud with no object in it."""
    if ref.scale is not None and ref.scale != 1.0:
        raise ServiceError("bad_request", f"object {ref.object_id}: scaled objects are not supported by the sampler")
    try:
        if ref.library_id is not None:
            return load_library_object(ref.library_id)
        if ref.mesh is not None:
            return load_uploaded_mesh(ref.mesh)
    except ObjectLoadError as exc:
        raise SamplerInputError(str(exc)) from exc
    assert ref.point_cloud is not None
    from shared.world.perception.object_model import bps_points

    try:
        captured = captured_object(ref)
    except ObjectLoadError as exc:
        raise SamplerInputError(str(exc)) from exc
    return bps_points(captured.object_points)


def job_budget(job: Message) -> float:
    """Seconds a SampleRequest may take: its samples' denoising and guided steps, with a margin."""
    if not isinstance(job, SampleRequest):
        return BUDGET_BASE_S
    guided = job.guided_steps if job.critic_guidance is not None else 0
    per_sample = (job.steps or DEFAULT_STEPS) * SECONDS_PER_SAMPLE_STEP + guided * SECONDS_PER_GUIDED_SAMPLE_STEP
    return BUDGET_BASE_S + BUDGET_MARGIN * job.k * per_sample


def handlers(checkpoints: Mapping[str, str | Path] | None = None,
             nn_indexes: Mapping[str, str | Path] | None = None,
             ) -> dict[type[Message], Callable[[Any], Message]]:  # each handler takes its key's type
    """Message type -> handler, served by every sampler worker."""
    return {SampleRequest: SamplerService(checkpoints, nn_indexes=nn_indexes).handle}
