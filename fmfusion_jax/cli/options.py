"""The options several `fmfusion` subcommands take, each declared once here (the help text, where it
differs between commands, is the command's own)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

VERBOSE_HELP = "more logging (-v info, -vv debug)"


def add_verbose(parser: argparse.ArgumentParser, dest: str = "verbose") -> None:
    """`-v/--verbose`, counted (`-vv`) into `dest`."""
    parser.add_argument("-v", "--verbose", action="count", default=0, dest=dest, help=VERBOSE_HELP)


def add_config(parser: argparse.ArgumentParser, help: str, default: str | None = None) -> None:
    """`--config NAME|FILE`: a packaged config or a config file."""
    parser.add_argument("--config", default=default, help=help)


def add_overrides(parser: argparse.ArgumentParser, help: str, metavar: str = "KEY=VALUE", dest: str = "overrides") -> None:
    """`--set KEY=VALUE`, repeatable, collected into the list `dest`."""
    parser.add_argument("--set", dest=dest, action="append", default=[], metavar=metavar, help=help)


def add_no_progress(parser: argparse.ArgumentParser, help: str = "no progress bars") -> None:
    """`--no-progress`."""
    parser.add_argument("--no-progress", action="store_true", help=help)


def add_out(parser: argparse.ArgumentParser, help: str, **kwargs: Any) -> None:
    """`--out DIR`: the output folder (`required`, `default`, `metavar` as the command has them)."""
    parser.add_argument("--out", type=Path, help=help, **kwargs)


def add_seed(parser: argparse.ArgumentParser, help: str, default: int | None = 0) -> None:
    """`--seed N`."""
    parser.add_argument("--seed", type=int, default=default, help=help)


#: `--layout`'s choices: `io.scene.LAYOUTS` (a test keeps them equal; the parsers do not import the readers).
LAYOUT_CHOICES = ("auto", "scannet", "scenenn", "tum", "replica", "redwood", "rosbag", "record3d", "realsense")


def add_layout(parser: argparse.ArgumentParser, help: str, choices: tuple[str, ...] = LAYOUT_CHOICES) -> None:
    """`--layout`: the scene folder's layout (`auto`: detected)."""
    parser.add_argument("--layout", default="auto", choices=choices, help=help)


def add_stride(parser: argparse.ArgumentParser, help: str, metavar: str | None = None) -> None:
    """`--stride N`: read every N-th frame."""
    parser.add_argument("--stride", type=int, default=1, metavar=metavar, help=help)


def add_max_frames(parser: argparse.ArgumentParser, help: str) -> None:
    """`--max-frames N`."""
    parser.add_argument("--max-frames", type=int, default=None, metavar="N", help=help)


def _int_at_least(text: str, least: int) -> int:
    """`text` as a whole number of at least `least`; anything else is a usage error naming the value."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"must be at least {least}, got {value}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: a whole number of at least 1."""
    return _int_at_least(text, 1)


def non_negative_int(text: str) -> int:
    """An argparse type: a whole number of at least 0."""
    return _int_at_least(text, 0)


def add_depth_max(parser: argparse.ArgumentParser) -> None:
    """`--depth-max M`: depth truncation."""
    parser.add_argument("--depth-max", type=float, default=4.0, help="depth truncation in metres (default 4.0)")


def add_json(parser: argparse.ArgumentParser, help: str) -> None:
    """`--json FILE`: also write the result as JSON."""
    parser.add_argument("--json", type=Path, metavar="FILE", help=help)
