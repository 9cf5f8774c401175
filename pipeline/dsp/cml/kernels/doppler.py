"""Compiled (numba) search over the phase step between ramps of one point of the range grid:
with Rm > 1 model ramps a point's back projections ``U_rp`` (ramp r, antenna p) have a
**total** ``sum_r sum_p |U_rp|^2`` and at a phase step phi the energy ``E_phi = sum_p |sum_r
exp(-i c_r phi) U_rp|^2`` (``c_r = r - (Rm - 1) / 2``, the ramp from the middle of the
frame): its peak over phi (:func:`doppler`), where it peaks (:func:`doppler_phase`). Two
ramps, U and V: the peak is ``|U|^2 + |V|^2 + 2 |sum_p conj(U_p) V_p|`` at phi = the angle of
that sum (closed form); more, a grid of phase steps."""

from __future__ import annotations

import math

from numba import njit

from pipeline.dsp.cml.kernels.layout import FAST


#: the phase steps a frame of R >= 3 model ramps is searched at: this many a ramp, evenly
#: over [0, 2 pi) (two ramps: the exact maximum, closed form); the grid's worst loss of a
#: tone's energy is under 1 dB for R = 3 (|1 + 2 cos(pi / 12)|^2 / 9 = 0.90)
DOPPLER_PER_RAMP = 4

#: the search over range runs on the residual steered to a phase step only where the peak over
#: the phase step beats the static energy (phi = 0) by more than this many times the mean
#: total energy of a cell (noise's, about): a static target is searched as the static model
#: searches it (measured on the chamber recording: at 4 the mean error is 9 % above the
#: static model's, at 8 and beyond the same), a target at a blind speed (static energy ~0)
#: steered to as soon as it stands 8 cells' noise above it
STEER_GAIN = 8.0


@njit(cache=True, nogil=True, inline="always")
def doppler(vals, rm):
    """The total ``sum_r sum_p |vals[r, p]|^2`` and the peak over the phase step phi of
    ``sum_p |sum_r exp(-i c_r phi) vals[r, p]|^2`` of one point's back projections ``vals``
    (Rm, 2) complex (``c_r = r - (Rm - 1) / 2``): one ramp, both ``|U|^2``; two, the peak
    ``total + 2 |sum_p conj(U_0p) U_1p|``; more, the largest on :data:`DOPPLER_PER_RAMP`
    Rm phase steps."""
    if rm == 1:
        a = vals[0, 0]
        b = vals[0, 1]
        e = (a.real * a.real + b.real * b.real) + (a.imag * a.imag + b.imag * b.imag)
        return e, e
    total = 0.0
    for r in range(rm):
        for p in range(2):
            v = vals[r, p]
            total += v.real * v.real + v.imag * v.imag
    if rm == 2:
        x = vals[0, 0].conjugate() * vals[1, 0] + vals[0, 1].conjugate() * vals[1, 1]
        return total, total + 2.0 * abs(x)
    best = 0.0
    d = DOPPLER_PER_RAMP * rm
    for j in range(d):
        e = _steered(vals, rm, 2.0 * math.pi * j / d)
        best = max(best, e)
    return total, best


@njit(cache=True, nogil=True, inline="always")
def _steered(vals, rm, phi) -> float:
    """``sum_p |sum_r exp(-i c_r phi) vals[r, p]|^2``."""
    e = 0.0
    for p in range(2):
        acc = 0.0j
        for r in range(rm):
            c = r - (rm - 1) / 2.0
            acc += complex(math.cos(c * phi), -math.sin(c * phi)) * vals[r, p]
        e += acc.real * acc.real + acc.imag * acc.imag
    return e


@njit(cache=True, nogil=True)
def doppler_phase(vals, rm) -> float:
    """The phase step (rad, in (-pi, pi]) at the peak of :func:`doppler` of ``vals`` (Rm, 2):
    one ramp 0; two, ``angle(sum_p conj(U_0p) U_1p)``; more, the grid's best refined by a
    parabola through it and its neighbours."""
    if rm == 1:
        return 0.0
    if rm == 2:
        x = vals[0, 0].conjugate() * vals[1, 0] + vals[0, 1].conjugate() * vals[1, 1]
        return math.atan2(x.imag, x.real)
    d = DOPPLER_PER_RAMP * rm
    step = 2.0 * math.pi / d
    best, top = 0, -1.0
    for j in range(d):
        e = _steered(vals, rm, step * j)
        if e > top:
            top, best = e, j
    left, right = _steered(vals, rm, step * (best - 1)), _steered(vals, rm, step * (best + 1))
    curv = left - 2.0 * top + right
    off = min(max(0.5 * (left - right) / curv, -0.5), 0.5) if curv < 0.0 else 0.0
    phi = step * (best + off)
    return phi - 2.0 * math.pi if phi > math.pi else phi


@njit(**FAST)
def two_ramps(uc, sc, coarse, peaks, cross):
    """:func:`doppler` of two ramps at every coarse point of ``uc`` (2, 2, Lc) times ``sc``:
    totals into ``coarse``, peaks into ``peaks`` (Lc,), and the cross term ``sum_p conj(U_0p)
    U_1p`` into ``cross`` (2, Lc) (its real and imaginary parts, all three times ``sc^2``: the
    energy at a phase step phi is ``coarse + 2 (Re cross cos phi + Im cross sin phi)``), one
    vectorized pass."""
    s2 = sc * sc
    u0, u1, v0, v1 = uc[0, 0], uc[0, 1], uc[1, 0], uc[1, 1]
    for c in range(coarse.shape[0]):
        a0, a1, b0, b1 = u0[c], u1[c], v0[c], v1[c]
        total = (a0.real * a0.real + a0.imag * a0.imag + a1.real * a1.real + a1.imag * a1.imag
                 + b0.real * b0.real + b0.imag * b0.imag + b1.real * b1.real + b1.imag * b1.imag)
        xr = a0.real * b0.real + a0.imag * b0.imag + a1.real * b1.real + a1.imag * b1.imag  # sum conj(a) b
        xi = a0.real * b0.imag - a0.imag * b0.real + a1.real * b1.imag - a1.imag * b1.real
        coarse[c] = total * s2
        peaks[c] = (total + 2.0 * math.sqrt(xr * xr + xi * xi)) * s2
        cross[0, c] = xr * s2
        cross[1, c] = xi * s2


@njit(cache=True, nogil=True, inline="always")
def static_energy(vals, rm) -> float:
    """The energy at phase step 0, ``sum_p |sum_r vals[r, p]|^2``, of ``vals`` (Rm, 2)."""
    e = 0.0
    for p in range(2):
        acc = 0.0j
        for r in range(rm):
            acc += vals[r, p]
        e += acc.real * acc.real + acc.imag * acc.imag
    return e

