"""Raster acceleration of the distance queries: float32 samples of a height function in
blocks with their maxima (a two-level branch-and-bound nearest-solid search), and the local
refinement of a raster hit on the analytic height function. World ENU, metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.planner.types import FloatArray
from companion.sim.world.features import BBox, HeightFn

BoxedHeightFn = Callable[[FloatArray, FloatArray, BBox], FloatArray]
"""A height function also given its points' bounding box (xmin, xmax, ymin, ymax)."""


class Raster:
    """float32 samples of a height function on a regular grid, for nearest-solid searches.

    Grid point (ix, iy) is at (x0 + ix*cell, y0 + iy*cell); -inf marks "no solid". Samples
    are stored in B x B blocks with each block's maximum, for a two-level branch-and-bound
    search: a block can hold the nearest point only if its lower bound beats the best
    upper bound (the distance to the block's highest sample, or one given).
    """

    B = 8

    def __init__(
        self, bbox: BBox, cell: float, fn: HeightFn, boxed: BoxedHeightFn | None = None
    ) -> None:
        """fn(x, y): the heights, evaluated over rows of the grid at once. boxed: the same
        function given the bounding box fn would measure; if given, blocks are sampled
        when a search first needs them (`_ensure`), bit for bit as the whole grid would."""
        B = self.B
        # Grid points on multiples of the cell, covering bbox.
        self.x0 = math.floor(bbox[0] / cell) * cell
        self.y0 = math.floor(bbox[2] / cell) * cell
        bbox = (
            self.x0,
            math.ceil(bbox[1] / cell) * cell,
            self.y0,
            math.ceil(bbox[3] / cell) * cell,
        )
        self.cell = cell
        self.nx = round((bbox[1] - bbox[0]) / cell) + 1
        self.ny = round((bbox[3] - bbox[2]) / cell) + 1
        self.x1 = self.x0 + (self.nx - 1) * cell
        self.y1 = self.y0 + (self.ny - 1) * cell
        self.nbx, self.nby = -(-self.nx // B), -(-self.ny // B)
        self._xs = self.x0 + np.arange(self.nx, dtype=np.float64) * cell
        self._rows = max(1, 1_000_000 // self.nx)  # grid rows per evaluation of fn
        span = B * cell
        self.brx0 = self.x0 + np.arange(self.nbx, dtype=np.float64)[None, :] * span
        self.bry0 = self.y0 + np.arange(self.nby, dtype=np.float64)[:, None] * span
        self.brx0, self.bry0 = np.broadcast_arrays(self.brx0, self.bry0)
        self.offs = np.arange(B, dtype=np.float64) * cell
        self._boxed = boxed
        self._ne: tuple[NDArray[np.floating[Any]], ...] | None = None
        if boxed is not None:
            self.zb = np.full((self.nby, self.nbx, B, B), -np.inf, dtype=np.float32)
            self.bmax = np.full((self.nby, self.nbx), -np.inf)
            self.ax = self.brx0.copy()
            self.ay = self.bry0.copy()
            t = self.TILE
            self._tiles = np.zeros((-(-self.nby // t), -(-self.nbx // t)), dtype=bool)
            return
        z = np.full((self.nby * B, self.nbx * B), -np.inf, dtype=np.float32)
        xs = self._xs
        for r0 in range(0, self.ny, self._rows):
            r1 = min(self.ny, r0 + self._rows)
            ys = self.y0 + np.arange(r0, r1, dtype=np.float64) * cell
            z[r0:r1, : self.nx] = fn(xs[None, :], ys[:, None])
        # Block-major copy: zb[by, bx] is the B x B block (rows y, cols x).
        self.zb = np.ascontiguousarray(z.reshape(self.nby, B, self.nbx, B).transpose(0, 2, 1, 3))
        flat = self.zb.reshape(self.nby, self.nbx, B * B)
        arg = np.argmax(flat, axis=2)
        self.bmax = np.take_along_axis(flat, arg[..., None], axis=2)[..., 0].astype(np.float64)
        self.ax = self.brx0 + (arg % B) * cell
        self.ay = self.bry0 + (arg // B) * cell

    TILE = 16
    """A lazy raster samples TILE x TILE blocks at a time (a few metres a side)."""

    @property
    def built_blocks(self) -> NDArray[np.bool_]:
        """(nby, nbx): the blocks sampled so far."""
        if self._boxed is None:
            return np.ones((self.nby, self.nbx), dtype=bool)
        t = self.TILE
        full = np.repeat(np.repeat(self._tiles, t, axis=0), t, axis=1)
        return full[: self.nby, : self.nbx]

    def _ensure(self, by0: int, by1: int, bx0: int, bx1: int) -> None:
        """Sample the tiles that hold blocks [by0, by1) x [bx0, bx1), if not yet (a lazy
        raster)."""
        if self._boxed is None:
            return
        t = self.TILE
        ty0, ty1, tx0, tx1 = by0 // t, (by1 - 1) // t + 1, bx0 // t, (bx1 - 1) // t + 1
        if self._tiles[ty0:ty1, tx0:tx1].all():
            return
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                if not self._tiles[ty, tx]:
                    self._sample(
                        ty * t, min(ty * t + t, self.nby), tx * t, min(tx * t + t, self.nbx)
                    )
                    self._tiles[ty, tx] = True

    def _sample(self, by0: int, by1: int, bx0: int, bx1: int) -> None:
        """Sample blocks [by0, by1) x [bx0, bx1): each row with the features the whole
        grid's evaluation of its rows in __init__ uses (the features meeting those rows'
        box, measured on the whole width), so every sample is the same, bit for bit."""
        assert self._boxed is not None
        B, cell = self.B, self.cell
        nby, nbx = by1 - by0, bx1 - bx0
        i0, i1 = bx0 * B, min(bx1 * B, self.nx)
        z = np.full((nby * B, nbx * B), -np.inf, dtype=np.float32)
        r, end = by0 * B, min(by1 * B, self.ny)
        while r < end:
            k0 = r // self._rows * self._rows  # the rows of __init__'s evaluation
            k1 = min(self.ny, k0 + self._rows)
            ys = self.y0 + np.arange(k0, k1, dtype=np.float64) * cell
            box = (float(self._xs[0]), float(self._xs[-1]), float(ys[0]), float(ys[-1]))
            r1 = min(end, k1)
            seg = ys[r - k0 : r1 - k0]
            z[r - by0 * B : r1 - by0 * B, : i1 - i0] = self._boxed(
                self._xs[None, i0:i1], seg[:, None], box
            )
            r = r1
        w = (slice(by0, by1), slice(bx0, bx1))
        self.zb[w] = z.reshape(nby, B, nbx, B).transpose(0, 2, 1, 3)
        flat = self.zb[w].reshape(nby, nbx, B * B)
        arg = np.argmax(flat, axis=2)
        self.bmax[w] = np.take_along_axis(flat, arg[..., None], axis=2)[..., 0].astype(np.float64)
        self.ax[w] = self.brx0[w] + (arg % B) * cell
        self.ay[w] = self.bry0[w] + (arg // B) * cell

    @property
    def _ne_cols(self) -> tuple[NDArray[np.floating[Any]], ...]:
        """The blocks that hold solid, as `_search`'s columns (samples every block)."""
        if self._ne is None:
            self._ensure(0, self.nby, 0, self.nbx)
            ne = np.nonzero(np.isfinite(self.bmax))
            self._ne = tuple(
                a[ne] for a in (self.brx0, self.bry0, self.bmax, self.ax, self.ay, self.zb)
            )
        return self._ne

    def nearest_sample(self, px: float, py: float, pz: float) -> tuple[float, float, float]:
        """(distance, qx, qy) to the solid under the grid point nearest p_xy (inside)."""
        ix = min(max(round((px - self.x0) / self.cell), 0), self.nx - 1)
        iy = min(max(round((py - self.y0) / self.cell), 0), self.ny - 1)
        B = self.B
        self._ensure(iy // B, iy // B + 1, ix // B, ix // B + 1)
        z = float(self.zb[iy // B, ix // B, iy % B, ix % B])
        qx, qy = self.x0 + ix * self.cell, self.y0 + iy * self.cell
        return math.hypot(qx - px, qy - py, max(pz - z, 0.0)), qx, qy

    def contains(self, px: float, py: float, r: float) -> bool:
        return px - r >= self.x0 and px + r <= self.x1 and py - r >= self.y0 and py + r <= self.y1

    def search_window(self, px: float, py: float, pz: float, r: float) -> Hit:
        """`_search` over the blocks within r (m) of p_xy, horizontally."""
        span = self.B * self.cell
        bx0 = max(0, int((px - r - self.x0) // span))
        bx1 = min(self.nbx, int((px + r - self.x0) // span) + 1)
        by0 = max(0, int((py - r - self.y0) // span))
        by1 = min(self.nby, int((py + r - self.y0) // span) + 1)
        if bx0 >= bx1 or by0 >= by1:
            return NO_HIT
        self._ensure(by0, by1, bx0, bx1)
        w = (slice(by0, by1), slice(bx0, bx1))
        if (by1 - by0) * (bx1 - bx0) <= self.WHOLE_WINDOW_BLOCKS:
            hit = self._search_whole(px, py, pz, r, w)
            if hit is not None:
                return hit
        cols = (self.brx0[w], self.bry0[w], self.bmax[w], self.ax[w], self.ay[w], self.zb[w])
        return self._search(px, py, pz, r, cols)

    WHOLE_WINDOW_BLOCKS = 400
    """`search_window` measures every sample of a window of at most this many blocks (fewer
    array operations than pruning blocks first)."""

    def _search_whole(
        self, px: float, py: float, pz: float, ub: float, w: tuple[slice, slice]
    ) -> Hit | None:
        """`_search` over the blocks w by measuring all their samples: the same nearest
        sample (ties: the first in block order, as `_search` takes them), or None where
        `_search` would have pruned it (farther than its bound: `_search` decides)."""
        rx0 = self.brx0[w][:, :, None, None]
        ry0 = self.bry0[w][:, :, None, None]
        offs = self.offs
        xs = rx0 + offs[None, None, None, :] - px  # (by, bx, 1, B), as _search's
        ys = ry0 + offs[None, None, :, None] - py  # (by, bx, B, 1)
        dz = np.maximum(pz - self.zb[w].astype(np.float64), 0.0)
        d2 = xs * xs + ys * ys + dz**2
        nearest = _nearest(d2, xs, ys)
        if nearest is None:
            return NO_HIT
        best, qx, qy = nearest
        # _search keeps the blocks whose bound is within ub2 (<= ub^2 and <= this sample's
        # block's own bound): this sample is among them if it is within ub^2.
        if not best <= ub * ub:
            return None
        return Hit(math.sqrt(best), qx + px, qy + py)

    def search_all(self, px: float, py: float, pz: float, ub: float) -> Hit:
        """`_search` over every block that holds solid."""
        return self._search(px, py, pz, ub, self._ne_cols)

    def _search(
        self,
        px: float,
        py: float,
        pz: float,
        ub: float,
        cols: tuple[NDArray[np.floating[Any]], ...],
    ) -> Hit:
        """Nearest sample q by sqrt(|q - p_xy|^2 + max(0, pz - z(q))^2) (m), among the
        blocks that can beat ub. cols: per block (any array shape S) origin x, origin y,
        max, argmax x, argmax y and the samples (S + (B, B)).
        """
        rx0, ry0, bmax, ax, ay, zb = cols
        if rx0.size == 0:
            return NO_HIT
        ext = (self.B - 1) * self.cell
        dx = np.maximum(rx0 - px, 0.0) + np.maximum(px - ext - rx0, 0.0)
        dy = np.maximum(ry0 - py, 0.0) + np.maximum(py - ext - ry0, 0.0)
        dz2 = np.maximum(pz - bmax, 0.0) ** 2
        lb2 = dx * dx + dy * dy + dz2
        ub2 = min(ub * ub, float(np.min((ax - px) ** 2 + (ay - py) ** 2 + dz2)))
        if not math.isfinite(ub2):
            return NO_HIT
        keep = lb2 <= ub2 * (1.0 + 1e-9) + 1e-12
        xs = rx0[keep][:, None, None] + self.offs[None, None, :] - px
        ys = ry0[keep][:, None, None] + self.offs[None, :, None] - py
        d2 = xs * xs + ys * ys + np.maximum(pz - zb[keep].astype(np.float64), 0.0) ** 2
        nearest = _nearest(d2, xs, ys)
        if nearest is None:
            return NO_HIT
        best, qx, qy = nearest
        return Hit(math.sqrt(best), qx + px, qy + py)


def _nearest(
    d2: NDArray[np.float64], xs: NDArray[np.float64], ys: NDArray[np.float64]
) -> tuple[float, float, float] | None:
    """The least of the squared distances d2 (the first of equals) and its sample's x and y
    offsets (xs, ys broadcast to d2's shape); None if there is none or it is not finite."""
    if d2.size == 0:
        return None
    k = int(np.argmin(d2))
    best = float(d2.flat[k])
    if not math.isfinite(best):
        return None
    return (
        best,
        float(np.broadcast_to(xs, d2.shape).flat[k]),
        float(np.broadcast_to(ys, d2.shape).flat[k]),
    )


class Hit(NamedTuple):
    """Result of a raster search: distance (m) and the sample's (x, y)."""

    dist: float
    x: float
    y: float


NO_HIT = Hit(math.inf, 0.0, 0.0)


def _grid(n: int) -> tuple[FloatArray, FloatArray]:
    g = np.linspace(-1.0, 1.0, n)
    return np.tile(g, n), np.repeat(g, n)


_GRID_FIRST = _grid(11)
_GRID_NEXT = _grid(9)


def local_min(
    p: tuple[float, float, float],
    qx: float,
    qy: float,
    best: float,
    span: float,
    fn: HeightFn,
    target: float = 0.005,
    max_moves: int = 16,
    boxed: BoxedHeightFn | None = None,
) -> float:
    """Refine min sqrt(|q - p_xy|^2 + max(0, pz - fn(q))^2) (m) around (qx, qy).

    Evaluates fn on square grids of half-width `span` (m) centred on the best point so
    far: while the best point lands near the grid's edge the grid follows it (up to
    max_moves times), otherwise it shrinks, until its step is below `target` (m). The
    first grid also holds p_xy itself; if p is at or below fn there, returns 0. boxed:
    fn given the points' bounding box too (xmin, xmax, ymin, ymax; known here for each
    grid: its corners, and p), used instead of fn if given.
    """
    px, py, pz = p
    gx, gy = _GRID_FIRST
    first = True
    moves = 0
    while True:
        size = gx.size + 1 if first else gx.size
        X = np.empty(size)
        Y = np.empty(size)
        # qx + span g, as (span g) + qx; p_xy last on the first grid
        np.multiply(gx, span, out=X[: gx.size])
        X[: gx.size] += qx
        np.multiply(gy, span, out=Y[: gy.size])
        Y[: gy.size] += qy
        if first:
            X[-1], Y[-1] = px, py
        if boxed is None:
            z = fn(X, Y)
        else:
            # the grid's extremes are its corners (g = -1 and 1: exactly qx -+ span)
            x0, x1, y0, y1 = qx - span, qx + span, qy - span, qy + span
            if first:
                x0, x1, y0, y1 = min(x0, px), max(x1, px), min(y0, py), max(y1, py)
            z = boxed(X, Y, (x0, x1, y0, y1))
        d2 = (X - px) ** 2 + (Y - py) ** 2 + np.maximum(pz - z, 0.0) ** 2
        if first and d2[-1] == 0.0:
            return 0.0
        first = False
        k = int(np.argmin(d2))
        on_edge = False
        if d2[k] < best * best:
            best = math.sqrt(float(d2[k]))
            qx, qy = float(X[k]), float(Y[k])
            # Near the grid's edge: the minimum may lie beyond it (a slanted wall or edge
            # seen through the grid's staircase), so follow it.
            on_edge = k < gx.size and max(abs(gx[k]), abs(gy[k])) >= 0.7
        if on_edge and moves < max_moves:
            moves += 1
            continue
        step = 2.0 * span / (round(math.sqrt(gx.size)) - 1)
        if step <= target:
            return best
        span = step
        gx, gy = _GRID_NEXT
