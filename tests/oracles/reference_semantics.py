"""Plain NumPy references of the association, label-fusion, merge and maintenance kernels.

Written for clarity, with explicit loops and sorting, as the test oracle of the jitted functions in
`detections`, `association`, `label_fusion`, `merge` and `maintenance`. Not for use in the pipeline.
"""

from __future__ import annotations

import numpy as np

# ----------------------------------------------------------------------------- detections


def detection_pixel_image(masks: np.ndarray, valid: np.ndarray, stride: int) -> np.ndarray:
    sub = masks[:, ::stride, ::stride] & valid[:, None, None]
    area = sub.reshape(sub.shape[0], -1).sum(1)
    out = np.full(sub.shape[1:], -1, np.int32)
    for v in range(sub.shape[1]):
        for u in range(sub.shape[2]):
            covering = [n for n in range(sub.shape[0]) if sub[n, v, u]]
            if covering:
                out[v, u] = min(covering, key=lambda n: (area[n], n))
    return out


def depth_percentile_bins(depths: np.ndarray, lo: float, hi: float, bin_size: float, num_bins: int):
    """Bins holding the order statistics of rank floor(lo (n-1)) and ceil(hi (n-1)) of `depths`."""
    d = np.sort(depths.astype(np.float32))
    last = np.float32(len(d) - 1)
    r_lo = int(np.floor(np.float32(lo) * last))
    r_hi = int(np.ceil(np.float32(hi) * last))

    def to_bin(x):
        return int(np.clip(np.floor(np.float32(x) / np.float32(bin_size)), 0, num_bins - 1))

    return to_bin(d[r_lo]), to_bin(d[r_hi])


def filter_detection_depth(det_image, depth_s, n_max, lo=0.1, hi=0.9, bin_size=0.01, depth_max=4.0):
    num_bins = max(1, int(np.ceil(depth_max / bin_size)))
    out = np.full(det_image.shape, -1, np.int32)
    bins = np.clip(np.floor(depth_s.astype(np.float32) / np.float32(bin_size)), 0, num_bins - 1).astype(int)
    for n in range(n_max):
        sel = (det_image == n) & (depth_s > 0)
        if not sel.any():
            continue
        b_lo, b_hi = depth_percentile_bins(depth_s[sel], lo, hi, bin_size, num_bins)
        keep = sel & (bins >= b_lo) & (bins <= b_hi)
        out[keep] = n
    return out


# ----------------------------------------------------------------------------- association


def association_scores(det_image, pixel_instances, n_max, k):
    inter = np.zeros((n_max, k), np.int32)
    det_area = np.zeros(n_max, np.int32)
    inst_area = np.zeros(k, np.int32)
    hs, ws, _ = pixel_instances.shape
    for v in range(hs):
        for u in range(ws):
            d = det_image[v, u]
            seen = {int(i) for i in pixel_instances[v, u] if 0 <= i < k}
            if 0 <= d < n_max:
                det_area[d] += 1
            for i in seen:
                inst_area[i] += 1
                if 0 <= d < n_max:
                    inter[d, i] += 1
    return inter, det_area, inst_area


def association_score_matrix(inter, det_area, inst_area, metric):
    out = np.zeros(inter.shape, np.float64)
    for n in range(inter.shape[0]):
        for j in range(inter.shape[1]):
            if metric == "iou":
                denom = det_area[n] + inst_area[j] - inter[n, j]
            else:
                denom = inst_area[j]
            out[n, j] = inter[n, j] / denom if denom > 0 else 0.0
    return out


def match_detections(scores, valid_det, valid_inst, threshold, one_to_one=True, rank=None):
    n, k = scores.shape
    rank = scores if rank is None else rank
    cands = [
        (-float(rank[i, j]), i, j)
        for i in range(n)
        for j in range(k)
        if valid_det[i] and valid_inst[j] and scores[i, j] > threshold
    ]
    match = np.full(n, -1, np.int32)
    if not one_to_one:
        for _, i, j in sorted(cands):
            if match[i] < 0:
                match[i] = j
        return match
    used = set()
    for _, i, j in sorted(cands):
        if match[i] < 0 and j not in used:
            match[i] = j
            used.add(j)
    return match


def allocate_instances(valid, needs_new):
    free = [j for j in range(len(valid)) if not valid[j]]
    inst = np.full(len(needs_new), -1, np.int32)
    new_valid = np.array(valid, bool)
    taken = 0
    overflow = 0
    for i, need in enumerate(needs_new):
        if not need:
            continue
        if taken < len(free):
            inst[i] = free[taken]
            new_valid[free[taken]] = True
            taken += 1
        else:
            overflow += 1
    return inst, new_valid, overflow


# ----------------------------------------------------------------------------- label fusion


def measurement_likelihood(label_scores, likelihood):
    n, o = label_scores.shape
    out = np.zeros((n, likelihood.shape[1]))
    for i in range(n):
        for y in range(o):
            out[i] += label_scores[i, y] * likelihood[y]
    return out


def measurement_log_likelihood(label_scores, likelihood, eps=1e-3, score_weighted=False):
    n, o = label_scores.shape
    out = np.zeros((n, likelihood.shape[1]))
    for i in range(n):
        for y in range(o):
            if label_scores[i, y] > 0:
                w = label_scores[i, y] if score_weighted else 1.0
                out[i] += w * np.log(np.maximum(likelihood[y], eps))
    return out


