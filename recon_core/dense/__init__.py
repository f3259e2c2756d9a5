"""Step 3 of the method: per tile pair rectification and stereo matching, dense tracks, triangulation."""
