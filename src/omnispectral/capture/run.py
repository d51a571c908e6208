"""The capture loop: for each planned direction, move, settle, bracket both cameras, write every frame.

The same loop runs real and simulated devices.  It resumes a session after its last complete frame,
retries a device that does not answer or reports a position off target a bounded number of times,
and otherwise stops cleanly (an event with the reason is logged; the session stays valid and can be
resumed).  Progress is reported per frame to a callback ``progress("capture", done, total)``.

Sun bracket (a rig with a ``[sun]`` table): after the first direction whose shortest exposure clips in
camera A (:func:`clips`), the head turns to centre the clipped spot (the sun) in camera A's frame
(:func:`aim_at_clipped_spot`: its centroid through the rig's camera model), the filter changer puts the plan's
neutral-density filter in front of both lenses and the loop shoots the attenuated bracket there: direction
index ``plan.n_directions`` (after the grid), exposure indices from ``SUN_EXPOSURE_BASE``, ``"filter"`` in
the journal records and an event ``sun`` with the pose.  Centred, the sun lies whole in both cameras'
frames, unless a near object hides the sun from camera B's viewpoint only: then the bracket is repeated
with the sun off-centre in pan (:data:`SUN_RETRY_PAN_FRACTIONS`), which moves B around the pan axis, until
each camera has seen it whole (:func:`sun_seen_whole`).  A resumed run finishes started sun brackets at
their recorded poses.

Dark extension (a rig with a ``[dark]`` table): after a direction's bracket, the darkest pixels of its longest
exposure are metered in every camera (:func:`dark_exposures_needed`); where their signal-to-noise ratio is
below the plan's, both cameras shoot exposures of 2, 4, … times the longest (exposure indices from
``DARK_EXPOSURE_BASE``) and the event ``dark`` records how many (0: none needed).  A resumed run meters a direction
whose bracket it finds complete without a ``dark`` event, and finishes the extensions its events name.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from omnispectral.capture.devices import Camera, Clock, DeviceError, DeviceTimeout, FilterChanger, PanTiltHead
from omnispectral.capture.plan import Direction, Plan
from omnispectral.capture.session import Session, dark_extensions
from omnispectral.errors import OmnispectralError
from omnispectral.imaging.geometry import ray_to_lonlat
from omnispectral.io import clean_temp_files
from omnispectral.locking import directory_lock
from omnispectral.progress import ProgressCallback
from omnispectral.rig import DARK_EXPOSURE_BASE, MAX_SUN_BRACKETS, SUN_EXPOSURE_BASE, Rig

__all__ = ["EXPOSURE_TOLERANCE", "SUN_RETRY_PAN_FRACTIONS", "CaptureResult", "RetryPolicy", "aim_at_clipped_spot",
           "clipped_centroid_px", "clips", "dark_exposures_needed", "darkest_signal_dn", "every_camera_saw_sun",
           "expose_all", "expose_and_write", "exposure_differs", "exposures_set_otherwise", "goto_direction",
           "longest_frames", "recorded_sun_pose", "run_capture", "shoot_missing", "shoot_sun_bracket", "shortest_frame",
           "sun_poses", "sun_seen_whole"]

#: Relative difference between the requested and the set exposure above which a frame records both.
EXPOSURE_TOLERANCE = 1e-3


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
    #: :func:`exposures_set_otherwise` of the session after the run (empty when every camera set what was asked)
    exposures_set_otherwise: list = field(default_factory=list)

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
    """Set the exposure on the named cameras, trigger them together, read every frame (bounded retries).

    Returns ``{name: (frame, metadata, exposure_set_s)}``: ``exposure_set_s`` is the exposure the camera reports
    it set (a real camera clamps to its range and rounds to its clock: :meth:`Camera.set_exposure`), which is
    the one the merge must divide by.
    """
    set_s = {n: float(cameras[n].set_exposure(exposure_s)) for n in names}
    for n in names:
        cameras[n].trigger()
    frames = {}
    for n in names:
        problem = ""
        for attempt in range(policy.retries + 1):
            try:
                frames[n] = (*cameras[n].read_frame(policy.timeout_s), set_s[n])
                break
            except DeviceTimeout as exc:
                problem = str(exc)
                if attempt < policy.retries:
                    cameras[n].trigger()
        else:
            raise DeviceError(f"camera {n}: no frame after {policy.retries + 1} attempts: {problem}")
    return frames


def exposures_set_otherwise(session: Session) -> list[dict]:
    """The session's exposures a camera set otherwise than planned: one entry per camera, exposure index and
    the two times, with the number of frames (journal records with ``exposure_s_requested``)."""
    counts: dict[tuple, int] = {}
    for (_, c, k), rec in session.completed().items():
        if "exposure_s_requested" in rec:
            key = (c, k, float(rec["exposure_s_requested"]), float(rec["exposure_s"]))
            counts[key] = counts.get(key, 0) + 1
    return [{"camera": c, "exposure_index": k, "requested_s": req, "set_s": got, "n_frames": n}
            for (c, k, req, got), n in sorted(counts.items())]


def exposure_differs(requested_s: float, set_s: float) -> bool:
    """Whether a camera set an exposure other than the one asked, beyond :data:`EXPOSURE_TOLERANCE` (relative)."""
    return abs(set_s - requested_s) > EXPOSURE_TOLERANCE * requested_s


def clips(frame: np.ndarray, bit_depth: int, clip_fraction: float, min_pixels: int) -> bool:
    """Whether at least ``min_pixels`` pixels of a raw frame reach ``clip_fraction`` of the maximum code."""
    level = clip_fraction * ((1 << int(bit_depth)) - 1)
    peak = frame if frame.ndim == 2 else frame.max(axis=2)
    return int(np.count_nonzero(peak >= level)) >= int(min_pixels)


def clipped_centroid_px(frame: np.ndarray, bit_depth: int, clip_fraction: float) -> tuple[float, float] | None:
    """``(x, y)`` centroid of a raw frame's pixels at ``clip_fraction`` of the maximum code, or ``None``."""
    peak = frame if frame.ndim == 2 else frame.max(axis=2)
    rows, cols = np.nonzero(peak >= clip_fraction * ((1 << int(bit_depth)) - 1))
    return (float(cols.mean()), float(rows.mean())) if rows.size else None


