"""`fmfusion eval`: benchmark-format predictions scored against ScanNet ground truth (AP, AP50, AP25), with the
error analysis (`--explain`), the detector's reach (`--detections`) and the ground truth written as
predictions (`--export-gt`)."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

from fmfusion_jax.errors import UserError
from fmfusion_jax.evaluation.explain import explain_scene
from fmfusion_jax.evaluation.explain_report import write_explanation
from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
from fmfusion_jax.io.benchmark_format import (
    export_ground_truth_as_predictions,
    read_benchmark_predictions,
    write_benchmark_predictions,
)
from fmfusion_jax.io.ground_truth import load_benchmark_gt_txt, load_scannet_ground_truth
from fmfusion_jax.likelihood.reach import detector_reach

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class _GroundTruthSource:
    scene: str
    path: Path
    kind: str  # "scene" (a ScanNet scene folder) or "txt" (benchmark ids per vertex)
    explicit: bool  # named on the command line rather than found in a folder


def run_eval(
    predictions: list[Path],
    ground_truth: list[Path],
    labels_tsv: Path | None = None,
    json_path: Path | None = None,
    explain_dir: Path | None = None,
    detections: Path | None = None,
    export_gt: Path | None = None,
    progress: bool = True,
) -> int:
    """`fmfusion eval`: scores `predictions` (files or folders) against `ground_truth` and prints the table;
    with `export_gt`, writes the ground truth as predictions instead. Returns the exit status. `progress`: a
    progress bar while the detector's reach is measured (`detections`), the one long step."""
    if not ground_truth:
        raise UserError("no ground truth: pass --gt with a ScanNet scene folder, a benchmark gt .txt, or a folder of them")
    sources = _find_ground_truth(ground_truth)
    if export_gt is not None:
        if predictions:
            raise UserError("--export-gt writes ground truth as predictions; do not pass predictions with it")
        if explain_dir is not None:
            raise UserError("--explain explains predictions; it does not go with --export-gt")
        return _export_ground_truth(sources, export_gt, labels_tsv)
    if not predictions:
        raise UserError(
            "nothing to evaluate: pass prediction <scene>.txt files or folders (PRED), "
            "or --export-gt OUT_DIR to write the ground truth as predictions"
        )
    pairs = _pair(_find_predictions(predictions), sources)
    if detections is not None and (len(pairs) != 1 or pairs[0][1].kind != "scene"):
        raise UserError("--detections needs exactly one scene, given as its scene folder (--gt SCENE)")
    return _evaluate(pairs, labels_tsv, json_path, explain_dir, detections, progress)


def _evaluate(
    pairs: list[tuple[Path, _GroundTruthSource]],
    labels_tsv: Path | None,
    json_path: Path | None,
    explain_dir: Path | None = None,
    detections: Path | None = None,
    progress: bool = True,
) -> int:

    scenes, names, meshes = [], [], []
    for pred_path, source in pairs:
        if explain_dir is not None:
            gt_ids, mesh = _load_ground_truth_with_mesh(source, labels_tsv)
            meshes.append(mesh)
        else:
            gt_ids = _load_ground_truth_ids(source, labels_tsv)
        preds = read_benchmark_predictions(pred_path, num_vertices=len(gt_ids))
        log.info(
            "%s: %d predictions (%d instances) vs ground truth %s",
            pred_path,
            preds.num_predictions,
            preds.num_instances,
            source.path,
        )
        scenes.append((gt_ids, preds))
        names.append(pred_path.stem)
    result = evaluate_scenes(scenes, scene_names=names)
    print(f"ScanNet instance benchmark, {len(names)} scene(s): {', '.join(names)}")
    print(result.to_table())
    if json_path is not None:
        summary = result.to_json_dict()
        summary["predictions"] = {p.stem: str(p) for p, _ in pairs}
        summary["ground_truth"] = {p.stem: str(s.path) for p, s in pairs}
        try:
            json_path.parent.mkdir(parents=True, exist_ok=True)
            json_path.write_text(json.dumps(summary, indent=2) + "\n")
        except OSError as error:
            raise UserError(f"cannot write {json_path}: {error}") from error
        print(f"wrote {json_path}")
    found = _explain(scenes, names, meshes, explain_dir) if explain_dir is not None else None
    if detections is not None:
        _reach(pairs[0][1].path, detections, found, explain_dir, progress)
    return 0


def _reach(scene_dir: Path, detections: Path, found: dict[int, bool] | None, out_dir: Path | None, progress: bool = True) -> None:
    """The detector's reach (`likelihood.reach`) printed, and written beside the error analysis."""

    reach = detector_reach(scene_dir, detections, progress=progress)
    text = reach.markdown(found)
    print(text)
    if out_dir is not None:
        record = reach.to_json() | ({"found": {str(k): v for k, v in found.items()}} if found is not None else {})
        try:
            (out_dir / "reach.md").write_text(text)
            (out_dir / "reach.json").write_text(json.dumps(record, indent=1) + "\n")
        except OSError as error:
            raise UserError(f"cannot write the detector reach into {out_dir}: {error}") from error
        print(f"wrote {out_dir / 'reach.md'}, {out_dir / 'reach.json'}")


