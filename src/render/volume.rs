//! Volume rendering of an SDF (NeuS's discrete opacity), for rays whose answer a first hit cannot
//! give: behind a surface that should not be there, only an integral along the ray passes gradient.
//!
//! Samples `t_0 < … < t_{n-1}` along a ray with SDF values `f_i`; with `p_i = σ(s·f_i)` (the
//! logistic CDF of sharpness `s`), segment `i` (`i < n−1`) has opacity
//! `α_i = max((p_i − p_{i+1}) / p_i, 0)` (NeuS eq. 13: exact for a plane, whatever the spacing;
//! zero where the ray leaves the surface), transmittance `T_i = Π_{j<i} (1 − α_j)`, weight
//! `w_i = T_i·α_i`, colour `C = Σ w_i c_i` (`c_i`: the radiance at sample `i`) and opacity
//! `O = Σ w_i`. Everything is host arithmetic in f64 per ray; the field and radiance evaluations
//! stay batched on the backend.

/// Forward values of one ray.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Composite {
    /// `α_i`, `[n − 1]`.
    pub alpha: Vec<f64>,
    /// `w_i`, `[n − 1]`.
    pub weights: Vec<f64>,
    pub colour: [f64; 3],
    pub opacity: f64,
}

fn logistic(z: f64) -> f64 {
    if z >= 0.0 {
        1.0 / (1.0 + (-z).exp())
    } else {
        let e = z.exp();
        e / (1.0 + e)
    }
}

/// `α_i` and `(∂α_i/∂f_i, ∂α_i/∂f_{i+1})`. Written as `1 − σ(s f_{i+1})/σ(s f_i)`, which is
/// `1 − e^{s(f_{i+1} − f_i)}·(1 + e^{−s f_i})/(1 + e^{−s f_{i+1}})`: finite deep inside the
/// object, where both `p` underflow.
fn segment_alpha(f0: f64, f1: f64, s: f64) -> (f64, f64, f64) {
    // ln(p1/p0) = ln σ(s f1) − ln σ(s f0); ln σ(z) = −softplus(−z).
    let softplus = |z: f64| if z > 0.0 { z + (-z).exp().ln_1p() } else { z.exp().ln_1p() };
    let ratio = (softplus(-s * f0) - softplus(-s * f1)).exp();
    if !(ratio < 1.0) {
        return (0.0, 0.0, 0.0);
    }
    // d ln σ(z)/dz = 1 − σ(z) = σ(−z).
    let a = 1.0 - ratio;
    let d0 = ratio * s * logistic(-s * f0);
    let d1 = -ratio * s * logistic(-s * f1);
    (a, d0, d1)
}

/// Composite one ray: `f` `[n]`, `colours` `[n]` (the last sample's colour is unused).
pub fn composite(f: &[f64], colours: &[[f64; 3]], s: f64) -> Composite {
    let n = f.len();
    let mut out = Composite::default();
    let mut t = 1.0f64;
    for i in 0..n.saturating_sub(1) {
        let (a, _, _) = segment_alpha(f[i], f[i + 1], s);
        let w = t * a;
        out.alpha.push(a);
        out.weights.push(w);
        for ch in 0..3 {
            out.colour[ch] += w * colours[i][ch];
        }
        out.opacity += w;
        t *= 1.0 - a;
    }
    out
}

/// Gradients of `dC·C + dO·O` with respect to `f` `[n]` and the colours `[n]`, from the forward
/// values `fwd`. `∂/∂α_i = T_i·(g_i − S_i)` with `g_i = dC·c_i + dO` and the suffix
/// `S_i = Σ_{k>i} g_k α_k Π_{i<j<k} (1 − α_j)` (no division by `1 − α_i`).
pub fn composite_backward(f: &[f64], colours: &[[f64; 3]], s: f64, fwd: &Composite, d_colour: [f64; 3], d_opacity: f64) -> (Vec<f64>, Vec<[f64; 3]>) {
    let n = f.len();
    let m = n.saturating_sub(1);
    let mut d_f = vec![0.0; n];
    let mut d_c = vec![[0.0; 3]; n];
    let g = |i: usize| d_colour[0] * colours[i][0] + d_colour[1] * colours[i][1] + d_colour[2] * colours[i][2] + d_opacity;
    // Transmittances.
    let mut trans = Vec::with_capacity(m);
    let mut t = 1.0;
    for i in 0..m {
        trans.push(t);
        t *= 1.0 - fwd.alpha[i];
    }
    let mut suffix = 0.0;
    for i in (0..m).rev() {
        for ch in 0..3 {
            d_c[i][ch] = fwd.weights[i] * d_colour[ch];
        }
        let d_alpha = trans[i] * (g(i) - suffix);
        let (_, d0, d1) = segment_alpha(f[i], f[i + 1], s);
        d_f[i] += d_alpha * d0;
        d_f[i + 1] += d_alpha * d1;
        suffix = g(i) * fwd.alpha[i] + (1.0 - fwd.alpha[i]) * suffix;
    }
    (d_f, d_c)
}

