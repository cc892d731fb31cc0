//! Multilayer perceptrons: configuration, parameter layout, initialisers, forward and backward
//! (parameter gradients and input gradients) on the cpu backend (generic over f32/f64, GEMMs by
//! the `gemm` crate, one thread per call, rayon over row chunks) and on wgpu (`shaders/mlp.wgsl`:
//! a tiled GEMM with workgroup memory plus elementwise activation / skip / bias / weight-norm
//! kernels).
//!
//! # Network
//! Linear layers `0..=L` for `L = widths.len()` hidden layers. Layer `l` maps `u_l` (its input,
//! `[n, in_l]`) to `z_l = u_l·W_lᵀ + b_l` and `h_l = act(z_l)`; the last layer uses
//! `output_activation`. `u_0 = x`, `u_l = h_{l-1}` except for a skip layer `l` (IDR), where
//! `u_l = concat(h_{l-1}, x)/√2` and layer `l-1` therefore outputs `widths[l-1] - in_dim`.
//!
//! # Parameter layout (one flat f32 vector)
//! For each layer in order: `W` row-major `[out][in]` (with weight norm: the direction `v`
//! `[out][in]`, then the gain `g` `[out]`, `W_i = g_i·v_i/‖v_i‖` per output row), then `b` `[out]`.
//! [`Mlp::layers`] gives every offset.

use crate::nn::simd::SimdLevel;
use std::f64::consts::PI;
use std::fmt::Debug;
use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

use crate::backend::gpu::{groups_1d, shaders, Access, Bind, GpuBuffer, GpuContext, KernelSpec};
use crate::backend::{Backend, BackendError, Tensor};

/// WGSL source of the MLP kernel family.
pub const MLP_WGSL: &str = include_str!("../../shaders/mlp.wgsl");

// ---- configuration -------------------------------------------------------------------------

/// Elementwise activation.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Activation {
    None,
    Relu,
    LeakyRelu(f32),
    /// `log(1 + exp(β z))/β`, overflow-safe (exactly `z` past `βz = 20`, as PyTorch's threshold).
    Softplus {
        beta: f32,
    },
    /// Overflow-safe logistic function.
    Sigmoid,
}

impl Activation {
    /// Kernel code and parameter (mirrors `act_fwd` in `shaders/mlp.wgsl`).
    fn code(&self) -> (u32, f32) {
        match *self {
            Activation::None => (0, 0.0),
            Activation::Relu => (1, 0.0),
            Activation::LeakyRelu(s) => (2, s),
            Activation::Softplus { beta } => (3, beta),
            Activation::Sigmoid => (4, 0.0),
        }
    }

    /// `act(z)`.
    pub fn forward<T: Real>(&self, z: T) -> T {
        let zero = T::zero();
        match *self {
            Activation::None => z,
            Activation::Relu => z.max_(zero),
            Activation::LeakyRelu(s) => {
                if z > zero {
                    z
                } else {
                    T::from_f64(s as f64) * z
                }
            }
            Activation::Softplus { beta } => softplus(z, T::from_f64(beta as f64), T::from_f64(1.0 / beta as f64)),
            Activation::Sigmoid => sigmoid(z),
        }
    }

    /// `act'(z)`.
    pub fn derivative<T: Real>(&self, z: T) -> T {
        let zero = T::zero();
        let one = T::one();
        match *self {
            Activation::None => one,
            Activation::Relu => {
                if z > zero {
                    one
                } else {
                    zero
                }
            }
            Activation::LeakyRelu(s) => {
                if z > zero {
                    one
                } else {
                    T::from_f64(s as f64)
                }
            }
            Activation::Softplus { beta } => softplus_derivative(z, T::from_f64(beta as f64)),
            Activation::Sigmoid => {
                let s = sigmoid(z);
                s * (one - s)
            }
        }
    }

    /// `act(z)` over a slice; the match is outside the loops so each loop vectorises, with the
    /// widest vectors this CPU has ([`SimdLevel::detected`]: runtime dispatch, the crate is
    /// built for baseline x86-64). Every level gives the same bits.
    pub fn forward_slice<T: Real>(&self, z: &[T]) -> Vec<T> {
        self.forward_slice_at(SimdLevel::detected(), z)
    }

