"""The paper's Monte Carlo (Sec. 5) with the protocol of docs/design.md.

Every run draws K targets in a 40 x 40 polar grid of cells (distinct range cells,
range centres snapped to the range grid unless ``off_grid``), uniform phases, the
strongest amplitude 1 and the others U[0, 1]; a scheme measures them, PBP localizes,
and each true target's error is ``min_k |R e^{i theta} - R_hat_k e^{i theta_hat_k}|``.

Schemes are named ``<kind>_m<M>``: ``dither`` / ``nodither`` (1-bit, delta per run the
smallest 1-bit step, alpha 1 / 0; ``dither_a<alpha>_m<M>``: another alpha in (0, 1]) and
``32bit`` (unquantized complex64 values).
M a multiple of N means whole ramps (FFT path); M < N means a random subset of the N
frequencies drawn per run (dense path).

Determinism: runs are cut into chunks of ``CHUNK_RUNS``; the scenes of chunk c for
sparsity K come from ``SeedSequence(seed, spawn_key=(K, c))`` -- every scheme sees the
same scenes -- and a scheme's own randomness (dither, subsets) from
``SeedSequence(seed, spawn_key=(K, c, crc32(scheme)))``. The result depends on the seed
and the number of runs, not on the number of worker processes.
"""

from __future__ import annotations

import multiprocessing
import os
import re
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from radar_driver.lifetime import watch_parent
from radar_driver.model import RadarConfig, simulate_frames, snap_to_range_grid
from radar_driver.options import finite_float, nonneg_float, nonneg_int, option, pos_int

from pipeline.defaults import DEFAULT_MAX_TARGETS
from pipeline.errors import ParameterError
from pipeline.dsp.decode import ALGOS, Algo, DecoderConfig, decode
from pipeline.dsp.gate import RangeGate, check_gate
from pipeline.dsp.localize import DEFAULT_PFA, Detections, check_pfa, match_detections, position_error_m
from pipeline.dsp.score import DETECTION_DISTANCE_M, FrameScores, score_frames, summarize as summarize_scores
from pipeline.dsp.noise import auto_alpha, estimate_noise_sigma
from replay.progress import Progress
from experiments.placement import separated_ranges
from experiments.speeds import draw_speeds, parse_speeds
from pipeline.dsp.quantize import auto_delta, batch_unit_dither, dequantize, quantize

GRID_CELLS = 40
ANGLE_CELL_DEG = 180.0 / GRID_CELLS
DEFAULT_SCHEMES = ("nodither_m512", "dither_m512", "32bit_m16", "32bit_m256")
CHUNK_RUNS = 4096
WITHIN_DEG = 60.0
OVER_M = 5.0

_SCHEME_RE = re.compile(r"^(nodither|dither|32bit)(?:_a([01](?:\.[0-9]+)?|auto))?_m([1-9][0-9]*)$")
#: how the cml decoder learns the sensor noise: ``codes`` (it estimates it from the codes,
#: what the live localizer does), ``true`` (the scene's noise_sigma), ``frames`` (the
#: quantizer's estimate from the full frames, :func:`pipeline.dsp.noise.estimate_noise_sigma`)
DECODER_NOISE = ("codes", "true", "frames")


@dataclass(frozen=True)
class Scheme:
    """A measurement scheme: ``bits`` 1 (quantized, ``alpha`` dither) or None (32-bit).
    ``adaptive``: alpha per run from the noise the quantizer estimates in the frame
    (:func:`pipeline.dsp.noise.auto_alpha`; ``alpha`` is then nan)."""

    name: str
    n_measurements: int
    bits: int | None
    alpha: float
    adaptive: bool = False

    @classmethod
    def parse(cls, name: str, config: RadarConfig) -> "Scheme":
        m = _SCHEME_RE.match(name)
        if not m or (m.group(2) is not None and (m.group(1) != "dither" or (
                m.group(2) != "auto" and not 0 < float(m.group(2)) <= 1))):
            raise ParameterError(f"scheme {name!r} is not of the form dither_m<M>, dither_a<alpha>_m<M> (0 < alpha "
                                 "<= 1), dither_aauto_m<M> (alpha from the noise), nodither_m<M> or 32bit_m<M>")
        kind, n_meas = m.group(1), int(m.group(3))
        n = config.samples_per_ramp
        if n_meas % n and n_meas > n:
            raise ParameterError(f"scheme {name!r}: M={n_meas} must be a multiple of N={n} (whole ramps) or below "
                                 f"N (a subset)")
        if kind == "32bit":
            return cls(name, n_meas, None, 0.0)
        if m.group(2) == "auto":
            if n_meas % n:
                raise ParameterError(f"scheme {name!r}: auto alpha estimates the noise on whole ramps; M={n_meas} "
                                     f"is not a multiple of N={n}")
            return cls(name, n_meas, 1, float("nan"), adaptive=True)
        alpha = float(m.group(2)) if m.group(2) is not None else 1.0 if kind == "dither" else 0.0
        return cls(name, n_meas, 1, alpha)

    def ramps(self, config: RadarConfig) -> int:
        n = config.samples_per_ramp
        return self.n_measurements // n if self.n_measurements % n == 0 else 0


