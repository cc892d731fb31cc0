// Input encodings: frequency positional encoding and the multiresolution hash grid.
// Launched by src/nn/encoding.rs (Rust mirrors: EncParams, GridLevelGpu); layouts and
// conventions are documented there and the cpu twins in that file are the reference.
//
// Bindings (0 uniform, storage from 1 in KernelSpec order):
//   freq_forward:          1 x (read), 2 out (rw)
//   freq_backward:         1 x (read), 2 d_out (rw), 3 d_x (rw)
//   grid_forward:          1 levels, 2 params, 3 x (read), 4 out (rw)
//   grid_backward_params:  1 levels, 2 params, 3 x (read), 4 d_out (rw), 5 d_params (rw, atomic)
//   grid_backward_x:       1 levels, 2 params, 3 x (read), 4 d_out (rw), 5 d_x (rw)
// Entry points that are never in one pipeline share binding numbers.

struct EncParams {
    n: u32,
    in_dim: u32,
    n_freqs_or_levels: u32,
    include_input_or_features: u32,
    out_dim: u32,
    table_mask: u32,
    bound: f32,
    inv_2b: f32,
};

struct GridLevelGpu {
    resolution: u32,
    offset: u32,
    entries: u32,
    dense: u32,
};

const WG: u32 = 64u;

@group(0) @binding(0) var<uniform> P: EncParams;

// ---- frequency encoding -----------------------------------------------------------------------

@group(0) @binding(1) var<storage, read> fx: array<f32>;
@group(0) @binding(2) var<storage, read_write> fbuf: array<f32>;
@group(0) @binding(3) var<storage, read_write> fdx: array<f32>;

// One invocation per (point, coordinate).
@compute @workgroup_size(64)
fn freq_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = linear_index(gid, nwg, WG);
    let d_in = P.in_dim;
    if (t >= P.n * d_in) { return; }
    let i = t / d_in;
    let d = t % d_in;
    let v = fx[t];
    var c = i * P.out_dim;
    if (P.include_input_or_features != 0u) {
        fbuf[c + d] = v;
        c += d_in;
    }
    var f = 1.0;
    for (var k = 0u; k < P.n_freqs_or_levels; k++) {
        let a = f * v;
        fbuf[c + d] = sin(a);
        fbuf[c + d_in + d] = cos(a);
        c += 2u * d_in;
        f *= 2.0;
    }
}

@compute @workgroup_size(64)
fn freq_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = linear_index(gid, nwg, WG);
    let d_in = P.in_dim;
    if (t >= P.n * d_in) { return; }
    let i = t / d_in;
    let d = t % d_in;
    let v = fx[t];
    var c = i * P.out_dim;
    var g = 0.0;
    if (P.include_input_or_features != 0u) {
        g = fbuf[c + d];
        c += d_in;
    }
    var f = 1.0;
    for (var k = 0u; k < P.n_freqs_or_levels; k++) {
        let a = f * v;
        g += f * (cos(a) * fbuf[c + d] - sin(a) * fbuf[c + d_in + d]);
        c += 2u * d_in;
        f *= 2.0;
    }
    fdx[t] = g;
}

// ---- hash grid -------------------------------------------------------------------------------

@group(0) @binding(1) var<storage, read> levels: array<GridLevelGpu>;
@group(0) @binding(2) var<storage, read> params: array<f32>;
@group(0) @binding(3) var<storage, read> gx: array<f32>;
@group(0) @binding(4) var<storage, read_write> gbuf: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_params: array<atomic<u32>>;
@group(0) @binding(5) var<storage, read_write> gdx: array<f32>;

struct Cell {
    base: vec3<u32>,
    frac: vec3<f32>,
    inside: vec3<f32>, // 1 inside the cube, 0 where the coordinate was clamped
};

// Mirrors `locate` in encoding.rs: clamp to the cube (NaN goes to the low face), then the cell.
fn locate(p: vec3<f32>, res: u32) -> Cell {
    var cell: Cell;
    let r = f32(res);
    for (var d = 0u; d < 3u; d++) {
        var u = (p[d] + P.bound) * P.inv_2b;
        var inside = 1.0;
        if (!(u > 0.0 && u < 1.0)) {
            u = select(0.0, 1.0, u >= 1.0);
            inside = 0.0;
        }
        let pos = u * r;
        let i = min(u32(floor(pos)), res - 1u);
        cell.base[d] = i;
        cell.frac[d] = pos - f32(i);
        cell.inside[d] = inside;
    }
    return cell;
}

