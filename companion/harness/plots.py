"""Figures of a run, laid out like the paper's Fig. 6 and Fig. 7 (section 4).

- fig6.png: (a) plan view: terrain height map, obstacle features, the original route (dashed
  grey, base points marked), the flown path (black), remembered obstacle points (red dots);
  (b) z along the flown path against distance travelled, with the terrain under the vehicle
  and the H_d band; (c) 3-D view of the terrain with the flown trajectory.
- fig7.png, against time: (a) phi* with its thresholds and the decision shaded; (b) min d_i
  and the true clearance with D_min; (c) phi_d and pitch with +-phi_max; (d) H with H_d and
  its +-0.15 m band; (e) speed of X_d with the reference speed and v_d.

matplotlib is an optional dependency (the `plots` extra). It is imported inside
`write_figures` and used through `matplotlib.figure.Figure` directly: no pyplot, no backend
switch, no global state touched. Frame: local ENU metres, angles radians, time seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.planner.params import PlannerParams
from companion.planner.route import Route
from companion.sim.world import World

__all__ = ["HEIGHT_BAND_M", "PlotParams", "write_figures"]

HEIGHT_BAND_M = 0.15
"""The paper's bound on |H - H_d| (Fig. 7d), metres."""


@dataclass(frozen=True)
class PlotParams:
    """The planner parameters the figures draw: H_d and D_min (m), phi_max (rad), v_d (m/s)
    and eq. (7)'s side threshold (rad), taken from the planner's own function."""

    h_d_m: float
    d_min_m: float
    phi_max_rad: float
    v_d_mps: float
    side_threshold_rad: float

    def __post_init__(self) -> None:
        for name in ("h_d_m", "d_min_m", "phi_max_rad", "v_d_mps", "side_threshold_rad"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")

    @classmethod
    def from_planner(cls, params: PlannerParams) -> PlotParams:
        """The figures' parameters of a planner configuration (eq. (7) as the planner has it)."""
        return cls(
            h_d_m=params.h_d_m,
            d_min_m=params.d_min_m,
            phi_max_rad=params.phi_max_rad,
            v_d_mps=params.v_d_mps,
            side_threshold_rad=params.side_threshold_rad,
        )


_DPI = 110
_MAX_EVENT_LINES = 200
_FIGSIZE = (12.0, 9.0)
_DECISION_COLOURS = {"vertical": "#d9ecd0", "horizontal": "#fdd49e", "blocked": "#f4a3a3"}
_DECISION_LABELS = {
    "vertical": "vertical (climb over)",
    "horizontal": "horizontal (go round)",
    "blocked": "blocked (stop)",
}


def _import_matplotlib() -> Any:
    try:
        import matplotlib  # noqa: F401
        from matplotlib.figure import Figure
        from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the 3-D projection)
    except ImportError as exc:
        raise RuntimeError(
            "figures need matplotlib: install the `plots` extra "
            "(pip install 'terrain-companion[plots]') or run without plots"
        ) from exc
    return Figure


_WIDE_ASPECT = 1.8
"""Plan views at least this much wider than tall get the stacked, full-width layout."""
_PLAN_ASPECT_WIDE = 3.8
_PLAN_ASPECT_TALL = 0.68
"""Width / height of the plan view's cell in the two layouts (12 x 9 in figure)."""


def _xy_extent(
    route_xy: np.ndarray, trace_xy: np.ndarray, extra_xy: np.ndarray | None
) -> tuple[tuple[float, float, float, float], bool]:
    """Plan-view extent and layout: the bounding box of the route and the flown path (and
    extra points) with a margin, padded to the shape of the cell it is drawn in; and
    whether that is the wide (stacked) layout."""
    pts = [route_xy, trace_xy]
    if extra_xy is not None and len(extra_xy):
        pts.append(extra_xy)
    allp = np.concatenate([p[np.all(np.isfinite(p), axis=1)] for p in pts])
    if len(allp) == 0:
        allp = np.zeros((1, 2))
    x0, y0 = allp.min(axis=0)
    x1, y1 = allp.max(axis=0)
    span = max(x1 - x0, y1 - y0, 1.0)
    m = max(5.0, 0.08 * span)
    x0, x1, y0, y1 = x0 - m, x1 + m, y0 - m, y1 + m
    w, h = x1 - x0, y1 - y0
    wide = w >= _WIDE_ASPECT * h
    target = _PLAN_ASPECT_WIDE if wide else _PLAN_ASPECT_TALL
    if w < target * h:
        c = 0.5 * (x0 + x1)
        x0, x1 = c - 0.5 * target * h, c + 0.5 * target * h
    else:
        c = 0.5 * (y0 + y1)
        y0, y1 = c - 0.5 * w / target, c + 0.5 * w / target
    return (float(x0), float(x1), float(y0), float(y1)), wide


