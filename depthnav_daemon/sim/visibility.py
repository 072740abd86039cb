"""What the sensors can see of a synthetic scene: the geometry behind the safety contract's truth
(sim.contract states the rules and judges the outputs with them).

Truth comes from the outlines only, sampled every SAMPLE_STEP_M (each sample to the next is a
segment): boxes (heights inside the scan band) and holes (drop-off edges). Per sensor and sample:

- *in view* (a box): at some of its band heights it lies on a pixel row the scan reads (a row
  centre) inside the image's columns, within the sensor's depth range; *visible*: in view with no
  box nearer on that camera ray (the finite truth). *Floor seen*: its floor point (z = 0)
  projects into the rows and columns the scan reads. A table top (a box above the floor) whose
  floor is seen but whose band body lies wholly outside the rows and columns read (above the top
  row, or beside the image where a tilted camera's sides lean out) is an *overhang*.
- a drop-off edge: a sample of a hole's outline where the camera's ray enters the hole (a near
  edge) of a hole deeper than the cliff's ground margin. *Floor seen*: its floor point projects
  into the cliff stage's blocks, within the cliff's range_max. *Below resolution*: floor seen, but
  the ray a block and a sample stride of rows above the edge's row (what a block needs to fill)
  no longer drops the ground margin (and the noise model's sigmas, CliffParams) inside the hole:
  the hole's extent along the ray is below the stage's resolution there. *In view*: floor seen,
  not below resolution and a block plus a stride below the blocks' top; *visible*: in view and
  no box hides it.
- *dead*: its floor point projects below the lowest row the stage reads, or lies nearer the
  camera's foot than where the bottom row read meets the floor (the lower dead zone; behind the
  camera only the latter). *Covered*: in view or floor seen. Neither *in view* nor *floor seen*
  asks whether a box hides the point (floor a box hides was not read either); *visible* does.

The +inf truth (*claim*) of the sensor's own scans: in view or floor seen, except overhangs and
below-resolution edges (each reported apart); base-frame and merged outputs also claim what no
sensor covered outside every sensor's dead zone (the base ray's part beside, behind or past the
view). The camera model is written here from the conventions (drivers.base, pipeline.geometry
docstrings: camera x right, y down, z forward, pixel centres at integers, tilt positive down, roll
positive left side up, yaw counter-clockwise), not taken from the stages; which rows a stage reads
is configuration (scan_table.scan_rows, CliffParams).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depthnav_daemon.pipeline.geometry import Mount
from depthnav_daemon.pipeline.params import CliffParams, ScanParams
from depthnav_daemon.pipeline.scan_table import scan_rows
from depthnav_daemon.sim.synthetic import Scene, sensor_world_pose
from depthnav_daemon.sim.truth import slab
from depthnav_daemon.sim.worlds import perimeter, rect_of
from drivers.base import Intrinsics

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]
Layout = tuple[float, float, int]  # angle_min rad, increment rad, bins
Origin = tuple[float, float, float]  # x, y, yaw of the frame bearings are measured in
SAMPLE_STEP_M = 0.01
SENSOR_DEPTH_M = (0.35, 8.0)  # optical depth the simulated sensor reads (synthetic.render)
Z_LEVELS = 6  # heights tried per sample for occlusion
NEAR_EDGE_M = 0.015  # an edge sample this close to where its ray enters the hole is a near edge
EPS = 1e-9
TURN_M2 = 1e-12  # cross product of two outline steps (m^2) at a corner (steps ~1 cm: ~1e-4)
FAR_M = 100.0  # beyond every world


@dataclass(frozen=True, slots=True)
class Boundary:
    """Outline samples: world points (N, 2), the next sample on the same outline (N,), drop-off
    edge or box (N,), height span inside the scan band (N,) m (edges 0), box or hole index,
    whether a box stands above the floor (a table top: ``raised``), and the side of its outline
    each sample lies on: the side's two corners (N, 2, 2) (a sample at a corner starts its side)."""

    xy: F64
    nxt: npt.NDArray[np.int64]
    edge: B
    z_lo: F64
    z_hi: F64
    owner: npt.NDArray[np.int64]
    raised: B
    side: F64


