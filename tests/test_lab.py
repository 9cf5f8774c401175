"""Lab files (docs/lab.md): ``qradar run LAB.toml`` reads the options of ``run`` as keys (each
command-line option is one, by construction: both are made from the same fields), the
command line overrides the file, a mistake is one line naming the file, the line and the
key, ``--print-config`` writes the effective file, which reads back to the same run; the
schema's documentation is generated; ``up``'s nodes are placed by host. In process: no
node starts (tests/test_up.py starts them)."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import pytest

from pipeline.bus.session import BusConfig
from qradar.cli import build_parser, main, with_config
from qradar.cli import lab
from qradar.cli.schema import LabError, Schema, read_table
from qradar.cli.sensor import DRIVE_PARTS
from qradar.cli.run_command import RUN_PARTS, run_config
from qradar.drivers import DriverProcess
from qradar.sensors import SensorSpec
from radar_driver.session import SessionConfig
from zenoh_helpers import QRADAR

ROOT = Path(__file__).resolve().parents[1]
RUN = Schema("run", RUN_PARTS)


def parse(*argv: str):
    """``qradar ARGV``'s parsed options, a lab file's under the command line's."""
    parser = build_parser()
    return with_config(parser, parser.parse_args(list(argv)), list(argv))


def qradar(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


LAB = """\
# a chamber day with two sensors
duration = 30
truth = "measured.toml"

[[sensor]]
url = "/dev/ttyUSB0"
id = "kmd2-0"
pose = [0.0, 0.0, 0.0]

[[sensor]]
url = "socket://127.0.0.1:3001"
id = "kmd2-1"
profile = "kmd2-blocks"
pose = [0.0, 1.5, -10.0]
host = "pc1"

[quantizer]
bits = 1
alpha = "auto"

[decoder]
algo = "pbp"
K = "auto"
max-targets = 3

[gate]
min-range-m = 2.0

[tracks]
track = true
integrate = 0.5

[recording]
no-record = true
split-size = 100.0

[views]
web = "127.0.0.1:0"

[zenoh]
connect = ["tcp/127.0.0.1:7447"]
prefix = "lab"
"""


@pytest.fixture
def lab_file(tmp_path: Path) -> Path:
    (tmp_path / "measured.toml").write_text("[[target]]\nrange_m = 4.87\nangle_deg = -20.0\n"
                                            "[[target]]\nrange_m = 9.23\nangle_deg = 15.0\n")
    path = tmp_path / "lab.toml"
    path.write_text(LAB.replace('"measured.toml"', json.dumps(str(tmp_path / "measured.toml"))))
    return path


def test_every_option_of_run_is_a_key_that_sets_what_its_flag_sets():
    """Each option of ``qradar run`` (but the command line's machinery) is a key of the lab
    file, in a table named by its part, and reading the key sets the same parsed value."""
    parser = next(a for a in build_parser()._actions if hasattr(a, "choices") and a.choices
                  and "run" in a.choices).choices["run"]
    flags = [a for a in parser._actions if a.option_strings and not set(a.option_strings) & {
        "-h", "-v", "--print-config"}]
    assert len(flags) >= 43
    for a in flags:
        e = a.qradar_entry
        assert RUN.entry(e.table, e.key) == e and e.dest == a.dest
        assert f"--{e.key}" in a.option_strings, (e.key, a.option_strings)  # the key is the flag's name


def test_a_lab_file_gives_run_its_options(lab_file):
    args = parse("run", str(lab_file))
    assert (args.duration_s, args.bits, args.alpha, args.algo, args.k, args.max_targets) == (30, 1, "auto", "pbp",
                                                                                             "auto", 3)
    assert [s.sensor_id for s in args.sensor_specs] == ["kmd2-0", "kmd2-1"]
    assert args.sensor_specs[1].pose == (0.0, 1.5, -10.0) and args.sensor_specs[1].host == "pc1"
    cfg = run_config(args)
    assert cfg.auto_k and cfg.k == 3 and cfg.tracking.integrate_s == 0.5 and cfg.min_range_m == 2.0
    assert cfg.record is None and cfg.bus.connect == ("tcp/127.0.0.1:7447",) and cfg.bus.prefix == "lab"
    assert cfg.web.port == 0 and cfg.web.poses == {"kmd2-0": (0.0, 0.0, 0.0), "kmd2-1": (0.0, 1.5, -10.0)}


def test_the_command_line_overrides_the_file(lab_file):
    args = parse("run", str(lab_file), "--duration", "5", "--bits", "2", "--connect", "tcp/10.0.0.1:7447",
                 "--sensor", "/dev/ttyUSB9,id=other", "--K", "2")
    assert (args.duration_s, args.bits, args.k, args.max_targets) == (5.0, 2, 2, 3)  # max-targets: the file's
    assert args.connect == ["tcp/10.0.0.1:7447"]  # a list on the command line replaces the file's
    assert [s.sensor_id for s in args.sensor_specs] == ["other"]
    assert args.prefix == "lab"


def test_print_config_writes_the_effective_file_which_reads_back_to_the_same_run(lab_file, capsys, tmp_path):
    code, text, err = qradar(capsys, "run", str(lab_file), "--duration", "7", "--print-config")
    assert code == 0, err
    data = tomllib.loads(text)
    assert data["duration"] == 7.0 and data["sensor"][1]["pose"] == [0.0, 1.5, -10.0]
    assert data["decoder"]["K"] == "auto" and data["zenoh"]["connect"] == ["tcp/127.0.0.1:7447"]
    again = tmp_path / "effective.toml"
    again.write_text(text)
    first, second = parse("run", str(lab_file), "--duration", "7"), parse("run", str(again))
    assert {e.dest: getattr(first, e.dest) for e in RUN.entries} == {e.dest: getattr(second, e.dest)
                                                                     for e in RUN.entries}
    assert run_config(first) == run_config(second)
    code, text2, _ = qradar(capsys, "run", str(again), "--print-config")
    assert text2 == text  # a fixed point


def test_the_default_run_prints_a_complete_file(capsys):
    code, text, _ = qradar(capsys, "run", "--print-config")
    data = tomllib.loads(text)
    assert code == 0 and data["duration"] == 15.0 and data["quantizer"]["bits"] == 1 and "alpha" not in \
        data["quantizer"]  # run's alpha: the decoder's best, not a value of its own


@pytest.mark.parametrize("argv, words", [
    (("--min-range-m", "100", "--max-range-m", "10"), "range gate: min_range_m=100 must be below max_range_m=10"),
    (("--sensor", "/dev/ttyUSB9,id=a", "--min-range-m", "100", "--max-range-m", "10"), "min_range_m=100 must be below"),
    (("--min-range-m", "160"), "min_range_m=160 is beyond the radar's unambiguous range"),
    (("--algo", "cml", "--K", "200"), "K=200 must be at most N/2 = 128 for cml")])
def test_print_config_prints_only_a_config_that_runs(capsys, argv, words):
    """The localizer's checks a run makes before it starts, made before the file is printed
    (a real sensor's radar is known once its port opens: there, the gate's ends)."""
    code, text, err = qradar(capsys, "run", *argv, "--print-config")
    lines = err.strip().splitlines()
    assert code == 2 and text == "" and len(lines) == 1 and lines[0].startswith("qradar run: error: "), err
    assert words in lines[0]


@pytest.mark.parametrize("text, where, words", [
    ("duration = 3\nbogus = 1\n", 2, "unknown key bogus; known: sensor, calibration"),
    ("frames = 20\nno-record = true\n", 2, "no-record is not a key here: write it under [recording] (no-record = "),
    ("[recording]\nframes = 20\n", 2, "[recording] frames is not a key here: write it at the top level, before any"),
    ("duration = 3\n[quantiser]\nbits = 1\n", 2, "unknown table [quantiser]; tables: quantizer"),
    ("duration = 3\n[quantizer]\nbitz = 1\n", 3, "unknown key [quantizer] bitz; known: bits, alpha"),
    ("duration = 3\n[quantizer]\nbits = \"1\"\n", 3, "[quantizer] bits = '1': must be an integer, not a string"),
    ("duration = \"long\"\n", 1, "duration = 'long': must be a number, not a string"),
    ("duration = 3\n[quantizer]\nbits = 0\n", 3, "[quantizer] bits = 0: must be >= 1"),
    ("duration = -3\n", 1, "duration = -3: must be > 0"),
    ("[decoder]\nalgo = \"best\"\n", 2, "[decoder] algo = 'best': must be one of pbp, qiht, cml"),
    ("[recording]\nno-record = 1\n", 2, "[recording] no-record = 1: must be true or false, not an integer"),
    ("[zenoh]\nconnect = \"tcp/x:1\"\n", 2, "[zenoh] connect = 'tcp/x:1': must be an array, not a string"),
    ("[[sensor]]\nurl = \"/dev/x\"\nid = \"a\"\n\n[[sensor]]\nurl = \"/dev/y\"\nidd = \"b\"\n", 7,
     "[[sensor]] 2: unknown key 'idd'; known: url, id, profile"),
    ("[[sensor]]\nurl = \"/dev/x\"\nid = \"a\"\nramps = 0\n", 4, "[[sensor]] 1: ramps = 0: must be >= 1"),
    ("[[sensor]]\nurl = \"/dev/x\"\n", 1, "[[sensor]] 1: missing id"),
    ("[[sensor]]\nurl = \"/dev/x\"\nid = \"a\"\npose = [1.0, 2.0]\n", 4, "pose"),
    ("duration = 3\n[quantizer\n", 2, "not TOML"),
])
def test_a_mistake_is_one_line_naming_the_file_the_line_and_the_key(tmp_path, capsys, text, where, words):
    path = tmp_path / "lab.toml"
    path.write_text(text)
    code, out, err = qradar(capsys, "run", str(path))
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"qradar run: error: {path}:{where}: ") and words in lines[0], lines[0]