    /// [`Activation::forward_slice`] with the loops built for `level` (one this CPU lacks runs
    /// at the widest one it has): `bench nn` times the levels against each other.
    pub fn forward_slice_at<T: Real>(&self, level: SimdLevel, z: &[T]) -> Vec<T> {
        #[cfg(target_arch = "x86_64")]
        match level.min(SimdLevel::detected()) {
            // SAFETY: the CPU has these features (`SimdLevel::detected` found them).
            SimdLevel::Avx512 => return unsafe { self.forward_slice_avx512(z) },
            SimdLevel::Avx2 => return unsafe { self.forward_slice_avx2(z) },
            SimdLevel::Scalar => {}
        }
        let _ = level;
        self.forward_slice_impl(z)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
    unsafe fn forward_slice_avx512<T: Real>(&self, z: &[T]) -> Vec<T> {
        self.forward_slice_impl(z)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn forward_slice_avx2<T: Real>(&self, z: &[T]) -> Vec<T> {
        self.forward_slice_impl(z)
    }

    #[inline(always)]
    fn forward_slice_impl<T: Real>(&self, z: &[T]) -> Vec<T> {
        let zero = T::zero();
        // Written once into fresh capacity (zeroing it first was a memset of every activation).
        // Explicit loops with inlined bodies: a closure (`map`) is compiled without the caller's
        // target features, and its loop does not vectorise.
        let mut out: Vec<T> = Vec::with_capacity(z.len());
        let slots = &mut out.spare_capacity_mut()[..z.len()];
        match *self {
            Activation::None => {
                for (o, &v) in slots.iter_mut().zip(z) {
                    o.write(v);
                }
            }
            Activation::Relu => {
                for (o, &v) in slots.iter_mut().zip(z) {
                    o.write(v.max_(zero));
                }
            }
            Activation::LeakyRelu(s) => {
                let s = T::from_f64(s as f64);
                for (o, &v) in slots.iter_mut().zip(z) {
                    o.write(if v > zero { v } else { s * v });
                }
            }
            Activation::Softplus { beta } => {
                let (b, inv_b) = (T::from_f64(beta as f64), T::from_f64(1.0 / beta as f64));
                for (o, &v) in slots.iter_mut().zip(z) {
                    o.write(softplus(v, b, inv_b));
                }
            }
            Activation::Sigmoid => {
                for (o, &v) in slots.iter_mut().zip(z) {
                    o.write(sigmoid(v));
                }
            }
        }
        // SAFETY: every one of the first z.len() slots was written just above.
        unsafe { out.set_len(z.len()) };
        out
    }

    /// `dh · act'(z)` over slices (the backward of [`Activation::forward_slice`]).
    pub fn backward_slice<T: Real>(&self, z: &[T], dh: &[T]) -> Vec<T> {
        self.backward_slice_at(SimdLevel::detected(), z, dh)
    }

    /// [`Activation::backward_slice`] with the loops built for `level` (see
    /// [`Activation::forward_slice_at`]).
    pub fn backward_slice_at<T: Real>(&self, level: SimdLevel, z: &[T], dh: &[T]) -> Vec<T> {
        #[cfg(target_arch = "x86_64")]
        match level.min(SimdLevel::detected()) {
            // SAFETY: the CPU has these features (`SimdLevel::detected` found them).
            SimdLevel::Avx512 => return unsafe { self.backward_slice_avx512(z, dh) },
            SimdLevel::Avx2 => return unsafe { self.backward_slice_avx2(z, dh) },
            SimdLevel::Scalar => {}
        }
        let _ = level;
        self.backward_slice_impl(z, dh)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
    unsafe fn backward_slice_avx512<T: Real>(&self, z: &[T], dh: &[T]) -> Vec<T> {
        self.backward_slice_impl(z, dh)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn backward_slice_avx2<T: Real>(&self, z: &[T], dh: &[T]) -> Vec<T> {
        self.backward_slice_impl(z, dh)
    }

    #[inline(always)]
    fn backward_slice_impl<T: Real>(&self, z: &[T], dh: &[T]) -> Vec<T> {
        let (zero, one) = (T::zero(), T::one());
        assert_eq!(z.len(), dh.len(), "activation backward: pre-activations and gradients differ in length");
        // As the forward: written once into fresh capacity, explicit loops.
        let mut out: Vec<T> = Vec::with_capacity(z.len());
        let it = out.spare_capacity_mut()[..z.len()].iter_mut().zip(z).zip(dh);
        match *self {
            Activation::None => {
                for ((o, _), &g) in it {
                    o.write(g);
                }
            }
            Activation::Relu => {
                for ((o, &v), &g) in it {
                    o.write(if v > zero { g } else { zero });
                }
            }
            Activation::LeakyRelu(s) => {
                let s = T::from_f64(s as f64);
                for ((o, &v), &g) in it {
                    o.write(if v > zero { g } else { s * g });
                }
            }
            Activation::Softplus { beta } => {
                let b = T::from_f64(beta as f64);
                for ((o, &v), &g) in it {
                    o.write(g * softplus_derivative(v, b));
                }
            }
            Activation::Sigmoid => {
                for ((o, &v), &g) in it {
                    let s = sigmoid(v);
                    o.write(g * s * (one - s));
                }
            }
        }
        // SAFETY: every one of the first z.len() slots was written just above (dh has as many).
        unsafe { out.set_len(z.len()) };
        out
    }

    fn check(&self) -> Result<(), BackendError> {
        match *self {
            Activation::Softplus { beta } if !(beta.is_finite() && beta > 0.0) => {
                Err(BackendError::Config(format!(
                    "softplus beta must be positive and finite, got {beta}"
                )))
            }
            Activation::LeakyRelu(s) if !s.is_finite() => Err(BackendError::Config(format!(
                "leaky ReLU slope must be finite, got {s}"
            ))),
            _ => Ok(()),
        }
    }
}

/// `1/(1 + e^{-z})`: overflow-safe without branches (f32's `exp_` clamps its argument; f64's
/// `exp` → ∞ gives 0).
#[inline(always)]
fn sigmoid<T: Real>(z: T) -> T {
    T::one() / (T::one() + (-z).exp_())
}

#[inline(always)]
fn softplus<T: Real>(z: T, beta: T, inv_beta: T) -> T {
    let y = beta * z;
    // ln(1 + e^{−|y|}) takes its argument in (0, 1], the range `ln_1p_` needs; a product by
    // 1/β, not a division by β (a division is the slowest step of this loop). |y| is capped at
    // SOFTPLUS_FLOOR (compares, not `min`, so that NaN goes on through), where the result is 0.
    let a = y.abs_();
    let floor = T::from_f64(SOFTPLUS_FLOOR);
    let a = if a > floor { floor } else { a };
    let sp = (y.max_(T::zero()) + (-a).exp_().ln_1p_()) * inv_beta;
    // Past βz = 20 softplus equals z to f32 precision (and β·z may overflow): a select, so
    // the loop still vectorises.
    if y > T::from_f64(20.0) {
        z
    } else if y < -floor {
        T::zero()
    } else {
        sp
    }
}

/// Below `βz = −SOFTPLUS_FLOOR` softplus is 0 and its derivative σ(βz) is 0: their true values
/// (under 2e-35 and 2e-35/β) would be subnormal, or become so in the next layer's products, and
/// every operation on a subnormal costs a microcode assist (`bench nn`'s randomly initialised
/// networks, whose pre-activations reach that far, ran their forward 3-10× and their
/// forward+backward 6-20× slower).
const SOFTPLUS_FLOOR: f64 = 80.0;

/// σ(βz), softplus's derivative: 0 below `βz = −SOFTPLUS_FLOOR`, as [`softplus`] is.
#[inline(always)]
fn softplus_derivative<T: Real>(z: T, beta: T) -> T {
    let y = beta * z;
    let s = sigmoid(y);
    if y < T::from_f64(-SOFTPLUS_FLOOR) {
        T::zero()
    } else {
        s
    }
}

/// An MLP's shape and options. See the module docs for the layer and skip conventions.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MlpConfig {
    pub in_dim: usize,
    /// Hidden layer widths (the width a skip layer *receives*, i.e. after the concatenation).
    pub widths: Vec<usize>,
    pub out_dim: usize,
    pub activation: Activation,
    pub output_activation: Activation,
    /// Linear-layer indices (1..=widths.len()) whose input is `concat(h, x)/√2`.
    pub skip_layers: Vec<usize>,
    pub weight_norm: bool,
}

/// Where one linear layer lives in the flat parameter vector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LayerLayout {
    pub in_dim: usize,
    pub out_dim: usize,
    /// `W` (or `v` with weight norm), `[out][in]` row-major.
    pub w: usize,
    /// `g` `[out]` with weight norm.
    pub g: Option<usize>,
    pub b: usize,
    /// This layer's input is `concat(h_{l-1}, x)/√2`.
    pub skip: bool,
    /// Offset of this layer's `W` in the dense (weight-norm-free) layout `[W, b]` per layer.
    pub dense_w: usize,
    pub dense_b: usize,
}

/// A validated MLP: config plus its parameter layout.
#[derive(Clone, Debug)]
pub struct Mlp {
    pub config: MlpConfig,
    pub layers: Vec<LayerLayout>,
    num_params: usize,
    num_dense: usize,
}

/// How to initialise parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Init {
    /// Weights `N(0, gain/√in)` (gain √2 for ReLU-like activations, 1 otherwise), biases 0.
    Default,
    /// IDR/SAL geometric initialisation: the network starts as the SDF of a sphere of `radius`
    /// (output 0). `raw_dims`: the first `raw_dims` input dims are the raw position; the others
    /// (positional-encoding terms) start with zero weights in the first and skip layers.
    Geometric { radius: f32, raw_dims: usize },
}

/// √2, the skip-connection scale.
const SQRT2: f64 = std::f64::consts::SQRT_2;

impl Mlp {
    /// Validate a config (zero widths, skip positions, dims) and compute the layout.
    pub fn new(config: MlpConfig) -> Result<Self, BackendError> {
        let c = &config;
        if c.in_dim == 0 || c.out_dim == 0 {
            return Err(BackendError::Config(format!(
                "MLP in_dim ({}) and out_dim ({}) must be > 0",
                c.in_dim, c.out_dim
            )));
        }
        if let Some(i) = c.widths.iter().position(|&w| w == 0) {
            return Err(BackendError::Config(format!(
                "MLP hidden layer {i} has zero width"
            )));
        }
        c.activation.check()?;
        c.output_activation.check()?;
        let n_layers = c.widths.len() + 1;
        for &s in &c.skip_layers {
            if s == 0 || s >= n_layers {
                return Err(BackendError::Config(format!(
                    "skip layer {s} must be in 1..={}",
                    n_layers - 1
                )));
            }
            if c.widths[s - 1] <= c.in_dim {
                return Err(BackendError::Config(format!(
                    "skip into layer {s}: width {} must exceed in_dim {}",
                    c.widths[s - 1],
                    c.in_dim
                )));
            }
        }
        let mut layers = Vec::with_capacity(n_layers);
        let (mut off, mut dense) = (0, 0);
        for l in 0..n_layers {
            let in_dim = if l == 0 { c.in_dim } else { c.widths[l - 1] };
            let out_dim = if l + 1 == n_layers {
                c.out_dim
            } else if c.skip_layers.contains(&(l + 1)) {
                c.widths[l] - c.in_dim
            } else {
                c.widths[l]
            };
            let w = off;
            off += in_dim * out_dim;
            let g = c.weight_norm.then(|| {
                off += out_dim;
                off - out_dim
            });
            let b = off;
            off += out_dim;
            let dense_w = dense;
            let dense_b = dense + in_dim * out_dim;
            dense = dense_b + out_dim;
            layers.push(LayerLayout {
                in_dim,
                out_dim,
                w,
                g,
                b,
                skip: c.skip_layers.contains(&l),
                dense_w,
                dense_b,
            });
        }
        Ok(Self {
            config,
            layers,
            num_params: off,
            num_dense: dense,
        })
    }

    pub fn num_params(&self) -> usize {
        self.num_params
    }

    pub fn in_dim(&self) -> usize {
        self.config.in_dim
    }

    pub fn out_dim(&self) -> usize {
        self.config.out_dim
    }

    /// Multiply-adds per point of one forward pass (×2 for FLOPs; backward is about twice that).
    pub fn macs_per_point(&self) -> usize {
        self.layers.iter().map(|l| l.in_dim * l.out_dim).sum()
    }

    fn act(&self, l: usize) -> Activation {
        if l + 1 == self.layers.len() {
            self.config.output_activation
        } else {
            self.config.activation
        }
    }

    /// Check a parameter vector's length.
    pub fn check_params(&self, len: usize) -> Result<(), BackendError> {
        if len != self.num_params {
            return Err(BackendError::Shape(format!(
                "MLP expects {} parameters, got {len}",
                self.num_params
            )));
        }
        Ok(())
    }

    fn check_input(&self, len: usize) -> Result<usize, BackendError> {
        if len % self.config.in_dim != 0 {
            return Err(BackendError::Shape(format!(
                "MLP input of {len} values is not a multiple of in_dim {}",
                self.config.in_dim
            )));
        }
        Ok(len / self.config.in_dim)
    }

