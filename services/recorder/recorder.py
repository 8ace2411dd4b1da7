"""Recorder algorithm: bus samples into size-rotated MCAP files (no Zenoh here; see service.py).

Files are named `gd2p-<UTC start time>-<seq>.mcap` (seq from 0000, one start time per recorder run,
so a run's files sort together; a name already in the directory is skipped). A file is written as
`<name>.part` and renamed when it is complete (rotated or closed), so any `*.mcap` in the directory
is a finished, readable file.

A recorder that dies without closing its file (SIGKILL, OOM kill, power loss) leaves a `.part` with
no MCAP footer. The next recorder on the directory finalises it at start (`recover_unfinished`):
every complete chunk is copied into `<name>.mcap` (see `visualisation.recording.recover_mcap`) and the
`.part` is removed; the log says how many messages were recovered. The writer holds an exclusive
`flock` on its `.part` while it writes, so a recorder starting beside a live one leaves that one's
file alone. A `.part` that is not MCAP at all is renamed `<name>.unrecoverable` and kept.
"""
from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import IO

from visualisation.recording import McapWriter, RecordingError, is_complete_mcap, recover_mcap

log = logging.getLogger("gd2p.recorder")

MIB = 1 << 20
DEFAULT_MAX_FILE_MB = 256.0
PART_SUFFIX = ".part"
UNRECOVERABLE_SUFFIX = ".unrecoverable"
FILE_GLOB = "gd2p-*.mcap"


class RecorderError(RuntimeError):
    """The recorder cannot write where or how it was asked to."""


@dataclass(frozen=True)
class Recovered:
    """One unfinished file found at start and what became of it."""

    source: Path  # the unfinished file as found
    path: Path | None  # the finished MCAP now holding its messages (None: nothing to keep, or unrecoverable)
    messages: int
    note: str  # why reading stopped, or what was done


def recover_unfinished(record_dir: str | os.PathLike, *, chunk_bytes: int = 1 << 20) -> list[Recovered]:
    """Finalise every unfinished recording in `record_dir` (see the module docstring); what was done, per file.

    `<name>.part` files no live writer holds become `<name>.mcap` (or `<name>-recovered.mcap` if that
    name is taken); a `*.mcap` that does not open (no footer) is recovered in place. Files with no
    complete message are removed.
    """
    record_dir = Path(record_dir)
    done: list[Recovered] = []
    for part in sorted(record_dir.glob(FILE_GLOB + PART_SUFFIX)):
        with _exclusive(part) as locked:
            if not locked:
                log.info("leaving %s alone: another recorder is writing it", part)
                continue
            final = part.with_name(part.name[: -len(PART_SUFFIX)])
            if final.exists():
                final = final.with_name(f"{final.stem}-recovered.mcap")
            done.append(_recover_one(part, final, chunk_bytes))
    for path in sorted(record_dir.glob(FILE_GLOB)):
        if not is_complete_mcap(path):
            done.append(_recover_one(path, path, chunk_bytes))
    return done


def _recover_one(source: Path, destination: Path, chunk_bytes: int) -> Recovered:
    try:
        recovery = recover_mcap(source, destination, chunk_bytes=chunk_bytes)
    except OSError as exc:  # e.g. a full disk: keep the file as it is for the next start, and record anyway
        log.error("cannot recover %s now (%s); left as it is", source, exc)
        return Recovered(source, None, 0, f"failed: {exc}")
    except RecordingError as exc:
        kept = source.with_name(source.name + UNRECOVERABLE_SUFFIX)
        try:
            os.replace(source, kept)
        except OSError as move_error:
            log.error("cannot recover %s (%s) nor set it aside (%s)", source, exc, move_error)
            return Recovered(source, None, 0, f"unrecoverable: {exc}")
        log.error("cannot recover %s (%s); kept it as %s", source, exc, kept)
        return Recovered(source, None, 0, f"unrecoverable: {exc}")
    if recovery.messages == 0:
        destination.unlink(missing_ok=True)
        source.unlink(missing_ok=True)
        log.warning("removed unfinished recording %s: it held no complete message", source)
        return Recovered(source, None, 0, "no complete message")
    if source != destination:
        source.unlink()
    note = "complete" if recovery.complete else f"cut ({recovery.stopped_by})"
    log.warning("recovered %d messages on %d channels from unfinished recording %s into %s; reading stopped: %s",
                recovery.messages, recovery.channels, source, destination, note)
    return Recovered(source, destination, recovery.messages, note)


@contextlib.contextmanager
def _exclusive(path: Path) -> Iterator[bool]:
    """Yields True holding an exclusive flock on `path`; False if a live writer holds it or it is gone."""
    try:
        handle = open(path, "rb")
    except FileNotFoundError:  # finished (renamed) meanwhile by its writer
        yield False
        return
    with handle:  # closing it releases the lock
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:  # its writer may have finished (renamed) it between our open and our lock
            same = os.stat(path).st_ino == os.fstat(handle.fileno()).st_ino
        except FileNotFoundError:
            same = False
        yield same


class RotatingRecorder:
    """Append samples to MCAP files in `record_dir`, starting a new file past `max_file_bytes`.

    A file closes once its flushed size reaches the limit; since the writer flushes whole zstd
    chunks, a file may exceed the limit by one chunk (chunk size <= limit / 8) plus its MCAP
    summary, which repeats the file's schemas and channels (a few kB per message model).

    On construction it finalises the unfinished files a dead recorder left in `record_dir`
    (`recover_unfinished`; the result is in `self.recovered`) unless `recover=False`.
    """

    def __init__(self, record_dir: str | os.PathLike, max_file_bytes: int = int(DEFAULT_MAX_FILE_MB * MIB), *,
                 started_at: datetime | None = None, recover: bool = True):
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
        self._stream: IO[bytes] | None = None  # the open `.part`, flock-ed while it is written
        self._current: Path | None = None
        self.files: list[Path] = []  # completed files, in order
        self.message_count = 0
        self.recovered: list[Recovered] = recover_unfinished(self.record_dir, chunk_bytes=self.chunk_bytes) if recover else []

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

    def __enter__(self) -> RotatingRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ files
    def _open_next(self) -> McapWriter:
        while True:  # a recorder restarted within the same second must not overwrite its predecessor's files
            current = self.record_dir / f"{self._prefix}-{self._seq:04d}.mcap"
            self._seq += 1
            if not any(p.exists() for p in (current, self._part(current), current.with_name(f"{current.stem}-recovered.mcap"))):
                break
        stream = open(self._part(current), "wb")
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)  # a new file: nobody else holds it
        self._current, self._stream = current, stream
        self._writer = McapWriter(stream, chunk_bytes=self.chunk_bytes)
        log.info("recording to %s", self._current)
        return self._writer

    def _finish_current(self) -> None:
        if self._writer is None or self._current is None:
            return
        self._writer.close()
        assert self._stream is not None
        try:
            os.replace(self._part(self._current), self._current)  # still locked: no recoverer touches it meanwhile
        finally:
            self._stream.close()
        self.files.append(self._current)
        log.info("closed %s (%d messages so far)", self._current, self.message_count)
        self._writer = None
        self._stream = None
        self._current = None

    @staticmethod
    def _part(path: Path) -> Path:
        return path.with_name(path.name + PART_SUFFIX)
