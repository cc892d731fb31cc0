// Fused Adam. Launched by src/nn/adam.rs (Rust mirror: AdamParams); the update formula and
// its cpu twin are documented there.
//
// Bindings (0 uniform, storage from 1 in KernelSpec order):
//   grad_stats:   1 grads (read), 2 partials (rw): per workgroup [sum of squares, non-finite count]
//                 at pair partial_offset + workgroup id (a group step shares one partials buffer)
//   adam_update:  1 grads (read), 2 params (rw), 3 m (rw), 4 v (rw)
// The two entry points are never in one pipeline and share binding numbers.

struct AdamParams {
    n: u32,
    lr: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    weight_decay: f32,
    grad_scale: f32,
    bc1: f32,
    bc2: f32,
    n_threads: u32,
    partial_offset: u32,
    // 1: an entry whose gradient is exactly 0 is left untouched (AdamConfig::skip_zero_gradients).
    skip_zero: u32,
};

@group(0) @binding(0) var<uniform> A: AdamParams;
@group(0) @binding(1) var<storage, read> grads: array<f32>;
@group(0) @binding(2) var<storage, read_write> partials: array<f32>;
@group(0) @binding(2) var<storage, read_write> params: array<f32>;
@group(0) @binding(3) var<storage, read_write> m1: array<f32>;
@group(0) @binding(4) var<storage, read_write> m2: array<f32>;

const STATS_WG: u32 = 256u;
var<workgroup> sum_sq: array<f32, 256>;
var<workgroup> bad: array<f32, 256>;

fn is_finite_f32(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// Grid-stride partial sums; one workgroup writes one pair. 1-D launch of at most 256 groups.
@compute @workgroup_size(256)
fn grad_stats(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
) {
    var s = 0.0;
    var nf = 0.0;
    for (var i = gid.x; i < A.n; i += A.n_threads) {
        let g = grads[i];
        if (is_finite_f32(g)) {
            s += g * g;
        } else {
            nf += 1.0;
        }
    }
    sum_sq[lid] = s;
    bad[lid] = nf;
    workgroupBarrier();
    for (var stride = STATS_WG / 2u; stride > 0u; stride /= 2u) {
        if (lid < stride) {
            sum_sq[lid] += sum_sq[lid + stride];
            bad[lid] += bad[lid + stride];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        let o = 2u * (A.partial_offset + wid.x);
        partials[o] = sum_sq[0];
        partials[o + 1u] = bad[0];
    }
}

@compute @workgroup_size(256)
fn adam_update(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= A.n) { return; }
    if (A.skip_zero != 0u && grads[i] == 0.0) { return; }
    let g = grads[i] * A.grad_scale;
    let m = A.beta1 * m1[i] + (1.0 - A.beta1) * g;
    let v = A.beta2 * m2[i] + (1.0 - A.beta2) * g * g;
    m1[i] = m;
    m2[i] = v;
    let p = params[i];
    params[i] = p - A.lr * ((m / A.bc1) / (sqrt(v / A.bc2) + A.eps) + A.weight_decay * p);
}
