"""Tracks: targets that persist, move, and get sharper with time (issue 25).

Per sensor, in the sensor's plane (``x_m`` along boresight, ``y_m`` across it:
:func:`radar_driver.model.polar_to_xy`), a global-nearest-neighbour tracker:

* **State**: a constant-velocity Kalman filter per track, ``(x, y, vx, vy)`` (m, m/s) and
  its 4 x 4 covariance; process noise a white acceleration of std ``accel_mps2`` (m/s^2)
  on each axis (the discretized Wiener-process acceleration model).
* **Measurements**: each frame's targets, ``(range_m, angle_deg)`` -> ``(x, y)`` with the
  polar noise carried to the plane by the Jacobian. The noise of a target follows its
  detection statistic (``statistic_db``, its power over the noise's per range bin, a
  signal-to-noise ratio S): ``sigma_theta = snr_angle_rad / (cos(theta) sqrt(S))`` (the
  phase between the antennas; d = lambda / 2) and ``sigma_R = snr_range_m / sqrt(S)``, the
  constants measured on the shipped scenes with the default decoder (1 bit, cml: README),
  never below ``min_range_sigma_m`` / ``min_angle_sigma_deg``; a target without a
  statistic gets ``range_sigma_m`` and ``angle_sigma_deg``.
* **Gating and assignment**: the squared Mahalanobis distance of every (track, target)
  pair under the innovation covariance ``S = H P H^T + R``; pairs beyond ``gate_chi2``
  (chi-square, 2 degrees of freedom; 13.8 = 99.9 %) are forbidden, and the rest solved as
  one assignment (Hungarian, ``scipy.optimize.linear_sum_assignment``) on the cost
  ``d^2 + ln det S`` (the negative log-likelihood of the pair, as GNN trackers use).
* **Timestamps**: a frame's timestamp is the host's clock when it arrived (a K-MD2's
  frames carry none), late by however long a busy host took, and the frames after a stall
  come bunched. A target stamped ``e`` late is where the track was ``e`` before the stamp:
  ``v e`` behind its prediction. So each (track, target) pair's measurement noise adds
  ``timestamp_sigma_s^2 (v v^T + P_vv)`` (the track's predicted velocity and its
  covariance): a moving track keeps its targets through the host's delays, and the range's
  precision along the motion is what the clock allows (a static track's is untouched).
* **Births and deaths**: a target no track takes starts a *tentative* track; it is
  *confirmed* after ``confirm_hits`` hits and dies at its ``tentative_misses``-th miss
  before that. A confirmed track dies when it has not been seen for ``max_coast_s``.
  At most ``max_tracks`` tracks a sensor (new targets beyond are not tracked).
* **Static**: a confirmed track is static while its velocity is consistent with zero:
  ``v^T P_vv^{-1} v`` below ``static_chi2`` (chi-square, 2 dof; 9.21 = 99 %) to become
  static, above ``moving_chi2`` (13.8 = 99.9 %) to stop being static (a hysteresis, so
  that the 1 % of frames of a static reflector whose estimate strays do not end it).

* **Doppler** (decoders that measure it, ``cml``): a target's ``radial_velocity_mps`` is its
  radial velocity modulo the radar's ambiguity interval V (0.249 m/s for 25 ms between
  ramps). A track unwraps its targets' Doppler from frame to frame (a change under V/2 a
  frame: 2.5 m/s^2 at 20 Hz) and integrates it to the displacement D(t); its measured
  ranges then follow ``R(t) - D(t) = R0 + n V t``, and a weighted straight-line fit over
  the last ``doppler_window_s`` (forgotten exponentially) tells the whole number n: the
  ambiguity, resolved over frames once the slope is known to ``V / 8`` (its residual
  scatter counted) and lies within a quarter of V of a whole n. From then on the unwrapped
  Doppler plus n V is a measurement of the filter's radial velocity (an extended Kalman
  update, noise ``doppler_sigma_mps``; one whose innovation is beyond 99.9 % is left out),
  so the track's velocity and the frames' Doppler agree, and the track reports it. A gap
  without Doppler longer than ``doppler_gap_s`` starts the track's Doppler history afresh.

Only confirmed tracks are reported. The math is pure functions on arrays with the
track axis first, and :class:`SensorTracks` one sensor's state;
:class:`pipeline.nodes.tracker.Tracker` holds the sensors' states (bounded, forgotten with
:meth:`~pipeline.nodes.tracker.Tracker.forget`) and the integration of static tracks (the
codes of their last frames decoded together, :mod:`pipeline.dsp.integrate`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from radar_driver.model import fold, polar_to_xy

from pipeline.errors import ParameterError

#: chi-square quantiles, 2 degrees of freedom
CHI2_2DOF_99 = 9.2103
CHI2_2DOF_999 = 13.8155
#: the cost of a forbidden (gated out) pair in the assignment
_FORBIDDEN = 1e12

#: H: the filter's measurement is its position
_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
#: chi-square quantile, 1 degree of freedom, 99.9 %: the gate of a Doppler update
CHI2_1DOF_999 = 10.8276
#: the Doppler's ambiguity is resolved when the fit's slope is known to V / RESOLVE_SIGMAS ...
RESOLVE_SIGMAS = 8.0
#: ... lies within this fraction of V of a whole number of V ...
RESOLVE_FRACTION = 0.25
#: ... on at least this many frames
RESOLVE_FRAMES = 10


@dataclass(frozen=True)
class TrackerConfig:
    """The tracker's parameters (see the module docstring).

    accel_mps2 : std of the white acceleration of the motion model, m/s^2 (each axis).
    range_sigma_m, angle_sigma_deg : measurement noise of a target's range (m) and angle
        (deg) when it has no detection statistic.
    snr_range_m, snr_angle_rad : the noise of a target of statistic S (linear):
        ``snr_range_m / sqrt(S)`` m, ``snr_angle_rad / (cos(theta) sqrt(S))`` rad.
    min_range_sigma_m, min_angle_sigma_deg : floors of those.
    gate_chi2 : gate on the squared Mahalanobis distance (2 dof).
    confirm_hits : hits that confirm a tentative track.
    tentative_misses : misses that end a tentative track.
    max_coast_s : a confirmed track not seen for this long dies, s.
    static_chi2, moving_chi2 : the static test's thresholds, to enter and to leave (2 dof).
    static_min_hits : hits a track needs before it can be static.
    init_speed_mps : std of the velocity of a new track, m/s (each axis).
    max_tracks : tracks a sensor holds at most.
    max_gap_s : a frame this much later than the sensor's last, or earlier, starts its
        tracks afresh (a restarted sensor), s; a frame earlier by less (one that came late)
        is left out.
    integrate_s : static tracks are refined on the codes of this many seconds of frames
        together (0: no integration; :mod:`pipeline.dsp.integrate`).
    doppler_sigma_mps : noise of a track's resolved Doppler (its radial velocity), m/s.
    doppler_window_s : memory of the fit that resolves the Doppler's ambiguity, s.
    doppler_gap_s : a track without Doppler for longer starts its Doppler history afresh, s.
    timestamp_sigma_s : std of a frame's timestamp error (the host's clock when the frame
        arrived: its delays on a busy host), s; a moving track's measurement noise along its
        velocity (module docstring).
    """

    accel_mps2: float = 1.0
    range_sigma_m: float = 0.05
    angle_sigma_deg: float = 2.0
    snr_range_m: float = 0.06
    snr_angle_rad: float = 0.13
    min_range_sigma_m: float = 0.002
    min_angle_sigma_deg: float = 0.1
    gate_chi2: float = CHI2_2DOF_999
    confirm_hits: int = 3
    tentative_misses: int = 2
    max_coast_s: float = 1.5
    static_chi2: float = CHI2_2DOF_99
    moving_chi2: float = CHI2_2DOF_999
    static_min_hits: int = 5
    init_speed_mps: float = 3.0
    max_tracks: int = 16
    max_gap_s: float = 5.0
    integrate_s: float = 1.0
    doppler_sigma_mps: float = 0.02
    doppler_window_s: float = 5.0
    doppler_gap_s: float = 0.25
    timestamp_sigma_s: float = 0.05

    def __post_init__(self) -> None:
        for name in ("accel_mps2", "range_sigma_m", "angle_sigma_deg", "snr_range_m", "snr_angle_rad",
                     "min_range_sigma_m", "min_angle_sigma_deg", "gate_chi2", "max_coast_s", "static_chi2",
                     "moving_chi2", "init_speed_mps", "max_gap_s", "doppler_sigma_mps", "doppler_window_s",
                     "doppler_gap_s", "timestamp_sigma_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (np.isfinite(v) and v > 0):
                raise ParameterError(f"tracker: {name}={v!r} must be a finite number > 0")
        for name in ("confirm_hits", "tentative_misses", "static_min_hits", "max_tracks"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ParameterError(f"tracker: {name}={v!r} must be an integer >= 1")
        if self.moving_chi2 < self.static_chi2:
            raise ParameterError(f"tracker: moving_chi2={self.moving_chi2!r} must be >= static_chi2="
                                 f"{self.static_chi2!r} (the static test's hysteresis)")
        v = self.integrate_s
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (np.isfinite(v) and 0 <= v <= 60):
            raise ParameterError(f"tracker: integrate_s={v!r} must be a number of seconds in [0, 60]")


# -- the math: pure functions, track axis first -------------------------------------------------
@lru_cache(maxsize=64)
def cv_model(dt_s: float, accel_mps2: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition F (4, 4) and process noise Q (4, 4) of the constant-velocity model over
    ``dt_s`` seconds, for a white acceleration of std ``accel_mps2`` (m/s^2) on each axis;
    state ``(x, y, vx, vy)``. Read-only (cached: a sensor's frame period repeats)."""
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt_s
    q1 = accel_mps2 ** 2 * np.array([[dt_s ** 4 / 4, dt_s ** 3 / 2], [dt_s ** 3 / 2, dt_s ** 2]])
    q = np.zeros((4, 4))
    q[np.ix_([0, 2], [0, 2])] = q1
    q[np.ix_([1, 3], [1, 3])] = q1
    f.flags.writeable = q.flags.writeable = False
    return f, q


