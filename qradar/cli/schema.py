"""A command's options, made from config fields (:mod:`radar_driver.options`): each
option is one field, its default the field's, its help the field's option's. A command
lists its :class:`Part`\\ s (a dataclass, the fields it takes, the lab file's table they
sit in, and what this command changes: a default of its own, a flag); the
:class:`Schema` of those parts adds the argparse options, reads a lab file's (or a
``--config-json``'s) values into the same names, writes them back, and builds the
configs from the parsed values. The one definition of each default is thus the field's,
or a part's ``defaults`` where a command has a default of its own (``run``'s alpha)."""

from __future__ import annotations

import argparse
import dataclasses
import enum
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from pipeline.errors import ParameterError, PipelineError
from radar_driver.errors import RadarError
from radar_driver.options import (MISSING, Option, OptionValueError, default_of, is_switch, options_of, read_text,
                                  read_value, with_value)
from replay.errors import ReplayError


class LabError(ParameterError):
    """A lab file (or a ``--config-json``) that does not read: one line naming the file,
    the line, the key and what was expected. ``key``: the key of a table's item at fault."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key


@dataclass(frozen=True)
class Part:
    """The options of dataclass ``cls`` in a command: ``only`` these fields (default:
    every field with an option), in the lab file's table ``table`` (None: its top level).
    ``options``: the options of a class whose fields carry none (a module owned
    elsewhere), by field name. ``change``: per field, the Option's fields this command
    replaces (its help, flag, aliases, choices). ``defaults``: per field, this command's
    own default (its one definition). ``group``, ``description``: the ``--help`` group
    (default: the table's name). ``exclusive``: fields that do not go together. ``dests``:
    per field, the name of its parsed value when another part's field has the same name."""

    cls: type
    table: str | None = None
    only: tuple[str, ...] | None = None
    options: Mapping[str, Option] | None = None
    change: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    defaults: Mapping[str, Any] = field(default_factory=dict)
    group: str | None = None
    description: str | None = None
    exclusive: tuple[tuple[str, ...], ...] = ()
    dests: Mapping[str, str] = field(default_factory=dict)

    def entries(self) -> list["Entry"]:
        found = options_of(self.cls, dict(self.options) if self.options is not None else None)
        names = self.only if self.only is not None else tuple(found)
        unknown = [n for n in (*names, *self.change, *self.defaults) if n not in found]
        if unknown:
            raise TypeError(f"{self.cls.__name__} has no option field {unknown}")
        hints = _hints(self.cls)
        out = []
        for name in names:
            f, opt = found[name]
            opt = dataclasses.replace(opt, **self.change.get(name, {}))
            own = name in self.defaults
            default = self.defaults[name] if own else default_of(f)
            out.append(Entry(name, self, opt, hints.get(name, Any), _plain(default, opt), own))
        return out


def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # an annotation naming what the module imports only for type checkers
        return {}


def _plain(value: Any, opt: Option) -> Any:
    """A default as the option holds it: lists for tuples, an enum's value, in the option's unit."""
    if value is MISSING or value is None:
        return None
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, tuple) and opt.many is not None:
        return [_plain(v, opt) for v in value]
    if opt.scale is not None and isinstance(value, (int, float)):
        return value / opt.scale
    return value


@dataclass(frozen=True)
class Entry:
    """One option of a command: field ``name`` of ``part.cls``, its Option (this
    command's changes applied), type, default (``own``: the part's, not the field's)."""

    name: str
    part: Part
    option: Option
    hint: Any
    default: Any
    own: bool

    @property
    def dest(self) -> str:
        return self.part.dests.get(self.name, self.name)

    @property
    def key(self) -> str:
        return self.option.key(self.name)

    @property
    def table(self) -> str | None:
        return self.part.table

    @property
    def switch(self) -> bool:
        return is_switch(self.option, self.hint)

    def where(self) -> str:
        """The key as a lab file writes it: ``[table] key``."""
        return f"[{self.table}] {self.key}" if self.table else self.key

    def read(self, value: Any) -> Any:
        """A file's value (TOML types) as the option holds it."""
        opt = self.option
        if opt.table is not None:
            if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
                raise OptionValueError(f"must be an array of tables ([[{self.key}]]), not {type(value).__name__}")
            return [read_table(opt.table, v) for v in value]  # (Schema.read names the item at fault)
        value = read_value(opt, self.hint, value)
        return not value if opt.negate else value

    def show(self, value: Any) -> Any:
        """The value as a file writes it (TOML types)."""
        if self.option.negate:
            return not value
        if self.option.table is not None:
            return [table_of(v) for v in value]
        return _toml_value(value)


