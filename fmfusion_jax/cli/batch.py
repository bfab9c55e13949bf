"""`fmfusion batch DATASET --out OUT`: `fmfusion run` over many scenes, with one pooled benchmark."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options
from fmfusion_jax.errors import UserError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "batch",
        help="fuse and score many scenes (a folder of scenes or a split file), locally or on Ray",
        description="Runs `fmfusion run` on every scene of a dataset, each scene in a process of its own "
        "(a scene that fails or runs past --scene-timeout is recorded and the batch goes on), writes each "
        "scene's outputs into OUT/<scene>/, and at the end the ScanNet benchmark pooled over all scored scenes "
        "with a per-scene table (OUT/batch.md, batch.csv, batch.json). --resume skips the scenes already done.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("dataset", type=Path, help="a folder of scene folders, or a split file of scene ids")
    parser.add_argument("--root", type=Path, help="folder of the scenes of a split file (default: the file's folder)")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--detections", metavar="PATTERN", help="each scene's detection folder: {scene} is its name, {root} its parent"
    )
    source.add_argument("--simulate", action="store_true", help="simulate each scene's detections from its ground truth")
    source.add_argument(
        "--models",
        type=Path,
        metavar="DIR",
        help="detect with the models of DIR (`fmfusion detect`, into OUT/_detections/<scene>, continued on --resume)",
    )
    options.add_out(parser, required=True, help="output folder")
    parser.add_argument("--workers", type=int, default=1, help="scenes fused at once on this machine (default 1)")
    parser.add_argument("--ray", metavar="ADDRESS", help="run one Ray task per scene on this cluster (auto, local or an address)")
    parser.add_argument("--ray-cpus", type=float, default=1.0, metavar="N", help="CPUs a scene's Ray task declares")
    parser.add_argument("--ray-gpus", type=float, default=0.0, metavar="N", help="GPUs a scene's Ray task declares")
    parser.add_argument("--batch", type=int, metavar="K", help="fuse K scenes at once in this process, vmapped on one device")
    parser.add_argument("--resume", action="store_true", help="skip the scenes whose outputs are complete")
    parser.add_argument("--scene-timeout", type=float, metavar="S", help="stop a scene after S seconds (recorded as timeout)")
    parser.add_argument(
        "--scene-memory",
        type=float,
        metavar="GIB",
        help="stop a scene whose process holds more than this resident memory (recorded as memory)",
    )
    options.add_config(parser, help="config of every scene's run (default: scannet)")
    options.add_overrides(parser, help="override a config value of every scene's run (repeatable)")
    options.add_no_progress(parser, help="no progress lines (a line per finished scene, and how far running scenes got)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.batch import Batch, list_scenes, pooled_benchmark, write_reports
    from fmfusion_jax.config import load_config

    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    if args.scene_timeout is not None and args.scene_timeout <= 0:
        raise UserError(f"--scene-timeout must be > 0, got {args.scene_timeout}")
    if args.scene_memory is not None and args.scene_memory <= 0:
        raise UserError(f"--scene-memory must be > 0 GiB, got {args.scene_memory}")
    load_config(args.config or "scannet", args.overrides)  # a bad config fails now, not in every scene
    scenes = list_scenes(args.dataset, args.root)
    options = (
        ["--config", str(Path(args.config).resolve()) if os.path.isfile(args.config) else args.config] if args.config else []
    )
    for item in args.overrides:
        options += ["--set", item]
    options.append("--restart")  # an interrupted scene of an earlier batch starts over
    args.out.mkdir(parents=True, exist_ok=True)
    batch = Batch(
        scenes,
        args.out,
        detections=args.detections,
        simulate=args.simulate,
        models=args.models,
        run_options=options,
        timeout_s=args.scene_timeout,
        memory_mib=None if args.scene_memory is None else 1024 * args.scene_memory,
    )
    if args.resume:
        batch.load()
    tasks = batch.pending(args.resume)
    skipped = len(batch.tasks) - len(tasks)
    total = len(tasks)
    print(f"{len(batch.tasks)} scenes, {total} to run" + (f" ({skipped} done before)" if skipped else ""), file=sys.stderr)
    done = 0

    def report(record: dict) -> None:
        nonlocal done
        done += 1
        if not args.no_progress:
            score = f", AP50 {100 * record['mAP50']:.1f}" if record.get("mAP50") is not None else ""
            what = record["status"] if record["status"] == "ok" else f"{record['status']}: {record.get('error')}"
            print(f"[{done}/{total}] {record['scene']}: {what}{score} ({record.get('seconds', 0):.0f} s)", file=sys.stderr)

    if args.batch:
        if args.batch < 1 or args.ray:
            raise UserError("--batch K needs K >= 1 and no --ray")
        batch.run_vmapped(tasks, args.batch, load_config(args.config or "scannet", args.overrides), report)
    elif args.ray:
        batch.run_ray(tasks, args.ray, report, cpus_per_scene=args.ray_cpus, gpus_per_scene=args.ray_gpus)
    else:
        batch.run_local(
            tasks,
            args.workers,
            report,
            None if args.no_progress else lambda scene, text: print(f"  {scene}: {text}", file=sys.stderr),
        )
    records = [batch.records[t.name] for t in batch.tasks if t.name in batch.records]
    pooled, scored = pooled_benchmark(records)
    print(write_reports(args.out, records, pooled, scored))
    failed = sum(r.get("status") != "ok" for r in records)
    return 1 if failed else 0
