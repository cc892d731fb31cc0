//! Fit K spherical Gaussians to an HDR latlong map (`fit-env`): parametrisation, initialisation,
//! loss + analytic gradient (cpu twin in f64), the Adam loop, error metrics and the `auto` ladder.
//!
//! Parameters, 7 per lobe: `[ξx, ξy, ξz, rλ, rμr, rμg, rμb]` with axis `a = ξ/‖ξ‖`, sharpness
//! `λ = exp(rλ)` (> 0) and amplitude `μ = exp(rμ)` (> 0): every value of the raw parameters is a
//! valid environment, so Adam needs no projection. Exp (not softplus) keeps Adam's steps relative,
//! which suits amplitudes spanning 1e-3 .. 3e4 in one map.
//!
//! Loss (on a downsampled, area-averaged map with solid-angle weights `w_p ∝ sin θ`, Σw = 1):
//! `L = Σ_p w_p Σ_c (log1p(f_pc) − log1p(t_pc))² / 3`. Plain L2 on radiance lets the sun (up to
//! 3e4) dominate and leaves the rest of the sky black; log1p is L2 for dim pixels and relative
//! for bright ones.
//! Plus an energy term `β Σ_c (ln(E_c + ε) − ln(T_c + ε))² / 3`, with `E_c = Σ_k μ_kc S(λ_k)` the
//! fit's solid-angle mean radiance in closed form (`S(λ) = (1 − e^{−2λ}) / 2λ`) and `T_c` the map's.
//! The log loss alone keeps too little energy on maps whose light is in a few bright pixels (a sun
//! or softboxes a fit-grid pixel averages away): it saturates there while the sky dominates the
//! pixel count. Diffuse relighting sees exactly that energy, so it gets its own term.

use rayon::prelude::*;
use serde::Serialize;

use crate::backend::{Backend, BackendError, Tensor};
use crate::nn::adam::{AdamConfig, AdamItem, AdamState, LrSchedule};
use crate::sg::env::{latlong_dir, EnvSgs, LatlongConvention, SgLobe};

/// Raw parameters per lobe.
pub const PARAMS_PER_LOBE: usize = 7;
/// The `--lobes auto` ladder.
pub const LOBE_LADDER: [usize; 5] = [8, 16, 32, 64, 128];
/// Default tolerance of `--lobes auto` on the relative log-space error (`relative_log_l2`) of the
/// full-res re-render: a bound on how the sky looks, beside the irradiance bound below that decides
/// relighting. Log space because the radiance-space relative L2 of a map with a sun is dominated by
/// a few pixels no K ≤ 128 resolves (sunset.exr: 0.99 at every K while the sky matches to 0.15 in
/// log space). 0.5, not tighter: the dim, detailed maps (night, forest, envmap6) stay above 0.45
/// even at K = 128 (bench env), so a tighter default would make `auto` mean "always 128".
pub const DEFAULT_TOLERANCE: f64 = 0.5;
/// Default tolerance of `--lobes auto` on the relative diffuse-irradiance error
/// (`irradiance_error`, see [`FitError`]): what a Lambertian asset relit by the fit sees.
pub const DEFAULT_IRRADIANCE_TOLERANCE: f64 = 0.05;

/// What `--lobes auto` requires of a rung: both errors within their tolerances.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct AutoTolerance {
    /// On `relative_log_l2`.
    pub log_l2: f64,
    /// On `irradiance_error`.
    pub irradiance: f64,
}

impl AutoTolerance {
    pub fn accepts(&self, e: &FitError) -> bool {
        e.relative_log_l2 <= self.log_l2 && e.irradiance_error <= self.irradiance
    }
}
/// Default weight β of the energy term.
pub const DEFAULT_ENERGY_WEIGHT: f64 = 0.5;
/// ε of the energy term (mean radiance; keeps a black channel finite).
pub const ENERGY_EPS: f64 = 1e-6;

/// Solid-angle mean over the sphere of a unit-amplitude SG with sharpness `λ`,
/// `S(λ) = (1 − e^{−2λ}) / 2λ`, and `dS/dλ` (series below λ = 1e-3).
pub fn sg_mean_factor(lambda: f64) -> (f64, f64) {
    if lambda < 1e-3 {
        let l = lambda;
        (1.0 - l + 2.0 * l * l / 3.0 - l * l * l / 3.0, -1.0 + 4.0 * l / 3.0 - l * l)
    } else {
        let e = (-2.0 * lambda).exp();
        let s = -(-2.0 * lambda).exp_m1() / (2.0 * lambda);
        (s, (2.0 * lambda * e - (1.0 - e)) / (2.0 * lambda * lambda))
    }
}

/// What a fit needs beyond the map.
#[derive(Clone, Debug, Serialize)]
pub struct FitConfig {
    pub lobes: usize,
    pub iterations: usize,
    /// Adam base learning rate (decays exponentially to 10% over the run).
    pub lr: f32,
    pub seed: u64,
    /// Width of the downsampled map the loss sees (height = width / 2).
    pub fit_width: usize,
    /// Weight β of the loss's energy term (0: log loss only).
    pub energy_weight: f64,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self { lobes: 32, iterations: 300, lr: 0.05, seed: 0, fit_width: 128, energy_weight: DEFAULT_ENERGY_WEIGHT }
    }
}

/// The downsampled map the loss sees: per pixel RGB target, direction and solid-angle weight.
#[derive(Clone, Debug)]
pub struct FitTarget {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<f32>,
    /// Per pixel `[dx, dy, dz, weight]` (weights sum to 1).
    pub dir_weight: Vec<[f32; 4]>,
    /// Solid-angle mean radiance per channel of the full-resolution map (the energy term's target).
    pub mean: [f64; 3],
    /// Weight β of the energy term (0 turns it off).
    pub energy_weight: f64,
}

