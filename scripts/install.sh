#!/usr/bin/env bash
# Install everything depthnav needs on a Debian machine: the native sensor libraries (apt, when
# root), a virtual environment in .venv with depthnav and its test tools, and the compiled kernels
# (this user's and, as root, the service's). Safe to run again.
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
# compile the numeric kernels now, not at the robot's first start: into this user's cache (the
# tests, depthnav at a terminal) and, as root, into the service's: the unit's NUMBA_CACHE_DIR,
# owned by the unit's User= (a root-owned cache would stop the service at its first import)
.venv/bin/depthnav warmup
UNIT=configs/systemd/depthnav.service
svc_cache=$(sed -n 's/^Environment=NUMBA_CACHE_DIR=//p' "$UNIT")
svc_user=$(sed -n 's/^User=//p' "$UNIT")
again="sudo $PWD/.venv/bin/depthnav warmup --cache-dir $svc_cache --owner $svc_user"
if [ "$(id -u)" -ne 0 ]; then
  echo "depthnav install: for the service, compile its kernels as root: $again" >&2
elif ! id "$svc_user" >/dev/null 2>&1; then
  echo "depthnav install: no user '$svc_user' yet (systemd-sysusers, see the README); then: $again" >&2
else
  # the kernels just compiled are this machine's: start the service's cache from them
  user_cache=$(.venv/bin/python -c \
    'from depthnav_daemon.daemon.kernel_cache import cache_dir; print(cache_dir())')
  install -d -o "$svc_user" -g "$(id -gn "$svc_user")" "${svc_cache%/*}" "$svc_cache"
  cp -a "$user_cache/." "$svc_cache/"
  .venv/bin/depthnav warmup --cache-dir "$svc_cache" --owner "$svc_user"
fi
