//! The SDF network: an input encoding followed by an [`Mlp`]; output `(sdf, feature)` per point.
//!
//! Gradients of the SDF with respect to `x` (normals, the eikonal term) are **numerical**:
//! central differences over a 6-point stencil (Neuralangelo). A loss on the SDF and on its
//! x-gradient is then a loss on 7 field evaluations per point, so its backward is an ordinary
//! first-order backward of the encoding + MLP ([`SdfField::value_and_grad`]); no second-order
//! derivatives are needed. The analytic input gradient of the MLP is still available
//! ([`Backend::mlp_backward`]'s `d_input`) and is used by the tests to check the stencil.
//!
//! Parameter layout: `[encoding parameters, MLP parameters]` (see [`crate::nn::mlp`]).
//!
//! Encodings ([`PositionEncoder`]): the frequency encoding with the input included for the paper
//! preset, and the raw position concatenated with the multiresolution hash grid (NeuS2) for the
//! fast preset. The MLP runs on the chosen backend. On the cpu backend, and for the frequency
//! encoding everywhere, the encoding runs on the host through the cpu twins of `nn::encoding`; on
//! wgpu the hash grid runs its WGSL twin and `shaders/field.wgsl` assembles the MLP's input rows
//! on the device, so only the points go up and only the outputs come back, and the parameters stay
//! on the device between calls while they are unchanged (tracing evaluates the field dozens of
//! times per training step).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use crate::backend::gpu::{groups_1d, shaders, Access, GpuBuffer, GpuContext, KernelSpec};
use crate::backend::{Backend, BackendError, Tensor};
use crate::nn::encoding::{encoding_backward_cpu, encoding_forward_cpu, frequency_backward_cpu, hash_grid_backward_x_cpu, EncodingConfig};
use crate::nn::mlp::{Activation, Init, Mlp, MlpConfig};

/// An input encoding the field can use. Only parameter gradients are needed (x-gradients are
/// numerical, see the module docs).
pub trait Encoder: Send + Sync + std::fmt::Debug {
    fn in_dim(&self) -> usize;
    fn out_dim(&self) -> usize;
    fn num_params(&self) -> usize;
    fn init(&self, seed: u64) -> Vec<f32>;
    /// `x` `[n, in_dim]` → `[n, out_dim]`.
    fn forward(&self, params: &[f32], x: &[f32]) -> Vec<f32>;
    /// `dL/dparams` from `dL/d(encoding)` `[n, out_dim]`.
    fn backward_params(&self, params: &[f32], x: &[f32], d_enc: &[f32]) -> Vec<f32>;
    /// Coarse-to-fine training (Neuralangelo): only the first `levels` grid levels feed the
    /// MLP (the others output 0 and receive no gradient); `None` = all. Encoders without levels
    /// ignore it.
    fn set_active_levels(&mut self, _levels: Option<usize>) {}
    /// Where the encoding has a WGSL twin: the row layout [`SdfField`] assembles on the device.
    fn device_layout(&self) -> Option<DeviceLayout> {
        None
    }
}

/// An encoder row as the device builds it: `raw` input columns, then `enc` encoding columns of
/// which the first `active` are kept (the rest are zero, see [`Encoder::set_active_levels`]).
#[derive(Clone, Debug)]
pub struct DeviceLayout {
    pub encoding: EncodingConfig,
    pub raw: usize,
    pub enc: usize,
    pub active: usize,
}

static HOST_ENCODING_NS: AtomicU64 = AtomicU64::new(0);

/// Seconds spent so far in this process in [`PositionEncoder`]'s host encodings (forward and
/// backward), whatever the backend: the reports divide the difference over a run by its steps.
pub fn host_encoding_seconds() -> f64 {
    HOST_ENCODING_NS.load(Ordering::Relaxed) as f64 * 1e-9
}

fn timed<T>(f: impl FnOnce() -> T) -> T {
    let t = Instant::now();
    let out = f();
    HOST_ENCODING_NS.fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
    out
}

/// The field's position encoding, computed by the cpu twins of `nn::encoding`:
/// - paper preset: the frequency encoding with the input included (IDR/NeRF),
///   `[x, sin(2^0 x), cos(2^0 x), ..., sin(2^(F-1) x), cos(2^(F-1) x)]`, no parameters;
/// - fast preset (NeuS2): `[x, grid(x)]`, the raw position (so the geometric initialisation sees
///   it) followed by the hash grid's `levels·F` features over `[-1, 1]^3`.
#[derive(Clone, Debug)]
pub struct PositionEncoder {
    pub encoding: EncodingConfig,
    /// Prepend the raw position to the encoding's output.
    pub raw_xyz: bool,
    /// Hash-grid levels that feed the MLP (coarse to fine); `None` = all.
    pub active_levels: Option<usize>,
}

impl PositionEncoder {
    fn raw_dim(&self) -> usize {
        if self.raw_xyz {
            3
        } else {
            0
        }
    }

    /// Columns `[start, end)` of the encoded row that belong to inactive grid levels.
    fn inactive_columns(&self) -> Option<(usize, usize)> {
        let EncodingConfig::HashGrid { levels, features_per_level, .. } = self.encoding else {
            return None;
        };
        let active = self.active_levels?.min(levels as usize);
        let f = features_per_level as usize;
        (active < levels as usize).then(|| (self.raw_dim() + active * f, self.raw_dim() + levels as usize * f))
    }
}