def aim_at_clipped_spot(model, frame: np.ndarray, bit_depth: int, clip_fraction: float, pan_deg: float,
                        tilt_deg: float, index: int) -> Direction | None:
    """The head pose that centres a frame's clipped spot in the camera: camera A's optical axis at pose
    ``(pan, tilt)`` points at longitude ``pan``, latitude ``tilt`` (``omnispectral.imaging.geometry``), so
    the pose is the spot's world direction."""
    spot = clipped_centroid_px(frame, bit_depth, clip_fraction)
    if spot is None:
        return None
    ray, valid = model.pixel_to_world(np.array(spot), pan_deg, tilt_deg)
    if not bool(valid):
        return None
    lon, lat = ray_to_lonlat(ray)
    return Direction(index, -1, -1, round(float(lon), 6), round(float(np.clip(lat, -90.0, 90.0)), 6))


def shortest_frame(session: Session, plan: Plan, direction: int,
                   fresh: dict) -> tuple[np.ndarray, int, tuple[float, float]] | None:
    """Camera A's shortest regular exposure of a direction with its bit depth and the head's reported pose:
    the frame just read, else read back."""
    if "A" in fresh:
        return fresh["A"]
    try:
        frame, meta = session.read_frame(direction, "A", int(np.argmin(plan.exposures_s)))
    except OmnispectralError:
        return None  # a missing or damaged frame: session verify names it
    pose = (float(meta.get("pan_deg_reported", meta.get("pan_deg_commanded"))),
            float(meta.get("tilt_deg_reported", meta.get("tilt_deg_commanded"))))
    return np.asarray(frame), int(meta.get("bit_depth", 12)), pose


