"""The ``yauyau`` console script: precompute, models, filter, smooth, simulate, plot, serve,
analyze, check, fit.

Each subcommand lives in ``service/cli/<name>.py`` with ``add_arguments(parser)`` and
``run(args) -> int``.  User errors (:class:`solver.YauyauError`, ``storage.StoreError``) print one
line naming the field and exit with status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import os
import sys

from yauyau import __version__

COMMANDS = {
    "precompute": "solve the Kolmogorov propagators offline and store the model (prints its id)",
    "models": "list the stored models",
    "filter": "run a filter over a file of observations (increments or measurements, regular or timed)",
    "smooth": "run the optimal smoother over a recorded file: each row given every row (or --lag L after)",
    "simulate": "simulate a sample path and its observations (CSV files filter reads)",
    "plot": ("plot a filtered run: mean and 95 percent band, the smoothed one beside it, truth, density "
             "heat map (PNG or SVG)"),
    "serve": "serve the HTTP API",
    "analyze": "estimation-algebra analysis of a model spec and the recommended method",
    "fit": "maximum-likelihood estimates of a spec's parameters from a record, with standard errors",
    "check": "whether the spec's discretisation resolves its posterior, before any data",
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser; with ``only`` (the command about to run) just that command's module is imported,
    so a command pays for its own imports only (``yauyau filter`` never loads the analysis)."""
    parser = argparse.ArgumentParser(prog="yauyau", description="Real-time optimal nonlinear filtering.")
    parser.add_argument("--version", action="version", version=f"yauyau {version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, help_text in COMMANDS.items():
        cmd = sub.add_parser(name, help=help_text, description=help_text)
        if only is None or name == only:
            module = importlib.import_module(f"yauyau.service.cli.{name}")
            module.add_arguments(cmd)
            cmd.set_defaults(_module=module)
    return parser


def version() -> str:
    """The installed distribution's version (a checkout run without installing: the package's own)."""
    try:
        return importlib.metadata.version("yauyau")
    except importlib.metadata.PackageNotFoundError:
        return __version__


def main(argv: list[str] | None = None) -> int:
    from yauyau.solver.errors import YauyauError
    from yauyau.storage.errors import StoreError

    argv = sys.argv[1:] if argv is None else list(argv)
    first = argv[0] if argv else None
    # a command's module only for that command; none for --version; all of them for the help
    args = build_parser(first if first in COMMANDS or first == "--version" else None).parse_args(argv)
    try:
        return int(args._module.run(args) or 0)
    except (YauyauError, StoreError) as exc:
        print(f"yauyau {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `yauyau analyze spec.toml | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print(f"yauyau {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