def predict(x: np.ndarray, p: np.ndarray, dt_s: float, accel_mps2: float) -> tuple[np.ndarray, np.ndarray]:
    """Kalman prediction of T tracks: x (T, 4), p (T, 4, 4) -> the same, ``dt_s`` s later."""
    f, q = cv_model(dt_s, accel_mps2)
    return x @ f.T, f @ p @ f.T + q


def measurement_sigmas(statistic_db: np.ndarray | None, angle_deg: np.ndarray,
                       cfg: TrackerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Range (m) and angle (deg) noise (K,) of targets of detection statistic ``statistic_db``
    (K,) (dB; None or NaN: the configured constants), see the module docstring."""
    a = np.asarray(angle_deg, dtype=float)
    if statistic_db is None:
        return np.full(a.shape, cfg.range_sigma_m), np.full(a.shape, cfg.angle_sigma_deg)
    stat = np.asarray(statistic_db, dtype=float)
    known = np.isfinite(stat)
    root = 10.0 ** (np.where(known, stat, 0.0) / 20.0)  # sqrt(S) = 10^(dB / 20)
    cos = np.maximum(np.cos(np.deg2rad(a)), 0.1)
    sr = np.where(known, np.maximum(cfg.snr_range_m / root, cfg.min_range_sigma_m), cfg.range_sigma_m)
    sa = np.where(known, np.maximum(np.rad2deg(cfg.snr_angle_rad / (cos * root)), cfg.min_angle_sigma_deg),
                  cfg.angle_sigma_deg)
    return sr, sa


def measurements(range_m: np.ndarray, angle_deg: np.ndarray, range_sigma_m,
                 angle_sigma_deg) -> tuple[np.ndarray, np.ndarray]:
    """Targets (K,) -> positions z (K, 2) (x_m, y_m) and their covariances r (K, 2, 2), m^2:
    ``J diag(sigma_r^2, sigma_theta^2) J^T`` with J the Jacobian of the polar -> plane map;
    the sigmas (m, deg) scalars or (K,)."""
    rng = np.asarray(range_m, dtype=float)
    th = np.deg2rad(np.asarray(angle_deg, dtype=float))
    x, y = polar_to_xy(rng, th)
    c, s = np.cos(th), np.sin(th)
    vr, va = range_sigma_m ** 2, (np.deg2rad(angle_sigma_deg) * rng) ** 2
    r = np.empty(rng.shape + (2, 2))
    r[..., 0, 0] = vr * c * c + va * s * s
    r[..., 1, 1] = vr * s * s + va * c * c
    r[..., 0, 1] = r[..., 1, 0] = (vr - va) * c * s
    z = np.empty(rng.shape + (2,))
    z[..., 0], z[..., 1] = x, y
    return z, r


def innovations(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray,
                track_r: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Squared Mahalanobis distance d2 (T, K) of every (track, target) pair, and the
    pair's ``ln det S`` (T, K), S = H P H^T + R (m^2); ``track_r`` (T, 2, 2): measurement
    noise of each track's own added to every target's R (:func:`timing_noise`)."""
    hp = p[:, :2, :2] if track_r is None else p[:, :2, :2] + track_r
    s = hp[:, None] + r[None]  # (T, K, 2, 2)
    nu = z[None] - x[:, None, :2]  # (T, K, 2)
    det = s[..., 0, 0] * s[..., 1, 1] - s[..., 0, 1] * s[..., 1, 0]
    # nu^T S^-1 nu of a 2 x 2 S, written out
    d2 = (s[..., 1, 1] * nu[..., 0] ** 2 - 2 * s[..., 0, 1] * nu[..., 0] * nu[..., 1]
          + s[..., 0, 0] * nu[..., 1] ** 2) / det
    return d2, np.log(det)


@lru_cache(maxsize=1)
def assignment_solver():
    """scipy's Hungarian solver, imported on first use (every command imports this module;
    a :class:`Tracker` imports it when made, so that no frame waits the ~0.3 s)."""
    from scipy.optimize import linear_sum_assignment

    return linear_sum_assignment


def assign(d2: np.ndarray, logdet: np.ndarray, gate_chi2: float) -> tuple[np.ndarray, np.ndarray]:
    """Global nearest-neighbour assignment: (track rows, target columns) of the pairs that
    minimize the summed cost ``d2 + ln det S`` with no pair beyond the gate, each track and
    target in one pair at most."""
    if d2.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    ok = d2 <= gate_chi2
    cost = np.where(ok, d2 + logdet, _FORBIDDEN)
    rows, cols = assignment_solver()(cost)
    keep = ok[rows, cols]
    return rows[keep], cols[keep]


def timing_noise(x: np.ndarray, p: np.ndarray, timestamp_sigma_s: float) -> np.ndarray:
    """The position noise (T, 2, 2) (m^2) of a measurement whose timestamp is off by a
    random error of std ``timestamp_sigma_s`` (s), for tracks x (T, 4), p (T, 4, 4) at that
    timestamp: the target is where the track was ``e`` earlier, ``v e`` from its prediction,
    so ``sigma^2 E[v v^T] = sigma^2 (v v^T + P_vv)``."""
    v = x[:, 2:]
    return timestamp_sigma_s ** 2 * (v[:, :, None] * v[:, None, :] + p[:, 2:, 2:])


def update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update of T tracks by their measurements: x (T, 4), p (T, 4, 4), z (T, 2),
    r (T, 2, 2) -> x, p (Joseph form, symmetric)."""
    gain = p[:, :, :2] @ _inv2(p[:, :2, :2] + r)  # P H^T S^-1: (T, 4, 2)
    x = x + np.einsum("tij,tj->ti", gain, z - x[:, :2])
    ikh = np.eye(4) - gain @ _H
    p = ikh @ p @ ikh.transpose(0, 2, 1) + gain @ r @ gain.transpose(0, 2, 1)
    return x, 0.5 * (p + p.transpose(0, 2, 1))


def velocity_chi2(x: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``v^T P_vv^{-1} v`` (T,): the chi-square (2 dof) of the hypothesis "the track does not move"."""
    v = x[:, 2:]
    return np.einsum("ti,tij,tj->t", v, _inv2(p[:, 2:, 2:]), v)


def radial_velocity(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The radial velocity h (T,) (m/s, + = away) of states x (T, 4) and its Jacobian
    (T, 4): ``h = (x vx + y vy) / R``."""
    rho = np.maximum(np.hypot(x[:, 0], x[:, 1]), 1e-9)
    ux, uy = x[:, 0] / rho, x[:, 1] / rho
    h = ux * x[:, 2] + uy * x[:, 3]
    jac = np.stack([(x[:, 2] - ux * h) / rho, (x[:, 3] - uy * h) / rho, ux, uy], axis=1)
    return h, jac


def update_radial_velocity(x: np.ndarray, p: np.ndarray, v: np.ndarray, sigma_mps: float,
                           gate_chi2: float = CHI2_1DOF_999) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extended Kalman update of T tracks by measured radial velocities v (T,) (m/s) of
    std ``sigma_mps``: x (T, 4), p (T, 4, 4) -> x, p, and the mask (T,) of the updates made
    (an innovation beyond ``gate_chi2``, 1 dof, is left out)."""
    h, jac = radial_velocity(x)
    ph = (p @ jac[:, :, None])[:, :, 0]  # P H^T (T, 4)
    s = (jac * ph).sum(axis=1) + sigma_mps ** 2
    nu = v - h
    ok = nu * nu / s <= gate_chi2
    gain = np.where(ok[:, None], ph / s[:, None], 0.0)  # K (T, 4)
    x = x + gain * nu[:, None]
    p = p - gain[:, :, None] * ph[:, None, :]  # P - K S K^T = P - K (P H^T)^T: a scalar measurement
    return x, 0.5 * (p + p.transpose(0, 2, 1)), ok


def doppler_fit(sums: np.ndarray, ambiguity_mps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The straight-line fit of ``R - D = R0 + n V t`` from its weighted sums (T, 7) (W, Wt,
    Wtt, Wy, Wty, Wyy, N: weights 1/sigma_R^2, t in s, y = R - D in m, N the decayed count):
    the slope in units of V (T,), its std in those units (scaled up by the residual scatter
    when it exceeds the ranges' sigmas), and the nearest whole n (T,)."""
    w, wt, wtt, wy, wty, wyy, n = sums.T
    with np.errstate(divide="ignore", invalid="ignore"):
        den = w * wtt - wt * wt
        slope = (w * wty - wt * wy) / den
        icpt = (wy - slope * wt) / w
        chi2 = np.maximum(wyy - 2 * icpt * wy - 2 * slope * wty + icpt * icpt * w + 2 * icpt * slope * wt
                          + slope * slope * wtt, 0.0)
        scale = np.maximum(1.0, chi2 / np.maximum(n - 2.0, 1.0))
        sd = np.sqrt(w / den * scale)
    return slope / ambiguity_mps, sd / ambiguity_mps, np.round(slope / ambiguity_mps)


def _inv2(a: np.ndarray) -> np.ndarray:
    """Inverses of 2 x 2 matrices (..., 2, 2), written out."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    out = np.empty(a.shape)
    out[..., 0, 0] = a[..., 1, 1] / det
    out[..., 1, 1] = a[..., 0, 0] / det
    out[..., 0, 1] = -a[..., 0, 1] / det
    out[..., 1, 0] = -a[..., 1, 0] / det
    return out


def new_tracks(z: np.ndarray, r: np.ndarray, init_speed_mps: float) -> tuple[np.ndarray, np.ndarray]:
    """Initial states (K, 4) and covariances (K, 4, 4) of tracks born at positions z (K, 2)
    of covariance r (K, 2, 2): at rest, velocity std ``init_speed_mps`` a axis."""
    k = z.shape[0]
    x = np.zeros((k, 4))
    x[:, :2] = z
    p = np.zeros((k, 4, 4))
    p[:, :2, :2] = r
    p[:, 2, 2] = p[:, 3, 3] = init_speed_mps ** 2
    return x, p


# -- the state ------------------------------------------------------------------------------------
@dataclass
class SensorTracks:
    """The tracks of one sensor, arrays with the track axis first (T tracks)."""

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    x: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    p: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    hits: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    misses: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # in a row
    born_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    seen_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    confirmed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: when the track became static (ns), -1 while it moves
    static_since_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: the integrated position (x_m, y_m) of a static track, NaN when there is none
    refined: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    #: Doppler history (module docstring): the last unwrapped Doppler (m/s, NaN: none), when
    #: (ns), since when (ns), its integral D (m), the fit's decayed sums (T, 7), frames in it,
    #: the resolved whole number of V (NaN: unresolved)
    dop_u: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dop_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    dop_t0_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    dop_d: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dop_sums: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    dop_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    dop_n: np.ndarray = field(default_factory=lambda: np.zeros(0))
    last_ns: int | None = None
    next_id: int = 1
    #: the Doppler's ambiguity interval V of the sensor's radar, m/s (NaN: no Doppler seen)
    ambiguity_mps: float = float("nan")
    #: Doppler updates left out (innovation beyond the gate), and resolutions that changed n
    doppler_rejected: int = 0
    doppler_changed: int = 0

    PER_TRACK = ("ids", "x", "p", "hits", "misses", "born_ns", "seen_ns", "confirmed", "static_since_ns", "refined",
                 "dop_u", "dop_ns", "dop_t0_ns", "dop_d", "dop_sums", "dop_frames", "dop_n")

    def keep(self, mask: np.ndarray) -> None:
        for name in self.PER_TRACK:
            setattr(self, name, getattr(self, name)[mask])

    def append(self, x: np.ndarray, p: np.ndarray, now_ns: int) -> None:
        k = x.shape[0]
        ids = np.arange(self.next_id, self.next_id + k, dtype=np.int64)
        self.next_id += k
        add = {"ids": ids, "x": x, "p": p, "hits": np.ones(k, dtype=np.int64), "misses": np.zeros(k, dtype=np.int64),
               "born_ns": np.full(k, now_ns, dtype=np.int64), "seen_ns": np.full(k, now_ns, dtype=np.int64),
               "confirmed": np.zeros(k, dtype=bool), "static_since_ns": np.full(k, -1, dtype=np.int64),
               "refined": np.full((k, 2), np.nan), "dop_u": np.full(k, np.nan),
               "dop_ns": np.zeros(k, dtype=np.int64), "dop_t0_ns": np.zeros(k, dtype=np.int64),
               "dop_d": np.zeros(k), "dop_sums": np.zeros((k, 7)), "dop_frames": np.zeros(k, dtype=np.int64),
               "dop_n": np.full(k, np.nan)}
        for name in self.PER_TRACK:
            setattr(self, name, np.concatenate([getattr(self, name), add[name]]))

    @property
    def static(self) -> np.ndarray:
        return self.static_since_ns >= 0

    @property
    def doppler_mps(self) -> np.ndarray:
        """Each track's radial velocity from its Doppler, ambiguity resolved (m/s, + = away;
        NaN while unresolved or without Doppler), (T,)."""
        return self.dop_u + self.dop_n * self.ambiguity_mps


def step_tracks(st: SensorTracks, cfg: TrackerConfig, now_ns: int, range_m: np.ndarray, angle_deg: np.ndarray,
                statistic_db: np.ndarray | None = None, radial_velocity_mps: np.ndarray | None = None,
                ambiguity_mps: float | None = None) -> None:
    """One frame of one sensor: predict to ``now_ns``, gate and assign its targets (K,)
    (``statistic_db`` (K,): their detection statistics, for their noise), update, confirm,
    end and start tracks, and test each for being static. ``radial_velocity_mps`` (K,): the
    targets' Doppler, known modulo ``ambiguity_mps`` (the radar's V; NaN or None: none), for
    the tracks' velocity (module docstring). In place."""
    if late(st, cfg, now_ns):
        return  # a frame that came late: the tracks have moved past it
    if st.last_ns is not None and not 0 <= now_ns - st.last_ns <= cfg.max_gap_s * 1e9:
        st.keep(np.zeros(len(st.ids), dtype=bool))  # time went far back (a restart) or a long gap: afresh
    dt = 0.0 if st.last_ns is None else (now_ns - st.last_ns) / 1e9
    st.last_ns = now_ns
    if len(st.ids) and dt > 0:
        st.x, st.p = predict(st.x, st.p, dt, cfg.accel_mps2)
    ok = np.isfinite(range_m) & np.isfinite(angle_deg)
    angle = np.asarray(angle_deg, float)[ok]
    sr, sa = measurement_sigmas(None if statistic_db is None else np.asarray(statistic_db, float)[ok], angle, cfg)
    z, r = measurements(np.asarray(range_m, float)[ok], angle, sr, sa)
    rt = timing_noise(st.x, st.p, cfg.timestamp_sigma_s)  # the host clock's delays, per track
    d2, logdet = innovations(st.x, st.p, z, r, rt)
    # confirmed tracks choose first: a tentative track never takes a confirmed one's target
    rows, cols = _assign_confirmed_first(d2, logdet, st.confirmed, cfg.gate_chi2)
    hit = np.zeros(len(st.ids), dtype=bool)
    hit[rows] = True
    if rows.size:
        st.x[rows], st.p[rows] = update(st.x[rows], st.p[rows], z[cols], r[cols] + rt[rows])
        if radial_velocity_mps is not None and ambiguity_mps is not None and ambiguity_mps > 0:
            dop = np.asarray(radial_velocity_mps, float)[ok][cols]
            has = np.isfinite(dop)
            if has.any():
                doppler_step(st, cfg, now_ns, rows[has], np.asarray(range_m, float)[ok][cols][has], sr[cols][has],
                             dop[has], float(ambiguity_mps))
    st.hits[hit] += 1
    st.misses[hit] = 0
    st.misses[~hit] += 1
    st.seen_ns[hit] = now_ns
    st.confirmed |= st.hits >= cfg.confirm_hits
    alive = np.where(st.confirmed, now_ns - st.seen_ns <= cfg.max_coast_s * 1e9, st.misses < cfg.tentative_misses)
    # static test, with its hysteresis
    chi2 = velocity_chi2(st.x, st.p) if len(st.ids) else np.zeros(0)
    static = np.where(st.static, chi2 <= cfg.moving_chi2, chi2 <= cfg.static_chi2)
    static &= st.confirmed & (st.hits >= cfg.static_min_hits)
    st.static_since_ns = np.where(static, np.where(st.static, st.static_since_ns, now_ns), -1)
    st.refined[~static] = np.nan
    if not alive.all():
        st.keep(alive)
    free = np.ones(z.shape[0], dtype=bool)
    free[cols] = False
    room = cfg.max_tracks - len(st.ids)
    born = np.flatnonzero(free)[:max(room, 0)]
    if born.size:
        st.append(*new_tracks(z[born], r[born], cfg.init_speed_mps), now_ns)


def doppler_step(st: SensorTracks, cfg: TrackerConfig, now_ns: int, rows: np.ndarray, range_m: np.ndarray,
                 range_sigma_m: np.ndarray, doppler_mps: np.ndarray, ambiguity_mps: float) -> None:
    """The Doppler of the targets (J,) that tracks ``rows`` (J,) took this frame, of ranges
    ``range_m`` (m) and range noise ``range_sigma_m`` (m): unwrapped onto each track's history,
    integrated, the ambiguity's fit updated and, where it is resolved, the filter updated
    by the radial velocity (module docstring). In place."""
    v = ambiguity_mps
    if st.ambiguity_mps != v:  # another radar (or the first Doppler): every history afresh
        st.dop_u[:] = np.nan
        st.ambiguity_mps = v
    dt = (now_ns - st.dop_ns[rows]) / 1e9
    fresh = ~np.isfinite(st.dop_u[rows]) | (dt > cfg.doppler_gap_s) | (dt < 0)
    dt = np.where(fresh, 0.0, dt)
    prev = np.where(fresh, doppler_mps, st.dop_u[rows])
    u = prev + fold(doppler_mps - prev, v)  # the alias nearest the last: continuity
    d = np.where(fresh, 0.0, st.dop_d[rows] + 0.5 * (prev + u) * dt)
    t0 = np.where(fresh, now_ns, st.dop_t0_ns[rows])
    t = (now_ns - t0) / 1e9
    y = range_m - d
    w = 1.0 / range_sigma_m ** 2
    keep = np.where(fresh, 0.0, np.exp(-dt / cfg.doppler_window_s))
    sums = st.dop_sums[rows] * keep[:, None] + np.stack([w, w * t, w * t * t, w * y, w * t * y, w * y * y,
                                                         np.ones_like(w)], axis=1)
    frames = np.where(fresh, 1, st.dop_frames[rows] + 1)
    slope, sd, whole = doppler_fit(sums, v)
    sure = (frames >= RESOLVE_FRAMES) & (sd <= 1.0 / RESOLVE_SIGMAS) & (np.abs(slope - whole) <= RESOLVE_FRACTION)
    was = np.where(fresh, np.nan, st.dop_n[rows])
    n = np.where(sure, whole, was)
    st.doppler_changed += int(np.sum(sure & np.isfinite(was) & (whole != was)))
    st.dop_u[rows], st.dop_ns[rows], st.dop_t0_ns[rows], st.dop_d[rows] = u, now_ns, t0, d
    st.dop_sums[rows], st.dop_frames[rows], st.dop_n[rows] = sums, frames, n
    known = np.isfinite(n)
    if known.any():
        upd = rows[known]
        st.x[upd], st.p[upd], made = update_radial_velocity(st.x[upd], st.p[upd], u[known] + n[known] * v,
                                                            cfg.doppler_sigma_mps)
        st.doppler_rejected += int(np.sum(~made))


def late(st: SensorTracks, cfg: TrackerConfig, now_ns: int) -> bool:
    """True for a frame earlier than the sensor's last by less than ``max_gap_s`` (reordered)."""
    return st.last_ns is not None and 0 < st.last_ns - now_ns <= cfg.max_gap_s * 1e9


def _assign_confirmed_first(d2, logdet, confirmed, gate_chi2):
    """:func:`assign` for the confirmed tracks, then for the tentative ones on the targets left."""
    if confirmed.all() or not confirmed.any():
        return assign(d2, logdet, gate_chi2)
    conf = np.flatnonzero(confirmed)
    rows_c, cols_c = assign(d2[conf], logdet[conf], gate_chi2)
    rows_c = conf[rows_c]
    left = np.ones(d2.shape[1], dtype=bool)
    left[cols_c] = False
    left = np.flatnonzero(left)
    tent = np.flatnonzero(~confirmed)
    rows_t, cols_t = assign(d2[tent][:, left], logdet[tent][:, left], gate_chi2)
    return np.concatenate([rows_c, tent[rows_t]]), np.concatenate([cols_c, left[cols_t]])


def report(st: SensorTracks, now_ns: int) -> list[dict]:
    """The confirmed tracks as the tracks message lists them (docs/wire-formats.md):
    position (the integrated one while static and integrated), velocity, ``sigma_m`` (the
    filter's position std, RMS of the two axes), age, hits, static, and the radial velocity
    of the Doppler with its ambiguity resolved (left out while unresolved)."""
    out = []
    doppler = st.doppler_mps
    for i in np.flatnonzero(st.confirmed).tolist():
        xy = st.refined[i] if np.isfinite(st.refined[i]).all() else st.x[i, :2]
        x, y = float(xy[0]), float(xy[1])
        out.append({"track_id": int(st.ids[i]), "range_m": float(np.hypot(x, y)),
                    "angle_deg": float(np.rad2deg(np.arctan2(y, x))), "x_m": x, "y_m": y,
                    "vx_mps": float(st.x[i, 2]), "vy_mps": float(st.x[i, 3]),
                    "sigma_m": float(np.sqrt(0.5 * (st.p[i, 0, 0] + st.p[i, 1, 1]))),
                    "age_s": (now_ns - int(st.born_ns[i])) / 1e9, "hits": int(st.hits[i]),
                    "static": bool(st.static_since_ns[i] >= 0)})
        if np.isfinite(doppler[i]):
            out[-1]["radial_velocity_mps"] = float(doppler[i])
    return out