def darkest_signal_dn(frame: np.ndarray, percentile: float, black_level_dn: float = 0.0) -> float:
    """The ``percentile`` of a frame's per-pixel darkest channel above the black level (DN): the signal of its
    darkest pixels."""
    darkest = frame.min(axis=-1) if frame.ndim == 3 else frame
    return float(np.percentile(darkest, percentile)) - black_level_dn


def dark_exposures_needed(frames: dict[str, np.ndarray], rig: Rig, dark: dict) -> int:
    """How many exposures of the dark extension ``dark`` (the plan's) a direction needs after its bracket.

    Each camera's longest exposure ``frames[c]`` is metered (:func:`darkest_signal_dn`); its darkest pixels need
    the signal at which the camera's noise model gives the plan's signal-to-noise ratio
    (:meth:`~omnispectral.spectral.noise.SensorNoiseModel.dn_for_snr`), and each exposure of the extension
    doubles the signal: ``ceil(log2(needed / metered))`` exposures, the most the plan allows for a pixel at 0 DN,
    the largest over the cameras."""
    n_max = len(dark["exposures_s"])
    need = 0
    for c, frame in frames.items():
        cam = rig.cameras[c]
        signal = darkest_signal_dn(frame, float(dark["percentile"]), cam.black_level_dn)
        wanted = cam.noise_model().dn_for_snr(float(dark["snr"]))
        if signal < wanted:
            need = max(need, n_max if signal <= 0 else min(n_max, math.ceil(math.log2(wanted / signal))))
    return need


def longest_frames(session: Session, plan: Plan, direction: int, names, fresh: dict) -> dict[str, np.ndarray] | None:
    """Each camera's longest regular exposure of a direction: the frame just shot, else read back (``None``
    when one is missing or damaged: ``session verify`` names it)."""
    k_long = int(np.argmax(plan.exposures_s))
    out = {}
    for c in names:
        if c in fresh:
            out[c] = fresh[c]
            continue
        try:
            out[c] = np.asarray(session.read_frame(direction, c, k_long)[0])
        except OmnispectralError:
            return None
    return out


#: Pan offsets (fractions of camera A's pan field of view) of the retries when camera B does not see the sun
#: whole from the aimed pose (a near object hiding it from B's viewpoint only): each moves B's centre around
#: the pan axis while the sun stays in both frames.
SUN_RETRY_PAN_FRACTIONS = (-0.3, 0.3)
assert len(SUN_RETRY_PAN_FRACTIONS) + 1 == MAX_SUN_BRACKETS


def sun_poses(first: Direction, pan_fov_deg: float) -> list[Direction]:
    """The aimed pose and its retries (:data:`SUN_RETRY_PAN_FRACTIONS`), direction indices in order."""
    return [first] + [Direction(first.index + 1 + i, -1, -1, round(first.pan_deg - f * pan_fov_deg, 6),
                                first.tilt_deg) for i, f in enumerate(SUN_RETRY_PAN_FRACTIONS)]


def sun_seen_whole(frame: np.ndarray, bit_depth: int, clip_fraction: float, contrast: float = 20.0) -> bool:
    """Whether an attenuated frame shows the sun whole: its brightest pixel stands ``contrast`` times above
    the frame's median, is not clipped, and lies at least 8 px inside every edge."""
    peak = frame.astype(np.float64) if frame.ndim == 2 else frame.astype(np.float64).max(axis=2)
    r, c = np.unravel_index(int(np.argmax(peak)), peak.shape)
    h, w = peak.shape
    top = peak[r, c]
    return bool(8 <= r < h - 8 and 8 <= c < w - 8 and top < clip_fraction * ((1 << int(bit_depth)) - 1)
                and top > contrast * max(float(np.median(peak)), 1.0))


