"""The inspection report's figures, drawn with matplotlib (Agg, no display) as PNG bytes:
the part seen from several sides coloured by signed deviation with a colour bar in mm and
callouts naming each toleranced face with its values and verdicts; a close-up of one face
in its own surface coordinates; the histogram of the signed deviations.

Points are the feet of the scan points on the CAD model (model frame, mm), so every view
shows the part as designed, coloured by how far it departs from it (positive: excess
material) on the tolerance-tied scale of `inspection.deviation_colours`: the deviation the
figures are taken from (the form surface's, noise filtered out), at the points the figures
count. Behind them the CAD model is drawn as a light grey shaded mesh (decimated to at
most `MAX_TRIANGLES` triangles), so unscanned regions read as the part, not as empty
space. At most `MAX_POINTS` points are drawn (a fixed-seed sample), which keeps a drawing
to a few seconds; the colours and statistics use every point. Every view carries a callout
per toleranced face that faces it (at least `FACING` of the face's points turned towards
the viewer); a face facing none of the views is called out on the one it faces most."""

from __future__ import annotations

import io
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from inspection.deviation_colours import ColourScale, shown_count, shown_deviations
from inspection.figures import limited_by
from inspection.tolerances import overall

MAX_POINTS = 40_000
MAX_TRIANGLES = 6_000  # the CAD mesh drawn behind the points is decimated to this many
DOT_PT2 = 0.6  # a point's dot: the area of a disc this many pt² across (0.77 pt, 1.0 px at 96 dpi)
DOT_SIDES = 8  # drawn as a regular polygon of the disc's area: a fifth cheaper for Agg than a circle, alike at 1 px
DOT_AREA_RATIO = np.pi / (DOT_SIDES / 2 * np.sin(2 * np.pi / DOT_SIDES))  # disc / polygon, inscribed in one circle
PNG_LEVEL = 3  # zlib level of the figures' PNGs: half Pillow's default 6's time, the same size (the part views)
FACING = 0.3  # a face is called out on a view when this share of its points faces the viewer
GRAZING = 0.1  # a point faces the viewer when its normal's component towards the eye exceeds this (~6 deg)
LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])  # the mesh's shading light (model frame)
# (title, elevation deg, azimuth deg) of the part views
VIEWS = (("from front left, above", 30.0, -120.0), ("from back right, above", 30.0, 60.0),
         ("from above", 90.0, -90.0), ("from front right, low", 12.0, -40.0))
VERDICT_COLOURS = {"conforming": "#1a7a1a", "non-conforming": "#c01818", "uncertain": "#b06000",
                   "not measured": "#555555"}


def _png(fig: Any) -> bytes:
    """The figure as PNG bytes at 96 dpi, zlib level `PNG_LEVEL`."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=96, pil_kwargs={"compress_level": PNG_LEVEL})
    plt.close(fig)
    return buf.getvalue()


def _sample(n: int, limit: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most `limit` of n items, the same for the same n."""
    if n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, limit, replace=False))


def face_verdict(row: Any) -> str:
    """A face's verdict word over its characteristics ("" without any)."""
    words = [v for _, v in row.verdicts.values()]
    return overall(words) if words else ""


def eye_direction(elev_deg: float, azim_deg: float) -> np.ndarray:
    """The unit vector from the scene towards matplotlib's 3D camera at (elev, azim)."""
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def callout_views(report: Any, views: Any = VIEWS) -> dict[int, list[int]]:
    """Per view (index in `views`), the rows of `report.faces` called out on it: toleranced
    faces with points of which at least `FACING` face the viewer; a face facing none of
    the views goes on the one it faces most."""
    seg = report.segmentation
    eyes = np.array([eye_direction(elev, azim) for _, elev, azim in views])
    out: dict[int, list[int]] = {k: [] for k in range(len(views))}
    for i, row in enumerate(report.faces):
        on = seg.face == row.index
        if not face_verdict(row) or not on.any():
            continue
        facing = (seg.normal[on] @ eyes.T > GRAZING).mean(axis=0)
        for k in np.flatnonzero(facing >= FACING) if (facing >= FACING).any() else [int(np.argmax(facing))]:
            out[int(k)].append(i)
    return out


def display_mesh(cad: Any, limit: int = MAX_TRIANGLES) -> tuple[np.ndarray, np.ndarray]:
    """The CAD model's triangles (T, 3, 3) mm for drawing, decimated by quadric error
    (open3d) to at most `limit`, and their grey level (0..1) shaded by `LIGHT`."""
    v, t = cad.tessellation.vertices, cad.tessellation.triangles
    if len(t) > limit:
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
        mesh = mesh.simplify_quadric_decimation(limit)
        v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    tri = v[t]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return tri, 0.5 + 0.35 * np.abs(n @ LIGHT)


