"""Simulated parts for the bench station: the demo part with known imposed defects.

Built on `sim.parts`, so one defect model serves inspection and the station: the demo
part's STEP model (`config/parts/demo_part.step`, part frame mm, z up, base on z = 0)
tessellated to `CHORD_MM` (0.25 um), one scene object per CAD face, with per-face analytic
defects imposed by `sim.parts.deform`:

    high top bow      PlaneBow on the high top (#657, 35 x 60 mm at z = 22) centred on the
                      face, radius = its half-diagonal: d = b at the centre, 0 at the
                      corners. The shape is symmetric, so its minimum-zone flatness is b;
                      its profile zone about nominal (2 max|d|) is 2b.
    boss lobing       Lobing (3 lobes, amplitude a) on the boss's side (#17, radius 12 mm):
                      cylindricity 2a over the whole side. One view sees about half the
                      side, whose own zone is 0.52..0.90 of 2a depending on where the lobes
                      fall (a Chebyshev fit of cos 3θ over ±75° with a free centre and
                      radius), so the verdicts use amplitudes that are clear either way.
                      Only the side's vertices move (sim.parts deforms face by face), so its
                      edges part from the low top and the chamfer by up to a: a seam of
                      <= 0.1 mm, under one camera pixel (~0.12 mm) at 400 mm.
    chamfer lobing    Lobing (3 lobes, amplitude c, radial) on the boss's top chamfer (#105, a
                      45 degree cone 1.5 mm wide): its signed deviation from nominal is
                      c cos 45 cos 3θ, so its profile zone about nominal (2 max|d|) is
                      2 c cos 45 (the cone's semi-angle from the CAD model). In phase with the
                      boss lobing, so the two faces still meet where both are lobed alike.
    high top raised   the high section made h taller (every vertex at z = 22 over x <= -10
                      moves up, on every face, so the mesh stays closed): the high top's
                      flatness stays 0, its profile zone about nominal is 2h.

Characteristics without a defect are true to nominal (value 0, to the 0.25 um chord).
`imposed` holds these values by the demo program's characteristic names
(`config/parts/demo_part.toml` names the same faces, `CHARACTERISTIC_FACES`; the turntable
program `config/parts/demo_part_turntable.toml` those of `TURNTABLE_FACES`).

Placement: the rig looks at the bench `TILT_RAD` (34 degrees) off its normal, as in the
inspection tests, so the boss's side is in view; each part lies on the bench turned and
shifted by a small amount of its own (as an operator places it), so registration is never
given one pose. On a rig with a turntable (`SimPart.on_stage`) the part stands on the
platter, its base centre on the axis, turned and shifted by the same amounts of its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np

from scanner.config import CONFIG_DIR
from scanner.stage_model import StageModel
from sim.parts import Defect, Lobing, PlaneBow, deform, lying_pose, part_scene
from sim.parts_demo import BOSS_CENTER, BOSS_RADIUS, CHORD_MM, HIGH_TOP, PLATE_X, PLATE_Y, STEP_X
from sim.scene import Scene
from sim.stage_bench import part_on_stage

STEP_MODEL = CONFIG_DIR / "parts" / "demo_part.step"
TRUTH_FILE = "sim_part.json"  # written into every session of a simulated station part
HIGH_TOP_FACE, LOW_TOP_FACE, BOSS_SIDE_FACE, CHAMFER_FACE = "#657", "#158", "#17", "#105"  # ids in STEP_MODEL
# The face each characteristic of the demo part program is on (the program must agree).
CHARACTERISTIC_FACES = {"high_top_flatness": HIGH_TOP_FACE, "low_top_flatness": LOW_TOP_FACE,
                        "boss_cylindricity": BOSS_SIDE_FACE, "high_top_profile": HIGH_TOP_FACE,
                        "high_top_sq": HIGH_TOP_FACE}
# ... and of the turntable program, which measures the whole part: the chamfer all round
TURNTABLE_FACES = {"high_top_flatness": HIGH_TOP_FACE, "low_top_flatness": LOW_TOP_FACE,
                   "boss_cylindricity": BOSS_SIDE_FACE, "boss_chamfer_profile": CHAMFER_FACE}
LOBES = 3
BOW_EDGE_MM = 1.0  # the bowed face is refined to this edge length: the mesh follows d to < 0.1 um
TILT_RAD = (0.6, 0.0)  # the bench seen 34 degrees off its normal (about the camera's x axis)
DISTANCE_MM = 400.0  # the part's bounding-box centre from the camera
BASE_TURN_RAD = 0.3  # the placement every part's own turn is relative to


@cache
def nominal_model() -> Any:
    """The demo part's STEP model tessellated to `CHORD_MM` (an `inspection.cad.CadModel`)."""
    from inspection.cad import load_cad

    return load_cad(STEP_MODEL, deflection_mm=CHORD_MM)


