//! The f32 hash grid on x86-64 CPUs with AVX2: the cells of 8 points at a time, one point per
//! lane. Each lane does the scalar twin's operations in the scalar twin's order (no fused
//! multiply-adds; every sum over corners and levels in the same sequence), so the results are
//! the same bits; `tests` below check that against the scalar code. Two features per level only
//! (every preset); other widths take the scalar path.
//!
//! Why: on the cpu backend the encoding is about half of a stage-1 step, and most of it was the
//! per-point scalar arithmetic of locating a cell (clamp, floor, hash, weights), not table reads.

use std::arch::x86_64::*;

use rayon::prelude::*;

use super::{grid_chunk_rows, GridGeom, GridLevel};

const LANES: usize = 8;

/// Whether this CPU runs the AVX2 path.
pub(super) fn available() -> bool {
    std::is_x86_feature_detected!("avx2")
}

/// Whether `g` and the parameter count suit the AVX2 path: two features per level, every table
/// entry's first feature addressable by an `i32` gather index, and a full parameter vector (the
/// gathers read entries of levels' tables by index without bounds checks).
pub(super) fn suits(g: &GridGeom, num_params: usize, params_len: Option<usize>) -> bool {
    g.f == 2 && num_params <= i32::MAX as usize && params_len.is_none_or(|l| l >= num_params)
}

/// A point block's coordinates, structure of arrays, padded with zeros to whole blocks of 8.
struct Soa {
    c: [Vec<f32>; 3],
}

impl Soa {
    fn of(x: &[f32]) -> Self {
        let n = x.len() / 3;
        let padded = n.div_ceil(LANES) * LANES;
        let c = std::array::from_fn(|d| {
            let mut v = vec![0.0; padded];
            for (o, row) in v.iter_mut().zip(x.chunks_exact(3)) {
                *o = row[d];
            }
            v
        });
        Soa { c }
    }
}

/// The cells of 8 points in one level (the lane form of `Corners`).
struct Corners8 {
    /// Entry index of each corner (the level's offset included).
    idx: [__m256i; 8],
    w: [__m256; 8],
    /// Axis factors `[1 − frac, frac]` per coordinate.
    axis: [[__m256; 2]; 3],
    /// All-ones lanes where the coordinate is inside the cube.
    inside: [__m256; 3],
}

/// Per-level constants of the lane code.
#[derive(Clone, Copy)]
struct LevelLanes {
    bound: __m256,
    inv_2b: __m256,
    res: __m256,
    res_m1: __m256i,
    offset: __m256i,
    mask: __m256i,
    /// Dense index scales `(1, s, s²)` or the hash primes.
    scale: [__m256i; 3],
    dense: bool,
}

impl LevelLanes {
    #[inline(always)]
    unsafe fn new(lvl: &GridLevel, bound: f32, inv_2b: f32, table_mask: u32) -> Self {
        let s = lvl.resolution.wrapping_add(1);
        let scale = if lvl.dense { [1, s, s.wrapping_mul(s)] } else { super::HASH_PRIMES };
        LevelLanes {
            bound: _mm256_set1_ps(bound),
            inv_2b: _mm256_set1_ps(inv_2b),
            res: _mm256_set1_ps(lvl.resolution as f32),
            res_m1: _mm256_set1_epi32((lvl.resolution - 1) as i32),
            offset: _mm256_set1_epi32(lvl.offset as i32),
            mask: _mm256_set1_epi32(table_mask as i32),
            scale: [
                _mm256_set1_epi32(scale[0] as i32),
                _mm256_set1_epi32(scale[1] as i32),
                _mm256_set1_epi32(scale[2] as i32),
            ],
            dense: lvl.dense,
        }
    }
}