def part_views(report: Any, scale: ColourScale) -> bytes:
    """The part from the sides in `VIEWS`, the CAD model as a light mesh behind its points,
    the points coloured by their shown deviation on `scale`, one colour bar in mm; each
    view carries the callouts `callout_views` gives it (a face's name, values and verdicts
    at the centre of its points)."""
    seg = report.segmentation
    dev_all = shown_deviations(report)
    ok = seg.assigned & np.isfinite(dev_all)
    pts, dev = seg.foot[ok], dev_all[ok]
    pick = _sample(len(pts))
    colours = scale.rgb(dev[pick])
    fig = plt.figure(figsize=(11.0, 8.6))
    mesh = display_mesh(report.cad) if report.cad is not None else None
    corners = np.vstack([pts] + ([mesh[0].reshape(-1, 3)] if mesh is not None else []))
    lo, hi = (corners.min(axis=0), corners.max(axis=0)) if len(corners) else (np.zeros(3), np.ones(3))
    callouts = callout_views(report)
    for k, (title, elev, azim) in enumerate(VIEWS):
        ax = fig.add_subplot(2, 2, k + 1, projection="3d")
        ax.computed_zorder = False  # the mesh stays behind the points, the callouts in front
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_pane_color((1.0, 1.0, 1.0, 0.0))  # clear panes: the grey is the part
        if mesh is not None:
            grey = mesh[1][:, None] * np.ones(3)
            ax.add_collection3d(Poly3DCollection(mesh[0], facecolors=np.column_stack([grey, np.full(len(grey), 0.55)]),
                                                 edgecolors="none", zorder=1))
        ax.scatter(*pts[pick].T, c=colours, marker=(DOT_SIDES, 0, 0), s=DOT_PT2 * DOT_AREA_RATIO, linewidths=0,
                   depthshade=False, zorder=2)
        ax.view_init(elev=elev, azim=azim)
        ax.set_box_aspect(np.maximum(hi - lo, 1e-3))
        ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[1], hi[1]), ax.set_zlim(lo[2], hi[2])
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (mm)", fontsize=8), ax.set_ylabel("y (mm)", fontsize=8)
        if abs(elev) < 90.0:  # looking straight down z its axis collapses to a point: no ticks, no label
            ax.set_zlabel("z (mm)", fontsize=8)
        else:
            ax.set_zticks([])
        ax.tick_params(labelsize=7)
        _callouts(ax, [report.faces[i] for i in callouts[k]], seg)
    fig.subplots_adjust(left=0.02, right=0.86, bottom=0.03, top=0.95, wspace=0.05, hspace=0.12)
    _colour_bar(fig, fig.add_axes((0.9, 0.15, 0.02, 0.7)), scale, "deviation from nominal (mm); + excess material")
    return _png(fig)


def _colour_bar(fig: Any, cax: Any, scale: ColourScale, label: str) -> None:
    """The scale's bar with ticks at the zone's edges and twice them."""
    cmap, norm = scale.colormap()
    bar = fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), cax=cax)
    h = scale.h_mm
    bar.set_ticks([-2 * h, -h, 0.0, h, 2 * h])
    bar.set_ticklabels([f"{-2 * h:+.3f}", f"{-h:+.3f}", "0", f"{h:+.3f}", f"{2 * h:+.3f}"])
    bar.ax.tick_params(labelsize=7)
    bar.set_label(f"{label}\ngreen: within ±{h:.3f} mm", fontsize=8)


def value_text(e: Any) -> str:
    """A figure as the callouts print it (mm): "0.0123 ± 0.0020", "< 0.0092", "not measured"."""
    if e is None:
        return "not measured"
    if e.value is None:
        return f"< {e.limit:.4f}" if e.limit is not None else "not measured"
    return f"{e.value:.4f} ± {e.U:.4f}"


def callout_text(row: Any) -> str:
    """A face's callout: its title, then per characteristic its value, tolerance (mm) and verdict."""
    lines = [row.title]
    for key, (tol, verdict) in row.verdicts.items():
        e = row.form.figure(limited_by(key).name) if row.form.status == "ok" else None
        lines.append(f"{key.removesuffix('_mm').replace('_ls', ' LS')} {value_text(e)} / {tol:.3f} mm: {verdict}")
    return "\n".join(lines)


def _callouts(ax: Any, rows: Any, seg: Any) -> None:
    """A label per face row (`callout_text`) in its verdict's colour, with a leader to the
    mean of its points; taken left to right across the view, the labels go alternately
    above and below their points, so neighbours do not cover each other."""
    from mpl_toolkits.mplot3d import proj3d

    anchors = []
    for row in rows:
        c = seg.foot[seg.face == row.index].mean(axis=0)
        x, y, _ = proj3d.proj_transform(*c, ax.get_proj())
        anchors.append((float(x), float(y), row))
    for k, (x, y, row) in enumerate(sorted(anchors, key=lambda a: a[0])):
        colour = VERDICT_COLOURS.get(face_verdict(row), "#000")
        above = k % 2 == 0
        ax.annotate(callout_text(row), (x, y), xytext=(0, 26 if above else -26), textcoords="offset points",
                    fontsize=6.5, color=colour, ha="center", va="bottom" if above else "top", zorder=10,
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": colour, "alpha": 0.85},
                    arrowprops={"arrowstyle": "-", "color": colour, "lw": 0.8})


