"""The safety contract of every range depthnav outputs, and its judge, from the scene's geometry.

Per bearing bin [phi - inc/2, phi + inc/2] (REP 117 values), ``sim.visibility`` says what a
sensor sees (geometry only, no stage code) and the judge reads the contract so:

- finite r: unsafe ("far") only if r > truth + err, the truth being the nearest *visible*
  obstacle or drop-off edge on the bin (an outline partly in the bin counts), AND neither
  neighbour bin of the same output (j - 1, j + 1; round the circle for a 360 deg output) holds a
  finite value <= truth + err: the bearing is exact to one bin (an outline ending inside a bin
  between pixel centres may be reported on the neighbour). Such bins are counted ``beside``
  (not unsafe). The same for the memory and the MAVLink sectors (one sector).
- +inf, live outputs (level, base-frame and merged scans and cliff scans, live sectors): unsafe
  if on the bin, within range_max, a sample outside the lower dead zone is in view (the body of a
  box or a drop-off edge the stage reads) OR its floor point (where the ray enters it, z = 0)
  projects into the image rows/cols the stage reads (the sensor saw the floor there: a box
  standing there would have been seen; a box hiding it does not excuse it) OR, for base-frame and
  merged outputs, no sensor's view covered it (the contract says such a bin is NaN). Stated
  exceptions, reported apart, never unsafe: ``overhang`` (a table top, a box above the floor,
  whose band body is outside the view, above its top edge or beside it, while its floor point is
  seen) and
  ``below_resolution`` (a drop-off whose extent along the ray there is below the cliff stage's:
  a block plus a row stride). Any other drop-off edge on floor the cliff rows read makes +inf
  unsafe. The bearing is exact to one bin here too: a +inf bin whose truth (the nearest claimed
  point) a neighbour bin reports (finite <= truth + err, or -inf) is counted ``beside`` (and
  again as ``clear_held``, the table's "(held)"), not unsafe. A truth within the stated error of
  range_max may read beyond it: +inf there is not unsafe (it is counted nowhere). For the memory
  the bearing is exact to one bin plus its odometry's drift seen at the truth's range (heading
  + position / r, in bins, rounded up): its points are where the odometry put them, so a drift
  turns them as much as it moves them (a box corner 1.28 m away read 1.5 bins over with a
  0.015 rad heading drift).
- +inf, the memory (``memory``, ``memory_sectors``): unsafe if anything is on the bin within its
  range_max, except table tops no sensor ever saw (``overhang``), the edges of a hole the cliff
  stage only ever saw below its resolution (``below``: the memory clears what the live cliff scan
  read free, under the live scan's own exception) and what lies nearer the robot
  than the memory's ``blind_m`` (the disc round the base origin it does not judge; the value the
  memory used, pipeline.memory.scan_limits): counted ``blind``. A table top seen before and read
  +inf later is unsafe, but counted apart as ``overhang_cleared`` (the memory may clear it when
  the robot is close and the top is above the view).
- NaN: unknown (always safe); -inf: something nearer than range_min (it must be within
  range_min + 0.05 m, else a "false too-close", counted apart; asserted 0 for the level outputs
  only: in the base frame a sensor's -inf stays -inf though its obstacle may lie up to the
  sensor's offset beyond the base range_min).
The memory's finite truth is every outline sample a sensor has seen so far on the drive (visible
within the stage's range limits), read from the true pose. Stated errors: 0.02 m obstacles,
0.05 m drop-off edges; + k (r^2 + 1) with Kinect-like depth noise (k: 3 sigma of its depth error
+ half its quantisation step); + twice the odometry's drift so far (position + heading x r) and a
cell's diagonal (it keeps one point per cell; coverage is judged without it) for the memory.
Coverage: the share of bins with a visible truth within range_max whose output is within err of
it (all-NaN is safe but useless).

``python -m depthnav_daemon.sim.contract --drives N --seed S`` prints the table per output.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np
import numpy.typing as npt

from depthnav_daemon.daemon.memory_keeper import sensor_view
from depthnav_daemon.pipeline import memory as pm
from depthnav_daemon.pipeline.coverage import floor_extent
from depthnav_daemon.pipeline.laser_scan import LaserScan
from depthnav_daemon.pipeline.memory_io import SensorView
from depthnav_daemon.sim import visibility as vis
from depthnav_daemon.sim.synthetic import KinectNoise
from depthnav_daemon.sim.visibility import F64, B, Claims, truth
from depthnav_daemon.sim.worlds import Case, Step, random_case, run_case, suite_params
from depthnav_daemon.sinks.mavlink.sectors import UNKNOWN, Sectors
from drivers.base import KINECT_V1, Intrinsics

TOO_CLOSE_SLACK_M = 0.05
EXAMPLES = 3  # unsafe frames a tally keeps per kind (far, clear), from as many drives
ERR_OBSTACLE_M, ERR_EDGE_M = 0.02, 0.05


@dataclass
class Counts:
    """The judge's tally for one output (module docstring): unsafe_far, unsafe_clear, beside
    (finite and +inf; clear_held: its +inf ones), overhang, overhang_cleared, below_resolution,
    blind, false_too_close, nan (bins); ``errors``:
    truth - r (m, positive = nearer) of finite bins with a visible truth; ``excess``:
    r - truth - err of the unsafe_far bins."""

    bins: int = 0
    unsafe_far: int = 0
    unsafe_clear: int = 0
    clear_held: int = 0  # of beside: the +inf bins a neighbour bin reports
    beside: int = 0
    overhang: int = 0
    overhang_cleared: int = 0
    below_resolution: int = 0
    blind: int = 0
    subpixel: int = 0  # finite bins beyond a side seen edge-on (narrower than a pixel column)
    false_too_close: int = 0
    nan: int = 0
    with_truth: int = 0
    covered: int = 0
    errors: list[F64] = field(default_factory=list)
    excess: list[F64] = field(default_factory=list)
    examples: list[str] = field(default_factory=list)

    def add(self, other: Counts) -> None:
        """Add ``other``'s tally; examples kept per kind from EXAMPLES different drives."""
        for f in fields(self):
            if f.name != "examples":
                setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))
        for ex in other.examples:
            kind, drive = ex.split()[0], ex.split()[1]
            mine = [e for e in self.examples if e.split()[0] == kind]
            if len(mine) < EXAMPLES and all(e.split()[1] != drive for e in mine):
                self.examples.append(ex)

    @property
    def unsafe(self) -> int:
        return self.unsafe_far + self.unsafe_clear

    @property
    def coverage(self) -> float:
        """Share of bins with a visible truth whose output is within err of it."""
        return self.covered / self.with_truth if self.with_truth else 1.0

    def percentiles(self) -> F64:
        """Safe-side error p50, p95 and max, m (NaN without any)."""
        e = np.concatenate(self.errors) if self.errors else np.zeros(0)
        return np.percentile(e, [50, 95, 100]) if e.size else np.full(3, np.nan)

    def line(self, name: str) -> str:
        x = np.concatenate(self.excess) if self.excess else np.zeros(1)
        p = " ".join(f"{v:6.3f}" for v in self.percentiles())
        counts = (self.unsafe_far, self.unsafe_clear, self.clear_held, self.beside, self.overhang)
        counts += (self.overhang_cleared, self.below_resolution, self.blind, self.subpixel)
        counts += (self.false_too_close,)
        return (
            f"{name:<15}{self.bins:>8}" + "".join(f"{v:>7}" for v in counts)
            + f"{self.nan / max(self.bins, 1):>7.1%}{self.coverage:>7.1%}  {p}"
            + f"  {np.max(x, initial=0.0):6.3f}"
        )  # fmt: skip


