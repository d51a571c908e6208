"""Optional dependencies: which ``pip install 'omnispectral[EXTRA]'`` brings a module that is not installed.

The core (processing, exports, the simulator) needs only the dependencies in ``pyproject.toml``'s
``dependencies``; rendering (Mitsuba 3), real GenICam cameras (harvesters, genicam), the Dask cluster
scheduler (distributed) and the web viewer (Starlette, uvicorn) are extras.  Code that needs one imports it
where it is used; a missing one surfaces as ``ModuleNotFoundError``, which :func:`missing_extra_message` turns
into one line naming the extra (the command line prints it, exit 1).
"""

from __future__ import annotations

__all__ = ["EXTRAS", "missing_extra_message"]

#: Top-level module name → the extra of ``pyproject.toml`` that installs it.
EXTRAS = {
    "mitsuba": "render",
    "drjit": "render",
    "harvesters": "devices",
    "genicam": "devices",
    "distributed": "cluster",
    "starlette": "view",
    "uvicorn": "view",
}


def missing_extra_message(exc: ModuleNotFoundError) -> str | None:
    """One line for a missing optional module (``None`` when ``exc`` is not about one of :data:`EXTRAS`).

    Parameters
    ----------
    exc : ModuleNotFoundError
        The error an import raised.

    Returns
    -------
    str or None
        E.g. ``"this needs the optional module mitsuba: pip install 'omnispectral[render]'"``.
    """
    root = (exc.name or "").split(".")[0]
    extra = EXTRAS.get(root)
    if extra is None:
        return None
    return f"this needs the optional module {root}: pip install 'omnispectral[{extra}]'"
