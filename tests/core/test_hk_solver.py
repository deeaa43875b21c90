"""Tests of fingerps_recon.photometric.hk_solver on rendered HK and Lambertian scenes.

The solver runs the compiled passes of fingerps_recon.photometric.hk_*_kernel (numba is
required); its minimum is checked against scipy's least_squares per pixel (float64), on a
small scene and on the rig's finger with the node's per-pixel lights. The first test of a
session compiles the kernels or loads them from numba's on-disk cache.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from analytic_surfaces import sphere_normals
from scipy.optimize import least_squares

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric import hk_solver, kernel_threads
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.hk_model import PhaseConvention, SkinParams, hk_reflectance
from fingerps_recon.photometric.hk_solver import HKResult, solve_hk
from fingerps_recon.photometric.lambertian import lambertian_shading, solve_lambertian

# Seven lights around the camera at 21-26 degrees from its axis, as on the rig (PS frame).
_AZIMUTH = np.radians([8.0, 57.0, 110.0, 160.0, 209.0, 262.0, 313.0])
_TILT = np.radians([23.0, 25.0, 22.0, 26.0, 24.0, 21.0, 25.5])
LIGHTS = np.stack(
    [np.cos(_AZIMUTH) * np.sin(_TILT), np.sin(_AZIMUTH) * np.sin(_TILT), np.cos(_TILT)], axis=1
)
INTENSITIES = np.array([1.0, 0.93, 1.06, 0.88, 0.97, 1.04, 0.91])
SCALE = 45.0  # the rig's A: the single-scattering term is ~10 % of the signal
def _surface(size: int = 61, *, ridges: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H, W, 3) of a sphere cap out to 72 degrees (PS frame; tests/
    analytic_surfaces.sphere_normals), optionally with ridges along x, and its mask."""
    sphere, mask, _ = sphere_normals(size, size, radius_px=(size - 1) / 2 - 0.5, within=0.9)
    x, y, z = sphere[mask].T
    gx, gy = -x / z, -y / z
    if ridges:
        gx = gx + 0.25 * np.cos(2 * np.pi * x / 0.25)
    n = np.stack([-gx, -gy, np.ones_like(x)], axis=-1)
    normals = np.zeros_like(sphere)
    normals[mask] = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return normals, mask


