"""Push-pose synthesis: `generate(object, hand, n, seed, config)` (paper §"Dataset Generation").

Poses are optimised in batches of `config.batch_size`; batch c of a run draws all its randomness
from a `torch.Generator` seeded by (seed, c), so a seed fixes the result, and the first batches of
a larger run equal a smaller run with the same seed. Set `torch.set_num_threads(1)` in worker
processes (docs/architecture.md §Compute); results are bitwise reproducible for a given thread count.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from shared.frames import matrix_to_r6, r6_to_matrix
from shared.robots.hands import HandModel, load_hand
from shared.synthesis.config import TERMS, GenerationConfig
from shared.synthesis.energy import EnergyTerms, HandGeometry, evaluate_energy, max_penetration
from shared.synthesis.init import initial_poses, sample_contacts
from shared.synthesis.optimizer import AnnealingOptimizer
from shared.synthesis.scene import PushScene
from shared.world.objects import ObjectModel

ProgressCallback = Callable[[int], None]  # called with the number of iterations just finished
TOTAL = "total"


class GenerationError(RuntimeError):
    """A generation request that cannot run (bad n, unknown hand, unusable object)."""


@dataclass
class GenerationOutput:
    """Optimised poses in D and what is known about each of them."""

    object_id: str
    hand: str
    poses: np.ndarray  # [n,25] in D, r6 orthonormal
    energies: dict[str, np.ndarray]  # unweighted term [n] by short name, plus "total" (weighted sum)
    palm_normals: np.ndarray  # [n,3] in D
    max_penetration_m: np.ndarray  # [n] deepest hand-object interpenetration, both ways
    object_transform_d: np.ndarray  # 4x4 T_D_O the poses were optimised against
    contacts: np.ndarray  # [n,K] selected candidate indices at the end
    contact_distances_m: np.ndarray  # [n,K] signed distance of each selected contact to the object
    contact_offset_m: float  # the pre-contact offset E_dis aimed the contacts at
    history: dict[str, np.ndarray] = field(default_factory=dict)  # [iterations] batch mean per term + "total"
    elapsed_s: float = 0.0

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def good(self, min_palm_x: float = 0.7, max_penetration_m: float = 0.005,
             contact_tolerance_m: float = 0.005) -> np.ndarray:
        """[n] bool: palm faces +x, penetration is small, every contact within tolerance of the offset.

        The quick pre-physics filter of docs/architecture.md §Compute ("face +x, penetrate <= 5 mm, all contacts
        within 5 mm"); the validator decides what really pushes.
        """
        gap = np.abs(self.contact_distances_m - self.contact_offset_m)
        contacts_close = (gap <= contact_tolerance_m).all(1)
        return (self.palm_normals[:, 0] >= min_palm_x) & (self.max_penetration_m <= max_penetration_m) & contacts_close


def generate(scene: PushScene | ObjectModel, hand: HandModel | str, n: int, seed: int,
             config: GenerationConfig | None = None, progress: ProgressCallback | None = None) -> GenerationOutput:
    """Optimise `n` pre-contact push poses (grasp poses if `config.grasp_only`) of `hand` for `scene`.

    An ObjectModel is placed as on the bus: default resting pose, yaw 0 (`PushScene.from_object`).
    """
    config = config or GenerationConfig()
    if n < 1:
        raise GenerationError(f"n must be >= 1, got {n}")
    if isinstance(scene, ObjectModel):
        scene = PushScene.from_object(scene, surface_points=config.object_points,
                                      check_points=config.penetration_check_points)
    hand_model = load_hand(hand) if isinstance(hand, str) else hand
    geometry = hand_geometry(hand_model)
    started = time.perf_counter()
    batches = [_optimise_batch(hand_model, geometry, scene, size, batch_generator(seed, index), config, progress)
               for index, size in enumerate(_batch_sizes(n, config.batch_size))]
    output = _concatenate(batches, scene, hand_model, config)
    output.elapsed_s = time.perf_counter() - started
    return output


def batch_generator(seed: int, batch_index: int) -> torch.Generator:
    """The generator of batch `batch_index` of a run seeded with `seed` (independent streams)."""
    state = np.random.SeedSequence([seed, batch_index]).generate_state(1, dtype=np.uint64)[0]
    return torch.Generator().manual_seed(int(state) & 0x7FFF_FFFF_FFFF_FFFF)


_GEOMETRY_CACHE: dict[str, HandGeometry] = {}


def hand_geometry(hand: HandModel) -> HandGeometry:
    """The hand's `HandGeometry`, built once per process."""
    if hand.name not in _GEOMETRY_CACHE:
        _GEOMETRY_CACHE[hand.name] = HandGeometry(hand)
    return _GEOMETRY_CACHE[hand.name]


# --------------------------------------------------------------------------------- one batch


@dataclass
class _BatchResult:
    poses: torch.Tensor
    terms: dict[str, torch.Tensor]
    total: torch.Tensor
    contacts: torch.Tensor
    history: torch.Tensor  # [iterations, len(TERMS) + 1]


def _optimise_batch(hand: HandModel, geometry: HandGeometry, scene: PushScene, size: int,
                    generator: torch.Generator, config: GenerationConfig,
                    progress: ProgressCallback | None) -> _BatchResult:
    pose = initial_poses(hand, scene.hull_vertices, size, config.init, generator, push=not config.grasp_only)
    contacts = sample_contacts(len(hand.contact_candidates), size, config.contacts_per_pose, generator)
    optimizer = AnnealingOptimizer(config.annealing, len(hand.contact_candidates), generator)
    energy, gradient = _energy_and_gradient(hand, geometry, scene, pose, contacts, config)
    history = torch.zeros(config.iterations if config.record_history else 0, len(TERMS) + 1)
    for iteration in range(config.iterations):
        proposal = optimizer.propose(pose, gradient, contacts)
        new_energy, new_gradient = _energy_and_gradient(hand, geometry, scene, proposal.pose, proposal.contacts, config)
        accept = optimizer.accept(energy.total, new_energy.total)
        pose = torch.where(accept[:, None], proposal.pose, pose)
        gradient = torch.where(accept[:, None], new_gradient, gradient)
        contacts = torch.where(accept[:, None], proposal.contacts, contacts)
        energy = _select(accept, new_energy, energy)
        if config.record_history:
            history[iteration] = _batch_means(energy)
        if progress is not None:
            progress(1)
    pose = finalise_poses(hand, pose)
    with torch.no_grad():
        energy = evaluate_energy(hand, geometry, scene, pose, contacts, config)
    return _BatchResult(pose, energy.terms, energy.total, contacts, history)


def finalise_poses(hand: HandModel, pose: torch.Tensor) -> torch.Tensor:
    """Clean optimiser output: r6 made orthonormal, joints clamped to their limits.

    E_j (weight 1, as in the paper) leaves violations of a few degrees; a simulator or a real hand
    stops at the limit anyway, so the returned pose (and the energies reported for it) use the limit.
    """
    rotation = r6_to_matrix(pose[:, 3:9])
    joints = pose[:, 9:].clamp(hand.joint_lower, hand.joint_upper)
    return torch.cat((pose[:, :3], matrix_to_r6(rotation), joints), dim=1).detach()


def _energy_and_gradient(hand: HandModel, geometry: HandGeometry, scene: PushScene, pose: torch.Tensor,
                         contacts: torch.Tensor, config: GenerationConfig) -> tuple[EnergyTerms, torch.Tensor]:
    pose = pose.detach().requires_grad_(True)
    energy = evaluate_energy(hand, geometry, scene, pose, contacts, config)
    (gradient,) = torch.autograd.grad(energy.total.sum(), pose)
    detached = EnergyTerms({k: v.detach() for k, v in energy.terms.items()}, energy.total.detach())
    return detached, gradient


def _select(accept: torch.Tensor, new: EnergyTerms, old: EnergyTerms) -> EnergyTerms:
    terms = {k: torch.where(accept, new.terms[k], old.terms[k]) for k in old.terms}
    return EnergyTerms(terms, torch.where(accept, new.total, old.total))


def _batch_means(energy: EnergyTerms) -> torch.Tensor:
    return torch.stack([energy.terms[k] for k in TERMS] + [energy.total]).mean(1)


def _batch_sizes(n: int, batch_size: int) -> list[int]:
    full, rest = divmod(n, batch_size)
    return [batch_size] * full + ([rest] if rest else [])


# ----------------------------------------------------------------------------------- results


def _concatenate(batches: list[_BatchResult], scene: PushScene, hand: HandModel,
                 config: GenerationConfig) -> GenerationOutput:
    poses = torch.cat([b.poses for b in batches])
    rotation = r6_to_matrix(poses[:, 3:9])
    energies = {k: torch.cat([b.terms[k] for b in batches]).numpy() for k in TERMS}
    energies[TOTAL] = torch.cat([b.total for b in batches]).numpy()
    palm = rotation @ hand.palm_normal_base
    penetration = max_penetration(hand, hand_geometry(hand), scene, poses, scene.check_points)
    contacts = torch.cat([b.contacts for b in batches])
    with torch.no_grad():
        contact_points, _ = hand.contact_points(hand.forward(poses), contacts)
        contact_distances = scene.distance(contact_points)[0]
    return GenerationOutput(
        object_id=scene.object_id,
        hand=hand.name,
        poses=poses.numpy().astype(np.float64),
        energies={k: v.astype(np.float64) for k, v in energies.items()},
        palm_normals=palm.numpy().astype(np.float64),
        max_penetration_m=penetration.numpy().astype(np.float64),
        object_transform_d=scene.transform_d.copy(),
        contacts=contacts.numpy(),
        contact_distances_m=contact_distances.numpy().astype(np.float64),
        contact_offset_m=config.contact_offset_m,
        history=_merge_history(batches),
    )


def _merge_history(batches: list[_BatchResult]) -> dict[str, np.ndarray]:
    """Batch-mean curves averaged over batches, weighted by batch size."""
    if batches[0].history.shape[0] == 0:
        return {}
    sizes = torch.tensor([float(b.poses.shape[0]) for b in batches])
    stacked = torch.stack([b.history for b in batches])  # [batches, iterations, terms + 1]
    merged = (stacked * sizes[:, None, None]).sum(0) / sizes.sum()
    names = list(TERMS) + [TOTAL]
    return {name: merged[:, i].numpy().astype(np.float64) for i, name in enumerate(names)}