@dataclass(frozen=True, eq=False)
class SimPart:
    """A simulated part: `imposed` the true value (mm) of each characteristic in
    `CHARACTERISTIC_FACES`; `vertices` (N, 3) mm, `triangles` (M, 3) and `face` (M,) CAD
    face index of each triangle, in the part frame; `turn_rad` (about the bench normal) and
    `shift_mm` (x, y along the bench, part frame) its placement; `defects` as imposed."""

    name: str
    description: str
    imposed: dict[str, float]
    vertices: np.ndarray = field(repr=False)
    triangles: np.ndarray = field(repr=False)
    face: np.ndarray = field(repr=False)
    turn_rad: float = 0.0
    shift_mm: tuple[float, float] = (0.0, 0.0)
    defects: tuple[str, ...] = ()

    def on_stage(self, stage: StageModel) -> Scene:
        """The part standing on the platter of `stage` (its nominal axes, the simulator's
        truth) at stage 0, turned and shifted by its own placement; the stage turns it."""
        from scipy.spatial.transform import Rotation

        placement = np.eye(4)
        placement[:3, :3] = Rotation.from_euler("z", self.turn_rad).as_matrix()
        placement[:2, 3] = self.shift_mm
        return part_on_stage(self.vertices, self.triangles, self.face, (0.0, 0.0, 1.0), stage, placement=placement)

    def pose(self, view: int = 0, views: int = 1) -> np.ndarray:
        """Part -> camera pose for view k of n: the operator turns the part a further k/n
        of a revolution on the bench."""
        turn = BASE_TURN_RAD + self.turn_rad + 2.0 * np.pi * view / views
        shift = np.eye(4)
        shift[:2, 3] = self.shift_mm
        return lying_pose(self.vertices, turn, DISTANCE_MM, TILT_RAD) @ shift

    def scene(self, view: int = 0, views: int = 1) -> Scene:
        """The part on the bench for view k of n, one scene object per CAD face."""
        scene, _ = part_scene(self.vertices, self.triangles, self.face, self.pose(view, views),
                              name=f"demo_part-{self.name}")
        return scene

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "description": self.description, "imposed_mm": dict(self.imposed),
                "defects": list(self.defects), "turn_rad": self.turn_rad, "shift_mm": list(self.shift_mm),
                "cad": STEP_MODEL.name}


def raise_high_section(vertices: np.ndarray, raise_mm: float) -> np.ndarray:
    """The high section made `raise_mm` taller: every vertex on z = HIGH_TOP over the high
    section (x <= STEP_X), of every face, moves up, so the faces still meet."""
    v = vertices.copy()
    v[np.isclose(v[:, 2], HIGH_TOP) & (v[:, 0] <= STEP_X + 1e-9), 2] += raise_mm
    return v


