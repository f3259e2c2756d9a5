"""How well a control set fixes H_A's height scale, in plain words, and when to refuse it.

Flat land is the normal case: the height scale of H_A is set by how far the GCPs lie off their
best-fit plane, and by the images' lines of sight when their metadata states them
(recon_core.euclidean.held). Two figures, one definition: the standard deviation of the height
of a point `structure_height_m` above the GCPs (a 40 m roof by default), "the expected height
error".

- Before any compute (the pre-flight), only the GCPs' ground coordinates are known: the figure
  is sigma / d_rms times the structure's height, sigma a GCP's height uncertainty (0.4 m),
  d_rms the GCPs' RMS distance from their plane: conservative (it ignores the averaging over
  N points).
- After the fit, the figure comes from the fit's own covariance (`looseness`): the GCPs'
  triangulation covariances from their image observations and, when the images' lines of sight
  hold the fit, theirs. Both the GCPs' figure alone and the figure with the images are reported.

Only what no data can fix is refused: fewer than 3 control GCPs, collinear ones, or an expected
height error above REFUSE_HEIGHT_ERROR_M (25 % of the structure) after the fit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_core.euclidean.held import Looseness

REFUSE_HEIGHT_ERROR_M = 10.0   # expected error on the quoted structure (25 % of 40 m)
WITH_PRIOR = " (with the cameras' metric constraint)"
VIEW_ADVICE = ("or give each image its viewing angles (\"view\" in its sidecar; `aerec site init` "
               "reads them from the products' metadata): they hold the height scale")


def plane(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The best-fit plane of (n, 3) points: its unit normal (pointing up) and the singular
    values of the centred coordinates."""
    _, s, Vt = np.linalg.svd(X - X.mean(axis=0), full_matrices=False)
    return Vt[-1] * (1.0 if Vt[-1][2] >= 0 else -1.0), s


def conditioning(X_enu: np.ndarray, affine_height_sigma_m: float = 0.4,
                 structure_height_m: float = 40.0, warn_height_error_m: float = 2.0,
                 poor_height_error_m: float = 5.0, prior_ratio: float | None = None,
                 loose: Looseness | None = None, loose_gcp: Looseness | None = None,
                 images: int = 0, best_next: dict | None = None) -> dict[str, Any]:
    """How well the control GCPs (and the images) fix the height scale of H_A.

    Args:
        X_enu: (n, 3) control GCPs in ENU metres.
        affine_height_sigma_m: a GCP's height uncertainty for the figure before any fit.
        structure_height_m: height of the structure the error is quoted for (e.g. a 40 m roof).
        warn_height_error_m, poor_height_error_m: thresholds on the expected height error (m).
        prior_ratio: the metric prior's ratio of height sigmas (recon_core.euclidean.metric_prior).
        loose: what the fit leaves loose (its covariance); None: the figure before any fit.
        loose_gcp: the same for the GCPs alone, when `loose` is the fit with `images` images.
        best_next: {"id", "expected_height_error_m"}: the check point that would help most as
            a control point.
    Returns:
        dict with n, plane_normal, plane_rms_m (d_rms), plane_max_m, singular_ratio,
        expected_height_scale_error (fraction), expected_height_error_m, structure_height_m,
        expected_edge_error_m and site_radius_m (the tilt's height error at the site's edge, when
        the fit knows how far the site reaches),
        basis ("plane": before any fit; "fit": the fit's covariance), gcp_only and with_images
        (looseness: height scale, shear and tilt sigmas) after a fit, level ("ok" | "warning" |
        "poor" | "degenerate") and warning (plain words or None).
    """
    X = np.asarray(X_enu, dtype=np.float64).reshape(-1, 3)
    out: dict[str, Any] = {"n": len(X), "affine_height_sigma_m": float(affine_height_sigma_m),
                           "structure_height_m": float(structure_height_m),
                           "warn_height_error_m": float(warn_height_error_m),
                           "poor_height_error_m": float(poor_height_error_m)}
    if len(X) < 3:
        out.update(level="degenerate", plane_rms_m=0.0, singular_ratio=0.0,
                   expected_height_scale_error=float("inf"), expected_height_error_m=float("inf"),
                   warning=f"only {len(X)} control GCPs: the height scale is undetermined; add GCPs, "
                           "at least 4 not all on one plane, or 3 with the images' viewing angles")
        return out
    normal, s = plane(X)
    d = (X - X.mean(axis=0)) @ normal
    d_rms = float(np.sqrt(np.mean(d ** 2)))
    if loose is None:
        frac = affine_height_sigma_m / d_rms if d_rms > 0 else float("inf")
        out["basis"] = "plane"
    else:
        frac = loose.height_scale
        out["basis"] = "fit"
        out["gcp_only"] = (loose_gcp or loose).to_dict()
        if images:
            out["with_images"] = loose.to_dict()
            out["images"] = int(images)
    if prior_ratio is not None and np.isfinite(prior_ratio):
        out.update(gcp_only_expected_height_error_m=float(frac * structure_height_m),
                   metric_prior_ratio=float(prior_ratio))
        frac = frac * prior_ratio if np.isfinite(frac) else frac
    err_m = frac * structure_height_m
    edge_m = loose.expected_edge_error_m if loose is not None and loose.site_radius_m > 0 else 0.0
    if loose is not None and loose.site_radius_m > 0:
        out.update(expected_edge_error_m=float(edge_m), site_radius_m=float(loose.site_radius_m))
    worst = max(err_m, edge_m)
    if not np.isfinite(worst):
        level = "degenerate"
    else:
        level = "ok" if worst <= warn_height_error_m else ("warning" if worst <= poor_height_error_m
                                                          else "poor")
    if best_next:
        out["best_next_gcp"] = best_next
    out.update(plane_normal=normal.tolist(), plane_rms_m=d_rms, plane_max_m=float(np.abs(d).max()),
               singular_ratio=float(s[-1] / s[0]) if s[0] > 0 else 0.0,
               expected_height_scale_error=float(frac), expected_height_error_m=float(err_m),
               level=level)
    out["warning"] = _warning(out, d_rms, frac, err_m, affine_height_sigma_m, prior_ratio)
    return out


