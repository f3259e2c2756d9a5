"""AE-Rec reconstruction core: affine reconstruction per date group, Euclidean upgrade by GCPs.

The core never imports the viewer (`aerec_viewer`).
"""

__version__ = "0.1.0"