/// Solid-angle weight of latlong row `y` (sin θ at the row centre).
fn row_weight(y: usize, height: usize) -> f64 {
    (std::f64::consts::PI * (y as f64 + 0.5) / height as f64).sin()
}

impl FitTarget {
    /// Area-average a `width`×`height` RGB map down to `fit_width`×`fit_width/2` (sin θ-weighted
    /// box filter; no upsampling: a smaller map is used as is).
    pub fn from_map(rgb: &[f32], width: usize, height: usize, conv: LatlongConvention, fit_width: usize) -> Self {
        let fw = fit_width.min(width).max(2);
        let fh = (fw / 2).max(1).min(height);
        let mut out = vec![0.0f32; fw * fh * 3];
        out.par_chunks_mut(fw * 3).enumerate().for_each(|(ty, row)| {
            let (y0, y1) = (ty * height / fh, ((ty + 1) * height / fh).max(ty * height / fh + 1));
            for tx in 0..fw {
                let (x0, x1) = (tx * width / fw, ((tx + 1) * width / fw).max(tx * width / fw + 1));
                let mut acc = [0.0f64; 3];
                let mut wsum = 0.0f64;
                for y in y0..y1 {
                    let w = row_weight(y, height);
                    for x in x0..x1 {
                        let i = (y * width + x) * 3;
                        for c in 0..3 {
                            acc[c] += w * rgb[i + c] as f64;
                        }
                        wsum += w;
                    }
                }
                for c in 0..3 {
                    row[tx * 3 + c] = (acc[c] / wsum.max(1e-30)) as f32;
                }
            }
        });
        let mut mean = [0.0f64; 3];
        let mut wsum = 0.0f64;
        for y in 0..height {
            let w = row_weight(y, height);
            for x in 0..width {
                for c in 0..3 {
                    mean[c] += w * (rgb[(y * width + x) * 3 + c] as f64).max(0.0);
                }
            }
            wsum += w * width as f64;
        }
        let mean = mean.map(|m| m / wsum.max(1e-30));
        let total: f64 = (0..fh).map(|y| row_weight(y, fh) * fw as f64).sum();
        let mut dir_weight = Vec::with_capacity(fw * fh);
        for y in 0..fh {
            let w = (row_weight(y, fh) / total) as f32;
            for x in 0..fw {
                let d = latlong_dir(conv, x, y, fw, fh);
                dir_weight.push([d[0], d[1], d[2], w]);
            }
        }
        Self { width: fw, height: fh, rgb: out, dir_weight, mean, energy_weight: DEFAULT_ENERGY_WEIGHT }
    }

    /// The same target with energy-term weight `beta`.
    pub fn with_energy_weight(mut self, beta: f64) -> Self {
        self.energy_weight = beta;
        self
    }

    /// Index of the target pixel nearest to direction `d`.
    fn nearest(&self, d: [f32; 3]) -> usize {
        let mut best = (f32::MIN, 0);
        for (i, p) in self.dir_weight.iter().enumerate() {
            let dot = p[0] * d[0] + p[1] * d[1] + p[2] * d[2];
            if dot > best.0 {
                best = (dot, i);
            }
        }
        best.1
    }
}

/// Points on a Fibonacci sphere (the paper's lobe axes).
pub fn fibonacci_sphere(n: usize) -> Vec<[f32; 3]> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - y * y).max(0.0).sqrt();
            let phi = golden * i as f64;
            [(r * phi.cos()) as f32, y as f32, (r * phi.sin()) as f32]
        })
        .collect()
}

/// Raw parameters → lobes.
pub fn params_to_env(params: &[f32]) -> EnvSgs {
    let lobes = params
        .chunks_exact(PARAMS_PER_LOBE)
        .map(|p| {
            let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt().max(1e-20);
            SgLobe {
                axis: [p[0] / n, p[1] / n, p[2] / n],
                sharpness: p[3].exp(),
                amplitude: [p[4].exp(), p[5].exp(), p[6].exp()],
            }
        })
        .collect();
    EnvSgs { lobes }
}

/// Lobes → raw parameters (amplitudes floored at 1e-8 so the log exists).
pub fn env_to_params(env: &EnvSgs) -> Vec<f32> {
    env.lobes
        .iter()
        .flat_map(|l| {
            let m = |v: f32| v.max(1e-8).ln();
            [l.axis[0], l.axis[1], l.axis[2], l.sharpness.max(1e-6).ln(), m(l.amplitude[0]), m(l.amplitude[1]), m(l.amplitude[2])]
        })
        .collect()
}

/// Share of the lobes the peak seeding may take (K / this).
pub const PEAK_LOBE_SHARE: usize = 4;
/// A pixel seeds a peak lobe when its residual luminance exceeds this multiple of the map's mean.
pub const PEAK_THRESHOLD: f64 = 16.0;

