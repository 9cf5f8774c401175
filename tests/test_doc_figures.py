"""Deterministic figures in docs/ against a fresh run of the command written above them
(docs/figures/regenerate.py, ``make docs-figures``, regenerates them). A number in the docs
must equal the run's to the digits it is written with (half a unit of its last digit)."""

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def regenerate():
    spec = importlib.util.spec_from_file_location("regenerate", ROOT / "docs" / "figures" / "regenerate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def written_numbers(cells: list[str]) -> list[tuple[float, float]]:
    """(value, tolerance) of the first number of each cell, the tolerance half a unit of its
    last written digit."""
    out = []
    for cell in cells:
        m = re.search(r"\d+(?:\.(\d+))?", cell)
        assert m, cell
        out.append((float(m.group(0)), 0.5 * 10.0 ** -len(m.group(1) or "") + 1e-12))
    return out


def test_the_chamber_reprocessing_table_is_what_its_command_gives(tmp_path):
    gen = regenerate()
    text = (ROOT / "docs" / "recording.md").read_text()
    head = f"`{gen.REPROCESS}`:"
    assert head in text, "docs/recording.md no longer shows the command this test runs"
    table = text[text.index(head):].split("\n\n")[1].splitlines()[2:]
    rows = gen.table_rows(gen.run_reprocess(tmp_path))
    assert len(table) == len(rows)
    for line in table:
        cells = [c.strip() for c in line.strip("|").split("|")]
        algo = next(a for a, name in gen.NAMES.items() if cells[0].strip("*") == name)
        for (doc, tol), got, col in zip(written_numbers(cells[1:]), rows[algo], range(1, 8)):
            assert abs(doc - got) <= tol, f"{algo}, column {col}: the docs say {doc}, the command gives {got:.4f}"