def judge(
    ranges: npt.ArrayLike,
    range_min: float,
    range_max: float,
    t: vis.Truth,
    err: F64,
    tag: str = "",
    circular: bool = False,
    err_claim: F64 | None = None,
    reach: npt.NDArray[np.int64] | None = None,
    err_cover: F64 | None = None,
    err_subpixel: F64 | None = None,
) -> Counts:
    """Judge one output's REP 117 ranges (n,) against its truth, with the stated error (n,) m at
    the visible truth (``err_claim``: at the claimed truth, default ``err``); ``circular``: the
    bins go round the circle (the first and last are neighbours); ``reach`` (n,): how many bins
    either side a bin's truth may be reported on (default 1: the bearing's resolution);
    ``err_cover``: the error coverage is judged with (default ``err``); ``err_subpixel``: the
    stated error at the nearest side seen edge-on (default ``err``)."""
    r = np.asarray(ranges, dtype=np.float64)
    near = np.minimum(t.visible, t.visible_edge)
    fin, ninf, inf = np.isfinite(r), r == -np.inf, r == np.inf
    with np.errstate(invalid="ignore"):
        lim = near + err
        far = fin & (r > lim)
        reach = np.ones(r.size, np.int64) if reach is None else reach
        near_fin = _nearest_around(np.where(fin, r, np.inf), reach, circular)  # what they hold
        held = near_fin <= lim
        claim_lim = t.claim + (err if err_claim is None else err_claim)
        near_any = _nearest_around(np.where(fin | ninf, r, np.inf), reach, circular)  # and -inf
        held_claim = near_any <= claim_lim
        truth_in = near <= range_max
        within = err if err_cover is None else err_cover
        good = (fin & (np.abs(r - near) <= within)) | (
            ninf & (near < range_min + TOO_CLOSE_SLACK_M)
        )
        # within the stated error of range_max a surface may read beyond it (noise, mm steps)
        claimed = inf & (t.claim <= range_max - (err if err_claim is None else err_claim))
        clear = claimed & ~held_claim
        rest = inf & ~claimed
        kinds = []
        blind = t.blind if t.blind is not None else np.full(r.size, np.inf)
        for within in (t.cleared, t.overhang, t.below, blind):  # each +inf bin in one kind at most
            kinds.append(rest & (within <= range_max))
            rest &= ~kinds[-1]
        lie = far & ~held
        sub = np.full(r.size, np.inf) if t.subpixel is None else t.subpixel
        edge_on = (
            fin & ~lie & ~(far & held) & (r > sub + (err if err_subpixel is None else err_subpixel))
        )
        c = Counts(
            bins=r.size,
            unsafe_far=int(lie.sum()),
            unsafe_clear=int(clear.sum()),
            clear_held=int((claimed & held_claim).sum()),
            beside=int((far & held).sum() + (claimed & held_claim).sum()),
            overhang=int(kinds[1].sum()),
            overhang_cleared=int(kinds[0].sum()),
            below_resolution=int(kinds[2].sum()),
            blind=int(kinds[3].sum()),
            subpixel=int(edge_on.sum()),
            false_too_close=int((ninf & ~(t.any < range_min + TOO_CLOSE_SLACK_M)).sum()),
            nan=int(np.isnan(r).sum()),
            with_truth=int(truth_in.sum()),
            covered=int((truth_in & good).sum()),
            errors=[(near - r)[fin & truth_in]],
            excess=[(r - near - err)[lie]],
        )
    if tag and lie.any():
        i = int(np.argmax(np.where(lie, r - np.where(lie, lim, 0.0), -np.inf)))
        c.examples.append(
            f"far {tag}: far={c.unsafe_far} clear={c.unsafe_clear}, bin {i}: "
            f"r={r[i]:.3f} truth={near[i]:.3f} err={err[i]:.3f}"
        )
    if tag and clear.any():
        i = int(np.argmin(np.where(clear, t.claim, np.inf)))
        c.examples.append(
            f"clear {tag}: far={c.unsafe_far} clear={c.unsafe_clear}, bin {i}: "
            f"+inf truth={t.claim[i]:.3f} (visible {near[i]:.3f})"
        )
    return c


