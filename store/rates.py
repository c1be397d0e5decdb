"""The rate vocabulary: parsing ``RATES`` specs, checking rate lists, naming and finding rates.

Rates are rainfall intensities in millimetres per hour (mm/h). Shards store them as float32
(``/rates``); everywhere in rainbench a rate is identified by its **decimal**: the shortest
decimal that reads back as the stored value (:func:`rate_decimal`, ``12.5`` for float32 12.5,
``0.1`` for float32 0.1). :func:`rate_token` names files and folders by it (``rate_0.1``), and
:func:`rate_rows` finds a rate the user wrote (``"0.1"``, ``0.1``) in a shard's ``/rates``
by comparing decimals, whatever the storage dtype.

Every refusal of a spec raises :class:`RatesError` with a single-line message that starts with
``RATES`` and quotes the spec.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from decimal import Decimal, InvalidOperation

import numpy as np

MAX_RATE_MM_H = 1000.0
"""Largest accepted rain rate in mm/h (the world record hourly rainfall is about 300 mm/h)."""

MAX_RATE_COUNT = 1001
"""Largest number of rates a spec may expand to (``"0:1000:1"`` is the largest sensible sweep)."""

_RANGE_EPS = 1e-9
"""Relative slack for the inclusive end of ``start:stop:step`` (so ``0:1:0.1`` gives 11 values)."""

_DECIMALS = 10
"""Range values are rounded to this many decimals so that ``0:1:0.1`` gives 0.3, not 0.30000000000000004."""


class RatesError(ValueError):
    """A rain-rate specification was refused. The message is one line starting with ``RATES``."""


def _fail(spec: str, reason: str) -> RatesError:
    quoted = json.dumps(spec)  # double-quoted, escapes newlines: the message stays on one line
    return RatesError(f"RATES {quoted}: {reason}")


def _parse_number(spec: str, text: str, what: str) -> float:
    stripped = text.strip()
    if not stripped:
        raise _fail(spec, f"empty {what}; expected a number in mm/h")
    try:
        value = float(stripped)
    except ValueError:
        raise _fail(spec, f"{what} {json.dumps(stripped)} is not a number; expected e.g. 0:100:10, 0,25,50 or 50") from None
    if not math.isfinite(value):
        raise _fail(spec, f"{what} {json.dumps(stripped)} is not finite; expected a finite number in mm/h")
    return value + 0.0  # turns -0.0 into 0.0


def _check_rate(spec: str, value: float, what: str) -> None:
    if value < 0.0:
        raise _fail(spec, f"{what} {value:g} is negative; expected rates in [0, {MAX_RATE_MM_H:g}] mm/h")
    if value > MAX_RATE_MM_H:
        raise _fail(spec, f"{what} {value:g} exceeds {MAX_RATE_MM_H:g} mm/h; expected rates in [0, {MAX_RATE_MM_H:g}] mm/h")


def _storage_problem(values: Sequence[float]) -> str | None:
    """Why ascending distinct ``values`` cannot be a shard's ``/rates`` (float32), or None: two
    that float32 does not tell apart, or a rate > 0 that it stores as 0 (a rainy row read back
    as the clean one)."""
    stored = np.asarray(values, dtype=np.float64).astype(np.float32)
    for value, single in zip(values, stored):
        if value > 0.0 and single == 0.0:
            return f"rate {value:g} is stored as 0 (shards hold rates as float32); expected 0 or a rate above 1e-45 mm/h (the smallest float32)"
    for index in range(len(values) - 1):
        if stored[index] == stored[index + 1]:
            return (f"rates {values[index]!r} and {values[index + 1]!r} are the same once stored as float32 "
                    "(a shard's /rates); expected rates that differ in float32")
    return None


def parse_rates(spec: str) -> tuple[float, ...]:
    """Parse a rain-rate spec into an ascending tuple of rates in mm/h.

    Accepted forms:

    * ``"start:stop:step"`` -- inclusive range, e.g. ``"0:100:10"`` -> ``(0.0, 10.0, ..., 100.0)``.
      The count is ``floor(s + 1e-9 max(1, s)) + 1`` with ``s = (stop - start) / step`` (a
      relative slack), so ``"0:1:0.1"`` gives 11 values; values are rounded to 10 decimals and
      the last is at most ``stop``.
    * ``"a,b,c"`` -- explicit list, returned sorted ascending; duplicates are refused.
    * ``"r"`` -- a single rate.

    Every rate must be finite and in ``[0, 1000]`` mm/h; a range needs ``step > 0`` and
    ``stop >= start``; at most 1001 rates; the rates must stay distinct, and a rate > 0 above 0,
    in float32 (a shard's ``/rates``).

    Args:
        spec: the text to parse.

    Returns:
        tuple of float rates in mm/h, strictly ascending, at least one element.

    Raises:
        RatesError: one-line message starting with ``RATES "<spec>":`` saying what was wrong.
    """
    if not isinstance(spec, str):
        raise RatesError(f"RATES {json.dumps(repr(spec))}: expected a string such as 0:100:10, got {type(spec).__name__}")
    text = spec.strip()
    if not text:
        raise _fail(spec, "empty spec; expected e.g. 0:100:10, 0,25,50 or 50")

    if ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise _fail(spec, f"a range needs exactly start:stop:step (3 fields), got {len(parts)} fields")
        start = _parse_number(spec, parts[0], "start")
        stop = _parse_number(spec, parts[1], "stop")
        step = _parse_number(spec, parts[2], "step")
        _check_rate(spec, start, "start")
        _check_rate(spec, stop, "stop")
        if step <= 0.0:
            raise _fail(spec, f"step {step:g} must be > 0")
        if stop < start:
            raise _fail(spec, f"stop {stop:g} is below start {start:g}; expected start <= stop")
        span = (stop - start) / step
        if span + 1 > MAX_RATE_COUNT:
            count_text = f"{math.floor(span) + 1}" if math.isfinite(span) else "more than 10^308"
            raise _fail(spec, f"expands to {count_text} rates; at most {MAX_RATE_COUNT} are allowed")
        count = math.floor(span + _RANGE_EPS * max(1.0, span)) + 1
        values = tuple(min(round(start + index * step, _DECIMALS), stop) + 0.0 for index in range(count))
        if any(lower >= upper for lower, upper in zip(values, values[1:])):
            raise _fail(spec, f"step {step:g} is finer than the {10.0 ** -_DECIMALS:g} mm/h "
                              "resolution of a range: its rates would repeat")
        return _storable(spec, values)

    if "," in text:
        values_list = [_parse_number(spec, part, f"item {index + 1}") for index, part in enumerate(text.split(","))]
        for index, value in enumerate(values_list):
            _check_rate(spec, value, f"item {index + 1}")
        ordered = sorted(values_list)
        for lower, upper in zip(ordered, ordered[1:]):
            if lower == upper:
                raise _fail(spec, f"rate {lower:g} is listed twice; expected distinct rates")
        if len(ordered) > MAX_RATE_COUNT:
            raise _fail(spec, f"lists {len(ordered)} rates; at most {MAX_RATE_COUNT} are allowed")
        return _storable(spec, tuple(ordered))

    value = _parse_number(spec, text, "rate")
    _check_rate(spec, value, "rate")
    return _storable(spec, (value,))


def _storable(spec: str, values: tuple[float, ...]) -> tuple[float, ...]:
    problem = _storage_problem(values)
    if problem is not None:
        raise _fail(spec, problem)
    return values


def check_rate_list(rates, what: str = "rates") -> tuple[float, ...]:
    """``rates`` as a tuple of floats if it is a non-empty, strictly ascending sequence of finite
    rates in ``[0, 1000]`` mm/h; otherwise a one-line ``ValueError`` naming ``what``. The one
    check of a rate list that code (not a RATES spec) hands over: configs, writers, readers."""
    if isinstance(rates, (str, bytes)) or not isinstance(rates, (Sequence, np.ndarray)):
        raise ValueError(f"{what}: expected a sequence of rates in mm/h, got {type(rates).__name__}")
    try:
        values = tuple(float(rate) for rate in rates)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected numbers in mm/h, got {list(rates)!r:.80}") from None
    if not values or not all(math.isfinite(v) and 0.0 <= v <= MAX_RATE_MM_H for v in values) \
            or any(lower >= upper for lower, upper in zip(values, values[1:])):
        raise ValueError(f"{what}: expected ascending distinct values in [0, {MAX_RATE_MM_H:g}] "
                         f"mm/h, got {tuple(rates)!r:.80}")
    problem = _storage_problem(values)
    if problem is not None:
        raise ValueError(f"{what}: {problem}")
    return values


def rate_decimal(rate) -> Decimal:
    """The decimal a rate stands for: a ``Decimal`` itself; a ``str`` as written (``"12.50"`` -> 12.5); a numpy
    float the shortest decimal that reads back as it in its own dtype (float32 0.1 -> 0.1); a
    Python number its shortest repr, or its shortest float32 decimal when it is exactly a
    float32 value (a rate read from a shard: 0.10000000149011612 -> 0.1). Raises
    ``ValueError`` for what is not a finite rate >= 0."""
    try:
        if isinstance(rate, Decimal):
            value = rate
        elif isinstance(rate, str):
            value = Decimal(rate.strip())
        elif isinstance(rate, np.floating):
            value = Decimal(np.format_float_positional(rate, unique=True, trim="-"))
        elif isinstance(rate, (int, float, np.integer)) and not isinstance(rate, bool):
            number = float(rate)
            single = np.float32(number) if abs(number) < 3e38 else None
            value = (Decimal(np.format_float_positional(single, unique=True, trim="-"))
                     if single is not None and float(single) == number else Decimal(repr(number)))
        else:
            raise InvalidOperation
    except (InvalidOperation, ValueError, OverflowError):
        raise ValueError(f"rate: expected a number in mm/h, got {rate!r}") from None
    if not value.is_finite() or value < 0:
        raise ValueError(f"rate: expected a finite rate >= 0 mm/h, got {rate!r}")
    return value.normalize() if value else Decimal(0)


def rate_token(rate) -> str:
    """Name of a rate in file and folder names (``rate_<token>``): its shortest float32
    decimal, as shards store rates: 0 -> "0", 12.5 -> "12.5", 100 -> "100", 0.1 -> "0.1"."""
    return format(rate_decimal(np.float32(float(rate_decimal(rate)))), "f")


class MissingRate(LookupError):
    """A rate that a shard's ``/rates`` does not hold: ``rate`` (its decimal), ``have`` (the
    stored rates' decimals)."""

    def __init__(self, rate: Decimal, have: Sequence[Decimal]) -> None:
        self.rate, self.have = rate, tuple(have)
        super().__init__(f"has no rate {format(rate, 'f')} mm/h (it has "
                         f"{', '.join(format(d, 'f') for d in self.have)})")


def rate_rows(stored: np.ndarray, wanted) -> list[int]:
    """Rows of ``stored`` (a shard's ``/rates``) holding each rate of ``wanted``, in that
    order: a rate matches the stored value whose decimal (:func:`rate_decimal`) is its own.
    A rate that is not there raises :class:`MissingRate`."""
    decimals = [rate_decimal(value) for value in stored]
    rows = []
    for rate in wanted:
        decimal = rate_decimal(rate)
        matches = [row for row, stored_decimal in enumerate(decimals) if stored_decimal == decimal]
        if not matches:
            raise MissingRate(decimal, decimals)
        rows.append(matches[0])
    return rows
