"""The smaller promises of the command line: every option has a help text, run's help
names its real default decoder, refusals come before anything starts and say why, and
zenoh's errors read as one line without Rust source paths."""

from __future__ import annotations

import argparse

import pytest

from pipeline.bus.session import zenoh_reason
from pipeline.errors import ParameterError
from qradar.cli import build_parser
from replay.errors import ReplayError
from replay.reprocess import parse_alphas
from zenoh_helpers import qradar


def subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_every_option_of_every_command_has_a_help_text():
    missing = [(name, a.option_strings) for name, p in subcommands().items() for a in p._actions
               if a.option_strings and a.help is not argparse.SUPPRESS and not (a.help or "").strip()]
    assert missing == []


def test_run_help_names_its_default_decoder():
    run = subcommands()["run"]
    default = next(a.default for a in run._actions if a.dest == "algo")
    text = run.format_help()
    assert f"default {default}" in " ".join(text.split()) and "the PBP localizer" not in text


@pytest.mark.parametrize("spec, words", [
    ("1:0:0.1", "start 1 is above stop 0"),
    ("0:1:0", "step 0 must be > 0"),
    ("0:1", "three numbers"),
    ("0:x:0.1", "must be three numbers"),
    ("0.2,1.5", "not 1.5"),
    ("a,b", "expected START:STOP:STEP"),
])
def test_an_alpha_sweep_says_what_is_wrong(spec, words):
    with pytest.raises(ReplayError, match=words):
        parse_alphas(spec)


def test_an_alpha_sweep_in_order_is_fine():
    assert parse_alphas("0:1:0.25").tolist() == [0.0, 0.25, 0.5, 0.75, 1.0]


def test_run_refuses_a_bad_k_before_starting_anything():
    out = qradar("run", "--K", "999", "--no-record")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "K=999" in lines[0] and "range bins" in lines[0]
    assert "simulated K-MD2" not in out.stderr  # no simulator was started


def test_the_limits_on_k_say_why():
    assert "distinct range cells" in qradar("montecarlo", "--K", "41", "--runs", "10").stderr
    # count options where each decoder is told K: they were ignored (and written into summary.json)
    out = qradar("montecarlo", "--K", "1", "--runs", "10", "--pfa", "0.1", "--max-targets", "3", "--no-plots")
    assert out.returncode == 2 and out.stderr.strip().splitlines()[-1] == (
        "qradar montecarlo: error: max_targets=3 (--max-targets), pfa=0.1 (--pfa) act with --count auto only (the "
        "decoders decide the count); here each is told the scene's K: give --count auto, or leave them out")
    assert "two samples a tone" in qradar("run", "--K", "200", "--algo", "cml", "--no-record").stderr
    # more targets than a live cml keeps up with (it was accepted, and took seconds a frame)
    for argv in (("--K", "17"), ("--K", "auto", "--max-targets", "99")):
        out = qradar("run", *argv, "--algo", "cml", "--no-record")
        assert out.returncode == 2 and "is more than cml decodes live: at most 16" in out.stderr, out.stderr


def test_a_k_taken_from_the_scene_is_named_so(tmp_path):
    scene = tmp_path / "crowd.toml"
    scene.write_text('name = "crowd"\n' + "".join(f"[[target]]\nrange_m = {5 + 4 * i}\nangle_deg = 0\namplitude = 0.5\n"
                                                   for i in range(17)))
    out = qradar("run", "--scene", str(scene), "--algo", "cml", "--no-record")
    last = out.stderr.strip().splitlines()[-1]
    assert out.returncode == 2 and last.startswith(
        "qradar run: error: no --K given: K=17, the scene's targets; K=17 is more"), last
    assert "is more than cml decodes live: at most 16" in last


@pytest.mark.parametrize("args", [
    ("localize", "--listen", "tcp/127.0.0.1:99999", "--duration", "1"),
    ("localize", "--mode", "client", "--connect", "tcp/127.0.0.1:1", "--duration", "1"),
])
def test_zenoh_errors_are_one_line_without_rust_paths(args):
    out = qradar(*args)
    assert out.returncode == 2
    line = out.stderr.strip()
    assert "\n" not in line and ".rs:" not in line and "cannot open zenoh session" in line


