"""Unroll a reconstructed fingertip onto a plane, keeping distances along the skin.

Nonparametric unwrapping as in Chen, Parziale, Diaz-Santana & Jain, "3D touchless
fingerprints: compatibility with legacy rolled images" (Biometric Consortium Conference,
2006): the surface is not fitted by a cylinder or an ellipsoid; a mesh of surface points is
laid out in the plane so that the distances between neighbouring points in the plane equal
their distances in 3D, as a network of springs at rest.

Steps (:func:`unroll_surface`):

1. Mesh. The image is cut into square blocks of ``s`` pixels (``spacing_mm`` at the median
   depth, 17 px = 0.5 mm on the rig); one node per block centre. The depth at a node is a
   local quadric fit z = a + b du + c dv + d du^2 + e du dv + f dv^2 to the masked depths
   of the blocks around it (Gaussian weights, sigma ``smoothing_nodes`` blocks: normalized
   convolution, Knutsson & Westin 1993, assembled from per-block moments, so it costs a
   few dozen convolutions of the small node grid). This smooths the surface at the mesh
   scale, so the ridges (~0.5 mm) do not enter the geometry (50 um ridges move the layout
   by ~1 um), and unlike a masked mean or a plane it is unbiased for the steep, curved
   margin of a finger at the edge of the mask. A node's 3D point is its depth times its
   pixel's ray K^-1 (u, v, 1).
2. Springs. Each pair of valid 4- and diagonal neighbours is a spring of rest length L_ij =
   |P_i - P_j| (3D). Initial layout: x = signed 3D arc length along each mesh row from the
   apex column, y = the same along each mesh column from the apex row (the grid's own
   orientation: x right, y down as in the image, the skin seen from outside as the camera
   sees it; :func:`fingerps_recon.surface.rolled_print.rolled_print` mirrors it left-right into
   the legacy orientation of rolled prints).
3. Relaxation: minimise sum_ij ((|x_i - x_j| - L_ij) / L_ij)^2 (relative strain, every
   spring weighted alike) by Levenberg-Marquardt; the normal equations are banded in the
   row-major node order, so each step is a banded Cholesky solve (~600-800 nodes on the
   rig, 3 iterations).
4. Rigid motion: the layout is rotated onto the image-plane positions of its nodes
   (Procrustes without reflection), so the finger keeps its direction in the image (the
   rig's finger points up the image), and shifted so that the apex (the node nearest the
   camera) is at the origin.

A developable surface (a cylinder) unrolls with zero strain; a doubly curved one (a
fingertip's cap, a sphere) cannot, and the residual strain (rms and max of
|x_i - x_j| / L_ij - 1) says how much the layout stretches the skin.

``layout=Layout.ROLLED`` lays the same mesh out as a finger rolled on a card instead
(:mod:`fingerps_recon.surface.rolled_layout`: arc lengths around and along the finger),
the plane of rolled and contact prints; the springs are still relaxed, for the strain
figures (how far the surface is from developable), and step 4 places either layout.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from enum import Enum
from functools import cached_property

import cv2
import numpy as np
import scipy.linalg

from fingerps_recon.errors import UnrollingError
from fingerps_recon.photometric.pixel_rays import checked_camera_matrix
from fingerps_recon.surface import print_kernel
from fingerps_recon.surface.mesh_raster import rasterise_mesh
from fingerps_recon.surface.rolled_layout import rolled_layout

# Neighbour offsets (rows, cols) of the springs: right, down, down-right, down-left.
_SPRINGS = ((0, 1), (1, 0), (1, 1), (1, -1))
# Levenberg-Marquardt: stop when the largest node step is below this (mm; a tenth of a
# 500 ppi pixel) ...
_STEP_TOLERANCE_MM = 5e-3
# ... or the relative decrease of the cost below this.
_COST_TOLERANCE = 1e-4
_LAMBDA_START = 1e-4
# Smallest eigenvalue of a node's normalised local-fit system (a sliver is left out).
_MIN_FIT_CONDITION = 1e-4


class Layout(Enum):
    """How the mesh is laid out in the plane."""

    SPRINGS = "springs"
    """Every neighbour distance kept as well as it can be (steps 2-3 above)."""
    ROLLED = "rolled"
    """Arc lengths around and along the finger, as rolling it on a card lays it out
    (:mod:`fingerps_recon.surface.rolled_layout`)."""


@dataclass(frozen=True)
class SurfaceUnrolling:
    """Result of :func:`unroll_surface`: the forward map from the image to the unrolled
    plane (x right, y down, millimetres, origin at the apex) and its inverse.

    Attributes
    ----------
    grid_shape : (gh, gw)
        Mesh rows and columns (one node per block of ``step_px`` pixels).
    step_px : int
        Block size, pixels.
    node_valid : (gh, gw) bool
        Nodes on the surface.
    node_pixel : (N, 2) float64
        Source pixel (col, row) of each valid node (row-major order of ``node_valid``).
    node_point_mm : (N, 3) float64
        Smoothed 3D point of each valid node, optical frame, millimetres.
    node_xy_mm : (N, 2) float64
        Unrolled position of each valid node, millimetres.
    springs : (E, 2) int
        Indices of the node pairs joined by a spring.
    spring_strain : (E,) float64
        |x_i - x_j| / L_ij - 1 of each spring after relaxation (the springs' layout, also
        when ``node_xy_mm`` is the rolled one: how far the surface is from developable).
    strain_rms, strain_max : float
        Root mean square and largest absolute spring strain.
    mask : (H, W) bool
        The source pixels with a valid depth that were unrolled.
    iterations : int
        Levenberg-Marquardt iterations used.
    """

    grid_shape: tuple[int, int]
    step_px: int
    node_valid: np.ndarray
    node_pixel: np.ndarray
    node_point_mm: np.ndarray
    node_xy_mm: np.ndarray
    springs: np.ndarray
    spring_strain: np.ndarray
    strain_rms: float
    strain_max: float
    mask: np.ndarray
    iterations: int

    @property
    def bounds_mm(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the nodes, millimetres."""
        lo, hi = self.node_xy_mm.min(axis=0), self.node_xy_mm.max(axis=0)
        return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])

    @cached_property
    def pixel_xy_mm(self) -> np.ndarray:
        """(H, W, 2) float32 unrolled (x, y) of every pixel, millimetres (bilinear between
        the nodes, linearly extrapolated up to two nodes beyond them); NaN outside
        ``mask``. Computed on first use."""
        grid, _ = self._extended
        step = self.step_px
        h, w = self.mask.shape
        up = cv2.resize(grid.astype(np.float32), (grid.shape[1] * step, grid.shape[0] * step),
                        interpolation=cv2.INTER_LINEAR)[step:step + h, step:step + w]
        up[~self.mask] = np.nan
        return up

    @cached_property
    def _extended(self) -> tuple[np.ndarray, np.ndarray]:
        """The node grid padded by one node on every side, with two rings of nodes
        extrapolated beyond the valid ones (they reach the mask's outline, which lies up
        to ~half a block beyond the outermost node): (gh + 2, gw + 2, 2) unrolled (x, y),
        NaN where empty, and the filled nodes."""
        return _extended_grid(self.node_xy_mm, self.node_valid)

    @cached_property
    def _mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Triangles of the extended grid: unrolled (x, y) (M, 2) and source pixel
        (col, row) (M, 2) of its nodes, and (T, 3) node indices (two triangles per cell,
        one where a corner is missing)."""
        grid, filled = self._extended
        step = self.step_px
        index = np.full(filled.shape, -1, dtype=np.int64)
        index[filled] = np.arange(int(filled.sum()))
        rows, cols = np.nonzero(filled)
        pixels = np.stack([(cols - 1) * step + (step - 1) / 2.0,
                           (rows - 1) * step + (step - 1) / 2.0], axis=1)
        return grid[filled], pixels, cell_triangles(index)

    def source_pixels(
        self, x_mm: np.ndarray, y_mm: np.ndarray, *, coarse_step: int = 4
    ) -> tuple[np.ndarray, np.ndarray]:
        """Inverse map: source pixel (col, row) of each point of a regular grid.

        Piecewise linear over the mesh's triangles in the unrolled plane (barycentric
        interpolation of the nodes' pixel positions; the mesh includes the two rings of
        extrapolated nodes of ``pixel_xy_mm``, so it reaches the mask's outline),
        evaluated every ``coarse_step`` grid points and interpolated bilinearly in between
        (the map is linear at the mesh scale, ~10 print pixels at 500 ppi).

        Parameters
        ----------
        x_mm : (Wo,) float
            Evenly spaced x of the grid's columns, millimetres.
        y_mm : (Ho,) float
            Evenly spaced y of the grid's rows.
        coarse_step : int
            Grid points between exact evaluations (1: every point).

        Returns
        -------
        map_x, map_y : (Ho, Wo) float32
            Source column and row, ready for ``cv2.remap``; NaN where the grid point is
            off the unrolled surface.
        """
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        if x.ndim != 1 or y.ndim != 1 or x.size < 2 or y.size < 2:
            raise UnrollingError("x_mm and y_mm must be 1-D arrays of at least 2 coordinates")
        step = max(1, int(coarse_step))
        dx = (x[-1] - x[0]) / (x.size - 1)
        dy = (y[-1] - y[0]) / (y.size - 1)
        cw = (x.size - 1) // step + 2  # one coarse point past the last grid point
        ch = (y.size - 1) // step + 2
        coarse = rasterise_mesh(*self._mesh, origin=(x[0], y[0]),
                                pitch=(dx * step, dy * step), shape=(ch, cw))
        fx = np.broadcast_to((np.arange(x.size, dtype=np.float32) / step)[None, :],
                             (y.size, x.size))
        fy = np.broadcast_to((np.arange(y.size, dtype=np.float32) / step)[:, None],
                             (y.size, x.size))
        fine = cv2.remap(coarse, np.ascontiguousarray(fx), np.ascontiguousarray(fy),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return fine[..., 0], fine[..., 1]


def unroll_surface(
    depth_m: np.ndarray,
    *,
    mask: np.ndarray,
    camera_matrix: np.ndarray,
    spacing_mm: float = 0.5,
    smoothing_nodes: float = 1.0,
    fit_order: int = 2,
    min_fill: float = 0.3,
    max_iterations: int = 50,
    min_nodes: int = 16,
    layout: Layout = Layout.SPRINGS,
) -> SurfaceUnrolling:
    """Unroll the surface seen in a depth map onto a plane (springs model, see the module).

    Parameters
    ----------
    depth_m : (H, W) float
        Optical z of each pixel's surface point, metres; non-finite outside the surface.
    mask : (H, W) bool
        The surface (finger) pixels.
    camera_matrix : (3, 3) float
        Pinhole intrinsics K.
    spacing_mm : float
        Mesh spacing in the image plane at the median depth, millimetres (>= 2 pixels).
        0.4 mm has twice the nodes (and the time) and halves the distance error at 50-60 deg
        slopes (1.75 % -> 1.2 % at worst on an 8 mm cylinder).
    smoothing_nodes : float
        Gaussian sigma of the local depth fit's weights, in mesh nodes (0: each block
        alone).
    fit_order : int
        Degree of the local polynomial fit of the depth: 1 (plane) or 2 (quadric, no
        curvature bias at the steep margins: 0.04 mm of depth at 60 deg on an 8 mm
        cylinder with a plane fit).
    min_fill : float
        Smallest fraction of a block's pixels on the surface for its node to be used.
    max_iterations : int
        Levenberg-Marquardt iterations at most.
    min_nodes : int
        Fewer valid nodes raise :class:`UnrollingError`.
    layout : Layout
        The map to the plane: the springs (steps 2-3 of the module docstring) or the
        rolled finger's arc lengths (:mod:`fingerps_recon.surface.rolled_layout`).

    Returns
    -------
    SurfaceUnrolling
    """
    k = checked_camera_matrix(camera_matrix)
    depth = np.asarray(depth_m)
    if not np.issubdtype(depth.dtype, np.floating):
        depth = depth.astype(np.float64)
    if depth.ndim != 2 or np.shape(mask) != depth.shape:
        raise UnrollingError(f"depth {depth.shape} and mask {np.shape(mask)} must be the same "
                             "(H, W) shape")
    valid = np.asarray(mask, dtype=bool) & np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise UnrollingError("no pixel with a finite positive depth inside the mask")
    if (not spacing_mm > 0 or not smoothing_nodes >= 0 or not 0 < min_fill <= 1
            or fit_order not in (1, 2)):
        raise UnrollingError("spacing_mm must be > 0, smoothing_nodes >= 0, 0 < min_fill <= 1 "
                             "and fit_order 1 or 2")
    z_ref_mm = 1e3 * float(np.median(depth[valid][::7].astype(np.float64)))
    pixel_mm = z_ref_mm / k[0, 0]
    step = max(2, round(spacing_mm / pixel_mm))

    node_valid, node_z_mm = _node_depths(depth, valid, step, smoothing_nodes, min_fill,
                                         z_ref_mm, fit_order)
    count = int(node_valid.sum())
    if count < min_nodes:
        raise UnrollingError(
            f"only {count} mesh nodes on the surface (at least {min_nodes} needed): the "
            "surface is too small or too fragmented to unroll")
    gh, gw = node_valid.shape
    rows, cols = np.nonzero(node_valid)
    pix = np.stack([cols * step + (step - 1) / 2.0, rows * step + (step - 1) / 2.0], axis=1)
    rays = np.concatenate([pix, np.ones((count, 1))], axis=1) @ np.linalg.inv(k).T
    points = (z_ref_mm + node_z_mm[rows, cols])[:, None] * rays

    index = np.full((gh, gw), -1, dtype=np.int64)
    index[rows, cols] = np.arange(count)
    springs = _springs(index)
    if springs.shape[0] < count:
        raise UnrollingError(f"the {count} mesh nodes are too loosely connected to unroll")
    rest = np.linalg.norm(points[springs[:, 1]] - points[springs[:, 0]], axis=1)

    apex = int(np.argmin(node_z_mm[rows, cols]))
    init = _arc_length_layout(points, index, rows[apex], cols[apex], step * pixel_mm)
    xy, iterations = _relax(init, springs, rest, max_iterations)
    # The springs' strain says how far the surface is from developable, whichever layout.
    strain = np.linalg.norm(xy[springs[:, 1]] - xy[springs[:, 0]], axis=1) / rest - 1.0
    if layout is Layout.ROLLED:
        xy = rolled_layout(points, cell_triangles(index), apex, step * pixel_mm)
    xy = _rigid_to_image(xy, pix * pixel_mm, apex)
    return SurfaceUnrolling(
        grid_shape=(gh, gw), step_px=step, node_valid=node_valid, node_pixel=pix,
        node_point_mm=points, node_xy_mm=xy, springs=springs, spring_strain=strain,
        strain_rms=float(np.sqrt(np.mean(strain**2))), strain_max=float(np.abs(strain).max()),
        mask=valid, iterations=iterations)


def _node_depths(depth: np.ndarray, valid: np.ndarray, step: int, sigma: float,
                 min_fill: float, z_ref_mm: float, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Local polynomial fit of the depth (mm, relative to ``z_ref_mm``) at each block
    centre: weighted least squares of z over the masked pixels of the blocks around it,
    Gaussian weights (sigma in blocks) per block (normalized convolution, Knutsson &
    Westin 1993).

    Moments of each block about its own centre (coordinates in blocks) are computed once;
    a neighbour block's moments about the target node's centre follow by the binomial
    shift sum_p C(k, p) a^(k - p) S_p, so the whole fit is a few dozen small correlations
    of the (gh, gw) moment grids and one small solve per node. Only the blocks of the box
    of ``valid`` are fitted (the others hold no surface)."""
    full_shape = (-(-depth.shape[0] // step), -(-depth.shape[1] // step))
    rows = np.flatnonzero(valid.any(axis=1))
    cols = np.flatnonzero(valid.any(axis=0))
    br, bc = rows[0] // step, cols[0] // step
    box = (slice(br * step, (rows[-1] // step + 1) * step),
           slice(bc * step, (cols[-1] // step + 1) * step))
    depth, valid = depth[box], valid[box]
    h, w = depth.shape
    gh, gw = -(-h // step), -(-w // step)
    d = (np.arange(step) - (step - 1) / 2.0) / step  # offset in blocks within a block
    powers = d[:, None] ** np.arange(2 * order + 1)  # (s, 2 order + 1)
    # mom[i, j, k, l] = sum over block (i, j) of m du^k dv^l (m: the mask; du along
    # columns, dv rows), zmom the same of z m
    mom = np.empty((gh, gw, 2 * order + 1, 2 * order + 1))
    zmom = np.empty((gh, gw, order + 1, order + 1))
    print_kernel.block_moments(depth, valid, z_ref_mm, powers, order + 1, mom, zmom)

    def shifted(moments: np.ndarray, k: int, el: int) -> np.ndarray:
        """Gaussian-weighted sum over neighbour blocks of sum m du^k dv^l about the node."""
        out = np.zeros(moments.shape[:2])
        for (p, q), kern in _shift_kernels(float(sigma), k, el):
            out += cv2.filter2D(moments[..., p, q], -1, kern, borderType=cv2.BORDER_CONSTANT)
        return out

    terms = [(k, n - k) for n in range(order + 1) for k in range(n, -1, -1)]
    cache: dict[tuple[int, int], np.ndarray] = {}
    node_valid = mom[..., 0, 0] >= min_fill * step * step
    mat = np.empty((int(node_valid.sum()), len(terms), len(terms)))
    for i, (k1, l1) in enumerate(terms):
        for j, (k2, l2) in enumerate(terms):
            key = (k1 + k2, l1 + l2)
            if key not in cache:
                cache[key] = shifted(mom, *key)[node_valid]
            mat[:, i, j] = cache[key]
    rhs = np.stack([shifted(zmom, k, el)[node_valid] for k, el in terms], axis=-1)
    # Smallest eigenvalue of the normalised system: the spread of the pixels around the
    # node along its least-covered direction (blocks^2k); a sliver of a block is left out.
    scale = 1.0 / np.sqrt(np.einsum("nii->ni", mat))
    norm = mat * scale[:, :, None] * scale[:, None, :]
    good = np.linalg.eigvalsh(norm)[:, 0] > _MIN_FIT_CONDITION
    sol = np.zeros_like(rhs)
    sol[good] = np.linalg.solve(mat[good], rhs[good][..., None])[..., 0]
    out = np.zeros(full_shape)
    out[br:br + gh, bc:bc + gw][node_valid] = sol[:, 0]
    idx = np.flatnonzero(node_valid)
    node_valid.reshape(-1)[idx[~good]] = False
    full_valid = np.zeros(full_shape, dtype=bool)
    full_valid[br:br + gh, bc:bc + gw] = node_valid
    return full_valid, out


@functools.lru_cache(maxsize=64)
def _shift_kernels(sigma: float, k: int, el: int) -> tuple[tuple[tuple[int, int], np.ndarray], ...]:
    """The correlation kernels of :func:`_node_depths`' binomial shift of the moments of
    order (k, el): ((p, q), C(k, p) C(el, q) g a^(k - p) b^(el - q)) over the neighbour
    blocks (a, b) (columns, rows; Gaussian weights g of sigma ``sigma`` blocks). They depend
    on the options only, so they are made once."""
    radius = max(0, math.ceil(2.5 * sigma))
    b, a = np.mgrid[-radius:radius + 1, -radius:radius + 1].astype(np.float64)  # rows, cols
    g = np.exp(-(a * a + b * b) / (2 * sigma * sigma)) if sigma > 0 else np.ones_like(a)
    kernels = []
    for p in range(k + 1):
        for q in range(el + 1):
            if radius == 0 and (k - p or el - q):
                continue  # a single block: no shift
            kern = math.comb(k, p) * math.comb(el, q) * g * a ** (k - p) * b ** (el - q)
            kern.setflags(write=False)
            kernels.append(((p, q), kern))
    return tuple(kernels)


def cell_triangles(index: np.ndarray) -> np.ndarray:
    """(T, 3) node indices of a node grid's triangles (``index``: (gh, gw) node index, -1
    where there is none): two a cell, one where a corner is missing."""
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    ad = (a >= 0) & (d >= 0)
    bc = ~ad & (b >= 0) & (c >= 0)
    tris = [np.stack([a, b, d], -1)[ad & (b >= 0)], np.stack([a, d, c], -1)[ad & (c >= 0)],
            np.stack([a, b, c], -1)[bc & (a >= 0)], np.stack([b, d, c], -1)[bc & (d >= 0)]]
    return np.concatenate(tris, axis=0)


def _springs(index: np.ndarray) -> np.ndarray:
    """(E, 2) node index pairs of valid 4- and diagonal neighbours."""
    gh, gw = index.shape
    pairs = []
    for dr, dc in _SPRINGS:
        c0, c1 = max(0, -dc), gw - max(0, dc)
        a = index[0:gh - dr, c0:c1]
        b = index[dr:gh, c0 + dc:c1 + dc]
        both = (a >= 0) & (b >= 0)
        pairs.append(np.stack([a[both], b[both]], axis=1))
    return np.concatenate(pairs, axis=0)


def _arc_length_layout(points: np.ndarray, index: np.ndarray, r0: int, c0: int,
                       nominal_mm: float) -> np.ndarray:
    """Initial layout: 3D arc length along mesh rows (x) and columns (y) from the apex's
    column and row; a step with a missing end counts as ``nominal_mm``."""
    gh, gw = index.shape
    grid = np.full((gh, gw, 3), np.nan)
    grid[index >= 0] = points
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=-1)
    dx = np.where(np.isfinite(dx), dx, nominal_mm)
    dy = np.where(np.isfinite(dy), dy, nominal_mm)
    x = np.concatenate([np.zeros((gh, 1)), np.cumsum(dx, axis=1)], axis=1)
    y = np.concatenate([np.zeros((1, gw)), np.cumsum(dy, axis=0)], axis=0)
    x -= x[:, c0:c0 + 1]
    y -= y[r0:r0 + 1, :]
    return np.stack([x[index >= 0], y[index >= 0]], axis=1)


def _relax(xy: np.ndarray, springs: np.ndarray, rest: np.ndarray,
           max_iterations: int) -> tuple[np.ndarray, int]:
    """Levenberg-Marquardt on the relative spring strains (|x_i - x_j| - L) / L.

    The normal equations are banded (springs join nodes at most one mesh row apart in the
    row-major node order), so each step is a banded Cholesky solve (LAPACK pbsv), the
    matrix assembled by ``np.bincount`` straight into LAPACK's lower band storage."""
    n = xy.shape[0]
    i, j = springs[:, 0], springs[:, 1]
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    bands = 2 * int((hi - lo).max()) + 2  # the diagonal and the sub-diagonals of J^T J
    size = 2 * n
    # Flat indices into the (bands, 2n) lower band storage ab[r - c, c] = A[r, c], r >= c:
    # the 2x2 blocks (lo, lo) and (hi, hi) get +u u^T, the block (hi, lo) -u u^T.
    def at(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return (r - c) * size + c

    diag_xx = np.concatenate([at(2 * lo, 2 * lo), at(2 * hi, 2 * hi)])
    diag_xy = np.concatenate([at(2 * lo + 1, 2 * lo), at(2 * hi + 1, 2 * hi)])
    diag_yy = np.concatenate([at(2 * lo + 1, 2 * lo + 1), at(2 * hi + 1, 2 * hi + 1)])
    off = np.stack([at(2 * hi, 2 * lo), at(2 * hi + 1, 2 * lo), at(2 * hi, 2 * lo + 1),
                    at(2 * hi + 1, 2 * lo + 1)])
    flat = np.concatenate([diag_xx, diag_xy, diag_yy, off.ravel()])
    grad_index = np.concatenate([2 * i, 2 * i + 1, 2 * j, 2 * j + 1])

    def residual(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = p[j] - p[i]
        length = np.linalg.norm(d, axis=1)
        return length / rest - 1.0, d, length

    r, d, length = residual(xy)
    cost = float(r @ r)
    lam = _LAMBDA_START
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 - reported
        # Row of the Jacobian of spring e: -u at node i, +u at node j.
        u = d / (np.maximum(length, 1e-12) * rest)[:, None]
        uxx, uxy, uyy = u[:, 0] * u[:, 0], u[:, 0] * u[:, 1], u[:, 1] * u[:, 1]
        weights = np.concatenate([uxx, uxx, uxy, uxy, uyy, uyy, -uxx, -uxy, -uxy, -uyy])
        jtj = np.bincount(flat, weights, minlength=bands * size).reshape(bands, size)
        ur = u * r[:, None]
        g = np.bincount(grad_index, np.concatenate([-ur[:, 0], -ur[:, 1], ur[:, 0], ur[:, 1]]),
                        minlength=size)
        diag = jtj[0].copy()
        improved = False
        for _ in range(8):
            a = jtj.copy()
            a[0] += lam * (diag + 1e-9 * diag.mean())
            try:
                step = -scipy.linalg.solveh_banded(a, g, lower=True, overwrite_ab=True,
                                                   check_finite=False).reshape(n, 2)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            trial = xy + step
            r_t, d_t, len_t = residual(trial)
            cost_t = float(r_t @ r_t)
            if cost_t < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        done = (cost - cost_t) <= _COST_TOLERANCE * cost or np.abs(step).max() < _STEP_TOLERANCE_MM
        xy, r, d, length, cost = trial, r_t, d_t, len_t, cost_t
        lam = max(lam / 10.0, 1e-9)
        if done:
            break
    return xy, iterations


def _rigid_to_image(xy: np.ndarray, image_mm: np.ndarray, apex: int) -> np.ndarray:
    """Rotate ``xy`` onto ``image_mm`` (least squares, no reflection); apex at the origin."""
    a = xy - xy.mean(axis=0)
    b = image_mm - image_mm.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    sign = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag([1.0, sign]) @ vt
    out = xy @ rot
    return out - out[apex]


def _extended_grid(xy: np.ndarray, node_valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """See ``SurfaceUnrolling._extended``."""
    gh, gw = node_valid.shape[0] + 2, node_valid.shape[1] + 2
    # Two more empty nodes on every side, so that the neighbours two steps away of every
    # grid node are array slices (they hold no node beyond the grid).
    pad = 2
    grid = np.zeros((gh + 2 * pad, gw + 2 * pad, 2))
    weight = np.zeros((gh + 2 * pad, gw + 2 * pad))
    inner = (slice(pad + 1, pad + gh - 1), slice(pad + 1, pad + gw - 1))
    grid[inner][node_valid] = xy
    weight[inner] = node_valid
    core = (slice(pad, pad + gh), slice(pad, pad + gw))
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))

    def shifted(a: np.ndarray, dr: int, dc: int) -> np.ndarray:
        """a at the node (r - dr, c - dc) of each grid node (r, c)."""
        return a[pad - dr:pad - dr + gh, pad - dc:pad - dc + gw]

    for _ in range(2):  # extrapolate one ring of nodes at a time (linear from two back)
        has = (weight > 0).astype(np.uint8)
        new = (cv2.dilate(has, cross)[core] > 0) & (weight[core] == 0)
        if not new.any():
            break
        # Linear extrapolation along each axis where possible, else the neighbours' mean.
        acc = np.zeros((gh, gw, 2))
        cnt = np.zeros((gh, gw))
        for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            ok = new & (shifted(weight, dr, dc) > 0) & (shifted(weight, 2 * dr, 2 * dc) > 0)
            acc[ok] += 2 * shifted(grid, dr, dc)[ok] - shifted(grid, 2 * dr, 2 * dc)[ok]
            cnt[ok] += 1
        fallback = new & (cnt == 0)
        if fallback.any():
            wsum = cv2.boxFilter(weight, -1, (3, 3), normalize=False,
                                 borderType=cv2.BORDER_CONSTANT)[core]
            total = cv2.boxFilter(grid * weight[..., None], -1, (3, 3), normalize=False,
                                  borderType=cv2.BORDER_CONSTANT)[core]
            acc[fallback] = total[fallback] / wsum[fallback][:, None]
            cnt[fallback] = 1
        grid[core][new] = acc[new] / cnt[new][:, None]
        weight[core][new] = 1.0
    grid, filled = grid[core].copy(), weight[core] > 0
    grid[~filled] = np.nan
    return grid, filled
