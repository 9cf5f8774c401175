"""What a recording holds, at a glance (``qradar info``, ``Recording.info()``): its sensors,
topics with message counts and rates, time span, the radar, quantizer, decoder, calibration
and truth it was made with, the losses it recorded, whether it was recovered, and the other
files of a split recording.

:func:`describe` reads the summary section and the metadata records only (no chunk), so an
hour of recording is described in milliseconds; a file without a summary (cut short by a
kill, its summary damaged) is read whole, every chunk's CRC checked, and says so. With
``check`` every chunk is read and checked in any case (as ``qradar record --verify``).
:func:`format_info` is the text the command prints.
"""

from __future__ import annotations

import json
import re
import time
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path

from pipeline.keys import DERIVED_TOPICS
from pipeline.wire import TOPICS

from .mcapread import McapFile

#: a split recording's later files: <stem>_0001.mcap, _0002, ... (replay.recorder)
SPLIT_PART = re.compile(r"^(?P<stem>.+)_(?P<part>\d{4})$")
#: log times from this on are ns since the epoch (wall clock); below, another clock
EPOCH_NS = 10**15
#: the metadata records :func:`describe` reads into its own sections
KNOWN_METADATA = ("qradar.versions", "qradar.recorder", "qradar.radar", "qradar.quantizer", "qradar.localizer",
                  "qradar.sensors", "qradar.calibration", "qradar.scene", "qradar.simulated_scene",
                  "qradar.recorder_counters", "qradar.recovery")


#: where a recording names when its truth's clock began: a real sensor's run its start (one
#: time), a split set's later file each sensor's first raw frame (by sensor), in that order
TRUTH_CLOCK_KEYS = (("qradar.scene", "truth_t0_ns"), ("qradar.recorder", "first_raw_ns"))


def truth_clocks(metadata: dict[str, dict[str, str]]) -> tuple:
    """The values of :data:`TRUTH_CLOCK_KEYS` in a recording's ``metadata``, each parsed once
    (None: absent or not JSON), for :func:`named_clock_ns`."""
    out = []
    for name, key in TRUTH_CLOCK_KEYS:
        try:
            out.append(json.loads(metadata[name][key]))
        except (KeyError, TypeError, ValueError, RecursionError):
            out.append(None)
    return tuple(out)


def named_clock_ns(clocks: tuple, sensor_id: str, first_ns: int) -> int | None:
    """When the truth's clock of ``sensor_id`` began (ns), as a recording's :func:`truth_clocks`
    name it, its first frame in the file at ``first_ns``: ``first_ns`` for a later file's sensor
    its recorder does not name (it began in that file); None: not named, or no time at or
    before ``first_ns``."""
    for named in clocks:
        start = named.get(sensor_id, first_ns) if isinstance(named, dict) else named
        if isinstance(start, int) and not isinstance(start, bool) and 0 <= start <= first_ns:
            return start
    return None


def _value(text: str):
    """A metadata value: JSON when it is (numbers, lists, objects, true/false, null), else the text."""
    try:
        return json.loads(text)
    except (TypeError, ValueError, RecursionError):  # RecursionError: a crafted value nested beyond the parser
        return text


def _values(entries: dict[str, str] | None) -> dict | None:
    return None if entries is None else {k: _value(v) for k, v in entries.items()}


def clock(ns: int | None) -> dict | None:
    """A log time as UTC and local time (ISO 8601, ms); None when it is not wall-clock ns."""
    if ns is None or ns < EPOCH_NS:
        return None
    s = ns / 1e9
    return {"ns": ns, "utc": datetime.fromtimestamp(s, timezone.utc).isoformat(timespec="milliseconds")
            .replace("+00:00", "Z"),
            "local": datetime.fromtimestamp(s).astimezone().isoformat(timespec="milliseconds")}


def split_files(path: Path) -> list[str]:
    """The files of the split recording ``path`` belongs to (``NAME.mcap``, ``NAME_0001.mcap``,
    ...), those present beside it, in order; just ``path`` when it is not split."""
    m = SPLIT_PART.match(path.stem)
    stem = m.group("stem") if m else path.stem
    parts = sorted(p for p in path.parent.glob(f"{glob_escape(stem)}_[0-9][0-9][0-9][0-9].mcap")
                   if SPLIT_PART.match(p.stem) and SPLIT_PART.match(p.stem).group("stem") == stem)
    first = path.with_name(f"{stem}.mcap")
    files = ([first] if first.exists() else []) + parts
    return [str(p) for p in files] if len(files) > 1 or path not in files else [str(path)]


