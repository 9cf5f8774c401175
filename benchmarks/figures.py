#!/usr/bin/env python3
"""docs/benchmarks.md's current figures: one table made from the result files of the last full
``make bench`` (``benchmarks/results/<script>.json``, written by ``harness.emit``), each figure
with the date, host and command of the run that measured it. The one place a present-tense
benchmark figure lives; the rest of docs/benchmarks.md is dated history.

    .venv/bin/python benchmarks/figures.py                          # print the table
    .venv/bin/python benchmarks/figures.py --update docs/benchmarks.md   # write it into the doc
    .venv/bin/python benchmarks/figures.py --results out/bench-short     # from other result files

tests/test_bench_figures.py holds the doc to the committed result files.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
BEGIN = "<!-- current-figures: begin (benchmarks/figures.py writes this table; do not edit by hand) -->"
END = "<!-- current-figures: end -->"


@dataclass(frozen=True)
class Figure:
    """One row of the table: what is measured, the script whose result file holds it, the key
    path in its ``figures`` (dots between levels) and the format of its value (``{:...}``)."""

    what: str
    script: str
    key: str
    fmt: str = "{:g}"
    unit: str = ""


#: the table's rows, in the order shown (each script's result file must hold each key: the test checks)
FIGURES: tuple[Figure, ...] = (
    # the decoders, 1-bit dithered frames of the paper's radar (M = 512), K = 2
    Figure("PBP, count given, a batch of 4 096 frames", "bench_pbp", "fft_batch_fps", "{:,.0f}", "frames/s"),
    Figure("PBP, count given, one frame at a time", "bench_pbp", "fft_single_fps", "{:,.0f}", "frames/s"),
    Figure("PBP `--K auto` (its test on residuals), batch of 1 024", "bench_pbp", "auto_batch_ms_per_frame",
           "{:.2f}", "ms a frame"),
    Figure("QIHT + ML, batch of 1 024", "bench_pbp", "qiht_batch_ms_per_frame", "{:.2f}", "ms a frame"),
    Figure("`cml`, count given, batch of 256 (CPU, median of turns)", "bench_cml", "ms_per_frame.cml", "{:.2f}",
           "ms a frame"),
    Figure("`cml --K auto`, batch of 256", "bench_cml", "ms_per_frame.cml_auto", "{:.2f}", "ms a frame"),
    Figure("`cml` against PBP, same frames, same process", "bench_cml", "ratio_to_pbp.cml", "{:.0f}", "×"),
    Figure("`cml`'s phase step between ramps over its static model, count given (goal ≤ 1.5)", "bench_cml",
           "motion_over_static.cml", "{:.2f}", "×"),
    Figure("the same, `--K auto` (goal ≤ 1.5)", "bench_cml", "motion_over_static.cml_auto", "{:.2f}", "×"),
    Figure("the same, positions only (`--no-uncertainty`), count given", "bench_cml",
           "motion_over_static.cml_positions", "{:.2f}", "×"),
    Figure("the same, positions only, `--K auto`", "bench_cml", "motion_over_static.cml_positions_auto", "{:.2f}",
           "×"),
    Figure("`cml` sensors a core can decode at 20 frames/s (decoding alone)", "bench_cml",
           "cml_sensors_per_core_at_20_fps", "{:d}"),
    Figure("PBP, one frame a call (CPU, best of 7)", "bench_decoders", "ms_per_frame.pbp_b1", "{:.2f}", "ms"),
    Figure("`cml`, one frame a call (as a live localizer decodes)", "bench_decoders", "ms_per_frame.cml_b1", "{:.2f}",
           "ms"),
    # the sensor's path
    Figure("serial driver on a pty, frames of the K-MD2", "bench_driver", "driver_frames_per_s", "{:,.0f}",
           "frames/s"),
    Figure("the driver against reading the pty raw", "bench_driver", "driver_over_raw_pty", "{:.2f}", "×"),
    Figure("protocol codec, valid stream in 4 KiB reads", "bench_codec", "valid_ramps_per_s_4kib_chunks", "{:,.0f}",
           "ramps/s"),
    Figure("protocol codec, worst garbage (1 MiB in one read)", "bench_codec", "worst_one_feed_cpu_ms", "{:.1f}",
           "ms CPU"),
    Figure("targets message, batch of 64, K = 2: encode", "bench_wire",
           "targets_b64_k2_us_per_frame.encode_targets_batch", "{:.1f}", "µs a frame"),
    Figure("quantized frame, batch of 64: decode", "bench_wire", "quantized_codec_b64_us_per_frame.decode_quantized_batch",
           "{:.1f}", "µs a frame"),
    Figure("`--alpha auto` against a fixed α, one frame", "bench_noise", "ratio_auto_to_fixed.b1", "{:.2f}", "×"),
    # the nodes
    Figure("quantize node, CPU a frame (500 sensors)", "bench_nodes", "cpu_us_per_frame.quantize", "{:.0f}", "µs"),
    Figure("localize node, PBP, CPU a frame", "bench_nodes", "cpu_us_per_frame.localize_pbp", "{:.0f}", "µs"),
    Figure("localize node, `cml`, CPU a frame", "bench_nodes", "cpu_us_per_frame.localize_cml", "{:.0f}", "µs"),
    Figure("localize node's steps, PBP, one frame a batch", "bench_localize_steps", "us_per_frame.b1", "{:.0f}",
           "µs a frame"),
    Figure("localize node's steps, PBP, 128 frames a batch", "bench_localize_steps", "us_per_frame.b128", "{:.0f}",
           "µs a frame"),
    Figure("tracker, walker scene, batch of 4", "bench_track", "tracker_ms_per_frame", "{:.2f}", "ms a frame"),
    Figure("tracker against its localizer", "bench_track", "tracker_over_localizer", "{:.2f}", "×"),
    Figure("health of 500 sensors, one slice of 50", "bench_health", "slice_median_ms", "{:.2f}", "ms (median)"),
    Figure("10 000 expired sensor ids: memory left after the last round", "bench_expiry",
           "rss_mb.forgotten_last_minus_before", "{:+.1f}", "MB RSS"),
    Figure("subscriber CPU a 320-B message at 10 000/s, polling", "bench_receive", "cpu_us_per_msg_best.poll",
           "{:.1f}", "µs"),
    Figure("subscriber CPU a message, zenoh's FIFO hand-off", "bench_receive", "cpu_us_per_msg_best.fifo", "{:.1f}",
           "µs"),
    Figure("recorder, 100 sensors: the most frames a sensor without a loss (of 10-160/s)", "bench_record",
           "best.frames_per_s_per_sensor", "{:d}", "frames/s"),
    Figure("recorder, messages/s written at that rate", "bench_record", "best.messages_per_s", "{:,.0f}", "msg/s"),
    Figure("a 10-s window of a 1-hour recording (590 MB)", "bench_reading", "window_10s.seconds", "{:.3f}", "s"),
    Figure("every target of the 1-hour recording", "bench_reading", "targets_of_the_whole_recording.seconds",
           "{:.1f}", "s"),
    Figure("`qradar info` of the 1-hour recording (the command, start-up included)", "bench_reading",
           "info.qradar_info_command_s", "{:.2f}", "s"),
    Figure("TLS and access control against plaintext, messages/s", "bench_secure", "secure_over_plain", "{:.2f}",
           "×"),
    # the stream at scale: one localizer process, sensors at 20 frames/s, no loss and p99 <= 20 ms
    Figure("one PBP localizer (K = 2): the most sensors at 20 frames/s, no loss, p99 ≤ 20 ms", "bench_stream",
           "largest_passing_sensors.edge_spread_pbp", "{}", "sensors"),
    Figure("its latency p99 there", "bench_stream", "p99_ms_at_largest.edge_spread_pbp", "{}", "ms"),
    Figure("one `cml` localizer (K = 2): the most sensors at 20 frames/s, no loss, p99 ≤ 20 ms", "bench_stream_cml",
           "largest_passing_sensors.edge_spread_cml", "{}", "sensors"),
    Figure("its latency p99 there", "bench_stream_cml", "p99_ms_at_largest.edge_spread_cml", "{}", "ms"),
    Figure("a flood of 5 000 frames/s beside an honest sensor: honest frames lost", "bench_isolation",
           "quantized.honest_lost", "{}"),
    Figure("the honest sensor's latency p99 under the flood (alone: next row)", "bench_isolation",
           "quantized.honest_p99_ms", "{}", "ms"),
    Figure("the honest sensor's latency p99 alone", "bench_isolation", "quantized.baseline_p99_ms", "{}", "ms"),
    Figure("the web view, 6 sensors at 20 Hz: the view's CPU", "bench_web", "sensors_6.view_cpu_pct", "{}",
           "% of a core"),
    Figure("the page's frame time p99 there (headless chromium)", "bench_web", "sensors_6.page_frame_ms_p99", "{}",
           "ms"),
)


class MissingFigure(LookupError):
    """A row's result file or key is not there."""


