"""Exceptions: one module per package holds them all under the package root; zenoh
failures are BusErrors; a cut or corrupted MCAP file never raises past ReplayError."""

import importlib
import pkgutil
import random
import struct
import time
from pathlib import Path

import pytest

import pipeline
import radar_driver
import replay
from pipeline.bus.session import BusConfig
from pipeline.errors import BusError, PipelineError
from radar_driver.errors import RadarError
from replay.errors import ReplayError
from replay.mcapio import McapFile
from zenoh_helpers import free_port

CHAMBER = Path(__file__).resolve().parents[1] / "recordings" / "chamber.mcap"
ROOTS = {radar_driver: RadarError, pipeline: PipelineError, replay: ReplayError}


def _exception_classes(module, namespace=None):
    """Exception classes in a module's namespace, and in those of the classes it defines."""
    for obj in list(vars(namespace or module).values()):
        if isinstance(obj, type):
            if issubclass(obj, BaseException):
                yield obj
            elif obj.__module__ == module.__name__ and obj is not namespace:
                yield from _exception_classes(module, obj)


@pytest.mark.parametrize("package", list(ROOTS), ids=lambda p: p.__name__)
def test_every_exception_lives_in_the_errors_module_under_the_root(package):
    root, errors_module = ROOTS[package], f"{package.__name__}.errors"
    modules = [importlib.import_module(info.name)
               for info in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]
    assert len(modules) >= 4
    seen = set()
    for module in [package] + modules:
        for cls in _exception_classes(module):
            if cls.__module__.split(".")[0] != package.__name__:
                continue  # builtins and other packages' exceptions
            assert cls.__module__ == errors_module, f"{cls.__qualname__} is defined in {cls.__module__}"
            assert issubclass(cls, root), f"{cls.__qualname__} does not derive from {root.__name__}"
            seen.add(cls)
    errors = importlib.import_module(errors_module)
    assert set(_exception_classes(errors)) <= seen | {root}


def test_moved_exceptions_keep_their_old_import_paths():
    from pipeline.dsp.decode import DitherUnavailable
    from pipeline.wire import WireError
    from radar_driver.protocol import ProtocolError
    from radar_driver.session import LinkError, SensorError, SensorResponseError, SensorTimeout
    from radar_driver.simulator import LinkDown

    for cls in (ProtocolError, SensorError, SensorTimeout, SensorResponseError, LinkError, LinkDown):
        assert cls.__module__ == "radar_driver.errors"
    assert WireError.__module__ == DitherUnavailable.__module__ == "pipeline.errors"
    exc = SensorResponseError("GNFD", 2)
    assert str(exc) == "sensor answered GNFD with RESP 2 (INVALID_PARAMETER)" and exc.code == 2
    assert "(UNDEFINED)" in str(SensorResponseError("INIT", 99))


def test_zenoh_client_to_a_closed_port_raises_bus_error_naming_the_endpoint():
    ep = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    with pytest.raises(BusError) as info:
        BusConfig(mode="client", connect=(ep,)).open()
    assert time.monotonic() - t0 < 5
    assert ep in str(info.value) and "mode=client" in str(info.value)
    assert not isinstance(info.value, ValueError)


def test_bad_zenoh_config_file_raises_bus_error_naming_the_file(tmp_path):
    bad = tmp_path / "zenoh.json5"
    bad.write_text('{ mode: "peer", ')
    for path in (bad, tmp_path / "missing.json5"):
        with pytest.raises(BusError, match=str(path)):
            BusConfig(config_file=path).open()


def _read(path):
    f = McapFile(path)
    try:
        f.scan()
    except ReplayError:
        return None
    return f


def _record_starts(data):
    starts, pos = [], 8
    while pos + 9 <= len(data):
        starts.append(pos)
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    return starts


def test_cut_or_corrupted_recording_ends_as_truncated_and_raises_only_replay_errors(tmp_path):
    data = CHAMBER.read_bytes()
    full = McapFile(CHAMBER)
    n_full = full.scan()
    assert not full.truncated and n_full > 0
    starts = _record_starts(data)
    assert len(starts) > 20
    case = tmp_path / "case.mcap"

    # cut short: inside the magic, at and around every record boundary, and on a stride
    offsets = {1, 7} | {s + d for s in starts for d in (0, 1, 12)} | set(range(8, len(data), len(data) // 61))
    for cut in sorted(o for o in offsets if o < len(data)):
        case.write_bytes(data[:cut])
        f = _read(case)
        if cut < 8:
            assert f is None  # NotMcapError
            continue
        assert f is not None and f.truncated and f.truncation_reason, cut

    # a chunk whose records length is absurd (a read that trusted it would try to allocate it):
    # the chunk is damaged, named, its messages lost; the others read. Chunk: opcode, length,
    # start and end times, uncompressed size and crc, compression string, then the uint64
    # records length.
    chunk = next(s for s in starts if data[s] == 0x06)
    assert data[chunk + 37:chunk + 45] == b"\x04\x00\x00\x00zstd"
    for pos, value in ((chunk + 45 + 6, 0x01), (chunk + 45 + 7, 0x80)):
        b = bytearray(data)
        b[pos] = value
        case.write_bytes(bytes(b))
        f = _read(case)
        assert f is not None and [d.offset for d in f.damaged] == [chunk] and f.read + f.lost == n_full

    # corrupted: record headers and fields overwritten, random bytes, sometimes also cut
    rng = random.Random(20261121)
    reasons = set()
    for i in range(200):
        b = bytearray(data)
        if i % 2:
            p = rng.choice(starts) + rng.randrange(0, 48)
            b[p] = rng.choice([0x00, 0xFF, b[p] ^ 0x80])
        else:
            for _ in range(rng.randrange(1, 6)):
                b[rng.randrange(8, len(b))] = rng.randrange(256)
        if i % 5 == 0:
            b = b[:rng.randrange(8, len(b))]
        case.write_bytes(bytes(b))
        f = _read(case)  # anything but a ReplayError fails the test here
        if f is not None and f.truncated:
            reasons.add(f.truncation_reason.split(":")[0])
    assert len(reasons) >= 3, reasons