/// Deterministic initialisation given `seed`, in two parts.
/// 1. Peak seeding: up to K/4 lobes go, one at a time, to the brightest pixel of the residual
///    (map minus the lobes placed so far) while it is brighter than [`PEAK_THRESHOLD`] (16) × the
///    map's mean luminance:
///    axis there, λ = 2π ln 2 / A from the solid angle A of the nearby pixels above half that peak
///    (an SG's half-maximum cap has that area), clamped to [5, what one fit pixel resolves], and
///    the amplitude that gives the lobe those pixels' radiant energy. Suns, lamps and softboxes get
///    a lobe of their size from the start; gradient descent rarely moves a broad lobe onto a
///    one-pixel light.
/// 2. The paper's initialisation for the rest: Fibonacci axes, λ = 10 + |20·N(0,1)|, μ = the
///    residual at the axis, scaled per channel so that the whole fit's solid-angle mean matches
///    the map's.
pub fn init_params(target: &FitTarget, lobes: usize, seed: u64) -> Vec<f32> {
    use rand_distr::{Distribution, StandardNormal};
    let n = target.dir_weight.len();
    let lum = |v: &[f32]| (v[0] + v[1] + v[2]) as f64 / 3.0;
    let mean_lum = (target.mean[0] + target.mean[1] + target.mean[2]) / 3.0;
    let mut resid: Vec<f32> = target.rgb.iter().map(|v| v.max(0.0)).collect();
    let mut lobes_out: Vec<SgLobe> = Vec::with_capacity(lobes);
    let max_peaks = if lobes >= 2 { (lobes / PEAK_LOBE_SHARE).max(1) } else { 0 };
    // Solid angle of a fit pixel: weights sum to 1 over the sphere.
    let omega = |i: usize| 4.0 * std::f64::consts::PI * target.dir_weight[i][3] as f64;
    for _ in 0..max_peaks {
        let (best, peak) = (0..n).map(|i| (i, lum(&resid[i * 3..i * 3 + 3]))).fold((0, f64::MIN), |a, b| if b.1 > a.1 { b } else { a });
        if !(peak > PEAK_THRESHOLD * mean_lum && peak > 0.0) {
            break;
        }
        let d = target.dir_weight[best];
        let axis = [d[0], d[1], d[2]];
        // The pixels within 0.5 rad (cos > 0.8775) above half the peak: their solid angle A and energy.
        let region: Vec<usize> = (0..n)
            .filter(|&i| {
                let p = target.dir_weight[i];
                p[0] * axis[0] + p[1] * axis[1] + p[2] * axis[2] > 0.8775 && lum(&resid[i * 3..i * 3 + 3]) >= 0.5 * peak
            })
            .collect();
        let area: f64 = region.iter().map(|&i| omega(i)).sum();
        let mut energy = [0.0f64; 3];
        for &i in &region {
            for c in 0..3 {
                energy[c] += omega(i) * resid[i * 3 + c] as f64;
            }
        }
        let ln2_2pi = 2.0 * std::f64::consts::PI * std::f64::consts::LN_2;
        let lambda_max = ln2_2pi / omega(best).max(1e-12);
        let lambda = (ln2_2pi / area.max(1e-12)).clamp(5.0_f64.min(lambda_max), lambda_max);
        // The amplitude that gives the lobe the region's energy (∫ SG = 4π μ S(λ)).
        let per_mu = 4.0 * std::f64::consts::PI * sg_mean_factor(lambda).0;
        let amp = energy.map(|e| ((e / per_mu) as f32).max(1e-4));
        let lobe = SgLobe { axis, sharpness: lambda as f32, amplitude: amp };
        // The lobe takes its region's energy; elsewhere it takes what it renders.
        resid.par_chunks_mut(3).zip(&target.dir_weight).for_each(|(r, p)| {
            let f = lobe.eval([p[0], p[1], p[2]]);
            for c in 0..3 {
                r[c] = (r[c] - f[c]).max(0.0);
            }
        });
        for &i in &region {
            resid[i * 3..i * 3 + 3].fill(0.0);
        }
        lobes_out.push(lobe);
    }
    let mut rng = crate::util::rng(seed);
    let mut background: Vec<SgLobe> = fibonacci_sphere(lobes - lobes_out.len())
        .iter()
        .map(|&a| {
            let z: f64 = StandardNormal.sample(&mut rng);
            let i = target.nearest(a) * 3;
            let amplitude = [resid[i], resid[i + 1], resid[i + 2]].map(|v| v.max(1e-4));
            SgLobe { axis: a, sharpness: (10.0 + (20.0 * z).abs()) as f32, amplitude }
        })
        .collect();
    // Scale the background so that peaks + background keep the map's mean radiance (per channel).
    let mean_of = |lobes: &[SgLobe]| {
        let mut m = [0.0f64; 3];
        for l in lobes {
            let s = sg_mean_factor(l.sharpness as f64).0;
            for c in 0..3 {
                m[c] += l.amplitude[c] as f64 * s;
            }
        }
        m
    };
    let (mp, mb) = (mean_of(&lobes_out), mean_of(&background));
    for l in &mut background {
        for c in 0..3 {
            let want = (target.mean[c] - mp[c]).max(0.05 * target.mean[c]).max(1e-6);
            l.amplitude[c] *= (want / mb[c].max(1e-12)) as f32;
        }
    }
    lobes_out.extend(background);
    env_to_params(&EnvSgs { lobes: lobes_out })
}

