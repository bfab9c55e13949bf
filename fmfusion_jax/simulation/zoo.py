"""The noise zoo: families of detection failure modes, one preset each, and seeded random combinations.

The pipeline is developed and judged against many noise models, never against one (the simulator's own
`default` noise draws labels from the very likelihood the fusion uses). Each family raises one kind of
failure that real Grounded-SAM detections show; `noise_zoo` gives one entry per family plus random
mixtures of them, reproducible from a seed.

    default      the documented noise model (`NoiseModel.preset("default")`)
    label_model  labels drawn from a perturbed likelihood, with confusions the published matrix lacks and
                 classes consistently named by one wrong label
    partial      partial masks: objects cut by occluders or segmented by part, large objects most
    merged       one mask over an object and its touching neighbour, of any kind but wall and floor
    border       dilated and eroded mask borders that bleed onto the floor and walls behind
    confusers    non-target objects detected as a class, false blobs, missed small objects, miscalibrated scores
    persistent   phantom objects fixed in the world (a spot of wall or floor, away from the objects), each
                 detected in most views as one closed class with one fixed label: fusion makes real
                 instances that cover no object
    background   wall, floor and unannotated regions taken for furniture (cabinet, bookshelf, table, ...)
                 in single frames: thin strips along the surface or large patches
    texture      large objects and background over-segmented into many small masks with random or weak
                 labels at low scores

A family at severity `s` moves each of its parameters from the `default` value to `default + s * (dose -
default)` (`FAMILY_DOSES`: severity 1 is the dose, 0 is `default`), probabilities clipped to [0, 1] and
exclusive probabilities scaled down to sum to at most 1. `NoiseModel.preset(family)` is the family at
severity 1, so `fmfusion simulate SCENE --out DIR --noise-preset border --set bleed_px=8` works.

The last three families (`LATER_FAMILIES`) were added after the zoo had been used: their parameters are
left out of the noise records at 0 (`noise.LATER_PARAMS`), so the other entries keep their cache names and
detections, and mixtures draw them from a stream of their own after the first five (see `noise_zoo`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fmfusion_jax.errors import UserError
from fmfusion_jax.simulation.noise import EXCLUSIVE_GROUPS, FAMILY_PRESETS, PROBABILITIES, NoiseModel

#: The noise families, in report order.
FAMILIES = ("default", *FAMILY_PRESETS)
#: The parameters of each family at severity 1, on top of `default`: a clear, realistic dose of its failure mode.
FAMILY_DOSES: dict[str, dict[str, float]] = {
    "default": {},
    "label_model": {
        "likelihood_perturbation": 0.7,
        "extra_confusion_prob": 0.25,
        "consistent_mislabel_prob": 0.3,
        "label_persistence": 0.5,
    },
    "partial": {
        "partial_large_prob": 0.5,
        "partial_prob": 0.35,
        "split_prob": 0.15,
        "partial_straight_share": 0.4,
        "partial_occluder_share": 0.3,
    },
    "merged": {"merge_neighbor_prob": 0.3, "merge_prob": 0.2},
    "border": {
        "bleed_prob": 0.5,
        "bleed_px": 8.0,
        "erode_prob": 0.2,
        "erode_px": 3.0,
        "border_offset_px": 2.5,
        "border_jitter_px": 3.0,
    },
    "confusers": {"confuser_prob": 0.5, "blob_rate": 0.8, "small_object_miss_prob": 0.5, "score_miscalibration": 0.6},
    "persistent": {"persistent_phantoms": 4.0, "persistent_radius_m": 0.3, "persistent_detect_prob": 0.8},
    "background": {"background_rate": 1.0, "background_strip_share": 0.5},
    "texture": {"texture_prob": 0.25},
}
#: Families added after the first zoo: mixtures draw them from a separate stream (see `noise_zoo`).
LATER_FAMILIES = ("persistent", "background", "texture")
#: The family name of a random combination of the families.
MIXED = "mixed"


@dataclasses.dataclass(frozen=True)
class ZooEntry:
    """One noise setting of the zoo.

    Attributes:
      name: unique, file-name safe (e.g. ``"border"``, ``"mixed-2"``).
      family: one of `FAMILIES`, or `MIXED`.
      noise: the noise model (its `seed` set).
    """

    name: str
    family: str
    noise: NoiseModel


def _fit(params: dict[str, Any]) -> dict[str, Any]:
    """Probabilities clipped to [0, 1]; exclusive ones (`EXCLUSIVE_GROUPS`) scaled down to sum to 1 at most."""
    out = {k: min(max(v, 0.0), 1.0) if k in PROBABILITIES else v for k, v in params.items()}
    base = NoiseModel()
    for group in EXCLUSIVE_GROUPS:
        if not any(name in out for name in group):
            continue
        total = sum(out.get(name, getattr(base, name)) for name in group)
        if total > 1.0:
            for name in group:
                out[name] = out.get(name, getattr(base, name)) / total
    return out


def _family_changes(family: str, severity: float) -> dict[str, Any]:
    """Noise parameters (on top of `default`) that make `family` the dominant failure mode.

    Each parameter goes linearly from its `default` value (severity 0) to its dose (severity 1) and on.
    """
    if family not in FAMILY_DOSES:
        raise UserError(f"unknown noise family {family!r}; choose one of {', '.join(FAMILIES)}")
    s, base = float(severity), NoiseModel()
    return _fit({name: getattr(base, name) + s * (dose - getattr(base, name)) for name, dose in FAMILY_DOSES[family].items()})


def family_noise(family: str, severity: float = 1.0, seed: int = 0, **changes: Any) -> NoiseModel:
    """The noise model of one family at `severity` (1 = the documented preset; 0 = `default`)."""
    if severity < 0:
        raise UserError(f"severity must be >= 0, got {severity}")
    params = _family_changes(family, severity)
    params.update(changes)
    return NoiseModel.preset("default", seed=seed, **params)


def noise_zoo(mixed: int = 4, seed: int = 0, severity: float = 1.0) -> list[ZooEntry]:
    """One entry per family of `FAMILIES`, then `mixed` random combinations (`"mixed-1"`, ...).

    A combination draws each family with probability 1/2 (at least two) at a random severity in
    [0.5, 1.5] x `severity`; its parameters are the union (the larger failure probability wins).
    Deterministic for a seed.

    The first five families are drawn from the stream the zoo always used (`[seed, 4242]`), at least two
    of them, so a mixture keeps its families and severities; `LATER_FAMILIES` are then drawn, each with
    probability 1/2, from a stream of the mixture's own (`[seed, 4243, i]`). Their parameters are their
    own, so a mixture that draws none of them is the very model (and cache) it was before.
    """
    entries = [ZooEntry(family, family, family_noise(family, severity, seed=seed)) for family in FAMILIES]
    rng = np.random.default_rng([seed, 4242])
    candidates = [f for f in FAMILIES if f != "default" and f not in LATER_FAMILIES]
    for i in range(1, mixed + 1):
        chosen = [f for f in candidates if rng.random() < 0.5]
        while len(chosen) < 2:
            extra = candidates[int(rng.integers(len(candidates)))]
            if extra not in chosen:
                chosen.append(extra)
        params: dict[str, Any] = {}
        for family in sorted(chosen, key=candidates.index):
            for key, value in _family_changes(family, severity * rng.uniform(0.5, 1.5)).items():
                params[key] = max(params.get(key, value), value)
        later = np.random.default_rng([seed, 4243, i])
        for family in LATER_FAMILIES:
            drawn, scale = later.random() < 0.5, later.uniform(0.5, 1.5)
            if drawn:
                for key, value in _family_changes(family, severity * scale).items():
                    params[key] = max(params.get(key, value), value)
        entries.append(ZooEntry(f"{MIXED}-{i}", MIXED, NoiseModel.preset("default", seed=seed, **_fit(params))))
    return entries


__all__ = ["FAMILIES", "FAMILY_DOSES", "LATER_FAMILIES", "MIXED", "ZooEntry", "family_noise", "noise_zoo"]
