"""The README's multi-terminal recipes, run as written: each block marked
``<!-- recipe: NAME -->`` is read from README.md and each of its lines started as a
process of its own (a terminal), with only what a test must change substituted: the
ports (free ones), /tmp/kmd2 and out/ (a temporary folder), the committed recording's
path. Every process is stopped at the end."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from replay.mcapio import McapFile
from pipeline.bus.session import BusConfig
from zenoh_helpers import alive_nodes, free_port, interrupt, wait_port, wait_until

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def recipe(name: str, page: Path = README) -> list[str]:
    """The command lines of ``page``'s block marked ``<!-- recipe: name -->`` (comments cut)."""
    m = re.search(rf"<!-- recipe: {re.escape(name)} -->\n```sh\n(.*?)```", page.read_text(), re.S)
    assert m, f"{page.name} has no recipe {name!r}"
    return [re.sub(r"\s+#.*$", "", line).strip() for line in m.group(1).splitlines() if line.strip()]


def lab_file(name: str) -> str:
    """The TOML block of README marked ``<!-- lab: name -->``: a lab file (docs/lab.md)."""
    m = re.search(rf"<!-- lab: {re.escape(name)} -->\n```toml\n(.*?)```", README.read_text(), re.S)
    assert m, f"README.md has no lab file {name!r}"
    return m.group(1)


def substitute(line: str, tmp: Path, ports: dict[str, int]) -> str:
    for old, new in ports.items():
        line = line.replace(old, str(new))
    line = line.replace("/tmp/kmd2", str(tmp / "kmd2")).replace(" out/", f" {tmp}/out/")
    return line.replace("recordings/chamber.mcap", str(ROOT / "recordings" / "chamber.mcap"))


class Terminals:
    """Each line a process (``bash -c``, with the block's variable assignments before it)."""

    def __init__(self, tmp: Path):
        self.tmp, self.env_lines, self.procs = tmp, [], {}
        self.env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}

    def run(self, line: str) -> subprocess.Popen | None:
        if re.match(r"^[A-Z_]+=", line):
            self.env_lines.append(line)
            return None
        script = "; ".join([*self.env_lines, f"exec {line}"])
        proc = subprocess.Popen(["bash", "-c", script], cwd=self.tmp, env=self.env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.procs[line.split()[1]] = proc
        return proc

    def stop(self, command: str, timeout_s: float = 20) -> tuple[str, str]:
        proc = self.procs[command]
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=timeout_s)
        return out, err

    def close(self) -> None:
        for proc in reversed(list(self.procs.values())):
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=10)


#: the node (its liveliness token, ``radar/alive/<node>/...``) each command of a recipe runs;
#: publishers alone (drive, replay) declare none: the later lines need not wait for them
NODE_OF = {"quantize": "quantize", "localize": "localize", "record": "record", "view": "view"}


def start_all(lines: list[str], t: Terminals, ports: dict[str, int]) -> None:
    """Each line in a terminal of its own, the next once this one is up (as a person types
    the next line when the last says it is running): a router once it listens, a simulator
    once its link is there, a node once the router sees its liveliness token (it declares
    it after its subscribers), a publisher (drive, replay) at once."""
    session = None
    try:
        for line in lines:
            proc = t.run(substitute(line, t.tmp, ports))
            if proc is None:
                continue
            command = line.split()[1]
            if command == "router":
                wait_port(ports["7447"])
                session = BusConfig(mode="client", connect=(f"tcp/127.0.0.1:{ports['7447']}",)).open()
            elif command == "sim":
                wait_until(lambda: (t.tmp / "kmd2").exists() or proc.poll() is not None, 20, "the simulator's link")
            elif command in NODE_OF and session is not None:
                node = NODE_OF[command]
                wait_until(lambda: node in alive_nodes(session) or proc.poll() is not None, 60, f"{line!r} up")
            assert proc.poll() is None, f"{line!r} exited: {proc.communicate()[1][-2000:]}"
    finally:
        if session is not None:
            session.close()


