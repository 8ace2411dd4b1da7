"""Weights and hyper-parameters of push-pose synthesis (paper Eq. 1 and appendix tables).

Energy weights are the paper's "Weight parameters" table; the optimiser settings are its
"Optimization hyperparameters" table (the same values as DexGraspNet's `Annealing` defaults).
What the paper leaves open was chosen by measurement on this machine (Allegro, B = 64 per object,
one thread; the same runs read out at several iteration counts, every pose pushed 0.20 m in the
validator's PyBullet episode, shared/validation/push.py, with its physics settings of the day):

    validator success at   500   1000  1500  2000  2500 iterations
    proc-box-010           0.80  0.84  0.84  0.83  0.80   (16 x 8 x 9 cm box)
    proc-cylinder-004      0.56  0.66  0.63  0.69  0.64   (13 cm diameter, 7.5 cm tall)
    proc-cylinder-010      0.42  0.44  0.50  0.48  0.45   (7 cm diameter, 7 cm tall)
    proc-box-003           0.42  0.44  0.50  0.47  0.50   (13 x 10 x 3 cm, flat)
    mean                   0.55  0.60  0.62  0.62  0.60
    "good" (pre-physics)   0.07  0.22  0.57  0.80  0.85   (palm x >= 0.7, pen <= 5 mm, contacts within 5 mm)

(This table predates the 3 mm penetration margin below; 64 pushes give about +-0.06 per cell.)

- iterations = 1500: validator success plateaus between 1000 and 1500; the energy curves
  (bench/results/*.png) show orientation and penetration settled by ~1000 while E_dis (contacts
  closing on the surface) keeps falling to ~2000 - the "good" share above. 1500 takes most of
  that (step size then 0.005 * 0.95^30 = 1.1 mm, temperature 18 * 0.95^50 = 1.4) at 75% of
  2000's cost; 2000 buys closed contacts, not more successful pushes.
- init.push_side_min_cos = 0.5: starting only on the back of the object (inward hull normal within
  60 deg of +x) instead of the whole +x half-space (0.0, which includes the top) raised validator
  success on proc-box-010 from 0.36 to 0.84: hands started on top stay on top and slide over.
- contacts_per_pose = 4: docs/architecture.md §Compute's measured setting, as DexGraspNet for Allegro.
- contact_offset_m = 0.005: E_dis pulls contacts 5 mm *outside* the surface so the push starts
  without hand-object penetration; a gap costs its size in final position error (docs/architecture.md §Simulation:
  1 cm of gap = 1 cm of the 3 cm budget), so 5 mm spends a sixth of it.
- penetration_margin_m = 0.003: object points within 3 mm of the hand count in E_pen (get_a_grip
  uses 5 mm). PyBullet's collision margins make it see ~3 mm more penetration than the exact
  primitives do; with the margin the share of episodes starting > 3 mm inside fell from 27/64
  to 8/64 (box) and 25/64 to 6/64 (cylinder) and success went 0.81 -> 0.88 and 0.64 -> 0.66.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

# Every energy term by short name, in the order of Eq. 1 (+ the get_a_grip terms).
TERMS: tuple[str, ...] = ("fc", "dis", "pen", "spen", "joints", "ff", "fp", "tpen", "dir", "arm")
# Terms that only make sense for pushing along +x of D; dropped for the grasp-pose baseline.
PUSH_TERMS: tuple[str, ...] = ("dir", "arm")


class GenerationConfigError(ValueError):
    """A configuration value that cannot work (negative weight, empty range, ...)."""


@dataclass(frozen=True)
class EnergyWeights:
    """w in E = w_fc E_fc + w_dis E_dis + ... (paper appendix, "Weight parameters")."""

    fc: float = 0.5
    dis: float = 500.0
    pen: float = 300.0
    spen: float = 100.0
    joints: float = 1.0
    ff: float = 3.0
    fp: float = 0.0
    tpen: float = 100.0
    dir: float = 200.0
    arm: float = 100.0  # the paper's w_kinematics

    def as_dict(self) -> dict[str, float]:
        return {name: float(getattr(self, name)) for name in TERMS}


@dataclass(frozen=True)
class AnnealingSettings:
    """RMSProp + Metropolis settings (paper appendix, "Optimization hyperparameters")."""

    switch_probability: float = 0.5  # each contact index is re-sampled with this probability per step
    mu: float = 0.98  # weight of the current squared gradient in the RMS estimate (DexGraspNet's convention)
    step_size: float = 0.005
    step_size_period: int = 50  # step size *= temperature_decay every this many steps
    starting_temperature: float = 18.0
    annealing_period: int = 30  # temperature *= temperature_decay every this many steps
    temperature_decay: float = 0.95


@dataclass(frozen=True)
class InitSettings:
    """Where the optimisation starts (after DexGraspNet's `initialize_convex_hull`).

    The palm centre is put at a point of the object's convex hull inflated by `hull_inflation_m`,
    moved out by a further uniform [`backoff_min_m`, `backoff_max_m`], the palm normal aimed at the
    object (inward hull normal) tilted by up to `jitter_max_rad` and rolled uniformly about itself.
    For pushes only hull points whose inward normal has x >= `push_side_min_cos` are used (the back
    of the object as seen along +x): E_dir would otherwise spend the first few hundred iterations
    dragging the hand around the object. Joints: truncated normal around the hand's open pose with
    sigma = `joint_jitter` * (upper - lower), truncated to the limits.
    """

    hull_inflation_m: float = 0.02
    backoff_min_m: float = 0.0
    backoff_max_m: float = 0.03
    jitter_max_rad: float = math.pi / 6
    push_side_min_cos: float = 0.5
    min_height_m: float = 0.015  # palm-centre start points lower than this above the table are skipped
    joint_jitter: float = 0.1


@dataclass(frozen=True)
class GenerationConfig:
    """Everything `synthesis.generate` needs besides the object, the hand, n and the seed."""

    weights: EnergyWeights = field(default_factory=EnergyWeights)
    annealing: AnnealingSettings = field(default_factory=AnnealingSettings)
    init: InitSettings = field(default_factory=InitSettings)
    iterations: int = 1500
    contacts_per_pose: int = 4
    batch_size: int = 256  # poses optimised together (docs/architecture.md §Compute: ~256 is cheapest per pose on CPU)
    grasp_only: bool = False  # drop E_dir and E_arm: the grasp-pose baseline
    contact_offset_m: float = 0.005  # E_dis target: contacts this far outside the surface
    penetration_margin_m: float = 0.003  # E_pen counts hand-object pairs closer than this
    table_clearance_m: float = 0.002  # E_tpen counts hand geometry lower than this above the table
    ff_min_distance_m: float = 0.02  # E_ff: selected contacts closer than this are penalised
    object_points: int = 1024  # object surface points checked for E_pen
    penetration_check_points: int = 4096  # denser samples for the reported max penetration
    record_history: bool = True  # batch-mean energy per iteration (for plots and energy_history)

    def __post_init__(self) -> None:
        _check(self.iterations >= 1, f"iterations must be >= 1, got {self.iterations}")
        _check(self.contacts_per_pose >= 1, f"contacts_per_pose must be >= 1, got {self.contacts_per_pose}")
        _check(self.batch_size >= 1, f"batch_size must be >= 1, got {self.batch_size}")
        _check(self.object_points >= 1, f"object_points must be >= 1, got {self.object_points}")
        for name, value in self.weights.as_dict().items():
            _check(value >= 0.0 and math.isfinite(value), f"weight {name} must be finite and >= 0, got {value}")
        a = self.annealing
        _check(0.0 <= a.switch_probability <= 1.0, f"switch_probability must be in [0, 1], got {a.switch_probability}")
        _check(0.0 < a.mu <= 1.0, f"mu must be in (0, 1], got {a.mu}")
        _check(a.step_size > 0 and a.starting_temperature > 0, "step_size and starting_temperature must be > 0")
        _check(a.step_size_period >= 1 and a.annealing_period >= 1, "periods must be >= 1")
        _check(0.0 < a.temperature_decay <= 1.0, f"temperature_decay must be in (0, 1], got {a.temperature_decay}")
        i = self.init
        _check(0.0 <= i.backoff_min_m <= i.backoff_max_m, "need 0 <= backoff_min_m <= backoff_max_m")
        _check(-1.0 <= i.push_side_min_cos < 1.0, f"push_side_min_cos must be in [-1, 1), got {i.push_side_min_cos}")

    @property
    def active_terms(self) -> tuple[str, ...]:
        """Terms that enter the total (all of them, minus E_dir / E_arm for grasp_only)."""
        return tuple(t for t in TERMS if not (self.grasp_only and t in PUSH_TERMS))

    def effective_weights(self) -> dict[str, float]:
        """Weights with the push terms zeroed when `grasp_only`."""
        return {t: (w if t in self.active_terms else 0.0) for t, w in self.weights.as_dict().items()}

    def replace(self, **changes: Any) -> GenerationConfig:
        """A copy with some fields changed (None values are ignored, so optional CLI flags pass through)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise GenerationConfigError(message)
