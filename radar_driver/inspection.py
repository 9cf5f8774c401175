"""What a capture holds, and which sensor profile reads it: the bring-up of an unknown
sensor, offline (``qradar inspect``). Pure functions on a :class:`~.capture.Capture`;
no I/O. (Not ``inspect.py``: that name is the standard library's.)

Two passes over the bytes the sensor sent, port opening by port opening:

1. **Without a profile** (:func:`split_messages`): messages are a 4-character header
   (an upper-case letter, then upper-case letters or digits), a uint32 LE length and
   that many bytes (plus up to 3 zero bytes of padding), followed by another message;
   a header the protocol knows may also be followed by garbage. Per header: count,
   declared lengths, rate; and the garbage bytes, resyncs and the message cut short at
   the end.
2. **With each profile** (:func:`score_profile`): the codec's
   :class:`~.protocol.StreamDecoder`; decoded RADCs become frames as the session makes
   them (the azimuth pair; ``ramps_per_frame`` consecutive RADCs by the DONE counter,
   or that many chirps of one RADC, ``chirp_select``), scored on the assumption of a
   single static reflector (:func:`score_frames`): the range profile's peak bin, the
   peak over the profile's median (sharpness, dB) and over the highest bin outside its
   main lobe (purity, dB: a wrong word order makes images of the reflector), and the
   angle at the peak per frame (the model's convention,
   :func:`~.model.angle_from_antennas_rad`) with its spread (deg).

A profile fits when at least :data:`MIN_FRAMES` frames decode, the sharpness is at least
:data:`MIN_SHARPNESS_DB`, the purity at least :data:`MIN_PURITY_DB`, the angle spreads
less than :data:`MAX_ANGLE_SPREAD_DEG` and, if the reflector's place is given
(:class:`Reflector`), it comes out there; the verdict is the fit with the purest peak
(then the sharpest). A single static reflector cannot tell which receivers are the
azimuth pair and in which order: swapping them flips the angle's sign (put the reflector
on antenna 2's side: the angle must come out positive).
"""

from __future__ import annotations

import re
import struct
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Iterable, Sequence

import numpy as np

from .capture import Capture, Kind
from .model import RadarConfig, angle_from_antennas_rad
from .profile import HEADERS, SensorProfile, packaged_profiles, resolve_profile
from .protocol import PREFIX_LEN, Done, Radc, StreamDecoder

#: a message header without a profile: an upper-case letter, then upper-case letters or digits
HEADER_RE = re.compile(rb"[A-Z][A-Z0-9]{3}")
#: the longest payload the profile-free split believes, bytes
MAX_PAYLOAD = 64 << 20
#: what a fit needs: frames, peak over median (dB), peak over the next outside its lobe (dB), angle spread (deg)
MIN_FRAMES = 3
MIN_SHARPNESS_DB = 15.0
MIN_PURITY_DB = 10.0
MAX_ANGLE_SPREAD_DEG = 3.0
#: bins either side of the peak that belong to its main lobe (Hann window: 2)
MAIN_LOBE_BINS = 3
#: the sharpness of a noiseless peak over an empty median, dB
MAX_SHARPNESS_DB = 120.0

Segment = list[tuple[int, bytes]]  # (time_ns, bytes) of the reads of one port opening


def segments(capture: Capture, kind: Kind = Kind.RX) -> list[Segment]:
    """The chunks of one direction, split at each OPEN: each segment is one byte stream
    (a reopened port starts afresh)."""
    out: list[Segment] = [[]]
    for r in capture.records:
        if r.kind == Kind.OPEN and out[-1]:
            out.append([])
        elif r.kind == kind and r.data:
            out[-1].append((r.time_ns, r.data))
    return [s for s in out if s]


# -- without a profile ---------------------------------------------------------------------------
@dataclass
class HeaderStats:
    """One header: ``count`` messages, their declared ``lengths`` (bytes -> count), and
    the times of the first and last (ns)."""

    count: int = 0
    lengths: Counter = field(default_factory=Counter)
    first_ns: int = 0
    last_ns: int = 0

    @property
    def rate_hz(self) -> float:
        """Messages a second between the first and the last (0 for fewer than 2)."""
        dt = (self.last_ns - self.first_ns) / 1e9
        return (self.count - 1) / dt if self.count > 1 and dt > 0 else 0.0

    def to_dict(self) -> dict:
        return {"count": self.count, "lengths": {str(k): v for k, v in sorted(self.lengths.items())},
                "rate_hz": round(self.rate_hz, 3)}


