"""Merging over-segmented instances (paper Sec. IV-A), for all pairs of the instance table at once.

Pipeline: `class_distribution` -> `semantic_similarity` -> `merge_pairs` (with the geometry's
`instance_overlap_counts`) -> `merge_groups` -> `merge_instance_table`, whose `new_id` goes to the
`cell_edits.remap_instances`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from fmfusion_jax.engine.label_fusion import _check_mode
from fmfusion_jax.engine.maintenance import TableRows


@jax.jit
def semantic_similarity(dist: jax.Array) -> jax.Array:
    """`(K, K)` semantic similarity `sigma(a, b) = p_a . p_b` (the paper's eq. of Sec. IV-A).

    `p` is the normalized class distribution (rows summing to 1, re-normalized here to be safe), not a
    unit vector: two uniform distributions over C classes score 1/C (0.05 for C = 20), two certain ones
    of the same class 1, so the thresholds 0.15 (online) and 0.1 (post) are on this scale.
    """
    total = jnp.sum(dist, axis=1, keepdims=True)
    p = dist / jnp.where(total > 0, total, 1.0)
    return jnp.dot(p, p.T, precision=jax.lax.Precision.HIGHEST)


def _larger_first(voxel_count: jax.Array) -> jax.Array:
    """`(K, K)` bool: row i is the larger of the pair (i, j) (more voxels; ties: lower index)."""
    k = voxel_count.shape[0]
    idx = jnp.arange(k)
    vi, vj = voxel_count[:, None], voxel_count[None, :]
    return (vi > vj) | ((vi == vj) & (idx[:, None] < idx[None, :]))


def _pair_mask(valid: jax.Array) -> jax.Array:
    k = valid.shape[0]
    return valid[:, None] & valid[None, :] & ~jnp.eye(k, dtype=bool)


@jax.jit
def merge_pairs(
    similarity: jax.Array,
    overlap: jax.Array,
    voxel_count: jax.Array,
    valid: jax.Array,
    sim_threshold: float = 0.15,
    overlap_ratio: float = 0.4,
) -> jax.Array:
    """`(K, K)` symmetric bool: pairs the online merge test joins (diagonal False).

    For a pair, `a` is the larger instance by voxel count (ties: lower index) and `b` the smaller; the
    pair merges when `sigma(a, b) > sim_threshold` and `overlap[a, b] / voxel_count[b] > overlap_ratio`,
    with `overlap[a, b]` the number of b's voxels inside a's inflated volume (the geometry's
    `instance_overlap_counts`); a `b` without voxels never merges.
    """
    # The test read from (i, j) with i the larger, then mirrored: a transpose of the boolean result is
    # cheaper than one of the int32 overlaps (strided reads of 4 MB at K = 1024). Exactly one of (i, j)
    # and (j, i) has its row as the larger instance, so `directed | directed.T` is the test of each pair.
    vb = voxel_count.astype(jnp.float32)[None, :]
    ratio = jnp.where(vb > 0, overlap.astype(jnp.float32) / jnp.where(vb > 0, vb, 1.0), 0.0)
    directed = _larger_first(voxel_count) & (ratio > overlap_ratio)
    return _pair_mask(valid) & (similarity > sim_threshold) & (directed | directed.T)


@jax.jit
def post_merge_pairs(
    similarity: jax.Array,
    overlap: jax.Array,
    voxel_count: jax.Array,
    valid: jax.Array,
    sim_threshold: float = 0.1,
    iou_threshold: float = 0.2,
) -> jax.Array:
    """`(K, K)` symmetric bool: the post-processing merge test (3D IoU > 0.2 and sigma > 0.1).

    `overlap` here is the plain (not inflated) voxel overlap, `overlap[a, b]` read with `a` the larger
    as in `merge_pairs` (for plain overlap both orders are the same count):
    `IoU = o / (voxel_count[a] + voxel_count[b] - o)`.
    """
    a_first = _larger_first(voxel_count)
    ov = jnp.where(a_first, overlap, overlap.T).astype(jnp.float32)
    union = voxel_count[:, None].astype(jnp.float32) + voxel_count[None, :].astype(jnp.float32) - ov
    iou = jnp.where(union > 0, ov / jnp.where(union > 0, union, 1.0), 0.0)
    return _pair_mask(valid) & (similarity > sim_threshold) & (iou > iou_threshold)


@jax.jit
def reunion_pairs(covered: jax.Array, observations: jax.Array, valid: jax.Array, min_frames) -> jax.Array:
    """`(K, K)` symmetric bool: fragments to reunite, whatever their labels.

    `covered[a, b]` counts the detection frames in which b (in view, not detected itself) lay mostly inside
    a detection fused into a. A pair joins when b was covered at least `min_frames` times and at least as
    often as it was detected on its own (`observations[b]`): the detector keeps seeing a and b as one
    object. A neighbour that a merged mask (a chair with its table) swallows now and then is detected on
    its own more often, and stays apart. `min_frames <= 0` turns the test off.
    """
    directed = (covered >= jnp.maximum(min_frames, observations[None, :])) & (min_frames > 0)
    return _pair_mask(valid) & (directed | directed.T)


@jax.jit
def separated_pairs(separated: jax.Array, covered: jax.Array, min_frames) -> jax.Array:
    """`(K, K)` symmetric bool: pairs never to merge, because the detector keeps seeing two objects.

    `separated[a, b]` counts the frames in which two different detections were fused into a and b;
    `covered[a, b] + covered[b, a]` those in which one detection covered both. A pair is kept apart while it
    was separated at least `min_frames` times and at least as often as it was covered: a chair that a
    merged mask sometimes joins to its table, or a cabinet under a counter, stays its own object however
    much the merged masks made their volumes overlap, while the halves of a split mask join once whole
    masks have covered them more often. `min_frames <= 0` turns the test off.
    """
    apart = (separated >= min_frames) & (separated >= covered + covered.T) & (min_frames > 0)
    return apart | apart.T


@jax.jit
def fold_pair_counts(counts: jax.Array, new_id: jax.Array, valid: jax.Array) -> jax.Array:
    """`(K, K)` pair counts after a merge or removal: rows and columns summed into each row's `new_id`
    (-1: dropped), the diagonal cleared. Skipped (one test) when no valid row changed its id."""
    k = counts.shape[0]
    changed = jnp.any(valid & (new_id != jnp.arange(k, dtype=new_id.dtype)))

    def fold():
        seg = jnp.where(new_id >= 0, new_id, k)
        rows = jax.ops.segment_sum(counts, seg, num_segments=k + 1)[:k]
        folded = jax.ops.segment_sum(rows.T, seg, num_segments=k + 1)[:k].T
        return jnp.where(jnp.eye(k, dtype=bool), 0, folded).astype(counts.dtype)

    return jax.lax.cond(changed, fold, lambda: counts)


@jax.jit
def merge_groups(pairs: jax.Array, valid: jax.Array, voxel_count: jax.Array) -> jax.Array:
    """`(K,)` int32 representative of each instance's group (connected component of `pairs`); -1 if invalid.

    The representative is the group's largest instance by voxel count (ties: lower index), so a merged
    instance keeps the identity of the bigger one, as in the paper (b is integrated into a).

    Min-label propagation over ranks (rank 0 = largest instance): each round every instance takes the
    smallest label among itself and its neighbours, then jumps once through the instance its label
    names (`label <- label[node_of_rank[label]]`). Labels only decrease and always name an instance of
    the same component, so at the fixed point every component carries its minimum rank. Propagation
    alone reaches the fixed point within (component diameter + 1) <= K rounds and the jump can only
    lower labels further, so a `while_loop` stopping at convergence, capped at K + 1 rounds, is exact;
    in practice pointer jumping makes it take about log2(diameter) + 2 rounds, each O(K^2) elementwise.
    """
    k = valid.shape[0]
    adj = pairs & _pair_mask(valid)
    adj = adj | adj.T
    order = jnp.lexsort((jnp.arange(k), -voxel_count.astype(jnp.int32)))  # largest first
    node_of_rank = order.astype(jnp.int32)
    rank = jnp.zeros((k,), jnp.int32).at[order].set(jnp.arange(k, dtype=jnp.int32))
    label0 = jnp.where(valid, rank, k)

    def step(label):
        neighbour = jnp.min(jnp.where(adj, label[None, :], k), axis=1)
        label = jnp.minimum(label, neighbour)
        jumped = label[node_of_rank[jnp.clip(label, 0, k - 1)]]
        return jnp.where(label < k, jnp.minimum(label, jumped), label)

    def cond(carry):
        _, changed, rounds = carry
        return changed & (rounds <= k)

    def body(carry):
        label, _, rounds = carry
        new = step(label)
        return new, jnp.any(new != label), rounds + 1

    label, _, _ = jax.lax.while_loop(cond, body, (label0, jnp.asarray(True), jnp.asarray(0, jnp.int32)))
    return jnp.where(valid, node_of_rank[jnp.clip(label, 0, k - 1)], -1)


class MergeResult(NamedTuple):
    """Result of `merge_instance_table`.

    Attributes:
      rows: the table after the merge. Representative rows hold their group's combined record; rows
        merged away are invalid and cleared (zeros, `created_frame`/`last_seen_frame` -1); other rows
        are unchanged.
      new_id: `(K,)` int32 for `cell_edits.remap_instances`: the representative of each valid row
        (itself when not merged), -1 for invalid rows.
    """

    rows: TableRows
    new_id: jax.Array


@functools.partial(jax.jit, static_argnames=("mode",))
def merge_instance_table(rows: TableRows, representative: jax.Array, mode: str = "additive") -> MergeResult:
    """Folds every group into its representative row (`representative` from `merge_groups`).

    Evidence: summed in both modes. Additive evidence is the sum of the fused measurements, so the sum
    is exactly what one instance would hold had it received both measurement streams (and with summed
    `observations`, the paper's average `p_t = evidence / t` is the pooled average). Bayes evidence is
    the log-likelihood sum relative to the shared uniform prior, so the sum is the pooled posterior
    without counting the prior twice (then shifted to row max 0). Histograms, observations and voxel
    counts are summed (voxels holding both instances count twice: recount with the geometry's
    `instance_voxel_counts` after the remap), `missed` and `created_frame` take the minimum,
    `last_seen_frame` the maximum. A valid row whose representative is out of range stays itself.
    """
    _check_mode(mode)
    valid = rows.valid
    k = valid.shape[0]
    idx = jnp.arange(k, dtype=jnp.int32)
    rep = jnp.where((representative >= 0) & (representative < k), representative, idx)
    seg = jnp.where(valid, rep, k)
    is_rep = valid & (rep == idx)
    merged_away = valid & ~is_rep

    def fold(x, op):
        return op(x, seg, num_segments=k + 1)[:k]

    def combine(x, op, cleared=0):
        expand = (slice(None),) + (None,) * (x.ndim - 1)
        return jnp.where(is_rep[expand], fold(x, op), jnp.where(merged_away[expand], jnp.full_like(x, cleared), x))

    evidence = combine(rows.label_evidence, jax.ops.segment_sum)
    if mode == "bayes":
        evidence = jnp.where(is_rep[:, None], evidence - jnp.max(evidence, axis=1, keepdims=True), evidence)
    merged = TableRows(
        valid=is_rep,
        label_evidence=evidence,
        open_label_histogram=combine(rows.open_label_histogram, jax.ops.segment_sum),
        observations=combine(rows.observations, jax.ops.segment_sum),
        missed=combine(rows.missed, jax.ops.segment_min),
        voxel_count=combine(rows.voxel_count, jax.ops.segment_sum),
        created_frame=combine(rows.created_frame, jax.ops.segment_min, -1),
        last_seen_frame=combine(rows.last_seen_frame, jax.ops.segment_max, -1),
    )
    return MergeResult(rows=merged, new_id=jnp.where(valid, rep, -1))
