"""Reconstruction: decoded projector coordinates to an organised point cloud.

Triangulation intersects each camera ray with the projector's surface of constant
coordinate. With projector distortion that surface is not a plane, so the intersection
is iterated: the undistorted projector coordinate depends weakly on the point's other
projector coordinate, read from a precomputed undistortion table.
The second mode is the reference-plane phase-to-height model of paper 000, Eq. 17.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, partial
from typing import Literal, overload

import cv2
import numpy as np

from scanner.decode import DecodeResult, in_bands
from scanner.errors import DecodeError
from scanner.geometry import Pinhole, RigModel, cubic_interpolate
from scanner.pointcloud import OrganisedCloud, from_planes, normals_into

_TABLE_OVERSAMPLE = 4  # table samples per projector pixel along the coded axis
_TABLE_ROWS = 257  # samples along the other normalised projector coordinate
_MAX_PASSES = 4
_CONVERGED = 1e-7  # change of the normalised projector coordinate (~2e-4 projector px)
_REMAP_COLS = 4096
_TABLE_COARSE_PX = 4.0  # projector pixels between exactly solved table columns
_NEWTON_TOLERANCE = 1e-13  # normalised coordinate


def _undistort_axis(c: np.ndarray, yn: np.ndarray, f: float, ctr: float, dist: np.ndarray, axis: int) -> np.ndarray:
    """(len(yn), len(c)) undistorted normalised coordinates x along the coded axis solving
    distort(x, y_n)[axis] = (c − ctr)/f by Newton steps from the ideal pinhole, until every
    step is below _NEWTON_TOLERANCE (Brown-Conrady, OpenCV's k1, k2, p1, p2, k3)."""
    cc, yy = np.meshgrid(c, yn)
    xd = (cc - ctr) / f
    x = xd.copy()
    k1, k2, p1, p2, k3 = dist
    if axis == 1:
        p1, p2 = p2, p1  # swapping x and y swaps the tangential terms
    for _ in range(50):
        r2 = x * x + yy * yy
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        fx = x * radial + 2 * p1 * x * yy + p2 * (r2 + 2 * x * x) - xd
        dradial = 2 * x * (k1 + r2 * (2 * k2 + 3 * k3 * r2))
        step = fx / (radial + x * dradial + 2 * p1 * yy + 6 * p2 * x)
        x -= step
        if not np.abs(step).max() > _NEWTON_TOLERANCE:
            break
    return x


class _UndistortTable:
    """x_n(c, y_n): the undistorted normalised projector coordinate along the coded axis, for
    a distorted pixel coordinate c and the normalised coordinate y_n across it."""

    def __init__(self, projector: Pinhole, axis: int) -> None:
        extent = projector.width if axis == 0 else projector.height
        K = projector.K
        # range of the cross coordinate, with margin for points outside the projector image
        corners = projector.normalized(np.array([[0, 0], [projector.width - 1, projector.height - 1]], float))
        lo, hi = corners[:, 1 - axis].min(), corners[:, 1 - axis].max()
        span = hi - lo
        self.y0, self.dy = lo - 0.25 * span, 1.5 * span / (_TABLE_ROWS - 1)
        c = np.arange(extent * _TABLE_OVERSAMPLE + 1) / _TABLE_OVERSAMPLE - 0.5
        yn = self.y0 + self.dy * np.arange(_TABLE_ROWS)
        if not projector.dist.any():
            self.table = np.repeat(((c - K[axis, 2]) / K[axis, axis])[None, :], _TABLE_ROWS, 0).astype(np.float32)
            return
        # solved exactly every _TABLE_COARSE_PX projector pixels, spread to every sample by
        # cubic interpolation (the undistortion is smooth at that scale)
        step = _TABLE_COARSE_PX
        coarse = np.arange(-0.5 - step, extent - 0.5 + 3 * step, step, dtype=np.float64)
        solved = _undistort_axis(coarse, yn, K[axis, axis], K[axis, 2], projector.dist, axis)
        self.table = cubic_interpolate(solved, c, coarse[0], step, axis=1).astype(np.float32)

    def __call__(self, coord: np.ndarray, y_n: np.ndarray) -> np.ndarray:
        """Table look-up (bilinear) for flat float32 arrays of equal length."""
        n = coord.size
        rows = -(-n // _REMAP_COLS)  # remap takes images below 32767 on a side
        mx = np.empty(rows * _REMAP_COLS, np.float32)
        my = np.zeros(rows * _REMAP_COLS, np.float32)
        np.multiply(coord + np.float32(0.5), np.float32(_TABLE_OVERSAMPLE), out=mx[:n])
        mx[n:] = 0
        np.multiply(y_n - np.float32(self.y0), np.float32(1.0 / self.dy), out=my[:n])
        out = cv2.remap(self.table, mx.reshape(rows, -1), my.reshape(rows, -1), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        return out.ravel()[:n]


@dataclass(eq=False)
class Triangulator:
    """Ray-surface triangulation for one rig; per-pixel constants are computed once."""

    rig: RigModel

    @cached_property
    def _rays(self) -> np.ndarray:
        return self.rig.camera.ray_grid

    def _constants(self, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float, float, float]]:
        """Per-pixel dot products of the camera ray with the projector axes (in the camera
        frame), and the matching scalars for the projector centre."""
        R, t = self.rig.cam_from_proj[:3, :3], self.rig.cam_from_proj[:3, 3]
        a_axis, a_other, a_z = R[:, axis], R[:, 1 - axis], R[:, 2]
        rays = self._rays
        dots = [(rays @ v.astype(np.float32)) for v in (a_axis, a_other, a_z)]
        return dots[0], dots[1], dots[2], (float(a_axis @ t), float(a_other @ t), float(a_z @ t), 0.0)

    def _tables(self, orientation: str) -> tuple:
        return self._vertical if orientation == "vertical" else self._horizontal

    def prepare(self, orientations: tuple[str, ...]) -> None:
        """Build the per-pixel constants and undistortion tables now rather than on first use."""
        for o in orientations:
            self._tables(o)
        _ = self._ray_planes

    @cached_property
    def _vertical(self) -> tuple:
        return self._constants(0) + (_UndistortTable(self.rig.projector, 0),)

    @cached_property
    def _horizontal(self) -> tuple:
        return self._constants(1) + (_UndistortTable(self.rig.projector, 1),)

    @overload
    def depth_scale(self, coord: np.ndarray, orientation: str, sensitivity: Literal[False] = False) -> np.ndarray: ...

    @overload
    def depth_scale(self, coord: np.ndarray, orientation: str,
                    sensitivity: Literal[True]) -> tuple[np.ndarray, np.ndarray]: ...

    @overload
    def depth_scale(self, coord: np.ndarray, orientation: str,
                    sensitivity: bool) -> np.ndarray | tuple[np.ndarray, np.ndarray]: ...

    def depth_scale(self, coord: np.ndarray, orientation: str,
                    sensitivity: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Ray parameter s (= depth z in mm, since rays have z = 1) for every pixel with a
        projector coordinate `coord` (NaN propagates); with `sensitivity`, also |dz/dcoord|
        (mm per projector pixel), which says how well this orientation constrains depth.
        Each pass of the iteration runs in bands of rows on every core."""
        alpha, gamma, beta, (a0, c1, b0, _), table = self._tables(orientation)
        if coord.shape != alpha.shape:
            raise DecodeError(f"{orientation} coordinate map is {coord.shape[::-1]} (w, h) but the rig camera is "
                              f"{alpha.shape[::-1]}")
        K = self.rig.projector.K
        axis = 0 if orientation == "vertical" else 1
        shape, width = coord.shape, coord.shape[1]
        c, al, ga, be = coord.ravel(), alpha.ravel(), gamma.ravel(), beta.ravel()
        a0, c1, b0 = np.float32(a0), np.float32(c1), np.float32(b0)
        x_n = np.empty_like(c)

        def refine(x: np.ndarray, sl: slice) -> np.ndarray:
            # the point lies on the surface X_p = x_n·Z_p of the projector frame, so along the
            # camera ray s·(α − x_n·β) = a0 − x_n·b0; its cross coordinate is y_n = Y_p / Z_p
            s = np.subtract(a0, x * b0)
            s /= al[sl] - x * be[sl]
            y_n = s * ga[sl]
            y_n -= c1
            y_n /= s * be[sl] - b0
            return table(c[sl], y_n)

        def flat(rows: slice) -> slice:
            return slice(rows.start * width, rows.stop * width)

        def one_pass(rows: slice, first: bool) -> None:
            sl = flat(rows)
            x = (c[sl] - np.float32(K[axis, 2])) * np.float32(1.0 / K[axis, axis]) if first else x_n[sl]
            x_n[sl] = refine(x, sl)  # the first pass starts from the distortion-free coordinate

        probe = slice(0, None, 97)  # convergence is judged on a dense subsample, not a full pass
        for passes in range(_MAX_PASSES):
            in_bands(shape[0], partial(one_pass, first=passes == 0))
            if not np.nanmax(np.abs(refine(x_n[probe], probe) - x_n[probe]), initial=0.0) >= _CONVERGED:
                break
        z = np.empty(c.size, np.float32)
        dz = np.empty(c.size, np.float32) if sensitivity else None

        def finish(rows: slice) -> None:
            sl = flat(rows)
            denom = al[sl] - x_n[sl] * be[sl]
            zr = np.subtract(a0, x_n[sl] * b0)
            zr /= denom
            zr[~(zr > 0)] = np.nan  # invalid coordinate, or behind the camera: no surface
            z[sl] = zr
            if dz is not None:
                d = np.abs((be[sl] * a0 - al[sl] * b0) / (denom * denom)) / np.float32(K[axis, axis])
                d[np.isnan(zr)] = np.nan
                dz[sl] = d

        in_bands(shape[0], finish)
        return (z.reshape(shape), dz.reshape(shape)) if dz is not None else z.reshape(shape)

    @cached_property
    def _ray_planes(self) -> tuple[np.ndarray, np.ndarray]:
        return np.ascontiguousarray(self._rays[..., 0]), np.ascontiguousarray(self._rays[..., 1])

    def cloud(self, z: np.ndarray, colors: np.ndarray, with_normals: bool = True) -> OrganisedCloud:
        """The organised cloud of depths z (H, W) along this rig's camera rays."""
        return cloud_from_depth(z, *self._ray_planes, colors, with_normals)


def to_texture8(texture: np.ndarray, bit_depth: int) -> np.ndarray:
    """Grey 8-bit colours from a texture in DN."""
    scaled = texture * (255.0 / (2 ** bit_depth - 1))
    return np.clip(scaled, 0, 255, out=scaled).astype(np.uint8)


def triangulate(decoded: DecodeResult, triangulator: Triangulator, with_normals: bool = True) -> OrganisedCloud:
    """Organised cloud by triangulation; with both fringe orientations the two depths are
    averaged, weighted by their expected precision."""
    shape = decoded.valid.shape
    if shape != (triangulator.rig.camera.height, triangulator.rig.camera.width):
        raise DecodeError(f"decoded maps are {shape[1]} x {shape[0]} but the rig camera is "
                          f"{triangulator.rig.camera.width} x {triangulator.rig.camera.height}")
    if len(decoded.maps) == 1:
        (orientation, m), = decoded.maps.items()
        z = triangulator.depth_scale(m.coordinate, orientation)
    else:
        # inverse-variance average: phase precision times the geometric depth sensitivity
        depths, weights = [], []
        for orientation, m in decoded.maps.items():
            zi, dz = triangulator.depth_scale(np.where(decoded.valid, m.coordinate, np.nan), orientation, True)
            depths.append(zi)
            weights.append(m.phase_weight * np.float32(m.period_px ** -2) / (dz * dz))
        z = (depths[0] * weights[0] + depths[1] * weights[1]) / (weights[0] + weights[1])
    return triangulator.cloud(z, to_texture8(decoded.texture, decoded.bit_depth), with_normals)


def phase_to_height_cloud(decoded: DecodeResult, rig: RigModel, orientation: str = "vertical") -> OrganisedCloud:
    """Organised cloud from the reference-plane model (paper 000, Eq. 17, per pixel when the
    calibration has the per-pixel maps): the height above the reference plane per pixel,
    placed along each camera ray. Pixels the model was not calibrated for have no point."""
    model = rig.phase_to_height
    if model is None:
        source = (f"the calibration file {rig.calibration}" if rig.calibration
                  else "the rig's nominal geometry (no calibration file)")
        raise DecodeError(f"no phase-to-height model in {source}: calibrate the rig with plate heights "
                          f"([calibrate] plate_heights_mm) and name that calibration under [rig] calibration, or "
                          f"reconstruct by triangulation")
    if orientation not in decoded.maps:
        raise DecodeError(f"phase-to-height needs {orientation} fringes; the scan has {list(decoded.maps)}")
    phase = decoded.maps[orientation].phase
    if model.reference_phase.shape != phase.shape:
        raise DecodeError(f"reference phase map {model.maps_file or '(in memory)'} is "
                          f"{model.reference_phase.shape[::-1]} (w, h) but the scan is {phase.shape[::-1]}")
    rays = rig.camera.ray_grid
    z = model.depth(np.where(decoded.valid, phase, np.nan), rays)
    return cloud_from_depth(z, np.ascontiguousarray(rays[..., 0]), np.ascontiguousarray(rays[..., 1]),
                            to_texture8(decoded.texture, decoded.bit_depth))


def cloud_from_depth(z: np.ndarray, ray_x: np.ndarray, ray_y: np.ndarray, colors: np.ndarray,
                     with_normals: bool = True) -> OrganisedCloud:
    """Organised cloud from depth z (H, W, mm) along rays (x/z, y/z, 1) given as planes,
    built in bands of rows on every core (normals from each band with one row either side)."""
    h = z.shape[0]
    points = np.empty((*z.shape, 3), np.float32)
    normals = np.empty((*z.shape, 3), np.float32)

    def band(rows: slice) -> None:
        top, bottom = max(rows.start - 1, 0), min(rows.stop + 1, h)
        x, y = ray_x[top:bottom] * z[top:bottom], ray_y[top:bottom] * z[top:bottom]
        own = slice(rows.start - top, rows.stop - top)
        from_planes(x[own], y[own], z[rows], out=points[rows])
        if not with_normals:
            normals[rows] = np.nan
            return
        normals_into(x, y, z[top:bottom], normals[top + 1:bottom - 1])  # the rows with a neighbour either side
        if rows.start == 0:
            normals[0] = np.nan  # the image border has no normal
        if rows.stop == h:
            normals[h - 1] = np.nan

    in_bands(h, band)
    return OrganisedCloud(points, colors, normals)
