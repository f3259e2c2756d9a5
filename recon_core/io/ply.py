"""PLY point clouds: binary little-endian, float64 x y z (UTM survives exactly), optional
uint8 RGB and float32 extra properties; an atomic streaming writer and a memory-mapped reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon_core.errors import InputError
from recon_core.io.files import atomic_path

# --------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4",
              "uint": "<u4", "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1",
              "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
              "float32": "<f4", "float64": "<f8"}


def _ply_dtype(n_extra: list[str], with_colors: bool) -> np.dtype:
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if with_colors:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    return np.dtype(fields + [(k, "<f4") for k in n_extra])


def write_ply(path: str | Path, xyz: np.ndarray, colors: np.ndarray | None = None,
              extra: dict[str, np.ndarray] | None = None, chunk: int = 1 << 20,
              comments: list[str] | tuple[str, ...] = ()) -> Path:
    """Write a binary little-endian PLY point cloud atomically.

    Args:
        xyz: (n, 3) float64 coordinates (stored as double so UTM survives exactly).
        colors: (n, 3) uint8 RGB, optional.
        extra: name -> (n,) values stored as float32 properties, optional.
        chunk: points per write (bounds the temporary memory).
        comments: header comment lines (e.g. the coordinate frame).
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    extra = {k: np.asarray(v).reshape(-1) for k, v in (extra or {}).items()}
    for k, v in extra.items():
        if len(v) != n or not k.isidentifier():
            raise ValueError(f"extra field {k!r}: bad name or length {len(v)} != {n}")
    if colors is not None:
        colors = np.asarray(colors).reshape(-1, 3)
        if len(colors) != n:
            raise ValueError(f"{len(colors)} colours for {n} points")
    with PlyWriter(path, list(extra), colors is not None, comments=comments) as w:
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            w.append(xyz[a:b], None if colors is None else colors[a:b],
                     {k: v[a:b] for k, v in extra.items()})
    return Path(path)


class PlyWriter:
    """Streaming binary little-endian PLY writer: append chunks, the count is set on close.

    The file is written under a temporary name and renamed onto `path` only when the block
    ends without an exception (a crash leaves no half-written cloud). The header is written
    first with room for any count (a padding comment absorbs the difference), so closing only
    rewrites the header in place: no second copy of a cloud of hundreds of millions of points.
    """

    _COUNT_DIGITS = 20

    def __init__(self, path: str | Path, extra: list[str] | tuple[str, ...] = (), with_colors: bool = True,
                 comments: list[str] | tuple[str, ...] = ()):
        for k in extra:
            if not k.isidentifier():
                raise ValueError(f"extra field {k!r}: bad name")
        for c in comments:
            if "\n" in c or "\r" in c or not c.isascii():
                raise ValueError(f"PLY comment {c!r}: one line of ASCII")
        self.comments = [f"comment {c}" for c in comments]
        self.path = Path(path)
        self.dtype = _ply_dtype(list(extra), with_colors)
        self.extra, self.with_colors = list(extra), with_colors
        self.n = 0
        self._ctx = atomic_path(self.path)
        self._tmp = self._ctx.__enter__()
        self._f = open(self._tmp, "wb")
        self._header_len = len(self._header(10 ** (self._COUNT_DIGITS - 1), 0)) + 10
        self._f.write(self._header(0, self._header_len))

    def _header(self, n: int, size: int) -> bytes:
        ply_name = {np.dtype("<f8"): "double", np.dtype("u1"): "uchar", np.dtype("<f4"): "float"}
        head = ["ply", "format binary_little_endian 1.0", "comment written by AE-Rec",
                *self.comments, f"element vertex {n}"]
        head += [f"property {ply_name[self.dtype[k]]} {k}" for k in (self.dtype.names or ())]
        text = "\n".join(head) + "\n"
        tail = "end_header\n"
        if size:
            pad = size - len(text) - len(tail) - len("comment \n")
            text += "comment " + " " * pad + "\n"
        return (text + tail).encode("ascii")

    def append(self, xyz: np.ndarray, colors: np.ndarray | None = None,
               extra: dict[str, np.ndarray] | None = None) -> None:
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        m = len(xyz)
        rec = np.empty(m, dtype=self.dtype)
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        if self.with_colors:
            if colors is None:
                raise ValueError("this PLY has colours: pass them")
            colors = np.asarray(colors).reshape(m, -1)
            for i, c in enumerate(("red", "green", "blue")):
                rec[c] = colors[:, i if colors.shape[1] == 3 else 0]
        extra = extra or {}
        if set(extra) != set(self.extra):
            raise ValueError(f"extra fields {sorted(extra)} != {sorted(self.extra)}")
        for k, v in extra.items():
            rec[k] = np.asarray(v).reshape(-1)
        assert self._f is not None               # open until close()
        rec.tofile(self._f)
        self.n += m

    def close(self, ok: bool = True) -> None:
        """Finish the file (ok) or discard it (not ok, e.g. after an exception)."""
        if self._f is None:
            return
        f, self._f = self._f, None
        try:
            if ok:
                f.seek(0)
                f.write(self._header(self.n, self._header_len))
            f.close()
        except BaseException as exc:
            f.close()
            self._ctx.__exit__(type(exc), exc, exc.__traceback__)
            raise
        if ok:
            self._ctx.__exit__(None, None, None)
        else:
            err = RuntimeError("PLY writing aborted")
            self._ctx.__exit__(RuntimeError, err, None)

    def __enter__(self) -> "PlyWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(ok=exc_type is None)


