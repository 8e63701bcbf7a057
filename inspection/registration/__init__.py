"""Part-in-whole registration of a single-view scan to a whole CAD model (or a cloud).

The method of paper 000 (Kong et al. 2023, section 3), with the coarse and fine steps of
paper 001 (Deng et al. 2023, section 3.2); one module per stage:

1. `target`, `clouds`: both clouds on one voxel grid (`TargetSettings.voxel_fraction`
   of the model's diagonal), normals averaged per voxel; the model prepared once.
2. `spheres`: multi-scale random sphere cover sets (RSCS, Eq. 19) and their FPFH and
   SHOT descriptors. The model is covered densely (centres every r/4), so every scan
   sphere has a model sphere at nearly the same place.
3. `matching`: correspondences by descriptor distinctiveness, merged across
   descriptors where they agree (Eq. 11).
4. `sac_ia`, `ndt`: coarse poses by SAC-IA (Kabsch on triplets, Eq. 12-15, scored by the
   Huber penalty of paper 001 Eq. 22) or RANSAC, or by NDT (paper 001 Eq. 23-26).
5. `hypotheses`, `verification`: the best distinct coarse poses, their half turns about
   the scan's principal axes and, for mostly planar scans, poses from the dominant
   plane, each refined by ICP and judged by fitness (scan points within the inlier
   distance of the model with agreeing normals) minus the fraction of scan points the
   posed model would hide from the sensor. A symmetric or prismatic part that fits
   several poses equally well is reported as ambiguous.
6. `point_to_plane`, `fine`, `gauss_newton`, `face_bias`: point-to-plane ICP with
   normal-angle rejection (paper 001 Eq. 27-29) on the dense scan, then, for STEP
   models, Gauss-Newton on the exact point-to-face distances with faces off as a whole
   left out.

`driver.register` strings the stages together; every tuning figure is a field of
`RegistrationSettings` or `TargetSettings` (`settings`), with its unit and reason.
A pose is reported only when it explains the scan: otherwise `RegistrationFailed`.
Transforms are 4x4, taking scan coordinates onto the model (SOURCE onto TARGET); mm.
"""

from inspection.registration.clouds import Samples
from inspection.registration.driver import Registration, register
from inspection.registration.point_to_plane import icp
from inspection.registration.rigid import kabsch, pose_difference, transform_points
from inspection.registration.settings import COARSE_METHODS, DESCRIPTORS, RegistrationSettings, TargetSettings
from inspection.registration.target import ModelTarget
from inspection.registration.verification import fitness

__all__ = ["COARSE_METHODS", "DESCRIPTORS", "ModelTarget", "Registration", "RegistrationSettings", "Samples",
           "TargetSettings", "fitness", "icp", "kabsch", "pose_difference", "register", "transform_points"]
