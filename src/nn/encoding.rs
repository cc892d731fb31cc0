//! Input encodings: frequency positional encoding (NeRF/IDR) and the multiresolution hash grid
//! (Instant-NGP), forward and backward (parameter and input gradients), on the cpu backend
//! (generic over f32/f64 so gradients can be checked in f64) and in WGSL (`shaders/encoding.wgsl`).
//!
//! Layouts (row-major):
//! - inputs `x`: `[n, in_dim]`;
//! - **frequency** output `[n, out_dim]` with `out_dim = in_dim·(include_input + 2·n_freqs)`, per row
//!   `[x_0..x_{d-1}, sin(2^0·x_0..), cos(2^0·x_0..), sin(2^1·x_0..), cos(2^1·x_0..), ...]`
//!   (the IDR/NeRF embedder order: for each frequency, the sines of every coordinate, then the
//!   cosines; frequencies are 2^k, k = 0..n_freqs-1, with no π factor);
//! - **hash grid** (in_dim = 3) output `[n, levels·F]`, level-major (`out[l·F + f]`); parameters
//!   are one flat vector, level after level, each level `[entries_l, F]` (see [`GridLevel`]).
//!
//! Hash grid level l has `R_l = floor(base_resolution · per_level_scale^l)` cells per axis over the
//! cube `[-bound, bound]^3` ((R_l+1)^3 vertices). A level whose vertices fit in the table
//! (`(R_l+1)^3 <= 2^log2_table_size`) is indexed densely (`i + j·(R+1) + k·(R+1)^2`), otherwise the
//! vertex is hashed: `(i·1 ^ j·2654435761 ^ k·805459861) mod 2^log2_table_size` (wrapping u32).
//! Points outside the cube are clamped onto its surface: the value is the boundary value and the
//! gradient with respect to a clamped coordinate is 0 (NaN inputs are treated as -bound).

use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::backend::cpu::CHUNK_ROWS;
use crate::backend::gpu::{groups_1d, shaders, Access, KernelSpec};
use crate::backend::{Backend, BackendError, Tensor};

/// The WGSL kernel family of this module.
pub const ENCODING_WGSL: &str = include_str!("../../shaders/encoding.wgsl");

/// Spatial-hash primes (Instant-NGP).
pub const HASH_PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// An input encoding.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum EncodingConfig {
    /// `[x, sin(2^k x), cos(2^k x)]`, k < n_freqs (order in the module docs). No parameters.
    Frequency { n_freqs: u32, include_input: bool },
    /// Multiresolution hash grid over `[-bound, bound]^3`.
    HashGrid {
        levels: u32,
        features_per_level: u32,
        log2_table_size: u32,
        base_resolution: u32,
        per_level_scale: f32,
        /// Half-size of the cube `[-bound, bound]^3` the grid covers.
        bound: f32,
    },
}

/// One hash-grid level: cells per axis, first table entry in the flat parameter vector (in
/// entries of F features), number of entries, and whether it is densely indexed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GridLevel {
    pub resolution: u32,
    pub offset: u32,
    pub entries: u32,
    pub dense: bool,
}

impl EncodingConfig {
    /// The paper's SDF encoding: PE with 6 frequencies, input included.
    pub fn frequency(n_freqs: u32) -> Self {
        EncodingConfig::Frequency {
            n_freqs,
            include_input: true,
        }
    }

    /// Instant-NGP defaults: 16 levels × 2 features, 2^19 entries, base 16, finest 2048 over [-1, 1]^3.
    pub fn hash_grid_default() -> Self {
        let levels = 16;
        let per_level_scale = (2048.0f64 / 16.0).powf(1.0 / (levels as f64 - 1.0)) as f32;
        EncodingConfig::HashGrid {
            levels,
            features_per_level: 2,
            log2_table_size: 19,
            base_resolution: 16,
            per_level_scale,
            bound: 1.0,
        }
    }

    /// Check the configuration for inputs of `in_dim` coordinates. Clear messages, no panics later.
    pub fn validate(&self, in_dim: usize) -> Result<(), BackendError> {
        let bad = |m: String| Err(BackendError::Config(format!("encoding: {m}")));
        match *self {
            EncodingConfig::Frequency { n_freqs, .. } => {
                if in_dim == 0 {
                    return bad("frequency encoding of 0-dimensional inputs".into());
                }
                if n_freqs > 24 {
                    return bad(format!(
                        "n_freqs = {n_freqs} (at most 24: 2^k·x loses all precision beyond)"
                    ));
                }
                if self.out_dim(in_dim) == 0 {
                    return bad("frequency encoding with 0 frequencies and include_input = false has no output".into());
                }
            }
            EncodingConfig::HashGrid {
                levels,
                features_per_level,
                log2_table_size,
                base_resolution,
                per_level_scale,
                bound,
            } => {
                if in_dim != 3 {
                    return bad(format!(
                        "the hash grid encodes 3-D points, got {in_dim}-D inputs"
                    ));
                }
                if !(1..=32).contains(&levels) {
                    return bad(format!("hash grid levels = {levels} (1..=32)"));
                }
                if !(1..=8).contains(&features_per_level) {
                    return bad(format!(
                        "hash grid features_per_level = {features_per_level} (1..=8)"
                    ));
                }
                if !(4..=24).contains(&log2_table_size) {
                    return bad(format!(
                        "hash grid log2_table_size = {log2_table_size} (4..=24)"
                    ));
                }
                if base_resolution == 0 {
                    return bad("hash grid base_resolution = 0".into());
                }
                if !(per_level_scale.is_finite() && per_level_scale >= 1.0) {
                    return bad(format!(
                        "hash grid per_level_scale = {per_level_scale} (finite, >= 1)"
                    ));
                }
                if !(bound.is_finite() && bound > 0.0) {
                    return bad(format!("hash grid bound = {bound} (finite, > 0)"));
                }
                let finest =
                    base_resolution as f64 * (per_level_scale as f64).powi(levels as i32 - 1);
                if finest > (1u64 << 24) as f64 {
                    return bad(format!(
                        "hash grid finest resolution {finest:.0} exceeds 2^24 cells per axis"
                    ));
                }
                if self.num_params() as u64 > u32::MAX as u64 / 2 {
                    return bad(format!(
                        "hash grid has {} parameters (too many for 32-bit indexing)",
                        self.num_params()
                    ));
                }
            }
        }
        Ok(())
    }

