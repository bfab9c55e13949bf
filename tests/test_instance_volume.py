"""Per-voxel instance slots (`engine.instance_volume`) against the NumPy references."""

from __future__ import annotations

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from oracles import reference as ref

from fmfusion_jax.engine import _geometry as geo
from fmfusion_jax.engine import cell_edits, tsdf
from fmfusion_jax.engine import instance_volume as iv
from fmfusion_jax.engine import occupied_cells as oc
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import init_voxel_blocks, local_voxel_index

H, W = 60, 80
ROOM = ref.BoxRoom(
    lo=(0.013, 0.021, 0.007),
    hi=(3.011, 2.517, 2.209),
    boxes=(((0.6, 0.5, 0.007), (1.3, 1.2, 0.75)),),
    spheres=(((1.9, 1.3, 0.8), 0.3),),
)
K = ref.scannet_like_intrinsics(W, H)
NUM_INSTANCES = 12
CONFIG = MapConfig.for_bounds(
    ROOM.lo,
    ROOM.hi,
    voxel_size=0.04,
    block_size=4,
    sdf_trunc=0.1,
    image_height=H,
    image_width=W,
    block_capacity=4096,
    max_touched_blocks=2048,
    alloc_pixel_stride=1,
    pixel_stride=2,
    instance_capacity=NUM_INSTANCES,
    pool_chunk_blocks=300,
    cell_chunk=1000,
)
POSES = ref.orbit_poses(ROOM, 5, radius=0.8, height=1.3)


@functools.cache
def frame(i: int):
    depth, color, labels = ROOM.render(POSES[i], K, H, W)
    return depth, color, POSES[i].astype(np.float32), labels


def noisy_labels(labels: np.ndarray, i: int) -> np.ndarray:
    """Surface labels as instance ids, re-segmented differently every other frame (overlaps)."""
    s = CONFIG.pixel_stride
    lab = labels[::s, ::s]
    lab = np.where(lab >= 0, (lab + (i % 2) * (lab % 3 == 0)) % 9, -1)
    lab[: lab.shape[0] // 4] = -1  # some pixels without detection
    return lab.astype(np.int32)


@functools.cache
def integrated_map(n_frames: int = len(POSES)):
    blocks = init_voxel_blocks(CONFIG)
    for i in range(n_frames):
        depth, color, T, labels = frame(i)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, CONFIG)
        blocks = iv.integrate_instances(blocks, depth, T, K, noisy_labels(labels, i), CONFIG)
    return blocks


def check_slot_invariants(blocks) -> None:
    ids = np.asarray(blocks.instance_id)
    w = np.asarray(blocks.instance_weight)
    assert np.all((ids >= 0) | (w == 0)), "an empty slot has a weight"
    assert np.all((ids < 0) | (w > 0)), "a held slot has no weight"
    for s in range(ids.shape[-1]):
        for t in range(s):
            assert not np.any((ids[..., s] >= 0) & (ids[..., s] == ids[..., t])), "an id twice in a voxel"
    assert np.all(ids[int(blocks.num_blocks) :] == -1), "ids outside the allocated blocks"


# ---------------------------------------------------------------------------------------------------
# Integration and lookup.


def test_integrate_and_lookup_match_reference():
    blocks = init_voxel_blocks(CONFIG)
    grid = None
    for i in range(len(POSES)):
        depth, color, T, labels = frame(i)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, CONFIG)
        fresh = ref.blocks_to_dense(blocks, CONFIG)
        if grid is not None:  # geometry from the kernel, instance slots from the reference
            fresh.instance_id, fresh.instance_weight = grid.instance_id, grid.instance_weight
        grid = fresh
        looked_up = np.asarray(iv.pixel_instances(blocks, depth, T, K, CONFIG))
        expected = ref.reference_pixel_instances(grid, depth, T.astype(np.float64), K, CONFIG)
        assert looked_up.shape == CONFIG.subsampled_shape + (CONFIG.instance_slots,)
        assert np.all(looked_up == expected, axis=-1).mean() > 0.99
        lab = noisy_labels(labels, i)
        blocks = iv.integrate_instances(blocks, depth, T, K, lab, CONFIG)
        grid = ref.reference_integrate_instances(grid, depth, T.astype(np.float64), K, lab, CONFIG)
        got = ref.blocks_to_dense(blocks, CONFIG)
        m = got.allocated
        # float32 vs float64 voxel assignment differs for a few points on voxel faces
        assert np.all(got.instance_id[m] == grid.instance_id[m], axis=-1).mean() > 0.99
        assert np.all(got.instance_weight[m] == grid.instance_weight[m], axis=-1).mean() > 0.99
    check_slot_invariants(blocks)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), rounds=st.integers(1, 4), n_votes=st.integers(1, 300))
