"""One config layer: settings dataclasses built from YAML mappings, each checking its own ranges.

A settings dataclass states what its values must be in ``__post_init__`` (with :func:`check`), so a
config built in code, read from an experiment file or from a transfer server's file keeps the same
rules and says the same thing.  :func:`from_mapping` builds any of them from a parsed YAML mapping:
unknown keys, wrong types and (through the dataclass) values out of range are one-line ValueErrors
naming the dotted setting.  This module imports nothing of the project, so every layer can use it.
"""

from __future__ import annotations

import dataclasses
import math
import reprlib
import types
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

T = TypeVar("T")
Rule = tuple[Callable[[Any], bool], str]
"""``(ok(value), what it must be)``: a setting's range beyond its type."""

MAX_EVAL_STEPS = 100_000
"""Bound of every step count (offsets, horizons, windows, epochs)."""
SEED_RANGE = (0, 2**32 - 1)


def inline_mapping(text: str, where: str, what: str, example: str, max_chars: int = 4096) -> dict:
    """A short YAML/JSON mapping written on a command line (``example``: one of ``what``), parsed; a one-line
    ValueError naming ``where`` otherwise.  :func:`from_mapping` then builds the settings from it."""
    if len(text) > max_chars:
        raise ValueError(f"{where}: {len(text)} characters; {what} are a short mapping")
    try:
        raw = yaml.safe_load(text)
    except (yaml.YAMLError, ValueError, OverflowError, RecursionError) as err:
        raise ValueError(f"{where}: not a YAML mapping ({' '.join(str(err).split())[:200]})") from None
    if not isinstance(raw, dict):
        raise ValueError(f"{where} must be a mapping of {what} such as '{example}', got {show(text)}")
    return raw


def show(value: Any) -> str:
    """A value for a one-line message: repr, cut short (a hostile file can hold a huge one)."""
    text = reprlib.repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def between(low: float, high: float, low_open: bool = False, high_open: bool = False) -> Rule:
    """A number in ``[low, high]`` (either end open); the message reads ``>= low`` when ``high`` is inf."""
    def ok(v: Any) -> bool:
        return (low < v if low_open else low <= v) and (v < high if high_open else v <= high)
    return ok, (f"{'>' if low_open else '>='} {low}" if math.isinf(high) else
                f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}")


def one_of(choices: Iterable[Any]) -> Rule:
    """A value among ``choices`` (shown as given: a tuple stays a tuple, a mapping its sorted keys)."""
    shown = sorted(choices) if isinstance(choices, Mapping) else choices
    return (lambda v: v in choices), f"one of {shown}"


POSITIVE = between(0, math.inf, low_open=True)
NON_NEGATIVE = between(0, math.inf)
FRACTION = between(0, 1, low_open=True, high_open=True)
STEPS = between(1, MAX_EVAL_STEPS)
SEED = between(*SEED_RANGE)


def check(obj: Any, rules: Mapping[str, Rule]) -> None:
    """ValueError ``<setting> must be <what>, got <value>`` for the first setting of ``obj`` out of its rule.

    Every element of a tuple setting is checked; None (a setting left unset) is not.  A value of a type
    the rule cannot compare (a config built in code with a string for a number) is out of range too.
    """
    for name, (ok, wanted) in rules.items():
        value = getattr(obj, name)
        if value is None:
            continue
        for item in value if isinstance(value, tuple) else (value,):
            try:
                good = bool(ok(item))
            except TypeError:
                good = False
            if not good:
                raise ValueError(f"{name} must be {wanted}, got {show(item)}")


def from_mapping(cls: type[T], data: Any, where: str = "", base: T | None = None) -> T:
    """A (nested) settings dataclass from a YAML mapping; ValueError naming the dotted setting otherwise.

    ``where``: the dotted path of ``data`` in its file, for messages.  Settings not given are ``base``'s
    (an instance of ``cls``) or the defaults; a nested mapping applies on top of that field's current value,
    so ``{l2_finetune: {train: {epochs: 3}}}`` keeps the method's own learning rate.  A class can name other
    bases from the mapping itself with a ``config_bases(values)`` classmethod (an experiment's definition).
    """
    name = getattr(cls, "config_kind", cls.__name__)
    if not isinstance(data, Mapping):
        raise ValueError(f"{where or name} must be a mapping of {cls.__name__} settings, got {show(data)}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(str(k) for k in data if k not in fields)
    if unknown:
        inside = f" in {where}" if where else ""
        raise ValueError(f"unknown {name} settings {show(unknown)}{inside}; known: {sorted(fields)}")
    hints = get_type_hints(cls)
    bases = {key: _current(f, base) for key, f in fields.items()}
    if hasattr(cls, "config_bases"):
        bases.update(cls.config_bases(data))  # type: ignore[attr-defined]
    kwargs = {key: _typed(value, hints[key], _join(where, key), bases.get(key)) for key, value in data.items()}
    try:
        return cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)  # type: ignore[type-var]
    except ValueError as err:  # a range of the dataclass's own: name where it sits
        raise ValueError(_within(where, str(err), fields)) from None


def _current(field: dataclasses.Field, base: Any) -> Any:
    """What a nested mapping for ``field`` applies on top of: ``base``'s value, else the field's default."""
    if base is not None:
        return getattr(base, field.name)
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None


def _join(where: str, key: Any) -> str:
    return f"{where}.{key}" if where else str(key)


def _within(where: str, message: str, fields: Mapping[str, Any]) -> str:
    """``message`` of a dataclass at ``where``: a setting's name gets the dotted path, anything else a prefix."""
    if not where:
        return message
    first = message.split(" ", 1)[0].split("[", 1)[0]
    return f"{where}.{message}" if first in fields else f"{where}: {message}"


_KINDS = {float: "a finite number", int: "an integer", bool: "true or false", str: "a string"}


def _typed(value: Any, hint: Any, where: str, base: Any = None) -> Any:
    """``value`` from YAML checked against a field's annotation (lists become tuples); ValueError otherwise.

    Numbers keep their type (an int for a float setting stays an int): results and cache keys hash the
    settings as given.  A mapping for a settings dataclass applies on top of ``base``, if any.
    """
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (hint,) = [a for a in args if a is not type(None)]
        return _typed(value, hint, where, base)
    if origin is tuple:
        many = len(args) == 2 and args[1] is Ellipsis
        if not isinstance(value, list) or not value or (not many and len(value) != len(args)):
            size = "a non-empty list" if many else f"a list of {len(args)}"
            raise ValueError(f"{where} must be {size}, got {show(value)}")
        hints = args[:1] * len(value) if many else args
        return tuple(_typed(v, h, f"{where}[{i}]") for i, (v, h) in enumerate(zip(value, hints, strict=True)))
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, Mapping):
            raise ValueError(f"{where} must be a mapping of {hint.__name__} settings, got {show(value)}")
        return from_mapping(hint, value, where, base)  # type: ignore[arg-type]
    if hint is Path and isinstance(value, str):
        return Path(value)
    if hint is bool:
        ok = isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif hint is float:  # ints are floats here; NaN and inf never are
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and (
            isinstance(value, int) or math.isfinite(value))
    else:
        ok = isinstance(value, hint)
    if not ok:
        raise ValueError(f"{where} must be {_KINDS.get(hint, hint)}, got {show(value)}")
    return value