impl Encoder for PositionEncoder {
    fn in_dim(&self) -> usize {
        3
    }
    fn out_dim(&self) -> usize {
        self.raw_dim() + self.encoding.out_dim(3)
    }
    fn num_params(&self) -> usize {
        self.encoding.num_params()
    }
    fn init(&self, seed: u64) -> Vec<f32> {
        self.encoding.init_params(seed)
    }
    fn forward(&self, params: &[f32], x: &[f32]) -> Vec<f32> {
        timed(|| self.forward_host(params, x))
    }
    fn backward_params(&self, params: &[f32], x: &[f32], d_enc: &[f32]) -> Vec<f32> {
        timed(|| self.backward_params_host(params, x, d_enc))
    }
    fn set_active_levels(&mut self, levels: Option<usize>) {
        self.active_levels = levels;
    }
    fn device_layout(&self) -> Option<DeviceLayout> {
        let EncodingConfig::HashGrid { .. } = self.encoding else {
            return None;
        };
        let (raw, enc) = (self.raw_dim(), self.encoding.out_dim(3));
        let active = self.inactive_columns().map_or(enc, |(a, _)| a - raw);
        Some(DeviceLayout { encoding: self.encoding.clone(), raw, enc, active })
    }
}

impl PositionEncoder {
    fn forward_host(&self, params: &[f32], x: &[f32]) -> Vec<f32> {
        let enc = encoding_forward_cpu(&self.encoding, params, x, 3);
        let mut out = if !self.raw_xyz {
            enc
        } else {
            let ed = self.encoding.out_dim(3);
            let mut out = Vec::with_capacity(x.len() / 3 * self.out_dim());
            for (p, f) in x.chunks_exact(3).zip(enc.chunks_exact(ed)) {
                out.extend_from_slice(p);
                out.extend_from_slice(f);
            }
            out
        };
        if let Some((a, b)) = self.inactive_columns() {
            let od = self.out_dim();
            out.chunks_exact_mut(od).for_each(|r| r[a..b].fill(0.0));
        }
        out
    }
    fn backward_params_host(&self, params: &[f32], x: &[f32], d_enc: &[f32]) -> Vec<f32> {
        if self.encoding.num_params() == 0 {
            return Vec::new();
        }
        encoding_backward_cpu(&self.encoding, params, x, 3, &self.encoding_columns(d_enc), false).0
    }

    /// `dL/d(encoding)` rows without the raw columns, inactive levels' columns zeroed.
    fn encoding_columns(&self, d_enc: &[f32]) -> Vec<f32> {
        let rd = self.raw_dim();
        let cut = self.inactive_columns();
        d_enc
            .chunks_exact(self.out_dim())
            .flat_map(|r| {
                r[rd..].iter().enumerate().map(move |(j, &v)| match cut {
                    Some((a, b)) if (a..b).contains(&(j + rd)) => 0.0,
                    _ => v,
                })
            })
            .collect()
    }

    /// `dL/dx` `[n, 3]` from `dL/d(encoding)` `[n, out_dim]`: the encoding's own position
    /// derivative (analytic for both encodings; a hash grid's is its trilinear interpolation's)
    /// plus the raw columns, which pass straight through.
    pub fn backward_x(&self, params: &[f32], x: &[f32], d_enc: &[f32]) -> Vec<f32> {
        timed(|| {
            let d = self.encoding_columns(d_enc);
            let mut dx = match self.encoding {
                EncodingConfig::Frequency { n_freqs, include_input } => frequency_backward_cpu(n_freqs, include_input, x, 3, &d),
                EncodingConfig::HashGrid { .. } => hash_grid_backward_x_cpu(&self.encoding, params, x, &d),
            };
            if self.raw_xyz {
                for (d, r) in dx.chunks_exact_mut(3).zip(d_enc.chunks_exact(self.out_dim())) {
                    d.iter_mut().zip(&r[..3]).for_each(|(a, b)| *a += b);
                }
            }
            dx
        })
    }
}

/// Which encoding feeds the MLP.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum FieldEncoding {
    /// Frequency PE, input included.
    Frequency { n_freqs: usize },
    /// Multiresolution hash grid (Instant-NGP), concatenated with the raw position (NeuS2).
    HashGrid {
        levels: usize,
        features_per_level: usize,
        log2_table_size: u32,
        base_resolution: u32,
        growth: f32,
    },
}

impl FieldEncoding {
    /// The `nn::encoding` configuration of this encoding (3-D inputs; the hash grid covers
    /// `[-1, 1]^3`). For the hash grid, the field also feeds the raw position ([`PositionEncoder::raw_xyz`]).
    pub fn encoding_config(&self) -> EncodingConfig {
        match *self {
            FieldEncoding::Frequency { n_freqs } => EncodingConfig::frequency(n_freqs as u32),
            FieldEncoding::HashGrid { levels, features_per_level, log2_table_size, base_resolution, growth } => {
                EncodingConfig::HashGrid {
                    levels: levels as u32,
                    features_per_level: features_per_level as u32,
                    log2_table_size,
                    base_resolution,
                    per_level_scale: growth,
                    bound: 1.0,
                }
            }
        }
    }

