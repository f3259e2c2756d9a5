"""Procedural urban scene for the synthetic sites, and the numba ray-casting kernels.

The scene is a height field ``h = H(x, y)`` (ellipsoidal metres) over *scene-local*
horizontal coordinates ``x = E - E0``, ``y = N - N0`` where ``(E, N)`` are UTM easting and
northing in the site's UTM zone and ``(E0, N0)`` a whole-metre origin near the scene centre.
Everything is evaluated analytically, point by point, in O(1): no grid of the scene is
stored except (a) a coarse grid of per-cell maxima used to skip empty space while ray
marching and (b) a cache of per-block parameters (street lines, buildings) computed from the
same hash functions, which only saves time: outside the cached area the hash path gives the
same numbers.

Content (all random parameters come from integer hashes of (index, seed)):

* terrain: two octaves of C2 value noise, a few metres of relief, plus the base height ``h0``;
* a street grid rotated by ``theta``: street centre lines on a jittered lattice (pitch
  60-84 m, widths 8-15 m) in the rotated coordinates ``u = x cos t + y sin t``,
  ``v = -x sin t + y cos t``; 0.15 m high sidewalks along the block edges;
* blocks (~40-75 m): parks (grass, paths, dense trees), open ground (bare soil or parking lots
  with stall lines) or built blocks with one or two buildings (3-40 m; flat roofs with
  parapets and rooftop boxes, gabled roofs with the ridge along u or v, hipped roofs) on a
  flat foundation at the terrain height of their centre;
* trees: a jittered 9 m lattice (3x3 neighbour look-up) in parks, yards and open ground, and
  rows of street trees along the sidewalks; paraboloid or half-ellipsoid crowns (radius
  1.8-4 m, 5-12 m high) standing on the terrain;
* materials: road (asphalt, lane lines, zebra crossings, stop lines), sidewalk slabs, grass,
  soil, parking, paths, roofs (per-building tone, panels, vents, stains, tile rows on pitched
  roofs), parapets, rooftop boxes, tree crowns, facades with windows. The albedo carries
  multi-octave value-noise texture down to 0.5 m wavelength; only vegetation depends on the
  season (never the geometry).

Kernels take a scene *context* tuple ``C = (P, LU, LV, TB, salt, iu0, jv0)`` (see
:meth:`SceneModel.ctx`): :func:`scene_eval` (height, gradient, material), :func:`build_accel`
(max grid), :func:`_march` (DDA over the max grid, fine steps <= 0.1 m only where the ray is
below a cell's maximum, bisection + secant refinement, wall detection), cast shadows and the
Lambertian shading kernel :func:`render_rows` used by :mod:`recon_core.synthetic.generator`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit, prange

# ----------------------------------------------------------------------------------------
# Parameter vector layout (float64 array P)
# (I_TREE_T records the tree lattice pitch, TREE_PITCH, for information)
I_COS, I_SIN, I_PU, I_PV, I_JU, I_JV, I_H0, I_TALL, I_TREE_T, I_PARK, I_OPEN, I_SW = range(12)
I_TER = 12          # N_TER x (amplitude, wavelength, offset x, offset y)
N_TER = 2
N_PARAMS = I_TER + 4 * N_TER

# Materials
M_ROAD, M_MARK, M_SIDEWALK, M_GRASS, M_SOIL, M_PARKING, M_PATH = 0, 1, 2, 3, 4, 5, 6
M_ROOF, M_PARAPET, M_ROOFBOX, M_TREE, M_FACADE = 7, 8, 9, 10, 11
MATERIAL_NAMES = ("road", "marking", "sidewalk", "grass", "soil", "parking", "path",
                  "roof", "parapet", "roofbox", "tree", "facade")

# Block types
B_PARK, B_OPEN, B_BUILT = 0, 1, 2

# Block record layout (cache of per-block parameters)
R_TYPE, R_F2, R_F3, R_NB = 0, 1, 2, 3
F_U0, F_U1, F_V0, F_V1, F_HB, F_RT, F_ALONGU, F_TANP, F_PAR, F_BOX = range(10)
F_BU0, F_BV0, F_BSU, F_BSV, F_BH, F_FOUND, F_TONE = range(10, 17)
NBF = 17
NREC = 4 + 2 * NBF

CURB = 0.15          # sidewalk height above the road (m)
TREE_PITCH = 9.0     # lattice of the park / yard trees (m)
STREET_TREE_STEP = 8.0
MAX_STRUCT_HEIGHT = 40.0 + 5.0 + 3.5 + 1.2   # building + ridge + roof box + parapet bound

# ----------------------------------------------------------------------------------------
# Integer hashing (splitmix64) and value noise
_K1 = np.uint64(0x9E3779B97F4A7C15)
_K2 = np.uint64(0xBF58476D1CE4E5B9)
_K3 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S43 = np.uint64(43)
_S22 = np.uint64(22)
_S1 = np.uint64(1)
_S11 = np.uint64(11)
_MASK21 = np.uint64(0x1FFFFF)
_INV21 = 1.0 / 2097152.0
_INV53 = 1.0 / 9007199254740992.0

# Inner kernels allocate nothing: compiled without reference counting (_nrt=False), which
# otherwise costs atomic increments on every call that passes the context's arrays.
_JIT: dict[str, Any] = dict(cache=True, fastmath=True, error_model="numpy", _nrt=False)
_AJIT: dict[str, Any] = dict(cache=True, fastmath=True, error_model="numpy")          # allocating kernels
_PJIT: dict[str, Any] = dict(cache=True, fastmath=True, error_model="numpy", parallel=True)


@njit(inline="always", **_JIT)
def _mix(z):
    z = (z ^ (z >> _S30)) * _K2
    z = (z ^ (z >> _S27)) * _K3
    return z ^ (z >> _S31)


@njit(inline="always", **_JIT)
def _h4(a, b, c, salt):
    """64-bit hash of three integers and a salt."""
    h = _mix(np.uint64(salt) + _K1 * np.uint64(c + 1))
    h = _mix(h ^ (np.uint64(a) * _K2 + _K1))
    return _mix(h ^ (np.uint64(b) * _K3 + _K2))


@njit(inline="always", **_JIT)
def _f3(h):
    """Three independent fractions in [0, 1) from one 64-bit hash (21 bits each)."""
    return (float((h >> _S43) & _MASK21) * _INV21,
            float((h >> _S22) & _MASK21) * _INV21,
            float((h >> _S1) & _MASK21) * _INV21)


@njit(inline="always", **_JIT)
def _u01(h):
    return float(h >> _S11) * _INV53


@njit(inline="always", **_JIT)
def _lattice(x, y, salt, tag):
    """(x, y)'s place in its unit lattice cell and the cell's corner values in [0, 1]:
    (tx, ty, v00, v10, v01, v11)."""
    fx = math.floor(x)
    fy = math.floor(y)
    ix = np.int64(fx)
    iy = np.int64(fy)
    return (x - fx, y - fy, _u01(_h4(ix, iy, tag, salt)), _u01(_h4(ix + 1, iy, tag, salt)),
            _u01(_h4(ix, iy + 1, tag, salt)), _u01(_h4(ix + 1, iy + 1, tag, salt)))


@njit(**_JIT)
def _vnoise(x, y, salt, tag):
    """Value noise on the unit lattice, smoothstep interpolation, in [0, 1]."""
    tx, ty, v00, v10, v01, v11 = _lattice(x, y, salt, tag)
    sx = tx * tx * (3.0 - 2.0 * tx)
    sy = ty * ty * (3.0 - 2.0 * ty)
    a = v00 + (v10 - v00) * sx
    b = v01 + (v11 - v01) * sx
    return a + (b - a) * sy


@njit(**_JIT)
def _fbm(x, y, salt, tag, wl0, n_oct):
    """Multi-octave value noise, wavelengths wl0, wl0/2, ... ; result roughly in [0, 1]."""
    s = 0.0
    amp = 1.0
    tot = 0.0
    wl = wl0
    for k in range(n_oct):
        s += amp * _vnoise(x / wl + 0.37 * k, y / wl - 0.61 * k, salt, tag + 17 * k)
        tot += amp
        amp *= 0.62
        wl *= 0.5
    return s / tot


# ----------------------------------------------------------------------------------------
# Terrain: N_TER octaves of C2 value noise (amplitude, wavelength, offset x, offset y)
@njit(**_JIT)
def _vnoise_grad(x, y, salt, tag):
    """Value noise with quintic fade and its gradient (unit lattice): (v, dv/dx, dv/dy)."""
    tx, ty, v00, v10, v01, v11 = _lattice(x, y, salt, tag)
    sx = tx * tx * tx * (tx * (6.0 * tx - 15.0) + 10.0)
    sy = ty * ty * ty * (ty * (6.0 * ty - 15.0) + 10.0)
    dsx = 30.0 * tx * tx * (tx - 1.0) * (tx - 1.0)
    dsy = 30.0 * ty * ty * (ty - 1.0) * (ty - 1.0)
    a = v00 + (v10 - v00) * sx
    b = v01 + (v11 - v01) * sx
    return a + (b - a) * sy, ((v10 - v00) + (v11 - v01 - v10 + v00) * sy) * dsx, (b - a) * dsy


@njit(**_JIT)
def _terrain_grad(x, y, P, salt):
    """Terrain height and gradient at (x, y)."""
    t = P[I_H0]
    gx = 0.0
    gy = 0.0
    for k in range(N_TER):
        o = I_TER + 4 * k
        amp = P[o]
        wl = P[o + 1]
        v, dvx, dvy = _vnoise_grad(x / wl + P[o + 2], y / wl + P[o + 3], salt, 200 + k)
        t += amp * (2.0 * v - 1.0)
        gx += 2.0 * amp * dvx / wl
        gy += 2.0 * amp * dvy / wl
    return t, gx, gy


@njit(**_JIT)
def _terrain(x, y, P, salt):
    return _terrain_grad(x, y, P, salt)[0]


@njit(inline="always", **_JIT)
def _terrain_c(x, y, C):
    """Terrain height and gradient from the cached lattices (same values as _terrain_grad)."""
    P = C[0]
    TV = C[5]
    HDR = C[6]
    t = P[I_H0]
    gx = 0.0
    gy = 0.0
    n = TV.shape[1]
    for k in range(N_TER):
        o = I_TER + 4 * k
        amp = P[o]
        wl = P[o + 1]
        X = x / wl + P[o + 2]
        Y = y / wl + P[o + 3]
        fx = math.floor(X)
        fy = math.floor(Y)
        ix = min(max(np.int64(fx) - HDR[4 + 2 * k], 0), n - 2)
        iy = min(max(np.int64(fy) - HDR[5 + 2 * k], 0), n - 2)
        tx = X - fx
        ty = Y - fy
        sx = tx * tx * tx * (tx * (6.0 * tx - 15.0) + 10.0)
        sy = ty * ty * ty * (ty * (6.0 * ty - 15.0) + 10.0)
        dsx = 30.0 * tx * tx * (tx - 1.0) * (tx - 1.0)
        dsy = 30.0 * ty * ty * (ty - 1.0) * (ty - 1.0)
        v00 = TV[k, ix, iy]
        v10 = TV[k, ix + 1, iy]
        v01 = TV[k, ix, iy + 1]
        v11 = TV[k, ix + 1, iy + 1]
        a = v00 + (v10 - v00) * sx
        b = v01 + (v11 - v01) * sx
        t += amp * (2.0 * (a + (b - a) * sy) - 1.0)
        gx += 2.0 * amp * ((v10 - v00) + (v11 - v01 - v10 + v00) * sy) * dsx / wl
        gy += 2.0 * amp * (b - a) * dsy / wl
    return t, gx, gy


# ----------------------------------------------------------------------------------------
# Street grid and blocks (hash path)
@njit(**_JIT)
def _line(n, pitch, jit, salt, axis):
    """Centre position and width of street line n along one axis."""
    f1, f2, f3 = _f3(_h4(n, axis, 7, salt))
    pos = n * pitch + (2.0 * f1 - 1.0) * jit
    if f3 < 0.18:
        w = 13.0 + 2.0 * f2
    else:
        w = 8.0 + 3.5 * f2
    return pos, w


@njit(**_JIT)
def _block_type(i, j, P, salt):
    f1, f2, f3 = _f3(_h4(i, j, 21, salt))
    if f1 < P[I_PARK]:
        return B_PARK, f2, f3
    if f1 < P[I_PARK] + P[I_OPEN]:
        return B_OPEN, f2, f3
    return B_BUILT, f2, f3


@njit(**_JIT)
def _shrink(lo, hi, s0, s1, min_size):
    """Apply setbacks s0, s1 to [lo, hi] keeping at least min_size (when possible)."""
    avail = (hi - lo) - min_size
    if avail <= 0.0:
        return lo, hi
    tot = s0 + s1
    if tot > avail:
        sc = avail / tot
        s0 *= sc
        s1 *= sc
    return lo + s0, hi - s1


@njit(**_JIT)
def _building_rect(i, j, k, A0, A1, B0, B1, salt):
    """Footprint of building k (0 or 1) of built block (i, j) in (u, v); valid flag first.

    (A0, A1, B0, B1) is the block's interior inside the sidewalks."""
    fnb, fsplit, fgap = _f3(_h4(i, j, 22, salt))
    lu = A1 - A0
    lv = B1 - B0
    if lu < 6.0 or lv < 6.0:
        return False, 0.0, 0.0, 0.0, 0.0
    nb = 1
    if fnb < 0.65 and max(lu, lv) > 34.0:
        nb = 2
    if k >= nb:
        return False, 0.0, 0.0, 0.0, 0.0
    u0, u1, v0, v1 = A0, A1, B0, B1
    if nb == 2:
        gap = 3.0 + 7.0 * fgap
        if lu >= lv:
            m = A0 + (0.35 + 0.3 * fsplit) * lu
            if k == 0:
                u1 = m - 0.5 * gap
            else:
                u0 = m + 0.5 * gap
        else:
            m = B0 + (0.35 + 0.3 * fsplit) * lv
            if k == 0:
                v1 = m - 0.5 * gap
            else:
                v0 = m + 0.5 * gap
    s1, s2, s3 = _f3(_h4(i, j, 30 + k, salt))
    s4, _, _ = _f3(_h4(i, j, 35 + k, salt))
    u0, u1 = _shrink(u0, u1, 0.5 + 8.0 * s1 * s1, 0.5 + 8.0 * s2 * s2, 8.0)
    v0, v1 = _shrink(v0, v1, 0.5 + 8.0 * s3 * s3, 0.5 + 8.0 * s4 * s4, 8.0)
    return True, u0, u1, v0, v1


