"""The exported instance map: host-side (NumPy) post-processing of the instances taken out of the engine.

The engine holds instances as voxel slots and a label table; `fmfusion_jax.mapping.export` extracts each
instance's points and fused distribution into `MapInstance`s. What happens here follows the reference
pipeline's post-processing before evaluation (see docs): drop small instances, the shower-curtain rule,
merging all floors, and the conversion to ScanNet benchmark predictions. Beyond the reference: each instance's
existence (`existence_probability`: is it an object at all?), which ranks the benchmark predictions and drops the
instances that lost it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fmfusion_jax.config import ExportConfig
from fmfusion_jax.labels import LabelSets

#: The classes of the room's structure: never ranked as objects, never dropped for their existence, and in the
#: benchmark transfer they only keep the surfaces' vertices from the objects.
STRUCTURE_CLASSES = ("wall", "floor")


@dataclasses.dataclass
class MapInstance:
    """One instance of the final map.

    Attributes:
      instance_id: row of the instance in the engine's table (stable within a run).
      distribution: `(C,)` fused class distribution (sums to 1).
      points: `(P, 3)` float32 world points (voxel centres) of the instance.
      observations: how many detections were fused into it.
      open_label_histogram: `(O,)` accumulated open-set label scores.
      missed: detection frames in which it was in view and not detected.
      existence: in [0, 1], the evidence that the instance is an object at all (`existence_probability`); 1 when
        not known.
    """

    instance_id: int
    distribution: np.ndarray
    points: np.ndarray
    observations: int
    open_label_histogram: np.ndarray
    missed: int = 0
    existence: float = 1.0

    @property
    def class_index(self) -> int:
        return int(np.argmax(self.distribution))

    @property
    def confidence(self) -> float:
        """The class probability times the existence: the benchmark ranks by it within a class."""
        return float(np.max(self.distribution)) * float(self.existence)


def observation_support(observations: int, scale: float) -> float:
    """`1 - exp(-observations / scale)`: an instance seen in one detection frame (a fragment, a false blob, a
    one-off mislabel) ranks below one that the detector found again and again. `scale <= 0`: 1."""
    if scale <= 0:
        return 1.0
    return float(1.0 - np.exp(-max(int(observations), 0) / scale))


def detector_hit_rate(observations: np.ndarray, missed: np.ndarray, min_observations: int = 5) -> float | None:
    """How often this run's detector finds an object it has in view, as the map shows it: the median hit rate
    `observations / (observations + missed)` of the instances detected at least `min_observations` times, each
    weighted by its observations (the well-detected objects decide, not the many one-off fragments). None when
    no instance was detected that often.

    Per run, not a constant: a closed-set front end finds a curtain in a quarter of the frames that show it,
    a simulated detector in nine of ten, so an absolute rate would either keep every phantom of the one or drop
    the real objects of the other."""
    obs, miss = np.asarray(observations, np.float64), np.asarray(missed, np.float64)
    sure = obs >= max(int(min_observations), 1)
    if not sure.any():
        return None
    rate, weight = obs[sure] / (obs[sure] + miss[sure]), obs[sure]
    order = np.argsort(rate, kind="stable")
    cumulative = np.cumsum(weight[order])
    return float(rate[order][np.searchsorted(cumulative, cumulative[-1] / 2.0)])


def existence_probability(
    observations: int, missed: int, hit_rate: float | None, support_scale: float, prior_strength: float
) -> float:
    """Evidence in [0, 1] that an instance is an object: `support * min(1, posterior / hit_rate)`.

    - `support = observation_support(observations, support_scale)`: seen in one detection frame only (a
      fragment, a false blob, a one-off mislabel), it ranks below what the detector found again and again.
    - `posterior = (observations + prior_strength * hit_rate) / (observations + missed + prior_strength)`: its
      hit rate (detected / in view), shrunk towards the detector's own rate (`detector_hit_rate`) by
      `prior_strength` pseudo-frames. An object is found about as often as the detector finds objects; a
      patch of wall that the detector called a door now and then is in view far more often than it is
      detected (negative evidence: seen but not detected). Only a rate below the detector's lowers it.
    `prior_strength <= 0` or no `hit_rate`: the support alone.
    """
    support = observation_support(observations, support_scale)
    if prior_strength <= 0 or hit_rate is None or hit_rate <= 0:
        return support
    obs, miss = max(int(observations), 0), max(int(missed), 0)
    posterior = (obs + prior_strength * hit_rate) / (obs + miss + prior_strength)
    return support * min(1.0, posterior / hit_rate)


def thickness(points: np.ndarray) -> float:
    """Standard deviation (metres) of `points (N, 3)` along their thinnest principal axis (0 below 3 points)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) < 3:
        return 0.0
    centred = points - points.mean(axis=0)
    return float(np.sqrt(max(np.linalg.eigvalsh(centred.T @ centred / len(points))[0], 0.0)))