impl Corners8 {
    /// `Corners::of` for 8 points: `locate`, the index terms and the trilinear weights.
    #[inline(always)]
    unsafe fn of(k: &LevelLanes, p: [__m256; 3]) -> Self {
        let zero = _mm256_setzero_ps();
        let one = _mm256_set1_ps(1.0);
        let ione = _mm256_set1_epi32(1);
        let mut axis = [[zero; 2]; 3];
        let mut inside = [zero; 3];
        let mut terms = [[_mm256_setzero_si256(); 2]; 3];
        for d in 0..3 {
            let u = _mm256_mul_ps(_mm256_add_ps(p[d], k.bound), k.inv_2b);
            // Ordered compares: false for NaN, which is clamped to the low face.
            let ins = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(u, zero), _mm256_cmp_ps::<_CMP_LT_OQ>(u, one));
            let face = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GE_OQ>(u, one), one);
            let u = _mm256_blendv_ps(face, u, ins);
            let pos = _mm256_mul_ps(u, k.res);
            // 0 <= pos <= resolution < 2^24: truncation is floor, exactly as the scalar cast.
            let i = _mm256_min_epi32(_mm256_cvttps_epi32(pos), k.res_m1);
            let frac = _mm256_sub_ps(pos, _mm256_cvtepi32_ps(i));
            axis[d] = [_mm256_sub_ps(one, frac), frac];
            inside[d] = ins;
            terms[d] = [
                _mm256_mullo_epi32(i, k.scale[d]),
                _mm256_mullo_epi32(_mm256_add_epi32(i, ione), k.scale[d]),
            ];
        }
        // No closures in the lane code: a closure does not inherit the caller's target features,
        // and an intrinsic left out of line is a call per operation.
        let mut idx = [_mm256_setzero_si256(); 8];
        for (c, i) in idx.iter_mut().enumerate() {
            let (tx, ty, tz) = (terms[0][c & 1], terms[1][(c >> 1) & 1], terms[2][c >> 2]);
            let local = if k.dense {
                _mm256_add_epi32(_mm256_add_epi32(tx, ty), tz)
            } else {
                _mm256_and_si256(_mm256_xor_si256(_mm256_xor_si256(tx, ty), tz), k.mask)
            };
            *i = _mm256_add_epi32(k.offset, local);
        }
        let xy = [
            _mm256_mul_ps(axis[0][0], axis[1][0]),
            _mm256_mul_ps(axis[0][1], axis[1][0]),
            _mm256_mul_ps(axis[0][0], axis[1][1]),
            _mm256_mul_ps(axis[0][1], axis[1][1]),
        ];
        let mut w = [zero; 8];
        for (c, wc) in w.iter_mut().enumerate() {
            *wc = _mm256_mul_ps(xy[c & 3], axis[2][c >> 2]);
        }
        Corners8 { idx, w, axis, inside }
    }

    /// `Corners::dw` for corner `c`: d weight / d frac per coordinate.
    #[inline(always)]
    unsafe fn dw(&self, c: usize) -> [__m256; 3] {
        let a = &self.axis;
        let (i, j, k) = (c & 1, (c >> 1) & 1, c >> 2);
        // The sign bit set where the corner's bit is 0 (negation is exact).
        let sign = [_mm256_set1_ps(-0.0), _mm256_setzero_ps()];
        [
            _mm256_xor_ps(_mm256_mul_ps(a[1][j], a[2][k]), sign[i]),
            _mm256_xor_ps(_mm256_mul_ps(a[0][i], a[2][k]), sign[j]),
            _mm256_xor_ps(_mm256_mul_ps(a[0][i], a[1][j]), sign[k]),
        ]
    }
}

/// Block `b` (8 rows) of a structure of arrays: the points' coordinates, or an accumulator's.
#[inline(always)]
unsafe fn load_points(soa: &Soa, b: usize) -> [__m256; 3] {
    [
        _mm256_loadu_ps(soa.c[0][b * LANES..].as_ptr()),
        _mm256_loadu_ps(soa.c[1][b * LANES..].as_ptr()),
        _mm256_loadu_ps(soa.c[2][b * LANES..].as_ptr()),
    ]
}

/// Both features of every corner entry, lanes 0–3 then lanes 4–7, each as the four lanes' pairs
/// `(table[2·idx], table[2·idx + 1])` in a row.
///
/// Safety: every lane's `idx` is an entry of `table` (the caller checked [`suits`]).
#[inline(always)]
unsafe fn gather_pairs(table: &[f32], idx: __m256i) -> (__m256, __m256) {
    let base = table.as_ptr().cast::<f64>();
    (
        _mm256_castpd_ps(_mm256_i32gather_pd::<8>(base, _mm256_castsi256_si128(idx))),
        _mm256_castpd_ps(_mm256_i32gather_pd::<8>(base, _mm256_extracti128_si256::<1>(idx))),
    )
}

/// Both features of every corner entry: `(table[2·idx], table[2·idx + 1])` per lane, split out
/// of [`gather_pairs`] (two 64-bit gathers and four shuffles beat two 32-bit gathers).
///
/// Safety: as [`gather_pairs`]'.
#[inline(always)]
unsafe fn gather_entry(table: &[f32], idx: __m256i) -> (__m256, __m256) {
    let (lo, hi) = gather_pairs(table, idx);
    // [lanes 0 1 4 5 | 2 3 6 7] of each feature, then the middle 64-bit halves swapped.
    let f0 = _mm256_shuffle_ps::<0b10_00_10_00>(lo, hi);
    let f1 = _mm256_shuffle_ps::<0b11_01_11_01>(lo, hi);
    (
        _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(f0))),
        _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(f1))),
    )
}

