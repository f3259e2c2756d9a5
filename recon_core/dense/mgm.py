"""MGM, the paper's matcher (More Global Matching: Facciolo, de Franchis and Meinhardt, BMVC 2015,
the matcher s2p uses), on a census cost.

SGM aggregates the matching cost along 1D scanlines, one per direction, and sums them; its
disparity maps show streaks along those lines. MGM keeps SGM's recursion and penalties but lets
each direction's message at a pixel come from two of its already visited neighbours, the one
behind it along the direction r and the one behind it across (r turned by 90 degrees), averaged:

    L_r(p, d) = C(p, d) + 1/2 sum_{q in {p - r, p - r_perp}} [ min(L_r(q, d), L_r(q, d +- 1) + P1,
                                                               min_k L_r(q, k) + P2) - min_k L_r(q, k) ]

so every direction's pass is a 2D sweep whose messages already carry two dimensions of the
image; S(p, d) = sum over 8 directions of L_r(p, d), the disparity its minimum (winner takes
all), refined to sub-pixel by the equiangular (V) fit, checked against the right image's
disparity taken from the same S (left-right check), smoothed by a 3 x 3 median of the valid
neighbours, and cleared of speckles (small isolated regions: mismatches).

The cost is the Hamming distance of census codes (window w x w, w <= 7: w^2 - 1 <= 48 bits),
0 .. w^2 - 1. The compiled kernels (numba: recursions with no library kernel) work on one row
strip at a time so that a volume stays under a memory budget; strips overlap so the messages
reaching a kept row have come a long way.

Convention (recon_core.dense.matchers): rows are epipolar lines, d = u_right - u_left.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

_JIT: dict[str, Any] = dict(cache=True, nogil=True)

# the 8 directions' sweeps: (neighbour 1 (dy, dx), neighbour 2 (dy, dx), column-major, y step, x step)
# neighbour 1 is p - r, neighbour 2 is p - r_perp; the sweep visits both before p
_SWEEPS = (
    ((0, -1), (-1, 0), False, 1, 1),      # r = (+x):   from the left and from above
    ((0, 1), (1, 0), False, -1, -1),      # r = (-x):   from the right and from below
    ((-1, 0), (0, 1), False, 1, -1),      # r = (+y):   from above and from the right
    ((1, 0), (0, -1), False, -1, 1),      # r = (-y):   from below and from the left
    ((-1, -1), (-1, 1), False, 1, 1),     # r = (+x+y): both from the row above
    ((1, 1), (1, -1), False, -1, 1),      # r = (-x-y): both from the row below
    ((1, -1), (-1, -1), True, 1, 1),      # r = (+x-y): both from the column on the left
    ((-1, 1), (1, 1), True, 1, -1),       # r = (-x+y): both from the column on the right
)


@njit(**_JIT)
def census(img: np.ndarray, r: int) -> np.ndarray:
    """(h, w) uint64 census codes of a (h, w) float32 image: bit k set where the k-th pixel of
    the (2r+1)^2 window (the centre left out) is darker than the centre; the window clamped at
    the borders."""
    h, w = img.shape
    out = np.zeros((h, w), np.uint64)
    for y in range(h):
        for x in range(w):
            c = img[y, x]
            code = np.uint64(0)
            for dy in range(-r, r + 1):
                yy = min(max(y + dy, 0), h - 1)
                for dx in range(-r, r + 1):
                    if dy == 0 and dx == 0:
                        continue
                    xx = min(max(x + dx, 0), w - 1)
                    code = code << np.uint64(1)
                    if img[yy, xx] < c:
                        code = code | np.uint64(1)
            out[y, x] = code
    return out


@njit(**_JIT)
def _popcount(v: np.uint64) -> int:
    v = v - ((v >> np.uint64(1)) & np.uint64(0x5555555555555555))
    v = (v & np.uint64(0x3333333333333333)) + ((v >> np.uint64(2)) & np.uint64(0x3333333333333333))
    v = (v + (v >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return int((v * np.uint64(0x0101010101010101)) >> np.uint64(56))


@njit(**_JIT)
def cost_volume(cl: np.ndarray, cr: np.ndarray, d0: int, D: int, out_cost: float) -> np.ndarray:
    """(h, w, D) float32: Hamming distance of left census (y, x) and right census (y, x + d0 + k);
    out_cost where x + d0 + k falls outside the right image."""
    h, w = cl.shape
    C = np.empty((h, w, D), np.float32)
    for y in range(h):
        for x in range(w):
            for k in range(D):
                xr = x + d0 + k
                if xr < 0 or xr >= w:
                    C[y, x, k] = out_cost
                else:
                    C[y, x, k] = _popcount(cl[y, x] ^ cr[y, xr])
    return C


@njit(**_JIT)
def _message(L: np.ndarray, y: int, x: int, k_d: int, P1: float, P2: float, acc: np.ndarray) -> None:
    """acc[d] += min(L[y,x,d], L[y,x,d+-1] + P1, min L[y,x] + P2) - min L[y,x]."""
    mn = L[y, x, 0]
    for d in range(1, k_d):
        if L[y, x, d] < mn:
            mn = L[y, x, d]
    top = mn + P2
    for d in range(k_d):
        v = L[y, x, d]
        if d > 0 and L[y, x, d - 1] + P1 < v:
            v = L[y, x, d - 1] + P1
        if d < k_d - 1 and L[y, x, d + 1] + P1 < v:
            v = L[y, x, d + 1] + P1
        if top < v:
            v = top
        acc[d] += v - mn


@njit(**_JIT)
def _sweep(C, S, L, a_dy, a_dx, b_dy, b_dx, col_major, y_step, x_step, P1, P2):
    """One direction's MGM pass over the whole volume: L its messages, added into S."""
    h, w, D = C.shape
    acc = np.empty(D, np.float32)
    n_out, n_in = (w, h) if col_major else (h, w)
    for i in range(n_out):
        for j in range(n_in):
            if col_major:
                x = i if x_step > 0 else w - 1 - i
                y = j if y_step > 0 else h - 1 - j
            else:
                y = i if y_step > 0 else h - 1 - i
                x = j if x_step > 0 else w - 1 - j
            for d in range(D):
                acc[d] = 0.0
            n = 0
            ya, xa = y + a_dy, x + a_dx
            if 0 <= ya < h and 0 <= xa < w:
                _message(L, ya, xa, D, P1, P2, acc)
                n += 1
            yb, xb = y + b_dy, x + b_dx
            if 0 <= yb < h and 0 <= xb < w:
                _message(L, yb, xb, D, P1, P2, acc)
                n += 1
            inv = 1.0 / n if n else 0.0
            for d in range(D):
                v = C[y, x, d] + acc[d] * inv
                L[y, x, d] = v
                S[y, x, d] += v


