"""Rig calibration from a session's own images, end to end (``omnispectral calibrate rig SESSION -o FILE``).

The steps, each in its module:

1. merge the session's HDR brackets (Hirai et al. 2018, Sec. 4.1; :func:`~omnispectral.product.merge.merge_session`);
2. per direction, block correspondences between camera A and camera B
   (:func:`~omnispectral.product.rigmeasure.measure_direction`, directions in parallel threads);
3. camera B's rotation change fitted to all of them together
   (:func:`~omnispectral.product.rigfit.fit_b_mounting`);
4. the result written as a rig calibration file (:class:`~omnispectral.product.rigfile.RigCalibration`)
   for ``process --rig-calibration``.

``process`` runs steps 2 and 3 on its own merged directions (:func:`calibrate_from_merged`) when it has no
better calibration (:mod:`omnispectral.product.rigsource`).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from omnispectral.capture.session import Session
from omnispectral.errors import InputFileError
from omnispectral.product.merge import merge_session
from omnispectral.product.rigfile import RigCalibration
from omnispectral.product.rigfit import fit_b_mounting
from omnispectral.product.rigmeasure import RigMeasurements, measure_direction
from omnispectral.progress import ProgressCallback, report_progress
from omnispectral.threads import ordered_thread_map

__all__ = ["calibrate_from_merged", "calibrate_session"]


def calibrate_from_merged(merged, progress: ProgressCallback | None = None) -> RigCalibration:
    """Rig calibration from a merged-directions directory (every direction's A and B images).

    Parameters
    ----------
    merged
        :class:`~omnispectral.mosaic.sources.MergedDirections` with cameras ``"A"`` and ``"B"``.
    progress
        ``progress("measure", done, total)`` after each direction measured, or ``None``.

    Returns
    -------
    RigCalibration
        The scene fit (:func:`~omnispectral.product.rigfit.fit_b_mounting`) of the directions that have
        both cameras' images.
    """
    model_a, model_b = merged.cameras["A"], merged.cameras["B"]
    meas = RigMeasurements.empty()
    sources = {(s.direction, s.camera): s for s in merged.sources()}
    dirs = [d for d in sorted({d for d, _ in sources}) if (d, "A") in sources and (d, "B") in sources]

    def measure(d: int) -> RigMeasurements:
        return measure_direction(d, sources[(d, "A")].read(), sources[(d, "B")].read(), model_a, model_b)

    for i, m in enumerate(ordered_thread_map(measure, dirs)):
        meas.extend(m)
        report_progress(progress, "measure", i + 1, len(dirs))
    return fit_b_mounting(meas, model_a, model_b, rig_name=merged.meta.get("rig", {}).get("name", ""))


def calibrate_session(session: str | Path, output: str | Path, work_dir: str | Path | None = None,
                      progress: ProgressCallback | None = None) -> RigCalibration:
    """Merge a session's brackets and fit camera B's mounting from them; saved for ``process --rig-calibration``.

    Parameters
    ----------
    session
        The session directory (two cameras).
    output
        The rig calibration file to write (JSON).
    work_dir
        Where the merged directions go (default: a temporary directory, removed afterwards).
    progress
        ``progress(stage, done, total)`` with stage ``"merge"`` or ``"measure"``, or ``None``.

    Returns
    -------
    RigCalibration
        The calibration written, ``source`` the session's absolute path.

    Raises
    ------
    InputFileError
        A one-camera session.
    """
    if "B" not in Session.open(session).cameras():
        raise InputFileError(session, "a one-camera session (three bands): there is no camera B to calibrate")
    with tempfile.TemporaryDirectory(prefix="omnispectral-rigcal-") as tmp:
        merged = merge_session(session, Path(work_dir) if work_dir else Path(tmp) / "merged", progress=progress)
        cal = calibrate_from_merged(merged, progress)
    cal.source = str(Path(session).resolve())
    cal.save(output)
    return cal
