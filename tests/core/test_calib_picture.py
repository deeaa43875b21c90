"""Tests of fingerps_calib.calibration_picture: the operator's PNGs and their geometry."""

from __future__ import annotations

import cv2
import numpy as np

from fingerps_calib.calibration_picture import (
    circle_outline,
    distort_points,
    flat_field_picture,
    lights_picture,
    sphere_outline,
    write_png,
)

K = np.array([[400.0, 0.0, 161.3], [0.0, 402.0, 118.7], [0.0, 0.0, 1.0]])
CENTER = np.array([0.006, -0.004, 0.07])
RADIUS = 0.008


def test_sphere_outline_is_the_tangent_cone():
    outline = sphere_outline(CENTER, RADIUS, K)
    rays = np.column_stack([outline, np.ones(len(outline))]) @ np.linalg.inv(K).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    # Every ray through the outline passes the centre at exactly the radius.
    along = rays @ CENTER
    distance = np.sqrt(CENTER @ CENTER - along**2)
    np.testing.assert_allclose(distance, RADIUS, rtol=1e-9)
    assert sphere_outline(np.array([0.0, 0.0, 0.001]), RADIUS, K).shape == (0, 2)
    assert sphere_outline(np.full(3, np.nan), RADIUS, K).shape == (0, 2)


def test_distort_points_inverts_undistort():
    distortion = np.array([-0.25, 0.1, 0.001, -0.002, 0.0])
    ideal = np.array([[30.0, 40.0], [160.0, 120.0], [np.nan, np.nan], [290.0, 200.0]])
    raw = distort_points(ideal, K, distortion)
    assert np.all(np.isnan(raw[2]))
    back = cv2.undistortPoints(raw[[0, 1, 3]].reshape(-1, 1, 2), K, distortion, P=K)
    np.testing.assert_allclose(back.reshape(-1, 2), ideal[[0, 1, 3]], atol=1e-3)
    np.testing.assert_array_equal(distort_points(ideal, K, None), ideal)


def test_lights_picture_draws_everything_and_survives_missing_leds(tmp_path):
    h, w = 240, 320
    vv, uu = np.mgrid[0:h, 0:w]
    outline = sphere_outline(CENTER, RADIUS, K)
    centre = outline.mean(axis=0)
    disc = np.hypot(uu - centre[0], vv - centre[1]) < 60
    images = np.stack([30.0 * disc for _ in range(3)])
    highlights = np.array([[centre[0] + 10, centre[1]], [np.nan, np.nan],
                           [centre[0], centre[1] - 12]])
    directions = np.array([[0.3, 0.1, -0.95], [np.nan] * 3, [-0.2, 0.3, -0.93]])
    picture = lights_picture(images, highlights_uv=highlights, directions_optical=directions,
                             edge_points_uv=outline, outline_uv=outline,
                             placement_directions=[directions, directions + 0.01],
                             title="light calibration", lines=["line one", "x " * 200],
                             problems=["LED 1: no highlight"])
    assert picture.dtype == np.uint8 and picture.ndim == 3 and picture.shape[1] == 960
    assert picture.shape[0] > 480 + 4 * 20  # panels, then the wrapped text
    # The refused-calibration text is red (BGR: red channel dominant) somewhere below.
    text = picture[480:].astype(int)
    assert np.any((text[..., 2] > 200) & (text[..., 1] < 120))
    # Some green (the outline) is drawn on the sphere panel.
    panel = picture[:480, :480].astype(int)
    assert np.any((panel[..., 1] > 180) & (panel[..., 0] < 120) & (panel[..., 2] < 120))
    path = write_png(tmp_path / "lights.png", picture)
    np.testing.assert_array_equal(cv2.imread(str(path)), picture)
    # An orthographic picture: a circle as the outline, no edge points.
    ortho = lights_picture(images[0], highlights_uv=highlights, directions_optical=directions,
                           outline_uv=circle_outline(centre, 60.0))
    assert ortho.shape[1] == 960


def test_flat_field_picture_shows_each_map():
    maps = np.stack([np.linspace(0.5, 1.0, 64 * 48).reshape(48, 64)] * 5).astype(np.float32)
    picture = flat_field_picture(maps, relative_intensities=np.linspace(1, 0.8, 5),
                                 fit_residuals=np.full(5, 0.005), lines=["camera x"])
    assert picture.ndim == 3 and picture.dtype == np.uint8
    assert picture.shape[1] == 4 * 240 + 20 + 44  # four maps a row, colour bar, legend
    # Two rows of maps (5 LEDs, 4 a row) of 22 px captions + 180 px maps, then the text.
    assert picture.shape[0] == 2 * (22 + 180) + 2 * 20 + 10