def split_note(path: str | Path, command: str) -> str | None:
    """One line when ``path`` is one file of a split recording (:func:`split_files`): which, of
    how many, and that ``command`` reads it alone; None for a file that is not split."""
    path = Path(path)
    files = split_files(path)
    if len(files) < 2:
        return None
    names = [Path(f).name for f in files]
    at = names.index(path.name) + 1 if path.name in names else "?"
    return (f"note: {path} is file {at} of the {len(files)} of a split recording ({', '.join(names)}); {command} "
            "reads this file alone (each file of the set is a complete recording)")


def glob_escape(text: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", text)


def _parts(topic: str) -> tuple[str | None, str | None]:
    """(sensor id, topic kind) of a qradar key ``<prefix>/<sensor>/<kind>``, else (None, None)."""
    bits = topic.rsplit("/", 2)
    if len(bits) == 3 and bits[2] in TOPICS + DERIVED_TOPICS:
        return bits[1], bits[2]
    return None, None


def describe(path: str | Path, check: bool = False) -> dict:
    """What the recording ``path`` holds (see the module's docstring), JSON-ready. ``check``:
    read every chunk (CRC checked) and report the damage found. Not MCAP: NotMcapError;
    unreadable: ReplayError."""
    t0 = time.perf_counter()
    path = Path(path)
    f = McapFile(path)
    summary = f.read_index()
    counts: Counter[int] = Counter()
    start_ns = end_ns = None
    chunks = []
    if summary is not None:
        stats = summary.statistics
        counts.update(stats.channel_message_counts if stats else {})
        if stats and stats.message_count:
            start_ns, end_ns = stats.message_start_time, stats.message_end_time
        chunks = summary.chunk_indexes
    read: Counter[int] = Counter()
    if check or summary is None:  # every chunk read, its CRC checked
        for ch, msg in f.messages():
            read[ch.id] += 1
            if summary is None:
                start_ns = msg.log_time if start_ns is None else min(start_ns, msg.log_time)
                end_ns = msg.log_time if end_ns is None else max(end_ns, msg.log_time)
        if summary is None:
            counts = read
    how = "checked" if check else "summary" if summary is not None else "read whole"
    duration_s = (end_ns - start_ns) / 1e9 if start_ns is not None else 0.0
    topics = []
    by_topic: Counter[str] = Counter()
    for cid, n in counts.items():
        by_topic[f.topic(cid)] += n
    for topic in sorted({c.topic for c in f.channels.values()} | set(by_topic)):
        n = by_topic.get(topic, 0)
        ch = next((c for c in f.channels.values() if c.topic == topic), None)
        schema = f.schemas.get(ch.schema_id) if ch is not None else None
        sensor, kind = _parts(topic)
        topics.append({"topic": topic, "sensor": sensor, "kind": kind, "messages": n,
                       "rate_hz": round(n / duration_s, 3) if duration_s > 0 else None,
                       "encoding": ch.message_encoding if ch is not None else None,
                       "schema": schema.name if schema is not None else None})
    md = f.metadata_dict()
    sensors = sorted({t["sensor"] for t in topics if t["sensor"] is not None and t["kind"] != "health"})
    counters = _values(md.get("qradar.recorder_counters"))
    recovery = _values(md.get("qradar.recovery"))
    scene = _scene(md.get("qradar.scene"))
    out = {
        "file": str(path), "bytes": path.stat().st_size, "index": how,
        "truncated": f.truncated, "truncation_reason": f.truncation_reason,
        "start": clock(start_ns), "end": clock(end_ns), "start_ns": start_ns, "end_ns": end_ns,
        "duration_s": round(duration_s, 3), "messages": sum(counts.values()),
        "chunks": len(chunks) if summary is not None else None,
        "compression": sorted({c.compression or "none" for c in chunks}) if chunks else None,
        "uncompressed_bytes": sum(c.uncompressed_size for c in chunks) if chunks else None,
        "sensors": sensors, "sensor_sources": _values(md.get("qradar.sensors")),
        "topics": topics,
        "radar": _values(md.get("qradar.radar")), "quantizer": _values(md.get("qradar.quantizer")),
        "decoder": _values(md.get("qradar.localizer")), "calibration": _calibration(md.get("qradar.calibration")),
        "truth": scene, "simulated_scene": _scene(md.get("qradar.simulated_scene")),
        "recorder": _values(md.get("qradar.recorder")), "versions": md.get("qradar.versions"),
        "losses": {
            "recorder": counters,  # None: the recorder never closed the file (killed)
            "chunks_checked": f.complete,
            "messages_read": sum(read.values()) if f.complete else None,
            "lost": f.lost if f.complete else None,
            "lost_by_topic": f.lost_by_topic if f.complete else None,
            "damage": f.damage_lines(),
        },
        "recovered": recovery,
        "split": split_files(path),
        "other_metadata": sorted(set(md) - set(KNOWN_METADATA)),
        "seconds_to_describe": round(time.perf_counter() - t0, 4),
    }
    return out


def _scene(entries: dict[str, str] | None) -> dict | None:
    if entries is None:
        return None
    out = {k: _value(v) for k, v in entries.items() if k != "scene"}
    scene = _value(entries.get("scene", "null"))
    if isinstance(scene, dict):
        out["name"] = scene.get("name")
        out["noise_std"] = scene.get("noise_std")
        out["targets"] = [{k: t.get(k) for k in ("range_m", "angle_deg", "amplitude")}
                          for t in scene.get("target", []) if isinstance(t, dict)]
    return out


def _calibration(entries: dict[str, str] | None) -> dict | None:
    if entries is None:
        return None
    out = {"file": entries.get("file")}
    summary = _value(entries.get("summary", "null"))
    if isinstance(summary, dict):
        out["entries"] = summary.get("entries", [])
    return out


# -- the text ------------------------------------------------------------------------------------
def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} B"