    /// Width of the encoded output for `in_dim`-dimensional inputs.
    pub fn out_dim(&self, in_dim: usize) -> usize {
        match *self {
            EncodingConfig::Frequency {
                n_freqs,
                include_input,
            } => in_dim * (include_input as usize + 2 * n_freqs as usize),
            EncodingConfig::HashGrid {
                levels,
                features_per_level,
                ..
            } => (levels * features_per_level) as usize,
        }
    }

    /// The hash grid's levels (empty for the frequency encoding).
    pub fn grid_levels(&self) -> Vec<GridLevel> {
        let EncodingConfig::HashGrid {
            levels,
            log2_table_size,
            base_resolution,
            per_level_scale,
            ..
        } = *self
        else {
            return Vec::new();
        };
        let table = 1u64 << log2_table_size.min(31);
        let mut offset = 0u64;
        (0..levels)
            .map(|l| {
                let r = (base_resolution as f64 * (per_level_scale as f64).powi(l as i32)).floor();
                let resolution = r.clamp(1.0, (1u64 << 24) as f64) as u32;
                let verts = (resolution as u64 + 1).pow(3);
                let dense = verts <= table;
                let entries = if dense { verts } else { table };
                let lvl = GridLevel {
                    resolution,
                    offset: offset.min(u32::MAX as u64) as u32,
                    entries: entries as u32,
                    dense,
                };
                offset += entries;
                lvl
            })
            .collect()
    }

    /// Number of trainable parameters (0 for the frequency encoding).
    pub fn num_params(&self) -> usize {
        match *self {
            EncodingConfig::Frequency { .. } => 0,
            EncodingConfig::HashGrid {
                features_per_level, ..
            } => {
                self.grid_levels()
                    .iter()
                    .map(|l| l.entries as usize)
                    .sum::<usize>()
                    * features_per_level as usize
            }
        }
    }

    /// Initial parameters: hash grid entries uniform in (-1e-4, 1e-4) from a seeded RNG.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        use rand::Rng;
        let mut rng = crate::util::rng(seed);
        (0..self.num_params())
            .map(|_| rng.random_range(-1e-4f32..1e-4f32))
            .collect()
    }
}

// ---- generic scalar for the cpu twins -------------------------------------------------------

/// The scalar type the cpu twins are generic over: f32 (the backend) and f64 (gradient checks).
pub trait Real:
    Copy
    + Send
    + Sync
    + PartialOrd
    + Default
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
{
    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
    fn sin(self) -> Self;
    fn cos(self) -> Self;
    /// The slice as f32 when `Self` is f32 (the hash grid's AVX2 path is f32 only).
    fn as_f32(s: &[Self]) -> Option<&[f32]>;
    /// An f32 vector as `Self` (the identity for f32).
    fn from_f32s(v: Vec<f32>) -> Vec<Self>;
}

impl Real for f32 {
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
    fn sin(self) -> Self {
        f32::sin(self)
    }
    fn cos(self) -> Self {
        f32::cos(self)
    }
    fn as_f32(s: &[Self]) -> Option<&[f32]> {
        Some(s)
    }
    fn from_f32s(v: Vec<f32>) -> Vec<Self> {
        v
    }
}

impl Real for f64 {
    fn from_f64(v: f64) -> Self {
        v
    }
    fn to_f64(self) -> f64 {
        self
    }
    fn sin(self) -> Self {
        f64::sin(self)
    }
    fn cos(self) -> Self {
        f64::cos(self)
    }
    fn as_f32(_: &[Self]) -> Option<&[f32]> {
        None
    }
    fn from_f32s(v: Vec<f32>) -> Vec<Self> {
        v.into_iter().map(f64::from).collect()
    }
}

// ---- frequency encoding (cpu) ----------------------------------------------------------------

/// Frequency encoding of `x` `[n, in_dim]` → `[n, out_dim]` (order in the module docs).
pub fn frequency_forward_cpu<T: Real>(
    n_freqs: u32,
    include_input: bool,
    x: &[T],
    in_dim: usize,
) -> Vec<T> {
    let od = in_dim * (include_input as usize + 2 * n_freqs as usize);
    let n = x.len() / in_dim.max(1);
    let mut out = vec![T::default(); n * od];
    if od == 0 {
        return out;
    }
    out.par_chunks_mut(CHUNK_ROWS * od)
        .zip(x.par_chunks(CHUNK_ROWS * in_dim))
        .for_each(|(o, xs)| {
            for (orow, xrow) in o.chunks_exact_mut(od).zip(xs.chunks_exact(in_dim)) {
                let mut c = 0;
                if include_input {
                    orow[..in_dim].copy_from_slice(xrow);
                    c = in_dim;
                }
                for k in 0..n_freqs {
                    let f = T::from_f64((1u64 << k) as f64);
                    for d in 0..in_dim {
                        let a = f * xrow[d];
                        orow[c + d] = a.sin();
                        orow[c + in_dim + d] = a.cos();
                    }
                    c += 2 * in_dim;
                }
            }
        });
    out
}