    /// Seeded initial parameters.
    pub fn init(&self, init: Init, seed: u64) -> Vec<f32> {
        let mut rng = crate::util::rng(seed);
        let mut p = vec![0f32; self.num_params];
        let n_layers = self.layers.len();
        for (l, lay) in self.layers.iter().enumerate() {
            let last = l + 1 == n_layers;
            let (mean, std) = match init {
                Init::Default => {
                    let gain = match self.act(l) {
                        Activation::Relu
                        | Activation::LeakyRelu(_)
                        | Activation::Softplus { .. } => SQRT2,
                        _ => 1.0,
                    };
                    (0.0, gain / (lay.in_dim as f64).sqrt())
                }
                Init::Geometric { .. } if last => (PI.sqrt() / (lay.in_dim as f64).sqrt(), 1e-4),
                Init::Geometric { .. } => (0.0, SQRT2 / (lay.out_dim as f64).sqrt()),
            };
            let normal = Normal::new(mean, std).expect("finite std");
            for o in 0..lay.out_dim {
                for i in 0..lay.in_dim {
                    let mut v = normal.sample(&mut rng) as f32;
                    if let Init::Geometric { raw_dims, .. } = init {
                        let d = self.config.in_dim;
                        // PE terms start silent: inputs raw_dims..d of layer 0, and the last
                        // d - raw_dims inputs (the re-injected PE terms) of a skip layer.
                        let pe_in_first = l == 0 && i >= raw_dims && !last;
                        let pe_in_skip = lay.skip && !last && i >= lay.in_dim - (d - raw_dims);
                        if pe_in_first || pe_in_skip {
                            v = 0.0;
                        }
                    }
                    p[lay.w + o * lay.in_dim + i] = v;
                }
            }
            if let Init::Geometric { radius, .. } = init {
                if last {
                    p[lay.b..lay.b + lay.out_dim].fill(-radius);
                }
            }
            if let Some(g) = lay.g {
                // PyTorch's weight_norm starts with g = ‖v‖, so W is unchanged.
                for o in 0..lay.out_dim {
                    let row = &p[lay.w + o * lay.in_dim..lay.w + (o + 1) * lay.in_dim];
                    let norm = row.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt();
                    p[g + o] = norm as f32;
                }
            }
        }
        p
    }
}

// ---- the scalar trait for the generic cpu twin ------------------------------------------------

/// f32 or f64: the cpu twin runs in f32 for speed and in f64 for finite-difference checks.
pub trait Real:
    Copy
    + Send
    + Sync
    + Debug
    + Default
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + Into<f64>
    + 'static
{
    fn from_f64(v: f64) -> Self;
    fn zero() -> Self {
        Self::from_f64(0.0)
    }
    fn one() -> Self {
        Self::from_f64(1.0)
    }
    /// `exp` (f32: a vectorisable polynomial with a clamped argument, see [`exp_f32`]).
    fn exp_(self) -> Self;
    /// `ln(1 + x)` for `x` in [0, 1], the range softplus uses (f32: a vectorisable series, see
    /// [`ln_1p_f32`]).
    fn ln_1p_(self) -> Self;
    fn abs_(self) -> Self;
    fn max_(self, o: Self) -> Self;
    fn sqrt_(self) -> Self;
    /// `C = beta·C + A·B` with `A` `[m,k]` at strides `(rsa, csa)`, `B` `[k,n]` at `(rsb, csb)`
    /// and `C` `[m,n]` row-major (row stride `n`).
    #[allow(clippy::too_many_arguments)]
    fn gemm(
        m: usize,
        k: usize,
        n: usize,
        a: &[Self],
        rsa: usize,
        csa: usize,
        b: &[Self],
        rsb: usize,
        csb: usize,
        beta: Self,
        c: &mut [Self],
    );
}

/// Check that a strided matrix lies inside its slice (the GEMMs below are `unsafe` calls).
fn strided_fits(len: usize, rows: usize, cols: usize, rs: usize, cs: usize) -> bool {
    rows == 0 || cols == 0 || (rows - 1) * rs + (cols - 1) * cs < len
}

/// Branch-free f32 `exp` (Cephes `expf` polynomial, ~1 ulp) that vectorises; the argument is
/// clamped to [-87.3, 88.3] so the result is always finite and normal. Its steps are fused
/// multiply-adds: one FMA instruction each where the CPU has them (the AVX2 slices), half the
/// latency of a product and a sum.
#[inline(always)]
fn exp_f32(x: f32) -> f32 {
    // max/min (not clamp) map NaN to a bound, so the conversions below never see NaN; the
    // NaN is put back at the end.
    let xc = x.max(-87.3).min(88.3);
    // floor(x·log2 e + ½) by truncation of a positive number (x ≥ −87.3): no libm call.
    let t = xc * std::f32::consts::LOG2_E + 0.5 + 128.0;
    // SAFETY: t is finite and in [1.5, 256], so it fits an i32. Integer steps wrap (they never
    // overflow here): a checked one would keep the loop from vectorising where overflow checks
    // are on (the test profile).
    let ni = unsafe { t.to_int_unchecked::<i32>() }.wrapping_sub(128);
    let n = ni as f32;
    let r = n.mul_add(2.121_944_4e-4, n.mul_add(-0.693_359_4, xc));
    let mut p = 1.987_569_1e-4f32;
    p = p.mul_add(r, 1.398_199_9e-3);
    p = p.mul_add(r, 8.333_452e-3);
    p = p.mul_add(r, 4.166_579_6e-2);
    p = p.mul_add(r, 1.666_666_5e-1);
    p = p.mul_add(r, 0.5);
    let e = (p * r).mul_add(r, r) + 1.0;
    let y = e * f32::from_bits((ni.wrapping_add(127) as u32) << 23);
    if x.is_nan() {
        x
    } else {
        y
    }
}

/// `ln(1 + e)` for `e` in [0, 1] (softplus's `e^{−|βz|}`): `2·atanh(s)` with `s = e/(2 + e)`
/// ≤ 1/3, whose odd series to `s¹³` is within 1.4e-8 relative (the next term, `s¹⁴/15`, is at
/// most 9⁻⁷/15). No cancellation at small `e`, one division, and no exponent bits to pick apart.
/// Below 1e-18, `ln(1 + e)` is `e` to f32 precision; the series then runs on 1e-18, so that no
/// lane computes with subnormals (see [`SOFTPLUS_FLOOR`]).
#[inline(always)]
fn ln_1p_f32(e: f32) -> f32 {
    const TINY: f32 = 1e-18;
    // A compare, not `max`, so that NaN goes on through.
    let s = if e < TINY { TINY } else { e } / (2.0 + e);
    let z = s * s;
    let mut p = 1.0f32 / 13.0;
    p = p.mul_add(z, 1.0 / 11.0);
    p = p.mul_add(z, 1.0 / 9.0);
    p = p.mul_add(z, 1.0 / 7.0);
    p = p.mul_add(z, 1.0 / 5.0);
    p = p.mul_add(z, 1.0 / 3.0);
    p = p.mul_add(z, 1.0);
    let l = 2.0 * s * p;
    if e < TINY {
        e
    } else {
        l
    }
}

trait StdMath {
    fn exp_std(self) -> Self;
    fn ln_1p_std(self) -> Self;
}
impl StdMath for f64 {
    fn exp_std(self) -> Self {
        self.exp()
    }
    fn ln_1p_std(self) -> Self {
        self.ln_1p()
    }
}
impl StdMath for f32 {
    fn exp_std(self) -> Self {
        exp_f32(self)
    }
    fn ln_1p_std(self) -> Self {
        ln_1p_f32(self)
    }
}

macro_rules! impl_real {
    ($t:ty) => {
        impl Real for $t {
            fn from_f64(v: f64) -> Self {
                v as $t
            }
            #[inline(always)]
            fn exp_(self) -> Self {
                self.exp_std()
            }
            #[inline(always)]
            fn ln_1p_(self) -> Self {
                self.ln_1p_std()
            }
            fn abs_(self) -> Self {
                self.abs()
            }
            fn max_(self, o: Self) -> Self {
                self.max(o)
            }
            fn sqrt_(self) -> Self {
                self.sqrt()
            }
            fn gemm(
                m: usize,
                k: usize,
                n: usize,
                a: &[Self],
                rsa: usize,
                csa: usize,
                b: &[Self],
                rsb: usize,
                csb: usize,
                beta: Self,
                c: &mut [Self],
            ) {
                assert!(
                    strided_fits(a.len(), m, k, rsa, csa),
                    "gemm: A out of bounds"
                );
                assert!(
                    strided_fits(b.len(), k, n, rsb, csb),
                    "gemm: B out of bounds"
                );
                assert!(c.len() >= m * n, "gemm: C out of bounds");
                if m == 0 || n == 0 {
                    return;
                }
                // SAFETY: the asserts above keep every strided access inside the slices; `c` is
                // exclusively borrowed and does not alias `a` or `b`. `gemm` computes
                // `dst = alpha·dst + beta·lhs·rhs` and reads `dst` only when told to.
                unsafe {
                    gemm::gemm(
                        m,
                        n,
                        k,
                        c.as_mut_ptr(),
                        1,
                        n as isize,
                        beta != 0.0,
                        a.as_ptr(),
                        csa as isize,
                        rsa as isize,
                        b.as_ptr(),
                        csb as isize,
                        rsb as isize,
                        beta,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    )
                }
            }
        }
    };
}
impl_real!(f32);
impl_real!(f64);

// ---- cpu twin --------------------------------------------------------------------------------

/// Rows per rayon task for large inputs: the whole network runs on one chunk at a time (its
/// activations stay in cache), big enough that the GEMMs reach their packed-kernel speed.
pub const CPU_CHUNK_ROWS: usize = 1024;

/// Fewest rows a chunk is cut to (a multiple of the GEMM kernels' row tiles).
const CPU_MIN_CHUNK_ROWS: usize = 64;

/// Rows per chunk for an input of `n` rows: [`CPU_CHUNK_ROWS`] from `4 · CPU_CHUNK_ROWS` rows on;
/// below that the input is cut into four chunks (rounded up to [`CPU_MIN_CHUNK_ROWS`]) so that a
/// small batch (stage 2's 1024 points, its indirect slots) still spreads over the cores instead of
/// running the whole network on one thread. A function of `n` alone, never of the thread count,
/// so a seeded run adds its gradients in the same order on any machine.
pub fn cpu_chunk_rows(n: usize) -> usize {
    n.div_ceil(4).next_multiple_of(CPU_MIN_CHUNK_ROWS).clamp(CPU_MIN_CHUNK_ROWS, CPU_CHUNK_ROWS)
}

/// What the cpu forward keeps for the backward, per row chunk.
#[derive(Clone, Debug, Default)]
pub struct CpuChunk<T> {
    rows: usize,
    /// Per layer: input `u_l` `[rows, in_l]` and pre-activation `z_l` `[rows, out_l]`.
    u: Vec<Vec<T>>,
    z: Vec<Vec<T>>,
}

/// The cpu forward's saved state (the effective weights and every layer's input/pre-activation).
#[derive(Clone, Debug, Default)]
pub struct CpuCache<T> {
    /// Dense `[W, b]` per layer (weight norm applied).
    dense: Vec<T>,
    /// Rows of every chunk but the last ([`cpu_chunk_rows`] of the input's rows).
    chunk_rows: usize,
    chunks: Vec<CpuChunk<T>>,
}

/// Dense `[W, b]` per layer from the parameter vector (applies weight norm).
fn dense_params<T: Real>(mlp: &Mlp, p: &[T]) -> Vec<T> {
    let mut d = vec![T::zero(); mlp.num_dense];
    for lay in &mlp.layers {
        let wsz = lay.in_dim * lay.out_dim;
        match lay.g {
            None => d[lay.dense_w..lay.dense_w + wsz].copy_from_slice(&p[lay.w..lay.w + wsz]),
            Some(g) => {
                for o in 0..lay.out_dim {
                    let v = &p[lay.w + o * lay.in_dim..lay.w + (o + 1) * lay.in_dim];
                    let norm = v.iter().fold(T::zero(), |s, &x| s + x * x).sqrt_();
                    let s = p[g + o] / norm;
                    for (i, &x) in v.iter().enumerate() {
                        d[lay.dense_w + o * lay.in_dim + i] = s * x;
                    }
                }
            }
        }
        d[lay.dense_b..lay.dense_b + lay.out_dim].copy_from_slice(&p[lay.b..lay.b + lay.out_dim]);
    }
    d
}

fn forward_chunk<T: Real>(mlp: &Mlp, dense: &[T], x: &[T], keep: bool) -> (Vec<T>, CpuChunk<T>) {
    let d = mlp.config.in_dim;
    let rows = x.len() / d;
    let s = T::from_f64(1.0 / SQRT2);
    let mut chunk = CpuChunk {
        rows,
        u: Vec::new(),
        z: Vec::new(),
    };
    let mut h: Vec<T> = x.to_vec();
    for (l, lay) in mlp.layers.iter().enumerate() {
        let u = if lay.skip {
            let a = lay.in_dim - d;
            let mut u = vec![T::zero(); rows * lay.in_dim];
            for r in 0..rows {
                let dst = &mut u[r * lay.in_dim..(r + 1) * lay.in_dim];
                for (o, &v) in dst[..a].iter_mut().zip(&h[r * a..(r + 1) * a]) {
                    *o = v * s;
                }
                for (o, &v) in dst[a..].iter_mut().zip(&x[r * d..(r + 1) * d]) {
                    *o = v * s;
                }
            }
            u
        } else {
            h
        };
        let (m, k, n) = (rows, lay.in_dim, lay.out_dim);
        // Each row starts as the bias (written once: no zeroing first).
        let bias = &dense[lay.dense_b..lay.dense_b + n];
        let mut z = Vec::with_capacity(m * n);
        for _ in 0..m {
            z.extend_from_slice(bias);
        }
        // z = u·Wᵀ + b: B(k, j) = W[j][k].
        T::gemm(
            m,
            k,
            n,
            &u,
            k,
            1,
            &dense[lay.dense_w..lay.dense_w + k * n],
            1,
            k,
            T::one(),
            &mut z,
        );
        let act = mlp.act(l);
        let hn: Vec<T> = act.forward_slice(&z);
        if keep {
            chunk.u.push(u);
            chunk.z.push(z);
        }
        h = hn;
    }
    (h, chunk)
}

/// cpu forward: `x` `[n, in_dim]` → output `[n, out_dim]`, plus the cache for [`cpu_backward`]
/// when `keep` is set.
pub fn cpu_forward<T: Real>(
    mlp: &Mlp,
    params: &[T],
    x: &[T],
    keep: bool,
) -> Result<(Vec<T>, CpuCache<T>), BackendError> {
    mlp.check_params(params.len())?;
    mlp.check_input(x.len())?;
    let dense = dense_params(mlp, params);
    let d = mlp.config.in_dim;
    let chunk_rows = cpu_chunk_rows(x.len() / d.max(1));
    let parts: Vec<(Vec<T>, CpuChunk<T>)> = x
        .par_chunks(chunk_rows * d)
        .map(|xc| forward_chunk(mlp, &dense, xc, keep))
        .collect();
    let mut out = Vec::with_capacity(x.len() / d * mlp.config.out_dim);
    let mut chunks = Vec::with_capacity(parts.len());
    for (o, c) in parts {
        out.extend_from_slice(&o);
        chunks.push(c);
    }
    Ok((out, CpuCache { dense, chunk_rows, chunks }))
}

/// Backward of one chunk: accumulates dense parameter gradients into `dd`, writes `dx`.
fn backward_chunk<T: Real>(
    mlp: &Mlp,
    dense: &[T],
    c: &CpuChunk<T>,
    dy: &[T],
    dx: &mut [T],
    dd: &mut [T],
) {
    let rows = c.rows;
    let d = mlp.config.in_dim;
    let s = T::from_f64(1.0 / SQRT2);
    dx.fill(T::zero());
    let n_layers = mlp.layers.len();
    // dz of the last layer.
    let act = mlp.act(n_layers - 1);
    let mut dz: Vec<T> = act.backward_slice(&c.z[n_layers - 1], dy);
    for l in (0..n_layers).rev() {
        let lay = &mlp.layers[l];
        let (k, n) = (lay.in_dim, lay.out_dim);
        let u = &c.u[l];
        // dW += dzᵀ·u: A(i, r) = dz[r][i] → rsa 1, csa n.
        T::gemm(
            n,
            rows,
            k,
            &dz,
            1,
            n,
            u,
            k,
            1,
            T::one(),
            &mut dd[lay.dense_w..lay.dense_w + n * k],
        );
        let db = &mut dd[lay.dense_b..lay.dense_b + n];
        for row in dz.chunks_exact(n) {
            for (a, &g) in db.iter_mut().zip(row) {
                *a += g;
            }
        }
        // du = dz·W.
        let mut du = vec![T::zero(); rows * k];
        T::gemm(
            rows,
            n,
            k,
            &dz,
            n,
            1,
            &dense[lay.dense_w..lay.dense_w + n * k],
            k,
            1,
            T::zero(),
            &mut du,
        );
        if l == 0 {
            for (a, &g) in dx.iter_mut().zip(&du) {
                *a += g;
            }
            break;
        }
        let dh: Vec<T> = if lay.skip {
            let a = k - d;
            let mut dh = vec![T::zero(); rows * a];
            for r in 0..rows {
                let src = &du[r * k..(r + 1) * k];
                for (o, &g) in dh[r * a..(r + 1) * a].iter_mut().zip(&src[..a]) {
                    *o = g * s;
                }
                for (o, &g) in dx[r * d..(r + 1) * d].iter_mut().zip(&src[a..]) {
                    *o += g * s;
                }
            }
            dh
        } else {
            du
        };
        let act = mlp.act(l - 1);
        dz = act.backward_slice(&c.z[l - 1], &dh);
    }
}

/// Map dense `[W, b]` gradients to the parameter layout (weight-norm backward).
fn dense_to_param_grads<T: Real>(mlp: &Mlp, params: &[T], dd: &[T]) -> Vec<T> {
    let mut gp = vec![T::zero(); mlp.num_params];
    for lay in &mlp.layers {
        let wsz = lay.in_dim * lay.out_dim;
        match lay.g {
            None => gp[lay.w..lay.w + wsz].copy_from_slice(&dd[lay.dense_w..lay.dense_w + wsz]),
            Some(g) => {
                // W = g v/‖v‖: dL/dg = dW·v/‖v‖, dL/dv = g/‖v‖ (dW − v (v·dW)/‖v‖²).
                for o in 0..lay.out_dim {
                    let v = &params[lay.w + o * lay.in_dim..lay.w + (o + 1) * lay.in_dim];
                    let dw = &dd[lay.dense_w + o * lay.in_dim..lay.dense_w + (o + 1) * lay.in_dim];
                    let n2 = v.iter().fold(T::zero(), |s, &x| s + x * x);
                    let norm = n2.sqrt_();
                    let vdw = v.iter().zip(dw).fold(T::zero(), |s, (&a, &b)| s + a * b);
                    gp[g + o] = vdw / norm;
                    let gn = params[g + o] / norm;
                    for i in 0..lay.in_dim {
                        gp[lay.w + o * lay.in_dim + i] = gn * (dw[i] - v[i] * vdw / n2);
                    }
                }
            }
        }
        gp[lay.b..lay.b + lay.out_dim].copy_from_slice(&dd[lay.dense_b..lay.dense_b + lay.out_dim]);
    }
    gp
}

/// cpu backward: given `dL/dy` `[n, out_dim]`, returns `(dL/dparams, dL/dx)`.
pub fn cpu_backward<T: Real>(
    mlp: &Mlp,
    params: &[T],
    cache: &CpuCache<T>,
    dy: &[T],
) -> Result<(Vec<T>, Vec<T>), BackendError> {
    mlp.check_params(params.len())?;
    let n: usize = cache.chunks.iter().map(|c| c.rows).sum();
    if cache.chunks.iter().any(|c| c.u.len() != mlp.layers.len()) {
        return Err(BackendError::Shape(
            "MLP backward needs a forward run with keep = true".into(),
        ));
    }
    if dy.len() != n * mlp.config.out_dim {
        return Err(BackendError::Shape(format!(
            "MLP backward: dL/dy has {} values, expected {n} x {}",
            dy.len(),
            mlp.config.out_dim
        )));
    }
    let (d, o) = (mlp.config.in_dim, mlp.config.out_dim);
    let mut dx = vec![T::zero(); n * d];
    // The parameter gradient is summed over row chunks in fixed groups, merged in order, so that
    // its rounding (and a seeded run) repeats on any thread count: rayon's fold splits where
    // threads steal. At most MAX_PARTIALS group sums are alive at once, fewer for big networks.
    const MAX_PARTIALS: usize = 64;
    const PARTIAL_BYTES: usize = 64 << 20;
    let partials = (PARTIAL_BYTES / (mlp.num_dense * std::mem::size_of::<T>()).max(1)).clamp(1, MAX_PARTIALS);
    let per = cache.chunks.len().div_ceil(partials).max(1);
    let rows = cache.chunk_rows.max(1);
    let sums: Vec<Vec<T>> = cache
        .chunks
        .par_chunks(per)
        .zip(dx.par_chunks_mut(per * rows * d))
        .zip(dy.par_chunks(per * rows * o))
        .map(|((cs, dxg), dyg)| {
            let mut dd = vec![T::zero(); mlp.num_dense];
            let parts = dxg.chunks_mut(rows * d).zip(dyg.chunks(rows * o));
            for (c, (dxc, dyc)) in cs.iter().zip(parts) {
                backward_chunk(mlp, &cache.dense, c, dyc, dxc, &mut dd);
            }
            dd
        })
        .collect();
    let mut sums = sums.into_iter();
    let mut dd = sums.next().unwrap_or_else(|| vec![T::zero(); mlp.num_dense]);
    for b in sums {
        for (x, y) in dd.iter_mut().zip(&b) {
            *x += *y;
        }
    }
    Ok((dense_to_param_grads(mlp, params, &dd), dx))
}

// ---- wgpu ------------------------------------------------------------------------------------

/// Mirrors `GemmParams` in `shaders/mlp.wgsl`: `C[c_off + i·ldc + j] = (acc ? C : 0) +
/// Σ_k A[a_off + i·rsa + k·csa]·B[b_off + k·rsb + j·csb] (+ bias[bias_off + j])`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GemmParams {
    pub m: u32,
    pub n: u32,
    pub k: u32,
    pub a_off: u32,
    pub rsa: u32,
    pub csa: u32,
    pub b_off: u32,
    pub rsb: u32,
    pub csb: u32,
    pub c_off: u32,
    pub ldc: u32,
    pub bias_off: u32,
    /// bit 0: add bias; bit 1: accumulate into C.
    pub flags: u32,
    /// Split-K: when > 0, workgroup z handles `k` range `[z·k_split, (z+1)·k_split)` and writes
    /// its partial product at `c_off + z·m·ldc` (summed afterwards by `split_reduce`).
    pub k_split: u32,
    pub _pad: [u32; 2],
}
const _: () = assert!(std::mem::size_of::<GemmParams>() == 64);

