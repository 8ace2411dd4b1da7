"""The pose store: validated push poses in Parquet shards plus a `manifest.json`.

Written by the data engine (`gd2p dataset build`), read by the sampler's training
(`shared.sampling.dataset.load_pose_dataset`), the Nearest-Neighbor index and `gd2p dataset stats`.

Layout of a store directory:

    manifest.json              what the store holds (below); the only file a reader trusts
    shards/<object_id>-<sha256 prefix>.parquet   every validated pose of one object (raw and augmented)

Columns of a shard (the first five are the reader contract of `shared.sampling.dataset`):

    object_id  string             library id
    hand       string             "allegro" | "leap"
    pose       list<float32>[25]  [p(3), r6(6), q(16)] of the hand base in D (push along +x)
    pose_index int32, null        resting pose of the object (null: its default one)
    yaw_rad    float64            yaw of the object about D's z axis
    stage      string             "raw" (a generator candidate) | "augmented" (a Halton copy)
    success    bool               the push's outcome (version 2; absent or null: a success, see below)
    pose_id    string             stable id: "<object>/r<round>/c<candidate>[/a<copy>]"
    parent_id  string, null       augmented rows: the pose_id of the raw pose they perturb
    round, candidate_index, generator_seed, validation_seed   provenance of the pose
    position_error_m, rotation_deg, max_tilt_deg, toppled, contact_kept, hand_table_contact,
    initial_penetration_m          the push outcome
    energy_<term>, max_penetration_m, palm_normal_x   generator figures (raw rows; null on copies)
    solver_iterations, time_step_s, push_speed_mps, push_distance_m, code_version

Versions: a version-1 store holds successes only (no `success` or `toppled` column, every object at
yaw 0 in its default resting pose); version 2 (the data engine of dataset v2) keeps the failed
pushes beside the successes, each object at random yaws and resting poses, and counts successes,
failures, families and resting poses in the manifest. Both open and read the same way.

Successes and failures: `rows()` - the one reader of the shards - returns the successes unless asked
for `outcome="failure"` or `"all"`, so every consumer of training poses (training, the
Nearest-Neighbor index, the data-size experiment, the statistics) sees what a version-1 store gave
it without filtering anything itself. A row whose `success` is absent (version 1) or null is a
success: version-1 stores kept nothing else.

Atomicity: one shard per finished object (the unit of work). A shard is written to a temporary
file, fsynced and renamed into place under a name of its own content (so it never replaces a file
the manifest lists); then the manifest - which lists the shard with its row count and sha256 and
marks the object done - is replaced the same way, and only then is the object's previous shard
deleted. A crash at any point leaves either the old manifest (the object is redone on resume; the
orphaned shard is deleted when a build next opens the store) or the new one, and whichever is on
disk describes exactly the files it lists. Readers only follow the manifest, so a half-written or
orphaned file is never visible.

Content hash: `content_hash` in the manifest is the hash of exactly the rows its shards hold, or
null while a build is in progress. Each shard commit sets it to null in the same atomic manifest
write that changes the shard list (recomputing it per object would read the whole store each
time); `record_run`, at the end of every build run (finished or interrupted), computes and stores
it. So a build killed between two runs leaves `"content_hash": null`, never a hash of other
content; `recorded_content_hash()` returns it and `verify()` checks it.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from shared.atomic import atomic_write_bytes

MANIFEST_NAME = "manifest.json"
SHARD_DIR = "shards"
LOCK_NAME = ".writer.lock"
STORE_FORMAT = "gd2p-pose-store"
STORE_VERSION = 2  # what this code writes (module docstring: Versions)
READABLE_VERSIONS = (1, 2)
STAGES = ("raw", "augmented")
OUTCOMES = ("success", "failure", "all")  # what `DatasetStore.rows` returns
SUCCESS_COLUMN = "success"
# Per-object counts kept in the manifest (what `gd2p dataset stats` reports per stage).
COUNT_KEYS = ("generated", "raw_successes", "augmented_validated", "augmented_successes")
# Build parameters that fix the content: resuming with other values would mix two datasets.
CONTENT_PARAMETERS = ("hand", "split", "per_object", "seed", "iterations", "min_poses", "min_rounds", "max_rounds",
                      "placement", "physics", "push_distance_m")
DEFAULT_POSE_KEY = "default"  # by_resting_pose key of rows whose pose_index is null (the default pose)
_SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]")
FamilyLookup = Callable[[str], str]  # object id -> family name


class StoreError(ValueError):
    """A store that cannot be opened or written as asked (missing, corrupt, other build)."""


@dataclass(frozen=True)
class ObjectStatus:
    """What the manifest knows about one finished object."""

    object_id: str
    counts: dict[str, int]
    shard: str | None  # relative path; None when the object gave no row
    rows: int  # stored rows, failures included
    successes: int  # rows that are successful pushes (all of them in a version-1 store)


# ----------------------------------------------------------------------------- atomic files
def table_to_parquet_bytes(table: pa.Table) -> bytes:
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    data: bytes = sink.getvalue().to_pybytes()
    return data


# ----------------------------------------------------------------------------- the store
class DatasetStore:
    """A pose store directory; see the module docstring. Not safe for two concurrent writers."""

    _lock_handle: IO[str] | None = None  # the writer lock file while held (see _lock_for_writing)

    def __init__(self, directory: Path, manifest: dict[str, Any]):
        self.directory = directory
        self.manifest = manifest

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, directory: str | os.PathLike[str]) -> DatasetStore:
        """An existing store (raises StoreError if there is none or its manifest is unreadable)."""
        directory = Path(directory)
        path = directory / MANIFEST_NAME
        if not path.is_file():
            raise StoreError(f"{directory}: not a pose store (no {MANIFEST_NAME})")
        try:
            manifest = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise StoreError(f"{path}: unreadable manifest: {exc}") from exc
        if not isinstance(manifest, dict) or manifest.get("format") != STORE_FORMAT:
            raise StoreError(f"{path}: not a {STORE_FORMAT} manifest")
        if manifest.get("version") not in READABLE_VERSIONS:
            raise StoreError(f"{path}: store version {manifest.get('version')} is not supported "
                             f"(this code reads versions {', '.join(map(str, READABLE_VERSIONS))})")
        return cls(directory, manifest)

    @property
    def version(self) -> int:
        version: int = self.manifest["version"]
        return version

    @classmethod
    def create_or_resume(cls, directory: str | os.PathLike[str], parameters: Mapping[str, Any]) -> DatasetStore:
        """Open the store for a build with `parameters`, creating it if the directory has none.

        Refuses (StoreError) to resume a store built with different content parameters
        (`CONTENT_PARAMETERS`): the result would be a mix of two datasets; and to open a store
        another live process is writing (an exclusive lock, released by the OS when that process
        dies, however it dies).
        """
        directory = Path(directory)
        if (directory / MANIFEST_NAME).is_file():
            store = cls.open(directory)
            if store.version != STORE_VERSION:
                raise StoreError(f"{directory}: a version-{store.version} store (built by an earlier data engine); "
                                 f"it stays readable, but a build writes version {STORE_VERSION}: use a new --out directory")
            store._check_same_build(parameters)
            store._lock_for_writing()
            store._remove_orphans()
            return store
        if directory.exists() and any(p.name not in (SHARD_DIR, LOCK_NAME) for p in directory.iterdir()):
            raise StoreError(f"{directory}: exists and is not a pose store; choose an empty or new directory")
        manifest = {"format": STORE_FORMAT, "version": STORE_VERSION, "hand": parameters["hand"],
                    "split": parameters["split"], "parameters": dict(parameters), "shards": [], "objects": {},
                    "runs": [], "totals": _totals({}), "content_hash": content_hash(pa.table({}))}
        store = cls(directory, manifest)
        store._lock_for_writing()
        store._save()
        return store

    def _lock_for_writing(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        handle = open(self.directory / LOCK_NAME, "a")
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            raise StoreError(f"{self.directory}: another build is writing this store right now") from None
        self._lock_handle = handle  # held until this object (or the process) goes away

    def _remove_orphans(self) -> None:
        """Delete shard files the manifest does not list (left by a build killed mid-commit); needs the lock."""
        listed = {self.directory / s["path"] for s in self.manifest["shards"]}
        shard_dir = self.directory / SHARD_DIR
        if shard_dir.is_dir():
            for path in shard_dir.iterdir():
                if path.is_file() and path not in listed:
                    path.unlink(missing_ok=True)

    def close(self) -> None:
        """Release the writer lock (also released when the process exits)."""
        handle = getattr(self, "_lock_handle", None)
        if handle is not None:
            handle.close()
            self._lock_handle = None

    def _check_same_build(self, parameters: Mapping[str, Any]) -> None:
        stored = self.manifest.get("parameters", {})
        differ = {k: (stored.get(k), parameters.get(k)) for k in CONTENT_PARAMETERS
                  if _canonical(stored.get(k)) != _canonical(parameters.get(k))}
        if differ:
            listing = ", ".join(f"{k}: stored {a!r}, asked {b!r}" for k, (a, b) in differ.items())
            raise StoreError(f"{self.directory}: was built with other parameters ({listing}); "
                             "use another --out directory or the same parameters to resume")

    # ------------------------------------------------------------------ reading
    @property
    def hand(self) -> str:
        hand: str = self.manifest["hand"]
        return hand

    def completed_objects(self) -> dict[str, ObjectStatus]:
        """Objects whose result is stored, by id (done objects are skipped on resume)."""
        return {oid: ObjectStatus(oid, dict(entry["counts"]), entry.get("shard"), int(entry.get("rows", 0)),
                                  int(entry.get("successes", entry.get("rows", 0))))
                for oid, entry in self.manifest["objects"].items() if entry.get("status") == "done"}

    def totals(self, family_of: FamilyLookup | None = None) -> dict[str, Any]:
        """The manifest's totals recomputed from its object entries (a version-1 manifest's lack the outcome,
        family and resting-pose counts); `family_of(object_id)` names the family of an entry that has none."""
        return _totals(self.manifest["objects"], family_of)

    def recorded_content_hash(self) -> str | None:
        """The manifest's content hash: the hash of the stored rows, or None while a build is in progress."""
        return self.manifest.get("content_hash")

    def shard_paths(self) -> list[Path]:
        return [self.directory / s["path"] for s in self.manifest["shards"]]

    def rows(self, columns: Sequence[str] | None = None, outcome: str = "success") -> pa.Table:
        """The stored rows of `outcome` ("success", the default, "failure" or "all"), shards in manifest order.

        The one reader of the shards: training, the Nearest-Neighbor index and the statistics get the
        successful pushes by default, as from a version-1 store; failures only when they ask. `columns`
        selects columns (all by default); an empty store gives an empty table.
        """
        if outcome not in OUTCOMES:
            raise StoreError(f"outcome must be one of {', '.join(OUTCOMES)}; got {outcome!r}")
        tables = [_read_shard(p, columns, outcome) for p in self.shard_paths()]
        if not tables:
            return pa.table({})
        return pa.concat_tables(tables, promote_options="default")

    def verify(self) -> None:
        """Raise StoreError if a listed shard is missing or its bytes differ from the manifest, or if the
        manifest's content hash (when it has one) is not the hash of the stored rows."""
        for entry in self.manifest["shards"]:
            path = self.directory / entry["path"]
            if not path.is_file():
                raise StoreError(f"{path}: listed in the manifest but missing")
            if _sha256_file(path) != entry["sha256"]:
                raise StoreError(f"{path}: content differs from the manifest's sha256 (modified or corrupt)")
        recorded = self.recorded_content_hash()
        if recorded is not None and recorded != self.content_hash():
            raise StoreError(f"{self.directory / MANIFEST_NAME}: content_hash {recorded[:16]}... is not the hash of "
                             "the stored rows (stale or modified); rerun the build command to refresh it")

    # ------------------------------------------------------------------ writing
    def write_object(self, object_id: str, rows: pa.Table, stats: Mapping[str, Any]) -> ObjectStatus:
        """Store one finished object atomically: its shard (if any row), then the manifest.

        `stats` must hold the per-stage counts (`COUNT_KEYS`); other entries (rounds, elapsed_s,
        seeds) are kept in the object's manifest entry. Re-writing an object replaces it.
        """
        missing = [k for k in COUNT_KEYS if k not in stats]
        if missing:
            raise StoreError(f"{object_id}: stats lack {missing}")
        if rows.num_rows and set(rows.column("object_id").unique().to_pylist()) != {object_id}:
            raise StoreError(f"{object_id}: rows of other objects given: {rows.column('object_id').unique().to_pylist()}")
        shard = None
        outcomes = _outcome_counts(rows)
        previous = {s["path"] for s in self.manifest["shards"] if s.get("object_id") == object_id}
        self.manifest["shards"] = [s for s in self.manifest["shards"] if s.get("object_id") != object_id]
        if rows.num_rows:
            data = table_to_parquet_bytes(rows)
            sha256 = hashlib.sha256(data).hexdigest()
            # Named by its content: never overwrites a shard the manifest on disk lists.
            shard = f"{SHARD_DIR}/{_SAFE_NAME.sub('_', object_id)}-{sha256[:16]}.parquet"
            atomic_write_bytes(self.directory / shard, data, durable=True)
            self.manifest["shards"].append({"path": shard, "object_id": object_id, "rows": rows.num_rows,
                                            "sha256": sha256})
            self.manifest["shards"].sort(key=lambda s: s["object_id"])
        counts = {k: int(stats[k]) for k in COUNT_KEYS}
        extra = {k: v for k, v in stats.items() if k not in COUNT_KEYS}
        self.manifest["objects"][object_id] = {"status": "done", "counts": counts, "shard": shard,
                                               "rows": rows.num_rows, **outcomes, **extra}
        self.manifest["objects"] = dict(sorted(self.manifest["objects"].items()))
        self.manifest["totals"] = _totals(self.manifest["objects"])
        self.manifest["content_hash"] = None  # in progress: set again by record_run
        self._save()
        for old in previous - {shard}:  # no longer listed by the manifest on disk
            (self.directory / old).unlink(missing_ok=True)
        return ObjectStatus(object_id, counts, shard, rows.num_rows, outcomes["successes"])

    def record_run(self, run: Mapping[str, Any]) -> None:
        """Append one build run (command line, wall time, figures) and refresh the content hash."""
        self.manifest["runs"].append(dict(run))
        self.manifest["content_hash"] = self.content_hash()
        self._save()

    def content_hash(self) -> str:
        """SHA-256 of every stored row (failures too), independent of shard order, file encoding and row order."""
        return content_hash(self.rows(outcome="all"))

    def _save(self) -> None:
        text = json.dumps(self.manifest, indent=1, sort_keys=False, default=_json_default)
        atomic_write_bytes(self.directory / MANIFEST_NAME, text.encode(), durable=True)