def _warning(c: dict, d_rms: float, frac: float, err_m: float, sigma: float,
             prior_ratio: float | None) -> str | None:
    """Plain-words warning for a set that fixes the height scale poorly, or None."""
    level, h, target = c["level"], c["structure_height_m"], c["warn_height_error_m"]
    if level == "ok":
        return None
    edge = c.get("expected_edge_error_m", 0.0)
    if np.isfinite(err_m) and np.isfinite(edge) and edge > err_m:
        return (f"the control GCPs lie nearly on one line, so the tilt across it is poorly fixed: expected "
                f"height error about {edge:.1f} m at the site's edge, {c['site_radius_m']:.0f} m from their "
                "centre" + (f", with the {c['images']} images' lines of sight" if c.get("images") else "")
                + ". Add a control GCP away from that line.")
    images = c.get("images", 0)
    nxt = c.get("best_next_gcp")
    better = (f"; {nxt['id']}, now a check point, would bring it to {nxt['expected_height_error_m']:.1f} m "
              "as a control point") if nxt else ""
    advice = ("Add a GCP well off that plane (a roof, a hill top or a valley bottom)" + better
              + ("" if images else "; " + VIEW_ADVICE) + ".")
    if not np.isfinite(err_m) or err_m > 1000.0:
        return (f"the control GCPs lie within {d_rms:.3f} m (RMS) of one plane"
                + (f" and the {images} images' lines of sight do not make up for it" if images else "")
                + f": the height scale is undetermined (expected height error over 1 km on a {h:.0f} m "
                  f"structure). " + advice)
    prior = prior_ratio is not None and np.isfinite(prior_ratio) and prior_ratio > 0
    text = (f"the control GCPs lie within {d_rms:.2f} m (RMS) of one plane, so the height scale is "
            f"poorly fixed: expected height error about {100 * frac:.0f} %, i.e. {err_m:.1f} m on a "
            f"{h:.0f} m structure")
    if images:
        g = (c.get("gcp_only") or {}).get("expected_height_error_m")
        text += f" with the {images} images' lines of sight" + (
            f" (the GCPs alone: {g:.1f} m)" if g is not None else " (the GCPs alone do not fix it)")
    elif prior:
        assert prior_ratio is not None
        text += f"{WITH_PRIOR}; the GCPs alone: {err_m / prior_ratio:.1f} m" + (
            "; the constraint is a linear estimate that cannot be relied on to make up for a set this "
            "flat: the check points will tell" if err_m / prior_ratio > REFUSE_HEIGHT_ERROR_M else "")
    if c.get("basis") == "plane":
        need = sigma * h / target
        advice = advice[:-1] + f"; about {need:.0f} m RMS off-plane spread brings it to {target:g} m."
    return text + ". " + advice


def flat_gcp_refusal(cond: dict[str, Any]) -> str | None:
    """The refusal for a control set that cannot fix the height scale (expected height error
    above REFUSE_HEIGHT_ERROR_M on the quoted structure, or fewer than 3 points), or None. Between
    the "poor" level (5 m) and this it is a warning. `upgrade.allow_flat_gcps` overrides it."""
    worst = max(cond.get("expected_height_error_m", 0.0), cond.get("expected_edge_error_m", 0.0))
    if cond.get("level") != "degenerate" and not worst > REFUSE_HEIGHT_ERROR_M:
        return None
    return (f"refused: {cond.get('warning') or 'the control GCPs cannot fix the height scale'} "
            "To go on anyway, set upgrade.allow_flat_gcps = true (aerec run --config FILE).")