def _perspective_views(size: int, focal_px: float = 200.0) -> np.ndarray:
    """(H, W, 3) unit directions towards a pinhole camera (PS frame)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    half = (size - 1) / 2
    towards = np.stack([-(u - half) / focal_px, (v - half) / focal_px, np.ones_like(u)], axis=-1)
    return towards / np.linalg.norm(towards, axis=-1, keepdims=True)


def _render(
    normals: np.ndarray, mask: np.ndarray, rho: np.ndarray, *, scale: float = SCALE,
    lights: np.ndarray = LIGHTS, views: np.ndarray | None = None,
    params: SkinParams = SkinParams(),  # noqa: B008
) -> np.ndarray:
    lgt = lights[:, None, None, :] if lights.ndim == 2 else lights
    v = np.array([0.0, 0.0, 1.0]) if views is None else views
    image = hk_reflectance(normals, lgt, v, rho=rho, scale=scale, params=params)
    return image * INTENSITIES[:, None, None] * mask


def _solve(images: np.ndarray, mask: np.ndarray, **kwargs: object) -> tuple[HKResult, object]:
    lam = solve_lambertian(images, LIGHTS, intensities=INTENSITIES, mask=mask)
    res = solve_hk(
        images, kwargs.pop("lights", LIGHTS), mask=lam.valid, init_normals=lam.normals,
        init_albedo=lam.albedo, intensities=INTENSITIES, **kwargs,
    )
    return res, lam


def _slopes_to_normal(p: float, q: float) -> np.ndarray:
    n = np.array([-p, -q, 1.0])
    return n / np.linalg.norm(n)


def test_same_minimum_as_scipy_least_squares_per_pixel() -> None:
    # An HK-rendered scene with 1 % noise, perspective views. The batched solver (A fitted)
    # and scipy's least_squares per pixel, with A fixed to the batched A, started from the
    # same Lambertian initialisation, must reach the same minimum of the same residual.
    normals, mask = _surface()
    rng = np.random.default_rng(1)
    rho = rng.uniform(0.4, 0.6, mask.shape)
    views = _perspective_views(mask.shape[0])
    images = _render(normals, mask, rho, views=views)
    images = images + 0.01 * rng.standard_normal(images.shape)
    usable = images > 0
    res, lam = _solve(images, mask, views=views, iterations=60, tol=0.0)
    scale = res.scale

    def residual(x: np.ndarray, r: int, c: int) -> np.ndarray:
        model = INTENSITIES * hk_reflectance(
            _slopes_to_normal(x[0], x[1]), LIGHTS, views[r, c], rho=x[2], scale=scale
        )
        return (images[:, r, c] - model)[usable[:, r, c]]

    candidates = np.flatnonzero(res.valid & usable.all(axis=0))
    for index in rng.choice(candidates, 50, replace=False):
        r, c = divmod(int(index), mask.shape[1])
        n0 = lam.normals[r, c].astype(np.float64)
        x0 = np.array([-n0[0] / n0[2], -n0[1] / n0[2], lam.albedo[r, c]])
        ref = least_squares(residual, x0, args=(r, c), method="lm", xtol=1e-15, ftol=1e-15,
                            gtol=1e-15)
        n_ref = _slopes_to_normal(ref.x[0], ref.x[1])
        n_hk = res.normals[r, c].astype(np.float64)
        n_hk /= np.linalg.norm(n_hk)
        assert angular_error_deg(n_hk, n_ref) < 0.05
        assert res.albedo[r, c] == pytest.approx(ref.x[2], rel=1e-3)
        x_hk = np.array([-n_hk[0] / n_hk[2], -n_hk[1] / n_hk[2], float(res.albedo[r, c])])
        cost_hk = np.sum(residual(x_hk, r, c) ** 2)
        cost_ref = np.sum(ref.fun**2)
        # What float32 can resolve: the solver forms each residual r_k = I_k - f_k in
        # float32, with an error of a few eps32 |I_k|, so the cost it minimises differs from
        # the float64 cost by up to ~2 eps32 sum |I_k| |r_k|, and it can stop anywhere within
        # twice that of the float64 minimum. Measured: at most 1.4 % of this bound (a rel.
        # difference of 2.5e-6); another local minimum would differ by a sizeable fraction of
        # the cost, and its normal by more than the 0.05 deg above.
        bound = 4 * np.finfo(np.float32).eps * np.sum(np.abs(images[:, r, c][usable[:, r, c]])
                                                      * np.abs(ref.fun))
        assert abs(cost_hk - cost_ref) <= bound, (cost_hk, cost_ref, bound)


@pytest.mark.parametrize("perspective", [False, True])
def test_noise_free_sphere_recovers_normals_and_scale(perspective: bool) -> None:
    normals, mask = _surface(ridges=False)
    rho = np.random.default_rng(2).uniform(0.4, 0.6, mask.shape)
    views = _perspective_views(mask.shape[0]) if perspective else None
    images = _render(normals, mask, rho, views=views)
    kwargs = {} if views is None else {"views": views}
    res, lam = _solve(images, mask, iterations=40, **kwargs)
    assert isinstance(res, HKResult)
    err = angular_error_deg(res.normals, normals, mask=res.valid)
    assert np.nanmax(err) < 0.05
    # The Lambertian start was biased by the single-scattering term.
    assert np.nanmean(angular_error_deg(lam.normals, normals, mask=res.valid)) > 1.0
    assert res.scale == pytest.approx(SCALE, rel=1e-3)
    np.testing.assert_allclose(res.albedo[res.valid], rho[res.valid], rtol=1e-3)
    assert res.normals.dtype == np.float32 and res.albedo.dtype == np.float32
    assert res.residual_rms.dtype == np.float32 and res.valid.dtype == bool
    assert np.all(res.normals[~res.valid] == 0) and np.all(res.albedo[~res.valid] == 0)
    np.testing.assert_allclose(np.linalg.norm(res.normals[res.valid], axis=-1), 1, atol=1e-6)
    assert np.max(res.residual_rms[res.valid]) < 1e-4


def test_near_lights_per_pixel_and_paper_phase_convention() -> None:
    # One light direction per pixel (near LEDs) and the paper's phase sign, noise-free.
    normals, mask = _surface(41, ridges=False)
    size = mask.shape[0]
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    points = np.stack([u - size / 2, size / 2 - v, np.zeros_like(u)], axis=-1) * 0.3e-3
    leds = 0.1 * LIGHTS  # LEDs 0.1 m from the surface's centre
    lights = leds[:, None, None, :] - points[None]
    lights /= np.linalg.norm(lights, axis=-1, keepdims=True)
    params = SkinParams(phase=PhaseConvention.PAPER)
    rho = np.full(mask.shape, 0.5)
    images = _render(normals, mask, rho, lights=lights, params=params, scale=2.0)
    init = np.where(mask[..., None], np.array([0.0, 0.0, 1.0]), 0.0)
    res = solve_hk(images, lights, mask=mask, init_normals=init, init_albedo=rho,
                   intensities=INTENSITIES, params=params, iterations=40)
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.05
    assert res.scale == pytest.approx(2.0, rel=1e-3)
    assert res.valid.sum() == mask.sum()


def test_per_pixel_intensities_weight_the_model() -> None:
    # Images under a per-pixel lighting field (as near LEDs give), not divided by it: the
    # field given as intensities (K, H, W) recovers the surface; a non-positive intensity
    # leaves that measurement out.
    normals, mask = _surface(41, ridges=False)
    rng = np.random.default_rng(5)
    field = rng.uniform(0.7, 1.3, (7, *mask.shape))
    rho = np.full(mask.shape, 0.5)
    images = _render(normals, mask, rho) / INTENSITIES[:, None, None] * field
    field[0, 20, 20] = 0.0
    images[0, 20, 20] = 99.0  # would spoil the fit if it were used
    init = normals + 0.05 * rng.standard_normal(normals.shape)  # a few degrees off
    init = np.where(mask[..., None], init, 0.0)
    res = solve_hk(images, LIGHTS, mask=mask, init_normals=init, init_albedo=rho,
                   intensities=field, iterations=40)
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.05
    assert res.scale == pytest.approx(SCALE, rel=1e-3) and res.valid[20, 20]


def test_fixed_scale_is_kept() -> None:
    normals, mask = _surface(41)
    rho = np.full(mask.shape, 0.5)
    images = _render(normals, mask, rho)
    res, _ = _solve(images, mask, scale=SCALE, iterations=30)
    assert res.scale == SCALE
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.05
    # A wrong fixed scale gives a worse fit than the fitted one.
    wrong, _ = _solve(images, mask, scale=0.5 * SCALE, iterations=30)
    assert wrong.cost_history[-1] > 100 * res.cost_history[-1]


def test_cost_history_is_non_increasing_and_iterations_counted() -> None:
    normals, mask = _surface()
    rng = np.random.default_rng(3)
    images = _render(normals, mask, rng.uniform(0.4, 0.6, mask.shape))
    images = images + 0.01 * rng.standard_normal(images.shape)
    res, _ = _solve(images, mask, iterations=8, tol=0.0)
    history = np.array(res.cost_history)
    assert res.iterations == 8 and history.size == 9
    assert np.all(np.diff(history) <= 0)
    assert history[1] < history[0] and history[-1] < 0.9 * history[0]
    stopped, _ = _solve(images, mask, iterations=50, tol=1e-3)
    assert stopped.iterations < 50 and len(stopped.cost_history) == stopped.iterations + 1
    none, _ = _solve(images, mask, iterations=0)
    assert none.iterations == 0 and len(none.cost_history) == 1
    assert res.mean_iterations == 8 and none.mean_iterations == 0


def test_held_a_counts_the_iterations_the_chunks_did() -> None:
    # With A held each chunk of pixels stops on its own: the mean over the chunks is at most
    # the most any chunk did, and a noise-free chunk stops before a noisy one.
    normals, mask = _surface(81)
    rng = np.random.default_rng(4)
    images = _render(normals, mask, rng.uniform(0.4, 0.6, mask.shape))
    noisy = images * (1 + 0.02 * rng.standard_normal(images.shape))
    clean = np.where(np.arange(mask.shape[0])[None, :, None] < mask.shape[0] // 2, images,
                     noisy)
    res, _ = _solve(clean, mask, scale=SCALE, iterations=20, tol=1e-6)
    assert 0 < res.mean_iterations < res.iterations <= 20
    none, _ = _solve(clean, mask, scale=SCALE, iterations=0)
    assert none.mean_iterations == 0


def test_lambertian_data_gives_scale_near_zero_and_the_lambertian_normals() -> None:
    normals, mask = _surface()
    rng = np.random.default_rng(4)
    rho = rng.uniform(0.4, 0.6, mask.shape)
    images = lambertian_shading(normals, LIGHTS[:, None, None, :], rho=rho)
    images = images * INTENSITIES[:, None, None] * mask
    images = images + 0.005 * rng.standard_normal(images.shape)
    res, lam = _solve(images, mask)
    # A = 0 is a valid answer (A >= 0); "near zero": its term is < 1 % of the signal.
    assert 0.0 <= res.scale < 0.1
    diff = angular_error_deg(res.normals, lam.normals, mask=res.valid)
    assert np.nanmedian(diff) < 0.01 and np.nanmean(diff) < 0.1
    err_hk = angular_error_deg(res.normals, normals, mask=res.valid)
    err_lam = angular_error_deg(lam.normals, normals, mask=res.valid)
    assert np.nanmean(err_hk) <= 1.02 * np.nanmean(err_lam)


def test_usable_mask_and_too_few_measurements() -> None:
    normals, mask = _surface(31)
    rho = np.full(mask.shape, 0.5)
    images = _render(normals, mask, rho)
    usable = np.ones(images.shape, dtype=bool)
    usable[2:, 10, 10] = False  # 2 usable measurements left: invalid
    usable[4:, 12, 12] = False  # 4 left: still solved
    corrupt = images.copy()
    corrupt[3, 12, 12] = 5.0  # a saturated value, marked unusable
    usable[3, 12, 12] = False
    init = np.where(mask[..., None], np.array([0.0, 0.0, 1.0]), 0.0)
    res = solve_hk(corrupt, LIGHTS, mask=mask, init_normals=init, init_albedo=rho,
                   intensities=INTENSITIES, usable=usable, iterations=40)
    assert not res.valid[10, 10] and res.valid[12, 12]
    assert angular_error_deg(res.normals[12, 12], normals[12, 12]) < 0.05
    assert res.valid.sum() == mask.sum() - 1


def test_grazing_normals_stay_finite() -> None:
    # Normals almost perpendicular to the view and a light in attached shadow: the
    # derivatives of c_i / (c_i + c_r) would blow up; the result must stay finite.
    normals = np.array([[[np.sin(np.radians(89.9)), 0.0, np.cos(np.radians(89.9))]] * 3])
    mask = np.ones((1, 3), dtype=bool)
    lights = np.array([[0.9, 0.0, 0.436], [0.6, 0.6, 0.529], [0.6, -0.6, 0.529],
                       [-0.3, 0.0, 0.954]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    images = hk_reflectance(normals, lights[:, None, None, :], np.array([0, 0, 1.0]), rho=0.5,
                            scale=SCALE) + 0.01
    init = np.tile(np.array([0.9, 0.0, 0.1]) / np.linalg.norm([0.9, 0.0, 0.1]), (1, 3, 1))
    res = solve_hk(images, lights, mask=mask, init_normals=init, init_albedo=np.full((1, 3), 0.5))
    assert np.all(np.isfinite(res.normals)) and np.all(np.isfinite(res.albedo))
    assert np.isfinite(res.scale) and np.all(np.isfinite(res.cost_history))


def test_numba_threads_do_not_change_the_result(monkeypatch: pytest.MonkeyPatch) -> None:
    # The numba passes add their global sums up per chunk of pixels in a fixed order: the
    # same answer, bit for bit, with 1 or 2 threads (here with many chunks).
    normals, mask = _surface()
    rng = np.random.default_rng(6)
    images = _render(normals, mask, rng.uniform(0.4, 0.6, mask.shape))
    images = images + 0.01 * rng.standard_normal(images.shape)
    results = []
    for threads in (1, 2):
        monkeypatch.setattr(kernel_threads, "_LIMIT", [threads])
        results.append(_solve(images, mask, iterations=6, tol=0.0)[0])
    one, two = results
    assert mask.sum() > 4 * hk_solver._kernels().model.CHUNK
    np.testing.assert_array_equal(one.normals, two.normals)
    np.testing.assert_array_equal(one.albedo, two.albedo)
    assert one.scale == two.scale and one.cost_history == two.cost_history


def test_without_numba_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    inputs = _good_inputs()
    images, lights = inputs.pop("images"), inputs.pop("lights")
    monkeypatch.setattr(hk_solver, "_KERNELS", [None, "ImportError: No module named 'numba'"])
    with pytest.raises(FingerpsReconError, match="install numba"):
        solve_hk(images, lights, **inputs)


@pytest.fixture(scope="module")
def rig_finger() -> dict[str, object]:
    """The simulated rig's finger burst (as bench/bench_recon_speed.py, without the flat
    field): solve_hk's inputs from the Lambertian start, distant lights."""
    from fingerps_driver.simulation import Scene, SimulatedRig
    from fingerps_recon.photometric.finger_mask import finger_mask

    rig = SimulatedRig()
    images = rig.render_burst(Scene.FINGER, seed=10).astype(np.float32)
    lights = rig.light_directions_ps()
    intensities = rig.light_intensities()
    shadow, saturated = 0.02 * rig.max_value(), float(rig.max_value())
    mask = finger_mask(images, threshold=0.15)
    lam = solve_lambertian(images, lights, intensities=intensities, mask=mask,
                           shadow_level=shadow, saturation_level=saturated)
    return {
        "images": images, "lights": lights, "mask": lam.valid & mask,
        "init_normals": lam.normals, "init_albedo": lam.albedo, "intensities": intensities,
        "usable": (images > shadow) & (images < saturated), "iterations": 10,
    }