def lookup(figures: Mapping[str, Any], key: str) -> Any:
    """The value at ``key`` ("a.b.c") in nested mappings; MissingFigure naming the key if absent."""
    value: Any = figures
    for part in key.split("."):
        if not isinstance(value, Mapping) or part not in value:
            raise MissingFigure(key)
        value = value[part]
    return value


def load(results: Path) -> dict[str, dict[str, Any]]:
    """Every result file in ``results``, by script stem (``bench_pbp``)."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}


def provenance(record: Mapping[str, Any]) -> str:
    """``2026-11-28, host (2 cores, load 2.1), numpy 2.4.6, abc1234``: where a run's figures come from."""
    host = record.get("host", {})
    bits = [str(record.get("date", "?"))[:10],
            f"{host.get('name', '?')} ({host.get('cpus', '?')} cores, load {host.get('load_1min', '?')})",
            f"numpy {host.get('numpy', '?')}"]
    if record.get("commit"):
        bits.append(str(record["commit"]))
    return ", ".join(bits)


def render(records: Mapping[str, Mapping[str, Any]], figures: Sequence[Figure] = FIGURES) -> str:
    """The markdown block (markers included): the figures' table, then each run's command and provenance."""
    rows = ["| what | figure | script |", "|---|---|---|"]
    used: list[str] = []
    for f in figures:
        if f.script not in records:
            raise MissingFigure(f"{f.script}.json")
        value = lookup(records[f.script]["figures"], f.key)
        text = f.fmt.format(value) + (f" {f.unit}" if f.unit else "")
        rows.append(f"| {f.what} | {text} | `{f.script}` |")
        if f.script not in used:
            used.append(f.script)
    runs = [f"- `{s}`: `.venv/bin/python {records[s]['command']}`; {provenance(records[s])}" for s in used]
    return "\n".join([BEGIN, "", *rows, "", "Measured by (the command, then date, host, load, numpy, commit):", "",
                      *runs, "", END])


def update(doc: Path, block: str) -> bool:
    """Put ``block`` between the markers in ``doc``; True if the file changed."""
    text = doc.read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"figures: {doc}: no '{BEGIN[:28]}...' / '{END}' markers to write between")
    head, rest = text.split(BEGIN, 1)
    new = head + block + rest.split(END, 1)[1]
    if new != text:
        doc.write_text(new)
    return new != text


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", type=Path, default=RESULTS, help="the result files' folder (default: %(default)s)")
    ap.add_argument("--update", type=Path, default=None, metavar="DOC", help="write the table into DOC")
    args = ap.parse_args(argv)
    try:
        block = render(load(args.results))
    except MissingFigure as e:
        print(f"figures: {args.results}: no {e.args[0]} (run `make bench`, or the script, first)", file=sys.stderr)
        return 1
    if args.update is None:
        print(block)
    else:
        print(f"figures: {args.update} {'updated' if update(args.update, block) else 'unchanged'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
