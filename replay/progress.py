"""A dependency-free progress bar on stderr for long work (Monte Carlo, re-processing)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``with Progress(total, "label") as bar: bar.update(n)``.

    On a terminal the bar redraws in place at most 10 times a second; elsewhere (CI logs)
    it prints a line at every 10 % step. ``enabled=False`` makes it silent.
    """

    def __init__(self, total: int, label: str, unit: str = "it", enabled: bool = True, stream: TextIO | None = None):
        self.total = max(int(total), 0)
        self.label = label
        self.unit = unit
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.done = 0
        self._t0 = time.monotonic()
        self._last_draw = 0.0
        self._last_decile = -1
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def __enter__(self) -> "Progress":
        self._t0 = time.monotonic()
        self._draw(force=True)
        return self

    def __exit__(self, *exc) -> None:
        self._draw(force=True)
        if self.enabled and self._tty:
            self.stream.write("\n")
            self.stream.flush()

    def update(self, n: int = 1) -> None:
        self.done = min(self.done + int(n), self.total) if self.total else self.done + int(n)
        self._draw()

    def line(self) -> str:
        """The current bar as text."""
        frac = self.done / self.total if self.total else 1.0
        elapsed = time.monotonic() - self._t0
        eta = elapsed * (1 - frac) / frac if frac > 0 else float("nan")
        width = 30
        filled = int(round(frac * width))
        bar = "#" * filled + "." * (width - filled)
        eta_txt = "done" if frac >= 1 else (f"eta {eta:5.1f}s" if eta == eta else "eta     ?")
        return f"{self.label} [{bar}] {frac:6.1%} {self.done}/{self.total} {self.unit} {elapsed:6.1f}s {eta_txt}"

    def _draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if self._tty:
            if force or now - self._last_draw >= 0.1:
                self.stream.write("\r" + self.line())
                self.stream.flush()
                self._last_draw = now
            return
        decile = int(10 * self.done / self.total) if self.total else 10
        if force and self.done == 0 or decile > self._last_decile:
            self._last_decile = decile
            self.stream.write(self.line() + "\n")
            self.stream.flush()
