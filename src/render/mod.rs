//! Sphere tracing, secondary rays and the min-SDF along rays: batched over rays, one batched
//! field evaluation per step, so the same loop runs on the cpu backend and on wgpu (the field
//! evaluates its MLP on whichever backend it was given).
//!
//! Everything works in the scene's normalised frame: the object inside the bounding sphere of
//! radius [`TraceConfig::bound`] (1, IDR's convention).
//!
//! Primary rays ([`trace`]), as IDR's ray tracer with the paper's refinement:
//! 1. intersect the bounding sphere; rays that miss it miss the object;
//! 2. sphere tracing from the near intersection, `sphere_steps` steps, a ray converges when
//!    |f| < threshold; a ray that steps past the far intersection misses; a ray that lands
//!    inside (f < 0) or runs out of steps is *unfinished*;
//! 3. unfinished rays: `sampler_samples` uniform samples between the last point known outside
//!    (when tracing overshot) or the near intersection (when it ran out of steps) and the far
//!    intersection; the first sign change (+ → −)
//!    is refined by `secant_steps` secant steps; no sign change = miss. The sampler's smallest
//!    value is that ray's min-SDF point (the mask loss reuses it). The *local* sampler
//!    ([`TraceConfig::local_samples`]) spends its samples where sphere tracing says the answer
//!    is: between the last point outside and the point inside for a ray that overshot, around
//!    the closest visited point for a ray that left the sphere;
//! 4. [`TraceMode::Refined`] (supplementary §6): threshold 1e-3 and one Newton step along the
//!    ray on every hit, `t ← t − f(x)/(∂f/∂t)` with a central difference for `∂f/∂t`.
//!
//! [`TraceMode::Classic`] is the public code's setting (threshold 5e-5, no Newton step).
//!
//! Where the field also evaluates on the device ([`SdfBatch::device`]: the fast preset's
//! hash-grid SDF on wgpu), steps 2 and 3's secant run there ([`device`], `shaders/trace.wgsl`):
//! the host looks at the rays every 8 steps instead of waiting for every step's values. Same
//! logic, same results (bit for bit on lavapipe); the sampler and the Newton step stay here.
//!
//! Where the field comes with a cheap lower bound ([`SdfBatch::lower_bound`]: a render's
//! field bounded by its own sampled grid, [`grid::GridBounded`]), [`trace`] marches each ray on
//! the bound to where the surface can first be, skips the rays it clears, and evaluates the
//! sampler's points only where the bound cannot prove them outside: the same surface for a
//! fraction of the field evaluations (stage 2's renders and `relight`).
//!
//! Secondary rays ([`trace_secondary`]): the same sphere-tracing step from `t = start_offset`
//! for a fixed step count (stage 2 traces from surface points toward each light lobe). On a
//! sampled grid ([`grid::SdfGrid`], stage 2's secondary rays) each ray marches to its end on its
//! own ([`PointSdf::march`]), eight rays at a time in AVX2 lanes where the CPU has them (the
//! scalar march's bits: `bench nn` reports the ratio).
//!
//! The differentiable surface point (implicit differentiation) lives in the trainer
//! (`train::stage1`), which owns the parameters: with `x0` from here,
//! `x(θ) = x0 − v·(f(x0;θ) − f(x0;θ0))/(∇f(x0)·v)`, so a loss's `∂L/∂x` reaches the parameters as
//! `−(∂L/∂x · v)/(∇f·v)` times `∂f(x0)/∂θ`.
//!
//! [`volume`]: NeuS's volume rendering of the SDF (opacity compositing along samples), which
//! stage 1 uses at the start of a run to open concavities a first hit cannot see into.

pub mod device;
pub mod grid;
pub mod volume;

use std::ops::ControlFlow;

use rayon::prelude::*;

use crate::backend::BackendError;
pub use device::DeviceSdf;

/// Tracing variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TraceMode {
    /// IDR's public code: threshold 5e-5, sphere tracing + sampler + secant.
    Classic,
    /// The paper's refined tracing: threshold 1e-3 plus a Newton step along the ray.
    Refined,
}

impl TraceMode {
    pub fn name(self) -> &'static str {
        match self {
            TraceMode::Classic => "classic",
            TraceMode::Refined => "refined",
        }
    }
}

/// Sphere-tracing settings. [`TraceConfig::new`] gives the paper's values for a mode.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TraceConfig {
    pub mode: TraceMode,
    /// Convergence threshold on |f|.
    pub threshold: f32,
    pub sphere_steps: usize,
    pub sampler_samples: usize,
    pub secant_steps: usize,
    /// Radius of the bounding sphere (normalised units).
    pub bound: f32,
    /// Newton step after convergence (refined mode).
    pub newton: bool,
    /// 0: IDR's sampler (every unfinished ray samples `sampler_samples` points over the rest of
    /// its segment). Otherwise the *local* sampler: a ray that overshot samples this many points
    /// between its last point outside and the point inside (the bracket sphere tracing found),
    /// and a ray that left the sphere samples them around its closest visited point; only rays
    /// out of steps sample their whole segment. Run files written before this field read 0.
    #[serde(default)]
    pub local_samples: usize,
}

impl TraceConfig {
    pub fn new(mode: TraceMode) -> Self {
        match mode {
            TraceMode::Classic => Self {
                mode,
                threshold: 5e-5,
                sphere_steps: 10,
                sampler_samples: 100,
                secant_steps: 32,
                bound: 1.0,
                newton: false,
                local_samples: 0,
            },
            TraceMode::Refined => Self {
                mode,
                threshold: 1e-3,
                sphere_steps: 10,
                sampler_samples: 100,
                secant_steps: 32,
                bound: 1.0,
                newton: true,
                local_samples: 0,
            },
        }
    }