/// Mirrors `EltParams` in `shaders/mlp.wgsl` (activation, skip, split-K reduction and weight-norm
/// kernels; each uses the fields its comment names).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub struct EltParams {
    pub n: u32,
    pub kind: u32,
    pub p: f32,
    pub scale: f32,
    pub rows: u32,
    pub cols: u32,
    pub a: u32,
    pub d: u32,
    pub off0: u32,
    pub off1: u32,
    pub off2: u32,
    pub _pad: u32,
}
const _: () = assert!(std::mem::size_of::<EltParams>() == 48);

/// GEMM output tile (rows and columns per workgroup) in `shaders/mlp.wgsl`.
const GEMM_TILE: usize = 64;
/// Split-K: at least this many K per split, at most [`MAX_SPLITS`] splits.
const SPLIT_K_MIN: usize = 1024;
const MAX_SPLITS: usize = 64;

fn spec(n_storage_read: usize, n_rw: usize) -> KernelSpec {
    let mut v = vec![Access::Read; n_storage_read];
    v.extend(std::iter::repeat_n(Access::ReadWrite, n_rw));
    KernelSpec::new(true, &v)
}

struct GpuMlp<'a> {
    ctx: &'a GpuContext,
    src: &'static str,
}

impl<'a> GpuMlp<'a> {
    fn new(ctx: &'a GpuContext) -> Self {
        Self {
            ctx,
            src: shaders::with_lib(MLP_WGSL),
        }
    }

