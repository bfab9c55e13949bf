"""Data association between a frame's detections and the map's instances (paper Sec. III-C).

Everything is counted per subsampled pixel: the detection image gives the detection at each pixel,
`pixel_instances` (from the geometry) the instances seen there. One `segment_sum` per instance slot over
the pixels yields the mask/projection intersections and both areas, hence the score matrix `[N, K]` for
all detections and instances at once. Areas are in subsampled pixels:
at stride `s` one pixel stands for `s * s` image pixels; ratios (IoU, overlap) are unaffected up to
sampling error.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

METRICS = ("iou", "projection_overlap")


class AssociationCounts(NamedTuple):
    """Pixel counts of one frame (subsampled pixels).

    Attributes:
      intersection: `(N, K)` int32, pixels of detection n where instance k is seen.
      det_area: `(N,)` int32, pixels of detection n.
      inst_area: `(K,)` int32, pixels where instance k is seen (the projected instance mask r_k).
    """

    intersection: jax.Array
    det_area: jax.Array
    inst_area: jax.Array


@functools.partial(jax.jit, static_argnames=("n_max", "k"))
def association_scores(det_image: jax.Array, pixel_instances: jax.Array, n_max: int, k: int) -> AssociationCounts:
    """Intersections and areas of detection masks and projected instances, by one `segment_sum`.

    Args:
      det_image: `(Hs, Ws)` int32 detection index in `[0, n_max)` or -1.
      pixel_instances: `(Hs, Ws, S)` int32 instance ids in `[0, k)` seen at each pixel, -1 = none.
        An id repeated in several slots of a pixel counts once.
      n_max, k: number of detection rows and instance rows (static).

    Returns:
      `AssociationCounts(intersection (N, K), det_area (N,), inst_area (K,))`, int32.
    """
    return association_counts(det_image, [pixel_instances[..., s] for s in range(pixel_instances.shape[-1])], n_max, k)


def association_counts(det_image: jax.Array, instance_slots, n_max: int, k: int) -> AssociationCounts:
    """`association_scores` (unjitted) with the instances seen as a list of S slots, int32 `(Hs, Ws)` each
    (`instance_volume.pixel_instance_slots`)."""
    ids = [slot.reshape(-1) for slot in instance_slots]
    det = det_image.reshape(-1)
    num_slots = len(ids)
    # A slot counts if it holds an id that no earlier slot of the same pixel holds.
    counts = [(ids[s] >= 0) & (ids[s] < k) for s in range(num_slots)]
    for s in range(num_slots):
        for t in range(s):
            counts[s] = counts[s] & (ids[s] != ids[t])
    # One table per slot, rows: detection + 1 (row 0: no detection), columns: instance + 1. Slot 0 counts every
    # pixel once, in column 0 when it holds no id: its rows sum to the detection areas. (One segment_sum of a
    # pseudo column and the S slots, S + 1 updates per pixel, cost 1.5x as much on the CPU.)
    row = jnp.where((det >= 0) & (det < n_max), det + 1, 0) * (k + 1)
    tables = [
        jax.ops.segment_sum(
            jnp.ones(det.shape, jnp.int32) if s == 0 else counts[s].astype(jnp.int32),
            row + jnp.where(counts[s], ids[s] + 1, 0),
            num_segments=(n_max + 1) * (k + 1),
        ).reshape(n_max + 1, k + 1)
        for s in range(num_slots)
    ]
    per_instance = functools.reduce(jnp.add, [t[:, 1:] for t in tables])
    det_area = jnp.sum(tables[0][1:], axis=1)
    return AssociationCounts(intersection=per_instance[1:], det_area=det_area, inst_area=jnp.sum(per_instance, axis=0))


@functools.partial(jax.jit, static_argnames=("metric",))
def association_score_matrix(
    intersection: jax.Array, det_area: jax.Array, inst_area: jax.Array, metric: str = "projection_overlap"
) -> jax.Array:
    """`(N, K)` float32 association scores in [0, 1] (0 where the denominator is 0).

    metric (static):
      "iou": |m ∩ r| / |m ∪ r|, the paper's Omega (Sec. III-C); the C++ version thresholds it at 0.3.
      "projection_overlap": |m ∩ r| / |r|, the share of the projected instance covered by the mask,
        the rule of the authors' Python pipeline behind the paper's results (threshold 0.5).
    """
    inter = intersection.astype(jnp.float32)
    if metric == "iou":
        denom = det_area[:, None].astype(jnp.float32) + inst_area[None, :].astype(jnp.float32) - inter
    elif metric == "projection_overlap":
        denom = jnp.broadcast_to(inst_area[None, :].astype(jnp.float32), inter.shape)
    else:
        raise ValueError(f"unknown association metric {metric!r}; expected one of {METRICS}")
    return jnp.where(denom > 0, inter / jnp.where(denom > 0, denom, 1.0), 0.0)


@functools.partial(jax.jit, static_argnames=("one_to_one",))
def match_detections(
    scores: jax.Array,
    valid_det: jax.Array,
    valid_inst: jax.Array,
    threshold: float,
    one_to_one: bool = True,
    rank: jax.Array | None = None,
) -> jax.Array:
    """Matches detections to instances: `(N,)` int32 instance index or -1.

    A pair is a candidate when both are valid and its score is strictly above `threshold` (the paper:
    "larger than a threshold"). Candidates are taken best first by `rank` `(N, K)` (default: `scores`): with
    projection-overlap scores and IoU ranks, a wall's mask that covers a door's projection whole (overlap 1)
    goes to the wall's instance, of its own size, and not to the door.

    one_to_one=True (default): deterministic greedy assignment by descending rank; each instance takes
    at most one detection. Rounds of a loop (one per detection that has a candidate) each take the best
    remaining candidate (ties: lower detection index, then lower instance index) and retire its detection
    and instance.
    one_to_one=False: the paper's per-detection rule read literally; each detection takes its best
    candidate instance, so an instance may take several detections.

    The two agree under the reference Python configuration (projection_overlap > 0.5): detection masks
    are disjoint (`detection_pixel_image` partitions the pixels), so the intersections of one instance
    with all detections sum to at most |r|, and at most one detection can cover more than half of it.
    With IoU > 0.3 (C++ configuration) two halves of a split mask can both pass; one-to-one then sends
    the weaker one to a new instance, which the merge step can join later if semantics and volume agree.
    """
    n, k = scores.shape
    order = scores if rank is None else rank
    cand = jnp.where(valid_det[:, None] & valid_inst[None, :] & (scores > threshold), order, -jnp.inf)
    if not one_to_one:
        best = jnp.argmax(cand, axis=1).astype(jnp.int32)
        return jnp.where(jnp.max(cand, axis=1) > -jnp.inf, best, -1)

    # Greedy on each detection's best min(N, K) candidates only: when detection d is matched, at most
    # N - 1 instances have been retired by other detections, so its pick is among its top N. `top_k`
    # keeps the lower instance index first among equal scores, so ties resolve as on the full matrix.
    t = min(n, k)
    top_score, top_inst = jax.lax.top_k(cand, t)  # (N, T)
    top_inst = top_inst.astype(jnp.int32)
    rows = jnp.arange(n, dtype=jnp.int32)[:, None]

    def body(_, carry):
        top_score, match = carry
        flat = jnp.argmax(top_score).astype(jnp.int32)
        r, c = flat // t, top_inst.reshape(-1)[flat]
        ok = top_score.reshape(-1)[flat] > -jnp.inf
        match = jnp.where(ok & (jnp.arange(n) == r), c, match)
        top_score = jnp.where(ok & ((rows == r) | (top_inst == c)), -jnp.inf, top_score)
        return top_score, match

    # a round matches one detection with a candidate or ends the matching: no more rounds than such detections
    rounds = jnp.sum(jnp.any(top_score > -jnp.inf, axis=1), dtype=jnp.int32)
    _, match = jax.lax.fori_loop(0, rounds, body, (top_score, jnp.full((n,), -1, jnp.int32)))
    return match


class Allocation(NamedTuple):
    """Result of `allocate_instances`.

    Attributes:
      instance_for_detection: `(N,)` int32 new slot of each detection that needed one, else -1
        (also -1 for those left without a slot when the table is full).
      new_valid: `(K,)` bool, `valid` with the handed-out slots set.
      overflow: `()` int32, detections that needed a slot and got none.
    """

    instance_for_detection: jax.Array
    new_valid: jax.Array
    overflow: jax.Array


@jax.jit
def allocate_instances(valid: jax.Array, needs_new: jax.Array) -> Allocation:
    """Hands free instance slots to detections, by cumulative sums (no scatter, no sorting).

    The j-th detection (in index order) with `needs_new` gets the j-th free slot (lowest index first).
    A valid slot is never handed out; when free slots run out, later detections get -1 and are counted
    in `overflow`.

    Args:
      valid: `(K,)` bool occupied slots.
      needs_new: `(N,)` bool detections that start a new instance.
    """
    free = ~valid
    cum_free = jnp.cumsum(free, dtype=jnp.int32)
    n_free = cum_free[-1]
    need_rank = jnp.cumsum(needs_new, dtype=jnp.int32) - 1
    n_need = jnp.sum(needs_new, dtype=jnp.int32)
    slot = jnp.searchsorted(cum_free, need_rank + 1, side="left").astype(jnp.int32)
    ok = needs_new & (need_rank < n_free)
    new_valid = valid | (free & (cum_free <= n_need))
    return Allocation(
        instance_for_detection=jnp.where(ok, slot, -1), new_valid=new_valid, overflow=jnp.maximum(n_need - n_free, 0)
    )


class Assignment(NamedTuple):
    """Every detection's instance after matching and allocation.

    Attributes:
      instance_for_detection: `(N,)` int32 matched or newly allocated instance, -1 for invalid
        detections and for those lost to overflow.
      is_new: `(N,)` bool, the detection started a new instance.
      created: `(K,)` bool, slots allocated in this call (their table rows must be reset).
      new_valid: `(K,)` bool.
      overflow: `()` int32.
    """

    instance_for_detection: jax.Array
    is_new: jax.Array
    created: jax.Array
    new_valid: jax.Array
    overflow: jax.Array


@jax.jit
def assign_detections(matched: jax.Array, valid_det: jax.Array, valid: jax.Array) -> Assignment:
    """Combines `match_detections` and `allocate_instances`: unmatched valid detections start instances."""
    needs_new = valid_det & (matched < 0)
    alloc = allocate_instances(valid, needs_new)
    inst = jnp.where(valid_det & (matched >= 0), matched, alloc.instance_for_detection)
    return Assignment(
        instance_for_detection=inst,
        is_new=needs_new & (alloc.instance_for_detection >= 0),
        created=alloc.new_valid & ~valid,
        new_valid=alloc.new_valid,
        overflow=alloc.overflow,
    )


@jax.jit
def instance_pixel_image(det_image: jax.Array, instance_for_detection: jax.Array) -> jax.Array:
    """`(Hs, Ws)` int32 instance each pixel is integrated into (the detection's instance), -1 for none.

    The `pixel_instance` argument of the geometry's `integrate_instances`.
    """
    n = instance_for_detection.shape[0]
    # one table read per pixel: entry 0 for the negative values (no detection, filtered), n + 1 past the rows
    table = jnp.concatenate(
        [jnp.full((1,), -1, jnp.int32), instance_for_detection.astype(jnp.int32), jnp.full((1,), -1, jnp.int32)]
    )
    return table[jnp.clip(det_image + 1, 0, n + 1)]
