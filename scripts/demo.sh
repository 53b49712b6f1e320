#!/usr/bin/env bash
# Build or reuse .venv/, then run the main job on the bundled default (see README).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/venv.sh
exec .venv/bin/ga-ros demo "$@"
