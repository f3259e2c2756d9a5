"""AE-Rec browser viewer (viser) around the reconstruction core.

The core never imports this package; `aerec view` reaches it through the `aerec.commands`
entry point, so importing the package stays cheap: the public names below load on first use.
docs/viewer.md describes it.
"""

from importlib import import_module

_EXPORTS = {
    "ViewerApp": "app",
    "ReconWorker": "worker", "DisplaySnapshot": "worker",
    "DisplayTransform": "display", "affine_display_transform": "display",
    "euclidean_display_transform": "display",
    "GcpSession": "gcp_panel", "GcpError": "gcp_panel", "PickPlane": "picking",
    "open_session": "gcp_panel", "add_observation": "gcp_panel", "new_gcp": "gcp_panel",
    "edit_gcp": "gcp_panel", "delete_gcp": "gcp_panel", "import_site_gcps": "gcp_panel",
    "set_affine_position": "gcp_panel", "pixel_from_ray": "picking",
    "run_upgrade": "results", "UpgradeOutcome": "results", "residual_table_markdown": "results",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
