"""Projected back projection (PBP, paper eq. 5) and target extraction.

``X_hat = P_Theta_K(Phi^* Z / M)``: back-project the (quantized) measurements, keep the
K range bins with the largest joint energy ``(|U_n1|^2 + |U_n2|^2)^(1/2)``, then read
range from the bin and angle from the phase between the antennas.

Two back projections give the same ``Phi^* Z / M``:

* :func:`back_project_ramps` for frames of whole ramps: fold the ramps, one inverse
  FFT of length N per antenna, times ``exp(+i 4 pi f0 R_n / c)``: O(M + N log N).
* :func:`back_project_dense` for any set of frequencies: a shared subset by an explicit
  ``Phi^H Z`` (its matrix cached), O(M N); a subset per frame by one inverse FFT of the
  samples put at their frequencies, O(M + N log N).

Shapes: Z is (B, M, 2); U and X_hat are (B, N, 2); supports and targets are (B, K),
ordered strongest first.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from radar_driver.model import (RadarConfig, angle_from_antennas_rad, carrier, polar_to_plane, polar_to_xy,
                                sensing_matrix)

from pipeline.errors import ParameterError
from pipeline.dsp.gate import LEAKAGE_BINS, RangeGate, boundary_skirts, check_gate
from pipeline.dsp.residual import residual_support


def _check_z(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z)
    if z.ndim != 3 or z.shape[-1] != 2:
        raise ParameterError(f"Z must have shape (B, M, 2), got {z.shape}")
    return z


def back_project_ramps(z: np.ndarray, config: RadarConfig) -> np.ndarray:
    """``Phi^* Z / M`` for frames of whole ramps (fast path).

    z : (B, M, 2) with M a multiple of N (measurement m at frequency index m mod N).
    Returns U, (B, N, 2) complex.
    """
    z = _check_z(z)
    n = config.samples_per_ramp
    b, m, _ = z.shape
    if m == 0 or m % n:
        raise ParameterError(f"M={m} is not a whole number of ramps of N={n} samples")
    folded = z if m == n else z.reshape(b, m // n, n, 2).sum(axis=1)  # (B, N, 2)
    # sum_k folded_k exp(+i 2 pi k n / N) = N * ifft; the f0 term exp(+i 4 pi f0 R_n / c)
    spectrum = np.fft.ifft(folded, axis=1)
    if m != n:
        spectrum *= n / m
    spectrum *= _conj_carrier(config)[None, :, None]
    return spectrum


def fold_ramps(z: np.ndarray, config: RadarConfig) -> np.ndarray:
    """The mean of the ramps of frames Z (B, M, 2) of whole ramps: (B, N, 2) complex."""
    z = _check_z(z)
    n = config.samples_per_ramp
    b, m, _ = z.shape
    return z.reshape(b, m // n, n, 2).mean(axis=1, dtype=np.complex128)


@lru_cache(maxsize=32)
def _conj_carrier(config: RadarConfig) -> np.ndarray:
    """``conj(carrier(config))``, (N,) complex128, read-only."""
    c = np.conj(carrier(config)).astype(np.complex128)
    c.flags.writeable = False
    return c


def back_project_dense(z: np.ndarray, config: RadarConfig, indices: np.ndarray | None = None) -> np.ndarray:
    """``Phi^* Z / M`` for any frequencies (dense path).

    z : (B, M, 2). indices : None (whole ramps), (M,) shared or (B, M) per-frame
    frequency indices in [0, N). Returns U, (B, N, 2) complex.
    """
    z = _check_z(z)
    if indices is not None and np.ndim(indices) == 2:
        return _back_project_subsets(z, config, indices)
    key = None if indices is None else np.asarray(indices, dtype=np.int64).tobytes()
    phi = _shared_adjoint(config, key)  # (M, N), cached: a live stream reuses one subset
    if phi.shape[-2] != z.shape[1]:
        raise ParameterError(f"Z {z.shape} does not match the frequencies {phi.shape[:-1]}")
    return np.einsum("mn,bmp->bnp", phi, z, optimize=True) / z.shape[1]


def _back_project_subsets(z: np.ndarray, config: RadarConfig, indices: np.ndarray) -> np.ndarray:
    """``Phi^* Z / M`` of frames Z (B, M, 2) of per-frame frequency subsets ``indices`` (B, M)
    in [0, N): ``Phi_mn = carrier_n exp(-2 pi i k_m n / N)`` (f_m = f0 + B k_m / N, R_n = n dR),
    so each frame's samples go to their frequencies (twice the same frequency: summed) and
    one inverse FFT of length N per antenna sums them, times the conjugate carrier:
    O(B (M + N log N)), not the dense O(B M N) complex exponentials (the Monte Carlo's subset
    schemes spent half their time in them). Equal to the dense sum to its rounding (1e-11
    relative: the dense phases are ~1e5 rad)."""
    k = np.asarray(indices)
    b, m, _ = z.shape
    if k.shape != (b, m):
        raise ParameterError(f"Z {z.shape} does not match the frequencies {k.shape}")
    config.frequencies_hz(k)  # integers in [0, N), or the error the dense matrix gave
    if m == 0:
        raise ParameterError(f"Z {z.shape}: frames of no frequency")
    k = k.astype(np.int64, copy=False)  # (unsigned 64-bit indices would mix into floats)
    n = config.samples_per_ramp
    spectrum = np.zeros((b * n, 2), dtype=np.complex128)
    np.add.at(spectrum, (np.arange(b)[:, None] * n + k).ravel(), z.reshape(b * m, 2))
    u = np.fft.ifft(spectrum.reshape(b, n, 2), axis=1)  # (1/N) sum_m exp(+2 pi i k_m n / N) z_m
    u *= _conj_carrier(config)[None, :, None] * (n / m)
    return u


@lru_cache(maxsize=32)
def _shared_adjoint(config: RadarConfig, indices_key: bytes | None) -> np.ndarray:
    """conj(Phi) for whole ramps (key None) or one shared subset (int64 bytes); read-only."""
    indices = None if indices_key is None else np.frombuffer(indices_key, dtype=np.int64)
    phi = np.conj(sensing_matrix(config, indices))
    phi.flags.writeable = False
    return phi


def back_project(z: np.ndarray, config: RadarConfig, indices: np.ndarray | None = None) -> np.ndarray:
    """``Phi^* Z / M``: the FFT path for whole ramps (``indices=None``), dense otherwise."""
    if indices is None:
        return back_project_ramps(z, config)
    return back_project_dense(z, config, indices)


def joint_energy(u: np.ndarray) -> np.ndarray:
    """``|U_n1|^2 + |U_n2|^2``, the squared joint norm of each bin: (B, N, 2) complex ->
    (B, N) float (squares of the real and imaginary parts; no reduction over the short
    antenna axis, which numpy does slowly)."""
    u = np.ascontiguousarray(u, dtype=np.complex128)
    p = np.square(u.view(np.float64)).reshape(u.shape[:-1] + (4,))  # Re, Im of antenna 1, then 2
    return (p[..., 0] + p[..., 1]) + (p[..., 2] + p[..., 3])


#: a frame shows a front end when its strongest return in the first or last LEAKAGE_BINS range
#: bins has at least this share of the power of its strongest return anywhere (-10 dB):
#: uncalibrated, the leakage is the strongest (1); calibrated by another front end's file, its
#: background subtracted from frames without one is a leakage of its own (0.23-1 measured, the
#: committed chamber recording 0.91); a fitting calibration leaves noise (0.001-0.025, 90th
#: percentile, 1-bit or not)
LEAKAGE_POWER_SHARE = 0.1
#: ... and stands this many times above the frame's median bin (its noise floor, about): a
#: frame of noise alone (the empty chamber, calibrated) has its strongest bin anywhere, and
#: near bins within 10 dB of it. Measured, 1-bit or not: a front end 120-60 000 times the
#: median (1st percentile 120), a fitting calibration's near bins 0.7-20 times (99th percentile)
LEAKAGE_OVER_FLOOR = 30.0
#: ... and is a peak of its own: this many times the bins just beyond the near ones (bin
#: ``bins`` and bin ``N - bins - 1``). A leakage or DC peaks in bin 0 (its neighbours beyond:
#: -15 dB and less); a target just beyond them (1.5 m: between bins 2 and 3) puts a sidelobe
#: into bin 1 within 10 dB of its peak, but its peak lies beyond
LEAKAGE_OVER_NEIGHBOUR = 2.0
#: 1-bit codes without a dither: a tone's complex sign ``sign(cos) + i sign(sin)`` holds
#: ``-1/3`` of it at minus three times its frequency (-9.5 dB, within LEAKAGE_POWER_SHARE): a
#: target at N/3 or 2N/3 bins (51.2 or 102.4 m on the paper's radar) puts that harmonic into
#: the near bins. The bins within this many of ``-3`` times the strongest return's bin (modulo
#: N; the bin's rounding and a 0.5-bin offset make 1.5) are not taken for a front end there
SIGN_HARMONIC_REACH = 2


def leakage_return(z: np.ndarray, config: RadarConfig, bins: int = LEAKAGE_BINS,
                   sign_codes: bool | np.ndarray = False) -> np.ndarray:
    """Whether each frame Z (B, M, 2) of whole ramps (quantized or not) has a return in the
    first or last ``bins`` range bins of the circular range axis, where a real front end's
    DC offset and TX-to-RX leakage sit (docs/design.md): a peak there within
    LEAKAGE_POWER_SHARE of the power of the frame's strongest return, LEAKAGE_OVER_FLOOR times
    its median bin and LEAKAGE_OVER_NEIGHBOUR times the bins just beyond: (B,) bool. In most
    frames of a sensor, its front end is not removed (no calibration, or one of another front
    end); 0-5 % of the frames of a calibrated one (the simulated chamber). ``sign_codes``
    (one for all, or (B,) bool): frames of 1-bit codes without a dither, whose quantizer's
    harmonic of a strongest return beyond the near bins is not taken for a front end
    (:data:`SIGN_HARMONIC_REACH`)."""
    n = config.samples_per_ramp
    energy = joint_energy(back_project_ramps(z, config))
    strongest = energy.max(axis=1)
    sign_codes = np.broadcast_to(np.asarray(sign_codes, dtype=bool), energy.shape[:1])
    if sign_codes.any():
        top = energy.argmax(axis=1)
        harmonic = sign_codes & (top >= bins) & (top < n - bins)  # the strongest is not itself near
        if harmonic.any():
            rows = np.flatnonzero(harmonic)
            cols = (-3 * top[rows, None] + np.arange(-SIGN_HARMONIC_REACH, SIGN_HARMONIC_REACH + 1)) % n
            energy[rows[:, None], cols] = 0.0
    near = np.maximum(energy[:, :bins].max(axis=1), energy[:, n - bins:].max(axis=1))
    beyond = np.maximum(energy[:, bins], energy[:, n - bins - 1])
    return ((near >= LEAKAGE_POWER_SHARE * strongest)
            & (near >= LEAKAGE_OVER_FLOOR * np.median(energy, axis=1)) & (near >= LEAKAGE_OVER_NEIGHBOUR * beyond))


def joint_support(u: np.ndarray, k: int, energy: np.ndarray | None = None) -> np.ndarray:
    """Indices of the K bins with the largest ``(|U_n1|^2 + |U_n2|^2)^(1/2)``,
    strongest first: (B, N, 2) -> (B, K) int. ``energy``: :func:`joint_energy` of U
    when already known."""
    u = np.asarray(u)
    n = u.shape[1]
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= n:
        raise ParameterError(f"K={k!r} must be an integer in [1, N={n}]")
    energy = joint_energy(u) if energy is None else energy  # monotone in the joint norm
    top = np.argpartition(-energy, k - 1, axis=1)[:, :k]
    frames = np.arange(top.shape[0])[:, None]
    order = np.argsort(-energy[frames, top], axis=1, kind="stable")
    return top[frames, order]


def project_theta_k(u: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """P_Theta_K(U): zero all but the K strongest rows (joint support).

    Returns (X_hat (B, N, 2), support (B, K) strongest first).
    """
    support = joint_support(u, k)
    x = np.zeros_like(u)
    rows = np.take_along_axis(u, support[:, :, None], axis=1)
    np.put_along_axis(x, support[:, :, None], rows, axis=1)
    return x, support


def pbp(z: np.ndarray, config: RadarConfig, k: int, indices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """PBP estimate ``P_Theta_K(Phi^* Z / M)``: (X_hat (B, N, 2), support (B, K))."""
    return project_theta_k(back_project(z, config, indices), k)


#: default false-alarm probability of ``K auto``: per frame and per test, the chance that a
#: residual with no target left crosses the detection threshold
DEFAULT_PFA = 1e-3
#: a detection statistic too large to be finite (a noiseless fit) is reported as this, dB
STATISTIC_CAP_DB = 300.0


def check_pfa(pfa) -> float:
    """``pfa`` if it is a false-alarm probability in (0, 1), else a ParameterError."""
    if isinstance(pfa, bool) or not (isinstance(pfa, (int, float)) and 0 < pfa < 1):
        raise ParameterError(f"pfa={pfa!r} must be a false-alarm probability in (0, 1)")
    return float(pfa)


def cfar_threshold(pfa: float, cells: float) -> float:
    """Detection threshold on (peak joint energy) / (mean joint energy per bin), linear.

    Under the null (white Gaussian residual: 4 real degrees of freedom a bin over the
    two antennas) the joint energy of a bin over its mean is Gamma(2, 1/2), exceeded
    with probability ``e^-2x (1 + 2x)``, so the largest of ``cells`` independent bins
    exceeds T with probability ``cells e^-2T (1 + 2T)``; T solves that equal to ``pfa``
    (0 < pfa < 1)."""
    base = np.log(max(cells, 1.0) / check_pfa(pfa))
    y = max(base, 1.0)
    for _ in range(50):  # y = log(cells / pfa) + log(1 + y), y = 2T: a contraction
        y = base + np.log1p(y)
    return float(y / 2.0)


def cfar_p_value(statistic_db: np.ndarray, cells: float) -> np.ndarray:
    """The chance that white Gaussian noise alone makes the largest of ``cells`` bins reach
    ``statistic_db`` (its joint energy over the bins' mean, dB; any shape): ``1 - (1 - e^-2x
    (1 + 2x))^cells`` with x the linear statistic (the null of :func:`cfar_threshold`)."""
    x = 10.0 ** (np.clip(np.asarray(statistic_db, dtype=float), -300.0, 300.0) / 10.0)
    with np.errstate(over="ignore", invalid="ignore"):
        one = np.exp(-2.0 * x) * (1.0 + 2.0 * x)  # one bin's
        return -np.expm1(max(cells, 1.0) * np.log1p(-np.minimum(one, 1.0 - 1e-16)))


def sequential_present(statistic_db: np.ndarray, threshold_db: float) -> np.ndarray:
    """Targets kept by a sequential test (B, K) bool: target t of a frame is kept while
    every target up to t has ``statistic_db >= threshold_db`` (targets in test order)."""
    return np.cumprod(np.asarray(statistic_db) >= threshold_db, axis=1).astype(bool)


def to_db(ratio: np.ndarray) -> np.ndarray:
    """10 log10 of a power ratio, capped at +-STATISTIC_CAP_DB (0 -> -cap, inf -> +cap)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        db = 10 * np.log10(ratio)
    return np.clip(np.nan_to_num(db, nan=-STATISTIC_CAP_DB), -STATISTIC_CAP_DB, STATISTIC_CAP_DB)


