"""On-disk cache of per-object artefacts, keyed by content hash.

Layout: `$GD2P_CACHE_DIR/objects/<key>/...` (default `~/.cache/gd2p`). Every write is atomic
(temporary file in the same directory + `os.replace`), so concurrent workers computing the same
object never see a half-written file: the last identical writer wins.
"""
from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np

from shared.atomic import atomic_write_bytes

CACHE_ENV = "GD2P_CACHE_DIR"


def cache_root(cache_dir: str | os.PathLike[str] | None = None) -> Path:
    """The objects cache directory (argument > $GD2P_CACHE_DIR > ~/.cache/gd2p)."""
    base = Path(cache_dir) if cache_dir is not None else Path(os.environ.get(CACHE_ENV, Path.home() / ".cache" / "gd2p"))
    return base.expanduser() / "objects"


def save_npz(path: Path, **arrays: np.ndarray) -> Path:
    """Atomically save arrays as an uncompressed .npz (fast to load, mmap-free)."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]  # mypy fears a key named allow_pickle: keys are array names
    return atomic_write_bytes(path, buffer.getvalue())


def load_npz(path: Path) -> dict[str, np.ndarray] | None:
    """Load a cached .npz fully into memory; None when missing or unreadable (treated as a miss)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError):
        return None
