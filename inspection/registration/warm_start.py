"""Warm-started registration: a station re-measuring the same part in the same fixture
starts from the previous part's pose instead of the global search.

The prior is refined as a coarse hypothesis is in `driver.register` (ICP on a subsample,
the local search of the fitness); the fine step leaves out its own local search, which
settled the prior's pose on the previous part (the demo part set down up to 1 mm or 2 deg
off the prior reaches the same pose without it). The refined pose is checked before it is
trusted: it must explain the scan as a global search's best would (fitness within 1.5
voxels at least `min_fitness`, less the fraction of scan points the posed model would
hide), and after the fine step the fitness must come within `WARM_FITNESS_DROP` of the
prior's. A part put in the fixture turned, another part, or a moved fixture fails the
check and the global search runs (`register_with_prior`), so a warm start never changes
which pose is found, only how long finding it takes.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from inspection.errors import RegistrationFailed
from inspection.measured_cloud import ScanCloud
from inspection.registration.driver import Registration, coarse_icp, judge, refine, register, scan_voxels
from inspection.registration.settings import DEFAULT_REGISTRATION_SETTINGS, RegistrationSettings
from inspection.registration.target import ModelTarget
from inspection.registration.verification import evaluate_pose, explore

WARM_FITNESS_DROP = 0.03  # the fine fitness may fall this much below the prior's (noise between parts)
WARM_METHOD = "prior+icp"


def register_from_prior(scan: ScanCloud, target: ModelTarget, prior: Registration,
                        settings: RegistrationSettings = DEFAULT_REGISTRATION_SETTINGS) -> Registration | None:
    """The pose taking `scan` onto `target` found from `prior` (the previous part's
    registration on this station), or None when the check fails (module docstring). It
    is ambiguous when the prior was (the same part in the same fixture has the same
    symmetries; its alternatives are the prior's); its free motions are its own."""
    rng = np.random.default_rng(settings.seed)
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    v = target.voxel_mm
    try:
        src_pts, src_nrm = scan_voxels(scan, target)
    except RegistrationFailed:
        return None  # the global search says why
    times["prepare"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    inlier = 1.5 * v
    sub = rng.choice(len(src_pts), size=min(1500, len(src_pts)), replace=False)
    sp, sn = src_pts[sub], src_nrm[sub]
    T = coarse_icp(sp, sn, target, prior.transform, settings)
    T = explore(sp, sn, target.coarse, T=T, inlier_mm=inlier, degrees=settings.coarse_turns_deg, icp_mm=4.0 * v,
                settings=settings)
    fit, _ = evaluate_pose(sp, sn, target.dense, T, inlier, settings.max_normal_deg)
    hidden = target.hidden_fraction(T, sp, scan.viewpoint, 2.0 * v) if scan.viewpoint is not None else 0.0
    times["verify"] = time.perf_counter() - t0
    if fit - hidden < settings.min_fitness:
        return None
    try:
        reg = refine(scan, target, T, settings=settings, rng=rng, times=times, method=WARM_METHOD, local_search=False)
    except RegistrationFailed:
        return None
    if reg.fitness < prior.fitness - WARM_FITNESS_DROP:
        return None
    return judge(reg, prior.comparisons, settings)


def register_with_prior(scan: ScanCloud, target: ModelTarget, prior: Registration | None,
                        settings: RegistrationSettings = DEFAULT_REGISTRATION_SETTINGS) -> Registration:
    """`register_from_prior` when there is a prior and it passes its check, else the global
    search (`register`); the result's timings say which ran ("warm_start" is the time a
    failed warm start cost before the global search)."""
    if prior is None:
        return register(scan, target, settings)
    t0 = time.perf_counter()
    warm = register_from_prior(scan, target, prior, settings)
    if warm is not None:
        return warm
    spent = time.perf_counter() - t0
    cold = register(scan, target, settings)
    timings = {**cold.timings_s, "warm_start": round(spent, 4)}
    timings["total"] = round(timings["total"] + spent, 4)
    return replace(cold, timings_s=timings)
