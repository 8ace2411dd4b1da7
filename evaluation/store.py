"""Resumable experiment results: one JSON line per finished unit of work, keyed, appended durably.

A long evaluation is many independent units (an episode, a trained model, an object's coverage).
Each finished unit is appended to `<out>/<experiment>/records.jsonl` and fsynced, so a run that is
killed loses at most the units in flight; a restarted run skips every key already recorded. A torn
last line (killed mid-write) is ignored on load and rewritten when its unit runs again.

The store also pins the experiment's settings: restarting with different settings into the same
directory is refused (the table would silently mix two protocols).
"""
from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from shared.atomic import atomic_write_text

RECORDS_FILE = "records.jsonl"
SETTINGS_FILE = "settings.json"


def read_records(path: Path) -> dict[str, dict[str, Any]]:
    """The finished units of a records file by key (a unit recorded twice: its last record)."""
    records = {}
    for line in Path(path).read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line torn by a kill: its unit runs again
        records[record["key"]] = record
    return records


class ResultStoreError(ValueError):
    """The output directory holds results of a different protocol."""


class ResultStore:
    """Append-only keyed records of one experiment in `directory`."""

    def __init__(self, directory: str | os.PathLike, settings: Mapping[str, Any]):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._check_settings(dict(settings))
        self.path = self.directory / RECORDS_FILE
        self.records: dict[str, dict[str, Any]] = read_records(self.path) if self.path.exists() else {}

    def _check_settings(self, settings: dict[str, Any]) -> None:
        path = self.directory / SETTINGS_FILE
        encoded = json.loads(json.dumps(settings))  # tuples -> lists, as they come back from disk
        if path.exists():
            stored = json.loads(path.read_text())
            if stored != encoded:
                changed = sorted(k for k in set(stored) | set(encoded) if stored.get(k) != encoded.get(k))
                raise ResultStoreError(f"{self.directory} holds results run with other settings ({', '.join(changed)}); "
                                       "use another --out or delete it to start over")
            return
        atomic_write_text(path, json.dumps(encoded, indent=2, sort_keys=True) + "\n")

    def done(self, key: str) -> bool:
        return key in self.records

    def pending(self, keys: Iterable[str]) -> list[str]:
        return [k for k in keys if k not in self.records]

    def add(self, key: str, record: Mapping[str, Any]) -> None:
        """Record a finished unit durably (a duplicate key replaces the earlier record on load)."""
        row = {"key": key, **record}
        line = json.dumps(row, sort_keys=True)
        if self.path.exists() and self.path.stat().st_size:
            with self.path.open("rb") as f:  # a torn last line must not swallow this one
                f.seek(-1, os.SEEK_END)
                if f.read(1) != b"\n":
                    line = "\n" + line
        with self.path.open("a") as f:
            f.write(line + "\n")
            f.flush()
            os.fsync(f.fileno())
        self.records[key] = row

    def values(self) -> list[dict[str, Any]]:
        return list(self.records.values())