    /// The field's encoder: the hash grid is fed with the raw position beside it (NeuS2).
    /// The project's hash grid: 16 levels × 2 features from base resolution 16 up to `finest`
    /// cells per axis over `[-1, 1]^3`, `2^log2_table` entries per level.
    pub fn hash_grid(finest: u32, log2_table: u32) -> Self {
        let (levels, base) = (16usize, 16u32);
        FieldEncoding::HashGrid {
            levels,
            features_per_level: 2,
            log2_table_size: log2_table,
            base_resolution: base,
            growth: ((finest.max(base + 1) as f32 / base as f32).ln() / (levels - 1) as f32).exp(),
        }
    }

    pub fn encoder(&self) -> PositionEncoder {
        let raw_xyz = matches!(self, FieldEncoding::HashGrid { .. });
        PositionEncoder { encoding: self.encoding_config(), raw_xyz, active_levels: None }
    }

    /// Width of the MLP's input: the encoded 3-D position (raw xyz included).
    pub fn encoded_dim(&self) -> usize {
        self.encoder().out_dim()
    }
}

/// An SDF network's configuration. Presets: [`SdfFieldConfig::paper`], [`SdfFieldConfig::fast`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SdfFieldConfig {
    pub encoding: FieldEncoding,
    pub widths: Vec<usize>,
    pub skip_layers: Vec<usize>,
    pub activation: Activation,
    pub weight_norm: bool,
    /// Feature channels after the SDF (the radiance net's input).
    pub feature_dim: usize,
    /// Geometric initialisation: the field starts as a sphere of this radius.
    pub init_radius: f32,
    /// Central-difference step for the numerical x-gradient.
    pub grad_step: f32,
}

impl SdfFieldConfig {
    /// The paper's (IDR's) SDF network: PE 6 frequencies (input included), 8×512, skip into
    /// layer 4, Softplus β = 100, geometric init, weight norm, 256 features.
    pub fn paper() -> Self {
        Self {
            encoding: FieldEncoding::Frequency { n_freqs: 6 },
            widths: vec![512; 8],
            skip_layers: vec![4],
            activation: Activation::Softplus { beta: 100.0 },
            weight_norm: true,
            feature_dim: 256,
            init_radius: 0.6,
            grad_step: 1e-3,
        }
    }

    /// The fast network (Instant-NGP / NeuS2 style): hash grid 16 levels × 2 features + a 2×64
    /// MLP, Softplus β = 100, geometric init, 15 features.
    pub fn fast() -> Self {
        Self {
            encoding: FieldEncoding::HashGrid {
                levels: 16,
                features_per_level: 2,
                log2_table_size: 19,
                base_resolution: 16,
                growth: 1.447,
            },
            widths: vec![64; 2],
            skip_layers: vec![],
            activation: Activation::Softplus { beta: 100.0 },
            weight_norm: false,
            feature_dim: 15,
            init_radius: 0.6,
            grad_step: 1e-3,
        }
    }

    /// The MLP the field uses on top of its encoding, if the encoding is available.
    pub fn mlp_config(&self, encoded_dim: usize) -> MlpConfig {
        MlpConfig {
            in_dim: encoded_dim,
            widths: self.widths.clone(),
            out_dim: 1 + self.feature_dim,
            activation: self.activation,
            output_activation: Activation::None,
            skip_layers: self.skip_layers.clone(),
            weight_norm: self.weight_norm,
        }
    }
}

/// What a loss sees at each point of [`SdfField::value_and_grad`].
#[derive(Clone, Debug, Default)]
pub struct FieldOutputs {
    /// `[n]`.
    pub sdf: Vec<f32>,
    /// Numerical ∇f, `[n, 3]`.
    pub gradient: Vec<f32>,
    /// `[n, feature_dim]`.
    pub feature: Vec<f32>,
}

/// A loss's derivatives with respect to [`FieldOutputs`] (same shapes; empty `feature` = 0).
#[derive(Clone, Debug, Default)]
pub struct FieldOutputGrads {
    pub sdf: Vec<f32>,
    pub gradient: Vec<f32>,
    pub feature: Vec<f32>,
}

/// An SDF network: encoder + MLP.
#[derive(Debug)]
pub struct SdfField {
    pub config: SdfFieldConfig,
    pub encoder: Box<dyn Encoder>,
    pub mlp: Mlp,
    /// The parameters' copy on the device, re-uploaded only when their bytes change: tracing
    /// evaluates the field dozens of times per training step with the same parameters.
    mirror: Mutex<Vec<(Vec<f32>, GpuBuffer)>>,
    /// Parameter slices (address, length) whose device copy is known current without comparing
    /// them, for as long as a [`PinnedParams`] borrows them (see [`SdfField::pin`]); one entry
    /// per live pin.
    pins: Mutex<Vec<(usize, usize, GpuBuffer)>>,
}

/// A borrow of an [`SdfField`]'s parameters during which their device copy is used without
/// comparing bytes: the borrow keeps them from changing, so the address and length name the
/// same values. Dropping it (before the optimiser writes them) forgets its pins.
pub struct PinnedParams<'a> {
    field: &'a SdfField,
    _params: &'a [f32],
    keys: Vec<(usize, usize)>,
}

