"""Shared fixtures: a radar configuration, a seeded rng, the zenoh ones (an embedded
peer session, a free loopback port, a bounded connect to a listener in another process),
a real recording of ``qradar run --track`` split into files, and a count of the chunks the
MCAP reader opens.
Helpers that are not fixtures (qradar, QRADAR, Collector, wait_until, free_port, wait_port,
rss_mb) live in zenoh_helpers. A test marked ``measure`` (it measures time or memory) runs on
one pytest-xdist worker with the others so marked (``make test`` runs four workers,
``--dist loadgroup``), never beside another measurement. benchmarks/ is on ``sys.path``: tests import a benchmark's pieces by name.
A test process is prepared as a ``qradar`` process is (:func:`qradar.entry.prepare_process`:
one BLAS thread), before numpy loads."""

import os
import subprocess
import sys
import time
from pathlib import Path

from qradar.entry import prepare_process

prepare_process()
#: pytest's assertion-rewritten test modules cached (tests/__pycache__/*-pytest-*.pyc, git-ignored)
#: even where PYTHONDONTWRITEBYTECODE is set (this host's environment sets it), as ``make test``
#: compiles qradar's own modules: without the cache each worker rewrites every test module when it
#: collects them, 4.3 s of CPU, against 1.3 s with it (``pytest --collect-only``, 2026-11-29)
sys.dont_write_bytecode = False

import numpy as np  # noqa: E402 (after prepare_process, as in a qradar process)
import pytest  # noqa: E402

import zenoh_helpers  # noqa: E402
from pipeline.bus.session import BusConfig  # noqa: E402
from pipeline.errors import PipelineError  # noqa: E402
from radar_driver.model import RadarConfig  # noqa: E402
from zenoh_helpers import QRADAR, WAIT_FLOOR_S  # noqa: E402

sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))

#: the modules that call cml's inner kernels on their own (``coarse_ratio``, ``peak``, ...): a node
#: uses them only inlined in the entry kernels that ``make`` compiles; ``make test``'s set-up
#: compiles them as these tests call them (tests/inner_kernels.py, ~45 s of CPU once); they share a
#: worker, so that a signature it misses is compiled once, not on each worker
INNER_KERNEL_TESTS = {"test_cml_count", "test_cml_detect", "test_cml_kernels"}


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own, which reads xdist_group into the nodeid
def pytest_collection_modifyitems(config, items):
    """Groups for ``--dist loadgroup``: the tests that measure on one worker; those of cml's
    inner kernels on one (:data:`INNER_KERNEL_TESTS`); the tests of a module that share one of
    its module-scoped fixtures (a run, a PKI, a Monte Carlo) on one worker, so that it runs
    once, not once on each worker that draws one of them."""
    for item in items:
        if item.get_closest_marker("measure") is not None:
            item.add_marker(pytest.mark.xdist_group("measure"))
        elif item.module.__name__ in INNER_KERNEL_TESTS:
            item.add_marker(pytest.mark.xdist_group("cml-inner-kernels"))
        elif any(d.scope == "module" for defs in item._fixtureinfo.name2fixturedefs.values() for d in defs):
            item.add_marker(pytest.mark.xdist_group(f"module-fixture:{item.module.__name__}"))


#: pause between two connection attempts, s
CONNECT_RETRY_S = 0.2
#: how long one opened session may wait for the peer or router to join before it is retried, s
CONNECT_ATTEMPT_S = 2.0
#: how often a session is polled for its peers / routers, s
CONNECT_POLL_S = 0.05


@pytest.fixture
def cfg() -> RadarConfig:
    return RadarConfig()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture
def bus() -> BusConfig:
    """The default bus: an isolated embedded peer (no listener, no scouting)."""
    return BusConfig()


@pytest.fixture
def zenoh_session(bus):
    """A session opened with ``bus.open()`` (the ``bus`` fixture of the same test), closed after."""
    session = bus.open()
    try:
        yield session
    finally:
        session.close()


