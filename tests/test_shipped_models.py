"""The shipped models: per hand the diffusion checkpoint, its critic and the nearest-neighbour index the defaults
load, each with a manifest naming the file's SHA-256; nothing else in the checkpoints directory, and the wheel's
package data names exactly these files."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from shared.sampling.checkpoint import SHIPPED_DIR, default_checkpoint_path, file_sha256, manifest_path, verify_file
from shared.sampling.critic_train import CriticError, default_critic_path, load_critic
from shared.sampling.nearest_neighbor import NearestNeighborBaseline, NearestNeighborError, default_nn_index_path

HANDS = ("allegro", "leap")
SHIPPED = {f"{hand}{suffix}" for hand in HANDS for suffix in (".pt", "_critic.pt", "_nn.npz")}


def test_the_defaults_load_the_shipped_files_and_each_has_a_manifest_with_its_sha256(monkeypatch):
    for hand in HANDS:
        for variable in ("GD2P_SAMPLER_CHECKPOINT_", "GD2P_CRITIC_CHECKPOINT_", "GD2P_SAMPLER_NN_INDEX_"):
            monkeypatch.delenv(variable + hand.upper(), raising=False)
        defaults = {default_checkpoint_path(hand), default_critic_path(hand), default_nn_index_path(hand)}
        assert {p.name for p in defaults} <= SHIPPED and all(p.parent == SHIPPED_DIR for p in defaults if p)
    for name in SHIPPED:
        manifest = json.loads(manifest_path(SHIPPED_DIR / name).read_text())
        assert manifest["sha256"] == file_sha256(SHIPPED_DIR / name), name
    models = {p.name for p in SHIPPED_DIR.iterdir() if not p.name.endswith(".manifest.json")}
    assert models == SHIPPED  # earlier generations are in git history, not in the tree


def test_the_wheel_ships_only_the_shipped_models():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    package_data = pyproject["tool"]["setuptools"]["package-data"]
    assert set(package_data["shared.sampling.checkpoints"]) == SHIPPED
    assert not any(p.endswith((".pt", ".npz", ".safetensors")) for p in package_data["*"])


@pytest.mark.parametrize(("name", "load", "error"), [("allegro_critic.pt", load_critic, CriticError),
                                                     ("leap_nn.npz", NearestNeighborBaseline.load, NearestNeighborError)])
def test_a_model_file_that_is_not_the_one_its_manifest_describes_is_refused_by_name(tmp_path, name, load, error):
    copy = tmp_path / name
    copy.write_bytes((SHIPPED_DIR / name).read_bytes())
    manifest_path(copy).write_text(manifest_path(SHIPPED_DIR / name).read_text())
    load(copy)  # the file and its manifest agree
    manifest = json.loads(manifest_path(copy).read_text())
    manifest_path(copy).write_text(json.dumps({**manifest, "sha256": "0" * 64}))
    with pytest.raises(error, match=f"{name}: its SHA-256 .* manifest {name}.manifest.json records 0000"):
        load(copy)
    manifest_path(copy).write_text(json.dumps({k: v for k, v in manifest.items() if k != "sha256"}))
    verify_file(copy)  # a manifest from before hashes were recorded: loads as it is