def test_a_missing_file_is_one_line(tmp_path, capsys):
    code, _, err = qradar(capsys, "run", str(tmp_path / "none.toml"))
    assert code == 2 and err.strip() == f"qradar run: error: {tmp_path / 'none.toml'}: cannot read (No such file or " \
        "directory)"


def test_the_lines_of_keys_in_tables_arrays_and_after_multi_line_strings():
    text = ('a = 1\ns = """x\ny = 2\n"""\n[t]\n"b" = 2\n[[arr]]\nc = 3\n[[arr]]\n  c = 4 # comment\n'
            '[t2]\nd = [\n 1,\n]\n')
    lines = lab.key_lines(text)
    assert lines[("a",)] == 1 and ("y",) not in lines and lines[("t", "b")] == 6
    assert lines[("arr", 0, "c")] == 8 and lines[("arr", 1, "c")] == 10 and lines[("arr", 1)] == 9
    assert lines[("t2", "d")] == 12


@pytest.mark.parametrize("value", ["plain", 'quote " and \\ back', "line\nbreak\ttab", "ünïcode", 3, -2.5, 1e-09,
                                   True, [1, 2], ["a", "b"], {"x_m": 1.0, "id": "a"}])
def test_the_writer_s_values_read_back(value):
    assert tomllib.loads(lab.dumps({"k": value}))["k"] == value


