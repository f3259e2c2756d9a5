"""SIFT features detected once per image, by window, for the whole image.

Tiles of one image overlap by d/3; detecting per image (not per tile) means a keypoint in an
overlap is one feature observed by several tile cameras, which is what stitches the tiles of an
image into one affine frame (docs/method.md, steps "features" and "sfm").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from recon_core.config import FeatureConfig
from recon_core.io.site import ImageInfo, read_downsampled, read_window


@dataclass
class ImageFeatures:
    """Keypoints of one image in full-image pixels (col, row), with uint8 SIFT descriptors."""

    image: str
    xy: np.ndarray           # (n, 2) float64
    desc: np.ndarray         # (n, 128) uint8
    scale: np.ndarray        # (n,) float32 keypoint size
    response: np.ndarray     # (n,) float32
    gray: np.ndarray         # (n,) uint8 intensity at the keypoint (for point colours)

    def __len__(self) -> int:
        return len(self.xy)

    def without_descriptors(self) -> "ImageFeatures":
        """The same keypoints with an empty (n, 0) descriptor array: what the SfM needs once
        matching is done (the descriptors are 128 of a keypoint's ~150 bytes)."""
        return ImageFeatures(self.image, self.xy, np.empty((len(self.xy), 0), np.uint8), self.scale,
                             self.response, self.gray)

    def subset(self, idx: np.ndarray) -> "ImageFeatures":
        return ImageFeatures(self.image, self.xy[idx], self.desc[idx], self.scale[idx],
                             self.response[idx], self.gray[idx])


@dataclass
class ToneCurve:
    """Maps raw radiometry to 8 bit: percentile stretch then a square root (keeps shadows)."""

    lo: float
    hi: float

    def apply(self, a: np.ndarray) -> np.ndarray:
        t = np.clip((a - self.lo) / max(self.hi - self.lo, 1e-6), 0.0, 1.0)
        out = np.sqrt(t) * 255.0
        out = np.nan_to_num(out, nan=0.0)
        return (out + 0.5).astype(np.uint8)


def tone_curve_for(images: list[ImageInfo], percentiles=(0.5, 99.5), factor: int = 8) -> ToneCurve:
    """One tone curve shared by several images, from joint percentiles of their overviews."""
    return _curve_of([_overview_values(im, factor) for im in images], percentiles)


OVERVIEW_MAX_PX = 2048 * 2048     # an overview (tone curve, coarse link) has at most this many pixels


def overview_factor(im: ImageInfo, factor: int) -> int:
    """`factor`, or the decimation that brings the image's overview down to OVERVIEW_MAX_PX."""
    return max(factor, int(np.ceil(np.sqrt(im.width * im.height / OVERVIEW_MAX_PX))))


def _overview_values(im: ImageInfo, factor: int = 8) -> np.ndarray:
    """The image's values for its tone curve, from its overview (finite ones; the full-resolution
    sample windows of the blank check when the overview has too few: a float image with NaN or
    infinite pixels scattered everywhere). The overview is decimated by `factor`, or more for an
    image over 16,000 px a side: at most OVERVIEW_MAX_PX pixels (a 40,000 px scene at factor 8
    was 25 Mpx, 0.6 GB of copies for two percentiles)."""
    f = overview_factor(im, max(1, min(factor, min(im.width, im.height) // 64)))
    ov = read_downsampled(im, f)
    v = ov[np.isfinite(ov)].ravel()
    if len(v) < 0.05 * ov.size:
        from recon_core.io.site import sample_values

        v = sample_values(im.path)[0]
    return v if len(v) else np.zeros(1)


def _curve_of(vals: list[np.ndarray], percentiles) -> ToneCurve:
    v = np.concatenate(vals) if vals else np.zeros(1)
    lo, hi = np.percentile(v, percentiles)
    return ToneCurve(float(lo), float(hi))


def group_tone_curves(images: list[ImageInfo], percentiles=(0.5, 99.5)) -> tuple[list[ToneCurve], list[str]]:
    """One shared tone curve for a group's images (same radiometry, same 8-bit mapping), except
    for an image whose own value range does not fit the shared one (a float32 reflectance image
    among uint16 counts would map to black: no keypoint): that image gets its own curve, and a
    warning says so. Returns (curve per image, warnings)."""
    vals = [_overview_values(im) for im in images]          # each overview read once
    owns = [_curve_of([v], percentiles) for v in vals]
    # the group's typical range: the median image's (an outlier, wider or narrower, cannot
    # drag it), then the shared curve from the images that fit it
    ref_lo = float(np.median([o.lo for o in owns]))
    ref_hi = float(np.median([o.hi for o in owns]))
    ref_w = max(ref_hi - ref_lo, 1e-12)

    def fits(o: ToneCurve) -> bool:
        w = max(o.hi - o.lo, 1e-12)
        overlap = max(0.0, min(o.hi, ref_hi) - max(o.lo, ref_lo))
        return 0.2 < w / ref_w < 5.0 and overlap / min(w, ref_w) >= 0.5

    fit = [v for v, o in zip(vals, owns) if fits(o)]
    shared = _curve_of(fit or vals, percentiles)
    curves, warnings = [], []
    for im in images:
        share = nonfinite_share(im)
        if share >= NONFINITE_WARN_SHARE:
            warnings.append(f"{im.name}: {100 * share:.0f} % of its pixels (where sampled) are NaN or infinite: "
                            f"no measurement there; gaps up to {2 * GAP_FILL_RADIUS_PX} px wide (lines, dropped "
                            "pixels) are filled for the feature detection, wider ones give no tie points")
    for im, own in zip(images, owns):
        if not fits(own):
            curves.append(own)
            warnings.append(f"{im.name}: its values ({im.dtype}, {own.lo:.4g} to {own.hi:.4g}) do not "
                            f"match the other images of its group ({ref_lo:.4g} to {ref_hi:.4g}); "
                            "stretched on its own for feature detection. Is it the same kind of "
                            "product (band, processing level, units)?")
        else:
            curves.append(shared)
    return curves, warnings


NONFINITE_WARN_SHARE = 0.01    # an image with this share of NaN or infinite pixels is said
GAP_FILL_RADIUS_PX = 2          # gaps of no measurement up to twice this wide are filled for SIFT


def nonfinite_share(im: ImageInfo) -> float:
    """The share of NaN or infinite pixels of a float image in the full-resolution windows the
    blank check samples (0 for an integer image)."""
    if not str(im.dtype).startswith("float"):
        return 0.0
    import warnings

    import rasterio
    from rasterio.windows import Window

    bad = total = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(im.path) as ds:
            w, h = min(ds.width, 64), min(ds.height, 64)
            for fy in (0.1, 0.5, 0.9):
                for fx in (0.1, 0.5, 0.9):
                    a = ds.read(1, window=Window(int(fx * (ds.width - w)), int(fy * (ds.height - h)), w, h))  # pyright: ignore[reportCallIssue]
                    bad += int(np.count_nonzero(~np.isfinite(a)))
                    total += a.size
    return bad / max(total, 1)


def fill_thin_gaps(raw: np.ndarray, radius: int = GAP_FILL_RADIUS_PX) -> np.ndarray:
    """`raw` (float, NaN where there is no measurement) with its thin gaps (missing lines or
    pixels, up to 2 radius wide) filled by the mean of the measured pixels around them, so that
    SIFT neither loses the keypoints near them (the detection mask) nor describes the keypoints
    beside them with a false edge. Wider gaps stay NaN (masked)."""
    bad = ~np.isfinite(raw)
    if not bad.any():
        return raw
    k = 2 * radius + 1
    val = np.where(bad, 0.0, raw).astype(np.float32)
    num = cv2.boxFilter(val, -1, (k, k), normalize=False, borderType=cv2.BORDER_REFLECT)
    den = cv2.boxFilter((~bad).astype(np.float32), -1, (k, k), normalize=False, borderType=cv2.BORDER_REFLECT)
    fill = bad & (den >= 0.2 * k * k)        # a 4 px wide gap's middle rows: 5 of 25
    out = raw.copy()
    out[fill] = num[fill] / den[fill]
    return out


def _blocks(length: int, block: int, margin: int):
    """(read_start, read_end, core_start, core_end) along one axis."""
    for c0 in range(0, length, block):
        c1 = min(c0 + block, length)
        yield max(0, c0 - margin), min(length, c1 + margin), c0, c1


def detect_blocks(image: ImageInfo, cfg: FeatureConfig) -> int:
    """How many blocks detect_image reads the image in (its progress steps)."""
    return (sum(1 for _ in _blocks(image.height, cfg.detect_block, 48))
            * sum(1 for _ in _blocks(image.width, cfg.detect_block, 48)))


def detect_image(image: ImageInfo, cfg: FeatureConfig, tone: ToneCurve | None = None,
                 spill: Path | None = None, on_block=None) -> ImageFeatures:
    """Detect SIFT on the whole image, read by blocks with a margin, deduplicated by block cores.

    With `spill`, each block's descriptors are appended to that file as it is detected (raw
    uint8 rows of 128) and come back as a read-only memory map of it: the process holds the
    keypoints' 25 bytes (position, size, response, intensity) but not their 128 bytes of
    descriptor (a 40,000 px scene: ~30 M keypoints, 4 GB of descriptors). Without it they are
    held in memory. The same keypoints either way. `on_block()` is called after each block (a
    progress step; it may raise to stop the detection, e.g. on Ctrl-C)."""
    tone = tone or tone_curve_for([image], cfg.stretch_percentiles)
    budget = max(500, int(cfg.max_features_per_mpx * image.width * image.height / 1e6))
    sift = cv2.SIFT_create(nfeatures=0, contrastThreshold=cfg.contrast_threshold)  # pyright: ignore[reportAttributeAccessIssue]
    margin = 48
    parts, descs = [], []
    sink = open(spill, "wb") if spill is not None else None
    try:
        for r0, r1, rc0, rc1 in _blocks(image.height, cfg.detect_block, margin):
            for c0, c1, cc0, cc1 in _blocks(image.width, cfg.detect_block, margin):
                if on_block is not None:
                    on_block()
                raw = fill_thin_gaps(read_window(image, c0, r0, c1 - c0, r1 - r0))
                img8 = tone.apply(raw)
                mask = np.isfinite(raw).astype(np.uint8) * 255
                del raw
                kps, desc = sift.detectAndCompute(img8, mask)
                if desc is None or not kps:
                    continue
                pts = np.array([k.pt for k in kps], dtype=np.float64) + (c0, r0)
                core = ((pts[:, 0] >= cc0) & (pts[:, 0] < cc1) & (pts[:, 1] >= rc0) & (pts[:, 1] < rc1))
                idx = np.flatnonzero(core)
                if not len(idx):
                    continue
                d8 = _to_uint8_desc(desc[idx])
                # exact duplicates (same position and descriptor) share a block core: dropped here
                keep = _unique_rows(pts[idx], d8)
                idx, d8 = idx[keep], d8[keep]
                ij = np.clip(np.round(pts[idx] - (c0, r0)).astype(int), 0, [img8.shape[1] - 1, img8.shape[0] - 1])
                parts.append((pts[idx], np.array([kps[i].size for i in idx], np.float32),
                              np.array([kps[i].response for i in idx], np.float32), img8[ij[:, 1], ij[:, 0]]))
                if sink is not None:
                    sink.write(np.ascontiguousarray(d8).tobytes())
                else:
                    descs.append(d8)
    finally:
        if sink is not None:
            sink.close()
    if not parts:
        return ImageFeatures(image.name, np.zeros((0, 2)), np.zeros((0, 128), np.uint8),
                             np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.uint8))
    xy, size, resp, gray = (np.concatenate(p) for p in zip(*parts))
    del parts
    desc = np.concatenate(descs) if sink is None or spill is None else _mapped_desc(spill, len(xy))
    feats = ImageFeatures(image.name, xy, desc, size, resp, gray)
    if len(feats) > budget:
        keep = np.sort(np.argsort(-feats.response, kind="stable")[:budget])
        if sink is None:
            feats = feats.subset(keep)
        else:                       # the kept rows copied to a new file by chunks, then renamed
            assert spill is not None            # the sink writes to it
            tmp = spill.with_name(spill.name + ".kept")
            with open(tmp, "wb") as out:
                for k in range(0, len(keep), 1 << 20):
                    out.write(np.ascontiguousarray(desc[keep[k:k + (1 << 20)]]).tobytes())
            feats = desc = None          # the old map closed before its file is replaced
            tmp.replace(spill)
            feats = ImageFeatures(image.name, xy[keep], _mapped_desc(spill, len(keep)), size[keep],
                                  resp[keep], gray[keep])
    return feats


def _mapped_desc(path: Path, n: int) -> np.ndarray:
    """n descriptors written raw to `path`, as a read-only memory map."""
    return np.memmap(path, dtype=np.uint8, mode="r", shape=(n, 128)) if n else np.zeros((0, 128), np.uint8)


def _to_uint8_desc(desc: np.ndarray) -> np.ndarray:
    """OpenCV's float SIFT descriptors hold integers 0..255: store them as uint8."""
    return np.clip(np.round(desc), 0, 255).astype(np.uint8)


def _unique_rows(xy: np.ndarray, desc: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the first of each set of exact duplicates (same position to 0.01
    px and same first descriptor bytes) that SIFT may return."""
    key = np.round(xy * 100).astype(np.int64)
    _, first = np.unique(np.concatenate([key, desc[:, :4].astype(np.int64)], axis=1), axis=0,
                         return_index=True)
    return np.sort(first)


def detect_overview(image: ImageInfo, factor: int, tone: ToneCurve, max_features: int = 4000):
    """SIFT on a downsampled copy of the whole image: (xy in full-image pixels, descriptors).
    The copy is decimated by `factor`, or more for an image over 16,000 px a side: at most
    OVERVIEW_MAX_PX pixels (SIFT's pyramid of a 5,000 px copy of a 40,000 px scene, doubled
    in size first, would be several GB)."""
    factor = overview_factor(image, factor)
    ov = read_downsampled(image, factor)
    img8 = tone.apply(ov)
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=0.01)  # pyright: ignore[reportAttributeAccessIssue]
    kps, desc = sift.detectAndCompute(img8, None)
    if desc is None:
        return np.zeros((0, 2)), np.zeros((0, 128), np.uint8)
    sx = image.width / ov.shape[1]
    sy = image.height / ov.shape[0]
    xy = np.array([k.pt for k in kps], dtype=np.float64)
    xy = np.stack([(xy[:, 0] + 0.5) * sx - 0.5, (xy[:, 1] + 0.5) * sy - 0.5], axis=1)
    return xy, _to_uint8_desc(desc)
