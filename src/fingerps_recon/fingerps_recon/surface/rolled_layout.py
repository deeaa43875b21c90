"""The unrolled plane of a finger rolled on a card: arc lengths around and along the finger.

An ink or live-scan rolled print is taken by rolling the finger across the card from nail
edge to nail edge: each cross-section of the finger touches the card along its own line, and
the card keeps the arc length around the finger (x) and the length along it (y). This module
lays a reconstruction's mesh nodes out in that plane (``Layout.ROLLED`` of
:func:`fingerps_recon.surface.surface_unrolling.unroll_surface`), where the springs model
(``Layout.SPRINGS``, Chen et al. 2006) keeps every neighbour distance as well as it can: on
a doubly curved cap the two maps differ by up to ~6 % locally (the springs compress the cap
radially), and it is the rolled one that the galleries' rolled and contact prints are in.

Steps (:func:`rolled_layout`), all on the nodes' 3D points (millimetres, optical frame):

1. The finger's axis in the image plane: first the direction of least curvature of a
   quadric z = q(x, y) fitted to the nodes (along a finger its curvature is the smaller
   one: the long radius of the cap, the bend of the shaft; the image's own axes when the
   two curvatures are within 20 %, a dome without a direction), then turned onto the crest:
   the line through each section's point nearest the camera (least squares; the quadric's
   axis was off by 2-3 deg on fingers turned by 9 deg, whose seen parts are lopsided).
2. The surface resampled from the nodes on a regular grid across (s) and along (t) the axis,
   half the mesh's spacing (linear over the mesh's triangles); a section
   that the image's edge cuts short of its crest is continued to it by the nearest whole
   one, shifted in depth to join it.
3. Cross-sections: the planes t = const, perpendicular to the axis (the finger is rolled
   about a straight axis; its bend away from the camera only shifts each section in depth).
   x is the 3D arc length along a node's section from the crest (the line of step 1), and
   y the 3D arc length along the crest from the apex's section.
4. Pitch: a finger pitched by p towards the camera is cut at p from its own sections (a
   node at depth z below the apex lands ~z tan p along the finger from its own section,
   0.35 mm at the margins for 5 deg), and the sections' shapes hardly show it (an ellipse
   R / cos p tall for a circle R). The crest does: the tip's cap is more curved along the
   finger (~1 / (e^2 R)) than the pad behind it (~1 / L), and where they meet the crest's
   slope is the finger's pitch (:func:`crest_pitch`). The nodes are turned by it about the
   across axis and steps 1-3 run again. On the rig's TRUE surface in five poses (pitch -6
   to +7 deg) the nodes' residual against the generator's skin coordinates is 0.004-0.04 mm
   median and 0.02-0.12 mm p95, against 0.003-0.11 and 0.02-0.32 mm without the pitch
   (``tests/core/test_rolled_layout.py``). A finger whose cap and pad are not told apart
   (curvatures within ``_CURVATURE_CONTRAST``) is taken as unpitched.

The result is a proper rotation of the image plane near the apex (slopes ~0 there), so
:func:`~fingerps_recon.surface.surface_unrolling.unroll_surface` places it as it places the
springs' layout (rotated onto the nodes' image positions, the apex at the origin).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from fingerps_recon.errors import UnrollingError
from fingerps_recon.surface.mesh_raster import rasterise_mesh

#: Grid rings the resampled surface is grown by beyond the mesh (``_grown``).
_GROWTH = 2
#: Passes that turn the axis onto the crest's direction, and the turn that ends them (rad).
_AXIS_PASSES = 3
_AXIS_TOLERANCE = 1e-3
#: Fewest sections with a crest of their own for the crest line (else the quadric's).
_MIN_CREST_SECTIONS = 5
#: Curvature ratio below which the quadric gives no axis (the image's axes are taken).
_ISOTROPIC = 0.8
#: The pitch's knot fit (``crest_pitch``): the crest within this of its point nearest the
#: camera (mm; the first pass: a finger pitched 15 deg back has that point ~L tan 15 deg =
#: 6.7 mm behind the knot), knots this far inside it and this far apart (mm), the fewest
#: crest points.
_PITCH_SEARCH_MM = 7.5
_PITCH_WINDOW_MM = 3.5
_KNOT_MARGIN_MM = 0.5
_KNOT_STEP_MM = 0.05
_PITCH_MIN_POINTS = 8
#: Passes of the fit, each in the frame turned by the pitch found before.
_PITCH_PASSES = 4
#: The cap's curvature over the pad's below which there is no knot to find.
_CURVATURE_CONTRAST = 1.5
#: Largest pitch taken (rad): the rig's limit (``FingertipShape.pitch_deg``, 15 deg).
_MAX_PITCH = math.radians(15.0)


def rolled_layout(points: np.ndarray, triangles: np.ndarray, apex: int, spacing_mm: float
                  ) -> np.ndarray:
    """(N, 2) rolled-plane (x, y) of the nodes, millimetres (module docstring).

    Parameters
    ----------
    points : (N, 3) float
        The mesh nodes' 3D points, optical frame, millimetres.
    triangles : (T, 3) int
        The mesh's triangles (node indices), over which the surface is interpolated.
    apex : int
        Index of the node nearest the camera (the origin of both arc lengths).
    spacing_mm : float
        The mesh's node spacing; the resampled surface's is half of it.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 6:
        raise UnrollingError("the rolled layout needs at least 6 nodes' 3D points (N, 3)")
    rel = pts - pts[apex]
    h = 0.5 * float(spacing_mm)
    across, along = _axis(rel)
    s, t, s_grid, t_grid, surface, line, across, along = _sections(rel, triangles, across,
                                                                   along, h)
    if line is not None:
        rows = np.arange(len(t_grid), dtype=np.float64)
        crest_col = (line[0] + line[1] * t_grid - s_grid[0]) / h
        crest_depth = ndimage.map_coordinates(surface, [rows, crest_col], order=1,
                                              cval=np.nan, prefilter=False)
        pitch = crest_pitch(t_grid, crest_depth)
        if pitch != 0.0:  # the sections again, across the finger's own axis
            rel = _pitched(rel, along, pitch)
            s, t, s_grid, t_grid, surface, line, across, along = _sections(
                rel, triangles, across, along, h)
    if line is None:  # too few sections with a crest of their own: the quadric's
        coef = _quadric(s, t, rel[:, 2])  # z ~ c0 + c1 s + c2 t + c3 s^2 + c4 s t + c5 t^2
        if not coef[3] > 0:
            raise UnrollingError("the surface is not convex across the finger: no crest to "
                                 "roll it from")
        line = (-coef[1] / (2 * coef[3]), -coef[4] / (2 * coef[3]))
    crest_s = line[0] + line[1] * t_grid
    crest_col = np.clip((crest_s - s_grid[0]) / h, 0.0, len(s_grid) - 1.001)
    zg = _continued_sections(surface, crest_col)

    # x: arc length along each section (grid row) from the crest.
    steps = np.sqrt(h * h + np.diff(_bridged(zg), axis=1) ** 2)
    arc = np.concatenate([np.zeros((len(t_grid), 1)),
                          np.cumsum(np.nan_to_num(steps, nan=h), axis=1)], axis=1)
    rows = np.arange(len(t_grid))
    c0 = crest_col.astype(np.int64)
    arc -= (arc[rows, c0] + (crest_col - c0) * (arc[rows, c0 + 1] - arc[rows, c0]))[:, None]

    # y: arc length along the crest from the apex's section.
    crest_z = _filled(ndimage.map_coordinates(zg, [rows.astype(np.float64), crest_col],
                                              order=1, cval=np.nan, prefilter=False))
    crest_steps = np.sqrt(h * h + (np.diff(crest_s)) ** 2 + np.diff(crest_z) ** 2)
    length = np.concatenate([[0.0], np.cumsum(crest_steps)])
    length -= np.interp(0.0, t_grid, length)

    x = ndimage.map_coordinates(arc, [(t - t_grid[0]) / h, (s - s_grid[0]) / h], order=1,
                                mode="nearest", prefilter=False)
    return np.stack([x, np.interp(t, t_grid, length)], axis=1)


