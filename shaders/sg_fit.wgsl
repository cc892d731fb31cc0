// Gradient of the SG environment fit loss (launched by src/sg/fit.rs, module `gpu`;
// Rust mirror of the params block: `SgFitParams`). cpu twin: `sg::fit::loss_grad_f64`.
//
// Raw parameters, 7 per lobe: [xi.x, xi.y, xi.z, log lambda, log mu.r, log mu.g, log mu.b].
// Loss L = sum_p w_p sum_c (log1p(f_pc) - log1p(t_pc))^2 / 3
//        + beta sum_c (ln(E_c + eps) - ln(T_c + eps))^2 / 3,  E_c = sum_k mu_kc S(lambda_k),
// S(l) = (1 - exp(-2l)) / 2l the solid-angle mean of a unit SG, T_c the map's mean radiance.
// Three passes, no float atomics:
//   residual:      per pixel, e_pc = dL/df_pc and the pixel's loss term.
//   lobe_partials: per (pixel chunk, lobe), the 7 partial sums over the chunk's pixels.
//   reduce:        per lobe, sum over chunks, add the energy term (every invocation sums E over
//                  the K lobes itself) and apply the chain rule; invocation K sums the loss.
struct SgFitParams {
    n_pixels: u32,
    n_lobes: u32,
    n_chunks: u32,
    chunk: u32,
    mean_r: f32,
    mean_g: f32,
    mean_b: f32,
    energy_weight: f32,
};

const ENERGY_EPS: f32 = 1e-6;

@group(0) @binding(0) var<uniform> params: SgFitParams;
@group(0) @binding(1) var<storage, read> raw: array<f32>;
@group(0) @binding(2) var<storage, read> target_rgb: array<f32>;
@group(0) @binding(3) var<storage, read> dir_weight: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> resid: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> partials: array<f32>;
@group(0) @binding(6) var<storage, read_write> grads: array<f32>;
@group(0) @binding(7) var<storage, read_write> loss_out: array<f32>;

struct Lobe {
    a: vec3<f32>,
    inv_n: f32,
    lambda: f32,
    mu: vec3<f32>,
};

fn lobe(k: u32) -> Lobe {
    let o = k * 7u;
    let xi = vec3<f32>(raw[o], raw[o + 1u], raw[o + 2u]);
    let n = max(length(xi), 1e-20);
    var l: Lobe;
    l.a = xi / n;
    l.inv_n = 1.0 / n;
    l.lambda = exp(raw[o + 3u]);
    l.mu = exp(vec3<f32>(raw[o + 4u], raw[o + 5u], raw[o + 6u]));
    return l;
}

// S(lambda) and dS/dlambda (series below 0.05, where f32 cancels).
fn sg_mean_factor(lambda: f32) -> vec2<f32> {
    if (lambda < 0.05) {
        let l = lambda;
        return vec2<f32>(1.0 - l + 2.0 * l * l / 3.0 - l * l * l / 3.0, -1.0 + 4.0 * l / 3.0 - l * l);
    }
    let e = exp(-2.0 * lambda);
    return vec2<f32>((1.0 - e) / (2.0 * lambda), (2.0 * lambda * e - (1.0 - e)) / (2.0 * lambda * lambda));
}

// The fit's mean radiance E_c over all lobes.
fn fit_mean() -> vec3<f32> {
    var e = vec3<f32>(0.0);
    for (var k = 0u; k < params.n_lobes; k++) {
        let l = lobe(k);
        e += l.mu * sg_mean_factor(l.lambda).x;
    }
    return e;
}

// The energy term's residual ln(E_c + eps) - ln(T_c + eps) for the fit's mean radiance e.
fn energy_log_ratio(e: vec3<f32>) -> vec3<f32> {
    return log(e + ENERGY_EPS) - log(vec3<f32>(params.mean_r, params.mean_g, params.mean_b) + ENERGY_EPS);
}