impl Drop for PinnedParams<'_> {
    fn drop(&mut self) {
        let mut pins = self.field.pins.lock().expect("field pins poisoned");
        for k in &self.keys {
            if let Some(i) = pins.iter().position(|(a, n, _)| (*a, *n) == *k) {
                pins.remove(i);
            }
        }
    }
}

impl SdfField {
    pub fn new(config: SdfFieldConfig) -> Result<Self, BackendError> {
        if !(config.grad_step.is_finite() && config.grad_step > 0.0) {
            return Err(BackendError::Config(format!(
                "grad_step must be positive, got {}",
                config.grad_step
            )));
        }
        config.encoding.encoding_config().validate(3)?;
        let encoder: Box<dyn Encoder> = Box::new(config.encoding.encoder());
        let mlp = Mlp::new(config.mlp_config(encoder.out_dim()))?;
        Ok(Self { config, encoder, mlp, mirror: Mutex::new(Vec::new()), pins: Mutex::new(Vec::new()) })
    }

    /// A field from an already-built encoder (e.g. a hash grid from `nn::encoding`).
    pub fn with_encoder(
        config: SdfFieldConfig,
        encoder: Box<dyn Encoder>,
    ) -> Result<Self, BackendError> {
        let mlp = Mlp::new(config.mlp_config(encoder.out_dim()))?;
        Ok(Self { config, encoder, mlp, mirror: Mutex::new(Vec::new()), pins: Mutex::new(Vec::new()) })
    }

    pub fn num_params(&self) -> usize {
        self.encoder.num_params() + self.mlp.num_params()
    }

    /// Seeded parameters: encoder init, then the MLP's geometric (sphere) init with the raw
    /// position as the first 3 encoded dims.
    pub fn init(&self, seed: u64) -> Vec<f32> {
        let mut p = self.encoder.init(seed);
        p.extend(self.mlp.init(
            Init::Geometric {
                radius: self.config.init_radius,
                raw_dims: 3,
            },
            seed + 1,
        ));
        p
    }

