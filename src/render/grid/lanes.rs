//! The secondary march on an [`SdfGrid`] eight rays at a time (AVX2).
//!
//! A ray's march is one dependency chain (position → cell → eight loads → seven lerps → the next
//! `t`), about 40 ns a step on this project's 2-core box, so marching rays one after another
//! leaves the core waiting. Here eight rays step together in the lanes of AVX2 registers (the
//! corners come in by gathers), and a lane whose ray has finished takes the next ray at once, so
//! the lanes stay full until the chunk runs out of rays.
//!
//! The results are [`march_scalar`](crate::render::march_scalar)'s bit for bit: [`at8`] is
//! [`SdfGrid::at`]'s operations in its order (no FMA; `min`/`max` with their operands ordered so
//! NaN stays NaN as `clamp` keeps it; the float-to-int conversion clamped as `as i32` saturates),
//! the position is `o + t·d` as `Rays::at`, and every lane the vector test does not prove to go
//! on is decided by the scalar [`march_step`]. `render::grid`'s tests check the bits.

use std::arch::x86_64::*;
use std::ops::ControlFlow;

use super::SdfGrid;
use crate::render::{march_step, sphere_interval, March, Marched, Rays};

const L: usize = 8;

/// Whether `g`'s node indices fit the gathers' 32-bit offsets.
pub(super) fn fits(g: &SdfGrid) -> bool {
    g.values.len() <= i32::MAX as usize
}

/// [`SdfGrid::at`] at eight points.
#[inline(always)]
unsafe fn at8(g: &SdfGrid, p: [__m256; 3]) -> __m256 {
    let n = g.nodes();
    let hi = _mm256_set1_ps((n - 1) as f32);
    let top = _mm256_set1_epi32(n as i32 - 2);
    let zero = _mm256_setzero_ps();
    let zi = _mm256_setzero_si256();
    let bound = _mm256_set1_ps(g.bound);
    let inv = _mm256_set1_ps(g.inv_spacing);
    let mut i = [zi; 3];
    let mut w = [zero; 3];
    for a in 0..3 {
        let u = _mm256_mul_ps(_mm256_add_ps(p[a], bound), inv);
        // clamp(0, hi): min/max return their second operand where one is NaN, so NaN stays.
        let u = _mm256_max_ps(zero, _mm256_min_ps(hi, u));
        // `u as i32` takes NaN to 0; the conversion gives i32::MIN there, which max(0) mends.
        let k = _mm256_min_epi32(_mm256_max_epi32(_mm256_cvttps_epi32(u), zi), top);
        i[a] = k;
        w[a] = _mm256_sub_ps(u, _mm256_cvtepi32_ps(k));
    }
    let nv = _mm256_set1_epi32(n as i32);
    let b = _mm256_add_epi32(_mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(i[2], nv), i[1]), nv), i[0]);
    let by = _mm256_add_epi32(b, nv);
    let bz = _mm256_add_epi32(b, _mm256_set1_epi32((n * n) as i32));
    let bzy = _mm256_add_epi32(bz, nv);
    let v = g.values.as_ptr();
    let v1 = v.add(1);
    let lerp = |a: __m256, b: __m256, t: __m256| _mm256_add_ps(a, _mm256_mul_ps(_mm256_sub_ps(b, a), t));
    let c00 = lerp(_mm256_i32gather_ps::<4>(v, b), _mm256_i32gather_ps::<4>(v1, b), w[0]);
    let c10 = lerp(_mm256_i32gather_ps::<4>(v, by), _mm256_i32gather_ps::<4>(v1, by), w[0]);
    let c01 = lerp(_mm256_i32gather_ps::<4>(v, bz), _mm256_i32gather_ps::<4>(v1, bz), w[0]);
    let c11 = lerp(_mm256_i32gather_ps::<4>(v, bzy), _mm256_i32gather_ps::<4>(v1, bzy), w[0]);
    lerp(lerp(c00, c10, w[1]), lerp(c01, c11, w[1]), w[2])
}

/// [`SdfGrid::at`] at `points.len()` (≤ 8) points through [`at8`] (for the tests).
#[cfg(test)]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn at_lanes(g: &SdfGrid, points: &[[f32; 3]]) -> Vec<f32> {
    let mut c = [[0.0f32; L]; 3];
    for (l, p) in points.iter().enumerate() {
        for a in 0..3 {
            c[a][l] = p[a];
        }
    }
    let v = at8(g, [_mm256_loadu_ps(c[0].as_ptr()), _mm256_loadu_ps(c[1].as_ptr()), _mm256_loadu_ps(c[2].as_ptr())]);
    let mut out = [0.0f32; L];
    _mm256_storeu_ps(out.as_mut_ptr(), v);
    out[..points.len()].to_vec()
}

/// Eight rays in flight: each lane's ray (an index into the chunk's results, or `IDLE`), its
/// origin, direction, `t`, exit `t1`, the value last looked up and the steps taken.
struct Lanes {
    ray: [usize; L],
    o: [[f32; L]; 3],
    d: [[f32; L]; 3],
    t: [f32; L],
    t1: [f32; L],
    fv: [f32; L],
    step: [i32; L],
    active: u32,
}

