"""MCAP files of bus traffic: write samples as they travelled, read them back as records or messages.

File layout (what the recorder writes and `gd2p replay` reads):
- one MCAP channel per (key expression, Zenoh encoding) — in practice one per key; topic = the key;
- bus messages (`application/msgpack;<Model>`): message_encoding "msgpack", schema named after the
  model with its pydantic JSON schema (schema encoding "jsonschema"), so a viewer can show fields;
- anything else (a foreign encoding, or a model this build does not know): the raw payload, no schema;
- every channel's metadata keeps the original Zenoh encoding under "zenoh_encoding", so a replay
  republishes each sample exactly as it was sent;
- zstd-compressed chunks; log_time = receive time, publish_time = the sample's Zenoh timestamp if
  it had one, else the receive time (both ns since the Unix epoch).

A file whose writer died (SIGKILL, power loss) has no summary or footer, and `make_reader` cannot
open it. `recover_mcap` reads such a file front to back, record by record, keeps every complete
chunk (CRC-checked) and writes what it holds as a new, complete MCAP; messages of the torn last
chunk, and those the writer still held in memory, are lost. `is_complete_mcap` tells the two apart.

This module knows nothing of Zenoh sessions; it only moves bytes.
"""
from __future__ import annotations

import contextlib
import itertools
import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from typing import IO, Any

from mcap.decoder import DecoderFactory
from mcap.exceptions import InvalidMagic
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Header, McapRecord, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from shared.atomic import atomic_writer
from shared.contracts.codec import decode, encode, model_name_from_encoding
from shared.contracts.messages import MESSAGE_TYPES, Message

MSGPACK_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
ZENOH_ENCODING_KEY = "zenoh_encoding"
LIBRARY = "gd2p-zenoh"
DEFAULT_CHUNK_BYTES = 1 << 20


class RecordingError(RuntimeError):
    """An MCAP file cannot be read as a gd2p recording (missing, truncated, or not MCAP)."""


@dataclass(frozen=True)
class Record:
    """One recorded sample: where it was published, how it was encoded, and when."""

    key: str
    encoding: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int

    def decode(self) -> Message:
        """The bus message (raises `shared.contracts.codec.CodecError` for a raw / foreign payload)."""
        return decode(self.payload, self.encoding)


@cache
def schema_for(model_name: str) -> bytes | None:
    """The JSON schema of a registered message model, or None if the name is unknown."""
    cls = MESSAGE_TYPES.get(model_name)
    if cls is None:
        return None
    return json.dumps(cls.model_json_schema(), sort_keys=True).encode()