/// Loss and its gradient w.r.t. the raw parameters, cpu reference in f64.
pub fn loss_grad_f64(params: &[f64], target: &FitTarget) -> (f64, Vec<f64>) {
    let k = params.len() / PARAMS_PER_LOBE;
    struct Lobe {
        a: [f64; 3],
        inv_n: f64,
        lambda: f64,
        mu: [f64; 3],
    }
    let lobes: Vec<Lobe> = params
        .chunks_exact(PARAMS_PER_LOBE)
        .map(|p| {
            let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt().max(1e-20);
            Lobe { a: [p[0] / n, p[1] / n, p[2] / n], inv_n: 1.0 / n, lambda: p[3].exp(), mu: [p[4].exp(), p[5].exp(), p[6].exp()] }
        })
        .collect();
    // Per lobe accumulators: [Vx, Vy, Vz, dL/dλ, dL/dμr, dL/dμg, dL/dμb] with
    // V = Σ_p (Σ_c e_pc μ_kc) g_k ω (the axis gradient is λ·(V − a(a·V))/‖ξ‖).
    // Summed in fixed groups merged in order (`util::fold_ordered`): the same bits on any thread
    // count, so a fit repeats itself.
    let (loss, acc, _) = crate::util::fold_ordered(
        target.dir_weight.len(),
        1024,
        || (0.0f64, vec![0.0f64; k * PARAMS_PER_LOBE], vec![0.0f64; k]),
        |(loss, acc, g), i| {
            let p = &target.dir_weight[i];
            let w = [p[0] as f64, p[1] as f64, p[2] as f64];
            let mut f = [0.0f64; 3];
            for (j, l) in lobes.iter().enumerate() {
                let cos = l.a[0] * w[0] + l.a[1] * w[1] + l.a[2] * w[2];
                g[j] = (l.lambda * (cos - 1.0)).exp();
                for c in 0..3 {
                    f[c] += l.mu[c] * g[j];
                }
            }
            let mut e = [0.0f64; 3];
            for c in 0..3 {
                let t = (target.rgb[i * 3 + c] as f64).max(0.0);
                let r = f[c].ln_1p() - t.ln_1p();
                *loss += p[3] as f64 * r * r / 3.0;
                e[c] = 2.0 * p[3] as f64 * r / (3.0 * (1.0 + f[c]));
            }
            for (j, l) in lobes.iter().enumerate() {
                let s = (e[0] * l.mu[0] + e[1] * l.mu[1] + e[2] * l.mu[2]) * g[j];
                let cos = l.a[0] * w[0] + l.a[1] * w[1] + l.a[2] * w[2];
                let o = j * PARAMS_PER_LOBE;
                acc[o] += s * w[0];
                acc[o + 1] += s * w[1];
                acc[o + 2] += s * w[2];
                acc[o + 3] += s * (cos - 1.0);
                for c in 0..3 {
                    acc[o + 4 + c] += e[c] * g[j];
                }
            }
        },
        |(l1, a1, _), (l2, a2, _)| {
            for (x, y) in a1.iter_mut().zip(&a2) {
                *x += y;
            }
            *l1 += l2;
        },
    );
    let mut grad = vec![0.0f64; params.len()];
    for (j, l) in lobes.iter().enumerate() {
        let o = j * PARAMS_PER_LOBE;
        let v = [acc[o], acc[o + 1], acc[o + 2]];
        let av = l.a[0] * v[0] + l.a[1] * v[1] + l.a[2] * v[2];
        for d in 0..3 {
            grad[o + d] = l.lambda * (v[d] - l.a[d] * av) * l.inv_n;
        }
        grad[o + 3] = acc[o + 3] * l.lambda;
        for c in 0..3 {
            grad[o + 4 + c] = acc[o + 4 + c] * l.mu[c];
        }
    }
    let mut loss = loss;
    let beta = target.energy_weight;
    if beta > 0.0 {
        let sk: Vec<(f64, f64)> = lobes.iter().map(|l| sg_mean_factor(l.lambda)).collect();
        let mut e = [0.0f64; 3];
        for (l, s) in lobes.iter().zip(&sk) {
            for c in 0..3 {
                e[c] += l.mu[c] * s.0;
            }
        }
        let mut q = [0.0f64; 3];
        for c in 0..3 {
            let r = (e[c] + ENERGY_EPS).ln() - (target.mean[c] + ENERGY_EPS).ln();
            loss += beta * r * r / 3.0;
            q[c] = 2.0 * beta * r / (3.0 * (e[c] + ENERGY_EPS));
        }
        for (j, (l, s)) in lobes.iter().zip(&sk).enumerate() {
            let o = j * PARAMS_PER_LOBE;
            for c in 0..3 {
                grad[o + 4 + c] += q[c] * s.0 * l.mu[c];
                grad[o + 3] += q[c] * l.mu[c] * s.1 * l.lambda;
            }
        }
    }
    (loss, grad)
}

/// The loss alone (f64), for finite differences.
pub fn loss_f64(params: &[f64], target: &FitTarget) -> f64 {
    loss_grad_f64(params, target).0
}

/// Solid-angle-weighted errors of an SG environment against a full-resolution map.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct FitError {
    /// sqrt(Σ w‖f − t‖² / Σ w‖t‖²) over every pixel and channel.
    pub relative_l2: f64,
    /// sqrt(Σ w‖log1p f − log1p t‖² / Σ w‖log1p t‖²): how the dim sky is matched.
    pub relative_log_l2: f64,
    /// Σ w f / Σ w t over pixels and channels: the fraction of the map's radiant energy the fit
    /// keeps (1 is right).
    pub energy_ratio: f64,
    /// Relative L2 over all normals of the diffuse irradiance E(n) = ∫ L(ω) max(0, n·ω) dω of the
    /// fit against the map's, both from their order-2 spherical-harmonic projections
    /// (Ramamoorthi & Hanrahan 2001; exact for the cosine kernel up to ~3%): what a Lambertian
    /// asset relit by the fit sees.
    pub irradiance_error: f64,
}

