"""The ``drillnav`` command line.

Each subcommand group lives in its own ``cli_*.py`` module exposing
``register(subparsers)``; this module only assembles them and turns every
expected failure into one clear line on stderr and a non-zero exit status.

Only the module of the command being run is imported (``drillnav --help``
imports none): a command's module pulls in what that command needs (zenoh,
FastAPI, OpenCV, ...), and a surgeon's terminal should not wait seconds for the
libraries of the other commands.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# One BLAS thread, set before anything loads numpy (its OpenBLAS reads this once): drillnav's matrices are small and
# many (6x6 normal matrices, least squares over a few hundred residuals), and OpenBLAS's threads spun on both cores for
# each call. Measured: the joint solve + tag location took 95 ms of CPU for 48 ms of wall time with 2 threads, 29 ms
# and 25 ms with one. The worker processes (joint solve, CT) inherit it. The DRR's threads are numba's, not BLAS's. A
# site that wants otherwise sets the variable itself.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from collections.abc import Sequence

from drillnav.registration.errors import DrillnavError

__all__ = ["main", "build_parser", "CliError"]

# Each command -> (module under drillnav.service whose ``register`` adds it, one-line help for ``drillnav --help``).
COMMANDS: dict[str, tuple[str, str]] = {
    "markers": ("cli_markers", "the multimodal marker set: export, printable sheets and jig, detection, measuring as built"),
    "sim": ("cli_sim", "the digital twin"),
    "register": ("cli_register", "register the drill axis to fluoroscopy from a camera frame and 1+ shots"),
    "calibrate": ("cli_calibrate", "camera and drill-axis calibration"),
    "serve": ("cli_serve", "run the daemon"),
    "listen": ("cli_stream", "print a stream as JSON lines (e.g. drill-axis)"),
    "replay": ("cli_stream", "republish an MCAP recording at the recorded timing"),
    "pki": ("cli_pki", "make the site's certificate authority and certificates for the zenoh bus"),
    "calibration": ("cli_calibration", "calibration files in other tools' formats"),
}
COMMAND_MODULES: tuple[str, ...] = tuple(dict.fromkeys(m for m, _ in COMMANDS.values()))

EXIT_USAGE = 2
EXIT_FAILURE = 1


class CliError(DrillnavError):
    """A command-line request that cannot be carried out (bad argument, unwritable output)."""


class _Subparsers:
    """Passes on to the real subparsers only the ``add_parser`` calls for ``wanted`` (a module may add several commands)."""

    def __init__(self, subparsers, wanted: str) -> None:
        self._subparsers, self._wanted = subparsers, wanted

    def add_parser(self, name: str, **kwargs):
        if name == self._wanted:
            return self._subparsers.add_parser(name, **kwargs)
        return argparse.ArgumentParser(prog=f"drillnav {name}", add_help=False)  # another command of the module: discarded


def _command_word(argv: Sequence[str]) -> str | None:
    """The command named in ``argv`` (the first word not an option), if it is one of :data:`COMMANDS`."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser; the full one of the command named in ``argv`` only (None: every command in full, e.g. for docs)."""
    parser = argparse.ArgumentParser(
        prog="drillnav",
        description="Drill-mounted video guidance for fluoroscopy-guided orthopaedic trauma surgery.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    if argv is None:
        for name in COMMAND_MODULES:
            importlib.import_module(f"drillnav.service.{name}").register(subparsers)
        return parser
    wanted = _command_word(argv)
    for command, (module, help_text) in COMMANDS.items():
        if command == wanted:
            importlib.import_module(f"drillnav.service.{module}").register(_Subparsers(subparsers, command))
            if command not in subparsers.choices:
                raise RuntimeError(f"drillnav.service.{module} did not add the command '{command}'")
        else:
            subparsers.add_parser(command, help=help_text)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; return the process exit status.

    Subcommand handlers are set as ``func`` on the parsed namespace and return
    an int status (0 on success).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
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