@pytest.fixture(scope="session")
def track_recording(tmp_path_factory) -> list[Path]:
    """The files of a real ``qradar run --track --record`` of 60 frames (one simulated sensor, PBP,
    calibrated with recordings/chamber-cal.json), split every 0.1 MB: ``run.mcap``,
    ``run_0001.mcap``, ... (at least two), in order; read only. Made once for the whole
    session: under pytest-xdist the first worker to need it makes it in the workers'
    common folder (under a lock), the others read it."""
    import fcntl

    shared = tmp_path_factory.getbasetemp()
    if "PYTEST_XDIST_WORKER" in os.environ:  # pytest-xdist's pattern: the workers' basetemps share a parent
        shared = shared.parent
    folder = shared / "track-recording"
    with open(shared / "track-recording.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        done = folder / "made"
        if not done.exists():
            _record_track_run(folder)
            done.touch()
    return sorted(folder.glob("run*.mcap"))


def _record_track_run(folder: Path) -> None:
    """The run of :func:`track_recording` into ``folder`` (made anew)."""
    import shutil

    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    calibration = Path(__file__).resolve().parents[1] / "recordings" / "chamber-cal.json"
    proc = subprocess.run([*QRADAR, "run", "--frames", "60", "--duration", "120", "--track", "--algo", "pbp",
                           "--calibration", str(calibration), "--split-size", "0.1",
                           "--record", str(folder / "run.mcap"), "--json"],
                          capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stderr[-2000:]
    files = sorted(folder.glob("run*.mcap"))
    assert files[0].name == "run.mcap" and len(files) >= 2, files


@pytest.fixture
def chunks_opened(monkeypatch) -> list[int]:
    """The body length of each chunk the MCAP reader decompresses and checks, in order
    (calls of replay.mcapread.open_chunk while the test runs)."""
    import replay.mcapread

    calls = []
    real = replay.mcapread.open_chunk

    def counting(body):
        calls.append(len(body))
        return real(body)

    monkeypatch.setattr(replay.mcapread, "open_chunk", counting)
    return calls


@pytest.fixture
def cli(capsys):
    """``qradar ARGV`` in this process, for what ends before anything starts (usage errors,
    ``--help``): ``cli(*argv)`` -> (exit status, stdout, stderr). Anything that opens a port,
    a session or a file runs in a process of its own (``zenoh_helpers.qradar``)."""
    from qradar.cli import main

    def run(*argv) -> tuple[int, str, str]:
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse's usage errors and --help
            code = exc.code if isinstance(exc.code, int) else 1
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture(name="free_port")
def free_port_fixture() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    return zenoh_helpers.free_port()


def _joined(session, timeout_s: float) -> bool:
    """True once ``session`` sees a peer or a router, polling for at most ``timeout_s``."""
    for _ in range(max(1, int(timeout_s / CONNECT_POLL_S)) + 1):
        if session.info.peers_zid() or session.info.routers_zid():
            return True
        time.sleep(CONNECT_POLL_S)
    return False


@pytest.fixture
def connect_when_ready():
    """``connect_when_ready(endpoint, timeout_s=WAIT_FLOOR_S, mode="peer", secure=None)``: a zenoh session
    connected to ``endpoint`` (with ``secure``, a pipeline.bus.security.SecureConfig, over mTLS),
    whose listener is in another process that may not be up yet.

    Each attempt opens a session (a client fails at once when nothing listens: a
    PipelineError) and waits up to CONNECT_ATTEMPT_S for a peer or router to join (a peer
    opens even when nothing listens); an attempt that fails is closed and retried after
    CONNECT_RETRY_S. At most ``timeout_s / CONNECT_RETRY_S + 1`` attempts, none started
    after ``timeout_s``; then the test fails saying what the last attempt saw. Sessions
    are closed when the test ends (closing one earlier in the test is fine too)."""
    opened = []

    def connect(endpoint: str, timeout_s: float = WAIT_FLOOR_S, mode: str = "peer", secure=None):
        timeout_s = max(timeout_s, WAIT_FLOOR_S)  # a bound says when the listener is lost, not how fast it comes
        bus = BusConfig(mode=mode, connect=(endpoint,), secure=secure)
        deadline = time.monotonic() + timeout_s
        max_attempts = int(timeout_s / CONNECT_RETRY_S) + 1
        last = "no attempt was made"
        for attempt in range(1, max_attempts + 1):
            try:
                session = bus.open()
            except PipelineError as exc:
                last = str(exc)
            else:
                t_open = time.monotonic()
                if _joined(session, max(0.0, min(CONNECT_ATTEMPT_S, deadline - t_open))):
                    opened.append(session)
                    return session
                session.close()
                last = (f"a session opened, but no peer or router had joined it "
                        f"{time.monotonic() - t_open:.1f} s later")
            if time.monotonic() >= deadline:
                break
            time.sleep(CONNECT_RETRY_S)
        pytest.fail(f"could not connect a zenoh {mode} to {endpoint} within {timeout_s} s "
                    f"({attempt} attempts); last attempt: {last}", pytrace=False)

    yield connect
    for session in opened:
        session.close()
