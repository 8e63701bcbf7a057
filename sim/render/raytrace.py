"""First hits of rays against a scene, in float64.

One ray per camera pixel centre, through the lens distortion (the camera's undistorted
normalised coordinates, i.e. `Pinhole.ray_grid`, computed here in float64), cast with
Open3D's `RaycastingScene` for meshes and in closed form for spheres, planes and boxes;
every mesh hit is re-intersected with its triangle in float64, so points are exact to
~1e-9 mm of the mesh, and primitives are exact surfaces.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from scanner.geometry import Pinhole
from sim.scene import Scene, SceneObject

_RAY_CACHE: OrderedDict[tuple, np.ndarray] = OrderedDict()
_RAY_LOCK = threading.Lock()


def camera_rays(camera: Pinhole) -> np.ndarray:
    """(H, W, 3) float64 ray directions (x/z, y/z, 1) through every pixel centre, lens
    distortion included: `Pinhole.ray_grid` in double precision. Cached per intrinsics
    (read-only array)."""
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes())
    with _RAY_LOCK:
        if key in _RAY_CACHE:
            _RAY_CACHE.move_to_end(key)
            return _RAY_CACHE[key]
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
    xy = camera.normalized(np.stack([u.ravel(), v.ravel()], axis=1))
    rays = np.empty((camera.height, camera.width, 3))
    rays[..., :2] = xy.reshape(camera.height, camera.width, 2)
    rays[..., 2] = 1.0
    rays.setflags(write=False)
    with _RAY_LOCK:
        _RAY_CACHE[key] = rays
        while len(_RAY_CACHE) > 4:
            _RAY_CACHE.popitem(last=False)
    return rays


class Tracer:
    """First hits of rays against a scene placed in the camera frame (float64 results)."""

    def __init__(self, scene: Scene, cam_from_world: np.ndarray) -> None:
        self.analytic: list[tuple[int, str, np.ndarray, SceneObject]] = []
        self.rc = None
        meshes = [(oid, obj) for oid, obj in sorted(scene.by_id().items()) if obj.kind == "mesh"]
        for oid, obj in sorted(scene.by_id().items()):
            if obj.kind != "mesh":
                self.analytic.append((oid, obj.kind, cam_from_world @ obj.pose, obj))
        if meshes:
            import open3d as o3d  # only for meshes: an analytic scene's scan skips its import (~0.4 s CPU)

            self.rc = o3d.t.geometry.RaycastingScene()
            verts, tris, tri_offset, v_offset = [], [], [], 0
            geom_to_oid: list[int] = []
            n_tris = 0
            cpu = o3d.core.Device("CPU:0")
            for oid, obj in meshes:
                assert obj.vertices is not None and obj.triangles is not None  # a mesh object has both
                T = cam_from_world @ obj.pose
                v = obj.vertices @ T[:3, :3].T + T[:3, 3]
                t = obj.triangles.astype(np.int64)
                gid = self.rc.add_triangles(o3d.core.Tensor(v.astype(np.float32), o3d.core.float32, cpu),
                                            o3d.core.Tensor(t.astype(np.uint32), o3d.core.uint32, cpu))
                if gid != len(geom_to_oid):
                    raise RuntimeError("unexpected Open3D geometry id order")
                geom_to_oid.append(oid)
                tri_offset.append(n_tris)
                verts.append(v)
                tris.append(t + v_offset)
                v_offset += len(v)
                n_tris += len(t)
            self.vertices = np.concatenate(verts)  # float64, camera frame
            self.triangles = np.concatenate(tris)  # global vertex indices
            self.tri_offset_arr = np.array(tri_offset, dtype=np.int64)
            self.geom_to_oid_arr = np.array(geom_to_oid, dtype=np.int32)

    def first_hit(self, origin: np.ndarray, dirs: np.ndarray, t_min: float = 1e-9
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For rays origin + t·dirs (dirs (N, 3), not necessarily unit; `origin` (3,) shared or
        (N, 3) per ray): t (N,) float64 (inf on a miss), object id (N,) int32 (0 on a miss),
        unit normal (N, 3) (unoriented)."""
        n = len(dirs)
        t_best = np.full(n, np.inf)
        oid = np.zeros(n, dtype=np.int32)
        normal = np.zeros((n, 3))
        o = np.asarray(origin, dtype=np.float64)
        if self.rc is not None and n:
            self._cast_meshes(o, dirs, t_min, t_best, oid, normal)
        for obj_id, kind, T, obj in self.analytic:
            if kind == "sphere":
                t, nrm = _hit_sphere(o, dirs, T[:3, 3], float(obj.radius_mm), t_min)  # type: ignore[arg-type]  # kind: set
            elif kind == "plane":
                t, nrm = _hit_plane(o, dirs, T, obj.size_mm, t_min)  # type: ignore[arg-type]  # kind: size set
            else:
                t, nrm = _hit_box(o, dirs, T, obj.size_mm, t_min)  # type: ignore[arg-type]  # kind: size set
            better = t < t_best
            t_best[better] = t[better]
            oid[better] = obj_id
            normal[better] = nrm[better]
        return t_best, oid, normal

    def _cast_meshes(self, o: np.ndarray, dirs: np.ndarray, t_min: float, t_best: np.ndarray,
                     oid: np.ndarray, normal: np.ndarray) -> None:
        import open3d as o3d

        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3] = o
        rays[:, 3:] = dirs
        assert self.rc is not None  # called only for a scene with meshes
        ans = self.rc.cast_rays(o3d.core.Tensor(rays, o3d.core.float32, o3d.core.Device("CPU:0")))
        t32 = ans["t_hit"].numpy()
        hit = np.flatnonzero(np.isfinite(t32))
        if not hit.size:
            return
        gid = ans["geometry_ids"].numpy()[hit].astype(np.int64)
        prim = ans["primitive_ids"].numpy()[hit].astype(np.int64)
        # `take` copies the same rows as fancy indexing in about half the time
        tri = self.triangles.take(self.tri_offset_arr[gid] + prim, axis=0)
        v0, v1, v2 = self.vertices.take(tri, axis=0).transpose(1, 0, 2)
        nrm = np.cross(v1 - v0, v2 - v0)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        d = dirs[hit]
        den = np.einsum("ij,ij->i", nrm, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ij,ij->i", nrm, v0 - (o if o.ndim == 1 else o[hit])) / den
        # keep Open3D's float32 answer where the float64 re-intersection is ill-conditioned
        bad = ~np.isfinite(t) | (np.abs(t - t32[hit]) > 1e-3 * np.maximum(1.0, np.abs(t32[hit])))
        t[bad] = t32[hit][bad]
        keep = t > t_min
        hit, t, nrm, gid = hit[keep], t[keep], nrm[keep], gid[keep]
        t_best[hit] = t
        oid[hit] = self.geom_to_oid_arr[gid]
        normal[hit] = nrm


def _pick_root(t1: np.ndarray, t2: np.ndarray, t_min: float) -> np.ndarray:
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    return np.where(near > t_min, near, np.where(far > t_min, far, np.inf))


def _hit_sphere(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float, t_min: float) -> tuple[np.ndarray, np.ndarray]:
    oc = o - c
    a = np.einsum("ij,ij->i", d, d)
    if oc.ndim == 1:
        b = d @ oc  # half of the usual b
        cq = float(oc @ oc - r * r)
    else:  # one origin per ray
        b = np.einsum("ij,ij->i", d, oc)
        cq = np.einsum("ij,ij->i", oc, oc) - r * r
    disc = b * b - a * cq
    ok = disc >= 0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    q = -(b + np.copysign(sq, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _pick_root(q / a, cq / q, t_min)
    t = np.where(ok & np.isfinite(t), t, np.inf)
    p = o + d * np.where(np.isfinite(t), t, 0.0)[:, None]
    return t, (p - c) / r


def _hit_plane(o: np.ndarray, d: np.ndarray, T: np.ndarray, size: tuple[float, float], t_min: float
               ) -> tuple[np.ndarray, np.ndarray]:
    R, p = T[:3, :3], T[:3, 3]
    ol = R.T @ (o - p) if o.ndim == 1 else (o - p) @ R
    dl = d @ R
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -ol[..., 2] / dl[:, 2]
    x = ol[..., 0] + t * dl[:, 0]
    y = ol[..., 1] + t * dl[:, 1]
    ok = np.isfinite(t) & (t > t_min) & (np.abs(x) <= size[0] / 2) & (np.abs(y) <= size[1] / 2)
    t = np.where(ok, t, np.inf)
    return t, np.broadcast_to(R[:, 2], d.shape)


def _hit_box(o: np.ndarray, d: np.ndarray, T: np.ndarray, size: tuple[float, float, float], t_min: float
             ) -> tuple[np.ndarray, np.ndarray]:
    R, p = T[:3, :3], T[:3, 3]
    ol = R.T @ (o - p) if o.ndim == 1 else (o - p) @ R
    dl = d @ R
    h = np.asarray(size, float) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dl
        t1 = (-h - ol) * inv
        t2 = (h - ol) * inv
    # a ray parallel to a slab: inside it -> (-inf, inf), outside -> empty
    par = dl == 0
    inside = np.abs(ol) <= h
    lo = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    hi = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    t_near = lo.max(axis=1)
    t_far = hi.min(axis=1)
    ok = t_far >= np.maximum(t_near, t_min)
    t = np.where(ok, np.where(t_near > t_min, t_near, t_far), np.inf)
    # the face hit: the entering slab for t_near, the leaving slab for t_far
    axis = np.where(t_near > t_min, lo.argmax(axis=1), hi.argmin(axis=1))
    nl = np.zeros_like(dl)
    nl[np.arange(len(d)), axis] = 1.0
    return t, nl @ R.T