    pub fn validate(&self) -> Result<(), BackendError> {
        let ok = self.threshold.is_finite()
            && self.threshold > 0.0
            && self.bound.is_finite()
            && self.bound > 0.0
            && self.sampler_samples >= 2
            && self.local_samples != 1;
        if !ok {
            return Err(BackendError::Config(format!("invalid trace settings {self:?}")));
        }
        Ok(())
    }
}

/// A batch of rays: origins and unit directions, normalised frame.
#[derive(Clone, Debug, Default)]
pub struct Rays {
    pub origins: Vec<[f32; 3]>,
    pub dirs: Vec<[f32; 3]>,
}

impl Rays {
    pub fn len(&self) -> usize {
        self.origins.len()
    }
    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }
    pub fn at(&self, i: usize, t: f32) -> [f32; 3] {
        let (o, d) = (self.origins[i], self.dirs[i]);
        [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]
    }
}

/// The ray's intersection interval `[t_near, t_far]` with the sphere of radius `r` at the
/// origin (t_near clamped at 0 for origins inside), or None.
pub fn sphere_interval(o: [f32; 3], d: [f32; 3], r: f32) -> Option<(f32, f32)> {
    let b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2];
    let c = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - r * r;
    let disc = b * b - c;
    if !(disc > 0.0) {
        return None;
    }
    let s = disc.sqrt();
    let (t0, t1) = (-b - s, -b + s);
    if t1 <= 0.0 {
        return None;
    }
    Some((t0.max(0.0), t1))
}

/// What tracing found for each ray.
#[derive(Clone, Debug, Default)]
pub struct TraceResult {
    /// The ray hit the surface.
    pub hit: Vec<bool>,
    /// Distance along the ray of the hit, or of the min-SDF point for rays that missed.
    pub t: Vec<f32>,
    /// The surface point (hits) or the min-SDF point along the ray (misses; for a ray that
    /// misses the bounding sphere, the point of the ray closest to the centre).
    pub points: Vec<[f32; 3]>,
    /// The field's value at `points` (as traced; before the Newton step for refined hits).
    pub sdf: Vec<f32>,
    /// The ray went through the sampler (did not converge by sphere tracing).
    pub sampled: Vec<bool>,
    /// Field evaluations spent (points).
    pub evaluations: usize,
}

impl TraceResult {
    pub fn hits(&self) -> usize {
        self.hit.iter().filter(|h| **h).count()
    }
}

/// A batched SDF: values at `[n, 3]` points (flattened).
pub trait SdfBatch {
    fn sdf(&self, points: &[f32]) -> Result<Vec<f32>, BackendError>;
    /// The same field evaluated on the device without a wait, where it can be: [`trace`] then
    /// runs its loops there ([`device`]).
    fn device(&self) -> Option<&dyn DeviceSdf> {
        None
    }
    /// The same field evaluated one point at a time, where that is cheap (a sampled grid):
    /// [`trace_secondary`] then marches each ray to its end on its own, the rays in parallel,
    /// instead of gathering every open ray's point for a batch at each step.
    fn pointwise(&self) -> Option<&dyn PointSdf> {
        None
    }
    /// A cheap lower bound of this field, where it has one ([`grid::GridBounded`]): [`trace`]
    /// then skips what the bound proves empty (see [`LowerBound`]).
    fn lower_bound(&self) -> Option<&dyn LowerBound> {
        None
    }
}

/// A cheap point-by-point lower bound `b(p) ≤ f(p)` of a field `f` that is 1-Lipschitz (the
/// assumption sphere tracing makes). [`trace`] uses it twice, leaving every hit where the field
/// alone finds it: sphere tracing on `f` starts where stepping by `b` from the sphere's near
/// intersection first comes within [`LowerBound::near`] of 0 (a ray `b` clears over its whole
/// segment misses, and is recorded as a ray missing the bounding sphere is), and the sampler
/// evaluates `f` only at its samples where `b ≤ 0` (`f > 0` at the others, so the first sign
/// change and its bracket's values are the field's own).
pub trait LowerBound: Sync {
    /// A value `≤ f(p)` (`-∞` where the bound knows nothing).
    fn lower(&self, p: [f32; 3]) -> f32;
    /// Marching by the bound stops this close to 0 (a step that small gains nothing).
    fn near(&self) -> f32;
    /// A stand-in for `f(p)` at a sampler point the bound proves positive: the sampler's
    /// closest point on a ray that misses is taken among the samples' values and these.
    fn estimate(&self, p: [f32; 3]) -> f32;
}

/// Steps of the bound's march at most (a ray out of them starts sphere tracing where it got to).
const BOUND_STEPS: usize = 128;

/// A field cheap enough to evaluate point by point (see [`SdfBatch::pointwise`]).
pub trait PointSdf: Sync {
    fn at(&self, p: [f32; 3]) -> f32;
    /// March rays `first..first + out.len()` of `rays` (a range inside it: panics otherwise)
    /// as [`trace_secondary`] does, one result per ray into `out`. The default is [`march_scalar`]; an override gives its results bit
    /// for bit ([`SdfGrid`](grid::SdfGrid) marches eight rays in SIMD lanes).
    fn march(&self, rays: &Rays, first: usize, m: &March, out: &mut [Marched]) {
        march_scalar(self, rays, first, m, out)
    }
}