    fn split<'a>(&self, params: &'a [f32]) -> Result<(&'a [f32], &'a [f32]), BackendError> {
        if params.len() != self.num_params() {
            return Err(BackendError::Shape(format!(
                "SDF field expects {} parameters, got {}",
                self.num_params(),
                params.len()
            )));
        }
        Ok(params.split_at(self.encoder.num_params()))
    }

    fn check_points(x: &[f32]) -> Result<usize, BackendError> {
        if x.len() % 3 != 0 {
            return Err(BackendError::Shape(format!(
                "points: {} values is not a multiple of 3",
                x.len()
            )));
        }
        Ok(x.len() / 3)
    }

    /// Raw outputs `[n, 1 + feature_dim]` at points `x` `[n, 3]`.
    pub fn eval(
        &self,
        backend: &Backend,
        params: &[f32],
        x: &[f32],
    ) -> Result<Vec<f32>, BackendError> {
        Self::check_points(x)?;
        let (pe, pm) = self.split(params)?;
        let (_, enc) = self.encode(backend, pe, x)?;
        let fwd = backend.mlp_forward(&self.mlp, &self.on_device(backend, pm), &enc, false)?;
        backend.to_vec(&fwd.output)
    }

    /// `params` on the backend: on wgpu, the device copy kept from an earlier call whose values
    /// were the same (compared bit for bit against the host copy kept beside it, in parallel:
    /// far cheaper than the upload), else a fresh upload.
    fn on_device(&self, backend: &Backend, params: &[f32]) -> Tensor {
        let Some(g) = backend.gpu().filter(|_| !params.is_empty()) else {
            return backend.upload(params);
        };
        let key = (params.as_ptr() as usize, params.len());
        if let Some((.., t)) = self.pins.lock().expect("field pins poisoned").iter().find(|(a, n, _)| (*a, *n) == key) {
            return Tensor::Device(t.clone());
        }
        let mut m = self.mirror.lock().expect("field mirror poisoned");
        if let Some((_, b)) = m.iter().find(|(host, _)| crate::util::same_bits(host, params)) {
            return Tensor::Device(b.clone());
        }
        let b = g.upload_f32("field.params", params);
        // The encoding's and the MLP's parameters, and one spare for a caller alternating sets.
        if m.len() >= 3 {
            m.remove(0);
        }
        m.push((params.to_vec(), b.clone()));
        Tensor::Device(b)
    }

    /// Keep `params` (all of the field's) on the device, found by address while the returned
    /// borrow lives: a training step evaluates the field a dozen times with the same parameters,
    /// and comparing a large hash grid's bytes with their device copy each time cost more host
    /// time than the launches. Without a GPU it does nothing. Pins nest: each borrow removes
    /// only its own when dropped.
    pub fn pin<'a>(&'a self, backend: &Backend, params: &'a [f32]) -> Result<PinnedParams<'a>, BackendError> {
        if backend.gpu().is_none() {
            return Ok(PinnedParams { field: self, _params: params, keys: Vec::new() });
        }
        let (pe, pm) = self.split(params)?;
        let copies = [pe, pm].map(|p| self.on_device(backend, p));
        self.pin_copies(params, [copies[0].device().ok(), copies[1].device().ok()])
    }

    /// Pin `params` to device copies the caller holds, `[encoding, MLP]`: for a trainer whose
    /// optimiser updates the parameters on the device, so that the host slice is only the key
    /// (its values may be older). Every evaluation must then find them by address: see
    /// [`SdfField::evaluates_on_device`].
    pub fn pin_device<'a>(&'a self, params: &'a [f32], copies: [&GpuBuffer; 2]) -> Result<PinnedParams<'a>, BackendError> {
        self.pin_copies(params, copies.map(Some))
    }

    fn pin_copies<'a>(&'a self, params: &'a [f32], copies: [Option<&GpuBuffer>; 2]) -> Result<PinnedParams<'a>, BackendError> {
        let (pe, pm) = self.split(params)?;
        let pairs: Vec<(&[f32], &GpuBuffer)> =
            [pe, pm].into_iter().zip(copies).filter_map(|(p, t)| Some((p, t?))).filter(|(p, _)| !p.is_empty()).collect();
        if let Some((p, t)) = pairs.iter().find(|(p, t)| t.len != p.len()) {
            return Err(BackendError::Shape(format!("pinned copy: {} values for {} parameters", t.len, p.len())));
        }
        let keys: Vec<(usize, usize)> = pairs.iter().map(|(p, _)| (p.as_ptr() as usize, p.len())).collect();
        self.pins.lock().expect("field pins poisoned").extend(pairs.iter().zip(&keys).map(|((_, t), k)| (k.0, k.1, (*t).clone())));
        Ok(PinnedParams { field: self, _params: params, keys })
    }

    /// The MLP's input rows for points `x`, and the points as a device tensor where the
    /// encoding ran on the device (the backward needs them). On wgpu a hash-grid encoder runs
    /// its WGSL twin and the row is assembled there; otherwise the host encodes and uploads.
    fn encode(&self, backend: &Backend, pe: &[f32], x: &[f32]) -> Result<(Option<Tensor>, Tensor), BackendError> {
        let (Some(g), Some(l)) = (backend.gpu(), self.encoder.device_layout()) else {
            return Ok((None, backend.from_vec(self.encoder.forward(pe, x))));
        };
        let n = x.len() / 3;
        let xt = backend.upload(x);
        let rows = device_rows(backend, g, &l, &self.on_device(backend, pe), &xt, n)?;
        Ok((Some(xt), rows))
    }

    /// The field with `params` on the device, for evaluations whose points and outputs stay
    /// there (the tracer's loops, `render::device`): `None` where the encoding runs on the host
    /// (the paper preset's frequency encoding, or the cpu backend).
    pub fn on_device_eval<'a>(&'a self, backend: &'a Backend, params: &[f32]) -> Result<Option<DeviceField<'a>>, BackendError> {
        let (Some(g), Some(layout)) = (backend.gpu(), self.encoder.device_layout()) else {
            return Ok(None);
        };
        let (pe, pm) = self.split(params)?;
        let (pe, pm) = (self.on_device(backend, pe), self.on_device(backend, pm));
        Ok(Some(DeviceField { field: self, backend, gpu: g.clone(), layout, pe, pm }))
    }

    /// SDF values `[n]`.
    pub fn sdf(
        &self,
        backend: &Backend,
        params: &[f32],
        x: &[f32],
    ) -> Result<Vec<f32>, BackendError> {
        let out = self.eval(backend, params, x)?;
        Ok(out.chunks_exact(self.mlp.out_dim()).map(|r| r[0]).collect())
    }

    /// The 7-point stencil: `x`, then `x ± h e_i` for i = 0..3, as 7 blocks of `n` points.
    fn stencil(&self, x: &[f32]) -> Vec<f32> {
        let h = self.config.grad_step;
        let mut pts = Vec::with_capacity(x.len() * 7);
        pts.extend_from_slice(x);
        for axis in 0..3 {
            for sign in [1.0f32, -1.0] {
                pts.extend(x.chunks_exact(3).flat_map(|p| {
                    let mut q = [p[0], p[1], p[2]];
                    q[axis] += sign * h;
                    q
                }));
            }
        }
        pts
    }

    fn outputs_from_stencil(&self, out: &[f32], n: usize) -> FieldOutputs {
        let od = self.mlp.out_dim();
        let h = self.config.grad_step;
        let sdf: Vec<f32> = (0..n).map(|i| out[i * od]).collect();
        let mut gradient = vec![0f32; n * 3];
        for axis in 0..3 {
            let (plus, minus) = ((1 + 2 * axis) * n, (2 + 2 * axis) * n);
            for i in 0..n {
                gradient[i * 3 + axis] = (out[(plus + i) * od] - out[(minus + i) * od]) / (2.0 * h);
            }
        }
        let feature = (0..n)
            .flat_map(|i| out[i * od + 1..(i + 1) * od].iter().copied())
            .collect();
        FieldOutputs {
            sdf,
            gradient,
            feature,
        }
    }

    /// SDF, numerical gradient and features at `x` `[n, 3]` (7 evaluations per point).
    pub fn eval_with_gradient(
        &self,
        backend: &Backend,
        params: &[f32],
        x: &[f32],
    ) -> Result<FieldOutputs, BackendError> {
        let n = Self::check_points(x)?;
        let out = self.eval(backend, params, &self.stencil(x))?;
        Ok(self.outputs_from_stencil(&out, n))
    }

    /// Evaluate at `x`, let `loss` turn the outputs into `(value, dL/doutputs)`, and return
    /// `(value, dL/dparams)`. First-order only: the gradient term's backward goes through the
    /// stencil evaluations (`dL/df(x ± h e_i) = ±dL/d∇f_i / 2h`).
    pub fn value_and_grad(
        &self,
        backend: &Backend,
        params: &[f32],
        x: &[f32],
        loss: impl FnOnce(&FieldOutputs) -> (f64, FieldOutputGrads),
    ) -> Result<(f64, Vec<f32>), BackendError> {
        let (value, [d_enc, d_mlp]) = self.value_and_grad_tensors(backend, params, x, loss)?;
        // The encoding's and the MLP's parameter gradients, read back with one wait.
        let (mut d_params, d_mlp) = match (d_enc, d_mlp) {
            (Tensor::Host(e), Tensor::Host(m)) => (e, m),
            (e, m) => backend.to_vec2(&e, &m)?,
        };
        d_params.extend(d_mlp);
        Ok((value, d_params))
    }

    /// [`SdfField::value_and_grad`] with the parameter gradient left where it was computed:
    /// `[encoding, MLP]` (the two halves of the parameter vector), device tensors where the
    /// encoding runs on the device, so an optimiser there needs no readback.
    pub fn value_and_grad_tensors(
        &self,
        backend: &Backend,
        params: &[f32],
        x: &[f32],
        loss: impl FnOnce(&FieldOutputs) -> (f64, FieldOutputGrads),
    ) -> Result<(f64, [Tensor; 2]), BackendError> {
        let n = Self::check_points(x)?;
        let (pe, pm) = self.split(params)?;
        let pts = self.stencil(x);
        let (pts_t, enc) = self.encode(backend, pe, &pts)?;
        let pm_t = self.on_device(backend, pm);
        let fwd = backend.mlp_forward(&self.mlp, &pm_t, &enc, true)?;
        let out = backend.to_vec(&fwd.output)?;
        let outputs = self.outputs_from_stencil(&out, n);
        let (value, g) = loss(&outputs);
        let od = self.mlp.out_dim();
        let fd = self.config.feature_dim;
        let check = |v: &[f32], len: usize, what: &str| {
            if v.len() != len && !v.is_empty() {
                return Err(BackendError::Shape(format!(
                    "loss gradient for {what}: {} values, expected {len}",
                    v.len()
                )));
            }
            Ok(())
        };
        check(&g.sdf, n, "sdf")?;
        check(&g.gradient, n * 3, "gradient")?;
        check(&g.feature, n * fd, "feature")?;
        let mut d_out = vec![0f32; pts.len() / 3 * od];
        let h2 = 2.0 * self.config.grad_step;
        for i in 0..n {
            if !g.sdf.is_empty() {
                d_out[i * od] = g.sdf[i];
            }
            if !g.feature.is_empty() {
                d_out[i * od + 1..(i + 1) * od].copy_from_slice(&g.feature[i * fd..(i + 1) * fd]);
            }
            if !g.gradient.is_empty() {
                for axis in 0..3 {
                    let dg = g.gradient[i * 3 + axis] / h2;
                    d_out[((1 + 2 * axis) * n + i) * od] += dg;
                    d_out[((2 + 2 * axis) * n + i) * od] -= dg;
                }
            }
        }
        let grads = backend.mlp_backward(&self.mlp, &pm_t, &fwd, &backend.from_vec(d_out))?;
        let d_enc = match (backend.gpu(), self.encoder.device_layout(), &pts_t) {
            (Some(g), Some(l), Some(pts_t)) => {
                let m = pts.len() / 3;
                let d_row = grads.d_input.device()?;
                let d_enc = g.zeros_f32("field.d_enc", m * l.enc);
                row_kernel(g, "split", &l, m, d_row, d_row, &d_enc, m * l.enc)?;
                let grid = self.on_device(backend, pe);
                backend.encoding_backward(&l.encoding, &grid, pts_t, m, &Tensor::Device(d_enc), false)?.0
            }
            _ if self.encoder.num_params() > 0 => {
                let (d_enc, d_mlp) = backend.to_vec2(&grads.d_input, &grads.d_params)?;
                let d = self.encoder.backward_params(pe, &pts, &d_enc);
                return Ok((value, [Tensor::Host(d), Tensor::Host(d_mlp)]));
            }
            _ => Tensor::Host(Vec::new()),
        };
        Ok((value, [d_enc, grads.d_params]))
    }

    /// Whether every evaluation on `backend` finds the parameters through their device copy
    /// (a GPU, and an encoding that either has no parameters or runs there): only then can the
    /// parameters' current values live on the device alone ([`SdfField::pin_device`]).
    pub fn evaluates_on_device(&self, backend: &Backend) -> bool {
        backend.gpu().is_some() && (self.encoder.num_params() == 0 || self.encoder.device_layout().is_some())
    }
}

