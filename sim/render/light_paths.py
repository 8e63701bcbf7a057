"""The ways projector light reaches camera pixels: the direct path, and optionally one
mirror bounce between surfaces (interreflection).

A path is a set of camera pixels, the projector pixel (u, v) whose light each of them gets
along it, and its weight (the renderer's unit: an albedo-1 Lambertian surface under full
white at normal incidence). The renderer samples the projector output at every path's
(u, v) and sums weight x output per pixel, so a pixel reached by two paths sees the sum of
two fringe signals of different phase: the phase error interreflection makes on shiny
concave corners. Ground truth (`ground_truth`) stays the direct path's.

Direct: every lit pixel, weight `reflectance.surface_weight` (albedo·cos plus the specular
lobe toward the camera).

One bounce (`Scene.interreflection`): at every pixel seeing a specular surface (F0 > 0), the
camera ray is mirrored about the normal and cast again; where it lands on a surface point
lit by the projector, that point's radiance toward the first surface (its own
`surface_weight` with the mirrored ray as the viewer, texture not applied) reaches the
camera scaled by the first surface's Fresnel reflectance at the mirror angle. Limits: one
ray per pixel (the lobe's spread around the mirror direction is not sampled: a sharp
reflected image), only specular first surfaces bounce (diffuse-diffuse transport is left
out), no ambient in the bounce.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanner.native_threads import native_threads
from sim.render.ground_truth import GroundTruth, projector_view
from sim.render.raytrace import Tracer
from sim.render.reflectance import material_maps, schlick_fresnel, surface_weight
from sim.scene import Scene

BOUNCE_OFFSET_MM = 1e-4  # a mirrored ray starts this far off its surface, so it does not hit it again


@dataclass(frozen=True, eq=False)
class LightPath:
    """Projector light reaching camera pixels `index` (flat, int64) from projector pixels
    `uv` (N, 2), scaled by `weight` (N,) float32."""

    name: str
    index: np.ndarray
    uv: np.ndarray
    weight: np.ndarray


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def direct_path(gt: GroundTruth, scene: Scene) -> LightPath:
    """Every lit pixel's light from the projector pixel the ground truth names."""
    lit = gt.lit.ravel()
    index = np.flatnonzero(lit)
    X = gt.points.reshape(-1, 3)[index]
    normal = gt.normal.reshape(-1, 3)[index]
    _, f0, rough = material_maps(scene, gt.object_id.ravel()[index])
    Cp = gt.model.cam_from_proj[:3, 3]
    weight = surface_weight(gt.albedo.ravel()[index], gt.cos_incidence.ravel()[index], normal, to_light=_unit(Cp - X),
                            to_view=_unit(-X), f0=f0, roughness=rough)
    return LightPath("direct", index, gt.proj_uv.reshape(-1, 2)[index], weight.astype(np.float32))


def bounce_path(gt: GroundTruth, scene: Scene) -> LightPath:
    """Light reaching specular pixels through one mirror bounce (see the module docstring)."""
    model = gt.model
    _, f0_all, _ = material_maps(scene, gt.object_id.ravel())
    index = np.flatnonzero(gt.hit.ravel() & (f0_all > 0))
    X1 = gt.points.reshape(-1, 3)[index]
    n1 = gt.normal.reshape(-1, 3)[index]
    d = _unit(X1)
    cos1 = -np.einsum("ij,ij->i", d, n1)
    r = d + 2.0 * cos1[:, None] * n1  # the camera ray mirrored about the normal
    tracer = Tracer(scene, np.linalg.inv(model.world_from_cam))
    t, oid, n2 = tracer.first_hit(X1 + BOUNCE_OFFSET_MM * n1, r, t_min=1e-9)
    hit = np.isfinite(t)
    index, X1, n1, r, cos1, t, oid, n2 = (a[hit] for a in (index, X1, n1, r, cos1, t, oid, n2))
    X2 = X1 + BOUNCE_OFFSET_MM * n1 + r * t[:, None]
    n2 = n2 * np.where(np.einsum("ij,ij->i", n2, r) > 0, -1.0, 1.0)[:, None]  # toward the first surface
    uv, lit, _, cos_inc = projector_view(model, tracer, X2, n2)
    index, X2, n2, r, cos1, oid, uv, cos_inc = (a[lit] for a in (index, X2, n2, r, cos1, oid, uv, cos_inc))
    f0_1 = f0_all[index]
    albedo2, f0_2, rough2 = material_maps(scene, oid)
    Cp = model.cam_from_proj[:3, 3]
    radiance = surface_weight(albedo2, cos_inc, n2, to_light=_unit(Cp - X2), to_view=-r, f0=f0_2, roughness=rough2)
    weight = schlick_fresnel(cos1, f0_1) * radiance
    keep = weight > 0
    return LightPath("bounce", index[keep], uv[keep], weight[keep].astype(np.float32))


def light_paths(gt: GroundTruth, scene: Scene) -> list[LightPath]:
    """The direct path, and the bounce path when the scene asks for interreflection. BLAS
    on one thread inside, as for `compute_ground_truth` (the bounce casts rays again)."""
    with native_threads(1):
        paths = [direct_path(gt, scene)]
        if scene.interreflection:
            paths.append(bounce_path(gt, scene))
    return paths