/// A secondary march's settings (see [`trace_secondary`]).
#[derive(Clone, Copy, Debug)]
pub struct March {
    pub start_offset: f32,
    pub steps: usize,
    pub threshold: f32,
    pub bound: f32,
}

/// One ray's march: `(hit, t, steps taken)`; `t` is +∞ where it did not hit.
pub type Marched = (bool, f32, usize);

/// [`PointSdf::march`]'s reference: each ray to its end on its own, [`march_step`] by step.
pub fn march_scalar<F: PointSdf + ?Sized>(f: &F, rays: &Rays, first: usize, m: &March, out: &mut [Marched]) {
    for (j, o) in out.iter_mut().enumerate() {
        let i = first + j;
        // A ray that misses the sphere, or a march of no steps, takes none.
        *o = (false, f32::INFINITY, 0);
        let Some((_, t1)) = sphere_interval(rays.origins[i], rays.dirs[i], m.bound) else {
            continue;
        };
        let mut t = m.start_offset;
        for step in 0..m.steps {
            match march_step(step, t, t1, f.at(rays.at(i, t)), m) {
                ControlFlow::Break(r) => {
                    *o = r;
                    break;
                }
                ControlFlow::Continue(tn) => t = tn,
            }
        }
    }
}

/// Step `step` of a march (0-based) at `t`, leaving at `t1`, with the field's value `fv` there
/// ([`secondary_step`]): the ray's result where it has finished (its last step included), or
/// the `t` it goes on from.
pub(crate) fn march_step(step: usize, t: f32, t1: f32, fv: f32, m: &March) -> ControlFlow<Marched, f32> {
    match secondary_step(step, t, t1, fv, m.threshold) {
        SecondaryStep::Hit => ControlFlow::Break((true, t, step + 1)),
        SecondaryStep::Open => ControlFlow::Break((false, f32::INFINITY, step + 1)),
        SecondaryStep::Next(tn) if step + 1 < m.steps => ControlFlow::Continue(tn),
        SecondaryStep::Next(_) => ControlFlow::Break((false, f32::INFINITY, m.steps)),
    }
}

impl<F: Fn(&[f32]) -> Result<Vec<f32>, BackendError>> SdfBatch for F {
    fn sdf(&self, points: &[f32]) -> Result<Vec<f32>, BackendError> {
        self(points)
    }
}

fn eval_at(f: &dyn SdfBatch, pts: &[[f32; 3]], count: &mut usize) -> Result<Vec<f32>, BackendError> {
    *count += pts.len();
    if pts.is_empty() {
        return Ok(Vec::new());
    }
    let flat: &[f32] = bytemuck::cast_slice(pts);
    let v = f.sdf(flat)?;
    if v.len() != pts.len() {
        return Err(BackendError::Shape(format!("sdf batch returned {} values for {} points", v.len(), pts.len())));
    }
    Ok(v)
}

/// Trace primary rays (see the module docs).
pub fn trace(f: &dyn SdfBatch, rays: &Rays, cfg: &TraceConfig) -> Result<TraceResult, BackendError> {
    cfg.validate()?;
    let n = rays.len();
    let mut evals = 0usize;
    let mut res = TraceResult {
        hit: vec![false; n],
        t: vec![0.0; n],
        points: vec![[0.0; 3]; n],
        sdf: vec![f32::INFINITY; n],
        sampled: vec![false; n],
        evaluations: 0,
    };
    let mut starts: Vec<Start> = Vec::with_capacity(n);
    for i in 0..n {
        match sphere_interval(rays.origins[i], rays.dirs[i], cfg.bound) {
            Some((lo, hi)) => starts.push(Start { ray: i, t0: lo, lo, hi }),
            None => record_miss(rays, i, &mut res),
        }
    }
    let bound = f.lower_bound();
    if let Some(b) = bound {
        starts = bound_starts(b, rays, starts, &mut res);
    }
    // Unfinished rays for the sampler, and the closest point sphere tracing visited on each.
    let dev = f.device();
    let unfinished = match dev {
        Some(d) if !starts.is_empty() => device::sphere_trace(d, rays, &starts, cfg, &mut res, &mut evals)?,
        _ => sphere_trace_host(f, rays, &starts, cfg, &mut res, &mut evals)?,
    };

    // Sampler + secant on unfinished rays.
    sample_and_refine(f, bound, rays, &unfinished, cfg, &mut res, &mut evals)?;
    if bound.is_some() {
        // A ray sphere tracing let go near the surface (it starts there now, with steps to
        // spare, and a grazing ray can step across a sliver of surface before leaving) gets
        // IDR's sampler over its whole segment, which the bound makes cheap: no ray that would
        // have run out of steps from the sphere, and been sampled so, is lost.
        let again: Vec<Segment> = starts
            .iter()
            .filter(|s| !res.hit[s.ray] && res.sdf[s.ray].is_finite())
            .map(|s| Segment { ray: s.ray, t0: s.lo, t1: s.hi, samples: cfg.sampler_samples, visited: None })
            .collect();
        sample_and_refine(f, bound, rays, &again, cfg, &mut res, &mut evals)?;
    }

    // Refined: one Newton step along the ray on every hit.
    if cfg.newton {
        let hits: Vec<usize> = (0..n).filter(|&i| res.hit[i]).collect();
        if !hits.is_empty() {
            let delta = 1e-3f32;
            let mut pts = Vec::with_capacity(hits.len() * 3);
            for &i in &hits {
                let t = res.t[i];
                pts.push(rays.at(i, t));
                pts.push(rays.at(i, t + delta));
                pts.push(rays.at(i, t - delta));
            }
            let v = eval_at(f, &pts, &mut evals)?;
            for (k, &i) in hits.iter().enumerate() {
                let (f0, fp, fm) = (v[3 * k], v[3 * k + 1], v[3 * k + 2]);
                let dfdt = (fp - fm) / (2.0 * delta);
                if !(f0.is_finite() && dfdt.is_finite()) || dfdt > -0.05 {
                    continue; // grazing or back-facing: keep the traced point
                }
                let step = (-f0 / dfdt).clamp(-10.0 * cfg.threshold, 10.0 * cfg.threshold);
                res.t[i] += step;
                res.points[i] = rays.at(i, res.t[i]);
            }
        }
    }
    res.evaluations = evals;
    Ok(res)
}

