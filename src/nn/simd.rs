//! Runtime choice of the vector width the cpu backend's elementwise loops are built for.

/// How wide the cpu backend's elementwise loops run (the activations, Adam, the gradient check):
/// the same loop built for baseline x86-64, for AVX2 + FMA (8 f32 lanes) or for AVX-512 (16
/// lanes, and 32 vector registers, so a polynomial's constants stay in registers). Ordered from
/// narrowest to widest. A loop does the same operations in the same order at every level (fused
/// multiply-adds are explicit `mul_add`s), so every level gives the same bits; only the speed
/// differs.
///
/// Each loop has its own pair of `#[target_feature]` wrappers around one `#[inline(always)]`
/// body, dispatched on the level. A shared generic wrapper that runs a closure (`level.run(||
/// body())`) was tried and measured: the closure is not inlined into the wrapper, its loop keeps
/// the baseline build, and `bench nn` fell to 1.0x for the activations and Adam (and the fast
/// field's forward to a fifth of its speed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SimdLevel {
    Scalar,
    Avx2,
    Avx512,
}

impl SimdLevel {
    pub const ALL: [SimdLevel; 3] = [SimdLevel::Scalar, SimdLevel::Avx2, SimdLevel::Avx512];

    /// The widest level this CPU runs (detected once).
    pub fn detected() -> SimdLevel {
        #[cfg(target_arch = "x86_64")]
        {
            static LEVEL: std::sync::OnceLock<SimdLevel> = std::sync::OnceLock::new();
            *LEVEL.get_or_init(|| {
                let avx2 = std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
                let avx512 = std::is_x86_feature_detected!("avx512f")
                    && std::is_x86_feature_detected!("avx512vl")
                    && std::is_x86_feature_detected!("avx512dq");
                match (avx2, avx512) {
                    (true, true) => SimdLevel::Avx512,
                    (true, false) => SimdLevel::Avx2,
                    _ => SimdLevel::Scalar,
                }
            })
        }
        #[cfg(not(target_arch = "x86_64"))]
        SimdLevel::Scalar
    }
}