/// The MLP input rows `[n, raw + enc]` of the device points `xt` `[n, 3]`: the hash grid's WGSL
/// encoding with the encoding parameters `pe`, assembled on the device.
fn device_rows(backend: &Backend, g: &GpuContext, l: &DeviceLayout, pe: &Tensor, xt: &Tensor, n: usize) -> Result<Tensor, BackendError> {
    let grid = backend.encoding_forward(&l.encoding, pe, xt, n)?;
    let out = g.zeros_f32("field.rows", n * (l.raw + l.enc));
    row_kernel(g, "assemble", l, n, xt.device()?, grid.device()?, &out, n * (l.raw + l.enc))?;
    Ok(Tensor::Device(out))
}

/// An SDF field whose parameters are on the device ([`SdfField::on_device_eval`]).
pub struct DeviceField<'a> {
    field: &'a SdfField,
    backend: &'a Backend,
    gpu: std::sync::Arc<GpuContext>,
    layout: DeviceLayout,
    pe: Tensor,
    pm: Tensor,
}

impl DeviceField<'_> {
    /// Raw outputs `[n, 1 + feature_dim]` at the device points `x` `[n, 3]`, left on the device
    /// (launches only, no wait).
    pub fn eval(&self, x: &GpuBuffer, n: usize) -> Result<GpuBuffer, BackendError> {
        let rows = device_rows(self.backend, &self.gpu, &self.layout, &self.pe, &Tensor::Device(x.clone()), n)?;
        let fwd = self.backend.mlp_forward(&self.field.mlp, &self.pm, &rows, false)?;
        Ok(fwd.output.device()?.clone())
    }

    pub fn out_dim(&self) -> usize {
        self.field.mlp.out_dim()
    }

    pub fn gpu(&self) -> &GpuContext {
        &self.gpu
    }
}