/// d_x of the frequency encoding given `d_out` `[n, out_dim]`.
pub fn frequency_backward_cpu<T: Real>(
    n_freqs: u32,
    include_input: bool,
    x: &[T],
    in_dim: usize,
    d_out: &[T],
) -> Vec<T> {
    let od = in_dim * (include_input as usize + 2 * n_freqs as usize);
    let mut dx = vec![T::default(); x.len()];
    if od == 0 || in_dim == 0 {
        return dx;
    }
    dx.par_chunks_mut(CHUNK_ROWS * in_dim)
        .zip(x.par_chunks(CHUNK_ROWS * in_dim))
        .zip(d_out.par_chunks(CHUNK_ROWS * od))
        .for_each(|((dxs, xs), dos)| {
            for ((dxrow, xrow), dorow) in dxs
                .chunks_exact_mut(in_dim)
                .zip(xs.chunks_exact(in_dim))
                .zip(dos.chunks_exact(od))
            {
                let mut c = 0;
                for d in 0..in_dim {
                    dxrow[d] = if include_input {
                        dorow[d]
                    } else {
                        T::default()
                    };
                }
                if include_input {
                    c = in_dim;
                }
                for k in 0..n_freqs {
                    let f = T::from_f64((1u64 << k) as f64);
                    for d in 0..in_dim {
                        let a = f * xrow[d];
                        dxrow[d] += f * (a.cos() * dorow[c + d] - a.sin() * dorow[c + in_dim + d]);
                    }
                    c += 2 * in_dim;
                }
            }
        });
    dx
}

// ---- hash grid (cpu) -------------------------------------------------------------------------

#[cfg(target_arch = "x86_64")]
mod grid_avx2;

/// Where a point falls in one level: cell corner, fractional position, and whether each
/// coordinate is inside the cube (clamped coordinates get no gradient).
struct Cell<T> {
    base: [u32; 3],
    frac: [T; 3],
    inside: [bool; 3],
}

#[inline(always)]
fn locate<T: Real>(p: [T; 3], bound: T, inv_2b: T, res: u32) -> Cell<T> {
    let zero = T::default();
    let one = T::from_f64(1.0);
    let r = T::from_f64(res as f64);
    let mut cell = Cell {
        base: [0; 3],
        frac: [zero; 3],
        inside: [true; 3],
    };
    for (d, &pd) in p.iter().enumerate() {
        let mut u = (pd + bound) * inv_2b;
        // False for NaN too: NaN is clamped to the low face.
        let inside = u > zero && u < one;
        if !inside {
            u = if u >= one { one } else { zero };
            cell.inside[d] = false;
        }
        let pos = u * r;
        // pos >= 0, so truncation is floor.
        let i = (pos.to_f64() as u32).min(res - 1);
        cell.base[d] = i;
        cell.frac[d] = pos - T::from_f64(i as f64);
    }
    cell
}

/// Table entry of a vertex in a level (relative to the level's offset).
#[inline(always)]
pub fn vertex_index(lvl: &GridLevel, v: [u32; 3], table_mask: u32) -> u32 {
    if lvl.dense {
        let s = lvl.resolution + 1;
        v[0] + v[1] * s + v[2] * s * s
    } else {
        (v[0].wrapping_mul(HASH_PRIMES[0])
            ^ v[1].wrapping_mul(HASH_PRIMES[1])
            ^ v[2].wrapping_mul(HASH_PRIMES[2]))
            & table_mask
    }
}

/// The 8 corners of the cell that holds a point in one level. Corner `c` has the offsets
/// `(c & 1, (c >> 1) & 1, c >> 2)`; its trilinear weight is `(a[0]·a[1])·a[2]` with `a[d]` the
/// axis factor `1 − frac` or `frac`, the order the WGSL kernel multiplies in.
struct Corners<T> {
    /// Entry index in the flat table (the level's offset included).
    idx: [usize; 8],
    w: [T; 8],
    /// Axis factors `[1 − frac, frac]` per coordinate.
    axis: [[T; 2]; 3],
    /// Whether each coordinate is inside the cube (clamped coordinates get no gradient).
    inside: [bool; 3],
}