@njit(**_JIT)
def _fill_block(i, j, a0, a1, b0, b1, P, salt, rec):
    """Compute the record of block (i, j) (street-bounded rectangle [a0,a1] x [b0,b1] in u, v)."""
    bt, f2, f3 = _block_type(i, j, P, salt)
    rec[:] = 0.0
    rec[R_TYPE] = bt
    rec[R_F2] = f2
    rec[R_F3] = f3
    if bt != B_BUILT:
        return
    sw = P[I_SW]
    c = P[I_COS]
    s = P[I_SIN]
    nb = 0
    for k in range(2):
        ok, u0, u1, v0, v1 = _building_rect(i, j, k, a0 + sw, a1 - sw, b0 + sw, b1 - sw, salt)
        if not ok:
            break
        o = 4 + NBF * k
        rec[o + F_U0] = u0
        rec[o + F_U1] = u1
        rec[o + F_V0] = v0
        rec[o + F_V1] = v1
        fh, frt, fdir = _f3(_h4(i, j, 40 + k, salt))
        fp, fpar, fbox = _f3(_h4(i, j, 50 + k, salt))
        uc = 0.5 * (u0 + u1)
        vc = 0.5 * (v0 + v1)
        tall = _vnoise(uc / 450.0, vc / 450.0, salt, 5) * P[I_TALL]
        e = 3.6 - 2.2 * tall
        hb = 3.0 + 37.0 * fh ** e
        rt = 0
        if hb < 16.0:
            if frt < 0.4:
                rt = 0
            elif frt < 0.75:
                rt = 1
            else:
                rt = 2
        rec[o + F_HB] = hb
        rec[o + F_RT] = rt
        rec[o + F_ALONGU] = 1.0 if fdir < 0.5 else 0.0
        rec[o + F_TANP] = math.tan(math.radians(20.0 + 18.0 * fp))
        rec[o + F_PAR] = 0.6 + 0.6 * fpar if (rt == 0 and fpar < 0.5) else 0.0
        box = rt == 0 and fbox < 0.6 and (u1 - u0) > 12.0 and (v1 - v0) > 12.0
        rec[o + F_BOX] = 1.0 if box else 0.0
        if box:
            fbu, fbv, fbs = _f3(_h4(i, j, 60 + k, salt))
            bsu = 2.5 + 4.0 * fbs
            bsv = 2.5 + 3.5 * (1.0 - fbs)
            rec[o + F_BU0] = u0 + 2.0 + fbu * (u1 - u0 - 4.0 - bsu)
            rec[o + F_BV0] = v0 + 2.0 + fbv * (v1 - v0 - 4.0 - bsv)
            rec[o + F_BSU] = bsu
            rec[o + F_BSV] = bsv
            rec[o + F_BH] = 1.6 + 1.8 * fbs
        rec[o + F_FOUND] = _terrain(c * uc - s * vc, s * uc + c * vc, P, salt)
        f1t, _, _ = _f3(_h4(i, j, 70 + k, salt))
        rec[o + F_TONE] = f1t
        nb += 1
    rec[R_NB] = nb


# ----------------------------------------------------------------------------------------
# Cached access. Context C = (P, LU, LV, TB, TT, TV, HDR, salt):
#   LU (nu, 2), LV (nv, 2): street lines (position, width) from index HDR[0] (u), HDR[1] (v);
#   TB (nu-1, nv-1, NREC): block records of blocks (HDR[0] + a, HDR[1] + b);
#   TT (na, nb, NTT): lattice tree cells (HDR[2] + a, HDR[3] + b);
#   TV (N_TER, n, n): terrain value-noise lattices, octave k from (HDR[4+2k], HDR[5+2k]).
# Every cached value is computed by the hash functions below: results are bit-identical.
@njit(inline="always", **_JIT)
def _line_c(n, C, axis):
    """Cached street line n (position, width). The Python side guarantees coverage (see
    SceneModel.ensure_tables); indices are clamped for memory safety only."""
    if axis == 0:
        T = C[1]
        k = min(max(n - C[6][0], 0), T.shape[0] - 1)
    else:
        T = C[2]
        k = min(max(n - C[6][1], 0), T.shape[0] - 1)
    return T[k, 0], T[k, 1]


@njit(inline="always", **_JIT)
def _axis(u, C, axis):
    """Block index i along one axis with its bounding street lines: (i, U_i, w_i, U_i+1, w_i+1)."""
    pitch = C[0][I_PU] if axis == 0 else C[0][I_PV]
    k = np.int64(math.floor(u / pitch))
    uk, wk = _line_c(k, C, axis)
    if u < uk:
        u0, w0 = _line_c(k - 1, C, axis)
        return k - 1, u0, w0, uk, wk
    u1, w1 = _line_c(k + 1, C, axis)
    if u >= u1:
        u2, w2 = _line_c(k + 2, C, axis)
        return k + 1, u1, w1, u2, w2
    return k, uk, wk, u1, w1


@njit(inline="always", **_JIT)
def _bidx(i, j, C):
    """Indices of block (i, j) in the cache (clamped: coverage is guaranteed by the caller)."""
    TB = C[3]
    return (min(max(i - C[6][0], 0), TB.shape[0] - 1),
            min(max(j - C[6][1], 0), TB.shape[1] - 1))


