//! SG algebra and the simplified Disney BRDF as spherical Gaussians (PhySG's closed form, which
//! the paper's stage 2 uses), forward and backward, on the cpu backend (the reference).
//!
//! SG: `G(ω; ξ, λ, μ) = μ·exp(λ(ω·ξ − 1))`. For a surface point with albedo `a`, perceptual
//! roughness `R` (α = R²), normal `n`, view direction `v` (surface → camera) and K environment
//! lobes, the outgoing radiance is
//!
//! `L = max(Σ_k spec_k, 0) + max(Σ_k diff_k, 0)` (per RGB channel), where
//! - `diff_k = ∫_{H(n)} G_k(ω)·a/π·cos⁺ dω` with the cosine as an SG minus a constant
//!   (`ω·n ≈ 32.7080·exp(0.0315(ω·n − 1)) − 31.7003`) and the hemisphere integral of an SG in
//!   closed form (Meder & Brüderlin's fit, as in PhySG's `hemisphere_int`);
//! - `spec_k` uses the GGX distribution as an SG in the half-vector domain,
//!   `D ≈ G(h; n, 2/R⁴, 1/(πR⁴))`, warped to the light domain around the reflection direction
//!   (axis `2(v·n)n − v`, sharpness `λ/(4 v·n)`), times the Fresnel (Schlick with the spherical
//!   Gaussian exponent, `F0 = 0.04`) and Schlick-GGX masking (`k = (R+1)²/8`) terms evaluated at
//!   the warped axis and divided by `4(ω·n)(v·n)`, multiplied with the light lobe and the cosine
//!   SG and integrated over the hemisphere in closed form.
//!
//! Numerical care (all mirrored by the backward, which differentiates the same code):
//! - normals, view directions and lobe axes are normalised inside, so their gradients are
//!   tangent and inputs need not be unit;
//! - roughness is clamped to `[R_MIN, 1]` (`2/R⁴` stays finite in f32), λ to `[LAMBDA_MIN, ∞)`;
//! - the SG product's exponent `λ' − λ1 − λ2` is computed as
//!   `2λ1λ2(ξ1·ξ2 − 1)/(λ' + λ1 + λ2)`, which does not cancel for sharp lobes;
//! - grazing views (`v·n → 0`) clamp as PhySG does (`max(·, 0)` plus a tiny epsilon).
//!
//! The backward is forward-mode automatic differentiation of the same generic code with dual
//! numbers ([`Dual`]): exact derivatives of the forward as written, checked against central
//! differences in the tests.

use std::f64::consts::PI;
use std::ops::{Add, Div, Mul, Neg, Sub};

use rayon::prelude::*;

use crate::backend::{Backend, BackendError, Tensor};

/// Smallest roughness used (α = R² = 4e-4; D's SG sharpness 2/R⁴ = 1.25e7).
pub const R_MIN: f64 = 0.02;
/// Smallest lobe sharpness used.
pub const LAMBDA_MIN: f64 = 1e-4;
/// Fresnel reflectance at normal incidence: 0.04, glTF's and Blender's dielectric (IOR 1.5), so
/// the asset renders in DCC tools as it was trained. The paper's code uses 0.02: on `make_scene.py`'s
/// glossy scene (rendered with Blender's Principled BSDF) that left the albedo 1.4–1.6× too dark (the
/// light grew to make the renderer's brighter highlights) and relit PSNR 2–4 dB lower.
pub const F0: f64 = 0.04;
const TINY: f64 = 1e-6;
/// The clamped cosine as an SG minus a constant: `μ_c·exp(λ_c(ω·n − 1)) − α_c`.
pub const COS_MU: f64 = 32.7080;
pub const COS_LAMBDA: f64 = 0.0315;
pub const COS_ALPHA: f64 = 31.7003;

/// The scalar operations the shading code needs: f32, f64, dual numbers, and packs of
/// [`crate::sg::lanes::LANES`] of either (whose comparisons are per lane, so the code takes no
/// branch on a value: both sides of a choice are formed and one is selected).
pub trait Scalar:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    fn c(v: f64) -> Self;
    fn exp(self) -> Self;
    fn sqrt(self) -> Self;
    /// `a` where `self < c`, else `b` (NaN: `b`); a dual takes the derivatives of its choice.
    fn select_lt(self, c: f64, a: Self, b: Self) -> Self;
    /// `a` where `self <= c`, else `b` (NaN: `b`).
    fn select_le(self, c: f64, a: Self, b: Self) -> Self;
    /// `a` where `self >= c`, else `b` (NaN: `b`).
    fn select_ge(self, c: f64, a: Self, b: Self) -> Self;
    /// `self + c` for a constant `c` (a dual skips the constant's zero tangents: the shading
    /// is mostly products and sums with constants, and its duals' work halves).
    #[inline(always)]
    fn add_c(self, c: f64) -> Self {
        self + Self::c(c)
    }
    /// `self·c` for a constant `c`.
    #[inline(always)]
    fn mul_c(self, c: f64) -> Self {
        self * Self::c(c)
    }
    /// `c − self` for a constant `c`.
    #[inline(always)]
    fn c_sub(self, c: f64) -> Self {
        Self::c(c) - self
    }
    /// `1/self`.
    #[inline(always)]
    fn recip(self) -> Self {
        Self::c(1.0) / self
    }
    /// 2^self.
    #[inline(always)]
    fn exp2(self) -> Self {
        self.mul_c(std::f64::consts::LN_2).exp()
    }
    /// max(self, lo) with the derivative of the branch taken (0 below; NaN: `lo`).
    #[inline(always)]
    fn max_c(self, lo: f64) -> Self {
        self.select_ge(lo, self, Self::c(lo))
    }
    /// min(self, hi) with the derivative of the branch taken (NaN: `hi`).
    #[inline(always)]
    fn min_c(self, hi: f64) -> Self {
        self.select_le(hi, self, Self::c(hi))
    }
}

