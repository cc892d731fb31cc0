// BRDF-as-SG shading (PhySG's closed form): forward and backward.
// Launched by src/sg/shade_gpu.rs; the reference is src/sg/shade.rs (same formulas, same clamps,
// same order). Params struct mirrors the Rust `ShadeParams`.
//
// The code is written once over dual numbers `Du { v, d }` (value and one tangent). The forward
// runs it with zero tangents; the backward runs it once per input (10 point inputs, then the 7
// parameters of each lobe), seeding that input's tangent: forward-mode AD, exact derivatives of
// the forward as written. Lobe gradients are written per point (`partial[n, K, 7]`) and summed
// over points by `reduce_lobes` (no float atomics, deterministic).
//
// Bindings (0 uniform, storage from 1):
//   shade_forward:  1 points (read), 2 lobes (read), 3 out (rw)
//   shade_backward: 1 points (read), 2 lobes (read), 3 d_out (read), 4 d_points (rw), 5 partial (rw)
//   reduce_lobes:   1 partial (read), 2 d_lobes (rw)

struct ShadeParams {
    n: u32,
    k: u32,
    _pad0: u32,
    _pad1: u32,
};

const WG: u32 = 64u;
const R_MIN: f32 = 0.02;
const LAMBDA_MIN: f32 = 1e-4;
const F0: f32 = 0.04;
const TINY: f32 = 1e-6;
const COS_MU: f32 = 32.7080;
const COS_LAMBDA: f32 = 0.0315;
const COS_ALPHA: f32 = 31.7003;
const POINT_STRIDE: u32 = 10u;
const LOBE_STRIDE: u32 = 7u;

@group(0) @binding(0) var<uniform> P: ShadeParams;
@group(0) @binding(1) var<storage, read> points: array<f32>;
@group(0) @binding(2) var<storage, read> lobes: array<f32>;
@group(0) @binding(3) var<storage, read_write> rgb_out: array<f32>;
@group(0) @binding(3) var<storage, read> d_out: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_points: array<f32>;
@group(0) @binding(5) var<storage, read_write> grad_partial: array<f32>;
@group(0) @binding(1) var<storage, read> r_partial: array<f32>;
@group(0) @binding(2) var<storage, read_write> r_lobes: array<f32>;

// ---- dual numbers -------------------------------------------------------------------------------

struct Du { v: f32, d: f32, };
struct V3 { x: Du, y: Du, z: Du, };
struct Sg { axis: V3, lambda: Du, mu: V3, };

fn c(v: f32) -> Du { return Du(v, 0.0); }
fn add(a: Du, b: Du) -> Du { return Du(a.v + b.v, a.d + b.d); }
fn sub(a: Du, b: Du) -> Du { return Du(a.v - b.v, a.d - b.d); }
fn mul(a: Du, b: Du) -> Du { return Du(a.v * b.v, a.d * b.v + a.v * b.d); }
fn dvd(a: Du, b: Du) -> Du { let q = a.v / b.v; return Du(q, (a.d - q * b.d) / b.v); }
fn neg(a: Du) -> Du { return Du(-a.v, -a.d); }
fn dexp(a: Du) -> Du { let e = exp(a.v); return Du(e, a.d * e); }
fn dsqrt(a: Du) -> Du {
    let s = sqrt(a.v);
    var ds = 0.0;
    if (s > 0.0) { ds = 0.5 / s; }
    return Du(s, a.d * ds);
}
fn max_c(a: Du, lo: f32) -> Du { if (a.v >= lo) { return a; } return c(lo); }
fn min_c(a: Du, hi: f32) -> Du { if (a.v <= hi) { return a; } return c(hi); }

fn v3(x: Du, y: Du, z: Du) -> V3 { return V3(x, y, z); }
fn vdot(a: V3, b: V3) -> Du { return add(add(mul(a.x, b.x), mul(a.y, b.y)), mul(a.z, b.z)); }
fn vscale(a: V3, s: Du) -> V3 { return V3(mul(a.x, s), mul(a.y, s), mul(a.z, s)); }
fn vadd(a: V3, b: V3) -> V3 { return V3(add(a.x, b.x), add(a.y, b.y), add(a.z, b.z)); }
fn vmul(a: V3, b: V3) -> V3 { return V3(mul(a.x, b.x), mul(a.y, b.y), mul(a.z, b.z)); }
fn vnormalize(a: V3) -> V3 {
    let l = max_c(dsqrt(vdot(a, a)), 1e-12);
    return vscale(a, dvd(c(1.0), l));
}

// ---- SG algebra (mirrors shade.rs) --------------------------------------------------------------

