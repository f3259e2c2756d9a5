"""The affine camera type against the stacked algebra and exact geometry."""

from __future__ import annotations

import numpy as np

from recon_core.geometry import affine
from recon_core.geometry.camera import AffineCamera


def test_camera_projects_like_the_stacked_algebra_and_shifts_to_windows():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(2, 4))
    X = rng.normal(size=(50, 3)) * 100
    cam = AffineCamera.from_array(P)
    np.testing.assert_allclose(cam.project(X), affine.project(P[None], X)[0], atol=1e-9)
    np.testing.assert_array_equal(cam.linear, P[:, :3])
    np.testing.assert_array_equal(cam.offset, P[:, 3])
    local = cam.in_window(300, 200)
    np.testing.assert_allclose(local.project(X), cam.project(X) - [300, 200], atol=1e-9)
    assert not cam.P.flags.writeable and cam.to_array().flags.writeable


def test_backprojection_lands_on_the_plane_and_reprojects():
    rng = np.random.default_rng(1)
    cam = AffineCamera.from_array(rng.normal(size=(2, 4)))
    n = np.array([0.1, -0.2, 1.0])
    uv = rng.uniform(0, 1000, (6, 2))
    X = cam.backproject_to_plane(uv, n, 42.0)
    np.testing.assert_allclose(X @ n, 42.0, atol=1e-8)
    np.testing.assert_allclose(cam.project(X), uv, atol=1e-8)