def test_the_sensor_grammar_and_a_sensor_table_read_into_the_same_spec():
    spec = SensorSpec.parse("socket://127.0.0.1:3001,id=lab1,profile=kmd2-cube256,ramps=4,chirp-select=stride")
    table = read_table(SensorSpec, {"url": "socket://127.0.0.1:3001", "id": "lab1", "profile": "kmd2-cube256",
                                    "ramps": 4, "chirp-select": "stride"})
    assert spec == table
    # the spec's keys are drive's options: the same defaults (and checks)
    assert (spec.baud, SensorSpec.parse("/dev/x,id=a").ramps) == (SessionConfig.baud, SessionConfig.ramps_per_frame)
    with pytest.raises(LabError, match="ramps = 0: must be >= 1"):
        read_table(SensorSpec, {"url": "/dev/x", "id": "a", "ramps": 0})


def test_a_driver_process_is_handed_its_config_as_drive_s_own_options():
    """DriverProcess's child reads the same SessionConfig its spec makes."""
    spec = SensorSpec.parse("/tmp/kmd2,id=lab1,baud=921600,ramps=3,chirp-select=stride")
    bus = BusConfig(mode="client", connect=("unixsock-stream//tmp/x/zenoh.sock",), prefix="lab")
    d = DriverProcess(spec, bus, frames=40, outstanding=2, received=lambda: 0)
    assert d.cmd[3:5] == ["drive", "--config-json"] and len(d.cmd) == 6  # nothing else on its command line
    args = parse(*d.cmd[3:])
    assert Schema("drive", DRIVE_PARTS).build(SessionConfig, args) == spec.session_config(outstanding=2)
    assert (args.frames, args.json, args.quiet, args.linger_stdin, args.parent_pid > 0) == (40, True, True, True, True)
    assert (args.mode, args.connect, args.prefix) == ("client", ["unixsock-stream//tmp/x/zenoh.sock"], "lab")


def test_a_config_json_with_a_mistake_is_one_line(capsys):
    code, _, err = qradar(capsys, "quantize", "--config-json", '{"quantizer": {"bits": "one"}}')
    assert code == 2 and err.strip() == ("qradar quantize: error: --config-json quantizer.bits: [quantizer] bits = "
                                         "'one': must be an integer, not a string")