RANGE_PLACEMENTS = ("grid", "cells", "continuous")


#: the scene's fields that only ``ranges="continuous"`` reads, and their options
CONTINUOUS_ONLY = (("range_min_m", "--range-interval"), ("range_max_m", "--range-interval"),
                   ("min_separation_m", "--min-separation-m"))


@dataclass(frozen=True)
class SceneSpec:
    """How the Monte Carlo places targets and what the sensor adds.

    ranges: ``grid`` (the paper's protocol: cell centres snapped to the range grid),
    ``cells`` (cell centres kept exact, off the grid) or ``continuous`` (uniform over
    [range_min_m, range_max_m], targets at least ``min_separation_m`` apart).
    max_angle_deg: angles within +-this (cells: the angle cells whose centre is inside;
    continuous: uniform). min_amplitude: the weaker targets' amplitudes are uniform in
    [min_amplitude, 1] (the strongest is 1). noise_sigma: complex white Gaussian noise,
    std of each of I and Q relative to the strongest amplitude, added to Gamma before
    quantization (every scheme, the 32-bit ones too). speeds: None (static targets, the
    paper's) or (lo, hi) m/s: each target's radial speed uniform in [lo, hi] with a random
    sign, the targets moving between the ramps of a frame (whole-ramp schemes only). The
    defaults are the paper's."""

    ranges: str = option("grid", "grid: cell centres on the range grid; cells: cell centres; continuous: uniform "
                         "over --range-interval (default grid)", choices=RANGE_PLACEMENTS)
    range_min_m: float = 3.0
    range_max_m: float = 150.0
    min_separation_m: float = option(1.5, "with --ranges continuous: targets at least this far apart (default 1.5)",
                                     parse=nonneg_float)
    max_angle_deg: float = option(90.0, "angles within +-this (default 90)", parse=nonneg_float)
    min_amplitude: float = option(0.0, "weaker targets' amplitudes uniform in [this, 1] (default 0)",
                                  parse=nonneg_float)
    noise_sigma: float = option(0.0, "sensor noise before quantization: std of I and of Q relative to the strongest "
                                "target (default 0)", parse=nonneg_float)
    speeds: tuple[float, float] | None = option(None, "radial speeds of the targets, m/s: uniform in LO:HI with a "
                                                "random sign, moving between the ramps (default: static)",
                                                parse=parse_speeds, metavar="LO:HI")

    def __post_init__(self) -> None:
        if self.speeds is not None:
            lo, hi = self.speeds
            if not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi):
                raise ParameterError(f"speeds={self.speeds!r} must be LO:HI m/s with 0 <= LO <= HI")
        if self.ranges not in RANGE_PLACEMENTS:
            raise ParameterError(f"ranges={self.ranges!r} must be one of {', '.join(RANGE_PLACEMENTS)}")
        for name in ("range_min_m", "range_max_m", "min_separation_m", "max_angle_deg", "min_amplitude",
                     "noise_sigma"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
                raise ParameterError(f"{name}={v!r} must be a finite number >= 0")
        if not 0 < self.max_angle_deg <= 90:
            raise ParameterError(f"max_angle_deg={self.max_angle_deg!r} must be in (0, 90]")
        if self.min_amplitude > 1:
            raise ParameterError(f"min_amplitude={self.min_amplitude!r} must be in [0, 1]")
        if not self.range_min_m < self.range_max_m:
            raise ParameterError(f"the range interval [{self.range_min_m}, {self.range_max_m}] m is empty")
        given = [f"{name}={getattr(self, name)!r} ({flag})" for name, flag in CONTINUOUS_ONLY
                 if self.ranges != "continuous" and getattr(self, name) != SceneSpec.__dataclass_fields__[name].default]
        if given:
            raise ParameterError(f"{', '.join(given)} place targets with --ranges continuous only; these ranges are "
                                 f"{self.ranges!r} (range cells' centres): give --ranges continuous, or leave them out")

    def check(self, config: RadarConfig, k_max: int) -> None:
        """Errors for a scene that cannot be drawn with this radar and up to ``k_max`` targets."""
        if self.ranges == "continuous":
            if self.range_max_m > config.max_range_m:
                raise ParameterError(f"range_max_m={self.range_max_m} is beyond the radar's {config.max_range_m} m")
            if (k_max - 1) * self.min_separation_m * 2 > self.range_max_m - self.range_min_m:
                raise ParameterError(
                    f"{k_max} targets {self.min_separation_m} m apart do not fit at random in "
                    f"[{self.range_min_m}, {self.range_max_m}] m; widen it or lower --min-separation-m")
        elif not np.any(np.abs(cell_centres(config)[1]) <= self.max_angle_deg):
            raise ParameterError(f"no angle cell centre lies within +-{self.max_angle_deg} deg")

    def to_dict(self) -> dict:
        """The fields; ``speeds`` only when the targets move (static scenes' files stand as they were)."""
        out = dict(vars(self))
        if self.speeds is None:
            del out["speeds"]
        return out


@dataclass(frozen=True)
class CountSpec:
    """How the decoders learn the number of targets. ``auto`` False: they are told each
    scene's K (the paper's protocol). ``auto`` True: they decide it (``K auto``), at most
    ``max_targets``, with false-alarm probability ``pfa`` per frame and test; a true
    target is then *found* when a detection not claimed by a stronger true target lies
    within ``gate_m`` of its range, detections left unclaimed are false targets, and the
    errors cover the found targets."""

    auto: bool = False
    max_targets: int = option(DEFAULT_MAX_TARGETS, "with --count auto: the most a frame has (default 4)", parse=pos_int)
    pfa: float = option(DEFAULT_PFA, "with --count auto: false-alarm probability per frame and test",
                        parse=lambda text: check_pfa(finite_float(text)))
    gate_m: float = option(0.6, "with --count auto: a true target is found by a detection within this range of it "
                           "(default 0.6, one range bin)", parse=nonneg_float)

    def __post_init__(self) -> None:
        if isinstance(self.max_targets, bool) or not isinstance(self.max_targets, int) or not \
                1 <= self.max_targets <= 16:
            raise ParameterError(f"max_targets={self.max_targets!r} must be an integer in [1, 16]")
        check_pfa(self.pfa)
        if isinstance(self.gate_m, bool) or not isinstance(self.gate_m, (int, float)) or not (
                np.isfinite(self.gate_m) and self.gate_m > 0):
            raise ParameterError(f"gate_m={self.gate_m!r} must be a finite number > 0")
        given = [f"{name}={getattr(self, name)!r} (--{name.replace('_', '-')})" for name in ("max_targets", "pfa",
                 "gate_m") if not self.auto and getattr(self, name) != CountSpec.__dataclass_fields__[name].default]
        if given:  # they act only when the decoders decide the count
            raise ParameterError(f"{', '.join(given)} act with --count auto only (the decoders decide the count); "
                                 "here each is told the scene's K: give --count auto, or leave them out")

    def to_dict(self) -> dict:
        return dict(vars(self))


#: amplitude of the weaker target from which K auto must find it (the issue's goal)
PD_AMPLITUDE = 0.3


@dataclass(frozen=True)
class MonteCarloConfig:
    """What to run: sparsities, runs per (scheme, K) (None = the paper's 320 000 x K),
    schemes, seed, off-grid ranges (the same as ``scene.ranges = "cells"``), worker
    processes (None = all cores), decoders, the scenes (:class:`SceneSpec`), how the
    decoders learn the target count (:class:`CountSpec`) and the range gate they search
    inside (None: the whole range axis, the paper's protocol)."""

    ks: tuple[int, ...] = option((1, 2), "sparsities (default 1 2)", flag="--K", many="+", parse=pos_int)
    runs: int | None = option(None, "runs per scheme and K (default: the paper's 320000 x K)", parse=pos_int)
    schemes: tuple[str, ...] = option(DEFAULT_SCHEMES, "dither_m<M>, dither_a<alpha>_m<M>, dither_aauto_m<M> (alpha "
                                      "from the noise the quantizer estimates in each frame), nodither_m<M>, "
                                      "32bit_m<M> (default: the paper's four)", many="+")
    seed: int = option(0, "random seed (runs are reproducible for a seed)", parse=nonneg_int)
    off_grid: bool = option(False, "keep range cell centres off the range grid (the same as --ranges cells)")
    workers: int | None = option(None, "worker processes (default: all cores)", parse=pos_int)
    radar: RadarConfig = field(default_factory=RadarConfig)
    algos: tuple[Algo, ...] = option((Algo.PBP,), f"decoders: {', '.join(ALGOS)} (default {Algo.PBP}); non-PBP "
                                     "results appear as <scheme>@<algo>", many="+")
    fallback_pbp: bool = option(False, "decode schemes without dither with PBP when a dither-aware algo is asked for")
    scene: SceneSpec = field(default_factory=SceneSpec)
    count: CountSpec = field(default_factory=CountSpec)
    gate: RangeGate | None = None
    decoder_noise: str = option("codes", "what cml is told of the noise: codes (it estimates it from the codes, as "
                                "live), true (the scene's --noise-sigma), frames (the quantizer's estimate from the "
                                "full frames) (default codes)", choices=DECODER_NOISE)

    def __post_init__(self) -> None:
        if self.decoder_noise not in DECODER_NOISE:
            raise ParameterError(f"decoder_noise={self.decoder_noise!r} must be one of {', '.join(DECODER_NOISE)}")
        if check_gate(self.gate) is not None:
            self.gate.check(self.radar)
        if self.off_grid and self.scene.ranges == "grid":
            object.__setattr__(self, "scene", replace(self.scene, ranges="cells"))
        object.__setattr__(self, "off_grid", self.scene.ranges != "grid")
        if not self.ks or any(isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= GRID_CELLS for k in self.ks):
            raise ParameterError(f"K values {self.ks!r} must be integers in [1, {GRID_CELLS}]: the targets of a "
                                 f"run sit in distinct range cells of the {GRID_CELLS} x {GRID_CELLS} grid")
        if self.runs is not None and (not isinstance(self.runs, int) or self.runs < 1):
            raise ParameterError(f"runs={self.runs!r} must be an integer >= 1")
        if not self.schemes:
            raise ParameterError("at least one scheme is needed")
        for s in self.schemes:
            Scheme.parse(s, self.radar)
        object.__setattr__(self, "algos", tuple(Algo(a) if a in ALGOS else a for a in self.algos))
        if len(set(self.schemes)) != len(self.schemes):
            raise ParameterError(f"schemes {self.schemes!r} repeat a name")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ParameterError(f"seed={self.seed!r} must be an integer >= 0")
        if self.workers is not None and (not isinstance(self.workers, int) or self.workers < 1):
            raise ParameterError(f"workers={self.workers!r} must be an integer >= 1")
        self.scene.check(self.radar, max(self.ks))
        if not self.algos or len(set(self.algos)) != len(self.algos):
            raise ParameterError(f"algos {self.algos!r} must be distinct and at least one")
        for a in self.algos:
            if a not in ALGOS:
                raise ParameterError(f"algo {a!r} is not known; available: {', '.join(ALGOS)}")
            DecoderConfig(algo=a, auto_k=self.count.auto, pfa=self.count.pfa)  # the decoder's own checks
            if a == Algo.PBP or self.fallback_pbp:
                continue
            for s in self.schemes:
                sch = Scheme.parse(s, self.radar)
                if a == Algo.CML and not sch.ramps(self.radar):
                    raise ParameterError(
                        f"algo {a!r} decodes frames of whole ramps; scheme {s!r} is a frequency subset. Drop it, or "
                        "pass --fallback-pbp to decode it with PBP")
                if a == Algo.QIHT and (sch.bits is None or sch.alpha == 0 or not sch.ramps(self.radar)):
                    raise ParameterError(
                        f"algo {a!r} decodes dithered 1-bit frames of whole ramps (dither_m<256 k>); scheme {s!r} "
                        "has no dither to regenerate. Drop it, or pass --fallback-pbp to decode it with PBP")

    def runs_for(self, k: int) -> int:
        return self.runs if self.runs is not None else 320_000 * k


# -- scenes -------------------------------------------------------------------------------
def cell_centres(config: RadarConfig, off_grid: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Range centres (40,) in m (snapped to the range grid unless ``off_grid``) and angle
    centres (40,) in deg."""
    r = (np.arange(GRID_CELLS) + 0.5) * config.max_range_m / GRID_CELLS
    if not off_grid:
        r = snap_to_range_grid(r, config)
    a = -90.0 + (np.arange(GRID_CELLS) + 0.5) * ANGLE_CELL_DEG
    return r, a


def draw_scenes(n_runs: int, k: int, rng: np.random.Generator, config: RadarConfig, off_grid: bool = False,
                scene: SceneSpec | None = None):
    """K targets per run. Returns (range_cell, angle_cell) ints and (range_m, angle_deg,
    amplitude complex), all (n_runs, K); target 0 is the strongest (amplitude 1), the
    others U[min_amplitude, 1]; phases uniform. ``grid``/``cells``: targets in distinct
    range cells at the cell centres; ``continuous``: uniform ranges and angles, the cells
    are those the targets fall in (for the maps)."""
    scene = scene or SceneSpec(ranges="cells" if off_grid else "grid")
    r_centres, a_centres = cell_centres(config, scene.ranges != "grid")
    if scene.ranges == "continuous":
        range_m = separated_ranges(n_runs, k, rng, scene.range_min_m, scene.range_max_m, scene.min_separation_m)
        angle_deg = rng.uniform(-scene.max_angle_deg, scene.max_angle_deg, (n_runs, k))
        range_cell = np.clip((range_m / (config.max_range_m / GRID_CELLS)).astype(int), 0, GRID_CELLS - 1)
        angle_cell = np.clip(((angle_deg + 90.0) / ANGLE_CELL_DEG).astype(int), 0, GRID_CELLS - 1)
    else:
        range_cell = np.argpartition(rng.random((n_runs, GRID_CELLS)), k - 1, axis=1)[:, :k]
        if scene.max_angle_deg >= 90:
            angle_cell = rng.integers(0, GRID_CELLS, (n_runs, k))
        else:
            allowed = np.flatnonzero(np.abs(a_centres) <= scene.max_angle_deg)
            angle_cell = allowed[rng.integers(0, allowed.size, (n_runs, k))]
        range_m, angle_deg = r_centres[range_cell], a_centres[angle_cell]
    mag = np.ones((n_runs, k))
    mag[:, 1:] = scene.min_amplitude + (1.0 - scene.min_amplitude) * rng.random((n_runs, k - 1))
    amplitude = mag * np.exp(2j * np.pi * rng.random((n_runs, k)))
    return range_cell, angle_cell, range_m, angle_deg, amplitude


def measure(scheme: Scheme, gamma_fn, n_runs: int, rng: np.random.Generator, config: RadarConfig,
            noise_sigma: float = 0.0, noise_rng: np.random.Generator | None = None, estimate: bool = False):
    """Measurements: unquantized frames (n_runs, M, 2) complex64, or a quantized scheme's
    codes (n_runs, M, 2, 2); the frequency indices (None or (n_runs, M)), the dither xi
    (None when there is none) and delta ((n_runs,) or None); with ``estimate``
    (or an adaptive scheme) a fifth item, the noise estimated from the full frames
    ((n_runs,), :func:`pipeline.dsp.noise.estimate_noise_sigma`). ``noise_sigma``: std of each
    of I and Q of white noise added to Gamma before quantization, drawn from ``noise_rng``
    (so that the dither does not depend on it)."""
    n = config.samples_per_ramp
    indices = None if scheme.ramps(config) else np.sort(
        np.argsort(rng.random((n_runs, n)), axis=1)[:, : scheme.n_measurements], axis=1)
    gamma = gamma_fn(indices)
    if noise_sigma > 0:
        gamma = gamma + noise_sigma * (noise_rng.standard_normal(gamma.shape) + 1j * noise_rng.standard_normal(gamma.shape))
    sigma_hat = estimate_noise_sigma(gamma, n) if (estimate or scheme.adaptive) and indices is None else None
    extra = (sigma_hat,) if estimate or scheme.adaptive else ()
    if scheme.bits is None:
        return (gamma.astype(np.complex64), indices, None, None) + extra
    delta = auto_delta(gamma)
    dither = None
    alpha = auto_alpha(sigma_hat, delta)[:, None, None] if scheme.adaptive else scheme.alpha
    if scheme.adaptive or scheme.alpha > 0:
        dither = batch_unit_dither(gamma.shape, rng, scale=alpha * delta[:, None, None])
    return (quantize(gamma, delta, scheme.bits, dither), indices, dither, delta) + extra


@dataclass
class ChunkResult:
    range_cell: np.ndarray  # (n, K)
    angle_cell: np.ndarray  # (n, K)
    angle_deg: np.ndarray  # (n, K) true angles
    error_m: np.ndarray  # (n, K); with K auto, NaN for a target not found
    amplitude: np.ndarray | None = None  # (n, K) true |amplitude| (K auto only)
    found: np.ndarray | None = None  # (n, K) bool (K auto only)
    false_targets: np.ndarray | None = None  # (n,) detections that are no true target (K auto only)
    # the honest score (pipeline.dsp.score), every run: each true target's error when a target was
    # matched to it within DETECTION_DISTANCE_M in the plane (NaN: missed) (n, K), the targets near no
    # true target (n,), the targets reported (n,)
    score_error_m: np.ndarray | None = None
    score_false: np.ndarray | None = None
    score_targets: np.ndarray | None = None
    score_nearest_m: np.ndarray | None = None  # (n, K) each true target to the nearest target


def run_chunk(k: int, schemes: tuple[str, ...], chunk: int, n_runs: int, seed: int, scene: SceneSpec,
              radar: RadarConfig, algos: tuple[str, ...] = (Algo.PBP,), fallback_pbp: bool = True,
              count: CountSpec = CountSpec(), gate: RangeGate | None = None,
              decoder_noise: str = "codes") -> dict[str, dict[str, ChunkResult]]:
    """One chunk of runs of each of ``schemes`` (the same scenes, their noiseless frames
    simulated once), decoded by each algo (a scheme's measurements the same for all); pure
    given its arguments, a scheme's results the same whichever others run. ``decoder_noise``:
    what cml is told of the noise (:data:`DECODER_NOISE`). Returns {scheme: {algo: ChunkResult}}."""
    scene_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(k, chunk)))
    rc, ac, r, a, x = draw_scenes(n_runs, k, scene_rng, radar, scene=scene)
    rc, ac = rc.astype(np.int8), ac.astype(np.int8)  # (n, K) cells, as the results keep them
    v = draw_speeds(n_runs, k, seed, chunk, scene.speeds)
    whole: dict[int, np.ndarray] = {}  # the noiseless frames of whole ramps, by ramp count

    def gamma_fn(scheme: Scheme, idx):
        ramps = scheme.ramps(radar)
        if idx is not None:
            return simulate_frames(r, a, x, radar, idx)
        if ramps not in whole:
            whole[ramps] = simulate_frames(r, a, x, radar, None, ramps=ramps, velocity_mps=v)
        return whole[ramps]

    out = {}
    for name in schemes:
        scheme = Scheme.parse(name, radar)
        if v is not None and not scheme.ramps(radar):
            raise ParameterError(f"--speeds needs whole ramps; scheme {name} measures a frequency subset")
        crc = zlib.crc32(name.encode())
        scheme_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(k, chunk, crc)))
        noise_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(k, chunk, crc, 1)))
        z, indices, xi, delta, *est = measure(scheme, partial(gamma_fn, scheme), n_runs, scheme_rng, radar,
                                              scene.noise_sigma, noise_rng, estimate=decoder_noise == "frames")
        noise = {"codes": None, "true": scene.noise_sigma, "frames": est[0] if est else None}[decoder_noise]
        out[name] = {}
        values = z if scheme.bits is None else None  # the codes' values, made once if a decoder needs them
        for algo in algos:
            decoder = DecoderConfig(algo=algo, fallback_pbp=fallback_pbp, auto_k=count.auto, pfa=count.pfa, gate=gate,
                                    uncertainty=False)  # positions are what it scores
            takes_codes = scheme.bits is not None and algo == Algo.CML and indices is None  # cml: the codes as they are
            if not takes_codes and values is None:
                values = dequantize(z, delta, scheme.bits)
            det = decode(z if takes_codes else values, xi, delta, scheme.bits, radar, count.max_targets if count.auto
                         else k, decoder, indices, noise_sigma=noise, alpha=scheme.alpha if xi is None else None)
            out[name][algo] = chunk_result(r, a, x, rc, ac, det, count)
    return out


def chunk_result(r, a, x, rc, ac, det: Detections, count: CountSpec) -> ChunkResult:
    """The errors and scores of one decoder's detections ``det`` of scenes ``r, a, x`` (int8 cells ``rc, ac``)."""
    err = position_error_m(r, a, det.range_m, det.angle_deg)
    sc = score_frames(r, a, det.range_m, det.angle_deg)
    scored = dict(score_error_m=sc.error_m.astype(np.float32), score_false=sc.false_targets.astype(np.int16),
                  score_targets=sc.targets.astype(np.int16), score_nearest_m=sc.nearest_m.astype(np.float32))
    if not count.auto:
        return ChunkResult(rc, ac, a, err, **scored)
    found, false_targets = match_detections(r, det.range_m, count.gate_m)
    return ChunkResult(rc, ac, a, np.where(found, err, np.nan), np.abs(x), found, false_targets, **scored)


# -- aggregation ----------------------------------------------------------------------------
def cell_mean_map(range_cell: np.ndarray, angle_cell: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` per (range cell, angle cell), NaN values left out: (40, 40)
    means (NaN where empty) and (40, 40) counts."""
    keep = ~np.isnan(values)
    if not keep.all():
        range_cell, angle_cell, values = range_cell[keep], angle_cell[keep], values[keep]
    flat = range_cell.astype(np.int64) * GRID_CELLS + angle_cell
    counts = np.bincount(flat, minlength=GRID_CELLS**2).reshape(GRID_CELLS, GRID_CELLS)
    sums = np.bincount(flat, weights=values, minlength=GRID_CELLS**2).reshape(GRID_CELLS, GRID_CELLS)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return means, counts


def within_60_columns() -> np.ndarray:
    """Boolean (40,) mask of the angle cells whose centre has |theta| < 60 deg."""
    _, a = cell_centres(RadarConfig())
    return np.abs(a) < WITHIN_DEG


def summarize(result: ChunkResult) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Figures and maps of all runs of one (scheme, K).

    Target 0 is the strongest; the weakest is the one of smallest amplitude, which the
    scene draw puts last (for K = 1 the only target is both). With K auto the error
    figures cover the found targets (NaN errors are left out), and the detection figures
    of :func:`detection_stats` are added."""
    err, a = result.error_m, result.angle_deg
    within = np.abs(a) < WITHIN_DEG
    maps: dict[str, np.ndarray] = {}
    strong_map, strong_n = cell_mean_map(result.range_cell[:, 0], result.angle_cell[:, 0], err[:, 0])
    weak_map, weak_n = cell_mean_map(result.range_cell[:, -1], result.angle_cell[:, -1], err[:, -1])
    all_map, all_n = cell_mean_map(result.range_cell.ravel(), result.angle_cell.ravel(), err.ravel())
    maps.update(all=all_map, all_count=all_n, strong=strong_map, strong_count=strong_n,
                weak=weak_map, weak_count=weak_n)
    cols = within_60_columns()
    sub = strong_map[:, cols]
    sub = sub[np.isfinite(sub)]
    found = ~np.isnan(err)

    def of(values: np.ndarray, fn) -> float:  # fn over the errors of found targets (NaN if none)
        v = values if found.all() else values[~np.isnan(values)]
        return float(fn(v)) if v.size else float("nan")

    stats = {
        "mean_m": of(err, np.mean),
        "median_m": of(err, np.median),
        "p90_m": of(err, lambda v: np.percentile(v, 90)),
        "median_within_60deg_m": of(err[within], np.median),
        "cells_over_5m_within_60deg": float(np.mean(sub > OVER_M)) if sub.size else float("nan"),
        "strong_mean_m": of(err[:, 0], np.mean),
        "weak_mean_m": of(err[:, -1], np.mean),
    }
    if result.found is not None:
        stats.update(detection_stats(result))
    if result.score_error_m is not None:  # strongest target first, the weakest last
        stats["score"] = summarize_scores(FrameScores(result.score_error_m.astype(float),
                                                      result.score_nearest_m.astype(float),
                                                      result.score_false, result.score_targets,
                                                      DETECTION_DISTANCE_M)).to_dict()
    return stats, maps


def detection_stats(result: ChunkResult) -> dict:
    """K auto figures: detection probability of the strongest and of the weakest target
    (and of the weakest when its amplitude >= PD_AMPLITUDE), false targets per frame and
    the fraction of frames with any, the fraction of frames with exactly K targets, and
    the weakest target's detection probability in amplitude bins of 0.1
    (``pd_weak_by_amplitude``: [bin's lower edge, pd, runs])."""
    found, amp = result.found, result.amplitude
    k = found.shape[1]
    count = found.sum(axis=1) + result.false_targets
    strong_enough = amp[:, -1] >= PD_AMPLITUDE
    edges = np.round(np.arange(0.0, 1.0001, 0.1), 1)
    idx = np.clip(np.digitize(amp[:, -1], edges) - 1, 0, len(edges) - 2)
    runs = np.bincount(idx, minlength=len(edges) - 1)
    hits = np.bincount(idx, weights=found[:, -1], minlength=len(edges) - 1)
    return {
        "pd_strong": float(found[:, 0].mean()),
        "pd_weak": float(found[:, -1].mean()),
        f"pd_weak_amp_ge_{PD_AMPLITUDE}": float(found[strong_enough, -1].mean()) if strong_enough.any() else
        float("nan"),
        "false_targets_per_frame": float(result.false_targets.mean()),
        "frames_with_false_targets": float(np.mean(result.false_targets > 0)),
        "count_exact": float(np.mean(count == k)),
        "pd_weak_by_amplitude": [[float(edges[i]), float(hits[i] / runs[i]), int(runs[i])]
                                 for i in range(len(runs)) if runs[i]],
    }


def _concat(parts: list[ChunkResult]) -> ChunkResult:
    return ChunkResult(*(None if getattr(parts[0], f) is None else np.concatenate([getattr(p, f) for p in parts])
                         for f in ChunkResult.__dataclass_fields__))


@dataclass
class MonteCarloResult:
    summary: dict
    maps: dict[str, np.ndarray]  # key "K{K}_{scheme}_{all|strong|weak}[_count]"
    run_config: dict


def run_montecarlo(cfg: MonteCarloConfig, progress: bool = True) -> MonteCarloResult:
    """Run every (K, scheme) of ``cfg``; returns the summary dict and the cell maps."""
    t0 = time.perf_counter()
    schemes = tuple(cfg.schemes)  # a job: (K, schemes, chunk, runs), a chunk's scenes simulated once for all schemes
    jobs = [(k, schemes, c, min(CHUNK_RUNS, cfg.runs_for(k) - start)) for k in cfg.ks
            for c, start in enumerate(range(0, cfg.runs_for(k), CHUNK_RUNS))]
    total_runs = sum(j[3] for j in jobs) * len(schemes)
    workers = cfg.workers or os.cpu_count() or 1
    parts: dict[tuple[int, str, str], list] = {(k, s, a): [] for k in cfg.ks for s in schemes for a in cfg.algos}
    algos = tuple(cfg.algos)

    def collect(job, result: dict[str, dict[str, ChunkResult]]) -> None:
        for s, by_algo in result.items():
            for a, res in by_algo.items():
                parts[(job[0], s, a)].append(res)

    with Progress(total_runs, "montecarlo", unit="runs", enabled=progress) as bar:
        if workers == 1:
            for job in jobs:
                collect(job, run_chunk(*job, cfg.seed, cfg.scene, cfg.radar, algos, cfg.fallback_pbp, cfg.count,
                                        cfg.gate, cfg.decoder_noise))
                bar.update(job[3] * len(schemes))
        else:
            # spawned (a fork of a process with threads hung on the locks they held); each ends with us
            with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                     initializer=watch_parent, initargs=(os.getpid(), "montecarlo worker")) as pool:
                futures = [(job, pool.submit(run_chunk, *job, cfg.seed, cfg.scene, cfg.radar, algos,
                                             cfg.fallback_pbp, cfg.count, cfg.gate, cfg.decoder_noise))
                           for job in jobs]
                for job, fut in futures:  # in submission order: deterministic assembly
                    collect(job, fut.result())
                    bar.update(job[3] * len(schemes))
    summary: dict = {}
    maps: dict[str, np.ndarray] = {}
    for k in cfg.ks:
        block = summary.setdefault(f"K{k}", {})
        for s in cfg.schemes:
            for a in cfg.algos:
                name_sa = s if a == Algo.PBP else f"{s}@{a}"
                stats, m = summarize(_concat(parts[(k, s, a)]))
                block[name_sa] = stats
                for name, arr in m.items():
                    maps[f"K{k}_{name_sa}_{name}"] = arr
    runs_per_k = {f"K{k}": cfg.runs_for(k) for k in cfg.ks}
    summary["runs"] = cfg.runs if cfg.runs is not None else runs_per_k
    summary["scene"], summary["count"] = cfg.scene.to_dict(), cfg.count.to_dict()
    if cfg.gate is not None:  # (the paper's protocol searches the whole range axis)
        summary["gate"] = cfg.gate.to_dict()
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    run_config = {
        "seed": cfg.seed, "off_grid": cfg.off_grid, "schemes": list(cfg.schemes), "ks": list(cfg.ks),
        "runs_per_k": runs_per_k, "workers": workers, "chunk_runs": CHUNK_RUNS, "radar": cfg.radar.to_dict(),
        "algos": [str(a) for a in cfg.algos], "fallback_pbp": cfg.fallback_pbp, "scene": cfg.scene.to_dict(),
        "count": cfg.count.to_dict(), "gate": None if cfg.gate is None else cfg.gate.to_dict(),
        "decoder_noise": cfg.decoder_noise}
    return MonteCarloResult(summary, maps, run_config)
