"""Optional dependencies (pyproject.toml's extras): import one, or say which extra installs it.

The light install (``pip install demq``) runs simulations, the queue and the service; figures need the
``plots`` extra (matplotlib): the cooling plots and snapshot pictures of the service, and the figures of
``demq validate``. Code that needs an extra calls :func:`require`, which raises :class:`MissingExtra` (an
ImportError whose message names the extra) when the package is absent; the service answers it with 501.
"""

from __future__ import annotations

import importlib


class MissingExtra(ImportError):
    """An optional package is not installed; ``extra`` is the pyproject.toml extra that installs it."""

    def __init__(self, package: str, extra: str, what: str):
        self.package, self.extra, self.what = package, extra, what
        super().__init__(f"{what} needs {package}, which is not installed: pip install 'demq[{extra}]' "
                         f"(from a checkout: pip install '.[{extra}]')")


def require(module: str, extra: str, what: str):
    """``importlib.import_module(module)``, or :class:`MissingExtra` naming ``extra`` and what needed it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtra(module.split(".")[0], extra, what) from exc


def require_matplotlib(what: str):
    """matplotlib with its non-interactive Agg backend (no display needed), or :class:`MissingExtra`."""
    mpl = require("matplotlib", "plots", what)
    mpl.use("Agg")
    return mpl