def _label_structure_parts(likelihood: np.ndarray, structure: list[int]) -> np.ndarray:
    """`(O, len(structure))` the part of each label's row of `likelihood (O, C)` (normalized: `p(class | label)`
    under a uniform prior) on each structure class."""
    rows = np.asarray(likelihood, np.float64)
    return (rows / np.maximum(rows.sum(axis=1, keepdims=True), 1e-12))[:, structure]


def structure_label_votes(open_label_histogram: np.ndarray, likelihood: np.ndarray, structure: list[int]) -> np.ndarray:
    """`(..., len(structure))` shares of an instance's open-set label scores that name each structure class (wall,
    floor); their sum is in [0, 1]. `open_label_histogram (..., O)`: one instance's, or a stack of them.

    Each label's votes are split over the classes as its row of `likelihood (O, C)` says (`p(class | label)`
    under a uniform prior): "wall" and "tile wall" go 0.9 to the wall, "carpet" 0.74 to the floor, "door" 0.1 to
    the wall. The additive fusion weighs a label by its row's sum, and the published rows of "wall" and "tile
    wall" sum to 0.09 against 0.57 for "closet": a patch of wall detected as "wall" most of the time and as
    "closet" or "door" now and then fuses as a door. Its labels still say wall. A histogram holds the summed
    detection scores per label; an empty one has no votes."""
    hist = np.asarray(open_label_histogram, np.float64)
    total = hist.sum(axis=-1, keepdims=True)
    votes = (hist @ _label_structure_parts(likelihood, structure)) / np.where(total > 0, total, 1.0)
    return np.clip(np.where(total > 0, votes, 0.0), 0.0, 1.0)


def expected_structure_share(likelihood: np.ndarray, structure: list[int]) -> np.ndarray:
    """`(C,)` the structure share (`structure_label_votes`, summed) of an object of each class whose labels come as
    its column of `likelihood (O, C)` says (`p(label | class)`: the column normalized). A door's detections name
    the wall now and then (0.12 under the published matrix), a bookshelf's hardly (0.04): the same share says more
    against a bookshelf than against a door."""
    rows = np.asarray(likelihood, np.float64)
    columns = rows / np.maximum(rows.sum(axis=0, keepdims=True), 1e-12)
    return np.clip(columns.T @ _label_structure_parts(likelihood, structure).sum(axis=1), 0.0, 1.0)


def as_structure(instance: MapInstance, votes: np.ndarray, structure: list[int]) -> MapInstance:
    """The instance as a piece of the room's structure: its distribution is its labels' structure `votes` over the
    `structure` classes (normalized), so that it is exported, merged (floors) and claims mesh vertices as walls and
    floors do, not as an object."""
    distribution = np.zeros_like(instance.distribution)
    distribution[structure] = votes / votes.sum()
    return dataclasses.replace(instance, distribution=distribution)


