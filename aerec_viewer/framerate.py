"""How fast the page redraws while the operator moves the view, and the point budget that follows.

viser draws on demand and reports the camera to the server whenever it changes, once per drawn
frame at most (throttled to 50 Hz). While the operator orbits, pans or zooms, the camera
messages therefore arrive at the page's frame rate, or slower when input, not drawing, is what
limits them: the rate of view updates the operator sees, measured without any script in the
page. `ViewRateMeter` turns the messages of one gesture into a rate once the hand rests;
`BudgetGovernor` lowers the point budget while that rate is under TARGET_FPS.

Software WebGL (a laptop without GPU, a remote desktop, a VM) is where this matters: its cost per
frame is a fixed part (the canvas, the image plane, outlines, labels: bench_viewer.py --fps)
plus a part per point, so the budget moves by the measured ratio and converges in a few steps.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

GESTURE_GAP_S = 0.6      # camera messages further apart belong to different gestures
REST_S = 1.0             # a gesture is over (and measured) once the view rests this long
MIN_INTERVALS = 6        # a gesture shorter than this says nothing


@dataclass
class ViewRateMeter:
    """Per client, the times its view moved; `rate` gives the view updates per second of the
    last finished gesture (the median interval between consecutive moves), once."""

    _moves: dict[int, list[float]] = field(default_factory=dict)
    # camera messages arrive on the server's thread, `rate` is asked on the viewer's
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def moved(self, client: int, t: float) -> None:
        with self._lock:
            ts = self._moves.setdefault(client, [])
            if ts and t - ts[-1] > GESTURE_GAP_S:
                ts.clear()                # an earlier gesture too short to measure
            ts.append(t)

    def rate(self, now: float) -> float | None:
        """The rate of a gesture that has just ended (None when none has); slowest client."""
        rates = []
        with self._lock:
            for ts in self._moves.values():
                if ts and now - ts[-1] >= REST_S:
                    if len(ts) > MIN_INTERVALS:
                        rates.append(1.0 / float(np.median(np.diff(ts))))
                    ts.clear()
        return min(rates) if rates else None


@dataclass
class BudgetGovernor:
    """Lowers the point budget while the view updates under TARGET_FPS, raises it back (never
    above the budget it started from) when it updates fast, and stops for good once the operator
    sets the budget. At the slider's floor and still slow, it asks for the tile outlines to be
    hidden (`hide_tiles`), once: the points are then no longer what is slow."""

    start: int                             # the budget it may return to
    user_set: bool = False
    TARGET_FPS: float = 15.0
    HIGH_FPS: float = 40.0
    MIN_BUDGET: int = 10_000
    hide_tiles: bool = False
    said: bool = False                     # the messages list has heard of it

    def observe(self, fps: float, budget: int) -> int | None:
        """The new budget after a gesture at `fps` view updates per second (None: keep it)."""
        if self.user_set:
            return None
        new = None
        if fps < self.TARGET_FPS and budget > self.MIN_BUDGET:
            # frame time ~ fixed + per point: aim under the target with a margin, and at least
            # one slider step (15 % from high budgets) so that a noisy measure still converges
            new = min(_round(budget * fps / (1.2 * self.TARGET_FPS)), _round(0.85 * budget),
                      max(self.MIN_BUDGET, budget - 10_000))
        elif fps < self.TARGET_FPS and not self.hide_tiles:
            self.hide_tiles = True
        elif fps > self.HIGH_FPS and budget < self.start:
            new = min(self.start, _round(budget * 1.5))
        if new is None or new == budget:
            return None
        return new


def _round(n: float) -> int:
    """To the panel slider's 10 k steps, not under its floor."""
    return int(max(BudgetGovernor.MIN_BUDGET, round(n / 10_000.0) * 10_000))