    fn kernel(
        &self,
        entry: &str,
        reads: usize,
        rws: usize,
    ) -> Result<std::sync::Arc<crate::backend::gpu::Kernel>, BackendError> {
        self.ctx.kernel("mlp", self.src, entry, &spec(reads, rws))
    }

    #[allow(clippy::too_many_arguments)]
    fn gemm(
        &self,
        b: &mut crate::backend::gpu::Batch<'_>,
        p: GemmParams,
        a: &GpuBuffer,
        bm: &GpuBuffer,
        bias: &GpuBuffer,
        c: &GpuBuffer,
    ) -> Result<(), BackendError> {
        let k = self.kernel("gemm", 3, 1)?;
        let tiles_n = (p.n as usize).div_ceil(GEMM_TILE);
        let tiles_m = (p.m as usize).div_ceil(GEMM_TILE);
        // A long reduction (dW = dZᵀ·U over the batch) on few output tiles: split K over
        // workgroups (z) into partial products, then sum them.
        let splits = (p.k as usize / SPLIT_K_MIN)
            .min(MAX_SPLITS)
            .min(256 / (tiles_n * tiles_m).max(1));
        if splits >= 2 && p.ldc == p.n && p.flags & 1 == 0 && p.k_split == 0 {
            let k_split = (p.k as usize).div_ceil(splits).div_ceil(16) * 16;
            let splits = (p.k as usize).div_ceil(k_split);
            let mn = p.m as usize * p.n as usize;
            let partial = self.ctx.zeros_f32("mlp split-k partials", splits * mn);
            let sp = GemmParams {
                c_off: 0,
                flags: 0,
                k_split: k_split as u32,
                ..p
            };
            b.dispatch(
                &k,
                Some(bytemuck::bytes_of(&sp)),
                &[a.into(), bm.into(), bias.into(), (&partial).into()],
                [tiles_n as u32, tiles_m as u32, splits as u32],
            )?;
            let ep = EltParams {
                n: u32_of(mn, "GEMM output")?,
                rows: splits as u32,
                off0: p.c_off,
                kind: (p.flags & 2 != 0) as u32,
                ..Default::default()
            };
            return self.elt(b, "split_reduce", ep, &[&partial], &[c], mn);
        }
        b.dispatch(
            &k,
            Some(bytemuck::bytes_of(&p)),
            &[a.into(), bm.into(), bias.into(), c.into()],
            [tiles_n as u32, tiles_m as u32, 1],
        )
    }

    fn elt(
        &self,
        b: &mut crate::backend::gpu::Batch<'_>,
        entry: &str,
        p: EltParams,
        reads: &[&GpuBuffer],
        rws: &[&GpuBuffer],
        threads: usize,
    ) -> Result<(), BackendError> {
        let k = self.kernel(entry, reads.len(), rws.len())?;
        let binds: Vec<Bind<'_>> = reads.iter().chain(rws).map(|&x| x.into()).collect();
        b.dispatch(
            &k,
            Some(bytemuck::bytes_of(&p)),
            &binds,
            groups_1d(threads, 256),
        )
    }
}

