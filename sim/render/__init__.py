"""Image formation for the simulated rig, with exact ground truth; one module per job:

  raytrace      first hits of the camera's pixel rays (and any others) on the scene, float64
  projection    OpenCV's distortion model vectorised; the projector image's field of view
  ground_truth  per pixel: point, normal, object, projector pixel, shadows, albedo, texture
  reflectance   Lambertian plus a Cook-Torrance GGX specular lobe (metal), per scene object
  light_paths   the direct path and one optional mirror bounce (interreflection)
  bspline       cubic B-spline sampling of projector images at fixed points
  sensor        electrons to digital numbers: shot and read noise, quantisation, clipping
  renderer      camera images of the scene under projector patterns, cached per pattern

Limits: one ray per pixel centre (no area integration at silhouettes besides the camera
blur), no inverse-square fall-off, interreflection only as one mirror bounce off specular
surfaces, projector light only from its centre (no aperture, so a glint is as sharp as the
lobe makes it).
"""

from sim.render.bspline import BSplineSampler
from sim.render.ground_truth import GroundTruth, compute_ground_truth, texture_albedo
from sim.render.projection import project_points, projector_field
from sim.render.raytrace import camera_rays
from sim.render.renderer import Renderer
from sim.render.sensor import SUPPORTED_BIT_DEPTHS, SensorModel

__all__ = ["SUPPORTED_BIT_DEPTHS", "BSplineSampler", "GroundTruth", "Renderer", "SensorModel", "camera_rays",
           "compute_ground_truth", "project_points", "projector_field", "texture_albedo"]