@pytest.mark.slow
def test_the_chain_by_hand_works_as_written(tmp_path):
    """docs/stream.md's nodes by hand, a terminal each."""
    ports = {"7447": free_port()}
    t = Terminals(tmp_path)
    try:
        start_all(recipe("chain", ROOT / "docs" / "stream.md"), t, ports)
        deadline = time.monotonic() + 90  # frames, not seconds (a fixed 6 s was all start-up on a busy host)
        while time.monotonic() < deadline and t.procs["record"].poll() is None and \
                recorded(tmp_path / "out" / "lab.mcap").count("radar/lab1/targets") < 50:
            time.sleep(0.5)
        for command in ("record", "drive", "sim", "localize", "quantize", "router"):
            out, err = t.stop(command)
            assert "Traceback" not in err, (command, err[-3000:])
            if command == "record":
                summary = json.loads(out.strip().splitlines()[-1])
    finally:
        t.close()
    assert summary["written"] > 0
    topics = [ch.topic for ch, _ in McapFile(tmp_path / "out" / "lab.mcap").messages()]
    for topic in ("raw", "quantized", "targets"):
        assert topics.count(f"radar/lab1/{topic}") >= 40, (topic, len(topics))


@pytest.mark.slow
def test_the_fleet_up_works_as_written(tmp_path):
    """``qradar sim`` and ``qradar up fleet.toml``: the README's fleet.toml's router, driver,
    quantizer, localizer and recorder, each a process; Ctrl-C (SIGINT) ends them all."""
    port = free_port()
    (tmp_path / "out").mkdir()
    (tmp_path / "fleet.toml").write_text(substitute(lab_file("fleet.toml"), tmp_path, {"7447": port})
                                         .replace('"out/', f'"{tmp_path}/out/'))
    lines = recipe("fleet")
    assert [ln.split()[1] for ln in lines] == ["sim", "up"]
    t = Terminals(tmp_path)
    try:
        start_all(lines[:1], t, {})
        up = t.run(lines[1])
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and up.poll() is None and \
                recorded(tmp_path / "out" / "lab.mcap").count("radar/lab1/targets") < 50:
            time.sleep(0.5)  # frames, not seconds: the recording holds 50 targets (the last of a frame's chain)
        up.send_signal(signal.SIGINT)
        out, err = up.communicate(timeout=60)
        t.stop("sim")
    finally:
        t.close()
    assert up.returncode == 0 and "Traceback" not in err, err[-3000:]
    nodes = json.loads(out.strip().splitlines()[-1])["up"]["nodes"]
    assert set(nodes) == {"router", "record", "localize", "quantize", "driver lab1"}, nodes
    topics = recorded(tmp_path / "out" / "lab.mcap")
    for topic in ("raw", "quantized", "targets"):
        assert topics.count(f"radar/lab1/{topic}") >= 40, (topic, len(topics))


def recorded(path: Path) -> list[str]:
    """The topics of a recording's messages so far ([] before its first chunk)."""
    try:
        return [ch.topic for ch, _ in McapFile(path).messages()]
    except Exception:  # not there yet, or no chunk yet
        return []


@pytest.mark.slow
def test_replay_and_view_work_as_written(tmp_path):
    ports = {"7447": free_port(), "8765": free_port()}
    t = Terminals(tmp_path)
    try:
        start_all(recipe("replay-view"), t, ports)
        replay_out, replay_err = t.procs["replay"].communicate(timeout=60)
        assert t.procs["replay"].returncode == 0, replay_err[-2000:]
        published = json.loads(replay_out.strip().splitlines()[-1])["published"]
        view_out, view_err = t.stop("view")  # it saw frames while the replay ran (seconds of them)
        t.stop("router")
    finally:
        t.close()
    seen = json.loads(view_out.strip().splitlines()[-1])
    assert published > 0 and seen["frames_in"] > 0 and seen["sensors"], seen
    assert "no zenoh peer or router reached" not in view_err


