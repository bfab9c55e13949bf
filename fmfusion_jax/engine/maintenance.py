"""Instance-table bookkeeping: in-view test, missed observations, removal, row reset.

All functions are pure and jitted over plain `(K,)`/`(K, X)` arrays of the instance table.
Conventions for a cleared (free) row: evidence, histogram and counters 0, `created_frame` and
`last_seen_frame` -1. A zero evidence row is the prior of both fusion modes (see `label_fusion`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp


@functools.partial(jax.jit, static_argnames=("stride",))
def instances_in_view(inst_area: jax.Array, valid: jax.Array, stride: int, min_projected_pixels: float = 800.0) -> jax.Array:
    """`(K,)` bool: valid instances whose projection in this frame covers more than `min_projected_pixels`.

    `inst_area` (from `association_scores`) counts subsampled pixels, each standing for `stride**2`
    image pixels. This is the projection part of the reference's active test (> 800 px); its other
    parts (centroid depth in [0.5, 5] m, enough observed voxels) are geometric and, if wanted, are
    and-ed in by the caller.
    """
    return valid & (inst_area.astype(jnp.float32) * float(stride * stride) > min_projected_pixels)


@functools.partial(jax.jit, static_argnames=("k",))
def matched_instances(instance_for_detection: jax.Array, valid_det: jax.Array, k: int) -> jax.Array:
    """`(K,)` bool: instances that received at least one detection this frame."""
    ok = valid_det & (instance_for_detection >= 0) & (instance_for_detection < k)
    seg = jnp.where(ok, instance_for_detection, k)
    return jax.ops.segment_max(ok.astype(jnp.int32), seg, num_segments=k + 1)[:k] > 0


@jax.jit
def update_missed(missed: jax.Array, valid: jax.Array, in_view: jax.Array, matched: jax.Array) -> jax.Array:
    """`(K,)` int32: +1 for each valid instance in view but not matched this detection frame.

    The count is cumulative (a later match does not reset it), a count of negative observations.
    """
    return missed + (valid & in_view & ~matched).astype(missed.dtype)


@jax.jit
def mark_seen(last_seen_frame: jax.Array, matched: jax.Array, frame: jax.Array | int) -> jax.Array:
    """`(K,)` int32: `frame` for matched instances, unchanged otherwise."""
    return jnp.where(matched, jnp.asarray(frame, last_seen_frame.dtype), last_seen_frame)


@jax.jit
def instances_to_remove(
    missed: jax.Array, voxel_count: jax.Array, valid: jax.Array, max_missed: int = 5, min_voxels: int = 500
) -> jax.Array:
    """`(K,)` bool: valid instances missed at least `max_missed` times that have fewer than `min_voxels`.

    Reference values: ScanNet 5 and 500, SceneNN 8 and 2000.
    """
    return valid & (missed >= max_missed) & (voxel_count < min_voxels)


class TableRows(NamedTuple):
    """The per-instance fields this module, `label_fusion` and `merge` work on.

    Field names are those of the map state's `InstanceTable`, so `TableRows.of(table)` reads them from
    it and `table._replace(**rows._asdict())` writes them back.

    Attributes:
      valid: `(K,)` bool.
      label_evidence: `(K, C)` float32 (see `label_fusion`; zeros = prior).
      open_label_histogram: `(K, O)` float32 summed open-set scores.
      observations: `(K,)` int32 fused detections.
      missed: `(K,)` int32 in view but unmatched.
      voxel_count: `(K,)` int32.
      created_frame, last_seen_frame: `(K,)` int32 frame indices (-1 on a cleared row).
    """

    valid: jax.Array
    label_evidence: jax.Array
    open_label_histogram: jax.Array
    observations: jax.Array
    missed: jax.Array
    voxel_count: jax.Array
    created_frame: jax.Array
    last_seen_frame: jax.Array

    @classmethod
    def of(cls, table) -> "TableRows":
        """The fields of any object (e.g. the map state's `InstanceTable`) having them as attributes."""
        return cls(*(getattr(table, name) for name in cls._fields))


def _clear(rows: TableRows, mask: jax.Array, frame_value) -> TableRows:
    def z(x):
        m = mask if x.ndim == 1 else mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.where(m, jnp.zeros_like(x), x)

    return rows._replace(
        label_evidence=z(rows.label_evidence),
        open_label_histogram=z(rows.open_label_histogram),
        observations=z(rows.observations),
        missed=z(rows.missed),
        voxel_count=z(rows.voxel_count),
        created_frame=jnp.where(mask, jnp.asarray(frame_value, rows.created_frame.dtype), rows.created_frame),
        last_seen_frame=jnp.where(mask, jnp.asarray(frame_value, rows.last_seen_frame.dtype), rows.last_seen_frame),
    )


@jax.jit
def reset_rows(rows: TableRows, created: jax.Array, frame: jax.Array | int) -> TableRows:
    """Initializes the rows of slots created this frame: prior evidence, zero counters, created and
    last seen at `frame`, valid. Call before fusing the frame's labels into them."""
    out = _clear(rows, created, frame)
    return out._replace(valid=rows.valid | created)


class Removal(NamedTuple):
    """Result of `remove_instances`: the table and `new_id` `(K,)` int32 for `remap_instances`
    (the row itself when kept, -1 when removed or invalid)."""

    rows: TableRows
    new_id: jax.Array


@jax.jit
def remove_instances(rows: TableRows, remove: jax.Array) -> Removal:
    """Invalidates and clears the rows in `remove` (`(K,)` bool)."""
    remove = remove & rows.valid
    out = _clear(rows, remove, -1)._replace(valid=rows.valid & ~remove)
    k = remove.shape[0]
    return Removal(rows=out, new_id=jnp.where(out.valid, jnp.arange(k, dtype=jnp.int32), -1))
