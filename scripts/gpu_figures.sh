#!/usr/bin/env bash
# The GPU figures in one call: what a session with a lent GPU runs (the `device` tool's 15 minutes
# allow one build-free pass of this and a shorter rerun). Every comparison is side by side on the
# same machine: wgpu against the cpu backend on its cores, and wgpu with the device optimiser
# against the host one.
#
#   PII=<pii-bake binary> OUT=<folder> PARTS="bake profile train bench material nn" scripts/gpu_figures.sh [STAGE1_ITERS] [STAGE2_ITERS]
#
# PARTS picks what runs, in this order (material before bench): `bake` (the README's quick-start
# bake of the bundled example, default preset, with --backend auto (stage 2's steps on whichever
# backend timed faster), wgpu and cpu, each timed end to end, Blender check off), `profile` (every
# kernel timed over 50 stage-1 and 30 stage-2 steps), `train` (stage 1 for
# STAGE1_ITERS on wgpu, wgpu with the host optimiser and cpu, then stage 2 for STAGE2_ITERS on each
# backend), `bench` (`bench train` on wgpu, its default variants, BENCH_SECONDS of training each,
# default 40: Chamfer against wall time), `material` (a default stage 1, then `bench material` on
# wgpu: 32 lobes, indirect ours and none, 2 relit views), `nn` (`bench nn`). Default: all six. STEP_TIMEOUT (s, default 300) bounds each run so
# that a slow one cannot spend the lease. Other defaults: PII=target/release/pii-bake, OUT=out/gpu,
# 300 and 300 iterations; NN_ARGS: extra `bench nn` arguments (a quick local check of this script
# on lavapipe: NN_ARGS="--networks fast --batches 64 --iters 1 --gemm-rows 64", BAKE_ARGS="--iterations
# 3 --material-iterations 3", PROFILE_ITERS=3 and 3 3; BAKE_ARGS go to both
# bakes, PROFILE_ITERS replaces the profiles' step counts). Writes
# OUT/summary.txt (one line per run: wall time, it/s, waits, launches, held-out PSNR),
# OUT/kernels.txt (the profiled runs' kernels per step, costliest first), OUT/log.txt and
# OUT/reports.tar.gz (every report). A binary built elsewhere can be carried stripped
# (`strip -o .gpu/pii-bake target/release/pii-bake`; the debug-info build is over 100 MB).
set -uo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"
PII="${PII:-target/release/pii-bake}"
OUT="${OUT:-out/gpu}"
S1="${1:-300}"
S2="${2:-300}"
PARTS="${PARTS:-bake profile train bench material nn}"
STEP_TIMEOUT="${STEP_TIMEOUT:-300}"
scene=tests/data/example
runs="$(mktemp -d)"
mkdir -p "$OUT"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
log="$OUT/log.txt"
: >"$log"

step() {
    echo "== $*" | tee -a "$log"
    local t0=$SECONDS
    timeout "$STEP_TIMEOUT" "$@" >>"$log" 2>&1
    local rc=$?
    echo "   ($((SECONDS - t0)) s, exit $rc)" | tee -a "$log"
    return 0
}
want() { case " $PARTS " in *" $1 "*) return 0 ;; esac; return 1; }

step "$PII" devices
if want bake; then
    # The quick-start path, end to end: stage 1 + stage 2 + export + eval, each backend.
    step "$PII" --backend auto bake "$scene" --out "$runs/bake_auto" --no-blender-check ${BAKE_ARGS:-}
    step "$PII" --backend wgpu bake "$scene" --out "$runs/bake_wgpu" --no-blender-check ${BAKE_ARGS:-}
    step "$PII" --backend cpu bake "$scene" --out "$runs/bake_cpu" --no-blender-check ${BAKE_ARGS:-}
fi
if want profile; then
    # Where the GPU's time goes: every kernel timed (slower than unprofiled; a diagnosis).
    step "$PII" --backend wgpu --profile-kernels -q train "$scene" --out "$runs/wgpu_profile" --stage geometry --iterations "${PROFILE_ITERS:-50}"
    if [ -f "$runs/bake_wgpu/run/train_report.json" ]; then
        cp -r "$runs/bake_wgpu/run" "$runs/wgpu_profile_s2"
        rm -f "$runs/wgpu_profile_s2"/material*
        step "$PII" --backend wgpu --profile-kernels -q train "$scene" --out "$runs/wgpu_profile_s2" --stage material --material-iterations "${PROFILE_ITERS:-30}"
    fi
fi
if want train; then
    # Stage 1, same seed and data: wgpu (device optimiser, the default), wgpu (host optimiser), cpu.
    step "$PII" --backend wgpu -q train "$scene" --out "$runs/wgpu" --stage geometry --iterations "$S1"
    step "$PII" --backend wgpu -q train "$scene" --out "$runs/wgpu_host_adam" --stage geometry --iterations "$S1" --geometry-set device_optimiser=false
    step "$PII" --backend cpu -q train "$scene" --out "$runs/cpu" --stage geometry --iterations "$S1"
    # Stage 2 on the wgpu run's geometry, each backend.
    cp -r "$runs/wgpu" "$runs/wgpu_s2" 2>/dev/null && cp -r "$runs/wgpu" "$runs/cpu_s2" 2>/dev/null
    step "$PII" --backend wgpu -q train "$scene" --out "$runs/wgpu_s2" --stage material --material-iterations "$S2"
    step "$PII" --backend cpu -q train "$scene" --out "$runs/cpu_s2" --stage material --material-iterations "$S2"
