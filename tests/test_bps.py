"""Basis point set: deterministic basis, correct distances, checkpoint round trip, clear errors."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from shared.world.bps import DEFAULT_BASIS_SIZE, DEFAULT_RADIUS_M, BasisPointSet, BPSError


def cloud(n: int = 2048, seed: int = 0, scale: float = 0.08) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-scale, scale, (n, 3))


def test_basis_is_deterministic_sized_and_uniform_in_the_ball():
    a, b = BasisPointSet(), BasisPointSet()
    assert a.basis.shape == (DEFAULT_BASIS_SIZE, 3) == (4096, 3)
    np.testing.assert_array_equal(a.basis, b.basis)
    assert a.fingerprint == b.fingerprint
    assert not np.array_equal(a.basis, BasisPointSet(seed=1).basis)
    radii = np.linalg.norm(a.basis, axis=1)
    assert radii.max() <= DEFAULT_RADIUS_M
    assert np.mean(radii < DEFAULT_RADIUS_M / 2) == pytest.approx(1 / 8, abs=0.02)  # uniform in volume
    assert np.abs(a.basis.mean(axis=0)).max() < 0.01


def test_encoding_is_the_distance_to_the_nearest_point():
    bps = BasisPointSet(n=512)
    points = cloud(300)
    encoded = bps.encode(points)
    assert encoded.shape == (512,) and encoded.dtype == np.float32
    np.testing.assert_allclose(encoded, cdist(bps.basis, points).min(axis=1), rtol=1e-6)
    np.testing.assert_array_equal(bps.encode(points), encoded)


def test_batch_encoding_matches_single_encoding():
    bps = BasisPointSet()
    clouds = np.stack([cloud(2048, seed=s) for s in range(3)])
    batch = bps.encode_batch(clouds)
    assert batch.shape == (3, 4096)
    np.testing.assert_array_equal(batch[1], bps.encode(clouds[1]))
    assert bps.encode_batch([cloud(10), cloud(20, seed=1)]).shape == (2, 4096)


def test_checkpoint_round_trip_encodes_identically():
    bps = BasisPointSet(n=1024, radius=0.25, seed=7)
    state = bps.to_dict()
    restored = BasisPointSet.from_dict(state)
    assert (restored.n, restored.radius, restored.seed) == (1024, 0.25, 7)
    np.testing.assert_array_equal(restored.encode(cloud(500)), bps.encode(cloud(500)))
    with pytest.raises(BPSError, match="shape"):
        BasisPointSet.from_dict({**state, "basis": state["basis"][:10]})
    with pytest.raises(BPSError, match="n, radius, seed"):
        BasisPointSet.from_dict({"radius": 0.3})


def test_bad_clouds_fail_clearly():
    bps = BasisPointSet(n=64)
    with pytest.raises(BPSError, match="empty"):
        bps.encode(np.zeros((0, 3)))
    with pytest.raises(BPSError, match="beyond the BPS ball"):
        bps.encode(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, DEFAULT_RADIUS_M + 0.01]]))
    with pytest.raises(BPSError, match=r"\[N, 3\]"):
        bps.encode(np.zeros((10, 2)))
    with pytest.raises(BPSError, match="non-finite"):
        bps.encode(np.array([[np.nan, 0.0, 0.0]]))
    with pytest.raises(BPSError, match=r"\[B, N, 3\]"):
        bps.encode_batch(np.zeros((10, 3)))
