"""A whole run: scene + detections -> map -> output files."""