def _nearest_around(side: F64, reach: npt.NDArray[np.int64], circular: bool) -> F64:
    """(n,) the least value bins j - reach[j] .. j + reach[j] other than j hold (+inf past the
    ends unless ``circular``)."""
    out = np.full(side.size, np.inf)
    for k in range(1, int(reach.max(initial=0)) + 1):
        left, right = np.roll(side, k), np.roll(side, -k)
        if not circular:
            left[: min(k, side.size)] = np.inf
            right[max(side.size - k, 0) :] = np.inf
        out = np.where(reach >= k, np.minimum(out, np.minimum(left, right)), out)
    return out


def live_claims(s: vis.Sight) -> Claims:
    """What a sensor's own (level-frame) scans are judged with."""
    return Claims(s.visible, s.claim, s.overhang, s.below, np.zeros_like(s.claim), None, s.subpixel)


def base_claims(sights: Sequence[vis.Sight]) -> Claims:
    """What base-frame scans of these sensors (merged if more) are judged with: also what no
    sensor covered, outside every sensor's dead zone."""

    def any_(name: str) -> B:
        return np.logical_or.reduce([getattr(s, name) for s in sights])

    claim = any_("claim") | (any_("drop") & ~any_("covered") & ~any_("dead"))
    no = np.zeros_like(claim)
    return Claims(
        any_("visible"), claim, any_("overhang"), any_("below"), no, None, any_("subpixel")
    )


