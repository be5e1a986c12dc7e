"""The ``xstack`` command line: one sub-command per pipeline stage.

Each sub-command lives in its own module ``xstack.cli.<name>`` that defines

``add_parser(subparsers) -> argparse.ArgumentParser``
    registers the sub-command, its help and options, and
``run(args) -> int``
    does the work and returns the exit status.

User mistakes raise :class:`xstack.errors.XstackError`; they are printed as one line
``error: ...`` on stderr with exit status 1, never as a traceback.

Every sub-command also gets ``-q/--quiet``, ``-v/--verbose``, ``--log FILE`` and
``--no-progress`` here, once; what goes to stdout (results, or the one ``--json`` object)
and what to stderr (messages, warnings, errors, progress bars on a terminal) is decided in
:mod:`xstack.cli._output`. ``docs/cli.md`` is generated from these parsers
(``python -m xstack.cli.docs``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import warnings
from collections.abc import Sequence
from typing import Any

from xstack.cli._output import add_common_options, error, session, warn
from xstack.errors import XstackError

#: Sub-commands in the order ``xstack --help`` lists them.
COMMANDS = ("convert", "export", "simulate", "image", "subtract", "uvstack", "imstack",
            "fit", "noise", "info", "demo")


def _load(name: str) -> Any | None:
    try:
        return importlib.import_module(f"xstack.cli.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"xstack.cli.{name}":
            return None  # stage not built into this version
        raise


def build_parser() -> argparse.ArgumentParser:
    """The top-level argument parser with every available sub-command."""
    from xstack import __version__

    parser = argparse.ArgumentParser(
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
            sp.set_defaults(_run=module.run)
    return parser


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


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: Any = None, line: str | None = None) -> None:
    """Warnings on the command line: one ``warning: ...`` line on stderr, no source line."""
    warn(str(message))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``xstack`` console script."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help(sys.stderr)
        return 2
    args._argv = argv
    warnings.filterwarnings("ignore", category=RuntimeWarning, module="dask")
    shown = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        with session(args):
            try:
                status = args._run(args)
            except XstackError as exc:
                error(str(exc))
                return 1
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
