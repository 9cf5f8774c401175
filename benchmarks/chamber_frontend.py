#!/usr/bin/env python3
"""What the receiver front end ([frontend] of a scene: DC, leakage, receiver and I/Q
imbalance) does to today's pipeline, which does not calibrate: per true target the
position error and the angle bias, and what the extra detections are (the leakage near
0 m, I/Q ghosts at the mirrored range N dR - R, others).

Frames: the scene's in-process simulated sensor (the same frames as a simulated K-MD2
with the same seed), or the raw frames of a recording (``--recording``, e.g. one made by
``qradar run --record``). Each is quantized to 1 bit with dither (``--alpha``, delta
auto; ``--unquantized``: also the 12-bit frames themselves) and decoded with each
``--algos`` told K (the scene's count) and with K auto::

    .venv/bin/python benchmarks/chamber_frontend.py [--scenes chamber chamber-ideal] [--frames 400]
    .venv/bin/python benchmarks/chamber_frontend.py --recording out/run.mcap --scenes chamber

Prints one JSON object per scene and decoder. A true target's estimate is the detection
within ``--gate-m`` of its range (nearest); ``angle_bias_deg`` is the median of estimated
minus true angle over the frames where it is found; ``error_m`` the median and p90 of
the distance in the plane to the nearest detection (what ``qradar run`` reports).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pipeline.dsp.calibration import load as load_calibration
from pipeline.dsp.decode import DecoderConfig, decode_batch
from pipeline.dsp.localize import position_error_m
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from radar_driver.scene import SimScene, resolve_scene
from radar_driver.source import SimSourceConfig, SimulatedSource


def frames_of(scene: SimScene, n: int, recording: Path | None, seed: int) -> np.ndarray:
    """(B, M, 2) raw frames: simulated, or the first sensor's of a recording."""
    if recording is not None:
        from replay.source import RecordingSource
        with RecordingSource(recording, rate=None) as src:
            frames = list(src.frames(n))
        first = frames[0].sensor_id
        return np.stack([f.data for f in frames if f.sensor_id == first]).astype(np.complex128)
    with SimulatedSource(SimSourceConfig(scene, rate_hz=0.0, frames=n, seed=seed)) as src:
        return np.stack([f.data for f in src.frames()]).astype(np.complex128)


def classify(scene: SimScene, rng_m: np.ndarray, gate_m: float) -> dict[str, float]:
    """Detections per frame by kind: at a true target (within the gate of its range; PBP
    may put two on one reflector off the grid), leakage (below 2 range bins), I/Q ghosts
    (within the gate of N dR - R of a target), others."""
    radar = scene.radar
    present = ~np.isnan(rng_m)
    frames = rng_m.shape[0]
    truth = np.array([t.range_m for t in scene.targets])
    mirror = radar.max_range_m - truth
    near = lambda ref: present & (np.abs(rng_m[..., None] - ref).min(axis=-1, initial=np.inf) <= gate_m)  # noqa: E731
    target = near(truth) if truth.size else np.zeros_like(present)
    leakage = present & ~target & (rng_m < 2 * radar.range_resolution_m)
    ghost = (near(mirror) if truth.size else np.zeros_like(present)) & ~target & ~leakage
    other = present & ~target & ~leakage & ~ghost
    return {"detections": round(present.sum() / frames, 3), "at_targets": round(target.sum() / frames, 3),
            "leakage": round(leakage.sum() / frames, 3), "ghosts": round(ghost.sum() / frames, 3),
            "other": round(other.sum() / frames, 3)}


def per_target(scene: SimScene, det, gate_m: float) -> list[dict[str, float | None]]:
    out = []
    b = det.range_m.shape[0]
    for t in scene.targets:
        tr, ta = np.full((b, 1), t.range_m), np.full((b, 1), t.angle_deg)
        err = position_error_m(tr, ta, det.range_m, det.angle_deg)[:, 0]
        d = np.abs(det.range_m - t.range_m)
        d[np.isnan(d)] = np.inf
        j = np.argmin(d, axis=1)
        found = d[np.arange(b), j] <= gate_m
        bias = det.angle_deg[np.arange(b), j][found] - t.angle_deg
        out.append({"range_m": t.range_m, "angle_deg": t.angle_deg, "amplitude": t.amplitude,
                    "found": round(float(found.mean()), 3),
                    "error_m_median": round(float(np.median(err)), 3),
                    "error_m_p90": round(float(np.percentile(err, 90)), 3),
                    "angle_bias_deg": round(float(np.median(bias)), 2) if found.any() else None})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["chamber", "chamber-ideal"])
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--recording", type=Path, default=None, help="raw frames of this MCAP file instead")
    ap.add_argument("--alpha", type=float, default=0.5)
    ap.add_argument("--algos", nargs="+", default=["cml", "pbp"])
    ap.add_argument("--gate-m", type=float, default=0.6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--unquantized", action="store_true", help="also decode the 12-bit frames (no quantizer)")
    ap.add_argument("--calibration", type=Path, default=None,
                    help="remove the front end this `qradar calibrate` file measured (its first entry's sensor) "
                    "before quantizing, as the quantize node does")
    args = ap.parse_args()
    cal = None if args.calibration is None else load_calibration(args.calibration)
    for name in args.scenes:
        scene = resolve_scene(name)
        frames = frames_of(scene, args.frames, args.recording, args.seed)
        if cal is not None:
            sid, cid = next(iter(cal.entries))
            frames, ok = cal.apply(frames, [sid] * len(frames), np.full(len(frames), cid))
            if not ok.all():
                sys.exit(f"{args.calibration}: its entry is for frames of M = {cal.entries[sid, cid].m}, these have "
                         f"M = {frames.shape[1]}")
        inputs = {"1-bit": quantize_frames(frames, QuantizerConfig(alpha=args.alpha, dither_seed=args.seed),
                                           np.arange(len(frames)))}
        if args.unquantized:
            inputs["unquantized"] = frames
        k = max(1, len(scene.targets))
        for kind, z in inputs.items():
            for algo in args.algos:
                for auto in (False, True):
                    det = decode_batch(z, scene.radar, 4 if auto else k, DecoderConfig(algo=algo, auto_k=auto))
                    print(json.dumps({"scene": scene.name, "frames": len(frames), "input": kind, "algo": algo,
                                      "calibration": None if cal is None else str(args.calibration),
                                      "alpha": args.alpha if kind == "1-bit" else None, "K": "auto" if auto else k,
                                      "targets": per_target(scene, det, args.gate_m),
                                      "per_frame": classify(scene, det.range_m, args.gate_m)}), flush=True)


if __name__ == "__main__":
    main()