/// What the wgpu forward keeps for the backward.
#[derive(Debug)]
pub struct GpuCache {
    /// Dense weights (weight-norm applied) `[W]` per layer at `dense_w` offsets; `None` without
    /// weight norm (the GEMMs read `W` from the parameters).
    weights: Option<GpuBuffer>,
    u: Vec<GpuBuffer>,
    z: Vec<GpuBuffer>,
    rows: usize,
}

/// The forward's saved state on either backend.
#[derive(Debug)]
pub enum MlpCache {
    Cpu(CpuCache<f32>),
    Gpu(GpuCache),
    /// Forward run without `keep`.
    None,
}

/// Forward result: the output `[n, out_dim]` and what backward needs.
#[derive(Debug)]
pub struct MlpForward {
    pub output: Tensor,
    pub rows: usize,
    pub cache: MlpCache,
}

/// Backward result.
#[derive(Debug)]
pub struct MlpGrads {
    /// `dL/dparams`, in the parameter layout.
    pub d_params: Tensor,
    /// `dL/dx` `[n, in_dim]`.
    pub d_input: Tensor,
}

fn u32_of(v: usize, what: &str) -> Result<u32, BackendError> {
    u32::try_from(v)
        .map_err(|_| BackendError::Shape(format!("{what} ({v}) exceeds the GPU's u32 indexing")))
}

fn gpu_forward(
    ctx: &GpuContext,
    mlp: &Mlp,
    params: &GpuBuffer,
    x: &GpuBuffer,
    keep: bool,
) -> Result<MlpForward, BackendError> {
    mlp.check_params(params.len)?;
    let rows = mlp.check_input(x.len)?;
    let g = GpuMlp::new(ctx);
    let mut batch = ctx.batch("mlp_forward");
    let weights = if mlp.config.weight_norm {
        let w = ctx.zeros_f32("mlp weights", mlp.num_dense);
        for lay in &mlp.layers {
            let p = EltParams {
                rows: lay.out_dim as u32,
                cols: lay.in_dim as u32,
                off0: lay.w as u32,
                off1: lay.g.unwrap_or(0) as u32,
                off2: lay.dense_w as u32,
                ..Default::default()
            };
            g.elt(&mut batch, "wn_fwd", p, &[params], &[&w], lay.out_dim)?;
        }
        Some(w)
    } else {
        None
    };
    let d = mlp.config.in_dim;
    let s = (1.0 / SQRT2) as f32;
    let (mut us, mut zs) = (Vec::new(), Vec::new());
    let mut h_prev: Option<GpuBuffer> = None;
    for (l, lay) in mlp.layers.iter().enumerate() {
        let (k, n) = (lay.in_dim, lay.out_dim);
        u32_of(rows * k.max(n), "MLP activation size")?;
        let u: GpuBuffer = if lay.skip {
            let u = ctx.zeros_f32("mlp u", rows * k);
            let h = h_prev.as_ref().expect("a skip layer is never layer 0");
            let p = EltParams {
                n: (rows * k) as u32,
                rows: rows as u32,
                a: (k - d) as u32,
                d: d as u32,
                scale: s,
                ..Default::default()
            };
            g.elt(&mut batch, "concat_fwd", p, &[h, x], &[&u], rows * k)?;
            u
        } else if l == 0 {
            // Layer 0 reads x directly; keep a copy so the cache owns its buffers.
            let u = ctx.zeros_f32("mlp u", rows * k);
            batch.copy(x, &u)?;
            u
        } else {
            h_prev.take().expect("previous activation")
        };
        let z = ctx.zeros_f32("mlp z", rows * n);
        let (wbuf, w_off) = match &weights {
            Some(w) => (w, lay.dense_w),
            None => (params, lay.w),
        };
        let gp = GemmParams {
            m: rows as u32,
            n: n as u32,
            k: k as u32,
            a_off: 0,
            rsa: k as u32,
            csa: 1,
            b_off: w_off as u32,
            rsb: 1,
            csb: k as u32,
            c_off: 0,
            ldc: n as u32,
            bias_off: lay.b as u32,
            flags: 1,
            k_split: 0,
            _pad: [0; 2],
        };
        g.gemm(&mut batch, gp, &u, wbuf, params, &z)?;
        let h = ctx.zeros_f32("mlp h", rows * n);
        let (kind, pp) = mlp.act(l).code();
        let ep = EltParams {
            n: (rows * n) as u32,
            kind,
            p: pp,
            ..Default::default()
        };
        g.elt(&mut batch, "act_fwd", ep, &[&z], &[&h], rows * n)?;
        if keep {
            us.push(u);
            zs.push(z);
        }
        h_prev = Some(h);
    }
    batch.submit()?;
    let output = Tensor::Device(h_prev.expect("at least one layer"));
    let cache = if keep {
        MlpCache::Gpu(GpuCache {
            weights,
            u: us,
            z: zs,
            rows,
        })
    } else {
        MlpCache::None
    };
    Ok(MlpForward {
        output,
        rows,
        cache,
    })
}

fn gpu_backward(
    ctx: &GpuContext,
    mlp: &Mlp,
    params: &GpuBuffer,
    c: &GpuCache,
    dy: &GpuBuffer,
) -> Result<MlpGrads, BackendError> {
    mlp.check_params(params.len)?;
    let rows = c.rows;
    if dy.len != rows * mlp.config.out_dim {
        return Err(BackendError::Shape(format!(
            "MLP backward: dL/dy has {} values, expected {rows} x {}",
            dy.len, mlp.config.out_dim
        )));
    }
    let g = GpuMlp::new(ctx);
    let d = mlp.config.in_dim;
    let s = (1.0 / SQRT2) as f32;
    let grads = ctx.zeros_f32("mlp grads", mlp.num_params);
    let dense_grads = c
        .weights
        .as_ref()
        .map(|_| ctx.zeros_f32("mlp dense grads", mlp.num_dense));
    let dx = ctx.zeros_f32("mlp dx", rows * d);
    let ones = ctx.upload_f32("mlp ones", &vec![1.0f32; rows]);
    let mut batch = ctx.batch("mlp_backward");
    let n_layers = mlp.layers.len();
    let mut dh: GpuBuffer = {
        // Borrow dy through a copy so every dh buffer is owned the same way.
        let b = ctx.zeros_f32("mlp dy", dy.len);
        batch.copy(dy, &b)?;
        b
    };
    let mut dx_written = false;
    for l in (0..n_layers).rev() {
        let lay = &mlp.layers[l];
        let (k, n) = (lay.in_dim, lay.out_dim);
        let dz = ctx.zeros_f32("mlp dz", rows * n);
        let (kind, pp) = mlp.act(l).code();
        let ep = EltParams {
            n: (rows * n) as u32,
            kind,
            p: pp,
            ..Default::default()
        };
        g.elt(&mut batch, "act_bwd", ep, &[&c.z[l], &dh], &[&dz], rows * n)?;
        // dW = dzᵀ·u into the weight gradient (dense buffer with weight norm).
        let (gw, gw_off) = match &dense_grads {
            Some(dg) => (dg, lay.dense_w),
            None => (&grads, lay.w),
        };
        let p = GemmParams {
            m: n as u32,
            n: k as u32,
            k: rows as u32,
            a_off: 0,
            rsa: 1,
            csa: n as u32,
            b_off: 0,
            rsb: k as u32,
            csb: 1,
            c_off: gw_off as u32,
            ldc: k as u32,
            bias_off: 0,
            flags: 0,
            k_split: 0,
            _pad: [0; 2],
        };
        g.gemm(&mut batch, p, &dz, &c.u[l], &dz, gw)?;
        // db = dzᵀ·1 as a GEMM, so the reduction over the batch is split over K like dW.
        let p = GemmParams {
            m: n as u32,
            n: 1,
            k: rows as u32,
            a_off: 0,
            rsa: 1,
            csa: n as u32,
            b_off: 0,
            rsb: 1,
            csb: 1,
            c_off: lay.b as u32,
            ldc: 1,
            bias_off: 0,
            flags: 0,
            k_split: 0,
            _pad: [0; 2],
        };
        g.gemm(&mut batch, p, &dz, &ones, &dz, &grads)?;
        // du = dz·W.
        let (wbuf, w_off) = match &c.weights {
            Some(w) => (w, lay.dense_w),
            None => (params, lay.w),
        };
        let target = if l == 0 {
            None
        } else {
            Some(ctx.zeros_f32("mlp du", rows * k))
        };
        let p = GemmParams {
            m: rows as u32,
            n: k as u32,
            k: n as u32,
            a_off: 0,
            rsa: n as u32,
            csa: 1,
            b_off: w_off as u32,
            rsb: k as u32,
            csb: 1,
            c_off: 0,
            ldc: k as u32,
            bias_off: 0,
            flags: if l == 0 && dx_written { 2 } else { 0 },
            k_split: 0,
            _pad: [0; 2],
        };
        match &target {
            None => {
                g.gemm(&mut batch, p, &dz, wbuf, &dz, &dx)?;
                break;
            }
            Some(du) => g.gemm(&mut batch, p, &dz, wbuf, &dz, du)?,
        }
        let du = target.expect("l > 0");
        dh = if lay.skip {
            let a = k - d;
            let nh = ctx.zeros_f32("mlp dh", rows * a);
            let ep = EltParams {
                n: (rows * k) as u32,
                rows: rows as u32,
                a: a as u32,
                d: d as u32,
                scale: s,
                kind: dx_written as u32,
                ..Default::default()
            };
            g.elt(&mut batch, "concat_bwd", ep, &[&du], &[&nh, &dx], rows * k)?;
            dx_written = true;
            nh
        } else {
            du
        };
    }
    if let Some(dg) = &dense_grads {
        for lay in &mlp.layers {
            let p = EltParams {
                rows: lay.out_dim as u32,
                cols: lay.in_dim as u32,
                off0: lay.w as u32,
                off1: lay.g.unwrap_or(0) as u32,
                off2: lay.dense_w as u32,
                ..Default::default()
            };
            g.elt(
                &mut batch,
                "wn_bwd",
                p,
                &[params, dg],
                &[&grads],
                lay.out_dim,
            )?;
        }
    }
    batch.submit()?;
    Ok(MlpGrads {
        d_params: Tensor::Device(grads),
        d_input: Tensor::Device(dx),
    })
}

