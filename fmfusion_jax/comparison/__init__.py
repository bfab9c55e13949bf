"""Comparisons of mapping methods on a set of scenes, shared by `fmfusion experiment` and `fmfusion experiment
--robustness` (`apps.experiments`, `apps.robustness`): the methods, the scenes they run on, one run of a
method on a scene (fused, exported, scored) and the pooled scores, and the markdown tables of the reports."""
