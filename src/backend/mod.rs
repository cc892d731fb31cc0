//! The compute interface: one [`Backend`] value that is either the **cpu** backend
//! (plain Rust + rayon, the reference) or the **wgpu** backend (WGSL kernels).
//!
//! Pattern every kernel family follows (see ARCHITECTURE.md):
//! - data lives in [`Tensor`]s: host `Vec<f32>` on the cpu backend, GPU storage buffers on wgpu;
//! - a family (MLP, encodings, SG shading, grid evaluation...) adds an inherent
//!   `impl Backend { pub fn family_op(&self, ...) -> Result<Tensor, BackendError> }` block in
//!   its own module, which matches on the variant and calls its cpu twin or launches its
//!   WGSL kernel through [`gpu::GpuContext`];
//! - the cpu twin is the reference the WGSL kernel is tested against.

pub mod cpu;
pub mod gpu;

use std::sync::Arc;

pub use cpu::CpuBackend;
pub use gpu::{GpuBuffer, GpuContext, GpuOptions};

/// Which backend the user asked for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// A real GPU through wgpu if there is one, else the cpu backend.
    #[default]
    Auto,
    /// Plain Rust with rayon.
    Cpu,
    /// WGSL kernels through wgpu (also on a software adapter such as lavapipe).
    Wgpu,
}

#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    #[error("no usable GPU adapter: {0}")]
    NoAdapter(String),
    #[error("GPU device request failed: {0}")]
    Device(String),
    #[error("GPU validation error in {label}: {message}")]
    Validation { label: String, message: String },
    #[error("GPU buffer mapping failed: {0}")]
    Map(String),
    #[error("shader {label} does not compile: {message}")]
    Shader { label: String, message: String },
    #[error("{0}")]
    Shape(String),
    #[error("{0}")]
    Config(String),
}

/// The install hint printed when no Vulkan/Metal/DX12 adapter exists.
pub const NO_ADAPTER_HINT: &str = "no Vulkan/Metal/DX12 adapter found; on Debian/Ubuntu install the CPU driver with \
`apt-get install mesa-vulkan-drivers libvulkan1`, or run with `--backend cpu`";

/// A compute backend. Cheap to clone.
#[derive(Clone)]
pub enum Backend {
    Cpu(CpuBackend),
    Gpu(Arc<GpuContext>),
}

impl std::fmt::Debug for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Backend({})", self.describe())
    }
}

impl Backend {
    /// The cpu backend on all cores.
    pub fn cpu() -> Self {
        Backend::Cpu(CpuBackend::new())
    }

    /// Pick a backend. `Auto`: a real (non-software) GPU → wgpu, otherwise cpu (lavapipe is far
    /// slower than vectorised Rust). `Wgpu` accepts software adapters. `adapter` forces an
    /// adapter by index or name substring (also from `PII_ADAPTER`).
    pub fn select(choice: BackendChoice, adapter: Option<&str>) -> Result<Self, BackendError> {
        let env_adapter = std::env::var("PII_ADAPTER").ok();
        let adapter = adapter.map(str::to_owned).or(env_adapter);
        match choice {
            BackendChoice::Cpu => Ok(Self::cpu()),
            BackendChoice::Wgpu => {
                let opts = GpuOptions { adapter, allow_software: true, ..Default::default() };
                Ok(Backend::Gpu(Arc::new(GpuContext::new(&opts)?)))
            }
            BackendChoice::Auto => {
                let opts = GpuOptions { adapter: adapter.clone(), allow_software: adapter.is_some(), ..Default::default() };
                match GpuContext::new(&opts) {
                    Ok(ctx) => Ok(Backend::Gpu(Arc::new(ctx))),
                    Err(e) => {
                        tracing::info!("using the cpu backend ({e})");
                        Ok(Self::cpu())
                    }
                }
            }
        }
    }

    /// A wgpu backend for tests: any adapter, software included, validation on.
    pub fn wgpu_for_tests() -> Result<Self, BackendError> {
        let opts = GpuOptions { allow_software: true, validation: true, ..Default::default() };
        Ok(Backend::Gpu(Arc::new(GpuContext::new(&opts)?)))
    }

    pub fn is_gpu(&self) -> bool {
        matches!(self, Backend::Gpu(_))
    }