def test_slot_rule_matches_reference_exactly(seed, rounds, n_votes):
    """Random votes crowded on a few voxels: claims, conflicts, decays and evictions."""
    rng = np.random.default_rng(seed)
    blocks = integrated_map(1)
    grid = ref.blocks_to_dense(blocks, CONFIG)
    n_alloc = int(blocks.num_blocks)
    coords = np.asarray(blocks.block_coords)[:n_alloc]
    hot = rng.integers(0, n_alloc, 3)  # a few blocks, a few voxels: many conflicts
    for _ in range(rounds):
        slot = rng.choice(hot, 512)[:n_votes]
        local = rng.integers(0, 2, (512, 3))[:n_votes]
        inst = rng.integers(-1, 6, 512)[:n_votes]
        slot = np.where(rng.random(n_votes) < 0.05, -1, slot)  # dropped votes
        voxel = local_voxel_index(local[:, 0], local[:, 1], local[:, 2], CONFIG.block_size)
        blocks = iv.apply_instance_hits(blocks, _pad(slot), _pad(voxel), _pad(inst), CONFIG)
        g = coords[np.maximum(slot, 0)] * CONFIG.block_size + local
        grid = ref.reference_apply_hits(grid, g, np.where(slot >= 0, inst, -1))
        got = ref.blocks_to_dense(blocks, CONFIG)
        assert np.array_equal(got.instance_id, grid.instance_id)
        assert np.array_equal(got.instance_weight, grid.instance_weight)
    check_slot_invariants(blocks)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    rounds=st.integers(1, 4),
    n_votes=st.integers(1, 300),
    weight=st.sampled_from([0.25, 0.5, 1.0, 2.0]),
)
def test_slot_rule_with_contrary_votes_matches_reference_exactly(seed, rounds, n_votes, weight):
    """Contrary votes (pixels outside a detected instance's mask) on crowded voxels, neutral pixels too."""
    rng = np.random.default_rng(seed)
    blocks = integrated_map(1)
    grid = ref.blocks_to_dense(blocks, CONFIG)
    n_alloc = int(blocks.num_blocks)
    coords = np.asarray(blocks.block_coords)[:n_alloc]
    hot = rng.integers(0, n_alloc, 3)
    for _ in range(rounds):
        slot = rng.choice(hot, 512)[:n_votes]
        local = rng.integers(0, 2, (512, 3))[:n_votes]
        inst = rng.integers(-1, 6, 512)[:n_votes]
        neutral = rng.random(512)[:n_votes] < 0.2
        detected = rng.random(NUM_INSTANCES) < 0.5
        voxel = local_voxel_index(local[:, 0], local[:, 1], local[:, 2], CONFIG.block_size)
        blocks = iv.apply_instance_hits(
            blocks,
            _pad(slot),
            _pad(voxel),
            _pad(inst),
            CONFIG,
            detected,
            _pad(neutral.astype(np.int32)).astype(bool),
            contrary_weight=weight,
        )
        g = coords[slot] * CONFIG.block_size + local
        grid = ref.reference_apply_hits(grid, g, inst, np.flatnonzero(detected), neutral, weight)
        got = ref.blocks_to_dense(blocks, CONFIG)
        assert np.array_equal(got.instance_id, grid.instance_id)
        assert np.array_equal(got.instance_weight, grid.instance_weight)
    check_slot_invariants(blocks)


