"""`fmfusion synth`'s work (the parser is `cli/synth.py`)."""

from __future__ import annotations

import time
from pathlib import Path

from fmfusion_jax.errors import UserError
from fmfusion_jax.simulation.procedural import generate_scene
from fmfusion_jax.simulation.scannet_writer import write_scannet_scene


def run_synth(
    *,
    objects: int,
    frames: int,
    size: str,
    room_text: str | None,
    out_dir: Path,
    overwrite: bool,
    seed: int,
    no_noise: bool,
    no_progress: bool,
) -> int:
    if not 1 <= objects <= 900:
        raise UserError(f"--objects {objects}: expected 1..900")
    if frames < 1:
        raise UserError(f"--frames {frames}: expected a positive number")
    width, height = parse_dimensions(size, 2, "--size")
    if width != int(width) or height != int(height) or not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise UserError(f"--size {size}: expected whole pixels within 16..4096, e.g. 640x480")
    room = parse_dimensions(room_text, 3, "--room") if room_text else None
    if room is not None and (min(room[:2]) < 2.0 or room[2] < 2.2 or max(room) > 100):
        raise UserError(f"--room {room_text}: width and depth must be at least 2 m, height at least 2.2 m")
    out = out_dir
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not overwrite)):
        raise UserError(f"{out}: exists and is not an empty folder (pass --overwrite, or choose another OUT_DIR)")

    started = time.perf_counter()
    try:
        scene = generate_scene(seed, room_size=room, num_objects=objects)
    except ValueError as error:
        raise UserError(str(error)) from None
    print(f"scene   {scene.summary()}")
    path = write_scannet_scene(
        scene,
        out,
        num_frames=frames,
        width=int(width),
        height=int(height),
        depth_noise=not no_noise,
        progress=not no_progress,
        overwrite=overwrite,
    )
    print(f"wrote   {path}  ({frames} frames {int(width)}x{int(height)}, {time.perf_counter() - started:.1f} s)")
    return 0


def parse_dimensions(text: str, count: int, what: str) -> tuple[float, ...]:
    """``"5x4x2.6"`` -> `(5.0, 4.0, 2.6)`; a `UserError` naming `what` when it is not `count` positive numbers."""
    parts = text.lower().replace("*", "x").split("x")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != count or not all(v > 0 for v in values):
        example = "5x4x2.6" if count == 3 else "640x480"
        raise UserError(f"{what} {text!r}: expected {count} positive numbers joined by 'x', e.g. {example}")
    return values
