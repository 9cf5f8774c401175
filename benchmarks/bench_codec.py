#!/usr/bin/env python3
"""K-MD2 StreamDecoder on adversarial garbage: is resync linear, and how fast?

For each kind of garbage (header-like bytes everywhere, nothing valid), the best of
``--repeat`` runs of feeding 1 MiB at once and in 4 KiB chunks, with:

- ``cpu ms``: the process's CPU time, and ``wall ms`` (target: well under 50 ms for
  1 MiB at once; on a shared host the CPU time is the steadier figure);
- ``x valid``: the CPU time over that of decoding 1 MiB of valid ramps (RADC + DONE)
  the same way, measured in the same process: the baseline;
- ``t 1M/64K``: CPU time of 1 MiB over that of 64 KiB (linear: about 16; the old decoder,
  which rescanned the buffer once per skipped byte, took 23-63 s for 256 KiB);
- ``w 1M/64K``: the same ratio of work, ``stats.scanned_bytes`` (what the tests assert),
  and ``w/B``: bytes examined per byte fed.

    .venv/bin/python benchmarks/bench_codec.py [--repeat 5] [--json]

The figures (``harness.emit``: after the table, or alone with ``--json``) are keyed by
``<garbage>_<feed>`` (``random_one_feed``, ``radc_headers_4kib_chunks`` ...) under each column.
"""

from __future__ import annotations

import argparse

import numpy as np

from harness import emit, time_calls
from radar_driver.profile import DEFAULT_PROFILE
from radar_driver.protocol import Done, Radc, StreamDecoder, encode

MIB, SMALL, CHUNK = 1 << 20, 64 << 10, 4096


