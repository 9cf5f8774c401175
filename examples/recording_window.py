"""A window of a recording, read lazily: what the file holds (rec.info(), as `qradar info`),
the frames and targets of seconds START to END, their time from the recording's start, the
targets as a table (pandas when installed), and the tracks of a `--track` recording.

    .venv/bin/python examples/recording_window.py [recordings/chamber.mcap] [START_S] [END_S]
"""

import sys

import numpy as np

import qradar

path = sys.argv[1] if len(sys.argv) > 1 else "recordings/chamber.mcap"
start = float(sys.argv[2]) if len(sys.argv) > 2 else 1.0
end = float(sys.argv[3]) if len(sys.argv) > 3 else 3.0

info = qradar.open_recording(path).info()  # the summary and metadata only, as `qradar info --json`
print(f"{path}: {info['duration_s']:.1f} s, sensors {info['sensors']}, "
      + ", ".join(f"{t['kind']} {t['messages']}" for t in info["topics"] if t["kind"]))

rec = qradar.open_recording(path, topics=("raw", "targets", "tracks"), start=start, end=end)
raw = rec.raw()  # only the chunks of these seconds are read
print(f"window {start:g}-{end:g} s: raw {raw.data.shape}, t_s {raw.t_s.min():.2f} to {raw.t_s.max():.2f} s, "
      f"seq {int(raw.seq[0])} to {int(raw.seq[-1])}")

try:
    table = rec.to_pandas("targets")  # one row per target: sensor_id, seq, t_s, range_m, angle_deg, ...
    strongest = table[table["target"] == 0]
    print(f"targets table (pandas): {len(table)} rows; strongest target median range "
          f"{strongest['range_m'].median():.2f} m")
except qradar.ReplayError as exc:  # pandas not installed: the same columns as numpy arrays
    print(f"({exc})")
    table = rec.table("targets")
    first = table["target"] == 0
    print(f"targets table (numpy): {len(table['seq'])} rows; strongest target median range "
          f"{np.median(table['range_m'][first]):.2f} m")

if any(t["kind"] == "tracks" for t in info["topics"]):
    tracks = rec.tracks()  # one row per track and message
    ids = np.unique(tracks.track_id)
    print(f"tracks: {len(tracks)} messages, {len(tracks.track_id)} rows, track ids {ids.tolist()[:5]}")
else:
    print("tracks: none recorded (record with `qradar run --track`)")
