"""The ``jaxflex`` command line. Each subcommand lives in a module of this package that defines
``register(subparsers)``; ``main`` discovers them, so a new command needs no edit here.

Commands turn on float64 (identification and certificates need it), turn on JAX's persistent
compilation cache (in ``$JAXFLEX_CACHE_DIR``, default ``~/.cache/jaxflex/jax``; ``--no-cache``
turns it off) and keep the traced programs of the fitting engine, the simulator and the tuner
beside it (``jaxflex.runtime.tracecache``, its ``traces/`` folder; ``--no-trace-cache`` turns that
part off), so a second run on the same machine neither traces nor compiles them again, expose every CPU
core to JAX as a host device before JAX starts (``jaxflex.sweep.engine.use_all_cores``; a
count already set in ``XLA_FLAGS`` is kept; ``--host-devices 1`` turns it off), so batched
sweeps use all cores, add XLA CPU options for loops of small kernels
(``jaxflex.runtime.xla.use_lean_xla_cpu``; the commands in ``SMALL_LOOP_COMMANDS`` also
get its small-loop option; ``--no-lean-xla`` turns them off). These options are accepted
before or after the command's name.

A failure is one of three kinds (``jaxflex.io.errors``), each with its own exit code and a
one-line message: bad input (exit 2, the message names the input: a log, a parameter or
spread file, an option, an output path), a result that did not converge (exit 3), or a bug
(exit 70: the message says so, names the file holding the full traceback and asks for a
report). Ctrl-C: exit 130, no traceback, and no empty output folder left behind. Every
command with outputs gets ``--force`` and checks its outputs before computing
(``jaxflex.app.cli.outputs``); its ``--help`` shows the defaults and ends with a worked example
(the module's ``EXAMPLE``).
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import os
import pkgutil
import sys
import warnings
from pathlib import Path

from jaxflex.io.params import accepting_unconverged
from jaxflex.app.cli.outputs import add_force_option

# worked examples of the commands whose modules do not define EXAMPLE yet
class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's line breaks and appends ``(default: X)`` to each option whose
    help does not already state its default."""

    def _get_help_string(self, action: argparse.Action) -> str:
        h = action.help or ""
        if ("default" in h or action.default in (None, False, argparse.SUPPRESS)
                or not action.option_strings):
            return h
        return h + " (default: %(default)s)"


