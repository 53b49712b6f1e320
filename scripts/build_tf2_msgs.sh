#!/usr/bin/env bash
# Build tf2_msgs/msg/TFMessage (what /tf and /tf_static carry) into .venv/ from its .msg
# definition in scripts/tf2_msgs/: tf2_msgs is not on PyPI as a wheel. Only the message, not
# tf2_msgs' services and action (they need action_msgs plumbing ga_ros does not use). How, and
# what it installs: scripts/build_interfaces.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
exec bash scripts/build_interfaces.sh tf2_msgs scripts/tf2_msgs geometry_msgs std_msgs \
  builtin_interfaces
