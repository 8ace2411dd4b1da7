"""Shared command-line input checks: numeric argparse types and flag-named pydantic errors.

Numeric types (use as `type=` of `add_argument`). They reject what the value can never be
(nan, inf, out of range) with `argparse.ArgumentTypeError`, so argparse itself prints a usage
error naming the flag and exits with status 2, e.g.

    gd2p generate: error: argument --yaw-deg: must be a finite number, got 'nan'

    finite_float        any finite float
    positive_float      finite and > 0
    non_negative_float  finite and >= 0
    probability         finite and in [0, 1]
    positive_int        integer >= 1
    non_negative_int    integer >= 0
    float_range(lo, hi, lo_open=False, hi_open=False)   a finite float in [lo, hi] (open ends optional)

Flag-named model errors. A command that checks its input against a bus message model (the limits the
services enforce) must report a rejected value by the flag the user typed, not by the model field:

    validate_fields(SampleRequest, {"k": args.n, "seed": args.seed}, {"k": "--n", "seed": "--seed"},
                    command="sample")                     # raises FlagError("gd2p sample: --n: must be <= 1000, got 5000")
    describe_validation_error(exc, flags, command="push")  # the same text from a caught ValidationError

`flags` maps a field name - or a dotted path into a nested model, e.g. "settings.time_step_s" - to
the flag; the longest matching prefix of an error's location wins, and a field with no flag is named
by its dotted path.
"""
from __future__ import annotations

import argparse
import copy
import math
from collections.abc import Callable, Mapping
from functools import cache
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pydantic is imported when a check runs: `gd2p --help` stays fast
    from pydantic import BaseModel, ValidationError


# ============================================================================= argparse types
def finite_float(text: str) -> float:
    """A finite float (argparse type): nan and +-inf are usage errors."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite float > 0 (argparse type)."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite float >= 0 (argparse type)."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def probability(text: str) -> float:
    """A float in [0, 1] (argparse type)."""
    value = finite_float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text!r}")
    return value


def float_range(low: float, high: float, *, low_open: bool = False, high_open: bool = False) -> Callable[[str], float]:
    """An argparse type accepting a finite float in [low, high]; `*_open` excludes that end."""
    interval = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"

    def parse(text: str) -> float:
        value = finite_float(text)
        above = value > low if low_open else value >= low
        below = value < high if high_open else value <= high
        if not (above and below):
            raise argparse.ArgumentTypeError(f"must be in {interval}, got {text!r}")
        return value

    parse.__name__ = f"float in {interval}"
    return parse


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None


def positive_int(text: str) -> int:
    """An integer >= 1 (argparse type)."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An integer >= 0 (argparse type)."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


# ============================================================================= model errors by flag
class FlagError(ValueError):
    """Input a request model rejects, described by flag ("gd2p CMD: --flag: what is wrong", one line per problem)."""


def describe_validation_error(exc: ValidationError, flags: Mapping[str, str], command: str | None = None) -> str:
    """One line per problem of `exc`, naming the flag of each rejected field (see the module docstring)."""
    prefix = f"gd2p {command}: " if command else ""
    lines = [f"{prefix}{_flag_for(error['loc'], flags)}: {_what_is_wrong(error)}" for error in exc.errors(include_url=False)]
    return "\n".join(lines) or f"{prefix}invalid input"


def validate_fields(model: type[BaseModel], values: Mapping[str, Any], flags: Mapping[str, str],
                    command: str | None = None) -> dict[str, Any]:
    """Check `values` against the constraints `model` puts on those fields; FlagError naming flags if any fails.

    Only the given fields are checked (no other field is needed), with the model's own annotations and
    constraints, so a command enforces exactly the limits the service receiving the message enforces.
    Returns the validated (coerced) values.
    """
    from pydantic import ValidationError

    fields_model = _fields_model(model, tuple(sorted(values)))
    try:
        checked = fields_model.model_validate(dict(values))
    except ValidationError as exc:
        raise FlagError(describe_validation_error(exc, flags, command)) from None
    return {name: getattr(checked, name) for name in values}


@cache
def _fields_model(model: type[BaseModel], names: tuple[str, ...]) -> type[BaseModel]:
    from pydantic import create_model

    unknown = [n for n in names if n not in model.model_fields]
    if unknown:
        raise KeyError(f"{model.__name__} has no field(s) {unknown}")
    definitions = {n: (model.model_fields[n].annotation, copy.copy(model.model_fields[n])) for n in names}
    return create_model(f"{model.__name__}Fields", **definitions)  # type: ignore[call-overload]


def _flag_for(location: tuple, flags: Mapping[str, str]) -> str:
    parts = [str(p) for p in location]
    for end in range(len(parts), 0, -1):
        flag = flags.get(".".join(parts[:end]))
        if flag is not None:
            rest = ".".join(parts[end:])
            return f"{flag} ({rest})" if rest else flag
    return ".".join(parts) or "input"


_BOUNDS = {"greater_than": ("gt", ">"), "greater_than_equal": ("ge", ">="), "less_than": ("lt", "<"),
           "less_than_equal": ("le", "<=")}


def _what_is_wrong(error: Mapping[str, Any]) -> str:
    kind, ctx = error.get("type", ""), error.get("ctx") or {}
    got = f", got {error['input']!r}" if "input" in error and kind != "missing" else ""
    if kind in _BOUNDS:
        key, symbol = _BOUNDS[kind]
        return f"must be {symbol} {ctx.get(key)}{got}"
    if kind == "finite_number":
        return f"must be a finite number{got}"
    if kind == "missing":
        return "is required"
    message = str(error.get("msg", "is invalid"))
    if message.startswith("Input should be "):
        message = "must be " + message[len("Input should be "):]
    elif message.startswith("Value error, "):
        message = message[len("Value error, "):]
    return f"{message[:1].lower()}{message[1:]}{got}"
