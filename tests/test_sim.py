"""Tests of the simulator (sim/): scenes, ground truth, image formation, devices, faults.

Most tests use the bench rig with a reduced camera (same field of view, fewer pixels) so
the whole file runs in well under a minute. Nothing here measures wall time: the
simulated frame time at full resolution and the sequence period are measured by
`slscan bench sim` (with the load average and a peer); tests synchronise on events.
"""

from __future__ import annotations

import re
import time
from contextlib import suppress
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from scanner.config import CONFIG_DIR
from scanner.devices import TriggerType
from scanner.drivers.testing import grab_in_thread, wait_bound_s
from scanner.errors import ConfigError, DeviceDisconnected, DeviceError, WaitTimeout
from scanner.geometry import Pinhole, RigModel
from scanner.rig import DEFAULT_RIG, RigConfig, open_rig
from sim.render import BSplineSampler, Renderer, SensorModel, compute_ground_truth
from sim.scene import Scene, SceneObject, load_scene
from sim.virtual_devices import Faults, SimCamera, SimProjector
from sim.virtual_rig import open_sim_rig

BENCH = RigConfig.load(DEFAULT_RIG)
MODEL = BENCH.nominal_model()
PW, PH = MODEL.projector.width, MODEL.projector.height
SHORT = 0.3  # grab timeout in fault tests (s)


def small_model(width: int = 320, height: int = 256, **kw: object) -> RigModel:
    """The bench rig with a smaller camera of the same field of view and distortion."""
    cam = MODEL.camera
    s = width / cam.width
    K = cam.K.copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 2] = (width - 1) / 2
    K[1, 2] = (height - 1) / 2
    args = dict(camera=Pinhole(width, height, K, cam.dist), projector=MODEL.projector,
                cam_from_proj=MODEL.cam_from_proj, projector_gamma=MODEL.projector_gamma)
    args.update(kw)
    return RigModel(**args)  # type: ignore[arg-type]


def plane(distance: float = 450.0, pose: np.ndarray | None = None, albedo: float = 0.8) -> SceneObject:
    if pose is None:
        pose = np.eye(4)
        pose[2, 3] = distance
    return SceneObject(name="reference_plane", kind="plane", pose=pose, albedo=albedo, size_mm=(1000.0, 1000.0))


def sphere(centre: list[float], radius: float, albedo: float = 0.7, name: str = "sphere") -> SceneObject:
    pose = np.eye(4)
    pose[:3, 3] = centre
    return SceneObject(name=name, kind="sphere", pose=pose, albedo=albedo, radius_mm=radius)


def fringe(pitch: float, shift: float = 0.0, gamma: float = 1.0, vertical: bool = True) -> np.ndarray:
    """A gamma-precompensated uint8 sinusoidal fringe pattern."""
    n = PW if vertical else PH
    c = 0.5 + 0.5 * np.cos(2 * np.pi * np.arange(n) / pitch + shift)
    line = np.round(255 * c ** (1.0 / gamma)).astype(np.uint8)
    return np.ascontiguousarray(np.broadcast_to(line[None, :] if vertical else line[:, None], (PH, PW)))


def flat(value: int) -> np.ndarray:
    return np.full((PH, PW), value, dtype=np.uint8)


@pytest.fixture(scope="module")
def rig_toml(tmp_path_factory: pytest.TempPathFactory):
    """Writes variants of the bench rig TOML with a 320 x 256 camera."""
    text = DEFAULT_RIG.read_text()
    text = text.replace("width = 1280\nheight = 1024", "width = 320\nheight = 256")
    text = text.replace('patterns = "../patterns/heterodyne_3x4.toml"',
                        f'patterns = "{(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml").as_posix()}"')
    assert "width = 320" in text
    folder = tmp_path_factory.mktemp("rigs")
    count = [0]

    def make(trigger: str = "software", extra: str = "", bits: int = 12) -> Path:
        t = re.sub(r'trigger = "\w+"', f'trigger = "{trigger}"', text, count=1)
        t = t.replace("bit_depth = 12", f"bit_depth = {bits}")
        count[0] += 1
        p = folder / f"rig{count[0]}.toml"
        p.write_text(t + "\n" + extra)
        return p

    return make


@pytest.fixture(scope="module")
def sphere_scene() -> Scene:
    return load_scene(CONFIG_DIR / "scenes" / "sphere_plane.toml")


