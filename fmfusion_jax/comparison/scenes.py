"""The scenes of a comparison: real ScanNet scenes read in place and generated rooms, each prepared once
(generated, its detections simulated and cached) for every method."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fmfusion_jax.config import PipelineConfig, detection_frame_stride, load_config
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.scene import open_dataset_scene
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.procedural import generate_scene
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, PreparedScene, prepare_generated, prepare_real

if TYPE_CHECKING:
    from fmfusion_jax.io.ground_truth import SceneGroundTruth
    from fmfusion_jax.io.scene import Scene


log = logging.getLogger(__name__)

#: Detection variants: the default simulation, and the one without prompt augmentation (ablation B).
DETECTIONS_DEFAULT, DETECTIONS_NO_AUGMENTATION = "default", "noaug"


#: Config of real scenes: the default a user gets without --config (its detection schedule finds that a scene
#: like ../shared/data/scannet/scene0000_00 is subsampled in time and fuses every frame).
REAL_SCENE_CONFIG = "scannet"


@dataclasses.dataclass(frozen=True)
class SceneSource:
    """One scene of the experiment: a real folder, or a generated room.

    Attributes:
      name: the scene's name (folder name).
      kind: "real" or "generated".
      path: the real scene's folder (None for a generated one until prepared).
      spec: the generated scene's parameters.
    """

    name: str
    kind: str
    path: Path | None = None
    spec: GeneratedSceneSpec | None = None

    def config(self, overrides: Sequence[str] = (), max_frames: int | None = None) -> PipelineConfig:
        """The scene's config with `overrides` (`--set`, then a method's)."""
        if self.kind == "real":
            extra = [f"dataset.max_frames={max_frames}"] if max_frames else []
            return load_config(REAL_SCENE_CONFIG, extra + list(overrides))

        spec = self.spec
        assert spec is not None  # a generated scene has its spec
        room = generate_scene(spec.seed, num_objects=spec.num_objects).room_size  # no rendering: cheap
        return demo_config(spec.num_frames, spec.width, spec.height, overrides, room_size=room)

    def noise(self, seed: int):
        """The default noise model of this scene's detections (pixel counts scaled to generated images)."""

        if self.kind == "real":
            return NoiseModel.preset("default").replace(seed=int(seed))
        assert self.spec is not None  # a generated scene has its spec
        return demo_noise(seed, self.spec.width, self.spec.height)


def scene_sources(real_scenes: Sequence[str | Path], generated: Sequence[GeneratedSceneSpec]) -> list[SceneSource]:
    """The scenes, real first; a missing real folder, one without ground truth, or a repeated name is a
    UserError."""
    sources = []
    for path in real_scenes:
        path = Path(path)
        if not path.is_dir():
            raise UserError(f"scene folder {path} not found")
        if not (path / f"{path.name}_vh_clean_2.ply").is_file():
            raise UserError(
                f"{path} has no ground-truth mesh {path.name}_vh_clean_2.ply: the experiment scores "
                "every run against the scene's ground truth"
            )
        sources.append(SceneSource(path.name, "real", path=path))
    sources += [SceneSource(spec.name, "generated", spec=spec) for spec in generated]
    names = [s.name for s in sources]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise UserError(f"scene {', '.join(repeated)} given twice")
    if not sources:
        raise UserError("no scenes: name real scenes with --scenes or ask for generated ones with --generated N")
    return sources


@dataclasses.dataclass
class PreparedSource:
    """A scene ready to run: its detection folders per variant, the opened scene and its ground truth.

    Attributes:
      source: the scene.
      detections: variant -> `scene_sets.PreparedScene` (scene folder and detections folder).
      noise: variant -> the noise model's parameters.
      scene: the opened scene (`io.scene.Scene`) with the scene's dataset settings.
      gt: its `SceneGroundTruth`.
      seconds: wall time of the preparation.
    """

    source: SceneSource
    detections: dict[str, PreparedScene]
    noise: dict[str, dict[str, Any]]
    scene: Scene
    gt: SceneGroundTruth
    seconds: float

    def record(self) -> dict:
        """The scene's entry in experiment.json."""
        source, spec = self.source, self.source.spec
        return {
            "name": source.name,
            "kind": source.kind,
            "scene_dir": str(self.scene.path),
            "frames": len(self.scene),
            "gt_vertices": int(self.gt.num_vertices),
            "spec": dataclasses.asdict(spec) if spec else None,
            "config": REAL_SCENE_CONFIG if source.kind == "real" else "demo (scaled to the scene)",
            "detections": {v: str(p.detections_dir) for v, p in self.detections.items()},
            "noise": self.noise,
        }


def prepare_source(
    source: SceneSource,
    variants: Sequence[str],
    cache_dir: Path,
    seed: int,
    base_config: PipelineConfig,
    progress: bool,
    report: Callable[[str], None],
    given: Path | None = None,
) -> PreparedSource:
    """Makes (or finds in `cache_dir`) the scene and its simulated detections of each variant, on the
    detection frames of `base_config`, then opens the scene and reads its ground truth. `given`: a folder of
    (real) detections every variant reads instead."""

    start = time.perf_counter()
    every = detection_frame_stride(base_config) * base_config.dataset.frame_stride
    default_noise = source.noise(seed)
    detections, noise = {}, {}
    for variant in variants:
        variant_noise = default_noise if variant == DETECTIONS_DEFAULT else default_noise.replace(prompt_augmentation=False)
        report(
            f"preparing {source.name}: {'scene and ' if source.kind == 'generated' else ''}{variant} detections "
            f"(cached in {cache_dir})"
        )
        if given is not None:
            assert source.path is not None  # detections are given for real scenes only
            detections[variant] = PreparedScene(source.name, source.path, given)
            noise[variant] = {"detections": str(given), "simulated": False}
            continue
        if source.kind == "real":
            assert source.path is not None  # a real scene has its folder
            detections[variant] = prepare_real(source.path, cache_dir, variant_noise, every, variant, progress)
        else:
            assert source.spec is not None  # a generated scene has its spec
            detections[variant] = prepare_generated(source.spec, cache_dir, variant_noise, every, variant, progress)
        noise[variant] = variant_noise.to_dict()
    scene_dir = next(iter(detections.values())).scene_dir
    dataset = base_config.dataset
    scene = open_dataset_scene(scene_dir, dataset)
    gt = load_scannet_ground_truth(scene_dir)
    return PreparedSource(source, detections, noise, scene, gt, round(time.perf_counter() - start, 2))


def given_detections(source: SceneSource, pattern: str | None) -> Path | None:
    """The detection folder `pattern` names for a real scene (`{scene}`: its name), checked; None otherwise."""
    if pattern is None or source.kind != "real":
        return None
    folder = Path(pattern.replace("{scene}", source.name))
    if not folder.is_dir():
        raise UserError(f"--detections {pattern}: no folder {folder} for scene {source.name}")
    return folder
