"""Image tiles for the workspace's canvases: a pyramid of TILE x TILE windows read from the
site's images by window (never the whole image), decimated by 2**level, stretched to 8 bit with
the page's contrast, brightness and gamma, and encoded as PNG (lossless: the operator aims at
single pixels) or JPEG.

Tile (tx, ty) of level L covers the full-resolution window of columns [tx * TILE * 2**L,
(tx + 1) * TILE * 2**L) and the rows alike, clipped to the image: the page draws it over that
window, so an edge tile (narrower) lands where it belongs.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from recon_core.io.site import read_window
from recon_core.model.tiling import Window

TILE = 256                       # tile side in output pixels
RAW_CACHE_TILES = 160            # decoded float tiles kept (256 KB each: 40 MB)
ENCODED_CACHE_TILES = 400        # encoded tiles kept per stretch (a few tens of KB each)


@dataclass(frozen=True)
class Stretch:
    """The page's display of raw values: the image's own percentile stretch (lo, hi) narrowed by
    `contrast` around its middle, shifted by `brightness` (a fraction of the half range, + is
    brighter), then t ** (1 / gamma) (gamma 2 is the square root the 3D view's tone uses)."""

    lo: float
    hi: float
    contrast: float = 1.0
    brightness: float = 0.0
    gamma: float = 2.0

    def apply(self, g: np.ndarray) -> np.ndarray:
        """(h, w) float raw values -> (h, w) uint8; NaN (nodata) is black."""
        half = max(self.hi - self.lo, 1e-6) / 2.0
        mid = self.lo + half - self.brightness * half
        half /= self.contrast
        t = np.clip((g - (mid - half)) / (2.0 * half), 0.0, 1.0) ** (1.0 / self.gamma)
        return (np.nan_to_num(t * 255.0, nan=0.0) + 0.5).astype(np.uint8)


def levels(width: int, height: int) -> int:
    """Number of pyramid levels: level levels()-1 shows the whole image in one tile."""
    return max(1, int(math.ceil(math.log2(max(width, height, TILE) / TILE))) + 1)


def tile_window(image: str, width: int, height: int, level: int, tx: int, ty: int) -> Window:
    """The full-resolution window a tile covers (clipped to the image); ValueError when the tile
    lies outside the image or the level outside the pyramid."""
    if not 0 <= level < levels(width, height):
        raise ValueError(f"level {level} outside 0-{levels(width, height) - 1} for {image}")
    side = TILE << level
    col0, row0 = tx * side, ty * side
    if tx < 0 or ty < 0 or col0 >= width or row0 >= height:
        raise ValueError(f"tile ({tx}, {ty}) of level {level} lies outside {image} ({width} x {height})")
    return Window(image, col0, row0, min(side, width - col0), min(side, height - row0))


def out_shape(win: Window, level: int) -> tuple[int, int]:
    """(h, w) of a tile's pixels: its window decimated by 2**level (rounded up: an edge tile)."""
    f = 1 << level
    return max(1, -(-win.height // f)), max(1, -(-win.width // f))


class _Lru:
    """A small thread-safe least-recently-used map."""

    def __init__(self, size: int):
        self.size, self._d, self._lock = size, OrderedDict(), threading.Lock()

    def get(self, key):
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                return self._d[key]
        return None

    def put(self, key, value) -> None:
        with self._lock:
            self._d[key] = value
            self._d.move_to_end(key)
            while len(self._d) > self.size:
                self._d.popitem(last=False)


class TileSource:
    """Reads, stretches and encodes tiles of the images of an ImageSource (thread-safe)."""

    def __init__(self, images):
        self.images = images                  # imagery.ImageSource: infos and per-image tone
        self._raw = _Lru(RAW_CACHE_TILES)
        self._encoded = _Lru(ENCODED_CACHE_TILES)

    def base_stretch(self, name: str) -> tuple[float, float]:
        """(lo, hi): the image's own percentile stretch (imagery.ImageSource.image_tone)."""
        tone = self.images.image_tone(name)
        return float(tone.lo), float(tone.hi)

    def raw(self, name: str, level: int, tx: int, ty: int) -> tuple[np.ndarray, Window]:
        """The tile's raw values (float32, decimated by averaging) and its window."""
        im = self.images.info(name)
        win = tile_window(name, im.width, im.height, level, tx, ty)
        key = (name, level, tx, ty)
        got = self._raw.get(key)
        if got is None:
            got = read_window(im, win.col0, win.row0, win.width, win.height,
                              out_shape=out_shape(win, level) if level else None)
            self._raw.put(key, got)
        return got, win

    def encoded(self, name: str, level: int, tx: int, ty: int, *, contrast: float = 1.0,
                brightness: float = 0.0, gamma: float = 2.0, fmt: str = "png") -> bytes:
        """The tile as PNG or JPEG bytes with the page's stretch."""
        key = (name, level, tx, ty, contrast, brightness, gamma, fmt)
        got = self._encoded.get(key)
        if got is not None:
            return got
        g, _ = self.raw(name, level, tx, ty)
        lo, hi = self.base_stretch(name)
        px = Stretch(lo, hi, contrast, brightness, gamma).apply(g)
        params = [cv2.IMWRITE_PNG_COMPRESSION, 1] if fmt == "png" else [cv2.IMWRITE_JPEG_QUALITY, 90]
        ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", px, params)
        if not ok:
            raise RuntimeError(f"could not encode a tile of {name} as {fmt}")
        got = buf.tobytes()
        self._encoded.put(key, got)
        return got
