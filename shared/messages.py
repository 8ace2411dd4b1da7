"""Message contracts: every payload the system exchanges over Zenoh is one of these models.

Conventions
- Each message has `schema_version` (bumped on an incompatible change) and an `id`
  (request / job id; the dispatcher deduplicates on it, so ids make jobs idempotent).
- Arrays travel as `NDArray` (dtype + shape + raw little-endian bytes), never as lists.
- Every model is registered by class name in `MESSAGE_TYPES`; the codec looks types up there.
"""
from __future__ import annotations

import uuid
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

SCHEMA_VERSION = 1

MESSAGE_TYPES: dict[str, type["Message"]] = {}


def new_id() -> str:
    return uuid.uuid4().hex


class Message(BaseModel):
    """Base of every bus message."""

    model_config = ConfigDict(extra="forbid", frozen=False)
    schema_version: int = SCHEMA_VERSION
    id: str = Field(default_factory=new_id, min_length=1, max_length=128)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        MESSAGE_TYPES[cls.__name__] = cls


_ALLOWED_DTYPES = {"float32", "float64", "int32", "int64", "uint8", "uint16", "uint32", "int8", "int16", "bool"}


class NDArray(BaseModel):
    """A numpy array as dtype + shape + little-endian bytes."""

    model_config = ConfigDict(extra="forbid")
    dtype: str
    shape: list[int]
    data: bytes

    @field_validator("dtype")
    @classmethod
    def _known_dtype(cls, v: str) -> str:
        if v not in _ALLOWED_DTYPES:
            raise ValueError(f"unsupported array dtype {v!r}; allowed: {sorted(_ALLOWED_DTYPES)}")
        return v

    @model_validator(mode="after")
    def _size_matches(self) -> "NDArray":
        if any(d < 0 for d in self.shape):
            raise ValueError(f"negative dimension in shape {self.shape}")
        expected = int(np.prod(self.shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize
        if expected != len(self.data):
            raise ValueError(f"array of shape {self.shape} and dtype {self.dtype} needs {expected} bytes, got {len(self.data)}")
        return self

    @classmethod
    def from_numpy(cls, a: np.ndarray) -> "NDArray":
        a = np.asarray(a)
        dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
        a = np.ascontiguousarray(a, dtype=dt)
        return cls(dtype=a.dtype.name, shape=list(a.shape), data=a.tobytes())

    def to_numpy(self) -> np.ndarray:
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype).newbyteorder("<")).reshape(self.shape).copy()


class ErrorReply(Message):
    """What a service answers instead of a result when a request cannot be served.

    `code` is machine-readable: bad_request (malformed / unknown payload), not_implemented,
    infeasible, internal, timeout, unavailable.
    """

    code: str
    message: str
    request_type: str | None = None
    service: str | None = None

    CODES: ClassVar[tuple[str, ...]] = ("bad_request", "not_implemented", "infeasible", "internal", "timeout", "unavailable")


class HealthQuery(Message):
    """Ask a worker how it is."""


class WorkerStatus(Message):
    """A worker's answer to a health query (and what `gd2p status` aggregates)."""

    service: str
    worker_id: str
    pid: int
    host: str
    state: str = "ready"  # ready | busy | stopping
    in_flight: int = 0
    jobs_done: int = 0
    jobs_failed: int = 0
    uptime_s: float = 0.0
    capabilities: list[str] = Field(default_factory=list)