def _sections(rel: np.ndarray, triangles: np.ndarray, across: np.ndarray, along: np.ndarray,
              h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                 tuple[float, float] | None, np.ndarray, np.ndarray]:
    """The nodes' (s, t), the grid's (s_grid, t_grid), the surface on it, the crest line
    (None: too few crests) and the axis (across, along), turned onto the crest (step 1)."""
    line = None
    for _ in range(_AXIS_PASSES):
        s, t = rel[:, :2] @ across, rel[:, :2] @ along
        s_grid = np.arange(s.min() - h, s.max() + 2 * h, h)
        t_grid = np.arange(t.min() - h, t.max() + 2 * h, h)
        surface = _surface_grid(s, t, rel[:, 2], triangles, s_grid, t_grid)
        line = _crest_line(surface, s_grid, t_grid)
        if line is None:
            break
        turn = math.atan(line[1])  # the crest's direction: the finger's own axis
        if abs(turn) < _AXIS_TOLERANCE:
            break
        c, si = math.cos(turn), math.sin(turn)
        across, along = c * across - si * along, c * along + si * across
    return s, t, s_grid, t_grid, surface, line, across, along


def crest_pitch(t: np.ndarray, depth: np.ndarray) -> float:
    """The finger's pitch (rad, + the tip towards the camera) from the crest's depth profile
    ``depth`` (mm; NaN: no crest) along it, ``t`` (mm): its slope where the tip's cap meets
    the pad. That point is the knot of two parabolas joined with one slope (the cap's
    curvature ~1/(e^2 R), the pad's ~1/L along the finger), fitted by least squares within
    ``_PITCH_SEARCH_MM`` of the crest's point nearest the camera, then again within
    ``_PITCH_WINDOW_MM`` of it in the frame turned by the pitch found so far
    (``_PITCH_PASSES``: the parabolas are the finger's own there, and that point moves
    onto the knot). 0 when the two curvatures are not told apart (within
    ``_CURVATURE_CONTRAST``) or the crest is too short."""
    known = np.isfinite(depth)
    t, z = np.asarray(t, dtype=np.float64)[known], np.asarray(depth, dtype=np.float64)[known]
    pitch = 0.0
    for k in range(_PITCH_PASSES):
        c, si = math.cos(pitch), math.sin(pitch)
        fit = _knot_fit(c * t + si * z, c * z - si * t,
                        _PITCH_SEARCH_MM if k == 0 else _PITCH_WINDOW_MM)
        if fit is None:
            return 0.0
        slope, tip, pad = fit
        turn = math.atan(slope)
        pitch = float(np.clip(pitch + turn, -_MAX_PITCH, _MAX_PITCH))
        if abs(turn) < _AXIS_TOLERANCE:
            break
    low, high = sorted((tip, pad))
    return pitch if low > 0 and high > _CURVATURE_CONTRAST * low else 0.0


