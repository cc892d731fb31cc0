//! Fused Adam (decoupled weight decay, AdamW-style) with bias correction, global-norm gradient
//! clipping, learning-rate schedules, and a NaN/Inf guard: a step whose gradient holds a
//! non-finite value is skipped (parameters, moments and the step counter stay untouched) and
//! reported. cpu twin here, WGSL in `shaders/adam.wgsl`.
//!
//! One step with gradient `g`, clip scale `s = min(1, clip / ‖g‖)` (1 without clipping), step
//! counter `t` (1 on the first applied step):
//! ```text
//! m ← β1·m + (1−β1)·s·g          v ← β2·v + (1−β2)·(s·g)²
//! p ← p − lr·( (m / (1−β1^t)) / (sqrt(v / (1−β2^t)) + eps) + weight_decay·p )
//! ```
//! The weight decay is decoupled (Loshchilov & Hutter, `torch.optim.AdamW`), applied to the
//! parameter before the update (`p` on the right is the old value).
//!
//! With `skip_zero_gradients` an entry whose gradient is exactly 0 is left as it is (parameter and
//! both moments), as Instant-NGP does for its hash tables: a step touches a small share of a hash
//! grid's entries, and the untouched ones then cost a read of their gradient instead of a full
//! update (their moments do not decay while no ray reaches them).

use crate::nn::simd::SimdLevel;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::backend::gpu::{shaders, Access, KernelSpec};
use crate::backend::{Backend, BackendError, Tensor};

/// The WGSL kernel family of this module.
pub const ADAM_WGSL: &str = include_str!("../../shaders/adam.wgsl");

/// Adam hyper-parameters. `lr` is the base learning rate a [`LrSchedule`] scales.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    /// Decoupled weight decay (0 = none).
    pub weight_decay: f32,
    /// Clip the gradient's global L2 norm to this value (None = no clipping).
    pub grad_clip_norm: Option<f32>,
    /// Leave entries whose gradient is exactly 0 untouched (see the module docs).
    #[serde(default)]
    pub skip_zero_gradients: bool,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            lr: 1e-3,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 0.0,
            grad_clip_norm: None,
            skip_zero_gradients: false,
        }
    }
}

impl AdamConfig {
    pub fn with_lr(lr: f32) -> Self {
        Self {
            lr,
            ..Default::default()
        }
    }

    pub fn validate(&self) -> Result<(), BackendError> {
        let bad = |m: String| Err(BackendError::Config(format!("adam: {m}")));
        if !(self.lr.is_finite() && self.lr >= 0.0) {
            return bad(format!("lr = {} (finite, >= 0)", self.lr));
        }
        for (name, b) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&b) {
                return bad(format!("{name} = {b} (in [0, 1))"));
            }
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return bad(format!("eps = {} (finite, > 0)", self.eps));
        }
        if !(self.weight_decay.is_finite() && self.weight_decay >= 0.0) {
            return bad(format!(
                "weight_decay = {} (finite, >= 0)",
                self.weight_decay
            ));
        }
        if let Some(c) = self.grad_clip_norm {
            if !(c.is_finite() && c > 0.0) {
                return bad(format!("grad_clip_norm = {c} (finite, > 0)"));
            }
        }
        Ok(())
    }
}

/// Learning-rate schedules: a factor of the base learning rate as a function of the step
/// (0-based: the step about to be taken).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum LrSchedule {
    #[default]
    Constant,
    /// `decay_rate^(step / decay_steps)` (continuous; IDR: 0.1 over the whole run).
    Exponential { decay_rate: f32, decay_steps: u64 },
    /// Linear warm-up from 1/warmup_steps to 1 over `warmup_steps`, then a cosine from 1 down to
    /// `min_factor` at `total_steps` (and `min_factor` after).
    WarmupCosine {
        warmup_steps: u64,
        total_steps: u64,
        min_factor: f32,
    },
    /// `gamma^floor(step / step_size)`.
    Step { step_size: u64, gamma: f32 },
}

