"""The label likelihood `L[o, c] = p(y = o, o in prompt | c)`: summarized from data, and calibrated.

- `summarize`: the paper's Appendix B. From frames with ground-truth 2D instances and detections, the
  tagging likelihood p(o in prompt | c) and the detection likelihood p(y = o | o in prompt, c), whose
  product is the likelihood matrix (pure NumPy counting, and a driver over scenes).
- `calibrate`: the matrix fitted by gradient descent (`jax.grad` through the additive label fusion's
  class distribution) to the ground-truth classes of fused instances; parametrized so that it stays a
  valid likelihood.
- `matching`: a fused map's instances matched to the ground-truth instances (their histograms of
  open-set scores and true classes are what calibration and label accuracy need).
- `workflow`: the scene sets, runs and reports behind `fmfusion likelihood summarize | calibrate`.
"""
