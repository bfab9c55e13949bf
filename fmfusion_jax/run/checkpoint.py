"""A resumable run's checkpoint: the map and the position reached, written between frames."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from fmfusion_jax.errors import UserError
from fmfusion_jax.io.atomic import write_atomic
from fmfusion_jax.io.scene import Scene
from fmfusion_jax.run.outputs import capacity_used as capacity_used  # re-exported: experiments, likelihood, examples
from fmfusion_jax.run.outputs import score_instances as score_instances

log = logging.getLogger(__name__)


class Checkpoint:
    """A resumable run's state in `folder`: `checkpoint.npz` (the map, `Mapper.save`) and `checkpoint.json`
    (the scene position reached, the frames skipped and the config, to refuse a resume that differs)."""

    MAP_FILE = "checkpoint.npz"
    INFO_FILE = "checkpoint.json"

    def __init__(self, folder: Path, every: int = 0):
        """`every`: write one every this many frames (0: only when the run is interrupted)."""
        self.folder = Path(folder)
        self.every = int(every)

    def exists(self) -> bool:
        return (self.folder / self.INFO_FILE).is_file() and (self.folder / self.MAP_FILE).is_file()

    def info(self) -> dict[str, Any]:
        try:
            return json.loads((self.folder / self.INFO_FILE).read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise UserError(f"{self.folder / self.INFO_FILE}: unreadable checkpoint ({error})") from None

    def save(self, mapper, scene: Scene, position: int, skipped: list[tuple[str, str]]) -> None:
        """Writes the map, then the info that names it (each atomically: a crash leaves the previous pair)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        mapper.save(self.folder / self.MAP_FILE)
        info = {
            "scene": str(scene.path),
            "frames": len(scene),
            "position": position,
            "frames_integrated": mapper.frames_integrated,
            "skipped": [list(item) for item in skipped],
            "config": mapper.config.to_dict(),
        }
        write_atomic(self.folder / self.INFO_FILE, json.dumps(info, indent=1))

    def remove(self) -> None:
        for name in (self.MAP_FILE, self.INFO_FILE):
            (self.folder / name).unlink(missing_ok=True)
