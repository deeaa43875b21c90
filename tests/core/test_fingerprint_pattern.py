"""The SFinGe-style synthetic fingerprint generator (fingerps_driver.simulation.fingerprint_*).

Singular points by Poincare index (of the model's field and of the orientation measured on the
grown ridges), ridge period measured by FFT, minutiae, identities, the 500 ppi render, and
NIST NBIS (mindtct, bozorth3, NFIQ 2 through nbis-py) as the judge.
"""

from __future__ import annotations

import cv2
import nbis
import numpy as np
import pytest

from fingerps_driver.simulation.fingerprint_minutiae import MinutiaType
from fingerps_driver.simulation.fingerprint_orientation import (
    CLASS_FREQUENCIES,
    PatternClass,
    SingularKind,
    draw_class,
    poincare_index,
)
from fingerps_driver.simulation.fingerprint_pattern import (
    FingerprintPattern,
    generate_fingerprint,
    render_rolled_print,
)

SEEDS = {c: i + 10 for i, c in enumerate(PatternClass)}


@pytest.fixture(scope="module")
def fingers() -> dict[PatternClass, FingerprintPattern]:
    out = {}
    for c, seed in SEEDS.items():
        out[c] = generate_fingerprint(seed, pattern_class=c)
    return out


def measured_orientation(ridges: np.ndarray, *, pixel_mm: float, sigma_mm: float = 0.3):
    """Ridge orientation of an image by the gradient structure tensor, [0, pi), CCW."""
    gx = cv2.Sobel(ridges, cv2.CV_64F, 1, 0, ksize=3)
    gy = -cv2.Sobel(ridges, cv2.CV_64F, 0, 1, ksize=3)  # y up
    s = sigma_mm / pixel_mm
    gxx = cv2.GaussianBlur(gx * gx, (0, 0), s)
    gyy = cv2.GaussianBlur(gy * gy, (0, 0), s)
    gxy = cv2.GaussianBlur(gx * gy, (0, 0), s)
    return np.mod(0.5 * np.arctan2(2 * gxy, gxx - gyy) + np.pi / 2, np.pi)


def test_singular_points_have_their_poincare_index(fingers):
    for c, fp in fingers.items():
        cores = [p for p in fp.singular_points if p.kind is SingularKind.CORE]
        deltas = [p for p in fp.singular_points if p.kind is SingularKind.DELTA]
        expected = {
            PatternClass.ARCH: (0, 0),
            PatternClass.TENTED_ARCH: (1, 1),
            PatternClass.LEFT_LOOP: (1, 1),
            PatternClass.RIGHT_LOOP: (1, 1),
            PatternClass.WHORL: (2, 2),
        }[c]
        assert (len(cores), len(deltas)) == expected, c
        measured = measured_orientation(fp.ridges, pixel_mm=fp.pixel_mm)
        for field in (fp.orientation_rad, measured):
            if c is PatternClass.WHORL:
                x = np.mean([p.x_mm for p in cores])
                y = np.mean([p.y_mm for p in cores])
                index = poincare_index(field, pixel_mm=fp.pixel_mm, x_mm=x, y_mm=y, radius_mm=3.5)
                assert index == pytest.approx(1.0, abs=0.01), c
            else:
                for p in cores:
                    index = poincare_index(
                        field, pixel_mm=fp.pixel_mm, x_mm=p.x_mm, y_mm=p.y_mm, radius_mm=0.9
                    )
                    assert index == pytest.approx(0.5, abs=0.01), c
            for p in deltas:
                index = poincare_index(
                    field, pixel_mm=fp.pixel_mm, x_mm=p.x_mm, y_mm=p.y_mm, radius_mm=0.9
                )
                assert index == pytest.approx(-0.5, abs=0.01), c
    # No singular point elsewhere: index 0 on a lattice of circles clear of them (arch: all).
    fp = fingers[PatternClass.ARCH]
    for x in np.arange(4.0, 17.0, 3.0):
        for y in np.arange(4.0, 22.0, 3.0):
            index = poincare_index(
                fp.orientation_rad, pixel_mm=fp.pixel_mm, x_mm=x, y_mm=y, radius_mm=1.2
            )
            assert index == pytest.approx(0.0, abs=0.01), (x, y)


def test_ridges_follow_the_orientation_field(fingers):
    for c, fp in fingers.items():
        measured = measured_orientation(fp.ridges, pixel_mm=fp.pixel_mm, sigma_mm=0.5)
        diff = np.abs(np.angle(np.exp(2j * (measured - fp.orientation_rad)))) / 2
        far = np.ones(fp.mask.shape, bool)
        rows, cols = np.indices(fp.mask.shape)
        for p in fp.singular_points:
            far &= np.hypot((cols + 0.5) * fp.pixel_mm - p.x_mm,
                            (rows + 0.5) * fp.pixel_mm - p.y_mm) > 1.5
        assert np.degrees(np.median(diff[fp.mask & far])) < 6.0, c