def grid_statistic_db(u: np.ndarray, support: np.ndarray, energy: np.ndarray | None = None,
                      cells: int | None = None) -> np.ndarray:
    """Cell-averaging statistic of the support bins of a back projection U (B, N, 2),
    support (B, K) strongest first: dB, (B, K). Target t: its joint energy
    ``|U1|^2 + |U2|^2`` over the mean of the bins outside ``support[:, :t + 1]``.
    ``energy``: :func:`joint_energy` of U when already known; with a range gate, the
    energy with the bins outside the gate set to 0 and ``cells`` the bins inside (the
    mean is then over the gate's bins)."""
    energy = joint_energy(u) if energy is None else energy  # (B, N)
    n = energy.shape[1] if cells is None else cells
    e_t = energy[np.arange(energy.shape[0])[:, None], support]
    rest = (energy.sum(axis=1, keepdims=True) - np.cumsum(e_t, axis=1)) / np.maximum(
        n - 1 - np.arange(support.shape[1]), 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return to_db(e_t / np.maximum(rest, 0.0))


#: the per-target uncertainty columns of :class:`Detections` (the targets JSON's optional fields)
UNCERTAINTY_FIELDS = ("sigma_range_m", "sigma_angle_deg", "cov_range_angle")
#: the per-target columns of :class:`Detections` beyond its position, NaN where a decoder gives none
#: (the targets JSON's optional fields, in their order)
OPTIONAL_FIELDS = ("statistic_db", "p_value") + UNCERTAINTY_FIELDS + ("radial_velocity_mps",)


@dataclass(frozen=True)
class Detections:
    """Targets found in a batch of frames; every array is (B, K), strongest first.

    range_m (m), angle_deg (deg, positive = antenna 2 leads), x_m / y_m (m, x along
    boresight), amplitude (joint magnitude / sqrt(2), frame units), bin (range bin),
    statistic_db (detection statistic, dB: the target's joint power over the mean
    noise power per range bin of the back projection; see each decoder), present
    (bool: with ``K auto`` the slots past a frame's count are False and hold NaN);
    sigma_range_m (m), sigma_angle_deg (deg), cov_range_angle (m deg): how sure each target
    is (:mod:`pipeline.dsp.uncertainty`; NaN where the decoder gives none);
    p_value (the chance that noise alone makes the target in the gate: PBP, of its
    ``statistic_db``, :func:`cfar_p_value`; cml, a score test of the frame given the other
    targets, :mod:`pipeline.dsp.significance`);
    radial_velocity_mps (m/s, + = moving away, from the phase step between ramps: known
    modulo the radar's ``velocity_ambiguity_mps`` V and given in [-V/2, V/2); NaN where the
    decoder keeps the static model, as PBP and QIHT do).
    """

    range_m: np.ndarray
    angle_deg: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    amplitude: np.ndarray
    bin: np.ndarray
    statistic_db: np.ndarray | None = None
    present: np.ndarray | None = None
    sigma_range_m: np.ndarray | None = None
    sigma_angle_deg: np.ndarray | None = None
    cov_range_angle: np.ndarray | None = None
    radial_velocity_mps: np.ndarray | None = None
    p_value: np.ndarray | None = None

    def __post_init__(self) -> None:
        shape = np.shape(self.range_m)
        for name in OPTIONAL_FIELDS:
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(shape, np.nan))
        if self.present is None:
            object.__setattr__(self, "present", np.ones(shape, dtype=bool))

    @property
    def count(self) -> np.ndarray:
        """Targets per frame, (B,) int."""
        return self.present.sum(axis=1)

    def masked(self, present: np.ndarray) -> "Detections":
        """The same detections keeping only ``present`` (B, K): the others become NaN
        (bin -1) and not present."""
        present = np.asarray(present, dtype=bool) & self.present
        nan = lambda a: np.where(present, a, np.nan)  # noqa: E731
        return Detections(nan(self.range_m), nan(self.angle_deg), nan(self.x_m), nan(self.y_m),
                          nan(self.amplitude), np.where(present, self.bin, -1), nan(self.statistic_db), present,
                          *(nan(getattr(self, name)) for name in UNCERTAINTY_FIELDS), nan(self.radial_velocity_mps),
                          nan(self.p_value))

    def with_uncertainty(self, sigma_range_m: np.ndarray, sigma_angle_deg: np.ndarray,
                         cov_range_angle: np.ndarray, p_value: np.ndarray | None = None) -> "Detections":
        """These detections with each target's uncertainty (B, K) and, given, p-value (B, K)
        (NaN where absent)."""
        more = {} if p_value is None else {"p_value": np.where(self.present, p_value, np.nan)}
        return replace(self, sigma_range_m=np.where(self.present, sigma_range_m, np.nan),
                       sigma_angle_deg=np.where(self.present, sigma_angle_deg, np.nan),
                       cov_range_angle=np.where(self.present, cov_range_angle, np.nan), **more)

    def frame(self, i: int) -> list[dict[str, float]]:
        """The targets of frame ``i`` that are present, as plain dicts (for JSON)."""
        return [
            {
                "range_m": float(self.range_m[i, j]),
                "angle_deg": float(self.angle_deg[i, j]),
                "x_m": float(self.x_m[i, j]),
                "y_m": float(self.y_m[i, j]),
                "amplitude": float(self.amplitude[i, j]),
                "bin": int(self.bin[i, j]),
                **{name: float(getattr(self, name)[i, j]) for name in OPTIONAL_FIELDS
                   if np.isfinite(getattr(self, name)[i, j])},
            }
            for j in range(self.range_m.shape[1]) if self.present[i, j]
        ]