def every_camera_saw_sun(session: Session, plan: Plan, poses: list[Direction], done: set,
                         names: tuple[str, ...]) -> bool:
    """Whether, over the sun brackets shot so far, each camera saw the sun whole in its shortest frame."""
    k = SUN_EXPOSURE_BASE + int(np.argmin(plan.sun_bracket["exposures_s"]))
    for c in names:
        seen = False
        for pose in poses:
            if (pose.index, c, k) not in done:
                continue
            try:
                frame, meta = session.read_frame(pose.index, c, k)
            except OmnispectralError:
                continue
            if sun_seen_whole(np.asarray(frame), int(meta.get("bit_depth", 12)),
                              float(plan.sun_bracket["clip_fraction"])):
                seen = True
                break
        if not seen:
            return False
    return True


def recorded_sun_pose(session: Session, plan: Plan, done: set) -> Direction | None:
    """The pose of a sun bracket this capture started (from its first frame's record), or ``None``."""
    index = plan.n_directions
    keys = sorted(k for k in done if k[0] == index and k[2] >= SUN_EXPOSURE_BASE)
    if not keys:
        return None
    rec = session.completed()[keys[0]]
    return Direction(index, -1, -1, float(rec["pan_deg_commanded"]), float(rec["tilt_deg_commanded"]))


def run_capture(session: Session, head: PanTiltHead, cameras: dict[str, Camera], clock: Clock,
                policy: RetryPolicy | None = None,
                progress: ProgressCallback | None = None,
                filters: FilterChanger | None = None) -> CaptureResult:
    """Capture (or resume) every planned frame of ``session`` with the given devices; ``progress(stage, done,
    total)`` is called after every frame written.  ``filters`` moves the sun bracket's neutral-density filter
    (module docstring); without it, or without a sun bracket in the plan, the sun stays clipped.

    Holds the session's lock (:mod:`omnispectral.locking`) for the whole run: a second run on the same
    session is refused; temporary files a killed run left are removed first.

    Parameters
    ----------
    session : Session
        The session: its plan (directions, bracket in seconds, sun bracket), journal and frame files.
    head : PanTiltHead
        The pan/tilt head (real or simulated), commanded in degrees.
    cameras : dict of str to Camera
        The cameras by name (``"A"``, ``"B"``); each exposure triggers them together.
    clock : Clock
        Wall time of the journal records and the simulated seconds of the result.
    policy : RetryPolicy, optional
        Retries, timeout (s) and position tolerance (deg) of the devices; default :class:`RetryPolicy`.
    progress : ProgressCallback, optional
        ``progress("capture", done, total)``: once at the start, then after every frame written.
    filters : FilterChanger, optional
        The neutral-density filter changer of the sun bracket.

    Returns
    -------
    CaptureResult
        Frames planned, written by this run and already done before it, whether the session is complete,
        the reason a device stopped the run (``None`` otherwise), simulated and wall seconds.

    Raises
    ------
    LockedError
        When another run holds the session's lock.
    KeyboardInterrupt
        Re-raised after a ``stop`` event is logged; a device failure does not raise (it stops the run).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 3, Fig. 2 (two cameras on a programmable rotating table, both
       exposing at once), Sec. 4.1 (the exposure bracket of every direction), Sec. 5.1, Table 2.
    """
    with directory_lock(session.path, "capture"):
        clean_temp_files(session.path)
        return _run_capture_locked(session, head, cameras, clock, policy, progress, filters)


def expose_and_write(session: Session, d: Direction, cameras: dict[str, Camera], names: list[str], index: int,
                     exposure_s: float, policy: RetryPolicy, pose: tuple[float, float], clock: Clock,
                     extra: dict | None = None) -> dict:
    """One exposure on the named cameras (:func:`expose_all`), each frame written with its journal record
    (exposure ``index``, the exposure the camera set, the head's commanded and reported pose, ``extra``
    fields); returns the frames.

    A camera that set another exposure than ``exposure_s`` (:func:`exposure_differs`: out of its range) is
    recorded with the one it set and the requested one as ``exposure_s_requested``
    (:func:`exposures_set_otherwise` lists them)."""
    frames = expose_all(cameras, names, exposure_s, policy)
    for c in names:
        data, meta, set_s = frames[c]
        fields = {"camera_metadata": meta, **(extra or {})}
        if exposure_differs(exposure_s, set_s):
            fields["exposure_s_requested"] = exposure_s
        session.write_frame(data, direction=d.index, camera=c, exposure_index=index, exposure_s=set_s,
                            pan_deg_commanded=d.pan_deg, tilt_deg_commanded=d.tilt_deg,
                            pan_deg_reported=pose[0], tilt_deg_reported=pose[1],
                            timestamp=clock.now().isoformat(timespec="milliseconds"),
                            bit_depth=cameras[c].bit_depth, extra=fields)
    return {c: frames[c][:2] for c in names}


