"""The documentation site builds with warnings as errors, and its references are complete.

Builds ``docs/`` with Sphinx (the ``docs`` extra) into a temporary directory, once for the
module (12 s on an idle 2-core machine, 40 s while other jobs ran; ``XSTACK_DOCS_HTML=DIR``
checks an already built site instead), and checks the built HTML against the code itself: every name of
``xstack.__all__`` is a documented object of the API page, every sub-command of the parser
has its section on the command-line page, every Markdown page of ``docs/`` is in the site.
Skipped where Sphinx is not installed.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("sphinx")
pytest.importorskip("myst_parser")
pytest.importorskip("numpydoc")

import xstack  # noqa: E402
from xstack.cli import build_parser  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    # CI builds the site once with the README's command and points the checks at it
    built = os.environ.get("XSTACK_DOCS_HTML")
    if built:
        assert (Path(built) / "index.html").is_file(), built
        return Path(built)
    out = tmp_path_factory.mktemp("site")
    # -W: a warning fails the build, as in CI; doctrees outside the checkout
    run = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
         "-d", str(out / "doctrees"), str(DOCS), str(out / "html")],
        capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-4000:]
    return out / "html"


def _ids(page: Path) -> set[str]:
    return set(re.findall(r'id="([^"]+)"', page.read_text(encoding="utf-8")))


def test_api_page_documents_every_public_name(site):
    ids = _ids(site / "api.html")
    missing = [name for name in xstack.__all__ if f"xstack.{name}" not in ids]
    assert not missing, f"not documented on the API page: {missing}"
    # each documented object carries its docstring: the first line of stack_uv's is there
    text = (site / "api.html").read_text(encoding="utf-8")
    first = xstack.stack_uv.__doc__.strip().splitlines()[0].split("(")[0].strip()
    assert first[:40] in re.sub(r"<[^>]+>", "", text)


def test_api_page_documents_results_and_options(site):
    ids = _ids(site / "api.html")
    for dotted in ("xstack._result.Result", "xstack.uvstack.stack.StackResult",
                   "xstack.imstack.stack.ImstackResult", "xstack.fit.result.FitResult",
                   "xstack.noise.estimate.NoiseResult", "xstack.imaging.image.ImageResult",
                   "xstack.imaging.clean.CleanResult", "xstack.sim.simulate.SimulationResult"):
        assert dotted in ids, dotted
    # the options dataclasses, wherever they are defined (found independently of conf.py)
    import xstack.fit.imfit
    import xstack.fit.uvfit
    import xstack.imstack.stack
    import xstack.noise.estimate
    import xstack.uvstack.stack

    options = [f"{m.__name__}.{n}" for m in (xstack.uvstack.stack, xstack.imstack.stack,
                                              xstack.noise.estimate, xstack.fit.imfit,
                                              xstack.fit.uvfit)
               for n, obj in vars(m).items()
               if n.endswith("Options") and isinstance(obj, type) and obj.__module__ == m.__name__]
    for dotted in options:
        public = f"xstack.{dotted.rsplit('.', 1)[1]}"
        assert dotted in ids or public in ids, dotted


def test_cli_page_lists_every_command(site):
    ids = _ids(site / "cli.html")
    top = build_parser()
    (sub,) = [a for a in top._actions if isinstance(a, argparse._SubParsersAction)]
    assert len(sub.choices) >= 10
    missing = [name for name in sub.choices if f"xstack-{name}" not in ids]
    assert not missing, f"no section on the command-line page: {missing}"


def test_every_page_is_in_the_site(site):
    pages = [p.relative_to(DOCS).with_suffix(".html") for p in DOCS.rglob("*.md")
             if "_build" not in p.parts]
    assert Path("getting-started.html") in pages and Path("index.html") in pages
    assert [p for p in pages if not (site / p).is_file()] == []
    # the landing page links the getting-started page, the tutorial and both references
    index = (site / "index.html").read_text(encoding="utf-8")
    for page in ("getting-started.html", "tutorial.html", "cli.html", "api.html"):
        assert f'href="{page}"' in index, page


def test_absolute_values_are_not_substitutions():
    """``|x|`` in a docstring is an absolute value: escaped for reST, except in literals."""
    spec = importlib.util.spec_from_file_location("xstack_docs_conf", DOCS / "conf.py")
    conf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conf)
    lines = ["Largest |residual| inside", "pair (|dx|, |dy|) in arcsec", "``|x|`` stays",
             "| a | b |", "a || b"]
    conf._absolute_values(None, "function", "f", None, {}, lines)
    assert lines == [r"Largest \|residual\| inside", r"pair (\|dx\|, \|dy\|) in arcsec",
                     "``|x|`` stays", "| a | b |", "a || b"]


def test_landing_page_lists_pages_no_toctree_names():
    """A page added to ``docs/`` without editing index.md still enters the site, once."""
    spec = importlib.util.spec_from_file_location("xstack_docs_conf", DOCS / "conf.py")
    conf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conf)

    class App:
        class env:  # noqa: N801 - stands in for Sphinx's environment
            found_docs = {"index", "api", "cli", "bench/a", "bench/b", "new-page"}

    source = ["# x\n\n```{toctree}\n:glob:\n\napi\nxstack-other-pages\nbench/*\n```\n\n"
              "```{toctree}\n\ncli\n```\n"]
    conf._other_pages(App, "index", source)
    assert source[0] == ("# x\n\n```{toctree}\n:glob:\n\napi\nnew-page\nbench/*\n```\n\n"
                         "```{toctree}\n\ncli\n```\n")