def _knot_fit(t: np.ndarray, z: np.ndarray, window_mm: float
              ) -> tuple[float, float, float] | None:
    """(slope at the knot, curvature before it, after it) of ``crest_pitch``'s fit to the
    crest within ``window_mm`` of its point nearest the camera; None with fewer than
    ``_PITCH_MIN_POINTS`` points there."""
    if t.size < _PITCH_MIN_POINTS:
        return None
    near = np.abs(t - t[np.argmin(z)]) <= window_mm
    t, z = t[near], z[near]
    knots = np.arange(t.min() + _KNOT_MARGIN_MM, t.max() - _KNOT_MARGIN_MM, _KNOT_STEP_MM)
    if t.size < _PITCH_MIN_POINTS or knots.size == 0:
        return None
    d = t[None, :] - knots[:, None]
    design = np.stack([np.ones_like(d), d, 0.5 * d * d * (d < 0), 0.5 * d * d * (d >= 0)],
                      axis=2)
    transposed = design.transpose(0, 2, 1)
    coef = np.linalg.solve(transposed @ design, (transposed @ z)[..., None])
    residual = np.sum(((design @ coef)[..., 0] - z) ** 2, axis=1)
    _, slope, before, after = coef[int(np.argmin(residual)), :, 0]
    return float(slope), float(before), float(after)