def _toml_value(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_toml_value(v) for v in value]
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, Path):
        return str(value)
    return value


def read_table(cls: type, data: Mapping[str, Any], where: str = "") -> Any:
    """An instance of ``cls`` from a table of its option keys (a lab file's ``[[sensor]]``,
    the pairs of a ``--sensor`` spec): each value read as its option reads it, the rest
    the fields' defaults. An unknown key or a bad value: LabError naming the key."""
    entries = {e.key: e for e in Part(cls).entries()}
    kw = {}
    for key, value in data.items():
        e = entries.get(key)
        if e is None:
            raise LabError(f"{where}unknown key {key!r}; known: {', '.join(entries)}", key=key)
        try:
            kw[e.name] = e.read(value)
        except (OptionValueError, PipelineError, RadarError, ReplayError, ValueError) as exc:
            raise LabError(f"{where}{key} = {_short(value)}: {exc}", key=key) from None
    missing = [e.key for e in entries.values() if e.option.required and e.name not in kw]
    if missing:
        raise LabError(f"{where}missing {', '.join(missing)}")
    try:
        return cls(**kw)
    except (PipelineError, RadarError, ReplayError, ValueError) as exc:
        raise LabError(f"{where}{exc}") from None


def table_of(obj: Any) -> dict[str, Any]:
    """The table of ``obj``'s option keys that :func:`read_table` reads back (defaults left out)."""
    out = {}
    for e in Part(type(obj)).entries():
        value = getattr(obj, e.name)
        if value is not None and value != e.default:
            out[e.key] = e.show(value)
    return out


class ReplaceAppend(argparse.Action):
    """``action="append"`` whose first use on a command line replaces the default (a lab
    file's list) instead of adding to it: the command line overrides the file. ``extend``:
    each value is a list, whose items are added."""

    extend = False

    def __call__(self, parser, namespace, values, option_string=None):
        given = namespace.__dict__.setdefault("_appended", set())
        items = [] if self.dest not in given else list(getattr(namespace, self.dest) or [])
        given.add(self.dest)
        setattr(namespace, self.dest, items + (list(values) if self.extend else [values]))


class ReplaceExtend(ReplaceAppend):
    extend = True


def _reader(entry: Entry) -> Callable[[str], Any]:
    """argparse's ``type`` of an entry: its text read as a file's would be (argparse checks
    the choices itself, and says ``invalid choice``)."""
    opt = dataclasses.replace(entry.option, choices=None)

    def read(text: str) -> Any:
        try:
            value = read_text(opt, entry.hint, text)
        except (ValueError, PipelineError, RadarError, ReplayError) as exc:
            raise argparse.ArgumentTypeError(with_value(text, exc)) from None
        return value

    read.__name__ = getattr(entry.option.parse, "__name__", "value")
    return read