def test_zenoh_reason_cuts_the_source_path_and_joins_lines():
    exc = Exception("--> 1:1\n  | {bad\n  = expected array at /root/.cargo/git/x/zenoh-config/src/lib.rs:1486.")
    assert zenoh_reason(exc) == "--> 1:1 | {bad = expected array"


def test_run_checks_the_requests_in_flight():
    from pipeline.errors import ParameterError
    from qradar.run import RunConfig

    assert RunConfig().outstanding == 2
    with pytest.raises(ParameterError, match="outstanding=3 must be 1 or 2"):
        RunConfig(outstanding=3)


@pytest.mark.parametrize("argv, command", [(["run", "--json", "--K", "0"], "run"),
                                           (["drive", "--frames", "0", "--json"], "drive"),
                                           (["info", "--json", "--bogus", "x"], "info")])
def test_an_argument_error_with_json_prints_the_error_object_and_names_its_command(argv, command, cli):
    """As every other failure with ``--json``: one line on stderr naming the command (an option
    the top parser found unknown too: ``qradar info: error: unrecognized arguments``), and the
    error object on stdout, status 2."""
    import json

    code, out, err = cli(*argv)
    assert code == 2 and err.startswith(f"qradar {command}: error: ") and len(err.strip().splitlines()) == 1, err
    obj = json.loads(out)
    assert obj["exit_code"] == 2 and obj["command"] == command and obj["error"] in err
    code, out, err = cli(*[a for a in argv if a != "--json"])
    assert code == 2 and out == "" and err.startswith(f"qradar {command}: error: ")


def test_a_noise_level_given_twice_is_refused(tmp_path):
    out = qradar("montecarlo-time", "--noise-sigma", "0.1", "0", "0.1", "--runs", "2", "--out", str(tmp_path / "t"))
    assert out.returncode == 2 and out.stderr.strip().splitlines()[-1] == (
        "qradar montecarlo-time: error: --noise-sigma 0.1 0 0.1: 0.1 given twice; give each noise level once")
    assert not (tmp_path / "t").exists()  # refused before any work


def test_a_k_auto_refusal_names_the_most_targets_and_where_they_came_from(tmp_path):
    """With K auto the localizer refuses the most targets a frame, named as ``--max-targets``, in
    each of its refusals; a run whose most came from its scene says so (it named a flag not given)."""
    from pipeline.dsp.decode import Algo
    from pipeline.nodes.stream import LocalizerConfig
    from qradar.run import RunConfig, plan

    with pytest.raises(ParameterError, match=r"^--max-targets=10 targets do not fit in the range gate \[2, 5\] m"):
        LocalizerConfig(k=10, auto_k=True, min_range_m=2.0, max_range_m=5.0)
    with pytest.raises(ParameterError, match=r"^--max-targets=0 must be an integer in \[1, N = 256\]"):
        LocalizerConfig(k=0, auto_k=True)
    with pytest.raises(ParameterError, match=r"^K=0 must be an integer in \[1, N = 256\]"):
        LocalizerConfig(k=0)
    scene = tmp_path / "crowd.toml"
    scene.write_text('name = "crowd"\n' + "".join(f"[[target]]\nrange_m = {5 + 4 * i}\nangle_deg = 0\namplitude = 0.5\n"
                                                   for i in range(17)))
    with pytest.raises(ParameterError, match=r"^no --max-targets given: at most 17 targets a frame, the scene's "
                                             r"targets; --max-targets=17 is more than cml decodes live"):
        plan(RunConfig(scene=str(scene), algo=Algo.CML, auto_k=True, record=None))


def test_info_reads_a_crafted_deeply_nested_metadata_value_as_text():
    """A metadata value nested beyond the JSON parser (crafted: the CRC guards against damage,
    not craft) is shown as its text, not a traceback (re-processing took it as no clock already)."""
    from replay.mcapinfo import _values

    deep = "[" * 100000
    assert _values({"first_raw_ns": deep, "part": "1"}) == {"first_raw_ns": deep, "part": 1}
