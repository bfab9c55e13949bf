"""A frame's detections as fixed-shape arrays, and the per-pixel detection image.

The detector front end gives a variable number of detections per frame (`types.FrameDetections`).
The engine never sees a variable shape: `pack_detections` pads them on the host to a fixed capacity
`N` with a validity mask, so every jitted function below compiles once per configuration.

Per-pixel work runs on a stride-subsampled image (`Hs, Ws = ceil(H / stride), ceil(W / stride)`, the
pixels `[::stride, ::stride]`), the same subsampling the geometry uses for `pixel_instances`.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine._geometry import as_words, materialize
from fmfusion_jax.types import FrameDetections


class DetectionBatch(NamedTuple):
    """One frame's detections padded to a fixed capacity `N` (host arrays; jit converts them).

    The pixels come one of two ways: as a stack of masks, or (what the host adapter sends) as the label image
    the engine would make of them (`detection_pixel_image`), an `(Hs, Ws)` int16 image: a sixteenth of the bytes
    of a 32-row stack, and no per-detection pass over the pixels on the device.

    Attributes:
      masks: `(N, H, W)` bool at full resolution, or `(N, Hs, Ws)` at the fused pixel stride; rows past the
        real detections are all False. None when `pixel_detection` carries the pixels.
      label_scores: `(N, O)` float32, score of each open-set label (0 = label not measured).
      valid: `(N,)` bool, which rows hold a real detection.
      pixel_detection: `(Hs, Ws)` int16 (int32 for `N >= 2**15`) at the fused pixel stride: the row of the
        detection owning each pixel, -1 none (`pack_detections(..., as_image=True)`); None with `masks`.
    """

    masks: np.ndarray | None
    label_scores: np.ndarray
    valid: np.ndarray
    pixel_detection: np.ndarray | None = None


def select_detections(
    frame_detections: FrameDetections, open_labels: Sequence[str], max_detections: int, min_mask_pixels: int
) -> tuple[np.ndarray, int]:
    """Which detections `pack_detections` keeps: `(sorted indices, number usable)`.

    Usable: a mask of at least `min_mask_pixels` pixels and a score on some label of `open_labels`.
    When more than `max_detections` are usable, the `max_detections` with the highest score (max over
    their labels; ties: earlier detection) are kept. Indices are in the original order.
    """
    if frame_detections.num_detections == 0:
        return np.zeros((0,), np.int64), 0
    best = frame_detections.label_score_matrix(tuple(open_labels)).max(axis=1)
    all_masks = np.asarray(frame_detections.masks, bool)
    pixels = np.array([np.count_nonzero(mask) for mask in all_masks])  # per mask: with `axis`, numpy sums 5x slower
    keep = np.flatnonzero((pixels >= min_mask_pixels) & (best > 0))
    usable = int(keep.size)
    if usable > max_detections:
        order = np.argsort(-best[keep], kind="stable")[:max_detections]
        keep = np.sort(keep[order])
    return keep, usable


def pack_detections(
    frame_detections: FrameDetections,
    open_labels: Sequence[str],
    max_detections: int,
    min_mask_pixels: int,
    stride: int = 1,
    as_image: bool = False,
) -> DetectionBatch:
    """Pads a frame's detections into a `DetectionBatch` of capacity `max_detections` (host side).

    `stride`: the masks are sent at `[::stride, ::stride]` (the fused pixel grid: a quarter of the bytes at
    the default stride 2); the engine takes masks at full or at that resolution (`remaining_stride`).
    `as_image`: send the pixels as the label image at that stride (`DetectionBatch.pixel_detection`, made by
    `host_detection_pixel_image` with the engine's overlap rule) instead of the mask stack.

    Dropped: masks with fewer than `min_mask_pixels` pixels (full resolution; the reference uses 1000
    in its Python pipeline, 100 in C++) and detections with no score on any label of `open_labels`
    (they carry no semantic measurement). When more than `max_detections` remain, a warning is issued
    and those with the highest score (max over their labels; ties: earlier detection) are kept
    (`select_detections`). Kept detections stay in their original order.
    """
    open_labels = tuple(open_labels)
    height, width = subsampled_shape(*frame_detections.image_shape, stride)
    scores = np.zeros((max_detections, len(open_labels)), np.float32)
    valid = np.zeros((max_detections,), bool)
    if frame_detections.num_detections == 0:
        if as_image:
            return DetectionBatch(None, scores, valid, np.full((height, width), -1, _index_dtype(max_detections)))
        return DetectionBatch(np.zeros((max_detections, height, width), bool), scores, valid)

    keep, usable = select_detections(frame_detections, open_labels, max_detections, min_mask_pixels)
    if usable > max_detections:
        warnings.warn(
            f"{frame_detections.frame_name}: {usable} detections, capacity {max_detections}; "
            f"keeping the {max_detections} highest-scoring (raise detections.max_detections to keep all)",
            RuntimeWarning,
            stacklevel=2,
        )
    n = keep.size
    all_masks = np.asarray(frame_detections.masks, bool)
    kept_masks = subsampled_masks(all_masks if n == all_masks.shape[0] else all_masks[keep], stride)
    scores[:n] = frame_detections.label_score_matrix(open_labels)[keep]
    valid[:n] = True
    if as_image:
        return DetectionBatch(None, scores, valid, host_detection_pixel_image(kept_masks, max_detections))
    masks = np.zeros((max_detections, height, width), bool)
    masks[:n] = kept_masks
    return DetectionBatch(masks, scores, valid)


def subsampled_masks(masks: np.ndarray, stride: int) -> np.ndarray:
    """`masks[:, ::stride, ::stride]` of bool `(n, H, W)` masks, contiguous. At stride 2 with an even width each
    pair of columns is read as one little-endian uint16 whose low byte is the even column: 3x faster than
    numpy's strided copy of bools (a bool is stored as the byte 0 or 1)."""
    if stride == 2 and masks.shape[-1] % 2 == 0 and masks.flags.c_contiguous:
        return masks.view("<u2")[:, ::2, :].astype(np.uint8).view(bool)
    return np.ascontiguousarray(masks[:, ::stride, ::stride])


def _index_dtype(rows: int):
    """The narrowest integer type holding the detection indices of `rows` rows and `rows` itself (a sentinel)."""
    return np.int16 if rows < 2**15 else np.int32


def host_detection_pixel_image(masks: np.ndarray, max_detections: int) -> np.ndarray:
    """The label image of bool masks `(n, h, w)` (host side): int16 `(h, w)`, the index of the mask owning each
    pixel, -1 none. Where masks overlap, `detection_pixel_image`'s rule: the smallest mask wins (ties: lower
    index). `max_detections` (>= n) sets the dtype (int32 from 2**15 rows)."""
    image = np.full(masks.shape[1:], -1, _index_dtype(max_detections))
    areas = np.array([np.count_nonzero(mask) for mask in masks])
    # painted largest first, so smaller masks overwrite it; among equal areas the lower index is painted last
    for k in np.argsort(areas, kind="stable")[::-1]:
        np.copyto(image, k, where=masks[k], casting="unsafe")
    return image


def batch_pixel_image(batch: DetectionBatch, image_shape: tuple[int, int], stride: int) -> jax.Array:
    """int32 `(Hs, Ws)`: the detection owning each fused pixel, -1 none: the batch's label image as sent, or
    made from its masks (`detection_pixel_image`)."""
    if batch.pixel_detection is not None:
        labels = jnp.asarray(batch.pixel_detection)
        if labels.shape != subsampled_shape(*image_shape, stride):
            raise ValueError(f"pixel_detection has shape {labels.shape}, expected {subsampled_shape(*image_shape, stride)}")
        return labels.astype(jnp.int32)
    if batch.masks is None:
        raise ValueError("a DetectionBatch needs masks or pixel_detection")
    return detection_pixel_image(batch.masks, batch.valid, remaining_stride(batch.masks.shape, image_shape, stride))


def subsampled_shape(height: int, width: int, stride: int) -> tuple[int, int]:
    """`(Hs, Ws)` of an `(H, W)` image sampled at `[::stride, ::stride]`."""
    return math.ceil(height / stride), math.ceil(width / stride)


def remaining_stride(masks_shape: Sequence[int], image_shape: tuple[int, int], stride: int) -> int:
    """The stride still to apply to a batch's `(N, h, w)` masks for an `image_shape` frame fused at `stride`:
    1 when they were packed at that stride already (`pack_detections(..., stride=stride)`), else `stride`."""
    return 1 if tuple(masks_shape[1:]) == subsampled_shape(*image_shape, stride) else stride


@functools.partial(jax.jit, static_argnames=("stride",))
def detection_pixel_image(masks: jax.Array, valid: jax.Array, stride: int) -> jax.Array:
    """Per subsampled pixel, the index of the detection covering it, or -1.

    Args:
      masks: `(N, H, W)` bool.
      valid: `(N,)` bool.
      stride: pixel stride (static); pixels `[::stride, ::stride]` are used.

    Returns:
      `(Hs, Ws)` int32 detection index or -1.

    Where masks overlap, the smallest mask (fewest subsampled pixels; ties: lower index) wins. SAM's
    overlapping masks are mostly part/whole pairs (a pillow on a bed, a monitor on a desk): the small
    mask is the more specific object and usually the one in front. Giving the overlap to the large mask
    would leave the small object with no pixels, so it could never be associated or integrated, while
    the large object loses only a small share of its area. A partition also makes the masks disjoint,
    so association needs a single `segment_sum` over pixels.
    """
    n = masks.shape[0]
    sub = masks[:, ::stride, ::stride] & valid[:, None, None]
    area = mask_areas(sub)
    order = jnp.argsort(area, stable=True)  # smallest first, ties by index
    rank_dtype = _index_dtype(n)  # a narrow key: the per-pixel min is the cost
    rank = jnp.zeros((n,), rank_dtype).at[order].set(jnp.arange(n, dtype=rank_dtype))
    best = jnp.min(jnp.where(sub, rank[:, None, None], jnp.asarray(n, rank_dtype)), axis=0).astype(jnp.int32)
    return jnp.where(best < n, order.astype(jnp.int32)[jnp.minimum(best, n - 1)], -1)


def mask_areas(masks: jax.Array) -> jax.Array:
    """int32[N]: the pixels of each mask `bool[N, h, w]`. Counted four flags to a word (a population count of the
    mask bytes read as uint32): on the CPU, XLA summed the bools through a materialized int32 copy, 3x slower."""
    flat = masks.reshape(masks.shape[0], -1)
    words = as_words(flat)
    if words is None:
        return jnp.sum(flat, axis=1, dtype=jnp.int32)
    return jnp.sum(jax.lax.population_count(words), axis=1, dtype=jnp.int32)


def depth_bin_count(depth_max: float, bin_size: float) -> int:
    """Number of depth-histogram bins used by `filter_detection_depth`."""
    return max(1, math.ceil(depth_max / bin_size))


@functools.partial(jax.jit, static_argnames=("n_max", "bin_size", "depth_max"))
def filter_detection_depth(
    det_image: jax.Array,
    depth_s: jax.Array,
    n_max: int,
    lo: float = 0.1,
    hi: float = 0.9,
    *,
    bin_size: float = 0.01,
    depth_max: float = 4.0,
) -> jax.Array:
    """Drops each detection's pixels whose depth is outside that detection's [lo, hi] percentiles.

    Args:
      det_image: `(Hs, Ws)` int32 detection index or -1 (`detection_pixel_image`).
      depth_s: `(Hs, Ws)` float depth in metres at the same pixels (`depth[::stride, ::stride]`),
        0 = no measurement.
      n_max: number of detection rows `N` (static).
      lo, hi: percentile fractions (traced: changing them does not recompile).
      bin_size, depth_max: the depth histogram (static): `ceil(depth_max / bin_size)` bins from 0;
        deeper pixels fall into the last bin.

    Returns:
      `(Hs, Ws)` int32: `det_image` with dropped pixels set to -1. Pixels without depth are dropped
      too (they can be neither associated nor integrated).

    Method (no sorting): one `segment_sum` builds a depth histogram per detection; its cumulative sum
    locates the bins holding the order statistics of rank `floor(lo * (n - 1))` and
    `ceil(hi * (n - 1))` of the detection's `n` depths; pixels in those bins or between them are kept.
    Resolution: one bin (`bin_size`, 1 cm by default). Every pixel between the two order statistics is
    kept (so everything inside NumPy's linearly interpolated percentiles is kept); the only
    difference from an exact filter is that pixels sharing a bin with a threshold are kept as well.
    """
    num_bins = depth_bin_count(depth_max, bin_size)
    has_depth = depth_s > 0
    bins = jnp.clip(jnp.floor(depth_s / bin_size).astype(jnp.int32), 0, num_bins - 1)
    use = (det_image >= 0) & has_depth
    seg = jnp.where(use, det_image * num_bins + bins, n_max * num_bins)
    hist = jax.ops.segment_sum(jnp.ones(seg.size, jnp.int32), seg.reshape(-1), num_segments=n_max * num_bins + 1)[:-1].reshape(
        n_max, num_bins
    )
    cdf = jnp.cumsum(hist, axis=1)
    count = cdf[:, -1]
    last = jnp.maximum(count - 1, 0).astype(jnp.float32)
    rank_lo = jnp.floor(jnp.asarray(lo, jnp.float32) * last).astype(jnp.int32)
    rank_hi = jnp.ceil(jnp.asarray(hi, jnp.float32) * last).astype(jnp.int32)
    # The bin holding the order statistic of rank r is the first bin whose cdf exceeds r.
    bin_lo = jnp.sum(cdf <= rank_lo[:, None], axis=1, dtype=jnp.int32)
    bin_hi = jnp.sum(cdf <= rank_hi[:, None], axis=1, dtype=jnp.int32)
    # kept (detection, bin) pairs as a table read at the histogram's keys: one gather per pixel (gathering both
    # thresholds by detection cost 2.5x as much on the CPU)
    bin_index = jnp.arange(num_bins, dtype=jnp.int32)[None, :]
    kept_bins = (bin_index >= bin_lo[:, None]) & (bin_index <= bin_hi[:, None])
    # key n_max * num_bins: not used; computed once (fused into the gather, it was recomputed per pixel)
    kept_bins = materialize(jnp.concatenate([kept_bins.reshape(-1), jnp.zeros((1,), bool)]))
    return jnp.where(kept_bins[seg], det_image, -1)
