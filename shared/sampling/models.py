"""Which models a sampler worker loads for a hand, by their SHA-256: what a push's decision depended on.

`model_ids(hand)` resolves the paths the sampler service resolves (`$GD2P_SAMPLER_CHECKPOINT_<HAND>`,
`$GD2P_CRITIC_CHECKPOINT_<HAND>`, `$GD2P_SAMPLER_NN_INDEX_<HAND>`, else the shipped files) and names each by
the SHA-256 its manifest records (every loader checks the file against it: `checkpoint.verify_file`), or
by hashing the file when it has no manifest. A push's recording carries them (services/planner/recording.py)
so that `gd2p replay FILE.mcap --resim` can tell whether it plans with the same models.
"""
from __future__ import annotations

import json
import threading
from pathlib import Path

from shared.sampling.checkpoint import default_checkpoint_path, file_sha256, manifest_path
from shared.sampling.critic_train import default_critic_path
from shared.sampling.nearest_neighbor import default_nn_index_path

MODELS = ("diffusion", "critic", "nn_index")
_hashes: dict[tuple[str, int, int], str] = {}  # (path, size, mtime_ns) -> sha256 of a file without a manifest
_lock = threading.Lock()


def model_paths(hand: str) -> dict[str, Path | None]:
    """The diffusion checkpoint, the critic (None: turned off) and the NN index a sampler loads for `hand`."""
    return {"diffusion": default_checkpoint_path(hand), "critic": default_critic_path(hand),
            "nn_index": default_nn_index_path(hand)}


def model_id(path: Path | None) -> str:
    """"sha256:<hex>" of the model file (its manifest's record, else its bytes), "none" (turned off) or
    "missing: <path>"."""
    if path is None:
        return "none"
    if not path.is_file():
        return f"missing: {path}"
    try:
        recorded = json.loads(manifest_path(path).read_text()).get("sha256")
    except (OSError, ValueError, AttributeError):
        recorded = None
    if recorded:
        return f"sha256:{recorded}"
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    with _lock:
        if key not in _hashes:
            _hashes[key] = file_sha256(path)
        return f"sha256:{_hashes[key]}"


def model_ids(hand: str) -> dict[str, str]:
    """{"diffusion" | "critic" | "nn_index": model_id} of `hand`'s models, as a sampler here would load them."""
    return {name: model_id(path) for name, path in model_paths(hand).items()}