def detections_from_support(u: np.ndarray, support: np.ndarray, config: RadarConfig,
                            statistic_db: np.ndarray | None = None) -> Detections:
    """Range, angle and position of each support bin of U (B, N, 2); support (B, K)."""
    rows = u[np.arange(u.shape[0])[:, None], support]  # (B, K, 2)
    angle = angle_from_antennas_rad(rows[..., 0], rows[..., 1], config)
    rng_m = config.range_grid_m()[support]
    x, y = polar_to_xy(rng_m, angle)
    amp = np.sqrt(joint_energy(rows) / 2.0)
    return Detections(rng_m, np.rad2deg(angle), x, y, amp, support, statistic_db)


def gated_energy(energy: np.ndarray, mask: np.ndarray | None, k: int,
                 ends_bins: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, int]:
    """The joint energy (B, N) of a back projection seen through a range gate's bin mask
    (N,) bool (None: no gate) whose ends are ``ends_bins`` (:meth:`~pipeline.dsp.gate.RangeGate.bins`):
    (energy to pick a support from, -1 outside the gate and on the skirt of a return outside
    it (:func:`pipeline.dsp.gate.boundary_skirts`: a peak whose maximum lies beyond the gate's
    end is not a target inside); energy for the statistic, 0 outside; bins inside). ``k``
    bins must fit inside.""" 
    n = energy.shape[1]
    if mask is None:
        return energy, energy, n
    cells = int(mask.sum())
    if isinstance(k, (int, np.integer)) and not isinstance(k, bool) and k > cells:
        raise ParameterError(f"K={k} targets do not fit in the range gate's {cells} range bins")
    outside = ~mask
    pick, stat = energy.copy(), energy.copy()
    pick[:, outside] = -1.0  # below any energy: never in the support
    pick[boundary_skirts(energy, mask, ends_bins)] = -1.0
    stat[:, outside] = 0.0
    return pick, stat, cells


