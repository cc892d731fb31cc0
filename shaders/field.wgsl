// The SDF field's input row on the device: `[x (raw columns), encoding (enc columns)]` with the
// encoding's inactive (coarse-to-fine) columns zeroed, and the backward that takes the encoding's
// part of the row gradient back out. Launched by nn::field (Rust mirror: RowParams).
struct RowParams {
    n: u32,
    raw: u32,
    enc: u32,
    kept: u32,
};

@group(0) @binding(0) var<uniform> params: RowParams;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;

// a = x [n, raw], b = encoding [n, enc] → out [n, raw + enc].
@compute @workgroup_size(256)
fn assemble(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let w = params.raw + params.enc;
    let i = linear_index(gid, nwg, 256u);
    if (i >= params.n * w) { return; }
    let row = i / w;
    let c = i % w;
    if (c < params.raw) {
        out[i] = a[row * params.raw + c];
    } else if (c - params.raw < params.kept) {
        out[i] = b[row * params.enc + c - params.raw];
    } else {
        out[i] = 0.0;
    }
}

// a = d(row) [n, raw + enc] (b unused) → out = d(encoding) [n, enc], inactive columns 0.
@compute @workgroup_size(256)
fn split(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= params.n * params.enc) { return; }
    let row = i / params.enc;
    let c = i % params.enc;
    if (c < params.kept) {
        out[i] = a[row * (params.raw + params.enc) + params.raw + c];
    } else {
        out[i] = 0.0;
    }
}