def shoot_sun_bracket(session: Session, plan: Plan, d: Direction, cameras: dict[str, Camera], names_all,
                      filters: FilterChanger, policy: RetryPolicy, pose: tuple[float, float], clock: Clock,
                      done: set, on_frame: Callable[[], None], source: int | None = None) -> int:
    """The attenuated bracket at the head pose ``d`` aimed at the sun (module docstring; ``source``: the
    direction whose clipped spot it centres); returns the frames written."""
    sun = plan.sun_bracket
    keys = [(c, k) for k in range(len(sun["exposures_s"])) for c in names_all
            if (d.index, c, SUN_EXPOSURE_BASE + k) not in done]
    if not keys:
        return 0
    if len(keys) == len(sun["exposures_s"]) * len(names_all):
        session.log_event("sun", direction=d.index, filter=sun["filter"], pan_deg=d.pan_deg, tilt_deg=d.tilt_deg,
                          source_direction=source)
    filters.insert(sun["filter"])
    try:
        return shoot_missing(session, d, cameras, names_all, enumerate(sun["exposures_s"], SUN_EXPOSURE_BASE), policy,
                             pose, clock, done, on_frame, {"filter": sun["filter"]})
    finally:
        filters.remove()


def shoot_missing(session: Session, d: Direction, cameras: dict[str, Camera], names_all, exposures, policy: RetryPolicy,
                  pose, clock: Clock, done: set, on_frame: Callable[[], None], extra: dict | None = None) -> int:
    """Each ``(exposure index, exposure_s)`` of ``exposures`` on the cameras of ``names_all`` that have not shot it
    in direction ``d`` (``done``, updated), at the head pose ``pose`` (or a callable giving it, called only when
    something is left to shoot); returns the frames written."""
    written = 0
    for index, exposure in exposures:
        names = [c for c in names_all if (d.index, c, index) not in done]
        if not names:
            continue
        if callable(pose):
            pose = pose()
        expose_and_write(session, d, cameras, names, index, exposure, policy, pose, clock, extra)
        for c in names:
            done.add((d.index, c, index))
            written += 1
            on_frame()
    return written


