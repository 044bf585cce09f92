"""How a setting is declared once: its default, its help line, its check, its group and its flag.

:func:`setting` puts all of them in a dataclass field's metadata; :func:`check_fields` and
:func:`add_flags` read them back, so that a config's checks and its command's flags are generated from
the declarations (:mod:`langfield.training.config` declares TrainConfig's).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Whole:
    """A whole number >= ``low`` (and <= ``high``); ``optional``: None too, meaning sized to the scene."""

    low: int
    high: int | None = None
    optional: bool = False

    def accepts(self, value: Any) -> bool:
        if self.optional and value is None:
            return True
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            return False
        return value >= self.low and (self.high is None or value <= self.high)

    @property
    def expected(self) -> str:
        span = f">= {self.low}" if self.high is None else f"in [{self.low}, {self.high}]"
        return f"a whole number {span}" + (" (or None: sized to the scene)" if self.optional else "")


@dataclass(frozen=True)
class Number:
    """A finite number in [low, high] (``open_low``: > low)."""

    low: float
    high: float = math.inf
    open_low: bool = False

    def accepts(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
            return False
        if not math.isfinite(value) or value < self.low or value > self.high:
            return False
        return not (self.open_low and value == self.low)

    @property
    def expected(self) -> str:
        lower = f"> {self.low}" if self.open_low else f">= {self.low}"
        return f"a finite number {lower}" + ("" if self.high == math.inf else f" and <= {self.high}")


@dataclass(frozen=True)
class OneOf:
    """One of ``values``; ``aliases`` are accepted too but not offered (earlier names)."""

    values: tuple[Any, ...]
    aliases: tuple[Any, ...] = ()

    def accepts(self, value: Any) -> bool:
        return any(value is v or (type(value) is type(v) and value == v) for v in self.values + self.aliases)

    @property
    def expected(self) -> str:
        shown = [repr(v) for v in self.values]
        return ", ".join(shown[:-1]) + " or " + shown[-1] if len(shown) > 1 else shown[0]


@dataclass(frozen=True)
class Satisfies:
    """A value ``test(value)`` accepts, described by ``expected``."""

    test: Callable[[Any], bool]
    expected: str

    def accepts(self, value: Any) -> bool:
        return self.test(value)


FLAG = OneOf((True, False))
TRI_STATE = OneOf((None, True, False))  # None: decided by the scene's files


def is_box(value: Any) -> bool:
    if value is None:
        return True
    try:
        box = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return box.shape == (2, 3) and bool(np.isfinite(box).all()) and bool((box[1] > box[0]).all())


def bounds_arg(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """``--bounds xmin,ymin,zmin,xmax,ymax,zmax``."""
    vals = [float(v) for v in text.split(",")]
    if len(vals) != 6:
        raise argparse.ArgumentTypeError("--bounds takes six numbers: xmin,ymin,zmin,xmax,ymax,zmax")
    return (vals[0], vals[1], vals[2]), (vals[3], vals[4], vals[5])


def setting(
    default: Any,
    help: str,
    *,
    check: Whole | Number | OneOf | Satisfies,
    group: str,
    flag: str | None = None,
    parse: Callable[[str], Any] | None = None,
    choices: tuple[Any, ...] | None = None,
) -> Any:
    """One TrainConfig setting: ``default``, ``help`` (what it does, one line), the ``check`` its values
    pass, its ``group`` and, if ``langfield train`` sets it, its ``flag``. A flag ``--no-X`` on a
    setting that is True or None by default sets it False; a boolean setting's flag ``--X`` comes with
    ``--no-X``; other flags take a value (``parse`` it, else by the default's type; ``choices`` from a
    :class:`OneOf` check unless given)."""
    meta = {"help": help, "check": check, "group": group, "flag": flag, "parse": parse, "choices": choices}
    return dataclasses.field(default=default, metadata=meta)


def check_fields(obj: Any, flags: Mapping[str, str]) -> None:
    """Raises ValueError naming the first field of dataclass ``obj`` whose value its check refuses (and
    the field's flag from ``flags``)."""
    for f in dataclasses.fields(obj):
        check = f.metadata["check"]
        if not check.accepts(getattr(obj, f.name)):
            refuse(obj, f.name, check.expected, flags)


def refuse(obj: Any, name: str, expected: str, flags: Mapping[str, str]) -> None:
    """The one-line ValueError for setting ``name`` of ``obj``."""
    flag = f" ({flags[name]})" if name in flags else ""
    raise ValueError(f"{type(obj).__name__}.{name}{flag} must be {expected}, got {getattr(obj, name)!r}")


def add_flags(
    parser: argparse.ArgumentParser,
    cls: type,
    groups: Mapping[str, str],
    names: tuple[str, ...] | None = None,
) -> None:
    """Adds a flag for each field of dataclass ``cls`` that declares one (of ``names`` only, if given),
    in argument groups titled by ``groups``. Every flag defaults to None, so that a flag left unset keeps
    the field's default."""
    made: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        flag = f.metadata["flag"]
        if not flag or (names is not None and f.name not in names):
            continue
        group = f.metadata["group"]
        if group not in made:
            made[group] = parser.add_argument_group(groups[group])
        made[group].add_argument(flag, dest=f.name, default=None, **_flag_options(f))


def given_flags(args: argparse.Namespace, names: Iterable[str]) -> dict[str, Any]:
    """The settings among ``names`` whose flags :func:`add_flags` parsed a value for (unset flags are
    None)."""
    return {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}


def _flag_options(f: dataclasses.Field) -> dict[str, Any]:
    """argparse's options for field ``f``'s flag (module docstring of :func:`setting`)."""
    meta, default = f.metadata, f.default
    shown = "" if default is None else f" (default {default})"
    if meta["flag"].startswith("--no-"):
        return {"action": "store_const", "const": False, "help": "turn off: " + meta["help"]}
    if default is True or default is False:
        return {"action": argparse.BooleanOptionalAction, "help": meta["help"] + shown}
    options: dict[str, Any] = {"help": meta["help"] + shown}
    choices = meta["choices"] or (meta["check"].values if isinstance(meta["check"], OneOf) else None)
    if choices is not None:
        options["choices"] = list(choices)
    else:
        options["type"] = meta["parse"] or type(default)
    return options