@pytest.fixture(scope="module")
def sw_rig(rig_toml, sphere_scene):
    rig = open_sim_rig(RigConfig.load(rig_toml("software")), scene=sphere_scene, seed=3)
    yield rig
    rig.shutdown()


def fault_rig(rig_toml, scene: Scene, faults: Faults):
    return open_sim_rig(RigConfig.load(rig_toml("software")), scene=scene, faults=faults)


def acquire(rig, n: int, timeout: float = 2.0):
    """Software-triggered lockstep acquisition of n frames of a blank projector."""
    rig.camera.arm(n)
    out = []
    for _ in range(n):
        rig.camera.trigger()
        out.append(rig.camera.grab(timeout))
    return out


# ----------------------------------------------------------------------------- scenes


def test_bundled_scenes_load():
    demo = load_scene(None)
    assert demo.names == {0: "background", 1: "reference_plane", 2: "demo_part"}
    lo, hi = demo.objects[0].bounds()
    assert hi[2] == pytest.approx(420.0) and 60 < (hi - lo)[:2].max() < 120  # lies on the plane at 420 mm
    sp = load_scene(CONFIG_DIR / "scenes" / "sphere_plane.toml")
    assert sp.objects[0].kind == "sphere" and sp.objects[0].radius_mm == 20.0
    assert np.allclose(sp.reference_plane.plane_equation(), [0, 0, -1, 440])


def test_demo_part_is_watertight_and_matches_generator():
    import open3d as o3d

    from sim.parts_demo import OUTPUT, build_demo_part

    v, t = build_demo_part()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    assert mesh.is_watertight() and mesh.is_orientable() and not mesh.is_self_intersecting()
    assert mesh.get_volume() > 0  # outward normals
    ext = v.max(axis=0) - v.min(axis=0)
    assert 60 <= ext.max() <= 100
    stored = o3d.io.read_triangle_mesh(str(OUTPUT))
    assert len(stored.triangles) == len(t)
    assert np.allclose(np.asarray(stored.vertices), v, atol=1e-4)


def test_bare_mesh_scene_placement():
    s = Scene.load(CONFIG_DIR / "parts" / "demo_part.ply", working_distance_mm=380.0)
    lo, hi = s.objects[0].bounds()
    assert np.allclose((lo + hi) / 2, [0, 0, 380.0], atol=1e-9)
    assert s.reference_plane.pose[2, 3] == pytest.approx(hi[2])  # touches the far side
    assert np.allclose(s.reference_plane.pose[:3, :3], np.eye(3))
    # CAD +z faces the camera: the boss top (part z = 35) is the nearest point
    v = s.objects[0].world_vertices()
    assert v[np.argmin(v[:, 2])][2] == pytest.approx(lo[2])


@pytest.mark.parametrize("body, key", [
    ('[[objects]]\nsphere = { radius_mm = 10.0 }\nalbedo = 1.5\n', "objects[0].albedo"),
    ('[[objects]]\nmesh = "missing.ply"\n', "objects[0].mesh"),
    ('[[objects]]\nsphere = { radius_mm = -1.0 }\n', "objects[0].sphere.radius_mm"),
    ('[[objects]]\nsphere = { radius_mm = 5.0 }\nalbdo = 0.5\n', "objects[0].albdo"),
    ('[[objects]]\nsphere = { radius_mm = 5.0 }\nbox = { size_mm = [1, 2, 3] }\n', "objects[0]"),
    ('[[objects]]\nbox = { size_mm = [1, 2] }\n', "objects[0].box.size_mm"),
    ('[[objects]]\nsphere = { radius_mm = 5.0 }\npose = { translation_mm = [0, 0] }\n',
     "objects[0].pose.translation_mm"),
    ('[reference_plane]\nsize_mm = [10.0, 10.0]\n', "reference_plane"),
    ('[reference_plane]\ndistance_mm = "far"\n', "reference_plane.distance_mm"),
])
def test_broken_scene_names_file_and_key(tmp_path, body, key):
    p = tmp_path / "broken.toml"
    p.write_text(body)
    with pytest.raises(ConfigError) as err:
        Scene.load(p)
    assert err.value.key == key
    assert Path(err.value.path) == p
    assert str(p) in str(err.value) and key in str(err.value)


