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
from collections import deque
from dataclasses import dataclass, field

import numpy as np

GESTURE_GAP_S = 0.6      # camera messages further apart belong to different gestures
REST_S = 1.0             # a gesture is over (and measured) once the view rests this long
MIN_INTERVALS = 6        # a gesture shorter than this says nothing
# With the page's own frame reports: camera messages come at about half the drawn rate, so a
# slow page (1-4 fps) sends them 0.5-2 s apart; a gesture ends after this long without one.
DRAWN_GAP_S = 3.0
MIN_FRAMES = 4           # frame intervals within a gesture needed to measure it
MOVING_FRAMES = 8        # more frames than this between two camera messages: the view rested
EMPTY_FRAME_S = 0.025    # requestAnimationFrame also runs frames that draw nothing (~17 ms apart)
REPORT_WAIT_S = 5.0      # a finished gesture waits this long for the page's report of its frames
FRAMES_KEPT_S = 60.0     # frame times kept per client
FRAMES_SILENT_S = 10.0   # a page that reported no frame for this long is measured by its messages


@dataclass
class ViewRateMeter:
    """Per client, the times its view moved and (when its page reports them) the times the page
    drew a frame; `rate` gives the frame rate of the last finished gesture, once.

    A page that reports its frames (the counter iframe, `frames`) is measured by the frames it
    drew while its view moved (the median interval between frames from its first to its last
    camera message of the gesture); one that does not, by its camera messages (the median
    interval between consecutive moves: at most the drawn rate, about half of it in practice)."""

    _moves: dict[int, list[float]] = field(default_factory=dict)
    _frames: dict[int, deque] = field(default_factory=dict)
    _reported: dict[int, float] = field(default_factory=dict)   # client -> when it last reported
    source: str = ""                 # what the last rate measured: "drawn" frames or "camera" messages
    # camera messages and reports arrive on server threads, `rate` is asked on the viewer's
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def drawing(self, client: int, now: float) -> bool:
        """Does this client's page report its frames (recently)?"""
        t = self._reported.get(client)
        return t is not None and now - t < FRAMES_SILENT_S

    def frames(self, client: int, times: list[float], now: float) -> None:
        """The page of `client` drew frames at `times` (this clock), reported at `now`."""
        with self._lock:
            q = self._frames.setdefault(client, deque())
            q.extend(sorted(times))
            while q and q[0] < now - FRAMES_KEPT_S:
                q.popleft()
            self._reported[client] = now

    def moved(self, client: int, t: float) -> None:
        with self._lock:
            ts = self._moves.setdefault(client, [])
            gap = DRAWN_GAP_S if self.drawing(client, t) else GESTURE_GAP_S
            if ts and t - ts[-1] > gap:
                ts.clear()                # an earlier gesture too short to measure
            ts.append(t)

    def forget(self, client: int) -> None:
        with self._lock:
            for d in (self._moves, self._frames, self._reported):
                d.pop(client, None)

    def rate(self, now: float) -> float | None:
        """The rate of a gesture that has just ended (None when none has); slowest client."""
        rates: list[tuple[float, str]] = []
        with self._lock:
            for client, ts in self._moves.items():
                drawn = self.drawing(client, ts[-1]) if ts else False
                if not ts or now - ts[-1] < (DRAWN_GAP_S if drawn else REST_S):
                    continue
                if drawn:
                    if self._reported[client] < ts[-1] + 0.05 and now - ts[-1] < REPORT_WAIT_S:
                        continue          # the frames drawn until the last move are on their way
                    r = self._drawn_rate(client, ts)
                    if r is not None:
                        rates.append((r, "drawn"))
                        ts.clear()
                        continue
                if len(ts) > MIN_INTERVALS:
                    rates.append((1.0 / float(np.median(np.diff(ts))), "camera"))
                ts.clear()
        if not rates:
            return None
        r, self.source = min(rates)
        return r

    def _drawn_rate(self, client: int, moves: list[float]) -> float | None:
        """1 / the median interval between the frames drawn while the view moved: the frames
        between two camera messages at most MOVING_FRAMES apart (more: the hand rested, the
        idle page ran empty frames), without the empty frames of a slow page."""
        ts = np.asarray(moves)
        f = np.array([t for t in self._frames.get(client, ()) if ts[0] <= t <= ts[-1] + 0.05])
        if len(f) <= MIN_FRAMES:
            return None
        seg = np.searchsorted(ts, f)                  # the message interval each frame is in
        moving = np.bincount(seg, minlength=len(ts) + 1)[seg] <= MOVING_FRAMES
        both = moving[1:] & moving[:-1]
        iv = np.diff(f)[both]
        if len(iv) < MIN_FRAMES:
            return None
        slow = iv[iv > EMPTY_FRAME_S]
        if len(slow) >= len(iv) / 2:                  # a slow page: its empty frames are not drawn
            iv = slow
        return 1.0 / float(np.median(iv))


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


def counter_iframe(workspace_url: str, client: int) -> str:
    """The HTML of a tab's frame counter (workspace/static/frames.html): a 1-pixel iframe at the
    top of viser's panel, transparent. Not 0 x 0 nor display:none, and in view: Chromium stops the
    frames of a cross-origin iframe it considers hidden or off screen."""
    return (f'<iframe src="{workspace_url.rstrip("/")}/static/frames.html?client={int(client)}" '
            'title="frame counter" aria-hidden="true" tabindex="-1" '
            'style="display:block;width:1px;height:1px;border:0;opacity:0;margin:0;'
            'pointer-events:none"></iframe>')
