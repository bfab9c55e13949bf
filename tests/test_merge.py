"""Instance merging and table maintenance vs NumPy references, and their laws."""

from __future__ import annotations

import chex
import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import reference_semantics as R

from fmfusion_jax.engine import label_fusion as LF
from fmfusion_jax.engine import maintenance as MT
from fmfusion_jax.engine import merge as M

K, C, O = 16, 20, 38
CHECK = settings(max_examples=30, deadline=None)
seeds = st.integers(0, 2**32 - 1)


def random_instances(rng, k=K):
    """Peaked class distributions over a few classes, voxel counts with ties, overlaps <= counts."""
    dist = rng.dirichlet(np.full(C, 0.3), size=k)
    dist[: k // 3] = dist[k // 3 : 2 * (k // 3)]  # some pairs with the same semantics
    dist = dist.astype(np.float32)
    voxel_count = rng.integers(0, 6, k).astype(np.int32) * 100
    overlap = np.minimum(rng.integers(0, 600, (k, k)), voxel_count[None, :]).astype(np.int32)
    valid = rng.random(k) < 0.85
    return dist, overlap, voxel_count, valid


def random_rows(rng, k=K, mode="additive"):
    valid = rng.random(k) < 0.85
    if mode == "additive":
        evidence = (rng.random((k, C)) * (rng.random((k, C)) < 0.4)).astype(np.float32)
    else:
        evidence = -rng.exponential(3.0, (k, C)).astype(np.float32)
        evidence -= evidence.max(1, keepdims=True)
    return MT.TableRows(
        valid=valid,
        label_evidence=evidence,
        open_label_histogram=rng.random((k, O)).astype(np.float32),
        observations=rng.integers(0, 20, k).astype(np.int32),
        missed=rng.integers(0, 6, k).astype(np.int32),
        voxel_count=rng.integers(0, 2000, k).astype(np.int32),
        created_frame=rng.integers(0, 50, k).astype(np.int32),
        last_seen_frame=rng.integers(50, 100, k).astype(np.int32),
    )


def random_pairs(rng, k=K, density=0.12):
    pairs = rng.random((k, k)) < density
    return pairs | pairs.T


def partition(rep):
    """The groups of a representative vector, as a set of frozensets (invalid rows left out)."""
    groups: dict[int, set[int]] = {}
    for i, r in enumerate(rep):
        if r >= 0:
            groups.setdefault(int(r), set()).add(i)
    return {frozenset(g) for g in groups.values()}


# ----------------------------------------------------------------------------- merge tests


@CHECK
@given(seeds)
def test_similarity_and_pair_tests_match_reference(seed):
    rng = np.random.default_rng(seed)
    dist, overlap, voxel_count, valid = random_instances(rng)
    sim = np.asarray(M.semantic_similarity(dist))
    np.testing.assert_allclose(sim, R.semantic_similarity(dist), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(sim, sim.T, rtol=1e-6)
    pairs = np.asarray(M.merge_pairs(sim, overlap, voxel_count, valid))
    np.testing.assert_array_equal(pairs, R.merge_pairs(sim, overlap, voxel_count, valid))
    assert (pairs == pairs.T).all() and not pairs.diagonal().any()
    post = np.asarray(M.post_merge_pairs(sim, overlap, voxel_count, valid))
    np.testing.assert_array_equal(post, R.post_merge_pairs(sim, overlap, voxel_count, valid))


def test_similarity_scale():
    uniform = np.full((2, C), 1.0 / C, np.float32)
    np.testing.assert_allclose(np.asarray(M.semantic_similarity(uniform)), 1.0 / C, rtol=1e-6)
    certain = np.eye(C, dtype=np.float32)[[3, 3, 4]]
    np.testing.assert_allclose(np.asarray(M.semantic_similarity(certain)), [[1, 1, 0], [1, 1, 0], [0, 0, 1]])


def test_merge_pairs_reads_overlap_of_the_smaller_inside_the_larger():
    sim = np.ones((2, 2), np.float32)
    voxel_count = np.array([1000, 100], np.int32)
    overlap = np.array([[0, 41], [1000, 0]], np.int32)  # 41 of b's 100 voxels inside a (inflated)
    valid = np.ones(2, bool)
    assert np.asarray(M.merge_pairs(sim, overlap, voxel_count, valid))[0, 1]
    overlap[0, 1] = 40  # exactly 0.4 is not above the threshold
    assert not np.asarray(M.merge_pairs(sim, overlap, voxel_count, valid)).any()
    overlap[0, 1] = 90
    assert not np.asarray(M.merge_pairs(np.full((2, 2), 0.15, np.float32), overlap, voxel_count, valid)).any()


@CHECK
@given(seeds, st.sampled_from([0.05, 0.12, 0.3]))
def test_merge_groups_are_connected_components(seed, density):
    rng = np.random.default_rng(seed)
    pairs = random_pairs(rng, density=density)
    valid = rng.random(K) < 0.85
    voxel_count = rng.integers(0, 5, K).astype(np.int32)  # many ties
    rep = np.asarray(M.merge_groups(pairs, valid, voxel_count))
    np.testing.assert_array_equal(rep, R.merge_groups(pairs, valid, voxel_count))
    for group in partition(rep):
        members = sorted(group)
        assert rep[members[0]] == max(members, key=lambda m: (voxel_count[m], -m))  # the largest


@pytest.mark.parametrize("k", [40])
def test_merge_groups_converges_on_a_long_chain(k):
    rng = np.random.default_rng(1)
    order = rng.permutation(k)
    pairs = np.zeros((k, k), bool)
    pairs[order[:-1], order[1:]] = True  # a path through all instances: diameter k - 1
    voxel_count = rng.permutation(k).astype(np.int32)
    rep = np.asarray(M.merge_groups(pairs, np.ones(k, bool), voxel_count))
    assert (rep == np.argmax(voxel_count)).all()


@CHECK
@given(seeds)
def test_merging_does_not_depend_on_instance_order(seed):
    rng = np.random.default_rng(seed)
    pairs = random_pairs(rng)
    valid = rng.random(K) < 0.85
    voxel_count = rng.permutation(K).astype(np.int32) * 10  # distinct: the representative is unique
    rep = np.asarray(M.merge_groups(pairs, valid, voxel_count))
    perm = rng.permutation(K)  # new index i holds old instance perm[i]
    rep_p = np.asarray(M.merge_groups(pairs[np.ix_(perm, perm)], valid[perm], voxel_count[perm]))
    back = np.where(rep_p >= 0, perm[np.maximum(rep_p, 0)], -1)  # representatives in old indices
    np.testing.assert_array_equal(back[np.argsort(perm)], rep)
    # With ties the representative may change, never the partition.
    ties = (voxel_count // 50).astype(np.int32)
    part = partition(np.asarray(M.merge_groups(pairs, valid, ties)))
    part_p = partition(np.asarray(M.merge_groups(pairs[np.ix_(perm, perm)], valid[perm], ties[perm])))
    assert {frozenset(int(perm[i]) for i in g) for g in part_p} == part


@CHECK
@given(seeds, st.sampled_from(LF.MODES))
def test_merge_instance_table_matches_reference(seed, mode):
    rng = np.random.default_rng(seed)
    rows = random_rows(rng, mode=mode)
    rep = np.asarray(M.merge_groups(random_pairs(rng), rows.valid, rows.voxel_count))
    got = M.merge_instance_table(rows, rep, mode)
    want, want_id = R.merge_instance_table(rows._asdict(), rep, mode)
    for name in MT.TableRows._fields:
        np.testing.assert_allclose(np.asarray(getattr(got.rows, name)), want[name], rtol=1e-5, atol=1e-5, err_msg=name)
    np.testing.assert_array_equal(np.asarray(got.new_id), want_id)
    new_valid = np.asarray(got.rows.valid)
    assert (new_valid == (rows.valid & (rep == np.arange(K)))).all()
    assert (np.asarray(got.new_id)[rows.valid] >= 0).all() and new_valid[np.asarray(got.new_id)[rows.valid]].all()


@pytest.mark.parametrize("mode", LF.MODES)
def test_merged_evidence_equals_pooled_measurements(mode):
    """Merging two instances gives what one instance fed with both measurement streams would hold."""
    rng = np.random.default_rng(7)
    lik = rng.random((O, C)).astype(np.float32) * (rng.random((O, C)) < 0.4)
    scores = np.zeros((8, O), np.float32)
    for i in range(8):
        scores[i, rng.choice(O, 2, replace=False)] = rng.uniform(0.3, 1.0, 2)
    valid_det = np.ones(8, bool)
    split = np.array([0, 0, 0, 1, 1, 0, 1, 1], np.int32)  # detections split between instances 0 and 1
    zero = np.zeros((K, C), np.float32)
    evidence = LF.fuse_labels(zero, split, scores, lik, valid_det, mode)
    pooled = np.asarray(LF.fuse_labels(zero, np.zeros(8, np.int32), scores, lik, valid_det, mode))
    rows = MT.TableRows(
        valid=np.arange(K) < 2,
        label_evidence=evidence,
        open_label_histogram=np.zeros((K, O), np.float32),
        observations=np.array([4, 4] + [0] * (K - 2), np.int32),
        missed=np.zeros(K, np.int32),
        voxel_count=np.array([900, 300] + [0] * (K - 2), np.int32),
        created_frame=np.zeros(K, np.int32),
        last_seen_frame=np.zeros(K, np.int32),
    )
    rep = np.asarray(M.merge_groups(np.ones((K, K), bool), rows.valid, rows.voxel_count))
    merged = M.merge_instance_table(rows, rep, mode)
    np.testing.assert_allclose(np.asarray(merged.rows.label_evidence)[0], pooled[0], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(
        np.asarray(LF.class_distribution(merged.rows.label_evidence, mode))[0],
        np.asarray(LF.class_distribution(pooled, mode))[0],
        rtol=1e-5,
        atol=1e-6,
    )
    assert np.asarray(merged.rows.valid).tolist()[:2] == [True, False]
    assert np.asarray(merged.new_id).tolist()[:3] == [0, 0, -1]


# ----------------------------------------------------------------------------- maintenance


@CHECK
@given(seeds)
def test_missed_and_removal_match_reference(seed):
    rng = np.random.default_rng(seed)
    missed = rng.integers(0, 8, K).astype(np.int32)
    voxel_count = rng.integers(0, 1000, K).astype(np.int32)
    valid, in_view, matched = rng.random((3, K)) < 0.6
    got = np.asarray(MT.update_missed(missed, valid, in_view, matched))
    np.testing.assert_array_equal(got, R.update_missed(missed, valid, in_view, matched))
    remove = np.asarray(MT.instances_to_remove(got, voxel_count, valid))
    np.testing.assert_array_equal(remove, R.instances_to_remove(got, voxel_count, valid))
    rows = random_rows(rng)._replace(valid=valid, missed=got, voxel_count=voxel_count)
    out = MT.remove_instances(rows, remove)
    assert (np.asarray(out.rows.valid) == (valid & ~remove)).all()
    assert not np.asarray(out.rows.label_evidence)[remove].any()
    assert (np.asarray(out.rows.created_frame)[remove] == -1).all()
    np.testing.assert_array_equal(np.asarray(out.new_id), np.where(valid & ~remove, np.arange(K), -1))


def test_in_view_matched_seen_and_reset():
    inst_area = np.array([0, 199, 201, 500] + [0] * (K - 4), np.int32)  # subsampled pixels, stride 2
    valid = np.array([1, 1, 1, 0] + [0] * (K - 4), bool)
    np.testing.assert_array_equal(np.asarray(MT.instances_in_view(inst_area, valid, 2))[:4], [0, 0, 1, 0])
    matched = np.asarray(MT.matched_instances(np.array([2, 2, -1, 5], np.int32), np.array([1, 1, 1, 0], bool), K))
    np.testing.assert_array_equal(np.flatnonzero(matched), [2])
    np.testing.assert_array_equal(np.asarray(MT.mark_seen(np.zeros(K, np.int32), matched, 7))[:3], [0, 0, 7])
    rows = random_rows(np.random.default_rng(0))._replace(valid=np.zeros(K, bool))
    created = np.arange(K) == 4
    out = MT.reset_rows(rows, created, 9)
    assert np.asarray(out.valid)[4] and np.asarray(out.valid).sum() == 1
    assert not np.asarray(out.label_evidence)[4].any() and np.asarray(out.observations)[4] == 0
    assert np.asarray(out.created_frame)[4] == 9 == np.asarray(out.last_seen_frame)[4]
    np.testing.assert_array_equal(np.asarray(out.label_evidence)[~created], rows.label_evidence[~created])
    assert all(a is b for a, b in zip(MT.TableRows.of(out), out))


# ----------------------------------------------------------------------------- no recompilation


def test_merge_step_compiles_once():
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def merge_step(rows, overlap, sim_threshold):
        dist = LF.class_distribution(rows.label_evidence, "additive")
        pairs = M.merge_pairs(M.semantic_similarity(dist), overlap, rows.voxel_count, rows.valid, sim_threshold)
        rep = M.merge_groups(pairs, rows.valid, rows.voxel_count)
        return M.merge_instance_table(rows, rep, "additive")

    def calls(seed):
        rng = np.random.default_rng(seed)
        rows = random_rows(rng)
        overlap = rng.integers(0, 2000, (K, K)).astype(np.int32)
        merge_step(rows, overlap, 0.1 + 0.05 * seed)
        rep = M.merge_groups(random_pairs(rng), rows.valid, rows.voxel_count)
        M.merge_instance_table(rows, rep, "additive")

    calls(0)
    before = M.merge_groups._cache_size(), M.merge_instance_table._cache_size()
    for seed in range(1, 4):
        calls(seed)
    assert (M.merge_groups._cache_size(), M.merge_instance_table._cache_size()) == before


# --------------------------------------------------------------------------------------------------
# Reuniting fragments: pair counts of covered instances.


def reference_reunion_pairs(covered, observations, valid, min_frames):
    """Plain loops: a and b reunite when either covered the other often enough."""
    k = len(valid)
    out = np.zeros((k, k), bool)
    if min_frames <= 0:
        return out
    for a in range(k):
        for b in range(k):
            if a == b or not (valid[a] and valid[b]):
                continue
            ab = covered[a, b] >= max(min_frames, observations[b])
            ba = covered[b, a] >= max(min_frames, observations[a])
            out[a, b] = ab or ba
    return out


def reference_fold(counts, new_id):
    k = len(new_id)
    out = np.zeros_like(counts)
    for a in range(k):
        for b in range(k):
            if new_id[a] >= 0 and new_id[b] >= 0 and new_id[a] != new_id[b]:
                out[new_id[a], new_id[b]] += counts[a, b]
    return out


@CHECK
@given(seed=seeds, min_frames=st.integers(0, 4))
def test_reunion_pairs_match_reference(seed, min_frames):
    rng = np.random.default_rng(seed)
    covered = rng.integers(0, 6, (K, K)).astype(np.int32)
    observations = rng.integers(0, 6, K).astype(np.int32)
    valid = rng.random(K) < 0.8
    got = np.asarray(M.reunion_pairs(covered, observations, valid, min_frames))
    assert np.array_equal(got, reference_reunion_pairs(covered, observations, valid, min_frames))
    assert np.array_equal(got, got.T) and not np.any(np.diag(got))


@CHECK
@given(seed=seeds)
def test_fold_pair_counts_match_reference_and_keep_the_invariant(seed):
    """Counts follow their rows into the representatives; dropped rows and the diagonal end at zero."""
    rng = np.random.default_rng(seed)
    rows = random_rows(rng)
    dist, overlap, voxel_count, _ = random_instances(rng)
    rows = rows._replace(voxel_count=voxel_count)
    pairs = np.asarray(M.merge_pairs(dist @ dist.T, overlap, voxel_count, rows.valid, 0.15, 0.4))
    merged = M.merge_instance_table(rows, M.merge_groups(pairs, rows.valid, voxel_count))
    new_id = np.asarray(merged.new_id)
    counts = rng.integers(0, 5, (K, K)).astype(np.int32)
    counts[~np.asarray(rows.valid)] = 0
    counts[:, ~np.asarray(rows.valid)] = 0
    np.fill_diagonal(counts, 0)
    got = np.asarray(M.fold_pair_counts(counts, merged.new_id, rows.valid))
    assert np.array_equal(got, reference_fold(counts, new_id))
    dead = ~np.asarray(merged.rows.valid)
    assert not got[dead].any() and not got[:, dead].any()
    assert got.sum() <= counts.sum()


def test_a_fragment_covered_by_the_whole_object_reunites_a_neighbour_does_not():
    """Instance 1 (a part) lay in instance 0's masks 3 times and was detected alone once: it reunites with 0,
    whatever its labels. Instance 2 (a chair that a merged mask sometimes swallows with its table 0) was
    covered 2 times but detected alone 6 times: it stays."""
    covered = np.zeros((4, 4), np.int32)
    covered[0, 1], covered[0, 2] = 3, 2
    observations = np.array([8, 1, 6, 3], np.int32)
    valid = np.array([True, True, True, True])
    pairs = np.asarray(M.reunion_pairs(covered, observations, valid, 2))
    assert pairs[0, 1] and pairs[1, 0]
    assert not pairs[0, 2] and not pairs[2, 0] and not pairs[0, 3]
    assert not np.asarray(M.reunion_pairs(covered, observations, valid, 0)).any()


def test_separated_pairs_veto_what_the_detector_keeps_apart():
    """a, b shown apart 4 times and covered as one once: never merged; c, d apart 2 times, covered 3 times:
    free to merge; e, f apart once: below a minimum of 2, kept apart with a minimum of 1 (never covered)."""
    separated = np.zeros((6, 6), np.int32)
    covered = np.zeros((6, 6), np.int32)
    for (i, j), n in {(0, 1): 4, (2, 3): 2, (4, 5): 1}.items():
        separated[i, j] = separated[j, i] = n
    covered[0, 1], covered[2, 3], covered[3, 2] = 1, 2, 1
    apart = np.asarray(M.separated_pairs(separated, covered, 2))
    assert apart[0, 1] and apart[1, 0]
    assert not apart[2, 3] and not apart[4, 5]
    assert np.asarray(M.separated_pairs(separated, covered, 1))[4, 5]
    covered[4, 5] = 1  # covered as often as separated: still apart
    assert np.asarray(M.separated_pairs(separated, covered, 1))[4, 5]
    covered[5, 4] = 1  # covered more often: free to merge
    assert not np.asarray(M.separated_pairs(separated, covered, 1))[4, 5]
    assert not np.asarray(M.separated_pairs(separated, covered, 0)).any()
