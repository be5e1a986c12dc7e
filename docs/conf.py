"""Sphinx configuration of the xstack documentation site.

Build it (the ``docs`` extra installs Sphinx, myst-parser and numpydoc)::

    pip install -e '.[docs]' && sphinx-build -W -b html docs docs/_build/html

The pages are the Markdown files of ``docs/`` as they are (myst-parser); the command
reference is ``docs/cli.md``, generated from the argument parsers by ``python -m
xstack.cli.docs``; the API reference (``docs/api.md``) is generated from the docstrings
(autodoc + numpydoc). The build needs no network: no intersphinx inventories are fetched.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import importlib
import pkgutil
import re
import sys
from pathlib import Path

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective

# the checkout's package, also when it is not installed (e.g. building from a fresh clone)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import xstack  # noqa: E402

project = "xstack"
author = "the xstack developers"
copyright = "2026, the xstack developers"
release = version = xstack.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "numpydoc",
]

# .rst only because numpydoc loads autosummary, which asks for it; every page is Markdown
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "records"]  # realisation lines (and any report made there)

# Markdown: `$...$` maths as in the pages, heading anchors for the `page.md#section` links
# the pages use between each other.
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 4

# numpydoc renders the numpy-style sections; autodoc lists the members itself (no autosummary
# stub pages, which would need a generated tree of files).
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_default_options = {"show-inheritance": True}
# Type hints name third-party classes (xarray, numpy, astropy) that no inventory resolves
# offline; they render as plain text.
nitpicky = False

html_theme = "alabaster"
html_title = f"xstack {release}"
html_static_path: list[str] = []


def _options_classes() -> list[str]:
    """Dotted names of the options dataclasses (``UvstackOptions``, ``ImstackOptions``,
    ...), wherever in the package they are defined: found by import, so the page lists them
    as soon as they exist without naming modules that may not be there yet. A class that is
    also in ``xstack.__all__`` is documented under that public name."""
    found: dict[int, str] = {}
    for name in xstack.__all__:
        if name.endswith("Options"):
            try:
                found[id(getattr(xstack, name))] = f"xstack.{name}"
            except AttributeError:
                continue
    for info in pkgutil.walk_packages(xstack.__path__, "xstack."):
        # the command-line modules and the test helpers hold no public options classes, and
        # importing a __main__ would run the command line
        if info.name.startswith(("xstack.cli", "xstack.testing")) or info.name.endswith("__main__"):
            continue
        try:
            module = importlib.import_module(info.name)
        except Exception:  # a module with an optional dependency missing: nothing to list
            continue
        for attr, obj in vars(module).items():
            if (isinstance(obj, type) and attr.endswith("Options") and not attr.startswith("_")
                    and dataclasses.is_dataclass(obj) and obj.__module__ == info.name):
                found.setdefault(id(obj), f"{info.name}.{attr}")
    return sorted(found.values())


class OptionsClasses(SphinxDirective):
    """``{xstack-options}``: autodoc of every options dataclass that can be imported."""

    def run(self) -> list[nodes.Node]:
        names = _options_classes()
        if not names:
            para = nodes.paragraph(text="No options classes are defined in this version.")
            return [para]
        # the directive is used in Markdown pages: its content is parsed as MyST, and autodoc's
        # output is reST, so it goes through an eval-rst block
        lines = ["```{eval-rst}"]
        for dotted in names:
            lines += [f".. autoclass:: {dotted}", "   :members:", ""]
        lines.append("```")
        node = nodes.container()
        self.state.nested_parse(StringList(lines, source="xstack-options"), self.content_offset, node)
        return node.children


class RemainingApi(SphinxDirective):
    """``{xstack-remaining-api}``: autodoc of every name of ``xstack.__all__`` that the page
    has not documented above it, so a name added to the package is never missing from the
    reference."""

    def run(self) -> list[nodes.Node]:
        documented = self.env.get_domain("py").objects
        lines: list[str] = []
        for name in xstack.__all__:
            if f"xstack.{name}" in documented or name == "__version__":
                continue
            obj = getattr(xstack, name)
            kind = "autoclass" if isinstance(obj, type) else "autofunction"
            lines += [f".. {kind}:: xstack.{name}", ""]
        if not lines:
            return []
        lines = ["```{eval-rst}", *lines, "```"]  # as in OptionsClasses
        node = nodes.container()
        self.state.nested_parse(StringList(lines, source="xstack-remaining-api"), self.content_offset,
                                node)
        return node.children


_ABS = re.compile(r"(?<![\\`|])\|(\w[^|`]*?)\|(?![`|])")
_LITERAL = re.compile(r"(``.*?``)")


def _absolute_values(app, what, name, obj, options, lines: list[str]) -> None:
    """Escape ``|x|`` (an absolute value in a docstring) so reST does not read it as a
    substitution reference, which would fail the build; inline literals are left as they are.
    xstack's docstrings use no substitutions."""
    for i, line in enumerate(lines):
        parts = _LITERAL.split(line)
        lines[i] = "".join(part if part.startswith("``") else _ABS.sub(r"\\|\1\\|", part)
                           for part in parts)


#: line of a toctree in index.md that becomes every page no toctree of index.md names
OTHER_PAGES = "xstack-other-pages"


def _other_pages(app, docname: str, source: list[str]) -> None:
    """Fill the ``xstack-other-pages`` entry of the landing page's toctrees with the pages
    that none of its entries names (e.g. a page added by a later change), so every page of
    ``docs/`` is in the site without a glob that would list the named ones twice."""
    if docname != root_doc or OTHER_PAGES not in source[0]:
        return
    entries: list[str] = []
    for block in re.findall(r"```\{toctree\}\n(.*?)```", source[0], re.S):
        entries += [line.strip() for line in block.splitlines()
                    if line.strip() and not line.startswith(":") and line.strip() != OTHER_PAGES]
    named = {doc for doc in app.env.found_docs if any(fnmatch.fnmatchcase(doc, e) for e in entries)}
    others = sorted(app.env.found_docs - named - {root_doc})
    source[0] = source[0].replace(OTHER_PAGES + "\n", "".join(f"{doc}\n" for doc in others))


def _reread_index(app, env, added, changed, removed) -> list[str]:
    # the landing page's toctree depends on which pages exist, not only on its own text
    return [root_doc]


def setup(app):  # noqa: D103 - Sphinx's hook
    app.connect("source-read", _other_pages)
    app.connect("env-get-outdated", _reread_index)
    # before numpydoc (priority 500) rewrites the docstring into reST
    app.connect("autodoc-process-docstring", _absolute_values, priority=400)
    app.add_directive("xstack-options", OptionsClasses)
    app.add_directive("xstack-remaining-api", RemainingApi)