CLOSEUP_AXES = (0.1, 0.12, 0.7, 0.74)  # the face's map in a close-up (figure fractions: left, bottom, width, height)
CLOSEUP_CELLS = 160  # map cells along the face's longer side


def face_map(uv: np.ndarray, dev: np.ndarray,
             cells: int = CLOSEUP_CELLS) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The mean signed deviation (mm) per cell of a regular grid over the face's surface
    coordinates (NaN: no point), rows from v low to high; and its extent (u0, u1, v0, v1)."""
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    shape = np.maximum(np.round(cells * span / span.max()).astype(int), 1)
    edges = [np.linspace(lo[k], hi[k], shape[k] + 1) for k in (0, 1)]
    total, _, _ = np.histogram2d(uv[:, 0], uv[:, 1], edges, weights=dev)
    count, _, _ = np.histogram2d(uv[:, 0], uv[:, 1], edges)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / count, np.nan)
    return mean.T, (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def face_closeup(report: Any, row: Any, scale: ColourScale) -> bytes:
    """One face in its own surface coordinates (u, v: mm on a plane; angle and height on a
    cylinder, as the CAD face parametrises it), the mean shown deviation per map cell on
    `scale`, a colour bar in mm, the face's values and verdicts in the title; the points are
    those its figures count (the table's). The map fills `CLOSEUP_AXES`; the figure's height
    follows the face's aspect."""
    seg = report.segmentation
    shown = shown_deviations(report)
    on = (seg.face == row.index) & np.isfinite(shown)
    grid, extent = face_map(seg.uv[on], shown[on]) if on.any() else (np.full((1, 1), np.nan), (0.0, 1.0, 0.0, 1.0))
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9) if row.type == "plane" else 0.6
    width = 7.2
    height = float(np.clip(width * CLOSEUP_AXES[2] * aspect / CLOSEUP_AXES[3], 2.6, 6.0))
    fig = plt.figure(figsize=(width, height))
    ax = fig.add_axes(CLOSEUP_AXES)
    rgba = np.ones((*grid.shape, 4))
    rgba[..., :3] = scale.rgb(grid.ravel()).reshape(*grid.shape, 3)
    rgba[~np.isfinite(grid), 3] = 0.0  # no point in the cell: blank
    ax.imshow(rgba, origin="lower", extent=extent, aspect="auto", interpolation="nearest")
    plane = row.type == "plane"
    ax.set_xlabel("u (mm)" if plane else "u (face parameter)", fontsize=9)
    ax.set_ylabel("v (mm)" if plane else "v (face parameter)", fontsize=9)
    what = "form surface" if row.form.deviation_source == "form surface" else "raw points"
    ax.set_title("\n".join([f"{row.title} ({row.type}, {shown_count(report, row)} points, {what})"]
                            + callout_text(row).split("\n")[1:]), fontsize=8)
    cax = fig.add_axes((CLOSEUP_AXES[0] + CLOSEUP_AXES[2] + 0.03, CLOSEUP_AXES[1], 0.025, CLOSEUP_AXES[3]))
    _colour_bar(fig, cax, scale, "mean deviation (mm)")
    return _png(fig)


def deviation_histogram(report: Any, profile_tolerances_mm: dict[str, float]) -> bytes:
    """The signed deviations of every point on a face (mm), raw (noise included), with the
    ±t/2 zone of each profile tolerance drawn as dashed lines."""
    dev = report.segmentation.deviation_mm
    dev = dev[np.isfinite(dev)]
    fig, ax = plt.subplots(figsize=(7.2, 3.4))
    if len(dev):  # one filled outline from 0.5 (below one point on the log scale), not 120 bars: half the drawing
        counts, edges = np.histogram(dev, bins=120)
        ax.stairs(counts, edges, fill=True, color="#4a6fa5", baseline=0.5)
        ax.set_yscale("log")
    for name, t in profile_tolerances_mm.items():
        for x in (-t / 2, t / 2):
            ax.axvline(x, color="#c01818", ls="--", lw=1)
        ax.text(t / 2, 0.95, f" {name}: ±{t / 2:.3f} mm", transform=ax.get_xaxis_transform(), fontsize=8,
                color="#c01818", va="top")
    ax.set_xlabel("signed deviation from nominal (mm), every point on a face, noise included")
    ax.set_ylabel("points (log scale)")
    ax.set_title(f"{len(dev)} points; mean {np.mean(dev) if len(dev) else 0:+.4f} mm, "
                 f"SD {np.std(dev) if len(dev) else 0:.4f} mm", fontsize=10)
    fig.tight_layout()
    return _png(fig)
