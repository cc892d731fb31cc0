#!/usr/bin/env bash
# The project's test command (README, .ci/run): installs what the tests need, then runs every test.
# Rust tests run on the cpu backend and on lavapipe (wgpu); Python checks (Blender, usd-core,
# glTF-Validator) are driven from the Rust integration tests through PII_PYTHON / PII_GLTF_VALIDATOR.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"
bash scripts/setup.sh
export PII_VENV="${PII_VENV:-$repo/.venv}"
export PII_PYTHON="$PII_VENV/bin/python"
export PII_GLTF_VALIDATOR="$repo/scripts/gltf_validate.mjs"
export PII_SHARED_DATA="${PII_SHARED_DATA:-$repo/../shared/data}"
# lavapipe complains without a runtime dir.
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
cargo test --locked "$@"