impl<T: Real> Corners<T> {
    /// The point's cell in `lvl`. The table index terms are formed once per axis (two per axis,
    /// not eight per corner) and combined as [`vertex_index`] does: the same integers.
    #[inline(always)]
    fn of(lvl: &GridLevel, p: [T; 3], bound: T, inv_2b: T, table_mask: u32) -> Self {
        let cell = locate(p, bound, inv_2b, lvl.resolution);
        let one = T::from_f64(1.0);
        let axis = cell.frac.map(|f| [one - f, f]);
        let [bx, by, bz] = cell.base;
        let terms = |scale: [u32; 3]| {
            [
                [bx.wrapping_mul(scale[0]), (bx + 1).wrapping_mul(scale[0])],
                [by.wrapping_mul(scale[1]), (by + 1).wrapping_mul(scale[1])],
                [bz.wrapping_mul(scale[2]), (bz + 1).wrapping_mul(scale[2])],
            ]
        };
        let mut idx = [0usize; 8];
        if lvl.dense {
            let s = lvl.resolution + 1;
            let [tx, ty, tz] = terms([1, s, s * s]);
            for (c, i) in idx.iter_mut().enumerate() {
                *i = (lvl.offset + tx[c & 1] + ty[(c >> 1) & 1] + tz[c >> 2]) as usize;
            }
        } else {
            let [tx, ty, tz] = terms(HASH_PRIMES);
            for (c, i) in idx.iter_mut().enumerate() {
                *i = (lvl.offset + ((tx[c & 1] ^ ty[(c >> 1) & 1] ^ tz[c >> 2]) & table_mask)) as usize;
            }
        }
        let xy = [
            axis[0][0] * axis[1][0],
            axis[0][1] * axis[1][0],
            axis[0][0] * axis[1][1],
            axis[0][1] * axis[1][1],
        ];
        let w = std::array::from_fn(|c| xy[c & 3] * axis[2][c >> 2]);
        Corners { idx, w, axis, inside: cell.inside }
    }

    /// d weight / d frac of each corner: the weight with the axis factor of `d` replaced by ±1.
    #[inline(always)]
    fn dw(&self) -> [[T; 3]; 8] {
        let a = &self.axis;
        let signed = |v: T, bit: usize| if bit == 1 { v } else { -v };
        std::array::from_fn(|c| {
            let (i, j, k) = (c & 1, (c >> 1) & 1, c >> 2);
            [
                signed(a[1][j] * a[2][k], i),
                signed(a[0][i] * a[2][k], j),
                signed(a[0][i] * a[1][j], k),
            ]
        })
    }
}

/// Geometry of the grid the cpu twins and the WGSL launcher share.
pub(crate) struct GridGeom {
    levels: Vec<GridLevel>,
    f: usize,
    table_mask: u32,
    bound: f64,
}

impl GridGeom {
    /// Half-size of the cube `[-bound, bound]^3` the grid covers (as configured, f32).
    pub(crate) fn bound(&self) -> f32 {
        self.bound as f32
    }

    /// A flat parameter-sized vector cut into its levels' tables (each level owns a disjoint
    /// slice, so the levels' gradients can be scattered in parallel).
    fn level_tables_mut<'a, T>(&self, flat: &'a mut [T]) -> Vec<&'a mut [T]> {
        let mut tables = Vec::with_capacity(self.levels.len());
        let mut rest = flat;
        for lvl in &self.levels {
            let (head, tail) = rest.split_at_mut(lvl.entries as usize * self.f);
            tables.push(head);
            rest = tail;
        }
        tables
    }
}

pub(crate) fn grid_geom(cfg: &EncodingConfig) -> Option<GridGeom> {
    match *cfg {
        EncodingConfig::HashGrid {
            features_per_level,
            log2_table_size,
            bound,
            ..
        } => Some(GridGeom {
            levels: cfg.grid_levels(),
            f: features_per_level as usize,
            table_mask: ((1u64 << log2_table_size) - 1) as u32,
            bound: bound as f64,
        }),
        EncodingConfig::Frequency { .. } => None,
    }
}

fn point<T: Real>(x: &[T]) -> [T; 3] {
    [x[0], x[1], x[2]]
}

/// Rows per parallel chunk of the hash-grid twins: large, so that a level's table is read by
/// many points in turn, yet at least two chunks per thread; a chunk's outputs stay in L2.
fn grid_chunk_rows(n: usize) -> usize {
    n.div_ceil(2 * rayon::current_num_threads()).clamp(CHUNK_ROWS, 4096)
}

/// Hash grid forward on the cpu: `x` `[n, 3]` → `[n, levels·F]`. `cfg` must be a validated hash grid.
pub fn hash_grid_forward_cpu<T: Real>(cfg: &EncodingConfig, params: &[T], x: &[T]) -> Vec<T> {
    let Some(g) = grid_geom(cfg) else {
        return Vec::new();
    };
    #[cfg(target_arch = "x86_64")]
    if let (Some(p), Some(x)) = (T::as_f32(params), T::as_f32(x)) {
        if grid_avx2::available() && grid_avx2::suits(&g, cfg.num_params(), Some(p.len())) {
            // SAFETY: the CPU has AVX2 and the grid and parameters suit the lane code (checked).
            return T::from_f32s(unsafe { grid_avx2::forward(&g, p, x) });
        }
    }
    hash_grid_forward_scalar(&g, params, x)
}

/// The grid of `cfg` where its f32 twins run the AVX2 lane code on this CPU, None elsewhere
/// (`bench nn` times the lane code against the scalar twin on it).
pub(crate) fn hash_grid_lanes(cfg: &EncodingConfig) -> Option<GridGeom> {
    #[cfg(target_arch = "x86_64")]
    if let Some(g) = grid_geom(cfg) {
        if grid_avx2::available() && grid_avx2::suits(&g, cfg.num_params(), None) {
            return Some(g);
        }
    }
    None
}