@njit(**_AJIT)
def build_tree_table(C, a0, na, b0, nb):
    """Tree cells (a0 + a, b0 + b) with the `allowed` flag (needs the block tables in C)."""
    salt = C[7]
    TT = np.zeros((na, nb, NTT))
    for a in range(na):
        for b in range(nb):
            cx, cy, R, Ht, depth, ell, fe, fs = _tree_cell(a0 + a, b0 + b, salt)
            TT[a, b, 0] = cx
            TT[a, b, 1] = cy
            TT[a, b, 2] = R
            TT[a, b, 3] = Ht
            TT[a, b, 4] = depth
            TT[a, b, 5] = 1.0 if ell else 0.0
            TT[a, b, 6] = 1.0 if _lattice_tree_allowed(cx, cy, fe, C) else 0.0
            TT[a, b, 7] = fs
    return TT


@njit(**_AJIT)
def build_terrain_table(salt, x0, y0, n):
    """Value-noise lattice of the terrain octaves: TV[k, i, j] = value at (x0[k] + i, y0[k] + j)."""
    TV = np.zeros((N_TER, n, n))
    for k in range(N_TER):
        for i in range(n):
            for j in range(n):
                TV[k, i, j] = _u01(_h4(x0[k] + i, y0[k] + j, 200 + k, salt))
    return TV


@njit(**_AJIT)
def build_tables(P, salt, iu0, nu, jv0, nv):
    """Cache of street lines iu0..iu0+nu-1 (u) and jv0..jv0+nv-1 (v) and of their blocks."""
    LU = np.empty((nu, 2))
    LV = np.empty((nv, 2))
    for k in range(nu):
        LU[k, 0], LU[k, 1] = _line(iu0 + k, P[I_PU], P[I_JU], salt, 0)
    for k in range(nv):
        LV[k, 0], LV[k, 1] = _line(jv0 + k, P[I_PV], P[I_JV], salt, 1)
    TB = np.zeros((max(nu - 1, 0), max(nv - 1, 0), NREC))
    for a in range(nu - 1):
        a0 = LU[a, 0] + 0.5 * LU[a, 1]
        a1 = LU[a + 1, 0] - 0.5 * LU[a + 1, 1]
        for b in range(nv - 1):
            b0 = LV[b, 0] + 0.5 * LV[b, 1]
            b1 = LV[b + 1, 0] - 0.5 * LV[b + 1, 1]
            _fill_block(iu0 + a, jv0 + b, a0, a1, b0, b1, P, salt, TB[a, b])
    return LU, LV, TB


@njit(**_JIT)
def _find_building(u, v, TB, bi, bj, dil):
    """Record offset of the building of block (bi, bj) containing (u, v) (footprint dilated
    by dil), or -1."""
    for k in range(int(TB[bi, bj, R_NB])):
        o = 4 + NBF * k
        if (TB[bi, bj, o + F_U0] - dil <= u <= TB[bi, bj, o + F_U1] + dil
                and TB[bi, bj, o + F_V0] - dil <= v <= TB[bi, bj, o + F_V1] + dil):
            return o
    return -1


@njit(**_JIT)
def _roof(u, v, TB, bi, bj, o):
    """Roof height above the foundation at (u, v): (z, dz/du, dz/dv, material, aux)."""
    u0 = TB[bi, bj, o + F_U0]
    u1 = TB[bi, bj, o + F_U1]
    v0 = TB[bi, bj, o + F_V0]
    v1 = TB[bi, bj, o + F_V1]
    hb = TB[bi, bj, o + F_HB]
    rt = int(TB[bi, bj, o + F_RT])
    cap = 5.0
    if rt == 0:
        par = TB[bi, bj, o + F_PAR]
        if par > 0.0 and min(min(u - u0, u1 - u), min(v - v0, v1 - v)) < 0.4:
            return hb + par, 0.0, 0.0, M_PARAPET, 0.0
        if TB[bi, bj, o + F_BOX] > 0.0:
            bu0 = TB[bi, bj, o + F_BU0]
            bv0 = TB[bi, bj, o + F_BV0]
            if bu0 <= u <= bu0 + TB[bi, bj, o + F_BSU] and bv0 <= v <= bv0 + TB[bi, bj, o + F_BSV]:
                return hb + TB[bi, bj, o + F_BH], 0.0, 0.0, M_ROOFBOX, 0.0
        return hb, 0.0, 0.0, M_ROOF, 0.0
    tanp = TB[bi, bj, o + F_TANP]
    du = u - 0.5 * (u0 + u1)
    dv = v - 0.5 * (v0 + v1)
    hu = 0.5 * (u1 - u0)
    hv = 0.5 * (v1 - v0)
    if rt == 1:
        if TB[bi, bj, o + F_ALONGU] > 0.0:
            d = hv - abs(dv)
            if d * tanp >= cap:
                return hb + cap, 0.0, 0.0, M_ROOF, d
            return hb + d * tanp, 0.0, -math.copysign(tanp, dv), M_ROOF, d
        d = hu - abs(du)
        if d * tanp >= cap:
            return hb + cap, 0.0, 0.0, M_ROOF, d
        return hb + d * tanp, -math.copysign(tanp, du), 0.0, M_ROOF, d
    d1 = hu - abs(du)
    d2 = hv - abs(dv)
    if d1 < d2:
        d = d1
        gu = -math.copysign(tanp, du)
        gv = 0.0
    else:
        d = d2
        gu = 0.0
        gv = -math.copysign(tanp, dv)
    if d * tanp >= cap:
        return hb + cap, 0.0, 0.0, M_ROOF, d
    return hb + d * tanp, gu, gv, M_ROOF, d


# ----------------------------------------------------------------------------------------
# Trees
@njit(inline="always", **_JIT)
def _crown(r2, R, depth, ellipsoid):
    """Crown surface height relative to its top and d(height)/d(r^2) (negative)."""
    q2 = r2 / (R * R)
    if ellipsoid:
        q2 = min(q2, 0.995)
        s = math.sqrt(1.0 - q2)
        return depth * (s - 1.0), -0.5 * depth / (R * R * s)
    return -depth * q2, -depth / (R * R)


@njit(inline="always", **_JIT)
def _block_of(x, y, C):
    """Street-grid coordinates of (x, y): u, v; the block indices i, j; its two bounding street
    lines along each axis (centre, width); the block's inner edges a0 < a1 (u), b0 < b1 (v)."""
    P = C[0]
    c = P[I_COS]
    s = P[I_SIN]
    u = c * x + s * y
    v = -s * x + c * y
    i, U0, w0, U1, w1 = _axis(u, C, 0)
    j, V0, z0, V1, z1 = _axis(v, C, 1)
    return (u, v, i, j, U0, w0, U1, w1, V0, z0, V1, z1,
            U0 + 0.5 * w0, U1 - 0.5 * w1, V0 + 0.5 * z0, V1 - 0.5 * z1)


@njit(**_JIT)
def _lattice_tree_allowed(cx, cy, fexist, C):
    P = C[0]
    u, v, i, j, U0, w0, U1, w1, V0, z0, V1, z1, a0, a1, b0, b1 = _block_of(cx, cy, C)
    de = min(min(u - a0, a1 - u), min(v - b0, b1 - v))
    if de < P[I_SW] + 1.0:
        return False                      # roads, sidewalks (street trees are separate)
    bi, bj = _bidx(i, j, C)
    TB = C[3]
    bt = int(TB[bi, bj, R_TYPE])
    if bt == B_PARK:
        return fexist < 0.6
    if bt == B_OPEN:
        return fexist < 0.07
    if fexist >= 0.3:
        return False
    return _find_building(u, v, TB, bi, bj, 1.5) < 0


NTT = 8    # tree cell record: cx, cy, R, Ht, depth, ellipsoid, allowed, tone


@njit(**_JIT)
def _tree_cell(a, b, salt):
    """Lattice tree candidate of cell (a, b): (cx, cy, R, Ht, depth, ellipsoid, fexist, tone)."""
    T = TREE_PITCH
    f1, f2, f3 = _f3(_h4(a, b, 90, salt))
    R = 2.0 + 2.0 * f3
    fe, fH, fs = _f3(_h4(a, b, 91, salt))
    Ht = 5.0 + 7.0 * fH
    return ((a + 0.1 + 0.8 * f1) * T, (b + 0.1 + 0.8 * f2) * T, R, Ht,
            min(Ht - 1.8, R * (1.0 + 0.8 * fs)), fs < 0.5, fe, fs)


@njit(**_JIT)
def _lattice_trees(x, y, t, best, C, full):
    """Raise `best` to the crowns of the jittered-lattice trees covering (x, y).

    Crowns stand on the terrain height t at the point (a sub-decimetre approximation of the
    terrain at the trunk). Uses the cached tree cells. Returns (h, dh/dx, dh/dy, hit, tone)."""
    TT = C[4]
    HDR = C[6]
    T = TREE_PITCH
    fx = math.floor(x / T)
    fy = math.floor(y / T)
    ax = np.int64(fx) - HDR[2]
    ay = np.int64(fy) - HDR[3]
    gx = 0.0
    gy = 0.0
    hit = False
    tone = 0.0
    # neighbour cells whose tree area [0.1 T, 0.9 T] lies within the max crown radius (4 m)
    reach = 4.0 - 0.1 * T
    ox = x - fx * T
    oy = y - fy * T
    da0 = -1 if ox < reach else 0
    da1 = 1 if T - ox < reach else 0
    db0 = -1 if oy < reach else 0
    db1 = 1 if T - oy < reach else 0
    na = TT.shape[0]
    nb = TT.shape[1]
    for da in range(da0, da1 + 1):
        a = min(max(ax + da, 0), na - 1)
        for db in range(db0, db1 + 1):
            b = min(max(ay + db, 0), nb - 1)
            if TT[a, b, 6] == 0.0:
                continue
            R = TT[a, b, 2]
            dx = x - TT[a, b, 0]
            dy = y - TT[a, b, 1]
            r2 = dx * dx + dy * dy
            if r2 >= R * R:
                continue
            top = t + TT[a, b, 3]
            if top <= best:
                continue
            dz, dr2 = _crown(r2, R, TT[a, b, 4], TT[a, b, 5] > 0.0)
            z = top + dz
            if z <= best:
                continue
            best = z
            hit = True
            if full:
                gx = dr2 * 2.0 * dx
                gy = dr2 * 2.0 * dy
                tone = TT[a, b, 7]
    return best, gx, gy, hit, tone


