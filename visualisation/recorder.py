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

What is counted (`SequenceCounts`): publishers of recorded channels number their samples
(shared/bus/recorded.py: `{"publisher": id, "seq": n}` in the Zenoh attachment). Per key and publisher
id the recorder counts the samples it received and the numbers it never got (gaps: `missing`), and
those that came with a number at or below one already seen (`late`: out of order or repeated). A
publisher's first number sets where counting starts (`first_seq` > 1: the recorder heard it only from
there on, e.g. it started later); samples lost after the last one received cannot be seen. Samples
without numbers (the e-stop, the watchdog's beats, a foreign publisher) are counted as received under
publisher "". When a file is closed, its MCAP metadata gets (`METADATA_*`):
- `gd2p.recording`: the run (commit, recorder config, seeds: `run_info`), the file's index, whether it
  is the run's final file, and its received/missing sums;
- `gd2p.counts`: per `<key>#<publisher>` a JSON object {received, missing, late, first_seq, last_seq} of
  the samples this file holds (a gap is counted in the file of the sample after it);
- `gd2p.counts.total` (final file only): the same over the whole run, with the run's sums in
  `gd2p.recording` (`received_total`, `missing_total`).
A run whose last file was rotated full gets one more file holding only this metadata. A recovered
file (its writer died) has no counts: they are written when a file is closed.
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import IO

from visualisation.recording import McapWriter, RecordingError, is_complete_mcap, read_metadata, recover_mcap

log = logging.getLogger("gd2p.recorder")

MIB = 1 << 20
DEFAULT_MAX_FILE_MB = 256.0
PART_SUFFIX = ".part"
UNRECOVERABLE_SUFFIX = ".unrecoverable"
FILE_GLOB = "gd2p-*.mcap"


METADATA_RECORDING = "gd2p.recording"
METADATA_COUNTS = "gd2p.counts"
METADATA_TOTAL = "gd2p.counts.total"


class RecorderError(RuntimeError):
    """The recorder cannot write where or how it was asked to."""


@dataclass
class StreamCount:
    """What the recorder got of one publisher's samples on one key (see the module docstring)."""

    received: int = 0
    missing: int = 0
    late: int = 0
    first_seq: int | None = None
    last_seq: int | None = None


def stream_name(key: str, publisher: str) -> str:
    """`<key>#<publisher>` ('#' is never part of a key expression); publisher "" for unnumbered samples."""
    return f"{key}#{publisher}"


def parse_stream_name(name: str) -> tuple[str, str]:
    key, _, publisher = name.rpartition("#")
    return key, publisher


class SequenceCounts:
    """Received and missing samples per (key, publisher id): for the file being written and for the run."""

    def __init__(self) -> None:
        self.total: dict[tuple[str, str], StreamCount] = {}
        self.file: dict[tuple[str, str], StreamCount] = {}
        self._last: dict[tuple[str, str], int] = {}  # the highest number received per stream, over the run

    def count(self, key: str, sequence: tuple[str, int] | None) -> None:
        """One sample received on `key`, with its (publisher id, number) if it was numbered."""
        publisher, seq = sequence if sequence is not None else ("", None)
        stream = (key, publisher)
        counts = (self.total.setdefault(stream, StreamCount()), self.file.setdefault(stream, StreamCount()))
        gap = late = 0
        if seq is not None:
            last = self._last.get(stream)
            if last is None or seq > last:
                gap = 0 if last is None else seq - last - 1
                self._last[stream] = seq
            else:
                late = 1
        for c in counts:
            c.received += 1
            c.missing += gap
            c.late += late
            if seq is not None:
                c.first_seq = seq if c.first_seq is None else c.first_seq
                c.last_seq = seq if c.last_seq is None else max(c.last_seq, seq)

    def next_file(self) -> None:
        self.file = {}

    @staticmethod
    def as_metadata(counts: Mapping[tuple[str, str], StreamCount]) -> dict[str, str]:
        return {stream_name(key, publisher): json.dumps(asdict(c), sort_keys=True)
                for (key, publisher), c in sorted(counts.items())}

    @staticmethod
    def sums(counts: Mapping[tuple[str, str], StreamCount]) -> tuple[int, int]:
        """(received, missing) over every stream."""
        return sum(c.received for c in counts.values()), sum(c.missing for c in counts.values())


@dataclass(frozen=True)
class Recovered:
    """One unfinished file found at start and what became of it."""

    source: Path  # the unfinished file as found
    path: Path | None  # the finished MCAP now holding its messages (None: nothing to keep, or unrecoverable)
    messages: int
    note: str  # why reading stopped, or what was done


def recover_unfinished(record_dir: str | os.PathLike[str], *, chunk_bytes: int = 1 << 20) -> list[Recovered]:
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


@dataclass(frozen=True)
class RecordedCounts:
    """What a recording's metadata says of itself (`read_counts`)."""

    path: Path
    recording: dict[str, str]  # `gd2p.recording`: commit, config, seeds, file_index, final, sums
    file: dict[tuple[str, str], StreamCount]  # (key, publisher) -> counts of this file's samples
    total: dict[tuple[str, str], StreamCount] | None  # the run's, in its final file only

    @property
    def counted(self) -> bool:
        """False for a file without counts (written before counting existed, or recovered after a crash)."""
        return bool(self.recording)


def _streams(data: Mapping[str, str]) -> dict[tuple[str, str], StreamCount]:
    return {parse_stream_name(name): StreamCount(**json.loads(value)) for name, value in data.items()}


def read_counts(path: str | os.PathLike[str]) -> RecordedCounts:
    """The counts and run facts a recorder wrote into `path`'s metadata (RecordingError if unreadable)."""
    metadata = read_metadata(str(path))
    total = metadata.get(METADATA_TOTAL)
    return RecordedCounts(Path(path), metadata.get(METADATA_RECORDING, {}), _streams(metadata.get(METADATA_COUNTS, {})),
                          None if total is None else _streams(total))


class RotatingRecorder:
    """Append samples to MCAP files in `record_dir`, starting a new file past `max_file_bytes`.

    A file closes once its flushed size reaches the limit; since the writer flushes whole zstd
    chunks, a file may exceed the limit by one chunk (chunk size <= limit / 8) plus its MCAP
    summary, which repeats the file's schemas and channels (a few kB per message model).

    On construction it finalises the unfinished files a dead recorder left in `record_dir`
    (`recover_unfinished`; the result is in `self.recovered`) unless `recover=False`.
    """

    def __init__(self, record_dir: str | os.PathLike[str], max_file_bytes: int = int(DEFAULT_MAX_FILE_MB * MIB), *,
                 started_at: datetime | None = None, recover: bool = True, run_info: Mapping[str, str] | None = None):
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
        self.counts = SequenceCounts()
        self._closed = False
        self.run_info = {"started_utc": stamp.isoformat(), **(run_info or {})}  # commit, config, seeds
        self.recovered: list[Recovered] = recover_unfinished(self.record_dir, chunk_bytes=self.chunk_bytes) if recover else []

    @property
    def current_path(self) -> Path | None:
        """The final name of the file being written (it exists as `<name>.part` until complete)."""
        return self._current

    def record(self, key: str, payload: bytes, encoding: str, log_time_ns: int | None = None,
               publish_time_ns: int | None = None, sequence: tuple[str, int] | None = None) -> None:
        """Write one sample (with its publisher's (id, number), if numbered); rotates when the file is full."""
        if self._closed:
            raise RecorderError("record on a closed recorder")
        writer = self._writer or self._open_next()
        writer.write(key, payload, encoding, time.time_ns() if log_time_ns is None else log_time_ns, publish_time_ns)
        self.message_count += 1
        self.counts.count(key, sequence)
        if writer.bytes_on_disk() >= self.max_file_bytes:
            self._finish_current()

    def close(self) -> list[Path]:
        """Finish the current file with the run's totals (see the module docstring); every completed file."""
        if not self._closed:
            self._closed = True
            if self._writer is None and self.files:  # the last file was rotated full: one more for the totals
                self._open_next()
            self._finish_current(final=True)
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

    def _finish_current(self, final: bool = False) -> None:
        if self._writer is None or self._current is None:
            return
        self._write_metadata(self._writer, final)
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

    def _write_metadata(self, writer: McapWriter, final: bool) -> None:
        counts = self.counts
        received, missing = counts.sums(counts.file)
        recording = {**self.run_info, "file_index": str(len(self.files)), "final": str(final).lower(),
                     "received": str(received), "missing": str(missing)}
        if final:
            received_total, missing_total = counts.sums(counts.total)
            recording |= {"received_total": str(received_total), "missing_total": str(missing_total)}
        writer.add_metadata(METADATA_RECORDING, recording)
        writer.add_metadata(METADATA_COUNTS, counts.as_metadata(counts.file))
        if final:
            writer.add_metadata(METADATA_TOTAL, counts.as_metadata(counts.total))
        if missing:
            log.warning("%s: %d sample(s) missing (gaps in their publishers' numbers)", self._current, missing)
        counts.next_file()

    @staticmethod
    def _part(path: Path) -> Path:
        return path.with_name(path.name + PART_SUFFIX)
