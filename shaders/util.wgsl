// Elementwise utility kernels. Launched by backend::gpu::util_kernels (Rust mirror: AxpyParams).
struct AxpyParams {
    n: u32,
    a: f32,
    _pad0: u32,
    _pad1: u32,
};

@group(0) @binding(0) var<uniform> params: AxpyParams;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

@compute @workgroup_size(256)
fn axpy(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    if (i >= params.n) { return; }
    y[i] = params.a * x[i] + y[i];
}