def _grid(
    world: World, ext: tuple[float, float, float, float], n_long: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface heights on a grid over ext with about n_long cells along the longer side."""
    x0, x1, y0, y1 = ext
    w, h = x1 - x0, y1 - y0
    nx = max(2, round(n_long * (w / max(w, h))))
    ny = max(2, round(n_long * (h / max(w, h))))
    gx = np.linspace(x0, x1, nx)
    gy = np.linspace(y0, y1, ny)
    X, Y = np.meshgrid(gx, gy)
    return X, Y, np.asarray(world.height(X, Y), dtype=np.float64)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the True runs of a boolean array (stop exclusive)."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


def _shade_decisions(
    ax: Any, t: np.ndarray, decision: np.ndarray, which: tuple[str, ...], strength: float = 1.0
) -> None:
    """Shade the background where the decision is one of `which` (time spans per cycle)."""
    if len(t) == 0:
        return
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    dec = np.asarray(decision).astype(str)
    for name in which:
        for i0, i1 in _runs(dec == name):
            ax.axvspan(
                t[i0] - dt,
                t[i1 - 1],
                color=_DECISION_COLOURS[name],
                alpha=strength * (0.9 if name != "vertical" else 0.45),
                lw=0,
                zorder=0,
            )


def _note(ax: Any, text: str, x: float, y: float, ha: str = "right", va: str = "bottom") -> None:
    """A small boxed note at axes fraction (x, y)."""
    ax.text(
        x,
        y,
        text,
        transform=ax.transAxes,
        ha=ha,
        va=va,
        fontsize=8,
        zorder=7,
        bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "0.8", "alpha": 0.85},
    )


def _short(text: str, n: int = 30) -> str:
    s = text.split("(")[0].split(",")[0].strip() or text
    return s if len(s) <= n else s[: n - 1] + "…"


def _event_marks(
    events: list[tuple[float, str]] | None, min_gap_s: float
) -> list[tuple[float, str | None]]:
    """Events to draw: every event as a line, a label only where it does not crowd the
    previous label (and at most 12 labels)."""
    if not events:
        return []
    marks: list[tuple[float, str | None]] = []
    last = -math.inf
    labelled = 0
    for t, text in sorted(events, key=lambda e: e[0]):
        if t - last >= min_gap_s and labelled < 12:
            marks.append((t, _short(text)))
            last = t
            labelled += 1
        else:
            marks.append((t, None))
    return marks


def _path_length(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])


def _feature_centre(poly: np.ndarray, circle: tuple[float, float, float] | None) -> np.ndarray:
    if circle is not None:
        return np.array(circle[:2])
    return np.asarray(poly.mean(axis=0))


def _route_terrain_at_progress(
    world: World, route_xy: np.ndarray, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """Terrain height under the original route at each flown sample's progress along it:
    the route vertex nearest the sample, never going back along the route (m)."""
    if len(x) == 0 or len(route_xy) == 0:
        return np.zeros(len(x))
    idx = np.empty(len(x), dtype=np.int64)
    for k in range(0, len(x), 512):  # bounded memory: 512 samples x route vertices
        d2 = (x[k : k + 512, None] - route_xy[None, :, 0]) ** 2 + (
            y[k : k + 512, None] - route_xy[None, :, 1]
        ) ** 2
        idx[k : k + 512] = np.argmin(d2, axis=1)
    idx = np.maximum.accumulate(idx)
    r = route_xy[idx]
    return np.asarray(world.height(r[:, 0], r[:, 1]), dtype=np.float64)


def _detected(min_range: Any) -> np.ndarray:
    """Ranges with "nothing within range" (recorded as 0 or NaN) as NaN: a gap when drawn."""
    r = np.asarray(min_range, dtype=np.float64)
    return np.where(np.isfinite(r) & (r > 0.0), r, np.nan)


def _overlap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    """Whether two (x0, y0, x1, y1) rectangles intersect."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _inside(points: np.ndarray, r: tuple[float, float, float, float]) -> int:
    if len(points) == 0:
        return 0
    m = (
        (points[:, 0] > r[0])
        & (points[:, 0] < r[2])
        & (points[:, 1] > r[1])
        & (points[:, 1] < r[3])
    )
    return int(np.count_nonzero(m))


def _place_plan_labels(
    fig: Any,
    ax: Any,
    labels: list[tuple[str, np.ndarray]],
    handles: list[Any],
    lines: np.ndarray,
    marks: np.ndarray,
    wide: bool,
) -> None:
    """Obstacle labels and the legend of the plan view, placed where they hide least.

    Each label goes above, below, right or left of its feature, inside the axes (not into
    the title), clear of the other labels and of the marks (base points, start, goal,
    closest approach), crossing as few path/route points as possible. The legend takes
    the corner that covers no mark and fewest points, or goes outside on the right.
    Positions are worked out in axes fractions from sizes measured in one layout pass.
    """
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()

    def frac(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        return np.column_stack([(p[:, 0] - x0) / (x1 - x0), (p[:, 1] - y0) / (y1 - y0)])

    style = {"fontsize": 9, "color": "#8b1a1a", "fontweight": "bold", "zorder": 6}
    texts = [ax.text(0.5, 0.5, t, transform=ax.transAxes, **style) for t, _ in labels]
    legend = ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.85)
    fig.draw_without_rendering()
    box = ax.get_window_extent()
    renderer = fig.canvas.get_renderer() if hasattr(fig.canvas, "get_renderer") else None

    def size(artist: Any) -> tuple[float, float]:
        e = artist.get_window_extent(renderer)
        return e.width / box.width, e.height / box.height

    line_pts = frac(lines[:: max(1, len(lines) // 1500)])
    mark_pts = frac(marks)
    placed: list[tuple[float, float, float, float]] = []
    pad = 0.012
    for text, (_, poly) in zip(texts, labels, strict=True):
        w, h = size(text)
        q = frac(poly)
        fx0, fy0 = q.min(axis=0)
        fx1, fy1 = q.max(axis=0)
        cx, cy = 0.5 * (fx0 + fx1), 0.5 * (fy0 + fy1)
        candidates = [
            (cx - w / 2, fy1 + pad, "above"),
            (cx - w / 2, fy0 - pad - h, "below"),
            (fx1 + pad, cy - h / 2, "right"),
            (fx0 - pad - w, cy - h / 2, "left"),
        ]
        best: tuple[float, tuple[float, float, float, float]] | None = None
        for lx, ly, _where in candidates:
            r = (lx, ly, lx + w, ly + h)
            score = 0.0
            if r[0] < 0.005 or r[1] < 0.005 or r[2] > 0.995 or r[3] > 0.995:
                score += 1000.0
            score += 100.0 * sum(_overlap(r, o) for o in placed)
            score += 100.0 * _inside(mark_pts, r) + _inside(line_pts, r)
            if best is None or score < best[0]:
                best = (score, r)
        assert best is not None
        r = best[1]
        text.set_position((r[0], r[1]))
        text.set_ha("left")
        text.set_va("bottom")
        placed.append(r)

    # Legend: 1, 2 or 3 columns in each corner; the first that hides no mark and no label
    # and crosses the fewest path points.
    sizes = {1: size(legend)}
    legend.remove()
    for ncol in (2, 3):
        trial = ax.legend(handles=handles, loc="upper right", ncol=ncol, fontsize=8)
        fig.draw_without_rendering()
        sizes[ncol] = size(trial)
        trial.remove()
    m = 0.01
    scored = []
    for ncol, (w, h) in sizes.items():
        corners = {
            "upper right": (1 - m - w, 1 - m - h),
            "upper left": (m, 1 - m - h),
            "lower left": (m, m),
            "lower right": (1 - m - w, m),
        }
        for loc, (lx, ly) in corners.items():
            r = (lx, ly, lx + w, ly + h)
            score = 100.0 * (_inside(mark_pts, r) + sum(_overlap(r, o) for o in placed))
            scored.append((score + _inside(line_pts, r), ncol, loc))
    _, ncol, loc = min(scored)
    ax.legend(handles=handles, loc=loc, ncol=ncol, fontsize=8, framealpha=0.85)


def _fig6(
    Figure: Any,
    path: Path,
    world: World,
    route: Route,
    trace: dict[str, np.ndarray],
    params: PlotParams,
    memory_xy: np.ndarray | None,
    title: str,
) -> Path:
    """Fig. 6: (a) plan view, (b) height along the path, (c) 3-D view."""
    from matplotlib import colors

    x = np.asarray(trace["x"], dtype=np.float64)
    y = np.asarray(trace["y"], dtype=np.float64)
    z = np.asarray(trace["z"], dtype=np.float64)
    route_xy = route.polyline().points
    base = np.asarray(route.base_points)
    mem = None if memory_xy is None or len(memory_xy) == 0 else np.asarray(memory_xy)
    ext, wide = _xy_extent(route_xy, np.column_stack([x, y]), mem)
    X, Y, Z = _grid(world, ext, 500)
    zmin, zmax = float(Z.min()), float(Z.max())
    if zmax - zmin < 1e-6:
        zmax = zmin + 1.0
    view = _TerrainView(
        ext=ext,
        wide=wide,
        zmin=zmin,
        zmax=zmax,
        norm=colors.Normalize(vmin=zmin, vmax=zmax),
        cmap=colors.LinearSegmentedColormap.from_list(
            "terrain_soft", ["#f3efe2", "#d6c9a0", "#a88c5c", "#6e5537"]
        ),
    )

    fig = Figure(figsize=_FIGSIZE, dpi=_DPI, layout="constrained")
    if wide:  # a long strip: plan view, profile and 3-D view stacked, full width
        gs = fig.add_gridspec(3, 1, height_ratios=[1.0, 0.8, 1.15])
        ax_a = fig.add_subplot(gs[0])
        ax_b = fig.add_subplot(gs[1])
        ax_c = fig.add_subplot(gs[2], projection="3d", computed_zorder=False)
    else:  # plan view on the left, profile and 3-D view on the right
        gs = fig.add_gridspec(2, 2, width_ratios=[1.1, 1.0])
        ax_a = fig.add_subplot(gs[:, 0])
        ax_b = fig.add_subplot(gs[0, 1])
        ax_c = fig.add_subplot(gs[1, 1], projection="3d", computed_zorder=False)

    labels = _plan_view(fig, ax_a, world, view, (X, Y, Z), route_xy, base, x, y, trace, mem, params)
    _height_profile(ax_b, world, route_xy, x, y, z, params)
    data_artists = _view_3d(ax_c, world, view, route_xy, base, x, y, z)

    head = f"{title}: " if title else ""
    fig.suptitle(f"{head}trajectory (cf. paper Fig. 6)", fontsize=13)
    _place_plan_labels(
        fig,
        ax_a,
        labels.obstacle_labels,
        labels.handles,
        lines=np.concatenate([np.column_stack([x, y]), route_xy]),
        marks=np.concatenate(labels.marks),
        wide=wide,
    )
    _fill_cell_3d(fig, ax_c, data_artists)
    fig.savefig(path, dpi=_DPI)
    return path


@dataclass(frozen=True)
class _TerrainView:
    """What the plan view and the 3-D view share: the plotted xy extent (m), the layout, the
    height range (m) and the terrain's colour map."""

    ext: tuple[float, float, float, float]
    wide: bool
    zmin: float
    zmax: float
    norm: Any
    cmap: Any


@dataclass
class _PlanLabels:
    """What the plan view leaves for the label placement: legend handles, obstacle labels
    with their outlines, and the points labels must not cover."""

    handles: list[Any]
    obstacle_labels: list[tuple[str, np.ndarray]]
    marks: list[np.ndarray]


def _plan_view(
    fig: Any,
    ax_a: Any,
    world: World,
    view: _TerrainView,
    grid: tuple[np.ndarray, np.ndarray, np.ndarray],
    route_xy: np.ndarray,
    base: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    trace: dict[str, np.ndarray],
    mem: np.ndarray | None,
    params: PlotParams,
) -> _PlanLabels:
    """Fig. 6a: shaded terrain, features, original route, flown path, decisions, remembered
    obstacle points and the closest approach with its D_min ring."""
    from matplotlib import colors
    from matplotlib.patches import Patch, Polygon

    X, Y, Z = grid
    ext, wide, zmin, zmax, norm, cmap = (
        view.ext,
        view.wide,
        view.zmin,
        view.zmax,
        view.norm,
        view.cmap,
    )
    ls = colors.LightSource(azdeg=315, altdeg=45)
    dx = (ext[1] - ext[0]) / max(X.shape[1] - 1, 1)
    rgb = ls.shade(Z, cmap=cmap, norm=norm, blend_mode="soft", vert_exag=1.0, dx=dx, dy=dx)
    ax_a.imshow(rgb, origin="lower", extent=ext, interpolation="bilinear", zorder=0)
    if zmax - zmin > 0.05:
        levels = np.linspace(zmin, zmax, 9)[1:-1]
        ax_a.contour(X, Y, Z, levels=levels, colors="#7a6a50", linewidths=0.4, alpha=0.6)
    # An inset colorbar follows the plan view's drawn (equal-aspect) box.
    cax = ax_a.inset_axes((1.015, 0.0, 0.022 if wide else 0.035, 1.0))
    fig.colorbar(_scalar_mappable(norm, cmap), cax=cax, label="terrain height z (m)")
    handles: list[Any] = []
    obstacle_labels: list[tuple[str, np.ndarray]] = []
    for info in world.features:
        if info.polygon is None:
            continue
        c = _feature_centre(info.polygon, info.circle)
        inside = ext[0] <= c[0] <= ext[1] and ext[2] <= c[1] <= ext[3]
        if info.obstacle:
            ax_a.add_patch(
                Polygon(
                    info.polygon,
                    closed=True,
                    facecolor=(0.85, 0.2, 0.2, 0.18),
                    edgecolor="#b22222",
                    hatch="///",
                    lw=1.0,
                    zorder=2,
                )
            )
            if inside:
                obstacle_labels.append((f"{info.name}\n(obstacle)", info.polygon))
        elif inside:
            ax_a.plot(c[0], c[1], marker="+", color="#5a4a30", ms=8, zorder=3)
            ax_a.annotate(
                info.name,
                (c[0], c[1]),
                xytext=(0, 7),
                textcoords="offset points",
                ha="center",
                fontsize=9,
                color="#4a3a20",
                style="italic",
                zorder=6,
            )
    if any(f.obstacle and f.polygon is not None for f in world.features):
        handles.append(
            Patch(
                facecolor=(0.85, 0.2, 0.2, 0.18),
                edgecolor="#b22222",
                hatch="///",
                label="obstacle feature",
            )
        )
    (h_route,) = ax_a.plot(
        route_xy[:, 0],
        route_xy[:, 1],
        ls="--",
        color="0.45",
        lw=1.6,
        zorder=3,
        label="original route",
    )
    ax_a.plot(base[:, 0], base[:, 1], "s", color="0.35", ms=5, zorder=4)
    for i, (bx, by) in enumerate(base):
        ax_a.annotate(
            f"W{i + 1}",
            (bx, by),
            xytext=(5, -12),
            textcoords="offset points",
            fontsize=9,
            color="0.25",
            zorder=6,
        )
    (h_flown,) = ax_a.plot(x, y, "-", color="black", lw=1.4, zorder=4, label="flown path")
    handles[:0] = [h_route, h_flown]
    dec = np.asarray(trace["decision"]).astype(str)
    for name, colour in (("horizontal", "#fd8d3c"), ("blocked", "#e31a1c")):
        runs = _runs(dec == name)
        for k, (i0, i1) in enumerate(runs):
            h_dec = ax_a.plot(
                x[max(i0 - 1, 0) : i1],
                y[max(i0 - 1, 0) : i1],
                "-",
                color=colour,
                lw=6,
                alpha=0.55,
                solid_capstyle="butt",
                zorder=3.5,
                label=f"decision: {name}" if k == 0 else None,
            )[0]
            if k == 0:
                handles.append(h_dec)
    if mem is not None:
        handles.append(
            ax_a.scatter(
                mem[:, 0], mem[:, 1], s=4, color="red", zorder=5, label="remembered obstacle points"
            )
        )
    if len(x):
        handles.append(
            ax_a.plot(x[0], y[0], "o", color="#1a9641", ms=8, mec="black", zorder=6, label="start")[
                0
            ]
        )
    handles.append(
        ax_a.plot(
            base[-1, 0], base[-1, 1], "*", color="gold", ms=14, mec="black", zorder=6, label="goal"
        )[0]
    )
    clearance = np.asarray(trace.get("clearance", np.full(len(x), np.nan)), dtype=np.float64)
    closest_xy: np.ndarray | None = None
    if np.isfinite(clearance).any():
        i = int(np.nanargmin(clearance))
        closest_xy = np.array([x[i], y[i]])
        d_min = params.d_min_m
        ring = np.linspace(0.0, 2.0 * np.pi, 73)
        handles.append(
            ax_a.plot(
                x[i] + d_min * np.cos(ring),
                y[i] + d_min * np.sin(ring),
                ls=":",
                color="#2166ac",
                lw=1.3,
                zorder=5,
                label=f"D_min = {d_min:g} m around the closest approach",
            )[0]
        )
        handles.append(
            ax_a.plot(
                x[i],
                y[i],
                "D",
                color="#2166ac",
                mec="white",
                ms=6,
                zorder=6,
                label=f"closest approach: {clearance[i]:.2f} m at t = {trace['t'][i]:.1f} s",
            )[0]
        )
    ax_a.set_xlim(ext[0], ext[1])
    ax_a.set_ylim(ext[2], ext[3])
    ax_a.set_aspect("equal")
    ax_a.set_xlabel("x east (m)")
    ax_a.set_ylabel("y north (m)")
    ax_a.set_title("(a) plan view: original route (dashed) and flown path (solid)", fontsize=11)
    marks = [base, np.array([[x[0], y[0]]]) if len(x) else np.empty((0, 2))]
    if closest_xy is not None:
        marks.append(closest_xy[None, :])
    return _PlanLabels(handles, obstacle_labels, marks)


def _height_profile(
    ax_b: Any,
    world: World,
    route_xy: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    params: PlotParams,
) -> None:
    """Fig. 6b: z along the flown path against horizontal distance travelled, with the
    terrain under the vehicle, the H_d band and the terrain under the original route."""
    h_d = params.h_d_m
    s = _path_length(x, y)
    ground = np.asarray(world.height(x, y), dtype=np.float64)
    floor = min(float(ground.min()), float(z.min())) - 0.5 if len(z) else 0.0
    ax_b.fill_between(
        s, floor, ground, color="#c8b68a", alpha=0.8, lw=0, label="terrain under the vehicle"
    )
    ax_b.plot(s, ground, color="#6e5537", lw=1.0)
    ax_b.fill_between(
        s,
        ground + h_d - HEIGHT_BAND_M,
        ground + h_d + HEIGHT_BAND_M,
        color="#4393c3",
        alpha=0.25,
        lw=0,
        label=f"terrain + H_d ± {HEIGHT_BAND_M:g} m",
    )
    ax_b.plot(
        s, ground + h_d, ls="--", color="#2166ac", lw=0.9, label=f"terrain + H_d (H_d = {h_d:g} m)"
    )
    ax_b.plot(s, z, color="black", lw=1.4, label="vehicle z")
    # The terrain under the original route at the vehicle's progress along it (the route
    # point nearest the vehicle, never going back), on the same distance-travelled axis: what
    # the vehicle would have had to climb without the horizontal correction.
    r_ground = _route_terrain_at_progress(world, route_xy, x, y)
    if len(s) and np.max(r_ground - ground) > 0.25:
        ax_b.plot(
            s,
            r_ground,
            ls=":",
            color="#b22222",
            lw=1.1,
            label="terrain under the original route, at the same progress along it",
        )
    ax_b.set_ylim(bottom=floor)
    ax_b.set_xlim(0, float(s[-1]) if len(s) > 1 and s[-1] > 0 else 1.0)
    ax_b.set_xlabel("distance travelled (horizontal, m)")
    ax_b.set_ylabel("z (m)")
    ax_b.set_title("(b) height z along the flown path", fontsize=11)
    ax_b.legend(loc="best", fontsize=8, framealpha=0.85)
    ax_b.grid(alpha=0.3)


def _view_3d(
    ax_c: Any,
    world: World,
    view: _TerrainView,
    route_xy: np.ndarray,
    base: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
) -> list[Any]:
    """Fig. 6c: the terrain surface with the flown trajectory; returns the data artists."""
    ext, wide, zmin, zmax, norm, cmap = (
        view.ext,
        view.wide,
        view.zmin,
        view.zmax,
        view.norm,
        view.cmap,
    )
    X3, Y3, Z3 = _grid(world, ext, 140)
    data_artists = [
        ax_c.plot_surface(
            X3,
            Y3,
            Z3,
            cmap=cmap,
            norm=norm,
            rstride=1,
            cstride=1,
            lw=0.1,
            edgecolor=(0.3, 0.25, 0.2, 0.25),
            antialiased=True,
            alpha=0.9,
            zorder=1,
        ),
        *ax_c.plot(
            route_xy[:, 0],
            route_xy[:, 1],
            np.asarray(world.height(route_xy[:, 0], route_xy[:, 1])) + 0.05,
            ls="--",
            color="0.4",
            lw=1.0,
            zorder=3,
            label="original route (on ground)",
        ),
        *ax_c.plot(x, y, z, color="black", lw=1.8, zorder=4, label="flown trajectory"),
    ]
    if len(x):
        data_artists += ax_c.plot(
            [x[0]], [y[0]], [z[0]], "o", color="#1a9641", mec="black", ms=6, zorder=5
        )
        data_artists += ax_c.plot(
            [base[-1, 0]], [base[-1, 1]], [z[-1]], "*", color="gold", mec="black", ms=11, zorder=5
        )
    ztop = max(zmax, float(z.max()) if len(z) else zmax)
    ax_c.set_xlim(ext[0], ext[1])
    ax_c.set_ylim(ext[2], ext[3])
    ax_c.set_zlim(zmin, ztop)
    wx, wy, wz = ext[1] - ext[0], ext[3] - ext[2], max(ztop - zmin, 1.0)
    wl = max(wx, wy)
    # Heights exaggerated so the relief reads, but never taller than half the long side.
    ax_c.set_box_aspect((wx, wy, min(max(wz * 2.0, 0.15 * wl), 0.5 * wl)))
    ax_c.view_init(elev=28, azim=-62 if wide else -125)
    # Few ticks on the short axes: their projections are short and labels would stack.
    from matplotlib.ticker import MaxNLocator

    for axis, span in ((ax_c.xaxis, wx), (ax_c.yaxis, wy), (ax_c.zaxis, wz)):
        axis.set_major_locator(
            MaxNLocator(max(2, min(8, round(8 * span / wl))) if axis is not ax_c.zaxis else 3)
        )
    ax_c.set_xlabel("x (m)", labelpad=4)
    ax_c.set_ylabel("y (m)", labelpad=2)
    ax_c.set_zlabel("z (m)", labelpad=0)
    ax_c.tick_params(labelsize=7, pad=0)
    ax_c.set_title(
        "(c) 3-D view: flown trajectory (black), original route on the ground (dashed), "
        "heights exaggerated"
        if wide
        else "(c) 3-D view, heights exaggerated\nblack: flown trajectory, dashed: original route",
        fontsize=11,
    )
    return data_artists


def _axis_extent(fig: Any, ax: Any) -> Any:
    """Display-space extent of a 3-D axes' box: its corners, three axes, ticks and labels."""
    from matplotlib.transforms import Bbox
    from mpl_toolkits.mplot3d import proj3d

    renderer = fig.canvas.get_renderer() if hasattr(fig.canvas, "get_renderer") else None
    boxes = [a.get_tightbbox(renderer) for a in (ax.xaxis, ax.yaxis, ax.zaxis)]
    boxes = [b for b in boxes if b is not None and b.width > 0 and b.height > 0]
    (x0, x1), (y0, y1), (z0, z1) = ax.get_xlim(), ax.get_ylim(), ax.get_zlim()
    cx, cy, cz = np.meshgrid([x0, x1], [y0, y1], [z0, z1])
    px, py, _ = proj3d.proj_transform(cx.ravel(), cy.ravel(), cz.ravel(), ax.get_proj())
    corners = ax.transData.transform(np.column_stack([px, py]))
    boxes.append(Bbox([corners.min(axis=0), corners.max(axis=0)]))
    return Bbox.union(boxes)


def _fill_cell_3d(fig: Any, ax: Any, data_artists: list[Any]) -> None:
    """Let a 3-D view fill its layout cell.

    mplot3d draws into a square viewport centred in the axes' cell, which leaves a wide
    cell mostly empty. Lay the figure out once, freeze that layout, then zoom the view until
    its drawn extent (ticks and labels included) fills the cell, drawing the data unclipped.
    """
    fig.draw_without_rendering()
    cell = ax.get_position(original=True).transformed(fig.transFigure)
    fig.set_layout_engine("none")
    zoom = 1.0
    for _ in range(3):
        tight = _axis_extent(fig, ax)
        if tight is None or tight.width <= 0 or tight.height <= 0:
            break
        f = 0.97 * min(cell.width / tight.width, cell.height / tight.height)
        if abs(f - 1.0) < 0.02:
            break
        zoom *= f if f < 1.0 else 1.0 + 0.97 * (f - 1.0)
        ax.set_box_aspect(ax.get_box_aspect(), zoom=zoom)
        fig.draw_without_rendering()
    tight = _axis_extent(fig, ax)
    if tight is not None:  # the box is not drawn centred in its viewport: centre it
        w, h = fig.bbox.width, fig.bbox.height
        dx = (0.5 * (cell.x0 + cell.x1) - 0.5 * (tight.x0 + tight.x1)) / w
        dy = (0.5 * (cell.y0 + cell.y1) - 0.5 * (tight.y0 + tight.y1)) / h
        ax.set_position(ax.get_position(original=True).translated(dx, dy))
    for a in data_artists:  # inside the box, but the box now overflows the square viewport
        a.set_clip_on(False)
    # The title sits on the (moved) square viewport: put it back above the cell.
    title = ax.get_title()
    ax.set_title("")
    xc, yt = fig.transFigure.inverted().transform((0.5 * (cell.x0 + cell.x1), cell.y1 + 6.0))
    fig.text(xc, yt, title, ha="center", va="bottom", fontsize=11)


def _scalar_mappable(norm: Any, cmap: Any) -> Any:
    from matplotlib.cm import ScalarMappable

    sm = ScalarMappable(norm=norm, cmap=cmap)
    sm.set_array(np.array([]))
    return sm


def _fig7(
    Figure: Any,
    path: Path,
    trace: dict[str, np.ndarray],
    params: PlotParams,
    phi_star: np.ndarray | None,
    thresholds: np.ndarray | None,
    events: list[tuple[float, str]] | None,
    title: str,
) -> Path:
    """Fig. 7 against time: (a) phi*, (b) distances, (c) pitch, (d) H, (e) speed of X_d."""
    t = np.asarray(trace["t"], dtype=np.float64)
    decision = np.asarray(trace["decision"]).astype(str)

    fig = Figure(figsize=_FIGSIZE, dpi=_DPI, layout="constrained")
    axes = fig.subplots(5, 1, sharex=True, height_ratios=[1.3, 1.0, 1.0, 1.0, 1.0])
    ax_a, ax_b, ax_c, ax_d, ax_e = axes
    t_end = float(t[-1]) if len(t) else 1.0
    t0 = float(t[0]) - (float(t[1] - t[0]) if len(t) > 1 else 0.0) if len(t) else 0.0

    # Decision in the background: all three on (a), the avoiding ones faintly elsewhere.
    _shade_decisions(ax_a, t, decision, ("vertical", "horizontal", "blocked"))
    for ax in axes[1:]:
        _shade_decisions(ax, t, decision, ("horizontal", "blocked"), strength=0.45)

    _steepness_panel(ax_a, t, trace, params, phi_star, thresholds, has_events=bool(events))
    _event_lines(list(axes), events, t0, t_end)
    _steepness_legend(ax_a, decision)
    _distance_panel(ax_b, t, trace, params)
    _pitch_panel(ax_c, t, trace, params)
    _height_panel(ax_d, t, trace, params)
    _speed_panel(ax_e, t, trace, params)

    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_xlim(t0, t_end)
    head = f"{title}: " if title else ""
    fig.suptitle(f"{head}planner signals against time (cf. paper Fig. 7)", fontsize=13)
    fig.savefig(path, dpi=_DPI)
    return path


def _steepness_panel(
    ax_a: Any,
    t: np.ndarray,
    trace: dict[str, np.ndarray],
    params: PlotParams,
    phi_star: np.ndarray | None,
    thresholds: np.ndarray | None,
    has_events: bool,
) -> None:
    """Fig. 7a: phi* per sensor and its maximum, with the thresholds of eq. (7)."""
    phi_max = params.phi_max_rad
    if phi_star is not None and phi_star.ndim == 2 and len(phi_star) == len(t):
        for j in range(phi_star.shape[1]):
            ax_a.plot(
                t,
                phi_star[:, j],
                lw=0.7,
                alpha=0.45,
                zorder=2,
                label="φ*ᵢ per sensor" if j == 0 else None,
            )
    ax_a.plot(t, trace["phi_star_max"], color="black", lw=1.3, zorder=3, label="max φ*ᵢ")
    side_thr = params.side_threshold_rad  # eq. (7), the planner's own function
    thr_values = (
        sorted({round(float(v), 6) for v in np.asarray(thresholds).ravel()})
        if thresholds is not None and np.size(thresholds)
        else sorted({round(phi_max, 6), round(side_thr, 6)})
    )
    if abs(side_thr - phi_max) < 1e-6:
        ax_a.axhline(
            phi_max,
            color="#d7301f",
            ls="--",
            lw=1.1,
            zorder=3,
            label=f"φ_max = side threshold = {phi_max:.3g} rad",
        )
    else:
        ax_a.axhline(
            phi_max,
            color="#d7301f",
            ls="--",
            lw=1.1,
            zorder=3,
            label=f"φ_max = {phi_max:.3g} rad (forward)",
        )
        ax_a.axhline(
            side_thr,
            color="#fc8d59",
            ls="-.",
            lw=1.1,
            zorder=3,
            label=f"min(atan(H_d/D_min), φ_max) = {side_thr:.3g} rad (sides)",
        )
    for v in thr_values:  # any other threshold the planner used
        if min(abs(v - phi_max), abs(v - side_thr)) > 1e-6:
            ax_a.axhline(v, color="0.4", ls=":", lw=1.0, zorder=3, label=f"threshold {v:.3g} rad")
    ymax_a = max(float(np.max(trace["phi_star_max"])) if len(t) else 0.0, phi_max) * 1.15
    ax_a.set_ylim(-0.05 * ymax_a, ymax_a * (1.35 if has_events else 1.0))
    ax_a.set_ylabel("φ* (rad)")
    ax_a.set_title(
        "(a) steepness φ* of what the range sensors see, and the decision", fontsize=10, loc="left"
    )


def _event_lines(
    axes: list[Any], events: list[tuple[float, str]] | None, t0: float, t_end: float
) -> None:
    """The planner's events as vertical lines on every panel, labelled on the first."""
    ax_a = axes[0]
    marks = _event_marks(events, min_gap_s=0.06 * max(t_end - t0, 1e-9))
    if len(marks) > _MAX_EVENT_LINES:  # a flood of events: only the labelled ones
        marks = [m for m in marks if m[1] is not None]
    for te, label in marks:
        for ax in axes:
            ax.axvline(te, color="#6a3d9a", lw=0.7, alpha=0.7 if ax is ax_a else 0.35, zorder=1)
        if label is not None:
            ax_a.annotate(
                label,
                (te, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(2, -3),
                textcoords="offset points",
                rotation=0,
                ha="left",
                va="top",
                fontsize=7.5,
                color="#6a3d9a",
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.7},
                zorder=6,
            )


def _steepness_legend(ax_a: Any, decision: np.ndarray) -> None:
    """Fig. 7a's legend, beside it: its lines and the decisions shaded behind them."""
    from matplotlib.patches import Patch

    h, lab = ax_a.get_legend_handles_labels()
    present = [d for d in ("vertical", "horizontal", "blocked") if np.any(decision == d)]
    h += [Patch(color=_DECISION_COLOURS[d], label=_DECISION_LABELS[d]) for d in present]
    lab += [_DECISION_LABELS[d] for d in present]
    ax_a.legend(h, lab, loc="center left", bbox_to_anchor=(1.005, 0.5), fontsize=8)


def _distance_panel(
    ax_b: Any, t: np.ndarray, trace: dict[str, np.ndarray], params: PlotParams
) -> None:
    """Fig. 7b: min d_i over the obstacle sensors and the true clearance, with D_min."""
    d_min = params.d_min_m
    # Nothing within range is recorded as 0 (or NaN): drawn as a gap, not as a distance.
    min_range = _detected(trace["min_range"])
    clearance = np.asarray(trace["clearance"], dtype=np.float64)
    detected = min_range[np.isfinite(min_range)]
    top_b = max(float(detected.max()) if len(detected) else 0.0, 3.0 * d_min) * 1.15
    ax_b.plot(
        t,
        min_range,
        color="black",
        lw=1.1,
        label="min dᵢ measured (gaps: nothing in range)"
        + (f"\n  smallest {detected.min():.2f} m" if len(detected) else ""),
    )
    finite = np.isfinite(clearance)
    ax_b.plot(
        t,
        np.clip(clearance, 0.0, 2.0 * top_b),
        color="#2166ac",
        lw=1.0,
        ls="--",
        label="true clearance to obstacles"
        + (f"\n  smallest {clearance[finite].min():.2f} m" if finite.any() else ""),
    )
    ax_b.axhline(d_min, color="#d7301f", ls="--", lw=1.1, label=f"D_min = {d_min:g} m")
    if finite.any():
        i = int(np.argmin(np.where(finite, clearance, np.inf)))
        if clearance[i] < top_b:
            ax_b.plot(t[i], clearance[i], "o", color="#2166ac", ms=4)
            ax_b.annotate(
                f"min {clearance[i]:.2f} m",
                (t[i], clearance[i]),
                xytext=(4, -10),
                textcoords="offset points",
                fontsize=8,
                color="#2166ac",
            )
    ax_b.set_ylim(0.0, top_b)
    ax_b.set_ylabel("distance (m)")
    ax_b.set_title(
        "(b) min dᵢ over the obstacle sensors and true clearance", fontsize=10, loc="left"
    )
    ax_b.legend(loc="center left", bbox_to_anchor=(1.005, 0.5), fontsize=8)


def _pitch_panel(
    ax_c: Any, t: np.ndarray, trace: dict[str, np.ndarray], params: PlotParams
) -> None:
    """Fig. 7c: desired pitch phi_d and the vehicle's pitch, with +-phi_max."""
    phi_max = params.phi_max_rad
    ax_c.plot(t, trace["phi_d"], color="black", lw=1.2, label="φ_d (desired pitch)")
    pitch = np.asarray(trace["pitch"], dtype=np.float64)
    ax_c.plot(
        t,
        pitch,
        color="#1b9e77",
        lw=1.0,
        ls="--",
        label="vehicle pitch"
        + (f"\n  max |pitch| {np.max(np.abs(pitch)):.3f} rad" if len(pitch) else ""),
    )
    for sgn in (1.0, -1.0):
        ax_c.axhline(
            sgn * phi_max,
            color="#d7301f",
            ls="--",
            lw=1.1,
            label=f"±φ_max = ±{phi_max:g} rad" if sgn > 0 else None,
        )
    phi_d = np.asarray(trace["phi_d"], dtype=np.float64)
    beyond = np.nan_to_num(np.abs(pitch)) > phi_max + 1e-6
    if beyond.any():
        # The planner bounds phi_d (eq. 4); the airframe's own pitch is the tracker's: a
        # multirotor tilts to accelerate (take-off, catching up with X_d), beyond phi_max.
        max_phi_d = float(np.nanmax(np.abs(phi_d))) if np.isfinite(phi_d).any() else 0.0
        bounded = "stays within" if max_phi_d <= phi_max + 1e-6 else "is NOT within"
        _note(
            ax_c,
            f"vehicle pitch beyond ±φ_max in {float(np.mean(beyond)) * 100:.1f} % of cycles "
            f"(max {float(np.nanmax(np.abs(pitch))):.2f} rad): the autopilot's tracker\n"
            f"tilting the airframe (take-off, accelerating), not the planner; "
            f"φ_d {bounded} ±φ_max",
            0.995,
            0.96,
            va="top",
        )
    pitch_abs = np.abs(pitch[np.isfinite(pitch)])
    pitch_top = 1.2 * phi_max
    if len(pitch_abs):
        pitch_top = max(pitch_top, min(float(pitch_abs.max()) * 1.1, 3.0 * phi_max))
    ax_c.set_ylim(-pitch_top, pitch_top)
    ax_c.set_ylabel("pitch (rad)")
    ax_c.set_title("(c) desired pitch φ_d and vehicle pitch", fontsize=10, loc="left")
    ax_c.legend(loc="center left", bbox_to_anchor=(1.005, 0.5), fontsize=8)


def _height_panel(
    ax_d: Any, t: np.ndarray, trace: dict[str, np.ndarray], params: PlotParams
) -> None:
    """Fig. 7d: height H above the surface, with H_d and its +-0.15 m band."""
    h_d = params.h_d_m
    height = np.asarray(trace["height"], dtype=np.float64)
    ax_d.axhspan(
        h_d - HEIGHT_BAND_M,
        h_d + HEIGHT_BAND_M,
        color="#4393c3",
        alpha=0.2,
        lw=0,
        label=f"H_d ± {HEIGHT_BAND_M:g} m",
    )
    ax_d.axhline(h_d, color="#2166ac", ls="--", lw=1.0, label=f"H_d = {h_d:g} m")
    ax_d.plot(t, height, color="black", lw=1.1, label="H (shortest distance to surface)")
    # Zoom on the band once settled; say so if the approach from the start height is cut.
    settled = np.flatnonzero(np.abs(height - h_d) <= HEIGHT_BAND_M)
    lo, hi = h_d - 2.5 * HEIGHT_BAND_M, h_d + 2.5 * HEIGHT_BAND_M
    if len(settled):
        after = height[settled[0] :]
        after = after[np.isfinite(after)]
        if len(after):
            lo = min(lo, float(after.min()) - 0.05)
            hi = max(hi, float(after.max()) + 0.05)
        if len(t):
            err = np.abs(after - h_d)
            _note(
                ax_d,
                f"max |H − H_d| after settling (t ≥ {t[settled[0]]:.1f} s): "
                f"{float(err.max()) if len(err) else 0.0:.3f} m",
                0.995,
                0.04,
            )
    finite_h = height[np.isfinite(height)]
    if len(finite_h) and (finite_h.min() < lo or finite_h.max() > hi):
        _note(
            ax_d,
            f"axis clipped: H spans {finite_h.min():.2f}…{finite_h.max():.2f} m",
            0.995,
            0.96,
            va="top",
        )
    ax_d.set_ylim(lo, hi)
    ax_d.set_ylabel("H (m)")
    ax_d.set_title("(d) height H above the surface", fontsize=10, loc="left")
    ax_d.legend(loc="center left", bbox_to_anchor=(1.005, 0.5), fontsize=8)


def _speed_panel(
    ax_e: Any, t: np.ndarray, trace: dict[str, np.ndarray], params: PlotParams
) -> None:
    """Fig. 7e: speed of the reference point X_d, with the reference speed and v_d."""
    v_d = params.v_d_mps
    speed = np.asarray(trace["speed_xd"], dtype=np.float64)
    speed_err = np.abs(speed - np.asarray(trace["speed_ref"], dtype=np.float64))
    ax_e.plot(
        t,
        speed,
        color="black",
        lw=1.1,
        label="speed of X_d"
        + (f"\n  max |v − v_ref| {speed_err.max():.3f} m/s" if len(speed) else ""),
    )
    ax_e.plot(t, trace["speed_ref"], color="#e6550d", lw=1.0, ls="--", label="reference speed")
    ax_e.axhline(v_d, color="#2166ac", ls=":", lw=1.1, label=f"v_d = {v_d:g} m/s")
    ax_e.set_ylim(0.0, 1.25 * max(v_d, float(np.max(speed)) if len(speed) else v_d))
    ax_e.set_ylabel("speed (m/s)")
    ax_e.set_xlabel("time t (s)")
    ax_e.set_title("(e) speed of the reference point X_d", fontsize=10, loc="left")
    ax_e.legend(loc="center left", bbox_to_anchor=(1.005, 0.5), fontsize=8)


def write_figures(
    out_dir: Path,
    world: World,
    route: Route,
    trace: dict[str, np.ndarray],
    params: PlotParams,
    phi_star: np.ndarray | None = None,
    thresholds: np.ndarray | None = None,
    memory_xy: np.ndarray | None = None,
    events: list[tuple[float, str]] | None = None,
    title: str = "",
) -> list[Path]:
    """Write out_dir/fig6.png and out_dir/fig7.png of one run; return their paths.

    trace: columns of `harness.closed_loop.TRACE_COLUMNS` (one row per cycle); phi_star
    (cycles, obstacle sensors) and thresholds (obstacle sensors) in radians; memory_xy (n, 2)
    remembered obstacle points; events (t, text). RuntimeError if matplotlib (the `plots`
    extra) is not installed.
    """
    if not isinstance(params, PlotParams):
        raise TypeError(f"params must be a PlotParams, got {type(params).__name__}")
    Figure = _import_matplotlib()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [
        _fig6(Figure, out / "fig6.png", world, route, trace, params, memory_xy, title),
        _fig7(Figure, out / "fig7.png", trace, params, phi_star, thresholds, events, title),
    ]
