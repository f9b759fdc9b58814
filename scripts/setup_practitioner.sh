#!/usr/bin/env bash
# The tools the practitioner's benchmark (scripts/bench_practitioner.py) calls as a user would: Debian's colmap (CPU
# SIFT) and ffmpeg (ns-process-data needs both), then the project environment. Prints the environment's path last.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
if ! command -v colmap >/dev/null || ! command -v ffmpeg >/dev/null; then
    if command -v apt-get >/dev/null && [ "$(id -u)" = "0" ]; then
        echo "setup: installing colmap and ffmpeg (ns-process-data calls them)" >&2
        (apt-get update -qq && apt-get install -y -qq colmap ffmpeg) >&2
    else
        echo "setup: ns-process-data needs colmap and ffmpeg on PATH (Debian/Ubuntu: apt-get install colmap ffmpeg)" >&2
        exit 1
    fi
fi
bash "$ROOT/scripts/setup_env.sh" | tail -n 1