/// Mirrors `RowParams` in `shaders/field.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RowParams {
    n: u32,
    raw: u32,
    enc: u32,
    active: u32,
}

const FIELD_WGSL: &str = include_str!("../../shaders/field.wgsl");

/// Launch `assemble` or `split` of `shaders/field.wgsl` over `total` outputs.
fn row_kernel(
    g: &GpuContext,
    entry: &str,
    l: &DeviceLayout,
    n: usize,
    a: &GpuBuffer,
    b: &GpuBuffer,
    out: &GpuBuffer,
    total: usize,
) -> Result<(), BackendError> {
    if total > u32::MAX as usize {
        return Err(BackendError::Shape(format!("field rows: {total} values is too many for 32-bit indexing")));
    }
    let spec = KernelSpec::new(true, &[Access::Read, Access::Read, Access::ReadWrite]);
    let k = g.kernel("field", &shaders::with_lib(FIELD_WGSL), entry, &spec)?;
    let p = RowParams { n: n as u32, raw: l.raw as u32, enc: l.enc as u32, active: l.active as u32 };
    g.dispatch(&k, Some(bytemuck::bytes_of(&p)), &[a.into(), b.into(), out.into()], groups_1d(total, 256))
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    fn small() -> SdfFieldConfig {
        SdfFieldConfig {
            encoding: FieldEncoding::Frequency { n_freqs: 2 },
            widths: vec![16, 16],
            skip_layers: vec![],
            activation: Activation::Softplus { beta: 10.0 },
            weight_norm: false,
            feature_dim: 2,
            init_radius: 0.5,
            grad_step: 1e-3,
        }
    }

    #[test]
    fn presets_build_and_paper_has_the_idr_shape() {
        let f = SdfField::new(SdfFieldConfig::paper()).unwrap();
        assert_eq!(f.encoder.out_dim(), 39);
        let dims: Vec<(usize, usize)> =
            f.mlp.layers.iter().map(|l| (l.in_dim, l.out_dim)).collect();
        assert_eq!(dims[0], (39, 512));
        assert_eq!(dims[3], (512, 512 - 39));
        assert_eq!(dims[8], (512, 257));
        assert!(f.mlp.layers[4].skip);
    }

    #[test]
    fn numerical_gradient_matches_the_analytic_input_gradient() {
        let b = Backend::cpu();
        let f = SdfField::new(small()).unwrap();
        let p = f.init(3);
        let x = [0.3f32, -0.2, 0.1, -0.5, 0.4, 0.25];
        let o = f.eval_with_gradient(&b, &p, &x).unwrap();
        // Analytic: d sdf / dx through the PE and the MLP's input gradient.
        let enc = f.encoder.forward(&[], &x);
        let fwd = b
            .mlp_forward(&f.mlp, &b.upload(&p), &b.upload(&enc), true)
            .unwrap();
        let mut dy = vec![0f32; 2 * f.mlp.out_dim()];
        dy[0] = 1.0;
        dy[f.mlp.out_dim()] = 1.0;
        let de = b
            .to_vec(
                &b.mlp_backward(&f.mlp, &b.upload(&p), &fwd, &b.upload(&dy))
                    .unwrap()
                    .d_input,
            )
            .unwrap();
        let ed = f.encoder.out_dim();
        let mut analytic = vec![0f32; 6];
        for i in 0..2 {
            for a in 0..3 {
                let v = x[i * 3 + a];
                let mut g = de[i * ed + a];
                for k in 0..2 {
                    let s = (1 << k) as f32;
                    g += de[i * ed + 3 + k * 6 + a] * s * (s * v).cos();
                    g -= de[i * ed + 3 + k * 6 + 3 + a] * s * (s * v).sin();
                }
                analytic[i * 3 + a] = g;
            }
        }
        crate::testing::assert_close(
            "numerical vs analytic gradient",
            &o.gradient,
            &analytic,
            crate::testing::Tolerance::new(2e-2, 2e-3),
        );
    }

    #[test]
    fn eikonal_backward_matches_finite_differences_of_the_loss() {
        // L = Σ (|∇f| - 1)^2 + Σ f^2 through the stencil; check dL/dparams against central
        // differences of the same (f32) loss, at a loose f32 tolerance.
        let b = Backend::cpu();
        // A wider stencil keeps f32 rounding in the numerical gradient small next to the check.
        let f = SdfField::new(SdfFieldConfig {
            grad_step: 1e-2,
            ..small()
        })
        .unwrap();
        let p = f.init(5);
        let x = [0.3f32, -0.2, 0.1, -0.5, 0.4, 0.25, 0.9, 0.0, -0.1];
        let loss = |o: &FieldOutputs| {
            let mut g = FieldOutputGrads {
                sdf: vec![0.0; 3],
                gradient: vec![0.0; 9],
                feature: vec![],
            };
            let mut l = 0f64;
            for i in 0..3 {
                let v = &o.gradient[i * 3..i * 3 + 3];
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                l += ((n - 1.0) as f64).powi(2) + (o.sdf[i] as f64).powi(2);
                for a in 0..3 {
                    g.gradient[i * 3 + a] = 2.0 * (n - 1.0) * v[a] / n;
                }
                g.sdf[i] = 2.0 * o.sdf[i];
            }
            (l, g)
        };
        let (_, dp) = f.value_and_grad(&b, &p, &x, loss).unwrap();
        // Spot-check a spread of parameters.
        let h = 1e-2f32;
        for idx in (0..p.len()).step_by(37) {
            let mut pp = p.clone();
            pp[idx] += h;
            let (lp, _) = f.value_and_grad(&b, &pp, &x, loss).unwrap();
            pp[idx] -= 2.0 * h;
            let (lm, _) = f.value_and_grad(&b, &pp, &x, loss).unwrap();
            let fd = (lp - lm) / (2.0 * h as f64);
            let tol = crate::testing::Tolerance::new(5e-2, 5e-3);
            assert!(
                tol.ok(dp[idx] as f64, fd),
                "param {idx}: analytic {} vs finite difference {fd}",
                dp[idx]
            );
        }
    }
}

