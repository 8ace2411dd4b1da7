"""bench/critic_ranking.py: how a request's orders are read against its pushes, and what fine-tuning learns (no physics)."""
from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest
import torch

from conftest import load_bench
from shared.sampling.critic import CriticConfig, SuccessCritic


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_bench("critic_ranking")


def toy_group(bench: ModuleType, error_m: np.ndarray, success: np.ndarray, seed: int = 0) -> object:
    """A request of len(error_m) poses whose true distance from the target is the pose's first coordinate."""
    poses = torch.as_tensor(np.random.default_rng(seed).normal(size=(len(error_m), 25)), dtype=torch.float32)
    poses[:, 0] = torch.as_tensor(error_m * 100, dtype=torch.float32)
    return bench.Group("toy", poses, torch.zeros(1, 16), None, torch.as_tensor(success, dtype=torch.float32),
                       torch.as_tensor(np.minimum(error_m, bench.MISS_CAP_M), dtype=torch.float32))


def tiny_critic() -> SuccessCritic:
    torch.manual_seed(0)
    return SuccessCritic(CriticConfig(bps_dim=16, object_dim=2, hidden_dim=16, num_layers=1)).eval()


def test_the_prescreen_order_plans_passed_poses_closest_first_among_those_it_pushed(bench: ModuleType) -> None:
    # pose 3 is the closest passing one, but the prescreen only pushes the first 3 poses
    group = toy_group(bench, np.array([0.02, 0.05, 0.01, 0.001]), np.array([True, False, True, True]))
    orders = bench.orders(group, tiny_critic(), prescreened=3)
    assert orders["prescreen"].tolist() == [2, 0, 1]
    assert orders["critic"].tolist() == [0, 1, 2, 3]
    assert orders["oracle"].tolist() == [3, 2, 0, 1]


def test_a_miss_counts_at_most_the_cap_in_the_mean_distance(bench: ModuleType) -> None:
    group = toy_group(bench, np.array([0.01, 0.5]), np.array([True, False]))
    figures = bench.figures([group], [np.array([1, 0])], None, top=2)
    assert figures["top_error_cm"] == pytest.approx((1.0 + 100 * bench.MISS_CAP_M) / 2)
    assert figures["top_pass"] == 0.5 and figures["first_pass"] == 0.0
    assert figures["first_error_cm"] == pytest.approx(100 * bench.MISS_CAP_M)


def test_fine_tuning_learns_to_rank_the_poses_of_a_request_by_their_distance(bench: ModuleType) -> None:
    """The truth is readable from the poses: after fine-tuning, the error head ranks held-out requests by it."""
    rng = np.random.default_rng(1)

    def requests(n: int, seed: int) -> list[object]:
        out = []
        for i in range(n):
            error = rng.uniform(0.0, 0.08, size=24)
            out.append(toy_group(bench, error, error < 0.03, seed=seed + i))
        return out

    train, held_out = requests(32, 0), requests(8, 100)
    critic = tiny_critic()
    before = bench.figures(held_out, [np.arange(24)] * 8, bench.predicted_errors(held_out, critic), top=6)
    tuned = bench.fine_tune(train, critic, steps=150, learning_rate=3e-3, batch=8)
    predicted = bench.predicted_errors(held_out, tuned)
    after = bench.figures(held_out, [np.argsort(p) for p in predicted], predicted, top=6)
    assert after["spearman"] > 0.8 > before["spearman"]
    assert after["top_error_cm"] < 2.0
