#!/usr/bin/env bash
# Install tensegrity-gym and everything it needs into the current Python environment.
set -euo pipefail
cd "$(dirname "$0")/.."
# A plain `torch` requirement (stable-baselines3 brings one) pulls several GB of CUDA
# packages; the CPU build of torch 2.13.0 goes in first so that nothing else is fetched.
if ! python -c "import torch" >/dev/null 2>&1; then
    python -m pip install --quiet "torch==2.13.0"
fi
python -m pip install --quiet -e ".[dev]"