def boundary(scene: Scene, scan: ScanParams, step_m: float = SAMPLE_STEP_M) -> Boundary:
    """Sample every box outline whose height span meets the scan band, and every hole outline."""
    parts: list[tuple[F64, bool, float, float, int, bool]] = []
    for i, b in enumerate(scene.boxes):
        lo, hi = max(b.base_m, scan.min_obstacle_height_m), min(b.top_m, scan.max_obstacle_height_m)
        if lo <= hi:
            parts.append((perimeter(rect_of(b), step_m), False, lo, hi, i, b.base_m > 0))
    holes = enumerate(scene.holes)
    parts += [(perimeter(rect_of(h), step_m), True, 0.0, 0.0, i, False) for i, h in holes]
    sizes = np.array([len(p[0]) for p in parts], dtype=np.int64)
    start = np.repeat(np.cumsum(sizes) - sizes, sizes)
    idx = np.arange(int(sizes.sum()))
    nxt = start + (idx - start + 1) % np.repeat(sizes, sizes)
    col = [np.repeat(np.array([p[k] for p in parts]), sizes) for k in range(1, 6)]
    xy = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 2))
    edge, raised = col[0].astype(bool), col[4].astype(bool)
    side = np.concatenate([_sides(p[0]) for p in parts]) if parts else np.zeros((0, 2, 2))
    return Boundary(
        xy, nxt, edge, col[1] * 1.0, col[2] * 1.0, col[3].astype(np.int64), raised, side
    )


def _sides(outline: F64) -> F64:
    """Per sample of a rectangle's outline (perimeter: corners included, in order), the corners
    (N, 2, 2) of the side it lies on: the samples from one corner up to the next."""
    d = np.diff(np.concatenate([outline, outline[:1]]), axis=0)
    turn = np.abs(d[:, 0] * np.roll(d, 1, 0)[:, 1] - d[:, 1] * np.roll(d, 1, 0)[:, 0]) > TURN_M2
    corners = np.flatnonzero(turn)  # the samples where the outline turns: its corners
    k = np.searchsorted(corners, np.arange(len(outline)), side="right") - 1  # -1: before the first
    start = outline[corners[k % len(corners)]]
    end = outline[corners[(k + 1) % len(corners)]]
    return np.stack([start, end], axis=1)