@compute @workgroup_size(64)
fn residual(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 64u);
    if (i >= params.n_pixels) { return; }
    let dw = dir_weight[i];
    var f = vec3<f32>(0.0);
    for (var k = 0u; k < params.n_lobes; k++) {
        let l = lobe(k);
        f += l.mu * exp(l.lambda * (dot(l.a, dw.xyz) - 1.0));
    }
    let t = max(vec3<f32>(target_rgb[i * 3u], target_rgb[i * 3u + 1u], target_rgb[i * 3u + 2u]), vec3<f32>(0.0));
    let r = log(vec3<f32>(1.0) + f) - log(vec3<f32>(1.0) + t);
    let e = 2.0 * dw.w * r / (3.0 * (vec3<f32>(1.0) + f));
    resid[i] = vec4<f32>(e, dw.w * dot(r, r) / 3.0);
}

@compute @workgroup_size(64)
fn lobe_partials(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let idx = linear_index(gid, nwg, 64u);
    if (idx >= params.n_chunks * params.n_lobes) { return; }
    let chunk = idx / params.n_lobes;
    let k = idx % params.n_lobes;
    let l = lobe(k);
    var v = vec3<f32>(0.0);
    var dl = 0.0;
    var dmu = vec3<f32>(0.0);
    let p0 = chunk * params.chunk;
    let p1 = min(p0 + params.chunk, params.n_pixels);
    for (var p = p0; p < p1; p++) {
        let dw = dir_weight[p];
        let e = resid[p].xyz;
        let c = dot(l.a, dw.xyz);
        let g = exp(l.lambda * (c - 1.0));
        let s = dot(e, l.mu) * g;
        v += s * dw.xyz;
        dl += s * (c - 1.0);
        dmu += e * g;
    }
    let o = idx * 7u;
    partials[o] = v.x;
    partials[o + 1u] = v.y;
    partials[o + 2u] = v.z;
    partials[o + 3u] = dl;
    partials[o + 4u] = dmu.x;
    partials[o + 5u] = dmu.y;
    partials[o + 6u] = dmu.z;
}

// grads has n_lobes * 7 entries; invocation n_lobes writes the loss to loss_out[0].
@compute @workgroup_size(64)
fn reduce(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let k = linear_index(gid, nwg, 64u);
    if (k > params.n_lobes) { return; }
    if (k == params.n_lobes) {
        var loss = 0.0;
        for (var p = 0u; p < params.n_pixels; p++) {
            loss += resid[p].w;
        }
        if (params.energy_weight > 0.0) {
            let r = energy_log_ratio(fit_mean());
            loss += params.energy_weight * dot(r, r) / 3.0;
        }
        loss_out[0] = loss;
        return;
    }
    var s = array<f32, 7>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for (var c = 0u; c < params.n_chunks; c++) {
        let o = (c * params.n_lobes + k) * 7u;
        for (var j = 0u; j < 7u; j++) {
            s[j] += partials[o + j];
        }
    }
    let l = lobe(k);
    if (params.energy_weight > 0.0) {
        let e = fit_mean();
        let r = energy_log_ratio(e);
        let q = 2.0 * params.energy_weight * r / (3.0 * (e + ENERGY_EPS));
        let sf = sg_mean_factor(l.lambda);
        // s[3], s[4..6] are multiplied by lambda and mu below.
        s[3] += dot(q, l.mu) * sf.y;
        s[4] += q.x * sf.x;
        s[5] += q.y * sf.x;
        s[6] += q.z * sf.x;
    }
    let v = vec3<f32>(s[0], s[1], s[2]);
    let ga = l.lambda * (v - l.a * dot(l.a, v)) * l.inv_n;
    let o = k * 7u;
    grads[o] = ga.x;
    grads[o + 1u] = ga.y;
    grads[o + 2u] = ga.z;
    grads[o + 3u] = s[3] * l.lambda;
    grads[o + 4u] = s[4] * l.mu.x;
    grads[o + 5u] = s[5] * l.mu.y;
    grads[o + 6u] = s[6] * l.mu.z;
}
