#!/usr/bin/env bash
# Release check: thousands of damaged inputs through the CLI (tests/fuzz_inputs.rs, the ignored
# `fuzz_large` test), then a summary table: format x cases x clean errors x accepted x crashes.
#
#   scripts/fuzz.sh [CASES] [SEED]      defaults: 5000 cases, seed 1
#
# Environment: PII_FUZZ_THREADS (default 2), CARGO_PROFILE_ARGS (e.g. "--release"; the default
# is the test profile, the one the test command uses). Exits non-zero if any case crashed.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"
export PII_FUZZ_CASES="${1:-${PII_FUZZ_CASES:-5000}}"
export PII_FUZZ_SEED="${2:-${PII_FUZZ_SEED:-1}}"
export PII_FUZZ_THREADS="${PII_FUZZ_THREADS:-2}"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
# shellcheck disable=SC2086
cargo test ${CARGO_PROFILE_ARGS:-} --test fuzz_inputs -- --ignored --exact fuzz_large --nocapture
