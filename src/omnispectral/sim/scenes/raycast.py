"""Ray casting for the procedural scene: first hits on a ground plane, axis-aligned boxes, a flat board,
and the sun's shadow test, vectorised over blocks of rays (float32, as the scene renders).

Every ``intersect_*`` function takes unit rays ``d (N, 3)`` from an origin ``o`` (m) and updates the
per-ray record in place where it finds a nearer hit: distance ``t`` (m, ``inf`` = nothing yet), object
id ``obj`` and face normal id ``nid``.  Boxes use the slab method (Kay & Kajiya 1986) after a cone test
against their bounding spheres, so a box is only tested against the rays that can reach it.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["EPS_M", "cone_candidates", "intersect_board", "intersect_boxes", "intersect_ground", "sun_blocked"]

#: Ray offsets (m): hits closer than this are ignored (self-intersection of shadow rays).
EPS_M = 1e-3
#: Normal ids: ±X, ±Y, ±Z (axis-aligned faces), then a board's front and back.
N_PX, N_NX, N_PY, N_NY, N_PZ, N_NZ, N_CHART_FRONT, N_CHART_BACK = range(8)


def cone_candidates(d: np.ndarray, o: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """``(B, N)`` mask of rays whose direction lies in the cone from ``o`` around each bounding sphere."""
    v = centres - o
    dist = np.linalg.norm(v, axis=1)
    inside = dist <= radii * 1.0001
    axis = (v / np.where(inside, 1.0, dist)[:, None]).astype(np.float32)
    cos_lim = np.where(inside, -2.0, np.sqrt(np.maximum(0.0, 1.0 - (radii / np.maximum(dist, 1e-12)) ** 2)))
    # a little slack for float32 rounding of the dot products
    return (axis @ d.T) >= (cos_lim - 1e-6).astype(np.float32)[:, None]


def intersect_ground(dy: np.ndarray, o: np.ndarray, ground_y_m: float, ground_id: int, t, obj, nid) -> None:
    """Downward rays (``dy`` = the rays' y components) hit the plane ``y = ground_y_m`` below the origin."""
    h = np.float32(ground_y_m - o[1])
    if h >= 0:
        return
    down = np.flatnonzero(dy < 0)
    t[down] = h / dy[down]
    obj[down] = ground_id
    nid[down] = N_PY


def intersect_boxes(d: np.ndarray, comps, o: np.ndarray, box_lo_m: np.ndarray, box_hi_m: np.ndarray,
                    centres_m: np.ndarray, radii_m: np.ndarray, t, obj, nid) -> None:
    """Axis-aligned boxes ``(B, 3)`` corners (object id ``1 + j``); ``comps`` = the rays' x, y, z components
    (contiguous), ``centres_m``/``radii_m`` their bounding spheres."""
    mask = cone_candidates(d, o, centres_m, radii_m)
    lo = (box_lo_m - o).astype(np.float32)
    hi = (box_hi_m - o).astype(np.float32)
    tiny = np.float32(1e-20)
    for j in range(box_lo_m.shape[0]):
        idx = np.flatnonzero(mask[j])
        if idx.size == 0:
            continue
        near, far = [], []
        for a in range(3):
            c = comps[a][idx]
            inv = np.float32(1.0) / np.where(np.abs(c) < tiny, tiny, c)
            t0 = lo[j, a] * inv
            t1 = hi[j, a] * inv
            near.append(np.minimum(t0, t1))
            far.append(np.maximum(t0, t1))
        tn = np.maximum(np.maximum(near[0], near[1]), near[2])
        tf = np.minimum(np.minimum(far[0], far[1]), far[2])
        hit = (tn <= tf) & (tn > EPS_M) & (tn < t[idx])
        if not hit.any():
            continue
        sel = idx[hit]
        t[sel] = tn[hit]
        obj[sel] = j + 1
        axis = np.argmax(np.stack([near[a][hit] for a in range(3)]), axis=0)
        positive = d[sel, axis] > 0
        nid[sel] = 2 * axis + positive


def intersect_board(d: np.ndarray, o: np.ndarray, board, board_id: int, t, obj, nid) -> tuple[np.ndarray, np.ndarray]:
    """A flat rectangular board (``centre_m``, ``normal``, ``right``, ``up``, half sizes, ``patch_index(u, v)``);
    returns the rays on it and their patch index (-1: frame or back)."""
    radius = np.array([math.hypot(board.half_width_m, board.half_height_m)])
    mask = cone_candidates(d, o, board.centre_m[None], radius)[0]
    idx = np.flatnonzero(mask)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int32))
    if idx.size == 0:
        return empty
    nrm = board.normal.astype(np.float32)
    denom = d[idx] @ nrm
    num = np.float32((board.centre_m - o) @ board.normal)
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = num / denom
    rel = (o - board.centre_m).astype(np.float32) + tc[:, None] * d[idx]
    u = rel @ board.right.astype(np.float32)
    v = rel @ board.up.astype(np.float32)
    hit = (np.abs(u) <= board.half_width_m) & (np.abs(v) <= board.half_height_m) & (tc > EPS_M) & (tc < t[idx])
    if not hit.any():
        return empty
    sel = idx[hit]
    t[sel] = tc[hit]
    obj[sel] = board_id
    front = denom[hit] < 0
    nid[sel] = np.where(front, N_CHART_FRONT, N_CHART_BACK)
    patch = np.where(front, board.patch_index(u[hit], v[hit]), -1)
    return sel, patch


def sun_blocked(points_m: np.ndarray, sun_direction: np.ndarray, box_lo_m: np.ndarray, box_hi_m: np.ndarray,
                board) -> np.ndarray:
    """Whether the sun's centre is hidden from each point ``(N, 3)`` by a box or the board (shadow rays)."""
    s = sun_direction
    p = np.asarray(points_m, dtype=np.float32)
    blocked = np.zeros(p.shape[0], dtype=bool)
    if p.shape[0] == 0:
        return blocked
    # a zero component gets a huge inverse: the slab then spans (-big, big) when the point is
    # inside it and lies wholly before or behind the ray otherwise, which is what the test needs
    inv = np.array([1.0 / c if c != 0 else 1e20 for c in s])
    near = np.where(s >= 0, box_lo_m, box_hi_m).astype(np.float32)
    far = np.where(s >= 0, box_hi_m, box_lo_m).astype(np.float32)
    inv32 = inv.astype(np.float32)
    for j in range(box_lo_m.shape[0]):
        tn = (near[j, 0] - p[:, 0]) * inv32[0]
        tf = (far[j, 0] - p[:, 0]) * inv32[0]
        for a in (1, 2):
            tn = np.maximum(tn, (near[j, a] - p[:, a]) * inv32[a])
            tf = np.minimum(tf, (far[j, a] - p[:, a]) * inv32[a])
        blocked |= (tn <= tf) & (tf > EPS_M)
    ch = board
    sn = float(s @ ch.normal)
    if abs(sn) > 1e-9:
        tc = ((ch.centre_m - p) @ ch.normal) / sn
        rel = p - ch.centre_m + tc[:, None] * s
        blocked |= ((np.abs(rel @ ch.right) <= ch.half_width_m) & (np.abs(rel @ ch.up) <= ch.half_height_m)
                    & (tc > EPS_M))
    return blocked
