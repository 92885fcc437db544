"""The optional extras in tests: whether the ``plots`` extra (matplotlib) is installed, and what a figure route
answers with it (a PNG) and without it (501 naming the extra). Tests that need a real figure skip without
matplotlib and are marked heavy (.ci/run's second stage installs the extras and runs them). Whether the
``postgres`` extra (the psycopg driver) is installed: the PostgreSQL tests (marked postgres) need it, see
tests/jobs/conftest.py."""

from __future__ import annotations

import importlib.util

import pytest

HAVE_PLOTS = importlib.util.find_spec("matplotlib") is not None
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
NO_PLOTS = "pip install 'demq[plots]'"
HAVE_POSTGRES_DRIVER = importlib.util.find_spec("psycopg") is not None
NO_POSTGRES = "pip install 'demq[postgres]'"


#: Marks a test that needs matplotlib: skipped without it (before its fixtures run).
needs_plots = pytest.mark.skipif(not HAVE_PLOTS, reason="matplotlib (pip install '.[plots]')")


def assert_figure(r, min_bytes: int = 0) -> None:
    """A figure route's answer: a PNG of at least ``min_bytes`` with matplotlib, else 501 naming the extra."""
    if HAVE_PLOTS:
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == "image/png" and r.content[:8] == PNG_MAGIC and len(r.content) > min_bytes
    else:
        assert r.status_code == 501, r.text
        assert NO_PLOTS in r.json()["detail"]


def hide_matplotlib(monkeypatch) -> None:
    """Make ``import matplotlib`` (and its submodules the code imports) fail, as without the plots extra."""
    import sys

    for name in ("matplotlib", "matplotlib.figure", "matplotlib.pyplot"):
        monkeypatch.setitem(sys.modules, name, None)


def figure_or_missing_extra():
    """Around code that ends by drawing a figure: nothing with matplotlib; without it, expect the
    MissingExtra that names the extra (what the code wrote before the figure can still be checked)."""
    import contextlib

    from engine.optional import MissingExtra

    return contextlib.nullcontext() if HAVE_PLOTS else pytest.raises(MissingExtra, match=r"demq\[plots\]")


def hide_psycopg(monkeypatch) -> None:
    """Make ``import psycopg`` fail, as without the postgres extra."""
    import sys

    monkeypatch.setitem(sys.modules, "psycopg", None)
