"""Each option is defined once, on a config field (radar_driver.options): every option of
every command is made from a field, its default IS that field's default (or the one its
command declares as its own, in its part), and it has a help text. No help text is read
for its defaults: the default comes from the field, and the help shows it."""

import argparse
import dataclasses
import enum

from qradar.cli import build_parser

#: the options that are the command line's own machinery, not a configuration's
MACHINERY = {"-h", "-v", "--version", "--config-json", "--print-config"}


def actions():
    """(command, action) of every option and argument of every command."""
    out = []

    def walk(name: str, parser: argparse.ArgumentParser) -> None:
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sub, sp in a.choices.items():
                    walk(f"{name} {sub}", sp)
            elif not isinstance(a, (argparse._HelpAction, argparse._VersionAction)):
                out.append((name, a))

    walk("qradar", build_parser())
    return out


def machinery(cmd: str, a: argparse.Action) -> bool:
    return bool(set(a.option_strings) & MACHINERY) or cmd == "qradar" or (cmd == "qradar run" and a.dest == "lab")


def field_default(cls, name: str):
    """The default of field ``name`` of dataclass ``cls``, read from the class itself."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    if f.default is not dataclasses.MISSING:
        return f.default
    return None if f.default_factory is dataclasses.MISSING else f.default_factory()


def as_option(value, scale):
    """A field's default as the option holds it (its unit, a list, an enum's value)."""
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, tuple):
        return [as_option(v, None) for v in value]
    if scale is not None and value is not None:
        return value / scale
    return value


def test_every_option_comes_from_a_field_and_its_default_is_the_fields():
    made_by_hand, wrong, checked = [], [], 0
    for cmd, a in actions():
        if machinery(cmd, a):
            continue
        e = getattr(a, "qradar_entry", None)
        if e is None:
            made_by_hand.append(f"{cmd} {a.option_strings or a.dest}")
            continue
        expected = e.part.defaults[e.name] if e.own else as_option(field_default(e.part.cls, e.name), e.option.scale)
        if e.option.negate:
            expected = bool(expected)
        elif isinstance(a, argparse._StoreTrueAction):
            expected = bool(expected)
        if a.default != expected:
            wrong.append(f"{cmd} {a.option_strings}: default {a.default!r}, {e.part.cls.__name__}.{e.name}: "
                         f"{expected!r}")
        checked += 1
    assert not made_by_hand, f"options not made from a config field: {made_by_hand}"
    assert not wrong, "\n".join(wrong)
    assert checked > 200  # every command's options


def test_a_command_s_own_default_is_declared_in_one_part():
    """Where a command's default differs from the field's (run's alpha follows its decoder, its K
    the scene), its part declares it; nowhere else is a default written."""
    own = sorted({(cmd, e.name) for cmd, a in actions() if (e := getattr(a, "qradar_entry", None)) and e.own})
    assert own == [("qradar capture", "seconds"), ("qradar reprocess", "k"), ("qradar run", "alpha"),
                   ("qradar run", "k")], own


def test_every_option_has_help():
    missing = [f"{cmd} {' '.join(a.option_strings) or a.dest}" for cmd, a in actions()
               if not a.help or a.help == argparse.SUPPRESS and a.dest != "verbose"]
    assert not missing, missing


def test_a_changed_field_default_changes_the_option(monkeypatch):
    """The option reads its default from the field when the parser is made: one place."""
    from pipeline.nodes.intake import QueueConfig

    f = QueueConfig.__dataclass_fields__["queue_size"]
    monkeypatch.setattr(f, "default", 1234)
    args = build_parser().parse_args(["quantize"])
    assert args.queue_size == 1234


def test_each_command_is_built_alone_from_the_adder_the_table_names():
    """``qradar CMD`` builds only CMD's group (qradar.cli.ADDERS): the table names every
    command the full parser has, in `qradar -h`'s order, and each command's parser built alone
    is the full parser's."""
    from qradar.cli import ADDERS

    def commands(parser):
        return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices

    full = commands(build_parser())
    assert list(full) == [c for names in ADDERS.values() for c in names]
    for name, sub in full.items():
        alone = commands(build_parser(name))
        assert name in alone and len(alone) < len(full)
        assert [a.option_strings for a in alone[name]._actions] == [a.option_strings for a in sub._actions], name
    assert list(commands(build_parser("no-such-command"))) == list(full)  # argparse names them all
