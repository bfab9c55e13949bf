"""`fmfusion query OUT "text"`: the instances of a map that a phrase names, ranked."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter
from fmfusion_jax.errors import UserError


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
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the matches to this JSON file")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.scene_graph import build_scene_graph, query

    path = args.map / "instances.json" if args.map.is_dir() else args.map
    try:
        records = json.loads(path.read_text())["instances"]
    except FileNotFoundError:
        raise UserError(f"{path}: not found (give the output folder of fmfusion run or demo)") from None
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as error:
        raise UserError(f"{path}: not an instances.json ({error})") from None
    graph_path = path.parent / "scene_graph.json"
    graph = json.loads(graph_path.read_text()) if graph_path.is_file() else build_scene_graph(records)
    by_id = {r["id"]: r for r in records}
    matches = query(records, args.text, graph)[: max(1, args.top)]
    rows = []
    for m in matches:
        record = by_id[m.instance_id]
        box = record["oriented_box"]
        rows.append(
            {
                "id": m.instance_id,
                "class": record["class"],
                "score": round(m.score, 3),
                "why": m.why,
                "center": [round(x, 3) for x in box["center"]],
                "extent": [round(x, 3) for x in box["extent"]],
                "yaw": round(box["yaw"], 3),
            }
        )
        print(f"{m.instance_id:5d}  {record['class']:<15} score {m.score:5.2f}  at {rows[-1]['center']}  ({m.why})")
    if not rows:
        print(f"no instance matches {args.text!r}")
    if args.json:
        args.json.write_text(json.dumps({"query": args.text, "matches": rows}, indent=1))
    return 0
