"""The rational_polynomial and equidistant (fisheye) lens models (issue 33 item 3): their
formulas, their inverse, a synthetic floor rendered through them and calibrated back flat, and
what cannot be expressed refused in one line."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from depthnav_daemon.pipeline import lens
from depthnav_daemon.pipeline.geometry import Mount, pixel_rays
from depthnav_daemon.pipeline.pose import PoseParams, estimate_pose
from depthnav_daemon.pipeline.scan import depth_to_scan
from depthnav_daemon.sim.synthetic import Box, Scene, render
from drivers.base import Frame, Intrinsics
from drivers.formats.png_folder import write_png_folder
from tests.pipeline.test_lens import MOUNTS, scan_error_m
from tests.pipeline.test_scan import PARAMS

ROOT = Path(__file__).resolve().parents[2]
# an Azure-Kinect-like depth camera (640x576, rational_polynomial): strong barrel, tamed by k4-k6
RATIONAL = Intrinsics(
    640, 576, 504.0, 504.0, 321.0, 330.0, k1=0.45, k2=0.05, p1=1e-4, p2=-2e-4, k3=0.002,
    k4=0.80, k5=0.15, k6=0.01, distortion_model="rational_polynomial",
)  # fmt: skip
# a fisheye (Kannala-Brandt) seeing up to 75 deg off axis
FISHEYE = Intrinsics(
    640, 480, 300.0, 300.0, 320.0, 240.0, k1=-0.01, k2=0.02, k3=-0.005, k4=0.001,
    distortion_model="equidistant",
)  # fmt: skip
LENSES = {"rational": RATIONAL, "fisheye": FISHEYE}
# boxes towards the image corners, where the lenses move pixels most
BOXES = Scene(
    boxes=(
        Box(1.4, 0.75, 0.3, 0.3, 0.6, yaw_deg=10),
        Box(2.2, -1.3, 0.4, 0.3, 0.9),
        Box(3.0, 0.2, 0.3, 0.5, 0.5, yaw_deg=-20),
    )
)


def pinhole_of(intr: Intrinsics) -> Intrinsics:
    return Intrinsics(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)


# --- the formulas --------------------------------------------------------------------------------


def test_rational_and_equidistant_follow_opencv() -> None:
    """OpenCV's CALIB_RATIONAL_MODEL: R = (1 + k1 r2 + k2 r4 + k3 r6) / (1 + k4 r2 + k5 r4 +
    k6 r6); cv::fisheye: theta_d = theta (1 + k1 theta2 + k2 theta4 + k3 theta6 + k4 theta8),
    (xd, yd) = theta_d / r (x, y), theta = atan(r)."""

    def at(x: float, y: float, **kw: float | str) -> tuple[float, float]:
        intr = Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5, **kw)  # type: ignore[arg-type]
        xd, yd = lens.distort(x, y, intr)
        return float(xd), float(yd)

    rational = {"distortion_model": "rational_polynomial"}
    r2 = 0.4**2 + 0.3**2
    radial = (1 + 0.1 * r2 + 0.02 * r2**2 + 0.003 * r2**3) / (
        1 + 0.2 * r2 + 0.05 * r2**2 + 0.01 * r2**3
    )
    got = at(0.4, 0.3, k1=0.1, k2=0.02, k3=0.003, k4=0.2, k5=0.05, k6=0.01, **rational)
    assert got == pytest.approx((0.4 * radial, 0.3 * radial), rel=1e-14)
    # with k4..k6 = 0 it is plumb_bob exactly, tangential terms included
    assert at(0.3, 0.2, k1=0.1, p1=0.01, **rational) == at(0.3, 0.2, k1=0.1, p1=0.01)
    fisheye = {"distortion_model": "equidistant"}
    theta = math.atan(0.5)
    assert at(0.5, 0.0, **fisheye) == pytest.approx((theta, 0.0), rel=1e-14)  # ideal equidistant
    td = theta * (1 + 0.1 * theta**2 + 0.01 * theta**4 - 0.002 * theta**6 + 0.001 * theta**8)
    got = at(0.3, 0.4, k1=0.1, k2=0.01, k3=-0.002, k4=0.001, **fisheye)
    assert got == pytest.approx((0.3 * td / 0.5, 0.4 * td / 0.5), rel=1e-14)
    assert Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5, **fisheye).has_distortion  # type: ignore[arg-type]


@pytest.mark.parametrize("name", LENSES)
def test_undistort_inverts_distort_over_the_image(name: str) -> None:
    intr = LENSES[name]
    u = np.arange(intr.width, dtype=np.float64)[None, :]
    v = np.arange(intr.height, dtype=np.float64)[:, None]
    xd, yd = (u - intr.cx) / intr.fx + 0 * v, (v - intr.cy) / intr.fy + 0 * u
    x, y = lens.undistort(xd, yd, intr)
    assert np.isfinite(x).all() and np.isfinite(y).all()
    back_x, back_y = lens.distort(x, y, intr)
    assert np.abs(back_x - xd).max() < 1e-10 and np.abs(back_y - yd).max() < 1e-10
    # the lens matters: the corners' rays are far from the pinhole's
    assert np.hypot(x - xd, y - yd).max() > 0.1


def test_a_fisheye_pixel_beyond_90_deg_has_no_ray() -> None:
    """theta_d(90 deg) is the farthest a ray in front of the camera reaches: a distorted radius
    beyond it is no ray (NaN), not a ray behind the camera."""
    x, y = lens.undistort(np.array([0.0, 1.0, 1.7]), np.zeros(3), FISHEYE)
    assert x[0] == 0.0 and math.isclose(x[1], math.tan(1.0 - 0.0), rel_tol=0.05)
    assert np.isnan(x[2]) and np.isnan(y[2])


@pytest.mark.parametrize(
    ("kw", "text"),
    [
        ({"k4": 0.1}, "k4=0.1 is not a coefficient of the plumb_bob lens model (k1, k2, p1, p2,"),
        (
            {"p1": 0.01, "distortion_model": "equidistant"},
            "p1=0.01 is not a coefficient of the equidistant lens model (k1, k2, k3, k4)",
        ),
        ({"distortion_model": "fisheye"}, "lens model 'fisheye' cannot be expressed"),
        (
            {"k4": 3.0, "distortion_model": "rational_polynomial"},
            "lens distortion rational_polynomial (k1=0, k2=0, p1=0, p2=0, k3=0, k4=3, k5=0, "
            "k6=0) folds back inside the image",
        ),
        (
            {"distortion_model": "equidistant", "fx": 150.0, "fy": 150.0},
            "sees rays 87 deg or more off axis",
        ),
    ],
    ids=["k4_under_plumb_bob", "p1_under_fisheye", "unknown", "fold", "fisheye_beyond_87deg"],
)
def test_what_cannot_be_expressed_is_a_one_line_error(kw: dict, text: str) -> None:
    kw = dict(kw)  # the parameter's own dict is shared: not popped from
    pinhole = {"fx": 500.0, "fy": 500.0} | {k: kw.pop(k) for k in ("fx", "fy") if k in kw}
    with pytest.raises(ValueError) as info:
        Intrinsics(640, 480, pinhole["fx"], pinhole["fy"], 319.5, 239.5, **kw)
    said = str(info.value)
    assert text in said and "\n" not in said and len(said) < 400


def test_scaled_keeps_the_whole_model() -> None:
    half = RATIONAL.scaled(320, 288)
    assert half.distortion_model == "rational_polynomial" and half.distortion == RATIONAL.distortion
    assert FISHEYE.scaled(320, 240).distortion_model == "equidistant"


# --- a floor rendered through the lens and calibrated back ---------------------------------------

MOUNT = Mount(0.9, 30.0, 2.0)


def calibrate(spec: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "depthnav_daemon", "calibrate", "--device", spec, "--json",
         "--frames", "3"],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.parametrize("name", LENSES)
def test_a_floor_through_the_lens_calibrates_flat(tmp_path: Path, name: str) -> None:
    """Rendered through the lens (sim.synthetic casts each pixel's undistorted ray), written as
    a PNG folder whose camera.toml names the model, and read back by ``depthnav calibrate``:
    the floor is flat and where it was. Measured: rational 0.002 mm / 0.00001 deg, fisheye
    0.02 mm / 0.0004 deg; read as a pinhole both are off by 3.8-3.9 cm / 1.3 deg."""
    intr = LENSES[name]
    depth = render(Scene(), intr, MOUNT, min_range_m=0.05).depth_mm
    # un-rendered with the lens, the floor's points lie on one plane (millimetre rounding only)
    valid = depth > 0
    assert valid.mean() > 0.7
    points = pixel_rays(intr)[valid] * (depth[valid, None] / 1000.0)
    centred = points - points.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    assert np.sqrt(np.mean((centred @ normal) ** 2)) < 0.5e-3
    folder = tmp_path / name
    write_png_folder(folder, [Frame(i, i / 30, depth, intr) for i in range(3)], scale=1000.0)
    assert f"distortion_model = '{intr.distortion_model}'" in (folder / "camera.toml").read_text()
    got = calibrate(f"replay:{folder}?rate=max")
    assert abs(got["height_m"] - MOUNT.height_m) < 1e-3, got
    assert abs(got["tilt_deg"] - MOUNT.tilt_deg) < 0.05, got
    assert abs(got["roll_deg"] - MOUNT.roll_deg) < 0.05, got
    assert got["height_std_m"] < 1e-3 and got["tilt_std_deg"] < 0.05, got
    # the same frames read as an ideal pinhole (the lens dropped) are measurably off
    pin = estimate_pose(
        depth, pinhole_of(intr), PoseParams(height_max_m=3.0), np.random.default_rng(0)
    )
    assert (
        not pin.ok
        or abs(pin.height_m - MOUNT.height_m) > 0.02
        or abs(pin.tilt_deg - MOUNT.tilt_deg) > 0.5
    )


@pytest.mark.parametrize("mount", MOUNTS[:2], ids=lambda m: f"h{m.height_m}_t{m.tilt_deg:.0f}")
@pytest.mark.parametrize("name", LENSES)
def test_scan_through_the_lens_within_1cm(name: str, mount: Mount) -> None:
    """Boxes seen through the lens land in the scan where they are (measured: 0.5-0.9 mm, no
    false obstacle); read as a pinhole, 2-2.7 m off or hundreds of false bins."""
    intr = LENSES[name]
    view = render(BOXES, intr, mount, min_range_m=0.05)
    err, false = scan_error_m(view, depth_to_scan(view.depth_mm, intr, mount, PARAMS), PARAMS)
    assert err <= 0.01 and false == 0, (err, false)
    pin = depth_to_scan(view.depth_mm, pinhole_of(intr), mount, PARAMS)
    pin_err, pin_false = scan_error_m(view, pin, PARAMS)
    assert pin_err > 0.05 or pin_false > 5, (pin_err, pin_false)
