"""AE-Rec browser viewer (viser) around the reconstruction core."""
