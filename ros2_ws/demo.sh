#!/usr/bin/env bash
# The demo: set up (or re-check) the environment, then evaluate the bundled demo bag through the
# real node suite, printing the report table and writing plots to out/demo/.
set -euo pipefail
ws="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(dirname "$ws")"
bash "$ws/bootstrap.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST RMW_IMPLEMENTATION=rmw_fastrtps_cpp
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-42}"
cd "$root"
# out/demo is this script's own output: a re-run replaces the previous run's (eval refuses to overwrite)
rm -rf out/demo
exec "$ws/venv/bin/ptz-selfcal" eval bags/demo --out-dir out/demo "$@"
