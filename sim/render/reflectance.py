"""Surface reflectance: a Lambertian term plus a Cook-Torrance specular lobe (GGX).

The renderer's unit of light is an albedo-1 Lambertian surface under full projector white at
normal incidence, so a surface point returns, toward the camera,

    weight = π · BRDF(l, v) · cos θ_l
           = albedo · cos θ_l                          (Lambertian: BRDF = albedo / π)
           + π · D(h) · F(v·h) · G(l, v) / (4 cos θ_v)  (Cook-Torrance specular lobe)

with l the direction to the projector centre, v the direction to the camera, h their half
vector; D the GGX (Trowbridge-Reitz) normal distribution with α = roughness², F Schlick's
Fresnel approximation from the normal-incidence reflectance `specular` (F0: polished
aluminium ~0.91), G Smith's separable masking-shadowing for GGX. A polished surface's glint
(h along the normal) is tens of times brighter than white paper, so it saturates the camera
exactly where the mirror geometry puts the projector's reflection; elsewhere the same surface
is nearly black.

A matte surface (`specular` = 0) gets exactly the old Lambertian weight, bit for bit.
"""

from __future__ import annotations

import numpy as np

from sim.scene import MIN_ROUGHNESS, REFERENCE_PLANE_ID, Scene


def material_maps(scene: Scene, object_id: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(albedo without texture, specular F0, roughness) per entry of `object_id` (any shape),
    from each object's material; 0 albedo and specular where nothing is hit."""
    n = max([REFERENCE_PLANE_ID, *scene.by_id()]) + 1
    albedo, f0, rough = np.zeros(n), np.zeros(n), np.ones(n)
    for i, o in scene.by_id().items():
        albedo[i], f0[i], rough[i] = o.albedo, o.specular, o.roughness
    return albedo[object_id], f0[object_id], rough[object_id]


def ggx_distribution(cos_h: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """GGX normal distribution D (sr⁻¹) for the cosine between half vector and normal."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    den = c2 * (a2 - 1.0) + 1.0
    return a2 / (np.pi * den * den)


def smith_g1(cos_t: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Smith's masking term for GGX, one direction at cosine `cos_t` to the normal."""
    c2 = np.maximum(cos_t * cos_t, 1e-12)
    return 2.0 / (1.0 + np.sqrt(1.0 + alpha * alpha * (1.0 - c2) / c2))


def schlick_fresnel(cos_d: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """Schlick's Fresnel reflectance at cosine `cos_d` for normal-incidence reflectance `f0`."""
    return f0 + (1.0 - f0) * (1.0 - np.clip(cos_d, 0.0, 1.0)) ** 5


def specular_weight(normal: np.ndarray, to_light: np.ndarray, to_view: np.ndarray, f0: np.ndarray,
                    roughness: np.ndarray) -> np.ndarray:
    """The specular part of the weight (N,): π·D·F·G / (4 cos θ_v); unit vectors (N, 3),
    `normal` on the viewer's side; 0 where light or viewer is behind the surface or `f0` = 0."""
    cos_l = np.einsum("ij,ij->i", normal, to_light)
    cos_v = np.einsum("ij,ij->i", normal, to_view)
    h = to_light + to_view
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    alpha = np.maximum(roughness, MIN_ROUGHNESS) ** 2
    d = ggx_distribution(np.einsum("ij,ij->i", normal, h), alpha)
    f = schlick_fresnel(np.einsum("ij,ij->i", to_view, h), f0)
    g = smith_g1(cos_l, alpha) * smith_g1(cos_v, alpha)
    ok = (cos_l > 0) & (cos_v > 0) & (f0 > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.pi * d * f * g / (4.0 * cos_v)
    return np.where(ok, w, 0.0)


def surface_weight(albedo: np.ndarray, cos_incidence: np.ndarray, normal: np.ndarray, *, to_light: np.ndarray,
                   to_view: np.ndarray, f0: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """The full weight (N,) float64: albedo·cos θ_l plus the specular lobe where `f0` > 0
    (matte points keep the Lambertian weight exactly)."""
    weight = albedo * cos_incidence
    shiny = np.flatnonzero(f0 > 0)
    if shiny.size:
        weight = weight.copy()
        weight[shiny] += specular_weight(normal[shiny], to_light[shiny], to_view[shiny], f0[shiny], roughness[shiny])
    return weight
