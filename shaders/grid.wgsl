// Analytic SDF evaluated on a regular grid. Launched by src/mesh/grid.rs
// (Rust mirror: GridParams). The shape formulas mirror AnalyticShape::sdf in src/mesh/field.rs.
struct GridParams {
    // xyz: scene position of node (0, 0, z0); w unused.
    origin: vec4<f32>,
    // xyz: node spacing; w unused.
    spacing: vec4<f32>,
    // x, y: nodes per axis; z: nodes in this slab along z; w: first z index of the slab.
    dims: vec4<u32>,
    // x: shape id (0 sphere, 1 torus, 2 bowl, 3 rounded box); yzw unused.
    shape: vec4<u32>,
};

@group(0) @binding(0) var<uniform> params: GridParams;
@group(0) @binding(1) var<storage, read_write> values: array<f32>;

fn smin_poly(a: f32, b: f32, k: f32) -> f32 {
    let h = max(k - abs(a - b), 0.0) / k;
    return min(a, b) - h * h * k * 0.25;
}

fn shape_sdf(id: u32, p: vec3<f32>) -> f32 {
    switch id {
        case 0u: {
            return length(p) - 0.8;
        }
        case 1u: {
            let q = vec2<f32>(length(p.xz) - 0.55, p.y);
            return length(q) - 0.22;
        }
        case 2u: {
            let r = 0.75;
            let h = 0.2;
            let t = 0.04;
            let w = sqrt(r * r - h * h);
            let q = vec2<f32>(length(p.xz), p.y);
            var bowl: f32;
            if (h * q.x < w * q.y) {
                bowl = length(q - vec2<f32>(w, h)) - t;
            } else {
                bowl = abs(length(q) - r) - t;
            }
            let ball = length(p - vec3<f32>(0.0, -0.44, 0.0)) - 0.3;
            return smin_poly(bowl, ball, 0.1);
        }
        default: {
            let b = vec3<f32>(0.55, 0.35, 0.45);
            let rad = 0.1;
            let q = abs(p) - b + vec3<f32>(rad);
            return length(max(q, vec3<f32>(0.0))) + min(max(q.x, max(q.y, q.z)), 0.0) - rad;
        }
    }
}

@compute @workgroup_size(256)
fn eval_grid(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 256u);
    let nx = params.dims.x;
    let ny = params.dims.y;
    let n = nx * ny * params.dims.z;
    if (i >= n) { return; }
    let x = i % nx;
    let y = (i / nx) % ny;
    let z = i / (nx * ny);
    let p = params.origin.xyz + params.spacing.xyz * vec3<f32>(f32(x), f32(y), f32(z));
    values[i] = shape_sdf(params.shape.x, p);
}