@dataclass
class Split:
    """A byte stream cut into messages without a profile: per header its
    :class:`HeaderStats` (in order of first appearance), the ``garbage_bytes`` between
    messages in ``resyncs`` runs, and ``cut``: (header, declared length) of each message
    a segment ends inside (length -1: it ends inside the length)."""

    headers: dict[str, HeaderStats] = field(default_factory=dict)
    bytes: int = 0
    garbage_bytes: int = 0
    resyncs: int = 0
    cut: list[tuple[str, int]] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"bytes": self.bytes, "headers": {h: s.to_dict() for h, s in self.headers.items()},
                "garbage_bytes": self.garbage_bytes, "resyncs": self.resyncs,
                "cut": [{"header": h, "length": n} for h, n in self.cut]}


def _header_at(buf: bytes, pos: int) -> tuple[str, int] | None:
    """(header, declared length) if a plausible message prefix starts at ``pos``."""
    if len(buf) - pos < PREFIX_LEN or not HEADER_RE.fullmatch(buf, pos, pos + 4):
        return None
    (length,) = struct.unpack_from("<I", buf, pos + 4)
    return (buf[pos:pos + 4].decode("ascii"), length) if length <= MAX_PAYLOAD else None


def _next_header(buf: bytes, start: int, end: int | None = None) -> int | None:
    """Where the first plausible message prefix in ``buf[start:end]`` starts, or None."""
    end = len(buf) if end is None else end
    while (m := HEADER_RE.search(buf, start, end + 3)) is not None and m.start() < end:
        if _header_at(buf, m.start()) is not None:
            return m.start()
        start = m.start() + 1
    return None


def split_messages(segs: Iterable[Segment], split: Split | None = None) -> Split:
    """Cut each segment's bytes into messages by header and length, without a profile.

    A message is taken when another one (or the end) follows it, or, for a header the
    protocol knows, when no other message starts inside its payload (garbage may follow
    a message; a message cut short is followed by the next one inside its declared
    length). A message running past the end is ``cut`` unless another starts inside it.
    Adds to ``split`` if given."""
    out = split or Split()
    known = {h.decode() for h in HEADERS}
    for seg in segs:
        buf = b"".join(d for _, d in seg)
        ends = np.cumsum([len(d) for _, d in seg])
        times = [t for t, _ in seg]
        out.bytes += len(buf)
        n, pos, in_garbage = len(buf), 0, False
        while pos < n:
            head = _header_at(buf, pos)
            if head is not None:
                name, length = head
                end = pos + PREFIX_LEN + length
                pad = (-length) % 4
                nxt = end + pad if buf[end:end + pad] == bytes(pad) else end
                if end > n:
                    if _next_header(buf, pos + PREFIX_LEN) is None:
                        out.cut.append((name, length))
                        break
                elif (nxt >= n or _header_at(buf, nxt) is not None
                      or (name in known and _next_header(buf, pos + PREFIX_LEN, end) is None)):
                    t_ns = times[min(int(np.searchsorted(ends, end - 1, side="right")), len(times) - 1)]
                    st = out.headers.setdefault(name, HeaderStats(first_ns=t_ns))
                    st.count += 1
                    st.lengths[length] += 1
                    st.last_ns = t_ns
                    pos, in_garbage = nxt, False
                    continue
            elif n - pos < PREFIX_LEN and HEADER_RE.fullmatch(buf, pos, pos + 4):
                out.cut.append((buf[pos:pos + 4].decode("ascii"), -1))  # the length is cut too
                break
            if not in_garbage:
                out.resyncs += 1
                in_garbage = True
            nxt = _next_header(buf, pos + 1)
            if nxt is None:  # keep a tail that may be a header cut inside its length
                tail = HEADER_RE.search(buf, max(pos + 1, n - PREFIX_LEN + 1))
                nxt = tail.start() if tail is not None else n
            out.garbage_bytes += nxt - pos
            pos = nxt
    return out


