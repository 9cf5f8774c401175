"""Options: the fields of a configuration that a person sets, on a command line or in a
lab file, each defined once, on the field.

A config dataclass marks such a field with :func:`option`: its default (the field's own,
the one place it is written), its help, its flag and how its text reads (a parser that
says what it expected). The ``qradar`` command makes its options from these fields, and
a lab file (``qradar run lab.toml``) names the same fields by the same keys, read with
the same parsers; a class whose module cannot carry the metadata is given a table of
:class:`Option` by field name instead (:func:`options_of`).

Values read from a command line are text; values read from a file are TOML's (a string,
an integer, a float, a boolean, an array): :func:`read_value` checks a file value's type
against the field's annotation (``must be an integer, not a string``) and then reads it
as the command line would, so both say the same of a bad value.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from dataclasses import MISSING, dataclass
from pathlib import Path
from typing import Any, Callable, Literal

from .errors import OptionValueError

__all__ = ["MISSING", "META", "Option", "OptionValueError", "option", "like", "options_of", "read_value", "read_text",
           "pos_int", "nonneg_int", "pos_float", "nonneg_float", "finite_float", "prob", "file_kinds",
           "with_value"]

#: the metadata key of a field's Option
META = "qradar.option"


@dataclass(frozen=True)
class Option:
    """How a config field reads from a command line and a lab file.

    help: what it does (``--help``, the lab file's documentation). flag: its long flag,
    whose name without dashes is its key in a lab file (default: the field's name, ``_``
    as ``-``). aliases: other spellings on the command line (``-o``, ``--dither-seed``).
    parse: text -> value, raising ValueError with what it expected (None: by the field's
    type). many: ``"append"`` (repeated, one value each), ``"extend"`` (repeated, a list
    each), ``"+"``, ``"*"`` or a count (values in a row); a list in a file. scale: the
    field holds the option's value times this (``--queue-mb`` in MB, the field in bytes).
    negate: a switch that sets the field False (``--driver-in-process``:
    ``driver_process``). positional: an argument without a flag. required: no default.
    cli: False for a key of lab files only (a sensor's pose). table: the values are tables
    of this dataclass in a file (a lab file's ``[[sensor]]``), text for ``parse`` on a
    command line. kinds: the TOML types a file value may have (default: from the field's
    annotation, :func:`file_kinds`)."""

    help: str = ""
    flag: str | None = None
    aliases: tuple[str, ...] = ()
    metavar: str | tuple[str, ...] | None = None
    parse: Callable[[str], Any] | None = None
    choices: tuple | None = None
    many: str | int | None = None
    scale: float | None = None
    negate: bool = False
    positional: bool = False
    required: bool = False
    cli: bool = True
    table: type | None = None
    kinds: frozenset[str] | None = None

    def key(self, name: str) -> str:
        """The lab file's key of the field ``name``."""
        return (self.flag or name).lstrip("-").replace("_", "-") if not self.positional else name

    def flags(self, name: str) -> list[str]:
        """The command line's spellings (none for a positional argument)."""
        if self.positional:
            return []
        short = [a for a in self.aliases if not a.startswith("--")]  # -o first, as argparse's usage shows it
        return [*short, self.flag or "--" + name.replace("_", "-"), *(a for a in self.aliases if a not in short)]


def option(default: Any = MISSING, help: str = "", *, default_factory: Any = MISSING, **kw) -> Any:
    """A dataclass field with an :class:`Option` (``kw``: its other fields)."""
    return dataclasses.field(default=default, default_factory=default_factory,
                             metadata={META: Option(help=help, **kw)})


def like(cls: type, name: str, **change) -> Any:
    """A field with the default and option of ``cls``'s field ``name`` (``change``: the
    option's fields to change, e.g. its flag; ``required=True``: no default): one
    definition for two dataclasses."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    opt = dataclasses.replace(f.metadata[META], **change)
    if opt.required:
        return dataclasses.field(metadata={META: opt})
    return dataclasses.field(default=f.default, default_factory=f.default_factory, metadata={META: opt})


def options_of(cls: type, table: dict[str, Option] | None = None) -> dict[str, tuple[dataclasses.Field, Option]]:
    """The option fields of dataclass ``cls`` by name, in field order: those whose metadata
    holds an Option, or, for a class that cannot carry them, the fields ``table`` names."""
    out = {}
    for f in dataclasses.fields(cls):
        opt = table.get(f.name) if table is not None else f.metadata.get(META)
        if opt is not None:
            out[f.name] = (f, opt)
    if table is not None and set(table) - set(out):
        raise TypeError(f"{cls.__name__} has no field {sorted(set(table) - set(out))}")
    return out


def default_of(f: dataclasses.Field) -> Any:
    """A field's default (its factory's value), or MISSING."""
    if f.default is not MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not MISSING else MISSING


# -- parsers: text -> value, or an OptionValueError saying what was expected ---------------------
# (its message leaves the value out, ``must be >= 1``: the caller says where it came from)
def _number(text: str, kind: type, what: str):
    try:
        v = kind(text)
    except (TypeError, ValueError):
        raise OptionValueError(f"is not {what}") from None
    if kind is float and not math.isfinite(v):
        raise OptionValueError(f"is not {what} (finite)")
    return v


def pos_int(text: str) -> int:
    v = _number(text, int, "an integer")
    if v < 1:
        raise OptionValueError("must be >= 1")
    return v


def nonneg_int(text: str) -> int:
    v = _number(text, int, "an integer")
    if v < 0:
        raise OptionValueError("must be >= 0")
    return v


def pos_float(text: str) -> float:
    v = _number(text, float, "a number")
    if not v > 0.0:
        raise OptionValueError("must be > 0")
    return v


def nonneg_float(text: str) -> float:
    v = _number(text, float, "a number")
    if not v >= 0.0:
        raise OptionValueError("must be >= 0")
    return v


def finite_float(text: str) -> float:
    return _number(text, float, "a number")


def prob(text: str) -> float:
    v = _number(text, float, "a number")
    if not 0.0 <= v <= 1.0:
        raise OptionValueError("must be a probability in [0, 1]")
    return v


def with_value(text: str, exc: BaseException) -> str:
    """An error's message with the value it was about: an OptionValueError's gets it in
    front (``'0' must be >= 1``); another error's message names it already."""
    return f"{text!r} {exc}" if isinstance(exc, OptionValueError) else str(exc)


# -- types of a field, and what a file's value may be --------------------------------------------
_KIND_NAMES = {"bool": "a boolean", "int": "an integer", "float": "a number", "str": "a string",
               "list": "an array", "table": "a table"}


def file_kinds(hint: Any) -> frozenset[str]:
    """The TOML types a value of a field annotated ``hint`` may have: ``bool``, ``int``,
    ``float`` (an int too), ``str`` (a path, an enum's value, a literal string)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return frozenset().union(*(file_kinds(a) for a in typing.get_args(hint)))
    if origin is Literal:
        return frozenset().union(*(file_kinds(type(a)) for a in typing.get_args(hint)))
    if origin in (tuple, list):
        return file_kinds(typing.get_args(hint)[0]) if typing.get_args(hint) else frozenset({"str"})
    if hint is bool:
        return frozenset({"bool"})
    if hint is int:
        return frozenset({"int"})
    if hint is float:
        return frozenset({"int", "float"})
    if hint is type(None):
        return frozenset()
    if hint is str or (isinstance(hint, type) and issubclass(hint, (str, Path, enum.Enum))):
        return frozenset({"str"})
    return frozenset()


def _kind(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "float"
    if isinstance(value, str):
        return "str"
    return "list" if isinstance(value, list) else "table" if isinstance(value, dict) else type(value).__name__


def _scalar_type(hint: Any) -> type | None:
    """The one class a field's text becomes without a parser (int, float, Path, an enum,
    str), or None."""
    args = [a for a in (typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType)
                        else (hint,)) if a is not type(None)]
    if len(args) == 1 and typing.get_origin(args[0]) in (tuple, list):
        return _scalar_type(typing.get_args(args[0])[0])
    for kind in (bool, int, float, Path):
        if args == [kind]:
            return kind
    if len(args) == 1 and isinstance(args[0], type) and issubclass(args[0], enum.Enum):
        return args[0]
    return str


def read_text(opt: Option, hint: Any, text: str) -> Any:
    """One value of a field from its text (a command line's): the option's parser, else
    the field's type; then its choices."""
    if opt.parse is not None:
        value = opt.parse(text)
    else:
        kind = _scalar_type(hint)
        if kind is int:
            value = _number(text, int, "an integer")
        elif kind is float:
            value = finite_float(text)
        elif kind is Path:
            value = Path(text)
        elif isinstance(kind, type) and issubclass(kind, enum.Enum):
            try:
                value = kind(text).value
            except ValueError:
                raise OptionValueError(f"must be one of {', '.join(str(m.value) for m in kind)}") from None
        else:
            value = text
    if opt.choices is not None and value not in opt.choices:
        raise OptionValueError(f"must be one of {', '.join(map(str, opt.choices))}")
    return value


def read_value(opt: Option, hint: Any, value: Any) -> Any:
    """A field's value from a file (TOML types): its type checked against the field's
    (:func:`file_kinds`), then read as its text would be (:func:`read_text`); a switch
    takes a boolean, a list option an array."""
    if is_switch(opt, hint):
        if not isinstance(value, bool):
            raise OptionValueError(f"must be true or false, not {_KIND_NAMES.get(_kind(value), _kind(value))}")
        return value
    if opt.many is not None:
        if not isinstance(value, list):
            raise OptionValueError(f"must be an array, not {_KIND_NAMES.get(_kind(value), _kind(value))}")
        if isinstance(opt.many, int) and len(value) != opt.many:
            raise OptionValueError(f"must be an array of {opt.many} values, not {len(value)}")
        items = [read_value(dataclasses.replace(opt, many=None), hint, v) for v in value]
        return [x for v in items for x in v] if opt.many == "extend" else items
    kinds = opt.kinds or file_kinds(hint) or frozenset({"str"})
    kind = _kind(value)
    if kind not in kinds:
        wanted = " or ".join(sorted({_KIND_NAMES[k] for k in kinds if k in _KIND_NAMES
                                     and not (k == "int" and "float" in kinds)}))
        raise OptionValueError(f"must be {wanted}, not {_KIND_NAMES.get(kind, kind)}")
    return read_text(opt, hint, value if isinstance(value, str) else repr(value) if kind == "float" else str(value))


def is_switch(opt: Option, hint: Any) -> bool:
    """A flag without a value (``store_true``, or with ``negate`` ``store_false``)."""
    return opt.negate or (hint is bool and opt.parse is None and opt.many is None)
