"""What every ``xstack`` command prints, and where.

One contract for all sub-commands:

* **results** (what was computed and written, the key numbers) go to **stdout** through
  :func:`result`; with ``--json`` the only thing on stdout is one JSON object
  (:func:`xstack.cli.emit_json`) and the human result lines are left out;
* **messages** (what is being done, files written beside the result, timings) go to
  **stderr** through :func:`say` (``-v`` adds the :func:`detail` lines, ``-q`` leaves only
  warnings and errors);
* **warnings** are one ``warning: ...`` line on stderr (:func:`warn`), **errors** one
  ``error: ...`` line (:func:`error`), whatever ``-q`` says;
* **progress bars** only when stderr is a terminal and neither ``-q`` nor ``--no-progress``
  is given;
* ``--log FILE`` appends every message, warning, error and result line (``-v`` detail
  included) to FILE as well.

Figures in human output share one formatter, :func:`figure`: ``16.49 ± 3.18 µJy`` (value
and error to matching decimals, one SI prefix per line), :func:`count` for ``1 position`` /
``2 positions``, and ``µJy/beam`` where a value is per beam.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import IO, Any

from xstack.errors import XstackError

#: Prefixable base units (the rest, e.g. arcsec, are printed as they are).
PREFIXED_UNITS = ("Jy", "Hz", "m", "s", "Jy/beam", "Jy km/s")

#: Prefixes :func:`figure` chooses from: engineering steps of 10^3, n ... G.
_PREFIX_NAMES = ("n", "u", "m", "", "k", "M", "G")


@dataclass
class _State:
    quiet: bool = False
    verbose: bool = False
    json: bool = False
    progress: bool = True
    log: IO[str] | None = None
    own_log: bool = False
    started: float = field(default_factory=time.perf_counter)


_stack: list[_State] = [_State()]


def _now() -> _State:
    return _stack[-1]


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """Add ``-q/--quiet``, ``-v/--verbose``, ``--log FILE`` (and ``--no-progress`` where a
    command has no such option yet) to one sub-command's parser."""
    group = parser.add_argument_group("output")
    verbosity = group.add_mutually_exclusive_group()
    verbosity.add_argument("-q", "--quiet", action="store_true",
                           help="print only results, warnings and errors (no messages, no "
                                "progress bar)")
    verbosity.add_argument("-v", "--verbose", action="store_true",
                           help="print more detail about what is done")
    group.add_argument("--log", metavar="FILE", default=None,
                       help="also append every message, warning, error and result line to FILE")
    if "--no-progress" not in parser._option_string_actions:
        group.add_argument("--no-progress", action="store_true", help="no progress bar")


@contextlib.contextmanager
def session(args: argparse.Namespace) -> Iterator[None]:
    """Output settings of one command run (nested runs, as in ``xstack demo``, inherit the
    enclosing run's ``-q`` and ``--log`` and restore them afterwards)."""
    from xstack import _progress

    parent = _now()
    state = _State(quiet=bool(getattr(args, "quiet", False)) or parent.quiet,
                   verbose=bool(getattr(args, "verbose", False)) or parent.verbose,
                   json=bool(getattr(args, "json", False)),
                   log=parent.log)
    state.progress = (not state.quiet and not getattr(args, "no_progress", False)
                      and parent.progress and _isatty(sys.stderr))
    logname = getattr(args, "log", None)
    if logname:
        try:
            state.log = open(logname, "a", encoding="utf-8")  # noqa: SIM115
        except OSError as exc:
            raise XstackError(f"--log {logname}: cannot be written ({exc.strerror})") from None
        state.own_log = True
    _stack.append(state)
    previous = _progress.set_allowed(state.progress)
    # what the library says on its logger (e.g. where a MeasurementSet was converted to)
    # is a message of this run: on stderr unless -q, and in --log
    handler = _SayHandler()
    library_log = logging.getLogger("xstack")
    library_log.addHandler(handler)
    previous_level = library_log.level
    library_log.setLevel(logging.INFO)
    try:
        _to_log("$ xstack " + " ".join(getattr(args, "_argv", []) or []))
        yield
        detail(f"xstack {getattr(args, 'command', '')}: done in {seconds(elapsed())}")
    finally:
        library_log.removeHandler(handler)
        library_log.setLevel(previous_level)
        _progress.set_allowed(previous)
        _stack.pop()
        if state.own_log and state.log is not None:
            state.log.close()


class _SayHandler(logging.Handler):
    """Library log records (INFO and above, never warnings: those are ``warning:`` lines
    through :mod:`warnings`) as :func:`say` messages."""

    def emit(self, record: logging.LogRecord) -> None:
        say(" ".join(record.getMessage().split()))


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _to_log(line: str) -> None:
    log = _now().log
    if log is not None:
        log.write(line + "\n")
        log.flush()


def progress_enabled() -> bool:
    """Whether this run shows progress bars (a terminal, no ``-q``, no ``--no-progress``)."""
    return _now().progress


