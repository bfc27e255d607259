#!/usr/bin/env bash
# The whole test suite: set up (or re-check) the environment, lint, then pytest.
# Extra arguments go to pytest, e.g. `bash ros2_ws/test.sh tests/unit -k linear`.
set -euo pipefail
ws="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(dirname "$ws")"
bash "$ws/bootstrap.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST RMW_IMPLEMENTATION=rmw_fastrtps_cpp PYTHONDONTWRITEBYTECODE=1
cd "$root"
"$ws/venv/bin/ruff" check src tests benchmarks
"$ws/venv/bin/ruff" format --check --quiet src tests benchmarks
exec "$ws/venv/bin/python" -m pytest "${@:-tests}"