    pub fn name(&self) -> &'static str {
        match self {
            Backend::Cpu(_) => "cpu",
            Backend::Gpu(_) => "wgpu",
        }
    }

    /// One line for logs and reports, e.g. `wgpu (NVIDIA H100, Vulkan, DiscreteGpu)`.
    pub fn describe(&self) -> String {
        match self {
            Backend::Cpu(c) => format!("cpu ({} threads)", c.threads()),
            Backend::Gpu(g) => format!("wgpu ({}, {:?}, {:?})", g.info.name, g.info.backend, g.info.device_type),
        }
    }

    pub fn gpu(&self) -> Option<&Arc<GpuContext>> {
        match self {
            Backend::Gpu(g) => Some(g),
            Backend::Cpu(_) => None,
        }
    }

    // ---- tensors -------------------------------------------------------------------------

    pub fn upload(&self, data: &[f32]) -> Tensor {
        match self {
            Backend::Cpu(_) => Tensor::Host(data.to_vec()),
            Backend::Gpu(g) => Tensor::Device(g.upload_f32("tensor", data)),
        }
    }

    pub fn from_vec(&self, data: Vec<f32>) -> Tensor {
        match self {
            Backend::Cpu(_) => Tensor::Host(data),
            Backend::Gpu(g) => Tensor::Device(g.upload_f32("tensor", &data)),
        }
    }

    pub fn zeros(&self, len: usize) -> Tensor {
        match self {
            Backend::Cpu(_) => Tensor::Host(vec![0.0; len]),
            Backend::Gpu(g) => Tensor::Device(g.zeros_f32("zeros", len)),
        }
    }

    /// Copy a tensor to the host (a GPU readback on wgpu).
    pub fn to_vec(&self, t: &Tensor) -> Result<Vec<f32>, BackendError> {
        match (self, t) {
            (_, Tensor::Host(v)) => Ok(v.clone()),
            (Backend::Gpu(g), Tensor::Device(b)) => g.read_f32(b),
            (Backend::Cpu(_), Tensor::Device(_)) => Err(BackendError::Shape("device tensor given to the cpu backend".into())),
        }
    }

    /// [`Backend::to_vec`] of several tensors, with one wait for all of them on wgpu.
    pub fn to_vecs(&self, ts: &[&Tensor]) -> Result<Vec<Vec<f32>>, BackendError> {
        let Backend::Gpu(g) = self else {
            return ts.iter().map(|t| self.to_vec(t)).collect();
        };
        let dev: Vec<&gpu::GpuBuffer> = ts.iter().filter_map(|t| t.device().ok()).collect();
        let mut read = g.read_many::<f32>(&dev)?.into_iter();
        ts.iter()
            .map(|t| match t {
                Tensor::Host(v) => Ok(v.clone()),
                Tensor::Device(_) => read.next().ok_or_else(|| BackendError::Map("readback count".into())),
            })
            .collect()
    }

    /// [`Backend::to_vecs`] of two tensors.
    pub fn to_vec2(&self, a: &Tensor, b: &Tensor) -> Result<(Vec<f32>, Vec<f32>), BackendError> {
        let mut v = self.to_vecs(&[a, b])?.into_iter();
        Ok((v.next().unwrap_or_default(), v.next().unwrap_or_default()))
    }

    /// Block until all submitted GPU work is done (no-op on cpu). Benchmarks call this.
    pub fn sync(&self) -> Result<(), BackendError> {
        match self {
            Backend::Cpu(_) => Ok(()),
            Backend::Gpu(g) => g.wait_idle(),
        }
    }
}

/// A flat f32 tensor on one backend. Shapes are the convention of the operation that takes it
/// (row-major `[n, dim]` everywhere unless a function says otherwise).
#[derive(Debug)]
pub enum Tensor {
    Host(Vec<f32>),
    Device(GpuBuffer),
}

impl Tensor {
    pub fn len(&self) -> usize {
        match self {
            Tensor::Host(v) => v.len(),
            Tensor::Device(b) => b.len,
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The host data; an error on a device tensor.
    pub fn host(&self) -> Result<&[f32], BackendError> {
        match self {
            Tensor::Host(v) => Ok(v),
            Tensor::Device(_) => Err(BackendError::Shape("expected a host tensor, got a device tensor".into())),
        }
    }
    pub fn host_mut(&mut self) -> Result<&mut Vec<f32>, BackendError> {
        match self {
            Tensor::Host(v) => Ok(v),
            Tensor::Device(_) => Err(BackendError::Shape("expected a host tensor, got a device tensor".into())),
        }
    }
    pub fn device(&self) -> Result<&GpuBuffer, BackendError> {
        match self {
            Tensor::Device(b) => Ok(b),
            Tensor::Host(_) => Err(BackendError::Shape("expected a device tensor, got a host tensor".into())),
        }
    }
}
