"""The renderer's exposure in bands of rows gives the very frame the whole-frame formula gives
(each band blurred with the rows its blur reaches, the same noise drawn in the same order), and the light map, built from a row and a column,
the same values as from two full pixel grids; nearest_outline_mm is the least outline gap."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from cell.camera_model import CameraModel
from cell.sim.cell import nearest_outline_mm, outline_gap_mm
from cell.sim.parts import PartSpec, part_coverage, random_scene
from cell.sim.render import Optics, backlight, circles_coverage, expose
from cell.sim.sim_camera import SimCamera
from cell.sim.world import Truth, World


def _whole_frame_light(h: int, w: int, vignetting: float, gradient: float, angle_deg: float) -> np.ndarray:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ru = (u - w / 2) / (w / 2)
    rv = (v - h / 2) / (w / 2)
    r2 = (ru**2 + rv**2) / (1 + (h / w) ** 2)
    light = 1.0 - vignetting * r2
    a = np.deg2rad(angle_deg)
    light *= 1.0 + gradient * 0.5 * (np.cos(a) * ru + np.sin(a) * rv * w / h)
    return light


def _whole_frame_expose(opacity: np.ndarray, optics: Optics, rng: np.random.Generator, exposure: float) -> np.ndarray:
    import cv2

    h, w = opacity.shape
    light = _whole_frame_light(h, w, optics.vignetting, optics.backlight_gradient, optics.backlight_angle_deg)
    signal = optics.dark_level + (optics.bright_level - optics.dark_level) * light * (1 - opacity)
    signal *= exposure
    if optics.blur_sigma_px > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), optics.blur_sigma_px)
    bgr = signal[:, :, None] * np.array(optics.tint_bgr)[None, None, :]
    bgr += rng.normal(0.0, optics.noise_sigma, bgr.shape)
    return np.clip(np.rint(bgr), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("size", [(17, 16), (101, 67), (640, 150)])  # bands of 64 rows: one, and the last cut short
@pytest.mark.parametrize(
    "optics",
    [
        Optics(),
        Optics(blur_sigma_px=0.0),
        Optics(blur_sigma_px=2.6),  # a wider blur reaches further beyond each band
        Optics(blur_sigma_px=0.3, noise_sigma=0.0, vignetting=0.4, backlight_angle_deg=123.0),
    ],
)
@pytest.mark.parametrize("exposure", [1.0, 1.4])
def test_exposure_in_bands_is_the_whole_frame_formula(size: tuple[int, int], optics: Optics, exposure: float) -> None:
    w, h = size
    camera = CameraModel.looking_down(w, h, 0.5, (0.0, 0.0))
    opacity = np.random.default_rng(11).random((h, w))
    banded = expose(camera, opacity, optics, np.random.default_rng(3), exposure)
    whole = _whole_frame_expose(opacity, optics, np.random.default_rng(3), exposure)
    assert banded.dtype == np.uint8 and banded.shape == (h, w, 3)
    np.testing.assert_array_equal(banded, whole)


@pytest.mark.parametrize("size", [(1080, 1920), (67, 101), (1920, 1080)])
@pytest.mark.parametrize("args", [(0.25, 0.15, 30.0), (0.0, 0.0, 0.0), (0.4, -0.2, 123.0)])
def test_the_light_map_is_the_full_grid_formula(size: tuple[int, int], args: tuple[float, float, float]) -> None:
    light = backlight(*size, *args)
    np.testing.assert_array_equal(light, _whole_frame_light(*size, *args))
    assert not light.flags.writeable, "shared by every frame: read-only"


def _pairwise_gap_mm(a: PartSpec, b: PartSpec) -> float:
    """The gap as every pair of outline samples gives it (8 samples along each edge)."""

    def dense(p: PartSpec) -> np.ndarray:
        poly = p.top_view_outline_mm()
        t = np.linspace(0, 1, 8, endpoint=False)[:, None, None]
        return (poly + t * (np.roll(poly, -1, axis=0) - poly)).reshape(-1, 2)

    pa, pb = dense(a), dense(b)
    return float(np.sqrt(((pa[:, None, :] - pb[None, :, :]) ** 2).sum(-1)).min())


def test_nearest_outline_is_the_least_pairwise_gap_to_any_of_the_others() -> None:
    parts = random_scene(4) + random_scene(9)
    for i, part in enumerate(parts[:8]):
        others = parts[:i] + parts[i + 1 :]
        assert nearest_outline_mm(part, others) == min(_pairwise_gap_mm(part, q) for q in others)
        assert outline_gap_mm(part, others[0]) == _pairwise_gap_mm(part, others[0])


def test_a_sim_camera_frame_is_the_whole_frame_exposure_of_its_marks_and_parts() -> None:
    """The camera composes small windows in a buffer it keeps: frame after frame (the parts
    changing between them), the frame the whole-frame coverage would give (without noise: a live
    camera's noise comes from its pool, next test)."""
    model = CameraModel.looking_down(320, 200, 1.0, (130.0, 90.0))
    marks = np.array([(-6.0, -6.0), (270.0, -6.0), (-6.0, 182.0), (270.0, 182.0)])
    parts = random_scene(3)
    world = World(parts, Truth(0.0, 0.0, 0.0, 0.0), [])
    quiet = Optics(noise_sigma=0.0)
    camera = SimCamera(world, model, quiet, seed=5, marks_mm=marks, mark_diameter_mm=3.0)
    rng = np.random.default_rng(5)
    camera.connect()
    for _ in range(3):
        opacity = circles_coverage(model, marks, 1.5)
        for _, spec in world.table_specs():
            got = part_coverage(model, spec)
            if got is not None:
                (x0, y0), cov = got
                window = opacity[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]]
                np.maximum(window, cov, out=window)
        np.testing.assert_array_equal(camera.capture(), _whole_frame_expose(opacity, quiet, rng, 1.0))
        world.parts = world.parts[2:]  # parts leave the table between frames


def test_a_sim_camera_s_pooled_noise_has_the_optics_level_and_differs_frame_to_frame() -> None:
    """The live camera's noise (render.SensorNoise): zero mean, the configured sigma in each channel,
    and a new pattern each frame (consecutive frames' noise uncorrelated)."""
    model = CameraModel.looking_down(640, 360, 1.0, (130.0, 90.0))
    world = World([], Truth(0.0, 0.0, 0.0, 0.0), [])
    optics = Optics(blur_sigma_px=0.0, noise_sigma=3.0)
    camera = SimCamera(world, model, optics, seed=7)
    camera.connect()
    clean = expose(model, np.zeros((360, 640)), Optics(blur_sigma_px=0.0, noise_sigma=0.0))
    residuals = [camera.capture().astype(np.float64) - clean for _ in range(3)]
    for r in residuals:
        assert abs(r.mean()) < 0.05
        for channel in range(3):
            assert r[..., channel].std() == pytest.approx(3.0, rel=0.05)
    for a, b in itertools.pairwise(residuals):
        assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.05