def _at_scipy_minimum(inputs: dict[str, object], *, pixels: int = 30,
                      scale: float | None = None) -> None:
    """The batched solve (A fitted, or held at ``scale``) reaches, at a sample of pixels,
    the minimum scipy's least_squares (float64) finds for that pixel with A fixed to the
    batched A, from the same start: normals within 0.05 degrees, albedo within 1e-3, costs
    within what float32 resolves (see test_same_minimum_as_scipy_least_squares_per_pixel)."""
    inputs = dict(inputs)
    images, lights = inputs.pop("images"), inputs.pop("lights")
    res = solve_hk(images, lights, **{**inputs, "iterations": 40, "tol": 0.0, "scale": scale})
    assert res.valid.sum() > 100_000
    usable = np.asarray(inputs["usable"])
    views = np.asarray(inputs.get("views", (0.0, 0.0, 1.0)))
    power = np.asarray(inputs["intensities"])
    rng = np.random.default_rng(3)
    candidates = np.flatnonzero(res.valid & usable.all(axis=0))
    for index in rng.choice(candidates, pixels, replace=False):
        r, c = divmod(int(index), res.valid.shape[1])
        lgt = lights[:, r, c] if np.ndim(lights) == 4 else lights
        view = views[r, c] if views.ndim == 3 else views
        e = power[:, r, c] if power.ndim == 3 else power
        used = usable[:, r, c]
        values = np.asarray(images[:, r, c], dtype=np.float64)

        def residual(x: np.ndarray, lgt=lgt, view=view, e=e, used=used, values=values):
            model = e * hk_reflectance(_slopes_to_normal(x[0], x[1]), lgt, view, rho=x[2],
                                       scale=res.scale)
            return (values - model)[used]

        n_hk = res.normals[r, c].astype(np.float64)
        n_hk /= np.linalg.norm(n_hk)
        x_hk = np.array([-n_hk[0] / n_hk[2], -n_hk[1] / n_hk[2], float(res.albedo[r, c])])
        ref = least_squares(residual, x_hk, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert angular_error_deg(n_hk, _slopes_to_normal(ref.x[0], ref.x[1])) < 0.05
        assert res.albedo[r, c] == pytest.approx(ref.x[2], rel=1e-3)
        bound = 4 * np.finfo(np.float32).eps * np.sum(np.abs(values[used]) * np.abs(ref.fun))
        assert abs(np.sum(residual(x_hk) ** 2) - np.sum(ref.fun ** 2)) <= bound


def test_rig_finger_at_the_scipy_minimum(rig_finger: dict[str, object]) -> None:
    # ~170 000 finger pixels (hundreds of chunks, both threads), distant lights.
    _at_scipy_minimum(rig_finger)


def test_rig_finger_near_lights_at_the_scipy_minimum(rig_finger: dict[str, object]) -> None:
    # The node's inputs: per-pixel lights, views and intensities (float32).
    size = rig_finger["mask"].shape
    v, u = np.mgrid[0:size[0], 0:size[1]].astype(np.float64)
    views = np.stack([-(u - size[1] / 2) / 3000.0, (v - size[0] / 2) / 3000.0,
                      np.ones_like(u)], axis=-1)
    views /= np.linalg.norm(views, axis=-1, keepdims=True)
    points = np.stack([u - size[1] / 2, size[0] / 2 - v, np.zeros_like(u)], axis=-1) * 3e-5
    lights = 0.05 * np.asarray(rig_finger["lights"])[:, None, None, :] - points[None]
    lights /= np.linalg.norm(lights, axis=-1, keepdims=True)
    field = np.random.default_rng(7).uniform(0.8, 1.2, (len(lights), *size))
    _at_scipy_minimum({
        **rig_finger, "lights": lights.astype(np.float32), "views": views.astype(np.float32),
        "intensities": (field * np.asarray(rig_finger["intensities"])[:, None, None]).astype(
            np.float32),
    })


def test_rig_finger_with_a_held_at_the_scipy_minimum(rig_finger: dict[str, object]) -> None:
    # A held (the one-pass solve of every burst after the first), at the joint fit's A.
    _at_scipy_minimum(rig_finger, scale=solve_hk(**rig_finger).scale)


def test_held_a_refitted_burst_after_burst_comes_to_the_joint_fit(
        rig_finger: dict[str, object]) -> None:
    # Holding each solve at the previous solve's refit is block-coordinate descent on
    # (pixels, A): its fixed point is the joint minimum. From A 20 % off, the distance to
    # the jointly fitted A shrinks at every round, and at the jointly fitted A the refit
    # stays there (to 1e-3: the joint solve's own A is converged only to tol).
    inputs = dict(rig_finger)
    images, lights = inputs.pop("images"), inputs.pop("lights")
    joint = solve_hk(images, lights, **{**inputs, "iterations": 40, "tol": 0.0})
    held = 0.8 * joint.scale
    distances = [abs(held - joint.scale)]
    for _ in range(4):
        res = solve_hk(images, lights, **inputs, scale=held)
        assert res.scale == held
        assert res.cost_history[-1] <= res.cost_history[0]
        assert 1 <= res.iterations <= inputs["iterations"]
        held = res.refit_scale
        distances.append(abs(held - joint.scale))
    assert all(later < earlier for earlier, later in itertools.pairwise(distances))
    at_joint = solve_hk(images, lights, **{**inputs, "iterations": 40, "tol": 0.0},
                        scale=joint.scale)
    assert at_joint.refit_scale == pytest.approx(joint.scale, rel=1e-3)
    # The fitted solve reports its own A as the refit.
    assert joint.refit_scale == joint.scale


def test_prepared_lighting_gives_the_same_solve(rig_finger: dict[str, object]) -> None:
    # prepare_hk_lighting once (whole image) + solve_hk_prepared per burst is solve_hk.
    inputs = dict(rig_finger)
    images, lights = inputs.pop("images"), inputs.pop("lights")
    direct = solve_hk(images, lights, **inputs)
    lighting = hk_solver.prepare_hk_lighting(lights, shape=images.shape[1:],
                                             intensities=inputs["intensities"])
    prepared = hk_solver.solve_hk_prepared(
        images, lighting, mask=inputs["mask"], init_normals=inputs["init_normals"],
        init_albedo=inputs["init_albedo"], usable=inputs["usable"],
        iterations=inputs["iterations"])
    np.testing.assert_array_equal(prepared.valid, direct.valid)
    np.testing.assert_array_equal(prepared.normals, direct.normals)
    assert prepared.cost_history == direct.cost_history
    # A warm start (the previous burst's A) is closer after one iteration than the cold one.
    warm = hk_solver.solve_hk_prepared(
        images, lighting, mask=inputs["mask"], init_normals=inputs["init_normals"],
        init_albedo=inputs["init_albedo"], usable=inputs["usable"], iterations=1,
        initial_scale=direct.scale)
    cold = hk_solver.solve_hk_prepared(
        images, lighting, mask=inputs["mask"], init_normals=inputs["init_normals"],
        init_albedo=inputs["init_albedo"], usable=inputs["usable"], iterations=1)
    assert abs(warm.scale - direct.scale) < abs(cold.scale - direct.scale)
    # A lighting prepared for a smaller mask refuses a burst outside it.
    small = np.zeros_like(inputs["mask"])
    small[:10] = True
    part = hk_solver.prepare_hk_lighting(lights, shape=images.shape[1:],
                                         intensities=inputs["intensities"], mask=small)
    with pytest.raises(FingerpsReconError, match="not prepared"):
        hk_solver.solve_hk_prepared(images, part, mask=inputs["mask"],
                                    init_normals=inputs["init_normals"],
                                    init_albedo=inputs["init_albedo"])


def test_empty_mask_returns_nothing_valid() -> None:
    images = np.ones((3, 4, 5))
    res = solve_hk(images, LIGHTS[:3], mask=np.zeros((4, 5), bool),
                   init_normals=np.zeros((4, 5, 3)), init_albedo=np.zeros((4, 5)))
    assert not res.valid.any() and np.isnan(res.scale) and res.iterations == 0


def _good_inputs() -> dict[str, np.ndarray]:
    normals, mask = _surface(21)
    rho = np.full(mask.shape, 0.5)
    return {
        "images": _render(normals, mask, rho), "lights": LIGHTS.copy(), "mask": mask,
        "init_normals": np.where(mask[..., None], np.array([0.0, 0.0, 1.0]), 0.0),
        "init_albedo": rho,
    }


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"images": np.ones((7, 21))}, "images"),
        ({"images": np.ones((2, 21, 21)), "lights": LIGHTS[:2]}, "at least 3"),
        ({"lights": LIGHTS[:5]}, "lights"),
        ({"lights": np.ones((7, 20, 21, 3))}, "lights"),
        ({"lights": np.vstack([LIGHTS[:6], [[0.0, 0.0, 0.0]]])}, "zero"),
        ({"lights": np.vstack([LIGHTS[:6], [[np.nan, 0.0, 1.0]]])}, "non-finite"),
        ({"mask": np.ones((21, 20), bool)}, "mask"),
        ({"mask": np.ones((21, 21), np.uint8)}, "mask"),
        ({"init_normals": np.zeros((21, 21, 2))}, "init_normals"),
        ({"init_albedo": np.zeros((21, 20))}, "init_albedo"),
        ({"views": np.zeros(2)}, "views"),
        ({"views": np.zeros(3)}, "zero"),
        ({"intensities": np.ones(6)}, "intensities"),
        ({"intensities": np.array([1, 1, 1, 1, 1, 1, 0.0])}, "intensities"),
        ({"intensities": np.ones((7, 21, 20))}, "intensities"),
        ({"usable": np.ones((7, 21, 21), np.uint8)}, "usable"),
        ({"scale": -1.0}, "scale"),
        ({"scale": float("nan")}, "scale"),
        ({"iterations": -1}, "iterations"),
        ({"iterations": 2.5}, "iterations"),
        ({"tol": -1e-3}, "tol"),
        ({"params": "finger"}, "SkinParams"),
    ],
)
def test_bad_inputs_raise(change: dict[str, object], message: str) -> None:
    kwargs: dict[str, object] = {**_good_inputs(), **change}
    images, lights = kwargs.pop("images"), kwargs.pop("lights")
    with pytest.raises(FingerpsReconError, match=message):
        solve_hk(images, lights, **kwargs)