@functools.partial(jax.jit, static_argnames=("contrary_weight",))
def _hits_reporting_changes(blocks, slot, voxel, inst, detected, neutral, contrary_weight):
    return iv._apply_instance_hits(
        blocks, slot, voxel, inst, CONFIG, detected, neutral, contrary_weight=contrary_weight, report_changes=True
    )


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    rounds=st.integers(1, 4),
    n_votes=st.integers(1, 300),
    weight=st.sampled_from([0.0, 0.5, 2.0]),
)
def test_votes_report_every_voxel_whose_ids_they_changed(seed, rounds, n_votes, weight):
    """The kept census only visits the voxels of the votes flagged as changing an id (a claim or an emptied slot,
    by a decay or contrary votes): every voxel whose ids changed must have a flagged vote."""
    rng = np.random.default_rng(seed)
    blocks = integrated_map(1)
    n_alloc = int(blocks.num_blocks)
    hot = rng.integers(0, n_alloc, 3)
    for _ in range(rounds):
        slot = rng.choice(hot, 512)[:n_votes]
        local = rng.integers(0, 2, (512, 3))[:n_votes]
        inst = rng.integers(-1, 6, 512)[:n_votes]
        neutral = rng.random(512)[:n_votes] < 0.2
        detected = rng.random(NUM_INSTANCES) < 0.5
        voxel = local_voxel_index(local[:, 0], local[:, 1], local[:, 2], CONFIG.block_size)
        before = np.asarray(blocks.instance_id)
        blocks, changed = _hits_reporting_changes(
            blocks, _pad(slot), _pad(voxel), _pad(inst), detected, _pad(neutral.astype(np.int32)).astype(bool), weight
        )
        changed_voxels = {(int(b), int(v)) for b, v in zip(*np.nonzero((np.asarray(blocks.instance_id) != before).any(axis=-1)))}
        flagged = np.asarray(changed)[:n_votes]
        reported = {(int(b), int(v)) for b, v, f in zip(slot, voxel, flagged) if f}
        assert changed_voxels <= reported, sorted(changed_voxels - reported)


def _vote_one_voxel(blocks, config, instances, detected, weight):
    """Votes on voxel 0 of slot 0: `instances` int per pixel (-1 none), `detected` ids of the frame."""
    n = len(instances)
    mask = np.zeros(config.instance_capacity, bool)
    mask[list(detected)] = True
    return iv.apply_instance_hits(
        blocks,
        jnp.zeros(n, jnp.int32),
        jnp.zeros(n, jnp.int32),
        jnp.asarray(instances, jnp.int32),
        config,
        mask,
        None,
        contrary_weight=weight,
    )


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    frames=st.lists(st.tuples(st.integers(0, 3), st.integers(0, 3), st.booleans()), min_size=1, max_size=8),
    weight=st.sampled_from([0.5, 1.0]),
)
def test_membership_needs_consistent_evidence(frames, weight):
    """One instance on one voxel: after any sequence of frames (hits, pixels outside its mask, detected or
    not), the voxel holds the instance exactly when its hits since it last took the slot outweigh the
    contrary votes (`weight` each), counted only in frames where it was detected."""
    blocks = integrated_map(1)
    blocks = blocks._replace(
        instance_id=jnp.full_like(blocks.instance_id, -1), instance_weight=jnp.zeros_like(blocks.instance_weight)
    )
    net = 0.0
    for hits, others, detected in frames:
        pixels = [3] * hits + [-1] * others
        if not pixels:
            continue
        blocks = _vote_one_voxel(blocks, CONFIG, pixels, {3} if detected else set(), weight)
        if net > 0:  # holds the slot: hits add, contrary votes subtract
            net += hits - (weight * others if detected else 0.0)
        else:  # a fresh claim: its own contrary votes of this frame do not count (the slot was empty)
            net = float(hits)
        net = max(net, 0.0)
        held = int(blocks.instance_id[0, 0, 0]) == 3
        assert held == (net > 0), (frames, net)
        assert float(blocks.instance_weight[0, 0, 0]) == (net if held else 0.0)


