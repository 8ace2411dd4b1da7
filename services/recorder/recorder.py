"""Recorder algorithm: bus samples into size-rotated MCAP files (no Zenoh here; see service.py).

Files are named `gd2p-<UTC start time>-<seq>.mcap` (seq from 0000, one start time per recorder run,
so a run's files sort together). A file is written as `<name>.part` and renamed when it is complete
(rotated or closed), so any `*.mcap` in the directory is a finished, readable file.
"""
from __future__ import annotations

import logging
import os
import time
from datetime import datetime, timezone
from pathlib import Path

from shared.recording import McapWriter

log = logging.getLogger("gd2p.recorder")

MIB = 1 << 20
DEFAULT_MAX_FILE_MB = 256.0
PART_SUFFIX = ".part"


class RecorderError(RuntimeError):
    """The recorder cannot write where or how it was asked to."""


class RotatingRecorder:
    """Append samples to MCAP files in `record_dir`, starting a new file past `max_file_bytes`.

    A file closes once its flushed size reaches the limit; since the writer flushes whole zstd
    chunks, a file may exceed the limit by one chunk (chunk size <= limit / 8) plus its MCAP
    summary, which repeats the file's schemas and channels (a few kB per message model).
    """

    def __init__(self, record_dir: str | os.PathLike, max_file_bytes: int = int(DEFAULT_MAX_FILE_MB * MIB), *, started_at: datetime | None = None):
        if max_file_bytes <= 0:
            raise RecorderError(f"max file size must be positive, got {max_file_bytes} bytes")
        self.record_dir = Path(record_dir)
        try:
            self.record_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecorderError(f"cannot create record directory {self.record_dir}: {exc.strerror}") from None
        if not os.access(self.record_dir, os.W_OK):
            raise RecorderError(f"record directory {self.record_dir} is not writable")
        self.max_file_bytes = max_file_bytes
        self.chunk_bytes = max(4096, min(MIB, max_file_bytes // 8))
        stamp = (started_at or datetime.now(timezone.utc)).astimezone(timezone.utc)
        self._prefix = f"gd2p-{stamp.strftime('%Y%m%dT%H%M%SZ')}"
        self._seq = 0
        self._writer: McapWriter | None = None
        self._current: Path | None = None
        self.files: list[Path] = []  # completed files, in order
        self.message_count = 0

    @property
    def current_path(self) -> Path | None:
        """The final name of the file being written (it exists as `<name>.part` until complete)."""
        return self._current

    def record(self, key: str, payload: bytes, encoding: str, log_time_ns: int | None = None, publish_time_ns: int | None = None) -> None:
        """Write one sample; rotates to a new file when the current one is full."""
        writer = self._writer or self._open_next()
        writer.write(key, payload, encoding, time.time_ns() if log_time_ns is None else log_time_ns, publish_time_ns)
        self.message_count += 1
        if writer.bytes_on_disk() >= self.max_file_bytes:
            self._finish_current()

    def close(self) -> list[Path]:
        """Finish the current file; returns every completed file of this recorder."""
        self._finish_current()
        return list(self.files)

    def __enter__(self) -> "RotatingRecorder":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ files
    def _open_next(self) -> McapWriter:
        self._current = self.record_dir / f"{self._prefix}-{self._seq:04d}.mcap"
        self._seq += 1
        self._writer = McapWriter(str(self._part(self._current)), chunk_bytes=self.chunk_bytes)
        log.info("recording to %s", self._current)
        return self._writer

    def _finish_current(self) -> None:
        if self._writer is None or self._current is None:
            return
        self._writer.close()
        os.replace(self._part(self._current), self._current)
        self.files.append(self._current)
        log.info("closed %s (%d messages so far)", self._current, self.message_count)
        self._writer = None
        self._current = None

    @staticmethod
    def _part(path: Path) -> Path:
        return path.with_name(path.name + PART_SUFFIX)
