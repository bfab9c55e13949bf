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

from fmfusion_jax.simulation.noise import FAMILIES, FAMILY_DOSES, NoiseModel, family_changes, family_noise, fit_probabilities

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
            for key, value in family_changes(family, severity * rng.uniform(0.5, 1.5)).items():
                params[key] = max(params.get(key, value), value)
        later = np.random.default_rng([seed, 4243, i])
        for family in LATER_FAMILIES:
            drawn, scale = later.random() < 0.5, later.uniform(0.5, 1.5)
            if drawn:
                for key, value in family_changes(family, severity * scale).items():
                    params[key] = max(params.get(key, value), value)
        entries.append(ZooEntry(f"{MIXED}-{i}", MIXED, NoiseModel.preset("default", seed=seed, **fit_probabilities(params))))
    return entries


__all__ = ["FAMILIES", "FAMILY_DOSES", "LATER_FAMILIES", "MIXED", "ZooEntry", "family_noise", "noise_zoo"]
