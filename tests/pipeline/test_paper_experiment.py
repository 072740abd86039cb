"""The figs. 11-12 experiment: the exact scan's detection depends on box height only, never on
pose."""

from __future__ import annotations

from depthnav_daemon.sim.paper_experiment import BOX_HEIGHTS_M, format_table, run


def test_exact_detects_a_box_iff_taller_than_the_margin_at_every_pose() -> None:
    rows = run(noise=False)
    for r in rows:
        if r.method != "exact" or r.margin_m == 0.0:
            continue  # e_g = 0 keeps the floor itself (height 0) as an obstacle, as in the paper
        for h, seen in zip(BOX_HEIGHTS_M, r.detected, strict=True):
            if abs(h - r.margin_m) > 0.005:  # a box exactly as tall as the margin may go either way
                assert seen == (h > r.margin_m), (h, r)
        assert r.false_bins == 0, r


def test_paper_method_sees_the_floor_without_margin_and_tall_boxes_with_it() -> None:
    rows = run(noise=False)
    for r in rows:
        if r.method != "paper":
            continue
        if r.margin_m == 0.0:
            assert r.false_bins > 50, (
                r
            )  # no margin: the floor itself is the nearest "obstacle" (fig. 9)
        elif r.margin_m >= 0.05:
            assert r.detected[0], r  # the 40 cm box survives every margin and pose


def test_table_has_a_line_per_pose_and_margin() -> None:
    text = format_table(run(noise=False))
    assert text.count("\n") == 2 + 4 * 6 - 1
    assert "(1.20 m, 60 deg) | 20 cm" in text