/// A [`Scalar`] that is one number (not a pack of lanes): its value.
pub trait Value: Scalar {
    fn val(self) -> f64;
}

/// `e^x` in f64 without a libm call, so that it vectorises (the shading's packs of lanes,
/// [`crate::sg::lanes`]) and every form of the shading (f64, duals, lanes, at any SIMD level)
/// gets the same bits from it. Cody–Waite reduction by ln 2 (the round to nearest by the
/// 1.5·2⁵² shift, no `floor`), then the Taylor series to r¹³ on |r| ≤ ln 2/2 (the next term is
/// below 5e-18 relative); separate products and sums (no fused multiply-add, whose software
/// fallback is a call on CPUs without FMA), within 2 ulp of libm's `exp` (tested). Below −708
/// it returns 0 (libm: a subnormal number, down to 0 at −745), above 709 +∞ (libm: finite up
/// to 709.78); NaN stays NaN.
#[inline(always)]
pub fn exp_f64(x: f64) -> f64 {
    // max/min (not clamp) map NaN to a bound, so the bit steps below never see NaN.
    let xc = x.max(EXP_LO).min(EXP_HI);
    let t = xc * std::f64::consts::LOG2_E + EXP_SHIFT;
    let n = t - EXP_SHIFT;
    let r = (xc - n * EXP_LN2_HI) - n * EXP_LN2_LO;
    let mut p = EXP_TAYLOR[0];
    for c in &EXP_TAYLOR[1..] {
        p = p * r + c;
    }
    let e = 1.0 + (r + r * r * p);
    // t's low mantissa bits hold n (two's complement): 2^n from its bits.
    let scale = f64::from_bits(t.to_bits().wrapping_sub(EXP_SHIFT.to_bits()).wrapping_add(1023) << 52);
    let y = e * scale;
    if x.is_nan() {
        x
    } else if x < EXP_LO {
        0.0
    } else if x > EXP_HI {
        f64::INFINITY
    } else {
        y
    }
}

/// [`exp_f64`]'s range: 0 below, +∞ above.
pub(crate) const EXP_LO: f64 = -708.0;
pub(crate) const EXP_HI: f64 = 709.0;
/// 1.5·2⁵²: adding it rounds to an integer held in the low mantissa bits.
pub(crate) const EXP_SHIFT: f64 = 6_755_399_441_055_744.0;
/// ln 2 split: the high part has few mantissa bits, so `n·EXP_LN2_HI` is exact for |n| < 2¹¹.
pub(crate) const EXP_LN2_HI: f64 = 6.931_457_519_531_25e-1;
pub(crate) const EXP_LN2_LO: f64 = 1.428_606_820_309_417_232_12e-6;
/// 1/13!, 1/12!, …, 1/2!: the series after `1 + r`, highest first (Horner).
pub(crate) const EXP_TAYLOR: [f64; 12] = [
    1.0 / 6_227_020_800.0,
    1.0 / 479_001_600.0,
    1.0 / 39_916_800.0,
    1.0 / 3_628_800.0,
    1.0 / 362_880.0,
    1.0 / 40_320.0,
    1.0 / 5_040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
];