def _read_ply_header(f, path) -> tuple[int, np.dtype]:
    """Parse a binary little-endian PLY header. Returns (vertex count, vertex dtype)."""
    if f.readline().strip() != b"ply":
        raise InputError(path, "not a PLY file")
    n, fields, element = None, [], None
    while True:
        line = f.readline()
        if not line:
            raise InputError(path, "PLY header has no end_header")
        tok = line.decode("ascii", "replace").split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "end_header":
            break
        if tok[0] == "format" and tok[1] != "binary_little_endian":
            raise InputError(path, f"PLY format {tok[1]} is not supported (binary_little_endian only)")
        if tok[0] == "element":
            if element is None and tok[1] != "vertex":
                raise InputError(path, "the first PLY element must be 'vertex'")
            element = tok[1]
            if element == "vertex":
                n = int(tok[2])
        elif tok[0] == "property" and element == "vertex":
            if tok[1] == "list" or tok[1] not in _PLY_TYPES:
                raise InputError(path, f"unsupported vertex property {' '.join(tok[1:])}")
            fields.append((tok[2], _PLY_TYPES[tok[1]]))
    if n is None:
        raise InputError(path, "PLY file has no vertex element")
    return n, np.dtype(fields)


def open_ply(path: str | Path) -> np.ndarray:
    """Memory-map the vertices of a binary PLY as a structured array (nothing read yet)."""
    path = Path(path)
    with open(path, "rb") as f:
        n, dt = _read_ply_header(f, path)
        offset = f.tell()
    size = path.stat().st_size
    if size < offset + n * dt.itemsize:
        raise InputError(path, f"PLY file truncated: {(size - offset) // dt.itemsize} of {n} vertices")
    if not {"x", "y", "z"} <= set(dt.names or ()):
        raise InputError(path, "PLY vertices lack x, y, z")
    if n == 0:
        return np.zeros(0, dtype=dt)
    return np.memmap(path, dtype=dt, mode="r", offset=offset, shape=(n,))


def ply_fields(rec: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """(xyz (n, 3) float64, colors (n, 3) uint8 or None, extra) of PLY vertex records (copies)."""
    names = set(rec.dtype.names or ())
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    rgb = ("red", "green", "blue")
    colors = np.column_stack([rec[c] for c in rgb]).astype(np.uint8) if set(rgb) <= names else None
    extra = {k: np.array(rec[k]) for k in (rec.dtype.names or ()) if k not in ("x", "y", "z", *rgb)}
    return xyz, colors, extra


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """Read a binary little-endian PLY: (xyz (n, 3) float64, colors (n, 3) uint8 or None, extra)."""
    rec = open_ply(path)
    out = ply_fields(rec)
    del rec
    return out
