"""Output paths of the commands, checked before any computation.

Every command calls ``check_file`` / ``check_folder`` on its outputs right after parsing, so a
mistyped or unwritable ``--out`` fails in a second with a message saying what to do, not after
minutes of work; and an existing result is never overwritten without ``--force``.

Rules: an output *file*'s folder must exist (a typo in a folder name is not silently created);
an output *folder* is created at write time with its missing parents, so the nearest existing
ancestor must be a writable folder; a file is never where a folder is expected, nor the reverse.

Also here: ``writing`` (a command's result files are written whole or not at all, Ctrl-C
waits for them), ``interrupts_stop`` (Ctrl-C stops a computation whose library calls end a
solve on it and carry on) and ``suggest_command`` (a command a message suggests, built from the command
line given, so that it runs as printed).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from jaxflex.io.errors import InputError


class OutputError(InputError):
    """An output path that cannot or must not be written; the message says what to do."""


FORCE_HELP = "overwrite existing output files (default: refuse to overwrite)"


def add_force_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--force`` (overwrite existing outputs) to a command's parser."""
    parser.add_argument("--force", action="store_true", help=FORCE_HELP)


def _writable_folder(folder: Path, flag: str, path: Path) -> None:
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{flag} {path}: the folder {folder} is not writable; choose a folder "
                          "you can write to")


def check_file(path: str | os.PathLike, *, force: bool, flag: str = "--out") -> Path:
    """Check that the output file ``path`` can be written now: its folder exists and is
    writable, it is not a folder, and it does not exist unless ``force``. Returns the path;
    raises ``OutputError`` naming ``flag`` and what to do."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{flag} {p}: is a folder, but a file is expected here; give a file "
                          f"path such as {p / 'result'}{p.suffix or '.json'}")
    parent = p.parent if str(p.parent) else Path(".")
    for anc in (parent, *parent.parents):
        if anc.exists() and not anc.is_dir():
            raise OutputError(f"{flag} {p}: {anc} is a file, not a folder; choose another path")
    if not parent.is_dir():
        raise OutputError(f"{flag} {p}: the folder {parent} does not exist; create it first "
                          f"(mkdir -p {shlex.quote(str(parent))}) or choose another path")
    _writable_folder(parent, flag, p)
    if p.exists():
        if not force:
            raise OutputError(f"{flag} {p}: the file exists; pass --force to overwrite it, or "
                              "choose another path (nothing was written)")
        if not os.access(p, os.W_OK):
            raise OutputError(f"{flag} {p}: the file exists and is not writable")
    return p


def check_folder(path: str | os.PathLike, *, force: bool, flag: str = "--out",
                 marker: str | Sequence[str] | None = None, resume: bool = False) -> Path:
    """Check that the output folder ``path`` can be created or written now: it is not a file,
    its nearest existing ancestor is a writable folder, and (unless ``force`` or ``resume``)
    it does not already hold a result, recognised by the file ``marker`` (e.g.
    ``report.json``) or any of the files of a sequence of markers (every file the command
    would write there). Returns the path; raises ``OutputError`` naming ``flag`` and what to
    do. Nothing is created here."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{flag} {p}: is a file, but a folder is expected here; give a folder "
                          "path (it is created if missing)")
    anc = p
    while not anc.exists():
        if anc.parent == anc:
            break
        anc = anc.parent
    if anc.exists() and not anc.is_dir():
        raise OutputError(f"{flag} {p}: {anc} is a file, not a folder; choose another path")
    _writable_folder(anc, flag, p)
    markers = [marker] if isinstance(marker, str) else list(marker or ())
    held = [m for m in markers if (p / m).exists()]
    if held and not (force or resume):
        raise OutputError(f"{flag} {p}: the folder already holds a result ({', '.join(held)}); "
                          "pass --force to overwrite it, or choose another folder (nothing was "
                          "written)")
    return p


def check_outputs(force: bool, files: tuple[str | os.PathLike | None, ...] | list = (),
                  folders: tuple[str | os.PathLike | None, ...] | list = (),
                  marker: str | Sequence[str] | None = None, flag: str = "--out") -> None:
    """``check_file`` on each of ``files`` and ``check_folder`` (with ``marker``) on each of
    ``folders``; ``None`` entries are skipped. One call at the top of a command's ``run``."""
    for f in files:
        if f is not None:
            check_file(f, force=force, flag=flag)
    for d in folders:
        if d is not None:
            check_folder(d, force=force, flag=flag, marker=marker)


def suggest_command(argv: Sequence[str], add: Sequence[str] = (),
                    drop: Sequence[str] = ()) -> str:
    """The command line ``jaxflex ARGV`` with the flags ``drop`` (options without a value)
    removed and ``add`` appended unless already there, quoted for a POSIX shell: a command a
    message suggests runs as printed, with every option the user gave."""
    args = [a for a in argv if a not in drop]
    args += [a for a in add if a not in args]
    return "jaxflex " + shlex.join(args)


@contextlib.contextmanager
def writing() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) and SIGTERM while a command writes its result files, then
    raise ``KeyboardInterrupt`` if one came: an interrupted command leaves either nothing
    or its whole result, never a folder with half of it. Off the main thread (where no
    signal handler can be set) the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    sigs = (signal.SIGINT, signal.SIGTERM)
    old = {s: signal.signal(s, lambda num, frame: got.append(num)) for s in sigs}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if got:
        raise KeyboardInterrupt


#: After a first Ctrl-C inside ``interrupts_stop``, the period [s] at which a
#: ``KeyboardInterrupt`` is raised again until the block is left.
REPEAT_INTERRUPT_S: float = 0.25


@contextlib.contextmanager
def interrupts_stop() -> Iterator[Callable[[], None]]:
    """Make Ctrl-C (SIGINT) or SIGTERM stop the block even where a library call catches the
    ``KeyboardInterrupt`` and carries on (a fit's solve ends on it and returns its last
    point, ``jaxflex.fit.least_squares``): after the first signal, ``KeyboardInterrupt`` is
    raised again every ``REPEAT_INTERRUPT_S`` until it leaves the block, and once more at the
    block's end if the block finished anyway, so nothing computed after an interrupt is
    taken for a result. Yields ``check``, which raises ``KeyboardInterrupt`` once a signal has
    come (for progress callbacks). Off the main thread the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    got: list[int] = []
    done: list[bool] = []

    def again(num: int, frame: object) -> None:
        if not done:
            raise KeyboardInterrupt

    def first(num: int, frame: object) -> None:
        got.append(num)
        signal.signal(signal.SIGALRM, again)
        signal.setitimer(signal.ITIMER_REAL, REPEAT_INTERRUPT_S, REPEAT_INTERRUPT_S)
        raise KeyboardInterrupt

    def check() -> None:
        if got:
            raise KeyboardInterrupt

    sigs = (signal.SIGINT, signal.SIGTERM)
    old = {s: signal.signal(s, first) for s in sigs}
    old_alarm = signal.getsignal(signal.SIGALRM)
    try:
        yield check
    finally:
        done.append(True)
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, old_alarm)
        for s, h in old.items():
            signal.signal(s, h)
    if got:
        raise KeyboardInterrupt
