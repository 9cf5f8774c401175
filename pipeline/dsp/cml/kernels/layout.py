"""The arguments of cml's kernels, grouped, and the kernels' compile options.

A kernel takes a few namedtuples of arrays and numbers rather than tens of positional
arguments (numba passes a namedtuple as the struct of its fields: measured, a call with a
namedtuple of 12 arrays costs 1.6 us against 0.6 us for 12 arrays, and a cached kernel
taking one loads from the cache as one taking arrays does). Every array a kernel receives
is C-contiguous, aligned and writeable (:func:`pipeline.dsp.cml.likelihood.array`), so a
kernel has one compiled signature per dtype and number of dimensions, whatever its
caller's arrays.

Layouts (one block of B frames, R ramps of N samples, T targets found so far; the 4 real
parts of a sample are ``2 p + c``, antenna p, c = 0 real, 1 imaginary; Rm the ramps of the
model: R when each target has a phase step between ramps (its radial velocity), 1 for the
static model, every ramp the same):

* :data:`Codes`: ``kind`` (:data:`~pipeline.dsp.cml.kernels.likelihood.LSQ`, ``ONE_BIT``,
  ``MULTI_BIT``), ``lik`` (``LOGISTIC``, ``GAUSSIAN``), ``a``, ``b`` (B, R, N, 4) the
  codes' arrays (least squares: ``y``; 1 bit: the sign s and ``s xi``; b bits: the cell
  ``[lo, hi)`` of lambda), ``data`` (B, Rm, N, 4) ``Z - xi`` of each ramp (Rm = 1: summed
  over the ramps);
* :data:`Fit`: ``nu`` (B, T) ranges in bins, ``phi`` (B, T) phase steps between ramps
  (rad; 0 in the static model), ``amp`` (B, T, 2) complex amplitudes referred to mid-sweep
  and to the middle of the frame (ramp r's: ``amp exp(i (r - (R - 1) / 2) phi)``), ``live``
  (B, T) bool, ``lm`` (B,) damping, ``nll`` (B,) the negative log-likelihood at ``sigma``
  (B,) (NaN: no level evaluated yet), ``mu``, ``g``, ``h`` (B, Rm, N, 4) the model on each
  ramp and the NLL's first and second derivatives in each real part (Rm = 1: summed over
  the ramps);
* :data:`Steps`: one call's refinement levels ``levels`` (B, S) (noise std of each step),
  ``adapt`` (not below the wrong codes' RMS distance over ``wrong_per_sigma``), ``amp_cap``
  (B,) the largest amplitude change of a step, ``max_range_step`` (bins), ``max_phase_step``
  (rad);
* :data:`Gate`: the range gate on the detection grid: ``use``, its ends ``lo``, ``hi``
  (bins), ``outside`` (L,) the grid points beyond it, ``edges`` (Lc,) the coarse points
  within a coarse step of one of those;
* :data:`Grid`: the detection grid of ``oversample`` points a bin (L = oversample N), the
  guards (bins) of the count test and of detection, and the coarse grid's constants
  (:mod:`pipeline.dsp.cml.kernels.search`): ``rho``, ``table`` (L,) the fine grid's
  twiddles, ``tables`` the run tables, the gate's ``weights`` (Lc + 1,) and ``inside``;
* :data:`Sources`: a greedy stage's back projections: ``u`` (B, S, Rm, 2, L or Lc) the
  zero-padded inverse FFTs of S residuals (0: the linear residual ``Z - xi - model``, 1:
  the likelihood's score) per ramp of the model and antenna, ``src`` (B, S, Rm, 2, >= N)
  the same before the FFT, ``y`` (B, Rm, N, 2) the linear residual (Rm = 1: summed over
  ``ramps`` ramps), how many the count test reads (``count_sources``) and which one
  detection reads (``detect_source``; -1: none);
* :data:`Decision`: the count test's ``threshold`` (linear; < 0: none) and ``active`` (B,)
  bool, updated in place, the outputs ``stat`` (B,), ``nu0`` (B,) bins, ``amp0`` (B, 2),
  ``floor`` (B, 2) the least mean energy the test takes each residual (linear, score) to have
  (:func:`pipeline.dsp.cml.detect.count_floor`; 0: none), and ``phi0`` (B,) rad;
* :data:`Report`: what a result needs of the radar and the gate: ``range_res`` (m a bin),
  ``carrier`` (4 pi f0 / c, rad/m), the range gate ``use``, ``lo``, ``hi`` (bins; a target is
  reported when its range, modulo N, lies inside), ``cap`` (the statistic's cap, dB);
* :data:`Targets`: a result's arrays ``range_m`` (B, K), ``amp`` (B, K, 2), ``stat`` (B, K)
  dB, ``present`` (B, K), ``phi`` (B, K) the phase steps in (-pi, pi] (NaN: none).
"""

from __future__ import annotations

from collections import namedtuple

#: the kernels' options: compiled on first use and cached on disk (``__pycache__`` beside
#: the files, or ``NUMBA_CACHE_DIR``), released GIL
JIT = dict(cache=True, nogil=True)
#: the vectorized loops' options: no zero-division checks (they stop LLVM's vectorizer),
#: reassociated float sums
FAST = dict(cache=True, nogil=True, error_model="numpy", fastmath=True)

Codes = namedtuple("Codes", ["kind", "lik", "a", "b", "data"])
Fit = namedtuple("Fit", ["nu", "phi", "amp", "live", "lm", "nll", "sigma", "mu", "g", "h"])
Steps = namedtuple("Steps", ["levels", "adapt", "amp_cap", "max_range_step", "wrong_per_sigma", "max_phase_step"])
Gate = namedtuple("Gate", ["use", "lo", "hi", "outside", "edges"])
Grid = namedtuple("Grid", ["oversample", "count_guard", "sep_guard", "rho", "table", "tables", "weights", "inside"])
Sources = namedtuple("Sources", ["u", "src", "y", "ramps", "count_sources", "detect_source"])
Decision = namedtuple("Decision", ["threshold", "active", "stat", "nu0", "amp0", "floor", "phi0"])
Report = namedtuple("Report", ["range_res", "carrier", "use", "lo", "hi", "cap"])
Targets = namedtuple("Targets", ["range_m", "amp", "stat", "present", "phi"])
#: the coarse search's work arrays (:mod:`pipeline.dsp.cml.kernels.search`): ``energy``,
#: ``known``, ``near``, ``seen`` (L,), ``coarse``, ``peaks``, ``span``, ``edge`` (Lc,),
#: ``offsets`` (2, 2 half, N), ``turned`` (4 Rm, N), ``cell`` (2 half,), ``vals`` (Rm, 2)
#: complex (one point's back projection per ramp and antenna), ``totals`` (L,) the fine
#: grid's totals (without a coarse grid; else empty), ``chan`` (Lc,), ``steered`` (1, 2, N)
#: complex, ``phis`` (1,), ``turns`` (Rm,) complex (the steered channel and its ramps' factors,
#: :func:`~pipeline.dsp.cml.kernels.search.steer`), ``cross`` (2, Lc) two ramps' cross term at each coarse
#: point (:func:`~pipeline.dsp.cml.kernels.doppler.two_ramps`)
Scratch = namedtuple("Scratch", ["energy", "known", "near", "seen", "coarse", "peaks", "span", "edge", "offsets",
                                 "turned", "cell", "vals", "totals", "chan", "steered", "phis", "turns", "cross"])