fn sg_product(a: Sg, b: Sg) -> Sg {
    let u = vadd(vscale(a.axis, a.lambda), vscale(b.axis, b.lambda));
    let lam = max_c(dsqrt(vdot(u, u)), 1e-12);
    let axis = vscale(u, dvd(c(1.0), lam));
    let expo = dvd(mul(mul(mul(c(2.0), a.lambda), b.lambda), sub(vdot(a.axis, b.axis), c(1.0))),
                   add(add(lam, a.lambda), b.lambda));
    let e = dexp(expo);
    return Sg(axis, lam, vscale(vmul(a.mu, b.mu), e));
}

fn one_minus_exp_neg(x: Du) -> Du {
    if (x.v < 1e-4) {
        return mul(x, sub(c(1.0), mul(x, sub(c(0.5), mul(x, c(1.0 / 6.0))))));
    }
    return sub(c(1.0), dexp(neg(x)));
}

fn hemisphere_int(lambda: Du, cos_beta: Du) -> Du {
    let l = add(lambda, c(TINY));
    let inv = dvd(c(1.0), l);
    let t = dvd(mul(dsqrt(l), add(c(1.6988), mul(c(10.8438), inv))),
                add(add(c(1.0), mul(c(6.2201), inv)), mul(mul(c(10.2415), inv), inv)));
    let inv_a = dexp(neg(t));
    var s: Du;
    if (cos_beta.v >= 0.0) {
        let inv_b = dexp(neg(mul(t, cos_beta)));
        s = dvd(sub(c(1.0), mul(inv_a, inv_b)), sub(add(sub(c(1.0), inv_a), inv_b), mul(inv_a, inv_b)));
    } else {
        let b = dexp(mul(t, cos_beta));
        s = dvd(sub(b, inv_a), mul(sub(c(1.0), inv_a), add(b, c(1.0))));
    }
    let om = one_minus_exp_neg(l);
    let a_u = mul(mul(c(2.0 * PI), om), inv);
    let a_b = mul(a_u, dexp(neg(l)));
    return add(mul(a_b, sub(c(1.0), s)), mul(a_u, s));
}

fn cosine_hemisphere(g: Sg, n: V3) -> V3 {
    let cos_sg = Sg(n, c(COS_LAMBDA), v3(c(COS_MU), c(COS_MU), c(COS_MU)));
    let p = sg_product(cos_sg, g);
    let h1 = hemisphere_int(p.lambda, vdot(p.axis, n));
    let h2 = mul(hemisphere_int(g.lambda, vdot(g.axis, n)), c(COS_ALPHA));
    return V3(sub(mul(p.mu.x, h1), mul(g.mu.x, h2)),
              sub(mul(p.mu.y, h1), mul(g.mu.y, h2)),
              sub(mul(p.mu.z, h1), mul(g.mu.z, h2)));
}

struct Surface { albedo: V3, roughness: Du, normal: V3, view: V3, };
struct Contribution { spec: V3, diff: V3, };

fn lobe_contribution(s: Surface, light_in: Sg) -> Contribution {
    let n = vnormalize(s.normal);
    let v = vnormalize(s.view);
    let light = Sg(vnormalize(light_in.axis), max_c(light_in.lambda, LAMBDA_MIN), light_in.mu);
    let r = min_c(max_c(s.roughness, R_MIN), 1.0);
    let r2 = mul(r, r);
    let inv_r4 = dvd(c(1.0), mul(r2, r2));

    let vn = max_c(vdot(v, n), 0.0);
    let w = vnormalize(vadd(vscale(n, mul(c(2.0), vn)), vscale(v, c(-1.0))));
    let lam_w = dvd(mul(c(2.0), inv_r4), add(mul(c(4.0), vn), c(TINY)));
    let mu_d = mul(inv_r4, c(INV_PI));
    let h = vnormalize(vadd(w, v));
    let vh = max_c(vdot(v, h), 0.0);
    // 2^x = exp(x ln 2)
    let fexp = mul(neg(mul(add(mul(c(5.55473), vh), c(6.8316)), vh)), c(0.69314718055994530942));
    let fresnel = add(c(F0), mul(c(1.0 - F0), dexp(fexp)));
    let d1 = max_c(vdot(w, n), 0.0);
    let d2 = vn;
    let rp1 = add(r, c(1.0));
    let k = mul(mul(rp1, rp1), c(0.125));
    let g1 = dvd(d1, add(add(mul(d1, sub(c(1.0), k)), k), c(TINY)));
    let g2 = dvd(d2, add(add(mul(d2, sub(c(1.0), k)), k), c(TINY)));
    let moi = dvd(mul(mul(fresnel, g1), g2), add(mul(mul(c(4.0), d1), d2), c(TINY)));
    let mu_b = mul(mu_d, moi);
    let brdf = Sg(w, lam_w, v3(mu_b, mu_b, mu_b));
    let spec = cosine_hemisphere(sg_product(light, brdf), n);

    let kd = vscale(s.albedo, c(INV_PI));
    let lit = Sg(light.axis, light.lambda, vmul(light.mu, kd));
    let diff = cosine_hemisphere(lit, n);
    return Contribution(spec, diff);
}