@pytest.mark.parametrize("name", ["lights", "views"])
@pytest.mark.parametrize(("bad", "message"), [(np.nan, "non-finite"), (0.0, "zero")])
def test_bad_per_pixel_directions_inside_the_mask_raise(
    name: str, bad: float, message: str,
) -> None:
    inputs = _good_inputs()
    size = inputs["mask"].shape[0]
    inputs["views"] = _perspective_views(size)
    inputs["lights"] = np.broadcast_to(LIGHTS[:, None, None, :], (7, size, size, 3)).copy()
    where = (slice(None), 10, 10) if name == "lights" else (10, 10)
    inputs[name][where] = bad
    outside = {**inputs, name: inputs[name].copy()}
    images, lights = inputs.pop("images"), inputs.pop("lights")
    with pytest.raises(FingerpsReconError, match=f"{name} contain {message}"):
        solve_hk(images, lights, **inputs)
    # Outside the mask, bad directions do not matter.
    outside[name][where] = [0.0, 0.0, 1.0] if name == "views" else LIGHTS
    outside[name][(slice(None), 0, 0) if name == "lights" else (0, 0)] = bad
    assert not outside["mask"][0, 0]
    images, lights = outside.pop("images"), outside.pop("lights")
    assert solve_hk(images, lights, **outside).valid.any()


def test_inputs_are_not_modified() -> None:
    inputs = _good_inputs()
    size = inputs["mask"].shape[0]
    inputs["images"] = inputs["images"].astype(np.float32)
    inputs["views"] = _perspective_views(size)
    inputs["usable"] = inputs["images"] > 0
    inputs["intensities"] = np.ones(inputs["images"].shape) * INTENSITIES[:, None, None]
    inputs["lights"] = np.broadcast_to(LIGHTS[:, None, None, :], (7, size, size, 3)).copy()
    copies = {name: np.array(value, copy=True) for name, value in inputs.items()}
    images, lights = inputs.pop("images"), inputs.pop("lights")
    solve_hk(images, lights, **inputs)
    inputs["images"], inputs["lights"] = images, lights
    for name, value in inputs.items():
        np.testing.assert_array_equal(value, copies[name], err_msg=name)