# ----------------------------------------------------------------------------- helpers
def content_hash(table: pa.Table) -> str:
    """SHA-256 over the rows of `table` as sorted canonical JSON lines (column order ignored)."""
    lines = sorted(json.dumps(row, sort_keys=True, default=_json_default, allow_nan=True)
                   for row in table.to_pylist())
    digest = hashlib.sha256()
    for line in lines:
        digest.update(line.encode() + b"\n")
    return digest.hexdigest()


def _read_shard(path: Path, columns: Sequence[str] | None, outcome: str) -> pa.Table:
    """One shard's rows of `outcome` (see `DatasetStore.rows`): `columns` in that order (a column the shard
    lacks comes back null, e.g. `success` of a version-1 shard), all of the shard's when None."""
    names = pq.read_schema(path).names
    has_outcome = SUCCESS_COLUMN in names
    wanted = list(columns) if columns else None
    read = None if wanted is None else [c for c in wanted if c in names]
    if read is not None and has_outcome and outcome != "all" and SUCCESS_COLUMN not in read:
        read.append(SUCCESS_COLUMN)  # to filter on, dropped below
    table = pq.read_table(path, columns=read)
    if outcome != "all":
        ok = succeeded(table)
        table = table.filter(ok if outcome == "success" else pc.invert(ok))
    if wanted is None:
        return table
    return pa.table({c: table.column(c) if c in table.column_names else pa.nulls(table.num_rows) for c in wanted})