def test_invalid_toml_names_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[[objects]\nsphere = 3\n")
    with pytest.raises(ConfigError, match="bad.toml"):
        Scene.load(p)


# ----------------------------------------------------------------------- ground truth


def test_plane_depth_matches_analytic():
    model = small_model()
    rot = np.array([0.2, -0.3, 0.1])
    import cv2

    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rot)[0]
    pose[:3, 3] = [10.0, -5.0, 430.0]
    gt = compute_ground_truth(model, Scene(objects=(), reference_plane=plane(pose=pose)))
    assert gt.hit.all()
    n, c = pose[:3, 2], -pose[:3, 2] @ pose[:3, 3]
    # every GT point lies on its pixel's (distorted) camera ray ...
    uv = np.stack(np.meshgrid(np.arange(model.camera.width), np.arange(model.camera.height)), -1).reshape(-1, 2)
    assert np.abs(model.camera.project(gt.points.reshape(-1, 3)) - uv).max() < 1e-6
    # ... and on the plane: depth analytic along the ray
    rays = gt.points.reshape(-1, 3) / gt.depth.reshape(-1, 1)
    depth = -c / (rays @ n)
    assert np.abs(depth - gt.depth.ravel()).max() < 1e-9
    assert np.allclose(np.abs(gt.normal.reshape(-1, 3) @ n), 1.0)
    assert (gt.object_id == 1).all()


def test_camera_rays_are_ray_grid():
    from sim.render import camera_rays

    cam = small_model().camera
    assert np.abs(camera_rays(cam) - cam.ray_grid).max() < 1e-6  # ray_grid in float64


def test_box_and_mesh_formats(tmp_path):
    import open3d as o3d

    from sim.parts_demo import build_demo_part

    v, t = build_demo_part()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    mesh.compute_triangle_normals()
    for ext in ("stl", "obj"):
        assert o3d.io.write_triangle_mesh(str(tmp_path / f"part.{ext}"), mesh)
    (tmp_path / "s.toml").write_text(
        '[[objects]]\nmesh = "part.stl"\nname = "a"\n'
        '[[objects]]\nmesh = "part.obj"\nname = "b"\nscale = 0.5\n'
        '[[objects]]\nbox = { size_mm = [40, 30, 20] }\npose = { translation_mm = [0, 0, 400] }\n')
    s = Scene.load(tmp_path / "s.toml")
    assert [o.kind for o in s.objects] == ["mesh", "mesh", "box"] and s.id_of("b") == 3
    assert np.allclose(s.objects[0].bounds()[1], v.max(axis=0), atol=1e-4)
    assert np.allclose(s.objects[1].bounds()[1], v.max(axis=0) / 2, atol=1e-4)
    box_only = Scene(objects=(s.objects[2],))
    gt = compute_ground_truth(small_model(), box_only)
    on = gt.object_id == 2
    assert on.sum() > 500 and (gt.object_id[~on] == 0).all()
    assert np.abs(gt.depth[on] - 390.0).max() < 1e-9 and np.allclose(gt.normal[on], [0, 0, -1])
    assert np.abs(gt.points[on][:, :2]).max(axis=0) == pytest.approx([20, 15], abs=0.5)  # 0.49 mm pixels


def test_sphere_ground_truth_exact(sphere_scene):
    gt = compute_ground_truth(small_model(), sphere_scene)
    on = gt.object_id == 2
    assert on.sum() > 1000
    c = np.array([0, 0, 400.0])
    r = np.linalg.norm(gt.points[on] - c, axis=1)
    assert np.abs(r - 20.0).max() < 1e-9  # analytic: far below the 0.002 mm tessellation bound
    assert np.allclose(gt.normal[on], (gt.points[on] - c) / 20.0, atol=1e-9)
    assert np.allclose(gt.depth[gt.object_id == 1], 440.0, atol=1e-9)


def test_mesh_ground_truth_on_triangles():
    scene = load_scene(None)
    gt = compute_ground_truth(small_model(), scene)
    part = gt.mask("demo_part")
    assert part.sum() > 1000 and (gt.object_id == 1).sum() > 1000
    # the part's top faces: plane z = 420 - 35 (boss top, annulus) and 420 - 22 (high step)
    z = gt.depth[part]
    for level in (385.0, 398.0, 410.0):  # boss top, high step, low plate top: flat faces, exact
        assert (np.abs(z - level) < 1e-9).sum() > 20
    assert gt.depth[part].min() >= 385.0 - 1e-9 and gt.depth[part].max() <= 420.0 + 1e-9


