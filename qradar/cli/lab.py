"""Lab files: a command's options as TOML (``qradar run lab.toml``, ``qradar up lab.toml``,
a node's ``--config-json``), read with the line of every key for the errors, written
back (``--print-config``: the effective file, which reads back to the same values), and
documented from the schema (docs/lab.md).

The keys are the options' long flags without their dashes (``--split-size`` is
``split-size``), at the top level or in the table of the option's part (``[quantizer]
bits = 1``); a repeatable option is an array, a switch a boolean, and ``--sensor`` an
array of tables (``[[sensor]]``). The command line overrides the file."""

from __future__ import annotations

import json
import math
import re
import tomllib
from pathlib import Path
from typing import Any, Callable, Mapping

from radar_driver.options import file_kinds

from .schema import Entry, LabError, Schema

_ARRAY_HEADER = re.compile(r"\s*\[\[\s*([A-Za-z0-9_.-]+)\s*\]\]")
_HEADER = re.compile(r"\s*\[\s*([A-Za-z0-9_.-]+)\s*\]")
_KEY = re.compile(r"""\s*(?:"([^"]+)"|'([^']+)'|([A-Za-z0-9_-]+))\s*=""")


def key_lines(text: str) -> dict[tuple, int]:
    """The line (from 1) of each key of a TOML text, by its path: ``(key,)`` at the top
    level, ``(table, key)`` in a table, ``(array, i, key)`` in the i-th table of an
    array of tables; a table's header line under ``(table,)`` / ``(array, i)``."""
    out: dict[tuple, int] = {}
    table: tuple = ()
    counts: dict[str, int] = {}
    multiline = None  # the quote that ends a multi-line string
    for n, line in enumerate(text.splitlines(), 1):
        if multiline is not None:
            if multiline in line:
                multiline = None
            continue
        if m := _ARRAY_HEADER.match(line):
            name = m.group(1)
            table = (name, counts.get(name, 0))
            counts[name] = table[1] + 1
        elif m := _HEADER.match(line):
            table = (m.group(1),)
        elif m := _KEY.match(line):
            out.setdefault((*table, next(g for g in m.groups() if g)), n)
            rest = line[m.end():]
            for quote in ('"""', "'''"):
                if rest.count(quote) == 1:
                    multiline = quote
            continue
        else:
            continue
        out.setdefault(table, n)
    return out


def locator(name: str, text: str) -> Callable[[tuple], str]:
    """``where(path)`` -> ``name:line`` of the key at ``path`` (or of the nearest table)."""
    lines = key_lines(text)

    def where(path: tuple) -> str:
        for i in range(len(path), 0, -1):
            if path[:i] in lines:
                return f"{name}:{lines[path[:i]]}"
        return name

    return where


def read_file(path: str | Path, schema: Schema) -> dict[str, Any]:
    """The values (by dest) of lab file ``path``; LabError of one line for a file that
    cannot be read, is not TOML (its line), or holds an unknown key, a wrong type or a bad value."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise LabError(f"{path}: cannot read ({getattr(exc, 'strerror', None) or exc})") from None
    return read_text(text, str(path), schema)


def read_text(text: str, name: str, schema: Schema) -> dict[str, Any]:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"\(at line (\d+), column \d+\)", str(exc))
        at = f"{name}:{m.group(1)}" if m else name
        raise LabError(f"{at}: not TOML: {re.sub(r' [(]at line.*', '', str(exc))}") from None
    return schema.read(data, locator(name, text))


def read_json(text: str, schema: Schema, name: str = "--config-json") -> dict[str, Any]:
    """The values of a ``--config-json`` object (what ``qradar up`` and ``run``'s drivers
    hand their children): the same keys and tables as a lab file."""
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise LabError(f"{name}: not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise LabError(f"{name}: must be a JSON object of the command's options")
    return schema.read(data, lambda path: f"{name} {'.'.join(map(str, path))}")


# -- writing ----------------------------------------------------------------------------------------
_BARE = re.compile(r"[A-Za-z0-9_-]+")


def toml_key(key: str) -> str:
    return key if _BARE.fullmatch(key) else json.dumps(key)


def toml_value(value: Any) -> str:
    """One TOML value: a string, integer, float, boolean, array or inline table."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, Path):
        return json.dumps(str(value), ensure_ascii=False)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"no TOML form for {value!r}")


