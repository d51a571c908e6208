"""Acquisition planning: the direction grid, its overlap, and the acquisition time (paper Sec. 4.5, 5.5, Table 2).

Grid.  ``n_tilt`` rows cover latitude -90..90 with centres ``-90 + (i + 1/2) 180 / n_tilt``; each row
has ``n_pan`` directions ``-180 + (j + 1/2) 360 / n_pan`` (monotonic within a row, no wrap).  Rows are
visited bottom to top and the pan direction alternates (serpentine): the head never swings back.

Overlap.  ``overlap`` is the fraction of the frame, on each side, shared with the neighbour's margin: the
step between directions is ``fov (1 - 2 overlap)`` and the counts are
``n_pan = ceil(360 / (pan_fov (1 - 2 overlap)))``, ``n_tilt = ceil(180 / (tilt_fov (1 - 2 overlap)))``.
This reading reproduces the paper's Sec. 5.5 figures: the telephoto lens (14.5 x 10.8 deg) without overlap
needs 25 x 17 = 425 directions (~46 min) and with 12 % overlap 33 x 22 = 726 (~1 h 19 min).

Timing model, per direction: head move ``max(|d pan| / pan speed, |d tilt| / tilt speed)``, settle time,
then the bracket on both cameras at once (sum of the exposure times plus one read-out per frame).
The presets' head speed and settle time reproduce Table 2 (36 directions ~180 s; 1260 ~2 h 17 min).

Sun bracket (beyond the paper).  A rig with a ``[sun]`` table shoots one attenuated bracket through a
neutral-density filter, aimed at the sun once a direction's shortest exposure clips
(``omnispectral.capture.run``); the plan adds its cost (:func:`sun_bracket_time_s`).

Dark extension (beyond the paper).  A rig with a ``[dark]`` table adds exposures of 2, 4, … times the
bracket's longest to a direction whose darkest pixels stay noisy in it (:func:`dark_extension_plan`); the plan
states the most this adds to one direction, not in its total (only dark directions pay it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.io import atomic_path
from omnispectral.limits import check_directions
from omnispectral.rig import Rig

__all__ = ["Direction", "Plan", "dark_extension_plan", "direction_grid", "estimate_time", "format_duration",
           "grid_counts", "make_plan", "move_time_s", "overlap_of", "plot_tradeoff", "sun_bracket_plan",
           "sun_bracket_time_s", "tradeoff"]


@dataclass(frozen=True)
class Direction:
    """One viewing direction of the head: its index in capture order, grid row/column, pan and tilt."""

    index: int
    row: int
    col: int
    pan_deg: float
    tilt_deg: float

    def to_dict(self) -> dict:
        return {"index": self.index, "row": self.row, "col": self.col, "pan_deg": self.pan_deg,
                "tilt_deg": self.tilt_deg}


@dataclass(frozen=True)
class Plan:
    """A capture plan: directions in order, the overlap they give, and the estimated acquisition time."""

    rig_name: str
    n_pan: int
    n_tilt: int
    overlap: float
    overlap_pan: float
    overlap_tilt: float
    directions: tuple[Direction, ...]
    exposures_s: tuple[float, ...]
    timing_s: dict
    #: the sun bracket (:class:`~omnispectral.rig.SunBracketSpec` as a dict), or ``None``
    sun_bracket: dict | None = None
    #: the dark extension (:func:`dark_extension_plan`), or ``None``
    dark_extension: dict | None = None

    @property
    def n_directions(self) -> int:
        return len(self.directions)

    @property
    def estimated_s(self) -> float:
        return float(self.timing_s["total"])

    @property
    def estimated_max_s(self) -> float:
        """The estimate with the dark extension in every direction: what a capture can take at dusk (s)."""
        extra = (self.dark_extension or {}).get("max_s_per_direction", 0.0)
        return self.estimated_s + self.n_directions * float(extra)

    def to_dict(self) -> dict:
        return {"rig": self.rig_name, "n_directions": self.n_directions, "n_pan": self.n_pan, "n_tilt": self.n_tilt,
                "overlap": self.overlap, "overlap_pan": self.overlap_pan, "overlap_tilt": self.overlap_tilt,
                "estimated_s": self.estimated_s, "estimated_hms": format_duration(self.estimated_s),
                "timing_s": self.timing_s, "exposures_s": list(self.exposures_s),
                "directions": [d.to_dict() for d in self.directions],
                **({"sun_bracket": self.sun_bracket} if self.sun_bracket is not None else {}),
                **({"dark_extension": self.dark_extension} if self.dark_extension is not None else {})}

    @classmethod
    def from_dict(cls, d: dict) -> Plan:
        dirs = tuple(Direction(int(x["index"]), int(x["row"]), int(x["col"]), float(x["pan_deg"]),
                               float(x["tilt_deg"])) for x in d["directions"])
        return cls(d["rig"], int(d["n_pan"]), int(d["n_tilt"]), float(d["overlap"]), float(d["overlap_pan"]),
                   float(d["overlap_tilt"]), dirs, tuple(d["exposures_s"]), dict(d["timing_s"]),
                   d.get("sun_bracket"), d.get("dark_extension"))


def format_duration(seconds: float) -> str:
    """``2 h 17 min``, ``3 min 05 s`` or ``42.0 s``."""
    if seconds >= 3600:
        h, rem = divmod(round(seconds / 60), 60)
        return f"{h} h {rem:02d} min"
    if seconds >= 60:
        m, s = divmod(round(seconds), 60)
        return f"{m} min {s:02d} s"
    return f"{seconds:.1f} s"


def grid_counts(pan_fov_deg: float, tilt_fov_deg: float, overlap: float) -> tuple[int, int]:
    """Directions per row and rows for a given per-side overlap (module docstring)."""
    if not 0 <= overlap < 0.5:
        raise ConfigurationError(f"overlap must be in [0, 0.5), got {overlap}")
    keep = 1.0 - 2.0 * overlap
    n_pan = math.ceil(360.0 / (pan_fov_deg * keep) - 1e-9)
    n_tilt = math.ceil(180.0 / (tilt_fov_deg * keep) - 1e-9)
    return n_pan, n_tilt


def overlap_of(fov_deg: float, n: int, span_deg: float) -> float:
    """Per-side overlap that ``n`` directions over ``span_deg`` give a lens of ``fov_deg`` (may be < 0: gaps)."""
    return 0.5 * (1.0 - span_deg / (n * fov_deg))


def direction_grid(n_pan: int, n_tilt: int) -> tuple[Direction, ...]:
    """Serpentine grid, rows bottom to top (module docstring)."""
    if n_pan < 1 or n_tilt < 1:
        raise ConfigurationError(f"the grid needs at least one direction, got {n_pan} x {n_tilt}")
    dirs = []
    for row in range(n_tilt):
        tilt = -90.0 + (row + 0.5) * 180.0 / n_tilt
        cols = range(n_pan) if row % 2 == 0 else range(n_pan - 1, -1, -1)
        for col in cols:
            pan = -180.0 + (col + 0.5) * 360.0 / n_pan
            dirs.append(Direction(len(dirs), row, col, round(pan, 9), round(tilt, 9)))
    return tuple(dirs)


def move_time_s(rig: Rig, from_deg: tuple[float, float], to_deg: tuple[float, float]) -> float:
    """Head travel time between two (pan, tilt) positions, both axes moving together."""
    dpan = abs(to_deg[0] - from_deg[0])
    dtilt = abs(to_deg[1] - from_deg[1])
    return max(dpan / rig.head.pan_speed_deg_s, dtilt / rig.head.tilt_speed_deg_s)


def estimate_time(rig: Rig, directions: tuple[Direction, ...], exposures_s: tuple[float, ...]) -> dict:
    """Timing model of the module docstring, in seconds per component and in total.

    Parameters
    ----------
    rig : Rig
        The head's pan and tilt speeds (deg/s) and settle time (s), and the cameras' read-out time (s; the
        slowest camera's, both cameras exposing at once).
    directions : tuple of Direction
        The directions in capture order; the head starts at pan 0°, tilt 0°.
    exposures_s : tuple of float
        One direction's bracket, exposure times in seconds.

    Returns
    -------
    dict
        Seconds: ``total``, its parts ``moves`` (head travel), ``settle``, ``exposures`` and ``readout``
        (summed over the directions), and ``per_direction`` (``total / len(directions)``, 0 without directions).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.1, Table 2 (about 5 s per direction including capture and rotation;
       36 directions in about 180 s, 1260 in about 2 h 17 min).
    """
    readout = max(c.readout_s for c in rig.cameras.values())
    capture = float(sum(exposures_s)) + len(exposures_s) * readout
    moves = 0.0
    pos = (0.0, 0.0)
    for d in directions:
        moves += move_time_s(rig, pos, (d.pan_deg, d.tilt_deg))
        pos = (d.pan_deg, d.tilt_deg)
    n = len(directions)
    total = moves + n * (rig.head.settle_s + capture)
    return {"total": total, "moves": moves, "settle": n * rig.head.settle_s, "exposures": n * sum(exposures_s),
            "readout": n * len(exposures_s) * readout, "per_direction": total / n if n else 0.0}


def sun_bracket_time_s(rig: Rig) -> float:
    """The sun bracket: the head turns to the sun and back (a mean move of 90° in pan and 45° in tilt each
    way) and settles, the filter goes in, the attenuated exposures with their read-outs, the filter comes out."""
    if rig.sun is None:
        return 0.0
    readout = max(c.readout_s for c in rig.cameras.values())
    moves = 2.0 * move_time_s(rig, (0.0, 0.0), (90.0, 45.0)) + rig.head.settle_s
    return moves + 2.0 * rig.sun.change_s + rig.sun.total_s + len(rig.sun.exposures_s) * readout


def sun_bracket_plan(rig: Rig) -> dict | None:
    """What the plan records of the rig's sun bracket (its filter, exposures and expected cost)."""
    if rig.sun is None:
        return None
    return {"filter": rig.sun.filter, "exposures_s": list(rig.sun.exposures_s), "changer": rig.sun.changer,
            "change_s": rig.sun.change_s, "clip_fraction": rig.sun.clip_fraction,
            "min_clipped_px": rig.sun.min_clipped_px,
            "expected_s": sun_bracket_time_s(rig)}


def dark_extension_plan(rig: Rig, exposures_s: tuple[float, ...]) -> dict | None:
    """What the plan records of the rig's dark extension (:class:`~omnispectral.rig.DarkExtensionSpec`) after a
    bracket of ``exposures_s``: the exposures it may add (longest last), what triggers it, and the most it can
    add to one direction's time (not in the plan's total: only dark directions pay it)."""
    if rig.dark is None:
        return None
    extra = rig.dark.exposures_s(max(exposures_s))
    if not extra:
        return None
    readout = max(c.readout_s for c in rig.cameras.values())
    return {"exposures_s": list(extra), "percentile": rig.dark.percentile, "snr": rig.dark.snr,
            "longest_s": rig.dark.longest_s, "max_s_per_direction": float(sum(extra)) + len(extra) * readout}


def make_plan(rig: Rig, overlap: float | None = None, exposures_s: tuple[float, ...] | None = None) -> Plan:
    """The capture plan of a rig: its grid (or the one ``overlap`` implies), order and time estimate.

    Parameters
    ----------
    rig : Rig
        The rig: camera A's field of view (deg), its grid (``[grid]``), bracket, head and sun bracket.
    overlap : float, optional
        Per-side overlap as a fraction of the frame, in [0, 0.5) (module docstring); ``None``: the rig grid's
        counts, or the counts its own ``overlap`` implies.
    exposures_s : tuple of float, optional
        The bracket's exposure times in seconds (default: the rig's bracket).

    Returns
    -------
    Plan
        The serpentine direction grid (:func:`direction_grid`), the overlap it gives per axis, the bracket and
        the timing of :func:`estimate_time` (plus the sun bracket's expected cost when the rig has one).

    Raises
    ------
    ConfigurationError
        For an overlap outside [0, 0.5), more directions than the package's limit, or a grid that leaves gaps.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.5 (36 and 1260 directions), Sec. 5.5, Table 2 (directions and
       acquisition time).
    """
    cam = rig.camera_a
    if overlap is None and rig.grid.overlap is None:
        n_pan, n_tilt = rig.grid.n_pan, rig.grid.n_tilt
    else:
        n_pan, n_tilt = grid_counts(cam.pan_fov_deg, cam.tilt_fov_deg,
                                    overlap if overlap is not None else rig.grid.overlap)
    check_directions(n_pan, n_tilt, f"{rig.source or rig.name}: grid")
    o_pan = overlap_of(cam.pan_fov_deg, n_pan, 360.0)
    o_tilt = overlap_of(cam.tilt_fov_deg, n_tilt, 180.0)
    if o_pan < 0 or o_tilt < 0:
        raise ConfigurationError(f"{n_pan} x {n_tilt} directions leave gaps for a {cam.pan_fov_deg} x "
                                 f"{cam.tilt_fov_deg} deg field of view (overlap {o_pan:.3f} / {o_tilt:.3f} < 0)")
    exposures = tuple(exposures_s) if exposures_s is not None else rig.bracket.exposures_s
    dirs = direction_grid(n_pan, n_tilt)
    sun = sun_bracket_plan(rig)
    timing = estimate_time(rig, dirs, exposures)
    if sun is not None:  # the sun bracket's expected cost (Table 2's time plus the attenuated bracket)
        timing["sun_bracket"] = sun["expected_s"]
        timing["total"] += timing["sun_bracket"]
        timing["per_direction"] = timing["total"] / len(dirs)
    return Plan(rig.name, n_pan, n_tilt, min(o_pan, o_tilt) if overlap is None else float(overlap),
                o_pan, o_tilt, dirs, exposures, timing, sun, dark_extension_plan(rig, exposures))


def tradeoff(rig: Rig, overlaps=None) -> list[dict]:
    """Overlap vs directions vs acquisition time (paper Fig. 15a), relative to the rig's own grid.

    Parameters
    ----------
    rig : Rig
        The rig (:func:`make_plan`); its own plan is the reference of ``relative_time``.
    overlaps : array_like of float, optional
        Per-side overlaps (fractions of the frame, each in [0, 0.5)); default 0 to 0.40 in steps of 0.01.

    Returns
    -------
    list of dict
        Per overlap: ``overlap``, ``n_directions``, ``n_pan``, ``n_tilt``, ``estimated_s`` (seconds) and
        ``relative_time`` (``estimated_s`` over the rig plan's).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.5, Fig. 15a (overlapping pixels vs relative acquisition time).
    """
    reference = make_plan(rig)
    rows = []
    for o in np.round(np.arange(0.0, 0.401, 0.01) if overlaps is None else np.asarray(overlaps), 6):
        p = make_plan(rig, overlap=float(o))
        rows.append({"overlap": float(o), "n_directions": p.n_directions, "n_pan": p.n_pan, "n_tilt": p.n_tilt,
                     "estimated_s": p.estimated_s, "relative_time": p.estimated_s / reference.estimated_s})
    return rows


def plot_tradeoff(rig: Rig, rows: list[dict], path) -> None:
    """Fig. 15a-style plot: relative acquisition time and directions against the overlap.

    Parameters
    ----------
    rig : Rig
        The rig; its own plan is marked in red (the paper's red circle).
    rows : list of dict
        :func:`tradeoff`'s rows; the 0 % (blue) and 12 % (green) overlaps are marked as in the paper.
    path : str or pathlib.Path
        The PNG file written.

    Returns
    -------
    None

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.5, Fig. 15a (red: the current setting; blue: no overlap; green: 12 %).
    """
    import matplotlib  # lazy: matplotlib (pyplot) is needed for this plot only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = make_plan(rig)
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    o = [100 * r["overlap"] for r in rows]
    ax.plot(o, [r["relative_time"] for r in rows], "-", color="k", label="relative acquisition time")
    ax.axvline(100 * ref.overlap, color="red", lw=0.8, ls="--")
    ax.plot([100 * ref.overlap], [1.0], "o", color="red",
            label=f"this rig: {100 * ref.overlap:.1f} % overlap (pan {100 * ref.overlap_pan:.1f} %, tilt "
                  f"{100 * ref.overlap_tilt:.1f} %), {ref.n_directions} directions, {format_duration(ref.estimated_s)}")
    for r in rows:
        if r["overlap"] in (0.0, 0.12):
            ax.plot([100 * r["overlap"]], [r["relative_time"]], "o", color="blue" if r["overlap"] == 0 else "green",
                    label=f"{100 * r['overlap']:.0f} % ({r['n_directions']} directions, "
                          f"{format_duration(r['estimated_s'])})")
    ax.set_xlabel("overlap per side (% of the frame)")
    ax.set_ylabel("acquisition time relative to the rig grid")
    ax.set_title(f"{rig.name}: overlap vs acquisition time (paper Fig. 15a)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