def test_a_border_hit_seen_once_never_joins():
    """A voxel hit once by an instance's mask border, then seen outside that instance's mask in a frame where
    it is detected, is not the instance's; one that the instance's masks keep covering stays."""
    blocks = integrated_map(1)
    blocks = blocks._replace(
        instance_id=jnp.full_like(blocks.instance_id, -1), instance_weight=jnp.zeros_like(blocks.instance_weight)
    )
    border = _vote_one_voxel(blocks, CONFIG, [5, 5], {5}, 0.5)  # two border pixels
    border = _vote_one_voxel(border, CONFIG, [-1] * 4, {5}, 0.5)  # next view: outside the mask
    assert int(border.instance_id[0, 0, 0]) == -1
    object_voxel = _vote_one_voxel(blocks, CONFIG, [5, 5], {5}, 0.5)
    object_voxel = _vote_one_voxel(object_voxel, CONFIG, [5, 5, -1], {5}, 0.5)  # a partial miss
    object_voxel = _vote_one_voxel(object_voxel, CONFIG, [-1] * 4, set(), 0.5)  # not detected: no vote
    assert int(object_voxel.instance_id[0, 0, 0]) == 5
    assert float(object_voxel.instance_weight[0, 0, 0]) == 3.5


def _pad(x, n=512):
    """Fixed-length vote arrays (one compilation for every example), padded with -1 (no vote)."""
    out = np.full(n, -1, np.int32)
    out[: len(x)] = x
    return out


def test_misra_gries_eviction():
    """A strong slot survives a few contradicting votes; a weak one is evicted, then replaced."""
    one = dataclasses.replace(CONFIG, instance_slots=1)
    blocks = integrated_map(1)
    blocks = blocks._replace(
        instance_id=jnp.full_like(blocks.instance_id[..., :1], -1),
        instance_weight=jnp.zeros_like(blocks.instance_weight[..., :1]),
    )

    def vote(b, inst, times):
        return iv.apply_instance_hits(
            b, jnp.zeros(times, jnp.int32), jnp.zeros(times, jnp.int32), jnp.full(times, inst, jnp.int32), one
        )

    blocks = vote(blocks, 3, 5)  # 3 holds the voxel with weight 5
    blocks = vote(blocks, 7, 2)  # 7 contradicts twice: 3 keeps it with weight 3
    assert int(blocks.instance_id[0, 0, 0]) == 3 and float(blocks.instance_weight[0, 0, 0]) == 3
    blocks = vote(blocks, 7, 3)  # voted down to 0: emptied
    assert int(blocks.instance_id[0, 0, 0]) == -1 and float(blocks.instance_weight[0, 0, 0]) == 0
    blocks = vote(blocks, 7, 1)  # the newcomer takes the free slot
    assert int(blocks.instance_id[0, 0, 0]) == 7 and float(blocks.instance_weight[0, 0, 0]) == 1


def test_votes_in_unallocated_blocks_are_dropped():
    blocks = init_voxel_blocks(CONFIG)  # nothing allocated
    depth, color, T, labels = frame(0)
    out = iv.integrate_instances(blocks, depth, T, K, noisy_labels(labels, 0), CONFIG)
    assert np.all(np.asarray(out.instance_id) == -1)


def test_lookup_sees_what_was_integrated_from_the_same_view():
    blocks = integrated_map(1)
    depth, color, T, labels = frame(0)
    lab = noisy_labels(labels, 0)
    look = np.asarray(iv.pixel_instances(blocks, depth, T, K, CONFIG))
    seen = lab >= 0
    assert np.any(look == lab[..., None], axis=-1)[seen].mean() > 0.99


# ---------------------------------------------------------------------------------------------------
# Counts.


