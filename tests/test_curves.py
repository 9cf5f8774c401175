"""docs/science.md's curves (``make docs-figures``: ``python -m experiments.curves docs/figures``)
are there, and the detection probabilities its text quotes are what the command's seeded
points give (to the digits written)."""

import json
import re
from pathlib import Path

import pytest

from experiments.curves import SNR_DB, CurveConfig, detection

ROOT = Path(__file__).resolve().parents[1]
TEXT = (ROOT / "docs" / "science.md").read_text()
#: (the words in docs/science.md before the figure, decoder, bits, alpha, SNR dB)
QUOTED = [("`cml` finds it in\n", "cml", 1, 0.45, -12), ("% of the frames at α 0.45 and", "cml", 1, 1.0, -12),
          ("PBP in", "pbp", 1, 0.45, -12), ("−16 dB, `cml`", "cml", None, 0.0, -16), ("% and PBP", "pbp", None, 0.0, -16)]


def written(after: str) -> float:
    """The first percentage written after ``after`` in the curves' paragraph."""
    para = TEXT[TEXT.index("Curves (`make docs-figures`"):]
    m = re.search(r"(\d+\.\d) %", para[para.index(after) + len(after):])
    return float(m.group(1))


def test_the_curves_are_in_the_docs_and_their_numbers_beside_them():
    data = json.loads((ROOT / "docs" / "figures" / "curves.json").read_text())
    assert data["snr_db"] == list(SNR_DB)
    for name in ("detection_vs_snr", "false_targets", "ellipse_coverage"):
        assert (ROOT / "docs" / "figures" / f"{name}.png").stat().st_size > 10_000
        assert f"(figures/{name}.png)" in TEXT


@pytest.mark.parametrize("after, algo, bits, alpha, snr", QUOTED)
def test_the_quoted_detection_probabilities_are_the_commands(after, algo, bits, alpha, snr):
    cfg = CurveConfig()
    got = detection(algo, bits, alpha, snr, cfg.frames, cfg.seed + SNR_DB.index(snr))
    assert 100 * got == pytest.approx(written(after), abs=0.05 + 1e-9)
    data = json.loads((ROOT / "docs" / "figures" / "curves.json").read_text())
    label = "unquantized" if bits is None else f"1-bit, α {alpha:g}"
    assert data["detection"][algo][label][SNR_DB.index(snr)] == pytest.approx(got)