def add_global_options(parser: argparse.ArgumentParser, after_command: bool = False) -> None:
    """Add the options every command takes (``--accept-unconverged``, ``--no-cache``, ...).

    On the main parser they get their defaults; on a command's parser (``after_command``)
    their default is ``SUPPRESS``, so that one given before the command is not reset by the
    command's parser, and an option the command defines itself (identify's
    ``--accept-unconverged``) is left to the command."""
    own = parser._option_string_actions
    extra = {"default": argparse.SUPPRESS} if after_command else {}
    group = (parser.add_argument_group("global options (also accepted before the command)")
             if after_command else parser)

    def add(flag: str, **kw) -> None:
        if flag not in own:
            group.add_argument(flag, **{**kw, **extra})

    add("--accept-unconverged", action="store_true",
        help="use parameter files from an identification that did not converge "
             "or that holds unmarked unidentifiable parameters (refused otherwise)")
    add("--no-cache", action="store_true",
        help="do not use the persistent JAX compilation cache "
             "($JAXFLEX_CACHE_DIR, default ~/.cache/jaxflex/jax)")
    add("--no-trace-cache", action="store_true",
        help="trace every function again in each run (otherwise the traced "
             "programs of the fitting engine, the simulator and the tuner are "
             "kept in the cache's traces/ folder, jaxflex.runtime.tracecache)")
    add("--host-devices", type=int, default=None, metavar="N",
        help="CPU cores JAX may use as host devices for batched sweeps "
             "(default: every core, unless XLA_FLAGS sets a count; 1: one)")
    add("--no-lean-xla", action="store_true",
        help="keep XLA's default CPU options (otherwise the options in "
             "jaxflex.runtime.xla.LEAN_XLA_CPU_FLAGS are added to XLA_FLAGS: "
             "sequential loops of small kernels run on one thread; for discover "
             "and tune also SMALL_LOOP_XLA_CPU_FLAGS: a loop of small arrays "
             "runs as one compiled function)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand found in ``jaxflex.app.cli``."""
    parser = argparse.ArgumentParser(
        prog="jaxflex",
        description="Flexible-joint robots with LuGre friction: simulate, identify, tune, "
        "certify, sweep, export, discover. The options below are accepted before or after "
        "the command.",
    )
    add_global_options(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(mod, "register"):
            mod.register(sub)
            name = next(reversed(sub.choices))
            p = sub.choices[name]
            p.formatter_class = HelpFormatter
            example = getattr(mod, "EXAMPLE", None)
            if example and not p.epilog:
                p.epilog = "example:\n  " + example
            opts = p._option_string_actions
            if ("--out" in opts or "--log" in opts) and "--force" not in opts:
                add_force_option(p)
            add_global_options(p, after_command=True)
    return parser


def _show_warning(command: str):
    def show(message, category, filename, lineno, file=None, line=None):
        print(f"jaxflex {command}: warning: {category.__name__}: {message}", file=sys.stderr)
    return show


def enable_compilation_cache(traces: bool = True) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``$JAXFLEX_CACHE_DIR`` (default
    ``~/.cache/jaxflex/jax``); every compilation is kept (JAX's default keeps those over 1 s;
    an identification compiles some 85 small functions, and with a 0.5 s threshold only 4-5
    were kept: a second run of `identify` on a 3 s log took 1.5-2 s more CPU than with all
    kept, cache 1.2 MB). ``traces``: also keep traced programs in its ``traces/`` folder
    (``jaxflex.runtime.tracecache.enable``). Returns the folder, or None (with a note on stderr) if
    it cannot be created."""
    import jax

    folder = Path(os.environ.get("JAXFLEX_CACHE_DIR", Path.home() / ".cache" / "jaxflex" / "jax"))
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(f"jaxflex: note: compilation cache off ({folder}: {e})", file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if traces:
        from jaxflex.runtime import tracecache

        try:
            tracecache.enable(folder / "traces")
        except OSError as e:
            print(f"jaxflex: note: trace cache off ({folder / 'traces'}: {e})", file=sys.stderr)
    return folder


#: Commands that run faster with XLA's small-loop option (``jaxflex.sweep.engine.
#: SMALL_LOOP_XLA_CPU_FLAGS``); identify on a long log and batched sweeps are slower with it,
#: so they keep XLA's default).
SMALL_LOOP_COMMANDS = ("discover", "tune")


#: Exit codes: bad input, a result that did not converge, a bug (sysexits' EX_SOFTWARE),
#: an interrupt (128 + SIGINT).
EXIT_INPUT, EXIT_UNCONVERGED, EXIT_BUG, EXIT_INTERRUPTED = 2, 3, 70, 130


def _output_folders(args: argparse.Namespace) -> list[Path]:
    """The folders a command may create: its ``--out`` and ``--report`` when they name a
    folder (no suffix), with every missing ancestor, deepest first. Those that did not exist
    before the run and are empty after a failed or interrupted one are removed again."""
    made = []
    for key in ("out", "report"):
        v = getattr(args, key, None)
        if not isinstance(v, str) or not v:
            continue
        p = Path(v)
        if p.suffix:  # a file: its folder is never created by a command
            continue
        while not p.exists() and p != p.parent:
            made.append(p)
            p = p.parent
    return made


def _remove_empty(folders: list[Path]) -> None:
    for d in folders:  # deepest first
        try:
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
        except OSError:
            pass


def report_bug(command: str, argv: list[str], exc: BaseException) -> Path | None:
    """Write the traceback of ``exc`` with the command line and versions to a file in the
    temporary folder; returns its path (None if it cannot be written)."""
    import platform
    import shlex
    import tempfile
    import time
    import traceback

    text = (f"jaxflex {command}: a bug report\n"
            f"command: jaxflex {shlex.join(argv)}\n"
            f"time: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}\n"
            f"python {platform.python_version()} on {platform.platform()}\n")
    for mod in ("jax", "jaxlib", "numpy", "scipy", "equinox", "optimistix"):
        m = sys.modules.get(mod)
        if m is not None:
            text += f"{mod} {getattr(m, '__version__', '?')}\n"
    text += "\n" + "".join(traceback.format_exception(exc))
    try:
        fd, name = tempfile.mkstemp(prefix=f"jaxflex-{command}-bug-", suffix=".txt")
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
    except OSError:
        return None
    return Path(name)


def handle_failure(command: str, argv: list[str], exc: BaseException) -> int:
    """Print the one-line message for a failed command and return its exit code: bad input
    (2: the message names the input), not converged (3) or a bug (70: the traceback goes to
    a file the message names, with a request to report it); ``jaxflex.io.errors.classify``."""
    from jaxflex.io.errors import classify

    kind = classify(exc)
    msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
    if kind == "input":
        print(f"jaxflex {command}: error: {msg}", file=sys.stderr)
        return EXIT_INPUT
    if kind == "unconverged":
        print(f"jaxflex {command}: not converged: {msg}", file=sys.stderr)
        return EXIT_UNCONVERGED
    path = report_bug(command, argv, exc)
    where = (f"the full traceback is in {path}" if path is not None else
             "the traceback follows (it could not be saved to a file)")
    print(f"jaxflex {command}: internal error (a bug in jaxflex, not a problem with your "
          f"input): {type(exc).__name__}: {msg}. {where}; please report it with the command "
          "line and that file", file=sys.stderr)
    if path is None:
        import traceback

        traceback.print_exception(exc)
    return EXIT_BUG


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxflex`` command; returns the exit status: 0 done, 1 a negative
    answer (e.g. not certified), 2 bad input, 3 a result that did not converge, 70 a bug
    (traceback saved to a file), 130 interrupted."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a malformed command line (2), its message printed
        return int(e.code or 0) if isinstance(e.code, (int, type(None))) else EXIT_INPUT
    args.argv = argv
    import jax

    from jaxflex.runtime.xla import use_lean_xla_cpu
    from jaxflex.sweep.engine import use_all_cores

    if args.host_devices is not None and args.host_devices < 1:
        print(f"jaxflex: error: --host-devices must be >= 1, got {args.host_devices}",
              file=sys.stderr)
        return EXIT_INPUT
    use_all_cores(args.host_devices)  # before any JAX computation
    if not args.no_lean_xla:
        use_lean_xla_cpu(small_loops=args.command in SMALL_LOOP_COMMANDS)

    jax.config.update("jax_enable_x64", True)
    if not args.no_cache:
        enable_compilation_cache(traces=not args.no_trace_cache)
    new_folders = _output_folders(args)
    old_show = warnings.showwarning
    warnings.showwarning = _show_warning(args.command)  # one line, no source excerpt
    try:
        with warnings.catch_warnings(), accepting_unconverged(args.accept_unconverged):
            # numpy's overflow/invalid warnings in a fit's rejected trial steps are expected
            warnings.filterwarnings("ignore", "overflow encountered", RuntimeWarning)
            warnings.filterwarnings("ignore", "invalid value encountered", RuntimeWarning)
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        _remove_empty(new_folders)  # an interrupted command leaves no empty folder
        print(f"jaxflex {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 - every failure gets its kind's message and code
        _remove_empty(new_folders)
        return handle_failure(args.command, argv, e)
    finally:
        warnings.showwarning = old_show


def console() -> None:
    """The ``jaxflex`` command (``python -m jaxflex`` too): ``main`` on ``sys.argv``, then a
    quick exit once it has returned: the exit handlers run (logging, child processes) and the
    standard streams are flushed, but the interpreter's own teardown is skipped: unloading
    XLA's compiled programs and every module adds most of a second to each command. Every
    file a command writes is
    closed before ``main`` returns. An exception out of ``main`` exits the usual way."""
    rc = main()
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)
    if run_exit_handlers is None:  # no such hook in this Python: the usual exit
        sys.exit(rc)
    run_exit_handlers()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)


if __name__ == "__main__":
    console()