/// IDR's sampler over `segs` (the field's values at their samples, where a bound cannot prove
/// them outside) and the secant refinement of each first sign change; a segment without one
/// leaves its ray a miss at its smallest value.
fn sample_and_refine(
    f: &dyn SdfBatch,
    bound: Option<&dyn LowerBound>,
    rays: &Rays,
    segs: &[Segment],
    cfg: &TraceConfig,
    res: &mut TraceResult,
    evals: &mut usize,
) -> Result<(), BackendError> {
    if segs.is_empty() {
        return Ok(());
    }
    let dev = f.device();
    let mut offsets = Vec::with_capacity(segs.len() + 1);
    offsets.push(0usize);
    for u in segs {
        offsets.push(offsets.last().copied().unwrap_or(0) + u.samples);
    }
    let mut pts = Vec::with_capacity(offsets[segs.len()]);
    for u in segs {
        pts.extend((0..u.samples).map(|j| rays.at(u.ray, u.at(j))));
    }
    let v = match bound {
        None => eval_at(f, &pts, evals)?,
        Some(b) => {
            // The field where the bound cannot prove it positive, and just before each such
            // run of samples (a bracket's outside end is then the field's own value).
            let mut need: Vec<bool> = pts.par_iter().with_min_len(4096).map(|&p| !(b.lower(p) > 0.0)).collect();
            for w in offsets.windows(2) {
                for j in w[0] + 1..w[1] {
                    if need[j] && !need[j - 1] {
                        need[j - 1] = true;
                    }
                }
            }
            let at: Vec<[f32; 3]> = pts.iter().zip(&need).filter(|(_, &k)| k).map(|(p, _)| *p).collect();
            let mut fv = eval_at(f, &at, evals)?.into_iter();
            pts.iter().zip(&need).map(|(&p, &k)| if k { fv.next().unwrap_or(f32::NAN) } else { b.estimate(p) }).collect()
        }
    };
    // Secant brackets: (ray, t_lo, f_lo, t_hi, f_hi).
    let mut brackets: Vec<(usize, f32, f32, f32, f32)> = Vec::new();
    for (k, u) in segs.iter().enumerate() {
        let i = u.ray;
        res.sampled[i] = true;
        let row = &v[offsets[k]..offsets[k + 1]];
        let mut found = None;
        for j in 1..row.len() {
            if row[j - 1].is_finite() && row[j].is_finite() && row[j - 1] > 0.0 && row[j] <= 0.0 {
                found = Some(j);
                break;
            }
        }
        match found {
            Some(j) => brackets.push((i, u.at(j - 1), row[j - 1], u.at(j), row[j])),
            None => {
                let (mut tm, mut vm) = (u.t0, f32::INFINITY);
                for (j, &x) in row.iter().enumerate() {
                    if x.is_finite() && x < vm {
                        vm = x;
                        tm = u.at(j);
                    }
                }
                if let Some((tb, fb)) = u.visited.filter(|&(_, fb)| fb < vm) {
                    (tm, vm) = (tb, fb);
                }
                res.t[i] = tm;
                res.points[i] = rays.at(i, tm);
                res.sdf[i] = vm;
            }
        }
    }
    match dev {
        Some(d) if !brackets.is_empty() => device::secant(d, rays, &brackets, cfg, res, evals)?,
        _ => secant_host(f, rays, brackets, cfg, res, evals)?,
    }
    Ok(())
}

