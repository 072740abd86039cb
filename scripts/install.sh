#!/usr/bin/env bash
# Install everything depthnav needs on a Debian machine: the native sensor libraries (apt, when
# root), and a virtual environment in .venv with depthnav and its test tools. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

# systemd: systemd-analyze and systemd-sysusers check the shipped unit in the tests
# python3-rosbag: ROS 1's own rosbag (Debian), the tests check our .bag files with it
# libfastrtps-dev fastddsgen cmake g++: the tests build a Fast DDS subscriber to our ros2 sink
APT_PACKAGES=(libopenni2-0 libfreenect0.5 libfreenect-bin libusb-1.0-0 python3-venv systemd
  python3-rosbag libfastrtps-dev fastddsgen cmake g++)
missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null; then
    echo "depthnav install: apt-get install ${missing[*]}" >&2
    apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "depthnav install: missing Debian packages: ${missing[*]} (run: sudo apt-get install ${missing[*]})" >&2
  fi
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "depthnav install: creating .venv with $($PY --version)" >&2
  "$PY" -m venv .venv
fi
# pip's own output goes to a log; it is shown only when something fails
log=.venv/install.log
echo "depthnav install: pip install -e .[dev] into .venv (log: $log)" >&2
if ! { .venv/bin/python -m pip install --disable-pip-version-check --upgrade pip \
       && .venv/bin/python -m pip install --disable-pip-version-check -e ".[dev]"; } >"$log" 2>&1; then
  tail -n 30 "$log" >&2
  echo "depthnav install: pip failed; the whole log is in $log" >&2
  exit 1
fi
# compile and cache the numeric kernels now, not at the robot's first frame
.venv/bin/python -m depthnav_daemon.tools.warmup