impl Scalar for f64 {
    #[inline(always)]
    fn c(v: f64) -> Self {
        v
    }
    #[inline(always)]
    fn exp(self) -> Self {
        exp_f64(self)
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
    #[inline(always)]
    fn select_lt(self, c: f64, a: Self, b: Self) -> Self {
        if self < c {
            a
        } else {
            b
        }
    }
    #[inline(always)]
    fn select_le(self, c: f64, a: Self, b: Self) -> Self {
        if self <= c {
            a
        } else {
            b
        }
    }
    #[inline(always)]
    fn select_ge(self, c: f64, a: Self, b: Self) -> Self {
        if self >= c {
            a
        } else {
            b
        }
    }
}
impl Value for f64 {
    fn val(self) -> f64 {
        self
    }
}

impl Scalar for f32 {
    fn c(v: f64) -> Self {
        v as f32
    }
    fn exp(self) -> Self {
        f32::exp(self)
    }
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
    fn select_lt(self, c: f64, a: Self, b: Self) -> Self {
        if (self as f64) < c {
            a
        } else {
            b
        }
    }
    fn select_le(self, c: f64, a: Self, b: Self) -> Self {
        if self as f64 <= c {
            a
        } else {
            b
        }
    }
    fn select_ge(self, c: f64, a: Self, b: Self) -> Self {
        if self as f64 >= c {
            a
        } else {
            b
        }
    }
}
impl Value for f32 {
    fn val(self) -> f64 {
        self as f64
    }
}

/// A forward-mode dual number with `N` tangents.
#[derive(Clone, Copy, Debug)]
pub struct Dual<const N: usize> {
    pub v: f64,
    pub d: [f64; N],
}

impl<const N: usize> Dual<N> {
    /// The `i`-th input variable with value `v`.
    pub fn var(v: f64, i: usize) -> Self {
        let mut d = [0.0; N];
        d[i] = 1.0;
        Self { v, d }
    }
    #[inline(always)]
    fn map(self, v: f64, dv: f64) -> Self {
        Self { v, d: self.d.map(|x| x * dv) }
    }
}

impl<const N: usize> Add for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        let mut d = self.d;
        for (a, b) in d.iter_mut().zip(o.d) {
            *a += b;
        }
        Self { v: self.v + o.v, d }
    }
}
impl<const N: usize> Sub for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        let mut d = self.d;
        for (a, b) in d.iter_mut().zip(o.d) {
            *a -= b;
        }
        Self { v: self.v - o.v, d }
    }
}
impl<const N: usize> Mul for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        let mut d = [0.0; N];
        for i in 0..N {
            d[i] = self.d[i] * o.v + self.v * o.d[i];
        }
        Self { v: self.v * o.v, d }
    }
}
impl<const N: usize> Div for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        let inv = 1.0 / o.v;
        let q = self.v * inv;
        let mut d = [0.0; N];
        for i in 0..N {
            d[i] = (self.d[i] - q * o.d[i]) * inv;
        }
        Self { v: q, d }
    }
}
impl<const N: usize> Neg for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Self { v: -self.v, d: self.d.map(|x| -x) }
    }
}
impl<const N: usize> Scalar for Dual<N> {
    #[inline(always)]
    fn c(v: f64) -> Self {
        Self { v, d: [0.0; N] }
    }
    #[inline(always)]
    fn exp(self) -> Self {
        let e = exp_f64(self.v);
        self.map(e, e)
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        let s = self.v.sqrt();
        self.map(s, if s > 0.0 { 0.5 / s } else { 0.0 })
    }
    #[inline(always)]
    fn select_lt(self, c: f64, a: Self, b: Self) -> Self {
        if self.v < c {
            a
        } else {
            b
        }
    }
    #[inline(always)]
    fn select_le(self, c: f64, a: Self, b: Self) -> Self {
        if self.v <= c {
            a
        } else {
            b
        }
    }
    #[inline(always)]
    fn select_ge(self, c: f64, a: Self, b: Self) -> Self {
        if self.v >= c {
            a
        } else {
            b
        }
    }
    #[inline(always)]
    fn add_c(self, c: f64) -> Self {
        Self { v: self.v + c, d: self.d }
    }
    #[inline(always)]
    fn mul_c(self, c: f64) -> Self {
        self.map(self.v * c, c)
    }
    #[inline(always)]
    fn c_sub(self, c: f64) -> Self {
        Self { v: c - self.v, d: self.d.map(|x| -x) }
    }
    #[inline(always)]
    fn recip(self) -> Self {
        let inv = 1.0 / self.v;
        Self { v: inv, d: self.d.map(|x| -(inv * x) * inv) }
    }
}
impl<const N: usize> Value for Dual<N> {
    fn val(self) -> f64 {
        self.v
    }
}

type V3<S> = [S; 3];

