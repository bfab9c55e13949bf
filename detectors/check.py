"""`fmfusion models check DIR`: is a models folder usable, and how fast is it here?

`check_models_folder` validates the manifest (models.yaml, or the one inferred from the files), opens each
model against its contract, checks the vocabulary table against the models' class names, then runs the
whole front end on a generated image (and on a given one) and reports the milliseconds per model. Every
problem is collected as one line (nothing is raised for a bad folder), so one run lists them all.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from detectors.manifest import CLOSED_SET_ROLES, Manifest, assemble_closed_set, build_front_end, load_role, read_manifest
from fmfusion_jax.errors import UserError


@dataclasses.dataclass
class ModelsCheck:
    """The outcome of `check_models_folder`.

    Attributes:
      folder: the models folder.
      problems: one line per problem found (empty: the folder is usable).
      lines: the report, line by line (what was checked and the timings).
      timings_ms: image name -> model (``detector``, ``sam_encoder``, ...) -> milliseconds for that image.
    """

    folder: Path
    problems: list[str] = dataclasses.field(default_factory=list)
    lines: list[str] = dataclasses.field(default_factory=list)
    timings_ms: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def report(self) -> str:
        """The report and then the problems, as printed by `fmfusion models check`."""
        if self.ok:
            return "\n".join([*self.lines, "ok: the folder is usable"])
        return "\n".join([*self.lines, f"{len(self.problems)} problem(s):", *(f"  - {p}" for p in self.problems)])


def generated_image(height: int = 480, width: int = 640) -> np.ndarray:
    """`(height, width, 3)` uint8 RGB test card: a shaded room-like background with a few solid blocks."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    image = np.stack([120 + 60 * u / width, 110 + 50 * v / height, 100 + 40 * (u + v) / (width + height)], -1)
    for (u0, v0, u1, v1), colour in (
        ((0.08, 0.45, 0.45, 0.95), (40, 50, 110)),
        ((0.55, 0.30, 0.75, 0.90), (150, 100, 60)),
        ((0.80, 0.10, 0.95, 0.60), (220, 220, 210)),
    ):
        image[int(v0 * height) : int(v1 * height), int(u0 * width) : int(u1 * width)] = colour
    return image.clip(0, 255).astype(np.uint8)


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as `(H, W, 3)` uint8 RGB; `UserError` when it cannot be read."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise UserError(f"{path}: cannot read this image")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def check_models_folder(
    models_dir: str | Path, image: str | Path | np.ndarray | None = None, providers: str | Sequence[str] = "cpu"
) -> ModelsCheck:
    """Checks a models folder (module docstring); `image`: a file or an `(H, W, 3)` uint8 RGB array to run on too."""
    result = ModelsCheck(Path(models_dir))
    try:
        manifest = read_manifest(models_dir)
    except UserError as error:
        result.problems.append(str(error))
        return result
    result.lines.append(f"models folder {manifest.folder}: front end {manifest.front_end}, manifest {manifest.where}")
    models = _load(manifest, providers, result)
    if models is None:
        return result
    images: list[tuple[str, Any]] = [("generated 640x480 image", generated_image)]
    if image is not None:
        images.append((str(image) if not isinstance(image, np.ndarray) else "the given image", image))
    for name, source in images:
        try:
            rgb = source() if callable(source) else read_rgb(source) if not isinstance(source, np.ndarray) else source
            _run(models, name, rgb, result)
        except UserError as error:
            result.problems.append(f"{name}: {error}")
        except Exception as error:  # a model that loads but fails to run: report it, do not crash the check
            result.problems.append(f"running the front end on the {name} failed: {type(error).__name__}: {error}")
    return result


def _load(manifest: Manifest, providers, result: ModelsCheck):
    """The front end, each role checked on its own (every failing role is one problem); None if any failed."""
    if manifest.front_end == "grounded_sam":
        try:
            models = build_front_end(manifest, providers)
        except UserError as error:
            result.problems.append(str(error))
            return None
        result.lines.append("  ok  RAM tagger, GroundingDINO, SAM encoder and decoder match their contracts")
        return models
    parts: dict[str, Any] = {}
    for role in CLOSED_SET_ROLES:
        try:
            parts[role] = load_role(manifest, role, providers)
        except UserError as error:
            result.problems.append(str(error))
            continue
        if parts[role] is not None:
            result.lines.append(f"  ok  {role:<10}  {_describe(role, parts[role], manifest)}")
    if len(parts) < len(CLOSED_SET_ROLES):
        return None
    vocabulary = parts["vocabulary"]
    for source, names, what in (
        ("coco", parts["detector"].labels.names, "the detector's classes"),
        ("imagenet", parts["classifier"].names if parts["classifier"] else None, "the classifier's classes"),
    ):
        if names is None:
            continue
        # A table may list names another model has (a note); one that maps none of this model's is useless.
        unknown = vocabulary.unknown_names(source, names)
        if unknown:
            result.lines.append(f"  note: {len(unknown)} {source} name(s) of the vocabulary are not {what}: {unknown[:8]}")
        if not any(vocabulary.maps(source, name) for name in names):
            result.problems.append(f"{vocabulary.path}: none of {what} maps to an open-set label (section {source})")
    try:
        return assemble_closed_set(manifest, **parts)
    except UserError as error:
        result.problems.append(f"{manifest.where}: {error}")
        return None


def _describe(role: str, part: Any, manifest: Manifest) -> str:
    folder = manifest.folder
    if role == "detector":
        settings = f"{part.kind}, score > {part.score_threshold}, {len(part.labels.names)} classes"
        return f"{part.model.path.relative_to(folder)} ({settings})"
    if role == "segmenter":
        return f"{part.encoder.path.relative_to(folder)} + {part.decoder.path.relative_to(folder)}"
    if role == "classifier":
        return f"{part.model.path.relative_to(folder)} ({len(part.names)} classes)"
    return f"{part.path} ({sum(e is not None for table in part.tables.values() for e in table.values())} names mapped)"


def _run(models, name: str, image: np.ndarray, result: ModelsCheck) -> None:
    """Runs the front end on `image` (twice on the first image: the first call warms onnxruntime up)."""
    if not result.timings_ms:
        models.detect(image, "warm-up")
    models.reset()
    start = time.perf_counter()
    detections = models.detect(image, "check")
    total = time.perf_counter() - start
    ms = {key: 1000.0 * value for key, value in models.timings.items()}
    ms["total"] = 1000.0 * total
    result.timings_ms[name] = ms
    found = ", ".join(f"{max(d, key=d.__getitem__)} {max(d.values()):.2f}" for d in detections.labels) or "nothing"
    result.lines.append(f"  {name} ({image.shape[1]}x{image.shape[0]}): {detections.num_detections} detection(s): {found}")
    result.lines.append("    ms: " + ", ".join(f"{key} {value:.0f}" for key, value in ms.items()))