def _explain(scenes: list, names: list[str], meshes: list, explain_dir: Path) -> dict[int, bool]:
    """The error analysis of each scene (`evaluation.explain`): files in `explain_dir` (one scene) or
    `explain_dir/<scene>/`, and its counts printed. Returns whether each object (benchmark id) was found."""

    print("error analysis (objects by status | predictions by kind; docs/error-analysis.md):")
    found: dict[int, bool] = {}
    for (gt_ids, preds), name, mesh in zip(scenes, names, meshes):
        vertices, faces = mesh if mesh is not None else (None, None)
        explanation = explain_scene(gt_ids, preds, vertices, scene_name=name)
        found |= {g.gt_id: g.status == "found" for g in explanation.ground_truth}
        out_dir = explain_dir if len(scenes) == 1 else explain_dir / name
        try:
            written = write_explanation(out_dir, explanation, gt_ids, preds, vertices, faces)
        except OSError as error:
            raise UserError(f"cannot write the error analysis into {out_dir}: {error}") from error
        print(f"  {name}: {explanation.summary_line()}")
        note = "" if mesh is not None else " (no explain.png: the ground truth has no mesh; pass its scene folder)"
        print(f"  wrote {', '.join(str(p) for p in written)}{note}")
    return found


def _export_ground_truth(sources: list[_GroundTruthSource], out_dir: Path, labels_tsv: Path | None) -> int:

    for source in sources:
        preds = export_ground_truth_as_predictions(_load_ground_truth_ids(source, labels_tsv))
        try:
            txt = write_benchmark_predictions(out_dir, source.scene, preds)
        except OSError as error:
            raise UserError(f"cannot write into {out_dir}: {error}") from error
        print(f"wrote {txt} ({preds.num_instances} ground-truth instances of benchmark classes)")
    gt_args = " ".join(str(s.path) for s in sources)
    print(f"check with: fmfusion eval {out_dir} --gt {gt_args}")
    return 0


def _load_ground_truth_with_mesh(source: _GroundTruthSource, labels_tsv: Path | None):
    """`(gt_ids, (vertices, faces))` of a scene folder; `(gt_ids, None)` of a benchmark gt .txt."""

    if source.kind == "txt":
        return _load_ground_truth_ids(source, labels_tsv), None
    gt = load_scannet_ground_truth(source.path, labels_tsv)
    return gt.benchmark_ids(), (gt.vertices, gt.faces)


def _load_ground_truth_ids(source: _GroundTruthSource, labels_tsv: Path | None):

    if source.kind == "txt":
        return load_benchmark_gt_txt(source.path)
    return load_scannet_ground_truth(source.path, labels_tsv).benchmark_ids()


def _is_scene_folder(path: Path) -> bool:
    return (path / f"{path.name}_vh_clean_2.ply").is_file()


def _find_ground_truth(paths: list[Path]) -> list[_GroundTruthSource]:
    """Ground-truth sources by scene name: explicit scene folders / gt txts, or those found in folders."""
    sources: dict[str, _GroundTruthSource] = {}

    def add(source: _GroundTruthSource) -> None:
        other = sources.get(source.scene)
        if other is not None and other.path != source.path:
            raise UserError(f"two ground truths for scene {source.scene}: {other.path} and {source.path}; pass one")
        sources[source.scene] = source

    for path in paths:
        if path.is_file():
            if path.suffix != ".txt":
                raise UserError(f"--gt {path}: a file must be a benchmark ground-truth <scene>.txt")
            add(_GroundTruthSource(path.stem, path, "txt", True))
        elif path.is_dir() and _is_scene_folder(path):
            add(_GroundTruthSource(path.name, path, "scene", True))
        elif path.is_dir():
            found = [
                _GroundTruthSource(p.name, p, "scene", False)
                for p in sorted(path.iterdir())
                if p.is_dir() and _is_scene_folder(p)
            ]
            found += [_GroundTruthSource(p.stem, p, "txt", False) for p in sorted(path.glob("*.txt"))]
            if not found:
                raise UserError(
                    f"--gt {path}: no ScanNet scene folder (<scene>/<scene>_vh_clean_2.ply) or ground-truth <scene>.txt in it"
                )
            for source in found:
                add(source)
        else:
            raise UserError(f"--gt {path}: no such file or folder")
    return list(sources.values())


def _find_predictions(paths: list[Path]) -> list[Path]:
    """Prediction `<scene>.txt` files: the files given and the `*.txt` directly inside the folders given."""
    files: dict[str, Path] = {}
    for path in paths:
        if path.is_dir():
            found = sorted(path.glob("*.txt"))
            if not found:
                raise UserError(f"{path}: no prediction <scene>.txt in this folder")
        elif path.is_file():
            found = [path]
        else:
            raise UserError(f"{path}: no such prediction file or folder")
        for file in found:
            if file.stem in files and files[file.stem].resolve() != file.resolve():
                raise UserError(f"two predictions for scene {file.stem}: {files[file.stem]} and {file}; pass one")
            files[file.stem] = file
    return list(files.values())


def _pair(predictions: list[Path], sources: list[_GroundTruthSource]) -> list[tuple[Path, _GroundTruthSource]]:
    """Pairs predictions with ground truth by scene name (a lone pair of explicit paths is paired as given)."""
    if len(predictions) == 1 and len(sources) == 1 and sources[0].explicit:
        if predictions[0].stem != sources[0].scene:
            log.warning("pairing %s with ground truth of %s (names differ)", predictions[0], sources[0].scene)
        return [(predictions[0], sources[0])]
    by_scene = {s.scene: s for s in sources}
    missing = [p.stem for p in predictions if p.stem not in by_scene]
    if missing:
        raise UserError(
            f"no ground truth for scene(s) {', '.join(missing)}: pass their scene folders or gt .txt "
            "files with --gt (prediction files are named <scene>.txt)"
        )
    predicted = {p.stem for p in predictions}
    unpredicted = [s.scene for s in sources if s.explicit and s.scene not in predicted]
    if unpredicted:
        raise UserError(f"no predictions for scene(s) {', '.join(unpredicted)}: pass their <scene>.txt files")
    return [(p, by_scene[p.stem]) for p in predictions]