#[cfg(test)]
mod grid_tests {
    use super::*;

    /// The hash grid is linear in its table, so `<forward(p), d>` has the exact gradient
    /// `backward_params(d)`: central differences agree up to f32 rounding.
    #[test]
    fn hash_grid_encoder_backward_matches_finite_differences() {
        let enc = PositionEncoder {
            raw_xyz: true,
            active_levels: None,
            encoding: EncodingConfig::HashGrid {
                levels: 3,
                features_per_level: 2,
                log2_table_size: 8,
                base_resolution: 2,
                per_level_scale: 2.0,
                bound: 1.0,
            },
        };
        assert_eq!(enc.out_dim(), 3 + 6);
        let mut rng = crate::util::rng(7);
        let x: Vec<f32> = (0..5 * 3).map(|_| rand::Rng::random_range(&mut rng, -1.2f32..1.2)).collect();
        let d: Vec<f32> =
            (0..5 * enc.out_dim()).map(|_| rand::Rng::random_range(&mut rng, -1.0f32..1.0)).collect();
        let p = enc.init(3);
        let out = enc.forward(&p, &x);
        // Raw xyz leads each row.
        for (row, q) in out.chunks_exact(enc.out_dim()).zip(x.chunks_exact(3)) {
            assert_eq!(&row[..3], q);
        }
        let g = enc.backward_params(&p, &x, &d);
        assert_eq!(g.len(), p.len());
        let obj = |p: &[f32]| -> f64 {
            enc.forward(p, &x).iter().zip(&d).map(|(a, b)| (*a as f64) * (*b as f64)).sum()
        };
        let h = 1e-2f32;
        let touched: Vec<usize> = (0..p.len()).filter(|&i| g[i] != 0.0).take(40).collect();
        assert!(touched.len() >= 10, "the points touch the table");
        for i in touched.into_iter().chain([0, p.len() / 2, p.len() - 1]) {
            let (mut a, mut b) = (p.clone(), p.clone());
            a[i] += h;
            b[i] -= h;
            let fd = (obj(&a) - obj(&b)) / (2.0 * h as f64);
            assert!(
                (fd - g[i] as f64).abs() < 1e-4 + 1e-3 * fd.abs(),
                "param {i}: analytic {} vs fd {fd}",
                g[i]
            );
        }
    }

    #[test]
    fn fast_preset_builds_and_bad_grids_are_refused() {
        let f = SdfField::new(SdfFieldConfig::fast()).unwrap();
        assert_eq!(f.encoder.out_dim(), 3 + 32);
        assert_eq!(f.config.encoding.encoded_dim(), 35);
        assert_eq!(f.mlp.layers[0].in_dim, 35);
        let mut bad = SdfFieldConfig::fast();
        bad.encoding = FieldEncoding::HashGrid {
            levels: 0,
            features_per_level: 2,
            log2_table_size: 19,
            base_resolution: 16,
            growth: 1.4,
        };
        let e = SdfField::new(bad).unwrap_err().to_string();
        assert!(e.contains("levels"), "{e}");
    }
}