def test_projector_uv_reprojects(sphere_scene):
    model = small_model()
    gt = compute_ground_truth(model, sphere_scene)
    lit = gt.lit
    assert 0.5 < lit.mean() < 1.0
    X = gt.points[lit]
    P = model.proj_from_cam
    uv = model.projector.project(X @ P[:3, :3].T + P[:3, 3])
    assert np.abs(uv - gt.proj_uv[lit]).max() < 1e-6
    assert (gt.proj_uv[lit] >= -0.5).all() and (gt.proj_uv[lit][:, 0] <= PW - 0.5).all()
    assert np.isnan(gt.proj_uv[~lit]).all() and (gt.shadow == (gt.hit & ~lit)).all()
    # incidence: angle between the normal and the direction to the projector centre
    to_p = model.cam_from_proj[:3, 3] - X
    cos = np.einsum("ij,ij->i", gt.normal[lit], to_p) / np.linalg.norm(to_p, axis=1)
    assert np.allclose(gt.cos_incidence[lit], cos, atol=1e-12)


def test_shadow_behind_occluder():
    model = small_model()
    Cp = model.cam_from_proj[:3, 3]
    ball = np.array([40.0, 0.0, 300.0])  # between projector and plane, off the camera's line of sight
    scene = Scene(objects=(sphere(list(ball), 10.0),), reference_plane=plane(440.0))
    # the plane point straight behind the ball as seen from the projector centre
    s = (440.0 - Cp[2]) / (ball[2] - Cp[2])
    X = Cp + s * (ball - Cp)
    u, v = np.rint(model.camera.project(X[None])[0]).astype(int)
    renderer = Renderer(model, scene, SensorModel(blur_sigma_px=0.6), 0.8)
    gt = renderer.ground_truth
    assert gt.object_id[v, u] == 1  # the camera sees the plane there ...
    assert gt.occluded[v, u] and gt.shadow[v, u] and np.isnan(gt.proj_uv[v, u]).all()  # ... but not the projector
    assert gt.occluded.sum() > 100
    white = renderer.mean_dn(flat(255), 0.01, 12)
    ambient = renderer.mean_dn(None, 0.01, 12)
    assert white[v, u] == pytest.approx(ambient[v, u], rel=1e-6)  # no fringe light in the shadow
    lit_plane = gt.lit & (gt.object_id == 1)
    assert np.median(white[lit_plane]) > 10 * ambient[v, u]


# ------------------------------------------------------------------ image formation


def test_interpolation_accuracy_of_sampled_fringe():
    rng = np.random.default_rng(0)
    n = 20000
    uv = np.stack([rng.uniform(-0.5, PW - 0.5, n), rng.uniform(-0.5, PH - 0.5, n)], axis=1)
    sampler = BSplineSampler(uv, (PH, PW))
    for pitch in (12.0, 13.0, 16.0, 32.0):
        for vertical in (True, False):
            coord = np.arange(PW if vertical else PH)
            line = np.cos(2 * np.pi * coord / pitch + 0.3)
            img = np.broadcast_to(line[None, :] if vertical else line[:, None], (PH, PW))
            truth = np.cos(2 * np.pi * (uv[:, 0] if vertical else uv[:, 1]) / pitch + 0.3)
            # the spline's mirror boundary perturbs the outer ~6 px (decay 0.27 per px) of a non-symmetric image
            inner = (uv >= 6).all(axis=1) & (uv[:, 0] < PW - 7) & (uv[:, 1] < PH - 7)
            err = np.abs(sampler(img) - truth)[inner].max()
            assert err < 1e-3, (pitch, vertical, err)  # of the fringe amplitude (1)
            if pitch <= 16:  # the reason not to interpolate linearly
                lin = ndimage.map_coordinates(img, [uv[:, 1], uv[:, 0]], order=1, mode="mirror")
                assert np.abs(lin - truth)[inner].max() > 10 * err
    # the sparse sampler is scipy's cubic B-spline, borders included
    img = rng.random((PH, PW))
    ref = ndimage.map_coordinates(img, [uv[:, 1], uv[:, 0]], order=3, mode="mirror")
    assert np.abs(sampler(img) - ref).max() < 1e-5


