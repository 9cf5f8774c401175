"""The summary of ``qradar run``: what a run measured as a typed record (:class:`RunSummary`:
the ``--json`` object's fields, the human text of :func:`format_summary`), made from the
run's monitor, nodes and drivers at its end (:func:`summarize`)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, fields
from typing import TextIO

from pipeline.bus.audit import format_counts
from pipeline.dsp.calibration import Calibration
from pipeline.dsp.gate import gate_warning
from pipeline.dsp.score import score_text
from radar_driver.scene import SimScene
from radar_driver.simulator import SimulatorServer

from .figures import counts, round_sig, sig
from .monitor import Monitor


def _stat(value: float | None) -> float | None:
    """A figure of a fixed-size histogram (within 2 % of the exact one), to its meaningful digits."""
    return round_sig(None if value is None else float(value))


def simulator_lateness(sims: list[SimulatorServer]) -> dict:
    """The simulated sensors' own lateness (their process was not scheduled in time): late
    writes and seconds, for which each held its device clock. Not frames lost: a real
    K-MD2 measures on its own clock."""
    devs = [d for sim in sims for d in sim.devices]
    return {"late_writes": sum(d.late_writes for d in devs), "late_s": round(sum(d.late_s for d in devs), 4)}


@dataclass
class RunSummary:
    """What a run measured: the JSON object of ``--json`` (:meth:`to_dict`, keys in field
    order; the optional parts, None, left out) and the text of :func:`format_summary`.
    A new figure is a new plain field (a JSON-ready value). Read as the JSON object too:
    ``summary["frames_raw"]``."""

    scene: str | None
    sensors: int
    sensor_urls: dict[str, str] | None  # real sensors: where each one is (--sensor); simulated ones: null
    truth: str | None  # "simulated", the --truth file, or null (no position error)
    seconds: float
    frames_raw: int
    frames_quantized: int
    frames_targets: int
    rate_hz: dict[str, float]  # targets per second of each sensor (first to last frame)
    drops: int
    drops_detail: dict[str, int]
    # gaps in the sequence numbers, where each stage noticed them: a frame lost before the
    # quantizer is missing at every later stage too (pipeline.nodes.counters.judge_seq)
    frames_missing: dict[str, int]
    # restarts of a sender's count, and numbers out of line (forged or replayed), at each stage
    seq_resets: dict[str, int]
    implausible_seq: dict[str, int]
    worker_restarts: int
    latency_ms: dict[str, float | None]
    # the honest score (pipeline.dsp.score): per true target its detection rate and the median
    # error of its detections, false targets and targets a frame; null without a truth
    score: dict | None
    position_error_m: dict[str, float | None]  # each true target to the nearest target (median of nearest)
    bytes_per_raw_frame: float | None
    bytes_per_quantized_frame: float | None
    quantizer: dict
    localizer: dict
    calibration: dict | None  # {file, made, sensor_ids} or null: uncalibrated
    front_end: dict[str, dict]  # per sensor: calibrated (file or false), frames checked, leakage seen
    warnings: list[str]
    driver: dict[str, dict[str, int]]
    driver_process: bool
    # drivers that died and were started again (qradar.drivers.SupervisedDriver): how often, why, and the
    # sensors given up after too many deaths in a row
    driver_restarts: dict[str, int]
    driver_exits: dict[str, list[str]]
    sensors_gone: list[str]
    # the simulated sensors' own late writes (device clock held): apart from every loss above; null
    # with real sensors
    simulator: dict | None
    tracks: dict | None = None
    recording: dict | None = None  # state, files, written, dropped (queue), lost (write errors, by topic), error
    foxglove: dict | None = None
    web: dict | None = None  # run --web: the page's server (url, pages, events sent and dropped)
    interrupted: bool | None = None  # ended by Ctrl-C / SIGTERM
    audit: dict | None = None  # --secure: refused handshakes, denied messages

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)
                if not (getattr(self, f.name) is None and f.default is None)}

    def __getitem__(self, key: str):
        return self.to_dict()[key]

    def get(self, key: str, default=None):
        return self.to_dict().get(key, default)

    def format(self) -> str:
        return format_summary(self)

    @property
    def sensors_lost(self) -> list[str]:
        """The sensors without frames at the end of the run: their link lost and not back, or
        their driver given up after restarts."""
        return sorted({sid for sid, c in self.driver.items() if c.get("link_down")} | set(self.sensors_gone))

    @property
    def produced_nothing(self) -> bool:
        """Not one targets message, whether raw frames came or none did (a sensor that never
        answered, given up): the run's result is empty (its command ends with a non-zero status
        unless it was interrupted, :meth:`nothing_reason` saying why)."""
        return self.frames_targets == 0

    def nothing_reason(self) -> str:
        """Why a run that :attr:`produced_nothing` did: its localizer, or its sensors."""
        if self.frames_raw:
            return localizer_warning(self.frames_raw, 0)
        gone = f" ({', '.join(self.sensors_gone)} given up after restarts)" if self.sensors_gone else ""
        return (f"no frame came from any sensor in the run{gone}: check the sensor (power, cable, the --sensor URL "
                "and its profile) and the driver lines above")


def localizer_warning(raw: int, targets: int) -> str | None:
    """What a run whose localizer published targets for under half its raw frames says
    (None otherwise)."""
    if not raw or targets >= raw / 2:
        return None
    return (f"the localizer published targets for {targets} of {raw} raw frames: it fell behind or failed (see drops "
            "and processing errors) or spent the run loading its kernels (`make` compiles them at set-up; a pip "
            "install compiles them on first use, for minutes)")


def link_warnings(driver_stats: dict[str, dict[str, int]]) -> list[str]:
    """What a run whose sensors were reconnected (a link lost, a sensor that stopped answering)
    says, one line a sensor: how often, for how long, whether it was back at the end, and
    reconnects refused for another device."""
    out = []
    for sid, c in sorted(driver_stats.items()):
        if not c.get("link_losses"):
            continue
        wrong = c.get("wrong_device", 0)
        out.append(f"sensor {sid} was reconnected {c['link_losses']} time(s) (its link lost, or it stopped "
                   f"answering), {c.get('down_ms', 0) / 1e3:.1f} s without frames in all"
                   + (", and not back at the end of the run" if c.get("link_down") else "")
                   + (f"; {wrong} reconnect attempt(s) found another device on its port, not opened"
                      if wrong else "") + ": its frames of that time are missing")
    return out


def summarize(cfg, scene, monitor: Monitor, localizer, quantizer, drivers, seconds: float,
              simulator: dict | None = None, truth: SimScene | None = None,
              calibration: Calibration | None = None) -> RunSummary:
    """The run's summary. ``simulator``: the simulated sensors' lateness (None with real
    sensors); ``truth``: the true positions the errors were measured against (None: no
    error, ``position_error_m`` all None, no score)."""
    driver_stats = {sid: c for d in drivers for sid, c in getattr(d, "source", d).stats().items()}
    driver_drops = sum(c.get("dropped", 0) for c in driver_stats.values())
    q_tot, l_tot = quantizer.totals(), localizer.totals()
    queue_drops = l_tot["drops"] + q_tot["drops"]
    cnt, size = monitor.count, monitor.bytes
    lat, err = monitor.latency_ms, monitor.errors_m  # fixed-size histograms: within 2 % of the exact figures
    if truth is None:
        truth_name = None
    elif truth is scene:
        truth_name = "simulated"
    else:
        truth_name = str(cfg.truth)
    score = monitor.score()
    tracks = None
    if cfg.tracking is not None:
        tracks = {"messages": cnt["tracks"], "last_track_id": dict(sorted(monitor.track_ids.items())),
                  "integrate_s": cfg.tracking.integrate_s,
                  # each static true target to the nearest static track (within 1 m), every message
                  "static_track_error_m": {"median": _stat(monitor.static_track_errors_m.percentile(50)),
                                           "p90": _stat(monitor.static_track_errors_m.percentile(90))}}
    return RunSummary(
        scene=scene.name if scene is not None else None,
        sensors=cfg.n_sensors,
        sensor_urls={s.sensor_id: s.url for s in cfg.sensor_specs} if cfg.real else None,
        truth=truth_name,
        seconds=round(seconds, 2),
        frames_raw=cnt["raw"], frames_quantized=cnt["quantized"], frames_targets=cnt["targets"],
        rate_hz=monitor.rates_hz(),
        drops=driver_drops + queue_drops,
        drops_detail={"sensor_frames": driver_drops, "node_queues": queue_drops,
                      "decode_errors": l_tot["decode_errors"] + q_tot["decode_errors"],
                      "invalid_frames": l_tot["invalid_frames"] + q_tot["invalid_frames"],
                      "processing_errors": l_tot["processing_errors"] + q_tot["processing_errors"],
                      "undecodable_targets": monitor.bad_targets, "undecodable_health": monitor.bad_health,
                      "monitor_errors": monitor.failed_messages},
        frames_missing={"quantize": q_tot["frames_missing"], "localize": l_tot["frames_missing"],
                        "targets": monitor.targets_missing},
        seq_resets={"quantize": q_tot["seq_resets"], "localize": l_tot["seq_resets"],
                    "targets": monitor.targets_seq_resets},
        implausible_seq={"quantize": q_tot["implausible_seq"], "localize": l_tot["implausible_seq"],
                         "targets": monitor.targets_implausible_seq},
        worker_restarts=q_tot["worker_restarts"] + l_tot["worker_restarts"],
        latency_ms={"p50": _stat(lat.percentile(50)), "p99": _stat(lat.percentile(99))},
        score=None if score is None else score.to_dict(truth.truth(0.0)),
        position_error_m={"median": _stat(err.percentile(50)), "mean": _stat(err.mean()),
                          "p90": _stat(err.percentile(90))},
        bytes_per_raw_frame=round(size["raw"] / cnt["raw"], 1) if cnt["raw"] else None,
        bytes_per_quantized_frame=round(size["quantized"] / cnt["quantized"], 1) if cnt["quantized"] else None,
        quantizer={"bits": cfg.quantizer.bits, "alpha": cfg.quantizer.alpha, "delta": cfg.quantizer.delta,
                   "dither_seed": cfg.quantizer.dither_seed,
                   # alpha auto: each sensor's noise estimate and the alpha of its last frame
                   **({"noise": quantizer.noise.snapshot()} if getattr(quantizer, "noise", None) else {})},
        localizer={"algo": str(cfg.algo), "K": localizer.config.k, "K_auto": cfg.auto_k,
                   **localizer.config.gate.to_dict()},
        calibration=None if calibration is None else {
            "file": calibration.source, "made": calibration.meta.get("created_utc"),
            "sensor_ids": sorted(calibration.sensors)},
        front_end={sid: dict(st) for sid, st in sorted(monitor.front_end.items())},
        warnings=[*monitor.warnings.values(), *link_warnings(driver_stats),
                  *filter(None, [localizer_warning(cnt["raw"], cnt["targets"]),
                                 gate_warning(truth, localizer.config.gate)])],
        driver=driver_stats,
        driver_process=cfg.driver_process,
        driver_restarts={d.sensor_id: d.restarts for d in drivers if hasattr(d, "restarts")},
        driver_exits={d.sensor_id: list(d.exits) for d in drivers if getattr(d, "exits", None)},
        sensors_gone=[d.sensor_id for d in drivers if hasattr(d, "gone") and d.gone.is_set()],
        simulator=simulator,
        tracks=tracks,
    )


def format_summary(s: "dict | RunSummary") -> str:
    """The human summary of a run's summary (or of its JSON object, :meth:`RunSummary.to_dict`)."""
    s = s.to_dict() if isinstance(s, RunSummary) else s
    lat, err = s["latency_ms"], s["position_error_m"]
    urls = s.get("sensor_urls")
    where = (f"{len(urls)} sensor(s) " + ", ".join(f"{sid} on {url}" for sid, url in urls.items()) if urls
             else f"scene {s['scene']}, {s['sensors']} sensor(s)")
    rates = list((s.get("rate_hz") or {}).values())
    lines = [
        f"qradar run: {where}, {s['seconds']} s"
        + (", ended by Ctrl-C / SIGTERM" if s.get("interrupted") else ""),
        f"  frames      raw {s['frames_raw']}, quantized {s['frames_quantized']}, targets {s['frames_targets']}",
    ]
    if rates:
        lines.append(f"  rate        {rates[0]:.1f} frames/s" if len(rates) == 1 else
                     f"  rate        {min(rates):.1f} to {max(rates):.1f} frames/s per sensor")
    lines += [
        f"  drops       {s['drops']} ({counts(s['drops_detail'], skip_zero=True)})",
        f"  missing     {counts(s['frames_missing'])} (sequence gaps noticed at each stage)",
    ]
    for sid, n in (s.get("driver_restarts") or {}).items():
        exits = (s.get("driver_exits") or {}).get(sid) or []
        if n or exits:
            gone = sid in (s.get("sensors_gone") or [])
            lines.append(f"  driver      {sid}: restarted {n} time(s){', then given up' if gone else ''}"
                         + (f" (last: {exits[-1]})" if exits else ""))
    if s.get("simulator") is not None:
        lines.append(f"  simulator   {s['simulator']['late_writes']} late writes, {s['simulator']['late_s'] * 1e3:.1f} ms "
                     f"in all (the simulated sensors' own lateness on a busy host, device clock held: no frame lost)")
    lines.append(f"  latency     p50 {sig(lat['p50'])} ms, p99 {sig(lat['p99'])} ms (sensor timestamp -> targets "
                 "published)")
    cal = s.get("calibration")
    if "calibration" in s or "front_end" in s:
        lines.append(f"  calibration {cal['file']} (made {cal['made'] or 'n/a'})" if cal else
                     "  calibration none: the frames are uncalibrated")
    for w in s.get("warnings") or []:
        lines.append(f"  warning     {w}")
    if s.get("truth", "simulated") is None:
        lines.append("  error       none: no true positions (--truth SCENE.toml gives the reflectors' measured ones)")
    else:
        if s.get("score"):
            lines.append(f"  score       {score_text(s['score'])}, over {s['score']['frames']} frames")
        lines.append(f"  error       median {sig(err['median'])} m, mean {sig(err.get('mean'))} m, p90 "
                     f"{sig(err.get('p90'))} m (each true target to the nearest target, found or not: false targets "
                     "cost nothing here" + (f"; truth {s['truth']}" if s.get("truth") not in (None, "simulated")
                                            else "") + ")")
    tr = s.get("tracks")
    if tr is not None:
        e = tr["static_track_error_m"]
        ids = counts(tr["last_track_id"]) if tr["last_track_id"] else "none"
        lines.append(f"  tracks      {tr['messages']} messages, last track id {ids}; static tracks' error "
                     f"median {sig(e['median'])} m, p90 {sig(e['p90'])} m (--integrate {tr['integrate_s']:g} s)")
    raw_b, q_b = s["bytes_per_raw_frame"], s["bytes_per_quantized_frame"]
    lines.append(f"  bytes/frame raw {'n/a' if raw_b is None else f'{raw_b:g}'}, quantized "
                 f"{'n/a' if q_b is None else f'{q_b:g}'} ({s['quantizer']['bits']}-bit, alpha {s['quantizer']['alpha']})")
    rec = s.get("recording")
    if rec is not None:
        lines.append(f"  recording   {rec['state']}, {rec['files_written']} file(s) {', '.join(rec['files'])}; "
                     f"written {rec['written']}, dropped {rec['dropped']}, lost {rec['lost']}"
                     + (f" ({counts(rec['lost_by_topic'])})" if rec["lost"] else "")
                     + "".join(f", {k.replace('_', ' ')} {rec[k]}" for k in ("refused_time", "refused_size",
                                                                            "refused_shape", "refused_topic",
                                                                            "verify_errors") if rec.get(k))
                     + (f"; last write or read-back error: {rec['error']}" if rec["error"] else ""))
    audit_counts = s.get("audit")
    if audit_counts is not None:
        lines.append(f"  audit       {format_counts(audit_counts)} (--secure; docs/security.md)")
    return "\n".join(lines)


def print_json(summary: "RunSummary | dict", stream: TextIO | None = None) -> None:
    """``summary`` as one JSON line on ``stream`` (None: the process's stdout at the call)."""
    stream = sys.stdout if stream is None else stream
    stream.write(json.dumps(summary.to_dict() if isinstance(summary, RunSummary) else summary) + "\n")
    stream.flush()