#[inline(always)]
fn dot<S: Scalar>(a: V3<S>, b: V3<S>) -> S {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
#[inline(always)]
fn scale<S: Scalar>(a: V3<S>, s: S) -> V3<S> {
    [a[0] * s, a[1] * s, a[2] * s]
}
#[inline(always)]
fn add<S: Scalar>(a: V3<S>, b: V3<S>) -> V3<S> {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
/// `a / |a|` (floored length: a zero vector stays finite).
#[inline(always)]
pub fn normalize<S: Scalar>(a: V3<S>) -> V3<S> {
    let l = dot(a, a).sqrt().max_c(1e-12);
    scale(a, l.recip())
}

/// An SG with an RGB amplitude (axis assumed unit).
#[derive(Clone, Copy, Debug)]
pub struct Sg<S> {
    pub axis: V3<S>,
    pub lambda: S,
    pub mu: V3<S>,
}

/// SG value at direction `w`.
pub fn sg_eval<S: Scalar>(g: &Sg<S>, w: V3<S>) -> V3<S> {
    let e = (g.lambda * (dot(g.axis, w) - S::c(1.0))).exp();
    scale(g.mu, e)
}

/// The product of two SGs is an SG. The exponent `λ' − λ1 − λ2` is evaluated without
/// cancellation as `2λ1λ2(ξ1·ξ2 − 1)/(λ' + λ1 + λ2)`.
pub fn sg_product<S: Scalar>(a: &Sg<S>, b: &Sg<S>) -> Sg<S> {
    let (axis, lambda, e) = sg_product_shape(a.axis, a.lambda, b.axis, b.lambda);
    Sg { axis, lambda, mu: [a.mu[0] * b.mu[0] * e, a.mu[1] * b.mu[1] * e, a.mu[2] * b.mu[2] * e] }
}

/// [`sg_product`] without amplitudes: the product's axis and sharpness, and the factor `e` its
/// amplitude carries (`μ' = μ1·μ2·e`).
#[inline(always)]
fn sg_product_shape<S: Scalar>(a_axis: V3<S>, a_lambda: S, b_axis: V3<S>, b_lambda: S) -> (V3<S>, S, S) {
    let u = add(scale(a_axis, a_lambda), scale(b_axis, b_lambda));
    let lam = dot(u, u).sqrt().max_c(1e-12);
    let axis = scale(u, lam.recip());
    let expo = a_lambda.mul_c(2.0) * b_lambda * dot(a_axis, b_axis).add_c(-1.0) / (lam + a_lambda + b_lambda);
    (axis, lam, expo.exp())
}

/// `1 − e^{−x}` for x ≥ 0, accurate for small x.
#[inline(always)]
fn one_minus_exp_neg<S: Scalar>(x: S) -> S {
    one_minus_exp_neg_from(x, (-x).exp())
}

/// [`one_minus_exp_neg`] with `e^{−x}` given, for a caller that needs `e^{−x}` itself too.
#[inline(always)]
fn one_minus_exp_neg_from<S: Scalar>(x: S, exp_neg: S) -> S {
    // Below 1e-4: x − x²/2 + x³/6.
    x.select_lt(1e-4, x * (x * x.mul_c(1.0 / 6.0).c_sub(0.5)).c_sub(1.0), exp_neg.c_sub(1.0))
}

/// Integral of `G(ω; ξ, λ, 1)` over the whole sphere: `2π/λ·(1 − e^{−2λ})` (→ 4π as λ → 0).
pub fn sg_integral<S: Scalar>(lambda: S) -> S {
    let l = lambda.max_c(1e-12);
    S::c(2.0 * PI) * one_minus_exp_neg(S::c(2.0) * l) / l
}

/// Inner product (integral over the sphere of the product) of two SGs, per channel.
pub fn sg_inner<S: Scalar>(a: &Sg<S>, b: &Sg<S>) -> V3<S> {
    let p = sg_product(a, b);
    scale(p.mu, sg_integral(p.lambda))
}

/// Integral of `G(ω; ξ, λ, 1)` over the hemisphere around `n`, with `cos_beta = ξ·n`
/// (PhySG's `hemisphere_int`, the Meder & Brüderlin fit; exact at cos β = ±1 and λ → ∞).
#[inline(always)]
pub fn hemisphere_int<S: Scalar>(lambda: S, cos_beta: S) -> S {
    let l = lambda.add_c(TINY);
    let inv = l.recip();
    let t = l.sqrt() * inv.mul_c(10.8438).add_c(1.6988) / (inv.mul_c(6.2201).add_c(1.0) + inv.mul_c(10.2415) * inv);
    let inv_a = (-t).exp();
    // e^{−t|cos β|}: e^{−t cos β} on the upper side, e^{t cos β} on the lower; both formed,
    // one kept (no branch on the value, so that a pack of lanes takes the same path).
    let q = (-(t * cos_beta.select_ge(0.0, cos_beta, -cos_beta))).exp();
    let upper = (inv_a * q).c_sub(1.0) / (inv_a.c_sub(1.0) + q - inv_a * q);
    let lower = (q - inv_a) / (inv_a.c_sub(1.0) * q.add_c(1.0));
    let s = cos_beta.select_ge(0.0, upper, lower);
    // A_b = 2π/λ (e^{−λ} − e^{−2λ}) = 2π/λ e^{−λ}(1 − e^{−λ}); A_u = 2π/λ (1 − e^{−λ}).
    // e^{−λ} once for both.
    let e_l = (-l).exp();
    let om = one_minus_exp_neg_from(l, e_l);
    let a_u = om.mul_c(2.0 * PI) * inv;
    let a_b = a_u * e_l;
    a_b * s.c_sub(1.0) + a_u * s
}

/// `∫_{H(n)} G(ω; ξ, λ, 1)·cos⁺ dω` with the cosine as SG minus constant; `n` unit. An SG's
/// integral is its amplitude times this.
#[inline(always)]
fn cosine_hemisphere_unit<S: Scalar>(axis: V3<S>, lambda: S, n: V3<S>) -> S {
    let (p_axis, p_lambda, e) = sg_product_shape(n, S::c(COS_LAMBDA), axis, lambda);
    let h1 = hemisphere_int(p_lambda, dot(p_axis, n));
    let h2 = hemisphere_int(lambda, dot(axis, n));
    e.mul_c(COS_MU) * h1 - h2.mul_c(COS_ALPHA)
}

/// Per-point shading inputs.
#[derive(Clone, Copy, Debug)]
pub struct Surface<S> {
    pub albedo: V3<S>,
    pub roughness: S,
    pub normal: V3<S>,
    /// Surface → camera.
    pub view: V3<S>,
}

/// One lobe's (specular, diffuse) contribution before the final clamps: per channel
/// `spec_c = μ_c·F_s` and `diff_c = μ_c·(a_c/π)·F_d`, with the factors of [`lobe_factors`].
pub fn lobe_contribution<S: Scalar>(s: &Surface<S>, light: &Sg<S>) -> (V3<S>, V3<S>) {
    let (fs, fd) = lobe_factors(s.normal, s.view, s.roughness, light.axis, light.lambda);
    let spec = [0, 1, 2].map(|c| light.mu[c] * fs);
    let diff = [0, 1, 2].map(|c| light.mu[c] * (s.albedo[c] * S::c(1.0 / PI)) * fd);
    (spec, diff)
}

/// The two channel-free factors of a lobe's contribution (see [`lobe_contribution`]): the
/// specular `F_s` and the diffuse `F_d` of a unit-amplitude lobe on a unit albedo. Amplitude and
/// albedo enter linearly, so a gradient needs duals only in what these take.
pub fn lobe_factors<S: Scalar>(normal: V3<S>, view: V3<S>, roughness: S, axis: V3<S>, lambda: S) -> (S, S) {
    BrdfSg::new(normal, view, roughness).lobe_factors(axis, lambda)
}

/// Which SG form of the GGX BRDF shades a point.
///
/// Measured against Cycles' Principled BSDF (multiscatter GGX: what `make_scene.py` renders the
/// ground truth with and what Blender renders the asset with) by `pii-bake bench brdf`: a unit
/// sphere (base colour 0.8, 0.6, 0.4) under the SG re-render of the courtyard and envmap6 maps,
/// Cycles against each form under the same 128 lobes, PSNR at the true roughness R = 0.1…0.9.
/// PhySG's form loses a rough metal's energy (its lobe is clipped by the horizon and its masking
/// is the direct-light `k = (R+1)²/8`): 0.42–0.43 of Cycles' radiance at R = 0.9, 0.77–0.84 at
/// R = 0.3, and it fits best 0.05–0.1 rougher than the truth; metals 14.1–28.8 dB. The calibrated
/// form: metals 24.9–36.3 dB (energy 0.93–1.01 at every roughness, the best fit within 0.05 of
/// the true roughness); dielectrics 36.6–43.1 dB against 33.3–41.6. (Its first version scaled
/// the lobe to `B + F0·(1 − B)`, linear in F0: metals 20.7–37.1 dB, overshooting a coloured rough
/// metal's energy by 1.32 at R = 0.9; [`ggx_energy`] replaced it.)
///
/// In training (stage 2's default) it starts from PhySG's form ([`crate::train::stage2::Stage2Config::brdf_warmup`]):
/// from the first step a rough surface keeps its specular energy, which stage 2 can use as a
/// grey near-diffuse layer, a local minimum it does not leave (the bowl's roughness went to 1
/// everywhere, its training PSNR 26.1 against 27.8 dB from the warm-up).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum BrdfModel {
    /// PhySG's closed form as the paper uses it: D as an SG of sharpness `2/α²`, Schlick-GGX
    /// masking with `k = (R+1)²/8`, diffuse not attenuated by the specular.
    #[default]
    Physg,
    /// Calibrated to Cycles' Principled BSDF: D's SG as for `α·`[`CALIBRATED_ALPHA_SCALE`] (the
    /// SG has no GGX tail; the scale makes the fitted roughness the true one), separable Smith
    /// GGX masking, the lobe normalised so that a white furnace returns the energy Cycles' GGX
    /// reflects ([`ggx_energy`]: the SG loses to the horizon what GGX keeps), and the diffuse
    /// attenuated by what the dielectric specular layer reflects.
    Calibrated,
}

/// D's SG width in [`BrdfModel::Calibrated`], as a multiple of α: on the `bench brdf` spheres
/// (metal, before the energy terms were final) the best-fit SG roughness equalled the true one
/// from R = 0.1 to 0.8 at 1.2 on envmap6 and 1.5 on the courtyard map; 1.35 is between them.
pub const CALIBRATED_ALPHA_SCALE: f64 = 1.35;

/// The GGX lobe's directional albedo with Schlick's Fresnel, `E(F0) = F0·A + B`, as Karis'
/// analytic fit of the split-sum table ("Physically based shading on mobile", 2014) in perceptual
/// roughness and `n·v`: `B` near 1 for a smooth surface seen at grazing, small for a rough one.
pub fn env_brdf<S: Scalar>(r: S, nv: S) -> (S, S) {
    let (x, y, z, w) = (S::c(1.0) - r, S::c(0.0425) - S::c(0.0275) * r, S::c(1.04) - S::c(0.572) * r, S::c(0.022) * r - S::c(0.04));
    let grazing = (S::c(-9.28) * nv).exp2();
    let m = (x * x - grazing).select_lt(0.0, x * x, grazing);
    let a004 = m * x + y;
    (S::c(-1.04) * a004 + z, S::c(1.04) * a004 + w)
}

/// Gauss–Legendre nodes and weights on [0, 1] (8 points) for [`env_brdf_average`].
const GL8: [(f64, f64); 8] = [
    (0.019855071751231856, 0.050614268145188129),
    (0.101666761293186630, 0.111190517226687235),
    (0.237233795041835507, 0.156853322938943644),
    (0.408282678752175098, 0.181341891689180991),
    (0.591717321247824902, 0.181341891689180991),
    (0.762766204958164493, 0.156853322938943644),
    (0.898333238706813370, 0.111190517226687235),
    (0.980144928248768144, 0.050614268145188129),
];

/// A white GGX reflector's cosine-weighted average albedo `E_avg = 2∫ E(μ)·μ dμ` over the view
/// cosine μ ([`env_brdf`]'s `A + B`), by 8-point Gauss–Legendre quadrature.
pub fn env_brdf_average<S: Scalar>(r: S) -> S {
    let mut sum = S::c(0.0);
    for (mu, w) in GL8 {
        let (a, b) = env_brdf(r, S::c(mu));
        sum = sum + (a + b) * S::c(2.0 * mu * w);
    }
    sum
}

/// The energy a GGX lobe of reflectance `f0` reflects toward `n·v` under a white furnace, with
/// the multiple scattering Cycles adds (Kulla & Conty's compensation as `bsdf_microfacet.h`'s
/// `microfacet_ggx_preserve_energy` applies it): the single-scattering albedo `f0·A + B` times
/// `1 + F_ms·(1 − E)/E`, `E = A + B` the white lobe's albedo, `F_ms = F_avg·E_avg / (1 − F_avg·(1 − E_avg))`
/// and `F_avg = f0 + (1 − f0)/21` Schlick's hemispherical average. 1 at `f0 = 1` for every
/// roughness and view; not linear in `f0` (a coloured rough metal keeps less than `f0`).
pub fn ggx_energy<S: Scalar>(r: S, nv: S, f0: S) -> S {
    GgxEnergy::new(r, nv).at(f0)
}

/// [`ggx_energy`] at one roughness and view, its reflectance-free terms formed once: a point's
/// shading asks for it at F0 and at each albedo channel.
#[derive(Clone, Copy, Debug)]
pub struct GgxEnergy<S> {
    /// Karis' `A`, `B` ([`env_brdf`]), the white lobe's albedo `E` and its average `E_avg`.
    a: S,
    b: S,
    e: S,
    e_avg: S,
}

impl<S: Scalar> GgxEnergy<S> {
    pub fn new(r: S, nv: S) -> Self {
        let r = r.max_c(R_MIN).min_c(1.0);
        let (a, b) = env_brdf(r, nv);
        Self { a, b, e: (a + b).max_c(1e-3), e_avg: env_brdf_average(r).max_c(1e-3) }
    }

    /// The energy at reflectance `f0`.
    pub fn at(&self, f0: S) -> S {
        let f_avg = f0 + (S::c(1.0) - f0) * S::c(1.0 / 21.0);
        let f_ms = f_avg * self.e_avg / (S::c(1.0) - f_avg * (S::c(1.0) - self.e_avg));
        (f0 * self.a + self.b).max_c(0.0) * (S::c(1.0) + f_ms * (S::c(1.0) - self.e) / self.e)
    }

    /// The same terms in another scalar type.
    #[inline(always)]
    pub fn map<T: Scalar>(&self, f: impl Fn(S) -> T) -> GgxEnergy<T> {
        GgxEnergy { a: f(self.a), b: f(self.b), e: f(self.e), e_avg: f(self.e_avg) }
    }

    /// `d energy / d f0` at `f0`, in f64.
    pub fn slope(&self, f0: f64) -> f64
    where
        S: Value,
    {
        let c = |x: S| Dual::<1> { v: x.val(), d: [0.0] };
        GgxEnergy { a: c(self.a), b: c(self.b), e: c(self.e), e_avg: c(self.e_avg) }.at(Dual::var(f0, 0)).d[0]
    }
}

/// The BRDF side of a point's shading, the same for every lobe: the unit normal and the GGX
/// lobe as an SG warped to the light domain, its amplitude carrying Fresnel, masking and the
/// `1/(4(ω·n)(v·n))`.
#[derive(Clone, Copy, Debug)]
pub struct BrdfSg<S> {
    n: V3<S>,
    axis: V3<S>,
    lambda: S,
    amplitude: S,
    /// The amplitude per unit of reflected energy: with reflectance `f` instead of [`F0`] the
    /// amplitude is `amplitude + (E(f) − E(F0))·amplitude_energy` ([`BrdfSg::energy`]). PhySG's
    /// form: `E(f) = f` and this the amplitude's derivative in F0 (its Fresnel `F0 + (1 − F0)·s`
    /// is linear in F0); the calibrated form: the lobe normalised to a unit white furnace.
    amplitude_energy: S,
    /// The diffuse factor's weight: 1, or `1 − E(F0)`, what the dielectric specular layer
    /// leaves ([`BrdfModel::Calibrated`], [`ggx_energy`]).
    diffuse_weight: S,
    /// The calibrated form's energy at this roughness and view ([`BrdfSg::energy`]); `None`:
    /// PhySG's form, whose energy measure is the reflectance itself.
    ggx: Option<GgxEnergy<S>>,
}

impl<S: Scalar> BrdfSg<S> {
    /// PhySG's form ([`BrdfModel::Physg`]).
    pub fn new(normal: V3<S>, view: V3<S>, roughness: S) -> Self {
        Self::with_model(BrdfModel::Physg, normal, view, roughness)
    }

    pub fn with_model(model: BrdfModel, normal: V3<S>, view: V3<S>, roughness: S) -> Self {
        let calibrated = model == BrdfModel::Calibrated;
        let n = normalize(normal);
        let v = normalize(view);
        let r = roughness.max_c(R_MIN).min_c(1.0);
        let r2 = r * r;
        let inv_r4 = S::c(1.0) / (r2 * r2);
        // D as an SG around n, warped to the light domain.
        let inv_a2 = if calibrated { inv_r4 * S::c(1.0 / (CALIBRATED_ALPHA_SCALE * CALIBRATED_ALPHA_SCALE)) } else { inv_r4 };
        let vn = dot(v, n).max_c(0.0);
        let w = add(scale(n, S::c(2.0) * vn), scale(v, S::c(-1.0)));
        let w = normalize(w);
        let lam_w = S::c(2.0) * inv_a2 / (S::c(4.0) * vn + S::c(TINY));
        let mu_d = inv_a2 * S::c(1.0 / PI);
        let d1 = dot(w, n).max_c(0.0);
        let d2 = vn;
        let (g1, g2) = if calibrated {
            // Separable Smith GGX: G1(μ) = 2μ / (μ + sqrt(α² + (1 − α²)μ²)).
            let a2 = r2 * r2;
            let smith = |mu: S| S::c(2.0) * mu / (mu + (a2 + (S::c(1.0) - a2) * mu * mu).sqrt() + S::c(TINY));
            (smith(d1), smith(d2))
        } else {
            let k = (r + S::c(1.0)) * (r + S::c(1.0)) * S::c(0.125);
            (d1 / (d1 * (S::c(1.0) - k) + k + S::c(TINY)), d2 / (d2 * (S::c(1.0) - k) + k + S::c(TINY)))
        };
        let dg = mu_d * g1 * g2 / (S::c(4.0) * d1 * d2 + S::c(TINY));
        if !calibrated {
            // Fresnel at the lobe's axis (the calibrated form takes the energy from `ggx_energy` instead).
            let h = normalize(add(w, v));
            let vh = dot(v, h).max_c(0.0);
            let schlick = (-(S::c(5.55473) * vh + S::c(6.8316)) * vh).exp2();
            let fresnel = S::c(F0) + S::c(1.0 - F0) * schlick;
            return BrdfSg { n, axis: w, lambda: lam_w, amplitude: fresnel * dg, amplitude_energy: (S::c(1.0) - schlick) * dg, diffuse_weight: S::c(1.0), ggx: None };
        }
        // White furnace: the lobe without Fresnel under a constant unit environment (an SG of
        // sharpness LAMBDA_MIN around n is 1 to within 2e-4), normalised to 1 and scaled to the
        // energy Cycles' GGX reflects, multiple scattering included ([`ggx_energy`]).
        let (p_axis, p_lambda, e) = sg_product_shape(n, S::c(LAMBDA_MIN), w, lam_w);
        let furnace = dg * e * cosine_hemisphere_unit(p_axis, p_lambda, n);
        let unit = dg / (furnace + S::c(TINY));
        let ggx = GgxEnergy::new(r, vn);
        let e_f0 = ggx.at(S::c(F0));
        BrdfSg {
            n,
            axis: w,
            lambda: lam_w,
            amplitude: unit * e_f0,
            amplitude_energy: unit,
            // The diffuse keeps what the dielectric specular layer does not reflect.
            diffuse_weight: S::c(1.0) - e_f0,
            ggx: Some(ggx),
        }
    }

    /// The same BRDF side in another scalar type, each number through `f` (a point's side
    /// spread over a pack of lanes, [`crate::sg::lanes`]).
    #[inline(always)]
    pub fn map<T: Scalar>(&self, f: impl Fn(S) -> T) -> BrdfSg<T> {
        BrdfSg {
            n: self.n.map(&f),
            axis: self.axis.map(&f),
            lambda: f(self.lambda),
            amplitude: f(self.amplitude),
            amplitude_energy: f(self.amplitude_energy),
            diffuse_weight: f(self.diffuse_weight),
            ggx: self.ggx.map(|g| g.map(&f)),
        }
    }

    /// The energy measure `E(f)` of reflectance `f` in which the specular is linear
    /// ([`Self::lobe_factors_f0`]): `f` itself in PhySG's form, [`ggx_energy`] in the calibrated one.
    pub fn energy(&self, f: S) -> S {
        self.ggx.map_or(f, |g| g.at(f))
    }

    /// `dE/df` at `f` ([`Self::energy`]), in f64 at the point's roughness and view.
    pub fn energy_slope(&self, f: f64) -> f64
    where
        S: Value,
    {
        self.ggx.map_or(1.0, |g| g.slope(f))
    }

    /// [`lobe_factors`] of a light lobe (axis need not be unit; λ floored at [`LAMBDA_MIN`]).
    pub fn lobe_factors(&self, axis: V3<S>, lambda: S) -> (S, S) {
        let (spec, _, diff) = self.lobe_factors_f0(axis, lambda);
        (spec, diff)
    }

    /// [`Self::lobe_factors`] and the specular factor per unit of reflected energy, `(F_s, F_e, F_d)`:
    /// with reflectance `f` instead of [`F0`] the specular factor is `F_s + (E(f) − E(F0))·F_e`
    /// ([`Self::energy`]; in PhySG's form `E(f) = f` and `F_e = ∂F_s/∂F0`, exactly: its Fresnel
    /// term is linear in F0). A metallic mix `m` of the two (Principled BSDF's and glTF's linear
    /// blend) is `F_s + m·(E(albedo) − E(F0))·F_e`.
    #[inline(always)]
    pub fn lobe_factors_f0(&self, axis: V3<S>, lambda: S) -> (S, S, S) {
        let axis = normalize(axis);
        let lambda = lambda.max_c(LAMBDA_MIN);
        // Specular: the light times the BRDF's SG, cosine-weighted over the hemisphere.
        let (p_axis, p_lambda, e) = sg_product_shape(axis, lambda, self.axis, self.lambda);
        let spec_unit = e * cosine_hemisphere_unit(p_axis, p_lambda, self.n);
        // Diffuse: the light cosine-weighted over the hemisphere (times the albedo's weight in the caller).
        let diff = cosine_hemisphere_unit(axis, lambda, self.n) * self.diffuse_weight;
        (self.amplitude * spec_unit, self.amplitude_energy * spec_unit, diff)
    }
}

/// Outgoing radiance at one point under `lobes` (f64 or f32).
pub fn shade_point<S: Scalar>(s: &Surface<S>, lobes: &[Sg<S>]) -> V3<S> {
    let mut spec = [S::c(0.0); 3];
    let mut diff = [S::c(0.0); 3];
    for l in lobes {
        let (sp, df) = lobe_contribution(s, l);
        spec = add(spec, sp);
        diff = add(diff, df);
    }
    [0, 1, 2].map(|c| spec[c].max_c(0.0) + diff[c].max_c(0.0))
}

// ---- batched layout ------------------------------------------------------------------------

/// Floats per point: albedo 3, roughness 1, normal 3, view 3.
pub const POINT_STRIDE: usize = 10;
/// Floats per lobe: axis 3, sharpness 1, amplitude 3.
pub const LOBE_STRIDE: usize = 7;

fn surface_of<S: Scalar>(p: &[S]) -> Surface<S> {
    Surface { albedo: [p[0], p[1], p[2]], roughness: p[3], normal: [p[4], p[5], p[6]], view: [p[7], p[8], p[9]] }
}
fn lobe_of<S: Scalar>(l: &[S]) -> Sg<S> {
    Sg { axis: [l[0], l[1], l[2]], lambda: l[3], mu: [l[4], l[5], l[6]] }
}

/// Forward on the cpu: `points` `[n, 10]`, `lobes` `[K, 7]` → RGB `[n, 3]` (f64 reference).
pub fn shade_forward_cpu(points: &[f64], lobes: &[f64]) -> Vec<f64> {
    let lobes: Vec<Sg<f64>> = lobes.chunks_exact(LOBE_STRIDE).map(lobe_of).collect();
    points
        .par_chunks(POINT_STRIDE)
        .flat_map_iter(|p| shade_point(&surface_of(p), &lobes))
        .collect()
}

/// Gradients of `Σ d_out·L` with respect to every input.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ShadeGrads {
    /// `[n, 10]` in the point layout.
    pub d_points: Vec<f64>,
    /// `[K, 7]` in the lobe layout, summed over points.
    pub d_lobes: Vec<f64>,
}