def test_renderer_samples_fringe_at_ground_truth_uv(sphere_scene):
    r = Renderer(small_model(), sphere_scene, SensorModel(), 0.8)
    gt = r.ground_truth
    pitch = PW / 70
    img = np.broadcast_to(np.cos(2 * np.pi * np.arange(PW) / pitch), (PH, PW))
    got = r.sample_projector(img)[gt.lit]
    want = np.cos(2 * np.pi * gt.proj_uv[gt.lit][:, 0] / pitch)
    assert np.abs(got - want).max() < 1e-3
    assert (r.sample_projector(img)[~gt.lit] == 0).all()


def test_shading_formula_and_gamma(sphere_scene):
    model = small_model(projector_gamma=2.2)
    sensor = SensorModel(blur_sigma_px=0.0)
    r = Renderer(model, sphere_scene, sensor, projector_blur_sigma_px=0.8)
    gt = r.ground_truth
    full = r.irradiance(flat(255))
    assert np.allclose(full[gt.lit], (gt.albedo * gt.cos_incidence)[gt.lit], rtol=1e-5)
    assert (full[~gt.lit] == 0).all()
    half = r.irradiance(flat(128))
    assert np.allclose(half[gt.lit] / full[gt.lit], (128 / 255) ** 2.2, rtol=1e-5)
    assert np.allclose(r.projector_output(flat(128)), (128 / 255) ** 2.2, rtol=1e-6)
    # electrons = exposure * flux * (ambient + albedo cos output)
    e = r.mean_electrons(flat(128), 0.004)
    want = 0.004 * sensor.flux_e_per_s * (sensor.ambient + gt.albedo * gt.cos_incidence * (128 / 255) ** 2.2)
    assert np.allclose(e, want, rtol=1e-5)


@pytest.mark.parametrize("bits", [8, 10, 12])
def test_noise_matches_sensor_model(bits, sphere_scene):
    model = small_model()
    sensor = SensorModel(blur_sigma_px=0.0)
    r = Renderer(model, sphere_scene, sensor, 0.8)
    region = r.ground_truth.lit & (r.ground_truth.object_id == 1)  # the lit plane: flat, uniform
    pattern = flat(200)
    mean = r.mean_dn(pattern, 0.01, bits)[region]
    frames = np.stack([r.render(pattern, 0.01, bits, rng=k)[region].astype(np.float64) for k in range(12)])
    empirical = frames.std(axis=0, ddof=1)
    model_sigma = sensor.noise_sigma_dn(mean, bits)
    ratio = np.sqrt(np.mean(empirical ** 2) / np.mean(model_sigma ** 2))
    assert abs(ratio - 1) < 0.05, ratio
    assert abs(frames.mean() / mean.mean() - 1) < 2e-3  # unbiased


@pytest.mark.parametrize("bits, dtype", [(8, np.uint8), (10, np.uint16), (12, np.uint16)])
def test_quantisation_and_saturation(bits, dtype):
    sensor = SensorModel(full_well_e=10000.0, read_noise_e=5.0)
    top = (1 << bits) - 1
    g = sensor.gain_e_per_dn(bits)
    assert g == pytest.approx(10000.0 / top)
    rng = np.random.default_rng(1)
    mean_e = np.full((200, 200), 0.37 * 10000.0, dtype=np.float32)
    img = sensor.expose(mean_e, bits, rng)
    assert img.dtype == dtype
    assert img.mean() == pytest.approx(0.37 * top, rel=2e-3)  # full well maps onto 2**bits - 1
    assert img.std() == pytest.approx(float(sensor.noise_sigma_dn(0.37 * top, bits)), rel=0.05)
    sat = sensor.expose(np.full((50, 50), 1.5 * 10000.0, dtype=np.float32), bits, rng)
    assert (sat == top).all()  # clipped at 2**bits - 1
    dark = sensor.expose(np.zeros((50, 50), dtype=np.float32), bits, rng)
    assert dark.min() == 0 and dark.dtype == dtype  # read noise below zero clips at 0


def test_render_deterministic_with_seed(sphere_scene):
    r = Renderer(small_model(), sphere_scene, SensorModel(), 0.8)
    p = fringe(13.0)
    a, b, c = r.render(p, 0.01, 12, 5), r.render(p, 0.01, 12, 5), r.render(p, 0.01, 12, 6)
    assert (a == b).all() and not (a == c).all()


# ----------------------------------------------------------------------------- devices