def _when(c: dict | None, ns: int | None) -> str:
    if c is None:
        return "-" if ns is None else f"{ns} ns (not wall-clock time)"
    return f"{c['utc']} (local {c['local']})"


def _dict(d: dict | None, skip: tuple[str, ...] = ()) -> str:
    if not d:
        return "none"
    return ", ".join(f"{k} {v}" for k, v in d.items() if k not in skip and k != "qradar.crc32")


def _radar(r: dict) -> str:
    """The radar configuration in the units people read; the entries it does not know as they are."""
    try:
        n, ramps = int(r["samples_per_ramp"]), int(r["ramps_per_frame"])
        spacing = r.get("antenna_spacing_m")
        text = (f"f0 {float(r['f0_hz']) / 1e9:g} GHz, sweep {float(r['bandwidth_hz']) / 1e6:g} MHz, {n} samples x "
                f"{ramps} ramps (M = {n * ramps}), antenna spacing "
                + ("half a wavelength" if spacing is None else f"{float(spacing) * 1e3:g} mm"))
    except (KeyError, TypeError, ValueError):
        return _dict(r)
    cid = r.get("config_id")
    rest = {k: v for k, v in r.items() if k not in ("f0_hz", "bandwidth_hz", "samples_per_ramp", "ramps_per_frame",
                                                     "antenna_spacing_m", "config_id", "c_m_s")}
    return (text + (f", {_dict(rest)}" if rest else "")
            + (f", config id {cid:#010x}" if isinstance(cid, int) else ""))