@njit(**_JIT)
def _street_tree_row(ua, va, row_pos, line, side, axis, t, best, C, full):
    """Trees of one sidewalk row; the row runs along the other axis at `row_pos` on this axis.

    (ua, va): point coordinates across/along the row. Returns (h, d/dacross, d/dalong, hit, tone).
    """
    d_across = ua - row_pos
    if abs(d_across) >= 3.5:
        return best, 0.0, 0.0, False, 0.0
    salt = C[7]
    k = np.int64(math.floor(va / STREET_TREE_STEP + 0.5))
    fr, fR, fH = _f3(_h4(line * 2 + side, k, 100 + axis, salt))
    R = 1.8 + 1.7 * fR
    along = va - k * STREET_TREE_STEP
    r2 = d_across * d_across + along * along
    if r2 >= R * R:
        return best, 0.0, 0.0, False, 0.0
    row_on, _, _ = _f3(_h4(line, side, 102 + axis, salt))
    if row_on >= 0.45 or fr >= 0.85:
        return best, 0.0, 0.0, False, 0.0
    Ht = 5.0 + 5.0 * fH
    depth = min(Ht - 2.0, R * 1.3)
    top = t + Ht
    if top <= best:
        return best, 0.0, 0.0, False, 0.0
    dz, dr2 = _crown(r2, R, depth, fR < 0.4)
    z = top + dz
    if z <= best:
        return best, 0.0, 0.0, False, 0.0
    # the tree must stand along a block's side, not in an intersection
    pos_along = k * STREET_TREE_STEP
    _, V0, z0, V1, z1 = _axis(pos_along, C, 1 - axis)
    if pos_along < V0 + 0.5 * z0 + 2.0 or pos_along > V1 - 0.5 * z1 - 2.0:
        return best, 0.0, 0.0, False, 0.0
    if full:
        return z, dr2 * 2.0 * d_across, dr2 * 2.0 * along, True, 0.6 + 0.4 * fH
    return z, 0.0, 0.0, True, 0.0


# ----------------------------------------------------------------------------------------
# Road markings
@njit(**_JIT)
def _road_material(across, half_w, along, dist_int, line, blk, axis, salt):
    """Material of a road point in a street segment (not an intersection)."""
    aa = abs(across)
    if half_w >= 4.5 and aa < 0.1 and (along / 8.0 - math.floor(along / 8.0)) < 0.45:
        return M_MARK
    if abs(aa - (half_w - 0.6)) < 0.08:
        return M_MARK
    fz, fs, _ = _f3(_h4(line, blk, 110 + axis, salt))
    if fz < 0.55 and 0.8 < dist_int < 3.8 and aa < half_w - 0.3:
        t = (across + half_w) / 1.0
        if t - math.floor(t) < 0.5:
            return M_MARK
    if fs < 0.7 and 4.3 < dist_int < 4.7 and 0.2 < across < half_w - 0.3:
        return M_MARK
    return M_ROAD


# ----------------------------------------------------------------------------------------
# Scene evaluation
@njit(inline="always", **_JIT)
def _tree_rows(a, b, rows, lines, axis, t, h, gx, gy, mat, tone, aux, C, full, c, s, tgx, tgy):
    """The four street-tree rows along one street axis (axis 0: across = u, along = v; axis 1:
    across = v, along = u): the highest tree crown at (a, b) wins; gradients rotated to x, y."""
    sides = (1, 0, 0, 1)
    for r in range(4):
        if abs(a - rows[r]) >= 3.5:
            continue
        best, da, dl, hit, ttone = _street_tree_row(a, b, rows[r], lines[r], sides[r], axis,
                                                    t, h, C, full)
        if hit:
            h = best
            mat = M_TREE
            tone = ttone
            aux = 0.0
            gu, gv = (da, dl) if axis == 0 else (dl, da)
            gx = tgx + gu * c - gv * s
            gy = tgy + gu * s + gv * c
    return h, gx, gy, mat, tone, aux


@njit(**_JIT)
def scene_eval(x, y, C, full):
    """Height field at (x, y) (scene-local metres).

    Returns (h, dh/dx, dh/dy, material, tone, aux). Gradient and material are only meaningful
    when `full` is True (height-only evaluation skips some of them). `tone` is a per-object
    constant in [0, 1] (building, tree), `aux` a material-specific coordinate (distance from
    the eave for pitched roofs).

    Tree look-ups are skipped where no crown can reach: lattice trees stand >= sw + 1 m inside
    a block and >= 1.5 m from buildings with crowns <= 4 m, so they reach <= 0.5 m into streets
    and <= 2.5 m into a building footprint; street-tree crowns (<= 3.5 m) are tested only
    within 3.5 m of their row. The terrain is not evaluated on roofs unless trees are.
    """
    P = C[0]
    salt = C[7]
    c = P[I_COS]
    s = P[I_SIN]
    u, v, i, j, U0, w0, U1, w1, V0, z0, V1, z1, a0, a1, b0, b1 = _block_of(x, y, C)
    sw = P[I_SW]
    in_su = u < a0 or u > a1
    in_sv = v < b0 or v > b1
    h = 0.0
    gx = 0.0
    gy = 0.0
    mat = M_ROAD
    tone = 0.0
    aux = 0.0
    # classification: 0 street, 1 sidewalk, 2 roof, 3 ground inside a block
    kind = 0
    lattice = True
    bi = 0
    bj = 0
    o = -1
    if in_su or in_sv:
        # distance to the nearest curb across the street(s) the point is in
        cd = 0.0
        if in_su:
            cd = max(cd, min(a0 - u, u - (U0 - 0.5 * w0)) if u < a0 else min(u - a1, (U1 + 0.5 * w1) - u))
        if in_sv:
            cd = max(cd, min(b0 - v, v - (V0 - 0.5 * z0)) if v < b0 else min(v - b1, (V1 + 0.5 * z1) - v))
        lattice = cd <= 0.5
    elif min(min(u - a0, a1 - u), min(v - b0, b1 - v)) < sw:
        kind = 1
    else:
        bi, bj = _bidx(i, j, C)
        kind = 3
        if int(C[3][bi, bj, R_TYPE]) == B_BUILT:
            o = _find_building(u, v, C[3], bi, bj, 0.0)
            if o >= 0:
                kind = 2
    # street tree rows (positions across u: rows along v; across v: rows along u)
    hs = 0.5 * sw
    ru0 = a0 + hs
    ru1 = a1 - hs
    ru2 = U0 - 0.5 * w0 - hs
    ru3 = U1 + 0.5 * w1 + hs
    rv0 = b0 + hs
    rv1 = b1 - hs
    rv2 = V0 - 0.5 * z0 - hs
    rv3 = V1 + 0.5 * z1 + hs
    near_u = min(min(abs(u - ru0), abs(u - ru1)), min(abs(u - ru2), abs(u - ru3))) < 3.5
    near_v = min(min(abs(v - rv0), abs(v - rv1)), min(abs(v - rv2), abs(v - rv3))) < 3.5
    TB = C[3]
    if kind == 2:
        z, gu, gv, m, ax_ = _roof(u, v, TB, bi, bj, o)
        depth_in = min(min(u - TB[bi, bj, o + F_U0], TB[bi, bj, o + F_U1] - u),
                       min(v - TB[bi, bj, o + F_V0], TB[bi, bj, o + F_V1] - v))
        lattice = depth_in <= 2.5
        h = TB[bi, bj, o + F_FOUND] + z
        mat = m
        aux = ax_
        gx = gu * c - gv * s
        gy = gu * s + gv * c
        tone = TB[bi, bj, o + F_TONE]
        if not (lattice or near_u or near_v):
            return h, gx, gy, mat, tone, aux
    t, tgx, tgy = _terrain_c(x, y, C)
    if kind != 2:
        h = t
        gx = tgx
        gy = tgy
        mat = M_ROAD
        tone = 0.0
        aux = 0.0
        if kind == 0:
            if full and not (in_su and in_sv):
                if in_su:
                    if u < a0:
                        mat = _road_material(u - U0, 0.5 * w0, v, min(v - b0, b1 - v), i, j, 0, salt)
                    else:
                        mat = _road_material(u - U1, 0.5 * w1, v, min(v - b0, b1 - v), i + 1, j, 0, salt)
                else:
                    if v < b0:
                        mat = _road_material(v - V0, 0.5 * z0, u, min(u - a0, a1 - u), j, i, 1, salt)
                    else:
                        mat = _road_material(v - V1, 0.5 * z1, u, min(u - a0, a1 - u), j + 1, i, 1, salt)
        elif kind == 1:
            h = t + CURB
            mat = M_SIDEWALK
        else:
            bt = int(TB[bi, bj, R_TYPE])
            if bt == B_PARK:
                mat = M_GRASS
                if full:
                    if abs(u - 0.5 * (a0 + a1)) < 1.2 or abs(v - 0.5 * (b0 + b1)) < 1.2:
                        mat = M_PATH
            elif bt == B_OPEN:
                if TB[bi, bj, R_F2] < 0.5:
                    mat = M_SOIL
                else:
                    mat = M_PARKING
                    if full:
                        q = (v - b0) / 2.6
                        r = (u - a0 - sw) / 14.0
                        fr = r - math.floor(r)
                        if q - math.floor(q) < 0.06 and (0.05 < fr < 0.4 or 0.6 < fr < 0.95):
                            mat = M_MARK
            else:
                mat = M_GRASS if TB[bi, bj, R_F3] < 0.5 else M_SOIL
        if not (lattice or near_u or near_v):
            return h, gx, gy, mat, tone, aux
    if lattice:
        best, tgx2, tgy2, hit, ttone = _lattice_trees(x, y, t, h, C, full)
        if hit:
            h = best
            gx = tgx + tgx2
            gy = tgy + tgy2
            mat = M_TREE
            tone = ttone
            aux = 0.0
    if near_u:          # rows along v, across u
        h, gx, gy, mat, tone, aux = _tree_rows(u, v, (ru0, ru1, ru2, ru3), (i, i + 1, i, i + 1), 0, t,
                                               h, gx, gy, mat, tone, aux, C, full, c, s, tgx, tgy)
    if near_v:          # rows along u, across v
        h, gx, gy, mat, tone, aux = _tree_rows(v, u, (rv0, rv1, rv2, rv3), (j, j + 1, j, j + 1), 1, t,
                                               h, gx, gy, mat, tone, aux, C, full, c, s, tgx, tgy)
    return h, gx, gy, mat, tone, aux


