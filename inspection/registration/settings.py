"""What registration can be tuned by: how a model target is prepared (`TargetSettings`)
and how a scan is registered to it (`RegistrationSettings`). Every figure carries its
unit and the reason for its default; the defaults are the ones the NIST benchmark
(studies/nist_registration.py) was measured with."""

from __future__ import annotations

from dataclasses import dataclass, fields

COARSE_METHODS = ("sac-ia", "ransac", "ndt")
DESCRIPTORS = ("fpfh", "shot")


def _check_positive(settings: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(settings, name)
        if not value > 0:
            raise ValueError(f"{type(settings).__name__}.{name} must be > 0, got {value!r}")


@dataclass(frozen=True)
class TargetSettings:
    """How a model target is sampled. The scan's descriptors are computed the same way as
    the model's (they must be, to be comparable), so these belong to the target."""

    # voxel side = model diagonal / this (mm / mm): the coarse clouds every stage up to
    # verification works on; finer costs time in every stage, coarser loses small features
    voxel_fraction: float = 150.0
    # dense samples for ICP every voxel / this (mm / mm): ICP's residuals then come from the
    # scan's noise, not from the sample spacing
    dense_fraction: float = 3.0
    # descriptors are computed on a grid of sphere radius / this (mm / mm): enough points
    # in a support for stable histograms, few enough to describe thousands of spheres
    descriptor_fraction: float = 5.0
    # neighbours per descriptor support at most (points): a flat support holds ~80 grid
    # points (pi 5^2); its nearest 64 describe it at a bounded cost per sphere
    descriptor_nn: int = 64

    def __post_init__(self) -> None:
        _check_positive(self, tuple(f.name for f in fields(self)))


@dataclass(frozen=True)
class RegistrationSettings:
    """How a scan is registered (see `inspection.registration`).

    `descriptors`: any of "fpfh", "shot" (both: the multivariate combination);
    `coarse`: "sac-ia", "ransac" or "ndt"; `spheres`: m of Eq. 19 per RSCS scale;
    `hypotheses`: coarse poses scored; `verify`: distinct poses refined and verified;
    `min_fitness`: below it the registration fails; `max_normal_deg`: ICP's normal-angle
    rejection (deg); `max_points`: scan points used by the fine step; `ambiguity_margin`:
    another pose judged within it of the best makes the result ambiguous; `seed`:
    randomness. `pose_tolerance_deg` / `pose_tolerance_mm`: the accuracy a pose must be
    proven to (a motion whose U exceeds it is free; two poses within it are the same);
    `false_accept`: the largest probability of returning a pose when another the search
    found explains the scan as well (`evidence`). The fields after `false_accept` tune the
    stages; their comments say why."""

    descriptors: tuple[str, ...] = DESCRIPTORS
    coarse: str = "sac-ia"
    spheres: tuple[int, ...] = (200, 100, 50)
    hypotheses: int = 1500
    verify: int = 6
    min_fitness: float = 0.9
    max_normal_deg: float = 30.0
    max_points: int = 40000
    ambiguity_margin: float = 0.02
    seed: int = 0
    pose_tolerance_deg: float = 0.05
    pose_tolerance_mm: float = 0.05
    false_accept: float = 1e-3
    # SAC-IA: hypotheses scored on every evaluation point after a pre-score on a fifth of
    # them (poses): the pre-score is five times cheaper and only has to keep the good ones
    prescored: int = 150
    # verification: the most promising refined hypotheses explored further (poses): the
    # local search is the costliest step of verification, so only the leaders get it
    explored: int = 4
    # exploration turns about the scan's principal axes, and shifts along them by as many
    # inlier distances (deg): along a large plane a turn moves only edge points, which ICP
    # rejects as outliers but the fitness counts
    coarse_turns_deg: tuple[float, ...] = (2.5, 5.0, 10.0, 20.0, 30.0)
    # the same about the best pose on the dense scan with a tight inlier distance (deg)
    fine_turns_deg: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0, 2.0)
    # exploration: moves pre-scored on every n-th point (points), then the best
    # `explore_top` on all: the pre-score ranks the 60 moves at a quarter of the cost
    explore_prescore_stride: int = 4
    explore_top: int = 6
    # fine step: points seen more obliquely than this are left out (deg): grazing views
    # measure a surface worst (mixed pixels, widest footprint)
    max_incidence_deg: float = 75.0
    # the camera's blur (Gaussian sigma, px): the share of a pixel's light from beyond an
    # outline (`fine.mixing`), which a face's offset as a whole grows with. The rig's
    # [camera.sensor] blur_sigma_px where the scan's rig is known; else 1 px is assumed, a
    # camera focused on the part (wider than the simulated bench's 0.6 px, which states the
    # faces' offsets conservatively: module docstring of `evidence`)
    camera_blur_px: float = 1.0
    # points in the exact-distance (Gauss-Newton) refinement (points): any point will do,
    # so this bounds its cost (each step projects every point onto its face)
    exact_points: int = 40000
    # faces whose median residual departs from the faces' median by more than this times
    # the spread of the faces' medians are left out as a group (robust sigmas): a face off
    # as a whole must not pull the others
    face_bias_sigma: float = 3.0
    # residuals spreading more than this times the point noise (ratio): a large face may be
    # off as a whole, so fits leaving each big face out are tried
    offset_noise_ratio: float = 1.25
    # faces holding at least this share of the scan's points are the ones tried left out
    # (fraction): smaller faces cannot pull the fit far
    big_face_fraction: float = 0.05
    # scan points on which the best pose and each alternative are compared (points): the
    # sign test's power grows with them, its cost too (one ray cast per point and pose)
    eval_points: int = 4000
    # ICP: weight of a point-to-point term along the surface (ratio to the plane term): it
    # keeps points from sliding off a face's edge, which the plane metric alone does not see
    tangential_weight: float = 0.1

    def __post_init__(self) -> None:
        if self.coarse not in COARSE_METHODS:
            raise ValueError(f"unknown coarse method {self.coarse!r}; use one of {COARSE_METHODS}")
        if not self.descriptors or any(d not in DESCRIPTORS for d in self.descriptors):
            raise ValueError(f"descriptors must be a non-empty subset of {DESCRIPTORS}, got {self.descriptors}")
        _check_positive(self, ("hypotheses", "verify", "min_fitness", "max_normal_deg", "max_points", "prescored",
                               "explored", "explore_prescore_stride", "explore_top", "max_incidence_deg",
                               "camera_blur_px", "exact_points", "face_bias_sigma", "offset_noise_ratio",
                               "big_face_fraction", "pose_tolerance_deg", "pose_tolerance_mm", "false_accept",
                               "eval_points"))
        if not self.spheres or any(m <= 0 for m in self.spheres):
            raise ValueError(f"RegistrationSettings.spheres must be positive sphere counts, got {self.spheres}")
        if self.ambiguity_margin < 0 or not 0 <= self.tangential_weight < 1:
            raise ValueError(f"RegistrationSettings: ambiguity_margin must be >= 0 and tangential_weight in [0, 1), "
                             f"got {self.ambiguity_margin}, {self.tangential_weight}")


# The defaults as shared instances (settings are frozen): the functions' default arguments.
DEFAULT_TARGET_SETTINGS = TargetSettings()
DEFAULT_REGISTRATION_SETTINGS = RegistrationSettings()
