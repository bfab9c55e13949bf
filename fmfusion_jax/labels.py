"""The label sets (open-set labels L_o, closed classes L_c) and the label-likelihood matrices.

The figures live in `configs/labels/` (copied from the authors' published data, source named there);
this module reads them (and writes matrices in the same CSV format, for `fmfusion likelihood`).
"""

from __future__ import annotations

import dataclasses
import functools
from importlib import resources
from pathlib import Path

import numpy as np
import yaml

from fmfusion_jax.errors import UserError

#: nyu40 ids of the 18 classes of the ScanNet 3D semantic instance benchmark (no wall, no floor).
BENCHMARK_NYU40_IDS = (3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39)


def labels_dir() -> Path:
    """Folder of the label data files (`configs/labels` of the source tree, packaged with the wheel)."""
    return Path(str(resources.files("fmfusion_jax.configs.labels")))


@dataclasses.dataclass(frozen=True)
class LabelSets:
    """Open-set labels of interest and closed classes.

    Attributes:
      open_labels: the 38 open-set labels L_o (row order of every likelihood matrix).
      class_names: the 20 closed classes L_c (column order).
      nyu40_ids: `(20,)` int, NYU40 id of each closed class.
      class_colors: `(20, 3)` uint8 NYU40 palette colour of each class.
      prompt_augmentation_excluded: labels never added to a prompt by augmentation.
    """

    open_labels: tuple[str, ...]
    class_names: tuple[str, ...]
    nyu40_ids: np.ndarray
    class_colors: np.ndarray
    prompt_augmentation_excluded: tuple[str, ...]

    @property
    def num_open(self) -> int:
        return len(self.open_labels)

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def class_index(self, name: str) -> int:
        return self.class_names.index(name)

    def nyu40_to_class_index(self) -> dict[int, int]:
        return {int(n): i for i, n in enumerate(self.nyu40_ids)}

    def class_to_nyu40(self) -> dict[str, int]:
        """The NYU40 id of each closed-class name."""
        return dict(zip(self.class_names, (int(i) for i in self.nyu40_ids)))


@functools.cache
def load_label_sets(path: str | None = None) -> LabelSets:
    """Reads `label_sets.yaml` (the packaged one unless `path` is given)."""
    file = Path(path) if path else labels_dir() / "label_sets.yaml"
    data = yaml.safe_load(file.read_text())
    classes = data["closed_classes"]
    return LabelSets(
        open_labels=tuple(data["open_labels"]),
        class_names=tuple(c["name"] for c in classes),
        nyu40_ids=np.array([c["nyu40_id"] for c in classes], np.int32),
        class_colors=np.array([c["color"] for c in classes], np.uint8),
        prompt_augmentation_excluded=tuple(data.get("prompt_augmentation_excluded", ())),
    )


def normalize_columns(likelihood: np.ndarray) -> np.ndarray:
    """`(O, C)` likelihood -> the same with each class's column scaled to sum 1 (a column of zeros stays zeros).

    The published matrices give `p(y = o, o in prompt | c)`: a column sums to how often the class is detected
    (and tagged) at all, 0.43 for walls against 1.6 for desks in the statistical one. Label fusion sees
    detections only, so the column that matters is `p(y | c, detected)`: with the raw columns the additive update
    weighs every detection of a seldom-detected class less, and a wall's labels ("wall", "closet", "door",
    "shelf") summed to more door and bookshelf than wall."""
    likelihood = np.asarray(likelihood, np.float64)
    sums = likelihood.sum(axis=0, keepdims=True)
    return likelihood / np.where(sums > 0, sums, 1.0)


def read_likelihood_csv(path: str | Path, label_sets: LabelSets | None = None) -> np.ndarray:
    """Reads a `(num_open, num_classes)` likelihood matrix written as CSV with a header row.

    Rows and columns are checked against the label sets, so a matrix in another order is an error
    rather than a silently wrong model.
    """
    label_sets = label_sets or load_label_sets()
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise UserError(
            f"{path}: cannot read the likelihood matrix ({getattr(error, 'strerror', None) or error}); "
            "label_fusion.likelihood is statistical, manual or the path of a CSV"
        ) from None
    lines = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    if not lines:
        raise UserError(f"{path}: an empty likelihood matrix file")
    header = lines[0].split(",")
    if tuple(header[1:]) != label_sets.class_names:
        raise ValueError(f"{path}: columns {header[1:]} do not match the closed classes {list(label_sets.class_names)}")
    rows, values = [], []
    for line in lines[1:]:
        fields = line.split(",")
        rows.append(fields[0])
        values.append([float(x) for x in fields[1:]])
    if tuple(rows) != label_sets.open_labels:
        raise ValueError(f"{path}: rows {rows} do not match the open-set labels {list(label_sets.open_labels)}")
    matrix = np.asarray(values, np.float64)
    if not np.all(np.isfinite(matrix)) or matrix.min() < 0:
        raise ValueError(f"{path}: a likelihood matrix must be finite and non-negative")
    return matrix


def write_likelihood_csv(path: str | Path, matrix: np.ndarray, label_sets: LabelSets | None = None, comment: str = "") -> Path:
    """Writes a `(num_open, num_classes)` matrix in the format `read_likelihood_csv` reads.

    `comment` lines go first as `# ...`; values are written with `repr`, so a read gives the same floats.
    """
    label_sets = label_sets or load_label_sets()
    matrix = np.asarray(matrix, np.float64)
    if matrix.shape != (label_sets.num_open, label_sets.num_classes):
        raise ValueError(f"likelihood shape {matrix.shape}, expected {(label_sets.num_open, label_sets.num_classes)}")
    lines = [f"# {line}" for line in comment.splitlines()]
    lines.append("open_label," + ",".join(label_sets.class_names))
    lines += [name + "," + ",".join(repr(float(x)) for x in row) for name, row in zip(label_sets.open_labels, matrix)]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def load_likelihood(name: str = "statistical") -> np.ndarray:
    """The packaged likelihood `"statistical"` or `"manual"`, or a CSV file path."""
    if name in ("statistical", "manual"):
        return read_likelihood_csv(labels_dir() / f"likelihood_{name}.csv")
    return read_likelihood_csv(name)