def make_part(name: str, *, bow_mm: float = 0.0, lobe_mm: float = 0.0, raise_mm: float = 0.0,
              turn_rad: float = 0.0, shift_mm: tuple[float, float] = (0.0, 0.0), chamfer_mm: float = 0.0) -> SimPart:
    """The demo part with a high-top bow, boss lobing, a raised high section and chamfer
    lobing (mm, 0 = none) and its truth; placed `turn_rad`, `shift_mm` from the base placement."""
    model = nominal_model()
    tess = model.tessellation
    truth = dict.fromkeys({**CHARACTERISTIC_FACES, **TURNTABLE_FACES}, 0.0)
    defects: list[Defect] = []
    said = []
    v = tess.vertices
    if raise_mm:
        v = raise_high_section(v, raise_mm)
        said.append(f"high section raised {raise_mm * 1e3:.0f} um")
    if bow_mm:
        (x0, x1), (y0, y1) = (PLATE_X[0], STEP_X), PLATE_Y
        defects.append(PlaneBow(model.by_label(HIGH_TOP_FACE).index, ((x0 + x1) / 2, (y0 + y1) / 2, HIGH_TOP),
                                (0.0, 0.0, 1.0), bow_mm, float(np.hypot(x1 - x0, y1 - y0) / 2), BOW_EDGE_MM))
        truth["high_top_flatness"] = abs(bow_mm)
        said.append(f"high top bowed {bow_mm * 1e3:.0f} um")
    if lobe_mm:
        defects.append(Lobing(model.by_label(BOSS_SIDE_FACE).index, (*BOSS_CENTER, 0.0), (0.0, 0.0, 1.0), 1,
                              lobes=LOBES, amplitude_mm=lobe_mm))
        truth["boss_cylindricity"] = 2.0 * abs(lobe_mm)
        said.append(f"boss {LOBES}-lobed +-{lobe_mm * 1e3:.0f} um (radius {BOSS_RADIUS:g} mm)")
    if chamfer_mm:
        cone = model.by_label(CHAMFER_FACE)
        defects.append(Lobing(cone.index, (*BOSS_CENTER, 0.0), (0.0, 0.0, 1.0), 1, lobes=LOBES,
                              amplitude_mm=chamfer_mm))
        truth["boss_chamfer_profile"] = 2.0 * abs(chamfer_mm) * float(np.cos(cone.surface.semi_angle))
        said.append(f"chamfer {LOBES}-lobed +-{chamfer_mm * 1e3:.0f} um")
    # the high top's signed deviation from nominal runs from raise_mm (corners) to raise_mm + bow_mm (centre)
    truth["high_top_profile"] = 2.0 * max(abs(raise_mm), abs(raise_mm + bow_mm))
    v, t, f = deform(v, tess.triangles, tess.face, defects)
    return SimPart(name, ", ".join(said) or "nominal", truth, v, t, f, turn_rad, shift_mm,
                   tuple(repr(d) for d in defects))


@cache
def lineup(chamfer: bool = False) -> tuple[SimPart, ...]:
    """The parts that come to the simulated bench, in order (part k is lineup()[k % 5]).
    Against the demo program's tolerances (flatness and cylindricity 0.05 mm, profile zone
    0.1 mm, Sq 0.03 mm) parts 0 and 2 conform and 1 (flatness 0.15, profile 0.3), 3
    (cylindricity 0.2) and 4 (profile 1.0) do not. Every true value is at least 30 um from
    its tolerance (form figures are measured to ~5 um), and stays on its side of it as the
    scan sees it: half the boss's side keeps >= 0.52 of the lobing's zone (module
    docstring), and registration, a best fit of the whole part, takes some of a profile
    error into its pose (the 0.15 mm bow's zone reads ~0.21 mm, the 0.5 mm step's ~0.5 mm),
    still well beyond 0.1 mm. A step of 1 mm is not used: the part then no longer registers
    (82 % of the scan within reach of the model, 90 % needed).

    `chamfer`: the turntable's lineup (its program measures the boss's chamfer all round):
    parts 2 and 3 also have their chamfer lobed like their boss, +-20 um and +-100 um
    (profile zones 0.028 and 0.141 mm against the turntable program's 0.1 mm). The bench's
    chamfers stay nominal: there one view sees half the boss's side, and part 3's lobed
    chamfer beside it took that half-side's cylindricity from 0.120 to 0.0965 mm (measured),
    below the 0.52 of 0.2 mm the bench's acceptance holds it to."""
    c = 1.0 if chamfer else 0.0
    return (
        make_part("nominal", turn_rad=0.00, shift_mm=(0.0, 0.0)),
        make_part("bow150", bow_mm=0.150, turn_rad=0.12, shift_mm=(3.0, -2.0)),
        make_part("bow20-lobe10" + ("-chamfer20" if chamfer else ""), bow_mm=0.020, lobe_mm=0.010,
                  chamfer_mm=0.020 * c, turn_rad=0.09, shift_mm=(2.0, 2.0)),
        make_part("lobe100" + ("-chamfer100" if chamfer else ""), lobe_mm=0.100, chamfer_mm=0.100 * c, turn_rad=-0.10,
                  shift_mm=(-2.5, 1.5)),
        make_part("raised500", raise_mm=0.500, turn_rad=-0.15, shift_mm=(-3.0, -2.5)),
    )
