#!/usr/bin/env bash
# Build or reuse .venv/, then run the whole test suite. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/venv.sh
exec .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