def random_instance_field(seed: int, n_blocks: int = 40):
    """A pool with random instance slots (distinct ids per voxel) in random allocated blocks."""
    rng = np.random.default_rng(seed)
    grid = ref.empty_dense(CONFIG)
    bs = CONFIG.block_size
    shape = np.asarray(CONFIG.grid_shape)
    blocks = rng.choice(int(np.prod(shape)), n_blocks, replace=False)
    for b in blocks:
        c = np.array(np.unravel_index(b, shape)) * bs
        grid.allocated[c[0] : c[0] + bs, c[1] : c[1] + bs, c[2] : c[2] + bs] = True
    mask = grid.allocated & (rng.random(grid.allocated.shape) < 0.4)
    first = rng.integers(0, NUM_INSTANCES, mask.shape)
    second = (first + rng.integers(1, NUM_INSTANCES, mask.shape)) % NUM_INSTANCES
    has_second = rng.random(mask.shape) < 0.3
    grid.instance_id[..., 0] = np.where(mask, first, -1)
    grid.instance_id[..., 1] = np.where(mask & has_second, second, -1)
    grid.instance_weight = np.where(grid.instance_id >= 0, rng.integers(1, 5, grid.instance_id.shape), 0).astype(float)
    grid.weight = np.where(grid.allocated, rng.integers(0, 4, mask.shape), 0).astype(float)
    grid.tsdf = np.where(grid.allocated, rng.uniform(-1, 1, mask.shape).astype(np.float32), 1.0)
    return grid


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1))
def test_overlap_and_voxel_counts_match_reference(seed):
    grid = random_instance_field(seed)
    blocks = ref.dense_to_blocks(grid, CONFIG)
    # random fields put up to 16 distinct ids in a 2x2x2 cell: keep them all for an exact comparison
    exact = dataclasses.replace(CONFIG, overlap_ids_per_cell=16)
    for inflate in (False, True):
        got = oc.instance_overlap_counts(blocks, exact, inflate)
        assert int(got.dropped_cells) == 0
        expected = ref.reference_overlap_counts(grid, NUM_INSTANCES, inflate)
        np.testing.assert_array_equal(np.asarray(got.counts), expected)
    # with the default 4 ids per cell the crowded cells are reported and only lose counts
    capped = oc.instance_overlap_counts(blocks, CONFIG, True)
    assert int(capped.dropped_cells) > 0
    assert np.all(np.asarray(capped.counts) <= ref.reference_overlap_counts(grid, NUM_INSTANCES, True))
    counts = oc.instance_voxel_counts(blocks, CONFIG)
    expected = np.diag(ref.reference_overlap_counts(grid, NUM_INSTANCES, False))
    np.testing.assert_array_equal(np.asarray(counts.counts), expected)
    assert int(counts.dropped_cells) == 0


def test_inflated_overlap_of_the_integrated_room():
    blocks = integrated_map()
    grid = ref.blocks_to_dense(blocks, CONFIG)
    for inflate in (False, True):
        got = oc.instance_overlap_counts(blocks, CONFIG, inflate)
        expected = ref.reference_overlap_counts(grid, NUM_INSTANCES, inflate)
        np.testing.assert_array_equal(np.asarray(got.counts), expected)
    plain = np.asarray(oc.instance_overlap_counts(blocks, CONFIG, False).counts)
    inflated = np.asarray(oc.instance_overlap_counts(blocks, CONFIG, True).counts)
    assert np.all(inflated >= plain) and np.array_equal(np.diag(inflated), np.diag(plain))
    assert (inflated > plain).any()


def test_cell_capacity_drops_are_counted():
    grid = random_instance_field(3)
    small = dataclasses.replace(CONFIG, overlap_cell_capacity=100, cell_chunk=64)
    blocks = ref.dense_to_blocks(grid, small)
    full = oc.instance_voxel_counts(blocks, CONFIG)
    part = oc.instance_voxel_counts(blocks, small)
    assert int(part.dropped_cells) > 0 and int(full.dropped_cells) == 0
    assert np.all(np.asarray(part.counts) <= np.asarray(full.counts))
    assert np.asarray(part.counts).sum() < np.asarray(full.counts).sum()


# ---------------------------------------------------------------------------------------------------
# Pool-wide edits.