class McapWriter:
    """An MCAP file of bus samples; channels and schemas are registered on first use.

    Use as a context manager or call `close()`: an MCAP file without its footer is incomplete.
    """

    def __init__(self, output: str | os.PathLike[str] | IO[bytes], *, chunk_bytes: int = DEFAULT_CHUNK_BYTES,
                 compress: bool = True):
        self._owns_stream = isinstance(output, (str, os.PathLike))
        self._stream: IO[bytes] = open(output, "wb") if isinstance(output, (str, os.PathLike)) else output
        self._writer = Writer(
            self._stream,
            chunk_size=chunk_bytes,
            compression=CompressionType.ZSTD if compress else CompressionType.NONE,
        )
        self._writer.start(profile="", library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._sequence: dict[int, int] = {}
        self.message_count = 0
        self._closed = False

    # ------------------------------------------------------------------ writing
    def write(self, key: str, payload: bytes, encoding: str, log_time_ns: int | None = None, publish_time_ns: int | None = None) -> None:
        """Append one sample exactly as it travelled on the bus."""
        if self._closed:
            raise RecordingError("write on a closed MCAP writer")
        log_time_ns = time.time_ns() if log_time_ns is None else log_time_ns
        channel_id = self._channel(key, encoding)
        sequence = self._sequence[channel_id] = self._sequence.get(channel_id, -1) + 1
        self._writer.add_message(
            channel_id=channel_id,
            log_time=log_time_ns,
            data=bytes(payload),
            publish_time=log_time_ns if publish_time_ns is None else publish_time_ns,
            sequence=sequence,
        )
        self.message_count += 1

    def write_message(self, key: str, msg: Message, log_time_ns: int | None = None) -> None:
        """Encode a bus message with the codec and append it."""
        payload, encoding = encode(msg)
        self.write(key, payload, encoding, log_time_ns)

    def write_foreign(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes,
                      message_encoding: str, data: bytes, log_time_ns: int) -> None:
        """Append a message of a non-bus schema (e.g. a Foxglove protobuf schema, for viewers)."""
        if self._closed:
            raise RecordingError("write on a closed MCAP writer")
        channel_id = self._channels.get((topic, message_encoding))
        if channel_id is None:
            schema_id = self._schemas.get(schema_name)
            if schema_id is None:
                schema_id = self._schemas[schema_name] = self._writer.register_schema(
                    name=schema_name, encoding=schema_encoding, data=schema_data)
            channel_id = self._channels[(topic, message_encoding)] = self._writer.register_channel(
                topic=topic, message_encoding=message_encoding, schema_id=schema_id)
        sequence = self._sequence[channel_id] = self._sequence.get(channel_id, -1) + 1
        self._writer.add_message(channel_id=channel_id, log_time=log_time_ns, data=bytes(data),
                                 publish_time=log_time_ns, sequence=sequence)
        self.message_count += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Append an MCAP metadata record (a named map of strings, indexed in the summary)."""
        if self._closed:
            raise RecordingError("metadata on a closed MCAP writer")
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def bytes_on_disk(self) -> int:
        """Bytes flushed to the file so far (buffered chunk data not yet included)."""
        return self._stream.tell()

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._writer.finish()
        self._stream.flush()
        if self._owns_stream:
            self._stream.close()

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ registration
    def _channel(self, key: str, encoding: str) -> int:
        channel_id = self._channels.get((key, encoding))
        if channel_id is None:
            model = model_name_from_encoding(encoding)
            schema_data = schema_for(model) if model else None
            schema_id = self._schema(model, schema_data) if model and schema_data is not None else 0
            channel_id = self._writer.register_channel(
                topic=key,
                message_encoding=MSGPACK_ENCODING if schema_id else encoding or "application/octet-stream",
                schema_id=schema_id,
                metadata={ZENOH_ENCODING_KEY: encoding},
            )
            self._channels[(key, encoding)] = channel_id
        return channel_id

    def _schema(self, model: str, data: bytes) -> int:
        schema_id = self._schemas.get(model)
        if schema_id is None:
            schema_id = self._schemas[model] = self._writer.register_schema(name=model, encoding=SCHEMA_ENCODING, data=data)
        return schema_id


@contextlib.contextmanager
def _mcap_reader(path: str) -> Iterator[Any]:
    """An mcap reader of `path`; RecordingError for a file that cannot be opened or read as MCAP."""
    try:
        stream = open(path, "rb")
    except OSError as exc:
        raise RecordingError(f"cannot open recording {path}: {exc.strerror}") from None
    with stream:
        try:
            yield make_reader(stream)
        except RecordingError:
            raise
        except Exception as exc:  # the mcap package raises several unrelated types on a bad file
            raise RecordingError(f"{path} is not a readable MCAP file ({type(exc).__name__}: {exc})") from None


def read_metadata(path: str) -> dict[str, dict[str, str]]:
    """The metadata records of a recording by name (a name written twice: the last one)."""
    with _mcap_reader(path) as reader:
        return {record.name: dict(record.metadata) for record in reader.iter_metadata()}


def read_records(path: str) -> Iterator[Record]:
    """Every sample of an MCAP recording in log-time order."""
    with _mcap_reader(path) as reader:
        for _schema, channel, message in reader.iter_messages(log_time_order=True):
            yield Record(
                key=channel.topic,
                encoding=channel.metadata.get(ZENOH_ENCODING_KEY, channel.message_encoding),
                payload=message.data,
                log_time_ns=message.log_time,
                publish_time_ns=message.publish_time,
            )


# ----------------------------------------------------------------------------- recovery
@dataclass(frozen=True)
class Recovery:
    """What `recover_mcap` kept of a file: messages, channels, and why reading stopped."""

    messages: int
    channels: int
    complete: bool  # the source had its footer (nothing was lost)
    stopped_by: str | None  # the error that ended the read of a cut file, None if complete


class _ExactReads:
    """A file whose `read(n)` returns exactly n bytes or raises: a cut record is an error, never short data."""

    def __init__(self, stream: IO[bytes]):
        self._stream = stream

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        if size is not None and size >= 0 and len(data) != size:
            raise EOFError(f"file ends inside a record (wanted {size} bytes, {len(data)} left)")
        return data


def is_complete_mcap(path: str | os.PathLike[str]) -> bool:
    """True if the file opens with `make_reader` (magic, footer and summary all readable)."""
    try:
        with open(path, "rb") as stream:
            make_reader(stream).get_summary()
    except Exception:  # the mcap package raises several unrelated types on a bad file
        return False
    return True


def recover_mcap(source: str | os.PathLike[str], destination: str | os.PathLike[str], *,
                 chunk_bytes: int = DEFAULT_CHUNK_BYTES) -> Recovery:
    """Copy every complete record of a (possibly cut) MCAP file into a new, complete MCAP file.

    Reads `source` sequentially without its summary; reading stops at the first record that is cut
    or fails its CRC. Schemas, channels (with their metadata), messages (times, sequence numbers),
    metadata and attachments keep their content; the header's profile and library are kept. The
    destination is written to a temporary file, fsynced and renamed, so it is whole or absent.
    A file cut before its first record gives an empty recording. Raises RecordingError if `source`
    cannot be opened or does not start with the MCAP magic.
    """
    try:
        stream = open(source, "rb")
    except OSError as exc:
        raise RecordingError(f"cannot open recording {source}: {exc.strerror}") from None
    with stream:
        records = StreamReader(_ExactReads(stream), validate_crcs=True).records  # type: ignore[arg-type]
        first: McapRecord | None = None
        try:
            first = next(records)
        except (EOFError, StopIteration):  # cut before its first record: an empty recording
            records = iter(())
        except InvalidMagic as exc:
            raise RecordingError(f"{source} is not an MCAP file ({exc})") from None
        except Exception as exc:
            raise RecordingError(f"{source}: no readable MCAP record ({type(exc).__name__}: {exc})") from None
        header = first if isinstance(first, Header) else Header(profile="", library=LIBRARY)
        with atomic_writer(destination, "wb", durable=True) as out:
            writer = Writer(out, chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
            writer.start(profile=header.profile, library=header.library)
            schema_ids: dict[int, int] = {0: 0}
            channel_ids: dict[int, int] = {}
            messages = 0
            stopped_by: str | None = None
            records = itertools.chain([] if first is None or isinstance(first, Header) else [first], records)
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    break
                except Exception as exc:  # a cut or corrupt record: everything before it is kept
                    stopped_by = f"{type(exc).__name__}: {exc}"
                    break
                if isinstance(record, Schema):
                    if record.id not in schema_ids:
                        schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel):
                    if record.id not in channel_ids and record.schema_id in schema_ids:
                        channel_ids[record.id] = writer.register_channel(
                            record.topic, record.message_encoding, schema_ids[record.schema_id], dict(record.metadata))
                elif isinstance(record, McapMessage):
                    channel = channel_ids.get(record.channel_id)
                    if channel is not None:
                        writer.add_message(channel, record.log_time, record.data, record.publish_time, record.sequence)
                        messages += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
                elif isinstance(record, Attachment):
                    writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
            writer.finish()
    return Recovery(messages=messages, channels=len(channel_ids), complete=stopped_by is None, stopped_by=stopped_by)


class MessageDecoderFactory(DecoderFactory):
    """Lets `mcap`'s `iter_decoded_messages` turn msgpack channels back into bus messages."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        if message_encoding != MSGPACK_ENCODING or schema is None or schema.name not in MESSAGE_TYPES:
            return None
        cls = MESSAGE_TYPES[schema.name]
        return lambda data: decode(data, expected=cls)


def replay(
    records: Iterator[Record],
    publish: Callable[[Record], None],
    rate: float = 1.0,
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> int:
    """Publish records with their recorded spacing divided by `rate` (0 = as fast as possible).

    Returns the number of records published.
    """
    if rate < 0:
        raise ValueError(f"replay rate must be >= 0, got {rate}")
    start_wall: float | None = None
    start_log_ns = 0
    count = 0
    for record in records:
        if start_wall is None:
            start_wall, start_log_ns = clock(), record.log_time_ns
        elif rate > 0:
            delay = start_wall + (record.log_time_ns - start_log_ns) / 1e9 / rate - clock()
            if delay > 0:
                sleep(delay)
        publish(record)
        count += 1
    return count