# -- with a profile -------------------------------------------------------------------------------
@dataclass(frozen=True)
class FrameScore:
    """The range profile of frames of one static reflector: the ``peak_bin``, the peak
    over the profile's median (``sharpness_db``), over the highest bin outside its main
    lobe (``purity_db``: a wrong layout makes images of the reflector), and the angle of
    each frame at the peak (``angles_rad``, (F,))."""

    peak_bin: int
    sharpness_db: float
    purity_db: float
    angles_rad: np.ndarray


def score_frames(frames: np.ndarray, radar: RadarConfig) -> FrameScore:
    """Score frames of one static reflector.

    frames : (F, R, N, 2) complex, full-scale units (frame, ramp, sample, antenna).
    Each ramp's mean is removed (an ADC offset would otherwise peak at bin 0), the
    ramps are folded, Hann-windowed and back-projected per antenna (inverse FFT over
    the samples: bin n is range n dR); the magnitudes summed over frames and antennas
    make the range profile (N,). Ratios are 20 log10, at most :data:`MAX_SHARPNESS_DB`;
    the main lobe is :data:`MAIN_LOBE_BINS` either side of the peak (circular).
    """
    n = frames.shape[2]
    z = (frames - frames.mean(axis=2, keepdims=True)).sum(axis=1)  # (F, N, 2)
    u = np.fft.ifft(z * np.hanning(n)[None, :, None], axis=1)  # (F, N, 2)
    profile = np.abs(u).sum(axis=(0, 2))  # (N,)
    peak = int(np.argmax(profile))
    top = float(profile[peak])
    floor = top * 10 ** (-MAX_SHARPNESS_DB / 20)
    off = np.abs((np.arange(n) - peak + n // 2) % n - n // 2) > MAIN_LOBE_BINS
    second = float(profile[off].max(initial=0.0))

    def db(ratio_of: float) -> float:
        return float(20 * np.log10(top / max(ratio_of, floor))) if top > 0 else 0.0

    angles = angle_from_antennas_rad(u[:, peak, 0], u[:, peak, 1], radar)
    return FrameScore(peak, db(float(np.median(profile))), db(second), angles)


@dataclass
class ProfileScore:
    """How one profile reads the capture: RADCs decoded and ``invalid`` (plausible header,
    payload refused), bytes the decoder skipped, frames built, and on those frames
    (:func:`score_frames`) the range peak (bin, m), its ``sharpness_db`` and
    ``purity_db``, the median angle and its spread across frames (deg); ``fits`` and
    ``why``."""

    name: str
    payload_len: int
    radcs: int = 0
    invalid: int = 0
    skipped_bytes: int = 0
    frames: int = 0
    peak_bin: int | None = None
    range_m: float | None = None
    sharpness_db: float | None = None
    purity_db: float | None = None
    angle_deg: float | None = None
    angle_spread_deg: float | None = None
    fits: bool = False
    why: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


def _frames_of(messages: Sequence, profile: SensorProfile, ramps_per_frame: int, chirp_select: str) -> list[np.ndarray]:
    """Frames (R, N, 2) from decoded messages, as the session assembles them: a RADC
    counts when its DONE arrives; consecutive DONE counters make a frame of R RADCs."""
    lay = profile.radc
    az = list(lay.azimuth)
    chirps = lay.chirp_indices(ramps_per_frame, chirp_select) if lay.chirps > 1 else None
    frames, group, pending, last = [], [], None, None
    for m in messages:
        if isinstance(m, Radc):
            pending = m.words
        elif isinstance(m, Done):
            if pending is None or (last is not None and m.frame_counter != (last + 1) & 0xFFFFFFFF):
                group = []
            last = m.frame_counter
            if pending is None:
                continue
            words, pending = pending, None
            if chirps is not None:
                frames.append(lay.to_complex(words[az][:, chirps]))  # (R, N, 2)
                continue
            group.append(words[az, 0])
            if len(group) == ramps_per_frame:
                frames.append(lay.to_complex(np.stack(group)[:, :, None])[:, 0])  # (R, N, 2)
                group = []
    return frames


@dataclass(frozen=True)
class Reflector:
    """Where the capture's reflector is, if known: ``range_m`` and ``angle_deg``
    (positive: antenna 2's side); None = unknown. A fit must then agree within
    ``range_tol_m`` and ``angle_tol_deg``."""

    range_m: float | None = None
    angle_deg: float | None = None
    range_tol_m: float = 1.2
    angle_tol_deg: float = 5.0


def score_profile(segs: Sequence[Segment], profile: SensorProfile, ramps_per_frame: int = 2,
                  chirp_select: str = "first", radar: RadarConfig | None = None,
                  reflector: Reflector = Reflector()) -> ProfileScore:
    """Decode the sensor's bytes with ``profile`` and score the frames (see the module
    docstring). ``radar``: for the range bins and the angle (default: the paper's, with
    the profile's samples per chirp)."""
    lay = profile.radc
    score = ProfileScore(profile.name, lay.payload_len)
    if lay.chirps > 1 and ramps_per_frame > lay.chirps:
        score.why = f"a frame of {ramps_per_frame} ramps does not fit its {lay.chirps} chirps"
        return score
    radar = radar or RadarConfig(samples_per_ramp=lay.samples, ramps_per_frame=ramps_per_frame)
    frames: list[np.ndarray] = []
    last_error = ""
    for seg in segs:
        dec = StreamDecoder(profile)
        msgs = [m for _, data in seg for m in dec.feed(data)]
        score.radcs += sum(isinstance(m, Radc) for m in msgs)
        score.invalid += dec.stats.invalid
        score.skipped_bytes += dec.stats.skipped_bytes
        last_error = dec.stats.last_error or last_error
        frames += _frames_of(msgs, profile, ramps_per_frame, chirp_select)
    score.frames = len(frames)
    if not score.radcs:
        score.why = f"no RADC decodes (it expects {_thousands(lay.payload_len)} payload bytes)"
        if score.invalid:
            score.why += f"; {score.invalid} of that length refused: {last_error}"
        return score
    if not frames:
        score.why = f"{score.radcs} RADCs decode but make no frame of {ramps_per_frame} ramps"
        return score
    fs = score_frames(np.stack(frames), radar)
    deg = np.rad2deg(fs.angles_rad)
    score.peak_bin, score.sharpness_db, score.purity_db = fs.peak_bin, round(fs.sharpness_db, 2), round(fs.purity_db, 2)
    score.range_m = round(fs.peak_bin * radar.range_resolution_m, 3)
    score.angle_deg = round(float(np.median(deg)), 2)
    score.angle_spread_deg = round(float(np.std(deg)), 3)
    where = f"{score.range_m:.2f} m, {score.angle_deg:+.1f} deg"
    if score.frames < MIN_FRAMES:
        score.why = f"{score.frames} frames are too few to judge (at least {MIN_FRAMES})"
    elif not fs.sharpness_db >= MIN_SHARPNESS_DB:
        score.why = f"no sharp range peak ({fs.sharpness_db:.1f} dB over the median; a fit needs {MIN_SHARPNESS_DB:g})"
    elif not fs.purity_db >= MIN_PURITY_DB:
        score.why = (f"the peak has images ({fs.purity_db:.1f} dB over the next one; a fit needs {MIN_PURITY_DB:g}): "
                     f"a single reflector reads as several")
    elif not score.angle_spread_deg <= MAX_ANGLE_SPREAD_DEG:
        score.why = (f"the angle at the peak wanders ({score.angle_spread_deg:.1f} deg across frames; "
                     f"a fit needs {MAX_ANGLE_SPREAD_DEG:g})")
    elif reflector.range_m is not None and abs(score.range_m - reflector.range_m) > reflector.range_tol_m:
        score.why = f"the reflector comes out at {score.range_m:.2f} m, not {reflector.range_m:g} m"
    elif reflector.angle_deg is not None and abs(score.angle_deg - reflector.angle_deg) > reflector.angle_tol_deg:
        score.why = f"the reflector comes out at {score.angle_deg:+.1f} deg, not {reflector.angle_deg:+g} deg"
        if abs(reflector.angle_deg) > reflector.angle_tol_deg >= abs(score.angle_deg + reflector.angle_deg):
            score.why += (f" ({SIGN_FLIPPED}: the profile's azimuth pair in the other order, "
                          "azimuth = [1, 0] for [0, 1])")
    else:
        score.fits = True
        score.why = (f"one sharp range peak ({fs.sharpness_db:.1f} dB over the median, {fs.purity_db:.1f} dB over "
                     f"the next) at {where}, angle spread {score.angle_spread_deg:.2f} deg")
    return score


# -- the report -------------------------------------------------------------------------------------
@dataclass
class Report:
    """What ``qradar inspect`` says about a capture: the file, both directions split
    without a profile, every profile's score, the ``best`` fit (None: none fits), the
    fits that read it as well (``ambiguous``) and the ``verdict`` in words."""

    path: str
    header: dict
    records: int
    truncated: str | None
    duration_s: float
    segments: int
    line_speeds: list[int]
    sensor: Split
    host: Split
    reflector: Reflector
    scores: list[ProfileScore]
    best: str | None
    ambiguous: list[str]
    verdict: str

    def to_dict(self) -> dict:
        return {"path": self.path, "header": self.header, "records": self.records, "truncated": self.truncated,
                "duration_s": round(self.duration_s, 3), "segments": self.segments, "line_speeds": self.line_speeds,
                "sensor": self.sensor.to_dict(), "host": self.host.to_dict(), "reflector": asdict(self.reflector),
                "profiles": [s.to_dict() for s in self.scores], "best": self.best, "ambiguous": self.ambiguous,
                "verdict": self.verdict}


def _thousands(n: int) -> str:
    return f"{n:,}".replace(",", " ")


#: what a score's ``why`` says when only the angle's sign keeps it from fitting (swapped receivers)
SIGN_FLIPPED = "the sign flipped"

#: two fits whose purity and sharpness differ by less than this read the capture as well, dB
TIE_DB = 1.0


def verdict(scores: Sequence[ProfileScore], sensor: Split, tried: str = "shipped profile") -> tuple[str | None, list[str], str]:
    """(best profile or None, the other fits as good, one paragraph). The best fit has
    the purest peak (then the sharpest); without a fit, say what was seen (``tried``:
    what the candidates are, for "no ... fits")."""
    fits = sorted((s for s in scores if s.fits), key=lambda s: (s.purity_db, s.sharpness_db), reverse=True)
    if fits:
        best = fits[0]
        tied = [s for s in fits[1:] if best.purity_db - s.purity_db < TIE_DB
                and abs(best.sharpness_db - s.sharpness_db) < TIE_DB]
        text = f"{best.name} fits: {best.why}, over {best.frames} frames."
        if tied:
            text += (" " + ", ".join(f"{s.name} ({s.range_m:.2f} m, {s.angle_deg:+.1f} deg)" for s in tied)
                     + " read it as well: give the reflector's --range-m and --angle-deg to tell them apart.")
        rest = [s for s in scores if s is not best and s not in tied]
        if rest:
            text += " Rejected: " + "; ".join(f"{s.name}: {'fits less well' if s.fits else s.why}" for s in rest) + "."
        text += (" The angle's sign says the azimuth pair's order: with the reflector on antenna 2's side it must "
                 "come out positive.")
        return best.name, [s.name for s in tied], text
    flipped = [s for s in scores if SIGN_FLIPPED in s.why]
    if flipped:  # everything fits but the angle's sign: not a payload or layout to blame
        return None, [], (f"no {tried} fits, but {', '.join(s.name for s in flipped)} "
                          f"{'reads' if len(flipped) == 1 else 'read'} the reflector with "
                          f"the angle's sign flipped ({flipped[0].why.split(' (')[0]}): the receivers of the azimuth "
                          "pair are swapped; give a profile with the pair the other way round (docs/sensor.md).")
    radc = sensor.headers.get("RADC")
    if radc is None:
        seen = ", ".join(sensor.headers) or "no message"
        what = f"no RADC message in the sensor's bytes (seen: {seen})"
    else:
        what = f"RADC payloads of {', '.join(_thousands(n) for n in sorted(radc.lengths))} bytes"
    expect = ", ".join(f"{s.name} expects {_thousands(s.payload_len)}" for s in scores)
    whys = "; ".join(f"{s.name}: {s.why}" for s in scores if s.radcs)
    return None, [], f"no {tried} fits: {what}; {expect}" + (f" ({whys})" if whys else "") + "."


def inspect_capture(capture: Capture, profiles: Sequence[SensorProfile | str] | None = None,
                    ramps_per_frame: int = 2, chirp_select: str = "first",
                    reflector: Reflector = Reflector()) -> Report:
    """The report of a capture: the profile-free split of both directions, and every
    profile (default: the shipped ones) scored on the sensor's bytes."""
    cands = [resolve_profile(p) for p in (packaged_profiles() if profiles is None else profiles)]
    rx = segments(capture, Kind.RX)
    sensor = split_messages(rx)
    host = split_messages(segments(capture, Kind.TX))
    scores = [score_profile(rx, p, ramps_per_frame, chirp_select, reflector=reflector) for p in cands]
    best, tied, text = verdict(scores, sensor, "shipped profile" if profiles is None else "profile tried")
    h = capture.header
    return Report(str(capture.path), {"url": h.url, "start_time_ns": h.start_time_ns, "profile": h.profile, **h.extra},
                  len(capture.records), capture.truncated, capture.duration_s,
                  sum(r.kind == Kind.OPEN for r in capture.records),
                  [r.baud for r in capture.records if r.kind == Kind.BAUD and len(r.data) == 4],
                  sensor, host, reflector, scores, best, tied, text)


def _split_table(split: Split, indent: str = "  ") -> list[str]:
    rows = [f"{indent}{'header':<8}{'count':>7}{'rate /s':>9}  lengths (bytes: count)"]
    for name, st in split.headers.items():
        lengths = ", ".join(f"{_thousands(n)}: {c}" for n, c in sorted(st.lengths.items()))
        rows.append(f"{indent}{name:<8}{st.count:>7}{st.rate_hz:>9.1f}  {lengths}")
    extra = f"{indent}garbage: {_thousands(split.garbage_bytes)} bytes in {split.resyncs} runs"
    if split.cut:
        extra += "; cut short at the end: " + ", ".join(
            f"{h} of {_thousands(n)} bytes" if n >= 0 else f"{h} (inside its length)" for h, n in split.cut)
    return rows + [extra]


def format_report(r: Report) -> str:
    """The report as tables and a verdict, for a person."""
    h = r.header
    lines = [f"{r.path}: capture of {h['url']} (profile asked: {h['profile']}), {r.records} records over "
             f"{r.duration_s:.2f} s, {r.segments} port opening(s), line speeds {r.line_speeds or '-'}"]
    if r.truncated:
        lines.append(f"  the file ends early: {r.truncated}")
    lines.append(f"sensor -> host: {_thousands(r.sensor.bytes)} bytes")
    lines += _split_table(r.sensor)
    lines.append(f"host -> sensor: {_thousands(r.host.bytes)} bytes")
    lines += _split_table(r.host)
    lines.append("")
    ref = r.reflector
    if ref.range_m is not None or ref.angle_deg is not None:
        lines.append(f"reflector: range {ref.range_m if ref.range_m is not None else '?'} m, "
                     f"angle {ref.angle_deg if ref.angle_deg is not None else '?'} deg")
    lines.append(f"{'profile':<18}{'RADC bytes':>11}{'RADCs':>7}{'frames':>7}{'bin':>5}{'range m':>9}"
                 f"{'sharp dB':>9}{'pure dB':>8}{'angle':>7}{'spread':>7}  fits")

    def num(v, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    for s in r.scores:
        lines.append(f"{s.name:<18}{_thousands(s.payload_len):>11}{s.radcs:>7}{s.frames:>7}{num(s.peak_bin, 'd'):>5}"
                     f"{num(s.range_m, '.2f'):>9}{num(s.sharpness_db, '.1f'):>9}{num(s.purity_db, '.1f'):>8}"
                     f"{num(s.angle_deg, '+.1f'):>7}{num(s.angle_spread_deg, '.2f'):>7}  "
                     f"{'yes' if s.fits else 'no: ' + s.why}")
    lines.append("")
    lines.append(f"verdict: {r.verdict}")
    return "\n".join(lines)