// ---- loading with seeds -------------------------------------------------------------------------

// Input `seed` of a point (0..9) gets tangent 1; seeds >= 10 leave the point constant.
fn load_surface(i: u32, seed: u32) -> Surface {
    var q: array<Du, 10>;
    for (var t = 0u; t < POINT_STRIDE; t++) {
        q[t] = Du(points[i * POINT_STRIDE + t], select(0.0, 1.0, t == seed));
    }
    return Surface(V3(q[0], q[1], q[2]), q[3], V3(q[4], q[5], q[6]), V3(q[7], q[8], q[9]));
}

// Lobe j with its parameter `seed - 10` seeded (seeds < 10 leave the lobe constant).
fn load_lobe(j: u32, seed: u32) -> Sg {
    var q: array<Du, 7>;
    for (var t = 0u; t < LOBE_STRIDE; t++) {
        q[t] = Du(lobes[j * LOBE_STRIDE + t], select(0.0, 1.0, t + POINT_STRIDE == seed));
    }
    return Sg(V3(q[0], q[1], q[2]), q[3], V3(q[4], q[5], q[6]));
}

const NO_SEED: u32 = 1000u;

struct Sums { spec: vec3<f32>, diff: vec3<f32>, };

// Point i's specular and diffuse sums over all lobes, before the final clamps.
fn sums(i: u32) -> Sums {
    let s = load_surface(i, NO_SEED);
    var t = Sums(vec3<f32>(0.0), vec3<f32>(0.0));
    for (var j = 0u; j < P.k; j++) {
        let ct = lobe_contribution(s, load_lobe(j, NO_SEED));
        t.spec += vec3<f32>(ct.spec.x.v, ct.spec.y.v, ct.spec.z.v);
        t.diff += vec3<f32>(ct.diff.x.v, ct.diff.y.v, ct.diff.z.v);
    }
    return t;
}

@compute @workgroup_size(64)
fn shade_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, WG);
    if (i >= P.n) { return; }
    let t = sums(i);
    let rgb = max(t.spec, vec3<f32>(0.0)) + max(t.diff, vec3<f32>(0.0));
    rgb_out[i * 3u] = rgb.x;
    rgb_out[i * 3u + 1u] = rgb.y;
    rgb_out[i * 3u + 2u] = rgb.z;
}

@compute @workgroup_size(64)
fn shade_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, WG);
    if (i >= P.n) { return; }
    // Pass 1: the sums decide which channels the final clamps pass.
    let t = sums(i);
    let dy = vec3<f32>(d_out[i * 3u], d_out[i * 3u + 1u], d_out[i * 3u + 2u]);
    let ws = select(vec3<f32>(0.0), dy, t.spec >= vec3<f32>(0.0));
    let wd = select(vec3<f32>(0.0), dy, t.diff >= vec3<f32>(0.0));
    // Pass 2: one seeded run per input.
    for (var seed = 0u; seed < POINT_STRIDE + LOBE_STRIDE; seed++) {
        let s = load_surface(i, seed);
        var acc = 0.0;
        for (var j = 0u; j < P.k; j++) {
            let ct = lobe_contribution(s, load_lobe(j, seed));
            let g = dot(ws, vec3<f32>(ct.spec.x.d, ct.spec.y.d, ct.spec.z.d))
                  + dot(wd, vec3<f32>(ct.diff.x.d, ct.diff.y.d, ct.diff.z.d));
            if (seed < POINT_STRIDE) {
                acc += g;
            } else {
                grad_partial[(i * P.k + j) * LOBE_STRIDE + (seed - POINT_STRIDE)] = g;
            }
        }
        if (seed < POINT_STRIDE) {
            d_points[i * POINT_STRIDE + seed] = acc;
        }
    }
}

// One thread per lobe parameter: the sum over points of `partial`.
@compute @workgroup_size(64)
fn reduce_lobes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = linear_index(gid, nwg, WG);
    let m = P.k * LOBE_STRIDE;
    if (t >= m) { return; }
    var acc = 0.0;
    for (var i = 0u; i < P.n; i++) {
        acc += r_partial[i * m + t];
    }
    r_lobes[t] = acc;
}
