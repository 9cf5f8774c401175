"""Figures as people read them: to their meaningful digits, ``n/a`` for none, counters as
text (the human summaries of ``qradar run`` and its live lines)."""

from __future__ import annotations

import math

#: significant digits of a figure read from a fixed-size histogram (within 2 % of the exact one)
HISTOGRAM_DIGITS = 3


def round_sig(value: float | None, digits: int = HISTOGRAM_DIGITS) -> float | None:
    """``value`` rounded to ``digits`` significant digits (JSON), None for none or not finite."""
    if value is None or not math.isfinite(value):
        return None
    if value == 0:
        return 0.0
    return round(float(value), digits - 1 - math.floor(math.log10(abs(value))))


def sig(value: float | None, digits: int = HISTOGRAM_DIGITS) -> str:
    """``value`` with ``digits`` significant digits (no exponent below a million), ``n/a``
    for none: 28.7298 -> "28.7", 0.12812 -> "0.128", 1234.5 -> "1230"."""
    v = round_sig(value, digits)
    if v is None:
        return "n/a"
    if abs(v) >= 10 ** (digits - 1):
        return f"{v:.0f}"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(v)))) if v else 0
    return f"{v:.{decimals}f}"


def percent(value: float | None) -> str:
    """A fraction as a percentage to 0.1 %, ``n/a`` for none."""
    return "n/a" if value is None or not math.isfinite(value) else f"{100 * value:.1f} %"


def counts(d: dict, skip_zero: bool = False) -> str:
    """``{"a": 1, "b_c": 0}`` -> "a 1, b c 0" (``skip_zero``: only the non-zero ones, or "none")."""
    items = [(k, v) for k, v in d.items() if not (skip_zero and not v)]
    if not items:
        return "none"
    return ", ".join(f"{str(k).replace('_', ' ')} {sig(v) if isinstance(v, float) else v}" for k, v in items)
