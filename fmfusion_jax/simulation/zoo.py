"""The noise zoo: families of detection failure modes, one preset each, and seeded random combinations.

The pipeline is developed and judged against many noise models, never against one (the simulator's own
`default` noise draws labels from the very likelihood the fusion uses). Each family raises one kind of
failure that real Grounded-SAM detections show; `noise_zoo` gives one entry per family plus random
mixtures of them, reproducible from a seed.

    default      the documented noise model (`NoiseModel.preset("default")`)
    label_model  labels drawn from a perturbed likelihood, with confusions the published matrix lacks
    partial      partial masks: objects cut by occluders or segmented by part
    merged       one mask over an object and its touching neighbour
    border       dilated and eroded mask borders that bleed onto the floor and walls behind
    confusers    non-target objects detected as a class, false blobs, missed small objects, miscalibrated scores
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fmfusion_jax.errors import UserError
from fmfusion_jax.simulation.noise import NoiseModel

#: The noise families, in report order.
FAMILIES = ("default", "label_model", "partial", "merged", "border", "confusers")
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


def _family_changes(family: str, severity: float) -> dict[str, Any]:
    """Noise parameters (on top of `default`) that make `family` the dominant failure mode."""
    s = float(severity)
    if family == "default":
        return {}
    if family == "label_model":
        return {"label_persistence": min(1.0, 0.5 * s)}
    if family == "partial":
        return {"partial_prob": min(0.6, 0.35 * s), "split_prob": min(0.3, 0.15 * s)}
    if family == "merged":
        return {"merge_prob": min(1.0, 0.3 * s)}
    if family == "border":
        return {"border_offset_px": 4.0 * s, "border_jitter_px": 4.0 * s}
    if family == "confusers":
        return {"false_positive_rate": 1.0 * s, "small_object_miss_prob": min(1.0, 0.5 * s)}
    raise UserError(f"unknown noise family {family!r}; choose one of {', '.join(FAMILIES)}")


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
    """
    entries = [ZooEntry(family, family, family_noise(family, severity, seed=seed)) for family in FAMILIES]
    rng = np.random.default_rng([seed, 4242])
    candidates = [f for f in FAMILIES if f != "default"]
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
        entries.append(ZooEntry(f"{MIXED}-{i}", MIXED, NoiseModel.preset("default", seed=seed, **params)))
    return entries


__all__ = ["FAMILIES", "MIXED", "ZooEntry", "family_noise", "noise_zoo"]
