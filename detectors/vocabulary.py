"""The name table from closed-set model vocabularies (COCO, ImageNet) to FM-Fusion's open-set labels L_o.

`configs/labels/model_vocabulary.yaml` (our own table; its header says where the names come from) holds one
section per model vocabulary (``coco``, ``imagenet``); each entry maps a model name to an open-set label
with a weight in (0, 1] (how much the name says about the label), or to nothing. `Vocabulary.map_scores`
turns a model's ``{name: score}`` into ``{open label: score}``: score x weight, the max over the names that
map to the same label. The table is checked on load: an unknown label, a bad weight or a malformed entry is
a `UserError` naming the file and the entry.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import yaml

from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import labels_dir, load_label_sets

VOCABULARY_FILE = "model_vocabulary.yaml"
#: The sections a table may have: the detector's and the classifier's vocabularies.
SOURCES = ("coco", "imagenet")


@dataclasses.dataclass(frozen=True)
class LabelEntry:
    """What one model name says: an open-set label and how strongly (weight in (0, 1])."""

    label: str
    weight: float = 1.0


@dataclasses.dataclass(frozen=True)
class Vocabulary:
    """The validated table.

    Attributes:
      path: the file it was read from.
      tables: source (``"coco"``, ``"imagenet"``) -> model name -> `LabelEntry`, or None (dropped).
    """

    path: Path
    tables: dict[str, dict[str, LabelEntry | None]]

    def entry(self, source: str, name: str) -> LabelEntry | None:
        """The entry of `name` in `source`'s section; None when listed as null or not listed."""
        return self.tables.get(source, {}).get(name)

    def maps(self, source: str, name: str) -> bool:
        """Whether `name` of `source` names an open-set label."""
        return self.entry(source, name) is not None

    def map_scores(self, scores: Mapping[str, float] | Iterable[tuple[str, float]], source: str) -> dict[str, float]:
        """``{model name: score}`` (or `(name, score)` pairs) -> ``{open label: score x weight}``, max per label.

        Names without an open label are dropped; so an empty dict means nothing known was named.
        """
        pairs = scores.items() if isinstance(scores, Mapping) else scores
        out: dict[str, float] = {}
        for name, score in pairs:
            entry = self.entry(source, name)
            if entry is not None:
                out[entry.label] = max(out.get(entry.label, 0.0), float(score) * entry.weight)
        return out

    def unknown_names(self, source: str, names: Sequence[str]) -> list[str]:
        """Names of `source`'s section that are not in a model's `names` (typos, another model's vocabulary)."""
        known = set(names)
        return [name for name in self.tables.get(source, {}) if name not in known]


def default_vocabulary_path() -> Path:
    return labels_dir() / VOCABULARY_FILE


def load_vocabulary(path: str | Path | None = None, open_labels: Sequence[str] | None = None) -> Vocabulary:
    """Reads and checks a vocabulary table (the packaged one unless `path` is given).

    `open_labels`: the labels entries may name; None: the 38 of `label_sets.yaml`.
    """
    path = Path(path) if path is not None else default_vocabulary_path()
    allowed = set(open_labels if open_labels is not None else load_label_sets().open_labels)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise UserError(f"{path}: cannot read the model vocabulary ({error.strerror or error})") from None
    except yaml.YAMLError as error:
        raise UserError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected sections {', '.join(SOURCES)} mapping model names to open-set labels")
    unknown = [key for key in data if key not in SOURCES]
    if unknown:
        raise UserError(f"{path}: unknown section(s) {unknown}; expected {', '.join(SOURCES)}")
    tables: dict[str, dict[str, LabelEntry | None]] = {}
    for source, section in data.items():
        if section is None:
            section = {}
        if not isinstance(section, dict):
            raise UserError(f"{path}: section {source!r} must map model names to labels")
        tables[source] = {str(name): _entry(path, source, str(name), value, allowed) for name, value in section.items()}
    return Vocabulary(path, tables)


def _entry(path: Path, source: str, name: str, value, allowed: set[str]) -> LabelEntry | None:
    """One checked entry: `label`, ``{label, weight}`` or None."""
    where = f"{path}: {source} entry {name!r}"
    if value is None:
        return None
    if isinstance(value, str):
        label, weight = value, 1.0
    elif isinstance(value, dict):
        extra = set(value) - {"label", "weight"}
        if extra or "label" not in value:
            raise UserError(f"{where}: expected {{label: ..., weight: ...}}, got keys {sorted(value)}")
        label, weight = value["label"], value.get("weight", 1.0)
        if not isinstance(label, str):
            raise UserError(f"{where}: label {label!r} must be a string")
    else:
        raise UserError(f"{where}: expected an open-set label, {{label, weight}} or null, got {value!r}")
    if label not in allowed:
        raise UserError(f"{where} -> {label!r}: not an open-set label (the 38 open_labels of label_sets.yaml)")
    if isinstance(weight, bool) or not isinstance(weight, int | float) or not 0.0 < weight <= 1.0:
        raise UserError(f"{where}: weight {weight!r} must be a number in (0, 1]")
    return LabelEntry(label, float(weight))
