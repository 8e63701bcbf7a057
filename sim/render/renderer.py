"""Camera images of a scene lit by projector patterns, for one rig model.

Per pattern (projector command image, uint8 (Hp, Wp)):
  projector output = Gaussian defocus blur of (command / 255) ** gamma, in projector pixels
      (sigma along rows scaled by fy / fx, so the blur is round on a diamond-array DMD whose
      rows are closer than its columns), sampled at (u, v) with a cubic B-spline (`bspline`);
  electrons = exposure * flux * (ambient + Σ_paths weight * output(u, v)), then the camera's
      Gaussian defocus blur (camera pixels); the direct path's weight is albedo * cos(incidence)
      on a matte surface, plus a specular lobe on a shiny one (`reflectance`), and a scene
      with interreflection adds one mirror bounce (`light_paths`);
  image = the sensor's digitisation of the electrons (`sensor`).
Background pixels (nothing hit) and unlit surfaces get the ambient term only; ambient is
taken as uniform light, not multiplied by albedo (the formula above, as specified).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import cv2
import numpy as np

from scanner.geometry import RigModel
from sim.render.bspline import BSplineSampler
from sim.render.ground_truth import compute_ground_truth
from sim.render.light_paths import light_paths
from sim.render.sensor import SensorModel, check_bits
from sim.scene import Scene

# spline coefficients of the projector's output per (pattern, gamma, blur): shared by every
# renderer, so a scene change (a new Renderer) does not redo the patterns it has seen
_OUTPUT_CACHE: OrderedDict[tuple, np.ndarray] = OrderedDict()
_OUTPUT_LOCK = threading.Lock()
OUTPUT_CACHE_ENTRIES = 32  # ~4 MB each for the bench projector


class Renderer:
    """Renders camera images of a scene lit by projector patterns, for one rig model.

    Geometry is computed once (`ground_truth`); each distinct pattern's noise-free camera
    irradiance is cached (content-addressed, up to `cache_entries`), so repeated frames
    only cost the noise, and the projector output's spline coefficients are cached across
    renderers (OUTPUT_CACHE_ENTRIES), so the same patterns on a new scene cost only their
    sampling. Thread-safe."""

    def __init__(self, model: RigModel, scene: Scene, sensor: SensorModel,
                 projector_blur_sigma_px: float = 0.0, cache_entries: int = 64) -> None:
        if projector_blur_sigma_px < 0:
            raise ValueError("projector blur sigma must be >= 0")
        self.model = model
        self.scene = scene
        self.sensor = sensor
        self.projector_blur_sigma_px = float(projector_blur_sigma_px)
        self.ground_truth = compute_ground_truth(model, scene, sensor.blur_sigma_px)
        self.paths = light_paths(self.ground_truth, scene)
        self._lit_index = self.paths[0].index
        self._sampler = BSplineSampler(self.paths[0].uv, self.projector_shape)
        self._samplers = [BSplineSampler(p.uv, self.projector_shape) for p in self.paths[1:]]
        self._lut = ((np.arange(256) / 255.0) ** model.projector_gamma).astype(np.float32)
        self._cache: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self._cache_entries = int(cache_entries)
        self._lock = threading.Lock()

    @property
    def shape(self) -> tuple[int, int]:
        return (self.model.camera.height, self.model.camera.width)

    @property
    def projector_shape(self) -> tuple[int, int]:
        return (self.model.projector.height, self.model.projector.width)

    def projector_output(self, pattern: np.ndarray) -> np.ndarray:
        """Displayed light (Hp, Wp) float32, 0..1 of full white: gamma, then defocus blur."""
        pattern = self._check_pattern(pattern)
        img = self._lut[pattern]
        s = self.projector_blur_sigma_px
        if s > 0:
            K = self.model.projector.K
            img = cv2.GaussianBlur(img, (0, 0), sigmaX=s, sigmaY=s * K[1, 1] / K[0, 0],
                                   borderType=cv2.BORDER_REFLECT_101)
        return img

    def sample_projector(self, image: np.ndarray) -> np.ndarray:
        """A projector-space image (Hp, Wp) sampled at every lit camera pixel's (u, v):
        (H, W) float32, 0 where not lit."""
        out = np.zeros(self.shape[0] * self.shape[1], dtype=np.float32)
        if self._lit_index.size:
            out[self._lit_index] = self._sampler(image)
        return out.reshape(self.shape)

    def irradiance(self, pattern: np.ndarray | None) -> np.ndarray:
        """Projector light reaching the camera (H, W) float32, relative to an albedo-1
        surface under full white at normal incidence: albedo * cos * output(u, v), after the
        camera blur; no ambient. None = projector dark (zeros). Cached per pattern."""
        if pattern is None:
            return np.zeros(self.shape, dtype=np.float32)
        pattern = self._check_pattern(pattern)
        key = hashlib.blake2b(pattern.tobytes(), digest_size=16).digest()
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        out: np.ndarray = np.zeros(self.shape[0] * self.shape[1], dtype=np.float32)
        coeff = self._output_coefficients(pattern, key)
        if self._lit_index.size:
            out[self._lit_index] = self._sampler.sample(coeff) * self.paths[0].weight
        for path, sampler in zip(self.paths[1:], self._samplers):
            if path.index.size:
                out[path.index] += sampler.sample(coeff) * path.weight
        out = out.reshape(self.shape)
        if self.sensor.blur_sigma_px > 0:
            out = cv2.GaussianBlur(out, (0, 0), self.sensor.blur_sigma_px, borderType=cv2.BORDER_REFLECT_101)
        out.setflags(write=False)
        with self._lock:
            self._cache[key] = out
            while len(self._cache) > self._cache_entries:
                self._cache.popitem(last=False)
        return out

    def _output_coefficients(self, pattern: np.ndarray, digest: bytes) -> np.ndarray:
        K = self.model.projector.K
        key = (digest, self.projector_shape, self.model.projector_gamma, self.projector_blur_sigma_px,
               K[1, 1] / K[0, 0])
        with _OUTPUT_LOCK:
            if key in _OUTPUT_CACHE:
                _OUTPUT_CACHE.move_to_end(key)
                return _OUTPUT_CACHE[key]
        coeff = BSplineSampler.coefficients(self.projector_output(pattern))
        coeff.setflags(write=False)
        with _OUTPUT_LOCK:
            _OUTPUT_CACHE[key] = coeff
            while len(_OUTPUT_CACHE) > OUTPUT_CACHE_ENTRIES:
                _OUTPUT_CACHE.popitem(last=False)
        return coeff

    def mean_electrons(self, pattern: np.ndarray | None, exposure_s: float) -> np.ndarray:
        """Noise-free signal (H, W) float32 in electrons (before saturation)."""
        out = self.irradiance(pattern) + np.float32(self.sensor.ambient)
        out *= np.float32(exposure_s * self.sensor.flux_e_per_s)  # in place: no second full-frame temporary
        return out

    def mean_dn(self, pattern: np.ndarray | None, exposure_s: float, bit_depth: int) -> np.ndarray:
        """Noise-free signal (H, W) float64 in DN, neither quantised nor clipped."""
        return self.mean_electrons(pattern, exposure_s).astype(np.float64) / self.sensor.gain_e_per_dn(bit_depth)

    def render(self, pattern: np.ndarray | None, exposure_s: float, bit_depth: int,
               rng: np.random.Generator | int | None = None) -> np.ndarray:
        """One noisy camera image (H, W): uint8 for 8 bits, else uint16. `rng` (a Generator
        or a seed) makes it deterministic."""
        check_bits(bit_depth)
        if not exposure_s > 0:
            raise ValueError("exposure must be > 0")
        if not isinstance(rng, np.random.Generator):
            rng = np.random.default_rng(rng)
        return self.sensor.expose(self.mean_electrons(pattern, exposure_s), bit_depth, rng)

    def _check_pattern(self, pattern: np.ndarray) -> np.ndarray:
        pattern = np.asarray(pattern)
        if pattern.shape != self.projector_shape or pattern.dtype != np.uint8:
            raise ValueError(f"pattern must be uint8 {self.projector_shape}, got {pattern.dtype} {pattern.shape}")
        return pattern
