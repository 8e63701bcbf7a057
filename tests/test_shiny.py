"""Shiny parts in the simulator and the decoder: the specular reflectance model, material keys
in scene files, the one-bounce interreflection path, and decode's interreflection mask.

Truths used: closed forms written here (GGX normalisation by numerical integration, the
mirror point of a plane by reflecting the camera centre, the bounce point of a V corner by
line-plane intersection), and synthetic fringe stacks whose second light path is known.
"""

from __future__ import annotations

import numpy as np
import pytest

from scanner.config import CONFIG_DIR
from scanner.decode import DecodeSettings, decode
from scanner.errors import ConfigError
from scanner.geometry import Pinhole, RigModel
from scanner.patterns import PatternSet
from scanner.rig import DEFAULT_RIG, RigConfig
from sim.render import Renderer, SensorModel
from sim.render.light_paths import bounce_path
from sim.render.reflectance import ggx_distribution, specular_weight, surface_weight
from sim.scene import MATERIALS, Scene, SceneObject

BENCH = RigConfig.load(DEFAULT_RIG)
MODEL = BENCH.nominal_model()
SENSOR = SensorModel.from_config(BENCH)
CORNER = CONFIG_DIR / "scenes" / "concave_corner.toml"
HETERODYNE = CONFIG_DIR / "patterns" / "heterodyne_3x4.toml"


def reduced(width: int = 320, height: int = 256) -> RigModel:
    """The bench rig with a camera of the same field of view and fewer pixels (fast tests)."""
    cam = MODEL.camera
    K = cam.K.copy()
    K[:2, :2] *= width / cam.width
    K[0, 2], K[1, 2] = (width - 1) / 2, (height - 1) / 2
    return RigModel(camera=Pinhole(width, height, K, cam.dist), projector=MODEL.projector,
                    cam_from_proj=MODEL.cam_from_proj, projector_gamma=MODEL.projector_gamma)


def flat_plate(distance: float, **material: float) -> SceneObject:
    pose = np.eye(4)
    pose[2, 3] = distance
    return SceneObject(name="plate", kind="plane", pose=pose, size_mm=(600.0, 600.0), **material)  # type: ignore[arg-type]


# --- reflectance ---------------------------------------------------------------------------

@pytest.mark.parametrize("alpha", [0.05, 0.2, 0.6])
def test_ggx_distribution_is_normalised(alpha):
    """∫ D(h) cos θh dω over the hemisphere is 1 (the definition of a microfacet distribution)."""
    theta = np.linspace(0.0, np.pi / 2, 200001)
    d = ggx_distribution(np.cos(theta), np.full_like(theta, alpha))
    integral = np.trapezoid(d * np.cos(theta) * np.sin(theta), theta) * 2 * np.pi
    assert integral == pytest.approx(1.0, abs=2e-3)


def test_matte_weight_is_exactly_lambertian():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    albedo, cos = rng.uniform(0, 1, 500), rng.uniform(0, 1, 500)
    w = surface_weight(albedo, cos, n, to_light=n, to_view=n, f0=np.zeros(500), roughness=np.full(500, 0.3))
    assert np.array_equal(w, albedo * cos)


def test_specular_peak_at_mirror_direction_matches_closed_form():
    """At the mirror direction h = n: D = 1/(π α²), F = Schlick at the incidence angle, G from
    Smith's GGX term; π D F G / (4 cos θv), written here independently; the weight falls off
    away from the mirror direction."""
    f0, rough, theta = 0.9, 0.2, np.radians(25.0)
    alpha = rough ** 2
    n = np.array([[0.0, 0.0, 1.0]])
    light = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
    mirror = np.array([[-np.sin(theta), 0.0, np.cos(theta)]])
    g1 = 2.0 / (1.0 + np.sqrt(1.0 + alpha ** 2 * np.tan(theta) ** 2))
    fresnel = f0 + (1 - f0) * (1 - np.cos(theta)) ** 5
    expected = np.pi * (1 / (np.pi * alpha ** 2)) * fresnel * g1 * g1 / (4 * np.cos(theta))
    peak = specular_weight(n, light, mirror, np.array([f0]), np.array([rough]))[0]
    assert peak == pytest.approx(expected, rel=1e-9)
    off = np.array([[-np.sin(theta + 0.1), 0.0, np.cos(theta + 0.1)]])
    assert specular_weight(n, light, off, np.array([f0]), np.array([rough]))[0] < 0.5 * peak
    assert specular_weight(n, light, mirror, np.array([0.0]), np.array([rough]))[0] == 0.0