def test_remap_merges_and_deletes():
    grid = random_instance_field(5)
    blocks = ref.dense_to_blocks(grid, CONFIG)
    new_id = np.arange(NUM_INSTANCES)
    new_id[1] = 0  # merge 1 into 0
    new_id[4] = 2  # merge 4 into 2
    new_id[7] = -1  # delete 7
    out = cell_edits.remap_instances(blocks, jnp.asarray(new_id, jnp.int32), CONFIG)
    check_slot_invariants(out)
    got = ref.blocks_to_dense(out, CONFIG)
    # expected, voxel by voxel
    ids = grid.instance_id
    mapped = np.where(ids >= 0, new_id[np.maximum(ids, 0)], -1)
    w = np.where(mapped >= 0, grid.instance_weight, 0)
    dup = (mapped[..., 1] >= 0) & (mapped[..., 1] == mapped[..., 0])
    w0 = w[..., 0] + np.where(dup, w[..., 1], 0)
    np.testing.assert_array_equal(got.instance_id[..., 0], mapped[..., 0])
    np.testing.assert_array_equal(got.instance_id[..., 1], np.where(dup, -1, mapped[..., 1]))
    np.testing.assert_array_equal(got.instance_weight[..., 0], w0)
    # total weight per surviving id is conserved
    for k in range(NUM_INSTANCES):
        before = sum(grid.instance_weight[ids == j].sum() for j in np.flatnonzero(new_id == k))
        assert got.instance_weight[got.instance_id == k].sum() == before
    counts = np.asarray(oc.instance_voxel_counts(out, CONFIG).counts)
    assert counts[1] == counts[4] == counts[7] == 0


def test_fuse_instance_geometry_keeps_surface_voxels_only():
    grid = random_instance_field(9)
    blocks = ref.dense_to_blocks(grid, CONFIG)
    out = cell_edits.fuse_instance_geometry(blocks, CONFIG, 2.0, 0.05)
    got = ref.blocks_to_dense(out, CONFIG)
    keep = (grid.weight >= 2.0) & (np.abs(grid.tsdf) * CONFIG.sdf_trunc <= 0.05)
    np.testing.assert_array_equal(got.instance_id, np.where(keep[..., None], grid.instance_id, -1))
    np.testing.assert_array_equal(got.instance_weight, np.where(keep[..., None], grid.instance_weight, 0))
    np.testing.assert_array_equal(got.tsdf, grid.tsdf)


# ---------------------------------------------------------------------------------------------------
# Tracing.


def test_no_recompilation_and_vmap():
    counted_int = jax.jit(chex.assert_max_traces(iv._integrate_instances, n=1), static_argnames="config")
    counted_look = jax.jit(chex.assert_max_traces(iv._pixel_instances, n=1), static_argnames="config")
    blocks = integrated_map(1)
    for i in range(3):
        depth, color, T, labels = frame(i)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, CONFIG)
        counted_look(blocks, jnp.asarray(depth), jnp.asarray(T), jnp.asarray(K), CONFIG)
        labels_i = jnp.asarray(noisy_labels(labels, i))
        blocks = counted_int(blocks, jnp.asarray(depth), jnp.asarray(T), jnp.asarray(K), labels_i, CONFIG)

    depth0, _, T0, labels0 = frame(0)
    depth1, _, T1, labels1 = frame(1)
    start = integrated_map(2)
    singles = [
        iv.integrate_instances(start, d, T, K, noisy_labels(l, i), CONFIG)
        for i, (d, T, l) in enumerate(((depth0, T0, labels0), (depth1, T1, labels1)))
    ]
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), start)
    batched = jax.vmap(lambda b, d, T, l: iv.integrate_instances(b, d, T, K, l, CONFIG))(
        batch,
        jnp.stack([depth0, depth1]),
        jnp.stack([T0, T1]),
        jnp.stack([noisy_labels(labels0, 0), noisy_labels(labels1, 1)]),
    )
    for i, single in enumerate(singles):
        np.testing.assert_array_equal(np.asarray(single.instance_id), np.asarray(batched.instance_id[i]))
        np.testing.assert_array_equal(np.asarray(single.instance_weight), np.asarray(batched.instance_weight[i]))
    counts = jax.vmap(lambda b: oc.instance_overlap_counts(b, CONFIG, True).counts)(batched)
    for i, single in enumerate(singles):
        expected = oc.instance_overlap_counts(single, CONFIG, True).counts
        np.testing.assert_array_equal(np.asarray(counts[i]), np.asarray(expected))


# ---------------------------------------------------------------------------------------------------
# The one-pass census, the renaming that derives counts, and their helpers (used by `step.refine`).