def _pitched(rel: np.ndarray, along: np.ndarray, pitch: float) -> np.ndarray:
    """The nodes turned by ``pitch`` about the across axis: the finger's axis (the crest's
    direction where the cap meets the pad) into the image plane."""
    t = rel[:, :2] @ along
    c, si = math.cos(pitch), math.sin(pitch)
    out = rel.copy()
    out[:, :2] += ((c - 1.0) * t + si * rel[:, 2])[:, None] * along[None, :]
    out[:, 2] = c * rel[:, 2] - si * t
    return out


def _surface_grid(s: np.ndarray, t: np.ndarray, z: np.ndarray, triangles: np.ndarray,
                  s_grid: np.ndarray, t_grid: np.ndarray) -> np.ndarray:
    """(rows t, cols s) depth of the surface on the grid: linear over the mesh's triangles,
    grown by ``_GROWTH`` grid points beyond them, NaN elsewhere."""
    h = s_grid[1] - s_grid[0]
    depth = rasterise_mesh(np.c_[s, t], z, triangles, origin=(s_grid[0], t_grid[0]),
                           pitch=(h, h), shape=(len(t_grid), len(s_grid)))
    return _grown(depth.astype(np.float64), _GROWTH)


def _crest_line(zg: np.ndarray, s_grid: np.ndarray, t_grid: np.ndarray
                ) -> tuple[float, float] | None:
    """(a, b) of the crest s = a + b t: least squares through each section's point nearest
    the camera (a parabola through the grid's three nearest), where that point lies inside
    the section's known part, not at its end (a section cut short of its crest); None with
    fewer than ``_MIN_CREST_SECTIONS`` of them."""
    filled = np.where(np.isfinite(zg), zg, np.inf)
    col = np.argmin(filled, axis=1)
    rows = np.arange(len(t_grid))
    inner = (col > 0) & (col < len(s_grid) - 1) & np.isfinite(zg).any(axis=1)
    inner[inner] &= (np.isfinite(zg[rows[inner], col[inner] - 1])
                     & np.isfinite(zg[rows[inner], col[inner] + 1]))
    if int(inner.sum()) < _MIN_CREST_SECTIONS:
        return None
    r, c = rows[inner], col[inner]
    left, mid, right = zg[r, c - 1], zg[r, c], zg[r, c + 1]
    curve = left - 2 * mid + right
    offset = np.where(curve > 0, 0.5 * (left - right) / np.where(curve > 0, curve, 1.0), 0.0)
    crest = s_grid[0] + (c + np.clip(offset, -0.5, 0.5)) * (s_grid[1] - s_grid[0])
    slope, intercept = np.polyfit(t_grid[r], crest, 1)
    return float(intercept), float(slope)


def _continued_sections(zg: np.ndarray, crest_col: np.ndarray) -> np.ndarray:
    """``zg`` with each section that the image's edge cuts short of its crest continued to
    the crest by the nearest section that reaches it, shifted in depth to join the cut one
    at its edge (along a finger the sections change slowly: on the shaft each is the same
    one moved by the bend)."""
    known = np.isfinite(zg)
    rows = np.arange(zg.shape[0])
    crest = np.rint(crest_col).astype(np.int64)
    whole = known[rows, crest]
    if whole.all() or not whole.any():
        return zg
    cols = np.arange(zg.shape[1])[None, :]
    first = np.argmax(known, axis=1)[:, None]
    last = (zg.shape[1] - 1 - np.argmax(known[:, ::-1], axis=1))[:, None]
    cut = ~whole & known.any(axis=1)
    left = cut & (crest < first[:, 0])   # known part on the right of the crest
    right = cut & (crest > last[:, 0])   # known part on the left
    edge = np.where(left, first[:, 0], last[:, 0])
    # For every row, the nearest row whose section reaches its crest and the cut edge.
    donor = np.flatnonzero(whole)
    distance = np.abs(rows[:, None] - donor[None, :]).astype(np.float64)
    distance[~known[donor[None, :], edge[:, None]]] = np.inf
    nearest = donor[distance.argmin(axis=1)]
    offset = zg[rows, edge] - zg[nearest, edge]
    gap = ((left[:, None] & (cols >= crest[:, None] - 1) & (cols < first))
           | (right[:, None] & (cols > last) & (cols <= crest[:, None] + 1)))
    filled = zg[nearest] + offset[:, None]
    return np.where(gap, filled, zg)


