"""`fmfusion query OUT "text"`: the instances of a map that a phrase names, ranked."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "query",
        help="find instances of a map by text: a class, a label, or a relation ('sofa near the window')",
        description="Matches a phrase against the classes and the open-set labels each instance of a map was "
        "seen as (exact, synonyms, then close spellings); a phrase with a relation (on, in/inside, near, "
        "next to) keeps the instances that relation links to the second phrase in the map's scene graph. "
        "Prints the ranked instances with their boxes; --json writes them.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("map", type=Path, help="output folder of fmfusion run / demo (instances.json)")
    parser.add_argument("text", help="what to find, e.g. 'chair', 'something to sit on', 'lamp on the table'")
    parser.add_argument("--top", type=int, default=10, help="at most this many instances (default 10)")
    options.add_json(parser, help="also write the matches to this JSON file")
    parser.add_argument(
        "--picture",
        type=Path,
        metavar="FILE.png",
        help="also draw the map from above with the matches highlighted (needs labelled_points.npz)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.query import run_query  # lazy: the command's work loads only when it runs

    return run_query(
        map=args.map,
        text=args.text,
        top=args.top,
        json_path=args.json,
        picture=args.picture,
    )