def succeeded(table: pa.Table) -> pa.Array | pa.ChunkedArray:
    """Per row: a success (null or absent `success`: a success, as every version-1 row is)."""
    if SUCCESS_COLUMN not in table.column_names:
        return pa.array([True] * table.num_rows)
    return pc.fill_null(table.column(SUCCESS_COLUMN), True)


def _outcome_counts(rows: pa.Table) -> dict[str, Any]:
    """Successes, failures and both per resting pose of one object's rows (its manifest entry)."""
    outcomes = succeeded(rows).to_pylist() if rows.num_rows else []
    if "pose_index" in rows.column_names:
        poses = [DEFAULT_POSE_KEY if p is None else str(p) for p in rows.column("pose_index").to_pylist()]
    else:
        poses = [DEFAULT_POSE_KEY] * rows.num_rows
    by_pose: dict[str, dict[str, int]] = {}
    for pose, ok in zip(poses, outcomes, strict=True):
        entry = by_pose.setdefault(pose, {"rows": 0, "successes": 0})
        entry["rows"] += 1
        entry["successes"] += int(ok)
    successes = sum(outcomes)
    return {"successes": successes, "failures": len(outcomes) - successes,
            "by_resting_pose": dict(sorted(by_pose.items()))}


def _totals(objects: Mapping[str, Mapping[str, Any]], family_of: FamilyLookup | None = None) -> dict[str, Any]:
    """The manifest's totals: per-stage counts, rows, successes and failures, per family and resting pose.

    An object's family is its manifest entry's (version 2), else `family_of(object_id)`, else "unknown".
    """
    totals: dict[str, Any] = {k: 0 for k in COUNT_KEYS}
    for entry in objects.values():
        for k in COUNT_KEYS:
            totals[k] += int(entry["counts"][k])
    totals["objects"] = len(objects)
    totals["rows"] = sum(int(e.get("rows", 0)) for e in objects.values())
    totals["successes"] = sum(int(e.get("successes", e.get("rows", 0))) for e in objects.values())
    totals["failures"] = totals["rows"] - totals["successes"]
    totals["by_family"] = _family_totals(objects, family_of)
    totals["by_resting_pose"] = _resting_pose_totals(objects)
    return totals


