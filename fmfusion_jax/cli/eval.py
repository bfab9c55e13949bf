"""`fmfusion eval`: the ScanNet 3D semantic instance benchmark (AP, AP50, AP25) on benchmark-format predictions."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from fmfusion_jax.cli import options

log = logging.getLogger(__name__)

_EPILOG = """\
PRED is a <scene>.txt prediction file (lines 'pred_mask/<file>.txt <nyu40 id> <confidence>', one 0/1 mask
line per mesh vertex) or a folder of them. GT is a ScanNet scene folder (<scene>_vh_clean_2.ply, segs and
aggregation json; labels tsv in it or its parent), a benchmark ground-truth <scene>.txt (one
nyu40*1000+instance id per vertex), or a folder of either. Predictions and ground truth are paired by scene
name; a single PRED with a single GT is paired whatever the names. --gt and --pred take several
paths (and --explain an optional DIR), so list positional PREDs before them.

examples:
  fmfusion eval OUT/benchmark/scene0000_00.txt --gt ../shared/data/scannet/scene0000_00
  fmfusion eval OUT/benchmark --gt ../shared/data/scannet --json scores.json
  fmfusion eval OUT/benchmark/scene0000_00.txt --gt ../shared/data/scannet/scene0000_00 --explain /tmp/why
  fmfusion eval --gt ../shared/data/scannet/scene0000_00 --export-gt /tmp/gt_as_pred
  fmfusion eval /tmp/gt_as_pred --gt ../shared/data/scannet/scene0000_00    # scores 1.000 everywhere
"""


#: `--explain` without DIR (a distinct object, so that an explicit DIR is never mistaken for it).
_EXPLAIN_DEFAULT = Path("<default>")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "eval",
        help="score instance predictions with the ScanNet benchmark (AP, AP50, AP25)",
        description="Scores instance predictions in the ScanNet benchmark format by the rules of the ScanNet 3D\n"
        "semantic instance benchmark (18 classes; AP over IoU 0.50:0.05:0.90, AP50, AP25; per mesh\n"
        "vertex; scenes pooled per class) and prints the per-class table.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("pred", nargs="*", type=Path, metavar="PRED", help="prediction <scene>.txt files or folders of them")
    parser.add_argument(
        "--pred",
        dest="pred_option",
        action="extend",
        nargs="+",
        type=Path,
        default=[],
        metavar="PRED",
        help="same as the positional PRED (either form, or both)",
    )
    parser.add_argument(
        "--gt",
        action="extend",
        nargs="+",
        type=Path,
        default=[],
        metavar="GT",
        help="ground truth: scene folders, benchmark gt <scene>.txt files, or folders of either (required)",
    )
    parser.add_argument(
        "--labels-tsv",
        type=Path,
        metavar="TSV",
        help="raw label -> nyu40 tsv for scene folders (default: scannetv2-labels.combined.tsv or "
        "scannet-labels.combined.tsv in the scene folder, then its parent)",
    )
    options.add_json(parser, help="also write the scores to this JSON file")
    parser.add_argument(
        "--explain",
        nargs="?",
        const=_EXPLAIN_DEFAULT,
        type=Path,
        metavar="DIR",
        help="also write an error analysis (each ground-truth object's status, each prediction's "
        "kind: docs/error-analysis.md) as explain.md, explain.json and explain.png (the "
        "picture needs a scene folder as GT) into DIR, or DIR/<scene>/ for several scenes, "
        "and print its counts after the table; DIR defaults to the folder of the --json "
        "file, else ./explain",
    )
    parser.add_argument(
        "--detections",
        type=Path,
        metavar="DIR",
        help="the detections the map was made from (one scene folder as GT): also say which ground-truth objects "
        "the detector ever saw (a mask with IoU >= 0.5 in some frame) and the detector-limited ceiling of mAP50, "
        "beside what the map found; written as reach.md / reach.json with --explain",
    )
    parser.add_argument(
        "--export-gt",
        type=Path,
        metavar="OUT_DIR",
        help="instead of evaluating, write each GT scene's instances as benchmark-format "
        "predictions (confidence 1) into OUT_DIR, to check that ground truth scores 1.0",
    )
    options.add_no_progress(parser, "no progress bar while the detector's reach is measured (--detections)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.evaluate import run_eval  # lazy, as every command's app: `fmfusion --help` stays instant

    explain_dir = args.explain
    if explain_dir is _EXPLAIN_DEFAULT:
        explain_dir = args.json.parent if args.json is not None else Path("explain")
    predictions = [*args.pred, *args.pred_option]
    return run_eval(
        predictions,
        args.gt,
        args.labels_tsv,
        args.json,
        explain_dir,
        args.detections,
        args.export_gt,
        progress=not args.no_progress,
    )
