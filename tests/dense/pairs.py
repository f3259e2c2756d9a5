"""Rectified test pairs with a known disparity field (d = u_right - u_left), shared by the
matchers' tests: a smooth field by fixed-point inversion, and a 'building' (a block at a higher
disparity than the ground) whose right image shows the ground it hides."""

from __future__ import annotations

import cv2
import numpy as np


def texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, (h, w)), (0, 0), 1.2).astype(np.float32)


def smooth_pair(d_of, h=120, w=220, seed=0):
    """left(u, v) = T(u, v); right(u + d(u, v), v) = left(u, v) for a smooth field d_of(u, v): each
    right pixel's source u_l = u_r - d(u_l, v) by fixed-point iteration. Returns left, right
    (uint8) and d on the left grid."""
    T = texture(h, w + 80, seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    ul = u.copy()
    for _ in range(20):
        ul = u - d_of(ul, v)
    left = cv2.remap(T, u + 40, v, cv2.INTER_CUBIC)
    right = cv2.remap(T, ul + 40, v, cv2.INTER_CUBIC)
    return (np.clip(left, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8),
            d_of(u, v))


def block_pair(h=120, w=220, seed=3):
    """d = 1 on the ground, 7 on a 50 x 60 px block (u 80-140, v 35-85). Returns left, right, d
    on the left grid, and masks: the block and the ground away from its edges, and the ground
    the block hides in the right image (the 6 px strip right of it)."""
    T = texture(h, w + 80, seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    inside = (u >= 80) & (u < 140) & (v >= 35) & (v < 85)
    d_true = np.where(inside, 7.0, 1.0).astype(np.float32)
    left = np.clip(cv2.remap(T, u + 40, v, cv2.INTER_CUBIC), 0, 255).astype(np.uint8)
    on_block = (u - 7 >= 80) & (u - 7 < 140) & (v >= 35) & (v < 85)
    right = np.clip(cv2.remap(T, np.where(on_block, u - 7, u - 1) + 40, v, cv2.INTER_CUBIC),
                    0, 255).astype(np.uint8)
    block = (u >= 84) & (u < 136) & (v >= 39) & (v < 81)
    ground = ((u < 76) | (u >= 150)) & (u >= 20) & (u < w - 20) & (v >= 8) & (v < h - 8)
    hidden = (u >= 141) & (u < 146) & (v >= 39) & (v < 81)
    return left, right, d_true, block, ground, hidden