def test_open_rig_factory_and_extras(rig_toml):
    cfg = RigConfig.load(rig_toml("software", bits=10))
    with open_rig(cfg, scene=CONFIG_DIR / "scenes" / "sphere_plane.toml") as rig:
        assert isinstance(rig.camera, SimCamera) and isinstance(rig.projector, SimProjector) and rig.trigger is None
        assert rig.camera.bit_depth == 10 and rig.camera.exposure_s == 0.010
        gt = rig.extras["ground_truth"]
        assert gt.depth.shape == (256, 320) and rig.extras["scene"].name == "sphere_plane"
        assert gt.model is rig.extras["renderer"].model
        assert np.allclose(rig.model.cam_from_proj, gt.model.cam_from_proj)


def test_software_trigger_renders_current_pattern(sw_rig):
    cam, proj, r = sw_rig.camera, sw_rig.projector, sw_rig.extras["renderer"]
    pats = np.stack([fringe(13.0, k * np.pi / 2, 2.2) for k in range(4)])
    proj.load_patterns(pats)
    cam.arm(3)
    proj.show(2)
    cam.trigger()
    proj.show(0)  # changes after the trigger do not reach the exposure
    f = cam.grab(2.0)
    assert (f.index, f.pattern_index, f.bit_depth, f.exposure_s) == (0, 2, 12, 0.010)
    gen = cam._generation
    want = r.render(pats[2], 0.010, 12, np.random.default_rng([cam.seed, gen, 0]))
    assert (f.image == want).all()
    proj.blank()
    cam.trigger()
    f = cam.grab(2.0)
    assert f.index == 1 and f.pattern_index is None
    ambient = r.mean_dn(None, 0.01, 12)
    assert abs(f.image.mean() - ambient.mean()) < 1.0  # dark projector: ambient only
    cam.trigger()
    cam.grab(2.0)
    with pytest.raises(DeviceError, match="already triggered"):
        cam.trigger()  # only n frames per arming


def test_grab_timeout_names_device_and_index(sw_rig):
    cam = sw_rig.camera
    cam.arm(2)
    t0 = time.monotonic()
    with pytest.raises(WaitTimeout) as err:
        cam.grab(SHORT)
    assert SHORT <= time.monotonic() - t0 < wait_bound_s(SHORT)
    assert str(err.value).startswith("sim-camera: stopped waiting for frame index 0 after 0.3 s; 0 of 2 frames "
                                     "triggered since arm; it was never triggered (call trigger())")


def test_rendering_time_is_not_device_time(sw_rig, monkeypatch):
    """A loaded machine renders slowly; the simulated camera's grab timeout counts device
    time only, so a render taking 3x the timeout still delivers (a real camera would)."""
    cam, proj = sw_rig.camera, sw_rig.projector
    render = cam.renderer.render

    def slow_render(*args, **kwargs):
        time.sleep(3 * SHORT)  # stands for a slow render on a busy machine
        return render(*args, **kwargs)

    monkeypatch.setattr(cam.renderer, "render", slow_render)
    proj.load_patterns(np.stack([flat(10), flat(200)]))
    cam.arm(1)
    proj.show(1)
    cam.trigger()
    assert cam.grab(SHORT).index == 0


@pytest.mark.parametrize("delivered", [True, False])
def test_arm_flushes_stale_frames(sw_rig, delivered):
    """A frame of the previous arming never comes out: neither one delivered and waiting
    to be grabbed, nor one still being rendered when the camera is armed again."""
    cam, proj = sw_rig.camera, sw_rig.projector
    proj.load_patterns(np.stack([flat(10), flat(200)]))
    cam.arm(1)
    proj.show(1)
    cam.trigger()
    if delivered:
        assert cam.wait_delivered(1, wait_bound_s(1.0))
    cam.arm(1)  # the frame of the previous arming must not come out
    with pytest.raises(WaitTimeout):
        cam.grab(SHORT)
    proj.show(0)
    cam.trigger()
    f = cam.grab(2.0)
    assert f.index == 0 and f.pattern_index == 0


def test_hardware_trigger_ignored_in_software_mode(sw_rig):
    cam = sw_rig.camera
    cam.arm(1)
    before = cam.ignored_triggers
    cam.trigger_in()
    assert cam.ignored_triggers == before + 1
    with pytest.raises(WaitTimeout):
        cam.grab(0.1)


