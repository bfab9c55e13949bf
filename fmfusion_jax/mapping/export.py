"""The instances out of a fused map: points and class distributions pulled from the engine, with their
existence and the export rules of `fmfusion_jax.instances` applied.
"""

from __future__ import annotations

import logging

import jax
import numpy as np

from fmfusion_jax.engine import extraction, step
from fmfusion_jax.instances import MapInstance, drop_far_specks, postprocess_instances, score_existence
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.mapping.builder import FusionResult
from fmfusion_jax.mapping.engine_configs import fusion_likelihood

log = logging.getLogger(__name__)


def extract_map_instances(
    result: FusionResult, label_sets: LabelSets | None = None, postprocess: bool = True
) -> list[MapInstance]:
    """The map's instances as host-side objects, post-processed as the reference does before export."""
    label_sets = label_sets or load_label_sets()
    state = jax.device_get(result.state)
    distribution = np.asarray(step.class_distribution(result.state, result.fusion_config))
    export = result.config.export
    points = extraction.extract_instance_points(
        state, result.map_config, min_weight=export.min_weight, min_share=export.min_slot_share
    )
    table = state.instances
    voxel_size = result.map_config.voxel_size
    instances = [
        MapInstance(
            instance_id=int(k),
            distribution=distribution[k],
            points=drop_far_specks(np.asarray(points[int(k)], np.float32), voxel_size, export.speck_distance),
            observations=int(table.observations[k]),
            open_label_histogram=np.asarray(table.open_label_histogram[k]),
            missed=int(table.missed[k]),
        )
        for k in np.flatnonzero(np.asarray(table.valid))
        if k in points
    ]
    likelihood = fusion_likelihood(result.config) if result.likelihood is None else result.likelihood
    instances = score_existence(instances, label_sets, export, voxel_size, likelihood)
    if postprocess:
        instances = postprocess_instances(instances, label_sets, result.config.export)
    return instances
