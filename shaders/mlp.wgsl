// MLP kernel family, launched by src/nn/mlp.rs (Rust mirrors: GemmParams, EltParams).
// A tiled GEMM with workgroup memory (forward y = u·Wᵀ + b, dX = dZ·W, dW = dZᵀ·U) and
// elementwise kernels: activation forward/backward, skip concat forward/backward, split-K
// reduction, weight norm forward/backward. Bias gradients are GEMMs with a ones vector.

// Mirrors GemmParams (64 bytes):
// C[c_off + i*ldc + j] = (acc ? C : 0) + sum_k A[a_off + i*rsa + k*csa] * B[b_off + k*rsb + j*csb]
//                        (+ bias[bias_off + j] when flags & 1; acc = flags & 2).
// Split-K (k_split > 0): workgroup z sums k in [z*k_split, (z+1)*k_split) and writes its partial
// product at c_off + z*m*ldc; split_reduce adds the partials.
struct GemmParams {
    m: u32,
    n: u32,
    k: u32,
    a_off: u32,
    rsa: u32,
    csa: u32,
    b_off: u32,
    rsb: u32,
    csb: u32,
    c_off: u32,
    ldc: u32,
    bias_off: u32,
    flags: u32,
    k_split: u32,
    _pad1: u32,
    _pad2: u32,
};

// Mirrors EltParams (48 bytes). Each kernel's comment says which fields it reads.
struct EltParams {
    n: u32,
    kind: u32,
    p: f32,
    scale: f32,
    rows: u32,
    cols: u32,
    a: u32,
    d: u32,
    off0: u32,
    off1: u32,
    off2: u32,
    _pad: u32,
};

// ---- GEMM -------------------------------------------------------------------------------
// Workgroup 16x16 threads computes a 64x64 tile of C, 4x4 per thread (vec4 accumulators),
// K in steps of 16 staged through workgroup memory.

@group(0) @binding(0) var<uniform> gp: GemmParams;
@group(0) @binding(1) var<storage, read> ga: array<f32>;
@group(0) @binding(2) var<storage, read> gb: array<f32>;
@group(0) @binding(3) var<storage, read> gbias: array<f32>;
@group(0) @binding(4) var<storage, read_write> gc: array<f32>;

const TILE: u32 = 64u;
const TK: u32 = 16u;
var<workgroup> tile_a: array<vec4<f32>, 256>; // [kk][row / 4], 4 rows per vec4
var<workgroup> tile_b: array<vec4<f32>, 256>; // [kk][col / 4], 4 columns per vec4

@compute @workgroup_size(16, 16)
fn gemm(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let row0 = wid.y * TILE;
    let col0 = wid.x * TILE;
    let tid = lid.y * 16u + lid.x;
    // acc_i holds C[row0 + 4 lid.y + i, col0 + 4 lid.x + 0..3].
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    var k_begin = 0u;
    var k_end = gp.k;
    var c_base = gp.c_off;
    if (gp.k_split > 0u) {
        k_begin = wid.z * gp.k_split;
        k_end = min(gp.k, k_begin + gp.k_split);
        c_base = gp.c_off + wid.z * gp.m * gp.ldc;
    }
    for (var k0 = k_begin; k0 < k_end; k0 += TK) {
        // Each thread loads one vec4 of A (4 rows) and one of B (4 columns) for one kk.
        let kk = tid / 16u;
        let q = tid % 16u;
        let gk = k0 + kk;
        var va = vec4<f32>(0.0);
        var vb = vec4<f32>(0.0);
        if (gk < k_end) {
            for (var i = 0u; i < 4u; i++) {
                let gr = row0 + q * 4u + i;
                if (gr < gp.m) { va[i] = ga[gp.a_off + gr * gp.rsa + gk * gp.csa]; }
                let gcol = col0 + q * 4u + i;
                if (gcol < gp.n) { vb[i] = gb[gp.b_off + gk * gp.rsb + gcol * gp.csb]; }
            }
        }
        tile_a[kk * 16u + q] = va;
        tile_b[kk * 16u + q] = vb;
        workgroupBarrier();
        for (var k = 0u; k < TK; k++) {
            let a = tile_a[k * 16u + lid.y];
            let b = tile_b[k * 16u + lid.x];
            acc0 = fma(vec4<f32>(a.x), b, acc0);
            acc1 = fma(vec4<f32>(a.y), b, acc1);
            acc2 = fma(vec4<f32>(a.z), b, acc2);
            acc3 = fma(vec4<f32>(a.w), b, acc3);
        }
        workgroupBarrier();
    }
    let accs = array<vec4<f32>, 4>(acc0, acc1, acc2, acc3);
    for (var i = 0u; i < 4u; i++) {
        let r = row0 + lid.y * 4u + i;
        if (r >= gp.m) { continue; }
        for (var j = 0u; j < 4u; j++) {
            let c = col0 + lid.x * 4u + j;
            if (c >= gp.n) { continue; }
            var v = accs[i][j];
            if ((gp.flags & 1u) != 0u) { v += gbias[gp.bias_off + c]; }
            let idx = c_base + r * gp.ldc + c;
            if ((gp.flags & 2u) != 0u) { v += gc[idx]; }
            gc[idx] = v;
        }
    }
}

// ---- elementwise ------------------------------------------------------------------------

@group(0) @binding(0) var<uniform> ep: EltParams;
@group(0) @binding(1) var<storage, read> e_in0: array<f32>;
@group(0) @binding(2) var<storage, read> e_in1: array<f32>;
@group(0) @binding(2) var<storage, read_write> e_out1: array<f32>;
@group(0) @binding(3) var<storage, read_write> e_out2: array<f32>;

