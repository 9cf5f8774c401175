"""Compiled (numba) linear solves of cml's Gauss--Newton steps: Cholesky, with Gaussian
elimination with partial pivoting where the system is not positive definite."""

from __future__ import annotations

import math

from numba import njit

from pipeline.dsp.cml.kernels.layout import JIT


@njit(**JIT)
def _eliminate(m, rhs, x):
    """``m x = rhs`` by Gaussian elimination with partial pivoting (m and rhs overwritten)."""
    p = m.shape[0]
    for col in range(p):
        piv = col
        best = abs(m[col, col])
        for r in range(col + 1, p):
            if abs(m[r, col]) > best:
                best = abs(m[r, col])
                piv = r
        if piv != col:
            for c in range(p):
                m[col, c], m[piv, c] = m[piv, c], m[col, c]
            rhs[col], rhs[piv] = rhs[piv], rhs[col]
        d = m[col, col]
        for r in range(col + 1, p):
            fct = m[r, col] / d
            if fct != 0.0:
                for c in range(col, p):
                    m[r, c] -= fct * m[col, c]
                rhs[r] -= fct * rhs[col]
    for r in range(p - 1, -1, -1):
        acc = rhs[r]
        for c in range(r + 1, p):
            acc -= m[r, c] * x[c]
        x[r] = acc / m[r, r]


@njit(**JIT)
def solve(m, rhs, lw, x):
    """``x`` (P,) with ``m x = rhs``, m (P, P) symmetric: by Cholesky into ``lw`` (P, P) (the
    lower triangle), or, if m is not positive definite, by Gaussian elimination with partial
    pivoting (m and rhs then overwritten)."""
    p = m.shape[0]
    for j in range(p):
        d = m[j, j]
        for c in range(j):
            d -= lw[j, c] * lw[j, c]
        if not d > 0.0:
            _eliminate(m, rhs, x)
            return
        d = math.sqrt(d)
        lw[j, j] = d
        inv = 1.0 / d
        for r in range(j + 1, p):
            acc = m[r, j]
            for c in range(j):
                acc -= lw[r, c] * lw[j, c]
            lw[r, j] = acc * inv
    for r in range(p):  # L y = rhs, then L^T x = y
        acc = rhs[r]
        for c in range(r):
            acc -= lw[r, c] * x[c]
        x[r] = acc / lw[r, r]
    for r in range(p - 1, -1, -1):
        acc = x[r]
        for c in range(r + 1, p):
            acc -= lw[c, r] * x[c]
        x[r] = acc / lw[r, r]