def reference_remap(grid, new_id):
    """NumPy: ids renamed voxel by voxel, deleted slots emptied, a duplicate folded into the first slot."""
    ids = grid.instance_id
    mapped = np.where(ids >= 0, new_id[np.maximum(ids, 0)], -1)
    w = np.where(mapped >= 0, grid.instance_weight, 0)
    out = dataclasses.replace(grid, instance_id=mapped.copy(), instance_weight=w.copy())
    for s in range(1, ids.shape[-1]):
        for t in range(s):
            dup = (out.instance_id[..., s] >= 0) & (out.instance_id[..., s] == out.instance_id[..., t])
            out.instance_weight[..., t] += np.where(dup, out.instance_weight[..., s], 0)
            out.instance_weight[..., s] = np.where(dup, 0, out.instance_weight[..., s])
            out.instance_id[..., s] = np.where(dup, -1, out.instance_id[..., s])
    return out


_census = jax.jit(oc.census, static_argnames=("config", "overlap", "list_cells"))  # overlap: a mode name
_census_flag = jax.jit(oc.census, static_argnames=("config", "list_cells"))  # overlap: a traced bool
_remap_cells = jax.jit(cell_edits.remap_cells, static_argnames=("config",))


def run_census(blocks, config, overlap=None, keep=None, list_cells=False):
    if overlap is None or isinstance(overlap, str):
        return _census(blocks, config, overlap, keep, list_cells)
    return _census_flag(blocks, config, overlap, keep, list_cells)


def test_materialize_is_the_identity():
    rng = np.random.default_rng(1)
    for x in (
        rng.random((5, 7)).astype(np.float32),
        rng.integers(-3, 3, 9).astype(np.int32),
        rng.random(4) < 0.5,
        np.zeros((0, 2)),
    ):
        got = jax.jit(geo.materialize)(jnp.asarray(x))
        assert got.shape == x.shape and got.dtype == jnp.asarray(x).dtype
        np.testing.assert_array_equal(np.asarray(got), x)


