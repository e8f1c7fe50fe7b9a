"""Declared ranges of config fields, checked on construction, on load and after CLI overrides.

Each config dataclass declares one checker per field next to its definition (a dict passed to
:func:`check_fields` from its ``__post_init__``); the same checker gives ``--help`` its
"[range: ...]" text. A checker takes the value and returns it normalised (an int given for a
float becomes a float, a JSON list a tuple) or raises :class:`ConfigError` naming the option,
the rule and the value:

    option train.lr: must be a finite number > 0, got -1.0
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Callable


class ConfigError(ValueError):
    """A config value outside its declared range. ``option`` is the dotted name once known."""

    def __init__(self, option: str, rule: str, value: Any):
        self.option, self.rule, self.value = option, rule, value
        super().__init__(f"option {option}: must be {rule}, got {value!r}")

    def prefixed(self, prefix: str) -> "ConfigError":
        return ConfigError(prefix + self.option, self.rule, self.value)


@dataclasses.dataclass(frozen=True)
class Checker:
    """``rule``: the range in words (shown in --help and in errors); ``convert``: value ->
    normalised value, raising ValueError/TypeError when the value is outside the rule."""

    rule: str
    convert: Callable[[Any], Any]

    def __call__(self, value: Any) -> Any:
        try:
            return self.convert(value)
        except (TypeError, ValueError, OverflowError) as exc:
            raise ValueError(self.rule) from exc


def _bound_text(lo, hi, lo_open: bool, hi_open: bool) -> str:
    def fmt(v) -> str:
        return str(v) if isinstance(v, int) else f"{v:g}"

    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {fmt(lo)}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {fmt(hi)}")
    return " and ".join(parts)


def _in_bounds(v, lo, hi, lo_open, hi_open) -> bool:
    if lo is not None and (v <= lo if lo_open else v < lo):
        return False
    if hi is not None and (v >= hi if hi_open else v > hi):
        return False
    return True


def integer(lo: int | None = None, hi: int | None = None) -> Checker:
    """An int (not a bool) in [lo, hi]."""
    bounds = _bound_text(lo, hi, False, False)
    rule = "an integer" + (f" {bounds}" if bounds else "")

    def convert(v):
        if isinstance(v, bool) or not isinstance(v, int) or not _in_bounds(v, lo, hi, False, False):
            raise ValueError
        return v
    return Checker(rule, convert)


def real(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
         optional: bool = False) -> Checker:
    """A finite number in the interval (open ends with ``lo_open``/``hi_open``); None allowed when ``optional``."""
    bounds = _bound_text(lo, hi, lo_open, hi_open)
    rule = "a finite number" + (f" {bounds}" if bounds else "") + (" or None" if optional else "")

    def convert(v):
        if v is None and optional:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError
        v = float(v)
        if not math.isfinite(v) or not _in_bounds(v, lo, hi, lo_open, hi_open):
            raise ValueError
        return v
    return Checker(rule, convert)


def choice(*values: str) -> Checker:
    rule = "one of " + ", ".join(repr(v) for v in values)

    def convert(v):
        if not isinstance(v, str) or v not in values:
            raise ValueError
        return v
    return Checker(rule, convert)


def boolean() -> Checker:
    def convert(v):
        if not isinstance(v, bool):
            raise ValueError
        return v
    return Checker("true or false", convert)


def text(*, pattern_rule: str = "a string", accept: Callable[[str], bool] = lambda s: True) -> Checker:
    def convert(v):
        if not isinstance(v, str) or not accept(v):
            raise ValueError
        return v
    return Checker(pattern_rule, convert)


def colour_or_none() -> Checker:
    """None or three finite numbers in [0, 1] (an RGB colour)."""
    def convert(v):
        if v is None:
            return None
        if isinstance(v, (str, bytes)):
            raise ValueError
        values = list(v)
        if len(values) != 3 or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in values):
            raise ValueError
        out = tuple(float(c) for c in values)
        if not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in out):
            raise ValueError
        return out
    return Checker("None or three numbers in [0, 1] (r,g,b)", convert)


def default_checker(hint: Any) -> Checker | None:
    """The type-only checker of a field without a declared range (a field added later still gets
    its type checked): bool, int, float, str or a Literal of strings."""
    if hint is bool:
        return boolean()
    if hint is int:
        return integer()
    if hint is float:
        return real()
    if hint is str:
        return text()
    if typing.get_origin(hint) is typing.Literal:
        return choice(*typing.get_args(hint))
    return None


def check_fields(obj: Any, checks: dict[str, Checker], prefix: str = "") -> None:
    """Normalise every field of dataclass ``obj`` with its checker (in place); raise ConfigError
    naming ``prefix + field`` for the first bad value. Fields without a declared checker get
    the type-only one of :func:`default_checker`."""
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            continue
        checker = checks.get(f.name) or default_checker(hints.get(f.name))
        if checker is None:
            continue
        try:
            object.__setattr__(obj, f.name, checker(value))
        except ValueError:
            raise ConfigError(prefix + f.name, checker.rule, value) from None