def say(*lines: str) -> None:
    """Messages on stderr (not with ``-q``), and to ``--log``."""
    for line in lines:
        _to_log(line)
        if not _now().quiet:
            print(line, file=sys.stderr, flush=True)


def detail(*lines: str) -> None:
    """More detail: on stderr with ``-v`` only; always to ``--log``."""
    for line in lines:
        _to_log(line)
        if _now().verbose and not _now().quiet:
            print(line, file=sys.stderr, flush=True)


def result(*lines: str) -> None:
    """Result lines on stdout (left out with ``--json``: the JSON object carries them)."""
    for line in lines:
        _to_log(line)
        if not _now().json:
            print(line, file=sys.stdout, flush=True)


def warn(text: str) -> None:
    """One ``warning: ...`` line on stderr (also with ``-q``)."""
    line = "warning: " + " ".join(str(text).split())
    _to_log(line)
    print(line, file=sys.stderr, flush=True)


def error(text: str) -> None:
    """One ``error: ...`` line on stderr."""
    line = "error: " + " ".join(str(text).split())
    _to_log(line)
    print(line, file=sys.stderr, flush=True)


def elapsed() -> float:
    """Seconds since this run started."""
    return time.perf_counter() - _now().started


# --- figures ----------------------------------------------------------------------------

def _prefixes() -> list[tuple[str, float]]:
    """(symbol, factor) of the SI prefixes :func:`figure` uses, from astropy.units."""
    from astropy.units.core import si_prefixes

    table = {}
    for symbols, _, factor in si_prefixes:
        for s in symbols:
            table[s] = factor
    table[""] = 1.0
    return [("µ" if p == "u" else p, float(table[p])) for p in _PREFIX_NAMES]


def scale_for(values: Iterable[float], unit: str = "Jy") -> tuple[float, str]:
    """The factor and unit label of one SI prefix for all ``values`` (in ``unit``).

    The prefix puts the largest finite magnitude in [1, 1000); units that take no prefix
    (e.g. ``arcsec``) come back unchanged with factor 1.
    """
    if unit not in PREFIXED_UNITS:
        return 1.0, unit
    finite = [abs(float(v)) for v in values if v is not None and math.isfinite(float(v))]
    big = max(finite, default=0.0)
    if big == 0.0:
        return 1.0, unit
    choices = _prefixes()
    chosen = choices[0]
    for symbol, factor in choices:
        if big / factor >= 1.0 - 1e-12:
            chosen = (symbol, factor)
    return chosen[1], chosen[0] + unit


def _decimals(error: float, digits: int) -> int:
    """Decimals that give ``error`` ``digits`` significant figures (at least 0)."""
    if error == 0 or not math.isfinite(error):
        return 0
    return max(0, digits - 1 - math.floor(math.log10(abs(error))))


def figure(value: float | None, error: float | None = None, unit: str = "Jy", *,
           like: Iterable[float | None] = (), digits: int = 3) -> str:
    """``16.49 ± 3.18 µJy``: a value (and error) in ``unit`` with one SI prefix.

    Parameters
    ----------
    value, error
        In ``unit`` (e.g. Jy). ``None`` or NaN print as ``n/a`` / ``nan``.
    unit
        ``Jy``, ``Jy/beam``, ``Hz``, ``m``, ``s`` take an SI prefix; other units print as they
        are.
    like
        Further values of the same line: the prefix is chosen once for all of them, so every
        figure of a line shares it (pass the same ``like`` to each call).
    digits
        Significant figures of the error (of the value when there is no error); the value is
        printed to the error's decimals.
    """
    if value is None:
        return "n/a"
    factor, label = scale_for([value, *([error] if error is not None else []), *like], unit)
    v = float(value) / factor
    if error is None:
        if not math.isfinite(v):
            return f"{v} {label}"
        dec = _decimals(v, digits) if v != 0 else digits - 1
        return f"{v:.{dec}f} {label}"
    e = float(error) / factor
    dec = _decimals(e, digits)
    if not math.isfinite(e) or e == 0:
        dec = _decimals(v, digits + 1) if math.isfinite(v) and v != 0 else 2
    vs = f"{v:.{dec}f}" if math.isfinite(v) else str(v)
    es = f"{e:.{dec}f}" if math.isfinite(e) else str(e)
    return f"{vs} ± {es} {label}"


def count(n: int, noun: str, plural: str | None = None) -> str:
    """``1 position``, ``2 positions``, ``1,260 visibilities``."""
    n = int(n)
    word = noun if n == 1 else (plural or _plural(noun))
    return f"{n:,} {word}"


def _plural(noun: str) -> str:
    if noun.endswith("y") and noun[-2:-1] not in "aeiou":
        return noun[:-1] + "ies"
    if noun.endswith(("s", "x", "ch", "sh")):
        return noun + "es"
    return noun + "s"


def seconds(s: float) -> str:
    """``3.2 s``, ``2 min 5 s``."""
    if s < 60:
        return f"{s:.1f} s"
    m, r = divmod(int(round(s)), 60)
    return f"{m} min {r} s"