class Schema:
    """The options of command ``command``, from its parts, in order."""

    def __init__(self, command: str, parts: Iterable[Part]):
        self.command = command
        self.parts = list(parts)
        self.entries: list[Entry] = [e for p in self.parts for e in p.entries()]
        seen: dict[str, Entry] = {}
        keys: set[tuple[str | None, str]] = set()
        for e in self.entries:
            if e.dest in seen or (e.table, e.key) in keys:
                raise TypeError(f"qradar {command}: option {e.dest} ({e.where()}) is defined twice")
            seen[e.dest] = e
            keys.add((e.table, e.key))
        self.by_dest = seen
        self.reads_lab = False  # the command takes a lab file (``qradar run LAB.toml``)

    @property
    def tables(self) -> list[str]:
        out = []
        for e in self.entries:
            if e.table is not None and e.table not in out:
                out.append(e.table)
        return out

    def entry(self, table: str | None, key: str) -> Entry | None:
        return next((e for e in self.entries if e.table == table and e.key == key), None)

    # -- the command line --------------------------------------------------------------------
    def add_to(self, parser: argparse.ArgumentParser) -> None:
        """Add every option to ``parser``, in ``--help`` groups by part."""
        groups: dict[str, Any] = {}
        for part in self.parts:
            title = part.group or part.table
            if title is None:
                target = parser
            elif title not in groups:
                target = groups[title] = parser.add_argument_group(title, part.description)
            else:
                target = groups[title]
            exclusive = {}
            for names in part.exclusive:
                g = target.add_mutually_exclusive_group()
                exclusive.update({n: g for n in names})
            for e in (e for e in self.entries if e.part is part):
                if e.option.cli:
                    _add(exclusive.get(e.name, target), e)
                else:  # a key of lab files only: its default is the parsed value's unless a file gives it
                    parser.set_defaults(**{e.dest: e.default})

    def check_required(self, args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
        """argparse's message for a required option left out of the command line and the file."""
        missing = ["/".join(e.option.flags(e.name)) or e.name for e in self.entries
                   if e.option.required and getattr(args, e.dest, None) is None]
        if missing:
            parser.error(f"the following arguments are required: {', '.join(missing)}")

    def build(self, cls: type, args: argparse.Namespace, **extra) -> Any:
        """An instance of ``cls`` from the parsed values of its options here (in the
        field's units and types), ``extra`` for the others."""
        hints = _hints(cls)
        kw = {}
        for e in self.entries:
            if e.part.cls is not cls or e.name in extra:
                continue
            value = getattr(args, e.dest)
            if e.option.scale is not None and value is not None:
                value = value * e.option.scale
            if isinstance(value, list) and typing.get_origin(hints.get(e.name)) is not list:
                value = tuple(value)
            kw[e.name] = value
        return cls(**kw, **extra)

    # -- a lab file or a --config-json --------------------------------------------------------
    def read(self, data: Mapping[str, Any], where: Callable[[tuple], str]) -> dict[str, Any]:
        """The values (by dest) of a file's mapping; ``where(path)`` names the place of a
        key (``lab.toml:12``) for the errors: an unknown table or key, a wrong type, a bad
        value, each a LabError of one line."""
        out: dict[str, Any] = {}
        for key, value in data.items():
            e = self.entry(None, key)
            if e is None and key in self.tables:
                if not isinstance(value, dict):
                    raise LabError(f"{where((key,))}: [{key}] must be a table, not {type(value).__name__}")
                for sub, v in value.items():
                    self._read_one(self.entry(key, sub), (key, sub), v, where, out)
                continue
            self._read_one(e, (key,), value, where, out)
        return out

    def _read_one(self, e: Entry | None, path: tuple, value: Any, where, out: dict) -> None:
        if e is not None and e.option.table is not None and isinstance(value, list):
            out[e.dest] = _read_tables(e, path, value, where)
            return
        if e is None and len(path) == 1 and isinstance(value, dict):
            raise LabError(f"{where(path)}: unknown table [{path[0]}]; tables: {', '.join(self.tables)}")
        if e is None:
            table = path[0] if len(path) > 1 else None
            known = [x.key for x in self.entries if x.table == table]
            what = f"[{table}] {path[-1]}" if table else path[-1]
            home = [x.table for x in self.entries if x.key == path[-1] and x.table != table]
            if home:  # a key of another table (or of the top level) given here: say where it goes
                place = " or ".join("at the top level, before any table" if h is None else f"under [{h}]"
                                    for h in dict.fromkeys(home))
                raise LabError(f"{where(path)}: {what} is not a key here: write it {place} ({path[-1]} = ...)")
            tables = f"; tables: {', '.join(self.tables)}" if table is None and self.tables else ""
            raise LabError(f"{where(path)}: unknown key {what}; known: {', '.join(known)}{tables}")
        try:
            out[e.dest] = e.read(value)
        except LabError as exc:
            raise LabError(f"{where(path)}: {e.where()}: {exc}") from None
        except (OptionValueError, PipelineError, RadarError, ReplayError, ValueError) as exc:
            raise LabError(f"{where(path)}: {e.where()} = {_short(value)}: {exc}") from None

    def mapping(self, values: Mapping[str, Any], skip_defaults: bool = False) -> dict[str, Any]:
        """The file's nested mapping of ``values`` (by dest): top-level keys, then a
        table each (values None left out: a file has no null; empty lists and the
        defaults of keys of files only too, and every default with ``skip_defaults``)."""
        out: dict[str, Any] = {}
        for e in self.entries:
            if e.dest not in values:
                continue
            value = values[e.dest]
            if value is None or value == [] and not e.default or (skip_defaults or not e.option.cli) \
                    and value == e.default:  # (a key of files only, e.g. [hosts], is written when set)
                continue
            (out.setdefault(e.table, {}) if e.table else out)[e.key] = e.show(value)
        return out


def _read_tables(e: Entry, path: tuple, value: list, where: Callable[[tuple], str]) -> list:
    """An array of tables of ``e``'s dataclass (``[[sensor]]``), each item's mistake at its line."""
    items = []
    for i, item in enumerate(value):
        if not isinstance(item, dict):
            raise LabError(f"{where(path)}: {e.key} must be an array of tables ([[{e.key}]])")
        try:
            items.append(read_table(e.option.table, item))
        except LabError as exc:
            at = where((*path, i) if exc.key is None else (*path, i, exc.key))
            raise LabError(f"{at}: [[{e.key}]] {i + 1}: {exc}") from None
    return items


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _add(target, e: Entry) -> None:
    opt = e.option
    kw: dict[str, Any] = {"dest": e.dest, "help": opt.help, "default": e.default}
    if opt.metavar is not None:
        kw["metavar"] = opt.metavar
    elif not e.switch and not opt.positional and opt.choices is None:
        kw["metavar"] = e.key.upper().replace("-", "_")  # argparse's, from the flag (the dest is the field's)
    if e.switch:
        kw["action"] = "store_false" if opt.negate else "store_true"
        kw["default"] = bool(e.default) if e.default is not None else opt.negate
    else:
        kw["type"] = _reader(e) if opt.table is None else _table_reader(e)
        if opt.choices is not None:
            kw["choices"] = list(opt.choices)
        if opt.many in ("append", "extend"):
            kw["action"] = ReplaceAppend if opt.many == "append" else ReplaceExtend
            kw["default"] = None if e.default is None else list(e.default)
        elif opt.many is not None:
            kw["nargs"] = opt.many
    if opt.positional:
        kw.pop("dest")
        if e.default is not None or not opt.required:
            kw["nargs"] = kw.get("nargs", "?")
        action = target.add_argument(e.name, **kw)
    else:
        action = target.add_argument(*opt.flags(e.name), **kw)
    action.qradar_entry = e  # tests: every option comes from a field


def _table_reader(e: Entry) -> Callable[[str], Any]:
    parse = e.option.parse

    def read(text: str) -> Any:
        try:
            return parse(text)
        except (ValueError, PipelineError, RadarError, ReplayError) as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    read.__name__ = getattr(parse, "__name__", "value")
    return read




#: the help of ``--config-json``, the option every node command has for its parent
CONFIG_JSON_HELP = ("this command's options as one JSON object, with the keys and tables of a lab file (docs/lab.md); "
                    "the command line overrides it (how `qradar up` and `qradar run` hand their children a config)")


def add_command(sub, name: str, parts: Iterable[Part], func: Callable, config_json: bool = False,
                lab: bool = False, **parser_kw) -> argparse.ArgumentParser:
    """A subcommand whose options are made from ``parts``. ``config_json``: it also takes
    ``--config-json`` (a node that ``qradar up`` or a run starts); ``lab``: a lab file
    (``LAB.toml``, the options as keys) and ``--print-config``."""
    p = sub.add_parser(name, **parser_kw)
    schema = Schema(name, parts)
    schema.reads_lab = lab
    schema.add_to(p)
    if lab:
        p.add_argument("lab", nargs="?", type=Path, default=None, metavar="LAB.toml",
                       help="a lab file: the options as keys, in tables (docs/lab.md); the command line overrides it")
        p.add_argument("--print-config", action="store_true",
                       help="print the effective lab file (the file's options with the command line's over them) "
                       "and exit: it reads back to the same configuration")
    if config_json:
        p.add_argument("--config-json", metavar="JSON", default=None, help=CONFIG_JSON_HELP)
    p.set_defaults(func=func, schema=schema)
    return p


def values_of(args: argparse.Namespace, schema: Schema) -> dict[str, Any]:
    """The parsed values of ``schema``'s options, by dest."""
    return {e.dest: getattr(args, e.dest) for e in schema.entries if hasattr(args, e.dest)}