impl LrSchedule {
    /// The factor of the base learning rate at `step`.
    pub fn factor_at(&self, step: u64) -> f32 {
        match *self {
            LrSchedule::Constant => 1.0,
            LrSchedule::Exponential {
                decay_rate,
                decay_steps,
            } => (decay_rate as f64).powf(step as f64 / decay_steps.max(1) as f64) as f32,
            LrSchedule::WarmupCosine {
                warmup_steps,
                total_steps,
                min_factor,
            } => {
                if step < warmup_steps {
                    return (step + 1) as f32 / warmup_steps as f32;
                }
                let span = total_steps.saturating_sub(warmup_steps).max(1) as f64;
                let t = ((step - warmup_steps) as f64 / span).min(1.0);
                let c = 0.5 * (1.0 + (std::f64::consts::PI * t).cos());
                (min_factor as f64 + (1.0 - min_factor as f64) * c) as f32
            }
            LrSchedule::Step { step_size, gamma } => {
                (gamma as f64).powi((step / step_size.max(1)).min(i32::MAX as u64) as i32) as f32
            }
        }
    }

    /// The learning rate at `step` for a base learning rate `base_lr`.
    pub fn lr_at(&self, base_lr: f32, step: u64) -> f32 {
        base_lr * self.factor_at(step)
    }
}

/// Adam's moments for one parameter tensor, on the backend the parameters live on.
#[derive(Debug)]
pub struct AdamState {
    pub m: Tensor,
    pub v: Tensor,
    /// Applied steps so far (skipped steps do not count).
    pub step: u64,
}

impl AdamState {
    /// Zero moments for `len` parameters.
    pub fn new(backend: &Backend, len: usize) -> Self {
        Self {
            m: backend.zeros(len),
            v: backend.zeros(len),
            step: 0,
        }
    }
}

/// What one [`Backend::adam_step`] did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AdamStepReport {
    /// False when the gradient held NaN/Inf (or its norm overflowed): nothing was changed.
    pub applied: bool,
    /// Global L2 norm of the gradient before clipping (NaN/Inf when the step was skipped).
    pub grad_norm: f32,
    /// The factor the gradient was scaled by (1 without clipping).
    pub clip_scale: f32,
    /// Non-finite gradient values found.
    pub non_finite: u64,
    /// The state's step counter after this call.
    pub step: u64,
    /// The learning rate used.
    pub lr: f32,
}

/// Constants of one update, computed on the host in f64.
#[derive(Clone, Copy, Debug)]
struct StepConsts {
    lr: f32,
    scale: f32,
    bc1: f32,
    bc2: f32,
}

fn step_consts(cfg: &AdamConfig, lr: f32, norm: f64, t: u64) -> StepConsts {
    let scale = match cfg.grad_clip_norm {
        Some(c) if norm > c as f64 => (c as f64 / norm) as f32,
        _ => 1.0,
    };
    let t = t.min(i32::MAX as u64) as i32;
    let bc1 = (1.0 - (cfg.beta1 as f64).powi(t)) as f32;
    let bc2 = (1.0 - (cfg.beta2 as f64).powi(t)) as f32;
    StepConsts {
        lr,
        scale,
        bc1,
        bc2,
    }
}

/// The element-wise update, one entry at a time: the reference the cpu twin's slice loop
/// ([`update_slices`]) is tested against bit for bit, and what `shaders/adam.wgsl` does.
#[cfg(test)]
fn update(cfg: &AdamConfig, k: &StepConsts, p: &mut f32, g: f32, m: &mut f32, v: &mut f32) {
    if cfg.skip_zero_gradients && g == 0.0 {
        return;
    }
    let g = g * k.scale;
    *m = cfg.beta1 * *m + (1.0 - cfg.beta1) * g;
    *v = cfg.beta2 * *v + (1.0 - cfg.beta2) * g * g;
    let m_hat = *m / k.bc1;
    let v_hat = *v / k.bc2;
    *p -= k.lr * (m_hat / (v_hat.sqrt() + cfg.eps) + cfg.weight_decay * *p);
}