/// The 9 real SH basis functions (l ≤ 2) at unit direction `d`.
fn sh9(d: [f32; 3]) -> [f64; 9] {
    let (x, y, z) = (d[0] as f64, d[1] as f64, d[2] as f64);
    [
        0.282_094_791_773_878_1,
        0.488_602_511_902_919_9 * y,
        0.488_602_511_902_919_9 * z,
        0.488_602_511_902_919_9 * x,
        1.092_548_430_592_079_2 * x * y,
        1.092_548_430_592_079_2 * y * z,
        0.315_391_565_252_520_05 * (3.0 * z * z - 1.0),
        1.092_548_430_592_079_2 * x * z,
        0.546_274_215_296_039_6 * (x * x - y * y),
    ]
}

/// Cosine-lobe convolution factors Â_l for SH bands 0, 1, 2 of the 9 coefficients.
fn cosine_band(i: usize) -> f64 {
    use std::f64::consts::PI;
    match i {
        0 => PI,
        1..=3 => 2.0 * PI / 3.0,
        _ => PI / 4.0,
    }
}

/// Render `env` at the map's resolution and compare (negative map values count as 0).
pub fn fit_error(env: &EnvSgs, rgb: &[f32], width: usize, height: usize, conv: LatlongConvention) -> FitError {
    // Accumulators: 6 sums (see below), then 27 SH coefficients of the map and 27 of the fit.
    const N: usize = 6 + 54;
    let dphi_dtheta = 2.0 * std::f64::consts::PI / width as f64 * std::f64::consts::PI / height as f64;
    // Rows merged in order (`util::fold_ordered`): the same bits on any thread count.
    let s = crate::util::fold_ordered(
        height,
        1,
        || [0.0f64; N],
        |s, y| {
            let w = row_weight(y, height);
            for x in 0..width {
                let d = latlong_dir(conv, x, y, width, height);
                let f = env.eval(d);
                let sh = sh9(d);
                for c in 0..3 {
                    let t = (rgb[(y * width + x) * 3 + c] as f64).max(0.0);
                    let fv = f[c] as f64;
                    s[0] += w * (fv - t) * (fv - t);
                    s[1] += w * t * t;
                    let (lf, lt) = (fv.ln_1p(), t.ln_1p());
                    s[2] += w * (lf - lt) * (lf - lt);
                    s[3] += w * lt * lt;
                    s[4] += w * fv;
                    s[5] += w * t;
                    for (i, b) in sh.iter().enumerate() {
                        s[6 + c * 9 + i] += w * dphi_dtheta * t * b;
                        s[33 + c * 9 + i] += w * dphi_dtheta * fv * b;
                    }
                }
            }
        },
        |a, b| {
            for (x, y) in a.iter_mut().zip(&b) {
                *x += y;
            }
        },
    );
    let coeffs = |o: usize| -> Sh9Rgb { [0, 1, 2].map(|c| std::array::from_fn(|i| s[o + c * 9 + i])) };
    FitError {
        relative_l2: (s[0] / s[1].max(1e-30)).sqrt(),
        relative_log_l2: (s[2] / s[3].max(1e-30)).sqrt(),
        energy_ratio: s[4] / s[5].max(1e-30),
        irradiance_error: irradiance_error(&coeffs(33), &coeffs(6), [1.0; 3]),
    }
}

/// Order-2 spherical-harmonic coefficients of an RGB radiance distribution, per channel.
pub type Sh9Rgb = [[f64; 9]; 3];

/// The order-2 SH projection of a `width`×`height` latlong RGB map (negative values count as 0).
/// Any latlong layout gives the same [`irradiance_error`] between two maps of one layout: the
/// error is over all normals, so a rotation of both leaves it unchanged.
pub fn sh9_of_map(rgb: &[f32], width: usize, height: usize) -> Sh9Rgb {
    let dphi_dtheta = 2.0 * std::f64::consts::PI / width as f64 * std::f64::consts::PI / height as f64;
    let s = crate::util::fold_ordered(
        height,
        1,
        || [0.0f64; 27],
        |s, y| {
            let w = row_weight(y, height) * dphi_dtheta;
            for x in 0..width {
                let sh = sh9(latlong_dir(LatlongConvention::OpenExrUsd, x, y, width, height));
                for c in 0..3 {
                    let t = (rgb[(y * width + x) * 3 + c] as f64).max(0.0);
                    for (i, b) in sh.iter().enumerate() {
                        s[c * 9 + i] += w * t * b;
                    }
                }
            }
        },
        |a, b| {
            for (x, y) in a.iter_mut().zip(&b) {
                *x += y;
            }
        },
    );
    [0, 1, 2].map(|c| std::array::from_fn(|i| s[c * 9 + i]))
}

/// Relative L2 over all normals of the diffuse irradiance E(n) = ∫ L(ω) max(0, n·ω) dω that
/// `pred` (scaled per channel by `scale`) casts, against `truth`'s: both from their SH
/// projections (see [`FitError::irradiance_error`]). It reads what a Lambertian asset relit by
/// the light sees, which a radiance-space error of a map with a sun does not (there the sun's
/// few pixels are nearly all of the norm).
pub fn irradiance_error(pred: &Sh9Rgb, truth: &Sh9Rgb, scale: [f64; 3]) -> f64 {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for c in 0..3 {
        for i in 0..9 {
            let a2 = cosine_band(i).powi(2);
            let (t, f) = (truth[c][i], scale[c] * pred[c][i]);
            num += a2 * (f - t) * (f - t);
            den += a2 * t * t;
        }
    }
    (num / den.max(1e-30)).sqrt()
}

