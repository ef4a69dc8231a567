#!/usr/bin/env bash
# One-command setup for DRVS on Debian bookworm (or a derivative).
#
# Installs the Debian packages the project needs, creates .venv from Debian's
# /usr/bin/python3 with --system-site-packages, installs pybullet and the test
# tools into it, and installs the project (which generates drvs.msg and
# drvs.srv), with headless Chromium and Selenium for the browser test; with --rviz also Debian's rviz
# and xvfb; with --postgres PostgreSQL, PostGIS and psycopg for a registry in a database
# (docs/registry.md; `make test` asks for it: the registry's tests run against PostgreSQL too). Idempotent: a second run that finds everything in place does no
# installs and finishes within seconds. Works as root or through sudo.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$here"

APT_PACKAGES=(
  ros-core python3-rospy python3-rosservice python3-rosmsg python3-rosnode
  python3-rostopic python3-rosgraph python3-roslib python3-rospkg
  python3-genpy python3-genmsg
  ros-std-msgs ros-geometry-msgs ros-sensor-msgs ros-nav-msgs
  python3-std-msgs python3-geometry-msgs python3-sensor-msgs python3-nav-msgs
  python3-opencv python3-numpy python3-shapely python3-yaml
  python3-matplotlib python3-venv python3-pip python3-psutil
  python3-cachetools python3-hypothesis
  python3-cv-bridge python3-image-geometry python3-tf2-ros python3-message-filters tf2-tools
  python3-diagnostic-msgs ros-diagnostic-msgs python3-visualization-msgs ros-visualization-msgs
  python3-rosbag
  python3-scipy  # make bench: its natural photograph (scipy.misc.face) for the image-sharing comparison
  python3-mypy  # make lint and test/project/test_types.py: types of the pure packages
  python3-pandas python3-xmltodict  # py-motmetrics' dependencies (the scenario report's tracking metrics)
  python3-aiohttp  # drvs_gateway: DRVS over HTTP and Server-Sent Events (docs/gateway.md)
  # The floor-plan page's test in a real browser (test/scenarios/test_gateway_page.py): always
  # installed, since `make test` (and so CI) runs it; about 300 MB.
  chromium chromium-driver python3-selenium
  nodejs  # the roslibjs example of drvs_gateway's rosbridge endpoint, run by test/live/test_rosbridge.py
)
# npm: Debian's, unless a Node.js that brings its own is installed (NodeSource's conflicts with Debian's npm).
command -v npm >/dev/null 2>&1 || APT_PACKAGES+=(npm)
# RViz and a virtual display for its screenshot test, only when asked for:
# `scripts/setup.sh --rviz` (make rviz-setup, run_scenario.sh --rviz).
# PostgreSQL with PostGIS and psycopg 3, for `~registry:=postgresql://...` and its tests:
# `scripts/setup.sh --postgres` (make test); scripts/postgres.sh runs a private cluster.
for arg in "$@"; do
  case "$arg" in
    --rviz) APT_PACKAGES+=(rviz xvfb) ;;
    --postgres) APT_PACKAGES+=(postgresql-15 postgresql-15-postgis-3 python3-psycopg) ;;
    *) printf 'setup: unknown option %s (--rviz, --postgres)\n' "$arg" >&2; exit 2 ;;
  esac
done
# The test tools and the PyPI wheels, pinned to what the project was checked with (motmetrics:
# the tracking metrics of drvs/sim/tracking.py; 1.4.0 runs on Debian's numpy 1.24, scipy 1.10, pandas 1.5).
# roslibpy: the rosbridge client of drvs_gateway's Python example (test/live/test_rosbridge.py).
# pytest-xdist: `make test` runs the tests before the whole runs on two workers (Makefile).
PIP_PACKAGES=(pybullet==3.2.7 pytest==8.3.4 pytest-timeout==2.3.1 pytest-xdist==3.6.1 ruff==0.8.4 motmetrics==1.4.0 roslibpy==2.1.0)

say() { printf 'setup: %s\n' "$*"; }
die() { printf 'setup: error: %s\n' "$*" >&2; exit 1; }

missing_apt() {
  local p
  for p in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${db:Status-Status}\n' "$p" 2>/dev/null | grep -qx installed || echo "$p"
  done
}

missing=$(missing_apt)
if [ -n "$missing" ]; then
  command -v apt-get >/dev/null 2>&1 || die "apt-get not found. DRVS needs Debian bookworm (or a derivative) with these packages: $(echo $missing)"
  if [ "$(id -u)" -eq 0 ]; then
    SUDO=()
  elif command -v sudo >/dev/null 2>&1; then
    SUDO=(sudo)
  else
    die "installing Debian packages needs root: run as root or install sudo. Missing: $(echo $missing)"
  fi
  say "installing Debian packages: $(echo $missing)"
  "${SUDO[@]}" apt-get update -q
  # shellcheck disable=SC2086
  DEBIAN_FRONTEND=noninteractive "${SUDO[@]}" apt-get install -y -q --no-install-recommends $missing
fi

[ -x /usr/bin/python3 ] || die "/usr/bin/python3 is missing: install Debian's python3"
venv="$here/.venv"
if [ ! -x "$venv/bin/python" ]; then
  say "creating $venv from /usr/bin/python3 with --system-site-packages"
  /usr/bin/python3 -m venv --system-site-packages "$venv"
fi
py="$venv/bin/python"
"$py" -c 'import rospy, cv2, numpy, shapely, yaml, cv_bridge, image_geometry, tf2_ros, aiohttp' 2>/dev/null \
  || die "$venv cannot import rospy/cv2/numpy/shapely/yaml/cv_bridge/image_geometry/tf2_ros/aiohttp; delete .venv and run again"

pip_missing=()
for spec in "${PIP_PACKAGES[@]}"; do
  name=${spec%%==*}; want=${spec#*==}
  have=$("$py" -c "import importlib.metadata as m; print(m.version('$name'))" 2>/dev/null || true)
  [ "$have" = "$want" ] || pip_missing+=("$spec")
done
if [ ${#pip_missing[@]} -gt 0 ]; then
  say "installing from PyPI: ${pip_missing[*]}"
  "$py" -m pip install -q --disable-pip-version-check "${pip_missing[@]}"
fi

# Install the project (editable) when it is missing or its definitions changed.
stamp="$venv/.drvs-install-stamp"
digest=$(cat setup.py pyproject.toml package.xml msg/*.msg srv/*.srv 2>/dev/null | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$digest" ] \
   || ! "$py" -c 'import drvs.msg, drvs.srv' 2>/dev/null; then
  say "installing the drvs package (generates drvs.msg and drvs.srv)"
  "$py" -m pip install -q --disable-pip-version-check --no-build-isolation --no-deps -e .
  echo "$digest" > "$stamp"
fi

# roslibjs for the rosbridge example (examples/roslibjs, its package-lock.json), when the lock file changed.
js="$here/examples/roslibjs"
js_digest=$(sha256sum "$js/package-lock.json" | cut -d' ' -f1)
if [ "$(cat "$js/node_modules/.drvs-stamp" 2>/dev/null)" != "$js_digest" ]; then
  say "installing roslibjs from npm into examples/roslibjs/node_modules"
  (cd "$js" && npm ci --no-audit --no-fund --loglevel=error) && echo "$js_digest" > "$js/node_modules/.drvs-stamp"
fi
say "ready ($venv)"