def test_projector_sequence_triggers_camera(rig_toml, sphere_scene):
    with open_sim_rig(RigConfig.load(rig_toml("projector")), scene=sphere_scene) as rig:
        assert rig.camera.trigger_type is TriggerType.RISING_EDGE
        pats = np.stack([fringe(13.0, k * np.pi / 3) for k in range(6)])
        rig.projector.load_patterns(pats)
        rig.camera.arm(6)
        seen = []
        status = rig.projector.run_sequence(0.03, on_pattern=seen.append)
        frames = [rig.camera.grab(2.0) for _ in range(6)]
        status.wait(wait_bound_s(6 * 0.03))
        assert status.success and rig.projector.current_pattern is None  # dark after the last
        assert [f.index for f in frames] == list(range(6))
        assert [f.pattern_index for f in frames] == list(range(6)) == seen
        stamps = np.array([f.timestamp_s for f in frames])
        assert (np.diff(stamps) > 0).all()  # the period itself is measured by `slscan bench sim`
        with pytest.raises(DeviceError):
            rig.camera.trigger()  # hardware-triggered: software trigger refused


def test_projector_sequence_status_carries_a_listener_error(rig_toml, sphere_scene):
    """An `on_pattern` callback that raises ends the sequence; its waiter gets that error."""
    with open_sim_rig(RigConfig.load(rig_toml("projector")), scene=sphere_scene) as rig:
        rig.projector.load_patterns(np.stack([fringe(13.0, k * np.pi / 3) for k in range(6)]))

        def on_pattern(k: int) -> None:
            if k == 2:
                raise DeviceError("listener", "pattern 2 refused")

        status = rig.projector.run_sequence(0.03, on_pattern=on_pattern)
        with pytest.raises(DeviceError, match="listener: pattern 2 refused"):
            status.wait(wait_bound_s(6 * 0.03))
        assert rig.projector.current_pattern == 2  # the sequence stopped there


def test_trigger_box_drives_projector_and_camera(rig_toml, sphere_scene):
    with open_sim_rig(RigConfig.load(rig_toml("trigger_box")), scene=sphere_scene) as rig:
        rig.projector.load_patterns(np.stack([fringe(16.0, k * np.pi / 2) for k in range(5)]))
        rig.camera.arm(5)
        rig.trigger.arm(5, 0.03)
        status = rig.trigger.start()
        frames = [rig.camera.grab(2.0) for _ in range(5)]
        assert [(f.index, f.pattern_index) for f in frames] == [(k, k) for k in range(5)]
        status.wait(wait_bound_s(5 * 0.03))
        assert status.success and rig.trigger.pulses_sent == 5


def test_shutdown_idempotent_and_final(rig_toml, sphere_scene):
    rig = open_sim_rig(RigConfig.load(rig_toml("trigger_box")), scene=sphere_scene)
    rig.camera.arm(1)
    th, outcome = grab_in_thread(rig.camera, 600.0)
    rig.shutdown()
    rig.shutdown()
    th.join(wait_bound_s(1.0))
    assert not th.is_alive() and isinstance(outcome[0], DeviceDisconnected)  # a waiting grab wakes up
    for call in (lambda: rig.camera.arm(1), lambda: rig.camera.grab(0.1), lambda: rig.camera.set_exposure(0.01),
                 lambda: rig.projector.show(0), lambda: rig.projector.load_patterns(np.stack([flat(1)])),
                 lambda: rig.trigger.arm(1, 0.1), lambda: rig.trigger.start()):
        with pytest.raises(DeviceDisconnected):
            call()
    rig.camera.trigger_in()  # a pulse into a dead device is ignored, not raised into the sender


# ------------------------------------------------------------------------------ faults


def test_fault_drop_frame(rig_toml, sphere_scene):
    with fault_rig(rig_toml, sphere_scene, Faults(drop_frame=2)) as rig:
        rig.camera.arm(4)
        got = []
        for _ in range(4):
            rig.camera.trigger()
            try:
                got.append(rig.camera.grab(SHORT).index)
            except WaitTimeout:
                got.append("timeout")
        assert got == [0, 1, "timeout", 3]  # the next delivered frame after the gap is k + 1
        assert [f.index for f in acquire(rig, 4)] == [0, 1, 2, 3]  # transient: a retry succeeds


def test_fault_delay_frame(rig_toml, sphere_scene):
    with fault_rig(rig_toml, sphere_scene, Faults(delay_frame=1, delay_s=0.6)) as rig:
        cam = rig.camera
        cam.arm(3)
        cam.trigger()
        assert cam.grab(2.0).index == 0
        cam.trigger()
        with pytest.raises(WaitTimeout, match="stopped waiting for frame index 1"):
            cam.grab(SHORT)
        assert cam.grab(2.0).index == 1  # it arrives, late: a wait timeout, not a failed device