def format_info(info: dict) -> str:
    """The text of ``qradar info`` for :func:`describe`'s dict."""
    lines = []
    how = {"summary": "summary and metadata read (chunks not checked: --check reads them)",
           "read whole": "no summary: read whole, every chunk checked",
           "checked": "every chunk read, its CRC checked"}[info["index"]]
    lines.append(f"{info['file']}: {_size(info['bytes'])}, {how}")
    if info["truncated"]:
        lines.append(f"  CUT SHORT     {info['truncation_reason']} (`qradar recover` writes a complete, indexed copy)")
    lines.append(f"  start         {_when(info['start'], info['start_ns'])}")
    lines.append(f"  end           {_when(info['end'], info['end_ns'])}")
    n = info["chunks"]
    chunks = "" if n is None else f" in {n} chunk{'' if n == 1 else 's'} ({', '.join(info['compression'] or [])})"
    lines.append(f"  duration      {info['duration_s']:.3f} s, {info['messages']} messages{chunks}")
    src = info["sensor_sources"] or {}
    lines.append("  sensors       " + (", ".join(
        s + (f" ({_dict(src[s], ('baud',))})" if isinstance(src.get(s), dict) else "") for s in info["sensors"])
        or "none"))
    width = max([len(t["topic"]) for t in info["topics"]] + [5])
    for i, t in enumerate(info["topics"]):
        rate = "" if t["rate_hz"] is None else f"{t['rate_hz']:9.2f} Hz"
        lines.append(f"  {'topics' if i == 0 else '':14}{t['topic']:{width}} {t['messages']:9d} msgs{rate}  "
                     f"{t['schema'] or t['encoding'] or ''}")
    radar = info["radar"]
    if radar:
        lines.append(f"  radar         {_radar(radar)}")
    else:
        lines.append("  radar         not recorded (the default K-MD2's is assumed)")
    lines.append(f"  quantizer     {_dict(info['quantizer'])}")
    lines.append(f"  decoder       {_dict(info['decoder'])}")
    cal = info["calibration"]
    if cal is None:
        lines.append("  calibration   none (uncalibrated)")
    else:
        ids = [str(e.get("sensor_id")) for e in cal.get("entries", []) if isinstance(e, dict)]
        lines.append(f"  calibration   {cal['file']} (entries for {', '.join(ids) or 'no sensor'})")
    truth = info["truth"]
    if truth is None:
        lines.append("  truth         none")
    else:
        kind = "simulated scene" if truth.get("simulated") is True else f"measured ({truth.get('truth_file')})"
        targets = ", ".join(f"{t['range_m']} m {t['angle_deg']:+} deg" for t in truth.get("targets", []))
        lines.append(f"  truth         {truth.get('name')} ({kind}): {targets or 'no targets'}")
    losses = info["losses"]
    rec = losses["recorder"]
    lines.append("  recorder      " + ("no counters (the recorder did not close this file: killed?)" if rec is None
                                      else _dict(rec)))
    if losses["chunks_checked"] and not (losses["lost"] or losses["damage"]):
        lines.append("  damage        none found (every chunk checked)")
    elif losses["chunks_checked"]:
        lines.append(f"  damage        {losses['messages_read']} messages read, {losses['lost']} lost" +
                     (f" {losses['lost_by_topic']}" if losses["lost_by_topic"] else "") +
                     (f", {len(losses['damage'])} damaged chunk(s) or problem(s)" if losses["damage"] else ""))
    for d in losses["damage"]:
        lines.append(f"                {d}")
    rc = info["recovered"]
    if rc is not None:
        cut = ", the source was cut short" if rc.get("truncated") else ""
        lost = f" {rc['lost_by_topic']}" if rc.get("lost_by_topic") else ""
        lines.append(f"  recovered     from {rc.get('source')}: {rc.get('messages')} messages kept, {rc.get('lost')} "
                     f"lost{lost}{cut}")
        for d in rc.get("damage") or []:
            lines.append(f"                {d}")
    else:
        lines.append("  recovered     no")
    if len(info["split"]) > 1:
        lines.append(f"  split         {len(info['split'])} files: {', '.join(Path(p).name for p in info['split'])}")
    if info["recorder"]:  # each sensor's first frame (a later file of a split set): counted, not listed
        recorder = {k: v for k, v in info["recorder"].items() if k != "first_raw_ns"}
        if "first_raw_ns" in info["recorder"]:
            named = info["recorder"]["first_raw_ns"]
            recorder["first frames of"] = f"{len(named) if isinstance(named, dict) else '?'} sensor(s)"
        lines.append(f"  recorded      {_dict(recorder)}")
    if info["versions"]:
        lines.append(f"  versions      {_dict(info['versions'])}")
    if info["other_metadata"]:
        lines.append(f"  metadata      also {', '.join(info['other_metadata'])}")
    return "\n".join(lines)