/// Mirrors `AdamParams` in `shaders/adam.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct AdamParams {
    pub n: u32,
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    pub weight_decay: f32,
    pub grad_scale: f32,
    pub bc1: f32,
    pub bc2: f32,
    /// Invocations in the statistics launch (grid-stride).
    pub n_threads: u32,
    /// First (sum, count) pair this statistics launch writes in the shared partials buffer.
    pub partial_offset: u32,
    /// 1: leave entries with a zero gradient untouched (`AdamConfig::skip_zero_gradients`).
    pub skip_zero: u32,
}
const _: () = assert!(std::mem::size_of::<AdamParams>() == 48);

const STATS_WG: u32 = 256;
const MAX_STATS_GROUPS: usize = 256;

/// One parameter tensor of a [`Backend::adam_step_group`].
pub struct AdamItem<'a> {
    pub params: &'a mut Tensor,
    pub grads: &'a Tensor,
    pub state: &'a mut AdamState,
}

impl Backend {
    /// One fused Adam step on `params` with `grads` at learning rate `lr` (usually
    /// `schedule.lr_at(cfg.lr, state.step)`). A non-finite gradient never reaches the parameters:
    /// the step is skipped and reported (`applied = false`). Clipping uses this tensor's norm;
    /// for a model with several tensors use [`Backend::adam_step_group`].
    pub fn adam_step(
        &self,
        cfg: &AdamConfig,
        state: &mut AdamState,
        params: &mut Tensor,
        grads: &Tensor,
        lr: f32,
    ) -> Result<AdamStepReport, BackendError> {
        self.adam_step_group(
            cfg,
            &mut [AdamItem {
                params,
                grads,
                state,
            }],
            lr,
        )
    }

