"""NumPy oracles of the jitted engine kernels and analytic test scenes (test code, not shipped)."""
