"""The pushbroom model and the corrections it makes possible: the one owner of the bend.

Independent affine tile cameras leave a smooth bend of the structure nearly free; 4 GCPs fix an
affine map, not a bend. Everything that models, checks or removes that bend lives here, between
the shared layers (geometry, model) and the stages that call it: the per-image pushbroom model
and its check (pushbroom), the per-image tie (image_model), the sparse stage's closing
adjustments in their order (closing), what the views can see of a bend (observability), the
metric bend step (metric), and the bend held by control GCPs (gcp) or by a reference DEM (dem).
Each of the last three returns a BendFit (result): its warp or None, the summary the report gives
(with "applied", and "reason" when it stood aside), and, for the GCP and DEM bends, the H_A that
goes with the warp.
"""