/// Column `col` of the first `m` rows (`od` wide) of `rows`, zeros past `m`.
#[inline(always)]
unsafe fn load_column(rows: &[f32], od: usize, col: usize, m: usize) -> __m256 {
    let mut v = [0.0f32; LANES];
    for (lane, o) in v.iter_mut().enumerate().take(m) {
        *o = rows[lane * od + col];
    }
    _mm256_loadu_ps(v.as_ptr())
}

/// The forward of `super::hash_grid_forward_cpu` (f32, F = 2).
///
/// Safety: the CPU has AVX2 ([`available`]); `g` and `params` pass [`suits`].
#[target_feature(enable = "avx2")]
pub(super) unsafe fn forward(g: &GridGeom, params: &[f32], x: &[f32]) -> Vec<f32> {
    let od = g.levels.len() * 2;
    let n = x.len() / 3;
    let (bound, inv_2b) = (g.bound as f32, (0.5 / g.bound) as f32);
    let mut out = vec![0.0f32; n * od];
    let rows = grid_chunk_rows(n).div_ceil(LANES) * LANES;
    out.par_chunks_mut(rows * od).zip(x.par_chunks(rows * 3)).for_each(|(o, xs)| {
        // SAFETY: as the function's (the closure runs on a pool thread of the same CPU).
        unsafe { forward_chunk(g, params, xs, o, bound, inv_2b) }
    });
    out
}

#[target_feature(enable = "avx2")]
unsafe fn forward_chunk(g: &GridGeom, params: &[f32], xs: &[f32], o: &mut [f32], bound: f32, inv_2b: f32) {
    let od = g.levels.len() * 2;
    let n = xs.len() / 3;
    let soa = Soa::of(xs);
    let dup_lo = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3);
    let dup_hi = _mm256_setr_epi32(4, 4, 5, 5, 6, 6, 7, 7);
    for (l, lvl) in g.levels.iter().enumerate() {
        let k = LevelLanes::new(lvl, bound, inv_2b, g.table_mask);
        for b in 0..n.div_ceil(LANES) {
            let c8 = Corners8::of(&k, load_points(&soa, b));
            // Each corner's two features in one 64-bit gather per four lanes (half the gathered
            // elements of two f32 gathers), summed interleaved as the output rows hold them,
            // with each lane's weight duplicated over its two features.
            let (mut lo, mut hi) = (_mm256_setzero_ps(), _mm256_setzero_ps());
            for c in 0..8 {
                let (elo, ehi) = gather_pairs(params, c8.idx[c]);
                lo = _mm256_add_ps(lo, _mm256_mul_ps(_mm256_permutevar8x32_ps(c8.w[c], dup_lo), elo));
                hi = _mm256_add_ps(hi, _mm256_mul_ps(_mm256_permutevar8x32_ps(c8.w[c], dup_hi), ehi));
            }
            let mut pairs = [0.0f32; 2 * LANES];
            _mm256_storeu_ps(pairs.as_mut_ptr(), lo);
            _mm256_storeu_ps(pairs.as_mut_ptr().add(LANES), hi);
            for (lane, pair) in pairs.chunks_exact(2).take((n - b * LANES).min(LANES)).enumerate() {
                let row = (b * LANES + lane) * od + l * 2;
                o[row..row + 2].copy_from_slice(pair);
            }
        }
    }
}

/// The parameter gradient of `super::hash_grid_backward_params_cpu` (f32, F = 2): per level in
/// parallel, the points in order, each point's corners in order, as the scalar twin adds them.
///
/// Safety: the CPU has AVX2 ([`available`]); `g` passes [`suits`].
#[target_feature(enable = "avx2")]
pub(super) unsafe fn backward_params(g: &GridGeom, num_params: usize, x: &[f32], d_out: &[f32]) -> Vec<f32> {
    let od = g.levels.len() * 2;
    let n = x.len() / 3;
    let (bound, inv_2b) = (g.bound as f32, (0.5 / g.bound) as f32);
    let soa = Soa::of(x);
    let mut d_params = vec![0.0f32; num_params];
    g.level_tables_mut(&mut d_params).into_par_iter().enumerate().for_each(|(l, dp)| {
        // SAFETY: as the function's.
        unsafe { backward_params_level(g, l, &soa, n, od, d_out, dp, bound, inv_2b) }
    });
    d_params
}