def fuse(evidence, instance_for_detection, values, valid, mode, reset=None):
    out = np.array(evidence, np.float64)
    if reset is not None:
        out[np.asarray(reset, bool)] = 0
    for i, j in enumerate(instance_for_detection):
        if valid[i] and 0 <= j < len(out):
            out[j] += values[i]
    if mode == "bayes":
        out -= out.max(axis=1, keepdims=True)
    return out


def class_distribution(evidence, mode, prior_weight=1.0):
    e = np.asarray(evidence, np.float64)
    c = e.shape[1]
    if mode == "bayes":
        x = np.exp(e - e.max(1, keepdims=True))
        return x / x.sum(1, keepdims=True)
    num = e + prior_weight / c
    total = num.sum(1, keepdims=True)
    return np.where(total > 0, num / np.where(total > 0, total, 1), 1.0 / c)


def paper_additive_recursion(measurements):
    """The paper's final equation applied measurement by measurement: p_t = (z_t + (t-1) p_{t-1}) / t."""
    p = np.zeros_like(measurements[0], dtype=np.float64)
    for t, z in enumerate(measurements, start=1):
        p = (z + (t - 1) * p) / t
    return p


def update_label_statistics(hist, observations, instance_for_detection, label_scores, valid, reset=None):
    hist = np.array(hist, np.float64)
    obs = np.array(observations, np.int64)
    if reset is not None:
        hist[np.asarray(reset, bool)] = 0
        obs[np.asarray(reset, bool)] = 0
    for i, j in enumerate(instance_for_detection):
        if valid[i] and 0 <= j < len(obs):
            hist[j] += label_scores[i]
            obs[j] += 1
    return hist, obs


# ----------------------------------------------------------------------------- merge


def semantic_similarity(dist):
    p = np.asarray(dist, np.float64)
    p = p / p.sum(1, keepdims=True)
    k = len(p)
    return np.array([[float(np.dot(p[a], p[b])) for b in range(k)] for a in range(k)])


def _larger(a, b, voxel_count):
    return (a, b) if (voxel_count[a], -a) > (voxel_count[b], -b) else (b, a)


def merge_pairs(similarity, overlap, voxel_count, valid, sim_threshold=0.15, overlap_ratio=0.4):
    k = len(valid)
    out = np.zeros((k, k), bool)
    for i in range(k):
        for j in range(k):
            if i == j or not (valid[i] and valid[j]):
                continue
            a, b = _larger(i, j, voxel_count)
            ratio = overlap[a, b] / voxel_count[b] if voxel_count[b] > 0 else 0.0
            out[i, j] = similarity[i, j] > sim_threshold and ratio > overlap_ratio
    return out


def post_merge_pairs(similarity, overlap, voxel_count, valid, sim_threshold=0.1, iou_threshold=0.2):
    k = len(valid)
    out = np.zeros((k, k), bool)
    for i in range(k):
        for j in range(k):
            if i == j or not (valid[i] and valid[j]):
                continue
            a, b = _larger(i, j, voxel_count)
            union = voxel_count[a] + voxel_count[b] - overlap[a, b]
            iou = overlap[a, b] / union if union > 0 else 0.0
            out[i, j] = similarity[i, j] > sim_threshold and iou > iou_threshold
    return out


def merge_groups(pairs, valid, voxel_count):
    """Union-find over the valid pairs; representative = largest (ties: lowest index) of the component."""
    k = len(valid)
    parent = list(range(k))

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for i in range(k):
        for j in range(k):
            if i != j and valid[i] and valid[j] and (pairs[i, j] or pairs[j, i]):
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(k):
        if valid[i]:
            groups.setdefault(find(i), []).append(i)
    rep = np.full(k, -1, np.int32)
    for members in groups.values():
        best = max(members, key=lambda m: (voxel_count[m], -m))
        rep[members] = best
    return rep


def merge_instance_table(rows: dict, representative, mode="additive"):
    """`rows`: dict of the `TableRows` fields as NumPy arrays. Returns (new rows dict, new_id)."""
    valid = np.asarray(rows["valid"], bool)
    k = len(valid)
    out = {name: np.array(value) for name, value in rows.items()}
    out["label_evidence"] = out["label_evidence"].astype(np.float64)
    out["open_label_histogram"] = out["open_label_histogram"].astype(np.float64)
    for i in range(k):
        if valid[i] and representative[i] != i:
            out["valid"][i] = False
            for name in ("label_evidence", "open_label_histogram", "observations", "missed", "voxel_count"):
                out[name][i] = 0
            out["created_frame"][i] = -1
            out["last_seen_frame"][i] = -1
    for r in range(k):
        if not (valid[r] and representative[r] == r):
            continue
        members = [i for i in range(k) if valid[i] and representative[i] == r]
        for name in ("label_evidence", "open_label_histogram", "observations", "voxel_count"):
            out[name][r] = np.sum([rows[name][i] for i in members], axis=0)
        out["missed"][r] = min(rows["missed"][i] for i in members)
        out["created_frame"][r] = min(rows["created_frame"][i] for i in members)
        out["last_seen_frame"][r] = max(rows["last_seen_frame"][i] for i in members)
        if mode == "bayes":
            out["label_evidence"][r] -= out["label_evidence"][r].max()
    new_id = np.where(valid, representative, -1).astype(np.int32)
    return out, new_id


# ----------------------------------------------------------------------------- maintenance


def update_missed(missed, valid, in_view, matched):
    return np.array([m + int(v and iv and not mt) for m, v, iv, mt in zip(missed, valid, in_view, matched)])


def instances_to_remove(missed, voxel_count, valid, max_missed=5, min_voxels=500):
    return np.array([bool(v and m >= max_missed and c < min_voxels) for m, c, v in zip(missed, voxel_count, valid)])