def aggregate(C: np.ndarray, P1: float, P2: float) -> np.ndarray:
    """S: the 8 directions' MGM messages summed (h, w, D float32)."""
    S = np.zeros_like(C)
    L = np.empty_like(C)
    for (a_dy, a_dx), (b_dy, b_dx), col_major, y_step, x_step in _SWEEPS:
        _sweep(C, S, L, a_dy, a_dx, b_dy, b_dx, col_major, y_step, x_step, np.float32(P1), np.float32(P2))
    return S


@njit(**_JIT)
def _winners(S: np.ndarray, d0: int, uniqueness: float) -> tuple[np.ndarray, np.ndarray]:
    """Left disparity (WTA + V-fit; NaN at the range's ends, and where a disparity more than one
    step from the winner costs less than (1 + uniqueness) times the winner's: an ambiguous
    match) and right disparity (WTA on the same S along the right image's diagonals), both in
    d = u_right - u_left."""
    h, w, D = S.shape
    dl = np.full((h, w), np.nan, np.float32)
    dr = np.full((h, w), np.nan, np.float32)
    for y in range(h):
        for x in range(w):
            best, kb = np.inf, -1
            for k in range(D):
                if S[y, x, k] < best:
                    best, kb = S[y, x, k], k
            if uniqueness > 0 and kb >= 0:
                lim = best * (1.0 + uniqueness)
                for k in range(D):
                    if abs(k - kb) > 1 and S[y, x, k] <= lim:
                        kb = -1
                        break
            if 0 < kb < D - 1:
                a, c = S[y, x, kb - 1], S[y, x, kb + 1]
                slope = max(a, c) - best
                off = 0.5 * (a - c) / slope if slope > 0 else 0.0
                dl[y, x] = d0 + kb + off
        for xr in range(w):
            best, kb = np.inf, -1
            for k in range(D):
                x = xr - d0 - k
                if 0 <= x < w and S[y, x, k] < best:
                    best, kb = S[y, x, k], k
            if kb >= 0:
                dr[y, xr] = d0 + kb
    return dl, dr


@njit(**_JIT)
def _lr_check(dl: np.ndarray, dr: np.ndarray, tol: float) -> np.ndarray:
    h, w = dl.shape
    out = np.full((h, w), np.nan, np.float32)
    for y in range(h):
        for x in range(w):
            d = dl[y, x]
            if d != d:
                continue
            xr = int(np.floor(x + d + 0.5))
            if 0 <= xr < w and abs(dr[y, xr] - d) <= tol:
                out[y, x] = d
    return out