@dataclass(frozen=True, slots=True)
class Camera:
    """A pinhole at a world pose: foot (x, y) m, yaw rad, height h m, tilt (down) and roll (left
    side up) rad. Camera frame: x right, y down, z forward; pixel centres at integers."""

    x: float
    y: float
    yaw: float
    h: float
    tilt: float
    roll: float
    intr: Intrinsics

    @classmethod
    def at(cls, mount: Mount, intr: Intrinsics, pose: Origin) -> Camera:
        """The camera of ``mount`` on a robot at ``pose`` (x, y, yaw in the world)."""
        x, y, yaw = sensor_world_pose(mount, pose)
        return cls(x, y, yaw, mount.height_m, mount.tilt_rad, mount.roll_rad, intr)

    @property
    def origin(self) -> Origin:
        return self.x, self.y, self.yaw

    def axes(self) -> tuple[F64, F64]:
        """The camera's x, y, z axes as rows in the level frame's (forward, left, up) (3, 3)
        (pitched down about left, then rolled about forward), and their signs."""
        st, ct = math.sin(self.tilt), math.cos(self.tilt)
        sr, cr = math.sin(self.roll), math.cos(self.roll)
        a = np.array([(sr * st, cr, sr * ct), (cr * st, -sr, cr * ct), (ct, 0.0, -st)])
        return a, np.array([-1.0, -1.0, 1.0])

    def linear(self, xy: F64) -> list[tuple[F64, float]]:
        """Camera x, y, z of the points above ``xy`` (N, 2) as (a (N,), b): a + b z_world."""
        dx, dy = xy[:, 0] - self.x, xy[:, 1] - self.y
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        fwd, left = c * dx + s * dy, -s * dx + c * dy
        a, g = self.axes()
        return [
            (g[k] * (a[k, 0] * fwd + a[k, 1] * left - a[k, 2] * self.h), g[k] * a[k, 2])
            for k in range(3)
        ]

    def level_dirs(self, u: F64, v: F64) -> F64:
        """Level-frame (forward, left, up) (3, ...) of the rays through pixel coordinates u, v
        (broadcast together), per unit of camera z."""
        i = self.intr
        cam = np.stack(np.broadcast_arrays((u - i.cx) / i.fx, (v - i.cy) / i.fy, 1.0))
        a, g = self.axes()
        return np.tensordot(a.T, cam * g.reshape((3,) + (1,) * (cam.ndim - 1)), axes=1)

    def nearest_floor(self, row: float, cols: tuple[float, float]) -> float:
        """The nearest floor range from the camera's foot that pixel row ``row`` sees within
        ``cols`` (where the bottom row read meets the floor), m; +inf if none looks down."""
        fwd, left, up = self.level_dirs(np.arange(cols[0], cols[1] + 1.0), np.float64(row))
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(up < 0, self.h * np.hypot(fwd, left) / -up, np.inf)
        return float(r.min(initial=np.inf))

    def window(
        self, xy: F64, z_lo: F64, z_hi: F64, rows: Sequence[float], cols: Sequence[float]
    ) -> tuple[F64, F64]:
        """Heights [lo, hi] (N,) of the vertical segments above ``xy`` (z_lo..z_hi) that project
        within pixel rows/cols (inclusive) and the sensor's depth range; lo > hi: none."""
        (xa, xb), (ya, yb), (za, zb) = self.linear(xy)
        i = self.intr
        lo, hi = np.array(z_lo, dtype=float), np.array(z_hi, dtype=float)
        for g0, g1 in (  # g0 + g1 z >= 0
            (za - SENSOR_DEPTH_M[0], zb),
            (SENSOR_DEPTH_M[1] - za, -zb),
            (i.fx * xa + (i.cx - cols[0]) * za, i.fx * xb + (i.cx - cols[0]) * zb),
            ((cols[1] - i.cx) * za - i.fx * xa, (cols[1] - i.cx) * zb - i.fx * xb),
            (i.fy * ya + (i.cy - rows[0]) * za, i.fy * yb + (i.cy - rows[0]) * zb),
            ((rows[1] - i.cy) * za - i.fy * ya, (rows[1] - i.cy) * zb - i.fy * yb),
        ):
            if g1 > 0:
                lo = np.maximum(lo, -g0 / g1)
            elif g1 < 0:
                hi = np.minimum(hi, -g0 / g1)
            else:
                hi = np.where(g0 < 0, -np.inf, hi)
        return lo, hi

    def rows_at(self, xy: F64, z: F64) -> F64:
        """Image row (N,) of the points at heights z (N,) above ``xy``; -inf behind the camera."""
        _, (ya, yb), (za, zb) = self.linear(xy)
        depth = za + zb * z
        with np.errstate(divide="ignore", invalid="ignore"):
            v = self.intr.fy * (ya + yb * z) / depth + self.intr.cy
        return np.where(depth > EPS, v, -np.inf)

    def height_at_row(self, xy: F64, v: F64) -> F64:
        """Height (N, L) above ``xy`` (N, 2) that projects to image rows v (N, L)."""
        _, (ya, yb), (za, zb) = self.linear(xy)
        f, c = self.intr.fy, self.intr.cy
        return -(f * ya[:, None] + (c - v) * za[:, None]) / (f * yb + (c - v) * zb)

    def floor_row(self, xy: F64) -> F64:
        """Image row (N,) of the floor points ``xy``; +inf behind the camera."""
        _, (ya, _), (za, _) = self.linear(xy)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(za > EPS, self.intr.fy * ya / za + self.intr.cy, np.inf)