def score_existence(
    instances: list[MapInstance],
    label_sets: LabelSets,
    export: ExportConfig,
    voxel_size: float,
    likelihood: np.ndarray | None = None,
) -> list[MapInstance]:
    """Each instance with its `existence` (`existence_probability`), times `export.sheet_factor` for a sheet of a
    volumetric class; a surface whose labels name the structure (`structure_label_votes`, when the fusion's
    `likelihood (O, C)` is given) may be a piece of it (below).

    A sheet is an instance whose points are at most `export.planar_thickness` voxels thick (`thickness`): the
    surface of a wall, a counter front or the floor, which the detector called a cabinet, a bookshelf or a
    bed. Objects of those classes stand out of the surfaces they rest on; doors, windows, pictures, curtains
    (`export.flat_classes`), walls and floors may be flat. Weaker evidence, not a veto: a kitchen cabinet seen
    only from the front is a sheet too, and the detector finds it again and again.

    A surface is at most `export.surface_thickness` voxels thick: it may be a piece of a wall or the floor. When its
    existence times `1 - export.structure_label_factor * excess` falls below `export.min_existence` and its
    existence alone reached it, it is a piece of that structure (`as_structure`, at the lowered existence). The
    excess is the share of its label scores voting wall or floor beyond what an object of its fused class shows
    (`expected_structure_share`): doors' detections name the wall now and then, bookshelves' hardly. The labels
    decide that and nothing else: a surface they leave an object keeps its existence and rank. An object with volume
    is never judged by them (a detector that calls a toilet a wall is wrong about the label, not about the object)."""
    rate = detector_hit_rate(np.array([i.observations for i in instances]), np.array([i.missed for i in instances]))
    flat = {label_sets.class_index(name) for name in export.flat_classes if name in label_sets.class_names}
    sheet = export.planar_thickness * voxel_size
    structure = [label_sets.class_index(name) for name in STRUCTURE_CLASSES if name in label_sets.class_names]
    votes_of = None  # (N, len(structure)): every instance's structure votes, made in one product
    if likelihood is not None and export.structure_label_factor > 0 and structure and instances:
        votes_of = structure_label_votes(np.stack([i.open_label_histogram for i in instances]), likelihood, structure)
        expected = expected_structure_share(likelihood, structure)
    out = []
    for k, inst in enumerate(instances):
        existence = existence_probability(
            inst.observations, inst.missed, rate, export.support_observations, export.existence_prior
        )
        thick = thickness(inst.points)
        if sheet > 0 and inst.class_index not in flat and thick <= sheet:
            existence *= export.sheet_factor
        if votes_of is not None and inst.class_index not in structure and thick <= export.surface_thickness * voxel_size:
            votes = votes_of[k]
            excess = max(0.0, float(votes.sum()) - float(expected[inst.class_index]))
            object_existence = existence * max(0.0, 1.0 - export.structure_label_factor * excess)
            if object_existence < export.min_existence <= existence:
                inst, existence = as_structure(inst, votes, structure), object_existence
        out.append(dataclasses.replace(inst, existence=existence))
    return out


def drop_unlikely_instances(instances: list[MapInstance], label_sets: LabelSets, min_existence: float) -> list[MapInstance]:
    """Instances whose existence is below `min_existence` are not objects; walls and floors are kept (they are
    not ranked, and they keep the surfaces' mesh vertices from the objects in the benchmark transfer)."""
    structure = {label_sets.class_index(name) for name in STRUCTURE_CLASSES if name in label_sets.class_names}
    return [inst for inst in instances if inst.class_index in structure or inst.existence >= min_existence]


#: Least share of an instance's points its largest piece must hold to be its body (`drop_far_specks`): an instance
#: in many small pieces of similar size (a floor seen in patches between the furniture, few sparse samples) has no
#: body to measure specks from and is kept whole.
BODY_MIN_SHARE = 0.3


def drop_far_specks(points: np.ndarray, voxel_size: float, max_distance: float) -> np.ndarray:
    """`(P, 3)` points of an instance's voxel centres -> `(Q, 3)`, Q <= P: its body and what lies near it.

    The voxels fall into connected pieces (26-connected cells of two voxels, so a one-voxel gap does not
    split an object); the body is the largest piece, and a piece is kept when one of its points lies within
    `max_distance` metres of the body. A mask that bled onto a far wall or a wrong association far away
    leaves specks that claim mesh vertices there (and lower the instance's IoU) without being the object.
    `max_distance <= 0`, or a largest piece under `BODY_MIN_SHARE` of the points: every point."""
    from scipy import ndimage  # heavy: imported at export only
    from scipy.spatial import cKDTree

    points = np.asarray(points)
    if max_distance <= 0 or len(points) < 2:
        return points
    cells = np.floor((points - points.min(axis=0)) / (2.0 * voxel_size)).astype(np.int64)
    grid = np.zeros(cells.max(axis=0) + 1, bool)
    grid[tuple(cells.T)] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    if count < 2:
        return points
    piece = labels[tuple(cells.T)]
    body = piece == np.argmax(np.bincount(piece)[1:]) + 1
    if body.sum() < BODY_MIN_SHARE * len(points):
        return points
    near = np.zeros(count + 1, bool)
    # whether a point lies within reach is exact whatever the tree's shape: the quicker unbalanced one (0.25 -> 0.16 s
    # for a room's instances)
    tree = cKDTree(points[body], balanced_tree=False, compact_nodes=False)
    distance, _ = tree.query(points[~body], distance_upper_bound=max_distance)
    near[np.unique(piece[~body][np.isfinite(distance)])] = True
    return points[body | near[piece]]