@njit(**_JIT)
def _median3(d: np.ndarray) -> np.ndarray:
    """3 x 3 median of each valid pixel's valid neighbours (itself included)."""
    h, w = d.shape
    out = d.copy()
    buf = np.empty(9, np.float32)
    for y in range(h):
        for x in range(w):
            if d[y, x] != d[y, x]:
                continue
            n = 0
            for yy in range(max(y - 1, 0), min(y + 2, h)):
                for xx in range(max(x - 1, 0), min(x + 2, w)):
                    v = d[yy, xx]
                    if v == v:
                        buf[n] = v
                        n += 1
            out[y, x] = np.sort(buf[:n])[n // 2]
    return out


def strips(h: int, rows: int, overlap: int) -> list[tuple[int, int, int, int]]:
    """Row strips covering [0, h): (read from, read to, keep from, keep to), each read at most
    `rows` + 2 overlap rows, each kept row read with `overlap` rows of context on both sides
    (fewer at the image's own borders)."""
    if h <= rows + 2 * overlap:
        return [(0, h, 0, h)]
    out, k0 = [], 0
    while k0 < h:
        k1 = min(k0 + rows, h)
        out.append((max(k0 - overlap, 0), min(k1 + overlap, h), k0, k1))
        k0 = k1
    return out


def mgm_disparity(left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float, census_window: int = 5,
                  p1: float = 12.0, p2: float = 32.0, lr_max_diff_px: float = 1.0, median: bool = True,
                  speckle_window: int = 100, speckle_range: float = 2.0, uniqueness: float = 0.1,
                  max_volume_mb: float = 512.0, overlap_rows: int = 64) -> np.ndarray:
    """Disparity (h, w) float32 of a rectified pair (d = u_right - u_left, NaN invalid), searched
    in [floor(d_lo) - 1, ceil(d_hi) + 1] (one step beyond each end, so that a winner at the
    range's own ends is refined and not dropped)."""
    h, w = left.shape
    d0 = int(np.floor(d_lo)) - 1
    D = max(int(np.ceil(d_hi)) + 1 - d0 + 1, 3)
    r = census_window // 2
    cl = census(np.ascontiguousarray(left, np.float32), r)
    cr = census(np.ascontiguousarray(right, np.float32), r)
    bits = census_window * census_window - 1
    # three float32 volumes live at once (C, S, L): a strip of `fit` rows fills the budget, its
    # context rows included (fewer of them when the canvas is so wide that they would not fit;
    # a strip is 32 rows at least, over the budget only for a budget under 32 rows' volumes)
    fit = int(max_volume_mb * 2 ** 20 / (3 * 4 * w * D))
    overlap_rows = max(min(overlap_rows, (fit - 16) // 2), 8)
    rows = max(fit - 2 * overlap_rows, 16)
    out = np.full((h, w), np.nan, np.float32)
    for a, b, k0, k1 in strips(h, rows, overlap_rows):
        C = cost_volume(cl[a:b], cr[a:b], d0, D, float(bits))
        S = aggregate(C, p1, p2)
        del C
        dl, dr = _winners(S, d0, float(uniqueness))
        del S
        d = _lr_check(dl, dr, float(lr_max_diff_px))
        out[k0:k1] = d[k0 - a:k1 - a]
    if median:
        out = _median3(out)
    if speckle_window > 0:
        out = remove_speckles(out, speckle_window, speckle_range)
    return out


def remove_speckles(d: np.ndarray, max_size: int, max_diff: float) -> np.ndarray:
    """NaN where a connected region of disparities (neighbours within max_diff px) has at most
    max_size pixels: isolated blobs are mismatches (OpenCV's filterSpeckles, on 1/16 px)."""
    import cv2

    ok = np.isfinite(d)
    bad = np.int16(-32768)
    fixed = np.where(ok, np.round(np.nan_to_num(d) * 16), bad)
    fixed = np.clip(fixed, -32767, 32767).astype(np.int16)
    cv2.filterSpeckles(fixed, float(bad), int(max_size), int(round(max_diff * 16)))
    return np.where(ok & (fixed != bad), d, np.nan).astype(np.float32)


def warm_compiled_kernels() -> None:
    """Compile the kernels into numba's cache on a small pair (a second process does this while
    the first run's sparse stage works, so the dense stage loads them instead of compiling)."""
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (40, 48)).astype(np.uint8)
    mgm_disparity(img, np.roll(img, 2, axis=1), 0.0, 4.0)