/// `count` sorted samples in `[t[0], t[last]]` drawn by inverse CDF from the piecewise-constant
/// density `weights[i] + floor·mean(weights)` on `[t_i, t_{i+1}]` (stratified: one sample in each
/// `[(j + jitter)/count]` quantile). `floor` keeps some samples everywhere, so a surface the
/// coarse samples missed can still appear.
pub fn importance_samples(t: &[f32], weights: &[f64], count: usize, floor: f64, jitter: f32) -> Vec<f32> {
    let m = t.len().saturating_sub(1).min(weights.len());
    if m == 0 || count == 0 {
        return vec![t.first().copied().unwrap_or(0.0); count];
    }
    let mean = weights[..m].iter().sum::<f64>() / m as f64;
    // Without any weight the density is uniform.
    let extra = if mean > 0.0 { floor * mean } else { 1.0 };
    let mut cdf = Vec::with_capacity(m + 1);
    cdf.push(0.0);
    for w in &weights[..m] {
        let last = *cdf.last().unwrap();
        cdf.push(last + w.max(0.0) + extra);
    }
    let total = cdf[m];
    let mut out = Vec::with_capacity(count);
    let mut seg = 0;
    for j in 0..count {
        let u = (j as f64 + jitter as f64) / count as f64 * total;
        while seg + 1 < m && cdf[seg + 1] < u {
            seg += 1;
        }
        let width = cdf[seg + 1] - cdf[seg];
        let frac = if width > 0.0 { ((u - cdf[seg]) / width).clamp(0.0, 1.0) } else { 0.5 };
        out.push(t[seg] + (t[seg + 1] - t[seg]) * frac as f32);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{check_grad, Tolerance};

    fn loss(f: &[f64], c: &[[f64; 3]], s: f64, dc: [f64; 3], d_o: f64) -> f64 {
        let r = composite(f, c, s);
        dc[0] * r.colour[0] + dc[1] * r.colour[1] + dc[2] * r.colour[2] + d_o * r.opacity
    }

    #[test]
    fn a_plane_crossing_is_opaque_and_its_colour_wins() {
        // A ray through a plane at t = 0.5 (f = 0.5 − t): everything before is transparent.
        let ts: Vec<f64> = (0..64).map(|i| i as f64 / 63.0).collect();
        let f: Vec<f64> = ts.iter().map(|t| 0.5 - t).collect();
        let c: Vec<[f64; 3]> = ts.iter().map(|&t| if t < 0.5 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] }).collect();
        let r = composite(&f, &c, 400.0);
        assert!((r.opacity - 1.0).abs() < 1e-6, "{}", r.opacity);
        // The weight sits in the segments around the crossing.
        let peak = r.weights.iter().cloned().enumerate().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap().0;
        assert!((30..=32).contains(&peak), "{peak}");
        // Leaving the surface again (f rising) adds no opacity: a ray that only exits is clear.
        let exit: Vec<f64> = ts.iter().map(|t| t - 0.5).collect();
        assert!(composite(&exit, &c, 400.0).opacity < 1e-9);
        // Deep inside, where σ underflows, values stay finite.
        let deep: Vec<f64> = ts.iter().map(|t| -5.0 - t).collect();
        let r = composite(&deep, &c, 1e4);
        assert!(r.opacity.is_finite() && r.weights.iter().all(|w| w.is_finite()));
    }

    #[test]
    fn backward_matches_central_differences() {
        let f = vec![0.3, 0.21, 0.12, 0.05, -0.01, -0.04, 0.02, -0.08, -0.2];
        let c: Vec<[f64; 3]> = (0..f.len()).map(|i| [0.1 * i as f64, 1.0 - 0.07 * i as f64, 0.5 + 0.03 * (i as f64).sin()]).collect();
        let (dc, d_o) = ([0.7, -1.3, 0.4], 0.9);
        for s in [5.0, 30.0, 120.0] {
            let fwd = composite(&f, &c, s);
            let (df, dcol) = composite_backward(&f, &c, s, &fwd, dc, d_o);
            check_grad(&format!("d/df at s {s}"), &f, &df, 1e-6, Tolerance::new(1e-5, 1e-5), |x| loss(x, &c, s, dc, d_o));
            let flat: Vec<f64> = c.iter().flatten().copied().collect();
            let d_flat: Vec<f64> = dcol.iter().flatten().copied().collect();
            check_grad(&format!("d/dc at s {s}"), &flat, &d_flat, 1e-6, Tolerance::new(0.0, 1e-6), |x| {
                let cols: Vec<[f64; 3]> = x.chunks_exact(3).map(|v| [v[0], v[1], v[2]]).collect();
                loss(&f, &cols, s, dc, d_o)
            });
        }
    }

    #[test]
    fn importance_samples_follow_the_weights() {
        let t: Vec<f32> = (0..=10).map(|i| i as f32 / 10.0).collect();
        let mut w = vec![0.0; 10];
        w[6] = 1.0;
        let s = importance_samples(&t, &w, 20, 0.0, 0.5);
        assert_eq!(s.len(), 20);
        assert!(s.windows(2).all(|p| p[0] <= p[1]));
        assert!(s.iter().all(|&x| (0.6..=0.7).contains(&x)), "{s:?}");
        // A floor spreads some samples over the whole ray.
        let s = importance_samples(&t, &w, 20, 1.0, 0.5);
        assert!(s.iter().filter(|&&x| !(0.6..=0.7).contains(&x)).count() >= 5, "{s:?}");
        // No weight at all: uniform.
        let s = importance_samples(&t, &[0.0; 10], 10, 0.0, 0.5);
        assert!((s[0] - 0.05).abs() < 1e-6 && (s[9] - 0.95).abs() < 1e-6, "{s:?}");
    }
}
