"""Pictures of simulated detections: ground-truth instances beside the simulated masks and labels.

Two sources:

  # a real ScanNet scene (the picture is derived from ScanNet: it goes to outputs/, never into the repo)
  python examples/show_simulated_detections.py --scene ../shared/data/scannet/scene0000_00 \
      --frames 0 100 200 --out outputs/simulated-detections.png

  # a synthetic room drawn here (no dataset involved): the picture in docs/img/
  python examples/show_simulated_detections.py --synthetic --out docs/img/simulated-detections.png

Each row is one frame: the ground-truth instances of the closed classes (left), then the simulated
detections (right): one colour per detection, its border, and its main label with score.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.simulate import simulate_frame
from fmfusion_jax.types import FrameDetections

PALETTE = np.array(
    [
        (230, 25, 75),
        (60, 180, 75),
        (255, 225, 25),
        (0, 130, 200),
        (245, 130, 48),
        (145, 30, 180),
        (70, 240, 240),
        (240, 50, 230),
        (210, 245, 60),
        (250, 190, 212),
        (0, 128, 128),
        (220, 190, 255),
        (170, 110, 40),
        (255, 250, 200),
        (128, 0, 0),
        (170, 255, 195),
        (128, 128, 0),
        (255, 215, 180),
    ],
    np.uint8,
)


def _label_anchor(mask: np.ndarray) -> tuple[int, int]:
    """The mask pixel farthest from its border (a good place for its label), as (u, v)."""
    padded = np.pad(mask.astype(np.uint8), 1)  # the image border counts as the mask's border
    distance = cv2.distanceTransform(padded, cv2.DIST_L2, 3)[1:-1, 1:-1]
    v, u = np.unravel_index(int(np.argmax(distance)), distance.shape)
    return int(u), int(v)


def _put_label(image: np.ndarray, text: str, anchor: tuple[int, int]) -> None:
    font, scale, thickness = cv2.FONT_HERSHEY_SIMPLEX, 0.42, 1
    (w, h), base = cv2.getTextSize(text, font, scale, thickness)
    u = int(np.clip(anchor[0] - w // 2, 0, image.shape[1] - w - 1))
    v = int(np.clip(anchor[1] + h // 2, h + 2, image.shape[0] - base - 1))
    cv2.rectangle(image, (u - 2, v - h - 2), (u + w + 2, v + base), (0, 0, 0), -1)
    cv2.putText(image, text, (u, v), font, scale, (255, 255, 255), thickness, cv2.LINE_AA)


def draw_masks(color: np.ndarray, masks: np.ndarray, texts: list[str], alpha: float = 0.5) -> np.ndarray:
    """`color` (H, W, 3) RGB with each mask blended in its own colour, outlined and captioned."""
    out = color.astype(np.float32).copy()
    for k, mask in enumerate(masks):
        out[mask] = (1 - alpha) * out[mask] + alpha * PALETTE[k % len(PALETTE)]
    out = out.clip(0, 255).astype(np.uint8)
    for k, mask in enumerate(masks):
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, tuple(int(c) for c in PALETTE[k % len(PALETTE)]), 2)
    for mask, text in zip(masks, texts):
        if mask.any():
            _put_label(out, text, _label_anchor(mask))
    return out


def draw_ground_truth(color: np.ndarray, gt_image: np.ndarray, instance_classes: dict[int, int]) -> np.ndarray:
    label_sets = load_label_sets()
    ids = [i for i in np.unique(gt_image) if i in instance_classes and (gt_image == i).sum() >= 100]
    masks = np.stack([gt_image == i for i in ids]) if ids else np.zeros((0, *gt_image.shape), bool)
    return draw_masks(color, masks, [label_sets.class_names[instance_classes[i]] for i in ids])


def draw_detections(color: np.ndarray, detections: FrameDetections) -> np.ndarray:
    texts = [f"{name} {score:.2f}" for labels in detections.labels for name, score in [next(iter(labels.items()))]]
    return draw_masks(color, detections.masks, texts)


def _caption(image: np.ndarray, text: str) -> np.ndarray:
    bar = np.full((24, image.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar, image])


def synthetic_room(frame: int) -> tuple[np.ndarray, np.ndarray, dict[int, int]]:
    """A drawn 640x480 bedroom seen from a slowly panning camera: colour, instance ids, instance classes."""
    label_sets = load_label_sets()
    c = label_sets.class_index
    shift = 12 * frame
    ids = np.zeros((480, 640), np.int32)
    classes = {
        1: c("wall"),
        2: c("wall"),
        3: c("floor"),
        4: c("bed"),
        5: c("cabinet"),
        6: c("picture"),
        7: c("door"),
        8: c("window"),
        9: c("curtain"),
        10: c("table"),
        11: c("chair"),
        12: c("chair"),
    }
    polys = [
        (1, [(0, 0), (420, 0), (420, 300), (0, 330)]),  # back wall
        (2, [(420, 0), (640, 0), (640, 400), (420, 300)]),  # right wall
        (3, [(0, 330), (420, 300), (640, 400), (640, 480), (0, 480)]),  # floor
        (7, [(450, 60), (540, 80), (540, 350), (450, 310)]),  # door in the right wall
        (8, [(40, 50), (190, 50), (190, 180), (40, 180)]),  # window
        (9, [(20, 40), (60, 40), (60, 250), (20, 250)]),  # curtain left of the window
        (9, [(180, 40), (215, 40), (215, 250), (180, 250)]),
        (6, [(260, 70), (360, 70), (360, 140), (260, 140)]),  # picture
        (4, [(60, 260), (330, 250), (400, 330), (90, 380)]),  # bed
        (13, [(120, 215), (200, 213), (205, 262), (118, 265)]),  # pillow (not a target class)
        (5, [(340, 200), (410, 200), (410, 300), (340, 300)]),  # cabinet
        (10, [(450, 360), (620, 350), (640, 410), (470, 425)]),  # table
        (11, [(500, 300), (560, 300), (565, 440), (505, 445)]),  # chair behind the table
        (12, [(560, 380), (620, 385), (615, 478), (555, 478)]),  # chair in front
    ]
    for instance, points in polys:
        cv2.fillPoly(ids, [np.array([(u - shift, v) for u, v in points], np.int32)], int(instance))
    color = np.zeros((480, 640, 3), np.uint8)
    rng = np.random.default_rng(7)
    base = {i: rng.integers(60, 220, 3) for i in range(14)}
    for instance, value in base.items():
        color[ids == instance] = value
    shade = np.linspace(0.8, 1.1, 640)[None, :, None] * np.linspace(1.05, 0.85, 480)[:, None, None]
    color = (color * shade).clip(0, 255).astype(np.uint8)
    return color, ids, classes


def real_frames(scene_path: str, frames: list[int]):
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.simulation.render import GroundTruthRenderer, instance_classes

    scene = open_scene(scene_path)
    gt = load_scannet_ground_truth(scene.path)
    renderer = GroundTruthRenderer.from_ground_truth(gt)
    classes = instance_classes(gt)
    for i in frames:
        frame = scene.read_frame(i)
        yield frame.index, frame.name, frame.color, renderer.render(frame.depth, frame.T_world_camera, frame.intrinsics), classes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", help="a ScanNet scene folder (picture derived from ScanNet: keep it out of the repo)")
    source.add_argument("--synthetic", action="store_true", help="a drawn room, no dataset")
    parser.add_argument("--frames", type=int, nargs="+", default=[0, 100, 200], help="frames to show (real scene)")
    parser.add_argument("--preset", default="default", choices=("clean", "default", "hard"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="PNG to write")
    args = parser.parse_args(argv)

    noise = NoiseModel.preset(args.preset, seed=args.seed)
    if args.synthetic:
        rows = []
        for frame in (0, 1, 2):
            color, ids, classes = synthetic_room(frame * 4)
            rows.append((frame, f"frame-{frame:06d}", color, ids, classes))
    else:
        rows = real_frames(args.scene, args.frames)
    recent: list[set[str]] = []
    panels = []
    for index, name, color, gt_image, classes in rows:
        detections = simulate_frame(
            gt_image, classes, name, index, noise, recent_labels=set().union(*recent[-noise.augmentation_window :])
        )
        recent.append({label for labels in detections.labels for label in labels})
        left = _caption(draw_ground_truth(color, gt_image, classes), f"{name}: ground-truth instances")
        right = _caption(
            draw_detections(color, detections),
            f"simulated ({args.preset}, seed {args.seed}): {detections.num_detections} detections",
        )
        panels.append(np.concatenate([left, np.full((left.shape[0], 8, 3), 255, np.uint8), right], axis=1))
    picture = np.concatenate([np.concatenate([p, np.full((8, p.shape[1], 3), 255, np.uint8)]) for p in panels])
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    picture = cv2.resize(picture, (picture.shape[1] * 3 // 4, picture.shape[0] * 3 // 4), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(out), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
