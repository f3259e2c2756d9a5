"""What identifies an image's content for resume: a hash of all its bytes (and of the files a VRT
reads), computed once per version of the file.

A run resumes a finished stage only when its inputs are the same. A hash of a few sampled
windows let pixels edited elsewhere, with the size and modification time put back, resume the
old result; a hash of every byte does not, and it is cheap when it is not recomputed: sha1 runs
at about 1.8 GB/s here, so a 3 GB scene takes a few seconds once. It is recomputed only when the
file's identity changes: its inode, size, modification time or change time (the kernel sets the
change time on any write, and nothing can set it back), kept in OUT/stages/content_hashes.json.
A copied site is hashed once again and keeps its fingerprint.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

CACHE_NAME = "content_hashes.json"
CHUNK = 16 << 20                 # bytes read at a time (16 MB)
_memory: dict[str, str] = {}     # identity -> hash, for the process


def _identity(path: Path) -> str:
    st = path.stat()
    return f"{os.path.realpath(path)}|{st.st_ino}|{st.st_size}|{st.st_mtime_ns}|{st.st_ctime_ns}"


def _sha1(path: Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
    return h.hexdigest()


def own_hash(path: Path, cache: dict) -> str:
    """sha1 of the file's own bytes, from `cache` (identity -> hash) when it is the same version;
    'unreadable' when it cannot be read (the checks say so elsewhere)."""
    try:
        key = _identity(path)
    except OSError:
        return "unreadable"
    if key not in cache:
        try:
            cache[key] = _sha1(path)
        except OSError:
            return "unreadable"
        _memory[key] = cache[key]
    return cache[key]


def content_hash(path: str | Path, cache: dict | None = None, _seen: frozenset = frozenset()) -> str:
    """sha1 of the file's bytes, and for a VRT of the files it reads (recursively): each file's own
    hash comes from `cache` when it is the same version, the VRT's is put together every time
    (a source edited under an unchanged VRT changes it)."""
    path = Path(path)
    cache = _memory if cache is None else cache
    h = own_hash(path, cache)
    if path.suffix.lower() == ".vrt" and h != "unreadable" and str(path) not in _seen:
        from recon_core.io.site import _vrt_sources

        parts = [h] + [content_hash(Path(s), cache, _seen | {str(path)}) for s in _vrt_sources(path)]
        h = hashlib.sha1("|".join(parts).encode()).hexdigest()
    return h


class HashCache:
    """The content hashes of OUT's inputs, kept in OUT/stages (loaded once, saved when new)."""

    def __init__(self, out: str | Path | None):
        self.path = None if out is None else Path(out) / "stages" / CACHE_NAME
        self.table: dict[str, str] = dict(_memory)
        if self.path is not None and self.path.is_file():
            try:
                self.table.update(json.loads(self.path.read_text()))
            except (OSError, ValueError):
                pass
        self._n = len(self.table)

    def __call__(self, path: str | Path) -> str:
        return content_hash(path, self.table)

    def save(self) -> None:
        if self.path is None or len(self.table) == self._n or not self.path.parent.is_dir():
            return
        from recon_core.io.files import write_json

        try:
            write_json(self.path, self.table)
        except OSError:
            pass                                # a read-only OUT: the hashes are recomputed next time
