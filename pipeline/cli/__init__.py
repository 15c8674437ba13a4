"""The ``pipeline`` command: one module per command group, each command's options
one dataclass (pipeline.cli.options), registered in pipeline.cli.registry.

Exit codes: 0 success, 1 a stage failed (or another problem in the data), 2 bad
usage or configuration (nothing ran). A problem the user can fix ends in one
message (and, with ``--json``, a JSON error object on stdout); ``--debug`` adds
its traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from typing import Sequence

from pipeline import __version__, logger
from pipeline.cli.options import add_options, parse_options
from pipeline.cli.registry import COMMANDS
from pipeline.core import interrupts, progress
from pipeline.core.errors import PipelineError
from pipeline.core.fsutil import disk_full_error


def build_parser() -> argparse.ArgumentParser:
    # Loaded here, not on import: loading them takes a second, which Ctrl-C may interrupt.
    from pipeline.cli import batch, capture, fit, stages, studio, synthetic  # noqa: F401  (each registers its commands)

    parser = argparse.ArgumentParser(
        prog="pipeline", description="Photogrammetry-to-material pipeline: photos in, a Mitsuba 3 scene out."
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug messages")
    parser.add_argument("--debug", action="store_true", help="show the traceback of every error")
    parser.add_argument("--version", action="version", version=f"pipeline {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, entry in COMMANDS.items():
        add_options(sub.add_parser(name, help=entry.help, description=entry.options.__doc__), entry.options)
    return parser


def configure_logging(quiet: bool, verbose: bool) -> None:
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname).1s %(message)s"))
    handler.setLevel(level)
    logger.handlers[:] = [handler]
    logger.propagate = False
    progress.set_enabled(not quiet)
    if verbose:  # COLMAP's own log too (read where pipeline.colmap loads)
        os.environ["GLOG_minloglevel"] = "0"


def main(argv: Sequence[str] | None = None) -> int:
    interrupts.install()
    try:
        parser = build_parser()
    except (Exception, KeyboardInterrupt, interrupts.Interrupted) as e:
        if interrupts.interruption(e) is None:
            raise
        sys.stderr.write("E interrupted\n")
        return interrupts.exit_code(interrupts.interruption(e))
    args = parser.parse_args(argv)
    configure_logging(args.quiet, args.verbose)
    entry = COMMANDS[args.command]
    try:
        options = parse_options(entry.options, args, args.command)
        code = entry.run(options)
        if interrupts.interruption(None) is None:
            return code
        raise interrupts.interruption(None)  # a library swallowed it, and the command went on
    except PipelineError as e:
        if args.debug:
            raise
        return _fail(str(e), e.exit_code, args)
    except (Exception, KeyboardInterrupt, interrupts.Interrupted) as e:
        interruption = interrupts.interruption(e)
        if args.debug or (interruption is None and not disk_full_error(e)):
            raise
        if interruption is not None:
            kept = "; finished stages and fit checkpoints are kept, and the next run resumes from them"
            message = "interrupted" + (kept if args.command in ("run", "batch") else "")
            return _fail(message, interrupts.exit_code(interruption), args)
        where = getattr(e, "filename", None) or "the capture"
        return _fail(f"no space left on the disk holding {where}: free some space and run again", 1, args)


def _fail(message: str, code: int, args: argparse.Namespace) -> int:
    logger.error("%s", message)
    if getattr(args, "json", False):
        print(json.dumps({"error": message, "exit_code": code}))
    return code


__all__ = ["build_parser", "main"]


if __name__ == "__main__":
    sys.exit(main())