/// Sphere tracing of `starts` on the host, one batched evaluation of the rays still marching
/// per step: fills `res` for hits and broken values, returns the unfinished rays' segments.
fn sphere_trace_host(
    f: &dyn SdfBatch,
    rays: &Rays,
    starts: &[Start],
    cfg: &TraceConfig,
    res: &mut TraceResult,
    evals: &mut usize,
) -> Result<Vec<Segment>, BackendError> {
    let local = cfg.local_samples >= 2;
    let mut active: Vec<Marching> = starts
        .iter()
        .map(|s| Marching { ray: s.ray, t: s.t0, last_pos: s.t0, best_f: f32::INFINITY, best_t: s.t0, before_best: s.t0, lo: s.lo, hi: s.hi })
        .collect();
    let mut unfinished: Vec<Segment> = Vec::new();
    for step in 0..=cfg.sphere_steps {
        if active.is_empty() {
            break;
        }
        let pts: Vec<[f32; 3]> = active.iter().map(|m| rays.at(m.ray, m.t)).collect();
        let v = eval_at(f, &pts, evals)?;
        let mut next = Vec::with_capacity(active.len());
        for (k, m) in active.iter().enumerate() {
            let (i, t, fv) = (m.ray, m.t, v[k]);
            if !fv.is_finite() {
                // A broken field: treat as a miss at the near point.
                res.t[i] = t;
                res.points[i] = pts[k];
                continue;
            }
            if fv.abs() < cfg.threshold {
                res.hit[i] = true;
                res.t[i] = t;
                res.points[i] = pts[k];
                res.sdf[i] = fv;
                continue;
            }
            let m = if fv < m.best_f { Marching { best_f: fv, best_t: t, before_best: m.last_pos, ..*m } } else { *m };
            let visited = if local { Some((m.best_t, m.best_f)) } else { None };
            if fv < 0.0 {
                // Overshot into the surface: the first sign change lies after the last point
                // known outside (IDR samples from there to the far end; the local sampler
                // samples up to the point inside).
                let t1 = if local { t } else { m.hi };
                let samples = if local { cfg.local_samples } else { cfg.sampler_samples };
                unfinished.push(Segment { ray: i, t0: m.last_pos, t1, samples, visited });
                continue;
            }
            if step == cfg.sphere_steps {
                // Out of steps: the whole segment (its min-SDF point may lie behind t).
                unfinished.push(Segment { ray: i, t0: m.lo, t1: m.hi, samples: cfg.sampler_samples, visited });
                continue;
            }
            let tn = t + fv;
            if tn > m.hi {
                // Left the sphere without meeting the surface: sphere tracing's steps are too
                // coarse a min-SDF estimate. IDR samples the whole segment; the local sampler
                // samples between the points before and after the closest one visited.
                let seg = if local {
                    Segment { ray: i, t0: m.before_best, t1: (m.best_t + m.best_f).min(m.hi), samples: cfg.local_samples, visited }
                } else {
                    Segment { ray: i, t0: m.lo, t1: m.hi, samples: cfg.sampler_samples, visited: None }
                };
                unfinished.push(seg);
                continue;
            }
            next.push(Marching { t: tn, last_pos: t, ..m });
        }
        active = next;
    }
    Ok(unfinished)
}

/// The secant refinement of `brackets` `(ray, t_lo, f_lo, t_hi, f_hi)` on the host: a bracket
/// converges when |f| < threshold/10 at its secant point; one still open after `secant_steps`
/// steps hits at its last secant point.
fn secant_host(
    f: &dyn SdfBatch,
    rays: &Rays,
    mut brackets: Vec<(usize, f32, f32, f32, f32)>,
    cfg: &TraceConfig,
    res: &mut TraceResult,
    evals: &mut usize,
) -> Result<(), BackendError> {
    for _ in 0..cfg.secant_steps {
        if brackets.is_empty() {
            break;
        }
        let mid: Vec<[f32; 3]> = brackets.iter().map(|&(i, tl, fl, th, fh)| rays.at(i, secant(tl, fl, th, fh))).collect();
        let v = eval_at(f, &mid, evals)?;
        let mut next = Vec::with_capacity(brackets.len());
        for (k, &(i, tl, fl, th, fh)) in brackets.iter().enumerate() {
            let tm = secant(tl, fl, th, fh);
            let fm = v[k];
            if !fm.is_finite() || fm.abs() < cfg.threshold * 0.1 {
                res.hit[i] = true;
                res.t[i] = tm;
                res.points[i] = mid[k];
                res.sdf[i] = if fm.is_finite() { fm } else { 0.0 };
                continue;
            }
            if fm > 0.0 {
                next.push((i, tm, fm, th, fh));
            } else {
                next.push((i, tl, fl, tm, fm));
            }
        }
        brackets = next;
    }
    for &(i, tl, fl, th, fh) in &brackets {
        let tm = secant(tl, fl, th, fh);
        res.hit[i] = true;
        res.t[i] = tm;
        res.points[i] = rays.at(i, tm);
        res.sdf[i] = 0.5 * (fl + fh);
    }
    Ok(())
}

/// A ray that meets the bounding sphere over `[lo, hi]`: sphere tracing starts at `t0` (`lo`,
/// or where a [`LowerBound`]'s march got to).
struct Start {
    ray: usize,
    t0: f32,
    lo: f32,
    hi: f32,
}

/// A ray that misses before sphere tracing (the bounding sphere, or a bound that clears it):
/// its point is the closest to the centre, where the mask loss pushes the field up.
fn record_miss(rays: &Rays, i: usize, res: &mut TraceResult) {
    let (o, d) = (rays.origins[i], rays.dirs[i]);
    res.t[i] = (-(o[0] * d[0] + o[1] * d[1] + o[2] * d[2])).max(0.0);
    res.points[i] = rays.at(i, res.t[i]);
}

/// March every start by the bound (the rays in parallel): a ray the bound clears to its far end
/// misses (recorded in `res` as a ray that misses the sphere is); the others start sphere tracing
/// where the bound came within [`LowerBound::near`] of 0.
fn bound_starts(b: &dyn LowerBound, rays: &Rays, starts: Vec<Start>, res: &mut TraceResult) -> Vec<Start> {
    let near = b.near();
    let marched: Vec<Option<f32>> = starts
        .par_iter()
        .with_min_len(256)
        .map(|s| {
            let mut t = s.lo;
            for _ in 0..BOUND_STEPS {
                let l = b.lower(rays.at(s.ray, t));
                if !(l > near) {
                    return Some(t);
                }
                t += l;
                if t > s.hi {
                    return None;
                }
            }
            Some(t)
        })
        .collect();
    let mut kept = Vec::with_capacity(starts.len());
    for (s, m) in starts.into_iter().zip(marched) {
        match m {
            Some(t0) => kept.push(Start { t0, ..s }),
            None => record_miss(rays, s.ray, res),
        }
    }
    kept
}

