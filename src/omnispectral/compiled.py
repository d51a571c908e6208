"""Compiled kernels built on first use: Numba is imported then, not when the modules that hold them are.

Importing Numba and loading (or, once per environment, compiling) a kernel costs ~0.3-2 s, which a
command that does not run the kernel (``--help``, a listing) should not pay.  Without Numba the builders
give ``None`` and their callers run their NumPy definitions.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

__all__ = ["built_on_first_use"]


def built_on_first_use(build: Callable[[Any], Any]) -> Callable[[], Any]:
    """Decorator: ``build(numba)`` runs on the first call of the decorated function, whose later calls return
    the same result; ``None`` (and ``build`` never runs) when Numba is not installed.

    Parameters
    ----------
    build : callable
        ``build(numba) -> kernels``: defines (``numba.njit``) and returns the kernels.

    Returns
    -------
    callable
        ``() -> kernels or None``.
    """
    built: dict = {}

    @functools.wraps(build)
    def kernels():
        if "kernels" not in built:
            try:
                import numba
            except ImportError:  # pragma: no cover - numba is a dependency; the NumPy paths stay correct
                built["kernels"] = None
            else:
                built["kernels"] = build(numba)
        return built["kernels"]

    return kernels