const IDLE: usize = usize::MAX;

impl Lanes {
    fn new() -> Self {
        Lanes { ray: [IDLE; L], o: [[0.0; L]; 3], d: [[0.0; L]; 3], t: [0.0; L], t1: [0.0; L], fv: [0.0; L], step: [0; L], active: 0 }
    }

    /// Give every idle lane the next ray that meets the bounding sphere (`next` counts the
    /// chunk's rays handed out; those that miss the sphere get their result here).
    #[inline(always)]
    fn refill(&mut self, rays: &Rays, first: usize, m: &March, out: &mut [Marched], next: &mut usize) {
        for l in 0..L {
            if self.ray[l] != IDLE {
                continue;
            }
            while *next < out.len() {
                let j = *next;
                *next += 1;
                let i = first + j;
                match sphere_interval(rays.origins[i], rays.dirs[i], m.bound) {
                    None => out[j] = (false, f32::INFINITY, 0),
                    Some((_, e)) => {
                        self.ray[l] = j;
                        for a in 0..3 {
                            self.o[a][l] = rays.origins[i][a];
                            self.d[a][l] = rays.dirs[i][a];
                        }
                        self.t[l] = m.start_offset;
                        self.t1[l] = e;
                        self.step[l] = 0;
                        self.active |= 1 << l;
                        break;
                    }
                }
            }
        }
    }

    /// One step of every lane: look the field up at `o + t·d`, step the lanes that surely go
    /// on, and return the active lanes the vector test left undecided (with `t` not yet
    /// stepped) for [`Lanes::decide`].
    #[inline(always)]
    unsafe fn step(&mut self, g: &SdfGrid, m: &March) -> u32 {
        let thr = _mm256_set1_ps(m.threshold);
        let inf = _mm256_set1_ps(f32::INFINITY);
        let abs = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
        // Lanes go on while step + 1 < steps (steps > i32::MAX saturate: `decide` goes on).
        let steps = _mm256_set1_epi32(m.steps.min(i32::MAX as usize) as i32);
        let tv = _mm256_loadu_ps(self.t.as_ptr());
        let at = |a: usize| _mm256_add_ps(_mm256_loadu_ps(self.o[a].as_ptr()), _mm256_mul_ps(tv, _mm256_loadu_ps(self.d[a].as_ptr())));
        let f = at8(g, [at(0), at(1), at(2)]);
        let tn = _mm256_add_ps(tv, f);
        let s1 = _mm256_add_epi32(_mm256_loadu_si256(self.step.as_ptr() as *const __m256i), _mm256_set1_epi32(1));
        // A finite value at or above the threshold, still inside, steps left.
        let on = _mm256_and_ps(
            _mm256_and_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(f, abs), inf), _mm256_cmp_ps::<_CMP_GE_OQ>(f, thr)),
            _mm256_and_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(tn, _mm256_loadu_ps(self.t1.as_ptr())), _mm256_castsi256_ps(_mm256_cmpgt_epi32(steps, s1))),
        );
        _mm256_storeu_ps(self.fv.as_mut_ptr(), f);
        // The lanes that go on take `tn`; the others keep the `t` they looked up at.
        _mm256_storeu_ps(self.t.as_mut_ptr(), _mm256_blendv_ps(tv, tn, on));
        _mm256_storeu_si256(self.step.as_mut_ptr() as *mut __m256i, s1);
        self.active & !(_mm256_movemask_ps(on) as u32)
    }

    /// The undecided lanes of a step, by [`march_step`]: a finished ray's result goes to `out`
    /// and its lane goes idle.
    #[inline(always)]
    fn decide(&mut self, mut lanes: u32, m: &March, out: &mut [Marched]) {
        while lanes != 0 {
            let l = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            match march_step((self.step[l] - 1) as usize, self.t[l], self.t1[l], self.fv[l], m) {
                ControlFlow::Break(r) => {
                    out[self.ray[l]] = r;
                    self.ray[l] = IDLE;
                    self.active &= !(1 << l);
                }
                ControlFlow::Continue(tn) => self.t[l] = tn,
            }
        }
    }
}

/// [`PointSdf::march`](crate::render::PointSdf::march) for `g`: two sets of eight lanes, so
/// that one set's lookups overlap the other's.
///
/// # Safety
/// The CPU must have AVX2 and FMA, and `fits(g)` must hold.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn march_avx2(g: &SdfGrid, rays: &Rays, first: usize, m: &March, out: &mut [Marched]) {
    let mut a = Lanes::new();
    let mut b = Lanes::new();
    let mut next = 0usize;
    loop {
        a.refill(rays, first, m, out, &mut next);
        b.refill(rays, first, m, out, &mut next);
        if a.active == 0 && b.active == 0 {
            break;
        }
        let ua = a.step(g, m);
        let ub = b.step(g, m);
        a.decide(ua, m, out);
        b.decide(ub, m, out);
    }
}