def truth_file(name: str) -> str:
    """The TOML block of README marked ``<!-- truth: name -->``."""
    m = re.search(rf"<!-- truth: {re.escape(name)} -->\n```toml\n(.*?)```", README.read_text(), re.S)
    assert m, f"README.md has no truth file {name!r}"
    return m.group(1)


@pytest.mark.slow
def test_a_run_on_a_sensor_it_does_not_simulate_works_as_written(tmp_path):
    """``qradar run --sensor`` on ``qradar sim``'s pty, against README's measured.toml."""
    (tmp_path / "measured.toml").write_text(truth_file("measured.toml"))
    t = Terminals(tmp_path)
    try:
        start_all(recipe("real-sensor"), t, {})
        out, err = t.procs["run"].communicate(timeout=90)
        assert t.procs["run"].returncode == 0, err[-3000:]
        t.stop("sim")
    finally:
        t.close()
    assert "qradar run: 1 sensor(s) lab1 on " in out and "truth measured.toml" in out, out
    frames = re.search(r"frames      raw (\d+), quantized (\d+), targets (\d+)", out)
    # a busy host starts slowly and loses sensor frames (counted): 97 in one run under two busy loops
    assert frames and int(frames.group(1)) >= 50 and len(set(frames.groups())) == 1, out
    median = float(re.search(r"error       median ([0-9.]+) m", out).group(1))
    assert median < 0.5 and "lab1 #" in out and "Traceback" not in err


# -- one-shot recipes: each line a command that ends, run in order ----------------------------
def steps(name: str) -> list[str]:
    """The command lines of README's block marked ``<!-- recipe-steps: name -->``."""
    m = re.search(rf"<!-- recipe-steps: {re.escape(name)} -->\n```sh\n(.*?)```", README.read_text(), re.S)
    assert m, f"README.md has no recipe-steps {name!r}"
    return [re.sub(r"\s+#.*$", "", line).strip() for line in m.group(1).splitlines() if line.strip()]


def run_step(line: str, tmp: Path, timeout_s: float = 300) -> subprocess.CompletedProcess:
    """One line as a user types it (``qradar`` is .venv/bin/qradar), in ``tmp``, with the
    repository's recordings/ reachable under the same path."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    out = subprocess.run(["bash", "-c", line], cwd=tmp, env=env, stdin=subprocess.DEVNULL, capture_output=True,
                         text=True, timeout=timeout_s)
    assert out.returncode == 0 and "Traceback" not in out.stderr, (line, out.returncode, out.stderr[-3000:])
    return out


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """A folder like a checkout's: recordings/ (the committed ones) and out/."""
    (tmp_path / "recordings").mkdir()  # the committed files, each a link: a run's own recording stays in tmp_path
    for src in (ROOT / "recordings").iterdir():  # (a link to the folder let the recipes' runs record into it)
        if not src.name.startswith("run-"):
            (tmp_path / "recordings" / src.name).symlink_to(src)
    (tmp_path / "out").mkdir()
    return tmp_path


@pytest.mark.slow
def test_the_simulated_sensor_recipe_works_as_written(workdir):
    lines = steps("simulated")
    first = run_step(lines[0], workdir)
    median = float(re.search(r"error       median ([0-9.]+) m", first.stdout).group(1))
    assert median < 0.5, first.stdout  # the calibrated chamber
    summary = json.loads(run_step(lines[1], workdir).stdout)
    assert summary["frames_targets"] > 100 and summary["sensors"] == 3, summary
    assert summary["position_error_m"]["median"] < 0.5, summary  # the walker's truth follows each sensor's clock
    run_step(lines[2], workdir)
    assert (workdir / "out" / "mc" / "summary.json").exists()
    assert len(lines) == 3