def memory_claims(
    bd: vis.Boundary, seen_ever: B, inside: B | None = None, below_ever: B | None = None
) -> Claims:
    """What the memory is judged with: everything, but table tops never seen (overhang) or seen
    (cleared), what lies ``inside`` its blind disc (blind; None: nothing) and the edges of a hole
    the cliff stage only ever saw below its resolution (``below_ever``: some of its edge samples;
    none of them ever seen: below; the memory clears what the live cliff scan read free, under
    the live scan's own exception)."""
    up, no = bd.raised, np.zeros_like(bd.raised)
    inside = no if inside is None else inside
    below = no
    if below_ever is not None and bd.edge.any():  # per hole: some edge below, none ever seen
        n = int(bd.owner[bd.edge].max()) + 1
        hit = np.bincount(bd.owner[bd.edge], below_ever[bd.edge], n) > 0
        saw = np.bincount(bd.owner[bd.edge], seen_ever[bd.edge], n) > 0
        below = bd.edge & (hit & ~saw)[np.where(bd.edge, bd.owner, 0)] & ~inside
    out = ~inside & ~below
    return Claims(seen_ever, ~up & out, up & ~seen_ever & out, below, up & seen_ever & out, inside)


def noise_k(noise: KinectNoise | None) -> float:
    """k of the stated error's k (r^2 + 1) term for this depth noise (0: exact depth)."""
    if noise is None:
        return 0.0
    fb = noise.focal_px * noise.baseline_m
    return 3.0 * noise.disparity_sigma_px / fb + 0.5 / (fb * noise.subpixel)


def stated_error(
    t: vis.Truth,
    k: float,
    odom_m: float = 0.0,
    odom_rad: float = 0.0,
    cell_m: float = 0.0,
    at_claim: bool = False,
    at: F64 | None = None,
) -> F64:
    """The stated error per bin (n,) m at the nearest visible (or ``at_claim``: claimed; ``at``:
    these ranges') truth (module docstring); ``cell_m``: the memory's cell (it keeps one point
    per cell)."""
    r = t.claim if at_claim else np.minimum(t.visible, t.visible_edge) if at is None else at
    r = np.minimum(r, 10.0)
    base = np.where(t.visible_edge < t.visible, ERR_EDGE_M, ERR_OBSTACLE_M)
    return base + k * (r * r + 1.0) + 2.0 * (odom_m + odom_rad * r) + math.sqrt(2.0) * cell_m


OUTPUTS = tuple(
    "level_scan level_cliff base_scan base_cliff merged_scan merged_cliff sectors memory "
    "memory_sectors".split()
)