def test_docs_lab_md_holds_the_schema_as_generated():
    """docs/lab.md's key tables are the schema's own (regenerate: `make docs-lab`)."""
    text = (ROOT / "docs" / "lab.md").read_text()
    m = re.search(r"<!-- schema: begin -->\n(.*?)<!-- schema: end -->", text, re.S)
    assert m, "docs/lab.md has no generated schema"
    assert m.group(1) == lab.docs(RUN), "docs/lab.md is stale: make docs-lab"


def lab_block(name: str) -> str:
    """The TOML block of docs/lab.md marked ``<!-- lab: name -->``."""
    m = re.search(rf"<!-- lab: {re.escape(name)} -->\n```toml\n(.*?)```", (ROOT / "docs" / "lab.md").read_text(),
                  re.S)
    assert m, f"docs/lab.md has no lab file {name!r}"
    return m.group(1)


def test_the_two_sensor_chamber_is_one_file_of_at_most_40_lines(tmp_path, capsys):
    text = lab_block("chamber2.toml")
    assert len(text.splitlines()) <= 40
    (tmp_path / "chamber2.toml").write_text(text)
    (tmp_path / "cal.json").write_text("{}")
    args = parse("run", str(tmp_path / "chamber2.toml"))
    specs = args.sensor_specs
    assert len(specs) == 2 and all(s.pose is not None for s in specs) and args.calibration and args.truth
    before = (ROOT / "docs" / "lab.md").read_text().split("<!-- lab: chamber2.toml -->")[0]
    figure = re.search(r"(\d+) lines", before.rstrip().rsplit("\n\n", 1)[-1])
    assert figure and int(figure.group(1)) == len(text.splitlines())  # the count the docs give is this file's


def test_two_sensors_standing_apart_are_scored_against_one_measured_room(tmp_path):
    """Two simulated K-MD2s on ptys, the second standing 1.2 m to the side and turned 15
    deg (its simulator shows it the room's reflectors from there); one truth file measured
    from the room's origin. With their poses in the lab file each is scored against the
    truth as it sees it: both find both reflectors; without, the second misses one."""
    import subprocess
    import sys

    from qradar.liveview import seen_from
    from radar_driver.scene import resolve_scene
    from radar_driver.simulator import SimulatorServer

    room = resolve_scene("chamber-ideal")
    pose = (0.0, 1.2, -15.0)
    (tmp_path / "measured.toml").write_text("".join(f"[[target]]\nrange_m = {t.range_m}\nangle_deg = {t.angle_deg}\n"
                                                    for t in room.targets))
    sims = [SimulatorServer(scene, link_path=tmp_path / f"kmd2-{i}", rate_hz=20.0, seed=i, hold_clock_when_late=True)
            for i, scene in enumerate((room, seen_from(room, pose)))]
    text = ('truth = "measured.toml"\nframes = 30\njson = true\n\n[recording]\nno-record = true\n'
            + "".join(f'\n[[sensor]]\nurl = "{tmp_path / f"kmd2-{i}"}"\nid = "kmd2-{i}"\npose = {list(p)}\n'
                      for i, p in enumerate(((0.0, 0.0, 0.0), pose))))
    (tmp_path / "lab.toml").write_text(text)
    (tmp_path / "unposed.toml").write_text(re.sub(r"pose = .*\n", "", text))
    for sim in sims:
        sim.start()
    try:
        out = {}
        for name in ("lab", "unposed"):
            proc = subprocess.run([*QRADAR, "run", f"{name}.toml"], cwd=tmp_path,
                                  capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
            assert proc.returncode == 0, proc.stderr[-3000:]
            out[name] = json.loads(proc.stdout)
    finally:
        for sim in sims:
            sim.stop()
    posed, unposed = out["lab"]["score"], out["unposed"]["score"]
    assert posed["frames"] >= 50 and min(t["detection_rate"] for t in posed["targets"]) > 0.9, posed
    assert out["lab"]["position_error_m"]["median"] < 0.3, out["lab"]["position_error_m"]
    # unposed, the second sensor's frames are scored against the room as the first sees it: its view of the far
    # reflector lies 1.2 m from there, missed in half the frames
    assert min(t["detection_rate"] for t in unposed["targets"]) < 0.6, unposed
    assert out["unposed"]["position_error_m"]["median"] > 2 * out["lab"]["position_error_m"]["median"]