def _spans(items: Sequence, origin: Sequence[float], d: F64) -> tuple[F64, F64]:
    """Entry and exit (N, K) m of the 2-D rays from ``origin`` along unit ``d`` (N, 2) through
    the footprints of K boxes or holes; entry > exit: a miss."""
    t_in, t_out = np.empty((len(d), len(items))), np.empty((len(d), len(items)))
    for k, item in enumerate(items):
        cx, cy, length, width, yaw = rect_of(item)
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = origin[0] - cx, origin[1] - cy
        o = np.array([c * dx + s * dy, -s * dx + c * dy])
        dl = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)
        half = np.array([length / 2, width / 2])
        t_in[:, k], t_out[:, k] = slab(o[None, :], dl, -half, half)
    return t_in, t_out


def _unhidden(scene: Scene, cam: Camera, xy: F64, r: F64, z: F64) -> B:
    """Whether, at some of the heights z (N, L), the camera ray to the points xy (N, 2) at
    horizontal range r (N,) passes no box before reaching them (N,)."""
    if not scene.boxes or not len(xy):
        return np.ones(len(xy), bool)
    t_in, t_out = _spans(scene.boxes, (cam.x, cam.y), (xy - [cam.x, cam.y]) / r[:, None])
    r_in, r_end = np.maximum(t_in, 0.0), np.minimum(t_out, r[:, None] - 2e-3)
    hit = ((t_in <= t_out) & (r_in < r_end))[:, :, None]
    a1 = np.maximum(r_in / r[:, None], EPS)[:, :, None]  # share of the way at entry and exit
    a2 = np.maximum(r_end / r[:, None], EPS)[:, :, None]
    base = np.array([b.base_m for b in scene.boxes])[None, :, None] - cam.h
    top = np.array([b.top_m for b in scene.boxes])[None, :, None] - cam.h
    # the ray's heights over [entry, exit] meet [base, top] iff z lies in [zb1, zb2]
    zb1 = cam.h + np.minimum(base / a1, base / a2)
    zb2 = cam.h + np.maximum(top / a1, top / a2)
    zz = z[:, None, :]
    blocked = (hit & (zz >= zb1) & (zz <= zb2)).any(axis=1)  # (N, L)
    return ~blocked.all(axis=1)


@dataclass(frozen=True, slots=True)
class Sight:
    """One sensor's view of the outline samples at one pose (N,) each (module docstring):
    ``visible`` (the finite truth), ``claim`` (the +inf truth of its own scans), ``overhang``,
    ``below`` (resolution), ``covered``, ``dead``, ``drop`` (a box, or a near edge of a hole
    deeper than the margin: what the contract speaks of), ``seen`` (visible within the stage's
    range limits: what the memory may keep), ``subpixel`` (in view and unhidden, but inside a
    side seen edge-on: below pixel resolution, so not in ``visible``)."""

    visible: B
    claim: B
    overhang: B
    below: B
    covered: B
    dead: B
    drop: B
    seen: B
    subpixel: B