@njit(inline="always", **_JIT)
def _H(x, y, C):
    return scene_eval(x, y, C, False)[0]


# Parallel kernels: each prange iteration calls one non-NRT worker on a whole chunk, so that
# the context's arrays are not reference-counted per point (atomic contention between threads).
CHUNK = 4096


@njit(**_JIT)
def _height_chunk(x, y, out, k0, k1, C):
    for k in range(k0, k1):
        out[k] = scene_eval(x[k], y[k], C, False)[0]


@njit(**_PJIT)
def height_points(x, y, C):
    """H at points: x, y (n,) -> (n,) float64."""
    n = x.shape[0]
    out = np.empty(n)
    nch = (n + CHUNK - 1) // CHUNK
    for q in prange(nch):
        _height_chunk(x, y, out, q * CHUNK, min(n, (q + 1) * CHUNK), C)
    return out


@njit(**_JIT)
def _eval_chunk(x, y, out, k0, k1, C):
    for k in range(k0, k1):
        h, gx, gy, mat, tone, aux = scene_eval(x[k], y[k], C, True)
        out[k, 0] = h
        out[k, 1] = gx
        out[k, 2] = gy
        out[k, 3] = mat
        out[k, 4] = tone
        out[k, 5] = aux


@njit(**_PJIT)
def eval_points(x, y, C):
    """Full evaluation at points: (n,) -> (n, 6) [h, dh/dx, dh/dy, material, tone, aux]."""
    n = x.shape[0]
    out = np.empty((n, 6))
    nch = (n + CHUNK - 1) // CHUNK
    for q in prange(nch):
        _eval_chunk(x, y, out, q * CHUNK, min(n, (q + 1) * CHUNK), C)
    return out


@njit(**_JIT)
def _grid_row(x0, yy, dx, nx, out, r, C):
    for c in range(nx):
        out[r, c] = scene_eval(x0 + c * dx, yy, C, False)[0]


@njit(**_PJIT)
def height_grid(x0, y0, dx, dy, nx, ny, C):
    """H on a regular grid: sample (r, c) at (x0 + c dx, y0 + r dy) -> (ny, nx) float32."""
    out = np.empty((ny, nx), dtype=np.float32)
    for r in prange(ny):
        _grid_row(x0, y0 + r * dy, dx, nx, out, r, C)
    return out


# ----------------------------------------------------------------------------------------
# Acceleration grid: conservative per-cell maxima
@njit(**_JIT)
def _pool_max(samples, m, out, margin):
    """out[r, c] = max(samples[r*m : r*m + m + 3, c*m : c*m + m + 3]) + margin."""
    ny, nx = out.shape
    for r in range(ny):
        for c in range(nx):
            mx = -1e30
            for a in range(r * m, r * m + m + 3):
                for b in range(c * m, c * m + m + 3):
                    if samples[a, b] > mx:
                        mx = samples[a, b]
            out[r, c] = mx + margin


@dataclass
class AccelGrid:
    """Per-cell conservative maxima of H over a rectangle of the scene-local plane.

    Cell (r, c) covers x in [x0 + c cs, x0 + (c+1) cs], y in [y0 + r cs, y0 + (r+1) cs].
    `hmin`/`hmax` bound H over the grid (hmax = max of the cell maxima).
    """

    x0: float
    y0: float
    cs: float
    cellmax: np.ndarray = field(repr=False)
    hmin: float
    hmax: float


SAMPLE_STEP = 0.25
ACCEL_MARGIN = 0.2


def build_accel(C: tuple, x0: float, y0: float, x1: float, y1: float, cs: float = 1.0,
                sample_step: float = SAMPLE_STEP, strip_cells: int = 32,
                progress=None) -> AccelGrid:
    """Coarse max grid over [x0, x1] x [y0, y1] (scene-local metres).

    H is sampled every `sample_step` (0.25 m); a cell's maximum is the max of the samples in
    the cell dilated by one sample step, plus a margin: every point of the cell is within
    0.18 m of a sample of the dilated set that is at least as high up to the local slope
    (roofs <= 38 degrees: < 0.14 m; crown apexes: < 0.08 m; building edges are
    discontinuities whose high side is sampled), so the bound holds with a 0.2 m margin
    (0.4 m with 0.5 m sampling). Computed in strips (bounded memory).
    """
    m = max(1, int(round(cs / sample_step)))
    cs = m * sample_step
    margin = ACCEL_MARGIN if sample_step <= 0.25 else 0.4 * sample_step / 0.5
    nx = int(math.ceil((x1 - x0) / cs))
    ny = int(math.ceil((y1 - y0) / cs))
    cellmax = np.empty((ny, nx), dtype=np.float32)
    hmin = np.inf
    nstrips = (ny + strip_cells - 1) // strip_cells
    for k, r0 in enumerate(range(0, ny, strip_cells)):
        r1 = min(ny, r0 + strip_cells)
        ns_y = (r1 - r0) * m + 3
        ns_x = nx * m + 3
        samples = height_grid(x0 - sample_step, y0 + (r0 * m - 1) * sample_step, sample_step,
                              sample_step, ns_x, ns_y, C)
        _pool_max(samples, m, cellmax[r0:r1], margin)
        hmin = min(hmin, float(samples.min()))
        if progress is not None:
            progress(k + 1, nstrips)
    return AccelGrid(x0=float(x0), y0=float(y0), cs=float(cs), cellmax=cellmax,
                     hmin=hmin, hmax=float(cellmax.max()))


# ----------------------------------------------------------------------------------------
# Ray marching
STEP = 0.1            # horizontal step of the fine march (m)
SHADOW_STEP = 0.25    # horizontal step of the shadow march (m)
COARSE_TOL = 0.01     # bisection down to 1 cm, then secant (smooth) or more bisection (wall)
TOL = 1e-3            # final bracket for walls (m)
WALL_JUMP = 0.05      # a jump of H larger than this inside the final bracket is a wall


@njit(**_JIT)
def _dda_init(f, d, cs):
    """2D DDA set-up along one axis: (step sign, parameter of the first boundary, increment)."""
    i = math.floor(f)
    if d > 0.0:
        return 1, (i + 1 - f) * cs / d, cs / d
    if d < 0.0:
        return -1, (f - i) * cs / (-d), cs / (-d)
    return 0, np.inf, np.inf


@njit(inline="always", **_JIT)
def _dda_start(x, y, dx, dy, gx0, gy0, cs):
    """The grid cell of (x, y) and the DDA set-up of both axes for the direction (dx, dy):
    (ix, iy, stx, tmx, tdx, sty, tmy, tdy)."""
    fx = (x - gx0) / cs
    fy = (y - gy0) / cs
    stx, tmx, tdx = _dda_init(fx, dx, cs)
    sty, tmy, tdy = _dda_init(fy, dy, cs)
    return np.int64(math.floor(fx)), np.int64(math.floor(fy)), stx, tmx, tdx, sty, tmy, tdy


@njit(inline="always", **_JIT)
def _cell_max(grid, ix, iy):
    """The highest surface in a cell (infinite outside the grid: nothing passes there)."""
    ny, nx = grid.shape
    if 0 <= ix < nx and 0 <= iy < ny:
        return grid[iy, ix]
    return np.inf


@njit(inline="always", **_JIT)
def _dda_next(ix, iy, stx, sty, tmx, tmy, tdx, tdy):
    """One DDA step into the next cell the segment enters: (ix, iy, s_in, tmx, tmy)."""
    if tmx < tmy:
        return ix + stx, iy, tmx, tmx + tdx, tmy
    return ix, iy + sty, tmy, tmx, tmy + tdy


@njit(**_JIT)
def _march(tx, ty, tz, bx, by, bz, C, grid, gx0, gy0, cs, step):
    """First crossing of the segment T -> B (T above all surfaces, B below) with the surface.

    Returns (status, x, y, z): status 0 = miss, 1 = surface hit, 2 = wall hit (the segment
    crossed a discontinuity of H: the point is on the vertical face).
    """
    dx = bx - tx
    dy = by - ty
    dz = bz - tz
    L = math.sqrt(dx * dx + dy * dy)
    ix, iy, stx, tmx, tdx, sty, tmy, tdy = _dda_start(tx, ty, dx, dy, gx0, gy0, cs)
    ds = step / L if L > 1e-12 else 2.0
    s_in = 0.0
    while True:
        s_out = min(min(tmx, tmy), 1.0)
        cm = _cell_max(grid, ix, iy)
        if tz + dz * s_out <= cm:
            z_in = tz + dz * s_in
            s = s_in if z_in <= cm else (cm - tz) / dz
            f = (tz + dz * s) - _H(tx + dx * s, ty + dy * s, C)
            if f <= 0.0:
                return 1, tx + dx * s, ty + dy * s, tz + dz * s
            while s < s_out:
                s_n = min(s + ds, s_out)
                f_n = (tz + dz * s_n) - _H(tx + dx * s_n, ty + dy * s_n, C)
                if f_n <= 0.0:
                    return _refine(s, f, s_n, f_n, tx, ty, tz, dx, dy, dz, L, C)
                s = s_n
                f = f_n
        if s_out >= 1.0:
            break
        ix, iy, s_in, tmx, tmy = _dda_next(ix, iy, stx, sty, tmx, tmy, tdx, tdy)
    return 0, bx, by, bz


