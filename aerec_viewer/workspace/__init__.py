"""The image workspace: GCPs placed side by side in every image that sees them, on a small web
page of its own (one 2D canvas per image: pan, zoom at the cursor, a click places the GCP
selected in that tab), served by the viewer's process beside viser. Each browser tab keeps its
own selection, zoom and contrast; the working GCP set is the viewer's (docs: viewer.md,
"The image workspace")."""

from .api import ApiError, WorkspaceApi
from .server import WorkspaceServer

__all__ = ["ApiError", "WorkspaceApi", "WorkspaceServer"]
