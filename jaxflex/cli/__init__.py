"""The ``jaxflex`` command line. Each subcommand lives in a module of this package that defines
``register(subparsers)``; ``main`` discovers them, so a new command needs no edit here.

Commands turn on float64 (identification and certificates need it) and turn the library's
``ValueError``s (bad logs, bad parameters, bad gains) into a one-line message and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand found in ``jaxflex.cli``."""
    parser = argparse.ArgumentParser(
        prog="jaxflex",
        description="Flexible-joint robots with LuGre friction: simulate, identify, tune, "
        "certify, sweep, export, discover.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(mod, "register"):
            mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxflex`` command; returns the exit status."""
    args = build_parser().parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, KeyError) as e:
        print(f"jaxflex {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
