"""msgpack codec for bus messages.

Wire format: the msgpack encoding of `model.model_dump(mode="python")` (bytes stay bytes);
Zenoh encoding string `application/msgpack;<ModelName>`. Any payload that cannot be turned
into the expected model raises `CodecError` with a message naming the problem; services turn
that into an `ErrorReply(code="bad_request")`.

Size bound: a payload larger than its type's `MAX_PAYLOAD_BYTES` (shared/contracts/messages.py) is refused
before it is unpacked; `check_payload_size` lets a receiver refuse it before even copying it.
"""
from __future__ import annotations

from typing import TypeVar, overload

import msgpack
from pydantic import ValidationError

from shared.contracts.messages import DEFAULT_MAX_PAYLOAD_BYTES, MESSAGE_TYPES, ErrorReply, Message

ENCODING_PREFIX = "application/msgpack;"
M = TypeVar("M", bound=Message)


class CodecError(ValueError):
    """A payload could not be decoded into a known message."""


def encoding_for(model: type[Message] | Message) -> str:
    cls = model if isinstance(model, type) else type(model)
    return ENCODING_PREFIX + cls.__name__


def model_name_from_encoding(encoding: str | None) -> str | None:
    if not encoding:
        return None
    encoding = str(encoding)
    if not encoding.startswith(ENCODING_PREFIX):
        return None
    return encoding[len(ENCODING_PREFIX):] or None


def payload_limit(encoding: str | None, expected: type[Message] | None = None) -> int:
    """The most bytes a payload of this encoding (else of `expected`) may have."""
    cls = MESSAGE_TYPES.get(model_name_from_encoding(encoding) or "") or expected
    return cls.MAX_PAYLOAD_BYTES if cls is not None else DEFAULT_MAX_PAYLOAD_BYTES


def check_payload_size(size: int, encoding: str | None, expected: type[Message] | None = None) -> None:
    """Raise CodecError naming the size and the limit when a payload is too large to accept."""
    limit = payload_limit(encoding, expected)
    if size > limit:
        what = model_name_from_encoding(encoding) or (expected.__name__ if expected else "message")
        raise CodecError(f"{what} payload of {size} bytes exceeds the limit of {limit} bytes ({limit / 2**20:g} MiB)")


def encode(msg: Message) -> tuple[bytes, str]:
    """Return (payload bytes, Zenoh encoding string)."""
    if not isinstance(msg, Message):
        raise CodecError(f"can only encode shared.contracts.messages.Message instances, got {type(msg).__name__}")
    payload: bytes = msgpack.packb(msg.model_dump(mode="python"), use_bin_type=True)
    return payload, encoding_for(msg)


@overload
def decode(payload: bytes | bytearray | memoryview, encoding: str | None = None, expected: None = None) -> Message: ...
@overload
def decode(payload: bytes | bytearray | memoryview, encoding: str | None, expected: type[M]) -> M | ErrorReply: ...
@overload
def decode(payload: bytes | bytearray | memoryview, *, expected: type[M]) -> M | ErrorReply: ...
def decode(payload: bytes | bytearray | memoryview, encoding: str | None = None,
           expected: type[Message] | None = None) -> Message:
    """Decode a payload into a message.

    The model is taken from the encoding string, else from `expected`. If both are given they
    must agree (an `ErrorReply` is always accepted, so a caller sees the remote error).
    """
    name = model_name_from_encoding(encoding)
    if name is None and encoding and not str(encoding).startswith(ENCODING_PREFIX) and expected is None:
        raise CodecError(f"unsupported encoding {encoding!r}: expected '{ENCODING_PREFIX}<Model>'")
    if name is not None:
        cls = MESSAGE_TYPES.get(name)
        if cls is None:
            raise CodecError(f"unknown message type {name!r}")
        if expected is not None and cls is not expected and name != "ErrorReply":
            raise CodecError(f"expected a {expected.__name__} but the payload is a {name}")
    elif expected is not None:
        cls = expected
    else:
        raise CodecError("cannot decode: no message type in the encoding and none expected")
    check_payload_size(len(payload), encoding, cls)
    try:
        obj = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise CodecError(f"payload is not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise CodecError(f"a {cls.__name__} must be a msgpack map, got {type(obj).__name__}")
    version = obj.get("schema_version", cls.wire_schema())
    if version != cls.wire_schema():
        change = f": {cls.SCHEMA_CHANGE}" if cls.SCHEMA_CHANGE else ""
        raise CodecError(f"{cls.__name__} has schema_version {version!r}; this build speaks {cls.wire_schema()}{change}")
    try:
        return cls.model_validate(obj)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or '<root>'}: {e['msg']}" for e in exc.errors()[:5])
        raise CodecError(f"invalid {cls.__name__}: {problems}") from None
