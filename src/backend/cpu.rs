//! The cpu backend: plain Rust with rayon. Every kernel family's cpu twin lives beside its
//! WGSL launcher in that family's module; this type only carries the thread pool facts.

/// Marker for the cpu backend. Work runs on rayon's global pool.
#[derive(Clone, Debug, Default)]
pub struct CpuBackend {
    _private: (),
}

impl CpuBackend {
    pub fn new() -> Self {
        Self { _private: () }
    }
    pub fn threads(&self) -> usize {
        rayon::current_num_threads()
    }
}

/// Rows per rayon task for batched point work: big enough to amortise scheduling and let the
/// compiler vectorise the inner loops, small enough to balance over cores.
pub const CHUNK_ROWS: usize = 256;
