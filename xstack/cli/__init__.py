"""The ``xstack`` command line: one sub-command per pipeline stage.

Each sub-command lives in its own module ``xstack.cli.<name>`` that defines

``add_parser(subparsers) -> argparse.ArgumentParser``
    registers the sub-command, its help and options, and
``run(args) -> int``
    does the work and returns the exit status.

User mistakes raise :class:`xstack.errors.XstackError`; they are printed as one line
``error: ...`` on stderr with exit status 1, never as a traceback. A bad command line (an
unknown option, a bad value or unit) is one line ``error: COMMAND: ...`` with exit status 2,
without the usage block (``--help`` shows that). Warnings are one ``warning: ...`` line; where
an error or warning concerns an API parameter (``option=`` of
:class:`~xstack.errors.XstackError` / :class:`~xstack.errors.XstackWarning`), the line names
the command's flag instead (:func:`name_flags`).

Every sub-command also gets ``-q/--quiet``, ``-v/--verbose``, ``--log FILE`` and
``--no-progress`` here, once; what goes to stdout (results, or the one ``--json`` object)
and what to stderr (messages, warnings, errors, progress bars on a terminal) is decided in
:mod:`xstack.cli._output`. ``docs/cli.md`` is generated from these parsers
(``python -m xstack.cli.docs``).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import re
import signal
import sys
import threading
import warnings
from collections.abc import Iterator, Sequence
from typing import Any, NoReturn

from xstack.cli._cluster import cluster_of
from xstack.cli._output import add_common_options, error, session, warn
from xstack.cli._storage import storage_of
from xstack.errors import XstackError, XstackWarning

#: Sub-commands in the order ``xstack --help`` lists them.
COMMANDS = ("convert", "export", "simulate", "image", "subtract", "uvstack", "linestack",
            "imstack", "fit", "noise", "info", "demo", "reproduce")


def _load(name: str) -> Any | None:
    try:
        return importlib.import_module(f"xstack.cli.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"xstack.cli.{name}":
            return None  # stage not built into this version
        raise


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line ``error: COMMAND: ...`` (exit status 2).

    argparse's own ``error`` prints the whole usage block before the message; here the
    message stands alone (``xstack COMMAND --help`` shows the usage). Sub-command parsers
    are of this class too (argparse creates them with the parent's class).
    """

    #: The sub-command being parsed (set by :func:`main`), for errors that the top-level
    #: parser reports on a sub-command's behalf (e.g. ``unrecognized arguments``).
    command: str | None = None

    def error(self, message: str) -> NoReturn:
        words = self.prog.split()
        name = words[-1] if len(words) > 1 else (Parser.command or words[0])
        error(f"{name}: {message}")
        self.exit(2)


def build_parser() -> argparse.ArgumentParser:
    """The top-level argument parser with every available sub-command."""
    from xstack import __version__

    parser = Parser(
        prog="xstack",
        description="Stacking of radio-interferometric data in the uv- and image-domain "
                    "(Lindroos et al. 2015).")
    parser.add_argument("--version", action="version", version=f"xstack {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        module = _load(name)
        if module is not None:
            sp = module.add_parser(sub)
            add_common_options(sp)
            sp.set_defaults(_run=module.run, _parser=sp)
    return parser


QUOTES = "'\""

#: Unit suffixes of API parameter names that the flags leave out
#: (``min_separation_arcsec`` -> ``--min-separation``; a plural ``partitions`` may be a
#: repeatable ``--partition`` as well).
_UNIT_SUFFIXES = ("_arcsec", "_deg", "_jy", "_hz", "_m", "_s")


def _flag_action(parser: argparse.ArgumentParser | None, option: str) -> argparse.Action | None:
    """The action of ``parser`` whose flag sets API parameter ``option`` (or None)."""
    if parser is None or not option:
        return None
    by_dest = {a.dest: a for a in parser._actions if a.option_strings}
    names = [option] + [option[: -len(s)] for s in _UNIT_SUFFIXES if option.endswith(s)]
    names += [option[:-1]] if option.endswith("s") else []  # partitions -> --partition
    for name in names:
        if name in by_dest:
            return by_dest[name]
    return None


def _flag_of(action: argparse.Action) -> str:
    longs = [s for s in action.option_strings if s.startswith("--")]
    return (longs or action.option_strings)[0]


def name_flags(text: str, option: str | Sequence[str] | None,
               parser: argparse.ArgumentParser | None) -> str:
    """A library message as the command line says it: API parameter ``option`` -> its flag.

    ``option=VALUE`` in ``text`` becomes ``--flag VALUE`` (``--flag`` alone for a switch or an
    empty VALUE; the flag's choices ``a|b`` where VALUE is not one of them); a bare ``option``
    becomes ``--flag`` only if it has an underscore (``noise_image``; ``region`` may be prose);
    a message that does not name the parameter so gets `` (--flag)`` appended.
    Several parameters (a tuple) are translated one after the other. Text without a known
    parameter comes back unchanged.
    """
    if option is not None and not isinstance(option, str):
        for one in option:
            text = name_flags(text, one, parser)
        return text
    action = _flag_action(parser, option or "")
    if action is None:
        return text
    flag = _flag_of(action)
    switch = action.nargs == 0
    # option=VALUE always; a bare name only where it cannot be prose (it has an underscore)
    tail = r"(?:=([^\s,;)]*))" + ("?" if "_" in str(option) else "")
    pattern = re.compile(r"(?<![\w.-])" + re.escape(str(option)) + tail + r"(?![\w-])")

    def replace(match: re.Match[str]) -> str:
        value = match.group(1)
        if not value or switch:
            return flag
        value = value.strip(QUOTES)
        if action.choices is not None and value not in action.choices:
            value = "|".join(str(c) for c in action.choices)  # e.g. True/False -> yes|no
        return f"{flag} {value}"

    new, n = pattern.subn(replace, text)
    return new if n else f"{text} ({flag})"


def _warning_printer(parser: argparse.ArgumentParser | None):
    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: Any = None, line: str | None = None) -> None:
        """Warnings on the command line: one ``warning: ...`` line on stderr naming the flag."""
        option = message.option if isinstance(message, XstackWarning) else None
        warn(name_flags(str(message), option, parser))

    return show