def test_glint_lands_on_the_mirror_point_and_saturates():
    """A polished plate facing the camera: the brightest pixel is where the camera centre's
    mirror image lines up with the projector centre (x = baseline/2 on the plate), and it
    saturates at the rig exposure while a matte plate does not."""
    model = reduced()
    d = 420.0
    Cp = model.cam_from_proj[:3, 3]
    # the line from the projector centre to the camera's mirror image (0, 0, 2d) meets z = d here
    s = (d - Cp[2]) / (2 * d - Cp[2])
    mirror_point = Cp + s * (np.array([0.0, 0.0, 2 * d]) - Cp)
    expected_px = model.camera.project(mirror_point[None])[0]
    white = np.full((model.projector.height, model.projector.width), 255, np.uint8)
    shiny = Renderer(model, Scene((flat_plate(d, albedo=0.03, specular=0.91, roughness=0.12),)), SENSOR, 0.8)
    matte = Renderer(model, Scene((flat_plate(d, albedo=0.7),)), SENSOR, 0.8)
    img = shiny.irradiance(white)
    peak = np.unravel_index(np.argmax(img), img.shape)
    assert np.hypot(peak[1] - expected_px[0], peak[0] - expected_px[1]) < 3.0
    exposure = float(BENCH.camera.exposure_s or 0.01)
    assert shiny.render(white, exposure, 12, 0)[peak] == 4095
    assert matte.render(white, exposure, 12, 0).max() < 4095
    assert np.median(img[img > 0]) < 0.2 * np.median(matte.irradiance(white))  # dark away from the glint


# --- scene material keys ---------------------------------------------------------------------

def test_material_preset_and_overrides(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[[objects]]\nplane = { size_mm = [10, 10] }\nmaterial = "polished_aluminium"\nroughness = 0.3\n'
                 'pose = { translation_mm = [0, 0, 400] }\n')
    obj = Scene.load(p).objects[0]
    ref = MATERIALS["polished_aluminium"]
    assert (obj.albedo, obj.specular, obj.roughness) == (ref.albedo, ref.specular, 0.3)
    assert Scene.load(CONFIG_DIR / "scenes" / "demo.toml").objects[0].specular == 0.0
    assert Scene.load(CORNER).interreflection is True


@pytest.mark.parametrize("body, key", [
    ('material = "gold_leaf"', "objects[0].material"),
    ("specular = 1.5", "objects[0].specular"),
    ("roughness = 0.0", "objects[0].roughness"),
    ('specular = "high"', "objects[0].specular"),
])
def test_bad_material_names_file_and_key(tmp_path, body, key):
    p = tmp_path / "bad.toml"
    p.write_text(f"[[objects]]\nplane = {{ size_mm = [10, 10] }}\n{body}\npose = {{ translation_mm = [0, 0, 400] }}\n")
    with pytest.raises(ConfigError) as e:
        Scene.load(p)
    assert key in str(e.value) and "bad.toml" in str(e.value)


# --- interreflection in the renderer ---------------------------------------------------------------

@pytest.fixture(scope="module")
def corner_renderer() -> Renderer:
    return Renderer(reduced(), Scene.load(CORNER), SENSOR, 0.8)


