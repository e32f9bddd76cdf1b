"""What a setting may be. Each field of config.py declares its rule beside its default
(``n_features: Annotated[int, at_least(1)] = 1000``); :func:`checked` holds a value from a
TOML file or a flag to the field's type and rule. A bool needs no rule: its type is all."""

from __future__ import annotations

import math
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any


@dataclass(frozen=True)
class Bound:
    """A finite number (each number of a tuple) within lo..hi; None: no bound that side."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False  # lo itself is not allowed
    hi_open: bool = False

    def problem(self, x: float) -> str | None:
        if not math.isfinite(x):
            return "must be a finite number"
        low = self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo)
        high = self.hi is not None and (x >= self.hi if self.hi_open else x > self.hi)
        return f"must be {self.describe()}" if low or high else None

    def describe(self) -> str:
        """The bound in words: 'at least 1', 'in (0, 1]'."""
        if self.lo is None and self.hi is None:
            return "a finite number"
        if self.hi is None:
            return f"{'above' if self.lo_open else 'at least'} {_number(self.lo)}"
        if self.lo is None:
            return f"{'below' if self.hi_open else 'at most'} {_number(self.hi)}"
        return (f"in {'(' if self.lo_open else '['}{_number(self.lo)}, {_number(self.hi)}"
                f"{')' if self.hi_open else ']'}")


@dataclass(frozen=True)
class OneOf:
    """A string out of a fixed set."""

    choices: tuple[str, ...]

    def problem(self, s: str) -> str | None:
        return None if s in self.choices else f"must be one of {', '.join(self.choices)}"


@dataclass(frozen=True)
class Text:
    """Free text (a path, a topic), or text whose ``test`` says what is wrong with it;
    ``what`` names what the text must be (the config reference prints it)."""

    test: Callable[[str], str | None] | None = None
    what: str = "text"

    def problem(self, s: str) -> str | None:
        return self.test(s) if self.test is not None else None


Rule = Bound | OneOf | Text


def at_least(lo: float) -> Bound:
    return Bound(lo)


def above(lo: float) -> Bound:
    return Bound(lo, lo_open=True)


def _number(value: float) -> str:
    """A bound as people write it: 1000000, not 1e+06; 0.5 as 0.5."""
    return str(int(value)) if float(value).is_integer() and abs(value) < 1e15 else f"{value:g}"


def between(lo: float, hi: float, hi_open: bool = False) -> Bound:
    return Bound(lo, hi, hi_open=hi_open)


FINITE = Bound()
FRACTION = between(0.0, 1.0)  # a probability or a ratio
ANY_TEXT = Text()


def rules_of(cls: type) -> dict[str, tuple[Any, Rule | None]]:
    """Each field of the dataclass ``cls``: its type without the rule, and the rule (None
    when it declares none)."""
    out: dict[str, tuple[Any, Rule | None]] = {}
    for name, hint in typing.get_type_hints(cls, include_extras=True).items():
        if typing.get_origin(hint) is Annotated:
            base, *extras = typing.get_args(hint)
            rules = [e for e in extras if isinstance(e, (Bound, OneOf, Text))]
            out[name] = (base, rules[0] if rules else None)
        else:
            out[name] = (hint, None)
    return out


def checked(value: Any, hint: Any, rule: Rule | None) -> Any:
    """``value`` as the field's type (an int stays an int, a list becomes a tuple), or
    ValueError saying what is wrong with it (without naming the setting: callers do)."""
    value = _typed(value, hint)
    if rule is None:
        return value
    for item in (value if isinstance(value, tuple) else (value,)):
        if item is None:  # an optional setting left unset
            continue
        problem = rule.problem(item)
        if problem:
            raise ValueError(f"{item!r} {problem}" if isinstance(value, tuple) else problem)
    return value


def _typed(value: Any, hint: Any) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union):  # only `X | None` in config.py
        if value is None:
            return None
        return _typed(value, next(a for a in args if a is not type(None)))
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"expected a list, got {value!r}")
        fixed = not (len(args) == 2 and args[1] is Ellipsis)
        if fixed and len(value) != len(args):
            raise ValueError(f"expected a list of {len(args)} values, got {len(value)}")
        if not fixed and not value:
            raise ValueError("expected a list of at least one value, got an empty one")
        return tuple(_typed(v, args[i] if fixed else args[0]) for i, v in enumerate(value))
    # bool is an int in Python: true must not pass as 1, nor 1 as true.
    if hint is bool and isinstance(value, bool):
        return value
    if hint is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if hint is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if hint is str and isinstance(value, str):
        return value
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    raise ValueError(f"expected {names.get(hint, hint)}, got {value!r}")
