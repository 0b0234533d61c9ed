"""Parsing reply payloads of the serial line protocol (docs/protocols.md §1)."""

from __future__ import annotations

import math

from drivers.errors import ProtocolError


def parse_fields(device: str, request: str, payload: str, required: tuple[str, ...]) -> dict[str, str]:
    """`key=value key=value` -> dict; missing required keys are a ProtocolError."""
    fields: dict[str, str] = {}
    for token in payload.split():
        key, sep, value = token.partition("=")
        if not sep or not key:
            raise ProtocolError(device, f"reply to {request!r}: expected key=value pairs, got {payload!r}")
        fields[key] = value
    missing = [k for k in required if k not in fields]
    if missing:
        raise ProtocolError(device, f"reply to {request!r} lacks {', '.join(missing)}: {payload!r}")
    return fields


def parse_float(device: str, request: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ProtocolError(device, f"reply to {request!r}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ProtocolError(device, f"reply to {request!r}: {text!r} is not a finite number")
    return value


def parse_floats(device: str, request: str, payload: str, n: int) -> list[float]:
    """A payload of exactly n numbers separated by spaces."""
    parts = payload.split()
    if len(parts) != n:
        raise ProtocolError(device, f"reply to {request!r}: expected {n} numbers, got {payload!r}")
    return [parse_float(device, request, p) for p in parts]
