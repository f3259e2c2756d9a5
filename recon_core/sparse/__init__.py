"""Step 2 of the method: features, matching, tracks, incremental affine SfM, bundle adjustment."""