def _family_totals(objects: Mapping[str, Mapping[str, Any]], family_of: FamilyLookup | None) -> dict[str, dict[str, int]]:
    by_family: dict[str, dict[str, int]] = {}
    for object_id, entry in objects.items():
        name = entry.get("family") or (family_of(object_id) if family_of is not None else "unknown")
        family = by_family.setdefault(str(name), {"objects": 0, "rows": 0, "successes": 0, "failures": 0,
                                                  **dict.fromkeys(COUNT_KEYS, 0)})
        family["objects"] += 1
        family["rows"] += int(entry.get("rows", 0))
        family["successes"] += int(entry.get("successes", entry.get("rows", 0)))
        family["failures"] += int(entry.get("failures", 0))
        for k in COUNT_KEYS:
            family[k] += int(entry["counts"][k])
    return dict(sorted(by_family.items()))


def _resting_pose_totals(objects: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, int]]:
    by_pose: dict[str, dict[str, int]] = {}
    for entry in objects.values():
        for pose, counts in entry.get("by_resting_pose", {}).items():
            total = by_pose.setdefault(pose, {"rows": 0, "successes": 0})
            total["rows"] += int(counts["rows"])
            total["successes"] += int(counts["successes"])
    return dict(sorted(by_pose.items(), key=lambda item: (not item[0].isdigit(), int(item[0]) if item[0].isdigit() else 0)))


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _canonical(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=_json_default)


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):  # numpy scalars and arrays
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
