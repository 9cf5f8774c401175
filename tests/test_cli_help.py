"""``qradar --help`` and every command's help agree with the code: every option and
argument has help text, and a default written in a help text is the option's default
(the rest get theirs from the code, printed by DefaultsFormatter)."""

import argparse
import re

from qradar.cli import build_parser


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


def same(written: str, default) -> bool | None:
    """Whether the default a help text writes is ``default`` (None: not a value to compare)."""
    values = default if isinstance(default, (list, tuple)) else [default]
    tokens = [t.rstrip(":,") for t in written.split()[:len(values)]]
    if len(tokens) < len(values):
        return None
    try:
        return all(float(t) == float(v) for t, v in zip(tokens, values))
    except (TypeError, ValueError):
        pass
    if all(isinstance(v, str) for v in values) and all(re.fullmatch(r"[\w.*/:-]+", t) for t in tokens):
        return tokens == [str(v) for v in values]
    return None


def test_every_option_has_help():
    missing = [f"{cmd} {' '.join(a.option_strings) or a.dest}" for cmd, a in actions()
               if not a.help or a.help == argparse.SUPPRESS and a.dest != "verbose"]
    assert not missing, missing


def test_a_default_written_in_help_is_the_options_default():
    wrong = []
    for cmd, a in actions():
        if not a.help or a.default in (None, argparse.SUPPRESS):
            continue
        m = re.search(r"\(default:? ([^);]+)", a.help)
        if m and same(m.group(1).rstrip(", "), a.default) is False:
            wrong.append(f"{cmd} {a.option_strings}: help says {m.group(1)!r}, the default is {a.default!r}")
    assert not wrong, "\n".join(wrong)
