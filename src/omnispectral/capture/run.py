"""The capture loop: for each planned direction, move, settle, bracket both cameras, write every frame.

The same loop runs real and simulated devices.  It resumes a session after its last complete frame,
retries a device that does not answer or reports a position off target a bounded number of times,
and otherwise stops cleanly (an event with the reason is logged; the session stays valid and can be
resumed).  Progress is reported per frame to a callback ``progress("capture", done, total)``.

Sun bracket (a rig with a ``[sun]`` table): after a direction's regular bracket, when camera A's shortest
exposure clips (:func:`clips`), the filter changer puts the plan's neutral-density filter in front of both
lenses and the loop shoots the attenuated bracket, exposure indices from ``SUN_EXPOSURE_BASE`` with
``"filter"`` in their journal records; an event ``sun`` names the direction.  Once a sun bracket holds the
sun whole (:func:`sun_image_complete`: unclipped, away from the frame's edges) later directions need none.
A resumed run finishes a started sun bracket and decides again, from the stored frames, for the rest.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from omnispectral.capture.devices import Camera, Clock, DeviceError, DeviceTimeout, FilterChanger, PanTiltHead
from omnispectral.capture.plan import SUN_EDGE_MARGIN, Direction, Plan
from omnispectral.capture.session import Session
from omnispectral.errors import OmnispectralError
from omnispectral.io import clean_temp_files
from omnispectral.locking import directory_lock
from omnispectral.rig import SUN_EXPOSURE_BASE


@dataclass
class CaptureResult:
    """What a capture run did."""

    session: str
    n_planned: int
    n_written: int
    n_already_done: int
    complete: bool
    stopped_reason: str | None
    simulated_s: float
    wall_s: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class RetryPolicy:
    """How patient the loop is with devices."""

    retries: int = 3
    timeout_s: float = 30.0
    tolerance_deg: float = 0.05


def goto_direction(head: PanTiltHead, d: Direction, policy: RetryPolicy) -> tuple[float, float]:
    """Command the head to a direction and wait until it reports arriving there (bounded retries)."""
    problem = ""
    for _ in range(policy.retries + 1):
        try:
            head.move_to(d.pan_deg, d.tilt_deg)
            pan, tilt = head.wait_settled(policy.timeout_s)
        except DeviceTimeout as exc:
            problem = str(exc)
            continue
        err = max(abs(pan - d.pan_deg), abs(tilt - d.tilt_deg))
        if err <= policy.tolerance_deg:
            return pan, tilt
        problem = (f"reported pan {pan:.3f} deg, tilt {tilt:.3f} deg is {err:.3f} deg off target "
                   f"(tolerance {policy.tolerance_deg} deg)")
    raise DeviceError(f"head could not reach direction {d.index} (pan {d.pan_deg:.3f} deg, tilt {d.tilt_deg:.3f} deg)"
                      f" after {policy.retries + 1} attempts: {problem}")


def expose_all(cameras: dict[str, Camera], names: list[str], exposure_s: float, policy: RetryPolicy) -> dict:
    """Set the exposure on the named cameras, trigger them together, read every frame (bounded retries)."""
    for n in names:
        cameras[n].set_exposure(exposure_s)
    for n in names:
        cameras[n].trigger()
    frames = {}
    for n in names:
        problem = ""
        for attempt in range(policy.retries + 1):
            try:
                frames[n] = cameras[n].read_frame(policy.timeout_s)
                break
            except DeviceTimeout as exc:
                problem = str(exc)
                if attempt < policy.retries:
                    cameras[n].trigger()
        else:
            raise DeviceError(f"camera {n}: no frame after {policy.retries + 1} attempts: {problem}")
    return frames


def clips(frame: np.ndarray, bit_depth: int, clip_fraction: float, min_pixels: int) -> bool:
    """Whether at least ``min_pixels`` pixels of a raw frame reach ``clip_fraction`` of the maximum code."""
    level = clip_fraction * ((1 << int(bit_depth)) - 1)
    peak = frame if frame.ndim == 2 else frame.max(axis=2)
    return int(np.count_nonzero(peak >= level)) >= int(min_pixels)


def sun_image_complete(frame: np.ndarray, bit_depth: int, clip_fraction: float) -> bool:
    """Whether an attenuated frame holds the sun whole: its brightest pixel is not clipped and lies at least
    ``SUN_EDGE_MARGIN`` of the frame (and 8 px) inside every edge."""
    peak = frame if frame.ndim == 2 else frame.max(axis=2)
    r, c = np.unravel_index(int(np.argmax(peak)), peak.shape)
    h, w = peak.shape
    margin_r, margin_c = max(8, SUN_EDGE_MARGIN * h), max(8, SUN_EDGE_MARGIN * w)
    inside = margin_r <= r < h - margin_r and margin_c <= c < w - margin_c
    return bool(inside and peak[r, c] < clip_fraction * ((1 << int(bit_depth)) - 1))


def sun_already_whole(session: Session, plan: Plan, done: set) -> bool:
    """Whether an earlier sun bracket of this capture (read back from its frames) holds the sun whole: later
    directions then need none."""
    sun = plan.sun_bracket
    k = SUN_EXPOSURE_BASE + int(np.argmin(sun["exposures_s"]))
    for d in sorted({key[0] for key in done if key[1] == "A" and key[2] == k}):
        try:
            frame, meta = session.read_frame(d, "A", k)
        except OmnispectralError:
            continue
        if sun_image_complete(np.asarray(frame), int(meta.get("bit_depth", 12)), float(sun["clip_fraction"])):
            return True
    return False


def direction_holds_sun(session: Session, plan: Plan, direction: int, done: set, fresh: dict | None) -> bool:
    """Whether ``direction`` needs the sun bracket: one was started, or camera A's shortest exposure clips
    (``fresh``: the frames just read, by camera, else the stored frame is read back)."""
    sun = plan.sun_bracket
    if any((direction, c, SUN_EXPOSURE_BASE + k) in done for c in ("A", "B") for k in range(len(sun["exposures_s"]))):
        return True
    k_short = int(np.argmin(plan.exposures_s))
    if fresh is not None and "A" in fresh:
        frame, bit_depth = fresh["A"]
    else:
        try:
            frame, meta = session.read_frame(direction, "A", k_short)
        except OmnispectralError:
            return False  # a missing or damaged frame: session verify names it
        bit_depth = int(meta.get("bit_depth", 12)) if isinstance(meta, dict) else 12
    return clips(np.asarray(frame), bit_depth, float(sun["clip_fraction"]), int(sun["min_clipped_px"]))


def run_capture(session: Session, head: PanTiltHead, cameras: dict[str, Camera], clock: Clock,
                policy: RetryPolicy | None = None,
                progress: Callable[[str, int, int], None] | None = None,
                filters: FilterChanger | None = None) -> CaptureResult:
    """Capture (or resume) every planned frame of ``session`` with the given devices; ``progress(stage, done,
    total)`` is called after every frame written.  ``filters`` moves the sun bracket's neutral-density filter
    (module docstring); without it, or without a sun bracket in the plan, the sun stays clipped.

    Holds the session's lock (:mod:`omnispectral.locking`) for the whole run: a second run on the same
    session is refused; temporary files a killed run left are removed first.
    """
    with directory_lock(session.path, "capture"):
        clean_temp_files(session.path)
        return _run_capture_locked(session, head, cameras, clock, policy, progress, filters)


def shoot_sun_bracket(session: Session, plan: Plan, d: Direction, cameras: dict[str, Camera], names_all,
                      filters: FilterChanger, policy: RetryPolicy, pose: tuple[float, float], clock: Clock,
                      done: set, on_frame: Callable[[], None]) -> int:
    """The attenuated bracket of one direction (module docstring); returns the frames written."""
    sun = plan.sun_bracket
    keys = [(c, k) for k in range(len(sun["exposures_s"])) for c in names_all
            if (d.index, c, SUN_EXPOSURE_BASE + k) not in done]
    if not keys:
        return 0
    if len(keys) == len(sun["exposures_s"]) * len(names_all):
        session.log_event("sun", direction=d.index, filter=sun["filter"])
    written = 0
    filters.insert(sun["filter"])
    try:
        for k, exposure in enumerate(sun["exposures_s"]):
            index = SUN_EXPOSURE_BASE + k
            names = [c for c in names_all if (d.index, c, index) not in done]
            if not names:
                continue
            frames = expose_all(cameras, names, exposure, policy)
            for c in names:
                data, meta = frames[c]
                session.write_frame(data, direction=d.index, camera=c, exposure_index=index, exposure_s=exposure,
                                    pan_deg_commanded=d.pan_deg, tilt_deg_commanded=d.tilt_deg,
                                    pan_deg_reported=pose[0], tilt_deg_reported=pose[1],
                                    timestamp=clock.now().isoformat(timespec="milliseconds"),
                                    bit_depth=cameras[c].bit_depth,
                                    extra={"camera_metadata": meta, "filter": sun["filter"]})
                done.add((d.index, c, index))
                written += 1
                on_frame()
    finally:
        filters.remove()
    return written


def _run_capture_locked(session: Session, head: PanTiltHead, cameras: dict[str, Camera], clock: Clock,
                        policy: RetryPolicy | None,
                        progress: Callable[[str, int, int], None] | None,
                        filters: FilterChanger | None = None) -> CaptureResult:
    policy = policy or RetryPolicy()
    plan = session.plan()
    cut = session.repair_journal()
    done = set(session.completed())
    names_all = session.cameras()
    n_sun = len(plan.sun_bracket["exposures_s"]) * len(names_all) if plan.sun_bracket else 0
    sun_dirs = {k[0] for k in done if k[2] >= SUN_EXPOSURE_BASE}
    n_planned = Session.n_planned(plan, names_all) + n_sun * len(sun_dirs)
    n_before = len(done)
    session.log_event("resume" if n_before or cut else "start", frames_done=n_before, journal_cut=cut)
    t_wall, t_sim = time.perf_counter(), clock.monotonic()
    written = 0
    stopped = None
    progress = progress or None  # False (no progress) is accepted too
    if progress is not None:
        progress("capture", n_before, n_planned)
    try:
        k_short = int(np.argmin(plan.exposures_s))
        sun_whole = plan.sun_bracket is not None and filters is not None and sun_already_whole(session, plan, done)
        for d in plan.directions:
            todo = [(c, k) for k in range(len(plan.exposures_s)) for c in names_all if (d.index, c, k) not in done]
            sun_here = None
            if plan.sun_bracket is not None and filters is not None and not todo and not sun_whole:
                sun_here = direction_holds_sun(session, plan, d.index, done, None)
                sun_todo = sun_here and any((d.index, c, SUN_EXPOSURE_BASE + k) not in done for c in names_all
                                            for k in range(len(plan.sun_bracket["exposures_s"])))
                if not sun_todo:
                    continue
            elif not todo:
                continue
            pan_r, tilt_r = goto_direction(head, d, policy)
            fresh: dict = {}
            for k, exposure in enumerate(plan.exposures_s):
                names = [c for c in names_all if (d.index, c, k) not in done]
                if not names:
                    continue
                frames = expose_all(cameras, names, exposure, policy)
                for c in names:
                    data, meta = frames[c]
                    session.write_frame(data, direction=d.index, camera=c, exposure_index=k, exposure_s=exposure,
                                        pan_deg_commanded=d.pan_deg, tilt_deg_commanded=d.tilt_deg,
                                        pan_deg_reported=pan_r, tilt_deg_reported=tilt_r,
                                        timestamp=clock.now().isoformat(timespec="milliseconds"),
                                        bit_depth=cameras[c].bit_depth, extra={"camera_metadata": meta})
                    done.add((d.index, c, k))
                    written += 1
                    if k == k_short:
                        fresh[c] = (data, cameras[c].bit_depth)
                    if progress is not None:
                        progress("capture", len(done), n_planned)
            if plan.sun_bracket is None or filters is None or sun_whole:
                continue
            if sun_here is None:
                sun_here = direction_holds_sun(session, plan, d.index, done, fresh or None)
            if sun_here:
                if d.index not in sun_dirs:
                    sun_dirs.add(d.index)
                    n_planned += n_sun

                def on_frame(total=n_planned):
                    if progress is not None:
                        progress("capture", len(done), total)

                written += shoot_sun_bracket(session, plan, d, cameras, names_all, filters, policy, (pan_r, tilt_r),
                                             clock, done, on_frame)
                sun_whole = sun_already_whole(session, plan, {k for k in done if k[0] == d.index})
    except DeviceError as exc:
        stopped = str(exc)
        session.log_event("stop", reason=stopped, frames_done=len(done))
    except KeyboardInterrupt:
        session.log_event("stop", reason="interrupted", frames_done=len(done))
        raise
    complete = len(done) >= n_planned
    if complete:
        session.log_event("complete", frames_done=len(done))
    return CaptureResult(str(session.path), n_planned, written, n_before, complete, stopped,
                         clock.monotonic() - t_sim, time.perf_counter() - t_wall)
