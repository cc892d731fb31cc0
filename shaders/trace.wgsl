// Primary-ray tracing loops on the device (render::device; Rust mirror: TraceParams). The host
// tracer (render::trace) is the reference: sphere tracing's per-ray step and the secant
// refinement below follow its logic line for line, so the field's values never leave the device
// between steps. Each step is `*_points` (where every ray or bracket evaluates next), one field
// evaluation on the device (its outputs `[n, stride]`, the SDF in column 0), then the update.
struct TraceParams {
    n: u32,
    // Field outputs per point (the SDF is the first).
    stride: u32,
    // Sphere tracing: the step index, and 1 on the last step (a ray still marching is unfinished).
    step: u32,
    last: u32,
    threshold: f32,
    // 1: the local sampler's segments (TraceConfig::local_samples).
    local: u32,
    local_samples: u32,
    sampler_samples: u32,
};

@group(0) @binding(0) var<uniform> params: TraceParams;
// [n, 6]: origin, unit direction.
@group(0) @binding(1) var<storage, read> rays: array<f32>;
// Field outputs at `pts`.
@group(0) @binding(2) var<storage, read> vals: array<f32>;
// Per-ray marching state (STATE floats) or per-bracket secant state (BRACKET floats).
@group(0) @binding(3) var<storage, read_write> state: array<f32>;
@group(0) @binding(4) var<storage, read_write> pts: array<f32>;

// Marching state: t, last point outside, closest value visited, its t, the point before it,
// the sphere interval, then the outcome: status, result t and value, the sampler's segment
// (t0, t1, samples) and the closest visited point it may fall back on (t, value, whether any).
const STATE: u32 = 16u;
const S_T: u32 = 0u;
const S_LAST: u32 = 1u;
const S_BEST_F: u32 = 2u;
const S_BEST_T: u32 = 3u;
const S_BEFORE: u32 = 4u;
const S_LO: u32 = 5u;
const S_HI: u32 = 6u;
const S_STATUS: u32 = 7u;
const S_RES_T: u32 = 8u;
const S_RES_F: u32 = 9u;
const S_SEG_T0: u32 = 10u;
const S_SEG_T1: u32 = 11u;
const S_SEG_N: u32 = 12u;
const S_VIS_T: u32 = 13u;
const S_VIS_F: u32 = 14u;
const S_VIS: u32 = 15u;

// Status codes (Rust: render::device).
const MARCHING: u32 = 0u;
const HIT: u32 = 1u;
const BROKEN: u32 = 2u;
const UNFINISHED: u32 = 3u;

// Bracket (its ray is the ray of the same index): (t, f) outside, (t, f) inside, status
// (MARCHING = open, HIT = converged), the converged t and value.
const BRACKET: u32 = 8u;

fn finite(v: f32) -> bool {
    return (bitcast<u32>(v) & 0x7f800000u) != 0x7f800000u;
}

fn ray_point(ray: u32, t: f32) -> vec3<f32> {
    let o = vec3<f32>(rays[ray * 6u], rays[ray * 6u + 1u], rays[ray * 6u + 2u]);
    let d = vec3<f32>(rays[ray * 6u + 3u], rays[ray * 6u + 4u], rays[ray * 6u + 5u]);
    return o + t * d;
}

fn put_point(i: u32, p: vec3<f32>) {
    pts[i * 3u] = p.x;
    pts[i * 3u + 1u] = p.y;
    pts[i * 3u + 2u] = p.z;
}

fn set_status(b: u32, s: u32) {
    state[b + S_STATUS] = bitcast<f32>(s);
}

fn status_of(b: u32) -> u32 {
    return bitcast<u32>(state[b + S_STATUS]);
}

// Every ray's current point (rays no longer marching keep theirs: evaluated, not used).
@compute @workgroup_size(64)
fn march_points(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 64u);
    if (i >= params.n) { return; }
    put_point(i, ray_point(i, state[i * STATE + S_T]));
}

