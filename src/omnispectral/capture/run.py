"""The capture loop: for each planned direction, move, settle, bracket both cameras, write every frame.

The same loop runs real and simulated devices.  It resumes a session after its last complete frame,
retries a device that does not answer or reports a position off target a bounded number of times,
and otherwise stops cleanly (an event with the reason is logged; the session stays valid and can be
resumed).  Progress is reported per frame to a callback ``progress("capture", done, total)``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from omnispectral.capture.devices import Camera, Clock, DeviceError, DeviceTimeout, PanTiltHead
from omnispectral.capture.plan import Direction
from omnispectral.capture.session import Session
from omnispectral.io import clean_temp_files
from omnispectral.locking import directory_lock


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


def run_capture(session: Session, head: PanTiltHead, cameras: dict[str, Camera], clock: Clock,
                policy: RetryPolicy | None = None,
                progress: Callable[[str, int, int], None] | None = None) -> CaptureResult:
    """Capture (or resume) every planned frame of ``session`` with the given devices; ``progress(stage, done,
    total)`` is called after every frame written.

    Holds the session's lock (:mod:`omnispectral.locking`) for the whole run: a second run on the same
    session is refused; temporary files a killed run left are removed first.
    """
    with directory_lock(session.path, "capture"):
        clean_temp_files(session.path)
        return _run_capture_locked(session, head, cameras, clock, policy, progress)


def _run_capture_locked(session: Session, head: PanTiltHead, cameras: dict[str, Camera], clock: Clock,
                        policy: RetryPolicy | None,
                        progress: Callable[[str, int, int], None] | None) -> CaptureResult:
    policy = policy or RetryPolicy()
    plan = session.plan()
    cut = session.repair_journal()
    done = set(session.completed())
    names_all = session.cameras()
    n_planned = Session.n_planned(plan, names_all)
    n_before = len(done)
    session.log_event("resume" if n_before or cut else "start", frames_done=n_before, journal_cut=cut)
    t_wall, t_sim = time.perf_counter(), clock.monotonic()
    written = 0
    stopped = None
    progress = progress or None  # False (no progress) is accepted too
    if progress is not None:
        progress("capture", n_before, n_planned)
    try:
        for d in plan.directions:
            todo = [(c, k) for k in range(len(plan.exposures_s)) for c in names_all if (d.index, c, k) not in done]
            if not todo:
                continue
            pan_r, tilt_r = goto_direction(head, d, policy)
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
                    if progress is not None:
                        progress("capture", len(done), n_planned)
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
