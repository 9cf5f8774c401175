"""The Python API (qradar.api, docs/api.md) on the committed recording, and the examples
that docs/api.md shows, run as a user runs them."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import qradar
from pipeline.errors import ParameterError
from replay.errors import ReplayError

ROOT = Path(__file__).resolve().parents[1]
CHAMBER = ROOT / "recordings" / "chamber.mcap"


@pytest.fixture(scope="module")
def rec():
    return qradar.open_recording(CHAMBER)


def test_the_recording_as_arrays(rec):
    raw, quantized, targets = rec.raw(), rec.quantized(), rec.targets()
    assert rec.sensors == ["kmd2-0"] and not rec.truncated
    assert raw.data.shape == (len(raw), 512, 2) and raw.data.dtype == np.complex64
    assert (np.diff(raw.seq.astype(np.int64)) > 0).all()  # in sequence order
    assert len(quantized) == len(targets) == len(raw) == 106
    assert targets.range_m.shape == (106, 2) and (targets.count == 2).all() and targets.algo == "pbp"
    assert (targets.published_ns > targets.timestamp_ns).all()
    assert rec.radar.config_id() == raw.config_id == quantized.config_id
    assert len(rec.health()) > 0 and rec.unparsed == {}
    assert len(rec.scene().targets) == 2


def test_quantize_and_decode_reproduce_what_the_stream_published(rec):
    """The recording's raw frames quantized again give its quantized frames bit for bit
    (it was made with the older 'seedseq' dither), and PBP on them its targets exactly."""
    raw, quantized, targets = rec.raw(), rec.quantized(), rec.targets()
    again = qradar.quantize(raw, alpha=float(quantized.frames.alpha[0]), generator="seedseq")
    assert np.array_equal(again.codes, quantized.frames.codes)
    det = qradar.decode(quantized, rec.radar, k=2, algo="pbp")
    for name in ("range_m", "angle_deg", "x_m", "y_m"):  # the JSON carries 9 significant digits
        np.testing.assert_allclose(getattr(det, name), getattr(targets, name), rtol=2e-9, atol=0, err_msg=name)
    # the stream's own generator draws another dither: most codes, not all, agree
    assert not np.array_equal(qradar.quantize(raw, alpha=0.55).codes, quantized.frames.codes)


def test_errors_are_one_line(rec):
    with pytest.raises(ReplayError, match="no raw messages of sensor 'nope'"):
        rec.raw("nope")
    with pytest.raises(ParameterError):
        qradar.quantize(rec.raw(), alpha=2.0)
    with pytest.raises(ReplayError, match="not whole ramps"):
        qradar.decode(np.zeros((1, 300, 2), complex), rec.radar, k=1)
    with pytest.raises(AttributeError):
        qradar.not_a_name  # noqa: B018


def test_version():
    out = subprocess.run([sys.executable, "-m", "qradar", "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == f"qradar {qradar.__version__}"
    assert re.fullmatch(r"\d+\.\d+\.\d+.*", qradar.__version__)


def run_example(name: str, *args: str) -> str:
    out = subprocess.run([sys.executable, str(ROOT / "examples" / name), *args], capture_output=True, text=True,
                         timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def figure(text: str, pattern: str) -> float:
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not in:\n{text}"
    return float(m.group(1))


def test_example_recording_arrays():
    out = run_example("recording_arrays.py")
    assert "raw (106, 512, 2) complex64" in out and "targets (106, 2) by pbp" in out
    assert 0 < figure(out, r"median error ([\d.]+) m") < 10


def test_example_decode_again():
    out = run_example("decode_again.py", str(CHAMBER), "0.3")
    pbp = figure(out, r"alpha 0.30 pbp: median error ([\d.]+) m")
    cml = figure(out, r"alpha 0.30 cml: median error ([\d.]+) m")
    full = figure(out, r"unquantized cml: median error ([\d.]+) m")
    assert full < cml < 0.3 < pbp  # the chamber's reflectors are off the grid


@pytest.mark.slow
def test_example_montecarlo_sweep(tmp_path):
    out = run_example("montecarlo_sweep.py", str(tmp_path))
    pbp = figure(out, r"dither_m512: median position error ([\d.]+) m")
    cml = figure(out, r"dither_m512@cml: median position error ([\d.]+) m")
    assert cml < 0.2 < pbp
    assert {p.name for p in tmp_path.iterdir()} >= {"results.json", "alpha_sweep.png", "reconstructions.png"}