def localize(z: np.ndarray, config: RadarConfig, k: int, indices: np.ndarray | None = None,
             pfa: float | None = None, gate: RangeGate | None = None, alpha=None, quantized: bool = True,
             bits: int = 1, reach=None) -> Detections:
    """PBP targets of a batch of frames Z (B, M, 2) (quantized or not), each with its
    cell-averaging statistic (:func:`grid_statistic_db`). ``pfa``: decide the count (at
    most ``k``) by a sequential CFAR test with this false-alarm probability per frame
    and test over the N bins (:func:`cfar_threshold`); None: exactly ``k`` targets.
    ``gate``: search only the range bins inside this :class:`~pipeline.dsp.gate.RangeGate`
    (the statistic and the test then over those bins); None: the whole range axis. With
    ``pfa`` and whole ramps, each target after the first is tested on the residual of the ones
    before it (:func:`pipeline.dsp.residual.residual_support`; ``alpha``: the dither scale of
    ``bits``-bit frames (scalar or (B,)), whose quantizer's products set the floor of that test
    (``reach``: the steps their levels reach, :func:`pipeline.dsp.residual.product_floor_db`);
    None: not known; ``quantized`` False: unquantized frames, whose test's model holds the
    targets' tones alone, not the quantizer's). Each target's ``p_value``:
    :func:`cfar_p_value` of its statistic."""
    mask = None if check_gate(gate) is None else gate.check(config).bin_mask(config)
    u = back_project(z, config, indices)
    energy = joint_energy(u)
    pick, stat, cells = gated_energy(energy, mask, k, None if gate is None else gate.bins(config))
    if pfa is not None and indices is None:  # whole ramps: each test on the residual of the targets before it
        inside = np.ones(u.shape[1], dtype=bool) if mask is None else mask
        support, statistic = residual_support(fold_ramps(z, config), energy, pick, inside, k,
                                              cfar_threshold(pfa, cells), alpha, quantized, bits, reach)
    else:
        support = joint_support(u, k, pick)
        statistic = grid_statistic_db(u, support, stat, cells)
    det = replace(detections_from_support(u, support, config, statistic), p_value=cfar_p_value(statistic, cells))
    if pfa is None:
        return det
    return det.masked(sequential_present(det.statistic_db, 10 * np.log10(cfar_threshold(pfa, cells))))


