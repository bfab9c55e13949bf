"""The applications of the `fmfusion` command: each app is one module or package here, imports only the
layers below (runner, sources, io, evaluation, simulation, ...) and never another app."""