/// The per-channel scale of `pred` that minimises [`irradiance_error`] against `truth` (1 where
/// `pred` casts no light in a channel).
pub fn irradiance_scale(pred: &Sh9Rgb, truth: &Sh9Rgb) -> [f64; 3] {
    [0, 1, 2].map(|c| {
        let (mut ft, mut ff) = (0.0f64, 0.0f64);
        for i in 0..9 {
            let a2 = cosine_band(i).powi(2);
            ft += a2 * pred[c][i] * truth[c][i];
            ff += a2 * pred[c][i] * pred[c][i];
        }
        if ff > 0.0 { ft / ff } else { 1.0 }
    })
}

/// Result of one fit.
#[derive(Clone, Debug)]
pub struct FitResult {
    pub env: EnvSgs,
    pub iterations: usize,
    /// Adam steps skipped by the NaN/Inf guard.
    pub skipped_steps: usize,
    pub final_loss: f64,
    pub seconds: f64,
}

/// Fit `cfg.lobes` SGs to `target` with Adam on `backend`. `on_step(i)` is called after
/// every iteration (progress bars).
pub fn fit_sgs(backend: &Backend, target: &FitTarget, cfg: &FitConfig, mut on_step: impl FnMut(usize)) -> Result<FitResult, BackendError> {
    if cfg.lobes == 0 {
        return Err(BackendError::Config("fit-env: lobes must be > 0".into()));
    }
    let t0 = std::time::Instant::now();
    let init = init_params(target, cfg.lobes, cfg.seed);
    let adam = AdamConfig::with_lr(cfg.lr);
    let schedule = LrSchedule::Exponential { decay_rate: 0.1, decay_steps: cfg.iterations.max(1) as u64 };
    let mut params = backend.upload(&init);
    let mut state = AdamState::new(backend, init.len());
    let mut skipped = 0;
    let gpu = match backend {
        Backend::Gpu(g) => Some(gpu::FitKernels::new(g, target, cfg.lobes)?),
        Backend::Cpu(_) => None,
    };
    for i in 0..cfg.iterations {
        let grads: Tensor = match &gpu {
            Some(k) => k.gradient(&params)?,
            None => {
                let p: Vec<f64> = params.host()?.iter().map(|&v| v as f64).collect();
                let (_, g) = loss_grad_f64(&p, target);
                Tensor::Host(g.iter().map(|&v| v as f32).collect())
            }
        };
        let lr = schedule.lr_at(adam.lr, state.step);
        let rep = backend.adam_step_group(&adam, &mut [AdamItem { params: &mut params, grads: &grads, state: &mut state }], lr)?;
        if !rep.applied {
            skipped += 1;
        }
        on_step(i);
    }
    let raw = backend.to_vec(&params)?;
    let p64: Vec<f64> = raw.iter().map(|&v| v as f64).collect();
    let final_loss = loss_f64(&p64, target);
    Ok(FitResult { env: params_to_env(&raw), iterations: cfg.iterations, skipped_steps: skipped, final_loss, seconds: t0.elapsed().as_secs_f64() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{check_grad, Tolerance};

    #[test]
    fn fibonacci_axes_are_unit_and_spread() {
        let a = fibonacci_sphere(64);
        let mean: [f32; 3] = a.iter().fold([0.0; 3], |s, v| [s[0] + v[0], s[1] + v[1], s[2] + v[2]]);
        for v in &a {
            assert!(((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() - 1.0).abs() < 1e-5);
        }
        assert!(mean.iter().all(|m| (m / 64.0).abs() < 0.05), "{mean:?}");
    }

    #[test]
    fn params_round_trip() {
        let env = EnvSgs { lobes: vec![SgLobe { axis: [0.0, 0.6, 0.8], sharpness: 12.0, amplitude: [1.0, 2.0, 0.5] }] };
        let back = params_to_env(&env_to_params(&env));
        let l = back.lobes[0];
        assert!((l.sharpness - 12.0).abs() < 1e-4 && (l.amplitude[1] - 2.0).abs() < 1e-5 && (l.axis[2] - 0.8).abs() < 1e-6);
    }

    #[test]
    fn loss_gradient_matches_finite_differences() {
        // A small random map and 3 lobes with unnormalised axes.
        let (w, h) = (16, 8);
        let rgb: Vec<f32> = (0..w * h * 3).map(|i| ((i * 37 % 101) as f32 / 25.0).powi(2)).collect();
        let t = FitTarget::from_map(&rgb, w, h, LatlongConvention::OpenExrUsd, 16);
        // The 4th lobe's λ = e^-8 takes the series branch of the energy term.
        let params: Vec<f64> = vec![
            0.3, 0.9, -0.2, 1.5, 0.1, -0.5, 0.7, -0.8, 0.1, 0.7, 2.2, 1.0, 0.2, -1.0, 0.2, -0.6, -1.1, 0.8, -0.3, 0.0, 0.4, 0.1, 0.2, 0.9,
            -8.0, -1.0, -2.0, -1.5,
        ];
        for beta in [0.0, DEFAULT_ENERGY_WEIGHT, 3.0] {
            let t = t.clone().with_energy_weight(beta);
            let (_, g) = loss_grad_f64(&params, &t);
            check_grad(&format!("fit loss, energy weight {beta}"), &params, &g, 1e-6, Tolerance::new(1e-5, 1e-8), |p| loss_f64(p, &t));
        }
    }

    #[test]
    fn sg_mean_factor_matches_quadrature_and_its_derivative() {
        // ∫ e^{λ(cos θ − 1)} dω / 4π = ½ ∫_{-1}^{1} e^{λ(u − 1)} du, by Simpson's rule on 20001 nodes.
        let quad = |lambda: f64| {
            let n = 20_000;
            let h = 2.0 / n as f64;
            let f = |u: f64| (lambda * (u - 1.0)).exp();
            let mut s = f(-1.0) + f(1.0);
            for i in 1..n {
                s += f(-1.0 + i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 };
            }
            0.5 * s * h / 3.0
        };
        for lambda in [1e-6, 5e-4, 0.999e-3, 1.001e-3, 0.03, 0.05, 1.0, 37.0, 500.0] {
            let (s, ds) = sg_mean_factor(lambda);
            assert!((s - quad(lambda)).abs() < 1e-7 * s, "S({lambda}) = {s} vs {}", quad(lambda));
            let h = 1e-6 * lambda.max(1e-3);
            let fd = (sg_mean_factor(lambda + h).0 - sg_mean_factor(lambda - h).0) / (2.0 * h);
            assert!((ds - fd).abs() < 1e-6 * ds.abs().max(1e-6), "dS({lambda}) = {ds} vs {fd}");
        }
        // Large λ: S → 1/2λ, finite.
        let (s, ds) = sg_mean_factor(1e4);
        assert!((s * 2e4 - 1.0).abs() < 1e-12 && ds.is_finite() && ds < 0.0);
    }

    #[test]
    fn peak_seeding_puts_the_first_lobe_on_the_sun() {
        // A dim sky with a one-pixel sun (1e4) at a known pixel of a 128x64 map.
        let (w, h) = (128, 64);
        let mut rgb = vec![0.2f32; w * h * 3];
        let (sx, sy) = (37, 20);
        rgb[(sy * w + sx) * 3..(sy * w + sx) * 3 + 3].copy_from_slice(&[1e4, 9e3, 8e3]);
        let t = FitTarget::from_map(&rgb, w, h, LatlongConvention::OpenExrUsd, 128);
        let env = params_to_env(&init_params(&t, 8, 0));
        let sun = latlong_dir(LatlongConvention::OpenExrUsd, sx, sy, w, h);
        let first = env.lobes[0];
        let cos = first.axis.iter().zip(&sun).map(|(a, b)| a * b).sum::<f32>();
        assert!(cos > 0.9999, "first lobe axis {:?} vs sun {sun:?}", first.axis);
        // Its λ is what one fit pixel resolves, and it carries the sun's energy.
        let sun_energy = 1e4 * 4.0 * std::f64::consts::PI * t.dir_weight[sy * w + sx][3] as f64;
        let lobe_energy = first.amplitude[0] as f64 * 4.0 * std::f64::consts::PI * sg_mean_factor(first.sharpness as f64).0;
        assert!((lobe_energy / sun_energy - 1.0).abs() < 1e-3, "lobe {lobe_energy} vs sun {sun_energy}");
        // Only the sun is a peak: the other lobes are the Fibonacci background, and the whole
        // initialisation keeps the map's mean radiance.
        assert!(env.lobes[1..].iter().all(|l| l.amplitude[0] < 10.0), "{:?}", env.lobes);
        let mean: f64 = env.lobes.iter().map(|l| l.amplitude[0] as f64 * sg_mean_factor(l.sharpness as f64).0).sum();
        assert!((mean / t.mean[0] - 1.0).abs() < 0.05, "init mean {mean} vs map {}", t.mean[0]);
    }
}

/// The wgpu launcher of `shaders/sg_fit.wgsl`.
pub mod gpu {
    use std::sync::Arc;

    use crate::backend::gpu::{groups_1d, shaders, Access, GpuBuffer, GpuContext, KernelSpec};
    use crate::backend::{BackendError, Tensor};

    use super::{FitTarget, PARAMS_PER_LOBE};

    pub const SG_FIT_WGSL: &str = include_str!("../../shaders/sg_fit.wgsl");
    /// Pixels per chunk of the per-lobe partial sums.
    const CHUNK: u32 = 256;

    /// Mirrors `SgFitParams` in `shaders/sg_fit.wgsl`.
    #[repr(C)]
    #[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
    pub struct SgFitParams {
        pub n_pixels: u32,
        pub n_lobes: u32,
        pub n_chunks: u32,
        pub chunk: u32,
        /// The map's mean radiance (energy term target) and the term's weight β.
        pub mean: [f32; 3],
        pub energy_weight: f32,
    }
    const _: () = assert!(std::mem::size_of::<SgFitParams>() == 32);

    /// Buffers for one target and lobe count, reused every iteration.
    pub struct FitKernels {
        ctx: Arc<GpuContext>,
        p: SgFitParams,
        target: GpuBuffer,
        dir_weight: GpuBuffer,
        resid: GpuBuffer,
        partials: GpuBuffer,
        loss: GpuBuffer,
    }

    fn spec() -> KernelSpec {
        use Access::*;
        KernelSpec::new(true, &[Read, Read, Read, ReadWrite, ReadWrite, ReadWrite, ReadWrite])
    }

    impl FitKernels {
        pub fn new(ctx: &Arc<GpuContext>, target: &FitTarget, lobes: usize) -> Result<Self, BackendError> {
            let n = target.dir_weight.len();
            let n_chunks = n.div_ceil(CHUNK as usize);
            let dw: Vec<f32> = target.dir_weight.iter().flatten().copied().collect();
            Ok(Self {
                ctx: ctx.clone(),
                p: SgFitParams {
                    n_pixels: n as u32,
                    n_lobes: lobes as u32,
                    n_chunks: n_chunks as u32,
                    chunk: CHUNK,
                    mean: target.mean.map(|m| m as f32),
                    energy_weight: target.energy_weight as f32,
                },
                target: ctx.upload_f32("sg_fit target", &target.rgb),
                dir_weight: ctx.upload_f32("sg_fit dirs", &dw),
                resid: ctx.zeros_f32("sg_fit resid", n * 4),
                partials: ctx.zeros_f32("sg_fit partials", n_chunks * lobes * PARAMS_PER_LOBE),
                loss: ctx.zeros_f32("sg_fit loss", 1),
            })
        }

        /// The loss gradient w.r.t. `params` (a device tensor of K·7 raw parameters), as a new
        /// device tensor. Three dispatches in one submission.
        pub fn gradient(&self, params: &Tensor) -> Result<Tensor, BackendError> {
            let Tensor::Device(raw) = params else {
                return Err(BackendError::Shape("sg_fit: parameters are not on the GPU".into()));
            };
            let k = self.p.n_lobes as usize;
            if raw.len != k * PARAMS_PER_LOBE {
                return Err(BackendError::Shape(format!("sg_fit: {} parameters for {k} lobes", raw.len)));
            }
            let grads = self.ctx.zeros_f32("sg_fit grads", k * PARAMS_PER_LOBE);
            self.run(raw, &grads)?;
            Ok(Tensor::Device(grads))
        }

        /// Gradient and loss read back to the host (tests, reports).
        pub fn gradient_host(&self, params: &[f32]) -> Result<(f32, Vec<f32>), BackendError> {
            let raw = self.ctx.upload_f32("sg_fit raw", params);
            let grads = self.ctx.zeros_f32("sg_fit grads", params.len());
            self.run(&raw, &grads)?;
            Ok((self.ctx.read_f32(&self.loss)?[0], self.ctx.read_f32(&grads)?))
        }

        fn run(&self, raw: &GpuBuffer, grads: &GpuBuffer) -> Result<(), BackendError> {
            let src = shaders::with_lib(SG_FIT_WGSL);
            let spec = spec();
            let k_res = self.ctx.kernel("sg_fit", &src, "residual", &spec)?;
            let k_part = self.ctx.kernel("sg_fit", &src, "lobe_partials", &spec)?;
            let k_red = self.ctx.kernel("sg_fit", &src, "reduce", &spec)?;
            let u = bytemuck::bytes_of(&self.p);
            let binds = || {
                [
                    raw.into(),
                    (&self.target).into(),
                    (&self.dir_weight).into(),
                    (&self.resid).into(),
                    (&self.partials).into(),
                    grads.into(),
                    (&self.loss).into(),
                ]
            };
            let mut b = self.ctx.batch("sg_fit");
            b.dispatch(&k_res, Some(u), &binds(), groups_1d(self.p.n_pixels as usize, 64))?;
            b.dispatch(&k_part, Some(u), &binds(), groups_1d((self.p.n_chunks * self.p.n_lobes) as usize, 64))?;
            b.dispatch(&k_red, Some(u), &binds(), groups_1d(self.p.n_lobes as usize + 1, 64))?;
            b.submit()
        }
    }
}

/// One rung of a lobe ladder: a fit with K lobes and its errors on the full-res map.
#[derive(Clone, Debug, Serialize)]
pub struct Rung {
    pub lobes: usize,
    pub relative_l2: f64,
    pub relative_log_l2: f64,
    /// Radiant energy of the fit over that of the map (see [`FitError::energy_ratio`]).
    pub energy_ratio: f64,
    /// Relative L2 of the diffuse irradiance (see [`FitError::irradiance_error`]).
    pub irradiance_error: f64,
    pub final_loss: f64,
    pub iterations: usize,
    pub skipped_steps: usize,
    pub fit_seconds: f64,
    pub within_tolerance: bool,
    #[serde(skip)]
    pub env: EnvSgs,
}

/// Fit every K of `ladder` in order (stopping at the first `tolerance` accepts when
/// `stop_when_within`). `on_step(k, i)` is called after every Adam iteration.
#[allow(clippy::too_many_arguments)]
pub fn fit_ladder(
    backend: &Backend,
    rgb: &[f32],
    width: usize,
    height: usize,
    conv: LatlongConvention,
    ladder: &[usize],
    tolerance: &AutoTolerance,
    base: &FitConfig,
    stop_when_within: bool,
    mut on_rung: impl FnMut(&Rung),
    mut on_step: impl FnMut(usize, usize),
) -> Result<Vec<Rung>, BackendError> {
    let target = FitTarget::from_map(rgb, width, height, conv, base.fit_width).with_energy_weight(base.energy_weight);
    let mut rungs = Vec::new();
    for &k in ladder {
        let cfg = FitConfig { lobes: k, ..base.clone() };
        let r = fit_sgs(backend, &target, &cfg, |i| on_step(k, i))?;
        let err = fit_error(&r.env, rgb, width, height, conv);
        let rung = Rung {
            lobes: k,
            relative_l2: err.relative_l2,
            relative_log_l2: err.relative_log_l2,
            energy_ratio: err.energy_ratio,
            irradiance_error: err.irradiance_error,
            final_loss: r.final_loss,
            iterations: r.iterations,
            skipped_steps: r.skipped_steps,
            fit_seconds: r.seconds,
            within_tolerance: tolerance.accepts(&err),
            env: r.env,
        };
        on_rung(&rung);
        let done = stop_when_within && rung.within_tolerance;
        rungs.push(rung);
        if done {
            break;
        }
    }
    Ok(rungs)
}

/// The K `--lobes auto` picks from fitted rungs: the smallest within tolerance, else the largest.
pub fn auto_choice(rungs: &[Rung]) -> Option<&Rung> {
    rungs.iter().filter(|r| r.within_tolerance).min_by_key(|r| r.lobes).or_else(|| rungs.iter().max_by_key(|r| r.lobes))
}