def drop_small_instances(instances: list[MapInstance], min_points: int) -> list[MapInstance]:
    """Instances with fewer than `min_points` points are noise (reference: 200)."""
    return [inst for inst in instances if len(inst.points) >= min_points]


def apply_shower_curtain_rule(
    instances: list[MapInstance], label_sets: LabelSets, radius: float, both_ways: bool = True
) -> list[MapInstance]:
    """Curtain or shower curtain by the bathroom context: a curtain whose centre lies within `radius` of a
    toilet's or bathtub's centre is a shower curtain; with `both_ways`, a shower curtain farther than that
    from every toilet and bathtub (or in a room without one) is a curtain.

    Open-set detectors rarely say "shower curtain", and the published likelihood matrix gives the label
    "curtain" the same weight under both classes (0.665 vs 0.663), so the fused distribution cannot tell
    them apart: a stray "shower curtain" label tips any curtain over. The context decides instead (the
    reference applies the first direction only). The losing class's mass moves to the winning one; with
    `both_ways` also where the instance already has the winning class, so that its distribution does not offer
    the other as an alternative class of the same weight (`io.map_outputs.alternative_class_hypotheses`).
    """
    curtain = label_sets.class_index("curtain")
    shower = label_sets.class_index("shower curtain")
    anchors = [label_sets.class_index("toilet"), label_sets.class_index("bathtub")]
    anchor_centres = np.asarray(
        [inst.points.mean(axis=0) for inst in instances if inst.class_index in anchors and len(inst.points)]
    ).reshape(-1, 3)
    out = []
    for inst in instances:
        if inst.class_index in (curtain, shower) and len(inst.points):
            near = bool(len(anchor_centres)) and np.linalg.norm(anchor_centres - inst.points.mean(axis=0), axis=1).min() < radius
            source, target = (curtain, shower) if near else (shower, curtain)
            if both_ways or (inst.class_index == source and near):
                distribution = inst.distribution.copy()
                distribution[target] += distribution[source]
                distribution[source] = 0.0
                inst = dataclasses.replace(inst, distribution=distribution)
        out.append(inst)
    return out


def merge_same_class(instances: list[MapInstance], class_index: int) -> list[MapInstance]:
    """Merges every instance of one class into one (the reference merges all floors: a room has one)."""
    members = [inst for inst in instances if inst.class_index == class_index]
    if len(members) < 2:
        return instances
    counts = np.array([len(m.points) for m in members], np.float64)
    merged = MapInstance(
        instance_id=members[int(np.argmax(counts))].instance_id,
        distribution=np.average([m.distribution for m in members], axis=0, weights=counts),
        points=np.concatenate([m.points for m in members]),
        observations=sum(m.observations for m in members),
        open_label_histogram=np.sum([m.open_label_histogram for m in members], axis=0),
        missed=min(m.missed for m in members),
        existence=max(m.existence for m in members),
    )
    return [inst for inst in instances if inst.class_index != class_index] + [merged]


def postprocess_instances(instances: list[MapInstance], label_sets: LabelSets, export: ExportConfig) -> list[MapInstance]:
    """The reference's export post-processing, in its order, with the instances that are no objects
    (`drop_unlikely_instances`, existences scored before: `score_existence`) dropped after the small ones."""
    instances = drop_small_instances(instances, export.min_points)
    instances = drop_unlikely_instances(instances, label_sets, export.min_existence)
    instances = apply_shower_curtain_rule(
        instances, label_sets, export.shower_curtain_radius, both_ways=export.curtain_by_context
    )
    instances = merge_same_class(instances, label_sets.class_index("floor"))
    return sorted(instances, key=lambda inst: inst.instance_id)
