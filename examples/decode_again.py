"""Re-quantize a recording's raw frames with another dither scale and decode them with
each decoder: the offline question "what would alpha = 0.3 and cml have given?".

    .venv/bin/python examples/decode_again.py [recordings/chamber.mcap] [alpha]
"""

import sys

import numpy as np

import qradar

path = sys.argv[1] if len(sys.argv) > 1 else "recordings/chamber.mcap"
alpha = float(sys.argv[2]) if len(sys.argv) > 2 else 0.3
rec = qradar.open_recording(path)
raw = rec.raw()
true_range, true_angle, _ = rec.scene().arrays(0.0)
truth = np.repeat(true_range, len(raw), 0), np.repeat(true_angle, len(raw), 0)

codes = qradar.quantize(raw, alpha=alpha, bits=1)  # the dither the stream would draw for these frames
for algo in ("pbp", "cml"):
    det = qradar.decode(codes, rec.radar, k=true_range.shape[1], algo=algo)  # Detections, (F, K) arrays
    err = qradar.position_error_m(*truth, det.range_m, det.angle_deg)
    print(f"1-bit alpha {alpha:.2f} {algo}: median error {np.median(err):.3f} m, worst target mean "
          f"{err.mean(axis=0).max():.3f} m")
det = qradar.decode(raw, rec.radar, k=true_range.shape[1], algo="cml")  # the unquantized frames
print(f"unquantized cml: median error {np.median(qradar.position_error_m(*truth, det.range_m, det.angle_deg)):.3f} m")