/// The scalar hash grid forward (any [`Real`]; the reference of the AVX2 path).
pub(crate) fn hash_grid_forward_scalar<T: Real>(g: &GridGeom, params: &[T], x: &[T]) -> Vec<T> {
    let od = g.levels.len() * g.f;
    let n = x.len() / 3;
    let (bound, inv_2b) = (T::from_f64(g.bound), T::from_f64(0.5 / g.bound));
    let mut out = vec![T::default(); n * od];
    // Level-major inside each chunk: one level's table (a few MB at 2^19 entries) stays in the
    // last-level cache while the chunk's points read it, where point-major order walks all the
    // levels' tables (tens of MB) per point. Each output sums its corners in the same order.
    let rows = grid_chunk_rows(n);
    out.par_chunks_mut(rows * od)
        .zip(x.par_chunks(rows * 3))
        .for_each(|(o, xs)| {
            for (l, lvl) in g.levels.iter().enumerate() {
                for (orow, xrow) in o.chunks_exact_mut(od).zip(xs.chunks_exact(3)) {
                    let k = Corners::of(lvl, point(xrow), bound, inv_2b, g.table_mask);
                    let acc = &mut orow[l * g.f..(l + 1) * g.f];
                    if let [a0, a1] = acc {
                        // Two features per level (every preset): accumulate in registers.
                        let (mut s0, mut s1) = (*a0, *a1);
                        for (&idx, &w) in k.idx.iter().zip(&k.w) {
                            let e = &params[idx * 2..idx * 2 + 2];
                            s0 += w * e[0];
                            s1 += w * e[1];
                        }
                        (*a0, *a1) = (s0, s1);
                        continue;
                    }
                    for (&idx, &w) in k.idx.iter().zip(&k.w) {
                        for (f, a) in acc.iter_mut().enumerate() {
                            *a += w * params[idx * g.f + f];
                        }
                    }
                }
            }
        });
    out
}

/// Hash grid parameter gradient: `d_params` (len num_params) from `d_out` `[n, levels·F]`.
/// Parallel over levels (each level owns a disjoint slice of the table), so it is deterministic.
pub fn hash_grid_backward_params_cpu<T: Real>(
    cfg: &EncodingConfig,
    x: &[T],
    d_out: &[T],
) -> Vec<T> {
    let Some(g) = grid_geom(cfg) else {
        return Vec::new();
    };
    #[cfg(target_arch = "x86_64")]
    if let (Some(x), Some(d)) = (T::as_f32(x), T::as_f32(d_out)) {
        if grid_avx2::available() && grid_avx2::suits(&g, cfg.num_params(), None) {
            // SAFETY: the CPU has AVX2 and the grid suits the lane code (checked).
            return T::from_f32s(unsafe { grid_avx2::backward_params(&g, cfg.num_params(), x, d) });
        }
    }
    hash_grid_backward_params_scalar(&g, cfg.num_params(), x, d_out)
}

/// The scalar hash grid parameter gradient (the reference of the AVX2 path).
pub(crate) fn hash_grid_backward_params_scalar<T: Real>(g: &GridGeom, num_params: usize, x: &[T], d_out: &[T]) -> Vec<T> {
    let od = g.levels.len() * g.f;
    let (bound, inv_2b) = (T::from_f64(g.bound), T::from_f64(0.5 / g.bound));
    let mut d_params = vec![T::default(); num_params];
    g.level_tables_mut(&mut d_params).into_par_iter().enumerate().for_each(|(l, dp)| {
        let lvl = &g.levels[l];
        let base = lvl.offset as usize * g.f;
        for (xrow, dorow) in x.chunks_exact(3).zip(d_out.chunks_exact(od)) {
            let k = Corners::of(lvl, point(xrow), bound, inv_2b, g.table_mask);
            let dol = &dorow[l * g.f..(l + 1) * g.f];
            for (&idx, &w) in k.idx.iter().zip(&k.w) {
                let e = idx * g.f - base;
                for f in 0..g.f {
                    dp[e + f] += w * dol[f];
                }
            }
        }
    });
    d_params
}

/// Hash grid input gradient `d_x` `[n, 3]` from `d_out` (0 for clamped coordinates).
pub fn hash_grid_backward_x_cpu<T: Real>(
    cfg: &EncodingConfig,
    params: &[T],
    x: &[T],
    d_out: &[T],
) -> Vec<T> {
    let Some(g) = grid_geom(cfg) else {
        return Vec::new();
    };
    #[cfg(target_arch = "x86_64")]
    if let (Some(p), Some(x), Some(d)) = (T::as_f32(params), T::as_f32(x), T::as_f32(d_out)) {
        if grid_avx2::available() && grid_avx2::suits(&g, cfg.num_params(), Some(p.len())) {
            // SAFETY: the CPU has AVX2 and the grid and parameters suit the lane code (checked).
            return T::from_f32s(unsafe { grid_avx2::backward_x(&g, p, x, d) });
        }
    }
    hash_grid_backward_x_scalar(&g, params, x, d_out)
}

/// The scalar hash grid input gradient (the reference of the AVX2 path).
pub(crate) fn hash_grid_backward_x_scalar<T: Real>(g: &GridGeom, params: &[T], x: &[T], d_out: &[T]) -> Vec<T> {
    let od = g.levels.len() * g.f;
    let (bound, inv_2b) = (T::from_f64(g.bound), T::from_f64(0.5 / g.bound));
    let mut dx = vec![T::default(); x.len()];
    // Level-major inside each chunk, as the forward; each row still adds its levels in order.
    let rows = grid_chunk_rows(x.len() / 3);
    dx.par_chunks_mut(rows * 3)
        .zip(x.par_chunks(rows * 3))
        .zip(d_out.par_chunks(rows * od))
        .for_each(|((dxs, xs), dos)| {
            for (l, lvl) in g.levels.iter().enumerate() {
                for ((dxrow, xrow), dorow) in dxs
                    .chunks_exact_mut(3)
                    .zip(xs.chunks_exact(3))
                    .zip(dos.chunks_exact(od))
                {
                    let k = Corners::of(lvl, point(xrow), bound, inv_2b, g.table_mask);
                    let dpos = T::from_f64(lvl.resolution as f64) * inv_2b;
                    let dol = &dorow[l * g.f..(l + 1) * g.f];
                    for (&idx, dw) in k.idx.iter().zip(k.dw()) {
                        let mut s = T::default();
                        for f in 0..g.f {
                            s += dol[f] * params[idx * g.f + f];
                        }
                        for d in 0..3 {
                            if k.inside[d] {
                                dxrow[d] += s * dw[d] * dpos;
                            }
                        }
                    }
                }
            }
        });
    dx
}