def test_fault_stale_frame(rig_toml, sphere_scene):
    with fault_rig(rig_toml, sphere_scene, Faults(stale_frame=2)) as rig:
        pats = np.stack([fringe(13.0, k) for k in range(4)])
        rig.projector.load_patterns(pats)
        rig.camera.arm(4)
        frames = []
        for k in range(4):
            rig.projector.show(k)
            rig.camera.trigger()
            frames.append(rig.camera.grab(2.0))
        assert [(f.index, f.pattern_index) for f in frames] == [(0, 0), (1, 1), (1, 1), (3, 3)]
        assert (frames[2].image == frames[1].image).all()


def test_fault_disconnect_after(rig_toml, sphere_scene):
    with fault_rig(rig_toml, sphere_scene, Faults(disconnect_after=2)) as rig:
        cam = rig.camera
        assert [f.index for f in acquire(rig, 2)] == [0, 1]
        assert not cam.is_connected
        with pytest.raises(DeviceDisconnected):
            cam.grab(SHORT)
        with pytest.raises(DeviceDisconnected):
            cam.arm(1)
        with pytest.raises(DeviceDisconnected):
            cam.trigger()
    # frames triggered but not yet delivered when the camera goes are lost with it
    with fault_rig(rig_toml, sphere_scene, Faults(disconnect_after=1)) as rig:
        cam = rig.camera
        cam.arm(3)
        cam.trigger()
        cam.trigger()
        assert cam.grab(2.0).index == 0
        with pytest.raises(DeviceDisconnected, match="expected frame index 1"):
            cam.grab(2.0)
    # a grab already waiting when the camera goes (unplugged at run time) wakes with DeviceDisconnected
    with fault_rig(rig_toml, sphere_scene, Faults()) as rig:
        cam = rig.camera
        cam.arm(1)
        th, outcome = grab_in_thread(cam, 600.0)
        cam.set_faults(Faults(disconnect_after=0))
        th.join(wait_bound_s(1.0))
        assert not th.is_alive() and isinstance(outcome[0], DeviceDisconnected)


def test_faults_from_rig_toml(rig_toml, sphere_scene):
    cfg = RigConfig.load(rig_toml("software", extra="[sim.faults]\ndrop_frame = 1\nrepeat = true\n"))
    with open_sim_rig(cfg, scene=sphere_scene) as rig:
        assert rig.extras["faults"] == Faults(drop_frame=1, repeat=True)
        for _ in range(2):  # repeat = true: every arming loses frame 1
            rig.camera.arm(3)
            idx = []
            for _ in range(3):
                rig.camera.trigger()
                with suppress(WaitTimeout):
                    idx.append(rig.camera.grab(SHORT).index)
            assert idx == [0, 2]
    bad_path = rig_toml("software", extra="[sim.faults]\ndrop_frme = 1\n")
    with pytest.raises(ConfigError) as err:  # refused when the rig is loaded, before any device opens
        open_sim_rig(RigConfig.load(bad_path), scene=sphere_scene)
    assert err.value.key == "sim.faults.drop_frme" and str(bad_path) in str(err.value)
    bad = RigConfig.load(rig_toml("software", extra="[sim.faults]\ndelay_frame = 1\n"))
    with pytest.raises(ConfigError, match="sim.faults.delay_s"):
        open_sim_rig(bad, scene=sphere_scene)


def test_faults_validation():
    with pytest.raises(ValueError):
        Faults(drop_frame=-1)
    with pytest.raises(ValueError):
        Faults(delay_frame=2)


@pytest.mark.slow
def test_simbench_reports_every_figure_with_the_load():
    """`slscan bench sim` runs on the default bench rig and reports each figure beside the
    load average (its values are timings: printed, never asserted)."""
    from slscan.commands.bench.simulator import format_table, run_simbench

    r = run_simbench(repeats=1)
    assert (r["width"], r["height"], r["sequence_patterns"]) == (1280, 1024, 12)
    assert len(r["load_before"]) == len(r["load_after"]) == 3
    assert all(r[k] > 0 for k in ("frame_new_pattern_s", "frame_seen_pattern_s", "peer_sensor_s", "mean_period_s"))
    assert "load average" in format_table(r) and "x peer" in format_table(r)