const ND: usize = POINT_STRIDE + LOBE_STRIDE;

/// Backward on the cpu (forward-mode AD of the forward, exact): `d_out` `[n, 3]`.
pub fn shade_backward_cpu(points: &[f64], lobes: &[f64], d_out: &[f64]) -> ShadeGrads {
    let k = lobes.len() / LOBE_STRIDE;
    let per_point: Vec<(Vec<f64>, Vec<f64>)> = points
        .par_chunks(POINT_STRIDE)
        .zip(d_out.par_chunks(3))
        .map(|(p, dy)| {
            let surf: Surface<Dual<ND>> = surface_of(&(0..POINT_STRIDE).map(|i| Dual::var(p[i], i)).collect::<Vec<_>>());
            let mut contribs = Vec::with_capacity(k);
            let (mut spec, mut diff) = ([0.0f64; 3], [0.0f64; 3]);
            for l in lobes.chunks_exact(LOBE_STRIDE) {
                let lv: Vec<Dual<ND>> = (0..LOBE_STRIDE).map(|i| Dual::var(l[i], POINT_STRIDE + i)).collect();
                let (sp, df) = lobe_contribution(&surf, &lobe_of(&lv));
                for c in 0..3 {
                    spec[c] += sp[c].v;
                    diff[c] += df[c].v;
                }
                contribs.push((sp, df));
            }
            // The final clamps: a channel whose sum is clamped passes no gradient.
            let ws: [f64; 3] = [0, 1, 2].map(|c| if spec[c] >= 0.0 { dy[c] } else { 0.0 });
            let wd: [f64; 3] = [0, 1, 2].map(|c| if diff[c] >= 0.0 { dy[c] } else { 0.0 });
            let mut dp = vec![0.0; POINT_STRIDE];
            let mut dl = vec![0.0; k * LOBE_STRIDE];
            for (j, (sp, df)) in contribs.iter().enumerate() {
                for c in 0..3 {
                    for i in 0..POINT_STRIDE {
                        dp[i] += ws[c] * sp[c].d[i] + wd[c] * df[c].d[i];
                    }
                    for i in 0..LOBE_STRIDE {
                        dl[j * LOBE_STRIDE + i] += ws[c] * sp[c].d[POINT_STRIDE + i] + wd[c] * df[c].d[POINT_STRIDE + i];
                    }
                }
            }
            (dp, dl)
        })
        .collect();
    let mut d_lobes = vec![0.0; k * LOBE_STRIDE];
    let mut d_points = Vec::with_capacity(points.len());
    for (dp, dl) in per_point {
        d_points.extend(dp);
        for (a, b) in d_lobes.iter_mut().zip(dl) {
            *a += b;
        }
    }
    ShadeGrads { d_points, d_lobes }
}

