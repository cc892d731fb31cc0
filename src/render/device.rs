//! The primary tracer's loops on the device (`shaders/trace.wgsl`). Where a field evaluates on
//! the device ([`DeviceSdf`], the fast preset's hash-grid SDF on wgpu), [`super::trace`] runs
//! sphere tracing and the secant refinement there: the field's values stay on the device between
//! steps, and the host looks at the rays' state every [`CHECK_EVERY`] steps (a wait each) instead
//! of after every step. The sampler and the Newton step, one evaluation each, stay on the host.
//!
//! The kernels follow the host loops' logic line for line; every marching ray (or open bracket)
//! is evaluated at every step, including those that finished within a chunk of steps, so the
//! evaluation count is that of the device's work, not the host loop's.

use super::{Rays, Segment, Start, TraceConfig, TraceResult};
use crate::backend::gpu::{groups_1d, shaders, Access, GpuBuffer, GpuContext, Kernel, KernelSpec};
use crate::backend::BackendError;
use std::sync::Arc;

/// A batched SDF that can also evaluate on the device without a wait.
pub trait DeviceSdf {
    fn gpu(&self) -> &GpuContext;
    /// The field at the device points `x` `[n, 3]`, left on the device: `(outputs, stride)`, one
    /// point's SDF every `stride` values.
    fn eval_device(&self, x: &GpuBuffer, n: usize) -> Result<(GpuBuffer, usize), BackendError>;
}

/// Mirrors `TraceParams` in `shaders/trace.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct TraceParams {
    n: u32,
    stride: u32,
    step: u32,
    last: u32,
    threshold: f32,
    local: u32,
    local_samples: u32,
    sampler_samples: u32,
}
const _: () = assert!(std::mem::size_of::<TraceParams>() == 32);

const WGSL: &str = include_str!("../../shaders/trace.wgsl");
const WG: u32 = 64;
/// Floats per ray of the marching state and per secant bracket (`STATE`, `BRACKET` in the WGSL).
const STATE: usize = 16;
const BRACKET: usize = 8;
const MARCHING: u32 = 0;
const HIT: u32 = 1;
const BROKEN: u32 = 2;
const UNFINISHED: u32 = 3;
/// Steps run on the device between two looks at the state. Each look is a round trip (tens of
/// µs on a discrete GPU), each step a handful of launches; looking every 8 steps stops a loop
/// whose rays all finished early without a wait per step.
pub const CHECK_EVERY: usize = 8;
/// Rays per device pass (the field's working set stays that of `stage1::Model::sdf`'s chunks).
const CHUNK: usize = 1 << 16;

fn kernel(g: &GpuContext, entry: &str) -> Result<Arc<Kernel>, BackendError> {
    let spec = KernelSpec::new(true, &[Access::Read, Access::Read, Access::ReadWrite, Access::ReadWrite]);
    g.kernel("trace", &shaders::with_lib(WGSL), entry, &spec)
}

fn ray_rows<'a>(rays: &Rays, idx: impl Iterator<Item = &'a usize>) -> Vec<f32> {
    idx.flat_map(|&i| rays.origins[i].into_iter().chain(rays.dirs[i])).collect()
}

/// Run `steps` steps over the `n` items (rays or brackets, `width` floats of `state` each, their
/// rays' rows in `rays`): `points`, then the field, then `update`, every step. The host looks at
/// the state every [`CHECK_EVERY`] steps, stops once `open` holds for no item, and otherwise
/// carries on with the open items only (their rows uploaded afresh: no wait). Returns every
/// item's final state.
#[allow(clippy::too_many_arguments)]
fn run_steps(
    f: &dyn DeviceSdf,
    (points, update): (&str, &str),
    base: TraceParams,
    steps: usize,
    width: usize,
    rays: Vec<f32>,
    mut state: Vec<f32>,
    open: impl Fn(&[f32]) -> bool,
    evals: &mut usize,
) -> Result<Vec<f32>, BackendError> {
    let g = f.gpu();
    let (kp, ku) = (kernel(g, points)?, kernel(g, update)?);
    // The items on the device, in their order there.
    let mut live: Vec<usize> = (0..state.len() / width).collect();
    let mut step = 0;
    while step < steps && !live.is_empty() {
        let n = live.len();
        let rows = |src: &[f32], w: usize| -> Vec<f32> { live.iter().flat_map(|&i| src[i * w..(i + 1) * w].iter().copied()).collect() };
        let rays_b = g.upload_f32("trace.rays", &rows(&rays, 6));
        let state_b = g.upload_f32("trace.state", &rows(&state, width));
        let pts = g.zeros_f32("trace.points", 3 * n);
        let until = (step + CHECK_EVERY).min(steps);
        for s in step..until {
            let p = TraceParams { n: n as u32, step: s as u32, last: (s + 1 == steps) as u32, ..base };
            g.dispatch(&kp, Some(bytemuck::bytes_of(&p)), &[(&rays_b).into(), (&rays_b).into(), (&state_b).into(), (&pts).into()], groups_1d(n, WG))?;
            let (vals, stride) = f.eval_device(&pts, n)?;
            let p = TraceParams { stride: stride as u32, ..p };
            g.dispatch(&ku, Some(bytemuck::bytes_of(&p)), &[(&rays_b).into(), (&vals).into(), (&state_b).into(), (&pts).into()], groups_1d(n, WG))?;
            *evals += n;
        }
        step = until;
        let st = g.read_f32(&state_b)?;
        for (k, &i) in live.iter().enumerate() {
            state[i * width..(i + 1) * width].copy_from_slice(&st[k * width..(k + 1) * width]);
        }
        live.retain(|&i| open(&state[i * width..(i + 1) * width]));
    }
    Ok(state)
}

