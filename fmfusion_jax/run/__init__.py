"""A whole run: scene + detection source -> fused map -> output files (and a score when ground truth exists).

By concern: `scene_fusion` (`SceneFusion`: a scene's frames fused with bad frames skipped or fatal, read-ahead,
detections ahead, checkpoints, a stop between frames), `checkpoint`, `folder` (the output folder checked,
locked, written aside and swapped in whole), `outputs` (the registry of output writers) and `command`
(`run_and_export`, `write_outputs`, the closing summary: what `fmfusion run`, `demo`, `batch` and the
experiments share).
"""
