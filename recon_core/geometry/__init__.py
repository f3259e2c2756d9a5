"""Affine camera algebra, camera types and geodesy: pure maths, no I/O."""
