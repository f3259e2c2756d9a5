"""How fast the page draws while the operator moves the view, and the display that follows.

Each tab counts the frames its page draws: a 1-pixel iframe served by the image workspace
(`counter_iframe`, workspace/static/frames.html) runs in the page's own frame loop and posts the
times of its frames. Without those reports the rate falls back on viser's camera messages, sent
at most once per drawn frame (in practice about every second one). `ViewRateMeter` turns a
gesture (orbit, pan, zoom) into frame rates: every MID_S of reported frames while it goes on,
else once the hand rests.

Software WebGL (a laptop without GPU, a remote desktop, a VM) is where this matters: a frame
costs a fixed part (the canvas, the picking image, outlines, labels) plus about 1.5 us per point
(bench_viewer.py --fps). At rest the page draws once and may take its time; while a view moves,
`MotionGovernor` sets how many points are drawn (motion.py: a nested subsample of those shown)
and, when the fewest are still too slow, what else is hidden.
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
MID_S = 2.0              # a gesture that goes on is measured every this long of reported frames
FRAMES_KEPT_S = 60.0     # frame times kept per client
FRAMES_SILENT_S = 10.0   # a page that reported no frame for this long is measured by its messages


@dataclass
class ViewRateMeter:
    """Per client, the times its view moved and (when its page reports them) the times the page
    drew a frame; `rate` gives the frame rate of each part of a gesture, once.

    A page that reports its frames (the counter iframe, `frames`) is measured by the frames it
    drew while its view moved (drawn_rate), every MID_S while the gesture goes on: the display
    can follow within an orbit. One that does not is measured by its camera messages once the
    gesture ends (the median interval between consecutive moves: at most the drawn rate, about
    half of it in practice)."""

    _moves: dict[int, list[float]] = field(default_factory=dict)
    _frames: dict[int, deque] = field(default_factory=dict)
    _reported: dict[int, float] = field(default_factory=dict)   # client -> when it last reported
    _marks: dict[int, float] = field(default_factory=dict)      # client -> measured up to (its gesture)
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
                self._marks.pop(client, None)
            ts.append(t)

    def forget(self, client: int) -> None:
        with self._lock:
            for d in (self._moves, self._frames, self._reported, self._marks):
                d.pop(client, None)

    def rate(self, now: float) -> float | None:
        """The rate of the last part of a gesture not yet measured (None when there is none);
        the slowest client's. A page that reports its frames is measured every MID_S of frames
        while its gesture goes on, and for the rest once it has ended; one that does not, once
        its gesture has ended."""
        rates: list[tuple[float, str]] = []
        with self._lock:
            for client, ts in self._moves.items():
                if not ts:
                    continue
                drawn = self.drawing(client, ts[-1])
                ongoing = now - ts[-1] < (DRAWN_GAP_S if drawn else REST_S)
                mark = self._marks.get(client)
                if drawn:
                    part = [t for t in ts if mark is None or t >= mark]
                    if ongoing:
                        upto = self._reported[client]
                        part = [t for t in part if t <= upto]
                        if len(part) >= 2 and upto - part[0] >= MID_S:
                            r = self._drawn_rate(client, part)
                            if r is not None:
                                rates.append((r, "drawn"))
                                self._marks[client] = upto
                        continue
                    if self._reported[client] < ts[-1] + 0.05 and now - ts[-1] < REPORT_WAIT_S:
                        continue          # the frames drawn until the last move are on their way
                    r = self._drawn_rate(client, part) if len(part) >= 2 else None
                    if r is not None or mark is not None:
                        if r is not None:
                            rates.append((r, "drawn"))
                        ts.clear()
                        self._marks.pop(client, None)
                        continue
                if ongoing:
                    continue
                if len(ts) > MIN_INTERVALS:
                    rates.append((1.0 / float(np.median(np.diff(ts))), "camera"))
                ts.clear()
        if not rates:
            return None
        r, self.source = min(rates)
        return r

    def _drawn_rate(self, client: int, moves: list[float]) -> float | None:
        """Frames drawn per second while the view moved: the frames between two camera messages
        at most MOVING_FRAMES apart (more: the hand rested, the idle page ran empty frames),
        counted over the time they span. On a slow page (most of that time in frames longer than
        EMPTY_FRAME_S) the frames that came within EMPTY_FRAME_S of the one before drew nothing
        (requestAnimationFrame runs while the page waits for input) and are not counted; their
        time is. A mean, not a median interval: a stall is part of what the operator sees."""
        ts = np.asarray(moves)
        f = np.fromiter(self._frames.get(client, ()), float)
        f = f[(f >= ts[0]) & (f <= ts[-1] + 0.05)]
        if len(f) <= MIN_FRAMES:
            return None
        seg = np.searchsorted(ts, f)                  # the message interval each frame is in
        moving = np.bincount(seg, minlength=len(ts) + 1)[seg] <= MOVING_FRAMES
        both = moving[1:] & moving[:-1]
        iv = np.diff(f)[both]
        if len(iv) < MIN_FRAMES:
            return None
        return drawn_rate(iv)


def drawn_rate(intervals: np.ndarray) -> float:
    """Frames drawn per second from the intervals between a page's frames: their count over
    their span; on a slow page (most of the span in frames longer than EMPTY_FRAME_S), without
    the short ones, which drew nothing (requestAnimationFrame runs while the page waits)."""
    iv = np.asarray(intervals, float)
    slow = iv > EMPTY_FRAME_S
    total = float(np.sum(iv))
    if float(np.sum(iv[slow])) < total / 2:           # a fast page: every frame drew
        return len(iv) / total
    return int(np.count_nonzero(slow)) / total


# What the moving display sheds after its points, in this order (cheapest loss first): the
# registered tiles (outlines: fat-line instances; or textured quads), the GCP marks and labels
# (rings: fat-line instances; labels: one instance per glyph), the picking image (the fill of a
# textured plane: about 20 ms a frame at 1600 x 1000 on a loaded machine).
SHED = ("tiles", "labels", "image")


@dataclass
class MotionGovernor:
    """The display while a view moves: how many points it draws (`budget`; None: all shown) and
    how much of SHED it hides, set from each frame rate the meter gives.

    Under EDGE times TARGET_FPS the budget moves to draw at AIM times the target (by the line
    through the last two measures, frame time = fixed + per point, or by the ratio; at least
    15 % a step so a noisy measure still converges), down to MIN_BUDGET; at the floor and still
    slow, or when the fixed part alone is too slow, the next of SHED goes. Over HIGH_FPS it
    gives back in the reverse order, up to drawing all the points shown. At rest the display is
    never thinned."""

    budget: int | None = None
    shed: int = 0                          # SHED[:shed] are hidden while the view moves
    TARGET_FPS: float = 15.0
    EDGE: float = 1.1                      # within 10 % of the target is under it (a load that
    AIM: float = 1.25                      # grows tips it over); aim 25 % over the target
    HIGH_FPS: float = 40.0
    MIN_BUDGET: int = 2_000
    last: tuple[int, float] | None = None  # (points, frame time) of the last gesture, nothing shed

    def observe(self, fps: float, drawn: int) -> bool:
        """A gesture drew `drawn` points at `fps` frames a second: did the display change?"""
        seen, self.last = self.last, ((drawn, 1.0 / fps) if self.shed == 0 else None)
        if fps < self.TARGET_FPS * self.EDGE:
            floor = self.budget is not None and self.budget <= self.MIN_BUDGET
            if not floor and drawn > self.MIN_BUDGET * 1.05:
                aim = self._aim(drawn, fps, seen)
                self.budget = max(self.MIN_BUDGET, min(aim or self.MIN_BUDGET, _round(0.85 * drawn)))
                if aim is not None or self.shed == len(SHED):
                    return True
            # at the floor, or the rest of the frame alone is over the target: shed the next
            if self.shed < len(SHED):
                self.shed += 1
                return True
            return False
        if fps > self.HIGH_FPS:
            if self.shed:
                self.shed -= 1
                return True
            if self.budget is not None:
                self.budget = _round(max(self.budget, drawn) * 1.5)
                return True
        return False

    def _aim(self, drawn: int, fps: float, seen: tuple[int, float] | None) -> int | None:
        """The points that should draw at AIM times the target: from the line through this
        gesture and the one before (frame time = fixed + per point), when they drew different
        counts and the line rises (None: its fixed part alone is over the goal); else by the
        ratio."""
        goal = 1.0 / (self.AIM * self.TARGET_FPS)
        if seen is not None and abs(seen[0] - drawn) > 0.1 * drawn:
            per = (1.0 / fps - seen[1]) / (drawn - seen[0])
            fixed = 1.0 / fps - per * drawn
            if per > 0:
                return _round((goal - fixed) / per) if fixed < goal else None
        return _round(drawn * fps / (self.AIM * self.TARGET_FPS))

    def hidden(self) -> tuple[str, ...]:
        return SHED[:self.shed]


def _round(n: float) -> int:
    """To 2 significant digits (budgets from a few thousand points to millions)."""
    n = max(float(n), 1.0)
    step = 10.0 ** max(0, int(np.floor(np.log10(n))) - 1)
    return int(round(n / step) * step)


def counter_iframe(workspace_url: str, client: int) -> str:
    """The HTML of a tab's frame counter (workspace/static/frames.html): a 1-pixel iframe at the
    top of viser's panel, transparent. Not 0 x 0 nor display:none, and in view: Chromium stops the
    frames of a cross-origin iframe it considers hidden or off screen."""
    return (f'<iframe src="{workspace_url.rstrip("/")}/static/frames.html?client={int(client)}" '
            'title="frame counter" aria-hidden="true" tabindex="-1" '
            'style="display:block;width:1px;height:1px;border:0;opacity:0;margin:0;'
            'pointer-events:none"></iframe>')
