#!/usr/bin/env bash
# Set up the environment (reused when unchanged) and run the main job on the bundled demo scene.
# Extra arguments go to scripts/demo.py (e.g. --rebuild to retrain the demo NeRFs from scratch).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$(bash "$ROOT/scripts/setup_env.sh" | tail -n 1)"
cd "$ROOT"
# nerfstudio 1.1.5 on torch 2.13 prints deprecation notices at every import; keep the demo's output readable
export PYTHONWARNINGS="${PYTHONWARNINGS:-ignore::FutureWarning,ignore::DeprecationWarning}"
exec "$VENV/bin/python" scripts/demo.py "$@"
