"""docs/benchmarks.md's current figures come from the benchmarks' own result files: the table in
the doc is what ``benchmarks/figures.py`` makes of ``benchmarks/results/*.json``, every suite
script has a result file saying when, where and how it ran, and a run of the suite writes them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
sys.path.insert(0, str(BENCH))

import figures  # noqa: E402
import harness  # noqa: E402
import suite  # noqa: E402


def test_the_docs_table_is_the_one_made_from_the_result_files():
    block = figures.render(figures.load(figures.RESULTS))
    doc = (ROOT / "docs" / "benchmarks.md").read_text()
    assert block in doc, ("docs/benchmarks.md's current figures are not benchmarks/results' : run "
                          "`.venv/bin/python benchmarks/figures.py --update docs/benchmarks.md`")
    assert doc.count(figures.BEGIN) == 1 and doc.count(figures.END) == 1


def test_every_suite_script_has_a_result_file_that_says_when_where_and_how():
    records = figures.load(figures.RESULTS)
    for step in suite.SUITE:
        name = step.script.removesuffix(".py")
        assert name in records, f"benchmarks/results/{name}.json missing: run `make bench` (or the script)"
        rec = records[name]
        assert rec["script"] == step.script
        assert rec["command"].startswith(f"benchmarks/{step.script}")
        assert rec["date"][:4] == "2026" and rec["host"]["cpus"] >= 1 and "load_1min" in rec["host"]
        assert isinstance(rec["figures"], dict) and rec["figures"], name
        # a full run, not the smoke run of `make bench SHORT=1` (its figures are not worth quoting)
        if step.short:
            assert rec["command"] != " ".join([f"benchmarks/{step.script}", *step.short]), name
    # every row of the table names a script of the suite and a key its file holds
    for f in figures.FIGURES:
        assert f.script in records, f
        figures.lookup(records[f.script]["figures"], f.key)


def test_a_missing_key_is_named():
    with pytest.raises(figures.MissingFigure, match="ms_per_frame.cml"):
        figures.lookup({"ms_per_frame": {"pbp": 1.0}}, "ms_per_frame.cml")


def test_emit_writes_a_result_file_only_when_asked(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["/x/benchmarks/bench_demo.py", "--seconds", "3"])
    monkeypatch.delenv(harness.RESULTS_ENV, raising=False)
    harness.emit({"a": 1})
    assert json.loads(capsys.readouterr().out) == {"a": 1}
    assert not list(tmp_path.iterdir())
    monkeypatch.setenv(harness.RESULTS_ENV, str(tmp_path / "res"))
    harness.emit({"a": {"b": 2.5}})
    rec = json.loads((tmp_path / "res" / "bench_demo.json").read_text())
    assert rec["command"] == "benchmarks/bench_demo.py --seconds 3"
    assert rec["figures"] == {"a": {"b": 2.5}}
    assert rec["host"]["cpus"] == os.cpu_count()


def test_the_suite_writes_result_files_where_told_and_the_table_reads_them(tmp_path):
    """One quick script of the suite, run as `make bench SHORT=1` runs it, into a folder of the test's."""
    out = subprocess.run([sys.executable, str(BENCH / "suite.py"), "--short", "--only", "bench_noise",
                          "--results", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rec = json.loads((tmp_path / "bench_noise.json").read_text())
    assert rec["command"] == "benchmarks/bench_noise.py " + " ".join(dict(
        (s.script, s.short) for s in suite.SUITE)["bench_noise.py"])
    noise_rows = [f for f in figures.FIGURES if f.script == "bench_noise"]
    block = figures.render({"bench_noise": rec}, noise_rows)
    assert figures.BEGIN in block and "bench_noise.py --repeat 1" in block
    # a doc without the markers is refused, one with them is written between them
    doc = tmp_path / "doc.md"
    doc.write_text("# x\n")
    with pytest.raises(SystemExit, match="markers"):
        figures.update(doc, block)
    doc.write_text(f"# x\n\n{figures.BEGIN}\nold\n{figures.END}\n\nafter\n")
    assert figures.update(doc, block)
    assert doc.read_text() == f"# x\n\n{block}\n\nafter\n"
    assert not figures.update(doc, block)
