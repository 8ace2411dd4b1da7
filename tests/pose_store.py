"""Writing a pose store for tests the way the data engine does: through `DatasetStore`, one shard per object."""
from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc

from shared.data.dataset_store import DatasetStore


def write_pose_store(directory: Path, rows: pa.Table) -> Path:
    """A verified store holding `rows` (columns object_id, hand, pose and any others), one shard per object."""
    hands = rows.column("hand").unique().to_pylist()
    store = DatasetStore.create_or_resume(directory, {"hand": hands[0], "split": "train"})
    try:
        for object_id in rows.column("object_id").unique().to_pylist():
            mine = rows.filter(pc.equal(rows.column("object_id"), object_id))
            store.write_object(object_id, mine, {"generated": mine.num_rows, "raw_successes": mine.num_rows,
                                                 "augmented_validated": 0, "augmented_successes": 0})
        store.record_run({"command": "tests"})
    finally:
        store.close()
    return directory
