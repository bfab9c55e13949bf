"""Markdown tables and progress lines of the comparison reports."""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)


def stderr_report(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def percent(value: float | None) -> str:
    """AP as the paper prints it (%, one decimal); "-" where the class has no ground truth."""
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{100 * value:.1f}"


def fraction(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]], align_first_left: bool = True) -> str:
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join([":---" if align_first_left else "---:"] + ["---:"] * (len(header) - 1)) + "|",
    ]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def scene_kind(record: dict) -> str:
    """What a scene of a comparison is, from its record: a real ScanNet scene, or a generated room and its size."""
    if record["kind"] == "real":
        return "real ScanNet scene"
    spec = record["spec"]
    return f"generated room, seed {spec['seed']}, {spec['num_objects']} objects, {spec['width']}x{spec['height']}"
