//! The shading's numbers in packs of [`LANES`]: stage 2 shades every point under some 32 light
//! lobes, and the per-lobe factors ([`BrdfSg::lobe_factors_f0`]) are the same code for each
//! lobe. [`LaneDual`] runs that code on [`LANES`] lobes at once, as dual numbers whose value and
//! tangents are each one [`Pack`] of f64: an AVX-512 register or two AVX2 ones, chosen at run
//! time ([`SimdLevel`]); a CPU with neither runs the scalar code lobe by lobe.
//!
//! The packs are written with `core::arch` intrinsics, not as arrays for the compiler to
//! vectorise: the shading's dual arithmetic as `[f64; 8]` loops was tried, and LLVM's SLP
//! vectoriser left five of six operations scalar (0.4–1.4× the scalar duals' speed).
//!
//! Every operation is the one [`Dual`] does, in the same order, per lane; the comparisons of the
//! shading are selects ([`Scalar::select_lt`] and its kin) and `exp` is [`exp_f64`](super::shade::exp_f64)'s steps on
//! every form, so a lane gives exactly the bits of the scalar code on that lobe, at every level
//! (tested). Only the speed differs.

use std::ops::{Add, Div, Mul, Neg, Sub};

use super::shade::{BrdfSg, Dual, Scalar, Sg, EXP_HI, EXP_LN2_HI, EXP_LN2_LO, EXP_LO, EXP_SHIFT, EXP_TAYLOR};
use crate::nn::simd::SimdLevel;

/// Lobes per pack: one AVX-512 register of f64 (two AVX2 ones).
pub const LANES: usize = 8;

/// [`LANES`] f64 in registers: the operations the shading needs, each the IEEE operation per
/// lane (so the same bits as the scalar one). Implemented for AVX-512 and AVX2; only called
/// from code built with those features (see [`lobe_factors`]).
pub trait Pack: Copy {
    type Mask: Copy;
    fn splat(x: f64) -> Self;
    fn load(a: &[f64; LANES]) -> Self;
    fn store(self) -> [f64; LANES];
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    fn div(self, o: Self) -> Self;
    /// Flips the sign bit (−0 for +0, as the scalar negation).
    fn neg(self) -> Self;
    fn sqrt(self) -> Self;
    /// `max(self, o)`, `o` where either is NaN (so a NaN `self` gives the bound, as `f64::max`).
    fn max(self, o: Self) -> Self;
    /// `min(self, o)`, `o` where either is NaN.
    fn min(self, o: Self) -> Self;
    fn lt(self, o: Self) -> Self::Mask;
    fn le(self, o: Self) -> Self::Mask;
    fn ge(self, o: Self) -> Self::Mask;
    fn gt(self, o: Self) -> Self::Mask;
    fn is_nan(self) -> Self::Mask;
    /// `a` where `m`, else `b`.
    fn blend(m: Self::Mask, a: Self, b: Self) -> Self;
    /// `2^n` for `t = n + 1.5·2⁵²` ([`exp_f64`](super::shade::exp_f64)'s bit step).
    fn pow2_of_shifted(t: Self) -> Self;
}