impl Backend {
    /// MLP forward on `x` `[n, in_dim]`. With `keep`, the result holds what
    /// [`Backend::mlp_backward`] needs: every layer's input and pre-activation, i.e. about
    /// `2·Σ widths` floats per point (8×512: ~33 KB per point), so callers feed large batches in
    /// sub-batches (`bench nn` uses 8192 points on the cpu).
    pub fn mlp_forward(
        &self,
        mlp: &Mlp,
        params: &Tensor,
        x: &Tensor,
        keep: bool,
    ) -> Result<MlpForward, BackendError> {
        match self {
            Backend::Cpu(_) => {
                let (out, cache) = cpu_forward(mlp, params.host()?, x.host()?, keep)?;
                let rows = x.len() / mlp.config.in_dim;
                Ok(MlpForward {
                    output: Tensor::Host(out),
                    rows,
                    cache: if keep {
                        MlpCache::Cpu(cache)
                    } else {
                        MlpCache::None
                    },
                })
            }
            Backend::Gpu(g) => gpu_forward(g, mlp, params.device()?, x.device()?, keep),
        }
    }

    /// MLP backward: `dL/dy` `[n, out_dim]` → parameter and input gradients.
    pub fn mlp_backward(
        &self,
        mlp: &Mlp,
        params: &Tensor,
        fwd: &MlpForward,
        d_out: &Tensor,
    ) -> Result<MlpGrads, BackendError> {
        match (self, &fwd.cache) {
            (Backend::Cpu(_), MlpCache::Cpu(c)) => {
                let (dp, dx) = cpu_backward(mlp, params.host()?, c, d_out.host()?)?;
                Ok(MlpGrads {
                    d_params: Tensor::Host(dp),
                    d_input: Tensor::Host(dx),
                })
            }
            (Backend::Gpu(g), MlpCache::Gpu(c)) => {
                gpu_backward(g, mlp, params.device()?, c, d_out.device()?)
            }
            (_, MlpCache::None) => Err(BackendError::Shape(
                "MLP backward needs a forward run with keep = true".into(),
            )),
            _ => Err(BackendError::Shape(
                "MLP backward on a different backend than its forward".into(),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg() -> MlpConfig {
        MlpConfig {
            in_dim: 3,
            widths: vec![8, 8, 8],
            out_dim: 2,
            activation: Activation::Softplus { beta: 10.0 },
            output_activation: Activation::None,
            skip_layers: vec![2],
            weight_norm: true,
        }
    }

    /// `Real::gemm`'s contract, on both element types, against a plain triple loop: `A` and `B`
    /// row-major or transposed (the strides the MLP passes), `beta = 0` never reading `C` (NaN
    /// there stays out), `beta = 1` adding to it; shapes from one row to past a kernel's tiles,
    /// and `k` long enough (1000) that the library splits the sum into blocks.
    fn gemm_contract<T: Real + Into<f64>>(tol: f64) {
        let mut r = crate::util::rng(7);
        for &(m, k, n) in &[(1, 1, 1), (3, 5, 2), (17, 35, 64), (64, 64, 16), (70, 1000, 9), (1024, 64, 3)] {
            for (at, bt) in [(false, false), (false, true), (true, false), (true, true)] {
                let a: Vec<T> = (0..m * k).map(|_| T::from_f64(rand::Rng::random_range(&mut r, -1.0..1.0))).collect();
                let b: Vec<T> = (0..k * n).map(|_| T::from_f64(rand::Rng::random_range(&mut r, -1.0..1.0))).collect();
                let (rsa, csa) = if at { (1, m) } else { (k, 1) };
                let (rsb, csb) = if bt { (1, k) } else { (n, 1) };
                let c0: Vec<T> = (0..m * n).map(|i| T::from_f64(i as f64 * 0.25 - 3.0)).collect();
                for beta in [0.0, 1.0] {
                    let mut c = if beta == 0.0 { vec![T::from_f64(f64::NAN); m * n] } else { c0.clone() };
                    T::gemm(m, k, n, &a, rsa, csa, &b, rsb, csb, T::from_f64(beta), &mut c);
                    for i in 0..m {
                        for j in 0..n {
                            let mut want: f64 = if beta == 0.0 { 0.0 } else { c0[i * n + j].into() };
                            for l in 0..k {
                                let (x, y): (f64, f64) = (a[i * rsa + l * csa].into(), b[l * rsb + j * csb].into());
                                want += x * y;
                            }
                            let got: f64 = c[i * n + j].into();
                            assert!((got - want).abs() <= tol * (1.0 + want.abs()), "{m}x{k}x{n} at {at} bt {bt} beta {beta}: C[{i}][{j}] {got} vs {want}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn gemm_meets_its_contract_on_f32_and_f64() {
        gemm_contract::<f32>(1e-4);
        gemm_contract::<f64>(1e-12);
    }

    #[test]
    fn fast_f32_exp_and_ln_1p_match_std() {
        let mut worst = (0f64, 0f64);
        for i in 0..200_001 {
            let x = -87.0 + 175.0 * i as f32 / 200_000.0;
            let rel = ((exp_f32(x) as f64 - (x as f64).exp()) / (x as f64).exp()).abs();
            worst.0 = worst.0.max(rel);
            let e = (i as f32 / 200_000.0).powi(3) * 1.0;
            let want = (e as f64).ln_1p();
            let err = (ln_1p_f32(e) as f64 - want).abs() / want.max(1e-30);
            worst.1 = worst.1.max(if e == 0.0 {
                ln_1p_f32(e).abs() as f64
            } else {
                err
            });
        }
        assert!(
            worst.0 < 4e-7 && worst.1 < 4e-7,
            "worst relative errors exp {:e}, ln_1p {:e}",
            worst.0,
            worst.1
        );
        assert!(exp_f32(1e30).is_finite() && exp_f32(-1e30) >= 0.0);
        assert!(exp_f32(f32::INFINITY).is_finite());
        assert!(exp_f32(f32::NAN).is_nan(), "NaN must propagate");
    }

    #[test]
    fn softplus_never_computes_with_subnormals_and_keeps_nan() {
        // Subnormal intermediates cost a microcode assist per operation: the paper network's
        // forward ran at 7 GFLOP/s on random inputs, 73 without them. Every output and
        // derivative is normal or 0, from the pre-activations a network meets to ±1e30.
        let mut z: Vec<f32> = (0..20_001).map(|i| (i as f32 - 10_000.0) * 1e-3).collect();
        z.extend([-1e30, -1e5, -0.8, -0.80001, 1e5, 1e30, f32::MIN_POSITIVE, -f32::MIN_POSITIVE, 0.0, -0.0]);
        for beta in [1.0f32, 10.0, 100.0, 1000.0] {
            let act = Activation::Softplus { beta };
            let y = act.forward_slice(&z);
            let d = act.backward_slice(&z, &vec![1.0; z.len()]);
            for ((&v, &a), &g) in z.iter().zip(&y).zip(&d) {
                assert!(a.is_finite() && a >= 0.0 && !a.is_subnormal(), "softplus({v}) = {a:e} at beta {beta}");
                assert!((0.0..=1.0).contains(&g) && !g.is_subnormal(), "softplus'({v}) = {g:e} at beta {beta}");
                assert_eq!(a, act.forward(v), "slice and scalar forward differ at {v}");
                assert_eq!(g, act.derivative(v), "slice and scalar derivative differ at {v}");
                // Against f64 where the value is not flushed: f32's softplus is within 1e-6.
                let yb = beta as f64 * v as f64;
                let want = (yb.max(0.0) + (-yb.abs()).exp().ln_1p()) / beta as f64;
                // (β·z in f32 can round across either cut. Its rounding alone moves e^{βz} by
                // up to |βz|·2⁻²⁴ relative, hence the tolerance's second term.)
                if yb > -79.99 && yb < 19.99 {
                    let tol = 6e-7 + yb.abs() * 1.2e-7;
                    assert!(((a as f64 - want) / want).abs() < tol, "softplus({v}) = {a:e}, want {want:e} at beta {beta}");
                } else if yb < -80.01 {
                    assert_eq!(a, 0.0, "softplus({v}) at beta {beta}");
                }
            }
        }
        let act = Activation::Softplus { beta: 100.0 };
        assert!(act.forward_slice(&[f32::NAN])[0].is_nan(), "NaN must reach the step's check");
        assert!(act.forward(f32::NAN).is_nan());
        assert!(act.backward_slice(&[f32::NAN], &[1.0])[0].is_nan());
    }

    #[test]
    fn every_simd_level_gives_the_scalar_bits() {
        // The AVX2 and AVX-512 builds of the activation loops against the baseline build, on
        // the values a network meets, the cuts of softplus (βz = 20, −80) and the specials.
        let mut z: Vec<f32> = (0..40_001).map(|i| (i as f32 - 20_000.0) * 1.7e-3).collect();
        z.extend([-1e30, -1e5, -0.8, -0.80001, 0.2, 0.20001, 1e5, 1e30, f32::MIN_POSITIVE, -0.0, f32::NAN, f32::INFINITY, f32::NEG_INFINITY]);
        let dh: Vec<f32> = (0..z.len()).map(|i| ((i * 7919) % 1000) as f32 * 2e-3 - 1.0).collect();
        let acts = [
            Activation::None,
            Activation::Relu,
            Activation::LeakyRelu(0.01),
            Activation::Softplus { beta: 100.0 },
            Activation::Softplus { beta: 1.0 },
            Activation::Sigmoid,
        ];
        let bits32 = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let bits64 = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let z64: Vec<f64> = z.iter().map(|&v| v as f64).collect();
        let dh64: Vec<f64> = dh.iter().map(|&v| v as f64).collect();
        eprintln!("this CPU runs the activation loops at {:?}", SimdLevel::detected());
        for act in acts {
            let want = bits32(&act.forward_slice_at(SimdLevel::Scalar, &z));
            let want_d = bits32(&act.backward_slice_at(SimdLevel::Scalar, &z, &dh));
            let want64 = bits64(&act.forward_slice_at(SimdLevel::Scalar, &z64));
            let want64_d = bits64(&act.backward_slice_at(SimdLevel::Scalar, &z64, &dh64));
            for level in SimdLevel::ALL {
                assert_eq!(bits32(&act.forward_slice_at(level, &z)), want, "{act:?} forward at {level:?}");
                assert_eq!(bits32(&act.backward_slice_at(level, &z, &dh)), want_d, "{act:?} backward at {level:?}");
                assert_eq!(bits64(&act.forward_slice_at(level, &z64)), want64, "{act:?} f64 forward at {level:?}");
                assert_eq!(bits64(&act.backward_slice_at(level, &z64, &dh64)), want64_d, "{act:?} f64 backward at {level:?}");
            }
            // The default dispatch is the detected level's.
            assert_eq!(bits32(&act.forward_slice(&z)), want, "{act:?} forward");
        }
    }

    #[test]
    fn layout_with_skip_and_weight_norm() {
        let m = Mlp::new(cfg()).unwrap();
        let dims: Vec<(usize, usize)> = m.layers.iter().map(|l| (l.in_dim, l.out_dim)).collect();
        assert_eq!(dims, vec![(3, 8), (8, 5), (8, 8), (8, 2)]);
        assert!(m.layers[2].skip);
        // W + g + b per layer.
        assert_eq!(m.num_params(), (24 + 16) + (40 + 10) + (64 + 16) + (16 + 4));
        assert_eq!(m.layers[1].w, 40);
        assert_eq!(m.layers[1].g, Some(80));
        assert_eq!(m.layers[1].b, 85);
    }

    #[test]
    fn backward_gives_the_same_bits_on_any_thread_count() {
        // 37 row chunks (the last one short): the parameter gradient sums chunks in fixed groups,
        // so 1, 2, 3 and 8 threads add in the same order. rayon's fold did not.
        let m = Mlp::new(cfg()).unwrap();
        let p = m.init(Init::Default, 3);
        let n = 36 * CPU_CHUNK_ROWS + 517;
        let x: Vec<f32> = (0..n * 3).map(|i| ((i as f32) * 0.731).sin()).collect();
        let dy: Vec<f32> = (0..n * 2).map(|i| ((i as f32) * 0.377).cos() * 10f32.powi((i % 7) as i32 - 3)).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let (_, cache) = cpu_forward(&m, &p, &x, true).unwrap();
                cpu_backward(&m, &p, &cache, &dy).unwrap()
            })
        };
        let (dp1, dx1) = run(1);
        assert!(dp1.iter().all(|v| v.is_finite()) && dp1.iter().any(|v| *v != 0.0));
        for t in [2, 3, 8] {
            let (dp, dx) = run(t);
            assert!(dp.iter().zip(&dp1).all(|(a, b)| a.to_bits() == b.to_bits()), "{t} threads: dL/dparams differ");
            assert!(dx.iter().zip(&dx1).all(|(a, b)| a.to_bits() == b.to_bits()), "{t} threads: dL/dx differ");
        }
    }

    #[test]
    fn small_inputs_are_cut_into_four_chunks_that_sum_the_same_on_any_thread_count() {
        assert_eq!(cpu_chunk_rows(1), CPU_MIN_CHUNK_ROWS);
        assert_eq!(cpu_chunk_rows(1024), 256);
        assert_eq!(cpu_chunk_rows(1100), 320);
        assert_eq!(cpu_chunk_rows(4 * CPU_CHUNK_ROWS - 1), CPU_CHUNK_ROWS);
        assert_eq!(cpu_chunk_rows(100 * CPU_CHUNK_ROWS), CPU_CHUNK_ROWS);
        let m = Mlp::new(cfg()).unwrap();
        let p = m.init(Init::Default, 5);
        // 1000 rows: chunks of 256, 256, 256 and 232; a row's output is the one it has alone, to
        // rounding (the GEMM library sums a one-row product in another order than a tile's).
        let n = 1000;
        let x: Vec<f32> = (0..n * 3).map(|i| ((i as f32) * 0.291).sin()).collect();
        let dy: Vec<f32> = (0..n * 2).map(|i| ((i as f32) * 0.613).cos()).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let (y, cache) = cpu_forward(&m, &p, &x, true).unwrap();
                assert_eq!(cache.chunks.iter().map(|c| c.rows).collect::<Vec<_>>(), vec![256, 256, 256, 232]);
                let (dp, dx) = cpu_backward(&m, &p, &cache, &dy).unwrap();
                (y, dp, dx)
            })
        };
        let (y1, dp1, dx1) = run(1);
        for (r, yr) in y1.chunks(2).enumerate().step_by(97) {
            let (one, _) = cpu_forward(&m, &p, &x[3 * r..3 * r + 3], false).unwrap();
            assert!(one.iter().zip(yr).all(|(a, b)| (a - b).abs() <= 1e-6 * (1.0 + b.abs())), "row {r}: {one:?} alone vs {yr:?}");
        }
        // The parameter gradient against one f64 pass over all rows.
        let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
        let x64: Vec<f64> = x.iter().map(|&v| v as f64).collect();
        let dy64: Vec<f64> = dy.iter().map(|&v| v as f64).collect();
        let (_, c64) = cpu_forward(&m, &p64, &x64, true).unwrap();
        let (dp64, _) = cpu_backward(&m, &p64, &c64, &dy64).unwrap();
        let scale = dp64.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        assert!(dp1.iter().zip(&dp64).all(|(a, b)| (*a as f64 - b).abs() <= 1e-4 * scale), "f32 chunks vs f64");
        for t in [2, 3, 8] {
            let (y, dp, dx) = run(t);
            assert!(y.iter().zip(&y1).all(|(a, b)| a.to_bits() == b.to_bits()), "{t} threads: y differs");
            assert!(dp.iter().zip(&dp1).all(|(a, b)| a.to_bits() == b.to_bits()), "{t} threads: dL/dparams differ");
            assert!(dx.iter().zip(&dx1).all(|(a, b)| a.to_bits() == b.to_bits()), "{t} threads: dL/dx differ");
        }
    }

    #[test]
    fn geometric_init_starts_as_a_sphere() {
        let mut c = cfg();
        c.widths = vec![64, 64, 64];
        c.activation = Activation::Softplus { beta: 100.0 };
        c.out_dim = 1;
        let m = Mlp::new(c).unwrap();
        let p = m.init(
            Init::Geometric {
                radius: 0.5,
                raw_dims: 3,
            },
            7,
        );
        let x: Vec<f32> = vec![0.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0, -0.5, 0.0];
        let (y, _) = cpu_forward(&m, &p, &x, false).unwrap();
        // Roughly |x| - r: negative inside, positive outside, near zero on the sphere.
        assert!(y[0] < -0.2, "{y:?}");
        assert!(y[1] > 0.1, "{y:?}");
        assert!(y[2].abs() < 0.2, "{y:?}");
    }
}