@njit(inline="always", **_JIT)
def _bisect(s_lo, f_lo, s_hi, f_hi, tx, ty, tz, dx, dy, dz, scale, tol, C):
    """Halve the bracket [s_lo, s_hi] of the ray's crossing of the surface (f = ray height - H,
    f_lo > 0 >= f_hi) until it is shorter than tol (in metres along the ray)."""
    for _ in range(60):
        if (s_hi - s_lo) * scale <= tol:
            break
        s_m = 0.5 * (s_lo + s_hi)
        f_m = (tz + dz * s_m) - _H(tx + dx * s_m, ty + dy * s_m, C)
        s_lo, f_lo, s_hi, f_hi = _split(s_lo, f_lo, s_hi, f_hi, s_m, f_m)
    return s_lo, f_lo, s_hi, f_hi


@njit(**_JIT)
def _split(s_lo, f_lo, s_hi, f_hi, s_m, f_m):
    """The half of the bracket [s_lo, s_hi] that still holds the crossing, given the value
    f_m at s_m inside it (a point on or below the surface closes the bracket from below)."""
    if f_m <= 0.0:
        return s_lo, f_lo, s_m, f_m
    return s_m, f_m, s_hi, f_hi


@njit(**_JIT)
def _refine(s_lo, f_lo, s_hi, f_hi, tx, ty, tz, dx, dy, dz, L, C):
    """Refine the bracket [s_lo (above), s_hi (below)].

    A secant step first (exact on planar surfaces: accepted when |z - H| <= 0.1 mm); else
    bisection to 1 cm, then a secant step on a smooth surface or bisection to 1 mm on a
    discontinuity of H (wall: status 2)."""
    scale = max(L, abs(dz))
    den = f_lo - f_hi
    if den > 0.0:
        s_m = s_lo + (s_hi - s_lo) * f_lo / den
        f_m = (tz + dz * s_m) - _H(tx + dx * s_m, ty + dy * s_m, C)
        if abs(f_m) <= 1e-4:
            return 1, tx + dx * s_m, ty + dy * s_m, tz + dz * s_m
        s_lo, f_lo, s_hi, f_hi = _split(s_lo, f_lo, s_hi, f_hi, s_m, f_m)
    s_lo, f_lo, s_hi, f_hi = _bisect(s_lo, f_lo, s_hi, f_hi, tx, ty, tz, dx, dy, dz, scale,
                                      COARSE_TOL, C)
    # jump of H across the bracket (the ray height changes by dz (s_hi - s_lo) only)
    jump = (f_lo - f_hi) + dz * (s_hi - s_lo)
    if jump > WALL_JUMP:
        s_lo, f_lo, s_hi, f_hi = _bisect(s_lo, f_lo, s_hi, f_hi, tx, ty, tz, dx, dy, dz, scale,
                                          TOL, C)
        if (f_lo - f_hi) + dz * (s_hi - s_lo) > WALL_JUMP:
            return 2, tx + dx * s_hi, ty + dy * s_hi, tz + dz * s_hi
    den = f_lo - f_hi
    sstar = s_lo + (s_hi - s_lo) * (f_lo / den if den > 0.0 else 1.0)
    return 1, tx + dx * sstar, ty + dy * sstar, tz + dz * sstar


@njit(**_JIT)
def _shadowed(px, py, pz, sx, sy, sz, ztop, C, grid, gx0, gy0, cs, step):
    """True when the segment from P toward the sun (unit (sx, sy, sz), sz > 0) meets a surface
    before rising above ztop."""
    if pz >= ztop:
        return False
    tlen = (ztop - pz) / sz
    dx = sx * tlen
    dy = sy * tlen
    dz = ztop - pz
    L = math.sqrt(dx * dx + dy * dy)
    if L < 1e-9:
        return False                   # sun at the zenith: nothing above a height field point
    ix, iy, stx, tmx, tdx, sty, tmy, tdy = _dda_start(px, py, dx, dy, gx0, gy0, cs)
    ds = step / L
    s_in = 0.0
    while True:
        s_out = min(min(tmx, tmy), 1.0)
        cm = _cell_max(grid, ix, iy)
        if pz + dz * s_in <= cm:
            s_b = s_out if pz + dz * s_out <= cm else (cm - pz) / dz
            s = max(s_in, 0.3 * ds)
            while s < s_b:
                if pz + dz * s < _H(px + dx * s, py + dy * s, C):
                    return True
                s += ds
            if s_b >= 0.3 * ds and pz + dz * s_b < _H(px + dx * s_b, py + dy * s_b, C):
                return True
        if s_out >= 1.0:
            break
        ix, iy, s_in, tmx, tmy = _dda_next(ix, iy, stx, sty, tmx, tmy, tdx, tdy)
    return False


@njit(**_JIT)
def _cast_chunk(top, bot, hits, status, k0, k1, C, grid, gx0, gy0, cs):
    for k in range(k0, k1):
        st, x, y, z = _march(top[k, 0], top[k, 1], top[k, 2], bot[k, 0], bot[k, 1], bot[k, 2],
                             C, grid, gx0, gy0, cs, STEP)
        hits[k, 0] = x
        hits[k, 1] = y
        hits[k, 2] = z
        status[k] = st


@njit(**_PJIT)
def cast_rays(top, bot, C, grid, gx0, gy0, cs):
    """Cast segments top[k] -> bot[k] (n, 3) scene-local (x, y, h).

    Returns (hits (n, 3), status (n,) int8: 0 miss, 1 surface, 2 wall)."""
    n = top.shape[0]
    hits = np.empty((n, 3))
    status = np.empty(n, dtype=np.int8)
    ch = 256
    nch = (n + ch - 1) // ch
    for q in prange(nch):
        _cast_chunk(top, bot, hits, status, q * ch, min(n, (q + 1) * ch), C, grid, gx0, gy0, cs)
    return hits, status


# ----------------------------------------------------------------------------------------
# Appearance
# shading parameter vector layout (float64 array S)
S_SUNX, S_SUNY, S_SUNZ, S_SKY, S_VEG, S_ZTOP, S_DIFF = range(7)
N_SHADE = 7


@njit(**_JIT)
def _roof_albedo(base, x, y, tone, aux, fine, mid, C):
    """Roof texture: panels with per-panel tone, vents, stains; tile rows on pitched roofs."""
    P = C[0]
    salt = C[7]
    a = base + 0.05 * (mid - 0.5) + 0.06 * (fine - 0.5)
    if aux > 0.0:
        t = aux / 0.9
        if t - math.floor(t) < 0.15:
            a -= 0.05
        return a
    c = P[I_COS]
    s = P[I_SIN]
    u = c * x + s * y
    v = -s * x + c * y
    pu = math.floor(u / 4.3)
    pv = math.floor(v / 3.1)
    fp, fq, _ = _f3(_h4(np.int64(pu), np.int64(pv), 310, salt))
    a += 0.06 * (fp - 0.5)
    # seams between panels
    if u - pu * 4.3 < 0.12 or v - pv * 3.1 < 0.12:
        a -= 0.03
    # vents / skylights on a jittered 6 m lattice
    qu = math.floor(u / 6.0)
    qv = math.floor(v / 6.0)
    f1, f2, f3 = _f3(_h4(np.int64(qu), np.int64(qv), 320, salt))
    cu = (qu + 0.2 + 0.6 * f1) * 6.0
    cv = (qv + 0.2 + 0.6 * f2) * 6.0
    if f3 < 0.5 and abs(u - cu) < 0.45 and abs(v - cv) < 0.45:
        a = 0.05 if fq < 0.6 else 0.6
    return a


@njit(**_JIT)
def _albedo(mat, x, y, z, tone, aux, C, veg):
    """Panchromatic albedo of a material at a point; veg in [0, 1] is the season's greenness."""
    P = C[0]
    salt = C[7]
    fine = _fbm(x, y, salt, 300, 2.0, 3)          # 2, 1, 0.5 m
    mid = _fbm(x, y, salt, 400, 12.0, 3)          # 12, 6, 3 m
    if mat == M_ROAD:
        a = 0.085 + 0.05 * (mid - 0.5) + 0.06 * (fine - 0.5)
        if _vnoise(x / 7.0, y / 7.0, salt, 500) > 0.78:
            a += 0.035
        return a
    if mat == M_MARK:
        return 0.42 + 0.2 * fine - 0.1 * mid
    if mat == M_SIDEWALK:
        c = P[I_COS]
        s = P[I_SIN]
        u = (c * x + s * y) / 1.6
        v = (-s * x + c * y) / 1.6
        a = 0.24 + 0.05 * (mid - 0.5) + 0.06 * (fine - 0.5)
        if u - math.floor(u) < 0.07 or v - math.floor(v) < 0.07:
            a -= 0.06
        return a
    if mat == M_GRASS:
        patch = _fbm(x, y, salt, 600, 20.0, 2)
        return 0.2 - 0.07 * veg + 0.06 * (patch - 0.5) + 0.07 * (fine - 0.5) + 0.03 * (mid - 0.5)
    if mat == M_SOIL:
        return 0.23 + 0.08 * (mid - 0.5) + 0.07 * (fine - 0.5)
    if mat == M_PARKING:
        return 0.13 + 0.05 * (mid - 0.5) + 0.05 * (fine - 0.5)
    if mat == M_PATH:
        return 0.30 + 0.04 * (mid - 0.5) + 0.06 * (fine - 0.5)
    if mat == M_ROOF or mat == M_PARAPET or mat == M_ROOFBOX:
        k = int(tone * 6.0)
        base = 0.10 + 0.085 * k + 0.05 * (tone * 6.0 - k - 0.5)
        if mat == M_PARAPET:
            return base + 0.06 + 0.03 * (fine - 0.5)
        if mat == M_ROOFBOX:
            return 0.30 + 0.25 * tone + 0.05 * (fine - 0.5)
        return _roof_albedo(base, x, y, tone, aux, fine, mid, C)
    if mat == M_TREE:
        leaf = _fbm(x, y, salt, 700, 1.5, 3)
        if tone < 0.3:             # evergreen
            return 0.07 + 0.06 * (leaf - 0.5)
        return 0.07 + 0.08 * (1.0 - veg) + (0.05 + 0.05 * (1.0 - veg)) * (leaf - 0.5)
    return 0.2


