"""`python -m fmfusion_jax.cli ...`: the `fmfusion` command."""

from fmfusion_jax.cli import entry

entry()
