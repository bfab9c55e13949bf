"""The `fmfusion` command line: one module per subcommand, each with `register(subparsers)`.

A subcommand module defines `register(subparsers)` that adds its parser and sets `func` to a function
taking the parsed arguments and returning an exit code. Heavy imports (JAX) stay inside those functions
so that `fmfusion --help` is instant.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from fmfusion_jax.cli import options
from fmfusion_jax.compile_cache import enable_compile_cache
from fmfusion_jax.errors import UserError
from fmfusion_jax.xla_options import enable_gpu_command_buffers


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Adds "(default: X)" to an option's help unless the help already says its default, or there is
    none worth saying (None: "not given", the help explains what happens then; off flags; empty lists)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text or action.default is None or action.default is False or action.default == []:
            return text
        return super()._get_help_string(action)


#: Subcommand modules, in the order `--help` lists them.
SUBCOMMANDS = (
    "demo",
    "info",
    "synth",
    "simulate",
    "detect",
    "models",
    "track",
    "run",
    "batch",
    "query",
    "eval",
    "bench",
    "likelihood",
    "experiment",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fmfusion",
        description="Instance-aware semantic mapping from RGB-D video with open-set foundation-model detections.",
    )
    from fmfusion_jax import __version__  # lazy: the package's __init__ loads JAX (the Mapper)

    parser.add_argument("--version", action="version", version=f"fmfusion {__version__}")
    options.add_verbose(parser)
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"fmfusion_jax.cli.{name}").register(subparsers)
    _accept_verbose_after_subcommands(parser)
    return parser


def _accept_verbose_after_subcommands(parser: argparse.ArgumentParser) -> None:
    """`fmfusion run -v ...` as well as `fmfusion -v run ...`: every (nested) subcommand takes -v too,
    counted into its own field (a subparser's default would overwrite the top-level count)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in set(action.choices.values()):
                options.add_verbose(sub, dest="verbose_after_command")
                _accept_verbose_after_subcommands(sub)


def main(argv: list[str] | None = None, *, exit_at_once_on_interrupt: bool = False) -> int:
    """Runs one command; returns its exit status (2: a user error, printed in one line; 130: interrupted).

    `exit_at_once_on_interrupt`: after a Ctrl-C that reached a command as `KeyboardInterrupt` (commands without
    their own safe stop point), flush the streams and exit the process right away, skipping the interpreter's
    teardown, which can crash while the runtime's threads are mid-computation (`fmfusion` itself does this).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    args.verbose += getattr(args, "verbose_after_command", 0)
    level = logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if args.verbose < 2:  # JAX's own INFO lines (backend probing) are noise unless debugging
        logging.getLogger("jax").setLevel(logging.WARNING)
    enable_compile_cache()  # steps compiled by an earlier run load from disk (FMFUSION_COMPILE_CACHE=off: never)
    enable_gpu_command_buffers()  # on a GPU, the steps' loops run on the device (the CPU ignores it)
    try:
        return int(args.func(args) or 0)
    except UserError as error:
        print(f"fmfusion {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fmfusion {args.command}: interrupted", file=sys.stderr)
        if exit_at_once_on_interrupt:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(130)
        return 130


def entry() -> None:
    """The `fmfusion` console command (a process of its own: its threads share the C heap's arenas)."""
    from fmfusion_jax import host_memory

    host_memory.limit_malloc_arenas()
    sys.exit(main(exit_at_once_on_interrupt=True))


if __name__ == "__main__":
    sys.exit(main())