def test_bounce_lands_where_the_mirrored_ray_meets_the_other_plate(corner_renderer):
    """For pixels on the left plate, the bounce's projector pixel is the projection of the point
    where the camera ray, mirrored about the left plate's normal, meets the right plate."""
    r = corner_renderer
    gt = r.ground_truth
    bounce = r.paths[1]
    left = gt.object_id.ravel()[bounce.index] == Scene.load(CORNER).id_of("left_plate")
    assert left.sum() > 500
    idx, uv = bounce.index[left][::50], bounce.uv[left][::50]
    X1 = gt.points.reshape(-1, 3)[idx]
    n_left = np.array([-1.0, 0.0, 1.0]) / np.sqrt(2)
    n_right = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    d = X1 / np.linalg.norm(X1, axis=1, keepdims=True)
    ray = d - 2 * (d @ n_left)[:, None] * n_left
    apex = np.array([0.0, 0.0, 440.0])  # both plates contain the fold line through this point
    t = ((apex - X1) @ n_right) / (ray @ n_right)
    X2 = X1 + ray * t[:, None]
    P = r.model.proj_from_cam
    expected = r.model.projector.project(X2 @ P[:3, :3].T + P[:3, 3])
    # the renderer starts the mirrored ray BOUNCE_OFFSET_MM (1e-4 mm) off the plate: ~2e-4 px here
    assert np.max(np.abs(uv - expected)) < 1e-3
    assert np.array_equal(gt.proj_uv, Renderer(reduced(), Scene(Scene.load(CORNER).objects,
                                                                Scene.load(CORNER).reference_plane),
                                                SENSOR, 0.8).ground_truth.proj_uv, equal_nan=True)


def test_matte_scene_has_no_bounce():
    scene = Scene((flat_plate(420.0, albedo=0.7),), interreflection=True)
    gt = Renderer(reduced(), Scene((flat_plate(420.0, albedo=0.7),)), SENSOR).ground_truth
    assert bounce_path(gt, scene).index.size == 0


# --- decode's interreflection mask -----------------------------------------------------------------

def two_path_stack(ratio: float, shift_px: float, noise_dn: float = 2.0, seed: int = 0
                   ) -> tuple[np.ndarray, PatternSet, np.ndarray, np.ndarray]:
    """A heterodyne stack of 96 x 300 px: every column a projector coordinate u; the bottom
    half also gets a second path of `ratio` x the amplitude from u + `shift_px`. Returns the
    stack, patterns, the true coordinate per pixel and the second-path mask."""
    ps = PatternSet.load(HETERODYNE)
    extent = MODEL.projector.width
    u = np.linspace(30.0, extent - 30.0, 300)
    second = np.zeros((96, 300), bool)
    second[48:] = True
    rng = np.random.default_rng(seed)
    frames = []
    for spec in ps.frames():
        prof = ps.profile(spec, extent)
        direct = np.interp(u, np.arange(extent), prof)
        other = np.interp(u + shift_px, np.arange(extent), prof)
        img = 300.0 + 2000.0 * np.where(second, direct + ratio * other, direct)
        frames.append(img + rng.normal(0, noise_dn, img.shape))
    stack = np.clip(np.rint(frames), 0, 4095).astype(np.uint16)
    return stack, ps, np.broadcast_to(u, (96, 300)), second


def test_second_light_path_is_masked_with_its_own_reason():
    stack, ps, u, second = two_path_stack(ratio=0.4, shift_px=60.0)
    d = decode(stack, ps, 12, MODEL.projector.size, DecodeSettings(spatial_check=False))
    m = d.maps["vertical"]
    ir = m.masks["interreflection"]
    assert ir[~second].mean() < 0.01
    assert ir[second].mean() > 0.8
    assert not (ir & m.valid).any()
    assert not (ir & m.masks["order_error"]).any()  # one reason per pixel
    err = np.abs(m.coordinate - u)
    assert np.nanmax(err[m.valid & ~second]) < 0.5
    off = DecodeSettings(spatial_check=False, interreflection=False, self_check=False)
    unmasked = decode(stack, ps, 12, MODEL.projector.size, off)
    assert {c.name: c.passed for c in unmasked.checks}["frequency_agreement"] is False  # unmasked: it refuses itself
    before = unmasked.maps["vertical"]
    assert "interreflection" not in before.masks
    bad_before = (np.abs(before.coordinate - u) > 0.5) & before.valid & second
    bad_after = (err > 0.5) & m.valid & second
    assert bad_after.sum() < 0.1 * max(bad_before.sum(), 1)


def test_single_path_noise_is_not_called_interreflection():
    stack, ps, _, _second = two_path_stack(ratio=0.0, shift_px=0.0, noise_dn=6.0, seed=3)
    m = decode(stack, ps, 12, MODEL.projector.size, DecodeSettings(spatial_check=False)).maps["vertical"]
    assert m.masks["interreflection"].mean() < 0.005