def localize_frame(z: np.ndarray, config: RadarConfig, k: int, indices: np.ndarray | None = None,
                   gate: RangeGate | None = None) -> list[dict[str, float]]:
    """PBP targets of one frame Z (M, 2), strongest first, as dicts."""
    z = np.asarray(z)
    if z.ndim != 2 or z.shape[-1] != 2:
        raise ParameterError(f"a single frame Z must have shape (M, 2), got {z.shape}")
    idx = None if indices is None else np.asarray(indices)
    return localize(z[None], config, k, idx, gate=gate).frame(0)


def nearest_estimates(
    true_range_m: np.ndarray, true_angle_deg: np.ndarray, est_range_m: np.ndarray, est_angle_deg: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For each true target, the closest estimate in the plane: (error m (B, K),
    position x + i y of that estimate (B, K) complex, m).

    true_* : (B, K); est_* : (B, L); errors are ``min_k |R e^{i theta} - R_hat_k e^{i theta_hat_k}|``;
    NaN estimates (absent targets) are skipped, and a frame without any gives inf.
    """
    t = polar_to_plane(true_range_m, np.deg2rad(true_angle_deg))
    e = polar_to_plane(est_range_m, np.deg2rad(est_angle_deg))
    dist = np.abs(t[:, :, None] - e[:, None, :])  # (B, K, L)
    dist = np.where(np.isnan(dist), np.inf, dist)  # absent estimates (NaN) are never the nearest
    nearest = np.argmin(dist, axis=2)
    pos = np.take_along_axis(np.broadcast_to(e[:, None, :], dist.shape), nearest[:, :, None], axis=2)[..., 0]
    return np.take_along_axis(dist, nearest[:, :, None], axis=2)[..., 0], pos


def match_detections(true_range_m: np.ndarray, est_range_m: np.ndarray, gate_m: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching of detections to true targets by range: each true target in
    turn (strongest first) claims the nearest unclaimed detection within ``gate_m``.

    true_range_m : (B, K); est_range_m : (B, L), NaN for absent. Returns found (B, K)
    bool and false targets (B,) int (present detections left unclaimed)."""
    est = np.array(est_range_m, dtype=float)
    present = ~np.isnan(est)
    found = np.zeros(true_range_m.shape, dtype=bool)
    for t in range(true_range_m.shape[1]):  # K true targets, not frames
        dist = np.abs(est - true_range_m[:, t, None])
        dist[np.isnan(dist)] = np.inf
        j = np.argmin(dist, axis=1)
        hit = np.take_along_axis(dist, j[:, None], axis=1)[:, 0] <= gate_m
        found[:, t] = hit
        est[np.flatnonzero(hit), j[hit]] = np.nan  # claimed
    return found, present.sum(axis=1) - found.sum(axis=1)


def position_error_m(
    true_range_m: np.ndarray, true_angle_deg: np.ndarray, est_range_m: np.ndarray, est_angle_deg: np.ndarray
) -> np.ndarray:
    """Error of each true target: ``min_k |R e^{i theta} - R_hat_k e^{i theta_hat_k}|``, m.

    true_* : (B, K); est_* : (B, L). Returns (B, K). Other shapes: a ParameterError naming them.
    """
    shapes = [np.shape(a) for a in (true_range_m, true_angle_deg, est_range_m, est_angle_deg)]
    if any(len(s) != 2 for s in shapes) or shapes[0] != shapes[1] or shapes[2] != shapes[3] \
            or shapes[0][0] != shapes[2][0]:
        raise ParameterError(f"position_error_m takes true ranges and angles (B, K) and estimates (B, L) of the "
                             f"same B; got {', '.join(map(str, shapes))}")
    return nearest_estimates(true_range_m, true_angle_deg, est_range_m, est_angle_deg)[0]
