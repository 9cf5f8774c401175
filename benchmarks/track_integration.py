#!/usr/bin/env python3
"""Static tracks get sharper with time (issue 25): two figures, one PNG and one JSON.

1. **The chamber through the tracker**: the shipped `chamber` scene (two static
   reflectors off the range grid, sensor noise, the front end removed by
   recordings/chamber-cal.json as `qradar run --calibration` does), 1-bit dithered at the
   default alpha, decoded frame by frame by the default decoder (cml, K = 2, the live
   range gate), then tracked with ``--integrate S`` for each S: the median position error
   of the static tracks once S seconds of frames are integrated (frames from S + 1 s on;
   S = 0: the filter alone), pooled over both reflectors and ``--seeds`` noise seeds;
   beside it the per-frame targets' median.
2. **The Monte Carlo in time** (:func:`pipeline.dsp.integrate.time_monte_carlo`, also
   ``qradar montecarlo-time``): random static scenes (one target, continuous range in
   [3, 150] m, |angle| <= 60 deg), T frames each with a fresh dither (and fresh noise),
   decoded together for T = 1 .. 32: median error against T, with noise sigma = 0.1 of the
   amplitude and without, and the slope of log(median) against log(T).

    .venv/bin/python benchmarks/track_integration.py [--seeds 3] [--runs 40] [--out out/track]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from pipeline.dsp.calibration import load as load_calibration
from experiments.plots import draw_error_vs_frames
from pipeline.dsp.decode import DecoderConfig, decode_batch
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.integrate import time_monte_carlo
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.dsp.track import TrackerConfig
from pipeline.nodes.tracker import Integration, Tracker, track_batch
from pipeline.wire import FrameHeaders, decode_tracks
from radar_driver.scene import ramp_time_s, resolve_scene

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 20.0
SECONDS = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0)
FRAMES_T = (1, 2, 4, 8, 16, 32)


def chamber(seeds: int, seconds=SECONDS) -> dict:
    scene = resolve_scene("chamber")
    radar = scene.radar
    cal = load_calibration(ROOT / "recordings" / "chamber-cal.json")
    gate = RangeGate.default(radar)
    n = int((max(seconds) + 2.0) * RATE_HZ)
    rpf = radar.ramps_per_frame
    truth = scene.truth()
    tx = np.array([t["x_m"] for t in truth])
    ty = np.array([t["y_m"] for t in truth])
    errors = {s: [] for s in seconds}
    frame_errors = []
    for seed in range(seeds):
        t = ramp_time_s(np.arange(n * rpf), RATE_HZ * rpf)
        raw = scene.ramps(t, np.random.default_rng(100 + seed)).reshape(n, rpf * radar.samples_per_ramp, 2)
        frames, ok = cal.apply(raw, ["kmd2-0"] * n, np.full(n, radar.config_id()))
        assert ok.all()
        q = quantize_frames(frames, QuantizerConfig(), np.arange(n, dtype=np.uint64), dither_seed=seed)
        det = decode_batch(q, radar, 2, DecoderConfig(gate=gate))
        frame_errors += np.hypot(det.x_m[:, :, None] - tx, det.y_m[:, :, None] - ty).min(axis=1).ravel().tolist()
        headers = FrameHeaders(["kmd2-0"] * n, np.arange(n, dtype=np.uint64),
                               (np.arange(n) * (1e9 / RATE_HZ)).astype(np.int64), np.zeros(n, dtype=np.uint32))
        for s in seconds:
            tracker = Tracker(TrackerConfig(integrate_s=s), Integration(2, gate))
            msgs = [decode_tracks(p) for p in track_batch(tracker, headers, det, q, radar)]
            for i in range(int((s + 1.0) * RATE_HZ), n):
                for x, y in zip(tx, ty):
                    d = [np.hypot(k["x_m"] - x, k["y_m"] - y) for k in msgs[i].tracks if k["static"]]
                    if d and min(d) < 1.0:
                        errors[s].append(min(d))
        print(f"chamber seed {seed}: done", file=sys.stderr, flush=True)
    return {"seconds": list(seconds), "median_m": [float(np.median(errors[s])) for s in seconds],
            "p90_m": [float(np.percentile(errors[s], 90)) for s in seconds],
            "samples": [len(errors[s]) for s in seconds], "per_frame_target_median_m": float(np.median(frame_errors)),
            "seeds": seeds}


def plot(ch: dict, mcs: list[dict], path: Path) -> None:
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.8))
    s = np.array(ch["seconds"])
    x = np.where(s == 0, 0.05, s)
    a1.loglog(x, ch["median_m"], "o-", label="static tracks, median")
    a1.loglog(x, ch["p90_m"], "s--", alpha=0.6, label="static tracks, 90th percentile")
    a1.axhline(ch["per_frame_target_median_m"], color="gray", ls=":", label="targets of one frame, median")
    a1.axhline(0.03, color="red", ls="-.", lw=0.8, label="goal after 1 s: 0.03 m")
    a1.set_xticks(x, ["filter\nonly"] + [f"{v:g}" for v in s[1:]])
    a1.set_xlabel("--integrate, s (20 frames a second)")
    a1.set_ylabel("position error, m")
    a1.set_title(f"chamber (calibrated), 1 bit: {ch['seeds']} seeds, both reflectors")
    a1.grid(True, which="both", alpha=0.3)
    a1.legend(fontsize=8)
    draw_error_vs_frames(a2, mcs, f"Monte Carlo in time: 1 target off the grid, {mcs[0]['runs']} runs")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="chamber noise seeds")
    ap.add_argument("--runs", type=int, default=40, help="Monte Carlo runs per noise level")
    ap.add_argument("--out", type=Path, default=Path("out/track"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    ch = chamber(args.seeds)
    mcs = [time_monte_carlo(args.runs, FRAMES_T, s) for s in (0.1, 0.0)]
    result = {"chamber": ch, "monte_carlo": mcs, "seconds": round(time.monotonic() - t0, 1)}
    (args.out / "integration.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(ch, mcs, args.out / "integration.png")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