@njit(**_JIT)
def _facade(x, y, z, found_h, nx, ny, tone, salt):
    """Facade albedo with windows; (nx, ny) is the outward normal of the wall."""
    along = -ny * x + nx * y
    zr = z - found_h
    a = 0.6 * (0.15 + 0.4 * tone) + 0.06
    if zr > 1.0:
        f = (zr - 1.0) / 3.1
        g = along / 2.8
        if 0.25 < f - math.floor(f) < 0.7 and 0.2 < g - math.floor(g) < 0.75:
            a = 0.05 + 0.04 * _vnoise(math.floor(g), math.floor(f), salt, 800)
    return a


@njit(**_JIT)
def _shade_hit(status, x, y, z, rdx, rdy, C, grid, gx0, gy0, cs, S):
    """Radiance of a hit: albedo x (sun x cos(incidence) x lit + sky x view factor)."""
    P = C[0]
    salt = C[7]
    sx = S[S_SUNX]
    sy = S[S_SUNY]
    sz = S[S_SUNZ]
    if status == 0:
        return 0.0
    if status == 2:
        # wall: normal from H probes along the grid axes, facing the viewer
        c = P[I_COS]
        s = P[I_SIN]
        e = 0.15
        gu = _H(x + e * c, y + e * s, C) - _H(x - e * c, y - e * s, C)
        gv = _H(x - e * s, y + e * c, C) - _H(x + e * s, y - e * c, C)
        if abs(gu) >= abs(gv):
            nu = -math.copysign(1.0, gu)
            nv = 0.0
        else:
            nu = 0.0
            nv = -math.copysign(1.0, gv)
        nx = nu * c - nv * s
        ny = nu * s + nv * c
        if nx * rdx + ny * rdy > 0.0:
            nx = -nx
            ny = -ny
        nz = 0.0
        inner = scene_eval(x - 0.3 * nx, y - 0.3 * ny, C, True)
        if inner[3] == M_TREE:
            alb = 0.05
        elif inner[3] == M_SIDEWALK:
            alb = 0.22
        else:
            alb = _facade(x, y, z, _terrain(x, y, P, salt), nx, ny, inner[4], salt)
        px = x + 0.03 * nx
        py = y + 0.03 * ny
        pz = z
    else:
        r = scene_eval(x, y, C, True)
        gx = r[1]
        gy = r[2]
        inv = 1.0 / math.sqrt(gx * gx + gy * gy + 1.0)
        nx = -gx * inv
        ny = -gy * inv
        nz = inv
        alb = _albedo(r[3], x, y, z, r[4], r[5], C, S[S_VEG])
        px = x
        py = y
        pz = z + 0.02
    alb = max(alb, 0.01)
    cosi = nx * sx + ny * sy + nz * sz
    direct = 0.0
    if cosi > 0.0:
        if not _shadowed(px, py, pz, sx, sy, sz, S[S_ZTOP], C, grid, gx0, gy0, cs, SHADOW_STEP):
            direct = cosi
    sky = S[S_SKY] * (0.6 + 0.4 * nz)
    return alb * (S[S_DIFF] * direct + sky)


@njit(**_JIT)
def _render_row(top, bot, node_c0, node_step, col0, ncols, ss, C, grid, gx0, gy0, cs, S, out, rr):
    inv = 1.0 / (ss * ss)
    for ci in range(ncols):
        acc = 0.0
        for a in range(ss):
            q = rr * ss + a
            for b in range(ss):
                cc = col0 + ci + (b + 0.5) / ss - 0.5
                fk = (cc - node_c0) / node_step
                k = int(math.floor(fk))
                w = fk - k
                tx = top[q, k, 0] + w * (top[q, k + 1, 0] - top[q, k, 0])
                ty = top[q, k, 1] + w * (top[q, k + 1, 1] - top[q, k, 1])
                tz = top[q, k, 2] + w * (top[q, k + 1, 2] - top[q, k, 2])
                bx = bot[q, k, 0] + w * (bot[q, k + 1, 0] - bot[q, k, 0])
                by = bot[q, k, 1] + w * (bot[q, k + 1, 1] - bot[q, k, 1])
                bz = bot[q, k, 2] + w * (bot[q, k + 1, 2] - bot[q, k, 2])
                st, x, y, z = _march(tx, ty, tz, bx, by, bz, C, grid, gx0, gy0, cs, STEP)
                acc += _shade_hit(st, x, y, z, bx - tx, by - ty, C, grid, gx0, gy0, cs, S)
        out[rr, ci] = acc * inv


@njit(**_PJIT)
def render_rows(top, bot, node_c0, node_step, col0, ncols, ss, C, grid, gx0, gy0, cs, S):
    """Render a block of image rows.

    top, bot: (n_subrows, n_nodes, 3) scene-local (x, y, h) of each sub-row's rays at the top
    and bottom heights, exact at node columns node_c0 + k node_step and linear in between.
    Sub-row q = row * ss + a is at row offset (a + 0.5)/ss - 0.5. Returns (n_subrows // ss,
    ncols) float32 radiance for columns col0 .. col0 + ncols - 1 (ss x ss rays per pixel).
    """
    nrows = top.shape[0] // ss
    out = np.empty((nrows, ncols), dtype=np.float32)
    for rr in prange(nrows):
        _render_row(top, bot, node_c0, node_step, col0, ncols, ss, C, grid, gx0, gy0, cs, S, out, rr)
    return out


# ----------------------------------------------------------------------------------------
# Python-side model
SCENE_OVERRIDES = ("park", "open", "tall", "terrain")


def scene_params(seed: int, h0: float, overrides: dict | None = None) -> tuple[np.ndarray, int]:
    """Draw the scene parameter vector P and the hash salt for a seed.

    overrides: "park" and "open" (fractions of the blocks that are parks and open flat ground;
    the rest is built), "tall" (building height factor, 0.6-1.0 by default; lower = lower
    buildings), "terrain" (factor on the terrain relief)."""
    rng = np.random.default_rng([int(seed), 7001])
    P = np.zeros(N_PARAMS)
    theta = rng.uniform(0.0, np.pi / 2)
    P[I_COS], P[I_SIN] = np.cos(theta), np.sin(theta)
    P[I_PU] = rng.uniform(64.0, 84.0)
    P[I_PV] = rng.uniform(58.0, 78.0)
    P[I_JU] = rng.uniform(3.0, 7.0)
    P[I_JV] = rng.uniform(3.0, 7.0)
    P[I_H0] = h0
    P[I_TALL] = rng.uniform(0.6, 1.0)
    P[I_TREE_T] = TREE_PITCH
    P[I_PARK] = rng.uniform(0.08, 0.14)
    P[I_OPEN] = rng.uniform(0.04, 0.08)
    P[I_SW] = rng.uniform(2.5, 3.8)
    amps = np.array([3.2, 1.1]) * rng.uniform(0.7, 1.3, N_TER)
    wls = np.array([650.0, 220.0]) * rng.uniform(0.85, 1.2, N_TER)
    for k in range(N_TER):
        P[I_TER + 4 * k: I_TER + 4 * k + 4] = [amps[k], wls[k], rng.uniform(0, 100),
                                               rng.uniform(0, 100)]
    salt = int(rng.integers(1, 2**62))
    o = dict(overrides or {})
    unknown = set(o) - set(SCENE_OVERRIDES)
    if unknown:
        raise ValueError(f"unknown scene overrides {sorted(unknown)}; known: {SCENE_OVERRIDES}")
    if "park" in o:
        P[I_PARK] = o["park"]
    if "open" in o:
        P[I_OPEN] = o["open"]
    if "tall" in o:
        P[I_TALL] = o["tall"]
    if "terrain" in o:
        P[I_TER::4][:N_TER] *= o["terrain"]
    return P, salt


