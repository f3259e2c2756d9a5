"""File formats and the output layout: the site, GCP files, PLY, GeoTIFF, model files."""
