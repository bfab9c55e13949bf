"""The ScanNet instance benchmark's prediction format.

A scene's predictions are `<out>/<scene>.txt`, one line per prediction::

    pred_mask/<scene>_<k>.txt <nyu40 id> <confidence>

where the mask path is relative to the folder of `<scene>.txt` and each mask file holds one `0`/`1` per
line, one line per vertex of `<scene>_vh_clean_2.ply`, in the mesh's vertex order. Each line has a mask file of
its own: the official script keys the predictions by mask file. An instance may come again under another class,
an *alternative* class hypothesis (the benchmark scores each line on its own, per class), with a copy of its mask:
read back, a line whose mask equals an earlier line's and whose class differs is such an alternative. Two touching
hypotheses of one class may come again as one, a *union* hypothesis: read back, a line whose mask is the union of two
earlier lines' masks of its class (not unions themselves). Both kinds are hypotheses beside the map's instances (`alternative`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fmfusion_jax.errors import DataError
from fmfusion_jax.labels import BENCHMARK_NYU40_IDS

logger = logging.getLogger(__name__)

#: Bytes a mask file may have per mesh vertex (``0\\r\\n`` is 3), before it is refused unread.
_MASK_BYTES_PER_VERTEX = 4
#: ... and the cap when the vertex count is not known yet.
_MAX_MASK_BYTES = 256 * 2**20

if TYPE_CHECKING:
    from fmfusion_jax.io.ground_truth import SceneGroundTruth

#: Folder of the mask files, beside the `<scene>.txt` files.
MASK_FOLDER = "pred_mask"


@dataclasses.dataclass(frozen=True, eq=False)
class InstancePredictions:
    """Predicted instances of one scene, on the vertices of its evaluation mesh.

    Attributes:
      masks: `(P, V)` bool, one vertex mask per prediction.
      nyu40_ids: `(P,)` int64 nyu40 class of each prediction.
      confidences: `(P,)` float64 confidence of each prediction.
      alternative: `(P,)` bool, true for a hypothesis beside the instances: the same mask as an earlier
        prediction (its instance's most likely class) under another class, or the union of two earlier
        predictions of one class. None: no alternatives.
    """

    masks: np.ndarray
    nyu40_ids: np.ndarray
    confidences: np.ndarray
    alternative: np.ndarray = None  # type: ignore[assignment]  # None: no alternatives; normalised to (P,) bool

    def __post_init__(self) -> None:
        masks = np.asarray(self.masks, bool)
        if masks.ndim != 2:
            raise ValueError(f"masks must be (P, V), got shape {masks.shape}")
        ids = np.asarray(self.nyu40_ids).astype(np.int64).reshape(-1)
        confidences = np.asarray(self.confidences, np.float64).reshape(-1)
        alternative = np.zeros(len(masks), bool) if self.alternative is None else np.asarray(self.alternative, bool).reshape(-1)
        if ids.shape[0] != masks.shape[0] or confidences.shape[0] != masks.shape[0] or alternative.shape[0] != masks.shape[0]:
            raise ValueError(
                f"{masks.shape[0]} masks but {ids.shape[0]} nyu40 ids, {confidences.shape[0]} confidences and "
                f"{alternative.shape[0]} alternative flags"
            )
        # Normalised copies on a frozen dataclass.
        object.__setattr__(self, "masks", masks)
        object.__setattr__(self, "nyu40_ids", ids)
        object.__setattr__(self, "confidences", confidences)
        object.__setattr__(self, "alternative", alternative)

    @property
    def num_instances(self) -> int:
        """The predicted instances: the predictions less the alternative class and union hypotheses."""
        return int(np.count_nonzero(~self.alternative))

    @property
    def num_predictions(self) -> int:
        """Every prediction (line of `<scene>.txt`), alternative class and union hypotheses included."""
        return int(self.masks.shape[0])

    def primary(self) -> "InstancePredictions":
        """Each instance once, under its most likely class (the alternatives left out): what an error analysis
        counts as the map's instances."""
        if not self.alternative.any():
            return self
        keep = ~self.alternative
        return InstancePredictions(self.masks[keep], self.nyu40_ids[keep], self.confidences[keep])

    @property
    def num_vertices(self) -> int:
        return int(self.masks.shape[1])

    @staticmethod
    def empty(num_vertices: int) -> "InstancePredictions":
        return InstancePredictions(np.zeros((0, num_vertices), bool), np.zeros(0, np.int64), np.zeros(0))


def write_benchmark_predictions(out_dir: str | Path, scene_name: str, preds: InstancePredictions) -> Path:
    """Writes `<out_dir>/<scene_name>.txt` and its masks `<out_dir>/pred_mask/<scene_name>_<k>.txt`, one mask file
    per line: the official evaluation script keys the predictions by mask file, so an alternative class hypothesis
    has a copy of its instance's mask of its own (a file listed twice would keep only its last line).

    Mask files of an earlier run with more instances are not removed: only those listed count.

    Returns:
      the path of `<scene_name>.txt`.
    """
    out_dir = Path(out_dir)
    (out_dir / MASK_FOLDER).mkdir(parents=True, exist_ok=True)
    lines = []
    for k in range(preds.num_predictions):
        relative = f"{MASK_FOLDER}/{scene_name}_{k}.txt"
        # One byte '0'/'1' then '\n' per vertex, built as a (V, 2) byte array: fast for 10^5 vertices.
        rows = np.empty((preds.num_vertices, 2), np.uint8)
        rows[:, 0] = preds.masks[k].astype(np.uint8) + ord("0")
        rows[:, 1] = ord("\n")
        (out_dir / relative).write_bytes(rows.tobytes())
        # repr: the shortest text that reads back to the same float, so confidence ties and order survive.
        lines.append(f"{relative} {int(preds.nyu40_ids[k])} {float(preds.confidences[k])!r}")
    txt_path = out_dir / f"{scene_name}.txt"
    txt_path.write_text("".join(line + "\n" for line in lines))
    return txt_path


def read_benchmark_predictions(txt_path: str | Path, num_vertices: int | None = None) -> InstancePredictions:
    """Reads a `<scene>.txt` prediction file and its mask files.

    Args:
      txt_path: the scene's prediction list; mask paths are relative to its folder and must stay inside it
        (no absolute path, no `..` out of it; they must be regular files).
      num_vertices: expected mask length (the mesh's vertex count); None: all masks must agree.

    Raises:
      DataError: naming the file and line of a malformed entry, a missing mask file, a mask whose length is
        not `num_vertices` or whose values are not 0/1, or a mask file listed twice. A line whose mask equals an
        earlier line's, under another class, is an alternative class hypothesis, and one whose mask is the union of
        two earlier lines' masks of its class a union hypothesis (both `InstancePredictions.alternative`).
    """
    txt_path = Path(txt_path)
    try:
        text = txt_path.read_text()
    except FileNotFoundError:
        raise DataError(f"{txt_path}: prediction file not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{txt_path}: cannot read the prediction file ({error})") from error
    masks: list[np.ndarray] = []
    ids: list[int] = []
    confidences: list[float] = []
    alternative: list[bool] = []
    union: list[bool] = []  # the lines read as union hypotheses
    seen: dict[Path, int] = {}  # mask file -> line
    first_class_of: dict[bytes, int] = {}  # a mask's vertices -> the class of its first line
    resolved_folder = txt_path.parent.resolve()
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        where = f"{txt_path}:{number}"
        fields = line.split()
        if len(fields) != 3:
            raise DataError(f"{where}: expected 'MASK_PATH NYU40_ID CONFIDENCE', got {line.strip()!r}")
        relative, id_text, confidence_text = fields
        try:
            nyu40 = int(id_text)
        except ValueError:
            raise DataError(f"{where}: nyu40 id {id_text!r} is not an integer") from None
        try:
            confidence = float(confidence_text)
        except ValueError:
            raise DataError(f"{where}: confidence {confidence_text!r} is not a number") from None
        if not math.isfinite(confidence):
            raise DataError(f"{where}: confidence {confidence_text!r} is not finite")
        mask_path = _mask_path_inside(txt_path.parent, resolved_folder, relative, where)
        if mask_path in seen:  # the official script would keep the last of its lines only
            raise DataError(f"{where}: mask {relative} is already listed on line {seen[mask_path]}")
        seen[mask_path] = number
        mask = read_mask_file(
            mask_path, where, max_bytes=_MAX_MASK_BYTES if num_vertices is None else _MASK_BYTES_PER_VERTEX * num_vertices + 64
        )
        # the same vertices as an earlier line under another class: an alternative class hypothesis of its instance
        key = np.packbits(mask).tobytes() + mask.shape[0].to_bytes(8, "little")
        another_class = bool(mask.any()) and first_class_of.setdefault(key, nyu40) != nyu40
        union.append(not another_class and _is_union_of_two(mask, nyu40, masks, ids, union))
        alternative.append(another_class or union[-1])
        if num_vertices is None:
            num_vertices = mask.shape[0]
        if mask.shape[0] != num_vertices:
            raise DataError(
                f"{mask_path} (listed at {where}): {mask.shape[0]} lines but the mesh has {num_vertices} "
                "vertices: was it predicted on another mesh?"
            )
        masks.append(mask)
        ids.append(nyu40)
        confidences.append(confidence)
    unscored = sorted({nyu40 for nyu40 in ids if nyu40 not in BENCHMARK_NYU40_IDS})
    if unscored:
        logger.warning(
            "%s: %d predictions have nyu40 ids outside the %d benchmark classes (%s): they are not scored",
            txt_path,
            sum(nyu40 in unscored for nyu40 in ids),
            len(BENCHMARK_NYU40_IDS),
            ", ".join(map(str, unscored[:5])) + (" ..." if len(unscored) > 5 else ""),
        )
    if not masks:
        return InstancePredictions.empty(num_vertices or 0)
    return InstancePredictions(
        np.stack(masks), np.asarray(ids, np.int64), np.asarray(confidences, np.float64), np.asarray(alternative, bool)
    )


def _mask_path_inside(folder: Path, resolved_folder: Path, relative: str, where: str) -> Path:
    """`folder / relative`, refused (`DataError`) when it is absolute or leads out of `folder` (`resolved_folder`
    is `folder.resolve()`, resolved once per prediction file)."""
    if Path(relative).is_absolute():
        raise DataError(f"{where}: mask path {relative!r} is absolute; paths are relative to the prediction file")
    path = folder / relative
    try:
        inside = path.resolve().is_relative_to(resolved_folder)
    except (OSError, RuntimeError):  # a symlink loop
        inside = False
    if not inside:
        raise DataError(f"{where}: mask path {relative!r} leads out of {folder}")
    return path


def _is_union_of_two(mask: np.ndarray, nyu40: int, masks: list[np.ndarray], ids: list[int], union: list[bool]) -> bool:
    """Whether `mask` is the union of two earlier lines' masks of its class `nyu40` (instances or class hypotheses,
    not unions themselves), each a non-empty part of it: a union hypothesis (`io.map_outputs.union_hypotheses`)."""
    parts = [
        m
        for m, i, joined in zip(masks, ids, union)
        if i == nyu40 and not joined and len(m) == len(mask) and m.any() and not np.array_equal(m, mask) and not (m & ~mask).any()
    ]
    return any(np.array_equal(a | b, mask) for k, a in enumerate(parts) for b in parts[k + 1 :])


def read_mask_file(path: Path, listed_at: str = "", max_bytes: int = _MAX_MASK_BYTES) -> np.ndarray:
    """`(V,)` bool from a file of one `0`/`1` per line; a `DataError` for a file that is not a regular
    file, is larger than `max_bytes`, or holds anything but 0/1 lines (its content is never printed)."""
    where = f" (listed at {listed_at})" if listed_at else ""
    if path.exists() and not path.is_file():
        raise DataError(f"{path}{where}: not a regular file")
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise DataError(f"{path}{where}: mask file not found") from None
    if size > max_bytes:
        raise DataError(f"{path}{where}: {size} bytes, more than a mask of this mesh can have ({max_bytes})")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DataError(f"{path}{where}: mask file not found") from None
    except OSError as error:
        raise DataError(f"{path}{where}: cannot read the mask ({error})") from error
    # Fast path for the usual layout, b"0\n1\n...": every other byte a digit, the others newlines.
    raw = np.frombuffer(data, np.uint8)
    if raw.size % 2 == 0 and np.all(raw[1::2] == ord("\n")):
        digits = raw[0::2]
        if np.all((digits == ord("0")) | (digits == ord("1"))):
            return digits == ord("1")
    lines = data.decode("ascii", "replace").splitlines()
    values = np.zeros(len(lines), bool)
    for number, line in enumerate(lines, 1):
        value = line.strip()
        if value not in ("0", "1"):
            raise DataError(f"{path}:{number}{where}: not a mask value (each line must be 0 or 1)")
        values[number - 1] = value == "1"
    return values


def export_ground_truth_as_predictions(gt: "SceneGroundTruth | np.ndarray") -> InstancePredictions:
    """Each ground-truth instance of a benchmark class as a prediction of confidence 1.

    Args:
      gt: a `SceneGroundTruth`, or `(V,)` int benchmark ids (`nyu40 * 1000 + instance`).

    Returns:
      predictions in increasing benchmark-id order; small instances are included (the evaluator skips
      predictions under its minimum size, as it skips such ground truth).
    """
    ids = np.asarray(gt.benchmark_ids() if hasattr(gt, "benchmark_ids") else gt, np.int64)
    instance_ids = np.unique(ids)
    instance_ids = instance_ids[np.isin(instance_ids // 1000, BENCHMARK_NYU40_IDS)]
    masks = ids[None, :] == instance_ids[:, None]
    return InstancePredictions(masks, instance_ids // 1000, np.ones(len(instance_ids)))