@dataclass
class SceneModel:
    """The procedural scene of one site.

    Coordinates: scene-local (x, y) = (E - E0, N - N0) in the UTM zone `epsg`; heights are
    ellipsoidal (WGS84) metres. `lon0, lat0` is the geographic position of the local origin.
    """

    seed: int
    epsg: int
    E0: float
    N0: float
    lon0: float
    lat0: float
    h0: float
    P: np.ndarray = field(repr=False)
    salt: int = 0
    accel: AccelGrid | None = field(default=None, repr=False)
    tables: dict | None = field(default=None, repr=False)    # {"ctx": C, "box": covered xy box}

    @classmethod
    def create(cls, seed: int, lon: float, lat: float, h0: float,
               overrides: dict | None = None) -> "SceneModel":
        from recon_core.geometry.geodesy import geodetic_to_projected, projected_to_geodetic, utm_epsg_for

        epsg = utm_epsg_for(lon, lat)
        e, n, _ = geodetic_to_projected(np.array([lon, lat, 0.0]), epsg)
        E0, N0 = float(np.round(e)), float(np.round(n))
        lon0, lat0, _ = projected_to_geodetic(np.array([E0, N0, 0.0]), epsg)
        P, salt = scene_params(seed, h0, overrides)
        return cls(seed=int(seed), epsg=int(epsg), E0=E0, N0=N0, lon0=float(lon0),
                   lat0=float(lat0), h0=float(h0), P=P, salt=salt)

    @property
    def ctx(self) -> tuple:
        """Context tuple for the kernels: (P, LU, LV, TB, salt, iu0, jv0).

        The kernels only read the block cache: every caller must first make it cover the
        points it evaluates (:meth:`ensure_tables`; the methods of this class do it)."""
        if self.tables is None:
            self.ensure_tables(-1.0, -1.0, 1.0, 1.0)
        assert self.tables is not None          # ensure_tables sets it
        return self.tables["ctx"]

    # ---- coordinates
    def local_to_llh(self, xyh: np.ndarray) -> np.ndarray:
        """(..., 3) scene-local (x, y, h) -> (..., 3) (lon, lat, h)."""
        from recon_core.geometry.geodesy import projected_to_geodetic

        q = np.array(xyh, dtype=np.float64)
        q[..., 0] += self.E0
        q[..., 1] += self.N0
        return projected_to_geodetic(q, self.epsg)

    def llh_to_local(self, llh: np.ndarray) -> np.ndarray:
        """(..., 3) (lon, lat, h) -> (..., 3) scene-local (x, y, h)."""
        from recon_core.geometry.geodesy import geodetic_to_projected

        q = geodetic_to_projected(np.asarray(llh, dtype=np.float64), self.epsg)
        q[..., 0] -= self.E0
        q[..., 1] -= self.N0
        return q

    def uv(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Street-grid coordinates (u, v) of scene-local points."""
        c, s = self.P[I_COS], self.P[I_SIN]
        return c * np.asarray(x) + s * np.asarray(y), -s * np.asarray(x) + c * np.asarray(y)

    # ---- evaluation
    def height(self, x, y) -> np.ndarray:
        """H(x, y) at scene-local points; any broadcastable shapes -> float64 array."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        shp = x.shape
        self._ensure_points(x, y)
        return height_points(np.ascontiguousarray(x.ravel()), np.ascontiguousarray(y.ravel()),
                             self.ctx).reshape(shp)

    def height_utm(self, E, N) -> np.ndarray:
        """H at UTM easting/northing of the site's zone."""
        return self.height(np.asarray(E, dtype=np.float64) - self.E0,
                           np.asarray(N, dtype=np.float64) - self.N0)

    def evaluate(self, x, y) -> dict:
        """Full evaluation at points (n,): dict of h (n,), grad (n, 2), material (n,) int, tone."""
        x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).ravel())
        y = np.ascontiguousarray(np.asarray(y, dtype=np.float64).ravel())
        self._ensure_points(x, y)
        r = eval_points(x, y, self.ctx)
        return {"h": r[:, 0], "grad": r[:, 1:3], "material": r[:, 3].astype(int),
                "tone": r[:, 4]}

    def height_bounds(self) -> tuple[float, float]:
        """Bounds of H: from the acceleration grid when built, else analytic."""
        if self.accel is not None:
            return self.accel.hmin, self.accel.hmax
        amp = float(np.abs(self.P[I_TER::4][:N_TER]).sum())
        return self.h0 - amp - 0.5, self.h0 + amp + MAX_STRUCT_HEIGHT

    def gt_dsm(self, bounds: tuple[float, float, float, float], resolution: float = 0.5):
        """Ground-truth DSM on a UTM grid: H at cell centres (exact).

        bounds = (xmin, ymin, xmax, ymax) in UTM metres (multiples of the resolution);
        returns (dsm (rows, cols) float32, rasterio Affine transform), row 0 at ymax.
        """
        from affine import Affine

        xmin, ymin, xmax, ymax = bounds
        nx = int(round((xmax - xmin) / resolution))
        ny = int(round((ymax - ymin) / resolution))
        self.ensure_tables(xmin - self.E0, ymin - self.N0, xmax - self.E0, ymax - self.N0)
        dsm = height_grid(xmin - self.E0 + 0.5 * resolution, ymax - self.N0 - 0.5 * resolution,
                          resolution, -resolution, nx, ny, self.ctx)
        return dsm, Affine(resolution, 0.0, xmin, 0.0, -resolution, ymax)

    MAX_TABLE_EXTENT = 100e3

    def ensure_tables(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """Make the block cache cover the scene-local rectangle (plus ~200 m of margin)."""
        if self.tables is not None:
            bx0, by0, bx1, by1 = self.tables["box"]
            if bx0 <= x0 and by0 <= y0 and x1 <= bx1 and y1 <= by1:
                return
            x0, y0, x1, y1 = min(x0, bx0), min(y0, by0), max(x1, bx1), max(y1, by1)
        if max(x1 - x0, y1 - y0) > self.MAX_TABLE_EXTENT or not np.isfinite([x0, y0, x1, y1]).all():
            raise ValueError(f"scene query extent too large: {(x0, y0, x1, y1)}")
        self.build_tables(x0, y0, x1, y1)

    def _ensure_points(self, x: np.ndarray, y: np.ndarray) -> None:
        if x.size:
            self.ensure_tables(float(x.min()), float(y.min()), float(x.max()), float(y.max()))

    def build_tables(self, x0: float, y0: float, x1: float, y1: float, margin: int = 3) -> None:
        """Cache street lines and block records over a scene-local rectangle.

        The cache covers the rectangle's blocks plus `margin` blocks on every side (>= 170 m),
        which also covers the tree look-ups (<= 13 m away) and shadow rays leaving the
        rectangle (< 150 m)."""
        cx = np.array([x0, x1, x0, x1])
        cy = np.array([y0, y0, y1, y1])
        u, v = self.uv(cx, cy)
        iu0 = int(np.floor(u.min() / self.P[I_PU])) - margin
        iu1 = int(np.floor(u.max() / self.P[I_PU])) + margin
        jv0 = int(np.floor(v.min() / self.P[I_PV])) - margin
        jv1 = int(np.floor(v.max() / self.P[I_PV])) + margin
        salt = int(self.salt)
        LU, LV, TB = build_tables(self.P, salt, iu0, iu1 - iu0 + 1, jv0, jv1 - jv0 + 1)
        pad = 150.0
        bx0, by0, bx1, by1 = x0 - pad, y0 - pad, x1 + pad, y1 + pad
        # terrain lattices
        tv0 = np.zeros((N_TER, 2), dtype=np.int64)
        n = 2
        for k in range(N_TER):
            o = I_TER + 4 * k
            wl = self.P[o + 1]
            lx0 = int(np.floor(bx0 / wl + self.P[o + 2])) - 1
            ly0 = int(np.floor(by0 / wl + self.P[o + 3])) - 1
            lx1 = int(np.floor(bx1 / wl + self.P[o + 2])) + 2
            ly1 = int(np.floor(by1 / wl + self.P[o + 3])) + 2
            tv0[k] = lx0, ly0
            n = max(n, lx1 - lx0 + 1, ly1 - ly0 + 1)
        TV = build_terrain_table(salt, np.ascontiguousarray(tv0[:, 0]),
                                 np.ascontiguousarray(tv0[:, 1]), n)
        # lattice trees (the allowed flag needs the block tables)
        ta0 = int(np.floor(bx0 / TREE_PITCH)) - 2
        tb0 = int(np.floor(by0 / TREE_PITCH)) - 2
        na = int(np.floor(bx1 / TREE_PITCH)) + 2 - ta0 + 1
        nb = int(np.floor(by1 / TREE_PITCH)) + 2 - tb0 + 1
        hdr = np.array([iu0, jv0, ta0, tb0] + [int(v) for v in tv0.ravel()], dtype=np.int64)
        C0 = (self.P, LU, LV, TB, np.zeros((1, 1, NTT)), TV, hdr, salt)
        TT = build_tree_table(C0, ta0, na, tb0, nb)
        self.tables = {"ctx": (self.P, LU, LV, TB, TT, TV, hdr, salt),
                       "box": (bx0, by0, bx1, by1)}

    def build_accel(self, x0: float, y0: float, x1: float, y1: float, cs: float = 1.0,
                    sample_step: float = SAMPLE_STEP, progress=None) -> AccelGrid:
        """Build (and keep) the block cache and the acceleration grid over a rectangle.

        Rays cast with :meth:`cast_local` or the render kernels must stay inside it."""
        self.ensure_tables(x0, y0, x1, y1)
        self.accel = build_accel(self.ctx, x0, y0, x1, y1, cs, sample_step, progress=progress)
        return self.accel

    def cast_local(self, top: np.ndarray, bot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast segments (n, 3) -> (n, 3): first surface hit (scene-local), status (n,) int8."""
        a = self.accel
        assert a is not None, "cast_local before build_accel"
        pts = np.concatenate([np.asarray(top)[:, :2], np.asarray(bot)[:, :2]])
        self._ensure_points(pts[:, 0], pts[:, 1])
        return cast_rays(np.ascontiguousarray(top, dtype=np.float64),
                         np.ascontiguousarray(bot, dtype=np.float64), self.ctx,
                         a.cellmax, a.x0, a.y0, a.cs)

    def to_dict(self) -> dict:
        return {"seed": self.seed, "epsg": self.epsg, "E0": self.E0, "N0": self.N0,
                "lon0": self.lon0, "lat0": self.lat0, "h0": self.h0,
                "P": [float(v) for v in self.P], "salt": int(self.salt)}

    @classmethod
    def from_dict(cls, d: dict) -> "SceneModel":
        return cls(seed=int(d["seed"]), epsg=int(d["epsg"]), E0=float(d["E0"]),
                   N0=float(d["N0"]), lon0=float(d["lon0"]), lat0=float(d["lat0"]),
                   h0=float(d["h0"]), P=np.asarray(d["P"], dtype=np.float64),
                   salt=int(d["salt"]))