// Activation codes (Rust: Activation::code): 0 none, 1 relu, 2 leaky relu (p = slope),
// 3 softplus (p = beta), 4 sigmoid. Overflow-safe like the cpu twin.
fn act_f(z: f32, kind: u32, p: f32) -> f32 {
    switch kind {
        case 1u: { return max(z, 0.0); }
        case 2u: { return select(p * z, z, z > 0.0); }
        case 3u: {
            let y = p * z;
            if (y > 20.0) { return z; }
            return (max(y, 0.0) + log(1.0 + exp(-abs(y)))) / p;
        }
        case 4u: { return sigmoid(z); }
        default: { return z; }
    }
}

fn act_d(z: f32, kind: u32, p: f32) -> f32 {
    switch kind {
        case 1u: { return select(0.0, 1.0, z > 0.0); }
        case 2u: { return select(p, 1.0, z > 0.0); }
        case 3u: { return sigmoid(p * z); }
        case 4u: {
            let s = sigmoid(z);
            return s * (1.0 - s);
        }
        default: { return 1.0; }
    }
}

// h = act(z). Reads n, kind, p. Bindings: 1 z, 2 h.
@compute @workgroup_size(256)
fn act_fwd(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= ep.n) { return; }
    e_out1[i] = act_f(e_in0[i], ep.kind, ep.p);
}

// dz = dh * act'(z). Reads n, kind, p. Bindings: 1 z, 2 dh, 3 dz.
@compute @workgroup_size(256)
fn act_bwd(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= ep.n) { return; }
    e_out2[i] = e_in1[i] * act_d(e_in0[i], ep.kind, ep.p);
}

// u[r, c] = scale * (c < a ? h[r, c] : x[r, c - a]), u is [rows, a + d]. Reads n, rows, a, d,
// scale. Bindings: 1 h, 2 x, 3 u.
@compute @workgroup_size(256)
fn concat_fwd(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= ep.n) { return; }
    let w = ep.a + ep.d;
    let r = i / w;
    let c = i % w;
    var v: f32;
    if (c < ep.a) { v = e_in0[r * ep.a + c]; } else { v = e_in1[r * ep.d + c - ep.a]; }
    e_out2[i] = ep.scale * v;
}

// Split du [rows, a + d]: dh[r, c] = scale * du[r, c] for c < a; dx[r, c'] += scale * du[r, a + c'].
// Reads n, rows, a, d, scale. Bindings: 1 du, 2 dh, 3 dx.
@compute @workgroup_size(256)
fn concat_bwd(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= ep.n) { return; }
    let w = ep.a + ep.d;
    let r = i / w;
    let c = i % w;
    let v = ep.scale * e_in0[i];
    if (c < ep.a) {
        e_out1[r * ep.a + c] = v;
    } else {
        let j = r * ep.d + c - ep.a;
        e_out2[j] = e_out2[j] + v;
    }
}

// out[off0 + i] = (kind == 1 ? out[off0 + i] : 0) + sum_s part[s * n + i], s < rows (the
// split-K partial products). Reads n, rows, off0, kind. Bindings: 1 part, 2 out.
@compute @workgroup_size(256)
fn split_reduce(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= ep.n) { return; }
    var s = 0.0;
    if (ep.kind == 1u) { s = e_out1[ep.off0 + i]; }
    for (var k = 0u; k < ep.rows; k++) { s += e_in0[k * ep.n + i]; }
    e_out1[ep.off0 + i] = s;
}

// Weight norm, one thread per output row o of a [rows, cols] layer: v at params[off0],
// g at params[off1], W written at weights[off2]: W_o = g_o v_o / |v_o|. Bindings: 1 params, 2 W.
@compute @workgroup_size(256)
fn wn_fwd(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let o = linear_index(gid, nwg, 256u);
    if (o >= ep.rows) { return; }
    let v0 = ep.off0 + o * ep.cols;
    var n2 = 0.0;
    for (var i = 0u; i < ep.cols; i++) { n2 += e_in0[v0 + i] * e_in0[v0 + i]; }
    let s = e_in0[ep.off1 + o] / sqrt(n2);
    for (var i = 0u; i < ep.cols; i++) { e_out1[ep.off2 + o * ep.cols + i] = s * e_in0[v0 + i]; }
}

// Weight-norm backward for row o: dg = dW·v/|v|, dv = g/|v| (dW - v (v·dW)/|v|^2).
// Bindings: 1 params, 2 dW (dense, at off2), 3 grads (v at off0, g at off1).
@compute @workgroup_size(256)
fn wn_bwd(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let o = linear_index(gid, nwg, 256u);
    if (o >= ep.rows) { return; }
    let v0 = ep.off0 + o * ep.cols;
    let w0 = ep.off2 + o * ep.cols;
    var n2 = 0.0;
    var vdw = 0.0;
    for (var i = 0u; i < ep.cols; i++) {
        let v = e_in0[v0 + i];
        n2 += v * v;
        vdw += v * e_in1[w0 + i];
    }
    let norm = sqrt(n2);
    e_out2[ep.off1 + o] = vdw / norm;
    let gn = e_in0[ep.off1 + o] / norm;
    for (var i = 0u; i < ep.cols; i++) {
        e_out2[v0 + i] = gn * (e_in1[w0 + i] - e_in0[v0 + i] * vdw / n2);
    }
}