/// A ray being sphere traced: where it is, the last point known outside, the closest point
/// visited so far (its value and the point before it), which the local sampler searches around,
/// and its sphere interval.
#[derive(Clone, Copy)]
struct Marching {
    ray: usize,
    t: f32,
    last_pos: f32,
    best_f: f32,
    best_t: f32,
    before_best: f32,
    lo: f32,
    hi: f32,
}

/// An unfinished ray's sampled interval, with the closest point sphere tracing visited (the
/// local sampler's min-SDF can fall back on it).
struct Segment {
    ray: usize,
    t0: f32,
    t1: f32,
    samples: usize,
    visited: Option<(f32, f32)>,
}

impl Segment {
    fn at(&self, j: usize) -> f32 {
        self.t0 + (self.t1 - self.t0) * j as f32 / (self.samples - 1).max(1) as f32
    }
}

fn secant(tl: f32, fl: f32, th: f32, fh: f32) -> f32 {
    let den = fl - fh;
    if den.abs() < 1e-12 {
        return 0.5 * (tl + th);
    }
    (tl + fl * (th - tl) / den).clamp(tl.min(th), tl.max(th))
}

/// Secondary rays: sphere tracing from `t = start_offset` for at most `steps` steps (the paper's
/// 10 from 0.01 toward each light lobe; stage 2 takes more, see `Stage2Config::secondary_steps`).
/// A ray hits when |f| < `threshold` before it leaves the sphere of radius `bound`; a ray is traced
/// no further once it has hit or left. Returns `(hit, t)` per ray and the field evaluations spent.
///
/// A ray whose start point is already within the threshold is not a hit: it is its origin's own
/// surface seen by a ray leaving within ~`threshold/start_offset` rad of the tangent plane
/// (`f ≈ start_offset·sin α`), not an occluder. Measured in stage 2 on the example and bowl, such
/// first-step self-hits were ~37% and ~54% of all hits.
pub fn trace_secondary(
    f: &dyn SdfBatch,
    rays: &Rays,
    start_offset: f32,
    steps: usize,
    threshold: f32,
    bound: f32,
) -> Result<(Vec<bool>, Vec<f32>, usize), BackendError> {
    let n = rays.len();
    if let Some(pf) = f.pointwise() {
        return Ok(march_each(pf, rays, start_offset, steps, threshold, bound));
    }
    let mut hit = vec![false; n];
    let mut t_out = vec![f32::INFINITY; n];
    let mut active: Vec<(usize, f32, f32)> = (0..n)
        .filter_map(|i| sphere_interval(rays.origins[i], rays.dirs[i], bound).map(|(_, t1)| (i, start_offset, t1)))
        .collect();
    let mut evals = 0;
    for step in 0..steps {
        if active.is_empty() {
            break;
        }
        let pts: Vec<[f32; 3]> = active.iter().map(|&(i, t, _)| rays.at(i, t)).collect();
        let v = eval_at(f, &pts, &mut evals)?;
        let mut next = Vec::with_capacity(active.len());
        for (k, &(i, t, t1)) in active.iter().enumerate() {
            match secondary_step(step, t, t1, v[k], threshold) {
                SecondaryStep::Hit => {
                    hit[i] = true;
                    t_out[i] = t;
                }
                SecondaryStep::Open => {}
                SecondaryStep::Next(tn) => next.push((i, tn, t1)),
            }
        }
        active = next;
    }
    Ok((hit, t_out, evals))
}

/// What a secondary ray does after its field value `fv` at `t` (step `step`, leaving at `t1`).
enum SecondaryStep {
    Hit,
    /// Traced no further and not a hit: it left the bound, met a non-finite value, or started
    /// within the threshold of its origin's own surface (see [`trace_secondary`]).
    Open,
    Next(f32),
}

fn secondary_step(step: usize, t: f32, t1: f32, fv: f32, threshold: f32) -> SecondaryStep {
    if !fv.is_finite() {
        return SecondaryStep::Open;
    }
    if fv < threshold {
        return if step == 0 { SecondaryStep::Open } else { SecondaryStep::Hit };
    }
    let tn = t + fv;
    if tn <= t1 {
        SecondaryStep::Next(tn)
    } else {
        SecondaryStep::Open
    }
}

/// [`trace_secondary`]'s loop for one ray at a time, the rays in parallel in chunks
/// ([`PointSdf::march`]): the same steps ([`secondary_step`]) in the same order, so the same
/// hits, depths and evaluation count.
fn march_each(f: &dyn PointSdf, rays: &Rays, start_offset: f32, steps: usize, threshold: f32, bound: f32) -> (Vec<bool>, Vec<f32>, usize) {
    use rayon::prelude::*;
    const CHUNK: usize = 1024;
    let m = March { start_offset, steps, threshold, bound };
    let mut per: Vec<Marched> = vec![(false, f32::INFINITY, 0); rays.len()];
    per.par_chunks_mut(CHUNK).enumerate().for_each(|(c, out)| f.march(rays, c * CHUNK, &m, out));
    let evals = per.iter().map(|r| r.2).sum();
    let (hit, t) = per.into_iter().map(|(h, t, _)| (h, t)).unzip();
    (hit, t, evals)
}