#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
unsafe fn backward_params_level(
    g: &GridGeom,
    l: usize,
    soa: &Soa,
    n: usize,
    od: usize,
    d_out: &[f32],
    dp: &mut [f32],
    bound: f32,
    inv_2b: f32,
) {
    let lvl = &g.levels[l];
    let base = lvl.offset as usize * 2;
    let k = LevelLanes::new(lvl, bound, inv_2b, g.table_mask);
    for b in 0..n.div_ceil(LANES) {
        let m = (n - b * LANES).min(LANES);
        let block = &d_out[b * LANES * od..];
        let dol = [load_column(block, od, l * 2, m), load_column(block, od, l * 2 + 1, m)];
        let c8 = Corners8::of(&k, load_points(soa, b));
        let mut idx = [[0u32; LANES]; 8];
        let mut prod = [[[0.0f32; LANES]; 2]; 8];
        for c in 0..8 {
            _mm256_storeu_si256(idx[c].as_mut_ptr().cast(), c8.idx[c]);
            _mm256_storeu_ps(prod[c][0].as_mut_ptr(), _mm256_mul_ps(c8.w[c], dol[0]));
            _mm256_storeu_ps(prod[c][1].as_mut_ptr(), _mm256_mul_ps(c8.w[c], dol[1]));
        }
        for lane in 0..m {
            for c in 0..8 {
                let e = idx[c][lane] as usize * 2 - base;
                dp[e] += prod[c][0][lane];
                dp[e + 1] += prod[c][1][lane];
            }
        }
    }
}

/// The input gradient of `super::hash_grid_backward_x_cpu` (f32, F = 2).
///
/// Safety: the CPU has AVX2 ([`available`]); `g` and `params` pass [`suits`].
#[target_feature(enable = "avx2")]
pub(super) unsafe fn backward_x(g: &GridGeom, params: &[f32], x: &[f32], d_out: &[f32]) -> Vec<f32> {
    let od = g.levels.len() * 2;
    let (bound, inv_2b) = (g.bound as f32, (0.5 / g.bound) as f32);
    let mut dx = vec![0.0f32; x.len()];
    let rows = grid_chunk_rows(x.len() / 3).div_ceil(LANES) * LANES;
    dx.par_chunks_mut(rows * 3)
        .zip(x.par_chunks(rows * 3))
        .zip(d_out.par_chunks(rows * od))
        .for_each(|((dxs, xs), dos)| {
            // SAFETY: as the function's.
            unsafe { backward_x_chunk(g, params, xs, dos, dxs, bound, inv_2b) }
        });
    dx
}

