"""The ``drillnav`` command line.

Each subcommand group lives in its own ``cli_*.py`` module exposing
``register(subparsers)``; this module only assembles them and turns every
expected failure into one clear line on stderr and a non-zero exit status.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from drillnav.registration.errors import DrillnavError

__all__ = ["main", "build_parser", "CliError"]

# Modules under drillnav.service that contribute subcommands.
COMMAND_MODULES: tuple[str, ...] = (
    "cli_markers",
    "cli_sim",
    "cli_register",
    "cli_calibrate",
    "cli_serve",
    "cli_stream",
    "cli_pki",
    "cli_calibration",
)

EXIT_USAGE = 2
EXIT_FAILURE = 1


class CliError(DrillnavError):
    """A command-line request that cannot be carried out (bad argument, unwritable output)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="drillnav",
        description="Drill-mounted video guidance for fluoroscopy-guided orthopaedic trauma surgery.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"drillnav.service.{name}").register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; return the process exit status.

    Subcommand handlers are set as ``func`` on the parsed namespace and return
    an int status (0 on success).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("drillnav: interrupted", file=sys.stderr)
        return 130
    except (DrillnavError, ValueError, OSError) as exc:
        print(f"drillnav {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
