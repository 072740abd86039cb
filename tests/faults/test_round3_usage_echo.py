"""Round 3, part 2 (issue 35 item 7): argparse's usage errors quote the bad argument through
``short_repr`` (cut to about 60 characters, escaped): a 5000-digit ``--frame`` was echoed in
full, and a control character reached the terminal raw. Through the CLI in a child process."""

from __future__ import annotations

import pytest

from tests.faults.kit import FAST, depthnav_measured, one_error_line

CASES = {
    "5000 digits": (["snapshot", "--device", FAST, "--frame", "9" * 5000, "x.png"], "9" * 27),
    "ESC and NUL": (["snapshot", "--device", FAST, "--frame", "1\x1b[31m2", "x.png"], "\\x1b"),
    "newline": (["mount", "--height-m", "0.5\nerror: forged", "--tilt-deg", "15"], "\\n"),
    "unknown argument": (["run", "--device", FAST, "--zz" + "z" * 5000], "unrecognized"),
    "bad choice": (["run", "--device", FAST, "--method", "\x07" * 3 + "x" * 500], "\\x07"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_usage_error_echo_is_bounded_and_escaped(case: str) -> None:
    argv, shown = CASES[case]
    done = depthnav_measured(*argv)
    assert done.returncode == 2, done.stderr
    line = one_error_line(done.stderr)
    assert shown in line and len(line) <= 400, line
    assert not any(c in done.stderr for c in "\x00\x1b\x07"), repr(done.stderr)
    assert "\nerror: forged" not in done.stderr
    assert len(done.stderr) < 2000, len(done.stderr)  # the usage line, the error and its hint
