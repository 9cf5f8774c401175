"""What a recording's index costs, as docs/recording.md documents it, checked on a real recording
(``qradar run --sensors 3 --record``) with the measurement of ``benchmarks/bench_record.py
--index``: the index records in the file and what the ``mcap`` writer keeps in memory
until the file ends, per chunk (issue 28: 2-4 KB a chunk, where ~1 KB was documented)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def bench_record():
    import bench_record

    return bench_record


def documented() -> tuple[tuple[int, int, int], tuple[float, int]]:
    """((B a message, B a channel, B a chunk) in the file, (KB a chunk, B a channel) in
    memory), as docs/recording.md states them."""
    text = (ROOT / "docs" / "recording.md").read_text()
    text = " ".join(text.split())  # the sentences wrap
    f = re.search(r"\*\*(\d+) B a message plus (\d+) B a channel plus (\d+) B a chunk\*\*", text)
    m = re.search(r"\*\*at most ([\d.]+) KB a chunk plus (\d+) B a channel in it\*\*", text)
    assert f and m, "docs/recording.md no longer states the index's cost in the words this test reads"
    return tuple(int(x) for x in f.groups()), (float(m.group(1)), int(m.group(2)))


def test_the_documented_index_cost_holds_on_a_real_recording(tmp_path):
    (per_msg, per_channel, per_chunk), (mem_kb, mem_channel) = documented()
    bench = bench_record()
    path = tmp_path / "run.mcap"
    bench.record_run(path, sensors=3, seconds=6)
    cost = bench.index_cost(path)
    print(cost)
    assert cost["chunks"] >= 4 and cost["channels"] == 18  # raw, quantized, targets, pointcloud, profile, health x 3
    channels, messages = cost["message_index_records_per_chunk"], cost["messages_per_chunk"]
    assert channels >= 10 and messages >= 100
    # in the file: exact record sizes (the averages per chunk are rounded to 0.1)
    file_bound = per_msg * messages + per_channel * channels + per_chunk
    assert cost["file_index_bytes_per_chunk"] <= file_bound + 5, (cost, file_bound)
    assert cost["file_index_bytes_per_chunk"] >= 0.9 * file_bound, (cost, file_bound)  # not a loose bound either
    # in memory until the file ends
    memory_bound = 1000 * mem_kb + mem_channel * channels
    assert 0 < cost["memory_index_bytes_per_chunk"] <= memory_bound, (cost, memory_bound)
    assert cost["memory_index_bytes_per_chunk"] >= 0.6 * memory_bound, (cost, memory_bound)
