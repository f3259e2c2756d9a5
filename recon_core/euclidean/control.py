"""Which control GCPs the upgrade can use, and how many it needs: the one rule.

The pipeline's pre-flight (from the GCP file, before any model), the upgrade itself (on a date
group's model), the viewer's Upgrade button and every message that counts control GCPs ask
here (on a model, through recon_core.euclidean.georef.usable_control, which triangulates as the
upgrade does), so that the viewer's "ready" and the pipeline's refusal cannot disagree.

- A control GCP is usable in a group when it is enabled, has a finite surveyed position and an
  affine position in that group: picked on the group's cloud, or triangulated from its
  observations in registered tiles of two or more of the group's images (before the models
  exist: observed in two or more of the group's images).
- The upgrade needs MIN_CONTROL of them, MIN_CONTROL_HELD when two or more of the group's images
  state their viewing direction (their lines of sight hold the height scale:
  recon_core.euclidean.held; docs/accuracy.md, "Any 4 GCPs").
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from recon_core.config import Config
    from recon_core.io.gcps import GCP

MIN_CONTROL = 4          # control GCPs H_A needs from the GCPs alone (12 unknowns, 3 equations each)
MIN_CONTROL_HELD = 3     # ... when the images' lines of sight hold it (not on one line)


def min_control(held: bool) -> int:
    """The control GCPs an upgrade needs, held by the images' lines of sight or not."""
    return MIN_CONTROL_HELD if held else MIN_CONTROL


def control_needed(images, cfg: Config) -> int:
    """The control GCPs the upgrade of these images (ImageInfo) needs: MIN_CONTROL_HELD when two
    or more of them state their viewing direction and the fit uses them, else MIN_CONTROL."""
    seen = sum(1 for im in images if getattr(im, "view", None) is not None)
    return min_control(seen >= 2 and cfg.upgrade.view_sigma_deg > 0)


def unusable_reason(role: str, enabled: bool, affine_xyz, enu) -> str | None:
    """Why a GCP cannot enter the upgrade of a group, or None."""
    if role not in ("control", "check"):
        return f"unknown role {role!r} (expected 'control' or 'check')"
    if not enabled:
        return "disabled (\"enabled\": false in the GCP file)"
    if affine_xyz is None:
        return "no affine position (observed in fewer than two images of this group)"
    if not np.all(np.isfinite(np.asarray(affine_xyz, dtype=float))):
        return "affine position is not finite"
    if not np.all(np.isfinite(np.asarray(enu, dtype=float))):
        return "surveyed position is not finite"
    return None


def usable_before_models(gcp: GCP, image_names: set[str], group: int) -> bool:
    """The pre-flight's reading of the same rule, from the GCP file alone: an enabled control
    GCP observed in two or more of these images, or picked on the group's cloud."""
    return (gcp.role == "control" and gcp.enabled
            and (sum(1 for im in gcp.observations if im in image_names) >= 2 or group in gcp.affine_picked))


def count_words(n: int, need: int) -> str:
    """How the messages say a count of usable control GCPs against the need."""
    return (f"{n} control GCP(s) seen in 2 images or more, {need} needed" if n < need
            else f"{n} control GCPs seen in 2 images or more")


def need_words() -> str:
    """The rule in the words of a hint."""
    return (f"{MIN_CONTROL} control GCPs ({MIN_CONTROL_HELD} when the images state their viewing "
            "directions), each observed in 2 images")
