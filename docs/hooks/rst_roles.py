"""MkDocs hook: the docstrings' Sphinx roles (``:class:`X```, ``:meth:`X.y```) as plain code.

The docstrings are numpydoc, written for ``help()`` and Sphinx alike; mkdocstrings renders
``:class:`X``` as the literal text ``:class:`` before ``X`` in code. This drops the role marker and
keeps the code (no cross-reference: many of the names are relative to their module)."""
import re

ROLE = re.compile(r":(?:func|class|meth|mod|attr|data|obj|exc|math):(?=<code)")


def on_page_content(html, page, config, files):
    return ROLE.sub("", html)
