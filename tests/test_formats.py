"""One definition per format (pipeline/wire/fields.py): the writers, the readers' checks,
the JSON Schemas, the Foxglove point and the docs' tables are made from it, so a field
added to the definition is written, read, in the schema, in the Foxglove conversion and in
the docs' table with nothing else changed; and the schemas written into recordings come
from the package, not from docs/ beside it."""

import base64
import json
import shutil
import subprocess
import sys
from dataclasses import fields as dataclass_fields
from pathlib import Path

import numpy as np
import pytest

from pipeline.dsp.localize import Detections
from pipeline.wire import (FrameHeaders, HealthMsg, TargetsMsg, TracksMsg, decode_health, decode_targets,
                           decode_tracks, encode_targets_batch)
from pipeline.wire.fields import HEALTH, TARGETS, TRACKS, Field, field_table, json_schema, point_fields, with_tables
from pipeline.wire.foxglove import pointcloud_json, target_points
from pipeline.wire.messages import TargetColumns
from mcap.reader import make_reader

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("radar_driver", "pipeline", "replay", "qradar")

#: what a later issue adds to a target: one line of the definition
EXTRA = Field("snr_db", "number", "dB", "signal to noise ratio of the target", optional=True)


def test_the_docs_tables_are_the_definitions():
    text = (ROOT / "docs" / "wire-formats.md").read_text()
    assert text.count("<!-- fields:") == 6
    assert with_tables(text) == text, ("docs/wire-formats.md's field tables differ from pipeline/wire/fields.py: "
                                       "`python -m pipeline.wire.fields docs/wire-formats.md` rewrites them")


def test_the_message_classes_hold_the_definitions_fields():
    assert [f.name for f in dataclass_fields(HealthMsg)] == ["node", "sensor_id", "timestamp_ns", "frames_in",
                                                            "frames_out", "drops", "decode_errors", "latency_ms",
                                                            "bytes_in_per_s", "bytes_out_per_s", "extra",
                                                            "invalid_frames", "processing_errors", "frames_missing",
                                                            "seq_resets", "worker_restarts", "over_budget",
                                                            "refused", "implausible_seq", "denied_puts"]
    assert {f.name for f in dataclass_fields(HealthMsg)} == set(HEALTH.names[2:])
    det = {f.name for f in dataclass_fields(Detections)}
    assert set(TARGETS.item_names) <= det  # what the localizer writes has every target field


def _targets(fmt, with_extra: bool):
    t = {"range_m": 10.0, "angle_deg": 30.0, "x_m": 8.66025404, "y_m": 5.0, "amplitude": 0.5, "statistic_db": 21.5}
    if with_extra:
        t["snr_db"] = -1.25
    return TargetsMsg("s0", 4, 123, 7, "cml", 2, "quantized", [t, {k: v for k, v in t.items() if k != "statistic_db"}])


def test_a_target_field_added_to_the_definition_is_enough():
    fmt = TARGETS.with_item(EXTRA)  # the one-line change, on a copy
    msg = _targets(fmt, True)
    # written (one frame, and a batch of detections that carry it), and read back
    payload = msg.to_json(fmt)
    assert b'"snr_db":-1.25' in payload
    back = decode_targets(payload, "radar/s0/targets", fmt)
    assert back == msg and back.targets[0]["snr_db"] == -1.25
    cols = TargetColumns.of(msg.targets, fmt)
    heads = FrameHeaders(["s0"], [4], [123], [7])
    assert encode_targets_batch(heads, cols, "cml", 2, "quantized", 0, fmt=fmt) == [msg.to_json(fmt)]
    # optional: absent where not finite, and a writer whose detections lack it writes none
    cols.snr_db[0, 1] = np.nan
    assert encode_targets_batch(heads, cols, "cml", 2, "quantized", 0, fmt=fmt)[0].count(b"snr_db") == 1
    assert b"snr_db" not in _targets(fmt, False).to_json(fmt)
    # checked when read: a bad value is a WireError naming it
    with pytest.raises(ValueError, match="target field snr_db='fast' is not a number"):
        decode_targets(payload.replace(b"-1.25", b'"fast"'), "radar/s0/targets", fmt)
    # in the JSON Schema, with its unit
    item = json_schema(fmt)["properties"]["targets"]["items"]
    assert item["properties"]["snr_db"] == {"type": "number", "description":
                                                          "signal to noise ratio of the target (dB)"}
    assert "snr_db" not in item["required"]
    # in the Foxglove point (recordings' JSON point cloud, the live view's protobuf one)
    assert point_fields(fmt)[-1] == "snr_db"
    assert target_points(msg, fmt)["snr_db"].tolist() == [-1.25, -1.25]
    cloud = json.loads(pointcloud_json(msg, fmt=fmt))
    assert cloud["fields"][-1] == {"name": "snr_db", "offset": 4 * len(point_fields(fmt)) - 4, "type": 7}
    pts = np.frombuffer(base64.b64decode(cloud["data"]), dtype=np.dtype([(f, "<f4") for f in point_fields(fmt)]))
    assert pts["snr_db"].tolist() == [-1.25, -1.25] and cloud["point_stride"] == 4 * len(point_fields(fmt))
    # in the docs' table
    assert "| `snr_db` | number | dB | yes | signal to noise ratio of the target" in field_table(fmt, True)
    # and the definition itself still writes today's bytes (tests/test_wire_golden.py has them all)
    assert msg.to_json() == _targets(TARGETS, False).to_json()