fn unfinished(b: u32, t0: f32, t1: f32, samples: u32, visit: bool) {
    set_status(b, UNFINISHED);
    state[b + S_SEG_T0] = t0;
    state[b + S_SEG_T1] = t1;
    state[b + S_SEG_N] = bitcast<f32>(samples);
    state[b + S_VIS_T] = state[b + S_BEST_T];
    state[b + S_VIS_F] = state[b + S_BEST_F];
    state[b + S_VIS] = select(0.0, 1.0, visit);
}

// One sphere-tracing step of every marching ray (render::trace's loop body).
@compute @workgroup_size(64)
fn march(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_index(gid, nwg, 64u);
    if (i >= params.n) { return; }
    let b = i * STATE;
    if (status_of(b) != MARCHING) { return; }
    let t = state[b + S_T];
    let fv = vals[i * params.stride];
    if (!finite(fv)) {
        set_status(b, BROKEN);
        state[b + S_RES_T] = t;
        return;
    }
    if (abs(fv) < params.threshold) {
        set_status(b, HIT);
        state[b + S_RES_T] = t;
        state[b + S_RES_F] = fv;
        return;
    }
    if (fv < state[b + S_BEST_F]) {
        state[b + S_BEST_F] = fv;
        state[b + S_BEST_T] = t;
        state[b + S_BEFORE] = state[b + S_LAST];
    }
    let local = params.local != 0u;
    if (fv < 0.0) {
        let t1 = select(state[b + S_HI], t, local);
        let samples = select(params.sampler_samples, params.local_samples, local);
        unfinished(b, state[b + S_LAST], t1, samples, local);
        return;
    }
    if (params.last != 0u) {
        unfinished(b, state[b + S_LO], state[b + S_HI], params.sampler_samples, local);
        return;
    }
    let tn = t + fv;
    if (tn > state[b + S_HI]) {
        if (local) {
            let t1 = min(state[b + S_BEST_T] + state[b + S_BEST_F], state[b + S_HI]);
            unfinished(b, state[b + S_BEFORE], t1, params.local_samples, true);
        } else {
            unfinished(b, state[b + S_LO], state[b + S_HI], params.sampler_samples, false);
        }
        return;
    }
    state[b + S_T] = tn;
    state[b + S_LAST] = t;
}

// render::secant.
fn secant(tl: f32, fl: f32, th: f32, fh: f32) -> f32 {
    let den = fl - fh;
    if (abs(den) < 1e-12) {
        return 0.5 * (tl + th);
    }
    return clamp(tl + fl * (th - tl) / den, min(tl, th), max(tl, th));
}

fn bracket_mid(b: u32) -> f32 {
    return secant(state[b], state[b + 1u], state[b + 2u], state[b + 3u]);
}

// Every bracket's secant point.
@compute @workgroup_size(64)
fn secant_points(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let k = linear_index(gid, nwg, 64u);
    if (k >= params.n) { return; }
    let b = k * BRACKET;
    put_point(k, ray_point(k, bracket_mid(b)));
}

// One secant step of every open bracket (render::trace's secant loop body).
@compute @workgroup_size(64)
fn secant_update(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let k = linear_index(gid, nwg, 64u);
    if (k >= params.n) { return; }
    let b = k * BRACKET;
    if (bitcast<u32>(state[b + 4u]) != MARCHING) { return; }
    let tm = bracket_mid(b);
    let fm = vals[k * params.stride];
    if (!finite(fm) || abs(fm) < params.threshold * 0.1) {
        state[b + 4u] = bitcast<f32>(HIT);
        state[b + 5u] = tm;
        state[b + 6u] = select(0.0, fm, finite(fm));
        return;
    }
    if (fm > 0.0) {
        state[b] = tm;
        state[b + 1u] = fm;
    } else {
        state[b + 2u] = tm;
        state[b + 3u] = fm;
    }
}