#[target_feature(enable = "avx2")]
unsafe fn backward_x_chunk(
    g: &GridGeom,
    params: &[f32],
    xs: &[f32],
    dos: &[f32],
    dxs: &mut [f32],
    bound: f32,
    inv_2b: f32,
) {
    let od = g.levels.len() * 2;
    let n = xs.len() / 3;
    let soa = Soa::of(xs);
    // The chunk's input gradient, structure of arrays; each row adds its levels in order.
    let mut acc = Soa { c: std::array::from_fn(|_| vec![0.0f32; soa.c[0].len()]) };
    for (l, lvl) in g.levels.iter().enumerate() {
        let k = LevelLanes::new(lvl, bound, inv_2b, g.table_mask);
        let dpos = _mm256_set1_ps(lvl.resolution as f32 * inv_2b);
        for b in 0..n.div_ceil(LANES) {
            let m = (n - b * LANES).min(LANES);
            let block = &dos[b * LANES * od..];
            let dol = [load_column(block, od, l * 2, m), load_column(block, od, l * 2 + 1, m)];
            let c8 = Corners8::of(&k, load_points(&soa, b));
            let mut dx = load_points(&acc, b);
            for c in 0..8 {
                let (e0, e1) = gather_entry(params, c8.idx[c]);
                let s = _mm256_add_ps(
                    _mm256_add_ps(_mm256_setzero_ps(), _mm256_mul_ps(dol[0], e0)),
                    _mm256_mul_ps(dol[1], e1),
                );
                let dw = c8.dw(c);
                for d in 0..3 {
                    let t = _mm256_mul_ps(_mm256_mul_ps(s, dw[d]), dpos);
                    dx[d] = _mm256_blendv_ps(dx[d], _mm256_add_ps(dx[d], t), c8.inside[d]);
                }
            }
            for d in 0..3 {
                _mm256_storeu_ps(acc.c[d][b * LANES..].as_mut_ptr(), dx[d]);
            }
        }
    }
    for (i, row) in dxs.chunks_exact_mut(3).enumerate() {
        for d in 0..3 {
            row[d] = acc.c[d][i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{
        grid_geom, hash_grid_backward_params_cpu, hash_grid_backward_params_scalar, hash_grid_backward_x_cpu,
        hash_grid_backward_x_scalar, hash_grid_forward_cpu, hash_grid_forward_scalar, EncodingConfig,
    };
    use rand::Rng;

    /// Points that reach every branch of `locate`: inside, outside, exactly on the faces and on
    /// cell boundaries, NaN and infinities; an odd count over several parallel chunks, so the
    /// last block of 8 is partial.
    fn points(bound: f32, n: usize, seed: u64) -> Vec<f32> {
        let mut r = crate::util::rng(seed);
        let specials = [0.0, bound, -bound, 0.5 * bound, -0.25 * bound, f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e-30, -1e-30];
        (0..n * 3)
            .map(|i| match i % 7 {
                0 => specials[r.random_range(0..specials.len())],
                1 => r.random_range(-1.3 * bound..1.3 * bound),
                // A vertex of some level (k / 2^m of the cube).
                2 => -bound + 2.0 * bound * (r.random_range(0..=64) as f32 / 64.0),
                _ => r.random_range(-bound..bound),
            })
            .collect()
    }

    fn same_bits(what: &str, a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len(), "{what}: lengths");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(x.to_bits() == y.to_bits(), "{what}: element {i}: {x:e} (lanes) vs {y:e} (scalar)");
        }
    }

    /// The lane code gives the scalar twin's bits in all three passes, on dense and hashed levels.
    #[test]
    fn lanes_give_the_scalar_bits() {
        if !super::available() {
            eprintln!("this CPU has no AVX2: the lane code is not used here, nothing to compare");
            return;
        }
        let configs = [
            // Dense levels (4, 6) and hashed ones (9 .. 30) in a 2^9 table; an off-centre bound.
            EncodingConfig::HashGrid { levels: 6, features_per_level: 2, log2_table_size: 9, base_resolution: 4, per_level_scale: 1.5, bound: 1.5 },
            // The fast preset's shape: 16 levels, 2^16 entries, resolutions 16 .. 180.
            EncodingConfig::HashGrid { levels: 16, features_per_level: 2, log2_table_size: 16, base_resolution: 16, per_level_scale: 1.175, bound: 1.0 },
        ];
        for (k, cfg) in configs.iter().enumerate() {
            cfg.validate(3).unwrap();
            let EncodingConfig::HashGrid { bound, .. } = *cfg else { unreachable!() };
            let g = grid_geom(cfg).unwrap();
            let np = cfg.num_params();
            let mut r = crate::util::rng(10 + k as u64);
            let params: Vec<f32> = (0..np).map(|_| r.random_range(-1.0..1.0)).collect();
            let x = points(bound, 20_011, 20 + k as u64);
            let od = cfg.out_dim(3);
            let d_out: Vec<f32> = (0..x.len() / 3 * od)
                .map(|i| if i % 11 == 0 { -0.0 } else { r.random_range(-1.0..1.0) })
                .collect();
            same_bits("forward", &hash_grid_forward_cpu(cfg, &params, &x), &hash_grid_forward_scalar(&g, &params, &x));
            same_bits(
                "parameter gradient",
                &hash_grid_backward_params_cpu(cfg, &x, &d_out),
                &hash_grid_backward_params_scalar(&g, np, &x, &d_out),
            );
            same_bits(
                "input gradient",
                &hash_grid_backward_x_cpu(cfg, &params, &x, &d_out),
                &hash_grid_backward_x_scalar(&g, &params, &x, &d_out),
            );
        }
    }

    /// What the lane code takes: two features per level and a whole parameter vector.
    #[test]
    fn lanes_take_two_features_and_whole_tables_only() {
        let cfg = |f| EncodingConfig::HashGrid { levels: 3, features_per_level: f, log2_table_size: 8, base_resolution: 4, per_level_scale: 2.0, bound: 1.0 };
        let (two, four) = (cfg(2), cfg(4));
        let g2 = grid_geom(&two).unwrap();
        assert!(super::suits(&g2, two.num_params(), Some(two.num_params())));
        assert!(super::suits(&g2, two.num_params(), None));
        assert!(!super::suits(&g2, two.num_params(), Some(two.num_params() - 1)));
        assert!(!super::suits(&grid_geom(&four).unwrap(), four.num_params(), Some(four.num_params())));
    }
}