/// [`exp_f64`](super::shade::exp_f64)'s steps on a pack: the same bits per lane.
#[inline(always)]
fn exp_pack<P: Pack>(x: P) -> P {
    let xc = x.max(P::splat(EXP_LO)).min(P::splat(EXP_HI));
    let t = xc.mul(P::splat(std::f64::consts::LOG2_E)).add(P::splat(EXP_SHIFT));
    let n = t.sub(P::splat(EXP_SHIFT));
    let r = xc.sub(n.mul(P::splat(EXP_LN2_HI))).sub(n.mul(P::splat(EXP_LN2_LO)));
    let mut p = P::splat(EXP_TAYLOR[0]);
    for c in &EXP_TAYLOR[1..] {
        p = p.mul(r).add(P::splat(*c));
    }
    let e = P::splat(1.0).add(r.add(r.mul(r).mul(p)));
    let y = e.mul(P::pow2_of_shifted(t));
    // The scalar's choices, the first one taken last.
    let y = P::blend(x.gt(P::splat(EXP_HI)), P::splat(f64::INFINITY), y);
    let y = P::blend(x.lt(P::splat(EXP_LO)), P::splat(0.0), y);
    P::blend(x.is_nan(), x, y)
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Pack, LANES};
    use crate::sg::shade::EXP_SHIFT;
    use std::arch::x86_64::*;

    // SAFETY (every `unsafe` below): these methods run only inside functions built with the
    // features their intrinsics need (`lobe_factors_avx512` / `_avx2`), which are called only
    // where `SimdLevel::detected` found those features; loads and stores are of whole
    // `[f64; LANES]` arrays.

    /// One AVX-512 register.
    #[derive(Clone, Copy)]
    pub struct Avx512(__m512d);

    impl Pack for Avx512 {
        type Mask = __mmask8;
        #[inline(always)]
        fn splat(x: f64) -> Self {
            Self(unsafe { _mm512_set1_pd(x) })
        }
        #[inline(always)]
        fn load(a: &[f64; LANES]) -> Self {
            Self(unsafe { _mm512_loadu_pd(a.as_ptr()) })
        }
        #[inline(always)]
        fn store(self) -> [f64; LANES] {
            let mut a = [0.0; LANES];
            unsafe { _mm512_storeu_pd(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            Self(unsafe { _mm512_add_pd(self.0, o.0) })
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            Self(unsafe { _mm512_sub_pd(self.0, o.0) })
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            Self(unsafe { _mm512_mul_pd(self.0, o.0) })
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            Self(unsafe { _mm512_div_pd(self.0, o.0) })
        }
        #[inline(always)]
        fn neg(self) -> Self {
            Self(unsafe { _mm512_xor_pd(self.0, _mm512_set1_pd(-0.0)) })
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            Self(unsafe { _mm512_sqrt_pd(self.0) })
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            Self(unsafe { _mm512_max_pd(self.0, o.0) })
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            Self(unsafe { _mm512_min_pd(self.0, o.0) })
        }
        #[inline(always)]
        fn lt(self, o: Self) -> __mmask8 {
            unsafe { _mm512_cmp_pd_mask::<_CMP_LT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn le(self, o: Self) -> __mmask8 {
            unsafe { _mm512_cmp_pd_mask::<_CMP_LE_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn ge(self, o: Self) -> __mmask8 {
            unsafe { _mm512_cmp_pd_mask::<_CMP_GE_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> __mmask8 {
            unsafe { _mm512_cmp_pd_mask::<_CMP_GT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn is_nan(self) -> __mmask8 {
            unsafe { _mm512_cmp_pd_mask::<_CMP_UNORD_Q>(self.0, self.0) }
        }
        #[inline(always)]
        fn blend(m: __mmask8, a: Self, b: Self) -> Self {
            // `_mm512_mask_blend_pd(k, x, y)`: y where k, else x.
            Self(unsafe { _mm512_mask_blend_pd(m, b.0, a.0) })
        }
        #[inline(always)]
        fn pow2_of_shifted(t: Self) -> Self {
            unsafe {
                let bits = _mm512_sub_epi64(_mm512_castpd_si512(t.0), _mm512_set1_epi64(EXP_SHIFT.to_bits() as i64));
                let bits = _mm512_add_epi64(bits, _mm512_set1_epi64(1023));
                Self(_mm512_castsi512_pd(_mm512_slli_epi64::<52>(bits)))
            }
        }
    }

    /// Two AVX2 registers.
    #[derive(Clone, Copy)]
    pub struct Avx2([__m256d; 2]);

    // Each operation on both halves, written out: a closure would be built without the
    // caller's target features and keep its intrinsic as a call.
    macro_rules! halves {
        ($a:expr, $b:expr, $f:ident $(::<$c:ident>)?) => {
            unsafe { [$f$(::<$c>)?($a.0[0], $b.0[0]), $f$(::<$c>)?($a.0[1], $b.0[1])] }
        };
    }

    impl Pack for Avx2 {
        type Mask = [__m256d; 2];
        #[inline(always)]
        fn splat(x: f64) -> Self {
            let v = unsafe { _mm256_set1_pd(x) };
            Self([v, v])
        }
        #[inline(always)]
        fn load(a: &[f64; LANES]) -> Self {
            unsafe { Self([_mm256_loadu_pd(a.as_ptr()), _mm256_loadu_pd(a.as_ptr().add(4))]) }
        }
        #[inline(always)]
        fn store(self) -> [f64; LANES] {
            let mut a = [0.0; LANES];
            unsafe {
                _mm256_storeu_pd(a.as_mut_ptr(), self.0[0]);
                _mm256_storeu_pd(a.as_mut_ptr().add(4), self.0[1]);
            }
            a
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            Self(halves!(self, o, _mm256_add_pd))
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            Self(halves!(self, o, _mm256_sub_pd))
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            Self(halves!(self, o, _mm256_mul_pd))
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            Self(halves!(self, o, _mm256_div_pd))
        }
        #[inline(always)]
        fn neg(self) -> Self {
            Self(halves!(self, Self::splat(-0.0), _mm256_xor_pd))
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            unsafe { Self([_mm256_sqrt_pd(self.0[0]), _mm256_sqrt_pd(self.0[1])]) }
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            Self(halves!(self, o, _mm256_max_pd))
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            Self(halves!(self, o, _mm256_min_pd))
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Self::Mask {
            halves!(self, o, _mm256_cmp_pd::<_CMP_LT_OQ>)
        }
        #[inline(always)]
        fn le(self, o: Self) -> Self::Mask {
            halves!(self, o, _mm256_cmp_pd::<_CMP_LE_OQ>)
        }
        #[inline(always)]
        fn ge(self, o: Self) -> Self::Mask {
            halves!(self, o, _mm256_cmp_pd::<_CMP_GE_OQ>)
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Self::Mask {
            halves!(self, o, _mm256_cmp_pd::<_CMP_GT_OQ>)
        }
        #[inline(always)]
        fn is_nan(self) -> Self::Mask {
            halves!(self, self, _mm256_cmp_pd::<_CMP_UNORD_Q>)
        }
        #[inline(always)]
        fn blend(m: Self::Mask, a: Self, b: Self) -> Self {
            // `_mm256_blendv_pd(x, y, m)`: y where m's sign bit is set, else x.
            unsafe { Self([_mm256_blendv_pd(b.0[0], a.0[0], m[0]), _mm256_blendv_pd(b.0[1], a.0[1], m[1])]) }
        }
        #[inline(always)]
        fn pow2_of_shifted(t: Self) -> Self {
            unsafe {
                let shift = _mm256_set1_epi64x(EXP_SHIFT.to_bits() as i64);
                let bias = _mm256_set1_epi64x(1023);
                let lo = _mm256_add_epi64(_mm256_sub_epi64(_mm256_castpd_si256(t.0[0]), shift), bias);
                let hi = _mm256_add_epi64(_mm256_sub_epi64(_mm256_castpd_si256(t.0[1]), shift), bias);
                Self([_mm256_castsi256_pd(_mm256_slli_epi64::<52>(lo)), _mm256_castsi256_pd(_mm256_slli_epi64::<52>(hi))])
            }
        }
    }
}

/// A dual number with `N` tangents in each of [`LANES`] lanes (`N = 0`: plain values).
#[derive(Clone, Copy)]
pub struct LaneDual<P: Pack, const N: usize> {
    pub v: P,
    pub d: [P; N],
}

impl<P: Pack, const N: usize> LaneDual<P, N> {
    /// `x` in every lane.
    #[inline(always)]
    pub fn splat(x: Dual<N>) -> Self {
        let mut d = [P::splat(0.0); N];
        for t in 0..N {
            d[t] = P::splat(x.d[t]);
        }
        Self { v: P::splat(x.v), d }
    }

    /// One value per lane, without tangents (`tangent = None`) or as input variable `i`.
    #[inline(always)]
    pub fn input(v: &[f64; LANES], tangent: Option<usize>) -> Self {
        let mut d = [P::splat(0.0); N];
        for (t, row) in d.iter_mut().enumerate() {
            if tangent == Some(t) {
                *row = P::splat(1.0);
            }
        }
        Self { v: P::load(v), d }
    }

    /// The first `n` lanes as [`Dual`]s.
    #[inline(always)]
    fn lanes(&self, n: usize) -> impl Iterator<Item = Dual<N>> {
        let v = self.v.store();
        let mut d = [[0.0; LANES]; N];
        for t in 0..N {
            d[t] = self.d[t].store();
        }
        (0..n.min(LANES)).map(move |j| Dual { v: v[j], d: std::array::from_fn(|t| d[t][j]) })
    }

    #[inline(always)]
    fn select(m: P::Mask, a: Self, b: Self) -> Self {
        let mut d = b.d;
        for t in 0..N {
            d[t] = P::blend(m, a.d[t], b.d[t]);
        }
        Self { v: P::blend(m, a.v, b.v), d }
    }

    /// The chain rule through a function with value `f` and slope `df` per lane.
    #[inline(always)]
    fn chain(self, f: P, df: P) -> Self {
        let mut d = self.d;
        for t in 0..N {
            d[t] = d[t].mul(df);
        }
        Self { v: f, d }
    }
}

impl<P: Pack, const N: usize> Add for LaneDual<P, N> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        let mut d = self.d;
        for t in 0..N {
            d[t] = d[t].add(o.d[t]);
        }
        Self { v: self.v.add(o.v), d }
    }
}

impl<P: Pack, const N: usize> Sub for LaneDual<P, N> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        let mut d = self.d;
        for t in 0..N {
            d[t] = d[t].sub(o.d[t]);
        }
        Self { v: self.v.sub(o.v), d }
    }
}

impl<P: Pack, const N: usize> Mul for LaneDual<P, N> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        let mut d = self.d;
        for t in 0..N {
            d[t] = self.d[t].mul(o.v).add(self.v.mul(o.d[t]));
        }
        Self { v: self.v.mul(o.v), d }
    }
}

impl<P: Pack, const N: usize> Div for LaneDual<P, N> {
    type Output = Self;
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        let inv = P::splat(1.0).div(o.v);
        let q = self.v.mul(inv);
        let mut d = self.d;
        for t in 0..N {
            d[t] = self.d[t].sub(q.mul(o.d[t])).mul(inv);
        }
        Self { v: q, d }
    }
}

impl<P: Pack, const N: usize> Neg for LaneDual<P, N> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        let mut d = self.d;
        for t in 0..N {
            d[t] = d[t].neg();
        }
        Self { v: self.v.neg(), d }
    }
}

impl<P: Pack, const N: usize> Scalar for LaneDual<P, N> {
    #[inline(always)]
    fn c(v: f64) -> Self {
        Self { v: P::splat(v), d: [P::splat(0.0); N] }
    }
    #[inline(always)]
    fn exp(self) -> Self {
        let e = exp_pack(self.v);
        self.chain(e, e)
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        let s = self.v.sqrt();
        let ds = P::blend(s.gt(P::splat(0.0)), P::splat(0.5).div(s), P::splat(0.0));
        self.chain(s, ds)
    }
    #[inline(always)]
    fn select_lt(self, c: f64, a: Self, b: Self) -> Self {
        Self::select(self.v.lt(P::splat(c)), a, b)
    }
    #[inline(always)]
    fn select_le(self, c: f64, a: Self, b: Self) -> Self {
        Self::select(self.v.le(P::splat(c)), a, b)
    }
    #[inline(always)]
    fn select_ge(self, c: f64, a: Self, b: Self) -> Self {
        Self::select(self.v.ge(P::splat(c)), a, b)
    }
    #[inline(always)]
    fn add_c(self, c: f64) -> Self {
        Self { v: self.v.add(P::splat(c)), d: self.d }
    }
    #[inline(always)]
    fn mul_c(self, c: f64) -> Self {
        let c = P::splat(c);
        self.chain(self.v.mul(c), c)
    }
    #[inline(always)]
    fn c_sub(self, c: f64) -> Self {
        let mut d = self.d;
        for t in 0..N {
            d[t] = d[t].neg();
        }
        Self { v: P::splat(c).sub(self.v), d }
    }
    #[inline(always)]
    fn recip(self) -> Self {
        let inv = P::splat(1.0).div(self.v);
        let mut d = self.d;
        for t in 0..N {
            d[t] = inv.mul(d[t]).neg().mul(inv);
        }
        Self { v: inv, d }
    }
}

/// Per lobe `[F_s, F_e, F_d]` of [`BrdfSg::lobe_factors_f0`] for a point's BRDF side, in the
/// order of `lobes`, [`LANES`] lobes at a time where the CPU has AVX2 or AVX-512. With
/// `lobe_tangents = Some(i)` the lobe's axis is tangents `i..i + 3` and its sharpness tangent
/// `i + 3` (the point's own tangents come in through `brdf`); with `None` the lobes are
/// constants. The same bits as the scalar `brdf.lobe_factors_f0` on each lobe, at every `level`.
pub fn lobe_factors<const N: usize>(level: SimdLevel, brdf: &BrdfSg<Dual<N>>, lobes: &[Sg<f64>], lobe_tangents: Option<usize>) -> Vec<[Dual<N>; 3]> {
    assert!(lobe_tangents.is_none_or(|i| i + 4 <= N), "lobe tangents beyond the dual's {N}");
    #[cfg(target_arch = "x86_64")]
    match level.min(SimdLevel::detected()) {
        // SAFETY: the CPU has these features (`SimdLevel::detected` found them).
        SimdLevel::Avx512 => return unsafe { lobe_factors_avx512(brdf, lobes, lobe_tangents) },
        SimdLevel::Avx2 => return unsafe { lobe_factors_avx2(brdf, lobes, lobe_tangents) },
        SimdLevel::Scalar => {}
    }
    let _ = level;
    lobes
        .iter()
        .map(|l| {
            let input = |v: f64, k: usize| match lobe_tangents {
                Some(i) => Dual::var(v, i + k),
                None => Dual::c(v),
            };
            let (fs, fe, fd) = brdf.lobe_factors_f0([0, 1, 2].map(|a| input(l.axis[a], a)), input(l.lambda, 3));
            [fs, fe, fd]
        })
        .collect()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
unsafe fn lobe_factors_avx512<const N: usize>(brdf: &BrdfSg<Dual<N>>, lobes: &[Sg<f64>], lobe_tangents: Option<usize>) -> Vec<[Dual<N>; 3]> {
    lobe_factors_packs::<x86::Avx512, N>(brdf, lobes, lobe_tangents)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn lobe_factors_avx2<const N: usize>(brdf: &BrdfSg<Dual<N>>, lobes: &[Sg<f64>], lobe_tangents: Option<usize>) -> Vec<[Dual<N>; 3]> {
    lobe_factors_packs::<x86::Avx2, N>(brdf, lobes, lobe_tangents)
}

#[inline(always)]
fn lobe_factors_packs<P: Pack, const N: usize>(brdf: &BrdfSg<Dual<N>>, lobes: &[Sg<f64>], lobe_tangents: Option<usize>) -> Vec<[Dual<N>; 3]> {
    let packed = brdf.map(LaneDual::<P, N>::splat);
    let mut out = Vec::with_capacity(lobes.len());
    for chunk in lobes.chunks(LANES) {
        // A short last pack repeats its first lobe in the spare lanes (dropped below).
        let mut axis = [[0.0; LANES]; 3];
        let mut lambda = [0.0; LANES];
        for j in 0..LANES {
            let l = chunk.get(j).unwrap_or(&chunk[0]);
            for (a, row) in axis.iter_mut().enumerate() {
                row[j] = l.axis[a];
            }
            lambda[j] = l.lambda;
        }
        let tangent = |k: usize| lobe_tangents.map(|i| i + k);
        let axis = [LaneDual::<P, N>::input(&axis[0], tangent(0)), LaneDual::input(&axis[1], tangent(1)), LaneDual::input(&axis[2], tangent(2))];
        let lambda = LaneDual::input(&lambda, tangent(3));
        let (fs, fe, fd) = packed.lobe_factors_f0(axis, lambda);
        for ((s, e), d) in fs.lanes(chunk.len()).zip(fe.lanes(chunk.len())).zip(fd.lanes(chunk.len())) {
            out.push([s, e, d]);
        }
    }
    out
}

/// The per-lobe factors at `level` against the scalar duals lobe by lobe, on one point's BRDF
/// side under `lobes` (both BRDF forms, the lobes' axis and sharpness as tangents as stage 2
/// shades them), alternating within each round; checks the same bits. `bench nn` reports it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct LobeFactorLanes {
    pub level: SimdLevel,
    pub lobes: usize,
    /// Scalar time over `level`'s time (best of the rounds).
    pub speedup: f64,
    /// `level`'s time per lobe, ns.
    pub ns_per_lobe: f64,
}

/// Times [`lobe_factors`] at the detected level against the scalar code (`rounds` rounds of
/// `reps` points each). None where the CPU has no wider level.
pub fn bench_lobe_factors(lobes: usize, reps: usize, rounds: usize) -> anyhow::Result<Option<LobeFactorLanes>> {
    let level = SimdLevel::detected();
    if level == SimdLevel::Scalar || lobes == 0 {
        return Ok(None);
    }
    let mut rng = crate::util::rng(11);
    let unit = |rng: &mut rand::rngs::StdRng| {
        use rand::Rng;
        let a: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
        let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt().max(1e-9);
        a.map(|x| x / l)
    };
    let sgs: Vec<Sg<f64>> = (0..lobes).map(|k| Sg { axis: unit(&mut rng), lambda: 0.5 + (k as f64 * 3.7) % 60.0, mu: [1.0; 3] }).collect();
    let cst = |x: f64| Dual::<5>::c(x);
    let points: Vec<BrdfSg<Dual<5>>> = (0..reps.max(1))
        .map(|i| {
            let model = if i % 2 == 0 { super::shade::BrdfModel::Physg } else { super::shade::BrdfModel::Calibrated };
            let n = unit(&mut rng);
            let v = unit(&mut rng);
            let v = if v[0] * n[0] + v[1] * n[1] + v[2] * n[2] < 0.0 { v.map(|x| -x) } else { v };
            BrdfSg::with_model(model, n.map(cst), v.map(cst), Dual::var(0.1 + 0.8 * (i as f64 / reps as f64), 0))
        })
        .collect();
    let mut best = [f64::INFINITY; 2];
    for _ in 0..rounds.max(2) {
        let mut outs: [Vec<[Dual<5>; 3]>; 2] = Default::default();
        for (i, l) in [SimdLevel::Scalar, level].into_iter().enumerate() {
            let t = std::time::Instant::now();
            outs[i] = points.iter().flat_map(|b| lobe_factors(l, b, &sgs, Some(1))).collect();
            best[i] = best[i].min(t.elapsed().as_secs_f64());
        }
        if bits(&outs[0]) != bits(&outs[1]) {
            anyhow::bail!("SG lobe factors: the {level:?} packs and the scalar code disagree");
        }
    }
    let calls = (points.len() * lobes) as f64;
    Ok(Some(LobeFactorLanes { level, lobes, speedup: best[0] / best[1], ns_per_lobe: best[1] / calls * 1e9 }))
}

/// Every value and tangent of a list of factors, as bits.
fn bits<const N: usize>(f: &[[Dual<N>; 3]]) -> Vec<u64> {
    f.iter().flatten().flat_map(|d| std::iter::once(d.v.to_bits()).chain(d.d.iter().map(|x| x.to_bits()))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sg::shade::{exp_f64, BrdfModel, LAMBDA_MIN, R_MIN};

    fn unit(a: [f64; 3]) -> [f64; 3] {
        let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        a.map(|x| x / l)
    }

    /// Lobes that reach every branch of the shading: sharpness below the floor, at it, where the
    /// `1 − e^{−x}` series holds, ordinary, and D's sharpest; axes along, against and across the
    /// normal (cos β = 0 exactly), and not unit.
    fn lobes(n: [f64; 3], count: usize) -> Vec<Sg<f64>> {
        let lambdas = [1e-7, LAMBDA_MIN, 5e-5, 0.3, 4.0, 35.0, 900.0, 1.2e7];
        // Across the normal: n × x, or n × y where n is along x.
        let e = if n[0].abs() > 0.9 { [0.0, 1.0, 0.0] } else { [1.0, 0.0, 0.0] };
        let t = unit([n[1] * e[2] - n[2] * e[1], n[2] * e[0] - n[0] * e[2], n[0] * e[1] - n[1] * e[0]]);
        let axes = [n, n.map(|x| -x), t, unit([0.3, 0.9, -0.2]), [2.0, 0.1, 0.1], unit([-0.5, 0.2, 0.8]), unit([0.01, 0.0, 1.0])];
        (0..count).map(|k| Sg { axis: axes[k % axes.len()], lambda: lambdas[(k * 3) % lambdas.len()], mu: [1.0; 3] }).collect()
    }

    fn points() -> Vec<([f64; 3], [f64; 3], f64)> {
        let n = unit([0.2, 0.3, 0.93]);
        vec![
            (n, unit([0.1, 0.9, 0.4]), 0.4),
            (n, n, R_MIN),
            (n, unit([-0.3, -0.2, 0.93]), 1.0),
            // Grazing and back-facing views, roughness outside [R_MIN, 1].
            (unit([0.0, 0.0, 1.0]), unit([1.0, 0.0, 0.0]), 0.001),
            (unit([0.0, 1.0, 0.0]), unit([0.0, -1.0, 0.2]), 1.7),
            ([0.0, 0.0, 3.0], [0.5, 0.0, 0.5], 0.25),
        ]
    }

    #[test]
    fn every_level_gives_the_scalar_duals_bits() {
        for model in [BrdfModel::Physg, BrdfModel::Calibrated] {
            for (n, v, r) in points() {
                for count in [1, 7, 8, 13, 32] {
                    let sgs = lobes(n, count);
                    // Stage 2's gradient: roughness and the lobe as tangents.
                    let c5 = |x: f64| Dual::<5>::c(x);
                    let b5 = BrdfSg::with_model(model, n.map(c5), v.map(c5), Dual::var(r, 0));
                    let want5 = bits(&lobe_factors(SimdLevel::Scalar, &b5, &sgs, Some(1)));
                    // The geometry refinement's: the normal as tangents, the lobes constant.
                    let b3 = BrdfSg::with_model(model, [0, 1, 2].map(|a| Dual::<3>::var(n[a], a)), v.map(Dual::c), Dual::c(r));
                    let want3 = bits(&lobe_factors(SimdLevel::Scalar, &b3, &sgs, None));
                    let b0 = BrdfSg::with_model(model, n.map(Dual::<0>::c), v.map(Dual::c), Dual::c(r));
                    let want0 = bits(&lobe_factors(SimdLevel::Scalar, &b0, &sgs, None));
                    assert!(want5.iter().all(|&b| f64::from_bits(b).is_finite()), "{model:?} n {n:?} v {v:?} r {r}: non-finite factor");
                    for level in SimdLevel::ALL {
                        assert_eq!(bits(&lobe_factors(level, &b5, &sgs, Some(1))), want5, "{model:?} {level:?} n {n:?} v {v:?} r {r} K {count}");
                        assert_eq!(bits(&lobe_factors(level, &b3, &sgs, None)), want3, "{model:?} {level:?} (normal tangents) K {count}");
                        assert_eq!(bits(&lobe_factors(level, &b0, &sgs, None)), want0, "{model:?} {level:?} (values) K {count}");
                    }
                }
            }
        }
    }

    #[test]
    fn the_scalar_code_is_the_per_lobe_factors_with_the_lobe_as_tangents_one_to_four() {
        let (n, v, r) = points()[0];
        let c = |x: f64| Dual::<5>::c(x);
        let brdf = BrdfSg::with_model(BrdfModel::Calibrated, n.map(c), v.map(c), Dual::var(r, 0));
        let sgs = lobes(n, 9);
        let got = lobe_factors(SimdLevel::detected(), &brdf, &sgs, Some(1));
        let want: Vec<[Dual<5>; 3]> = sgs
            .iter()
            .map(|l| {
                let (s, e, d) = brdf.lobe_factors_f0([Dual::var(l.axis[0], 1), Dual::var(l.axis[1], 2), Dual::var(l.axis[2], 3)], Dual::var(l.lambda, 4));
                [s, e, d]
            })
            .collect();
        assert_eq!(bits(&got), bits(&want));
        // The tangents are live: the sharpness moves the specular factor of a lit lobe.
        assert!(got[3][0].d[4] != 0.0 && got[3][0].d[0] != 0.0, "{:?}", got[3][0]);
    }

    #[test]
    fn exp_is_within_two_ulp_of_libm_and_keeps_its_range() {
        let ulps = |a: f64, b: f64| (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs();
        let mut worst = 0;
        let mut check = |x: f64| {
            let (got, want) = (exp_f64(x), x.exp());
            let u = ulps(got, want);
            assert!(u <= 2, "exp({x:e}) = {got:e}, libm {want:e} ({u} ulp)");
            worst = worst.max(u);
        };
        for i in 0..=200_000 {
            check(-708.0 + 1417.0 * i as f64 / 200_000.0);
        }
        for i in -300..=300 {
            check((i as f64 * 0.1).exp2() * 1e-12);
            check(-(i as f64 * 0.1).exp2() * 1e-12);
        }
        check(0.0);
        assert_eq!(exp_f64(0.0), 1.0);
        assert_eq!(exp_f64(-0.0), 1.0);
        assert_eq!(exp_f64(-708.5), 0.0);
        assert_eq!(exp_f64(f64::NEG_INFINITY), 0.0);
        assert_eq!(exp_f64(709.5), f64::INFINITY);
        assert_eq!(exp_f64(f64::INFINITY), f64::INFINITY);
        assert!(exp_f64(f64::NAN).is_nan());
        assert!(worst >= 1, "compared against libm at all");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn every_pack_gives_exps_bits() {
        #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
        fn avx512(x: &[f64; LANES]) -> [f64; LANES] {
            exp_pack(x86::Avx512::load(x)).store()
        }
        #[target_feature(enable = "avx2,fma")]
        fn avx2(x: &[f64; LANES]) -> [f64; LANES] {
            exp_pack(x86::Avx2::load(x)).store()
        }
        let mut xs: Vec<f64> = (0..4096).map(|i| -750.0 + 1470.0 * i as f64 / 4095.0).collect();
        xs.extend([0.0, -0.0, 1e-300, -1e-300, f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -708.0, 709.0, -708.0000001, 709.0000001, 0.5 * std::f64::consts::LN_2]);
        while xs.len() % LANES != 0 {
            xs.push(1.0);
        }
        let level = SimdLevel::detected();
        for chunk in xs.chunks_exact(LANES) {
            let x: &[f64; LANES] = chunk.try_into().unwrap();
            let want: Vec<u64> = x.iter().map(|&v| exp_f64(v).to_bits()).collect();
            if level >= SimdLevel::Avx2 {
                // SAFETY: the CPU has AVX2 and FMA.
                assert_eq!(unsafe { avx2(x) }.map(f64::to_bits).to_vec(), want, "AVX2 at {x:?}");
            }
            if level >= SimdLevel::Avx512 {
                // SAFETY: the CPU has these features.
                assert_eq!(unsafe { avx512(x) }.map(f64::to_bits).to_vec(), want, "AVX-512 at {x:?}");
            }
        }
    }
}