def _grown(zg: np.ndarray, rings: int) -> np.ndarray:
    """``zg`` grown by ``rings`` grid points beyond its known ones, continued linearly from
    the two before along the sections (s), then along the finger (t), and the mean of both
    where both reach (the nodes on the mesh's outline sit on its edge, where the grid points
    around them are half outside; steep there, so a flat continuation would shorten arcs)."""
    for _ in range(rings):
        total = np.zeros_like(zg)
        count = np.zeros_like(zg)
        for axis in (0, 1):
            for step in (1, -1):
                one = np.roll(zg, step, axis=axis)
                two = np.roll(zg, 2 * step, axis=axis)
                edge = [slice(None)] * 2
                edge[axis] = slice(0, 2) if step == 1 else slice(-2, None)
                one[tuple(edge)] = np.nan
                line = 2.0 * one - two
                ok = np.isfinite(line) & ~np.isfinite(zg)
                total[ok] += line[ok]
                count[ok] += 1.0
        zg = np.where(count > 0, total / np.maximum(count, 1.0), zg)
    return zg


def _bridged(zg: np.ndarray) -> np.ndarray:
    """``zg`` with each row's inner gaps (NaN between known values) filled linearly."""
    known = np.isfinite(zg)
    cols = np.arange(zg.shape[1])
    before = np.maximum.accumulate(np.where(known, cols, -1), axis=1)
    after = np.minimum.accumulate(np.where(known, cols, zg.shape[1])[:, ::-1], axis=1)[:, ::-1]
    inner = ~known & (before >= 0) & (after < zg.shape[1])
    rows = np.nonzero(inner)[0]
    b, a = before[inner], after[inner]
    weight = (cols[None, :].repeat(len(zg), 0)[inner] - b) / (a - b)
    out = zg.copy()
    out[inner] = (1 - weight) * zg[rows, b] + weight * zg[rows, a]
    return out


def _axis(rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(across, along): unit image-plane directions, a proper rotation of (x, y), ``along``
    the direction of least curvature (pointing down the image)."""
    coef = _quadric(rel[:, 0], rel[:, 1], rel[:, 2])
    hessian = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    values, vectors = np.linalg.eigh(hessian)
    order = np.argsort(np.abs(values))
    if abs(values[order[0]]) > _ISOTROPIC * abs(values[order[1]]):
        return np.array([1.0, 0.0]), np.array([0.0, 1.0])
    along = vectors[:, order[0]]
    along = along if along[1] >= 0 else -along
    return np.array([along[1], -along[0]]), along


def _quadric(s: np.ndarray, t: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Least-squares (c0..c5) of z ~ c0 + c1 s + c2 t + c3 s^2 + c4 s t + c5 t^2."""
    design = np.stack([np.ones_like(s), s, t, s * s, s * t, t * t], axis=1)
    return np.linalg.lstsq(design, z, rcond=None)[0]


def _filled(profile: np.ndarray) -> np.ndarray:
    """A 1-D profile with its NaN ends and gaps filled linearly from the known values."""
    known = np.isfinite(profile)
    if not known.any():
        raise UnrollingError("the crest of the finger is not on the surface seen")
    index = np.arange(profile.size)
    return np.interp(index, index[known], profile[known])