def sight(bd: Boundary, scene: Scene, cam: Camera, scan: ScanParams, cliff: CliffParams) -> Sight:
    """The module docstring's rules for one sensor's scan and cliff stage."""
    i, n, box = cam.intr, len(bd.xy), ~bd.edge
    r = np.hypot(bd.xy[:, 0] - cam.x, bd.xy[:, 1] - cam.y)
    rows = scan_rows(i, scan)
    last, cols = min(rows.stop, i.height) - 1, (0, i.width - 1)
    lo, hi = cam.window(bd.xy, bd.z_lo, bd.z_hi, (rows.start, last), cols)
    step = rows.step or 1
    with np.errstate(invalid="ignore"):  # the rows a pixel row of the stage reads falls in
        v = np.sort(np.stack([cam.rows_at(bd.xy, lo), cam.rows_at(bd.xy, hi)]), axis=0)
        k0, k1 = np.ceil((v[0] - rows.start) / step), np.floor((v[1] - rows.start) / step)
    inview = box & (lo <= hi) & (k0 <= k1)
    zero = np.zeros(n)
    flo, fhi = cam.window(bd.xy, zero, zero, (rows.start, last), cols)
    floor = box & (flo <= fhi)
    over = bd.raised & floor & (lo > hi)  # a raised body wholly outside the view (top or sides)
    fr = cam.floor_row(bd.xy)
    dead = (np.isfinite(fr) & (fr > last)) | (r < cam.nearest_floor(last, cols))
    visible, subpixel = _box_visibility(bd, scene, cam, inview, r, (k0, k1), rows, scan)
    seen = visible & (r >= scan.range_min_m) & (r <= scan.range_max_m)
    claim, below, covered, drop = inview | (floor & ~over), np.zeros(n, bool), inview | floor, box

    e = np.flatnonzero(bd.edge)
    bs = cliff.block_size
    top = i.height - min(cliff.used_depth_height, i.height) // bs * bs  # first row of the blocks
    blocks, cols = (top, i.height - 1), (0, i.width // bs * bs - 1)
    t_in, t_out = _spans(scene.holes, (cam.x, cam.y), (bd.xy[e] - [cam.x, cam.y]) / r[e, None])
    pick = (np.arange(len(e)), bd.owner[e])
    m = cliff.ground_margin_m
    deep = np.array([h.depth_m > m for h in scene.holes] or [False])[bd.owner[e]]
    drop[e] = deep & (np.abs(t_in[pick] - r[e]) < NEAR_EDGE_M)
    lo, hi = cam.window(bd.xy[e], zero[e], zero[e], blocks, cols)
    cover = drop[e] & (lo <= hi) & (r[e] <= cliff.range_max_m)
    # the ray a block and a stride of rows above the edge's row still drops the margin in the hole
    q = np.flatnonzero(cover)
    d = (bd.xy[e[q]] - [cam.x, cam.y]) / r[e[q], None]
    up = cam.floor_row(bd.xy[e[q]]) - bs - cliff.row_step
    fine = np.zeros(len(e), bool)
    fr_up = _floor_range_at_row(cam, d, up, r[e[q]])
    # the stage's own resolution: beyond the floor by the margin's height and by its noise
    # model's sigmas at the floor's optical depth (CliffParams: depth > t + n k t^2)
    zc = cam.linear(np.array([[cam.x, cam.y]]) + d * np.minimum(fr_up, FAR_M)[:, None])[2][0]
    noise = cliff.noise_sigmas * cliff.depth_noise_k * np.maximum(zc, 0.0)
    fine[q] = t_out[pick][q] >= fr_up * np.maximum(1 + m / cam.h, 1 + noise)
    ok = fine & (cam.floor_row(bd.xy[e]) >= top + bs + cliff.row_step)
    ev = np.zeros(len(e), bool)
    ev[ok] = _unhidden(scene, cam, bd.xy[e[ok]], r[e[ok]], zero[e][ok, None])
    visible[e], seen[e], covered[e] = ev, ev & (r[e] >= cliff.range_min_m), cover
    claim[e], below[e] = cover & fine, cover & ~fine
    fr = cam.floor_row(bd.xy[e])
    near = cam.nearest_floor(i.height - 1, cols)
    dead[e] = (np.isfinite(fr) & (fr > i.height - 1)) | (r[e] < near)
    return Sight(visible, claim, over, below, covered, dead, drop, seen, subpixel)


def _box_visibility(
    bd: Boundary,
    scene: Scene,
    cam: Camera,
    inview: B,
    r: F64,
    k: tuple[F64, F64],
    rows: range,
    scan: ScanParams,
) -> tuple[B, B]:
    """(N,) each: the samples in view that no box hides at some of the pixel rows the stage
    reads between the first and last (``k``: indices into ``rows``) their band falls in, but
    those of sides seen edge-on; and those."""
    visible = np.zeros(len(bd.xy), bool)
    q = np.flatnonzero(inview)
    k0, k1 = k[0][q, None], k[1][q, None]
    at = rows.start + (rows.step or 1) * np.round(k0 + (k1 - k0) * np.linspace(0, 1, Z_LEVELS))
    visible[q] = _unhidden(scene, cam, bd.xy[q], r[q], cam.height_at_row(bd.xy[q], at))
    sub = visible & _subpixel_side(bd, cam, rows, scan.col_step)
    return visible & ~sub, sub


def _subpixel_side(bd: Boundary, cam: Camera, rows: range, col_step: int) -> B:
    """Box samples (N,) inside a side of their outline that no row of pixel centres the stage
    reads crosses twice: at most one used pixel centre per row has its level-frame bearing within
    the side's bearing span from the camera. Such a side is seen edge-on: a pixel's centre ray
    meets it at one depth while the side runs along the ray (seed 83: a 0.6 m side within
    0.03 deg), and no stage can tell where along it the rest lies. The side's corners stay (they
    end the sides beside it)."""
    inner = ~bd.edge & np.any(np.abs(bd.side[:, 0] - bd.xy) > EPS, axis=1)
    inner &= np.any(np.abs(bd.side[:, 1] - bd.xy) > EPS, axis=1)
    if not inner.any():
        return inner
    i = cam.intr
    v = np.arange(rows.start, min(rows.stop, i.height), rows.step or 1, dtype=float)
    u = np.arange(0, i.width, col_step, dtype=float)
    fwd, left, _ = cam.level_dirs(u[None, :], v[:, None])
    beta = np.sort(np.arctan2(left, fwd), axis=1)  # (rows, cols) level bearings, ascending
    sides, inv = np.unique(bd.side[inner].reshape(-1, 4), axis=0, return_inverse=True)
    ends = [
        np.arctan2(sides[:, 2 * k + 1] - cam.y, sides[:, 2 * k] - cam.x) - cam.yaw for k in (0, 1)
    ]
    lo = np.remainder(ends[0] + np.pi, 2 * np.pi) - np.pi
    hi = lo + np.remainder(ends[1] - ends[0] + np.pi, 2 * np.pi) - np.pi
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    most = np.zeros(len(sides), np.int64)
    for row in beta:  # bearings round the back of the camera do not fall in any row's span
        most = np.maximum(most, np.searchsorted(row, hi, "right") - np.searchsorted(row, lo))
    out = np.zeros(len(bd.xy), bool)
    out[np.flatnonzero(inner)] = (most <= 1)[inv.reshape(-1)]
    return out


def _floor_range_at_row(cam: Camera, d: F64, v: F64, r0: F64) -> F64:
    """Range (N,) from the camera's foot along unit directions d (N, 2), beyond r0 (N,), of the
    floor point that projects to image row v (N,); FAR_M where the row is beyond the horizon.
    The camera y and z of the floor point at range t are affine in t: row = v solves linearly."""
    foot = np.array([[cam.x, cam.y]])
    (_, (y0, _), (z0, _)), (_, (y1, _), (z1, _)) = cam.linear(foot), cam.linear(foot + d)
    y1, z1, c = y1 - y0, z1 - z0, v - cam.intr.cy
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (c * z0 - cam.intr.fy * y0) / (cam.intr.fy * y1 - c * z1)
    ok = (t >= r0 - 1e-9) & (z0 + z1 * t > EPS)
    return np.where(ok, np.maximum(t, r0), FAR_M)


@dataclass(frozen=True, slots=True)
class Claims:
    """Sample masks (N,) an output is judged with (sim.contract builds them per output):
    ``visible`` (its finite truth), ``claim`` (its +inf truth), and what +inf may lie over without
    being unsafe, each reported apart: ``overhang``, ``below`` (resolution), ``cleared`` (the
    memory's seen table tops), ``blind`` (the memory's blind disc; None: none); ``subpixel``:
    sides seen edge-on, not in ``visible`` (a finite range beyond them is reported apart)."""

    visible: B
    claim: B
    overhang: B
    below: B
    cleared: B
    blind: B | None = None
    subpixel: B | None = None


def segment_bins(b0: F64, b1: F64, r0: F64, r1: F64, layout: Layout) -> tuple[F64, ...]:
    """Which bins segments from bearing b0, range r0 to b1, r1 (N,) (rad, m) fall in: segment
    index, bin, and the nearest range (the range interpolated in bearing across a bin's share of
    the segment) (M,) each."""
    a0, inc, n = layout
    mid = a0 + (n - 1) * inc / 2
    b0 = np.remainder(b0 - mid + math.pi, 2 * math.pi) - math.pi + mid - a0
    b1 = b0 + np.remainder(b1 - (b0 + a0) + math.pi, 2 * math.pi) - math.pi
    lo, hi = np.minimum(b0, b1), np.maximum(b0, b1)
    r_lo, r_hi = np.where(b0 <= b1, r0, r1), np.where(b0 <= b1, r1, r0)
    slope = (r_hi - r_lo) / np.maximum(hi - lo, EPS)
    first = np.ceil(lo / inc - 0.5).astype(np.int64)
    last = np.floor(hi / inc + 0.5).astype(np.int64)
    full = n * inc >= 2 * math.pi - 1e-6
    out: list[tuple[F64, ...]] = []
    for o in range(int(min((last - first).max(initial=0), 64)) + 1):
        k = first + o
        ok = (k <= last) & (full | ((k >= 0) & (k < n)))
        a, z = np.maximum(lo, (k - 0.5) * inc), np.minimum(hi, (k + 0.5) * inc)
        val = r_lo + slope * np.where(slope >= 0, a - lo, z - lo)  # the nearer clipped end
        out.append((np.flatnonzero(ok), k[ok] % n, val[ok]))
    return tuple(np.concatenate(c) if out else np.zeros(0) for c in zip(*out, strict=True))


@dataclass(frozen=True, slots=True)
class Truth:
    """Per bin (n,) m, +inf none: the nearest visible obstacle and edge (finite check), the
    nearest claimed point (+inf check), the nearest of all (reports), and the nearest point of
    each kind +inf may lie over (Claims; ``blind`` None: no such kind), and the nearest side
    seen edge-on (``subpixel``)."""

    visible: F64
    visible_edge: F64
    claim: F64
    any: F64
    overhang: F64
    below: F64
    cleared: F64
    blind: F64 | None = None
    subpixel: F64 | None = None


def truth(bd: Boundary, c: Claims, origin: Origin, layout: Layout, kinds: B | None = None) -> Truth:
    """Bin the outline seen from ``origin`` with the sample masks ``c``; ``kinds`` keeps only some
    samples (e.g. ``bd.edge`` for a cliff scan; None: all). A segment is visible if both its ends
    are, claimed if both are (else its claimed end is), of a reported kind if either is."""
    d = bd.xy - origin[:2]
    rng, bearing = np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0]) - origin[2]
    keep = np.flatnonzero(np.ones(len(rng), bool) if kinds is None else kinds)
    j = bd.nxt[keep]
    seg, k, val = segment_bins(bearing[keep], bearing[j], rng[keep], rng[j], layout)
    seg, k = seg.astype(np.int64), k.astype(np.int64)

    def nearest(mask: B) -> F64:
        out = np.full(layout[2], np.inf)
        sel = mask[seg]
        np.minimum.at(out, k[sel], val[sel])
        return out

    def either(m: B) -> F64:
        return nearest(m[keep] | m[j])

    # a segment with one end claimed and one not crosses the claim's border somewhere between
    # its samples (SAMPLE_STEP_M apart): only its claimed end is claimed (the whole segment,
    # its unclaimed end's range included, would claim what the view did not cover)
    pb, pk, pv = segment_bins(bearing[keep], bearing[keep], rng[keep], rng[keep], layout)
    pb, pk = pb.astype(np.int64), pk.astype(np.int64)

    def claimed(m: B) -> F64:
        out = nearest(m[keep] & m[j])
        sel = m[keep][pb]
        np.minimum.at(out, pk[sel], pv[sel])
        return out

    return Truth(
        nearest(c.visible[keep] & c.visible[j] & ~bd.edge[keep]),
        nearest(c.visible[keep] & c.visible[j] & bd.edge[keep]),
        claimed(c.claim),
        nearest(np.ones(len(keep), bool)),
        either(c.overhang),
        either(c.below),
        either(c.cleared),
        None if c.blind is None else either(c.blind),
        None if c.subpixel is None else either(c.subpixel),
    )
