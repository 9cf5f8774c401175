"""A recording as numpy arrays: its raw and quantized frames, the targets the localizer
published, their error against the simulated scene's truth, and the latency.

    .venv/bin/python examples/recording_arrays.py [recordings/chamber.mcap]
"""

import sys

import numpy as np

import qradar

path = sys.argv[1] if len(sys.argv) > 1 else "recordings/chamber.mcap"
rec = qradar.open_recording(path)
print(f"{path}: sensors {rec.sensors}, radar M = {rec.radar.samples_per_ramp * rec.radar.ramps_per_frame}")

raw = rec.raw()  # Frames: data (F, M, 2) complex64, seq (F,), timestamp_ns (F,)
quantized = rec.quantized()  # Quantized: frames.codes (F, M, 2, 2) int (antenna, re/im), delta (F,), alpha (F,)
targets = rec.targets()  # Targets: range_m, angle_deg, x_m, y_m (F, K), NaN-padded; count (F,)
print(f"raw {raw.data.shape} {raw.data.dtype}, quantized {quantized.frames.codes.shape} (bits "
      f"{quantized.frames.bits}, alpha {quantized.frames.alpha[0]:.2f}), targets {targets.range_m.shape} by "
      f"{targets.algo}")

true_range, true_angle, _ = rec.scene().arrays(0.0)  # (1, K) each: the scene is static
errors = qradar.position_error_m(np.repeat(true_range, len(targets), 0), np.repeat(true_angle, len(targets), 0),
                                 np.nan_to_num(targets.range_m, nan=1e9), np.nan_to_num(targets.angle_deg))
latency_ms = (targets.published_ns - targets.timestamp_ns) / 1e6
print(f"published targets: median error {np.median(errors):.3f} m per true target over {len(targets)} frames; "
      f"latency p50 {np.median(latency_ms):.1f} ms")
print(f"health messages: {len(rec.health())}")