// Table entry of a vertex (relative to the level offset); mirrors `vertex_index`.
fn vertex_index(lvl: GridLevelGpu, v: vec3<u32>) -> u32 {
    if (lvl.dense != 0u) {
        let s = lvl.resolution + 1u;
        return v.x + v.y * s + v.z * s * s;
    }
    return ((v.x * 1u) ^ (v.y * 2654435761u) ^ (v.z * 805459861u)) & P.table_mask;
}

fn grid_point(i: u32) -> vec3<f32> {
    return vec3<f32>(gx[3u * i], gx[3u * i + 1u], gx[3u * i + 2u]);
}

// Trilinear weight of corner c and its derivative with respect to frac.
fn corner_weight(cell: Cell, c: u32) -> vec4<f32> {
    let bit = vec3<u32>(c & 1u, (c >> 1u) & 1u, (c >> 2u) & 1u);
    let on = vec3<f32>(bit);
    let w1 = mix(vec3<f32>(1.0) - cell.frac, cell.frac, on);
    let s = on * 2.0 - vec3<f32>(1.0);
    return vec4<f32>(w1.x * w1.y * w1.z, s.x * w1.y * w1.z, w1.x * s.y * w1.z, w1.x * w1.y * s.z);
}

fn corner_vertex(cell: Cell, c: u32) -> vec3<u32> {
    return cell.base + vec3<u32>(c & 1u, (c >> 1u) & 1u, (c >> 2u) & 1u);
}

// One invocation per (level, point), level-major.
@compute @workgroup_size(64)
fn grid_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = linear_index(gid, nwg, WG);
    let nl = P.n_freqs_or_levels;
    if (t >= P.n * nl) { return; }
    // Level-major: neighbouring invocations read the same level's table at nearby points.
    let i = t % P.n;
    let l = t / P.n;
    let nf = P.include_input_or_features;
    let lvl = levels[l];
    let cell = locate(grid_point(i), lvl.resolution);
    let o = i * P.out_dim + l * nf;
    for (var f = 0u; f < nf; f++) {
        gbuf[o + f] = 0.0;
    }
    for (var c = 0u; c < 8u; c++) {
        let w = corner_weight(cell, c).x;
        let e = (lvl.offset + vertex_index(lvl, corner_vertex(cell, c))) * nf;
        for (var f = 0u; f < nf; f++) {
            gbuf[o + f] += w * params[e + f];
        }
    }
}

// d_params[k] += v with a compare-exchange loop (float atomics are not core WGSL).
fn atomic_add_param(k: u32, v: f32) {
    var old = atomicLoad(&d_params[k]);
    loop {
        let r = atomicCompareExchangeWeak(&d_params[k], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) { break; }
        old = r.old_value;
    }
}

@compute @workgroup_size(64)
fn grid_backward_params(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = linear_index(gid, nwg, WG);
    let nl = P.n_freqs_or_levels;
    if (t >= P.n * nl) { return; }
    // Level-major: neighbouring invocations read the same level's table at nearby points.
    let i = t % P.n;
    let l = t / P.n;
    let nf = P.include_input_or_features;
    let lvl = levels[l];
    let cell = locate(grid_point(i), lvl.resolution);
    let o = i * P.out_dim + l * nf;
    for (var c = 0u; c < 8u; c++) {
        let w = corner_weight(cell, c).x;
        let e = (lvl.offset + vertex_index(lvl, corner_vertex(cell, c))) * nf;
        for (var f = 0u; f < nf; f++) {
            let g = w * gbuf[o + f];
            if (g != 0.0) {
                atomic_add_param(e + f, g);
            }
        }
    }
}

// One invocation per point: sums over levels and corners.
@compute @workgroup_size(64)
fn grid_backward_x(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, WG);
    if (i >= P.n) { return; }
    let nl = P.n_freqs_or_levels;
    let nf = P.include_input_or_features;
    let p = grid_point(i);
    var g = vec3<f32>(0.0);
    for (var l = 0u; l < nl; l++) {
        let lvl = levels[l];
        let cell = locate(p, lvl.resolution);
        let dpos = f32(lvl.resolution) * P.inv_2b;
        let o = i * P.out_dim + l * nf;
        for (var c = 0u; c < 8u; c++) {
            let dw = corner_weight(cell, c).yzw;
            let e = (lvl.offset + vertex_index(lvl, corner_vertex(cell, c))) * nf;
            var s = 0.0;
            for (var f = 0u; f < nf; f++) {
                s += gbuf[o + f] * params[e + f];
            }
            g += s * dw * dpos * cell.inside;
        }
    }
    gdx[3u * i] = g.x;
    gdx[3u * i + 1u] = g.y;
    gdx[3u * i + 2u] = g.z;
}