def _run_capture_locked(session: Session, head: PanTiltHead, cameras: dict[str, Camera], clock: Clock,
                        policy: RetryPolicy | None,
                        progress: ProgressCallback | None,
                        filters: FilterChanger | None = None) -> CaptureResult:
    policy = policy or RetryPolicy()
    plan = session.plan()
    cut = session.repair_journal()
    done = set(session.completed())
    names_all = session.cameras()
    want_sun = plan.sun_bracket is not None and filters is not None
    n_sun = len(plan.sun_bracket["exposures_s"]) * len(names_all) if plan.sun_bracket else 0
    sun_pose = recorded_sun_pose(session, plan, done) if want_sun else None
    rig = session.rig()
    extensions = dark_extensions(session, plan)
    n_planned = (Session.n_planned(plan, names_all) + n_sun * len({k[0] for k in done if k[2] >= SUN_EXPOSURE_BASE})
                 + sum(extensions.values()) * len(names_all))
    n_before = len(done)
    session.log_event("resume" if n_before or cut else "start", frames_done=n_before, journal_cut=cut)
    t_wall, t_sim = time.perf_counter(), clock.monotonic()
    written = 0
    stopped = None
    progress = progress or None  # False (no progress) is accepted too
    if progress is not None:
        progress("capture", n_before, n_planned)

    def on_frame():
        if progress is not None:
            progress("capture", len(done), n_planned)

    def dark_extension(d: Direction, longest: dict, pose: tuple[float, float] | None) -> int:
        """The direction's dark extension (module docstring): metered unless its event says, then shot."""
        nonlocal n_planned
        if d.index not in extensions:
            frames = longest_frames(session, plan, d.index, names_all, longest)
            if frames is None:
                return 0
            extensions[d.index] = dark_exposures_needed(frames, rig, plan.dark_extension)
            session.log_event("dark", direction=d.index, n_exposures=extensions[d.index])
            n_planned += extensions[d.index] * len(names_all)
        exposures = enumerate(plan.dark_extension["exposures_s"][:extensions[d.index]], DARK_EXPOSURE_BASE)
        # a resumed run whose bracket was shot before: the head is elsewhere, and goes there only to shoot
        return shoot_missing(session, d, cameras, names_all, exposures, policy,
                             pose if pose is not None else (lambda: goto_direction(head, d, policy)),
                             clock, done, on_frame)

    def sun_brackets(first: Direction, source: int | None) -> int:
        """The aimed bracket, then retries while a camera has not seen the sun whole (module docstring)."""
        nonlocal n_planned
        n = 0
        poses = sun_poses(first, rig.camera_a.pan_fov_deg)
        for i, pose in enumerate(poses):
            if i and (every_camera_saw_sun(session, plan, poses[:i], done, tuple(names_all))
                      or not every_camera_saw_sun(session, plan, poses[:i], done, ("A",))):
                break  # retries help camera B only, when A saw the sun whole
            started = sum(k[0] == pose.index for k in done)
            if started == n_sun:
                continue
            if not started:
                n_planned += n_sun
            pan_s, tilt_s = goto_direction(head, pose, policy)
            n += shoot_sun_bracket(session, plan, pose, cameras, names_all, filters, policy, (pan_s, tilt_s),
                                   clock, done, on_frame, source)
        return n

    try:
        k_short, k_long = int(np.argmin(plan.exposures_s)), int(np.argmax(plan.exposures_s))
        if sun_pose is not None:  # sun brackets a killed run started: finish them at their poses
            written += sun_brackets(sun_pose, None)
        model_a = rig.camera_model("A") if want_sun else None
        for d in plan.directions:
            todo = [(c, k) for k in range(len(plan.exposures_s)) for c in names_all if (d.index, c, k) not in done]
            fresh: dict = {}
            longest: dict = {}
            pose = None
            if todo:
                pose = pan_r, tilt_r = goto_direction(head, d, policy)
                for k, exposure in enumerate(plan.exposures_s):
                    names = [c for c in names_all if (d.index, c, k) not in done]
                    if not names:
                        continue
                    frames = expose_and_write(session, d, cameras, names, k, exposure, policy, (pan_r, tilt_r),
                                              clock)
                    for c in names:
                        data = frames[c][0]
                        done.add((d.index, c, k))
                        written += 1
                        if k == k_short:
                            fresh[c] = (data, cameras[c].bit_depth, (pan_r, tilt_r))
                        if k == k_long:
                            longest[c] = data
                        on_frame()
            if plan.dark_extension:
                written += dark_extension(d, longest, pose)
            if not want_sun or sun_pose is not None:
                continue
            shot = shortest_frame(session, plan, d.index, fresh)
            sun = plan.sun_bracket
            if shot is None or not clips(shot[0], shot[1], float(sun["clip_fraction"]), int(sun["min_clipped_px"])):
                continue
            sun_pose = aim_at_clipped_spot(model_a, shot[0], shot[1], float(sun["clip_fraction"]), *shot[2],
                                           index=plan.n_directions)
            if sun_pose is not None:
                written += sun_brackets(sun_pose, d.index)
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
                         clock.monotonic() - t_sim, time.perf_counter() - t_wall, exposures_set_otherwise(session))
