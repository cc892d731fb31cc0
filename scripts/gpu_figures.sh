#!/usr/bin/env bash
# The GPU figures in one call: what a session with a lent GPU runs (the `device` tool's 15 minutes
# allow one build-free pass of this, ~5-8 minutes on an H100, and a rerun). Every comparison is
# side by side on the same machine: wgpu against the cpu backend on its cores, and wgpu with the
# device optimiser against the host one.
#
#   PII=<pii-bake binary> OUT=<folder> scripts/gpu_figures.sh [STAGE1_ITERS] [STAGE2_ITERS]
#
# defaults: PII=target/release/pii-bake, OUT=out/gpu, 300 stage-1 and 300 stage-2 iterations on
# the bundled example; NN_ARGS: extra `bench nn` arguments (a quick local check of this script on
# lavapipe: NN_ARGS="--networks fast --batches 64 --iters 1 --gemm-rows 64" and 3 3). Writes OUT/summary.txt (one line per run: it/s, waits, launches, held-out
# PSNR), OUT/kernels.txt (the profiled run's kernels per step, costliest first), OUT/log.txt and
# OUT/reports.tar.gz (every report). A binary built elsewhere can be carried stripped
# (`strip -o .gpu/pii-bake target/release/pii-bake`; the debug-info build is over 100 MB).
set -uo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"
PII="${PII:-target/release/pii-bake}"
OUT="${OUT:-out/gpu}"
S1="${1:-300}"
S2="${2:-300}"
scene=tests/data/example
runs="$(mktemp -d)"
mkdir -p "$OUT"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
log="$OUT/log.txt"
: >"$log"

step() {
    echo "== $*" | tee -a "$log"
    "$@" >>"$log" 2>&1
    local rc=$?
    [ $rc -eq 0 ] || echo "   (exit $rc)" | tee -a "$log"
    return 0
}

step "$PII" devices
# shellcheck disable=SC2086
step "$PII" --backend wgpu bench nn ${NN_ARGS:-} --out "$runs/nn_wgpu.json"
# Stage 1, same seed and data: wgpu (device optimiser, the default), wgpu (host optimiser), cpu.
step "$PII" --backend wgpu -q train "$scene" --out "$runs/wgpu" --stage geometry --iterations "$S1"
step "$PII" --backend wgpu -q train "$scene" --out "$runs/wgpu_host_adam" --stage geometry --iterations "$S1" --geometry-set device_optimiser=false
step "$PII" --backend cpu -q train "$scene" --out "$runs/cpu" --stage geometry --iterations "$S1"
# Where the GPU's time goes: every kernel timed (slower than unprofiled; a diagnosis).
step "$PII" --backend wgpu --profile-kernels -q train "$scene" --out "$runs/wgpu_profile" --stage geometry --iterations 50
# Stage 2 on the wgpu run's geometry, each backend.
cp -r "$runs/wgpu" "$runs/wgpu_s2" 2>/dev/null && cp -r "$runs/wgpu" "$runs/cpu_s2" 2>/dev/null
step "$PII" --backend wgpu -q train "$scene" --out "$runs/wgpu_s2" --stage material --material-iterations "$S2"
step "$PII" --backend cpu -q train "$scene" --out "$runs/cpu_s2" --stage material --material-iterations "$S2"

python3 - "$runs" "$OUT" <<'EOF' || echo "summary failed" >>"$log"
import json, pathlib, sys
runs, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
lines = []
for name in ["wgpu", "wgpu_host_adam", "cpu", "wgpu_profile", "wgpu_s2", "cpu_s2"]:
    report = runs / name / ("material_report.json" if name.endswith("_s2") else "train_report.json")
    if not report.is_file():
        lines.append(f"{name:16} no report")
        continue
    r = json.loads(report.read_text())
    g = r.get("gpu_per_step") or {}
    lines.append(f"{name:16} {r['it_per_s']:8.2f} it/s  waits {g.get('waits', 0):6.1f} ({1e3 * g.get('wait_seconds', 0):.2f} ms)  "
                 f"launches {g.get('dispatches', 0):6.1f}  thread cpu {1e3 * (r.get('training_thread_cpu_seconds_per_step') or 0):.2f} ms  "
                 f"held-out {r['eval']['psnr']:.2f} dB  [{r['backend']}]")
(out / "summary.txt").write_text("\n".join(lines) + "\n")
k = runs / "wgpu_profile" / "train_report.json"
if k.is_file():
    ks = json.loads(k.read_text()).get("gpu_kernels_per_step") or []
    total = sum(x["seconds"] for x in ks) or 1e-30
    (out / "kernels.txt").write_text("".join(f"{x['kernel']:32} {1e3 * x['seconds']:9.3f} ms {100 * x['seconds'] / total:5.1f}% {x['launches']:7.1f} launches\n" for x in ks))
EOF
tar -czf "$OUT/reports.tar.gz" -C "$runs" $(cd "$runs" && ls -d nn_wgpu.json */train_report.json */material_report.json 2>/dev/null) 2>>"$log"
cat "$OUT/summary.txt" 2>/dev/null