fn check_shapes(points: usize, lobes: usize, d_out: Option<usize>) -> Result<usize, BackendError> {
    if points % POINT_STRIDE != 0 || lobes % LOBE_STRIDE != 0 {
        return Err(BackendError::Shape(format!(
            "sg shading: points ({points} floats) must be a multiple of {POINT_STRIDE}, lobes ({lobes}) of {LOBE_STRIDE}"
        )));
    }
    let n = points / POINT_STRIDE;
    if let Some(d) = d_out {
        if d != n * 3 {
            return Err(BackendError::Shape(format!("sg shading: d_out has {d} floats, expected {}", n * 3)));
        }
    }
    Ok(n)
}

impl Backend {
    /// Outgoing radiance `[n, 3]` at `points` `[n, 10]` (albedo, roughness, normal, view) under
    /// the SG environment `lobes` `[K, 7]` (axis, sharpness, amplitude). See the module docs.
    pub fn sg_shade_forward(&self, points: &Tensor, lobes: &Tensor) -> Result<Tensor, BackendError> {
        check_shapes(points.len(), lobes.len(), None)?;
        match self {
            Backend::Cpu(_) => {
                let p: Vec<f64> = points.host()?.iter().map(|&v| v as f64).collect();
                let l: Vec<f64> = lobes.host()?.iter().map(|&v| v as f64).collect();
                Ok(Tensor::Host(shade_forward_cpu(&p, &l).into_iter().map(|v| v as f32).collect()))
            }
            Backend::Gpu(g) => super::shade_gpu::forward(g, points, lobes),
        }
    }

    /// Backward of [`Backend::sg_shade_forward`]: (`d_points` `[n, 10]`, `d_lobes` `[K, 7]`).
    pub fn sg_shade_backward(&self, points: &Tensor, lobes: &Tensor, d_out: &Tensor) -> Result<(Tensor, Tensor), BackendError> {
        check_shapes(points.len(), lobes.len(), Some(d_out.len()))?;
        match self {
            Backend::Cpu(_) => {
                let f = |t: &Tensor| -> Result<Vec<f64>, BackendError> { Ok(t.host()?.iter().map(|&v| v as f64).collect()) };
                let g = shade_backward_cpu(&f(points)?, &f(lobes)?, &f(d_out)?);
                let h = |v: Vec<f64>| Tensor::Host(v.into_iter().map(|x| x as f32).collect());
                Ok((h(g.d_points), h(g.d_lobes)))
            }
            Backend::Gpu(g) => super::shade_gpu::backward(g, points, lobes, d_out),
        }
    }
}