def test_prefix_sum_and_compaction():
    rng = np.random.default_rng(0)
    for n in (1, 16, 17, 4097):
        x = rng.integers(0, 3, n).astype(np.int32)
        np.testing.assert_array_equal(np.asarray(geo.inclusive_cumsum(jnp.asarray(x))), np.cumsum(x))
        flags = rng.random(n) < 0.4
        values = (np.arange(n) * 7).astype(np.int32)
        for start, size in ((0, n), (3, n + 5), (2, max(1, n // 3))):
            out, found = geo.compact(jnp.full((size,), -1, jnp.int32), jnp.int32(start), jnp.asarray(flags), jnp.asarray(values))
            expected = np.full(size + n + start, -1)
            expected[start : start + flags.sum()] = values[flags]
            np.testing.assert_array_equal(np.asarray(out), expected[:size])
            assert int(found) == start + flags.sum()


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1))
@example(seed=0)  # rooms with cells of more than 4 kept ids (most seeds; not all: seed 121785 has none)
@example(seed=2)
def test_census_without_removed_ids_matches_the_reference_after_removal(seed):
    """`_census(..., keep)` counts as if the ids outside `keep` had been deleted from the voxels first."""
    grid = random_instance_field(seed)
    blocks = ref.dense_to_blocks(grid, CONFIG)
    keep = np.random.default_rng(seed).random(NUM_INSTANCES) < 0.7
    removed = reference_remap(grid, np.where(keep, np.arange(NUM_INSTANCES), -1))
    exact = dataclasses.replace(CONFIG, overlap_ids_per_cell=16)
    for overlap, inflate in (("inflated", True), ("plain", False), (jnp.bool_(False), True), (jnp.bool_(True), False)):
        census = run_census(blocks, exact, overlap, jnp.asarray(keep))
        np.testing.assert_array_equal(np.asarray(census.overlap), ref.reference_overlap_counts(removed, NUM_INSTANCES, inflate))
        np.testing.assert_array_equal(
            np.asarray(census.counts), np.diag(ref.reference_overlap_counts(removed, NUM_INSTANCES, False))
        )
        assert int(census.overfull) == 0 and int(census.dropped_cells) == 0
    # with 4 ids per cell the crowded cells keep their 4 largest ids among the kept ones, as a count of
    # the pool after the removal does
    after = ref.dense_to_blocks(removed, CONFIG)
    for overlap in ("inflated", jnp.bool_(False)):
        census = run_census(blocks, CONFIG, overlap, jnp.asarray(keep))
        expected = oc.instance_overlap_counts(after, CONFIG, True)
        np.testing.assert_array_equal(np.asarray(census.overlap), np.asarray(expected.counts))
        assert int(census.overfull + census.dropped_cells) == int(expected.dropped_cells)
        assert seed not in (0, 2) or int(expected.dropped_cells) > 0  # the pinned rooms test the crowded cells


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1))
def test_renaming_derives_the_new_counts_from_the_census(seed):
    """`_remap_cells` renames like the NumPy reference, with and without the census' list of cells, and its
    `gained` turns the counts before the renaming into the counts after it."""
    rng = np.random.default_rng(seed)
    grid = random_instance_field(seed)
    blocks = ref.dense_to_blocks(grid, CONFIG)
    new_id = np.arange(NUM_INSTANCES)
    a, b, c, d, e = rng.choice(NUM_INSTANCES, 5, replace=False)
    new_id[b] = a  # merge b and c into a
    new_id[c] = a
    new_id[e] = d  # merge e into d
    new_id[rng.integers(0, NUM_INSTANCES)] = -1  # delete one (unless it is a representative: then both)
    new_id = np.where(new_id >= 0, new_id, -1)
    new_id = np.where((new_id >= 0) & (new_id[np.maximum(new_id, 0)] < 0), -1, new_id)
    expected = reference_remap(grid, new_id)
    expected_counts = np.diag(ref.reference_overlap_counts(expected, NUM_INSTANCES, False))
    changed = new_id != np.arange(NUM_INSTANCES)
    for capacity in (2**18, 10):  # the census' list, or too many cells: found again
        config = dataclasses.replace(CONFIG, cell_list_capacity=capacity)
        census = run_census(blocks, config, "inflated", list_cells=True)
        listed = (census.cells, census.tags, census.occupied, census.occupied <= config.cell_list_capacity)
        assert bool(listed[-1]) == (capacity > 10)
        out, gained, _ = _remap_cells(blocks, jnp.asarray(new_id, jnp.int32), config, active=jnp.bool_(True), listed=listed)
        check_slot_invariants(out)
        got = ref.blocks_to_dense(out, CONFIG)
        np.testing.assert_array_equal(got.instance_id, expected.instance_id)
        np.testing.assert_array_equal(got.instance_weight, expected.instance_weight)
        counts = np.where(changed, 0, np.asarray(census.counts)) + np.asarray(gained)
        np.testing.assert_array_equal(counts, expected_counts)
    # inactive: nothing happens
    out, gained, _ = _remap_cells(blocks, jnp.asarray(new_id, jnp.int32), CONFIG, active=jnp.bool_(False))
    np.testing.assert_array_equal(np.asarray(out.instance_id), np.asarray(blocks.instance_id))
    assert not np.asarray(gained).any()


def test_cell_tags_flag_every_cell_holding_a_wanted_id():
    grid = random_instance_field(4)
    blocks = ref.dense_to_blocks(grid, CONFIG)
    result = run_census(blocks, dataclasses.replace(CONFIG, cell_list_capacity=2**18), list_cells=True)
    n = int(result.occupied)
    cells, tags = np.asarray(result.cells[:n]), result.tags[:n]
    rows = np.asarray(oc.cell_rows(blocks.instance_id))[cells]
    assert (rows >= 0).any(axis=1).all() and len(np.unique(cells)) == n
    for wanted_ids in ([0], [3, 7], [NUM_INSTANCES - 1]):
        wanted = np.isin(np.arange(NUM_INSTANCES), wanted_ids)
        flagged = np.asarray(oc.tag_holds(tags, jnp.asarray(wanted)))
        holds = np.isin(rows, wanted_ids).any(axis=1)
        assert flagged[holds].all()  # never misses a cell
        distinct = np.array([len(set(r[r >= 0])) for r in rows])
        np.testing.assert_array_equal(flagged[distinct <= 2], holds[distinct <= 2])  # exact for simple cells
