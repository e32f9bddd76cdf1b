"""The settings as a TOML file a user can start from (``fleetslam config``) and as the
reference page docs/config.md: every key with its value, the comment config.py gives it
(the comment lines above its field, so each text is written once) and its rule."""

from __future__ import annotations

import inspect
import json
import re
import textwrap
import types
import typing
from typing import Any

from fleetslam.config import SECTION_GROUPS, Config
from fleetslam.validation.rules import Bound, OneOf, Rule, Text, rules_of

REGENERATE = "fleetslam config --markdown > docs/config.md"
# What each group of sections is, said once above them (config.py: SECTION_GROUPS).
GROUP_TEXT = {
    "Algorithm parameters": "What tracking, mapping, loop closing, merging and the planner "
                            "compute from the frames.",
    "Deployment settings": "Where frames come from, how robot and cloud talk, how the "
                           "cloud's workers share robots, what a run shows and writes.",
}
_FIELD = re.compile(r"^    (\w+): ")


def field_comments(cls: type) -> dict[str, list[str]]:
    """The comment lines written right above each field of the dataclass ``cls``."""
    comments: dict[str, list[str]] = {}
    pending: list[str] = []
    for line in inspect.getsource(cls).splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            text = stripped[1:]  # its own indentation kept (a list under a key)
            pending.append(text[1:] if text.startswith(" ") else text)
            continue
        match = _FIELD.match(line)
        if match:
            comments[match.group(1)] = pending
        pending = []
    return comments


def _type_text(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union):  # only `X | None` in config.py
        return _type_text(next(a for a in args if a is not type(None)))
    if origin is tuple:
        item = {int: "integers", float: "numbers"}[args[0]]
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {item}"
        return f"a list of {len(args)} {item}"
    return {bool: "true or false", int: "an integer", float: "a number",
            str: "a string"}[hint]


def rule_text(hint: Any, rule: Rule | None) -> str:
    """What a setting may be, in words: 'an integer, at least 1'."""
    kind = _type_text(hint)
    if isinstance(rule, Bound):
        bound = "finite" if rule.lo is None and rule.hi is None else rule.describe()
        return f"{kind}{', each ' if kind.startswith('a list') else ', '}{bound}"
    if isinstance(rule, OneOf):
        return f"one of {', '.join(rule.choices)}"
    if isinstance(rule, Text):
        return rule.what
    return kind


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string: JSON's escapes are TOML's
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {value!r}")


def section_toml(name: str, section: Any) -> str:
    """One ``[name]`` table: its docstring, then each key's comments, rule and value (an
    unset optional key is commented out: TOML has no null)."""
    cls = type(section)
    lines = [f"[{name}]"] + [f"# {line}".rstrip() for line in
                             inspect.cleandoc(cls.__doc__ or "").splitlines()]
    comments = field_comments(cls)
    for key, (hint, rule) in rules_of(cls).items():
        value = getattr(section, key)
        lines.append("")
        lines += [f"# {line}".rstrip() for line in comments.get(key, [])]
        if value is None:  # TOML has no null: an unset optional key is left out
            lines += [f"# ({rule_text(hint, rule)}; unset by default)", f"# {key} ="]
        else:
            lines += [f"# ({rule_text(hint, rule)})", f"{key} = {_toml_value(value)}"]
    return "\n".join(lines) + "\n"


def config_toml(config: Config | None = None) -> str:
    """Every setting of ``config`` (default: the defaults) as a commented TOML file that
    ``load_config`` reads back to the same config."""
    config = config or Config()
    head = ("# fleetslam settings: every key, its default and what it may be. Keep the keys "
            "you change\n# and pass the file with --config FILE.\n")
    parts = [head]
    for group, names in SECTION_GROUPS.items():
        parts.append(f"\n# ==== {group} ====\n"
                     + "".join(f"# {line}\n" for line in textwrap.wrap(GROUP_TEXT[group], 86)))
        parts += [f"\n{section_toml(name, getattr(config, name))}" for name in names]
    return "".join(parts)


def reference_markdown() -> str:
    """docs/config.md: each section's defaults as a commented TOML block."""
    config = Config()
    parts = ["# Configuration reference\n",
             "Generated from `src/fleetslam/config.py` (do not edit; regenerate with "
             f"`{REGENERATE}`).\n",
             "Every setting has a default; a TOML file given with `--config FILE` (before "
             "or after the command) overrides the keys it names. A key that is unknown, of "
             "the wrong type or out of its range is an error naming the file and the key. "
             "`fleetslam config` prints all of it as one file to start from. Why a default "
             "is what it is, and the variants that lost: [decisions.md](decisions.md).\n"]
    for group, names in SECTION_GROUPS.items():
        parts.append(f"## {group}\n\n{GROUP_TEXT[group]}\n")
        parts += [f"### [{name}]\n\n```toml\n{section_toml(name, getattr(config, name))}```\n"
                  for name in names]
    return "\n".join(parts)