def dumps(mapping: Mapping[str, Any], header: str = "") -> str:
    """TOML text of a lab file's mapping: its top-level keys, its arrays of tables, then
    its tables (in the mapping's order)."""
    lines = [f"# {h}" if h else "#" for h in header.splitlines()]
    arrays = {k: v for k, v in mapping.items() if _tables(v)}
    tables = {k: v for k, v in mapping.items() if isinstance(v, dict)}
    lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in mapping.items() if k not in arrays and k not in tables]
    for k, items in arrays.items():
        for item in items:
            lines += ["", f"[[{toml_key(k)}]]", *_pairs(item)]
    for k, table in tables.items():
        lines += ["", f"[{toml_key(k)}]", *_pairs(table)]
    return "\n".join(lines).lstrip("\n") + "\n"


def _tables(value: Any) -> bool:
    """An array of tables (``[[name]]``)."""
    return isinstance(value, list) and bool(value) and all(isinstance(x, dict) for x in value)


def _pairs(table: Mapping[str, Any]) -> list[str]:
    return [f"{toml_key(k)} = {toml_value(v)}" for k, v in table.items()]


# -- documentation ------------------------------------------------------------------------------------
_KIND_WORDS = {"bool": "boolean", "int": "integer", "float": "number", "str": "string"}


def type_words(e: Entry) -> str:
    """A key's TOML type in words (``integer``, ``number or string``, ``array of strings``)."""
    if e.option.table is not None:
        return "array of tables"
    if e.switch:
        return "boolean"
    kinds = e.option.kinds or file_kinds(e.hint) or frozenset({"str"})
    words = " or ".join(sorted({_KIND_WORDS[k] for k in kinds if k != "int" or "float" not in kinds}))
    if e.option.many is not None:
        return f"array of {words.replace('string', 'strings').replace('number', 'numbers')}"
    return words


def _cell(text: str) -> str:
    """Text for a Markdown table's cell (argparse's ``%%`` as ``%``)."""
    return " ".join(str(text).replace("%%", "%").split()).replace("|", "\\|")


def docs(schema: Schema, heading: str = "###") -> str:
    """Markdown: a table per lab-file table of ``schema``: key, type, default, the command
    line's flag and what it does."""
    out = []
    for table in [None, *schema.tables]:
        entries = [e for e in schema.entries if e.table == table]
        title = "top level" if table is None else f"[{table}]"
        out += [f"{heading} {title}", "", "| key | type | default | command line | what it does |",
                "|---|---|---|---|---|"]
        for e in entries:
            default = "—" if e.default in (None, []) or e.option.table is not None else \
                f"`{toml_value(e.show(e.default))}`"
            flag = ", ".join(f"`{f}`" for f in e.option.flags(e.name)) if e.option.cli else "(file only)"
            out.append(f"| `{e.key}` | {type_words(e)} | {default} | {flag} | {_cell(e.option.help)} |")
            if e.option.table is not None:
                for sub in _table_entries(e):
                    d = "—" if sub.default in (None, []) else f"`{toml_value(sub.show(sub.default))}`"
                    out.append(f"| `{e.key}.{sub.key}` | {type_words(sub)} | {d} | "
                               f"{'in the spec' if sub.option.cli else '(file only)'} | {_cell(sub.option.help)} |")
        out.append("")
    return "\n".join(out)


def _table_entries(e: Entry) -> list[Entry]:
    from .schema import Part

    return Part(e.option.table).entries()


#: where docs/lab.md holds the generated tables
DOCS_BEGIN, DOCS_END = "<!-- schema: begin -->\n", "<!-- schema: end -->"


def update_docs(path: Path, schema: Schema) -> bool:
    """Write ``schema``'s tables (``qradar run``'s: a lab file's) between the markers of
    ``path`` (docs/lab.md); whether it changed."""
    text = path.read_text()
    head, _, rest = text.partition(DOCS_BEGIN)
    _, _, tail = rest.partition(DOCS_END)
    new = head + DOCS_BEGIN + docs(schema) + DOCS_END + tail
    path.write_text(new)
    return new != text

