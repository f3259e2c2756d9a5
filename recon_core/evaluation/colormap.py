"""Colour maps, hillshade, colour bars and PNG writing with numpy and cv2 only (no matplotlib).

Images are RGB uint8 arrays (height, width, 3); `save_png` converts to cv2's BGR.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from recon_core.io.files import atomic_path

NAN_GREY = (128, 128, 128)

# ColorBrewer RdBu reversed: blue (negative) - white - red (positive).
_DIVERGING = np.array([(5, 48, 97), (33, 102, 172), (67, 147, 195), (146, 197, 222),
                       (209, 229, 240), (247, 247, 247), (253, 219, 199), (244, 165, 130),
                       (214, 96, 77), (178, 24, 43), (103, 0, 31)], dtype=np.float64)
# A terrain-like sequential ramp for heights: dark blue-green - green - yellow - brown - white.
_HEIGHT = np.array([(40, 60, 120), (40, 130, 110), (90, 170, 80), (200, 200, 90),
                    (170, 120, 70), (140, 100, 80), (245, 245, 245)], dtype=np.float64)


def _ramp(t: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """Piecewise-linear colour ramp. t: (...) in [0, 1] (NaN allowed) -> (..., 3) uint8, NaN grey."""
    t = np.asarray(t, dtype=np.float64)
    nan = ~np.isfinite(t)
    x = np.clip(np.nan_to_num(t), 0.0, 1.0) * (len(anchors) - 1)
    i = np.minimum(np.floor(x).astype(np.int64), len(anchors) - 2)
    f = (x - i)[..., None]
    rgb = anchors[i] * (1 - f) + anchors[i + 1] * f
    rgb[nan] = NAN_GREY
    return np.round(rgb).astype(np.uint8)


def diverging(values: np.ndarray, clip: float) -> np.ndarray:
    """Signed values clipped to [-clip, clip] -> RGB (blue negative, white 0, red positive)."""
    return _ramp((np.asarray(values, dtype=np.float64) / clip + 1.0) / 2.0, _DIVERGING)


def sequential(values: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Heights in [vmin, vmax] -> RGB with a terrain-like ramp; NaN grey."""
    span = vmax - vmin if vmax > vmin else 1.0
    return _ramp((np.asarray(values, dtype=np.float64) - vmin) / span, _HEIGHT)


def hillshade(H: np.ndarray, res: float, azimuth_deg: float = 315.0,
              altitude_deg: float = 45.0) -> np.ndarray:
    """Lambertian hillshade of a DSM (height, width) with cell size res -> (height, width) in [0, 1].

    NaN cells (and their neighbours) get 1 (no shading).
    """
    gy, gx = np.gradient(np.asarray(H, dtype=np.float64), res)
    dzde, dzdn = gx, -gy                                 # rows run south
    az, alt = np.radians(azimuth_deg), np.radians(altitude_deg)
    light = np.array([np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)])
    shade = (-dzde * light[0] - dzdn * light[1] + light[2]) / np.sqrt(1 + dzde ** 2 + dzdn ** 2)
    return np.nan_to_num(np.clip(shade, 0.0, 1.0), nan=1.0)


def shaded(H: np.ndarray, res: float, vmin: float, vmax: float) -> np.ndarray:
    """Height colours modulated by a hillshade. (height, width) -> RGB uint8."""
    rgb = sequential(H, vmin, vmax).astype(np.float64)
    s = 0.45 + 0.55 * hillshade(H, res)[..., None]
    out = rgb * s
    out[~np.isfinite(H)] = NAN_GREY
    return np.clip(out, 0, 255).astype(np.uint8)


def resize_for_display(rgb: np.ndarray, min_side: int = 400, max_side: int = 1600) -> np.ndarray:
    """Nearest-neighbour enlargement of small images (integer factor) or area reduction of big ones."""
    h, w = rgb.shape[:2]
    if max(h, w) < min_side:
        k = int(np.ceil(min_side / max(h, w)))
        return np.repeat(np.repeat(rgb, k, axis=0), k, axis=1)
    if max(h, w) > max_side:
        s = max_side / max(h, w)
        return cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))),
                          interpolation=cv2.INTER_AREA)
    return rgb


def colorbar(height: int, vmin: float, vmax: float, fn: Callable[[np.ndarray], np.ndarray],
             unit: str = "m", n_ticks: int = 5, bar_w: int = 24, width: int = 110) -> np.ndarray:
    """A vertical colour bar panel (height, width, 3) RGB, vmax at the top, tick labels in `unit`.

    fn maps values (k,) to RGB (k, 3) uint8.
    """
    panel = np.full((height, width, 3), 255, np.uint8)
    top, bot = 12, height - 12
    vals = np.linspace(vmax, vmin, bot - top)
    panel[top:bot, 8:8 + bar_w] = fn(vals)[:, None, :]
    cv2.rectangle(panel, (8, top), (8 + bar_w, bot - 1), (0, 0, 0), 1)
    for v in np.linspace(vmin, vmax, n_ticks):
        y = int(round(top + (vmax - v) / (vmax - vmin) * (bot - 1 - top))) if vmax > vmin else top
        cv2.line(panel, (8 + bar_w, y), (8 + bar_w + 5, y), (0, 0, 0), 1)
        label = f"{v:+.1f} {unit}" if vmin < 0 < vmax else f"{v:.1f} {unit}"
        cv2.putText(panel, label, (8 + bar_w + 8, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 1, cv2.LINE_AA)
    return panel


def titled(rgb: np.ndarray, title: str, band: int = 26) -> np.ndarray:
    """Add a white title band above an RGB image."""
    head = np.full((band, rgb.shape[1], 3), 255, np.uint8)
    cv2.putText(head, title, (6, band - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                cv2.LINE_AA)
    return np.vstack([head, rgb])


def hstack(images: list[np.ndarray], gap: int = 8) -> np.ndarray:
    """Stack RGB images side by side on white, top-aligned."""
    h = max(im.shape[0] for im in images)
    parts = []
    for k, im in enumerate(images):
        pad = np.full((h, im.shape[1], 3), 255, np.uint8)
        pad[:im.shape[0]] = im
        parts.append(pad)
        if k < len(images) - 1:
            parts.append(np.full((h, gap, 3), 255, np.uint8))
    return np.hstack(parts)


def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG, atomically."""
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {path}")
    return Path(path)
