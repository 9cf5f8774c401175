"""The ``qradar`` command: one entry point with subcommands."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from radar_driver.errors import RadarError
from replay.errors import ReplayError

from .bus import bus_from_args, bus_options
from .errors import PipelineError

log = logging.getLogger("qradar")


def _nonneg_int(text: str) -> int:
    v = int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return v


def _pos_int(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return v


def _add_montecarlo(sub) -> None:
    from .montecarlo import DEFAULT_SCHEMES

    p = sub.add_parser(
        "montecarlo",
        help="reproduce the paper's Monte Carlo (Sec. 5, Figs. 2-4)",
        description="Monte Carlo of PBP localization with the DESIGN.md protocol; writes "
        "summary.json, maps.npz and polar error maps (PNG) to --out.",
    )
    p.add_argument("--K", dest="ks", type=_pos_int, nargs="+", default=[1, 2], help="sparsities (default 1 2)")
    p.add_argument("--runs", type=_pos_int, default=None,
                   help="runs per scheme and K (default: the paper's 320000 x K)")
    p.add_argument("--schemes", nargs="+", default=list(DEFAULT_SCHEMES),
                   help="dither_m<M>, nodither_m<M>, 32bit_m<M> (default: the paper's four)")
    p.add_argument("--seed", type=_nonneg_int, default=0)
    p.add_argument("--algos", nargs="+", default=["pbp"], help="decoders: pbp, qiht (default pbp); non-PBP "
                   "results appear as <scheme>@<algo>")
    p.add_argument("--fallback-pbp", action="store_true", help="decode schemes without dither with PBP "
                   "when a dither-aware algo is asked for")
    p.add_argument("--off-grid", action="store_true", help="keep range cell centres off the range grid")
    p.add_argument("--workers", type=_pos_int, default=None, help="worker processes (default: all cores)")
    p.add_argument("--out", type=Path, default=Path("montecarlo_out"), help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG maps")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_montecarlo)


def _cmd_montecarlo(args) -> int:
    from radar_driver.model import RadarConfig

    from .montecarlo import MonteCarloConfig, format_table, run_montecarlo
    from .plots import montecarlo_figures

    cfg = MonteCarloConfig(
        ks=tuple(args.ks), runs=args.runs, schemes=tuple(args.schemes), seed=args.seed,
        off_grid=args.off_grid, workers=args.workers, radar=RadarConfig(), algos=tuple(args.algos),
        fallback_pbp=args.fallback_pbp,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    result = run_montecarlo(cfg, progress=not args.quiet)
    (args.out / "summary.json").write_text(json.dumps(result.summary, indent=2) + "\n")
    (args.out / "config.json").write_text(json.dumps(result.run_config, indent=2) + "\n")
    np.savez_compressed(args.out / "maps.npz", **result.maps)
    pngs = [] if args.no_plots else montecarlo_figures(args.out, result.summary, result.maps, cfg.radar.max_range_m)
    from .plots import error_vs_m, error_vs_m_figure

    slopes = error_vs_m(result.summary)
    if slopes:
        (args.out / "error_vs_m.json").write_text(json.dumps(slopes, indent=2) + "\n")
        if not args.no_plots:
            pngs.append(error_vs_m_figure(args.out / "error_vs_m.png", slopes))
        for label, s in slopes.items():
            print(f"{label}: median error {s['error_m']} m at M = {s['M']}: slope {s['slope']:+.2f}")
    print(format_table(result.summary))
    print(f"\n{sum(result.run_config['runs_per_k'].values()) * len(cfg.schemes)} runs "
          f"(x {len(cfg.algos)} decoders) in "
          f"{result.summary['seconds']:.1f} s; wrote {args.out}/summary.json, maps.npz"
          + (f" and {len(pngs)} PNG maps" if pngs else ""))
    return 0


def _prob(text: str) -> float:
    v = float(text)
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a probability in [0, 1]")
    return v


def _nonneg_float(text: str) -> float:
    v = float(text)
    if not v >= 0.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return v


def _install_sigterm() -> None:
    """Turn SIGTERM and SIGINT into KeyboardInterrupt so that every command ends
    cleanly, also when started in the background (where a shell ignores SIGINT)."""
    import signal

    def handler(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def _add_sim(sub) -> None:
    p = sub.add_parser("sim", help="serve a simulated K-MD2 on a pty and/or TCP until interrupted",
                       description="A simulated RFbeam K-MD2 speaking the serial protocol; ramps from "
                       "the paper's model of a TOML scene, with noise, 12-bit ADC and optional faults.")
    p.add_argument("--scene", default="chamber",
                   help="TOML scene file, or the name of a packaged scene (chamber, single, walker)")
    p.add_argument("--link", type=Path, default=None, help="stable symlink path to the pty (e.g. /tmp/kmd2)")
    p.add_argument("--tcp", type=int, default=None, metavar="PORT", help="also serve socket://127.0.0.1:PORT")
    p.add_argument("--rate", type=_nonneg_float, default=20.0, help="frames per second (0 = as fast as polled)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="noise and fault seed")
    p.add_argument("--garbage", type=_prob, default=0.0, metavar="P", help="garbage burst before a message")
    p.add_argument("--truncate", type=_prob, default=0.0, metavar="P", help="RADC cut short")
    p.add_argument("--skip-done", type=_prob, default=0.0, metavar="P", help="DONE counter jumps")
    p.add_argument("--disconnect-after", type=_pos_int, default=None, metavar="N", help="drop the link after N frames")
    p.add_argument("--reconnect-after", type=_nonneg_float, default=1.0, metavar="T", help="link back after T s")
    p.set_defaults(func=_cmd_sim)


def _cmd_sim(args) -> int:
    from radar_driver.scene import resolve_scene
    from radar_driver.simulator import SimFaults, SimulatorServer

    if args.link is None and args.tcp is None:
        raise ValueError("give --link PATH and/or --tcp PORT")
    scene = resolve_scene(args.scene)
    faults = SimFaults(garbage_prob=args.garbage, truncate_prob=args.truncate, skip_done_prob=args.skip_done,
                       disconnect_after_frames=args.disconnect_after, reconnect_after_s=args.reconnect_after)
    _install_sigterm()
    server = SimulatorServer(scene, link_path=args.link, tcp_port=args.tcp, rate_hz=args.rate,
                             faults=faults, seed=args.seed)
    with server:
        where = [str(args.link)] if args.link else []
        if args.tcp is not None:
            where.append(f"socket://127.0.0.1:{server.tcp_port}")
        print(f"simulated K-MD2 ({scene.name}, {len(scene.targets)} targets, {args.rate:g} frames/s) on "
              f"{' and '.join(where)}; Ctrl-C to stop", flush=True)
        try:
            while not server.wait(0.5):
                if server.errors:
                    raise server.errors[0]
        except KeyboardInterrupt:
            pass
    return 0


def _add_drive(sub) -> None:
    p = sub.add_parser("drive", help="read frames from a K-MD2 (real or simulated)",
                       description="Drive a K-MD2 on any pyserial URL (/dev/ttyUSB0, a pty path, "
                       "socket://host:port, rfc2217://host:port), 8E1, reconnecting on errors.")
    p.add_argument("--port", required=True, help="pyserial URL or device path")
    p.add_argument("--frames", type=_pos_int, default=None, help="stop after N frames (default: until Ctrl-C)")
    p.add_argument("--baud", type=int, default=2_000_000, help="rate after INIT (115200, 460800, 921600, 2000000, 3000000)")
    p.add_argument("--ramps", type=_pos_int, default=2, help="ramps per frame (M = 256 x ramps)")
    p.add_argument("--timeout", type=float, default=0.5, help="seconds to wait for a GNFD answer")
    p.add_argument("--out", type=Path, default=None, help="save frames to FILE.npz (frames, M, 2)")
    p.add_argument("--json", action="store_true", help="end with one JSON object of counters on stdout")
    p.add_argument("--sensor-id", default="kmd2", help="sensor id in the zenoh keys (default kmd2)")
    p.add_argument("--no-publish", action="store_true", help="read frames without opening a zenoh session")
    bus_options(p)
    p.set_defaults(func=_cmd_drive)


def _cmd_drive(args) -> int:
    from radar_driver.session import SensorSession, SessionConfig

    from .nodes import DriverNode

    cfg = SessionConfig(url=args.port, baud=args.baud, ramps_per_frame=args.ramps, timeout_s=args.timeout)
    lines = sys.stderr if args.json else sys.stdout
    frames = []

    def show(frame) -> None:
        if args.out is not None:
            frames.append(frame)
        peak = np.abs(frame.data).max()
        print(f"frame {frame.seq:6d}  counters {frame.counters}  t {frame.timestamp_ns}  "
              f"peak {peak:.3f} FS", file=lines, flush=True)

    _install_sigterm()
    if args.no_publish:
        node = None
        session = SensorSession(cfg)
        try:
            with session:
                for frame in session.frames(args.frames):
                    show(frame)
        except KeyboardInterrupt:
            pass
    else:
        node = DriverNode(bus_from_args(args), args.sensor_id, cfg, frames=args.frames, on_frame=show)
        session = node.sensor
        try:
            node.start()
            while not node.done.wait(0.2):
                if node.errors:
                    break
        except KeyboardInterrupt:
            pass
        finally:
            node.stop()
        if node.errors:
            raise node.errors[0]
    if args.out is not None:
        np.savez_compressed(
            args.out,
            frames=np.stack([f.data for f in frames]) if frames else np.zeros((0, cfg.radar().n_measurements, 2), np.complex64),
            seq=np.array([f.seq for f in frames], dtype=np.int64),
            timestamp_ns=np.array([f.timestamp_ns for f in frames], dtype=np.int64),
            counters=np.array([f.counters for f in frames], dtype=np.int64).reshape(len(frames), cfg.ramps_per_frame),
            radar_config=json.dumps(cfg.radar().to_dict()),
        )
    c = session.counters.as_dict()
    if args.json:
        print(json.dumps(c))
    else:
        print("counters: " + ", ".join(f"{k}={v}" for k, v in c.items()))
    return 0


def _add_quantize(sub) -> None:
    p = sub.add_parser("quantize", help="node: radar/*/raw -> dithered b-bit quantization -> radar/<sensor>/quantized")
    p.add_argument("--bits", type=_pos_int, default=1)
    p.add_argument("--alpha", type=float, default=1.0, help="dither scale in [0, 1] (default 1)")
    p.add_argument("--delta", default="auto", help="'auto' (smallest 1-bit step per frame) or a step in full-scale units")
    p.add_argument("--delta-margin", type=_nonneg_float, default=0.0, help="auto delta x (1 + margin)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="dither seed (per sensor: seed * 2^32 + crc32(id))")
    p.add_argument("--queue", type=_pos_int, default=512, help="bounded input queue (frames)")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    bus_options(p)
    p.set_defaults(func=_cmd_quantize)


def _quantizer_config(args):
    from .quantize import QuantizerConfig

    delta = args.delta if args.delta == "auto" else float(args.delta)
    return QuantizerConfig(bits=args.bits, alpha=args.alpha, delta=delta, delta_margin=args.delta_margin,
                           dither_seed=args.seed)


def _serve(node, duration) -> int:
    from .nodes import run_nodes

    _install_sigterm()
    try:
        run_nodes([node], duration)
    except KeyboardInterrupt:
        pass
    t = node.totals()
    print(json.dumps({"node": node.name, **t}), flush=True)
    return 0


def _cmd_quantize(args) -> int:
    from .nodes import QuantizeNode

    return _serve(QuantizeNode(bus_from_args(args), _quantizer_config(args), queue_size=args.queue), args.duration)


def _add_localize(sub) -> None:
    p = sub.add_parser("localize", help="node: radar/*/quantized (or raw) -> PBP -> radar/<sensor>/targets")
    p.add_argument("--K", dest="k", type=_pos_int, default=2, help="targets per frame")
    p.add_argument("--algo", choices=["pbp", "qiht"], default="pbp",
                   help="pbp, or qiht: the dither-aware decoder (needs dithered frames)")
    p.add_argument("--fallback-pbp", action="store_true", help="with qiht: decode frames without dither by PBP")
    p.add_argument("--source", choices=["quantized", "raw"], default="quantized",
                   help="raw = the full-resolution baseline")
    p.add_argument("--queue", type=_pos_int, default=512, help="bounded input queue (frames)")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    bus_options(p)
    p.set_defaults(func=_cmd_localize)


def _cmd_localize(args) -> int:
    from .nodes import LocalizeNode, LocalizerConfig

    cfg = LocalizerConfig(k=args.k, algo=args.algo, source=args.source, fallback_pbp=args.fallback_pbp)
    return _serve(LocalizeNode(bus_from_args(args), cfg, queue_size=args.queue), args.duration)


def _add_source(sub) -> None:
    p = sub.add_parser("source", help="node: in-process simulated sensors -> radar/<id>/raw (no serial link)",
                       description="Simulated sensors that publish raw frames of a scene directly, bypassing "
                       "the serial protocol: for benchmarks and many-sensor set-ups.")
    p.add_argument("--scene", default="chamber")
    p.add_argument("--sensors", type=_pos_int, default=1)
    p.add_argument("--rate", type=float, default=20.0, help="frames per second per sensor")
    p.add_argument("--id-prefix", default="sim", help="sensor ids are <prefix>0, <prefix>1, ...")
    p.add_argument("--frames", type=_pos_int, default=None, help="frames per sensor, then stop")
    p.add_argument("--seed", type=_nonneg_int, default=0)
    p.add_argument("--duration", type=float, default=None)
    bus_options(p)
    p.set_defaults(func=_cmd_source)


def _cmd_source(args) -> int:
    import threading

    from radar_driver.scene import resolve_scene

    from .nodes import SimSourceNode, run_nodes

    node = SimSourceNode(bus_from_args(args), resolve_scene(args.scene), n_sensors=args.sensors, rate_hz=args.rate,
                         id_prefix=args.id_prefix, seed=args.seed, frames=args.frames)
    stop = threading.Event()
    threading.Thread(target=lambda: (node.done.wait(), stop.set()), daemon=True).start()
    _install_sigterm()
    try:
        run_nodes([node], args.duration, stop)
    except KeyboardInterrupt:
        pass
    print(json.dumps({"node": node.name, "late_ticks": node.late_ticks, "elapsed_s": round(node.elapsed_s, 3),
                      **node.totals()}), flush=True)
    return 0


def _add_record(sub) -> None:
    p = sub.add_parser("record", help="record radar/** from zenoh into MCAP")
    p.add_argument("-o", "--output", type=Path, required=True, help="FILE.mcap")
    p.add_argument("--topics", default=None, help="key expression (default <prefix>/**)")
    p.add_argument("--split-size", type=float, default=None, metavar="MB", help="new file every MB megabytes")
    p.add_argument("--split-duration", type=float, default=None, metavar="S", help="new file every S seconds")
    p.add_argument("--scene", default=None, help="ground-truth scene to store in the metadata (simulated sensor)")
    p.add_argument("--duration", type=float, default=None, help="stop after S seconds (default: Ctrl-C)")
    bus_options(p)
    p.set_defaults(func=_cmd_record)


def _cmd_record(args) -> int:
    from radar_driver.scene import resolve_scene
    from replay.recorder import RecorderNode

    meta = {}
    if args.scene:
        meta["qradar.scene"] = {"scene": json.dumps(resolve_scene(args.scene).to_dict()), "simulated": "true"}
    node = RecorderNode(bus_from_args(args), args.output, topics=args.topics, split_size_mb=args.split_size,
                        split_duration_s=args.split_duration, metadata=meta)
    print(f"recording {node.topics} to {args.output}; Ctrl-C to stop", file=sys.stderr, flush=True)
    _serve(node, args.duration)
    print(json.dumps({"files": [str(p) for p in node.paths], "written": node.written}), flush=True)
    return 0


def _add_recover(sub) -> None:
    p = sub.add_parser("recover", help="rewrite a cut-short MCAP (e.g. after SIGKILL) as a complete, indexed file")
    p.add_argument("file", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.set_defaults(func=_cmd_recover)


def _cmd_recover(args) -> int:
    from replay.mcapio import recover

    r = recover(args.file, args.output)
    print(json.dumps({"file": str(args.output), **r}))
    return 0


def _add_replay(sub) -> None:
    p = sub.add_parser("replay", help="publish an MCAP recording back onto zenoh")
    p.add_argument("file", type=Path)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rate", type=float, default=1.0, help="speed factor of the original timing (default 1)")
    g.add_argument("--fast", action="store_true", help="as fast as subscribers take it (publishers block, no drops)")
    p.add_argument("--loop", action="store_true")
    p.add_argument("--start", type=float, default=None, help="seconds from the start of the file")
    p.add_argument("--end", type=float, default=None, help="seconds from the start of the file")
    p.add_argument("--topics", default=None, help="key expression of the channels to play")
    p.add_argument("--replay-prefix", dest="replay_prefix", default=None,
                   help="publish under this key prefix instead of the recorded one (e.g. replay)")
    bus_options(p)
    p.set_defaults(func=_cmd_replay)


def _cmd_replay(args) -> int:
    from replay.player import PlayConfig, play

    cfg = PlayConfig(rate=args.rate, fast=args.fast, loop=args.loop, start_s=args.start, end_s=args.end,
                     topics=args.topics, prefix=args.replay_prefix)
    _install_sigterm()
    import threading

    stop = threading.Event()
    try:
        result = play(args.file, bus_from_args(args), cfg, stop=stop)
    except KeyboardInterrupt:
        return 0
    print(json.dumps({"published": result.published, "loops": result.loops, "truncated": result.truncated,
                      "seconds": round(result.seconds, 3)}))
    return 0


def _add_reprocess(sub) -> None:
    p = sub.add_parser("reprocess", help="re-quantize and re-localize a recording's raw frames offline (alpha sweep)")
    p.add_argument("file", type=Path)
    p.add_argument("--alpha", default="0:1:0.05", help="start:stop:step, a,b,c or one value (default 0:1:0.05)")
    p.add_argument("--bits", type=_pos_int, default=1)
    p.add_argument("--K", dest="k", type=_pos_int, default=None, help="targets (default: the truth's count)")
    p.add_argument("--algo", choices=["pbp", "qiht"], default="pbp",
                   help="decoder; qiht decodes alpha = 0 with PBP (there is no dither to use)")
    p.add_argument("--seed", type=_nonneg_int, default=0)
    p.add_argument("--sensor", default=None, help="sensor id (default: the first)")
    p.add_argument("--truth", type=Path, default=None, help="scene TOML with the true positions (real recordings)")
    p.add_argument("--out", type=Path, default=Path("out/reprocess"), help="folder for results.json and the plots")
    p.add_argument("--mcap", type=Path, default=None, help="also write the best alpha's targets to this MCAP")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_reprocess)


def _cmd_reprocess(args) -> int:
    from radar_driver.model import RadarConfig
    from replay.reprocess import (
        load_raw, parse_alphas, plot_alpha_sweep, plot_reconstructions, radar_for, sweep, truth_scene,
        write_targets_mcap)

    alphas = parse_alphas(args.alpha)
    rec = load_raw(args.file, args.sensor)
    scene = truth_scene(rec, args.truth)
    radar = radar_for(rec, scene.radar if scene else RadarConfig())
    t0_ns = int(rec.timestamp_ns[0])
    truth = scene.truth(0.0)
    if any(t.velocity_m_s for t in scene.targets):
        print("note: moving targets; the truth is taken at the first frame", file=sys.stderr)
    result = sweep(rec, radar, truth, alphas, bits=args.bits, k=args.k, seed=args.seed, progress=not args.quiet,
                   algo=args.algo)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = result.summary() | {"file": str(args.file), "first_timestamp_ns": t0_ns, "truncated": rec.truncated}
    (args.out / "results.json").write_text(json.dumps(summary, indent=2) + "\n")
    figs = [plot_alpha_sweep(result, args.out / "alpha_sweep.png"),
            plot_reconstructions(result, args.out / "reconstructions.png")]
    if args.mcap is not None:
        write_targets_mcap(result, result.best_index, radar, args.mcap)
    print(f"{rec.sensor_id}: {rec.frames.shape[0]} frames; best alpha {summary['best_alpha']:.2f} "
          f"(mean error {summary['error_at_best_m']} m; at alpha 0: {summary['error_at_alpha0_m']} m)")
    print(f"wrote {args.out / 'results.json'}, " + ", ".join(str(f) for f in figs)
          + (f", {args.mcap}" if args.mcap else ""))
    return 0


def _add_router(sub) -> None:
    p = sub.add_parser("router", help="a zenoh router for multi-host set-ups")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="e.g. tcp/0.0.0.0:7447 (default)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--zenoh-config", type=Path, default=None)
    p.add_argument("--duration", type=float, default=None)
    p.set_defaults(func=_cmd_router)


def _cmd_router(args) -> int:
    import time

    from .bus import BusConfig

    bus = BusConfig(mode="router", listen=tuple(args.listen or ["tcp/0.0.0.0:7447"]), connect=tuple(args.connect),
                    config_file=args.zenoh_config)
    _install_sigterm()
    session = bus.open()
    print(f"zenoh router {session.zid()} listening on {list(bus.listen)}; Ctrl-C to stop", flush=True)
    try:
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    return 0


def _add_run(sub) -> None:
    p = sub.add_parser("run", help="the main job: simulated K-MD2 -> driver -> quantize -> localize over zenoh",
                       description="Simulated K-MD2(s) on ptys, the serial driver, the 1-bit dithered quantizer "
                       "and the PBP localizer over an embedded zenoh peer; live targets beside the truth, "
                       "then a summary.")
    p.add_argument("--scene", default="chamber", help="scene file or packaged name (default chamber)")
    p.add_argument("--sensors", type=_pos_int, default=1, help="simulated sensors at once")
    p.add_argument("--duration", type=float, default=15.0, help="seconds (default 15; Ctrl-C stops earlier)")
    p.add_argument("--rate", type=float, default=20.0, help="frames per second per sensor")
    p.add_argument("--bits", type=_pos_int, default=1)
    p.add_argument("--alpha", type=float, default=None,
                   help="dither scale (default: 0.55 with pbp, the paper's best for its noisy chamber; "
                   "1 with qiht, which wants the full dither)")
    p.add_argument("--delta", default="auto")
    p.add_argument("--delta-margin", type=_nonneg_float, default=0.0)
    p.add_argument("--seed", type=_nonneg_int, default=0)
    p.add_argument("--K", dest="k", type=_pos_int, default=None, help="targets per frame (default: the scene's count)")
    p.add_argument("--algo", choices=["pbp", "qiht"], default="pbp", help="decoder of the localizer")
    p.add_argument("--json", action="store_true", help="print exactly one JSON summary object on stdout")
    p.add_argument("--record", type=Path, default=None,
                   help="MCAP file to record to (default recordings/run-<time>.mcap)")
    p.add_argument("--no-record", action="store_true", help="do not record")
    p.add_argument("--frames", type=_pos_int, default=None, help="stop after N frames per sensor")
    bus_options(p)
    p.set_defaults(func=_cmd_run)


def _cmd_run(args) -> int:
    import threading

    from .run import RunConfig, format_summary, print_json, run

    import time as _time

    record = None
    if not args.no_record:
        record = args.record or Path("recordings") / _time.strftime("run-%Y%m%d-%H%M%S.mcap")
    if args.alpha is None:
        args.alpha = 1.0 if args.algo == "qiht" else 0.55
    cfg = RunConfig(scene=args.scene, sensors=args.sensors, duration_s=args.duration, rate_hz=args.rate,
                    quantizer=_quantizer_config(args), k=args.k, algo=args.algo, bus=bus_from_args(args),
                    record=record, frames=args.frames)
    stop = threading.Event()
    _install_sigterm()
    live = sys.stderr if args.json else sys.stdout
    try:
        summary = run(cfg, live=live, stop=stop)
    except KeyboardInterrupt:
        raise
    if args.json:
        print_json(summary)
    else:
        print(format_summary(summary))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="qradar", description="1-bit dithered FMCW radar localization: simulation, streaming, replay."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_montecarlo(sub)
    _add_sim(sub)
    _add_drive(sub)
    _add_quantize(sub)
    _add_localize(sub)
    _add_source(sub)
    _add_router(sub)
    _add_run(sub)
    _add_record(sub)
    _add_recover(sub)
    _add_replay(sub)
    _add_reprocess(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (PipelineError, RadarError, ReplayError, ValueError, OSError) as exc:
        print(f"qradar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"qradar {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