def sector_ranges(s: Sectors) -> tuple[F64, vis.Layout, float, float]:
    """An OBSTACLE_DISTANCE payload as REP 117 ranges (n,) in a counter-clockwise layout, and its
    limits: UINT16_MAX -> NaN, max_distance + 1 -> +inf, min_distance -> -inf, else cm / 100."""
    cm = np.asarray(s.distances_cm, dtype=np.float64)[::-1]
    r = np.select(
        [cm == UNKNOWN, cm == s.max_cm + 1, cm == s.min_cm], [np.nan, np.inf, -np.inf], cm / 100
    )
    w, n = s.increment_f_deg, cm.size
    return (
        r,
        (-math.radians(s.angle_offset_deg + (n - 1) * w), math.radians(w), n),
        s.min_cm / 100,
        s.max_cm / 100,
    )


def _judge(
    out: Counts,
    ranges: tuple[F64, vis.Layout, float, float],
    bd: vis.Boundary,
    claims: Claims,
    origin: vis.Origin,
    kinds: B | None,
    err: tuple[float, float, float, float],
    tag: str,
) -> None:
    """Judge ranges (r, layout, range_min, range_max) seen from ``origin``; err: k, drift and
    the memory's cell (coverage is judged without the cell)."""
    r, lay, rmin, rmax = ranges
    t = truth(bd, claims, origin, lay, kinds)
    circular = lay[1] * lay[2] >= 2 * math.pi - 1e-6
    ec = stated_error(t, *err, at_claim=True)
    _, odom_m, odom_rad, _ = err
    reach = None
    if odom_m or odom_rad:  # the memory: its points turned by the odometry's drift (docstring)
        at = np.maximum(np.minimum(np.minimum(t.visible, t.visible_edge), t.claim), 0.1)
        reach = 1 + np.ceil((odom_rad + odom_m / at) / lay[1]).astype(np.int64)
    tight = stated_error(t, *err[:3])
    es = None if t.subpixel is None else stated_error(t, *err, at=t.subpixel)
    out.add(judge(r, rmin, rmax, t, stated_error(t, *err), tag, circular, ec, reach, tight, es))


def _of(scan: LaserScan) -> tuple[F64, vis.Layout, float, float]:
    lay = (float(scan.angle_min), float(scan.angle_increment), int(scan.ranges.size))
    return np.asarray(scan.ranges, dtype=np.float64), lay, scan.range_min, scan.range_max


def _note_view(state: pm.MemoryState, v: SensorView) -> None:
    """Note a view's dead zone in ``state`` as pipeline.memory.update does (for its blind_m)."""
    sc = v.scan
    a0, inc, n = float(sc.angle_min), float(sc.angle_increment), sc.ranges.size
    near, _ = floor_extent(v.intrinsics, v.mount.level_part(), a0, inc, n, v.rows)
    pm._note_sensor(state, v, near)


