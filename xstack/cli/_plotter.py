"""Draw a command's PNG in a second Python process that imported matplotlib while the command
computed.

Importing matplotlib (and astropy's tables, which a profile plot takes) costs ~1 s of one
core, and the command line pays it after its stack, when the picture's data exist. The
command's own start-up (imports, opening the store, planning) runs on one core; a child
process started first does those imports on the other, then waits for its figure: the
picture costs its rendering, not its imports. Measured in
``benchmarks/bench_uvstack_cli.py`` (docs/benchmarks.md, "What the command line pays for its
store").

The child only renders: it gets a ``module:function`` that returns a matplotlib Figure and
its arguments (pickled), and sends the PNG's bytes back. The command writes them itself
(atomically, at a local path or a URL with its own storage options), so the child needs no
access to the outputs. If the child cannot start or fails, the figure is drawn in the
command's own process instead: the output is the same, only the time differs.
"""

from __future__ import annotations

import importlib
import io
import pickle
import subprocess
import sys
from collections.abc import Sequence
from typing import Any

# runs in the child: sys.path and the modules to import first (message 1), then the job
# (message 2); the PNG's bytes on stdout, one "error: ..." line on stderr on failure
_CHILD = r"""
import importlib, pickle, sys
inp, out = sys.stdin.buffer, sys.stdout.buffer
path, preload = pickle.load(inp)
sys.path[:] = path
import matplotlib
matplotlib.use("Agg")
for name in preload:
    importlib.import_module(name)
try:
    job = pickle.load(inp)
except EOFError:  # the command ended without a picture
    sys.exit(0)
try:
    from xstack.cli._plotter import render_png
    out.write(render_png(*job))
except Exception as exc:
    sys.stderr.write(f"error: {type(exc).__name__}: {exc}\n")
    sys.exit(1)
"""


def render_png(target: str, args: Sequence[Any], kwargs: dict[str, Any]) -> bytes:
    """The PNG bytes of the Figure that ``module:function`` ``target`` returns for the arguments."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    module, _, name = target.partition(":")
    fig = getattr(importlib.import_module(module), name)(*args, **kwargs)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


class BackgroundPlotter:
    """A child process that imports ``preload`` now and renders one figure later.

    Parameters
    ----------
    preload
        Modules the child imports while the command computes (matplotlib's Figure and Agg
        canvas are always imported).

    Use as a context manager; :meth:`render` returns the PNG's bytes. Leaving the block without
    rendering ends the child.
    """

    def __init__(self, preload: Sequence[str] = ()) -> None:
        self._proc: subprocess.Popen[bytes] | None = None
        modules = ["matplotlib.figure", "matplotlib.backends.backend_agg", *preload]
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-c", _CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                stderr=subprocess.PIPE)
            assert self._proc.stdin is not None
            pickle.dump((list(sys.path), modules), self._proc.stdin)
            self._proc.stdin.flush()
        except (OSError, ValueError):  # no child: render() draws in this process
            self.close()

    def render(self, target: str, *args: Any, **kwargs: Any) -> bytes:
        """The PNG bytes of ``module:function(*args, **kwargs)`` (a matplotlib Figure)."""
        proc, self._proc = self._proc, None
        if proc is not None:
            try:
                data = pickle.dumps((target, args, kwargs))
                out, err = proc.communicate(data)
                if proc.returncode == 0 and out:
                    return out
            except (OSError, ValueError, pickle.PicklingError):
                proc.kill()
                proc.wait()
        return render_png(target, args, kwargs)  # the same figure, drawn here

    def close(self) -> None:
        """End the child if it is still waiting (no figure is made; it writes no file)."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()

    def __enter__(self) -> BackgroundPlotter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
