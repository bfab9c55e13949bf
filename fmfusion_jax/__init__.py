"""fmfusion-jax: instance-aware semantic mapping with open-set foundation-model detections, in JAX."""

__version__ = "0.1.0"