/// Encoding forward for any [`Real`] on the cpu (used by the backend and by f64 gradient checks).
pub fn encoding_forward_cpu<T: Real>(
    cfg: &EncodingConfig,
    params: &[T],
    x: &[T],
    in_dim: usize,
) -> Vec<T> {
    match *cfg {
        EncodingConfig::Frequency {
            n_freqs,
            include_input,
        } => frequency_forward_cpu(n_freqs, include_input, x, in_dim),
        EncodingConfig::HashGrid { .. } => hash_grid_forward_cpu(cfg, params, x),
    }
}

/// Encoding backward for any [`Real`] on the cpu: (d_params, d_x if wanted).
pub fn encoding_backward_cpu<T: Real>(
    cfg: &EncodingConfig,
    params: &[T],
    x: &[T],
    in_dim: usize,
    d_out: &[T],
    want_dx: bool,
) -> (Vec<T>, Option<Vec<T>>) {
    match *cfg {
        EncodingConfig::Frequency {
            n_freqs,
            include_input,
        } => (
            Vec::new(),
            want_dx.then(|| frequency_backward_cpu(n_freqs, include_input, x, in_dim, d_out)),
        ),
        EncodingConfig::HashGrid { .. } => (
            hash_grid_backward_params_cpu(cfg, x, d_out),
            want_dx.then(|| hash_grid_backward_x_cpu(cfg, params, x, d_out)),
        ),
    }
}

// ---- WGSL launcher ---------------------------------------------------------------------------

/// Mirrors `EncParams` in `shaders/encoding.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct EncParams {
    /// Points.
    pub n: u32,
    /// Input dimension (frequency) / 3 (hash grid).
    pub in_dim: u32,
    /// Frequencies (frequency) / levels (hash grid).
    pub n_freqs_or_levels: u32,
    /// Include the input (frequency) / features per level (hash grid).
    pub include_input_or_features: u32,
    pub out_dim: u32,
    pub table_mask: u32,
    pub bound: f32,
    pub inv_2b: f32,
}
const _: () = assert!(std::mem::size_of::<EncParams>() == 32);

/// Per-level table in a storage buffer: mirrors `GridLevelGpu` in `shaders/encoding.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GridLevelGpu {
    pub resolution: u32,
    pub offset: u32,
    pub entries: u32,
    pub dense: u32,
}
const _: () = assert!(std::mem::size_of::<GridLevelGpu>() == 16);

const WG: u32 = 64;

fn check_shapes(
    cfg: &EncodingConfig,
    params: &Tensor,
    x: &Tensor,
    n: usize,
    d_out: Option<&Tensor>,
) -> Result<usize, BackendError> {
    if n == 0 {
        if !x.is_empty() {
            return Err(BackendError::Shape(format!(
                "encoding: n = 0 but x has {} values",
                x.len()
            )));
        }
        return Ok(match cfg {
            EncodingConfig::HashGrid { .. } => 3,
            EncodingConfig::Frequency { .. } => 1,
        });
    }
    if x.len() % n != 0 {
        return Err(BackendError::Shape(format!(
            "encoding: x has {} values, not a multiple of n = {n}",
            x.len()
        )));
    }
    let in_dim = x.len() / n;
    cfg.validate(in_dim)?;
    if params.len() != cfg.num_params() {
        // The frequency encoding takes an empty (or any placeholder) tensor only if it is empty.
        return Err(BackendError::Shape(format!(
            "encoding: params have {} values, the configuration needs {}",
            params.len(),
            cfg.num_params()
        )));
    }
    if let Some(d) = d_out {
        let want = n * cfg.out_dim(in_dim);
        if d.len() != want {
            return Err(BackendError::Shape(format!(
                "encoding: d_out has {} values, expected n·out_dim = {want}",
                d.len()
            )));
        }
    }
    if n.saturating_mul(cfg.out_dim(in_dim)) > u32::MAX as usize {
        return Err(BackendError::Shape(format!(
            "encoding: batch of {n} points is too large for 32-bit indexing"
        )));
    }
    Ok(in_dim)
}

fn enc_params(cfg: &EncodingConfig, n: usize, in_dim: usize) -> EncParams {
    match *cfg {
        EncodingConfig::Frequency {
            n_freqs,
            include_input,
        } => EncParams {
            n: n as u32,
            in_dim: in_dim as u32,
            n_freqs_or_levels: n_freqs,
            include_input_or_features: include_input as u32,
            out_dim: cfg.out_dim(in_dim) as u32,
            table_mask: 0,
            bound: 0.0,
            inv_2b: 0.0,
        },
        EncodingConfig::HashGrid {
            levels,
            features_per_level,
            log2_table_size,
            bound,
            ..
        } => EncParams {
            n: n as u32,
            in_dim: 3,
            n_freqs_or_levels: levels,
            include_input_or_features: features_per_level,
            out_dim: cfg.out_dim(3) as u32,
            table_mask: ((1u64 << log2_table_size) - 1) as u32,
            bound,
            inv_2b: (0.5 / bound as f64) as f32,
        },
    }
}