/// The smallest sampled field value along each ray between `t0[i]` and `t1[i]` (`samples`
/// uniform samples, jittered by `jitter` ∈ [0, 1) of a sample spacing): returns `(t, point)`.
pub fn min_sdf_along(
    f: &dyn SdfBatch,
    rays: &Rays,
    t0: &[f32],
    t1: &[f32],
    samples: usize,
    jitter: f32,
) -> Result<(Vec<f32>, Vec<[f32; 3]>), BackendError> {
    let n = rays.len();
    let s = samples.max(2);
    let mut pts = Vec::with_capacity(n * s);
    let ts = |i: usize, j: usize| t0[i] + (t1[i] - t0[i]) * ((j as f32 + jitter).min((s - 1) as f32)) / (s - 1) as f32;
    for i in 0..n {
        for j in 0..s {
            pts.push(rays.at(i, ts(i, j)));
        }
    }
    let mut evals = 0;
    let v = eval_at(f, &pts, &mut evals)?;
    let mut t = vec![0.0; n];
    let mut p = vec![[0.0; 3]; n];
    for i in 0..n {
        let (mut jm, mut vm) = (0, f32::INFINITY);
        for j in 0..s {
            let x = v[i * s + j];
            if x.is_finite() && x < vm {
                vm = x;
                jm = j;
            }
        }
        t[i] = ts(i, jm);
        p[i] = pts[i * s + jm];
    }
    Ok((t, p))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sphere(r: f32) -> impl Fn(&[f32]) -> Result<Vec<f32>, BackendError> {
        move |p: &[f32]| Ok(p.chunks_exact(3).map(|q| (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - r).collect())
    }

    fn rays_toward_origin(n: usize) -> Rays {
        let mut r = Rays::default();
        for k in 0..n {
            let y = -0.9 + 1.8 * k as f32 / (n - 1) as f32;
            r.origins.push([0.0, y, 3.0]);
            r.dirs.push([0.0, 0.0, -1.0]);
        }
        r
    }

    #[test]
    fn both_modes_find_a_sphere_and_its_silhouette() {
        let f = sphere(0.5);
        let rays = rays_toward_origin(37);
        for mode in [TraceMode::Classic, TraceMode::Refined] {
            let cfg = TraceConfig::new(mode);
            let r = trace(&f, &rays, &cfg).unwrap();
            for i in 0..rays.len() {
                let y = rays.origins[i][1];
                let expect_hit = y.abs() < 0.5;
                if (y.abs() - 0.5).abs() < 0.02 {
                    continue; // silhouette: either is fine
                }
                assert_eq!(r.hit[i], expect_hit, "{mode:?} ray y={y}");
                if expect_hit {
                    let z = (0.25 - y * y).sqrt();
                    let tol = if mode == TraceMode::Classic { 1e-3 } else { 2e-3 };
                    assert!((r.points[i][2] - z).abs() < tol, "{mode:?} y={y}: z {} vs {z}", r.points[i][2]);
                } else {
                    // Min-SDF point: the ray's closest approach to the sphere (z = 0).
                    assert!(r.points[i][2].abs() < 0.05, "{mode:?} y={y}: min point {:?}", r.points[i]);
                }
            }
        }
    }

    #[test]
    fn refined_newton_step_tightens_a_loose_threshold() {
        let f = sphere(0.5);
        let rays = rays_toward_origin(9);
        let mut loose = TraceConfig::new(TraceMode::Refined);
        loose.threshold = 2e-2;
        loose.newton = false;
        let a = trace(&f, &rays, &loose).unwrap();
        loose.newton = true;
        let b = trace(&f, &rays, &loose).unwrap();
        let err = |r: &TraceResult| {
            (0..rays.len())
                .filter(|&i| r.hit[i])
                .map(|i| {
                    let p = r.points[i];
                    ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.5).abs()
                })
                .fold(0.0f32, f32::max)
        };
        assert!(a.hits() > 0 && a.hits() == b.hits());
        assert!(err(&b) < 0.2 * err(&a), "newton {} vs plain {}", err(&b), err(&a));
    }

    #[test]
    fn local_sampler_agrees_with_idrs_for_a_fraction_of_the_evaluations() {
        // A field that overestimates distance (slope 2.5) makes sphere tracing overshoot, and
        // grazing rays run out of steps or leave the sphere: every branch of the sampler.
        for slope in [1.0f32, 2.5] {
            let f = move |p: &[f32]| Ok::<_, BackendError>(p.chunks_exact(3).map(|q| slope * ((q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - 0.5)).collect());
            let rays = rays_toward_origin(91);
            let idr = TraceConfig::new(TraceMode::Refined);
            let local = TraceConfig { local_samples: 16, sphere_steps: 20, ..idr.clone() };
            let (a, b) = (trace(&f, &rays, &idr).unwrap(), trace(&f, &rays, &local).unwrap());
            assert!(b.sampled.iter().any(|s| *s), "slope {slope}: the sampler ran");
            for i in 0..rays.len() {
                let y = rays.origins[i][1];
                if (y.abs() - 0.5).abs() < 0.01 {
                    continue; // silhouette: either is fine
                }
                assert_eq!(b.hit[i], y.abs() < 0.5, "slope {slope} y={y}");
                assert_eq!(a.hit[i], b.hit[i], "slope {slope} y={y}");
                if b.hit[i] {
                    // Where sphere tracing lands on the far side (slope 2.5 can), so does IDR's.
                    let z = (0.25 - y * y).sqrt();
                    assert!((b.points[i][2] - a.points[i][2]).abs() < 2e-3, "slope {slope} y={y}: z {} vs IDR {}", b.points[i][2], a.points[i][2]);
                    assert!(slope > 1.0 || (b.points[i][2] - z).abs() < 2e-3, "y={y}: z {} vs {z}", b.points[i][2]);
                } else {
                    // The min-SDF value is the closest approach's, and no more than 0.005·slope above IDR's.
                    let truth = slope * (y.abs() - 0.5);
                    assert!((b.sdf[i] - truth).abs() < 0.01 * slope, "slope {slope} y={y}: {} vs {truth}", b.sdf[i]);
                    assert!(b.sdf[i] <= a.sdf[i] + 5e-3 * slope, "slope {slope} y={y}: {} vs IDR {}", b.sdf[i], a.sdf[i]);
                }
            }
            assert!(2 * b.evaluations < a.evaluations, "slope {slope}: {} vs IDR {} evaluations", b.evaluations, a.evaluations);
        }
        let mut bad = TraceConfig::new(TraceMode::Refined);
        bad.local_samples = 1;
        assert!(bad.validate().is_err());
    }

    #[test]
    fn thin_shell_behind_a_miss_goes_through_the_sampler() {
        // A thin plate |z| < 0.01: sphere tracing may step over it; the sampler + secant find it.
        let f = |p: &[f32]| Ok::<_, BackendError>(p.chunks_exact(3).map(|q| q[2].abs() - 0.01).collect());
        let rays = Rays { origins: vec![[0.3, 0.0, 2.0]], dirs: vec![[0.0, 0.0, -1.0]] };
        let r = trace(&f, &rays, &TraceConfig::new(TraceMode::Classic)).unwrap();
        assert!(r.hit[0]);
        assert!((r.points[0][2] - 0.01).abs() < 1e-3, "{:?}", r.points[0]);
    }

    #[test]
    fn secondary_rays_and_min_sdf() {
        let f = sphere(0.3);
        // From a point on a plane below the sphere, looking up (hits) and sideways (misses).
        let rays = Rays { origins: vec![[0.0, -0.6, 0.0], [0.0, -0.6, 0.0]], dirs: vec![[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]] };
        let (hit, t, _) = trace_secondary(&f, &rays, 0.01, 10, 1e-3, 1.0).unwrap();
        assert!(hit[0] && !hit[1]);
        assert!((t[0] - 0.3).abs() < 2e-3, "t {}", t[0]);
        // From the sphere's own surface, 1° above its tangent plane: the start point is within the
        // threshold of the origin's surface, which is not an occluder.
        let a = 1f32.to_radians();
        let grazing = Rays { origins: vec![[0.0, 0.3, 0.0]], dirs: vec![[a.cos(), a.sin(), 0.0]] };
        let (hit, _, _) = trace_secondary(&f, &grazing, 0.01, 10, 1e-3, 1.0).unwrap();
        assert!(!hit[0]);
        let (tm, pm) = min_sdf_along(&f, &rays, &[0.0, 0.0], &[1.2, 0.8], 61, 0.0).unwrap();
        assert!((tm[0] - 0.6).abs() < 0.03, "{tm:?}");
        assert!(pm[1][0] < 0.02, "sideways ray's min is at its start: {pm:?}");
    }

    #[test]
    fn a_shallow_secondary_ray_finds_an_occluder_across_a_cavity() {
        // A floor y = -0.3 and a ball of radius 0.2 at (0.5, -0.1, 0); a ray leaves the floor at
        // x = -0.5, 8° above it, toward the ball. Near the floor the field only lets it advance
        // by t·sin 8° a step, so from t = 0.01 the paper's 10 steps end at t ≈ 0.04 and call the
        // ray open; stage 2's default finds the ball about 0.82 away.
        let f = |p: &[f32]| {
            Ok::<_, BackendError>(p.chunks_exact(3).map(|q| (q[1] + 0.3).min(((q[0] - 0.5).powi(2) + (q[1] + 0.1).powi(2) + q[2] * q[2]).sqrt() - 0.2)).collect())
        };
        let a = 8f32.to_radians();
        let rays = Rays { origins: vec![[-0.5, -0.3, 0.0]], dirs: vec![[a.cos(), a.sin(), 0.0]] };
        let (hit, _, evals) = trace_secondary(&f, &rays, 0.01, 10, 5e-4, 1.0).unwrap();
        assert!(!hit[0] && evals == 10);
        let steps = crate::train::stage2::Stage2Config::new(crate::train::stage1::Preset::Fast, 1000).secondary_steps;
        let (hit, t, evals) = trace_secondary(&f, &rays, 0.01, steps, 5e-4, 1.0).unwrap();
        assert!(hit[0] && (t[0] - 0.82).abs() < 0.02, "{} steps: hit {} at t {}", steps, hit[0], t[0]);
        assert!(evals < steps, "the ray stops at its hit: {evals} evaluations");
    }

    #[test]
    fn rays_missing_the_bound_and_nan_fields_are_misses() {
        let f = sphere(0.5);
        let rays = Rays { origins: vec![[0.0, 2.0, 3.0]], dirs: vec![[0.0, 0.0, -1.0]] };
        let r = trace(&f, &rays, &TraceConfig::new(TraceMode::Classic)).unwrap();
        assert!(!r.hit[0]);
        assert_eq!(r.points[0], [0.0, 2.0, 0.0]);
        let nan = |p: &[f32]| Ok::<_, BackendError>(vec![f32::NAN; p.len() / 3]);
        let rays = rays_toward_origin(5);
        let r = trace(&nan, &rays, &TraceConfig::new(TraceMode::Refined)).unwrap();
        assert_eq!(r.hits(), 0);
        assert!(r.points.iter().flatten().all(|v| v.is_finite()));
    }
}