def emit_json(payload: dict[str, Any]) -> None:
    """Print one JSON object on stdout (the only thing a ``--json`` run prints there)."""
    sys.stdout.write(json.dumps(payload, indent=2, sort_keys=True, default=_json_default))
    sys.stdout.write("\n")
    sys.stdout.flush()


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived (``kill``, a batch scheduler's time limit, a container stopping).

    Raised in the main thread so that the run unwinds as after Ctrl-C: every temporary
    output and work directory is removed on the way out, where the default action of SIGTERM
    would end the process at once and leave them behind.
    """


@contextlib.contextmanager
def sigterm_unwinds() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread.

    A second SIGTERM while the first unwinds is ignored, so that the clean-up it started
    finishes (SIGKILL still ends the process). Outside the main thread, where Python cannot
    set signal handlers, the block runs with the handler the process has.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum: int, frame: Any) -> NoReturn:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise Terminated

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``xstack`` console script."""
    parser = build_parser()
    program = argv is None  # the console script or python -m xstack, not an in-process call
    if program:
        # chunk-sized arrays are returned to the OS when freed (xstack._memory)
        from xstack._memory import bound_heap

        bound_heap()
    argv = list(sys.argv[1:] if argv is None else argv)
    Parser.command = next((a for a in argv if a in COMMANDS), None)
    try:
        args = parser.parse_args(argv)
    finally:
        Parser.command = None
    if getattr(args, "_run", None) is None:
        parser.print_help(sys.stderr)
        return 2
    args._argv = argv
    sub = getattr(args, "_parser", None)
    warnings.filterwarnings("ignore", category=RuntimeWarning, module="dask")
    shown = warnings.showwarning
    warnings.showwarning = _warning_printer(sub)
    # only the program owns the process's signals; a caller of main() keeps its own
    terminable = sigterm_unwinds() if program else contextlib.nullcontext()
    try:
        with terminable, session(args), storage_of(args):  # --storage-options
            try:
                with cluster_of(args):  # --scheduler/--workers/DASK_SCHEDULER_ADDRESS
                    status = args._run(args)
            except XstackError as exc:
                error(name_flags(str(exc), exc.option, sub))
                return 1
            except OSError as exc:
                # a path the user gave that cannot be read or made (a file where a directory
                # should be, no permission, a full disk): one line, as for any bad input;
                # an OSError that names no file is a bug and keeps its traceback
                if exc.filename is None:
                    raise
                where = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
                error(f"{where}: {exc.strerror or exc}")
                return 1
            except Terminated:
                error("terminated (SIGTERM)")
                return 128 + signal.SIGTERM
            except KeyboardInterrupt:
                error("interrupted")
                return 130
    except XstackError as exc:  # e.g. a --log file that cannot be written
        error(str(exc))
        return 1
    finally:
        warnings.showwarning = shown
    return int(status or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
