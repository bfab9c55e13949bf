"""`fmfusion detect SCENE --models DIR --out DIR`: run the detection models on a scene's frames, into files."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options
from fmfusion_jax.errors import UserError

#: What `fmfusion detect` records in its output folder: the run's settings, so that a rerun continues (skipping
#: the frames done) only when it would make the same detections.
RECORD_FILE = "detect.json"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "detect",
        help="make detection files with the detection models (ONNX)",
        description="Runs a models folder's front end (a COCO detector + SAM + classifier, or RAM -> GroundingDINO "
        "-> SAM; see docs/detectors.md) on the frames of a scene that `fmfusion run` fuses (with the same "
        "--config and --set: by default the frames the camera-motion schedule picks; all of them on a sequence "
        "already subsampled in time) and writes one detection pair per frame (<frame>_label.json + "
        "<frame>_mask.png/.npy, the authors' format) for `fmfusion run --detections`. Rerun with the same "
        "arguments, it continues where it stopped (frames already written are kept).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("scene", type=Path, help="scene folder (ScanNet or SceneNN layout)")
    parser.add_argument(
        "--models",
        type=Path,
        required=True,
        metavar="DIR",
        help="models folder: a models.yaml naming each model's file, the shared layout (detector/, sam/, classifier/) "
        "or ram.onnx, groundingdino.onnx, sam_encoder.onnx, sam_decoder.onnx (docs/detectors.md)",
    )
    options.add_out(parser, required=True, metavar="DIR", help="detection folder to write (created)")
    options.add_layout(parser, choices=("auto", "scannet", "scenenn"), help="scene layout")
    options.add_stride(parser, metavar="N", help="read every N-th frame of the sequence")
    parser.add_argument(
        "--every",
        type=int,
        default=None,
        metavar="N",
        help="detect on every N-th frame read instead of the frames the detection schedule fuses",
    )
    options.add_max_frames(parser, help="read at most N frames")
    parser.add_argument(
        "--providers",
        default="cpu",
        choices=("cpu", "cuda", "auto"),
        help="onnxruntime execution provider (cuda falls back to cpu when unavailable)",
    )
    parser.add_argument(
        "--mask-format", default="png", choices=("png", "npy"), help="png (overlapping masks fall back to npy) or npy"
    )
    grounded = parser.add_argument_group("RAM -> GroundingDINO -> SAM folders only (the config's front_end keys)")
    grounded.add_argument(
        "--box-threshold", type=float, metavar="T", help="GroundingDINO: a box needs a token score above this (0.35)"
    )
    grounded.add_argument(
        "--text-threshold", type=float, metavar="T", help="GroundingDINO: a label needs all its token scores above this (0.25)"
    )
    grounded.add_argument(
        "--prompt-window", type=int, metavar="N", help="detection frames whose labels augment the prompt (5; 0: none)"
    )
    options.add_config(
        parser, default="scannet", help="config of the `fmfusion run` to detect for (its schedule and front_end section)"
    )
    options.add_overrides(parser, help="override a config value, e.g. --set front_end.proposals=false (repeatable)")
    options.add_no_progress(parser, help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from detectors import build_front_end, read_manifest
    from fmfusion_jax.config import load_config
    from fmfusion_jax.io.detections import label_path, write_frame_detections
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.pipeline import scheduled_positions

    if args.every is not None and args.every < 1:
        raise UserError(f"--every must be a positive integer, got {args.every}")
    flags = {"box_threshold": args.box_threshold, "text_threshold": args.text_threshold, "prompt_window": args.prompt_window}
    overrides = list(args.overrides) + [f"front_end.{key}={value}" for key, value in flags.items() if value is not None]
    config = load_config(args.config, overrides)
    scene = open_scene(args.scene, layout=args.layout, stride=args.stride, max_frames=args.max_frames)
    manifest_overrides = config.front_end.manifest_overrides()
    manifest = read_manifest(args.models, manifest_overrides)
    models = build_front_end(manifest, providers=args.providers)
    if args.every is not None:
        positions, rule = list(range(0, len(scene), args.every)), f"every {args.every} of {len(scene)} read"
    else:
        positions = scheduled_positions(scene.poses(), config)
        rule = f"the {len(positions)} of {len(scene)} frames the detection schedule fuses"
    record = {
        "scene": str(args.scene.resolve()),
        "models": str(args.models.resolve()),
        "front_end": manifest.front_end,
        "settings": {"overrides": manifest_overrides, "stride": args.stride, "mask_format": args.mask_format},
    }
    done = _frames_done(args.out, record, [scene.frame_names[p] for p in positions], label_path)
    todo = [p for p in positions if scene.frame_names[p] not in done]
    if done and manifest.front_end == "grounded_sam":
        # the prompt window needs the frames before: a continued run starts the window afresh (noted)
        print(f"continuing: {len(done)} frames already in {args.out}; the prompt window restarts at the first new frame")
    elif done:
        print(f"continuing: {len(done)} of {len(positions)} frames already in {args.out}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / RECORD_FILE).write_text(json.dumps(record, indent=1) + "\n")
    detections_total, started = 0, time.perf_counter()
    with tqdm(todo, desc=f"detect {scene.name}", unit="frame", disable=args.no_progress) as bar:
        for count, position in enumerate(bar, start=1):
            name = scene.frame_names[position]
            detections = models.detect(scene.read_color(position), name)
            write_frame_detections(args.out, detections, mask_format=args.mask_format)
            detections_total += detections.num_detections
            per_model = " ".join(f"{stage} {1000 * s / count:.0f}" for stage, s in models.timings.items())
            bar.set_postfix_str(f"{detections.num_detections} det; ms/frame {per_model}")
    elapsed = time.perf_counter() - started
    frames = max(len(todo), 1)
    stages = ", ".join(f"{stage} {1000 * seconds / frames:.0f} ms" for stage, seconds in models.timings.items())
    print(
        f"{len(todo)} frames of {scene.name} detected ({rule}, stride {args.stride}) -> "
        f"{detections_total} detections in {args.out}"
    )
    if todo:
        print(f"per frame: {1000 * elapsed / frames:.0f} ms ({stages}); providers {', '.join(models.providers)}")
    return 0


def _frames_done(out: Path, record: dict, names: list[str], label_path) -> set[str]:
    """The frames of `names` already written to `out` by a `fmfusion detect` with the same settings; a folder
    written with other settings (or not by `fmfusion detect`) is refused rather than mixed or overwritten."""
    if not out.exists():
        return set()
    if not out.is_dir():
        raise UserError(f"--out {out} exists and is not a folder")
    record_path = out / RECORD_FILE
    if not record_path.exists():
        if any(out.iterdir()):
            raise UserError(
                f"--out {out} is a folder that `fmfusion detect` did not write (no {RECORD_FILE}): choose a new folder"
            )
        return set()
    try:
        previous = json.loads(record_path.read_text())
    except (OSError, ValueError) as error:
        raise UserError(f"{record_path}: unreadable ({error}); choose a new --out folder") from None
    if previous != record:
        changed = sorted(k for k in set(previous) | set(record) if previous.get(k) != record.get(k))
        raise UserError(
            f"--out {out} holds detections made with other settings ({', '.join(changed)} differ): choose a new folder"
        )
    return {name for name in names if label_path(out, name).exists()}