fn level_table(cfg: &EncodingConfig) -> Vec<GridLevelGpu> {
    let mut t: Vec<GridLevelGpu> = cfg
        .grid_levels()
        .iter()
        .map(|l| GridLevelGpu {
            resolution: l.resolution,
            offset: l.offset,
            entries: l.entries,
            dense: l.dense as u32,
        })
        .collect();
    if t.is_empty() {
        t.push(GridLevelGpu {
            resolution: 1,
            offset: 0,
            entries: 0,
            dense: 1,
        });
    }
    t
}

impl Backend {
    /// Encode `x` (`[n, in_dim]`, in_dim = x.len()/n) → `[n, out_dim]`. `params` has
    /// `cfg.num_params()` values (an empty tensor for the frequency encoding).
    pub fn encoding_forward(
        &self,
        cfg: &EncodingConfig,
        params: &Tensor,
        x: &Tensor,
        n: usize,
    ) -> Result<Tensor, BackendError> {
        let in_dim = check_shapes(cfg, params, x, n, None)?;
        if n == 0 {
            return Ok(self.zeros(0));
        }
        match self {
            Backend::Cpu(_) => Ok(Tensor::Host(encoding_forward_cpu(
                cfg,
                params.host()?,
                x.host()?,
                in_dim,
            ))),
            Backend::Gpu(g) => {
                let p = enc_params(cfg, n, in_dim);
                let out = g.zeros_f32("encoding.out", n * cfg.out_dim(in_dim));
                let src = shaders::with_lib(ENCODING_WGSL);
                match cfg {
                    EncodingConfig::Frequency { .. } => {
                        let k = g.kernel(
                            "encoding",
                            &src,
                            "freq_forward",
                            &KernelSpec::new(true, &[Access::Read, Access::ReadWrite]),
                        )?;
                        g.dispatch(
                            &k,
                            Some(bytemuck::bytes_of(&p)),
                            &[x.device()?.into(), (&out).into()],
                            groups_1d(n * in_dim, WG),
                        )?;
                    }
                    EncodingConfig::HashGrid { levels, .. } => {
                        let lv = g.upload("encoding.levels", &level_table(cfg));
                        let spec = KernelSpec::new(
                            true,
                            &[Access::Read, Access::Read, Access::Read, Access::ReadWrite],
                        );
                        let k = g.kernel("encoding", &src, "grid_forward", &spec)?;
                        let binds = [
                            (&lv).into(),
                            params.device()?.into(),
                            x.device()?.into(),
                            (&out).into(),
                        ];
                        g.dispatch(
                            &k,
                            Some(bytemuck::bytes_of(&p)),
                            &binds,
                            groups_1d(n * *levels as usize, WG),
                        )?;
                    }
                }
                Ok(Tensor::Device(out))
            }
        }
    }