def judge_drive(case: Case, steps: Sequence[Step] | None = None) -> dict[str, Counts]:
    """Run (or take) the drive of ``case`` and judge every output on every frame."""
    params = suite_params(case.intr)
    sp, cp = params.scan, params.cliff
    assert cp is not None
    bd = vis.boundary(case.scene, sp)
    seen_ever = np.zeros(len(bd.xy), bool)
    below_ever = np.zeros(len(bd.xy), bool)
    k = noise_k(case.depth_noise)
    out = {name: Counts() for name in OUTPUTS}
    drift = (0.0, 0.0)
    box, edge = ~bd.edge, bd.edge
    mstate = pm.new_state(pm.MemoryParams())  # only its blind_m: what the memory noted of the views
    for step in steps if steps is not None else run_case(case, params):
        tag, pose, e = f"seed={case.seed} frame={step.index}", step.pose, (k, 0.0, 0.0, 0.0)
        cams = [vis.Camera.at(m, case.intr, pose) for m in case.rig]
        sights = [vis.sight(bd, case.scene, c, sp, cp) for c in cams]
        for j, (cam, s, res) in enumerate(zip(cams, sights, step.results, strict=True)):
            seen_ever |= s.seen
            below_ever |= s.below
            live, base, where = live_claims(s), base_claims([s]), f"{tag} sensor={j}"
            _judge(out["level_scan"], _of(res.level_scan), bd, live, cam.origin, box, e, where)
            _judge(out["base_scan"], _of(res.scan), bd, base, pose, box, e, where)
            if res.cliff is not None and res.level_cliff is not None:
                cliff = _of(res.level_cliff.scan)
                _judge(out["level_cliff"], cliff, bd, live, cam.origin, edge, e, where)
                _judge(out["base_cliff"], _of(res.cliff.scan), bd, base, pose, edge, e, where)
        merged = base_claims(sights)
        if len(sights) > 1:
            _judge(out["merged_scan"], _of(step.scan), bd, merged, pose, box, e, tag)
            if step.cliff is not None:
                _judge(out["merged_cliff"], _of(step.cliff), bd, merged, pose, edge, e, tag)
        _judge(out["sectors"], sector_ranges(step.sectors), bd, merged, pose, None, e, tag)
        o = step.odom
        drift = (
            max(drift[0], math.hypot(o[0] - pose[0], o[1] - pose[1])),
            max(drift[1], abs(math.remainder(o[2] - pose[2], 2 * math.pi))),
        )
        for res in step.results:
            _note_view(mstate, sensor_view(res, params))
        inside = np.hypot(*(bd.xy - pose[:2]).T) < pm.scan_limits(mstate)[0]
        mem = memory_claims(bd, seen_ever, inside, below_ever)
        e = (k, *drift, mstate.params.cell_m)
        _judge(out["memory"], _of(step.memory), bd, mem, pose, None, e, tag)
        sectors = sector_ranges(step.memory_sectors)
        _judge(out["memory_sectors"], sectors, bd, mem, pose, None, e, tag)
    return out


def table(totals: dict[str, Counts]) -> str:
    """Per output: bins; unsafe far and clear; beside (held: its +inf bins), overhang, overhang
    cleared, below resolution, blind and subpixel (reported, not unsafe); false too-close; NaN
    share; coverage; safe-side error p50/p95/max (m); worst excess of an unsafe far bin (m)."""
    names = "far clear (held) beside overhg oh_clr below blind subpx close NaN cover".split()
    head = f"{'output':<15}{'bins':>8}" + "".join(f"{n:>7}" for n in names)
    head += f"  {'p50':>6} {'p95':>6} {'max':>6}  {'excess':>6}"
    return "\n".join(
        [head, *(totals[n].line(n) for n in OUTPUTS if n in totals and totals[n].bins)]
    )


def run_suite(
    seeds: Sequence[int], frames: int = 8, intr: Intrinsics | None = None
) -> dict[str, Counts]:
    """Judge the random drives of ``seeds`` (worlds.random_case)."""
    totals = {name: Counts() for name in OUTPUTS}
    for s in seeds:
        for name, c in judge_drive(
            random_case(s, frames, intr or KINECT_V1.scaled(160, 120))
        ).items():
            totals[name].add(c)
    return totals


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m depthnav_daemon.sim.contract``: the table for N drives."""
    ap = argparse.ArgumentParser(prog="python -m depthnav_daemon.sim.contract")
    ap.add_argument("--drives", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0, help="first seed")
    ap.add_argument("--frames", type=int, default=8, help="frames per drive")
    ap.add_argument("--size", default="160x120", help="image WIDTHxHEIGHT (Kinect v1 scaled)")
    ap.add_argument("--examples", action="store_true", help="the first unsafe frames per output")
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.split("x"))
    t0 = time.perf_counter()
    totals = run_suite(range(a.seed, a.seed + a.drives), a.frames, KINECT_V1.scaled(w, h))
    took = time.perf_counter() - t0
    lines = [table(totals), f"{a.drives} drives x {a.frames} frames, {w}x{h}, seeds {a.seed}.."]
    lines[-1] += f"{a.seed + a.drives - 1}: {took:.1f} s"
    lines += [f"{n}: {ex}" for n in OUTPUTS for ex in totals[n].examples] if a.examples else []
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
