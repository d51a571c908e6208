"""The one progress-callback type of the library's long calls, and helpers to pass it on.

A long library call (a capture, a merge, a mosaic, a whole ``process`` run, a rendering) takes an optional
``progress`` argument of type :data:`ProgressCallback` and calls it as work advances::

    progress(stage, done, total)

``stage`` names what advances (``"merge"``, ``"tiles"``, ``"pyramid"``, ``"capture"``, …: a stable label, one
progress bar per stage), ``done`` is how many of its ``total`` units are finished (``0 <= done <= total``).
The command line draws it (``omnispectral.cli._common.ProgressBars`` is one); ``None`` reports nothing.

This is a base module: it imports nothing else of the package.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["ProgressCallback", "optional_progress", "report_progress", "under_stage"]

#: ``progress(stage, done, total)``: how far a named stage of a long call is (stage label, units done, units in all).
ProgressCallback = Callable[[str, int, int], None]


def optional_progress(progress: ProgressCallback | bool | None) -> ProgressCallback | None:
    """``progress`` itself, or ``None`` for "no progress" (``None`` or ``False``, which callers may pass too).

    Parameters
    ----------
    progress
        A :data:`ProgressCallback`, ``None`` or ``False``.

    Returns
    -------
    ProgressCallback or None
        The callback to call, or ``None`` when nothing is to be reported.
    """
    return progress or None


def report_progress(progress: ProgressCallback | None, stage: str, done: int, total: int) -> None:
    """Call ``progress(stage, done, total)`` unless ``progress`` is ``None``.

    Parameters
    ----------
    progress
        The callback, or ``None``.
    stage
        The stage's label.
    done, total
        Units finished, units in all.
    """
    if progress is not None:
        progress(stage, done, total)


def under_stage(progress: ProgressCallback | None, stage: str) -> ProgressCallback | None:
    """A callback that passes every report on to ``progress`` under the label ``stage`` (``None`` for ``None``).

    For a caller that runs a library call as one of its own stages under another name (``process`` reports
    the merge of the paper's registration as ``"merge + register"``).

    Parameters
    ----------
    progress
        The callback to report to, or ``None``.
    stage
        The label every report is given.

    Returns
    -------
    ProgressCallback or None
        ``lambda _stage, done, total: progress(stage, done, total)``, or ``None``.
    """
    if progress is None:
        return None
    return lambda _stage, done, total: progress(stage, done, total)