fi
if want material; then
    step "$PII" --backend wgpu -q train "$scene" --out "$runs/material_s1" --stage geometry
    step "$PII" --backend wgpu -q bench material --run "$runs/material_s1" --out "$runs/bench_material" --lobes 32 --indirect ours none --relight-views 2
fi
if want bench; then
    step "$PII" --backend wgpu -q bench train --out "$runs/bench_train" --seconds "${BENCH_SECONDS:-40}"
fi
if want nn; then
    # shellcheck disable=SC2086
    step "$PII" --backend wgpu bench nn ${NN_ARGS:-} --out "$runs/nn_wgpu.json"
fi

python3 - "$runs" "$OUT" <<'EOF' || echo "summary failed" >>"$log"
import json, pathlib, sys
runs, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
lines = []
def load(path):
    return json.loads(path.read_text()) if path.is_file() else None
def run_line(name, r):
    g = r.get("gpu_per_step") or {}
    ev = r.get("eval") or {}
    return (f"{name:20} {r['it_per_s']:8.2f} it/s  train {r.get('seconds', {}).get('train', float('nan')):7.1f} s  "
            f"waits {g.get('waits', 0):6.1f} ({1e3 * g.get('wait_seconds', 0):.2f} ms)  launches {g.get('dispatches', 0):6.1f}  "
            f"thread cpu {1e3 * (r.get('training_thread_cpu_seconds_per_step') or 0):.2f} ms  "
            f"eval {ev.get('psnr', float('nan')):.2f} dB  [{r['backend']}]"
            + (f"\n{'':22}host per step: {g.get('buffers', 0):.1f} buffers made in {1e3 * g.get('buffer_seconds', 0):.2f} ms ({g.get('reused_buffers', 0):.1f} reused), "
               f"bind groups {1e3 * g.get('bind_group_seconds', 0):.2f} ms, recording + submitting {1e3 * g.get('queue_seconds', 0):.2f} ms" if g else ""))
for name in ["bake_auto", "bake_wgpu", "bake_cpu"]:
    b = load(runs / name / "bake_report.json")
    if b is None:
        lines.append(f"{name:20} no bake report")
        continue
    sec = b.get("seconds", {})
    lines.append(f"{name:20} total {sec.get('total', float('nan')):7.1f} s = stage 1 {sec.get('stage1', float('nan')):.1f} + stage 2 {sec.get('stage2', float('nan')):.1f} + export {sec.get('export', float('nan')):.1f}")
    for stage, report in [("stage 1", "train_report.json"), ("stage 2", "material_report.json")]:
        r = load(runs / name / "run" / report)
        if r is not None:
            lines.append(run_line(f"  {stage}", r))
            if stage == "stage 2":
                lines.append("    steps on " + json.dumps(r.get("step_backend")))
                lines.append("    eval " + json.dumps(r.get("eval"))[:800])
    lines.append("  ground truth " + json.dumps(b.get("ground_truth"))[:800])
for name in ["wgpu", "wgpu_host_adam", "cpu", "wgpu_profile", "wgpu_profile_s2", "wgpu_s2", "cpu_s2"]:
    r = load(runs / name / ("material_report.json" if name.endswith("_s2") else "train_report.json"))
    if r is not None:
        lines.append(run_line(name, r))
tta = runs / "bench_train" / "bench-train-time-to-accuracy.csv"
if tta.is_file():
    lines.append("bench train, time to accuracy (each variant against the first):")
    lines += ["  " + row for row in tta.read_text().splitlines()]
(out / "summary.txt").write_text("\n".join(lines) + "\n")
kernels = []
for name in ["wgpu_profile", "wgpu_profile_s2"]:
    r = load(runs / name / ("material_report.json" if name.endswith("_s2") else "train_report.json"))
    ks = (r or {}).get("gpu_kernels_per_step") or []
    total = sum(x["seconds"] for x in ks) or 1e-30
    kernels.append(f"# {name}: {1e3 * total:.3f} ms of kernels per step")
    kernels += [f"{x['kernel']:32} {1e3 * x['seconds']:9.3f} ms {100 * x['seconds'] / total:5.1f}% {x['launches']:7.1f} launches" for x in ks]
(out / "kernels.txt").write_text("\n".join(kernels) + "\n")
EOF
tar -czf "$OUT/reports.tar.gz" -C "$runs" $(cd "$runs" && ls -d nn_wgpu.json */*_report.json */run/*_report.json */*.csv */run/*.csv bench_train/* bench_material/bench-material.* 2>/dev/null) 2>>"$log"
cat "$OUT/summary.txt" 2>/dev/null