def test_a_track_field_added_to_the_definition_is_enough():
    fmt = TRACKS.with_item(Field("sigma_v_mps", "number", "m/s", "velocity standard deviation"))
    track = {"track_id": 3, "range_m": 5.0, "angle_deg": 0.0, "x_m": 5.0, "y_m": 0.0, "vx_mps": 1.0, "vy_mps": 0.0,
             "sigma_m": 0.1, "age_s": 2.0, "hits": 7, "static": False, "sigma_v_mps": 0.25}
    msg = TracksMsg("s0", 9, 99, [track], 100)
    payload = msg.to_json(fmt)
    assert payload.endswith(b'"static":false,"sigma_v_mps":0.25}]}')
    assert decode_tracks(payload, "k", fmt) == msg
    with pytest.raises(ValueError, match="missing field sigma_v_mps"):  # required: a track without it is refused
        decode_tracks(TracksMsg("s0", 9, 99, [{k: v for k, v in track.items() if k != "sigma_v_mps"}], 100)
                      .to_json(), "k", fmt)
    assert "sigma_v_mps" in json_schema(fmt)["properties"]["tracks"]["items"]["required"]
    assert "| `sigma_v_mps` | number | m/s |  | velocity standard deviation |" in field_table(fmt, True)


def test_a_health_field_added_to_the_definition_is_written_and_read():
    """Health's fields are HealthMsg's (checked above): a new counter is a line in each."""
    fmt = HEALTH.with_field(Field("late_frames", "integer", doc="frames later than their deadline", optional=True,
                                  default=0, minimum=0))

    class Health(HealthMsg):  # the class's line, on a copy
        late_frames: int = 0

    msg = HealthMsg("localize", "s0", 5, 10)
    msg.__class__ = Health
    msg.late_frames = 4
    payload = msg.to_json(fmt)
    assert payload.endswith(b'"denied_puts":0,"late_frames":4}')
    assert json_schema(fmt)["properties"]["late_frames"]["minimum"] == 0
    assert decode_health(payload, "k") == HealthMsg("localize", "s0", 5, 10)  # today's reader: an unknown field ignored


def _schemas(path: Path) -> dict[str, tuple[str, str, bytes]]:
    """Each channel's schema (name, encoding, data) by its topic, as mcap's own reader reads them."""
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    return {ch.topic.rsplit("/", 1)[-1]: (summary.schemas[ch.schema_id].name, summary.schemas[ch.schema_id].encoding,
                                          bytes(summary.schemas[ch.schema_id].data))
            for ch in summary.channels.values()}


#: writes one message of every channel a recording may hold into sys.argv[1], with the replay package imported
#: from where Python finds it (printed first)
WRITE_ONE_OF_EACH = """
import sys
import replay.mcapio as m
print(m.__file__)
sink = m.McapSink(sys.argv[1])
for topic in ("raw", "quantized", "targets", "tracks", "health", "pointcloud", "scene", "profile"):
    sink.write(f"radar/s0/{topic}", b"{}", 1, 1, 0)
sink.close()
"""


def test_the_schemas_come_from_the_package_not_from_docs(tmp_path):
    """The packages copied alone into a folder (no docs/, no checkout beside them), as an
    installed wheel holds them: the schemas they write into a recording are byte for byte
    those the checkout writes, and each is the definition's."""
    alone = tmp_path / "site"
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, alone / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    runs = {}
    for name, path in (("alone", alone), ("checkout", ROOT)):
        out = tmp_path / f"{name}.mcap"
        proc = subprocess.run([sys.executable, "-c", WRITE_ONE_OF_EACH, str(out)], capture_output=True, text=True,
                              timeout=120, cwd=tmp_path, env={"PYTHONPATH": str(path), "PATH": "/usr/bin:/bin"})
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert Path(proc.stdout.split()[0]).is_relative_to(path), proc.stdout  # imported from there
        runs[name] = _schemas(out)
    assert not (alone / "docs").exists() and runs["alone"] == runs["checkout"]
    got = runs["alone"]
    assert set(got) == {"raw", "quantized", "targets", "tracks", "health", "pointcloud", "scene", "profile"}
    for topic, fmt in (("targets", TARGETS), ("tracks", TRACKS), ("health", HEALTH)):
        assert got[topic] == (fmt.title, "jsonschema", json.dumps(json_schema(fmt)).encode())
    assert got["raw"][:2] == ("qradar.RawFrame", "qradar/wire-v1")
    layout = json.loads(got["quantized"][2])
    assert [h["name"] for h in layout["header"]][-3:] == ["dither_seed", "alpha", "delta"]
    assert layout["header_bytes"] == 64 and layout["magic"] == "QRDR"
    assert got["scene"][0] == "foxglove.SceneUpdate" and got["profile"][0] == "qradar.RangeProfile"


def test_a_target_field_added_to_the_definition_reaches_the_web_page():
    """qradar/web/events.py sends the page every field the wire decoder kept: the new one under its own name."""
    from qradar.web.events import targets_event

    fmt = TARGETS.with_item(EXTRA)
    msg = decode_targets(_targets(fmt, True).to_json(fmt), "radar/s0/targets", fmt)
    first = targets_event(msg, None)["targets"][0]
    assert first["snr_db"] == -1.25
    assert {k: first[k] for k in ("r", "a", "amp", "stat")} == {"r": 10.0, "a": 30.0, "amp": 0.5, "stat": 21.5}
    assert "x_m" not in first and first["x"] == pytest.approx(8.66, abs=1e-3)
    today = decode_targets(_targets(fmt, True).to_json(fmt), "radar/s0/targets")  # read with today's definition
    assert "snr_db" not in targets_event(today, None)["targets"][0]