    /// One Adam step over several tensors (a whole model): the gradient norm for clipping is the
    /// global L2 norm over all of them, and a non-finite value in any gradient skips the step for
    /// all of them (nothing changes). Each tensor's bias correction uses its own state's step
    /// counter; the report's `step` is the largest counter after the call. On wgpu the whole
    /// group costs one readback (the gradient statistics) and two batched submissions.
    pub fn adam_step_group(
        &self,
        cfg: &AdamConfig,
        items: &mut [AdamItem<'_>],
        lr: f32,
    ) -> Result<AdamStepReport, BackendError> {
        cfg.validate()?;
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(BackendError::Config(format!(
                "adam: learning rate {lr} (finite, >= 0)"
            )));
        }
        for (i, it) in items.iter().enumerate() {
            let n = it.params.len();
            if it.grads.len() != n || it.state.m.len() != n || it.state.v.len() != n {
                return Err(BackendError::Shape(format!(
                    "adam: tensor {i}: params {n}, grads {}, m {}, v {} values (must be equal)",
                    it.grads.len(),
                    it.state.m.len(),
                    it.state.v.len()
                )));
            }
            if n > u32::MAX as usize {
                return Err(BackendError::Shape(format!(
                    "adam: tensor {i}: {n} parameters exceed 32-bit indexing"
                )));
            }
        }
        let max_step =
            |items: &[AdamItem<'_>]| items.iter().map(|it| it.state.step).max().unwrap_or(0);
        let grads: Vec<&Tensor> = items.iter().map(|it| it.grads).collect();
        let (sumsq, non_finite) = self.adam_grad_stats(&grads)?;
        let norm = sumsq.sqrt();
        if non_finite > 0 || !norm.is_finite() {
            return Ok(AdamStepReport {
                applied: false,
                grad_norm: if non_finite > 0 {
                    f32::NAN
                } else {
                    f32::INFINITY
                },
                clip_scale: 0.0,
                non_finite,
                step: max_step(items),
                lr,
            });
        }
        let scale = self.adam_apply(cfg, items, lr, norm)?;
        Ok(AdamStepReport {
            applied: true,
            grad_norm: norm as f32,
            clip_scale: scale,
            non_finite: 0,
            step: max_step(items),
            lr,
        })
    }

    /// Gradient statistics over several tensors, in order: the squared L2 norm (summed in f64)
    /// and the number of non-finite values. On wgpu one launch per tensor and one wait for a few
    /// partial sums, however large the tensors: the gradient itself never leaves the device.
    pub fn adam_grad_stats(&self, grads: &[&Tensor]) -> Result<(f64, u64), BackendError> {
        match self {
            Backend::Cpu(_) => {
                let host = grads.iter().map(|t| t.host()).collect::<Result<Vec<_>, _>>()?;
                Ok(grad_stats_host(&host))
            }
            Backend::Gpu(g) => {
                let groups: Vec<usize> = grads
                    .iter()
                    .map(|t| t.len().div_ceil(STATS_WG as usize).clamp(1, MAX_STATS_GROUPS))
                    .collect();
                let total: usize = groups.iter().sum();
                let partials = g.zeros_f32("adam.partials", 2 * total.max(1));
                let src = shaders::with_lib(ADAM_WGSL);
                let spec = KernelSpec::new(true, &[Access::Read, Access::ReadWrite]);
                let k = g.kernel("adam", src, "grad_stats", &spec)?;
                let mut batch = g.batch("adam.grad_stats");
                let mut offset = 0;
                for (t, &gr) in grads.iter().zip(&groups) {
                    if t.is_empty() {
                        continue;
                    }
                    let p = AdamParams {
                        n: t.len() as u32,
                        n_threads: gr as u32 * STATS_WG,
                        partial_offset: offset as u32,
                        ..bytemuck::Zeroable::zeroed()
                    };
                    let binds = [t.device()?.into(), (&partials).into()];
                    batch.dispatch(&k, Some(bytemuck::bytes_of(&p)), &binds, [gr as u32, 1, 1])?;
                    offset += gr;
                }
                batch.submit()?;
                let host = g.read_f32(&partials)?;
                let sumsq: f64 = host.chunks_exact(2).map(|c| c[0] as f64).sum();
                let nf: f64 = host.chunks_exact(2).map(|c| c[1] as f64).sum();
                Ok((sumsq, nf as u64))
            }
        }
    }

    /// The update of every item, whose gradients the caller has checked finite
    /// ([`Backend::adam_grad_stats`]); `norm` is the norm clipping reads. Each item's step counter
    /// advances. On wgpu the updates are queued, not waited for. Returns the clip scale.
    pub fn adam_apply(
        &self,
        cfg: &AdamConfig,
        items: &mut [AdamItem<'_>],
        lr: f32,
        norm: f64,
    ) -> Result<f32, BackendError> {
        let mut scale = 1.0;
        match self {
            Backend::Cpu(_) => {
                for it in items.iter_mut() {
                    scale = adam_update_host(
                        cfg,
                        it.state,
                        it.params.host_mut()?,
                        it.grads.host()?,
                        lr,
                        norm,
                    )?;
                }
            }
            Backend::Gpu(g) => {
                let src = shaders::with_lib(ADAM_WGSL);
                let spec = KernelSpec::new(
                    true,
                    &[
                        Access::Read,
                        Access::ReadWrite,
                        Access::ReadWrite,
                        Access::ReadWrite,
                    ],
                );
                let kern = g.kernel("adam", src, "adam_update", &spec)?;
                let mut batch = g.batch("adam.update");
                for it in items.iter_mut() {
                    let n = it.params.len();
                    let k = step_consts(cfg, lr, norm, it.state.step + 1);
                    scale = k.scale;
                    it.state.step += 1;
                    if n == 0 {
                        continue;
                    }
                    let p = AdamParams {
                        n: n as u32,
                        lr: k.lr,
                        beta1: cfg.beta1,
                        beta2: cfg.beta2,
                        eps: cfg.eps,
                        weight_decay: cfg.weight_decay,
                        grad_scale: k.scale,
                        bc1: k.bc1,
                        bc2: k.bc2,
                        n_threads: 0,
                        partial_offset: 0,
                        skip_zero: cfg.skip_zero_gradients as u32,
                    };
                    let binds = [
                        it.grads.device()?.into(),
                        it.params.device()?.into(),
                        it.state.m.device()?.into(),
                        it.state.v.device()?.into(),
                    ];
                    batch.dispatch(
                        &kern,
                        Some(bytemuck::bytes_of(&p)),
                        &binds,
                        crate::backend::gpu::groups_1d(n, 256),
                    )?;
                }
                batch.submit()?;
            }
        }
        Ok(scale)
    }
}

/// The cpu update of one tensor whose gradient the caller has checked (all finite: see
/// [`host_grad_norm`]), with `norm` the norm that clipping reads (the whole model's, or unused
/// without clipping): the element-wise step of [`Backend::adam_step_group`] without its own pass
/// over the gradient. Returns the clip scale.
pub fn adam_update_host(
    cfg: &AdamConfig,
    state: &mut AdamState,
    params: &mut [f32],
    grads: &[f32],
    lr: f32,
    norm: f64,
) -> Result<f32, BackendError> {
    if grads.len() != params.len() || state.m.len() != params.len() || state.v.len() != params.len() {
        return Err(BackendError::Shape(format!(
            "adam: params {}, grads {}, m {}, v {} values (must be equal)",
            params.len(),
            grads.len(),
            state.m.len(),
            state.v.len()
        )));
    }
    let k = step_consts(cfg, lr, norm, state.step + 1);
    let AdamState { m, v, .. } = &mut *state;
    let (m, v) = (m.host_mut()?, v.host_mut()?);
    const CH: usize = 4096;
    params
        .par_chunks_mut(CH)
        .zip(grads.par_chunks(CH))
        .zip(m.par_chunks_mut(CH))
        .zip(v.par_chunks_mut(CH))
        .for_each(|(((p, g), m), v)| update_slices(SimdLevel::detected(), cfg, &k, p, g, m, v));
    state.step += 1;
    Ok(k.scale)
}

/// One Adam step (the first, unclipped) over host slices with the loop built for `level`: what
/// `bench nn` times level against level.
pub(crate) fn update_host_at(level: SimdLevel, cfg: &AdamConfig, params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
    let k = step_consts(cfg, cfg.lr, 0.0, 1);
    update_slices(level, cfg, &k, params, grads, m, v)
}

/// [`update`] over slices, with the loop built for `level` (one this CPU lacks runs at the
/// widest it has). Every level gives the same bits.
fn update_slices(level: SimdLevel, cfg: &AdamConfig, k: &StepConsts, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    match level.min(SimdLevel::detected()) {
        // SAFETY: the CPU has these features (`SimdLevel::detected` found them).
        SimdLevel::Avx512 => return unsafe { update_slices_avx512(cfg, k, p, g, m, v) },
        SimdLevel::Avx2 => return unsafe { update_slices_avx2(cfg, k, p, g, m, v) },
        SimdLevel::Scalar => {}
    }
    let _ = level;
    update_slices_impl(cfg, k, p, g, m, v)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
unsafe fn update_slices_avx512(cfg: &AdamConfig, k: &StepConsts, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
    update_slices_impl(cfg, k, p, g, m, v)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn update_slices_avx2(cfg: &AdamConfig, k: &StepConsts, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
    update_slices_impl(cfg, k, p, g, m, v)
}

/// [`update`]'s arithmetic on every entry, its result kept where [`update`] would write it
/// (a select, not a branch, so the loop vectorises; a skipped entry's values are computed and
/// dropped). The same operations in the same order as [`update`]: the same bits.
#[inline(always)]
fn update_slices_impl(cfg: &AdamConfig, k: &StepConsts, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
    let n = p.len().min(g.len()).min(m.len()).min(v.len());
    let (p, g, m, v) = (&mut p[..n], &g[..n], &mut m[..n], &mut v[..n]);
    let skip_zero = cfg.skip_zero_gradients;
    for i in 0..n {
        let g0 = g[i];
        let gs = g0 * k.scale;
        let mi = cfg.beta1 * m[i] + (1.0 - cfg.beta1) * gs;
        let vi = cfg.beta2 * v[i] + (1.0 - cfg.beta2) * gs * gs;
        let m_hat = mi / k.bc1;
        let v_hat = vi / k.bc2;
        let pi = p[i] - k.lr * (m_hat / (v_hat.sqrt() + cfg.eps) + cfg.weight_decay * p[i]);
        let keep = skip_zero && g0 == 0.0;
        m[i] = if keep { m[i] } else { mi };
        v[i] = if keep { v[i] } else { vi };
        p[i] = if keep { p[i] } else { pi };
    }
}

/// The global L2 norm of host gradients, or None when any value is non-finite (the step must
/// be skipped). One parallel pass, summed in fixed blocks: the same bits on any thread count.
pub fn host_grad_norm(grads: &[&[f32]]) -> Option<f64> {
    let (sumsq, non_finite) = grad_stats_host(grads);
    (non_finite == 0 && sumsq.is_finite()).then(|| sumsq.sqrt())
}

/// Sum of squares (f64) and non-finite count over several host tensors, in tensor order.
fn grad_stats_host(grads: &[&[f32]]) -> (f64, u64) {
    grads.iter().fold((0.0f64, 0u64), |a, g| {
        let (s, n) = grad_stats_cpu(g);
        (a.0 + s, a.1 + n)
    })
}

/// Sum of squares (f64) and the number of non-finite values.
fn grad_stats_cpu(g: &[f32]) -> (f64, u64) {
    // Blocks of 4096 merged in order: the norm (and the clip scale) has the same bits on any
    // thread count.
    const BLOCK: usize = 4096;
    let level = SimdLevel::detected();
    crate::util::fold_ordered(
        g.len().div_ceil(BLOCK),
        1,
        || (0.0f64, 0u64),
        |acc, b| {
            let (s, n) = block_stats(level, &g[b * BLOCK..((b + 1) * BLOCK).min(g.len())]);
            acc.0 += s;
            acc.1 += n;
        },
        |a, b| {
            a.0 += b.0;
            a.1 += b.1;
        },
    )
}

/// Lanes of [`block_stats`]: this many running sums, added together in a fixed order at the end.
const STAT_LANES: usize = 16;

/// One block's sum of squares (f64) and non-finite count, with the loop built for `level`.
/// Sixteen running sums (value `i` into sum `i % 16`), not one: a single sum is a chain of
/// dependent additions, each waiting for the last (this check was 10% of a stage-1 step on a
/// 2^19-entry hash grid). The same bits at every level and on any thread count.
fn block_stats(level: SimdLevel, g: &[f32]) -> (f64, u64) {
    #[cfg(target_arch = "x86_64")]
    match level.min(SimdLevel::detected()) {
        // SAFETY: the CPU has these features (`SimdLevel::detected` found them).
        SimdLevel::Avx512 => return unsafe { block_stats_avx512(g) },
        SimdLevel::Avx2 => return unsafe { block_stats_avx2(g) },
        SimdLevel::Scalar => {}
    }
    let _ = level;
    block_stats_impl(g)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
unsafe fn block_stats_avx512(g: &[f32]) -> (f64, u64) {
    block_stats_impl(g)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn block_stats_avx2(g: &[f32]) -> (f64, u64) {
    block_stats_impl(g)
}

#[inline(always)]
fn block_stats_impl(g: &[f32]) -> (f64, u64) {
    let mut sums = [0.0f64; STAT_LANES];
    let mut bad = [0u32; STAT_LANES];
    let mut chunks = g.chunks_exact(STAT_LANES);
    for c in &mut chunks {
        for j in 0..STAT_LANES {
            let x = c[j];
            let ok = x.abs() < f32::INFINITY;
            let d = x as f64;
            sums[j] += if ok { d * d } else { 0.0 };
            bad[j] += u32::from(!ok);
        }
    }
    for (j, &x) in chunks.remainder().iter().enumerate() {
        let ok = x.abs() < f32::INFINITY;
        let d = x as f64;
        sums[j] += if ok { d * d } else { 0.0 };
        bad[j] += u32::from(!ok);
    }
    let mut s = 0.0f64;
    for v in sums {
        s += v;
    }
    (s, bad.iter().map(|&b| b as u64).sum())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_simd_level_gives_the_one_entry_update_and_the_same_stats() {
        // Entries with zero gradients (kept where sparse), signs, magnitudes over 1e-30..1e3,
        // moments already under way; with and without sparse updates, clipping and decay.
        let n = 10_007;
        let g: Vec<f32> = (0..n).map(|i| if i % 3 == 0 { 0.0 } else { ((i as f32) * 0.37).sin() * 10f32.powi((i % 34) as i32 - 30) }).collect();
        let p0: Vec<f32> = (0..n).map(|i| ((i as f32) * 0.11).cos()).collect();
        let m0: Vec<f32> = (0..n).map(|i| ((i as f32) * 0.05).sin() * 1e-3).collect();
        let v0: Vec<f32> = (0..n).map(|i| ((i as f32) * 0.07).sin().abs() * 1e-5).collect();
        for (skip, decay, scale) in [(true, 0.0, 1.0), (false, 0.0, 1.0), (true, 1e-2, 0.37)] {
            let cfg = AdamConfig { skip_zero_gradients: skip, weight_decay: decay, ..AdamConfig::with_lr(1e-2) };
            let k = StepConsts { lr: 1e-2, scale, bc1: 0.19, bc2: 0.0199 };
            let (mut pw, mut mw, mut vw) = (p0.clone(), m0.clone(), v0.clone());
            for i in 0..n {
                update(&cfg, &k, &mut pw[i], g[i], &mut mw[i], &mut vw[i]);
            }
            for level in SimdLevel::ALL {
                let (mut p, mut m, mut v) = (p0.clone(), m0.clone(), v0.clone());
                update_slices(level, &cfg, &k, &mut p, &g, &mut m, &mut v);
                let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&p), bits(&pw), "params at {level:?}, skip {skip}");
                assert_eq!(bits(&m), bits(&mw), "first moments at {level:?}, skip {skip}");
                assert_eq!(bits(&v), bits(&vw), "second moments at {level:?}, skip {skip}");
            }
            if skip {
                assert!((0..n).step_by(3).all(|i| pw[i] == p0[i] && mw[i] == m0[i]), "zero gradients leave entries alone");
            }
        }
        // The gradient check: the same sum and count at every level; non-finite values counted,
        // the sum within f64 rounding of the plain one.
        let mut g = g;
        g[5] = f32::NAN;
        g[77] = f32::INFINITY;
        g[4095] = f32::NEG_INFINITY;
        let want: f64 = g.iter().filter(|x| x.is_finite()).map(|&x| (x as f64) * (x as f64)).sum();
        let (s0, n0) = block_stats(SimdLevel::Scalar, &g);
        assert_eq!(n0, 3);
        assert!(((s0 - want) / want).abs() < 1e-12, "{s0} vs {want}");
        for level in SimdLevel::ALL {
            let (s, c) = block_stats(level, &g);
            assert_eq!((s.to_bits(), c), (s0.to_bits(), n0), "block stats at {level:?}");
        }
        assert_eq!(grad_stats_cpu(&g).1, 3);
    }

    #[test]
    fn schedules() {
        assert_eq!(LrSchedule::Constant.lr_at(0.5, 1000), 0.5);
        let e = LrSchedule::Exponential {
            decay_rate: 0.1,
            decay_steps: 100,
        };
        assert!((e.factor_at(100) - 0.1).abs() < 1e-7);
        assert!((e.factor_at(50) - 0.1f32.sqrt()).abs() < 1e-6);
        let w = LrSchedule::WarmupCosine {
            warmup_steps: 10,
            total_steps: 110,
            min_factor: 0.1,
        };
        assert!((w.factor_at(0) - 0.1).abs() < 1e-7);
        assert!((w.factor_at(9) - 1.0).abs() < 1e-7);
        assert!((w.factor_at(10) - 1.0).abs() < 1e-7);
        assert!((w.factor_at(60) - 0.55).abs() < 1e-6);
        assert!((w.factor_at(500) - 0.1).abs() < 1e-7);
        let s = LrSchedule::Step {
            step_size: 10,
            gamma: 0.5,
        };
        assert_eq!(s.factor_at(9), 1.0);
        assert_eq!(s.factor_at(25), 0.25);
    }

    #[test]
    fn bad_configs_are_errors() {
        assert!(AdamConfig {
            beta1: 1.0,
            ..Default::default()
        }
        .validate()
        .is_err());
        assert!(AdamConfig {
            grad_clip_norm: Some(0.0),
            ..Default::default()
        }
        .validate()
        .is_err());
        assert!(AdamConfig::default().validate().is_ok());
    }
}
