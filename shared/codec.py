"""msgpack codec for bus messages.

Wire format: the msgpack encoding of `model.model_dump(mode="python")` (bytes stay bytes);
Zenoh encoding string `application/msgpack;<ModelName>`. Any payload that cannot be turned
into the expected model raises `CodecError` with a message naming the problem; services turn
that into an `ErrorReply(code="bad_request")`.
"""
from __future__ import annotations

from typing import TypeVar

import msgpack
from pydantic import ValidationError

from shared.messages import MESSAGE_TYPES, SCHEMA_VERSION, Message

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


def encode(msg: Message) -> tuple[bytes, str]:
    """Return (payload bytes, Zenoh encoding string)."""
    if not isinstance(msg, Message):
        raise CodecError(f"can only encode shared.messages.Message instances, got {type(msg).__name__}")
    return msgpack.packb(msg.model_dump(mode="python"), use_bin_type=True), encoding_for(msg)


def decode(payload: bytes | bytearray | memoryview, encoding: str | None = None, expected: type[M] | None = None) -> M:
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
    try:
        obj = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise CodecError(f"payload is not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise CodecError(f"a {cls.__name__} must be a msgpack map, got {type(obj).__name__}")
    version = obj.get("schema_version", SCHEMA_VERSION)
    if version != SCHEMA_VERSION:
        raise CodecError(f"{cls.__name__} has schema_version {version!r}; this build speaks {SCHEMA_VERSION}")
    try:
        return cls.model_validate(obj)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or '<root>'}: {e['msg']}" for e in exc.errors()[:5])
        raise CodecError(f"invalid {cls.__name__}: {problems}") from None