fn base_params(cfg: &TraceConfig) -> TraceParams {
    let local = cfg.local_samples >= 2;
    TraceParams {
        n: 0,
        stride: 1,
        step: 0,
        last: 0,
        threshold: cfg.threshold,
        local: local as u32,
        local_samples: cfg.local_samples as u32,
        sampler_samples: cfg.sampler_samples as u32,
    }
}

/// Sphere tracing of `starts` on the device: fills `res` for rays that hit or met a broken
/// field and returns the unfinished rays' sampler segments (as the host loop does).
pub(super) fn sphere_trace(
    f: &dyn DeviceSdf,
    rays: &Rays,
    starts: &[Start],
    cfg: &TraceConfig,
    res: &mut TraceResult,
    evals: &mut usize,
) -> Result<Vec<Segment>, BackendError> {
    let mut unfinished = Vec::new();
    for chunk in starts.chunks(CHUNK) {
        let mut st = vec![0f32; chunk.len() * STATE];
        for (k, s) in chunk.iter().enumerate() {
            let b = &mut st[k * STATE..(k + 1) * STATE];
            b[..7].copy_from_slice(&[s.t0, s.t0, f32::INFINITY, s.t0, s.t0, s.lo, s.hi]);
            b[7] = f32::from_bits(MARCHING);
        }
        let marching = |b: &[f32]| b[7].to_bits() == MARCHING;
        let rows = ray_rows(rays, chunk.iter().map(|s| &s.ray));
        let st = run_steps(f, ("march_points", "march"), base_params(cfg), cfg.sphere_steps + 1, STATE, rows, st, marching, evals)?;
        for (s, b) in chunk.iter().zip(st.chunks_exact(STATE)) {
            let i = s.ray;
            match b[7].to_bits() {
                HIT => {
                    res.hit[i] = true;
                    res.t[i] = b[8];
                    res.points[i] = rays.at(i, b[8]);
                    res.sdf[i] = b[9];
                }
                BROKEN => {
                    res.t[i] = b[8];
                    res.points[i] = rays.at(i, b[8]);
                }
                UNFINISHED => unfinished.push(Segment {
                    ray: i,
                    t0: b[10],
                    t1: b[11],
                    samples: b[12].to_bits() as usize,
                    visited: (b[15] != 0.0).then_some((b[13], b[14])),
                }),
                other => return Err(BackendError::Device(format!("device tracing left ray {i} in state {other}"))),
            }
        }
    }
    Ok(unfinished)
}

/// The secant refinement of `brackets` `(ray, t_lo, f_lo, t_hi, f_hi)` on the device, filling
/// `res` as the host loop does.
pub(super) fn secant(
    f: &dyn DeviceSdf,
    rays: &Rays,
    brackets: &[(usize, f32, f32, f32, f32)],
    cfg: &TraceConfig,
    res: &mut TraceResult,
    evals: &mut usize,
) -> Result<(), BackendError> {
    for chunk in brackets.chunks(CHUNK) {
        let mut st = Vec::with_capacity(chunk.len() * BRACKET);
        for &(_, tl, fl, th, fh) in chunk {
            st.extend([tl, fl, th, fh, f32::from_bits(MARCHING), 0.0, 0.0, 0.0]);
        }
        let open = |b: &[f32]| b[4].to_bits() == MARCHING;
        let rows = ray_rows(rays, chunk.iter().map(|b| &b.0));
        let st = run_steps(f, ("secant_points", "secant_update"), base_params(cfg), cfg.secant_steps, BRACKET, rows, st, open, evals)?;
        for (&(i, ..), b) in chunk.iter().zip(st.chunks_exact(BRACKET)) {
            res.hit[i] = true;
            if b[4].to_bits() == HIT {
                res.t[i] = b[5];
                res.sdf[i] = b[6];
            } else {
                res.t[i] = super::secant(b[0], b[1], b[2], b[3]);
                res.sdf[i] = 0.5 * (b[1] + b[3]);
            }
            res.points[i] = rays.at(i, res.t[i]);
        }
    }
    Ok(())
}

impl DeviceSdf for crate::nn::field::DeviceField<'_> {
    fn gpu(&self) -> &GpuContext {
        crate::nn::field::DeviceField::gpu(self)
    }

    fn eval_device(&self, x: &GpuBuffer, n: usize) -> Result<(GpuBuffer, usize), BackendError> {
        Ok((self.eval(x, n)?, self.out_dim()))
    }
}