def garbage_kinds(size: int, seed: int = 0) -> dict[str, bytes]:
    """Adversarial garbage of ``size`` bytes by name (the kinds tests/test_protocol.py uses)."""
    def rep(unit: bytes) -> bytes:
        return (unit * (size // len(unit) + 1))[:size]

    rng = np.random.default_rng(seed)
    return {
        "random": rng.integers(0, 256, size, dtype=np.uint8).tobytes(),
        "radc headers": rep(b"RADC\x00\x08\x00\x00"),  # plausible length, payload fails at once
        "radc failing late": rep(b"RADC\x00\x08\x00\x00" + bytes(2040) + b"\xff\xff"),
        "rmrd headers": rep(b"RMRD\x00\x40\x00\x00"),  # stray headers inside each other
        "resp bad padding": rep(b"RESP\x04\x00\x00\x00\x00\xff\xff\xff"),
        "truncated headers": rep(b"RADRESDONGNFDONRMRPDATDA"),
        "all headers": rep(b"".join(DEFAULT_PROFILE.plausible_length())),
        "implausible lengths": rep(b"DONE\xff\xff\xff\xff"),
    }


def valid_ramps(size: int, seed: int = 0) -> bytes:
    """About ``size`` bytes of valid ramps (RADC + DONE, 2068 bytes each)."""
    rng = np.random.default_rng(seed)
    words = rng.integers(0, 4096, (64, *DEFAULT_PROFILE.radc.words_shape)).astype(np.uint16)
    n = size // 2068
    return b"".join(encode(Radc(words[i % 64])) + encode(Done(i)) for i in range(n))


def run(data: bytes, chunk: int | None, repeat: int) -> tuple[float, float, StreamDecoder]:
    """Best CPU and wall times (s) of decoding ``data`` fed in ``chunk``-byte pieces (None:
    at once), and the last decoder."""
    step = chunk or len(data)
    pieces = [data[i : i + step] for i in range(0, len(data), step)]
    decoders: list[StreamDecoder] = []

    def feed_all() -> None:
        decoders.append(d := StreamDecoder())
        for p in pieces:
            d.feed(p)

    t = time_calls(feed_all, repeat)
    return float(t.cpu_s.min()), float(t.wall_s.min()), decoders[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5, help="runs per figure; the best is kept")
    ap.add_argument("--json", action="store_true", help="print the figures (JSON) only, not the table")
    args = ap.parse_args()
    big, small = garbage_kinds(MIB), garbage_kinds(SMALL)
    valid = valid_ramps(MIB)
    base = {c: run(valid, c, args.repeat)[0] for c in (None, CHUNK)}
    rows = []
    for name in big:
        for chunk in (None, CHUNK):
            t_big, wall, d_big = run(big[name], chunk, args.repeat)
            t_small, _, d_small = run(small[name], chunk, args.repeat)
            rows.append({"garbage": name, "feed": "1 feed" if chunk is None else "4 KiB",
                         "cpu_ms": t_big * 1e3, "wall_ms": wall * 1e3, "x_valid": t_big / base[chunk],
                         "time_ratio": t_big / t_small,
                         "work_ratio": d_big.stats.scanned_bytes / d_small.stats.scanned_bytes,
                         "work_per_byte": d_big.stats.scanned_bytes / d_big.stats.bytes_in,
                         "skipped": d_big.stats.skipped_bytes, "invalid": d_big.stats.invalid})
    worst = max(r["cpu_ms"] for r in rows if r["feed"] == "1 feed")
    figures = figures_of(base, rows, worst, len(valid) // 2068)
    if args.json:
        emit(figures)
        return
    print(f"baseline: 1 MiB of valid ramps decodes in {base[None] * 1e3:.1f} ms CPU at once, "
          f"{base[CHUNK] * 1e3:.1f} ms in 4 KiB chunks ({len(valid) // 2068 / base[CHUNK]:,.0f} ramps/s)")
    print(f"{'garbage (1 MiB)':22s} {'feed':>7s} {'cpu ms':>7s} {'wall ms':>8s} {'x valid':>8s} {'t 1M/64K':>9s} "
          f"{'w 1M/64K':>9s} {'w/B':>5s} {'invalid':>8s}")
    for r in rows:
        print(f"{r['garbage']:22s} {r['feed']:>7s} {r['cpu_ms']:7.1f} {r['wall_ms']:8.1f} {r['x_valid']:8.2f} "
              f"{r['time_ratio']:9.1f} {r['work_ratio']:9.1f} {r['work_per_byte']:5.2f} {r['invalid']:8d}")
    print(f"worst 1 MiB in one feed: {worst:.1f} ms CPU (target: well under 50 ms); linear: ratios about 16")
    emit(figures)


def figures_of(base: dict, rows: list[dict], worst_ms: float, ramps: int) -> dict:
    """The table's figures, two levels: each column keyed ``<garbage>_<feed>`` (feed
    ``one_feed``: 1 MiB at once; ``4kib_chunks``: in 4 KiB chunks)."""
    def key(r: dict) -> str:
        return r["garbage"].replace(" ", "_") + ("_one_feed" if r["feed"] == "1 feed" else "_4kib_chunks")

    col = lambda name, digits: {key(r): round(r[name], digits) for r in rows}  # noqa: E731
    return {
        "valid_1mib_cpu_ms": {"one_feed": round(base[None] * 1e3, 3), "4kib_chunks": round(base[CHUNK] * 1e3, 3)},
        "valid_ramps_per_s_4kib_chunks": round(ramps / base[CHUNK]),
        "worst_one_feed_cpu_ms": round(worst_ms, 3),
        "cpu_ms": col("cpu_ms", 3), "wall_ms": col("wall_ms", 3),
        "ratio_cpu_to_valid": col("x_valid", 3),
        "ratio_cpu_1mib_to_64kib": col("time_ratio", 2), "ratio_work_1mib_to_64kib": col("work_ratio", 2),
        "scanned_bytes_per_byte": col("work_per_byte", 3),
        "skipped_bytes": col("skipped", 0), "invalid": col("invalid", 0),
    }


if __name__ == "__main__":
    main()
