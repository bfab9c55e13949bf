"""`python -m fmfusion_jax.cli ...`: the `fmfusion` command."""

import sys

from fmfusion_jax.cli import main

sys.exit(main())