    /// Backward of [`Backend::encoding_forward`]: `d_params` (len `num_params`, empty for the
    /// frequency encoding) and, if `want_dx`, `d_x` `[n, in_dim]`. The WGSL hash-grid parameter
    /// gradient is scattered with float atomics (a CAS loop), so its summation order varies.
    pub fn encoding_backward(
        &self,
        cfg: &EncodingConfig,
        params: &Tensor,
        x: &Tensor,
        n: usize,
        d_out: &Tensor,
        want_dx: bool,
    ) -> Result<(Tensor, Option<Tensor>), BackendError> {
        let in_dim = check_shapes(cfg, params, x, n, Some(d_out))?;
        if n == 0 {
            return Ok((self.zeros(cfg.num_params()), want_dx.then(|| self.zeros(0))));
        }
        match self {
            Backend::Cpu(_) => {
                let (dp, dx) = encoding_backward_cpu(
                    cfg,
                    params.host()?,
                    x.host()?,
                    in_dim,
                    d_out.host()?,
                    want_dx,
                );
                Ok((Tensor::Host(dp), dx.map(Tensor::Host)))
            }
            Backend::Gpu(g) => {
                let p = enc_params(cfg, n, in_dim);
                let src = shaders::with_lib(ENCODING_WGSL);
                let ub = bytemuck::bytes_of(&p);
                match cfg {
                    EncodingConfig::Frequency { .. } => {
                        let dp = g.zeros_f32("encoding.d_params", 0);
                        if !want_dx {
                            return Ok((Tensor::Device(dp), None));
                        }
                        let dx = g.zeros_f32("encoding.d_x", n * in_dim);
                        let spec = KernelSpec::new(
                            true,
                            &[Access::Read, Access::ReadWrite, Access::ReadWrite],
                        );
                        let k = g.kernel("encoding", &src, "freq_backward", &spec)?;
                        let binds = [x.device()?.into(), d_out.device()?.into(), (&dx).into()];
                        g.dispatch(&k, Some(ub), &binds, groups_1d(n * in_dim, WG))?;
                        Ok((Tensor::Device(dp), Some(Tensor::Device(dx))))
                    }
                    EncodingConfig::HashGrid { levels, .. } => {
                        let lv = g.upload("encoding.levels", &level_table(cfg));
                        let dp = g.zeros_f32("encoding.d_params", cfg.num_params());
                        let mut batch = g.batch("encoding.backward");
                        let spec = KernelSpec::new(
                            true,
                            &[
                                Access::Read,
                                Access::Read,
                                Access::Read,
                                Access::ReadWrite,
                                Access::ReadWrite,
                            ],
                        );
                        let kp = g.kernel("encoding", &src, "grid_backward_params", &spec)?;
                        let binds = [
                            (&lv).into(),
                            params.device()?.into(),
                            x.device()?.into(),
                            d_out.device()?.into(),
                            (&dp).into(),
                        ];
                        batch.dispatch(
                            &kp,
                            Some(ub),
                            &binds,
                            groups_1d(n * *levels as usize, WG),
                        )?;
                        let dx = if want_dx {
                            let dx = g.zeros_f32("encoding.d_x", n * 3);
                            let kx = g.kernel("encoding", &src, "grid_backward_x", &spec)?;
                            let binds = [
                                (&lv).into(),
                                params.device()?.into(),
                                x.device()?.into(),
                                d_out.device()?.into(),
                                (&dx).into(),
                            ];
                            batch.dispatch(&kx, Some(ub), &binds, groups_1d(n, WG))?;
                            Some(Tensor::Device(dx))
                        } else {
                            None
                        };
                        batch.submit()?;
                        Ok((Tensor::Device(dp), dx))
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vertex_indices_follow_the_instant_ngp_rules() {
        let dense = GridLevel {
            resolution: 4,
            offset: 0,
            entries: 125,
            dense: true,
        };
        assert_eq!(vertex_index(&dense, [1, 2, 3], 1023), 1 + 2 * 5 + 3 * 25);
        let hashed = GridLevel {
            resolution: 64,
            offset: 0,
            entries: 1024,
            dense: false,
        };
        // 2·2654435761 = 5308871522 ≡ 1013904226 (mod 2^32); 3·805459861 = 2416379583.
        let expected = (1u64 ^ 1_013_904_226u64 ^ 2_416_379_583u64) & 1023;
        assert_eq!(vertex_index(&hashed, [1, 2, 3], 1023) as u64, expected);
    }

    /// 4 levels of 2 features over `[-1, 1]³`, resolutions 4 to 32 in a 2^10 table: two dense
    /// levels and two hashed ones.
    fn four_levels() -> EncodingConfig {
        EncodingConfig::HashGrid {
            levels: 4,
            features_per_level: 2,
            log2_table_size: 10,
            base_resolution: 4,
            per_level_scale: 2.0,
            bound: 1.0,
        }
    }

    #[test]
    fn a_cells_corners_are_the_vertex_indices_and_trilinear_weights() {
        // `Corners::of` forms the 8 indices from per-axis terms and the weights from shared
        // products: against `vertex_index` and the per-corner product, on a dense and a hashed
        // level, inside the cube and clamped outside it.
        let hg = four_levels();
        let levels = hg.grid_levels();
        assert!(levels[1].dense && !levels[3].dense);
        for lvl in [levels[1], levels[3]] {
            for p in [[0.3f64, -0.71, 0.05], [-0.999, 0.5, 0.999], [1.7, -2.0, 0.2]] {
                let k = Corners::of(&lvl, p, 1.0, 0.5, 1023);
                let cell = locate(p, 1.0, 0.5, lvl.resolution);
                assert_eq!(k.inside, cell.inside);
                let dw = k.dw();
                for c in 0..8 {
                    let bit = [c & 1, (c >> 1) & 1, c >> 2];
                    let v = [0, 1, 2].map(|d| cell.base[d] + bit[d] as u32);
                    assert_eq!(k.idx[c], (lvl.offset + vertex_index(&lvl, v, 1023)) as usize, "corner {c} of {p:?}");
                    let a = [0, 1, 2].map(|d| if bit[d] == 1 { cell.frac[d] } else { 1.0 - cell.frac[d] });
                    assert_eq!(k.w[c], a[0] * a[1] * a[2], "weight of corner {c} of {p:?}");
                    let sign = bit.map(|b| if b == 1 { 1.0 } else { -1.0 });
                    assert_eq!(dw[c], [sign[0] * a[1] * a[2], a[0] * sign[1] * a[2], a[0] * a[1] * sign[2]]);
                }
            }
        }
    }

    #[test]
    fn sizes_and_levels() {
        let pe = EncodingConfig::frequency(6);
        assert_eq!(pe.out_dim(3), 39);
        assert_eq!(pe.num_params(), 0);
        let hg = four_levels();
        let lv = hg.grid_levels();
        // 5^3 = 125 and 9^3 = 729 fit in 1024 entries (dense); 17^3 and 33^3 do not (hashed).
        assert_eq!(
            lv.iter().map(|l| l.resolution).collect::<Vec<_>>(),
            vec![4, 8, 16, 32]
        );
        assert_eq!(
            lv.iter().map(|l| l.dense).collect::<Vec<_>>(),
            vec![true, true, false, false]
        );
        assert_eq!(
            lv.iter().map(|l| l.offset).collect::<Vec<_>>(),
            vec![0, 125, 854, 1878]
        );
        assert_eq!(hg.num_params(), (125 + 729 + 1024 + 1024) * 2);
        assert_eq!(hg.out_dim(3), 8);
        let p = hg.init_params(7);
        assert!(p.iter().all(|v| v.abs() < 1e-4));
        assert!(hg.validate(2).is_err());
    }
}