@pytest.mark.slow
def test_the_chamber_recipe_works_as_written_on_a_simulated_sensor(workdir):
    """Each line as written, /dev/ttyUSB0 being a simulated K-MD2 of the scene that step
    asks for: the empty chamber, the reflector at 3.1 m, then the chamber."""
    (workdir / "measured.toml").write_text(truth_file("measured.toml"))
    lines = steps("chamber")
    assert lines[-1] == "qradar run chamber.toml"
    scenes = ["--scene chamber --empty", "--scene chamber-reflector", None, "--scene chamber"]
    assert len(lines) == len(scenes)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    out = None
    for line, scene in zip(lines, scenes):
        if scene is None:
            run_step(line, workdir)
            continue
        link = workdir / f"kmd2-{len(line)}"
        (workdir / "chamber.toml").write_text(lab_file("chamber.toml").replace("/dev/ttyUSB0", str(link)))
        sim = subprocess.Popen(["bash", "-c", f"exec qradar sim {scene} --link {link} --hold-clock-when-late"],
                               cwd=workdir, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 20
            while not link.exists() and time.monotonic() < deadline:
                time.sleep(0.1)
            out = run_step(line.replace("/dev/ttyUSB0", str(link)), workdir)
        finally:
            sim.send_signal(signal.SIGTERM)
            sim.communicate(timeout=20)
    assert json.loads((workdir / "cal.json").read_text())["entries"]
    median = float(re.search(r"error       median ([0-9.]+) m", out.stdout).group(1))
    assert median < 0.5, out.stdout  # calibrated: 2 m without


@pytest.mark.slow
def test_the_reprocess_recipe_works_as_written(workdir):
    for line in steps("reprocess"):
        run_step(line, workdir)
    result = json.loads((workdir / "out" / "sweep" / "results.json").read_text())
    assert set(result["by_algo"]) == {"pbp", "cml"}
    assert (workdir / "out" / "sweep" / "alpha_sweep.png").stat().st_size > 0
    assert (workdir / "out" / "fixed.mcap").exists()


@pytest.mark.slow
def test_the_foxglove_recipe_works_as_written(workdir):
    (line,) = steps("foxglove")
    port = free_port()
    out = run_until_ctrl_c(line.replace("8765", str(port)), workdir, f"ws://127.0.0.1:{port}")
    assert "frames " in out and "Traceback" not in out  # its summary


@pytest.mark.slow
def test_the_web_recipe_works_as_written(workdir):
    (line,) = steps("web")
    port = free_port()
    out = run_until_ctrl_c(line.replace("8080", str(port)), workdir, f"web: page on http://127.0.0.1:{port}/")
    assert "frames " in out and "Traceback" not in out


def run_until_ctrl_c(line: str, tmp: Path, says: str, timeout_s: float = 60) -> str:
    """A line a user leaves running (as typed, in ``tmp``): once it ``says`` so on stdout and
    shows a frame's targets, Ctrl-C; its exit status 0 and what it printed (stdout)."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    proc = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=tmp, env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen, lines = False, []
    try:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:  # bounded: in time, and by the process's end (EOF)
            text = proc.stdout.readline()
            if not text:
                break
            lines.append(text)
            seen = seen or says in text
            if seen and " targets (" in text:
                break
    finally:
        out, err = interrupt(proc, 30)
    assert seen, f"{line!r} never said {says!r}: " + "".join(lines)[-2000:] + err[-2000:]
    assert proc.returncode == 0 and "Traceback" not in err, (line, proc.returncode, err[-3000:])
    return "".join(lines) + out


@pytest.mark.slow
def test_the_security_recipe_works_as_written(workdir):
    lines = steps("security")
    run_step(lines[0], workdir)
    listed = run_step(lines[1], workdir).stdout
    assert "sensor-kmd2-0" in listed and "router" in listed
    checked = run_step(lines[2], workdir).stdout
    assert "none but a router's names hosts" in checked and "FLAGGED" not in checked
    out = run_step(lines[3], workdir).stdout
    assert "0 refused_handshakes" in out and "frames" in out


def test_the_python_recipe_works_as_written(workdir):
    m = re.search(r"<!-- recipe-python: api -->\n```python\n(.*?)```", README.read_text(), re.S)
    assert m, "README.md has no recipe-python api"
    out = subprocess.run([sys.executable, "-c", m.group(1)], cwd=workdir, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("(106, 2)")


@pytest.mark.slow
def test_the_tracks_recipe_works_as_written(workdir):
    walk, chamber = steps("tracks")
    out = run_step(walk, workdir).stdout
    assert "tracks" in out and "Traceback" not in out
    out = run_step(chamber, workdir).stdout
    m = re.search(r"static tracks' error median ([0-9.]+) m", out)
    assert m, out[-3000:]
    assert float(m.group(1)) < 0.08, out[-2000:]  # one frame: ~0.12 m


def terminals_recipe(name: str) -> list[str]:
    """The command lines of README's block marked ``<!-- recipe-terminals: name -->``."""
    m = re.search(rf"<!-- recipe-terminals: {re.escape(name)} -->\n```sh\n(.*?)```", README.read_text(), re.S)
    assert m, f"README.md has no recipe-terminals {name!r}"
    return [re.sub(r"\s+#.*$", "", line).strip() for line in m.group(1).splitlines() if line.strip()]


def stop_sim(sim: subprocess.Popen) -> str:
    """Ctrl-C to a ``qradar sim`` (its process, as a terminal sends it): its summary."""
    sim.send_signal(signal.SIGINT)
    out, err = sim.communicate(timeout=20)
    assert sim.returncode == 0 and "Traceback" not in err, err[-2000:]
    return out


@pytest.mark.slow
def test_the_chamber_recipe_on_the_simulated_sensor_works_as_written(workdir):
    """README's chamber steps with their simulator lines, each as written (/tmp/kmd2 in the
    test's folder): a ``sim`` in a terminal of its own until Ctrl-C, the others in order. The
    uncalibrated runs say so; the calibration passes its checks; the calibrated run is the
    ideal sensor's."""
    (workdir / "measured.toml").write_text(truth_file("measured.toml"))
    (workdir / "chamber.toml").write_text(lab_file("chamber.toml"))  # its sensor overridden on the command line
    lines = [ln.replace("/tmp/kmd2", str(workdir / "kmd2")) for ln in terminals_recipe("chamber-simulated")]
    assert [ln.split()[1] for ln in lines] == ["sim", "run", "sim", "run", "calibrate", "sim", "run"]
    assert "--empty" in lines[0] and "--scene chamber-reflector" in lines[2]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    sim, outs = None, []
    try:
        for line in lines:
            if line.split()[1] != "sim":
                outs.append(run_step(line, workdir))
                continue
            if sim is not None:
                assert "simulator: " in stop_sim(sim)  # its summary on Ctrl-C
            sim = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=workdir, env=env, stdin=subprocess.DEVNULL,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            deadline = time.monotonic() + 60  # (a bound on the event: the loop ends once the link is there)
            while not (workdir / "kmd2").exists() and time.monotonic() < deadline:
                time.sleep(0.1)
            assert (workdir / "kmd2").exists(), line
    finally:
        if sim is not None and sim.poll() is None:
            stop_sim(sim)
    empty_run, _, calibrate, chamber = outs
    assert "calibration none" in empty_run.stdout and "uncalibrated" in empty_run.stdout
    assert "fit residual" in calibrate.stderr and "one reflector explains" in calibrate.stderr
    assert json.loads((workdir / "cal.json").read_text())["entries"]
    median = float(re.search(r"error       median ([0-9.]+) m", chamber.stdout).group(1))
    assert median < 0.5 and "calibration cal.json" in chamber.stdout and "warning" not in chamber.stdout, \
        chamber.stdout
