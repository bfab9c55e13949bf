"""Pictures of maps and their evaluation (NumPy + OpenCV; no engine)."""