def test_ridge_period_measured_by_fft_matches_the_period_map(fingers):
    block = 64  # 3.25 mm at 500 ppi
    window = np.outer(np.hanning(block), np.hanning(block))
    freq = np.fft.fftfreq(4 * block)  # zero-padded: peak located to ~1.5 %
    radius = np.hypot(freq[:, None], freq[None, :])
    for c, fp in fingers.items():
        assert 0.40 <= fp.period_mm.min() and fp.period_mm.max() <= 0.55
        errors = []
        for r0 in range(0, fp.ridges.shape[0] - block, block):
            for c0 in range(0, fp.ridges.shape[1] - block, block):
                if not fp.mask[r0:r0 + block, c0:c0 + block].all():
                    continue
                tile = fp.ridges[r0:r0 + block, c0:c0 + block]
                spectrum = np.fft.fft2((tile - tile.mean()) * window, s=(4 * block, 4 * block))
                power = np.abs(spectrum) ** 2
                power[radius < 1 / 20] = 0  # no DC leakage (period < 1 mm)
                peak = np.unravel_index(np.argmax(power), power.shape)
                period = fp.pixel_mm / radius[peak]
                expected = float(fp.period_mm[r0:r0 + block, c0:c0 + block].mean())
                assert 0.36 <= period <= 0.60, (c, r0, c0, period)
                errors.append(period / expected - 1)
        # Measured periods run 1-4 % longer than the map (curved ridges in a block).
        assert abs(np.median(errors)) < 0.05, c
        assert np.percentile(np.abs(errors), 90) < 0.12, c


def test_minutiae_present_both_types_and_clear_of_border_and_cores(fingers):
    for c, fp in fingers.items():
        kinds = [m.kind for m in fp.minutiae]
        low = 10 if c in (PatternClass.ARCH, PatternClass.TENTED_ARCH) else 20
        assert low <= len(fp.minutiae) <= 80, (c, len(fp.minutiae))
        assert kinds.count(MinutiaType.ENDING) >= 3 and kinds.count(MinutiaType.BIFURCATION) >= 3
        for m in fp.minutiae:
            row, col = int(m.y_mm / fp.pixel_mm), int(m.x_mm / fp.pixel_mm)
            assert fp.mask[row, col]
            assert 0.0 <= m.angle_rad < 2 * np.pi
            for p in fp.singular_points:
                assert np.hypot(m.x_mm - p.x_mm, m.y_mm - p.y_mm) > 1.5
            # A minutia sits on a ridge of the final pattern.
            assert fp.ridges[row - 1:row + 2, col - 1:col + 2].max() > 0


def test_identity_is_the_seed():
    a = generate_fingerprint(7, width_mm=12.0, height_mm=14.0)
    b = generate_fingerprint(7, width_mm=12.0, height_mm=14.0)
    c = generate_fingerprint(8, width_mm=12.0, height_mm=14.0, pattern_class=a.pattern_class)
    assert a.pattern_class is b.pattern_class
    np.testing.assert_array_equal(a.ridges, b.ridges)
    assert a.minutiae == b.minutiae
    assert abs(np.corrcoef(a.ridges.ravel(), c.ridges.ravel())[0, 1]) < 0.2
    assert a.ridges.shape == (round(14.0 / a.pixel_mm), round(12.0 / a.pixel_mm))


def test_class_drawn_with_natural_frequencies():
    rng = np.random.default_rng(0)
    draws = [draw_class(rng) for _ in range(4000)]
    for c, p in CLASS_FREQUENCIES.items():
        assert draws.count(c) / len(draws) == pytest.approx(p, abs=0.03), c


def test_render_500ppi_ridges_dark_on_white(fingers):
    fp = fingers[PatternClass.WHORL]
    image = render_rolled_print(fp)
    assert image.dtype == np.uint8
    assert image.shape == (round(25.0 * 500 / 25.4), round(20.0 * 500 / 25.4))
    inside = fp.mask
    assert image[inside & (fp.ridges > 0.5)].mean() < 60
    assert image[inside & (fp.ridges < -0.5)].mean() > 195
    assert (image[~inside] == 255).all()
    double = render_rolled_print(fp, ppi=1000.0)
    assert double.shape == (2 * image.shape[0], 2 * image.shape[1])


def test_nbis_mindtct_bozorth3_nfiq2_on_the_renders(fingers):
    extractor = nbis.new_nbis_extractor(nbis.NbisExtractorSettings(
        min_quality=0.0, get_center=False, check_fingerprint=False, compute_nfiq2=True,
        ppi=500.0,
    ))

    def template(image: np.ndarray):
        return extractor.extract_minutiae(cv2.imencode(".png", image)[1].tobytes())

    px_per_mm = 500 / 25.4
    loop, whorl = fingers[PatternClass.LEFT_LOOP], fingers[PatternClass.WHORL]
    image = render_rolled_print(loop)
    found = template(image)
    det = np.array([((d.x() + 0.5) / px_per_mm, (d.y() + 0.5) / px_per_mm, d.angle())
                    for d in found.get()])
    truth = np.array([(m.x_mm, m.y_mm, np.degrees(m.angle_rad)) for m in loop.minutiae])
    dist = np.hypot(truth[:, None, 0] - det[None, :, 0], truth[:, None, 1] - det[None, :, 1])
    hit = dist.min(axis=1) <= 0.3
    assert hit.mean() >= 0.85  # mindtct recall against the ground truth
    # Same angle convention as NBIS (ISO/IEC 19794-2): matched directions agree.
    angle_diff = (det[dist.argmin(axis=1)[hit], 2] - truth[hit, 2] + 180) % 360 - 180
    assert np.median(np.abs(angle_diff)) < 15

    h, w = image.shape
    m = cv2.getRotationMatrix2D((w / 2, h / 2), 4.0, 1.0)
    m[:, 2] += (12, -8)
    moved = cv2.warpAffine(image, m, (w, h), borderValue=255)
    genuine = found.compare(template(moved))
    impostor = found.compare(template(render_rolled_print(whorl)))
    assert genuine > 100 and impostor < 60 and genuine > 3 * impostor
    assert found.quality().score >= 30
