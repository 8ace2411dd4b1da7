"""Basis point set (BPS) encoding of an object's point cloud in the direction frame D.

4096 basis points, fixed seed, uniform in a ball around D's origin; each feature is the distance
from a basis point to the nearest object point (Prokudin et al. 2019, as GD2P conditions its
diffusion model). The basis travels with every checkpoint (`to_dict` / `from_dict`) so sampling
encodes objects exactly as training did.

Radius 0.30 m: D's origin is the object's centre of mass projected onto the table, and the
library's farthest surface points from it are the tops of tall objects (up to 25 cm high) and
the corners of 25 cm flat boxes (~18 cm); 0.30 m contains every library object with 5 cm to
spare while keeping the basis as dense as possible around the object. Points beyond the ball
are refused rather than silently encoded with clipped geometry.

Speed: a scipy cKDTree over the cloud, queried by the basis (2048 points: ~2–3 ms, docs/architecture.md §Compute).
"""
from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

DEFAULT_BASIS_SIZE = 4096
DEFAULT_RADIUS_M = 0.30
DEFAULT_SEED = 0


class BPSError(ValueError):
    """A point cloud that cannot be encoded (empty, malformed, or beyond the basis ball)."""


class BasisPointSet:
    """A fixed set of basis points uniform in a ball of `radius` metres around the origin."""

    def __init__(self, n: int = DEFAULT_BASIS_SIZE, radius: float = DEFAULT_RADIUS_M, seed: int = DEFAULT_SEED) -> None:
        if n < 1:
            raise ValueError(f"basis size must be >= 1, got {n}")
        if not radius > 0:
            raise ValueError(f"radius must be positive, got {radius}")
        self.n, self.radius, self.seed = int(n), float(radius), int(seed)
        self.basis = _uniform_ball(self.n, self.radius, self.seed)

    def __repr__(self) -> str:
        return f"BasisPointSet(n={self.n}, radius={self.radius}, seed={self.seed})"

    @property
    def fingerprint(self) -> str:
        """Hash of the basis points: equal iff two sets encode identically."""
        return hashlib.sha256(self.basis.astype("<f4").tobytes()).hexdigest()[:16]

    def encode(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] cloud (metres, in D) -> [n] float32 distances from each basis point to the cloud."""
        points = self._check_cloud(points)
        distances, _ = cKDTree(points).query(self.basis, k=1)
        encoded: np.ndarray = distances.astype(np.float32)
        return encoded

    def encode_batch(self, clouds: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
        """[B, N, 3] array or a list of [N_i, 3] clouds -> [B, n] float32."""
        if isinstance(clouds, np.ndarray) and clouds.ndim != 3:
            raise BPSError(f"a batch of clouds must be [B, N, 3], got shape {clouds.shape}")
        encoded = [self.encode(cloud) for cloud in clouds]
        if not encoded:
            return np.zeros((0, self.n), dtype=np.float32)
        return np.stack(encoded)

    def _check_cloud(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise BPSError(f"point cloud must be [N, 3], got shape {points.shape}")
        if len(points) == 0:
            raise BPSError("point cloud is empty: nothing to encode")
        if not np.all(np.isfinite(points)):
            raise BPSError("point cloud has non-finite (NaN/inf) coordinates")
        farthest = float(np.sqrt((points * points).sum(axis=1).max()))
        if farthest > self.radius * (1.0 + 1e-6):
            raise BPSError(
                f"object extends {farthest:.3f} m from D's origin, beyond the BPS ball of radius {self.radius} m "
                "(is the cloud in D, centred on the object, and in metres?)"
            )
        return points

    def to_dict(self) -> dict[str, Any]:
        """Everything needed to rebuild this basis, including the points themselves (for checkpoints)."""
        return {"n": self.n, "radius": self.radius, "seed": self.seed, "basis": self.basis.astype(np.float32).copy()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BasisPointSet:
        """Rebuild from `to_dict`; a stored basis is used as is (and must match its n)."""
        try:
            bps = cls(int(data["n"]), float(data["radius"]), int(data["seed"]))
        except (KeyError, TypeError) as exc:
            raise BPSError(f"not a BPS dict (needs n, radius, seed): {exc}") from exc
        if data.get("basis") is not None:
            basis = np.asarray(data["basis"], dtype=np.float64)
            if basis.shape != (bps.n, 3):
                raise BPSError(f"stored basis has shape {basis.shape}, expected ({bps.n}, 3)")
            bps.basis = basis
        return bps


def _uniform_ball(n: int, radius: float, seed: int) -> np.ndarray:
    """n points uniform in the ball: Gaussian directions, radii ~ radius * U^(1/3)."""
    rng = np.random.default_rng(seed)
    directions = rng.standard_normal((n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = radius * rng.uniform(0.0, 1.0, n) ** (1.0 / 3.0)
    # float32-representable values, so a basis restored from a checkpoint encodes bit-identically
    return (directions * radii[:, None]).astype(np.float32).astype(np.float64)
