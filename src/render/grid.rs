//! A frozen SDF sampled once on a regular grid over the bounding cube. Stage 2's secondary rays
//! march on it (a trilinear lookup instead of a network evaluation) and only the rays that hit
//! go back to the network, which places their hit points on its own surface
//! (`train::stage2::SurfaceCache::trace_lobe`).

use rayon::prelude::*;

use super::{march_scalar, DeviceSdf, LowerBound, March, Marched, PointSdf, Rays, SdfBatch};
use crate::backend::BackendError;
use crate::mesh::field::Aabb;
use crate::mesh::grid::GridSpec;

#[cfg(target_arch = "x86_64")]
mod lanes;

/// SDF values at `nodes³` nodes spanning `[-bound, bound]³` (the mesher's [`GridSpec`] layout,
/// x fastest).
#[derive(Clone)]
pub struct SdfGrid {
    bound: f32,
    spec: GridSpec,
    /// `1 / spec.spacing`: a lookup multiplies by it (a division in its dependency chain was a
    /// fifth of a secondary ray's step).
    inv_spacing: f32,
    values: Vec<f32>,
}

impl std::fmt::Debug for SdfGrid {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "SdfGrid {{ nodes: {}³, bound: {} }}", self.nodes(), self.bound)
    }
}

impl SdfGrid {
    /// Sample `f` at every node (in z-slabs of about 2^16 points per batch).
    pub fn sample(f: &dyn SdfBatch, bound: f32, nodes: usize) -> Result<Self, BackendError> {
        if !(bound.is_finite() && bound > 0.0) || nodes < 2 {
            return Err(BackendError::Config(format!("an SDF grid needs a positive bound and at least 2 nodes per axis (got {bound}, {nodes})")));
        }
        let n = nodes;
        let spec = GridSpec::over(&Aabb { min: [-bound; 3], max: [bound; 3] }, n);
        let slabs = ((1usize << 16) / (n * n)).max(1);
        let mut values = Vec::with_capacity(spec.len());
        for z0 in (0..n).step_by(slabs) {
            let pts: Vec<f32> = (z0..(z0 + slabs).min(n)).flat_map(|z| (0..n).flat_map(move |y| (0..n).flat_map(move |x| spec.node(x, y, z)))).collect();
            let v = f.sdf(&pts)?;
            if v.len() != pts.len() / 3 {
                return Err(BackendError::Shape(format!("sdf batch returned {} values for {} points", v.len(), pts.len() / 3)));
            }
            values.extend(v);
        }
        let inv_spacing = 1.0 / spec.spacing;
        Ok(Self { bound, spec, inv_spacing, values })
    }

    pub fn nodes(&self) -> usize {
        self.spec.dims[0]
    }

    /// Node spacing (normalised units).
    pub fn spacing(&self) -> f32 {
        self.spec.spacing
    }

    /// The sampled value at node `(x, y, z)`.
    pub fn node_value(&self, x: usize, y: usize, z: usize) -> f32 {
        self.values[self.spec.index(x, y, z)]
    }

    /// The position of node `(x, y, z)`.
    pub fn node_position(&self, x: usize, y: usize, z: usize) -> [f32; 3] {
        self.spec.node(x, y, z)
    }

    /// Field evaluations its sampling took.
    pub fn evaluations(&self) -> usize {
        self.values.len()
    }

    /// Trilinear interpolation at `p` (clamped into the cube; NaN where `p` has a NaN).
    /// The eight-ray march (`render::grid::lanes`, x86-64) gives its bits lane by lane: change both together.
    pub fn at(&self, p: [f32; 3]) -> f32 {
        let n = self.nodes();
        let hi = (n - 1) as f32;
        let top = n as i32 - 2;
        let mut i = [0usize; 3];
        let mut w = [0.0f32; 3];
        for a in 0..3 {
            let u = ((p[a] + self.bound) * self.inv_spacing).clamp(0.0, hi);
            // `as` takes NaN to 0 (the weight stays NaN, so does the value).
            let i0 = (u as i32).min(top);
            i[a] = i0 as usize;
            w[a] = u - i0 as f32;
        }
        let (sy, sz) = (n, n * n);
        let b = (i[2] * n + i[1]) * n + i[0];
        // One bounds check: the cell's last corner is `b + sz + sy + 1` ≤ n³ − 1.
        let v = &self.values[b..b + sz + sy + 2];
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let c00 = lerp(v[0], v[1], w[0]);
        let c10 = lerp(v[sy], v[sy + 1], w[0]);
        let c01 = lerp(v[sz], v[sz + 1], w[0]);
        let c11 = lerp(v[sz + sy], v[sz + sy + 1], w[0]);
        lerp(lerp(c00, c10, w[1]), lerp(c01, c11, w[1]), w[2])
    }
}

impl SdfBatch for SdfGrid {
    fn sdf(&self, points: &[f32]) -> Result<Vec<f32>, BackendError> {
        Ok(points.par_chunks_exact(3).with_min_len(4096).map(|q| self.at([q[0], q[1], q[2]])).collect())
    }
    fn pointwise(&self) -> Option<&dyn PointSdf> {
        Some(self)
    }
}

impl PointSdf for SdfGrid {
    fn at(&self, p: [f32; 3]) -> f32 {
        SdfGrid::at(self, p)
    }
    fn march(&self, rays: &Rays, first: usize, m: &March, out: &mut [Marched]) {
        #[cfg(target_arch = "x86_64")]
        if crate::nn::simd::SimdLevel::detected() >= crate::nn::simd::SimdLevel::Avx2 && lanes::fits(self) && m.steps > 0 {
            // SAFETY: AVX2 (and FMA, which the function's features name) were detected.
            unsafe { lanes::march_avx2(self, rays, first, m, out) };
            return;
        }
        march_scalar(self, rays, first, m, out)
    }
}

/// A field traced with its own sampled grid as a lower bound ([`LowerBound`]): `f(p) ≥ g(p) − m`
/// inside the grid's cube, `g` the grid's trilinear value. For a 1-Lipschitz `f` (what sphere
/// tracing assumes) a trilinear blend of its node values is within `h√3` of `f(p)` (no node of
/// a cell is further than that from a point in it), so `m` is that, or twice the largest gap
/// between the grid and the field measured at [`BOUND_CHECKS`] seeded points (half in the cells
/// next to the surface, half anywhere in the sphere) where the field is less regular than that.
/// Everything but the bound is the field's: [`trace`](super::trace) finds the same surface,
/// evaluating the field only near it.
pub struct GridBounded<'a> {
    pub field: &'a dyn SdfBatch,
    pub bound: GridLower<'a>,
}

/// `g(p) − margin` inside the grid's cube, `-∞` outside it.
pub struct GridLower<'a> {
    pub grid: &'a SdfGrid,
    pub margin: f32,
}

/// Points at which [`GridBounded::new`] measures the grid's gap to its field.
pub const BOUND_CHECKS: usize = 8192;

impl<'a> GridBounded<'a> {
    /// `grid` must be `field` sampled ([`SdfGrid::sample`]); `None` where the field is not finite
    /// at the check points (no bound can be trusted then).
    pub fn new(field: &'a dyn SdfBatch, grid: &'a SdfGrid) -> Result<Option<Self>, BackendError> {
        use rand::Rng;
        let (n, h, b) = (grid.nodes(), grid.spacing(), grid.bound);
        let mut rng = crate::util::rng(0x6a7d_b0d5);
        let near: Vec<(usize, usize, usize)> = (0..n - 1)
            .flat_map(|z| (0..n - 1).flat_map(move |y| (0..n - 1).map(move |x| (x, y, z))))
            .filter(|&(x, y, z)| grid.node_value(x, y, z).abs() < 2.0 * h)
            .collect();
        let mut pts: Vec<f32> = Vec::with_capacity(3 * BOUND_CHECKS);
        for k in 0..BOUND_CHECKS {
            let p = if k % 2 == 0 && !near.is_empty() {
                let (x, y, z) = near[rng.random_range(0..near.len())];
                let c = grid.node_position(x, y, z);
                [c[0] + h * rng.random::<f32>(), c[1] + h * rng.random::<f32>(), c[2] + h * rng.random::<f32>()]
            } else {
                // Uniform in the ball of radius `b` (rejection from the cube).
                loop {
                    let q: [f32; 3] = [rng.random_range(-b..b), rng.random_range(-b..b), rng.random_range(-b..b)];
                    if q[0] * q[0] + q[1] * q[1] + q[2] * q[2] <= b * b {
                        break q;
                    }
                }
            };
            pts.extend_from_slice(&p);
        }
        let v = field.sdf(&pts)?;
        let mut gap = 0.0f32;
        for (q, fv) in pts.chunks_exact(3).zip(&v) {
            let d = (fv - grid.at([q[0], q[1], q[2]])).abs();
            if !d.is_finite() {
                return Ok(None);
            }
            gap = gap.max(d);
        }
        Ok(Some(Self { field, bound: GridLower { grid, margin: (3f32.sqrt() * h).max(2.0 * gap) } }))
    }
}

/// `field` bounded by `grid` where there is one and the bound holds ([`GridBounded::new`]).
pub fn bounded<'a>(field: &'a dyn SdfBatch, grid: Option<&'a SdfGrid>) -> Result<Option<GridBounded<'a>>, BackendError> {
    match grid {
        Some(g) => GridBounded::new(field, g),
        None => Ok(None),
    }
}

impl SdfBatch for GridBounded<'_> {
    fn sdf(&self, points: &[f32]) -> Result<Vec<f32>, BackendError> {
        self.field.sdf(points)
    }
    fn device(&self) -> Option<&dyn DeviceSdf> {
        self.field.device()
    }
    fn pointwise(&self) -> Option<&dyn PointSdf> {
        self.field.pointwise()
    }
    fn lower_bound(&self) -> Option<&dyn LowerBound> {
        Some(&self.bound)
    }
}

impl LowerBound for GridLower<'_> {
    fn lower(&self, p: [f32; 3]) -> f32 {
        let b = self.grid.bound;
        if p.iter().any(|c| !(c.abs() <= b)) {
            return f32::NEG_INFINITY;
        }
        self.grid.at(p) - self.margin
    }
    fn near(&self) -> f32 {
        0.05 * self.grid.spacing()
    }
    fn estimate(&self, p: [f32; 3]) -> f32 {
        self.grid.at(p)
    }
}

/// A floor at y = −0.3 and a ball of `radius` over it at (0.2, −0.05, 0): what [`bench_march`]
/// and the tests march secondary rays through (hits, rays leaving, self-hits).
fn floor_and_ball(q: &[f32], radius: f32) -> f32 {
    (q[1] + 0.3).min(((q[0] - 0.2).powi(2) + (q[1] + 0.05).powi(2) + q[2] * q[2]).sqrt() - radius)
}

/// [`bench_march`]'s figures.
#[derive(Clone, Debug, serde::Serialize)]
pub struct GridMarchLanes {
    pub nodes: usize,
    pub rays: usize,
    pub steps_per_ray: f64,
    /// Scalar march time / lanes march time, one thread each.
    pub speedup: f64,
    pub ns_per_step_scalar: f64,
    pub ns_per_step_lanes: f64,
}

/// Times the secondary march on a grid (`nodes`³ samples of a ball on a floor) of `rays` rays
/// leaving the ball's and floor's surfaces, [`SdfGrid`]'s lanes against [`march_scalar`], on
/// one thread, best of `rounds`; the results are checked bit for bit. None where the lanes do
/// not run (no AVX2).
pub fn bench_march(nodes: usize, rays: usize, rounds: usize) -> anyhow::Result<Option<GridMarchLanes>> {
    #[cfg(target_arch = "x86_64")]
    {
        use rand::Rng;
        if crate::nn::simd::SimdLevel::detected() < crate::nn::simd::SimdLevel::Avx2 {
            return Ok(None);
        }
        let field = |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| floor_and_ball(q, 0.25)).collect()) };
        let g = SdfGrid::sample(&field, 1.0, nodes)?;
        if !lanes::fits(&g) {
            return Ok(None);
        }
        let mut rng = crate::util::rng(23);
        let mut r = Rays::default();
        for i in 0..rays.max(1) {
            let (o, n) = if i % 2 == 0 {
                ([rng.random_range(-0.8f32..0.8), -0.3, rng.random_range(-0.8f32..0.8)], [0.0, 1.0, 0.0])
            } else {
                let a: f32 = rng.random_range(0.0..std::f32::consts::PI);
                let b: f32 = rng.random_range(0.0..std::f32::consts::TAU);
                let n = [a.sin() * b.cos(), a.cos(), a.sin() * b.sin()];
                ([0.2 + 0.25 * n[0], -0.05 + 0.25 * n[1], 0.25 * n[2]], n)
            };
            // A direction in the upper hemisphere of the normal, as a lobe's rays are.
            let d: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0f32..1.0));
            let s = if d[0] * n[0] + d[1] * n[1] + d[2] * n[2] < 0.0 { -1.0 } else { 1.0 };
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            r.origins.push(o);
            r.dirs.push(d.map(|c| s * c / l));
        }
        let m = March { start_offset: 0.01, steps: 48, threshold: 5e-4, bound: 1.0 };
        let mut best = [f64::INFINITY; 2];
        let mut outs = [vec![(false, 0.0f32, 0usize); r.len()], vec![(false, 0.0f32, 0usize); r.len()]];
        for _ in 0..rounds.max(2) {
            let t = std::time::Instant::now();
            march_scalar(&g, &r, 0, &m, &mut outs[0]);
            best[0] = best[0].min(t.elapsed().as_secs_f64());
            let t = std::time::Instant::now();
            g.march(&r, 0, &m, &mut outs[1]);
            best[1] = best[1].min(t.elapsed().as_secs_f64());
            if outs[0].iter().zip(&outs[1]).any(|(a, b)| a.0 != b.0 || a.1.to_bits() != b.1.to_bits() || a.2 != b.2) {
                anyhow::bail!("grid march: the lanes and the scalar march disagree");
            }
        }
        let steps: usize = outs[0].iter().map(|o| o.2).sum();
        let per = |s: f64| s / steps.max(1) as f64 * 1e9;
        Ok(Some(GridMarchLanes {
            nodes,
            rays: r.len(),
            steps_per_ray: steps as f64 / r.len() as f64,
            speedup: best[0] / best[1],
            ns_per_step_scalar: per(best[0]),
            ns_per_step_lanes: per(best[1]),
        }))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (nodes, rays, rounds);
        Ok(None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nodes_are_exact_and_a_smooth_field_is_close_between_them() {
        let sphere = |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - 0.5).collect()) };
        let g = SdfGrid::sample(&sphere, 1.0, 65).unwrap();
        assert_eq!(g.evaluations(), 65 * 65 * 65);
        let h = g.spacing();
        assert!((h - 2.0 / 64.0).abs() < 1e-7);
        // A node.
        let p = [-1.0 + 40.0 * h, -1.0 + 20.0 * h, -1.0 + 33.0 * h];
        assert!((g.at(p) - sphere(&p).unwrap()[0]).abs() < 1e-6);
        // Between nodes near the surface: trilinear error ~h²κ/8.
        let mut rng = crate::util::rng(5);
        use rand::Rng;
        for _ in 0..200 {
            let d: [f32; 3] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            let r = 0.5 + rng.random_range(-0.05f32..0.05);
            let q = d.map(|c| c / l * r);
            let err = (g.at(q) - (r - 0.5)).abs();
            assert!(err < h * h, "{q:?}: {} vs {}", g.at(q), r - 0.5);
        }
        // Outside the cube: clamped to the boundary's value.
        assert!((g.at([3.0, 0.0, 0.0]) - 0.5).abs() < 1e-6);
        let batch = g.sdf(&[0.0, 0.0, 0.0, 0.25, 0.0, 0.0]).unwrap();
        assert!((batch[0] + 0.5).abs() < 1e-3 && (batch[1] + 0.25).abs() < 1e-3, "{batch:?}");
        assert!(SdfGrid::sample(&sphere, 1.0, 1).is_err());
    }

    #[test]
    fn secondary_rays_marched_one_by_one_match_the_batched_march() {
        // A floor, a ball over it and a NaN pocket: rays from the floor and the ball's surface
        // hit, leave, start on their own surface, run out of steps or meet NaN.
        let field = |p: &[f32]| -> Result<Vec<f32>, BackendError> {
            Ok(p.chunks_exact(3)
                .map(|q| {
                    if (q[0] - 0.6).abs() < 0.1 && (q[1] - 0.4).abs() < 0.1 && q[2].abs() < 0.1 {
                        return f32::NAN;
                    }
                    floor_and_ball(q, 0.2)
                })
                .collect())
        };
        let g = SdfGrid::sample(&field, 1.0, 97).unwrap();
        assert!(g.pointwise().is_some());
        let batched = |p: &[f32]| g.sdf(p);
        assert!(batched.pointwise().is_none());
        let mut rng = crate::util::rng(11);
        use rand::Rng;
        let (mut origins, mut dirs) = (Vec::new(), Vec::new());
        for i in 0..3000 {
            let o = if i % 2 == 0 {
                [rng.random_range(-0.8f32..0.8), -0.3, rng.random_range(-0.8f32..0.8)]
            } else {
                let a: f32 = rng.random_range(0.0..std::f32::consts::TAU);
                [0.2 + 0.2 * a.cos(), -0.05 + 0.2 * a.sin(), 0.0]
            };
            let d: [f32; 3] = [rng.random_range(-1.0..1.0), rng.random_range(0.0..1.0), rng.random_range(-1.0..1.0)];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            origins.push(o);
            dirs.push(d.map(|c| c / l));
        }
        let rays = crate::render::Rays { origins, dirs };
        for steps in [1, 10, 48] {
            let (h1, t1, e1) = crate::render::trace_secondary(&g, &rays, 0.01, steps, 5e-4, 1.0).unwrap();
            let (h2, t2, e2) = crate::render::trace_secondary(&batched, &rays, 0.01, steps, 5e-4, 1.0).unwrap();
            assert_eq!(h1, h2, "{steps} steps: hits");
            assert!(t1.iter().zip(&t2).all(|(a, b)| a.to_bits() == b.to_bits()), "{steps} steps: depths");
            assert_eq!(e1, e2, "{steps} steps: evaluations");
            if steps == 48 {
                let hits = h1.iter().filter(|h| **h).count();
                assert!(hits > 50 && hits < 2900, "{hits} hits");
            }
        }
    }

    /// A grid with a NaN node, its field the floor-and-ball of the test above.
    #[cfg(target_arch = "x86_64")]
    fn lanes_grid(nodes: usize) -> SdfGrid {
        let field = |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| floor_and_ball(q, 0.2)).collect()) };
        let mut g = SdfGrid::sample(&field, 1.0, nodes).unwrap();
        let k = g.spec.index(nodes / 2, nodes - 1, nodes / 3);
        g.values[k] = f32::NAN;
        g
    }

    #[cfg(target_arch = "x86_64")]
    fn has_avx2() -> bool {
        let ok = crate::nn::simd::SimdLevel::detected() >= crate::nn::simd::SimdLevel::Avx2;
        if !ok {
            eprintln!("no AVX2 on this CPU: the eight-lane march is not used here, nothing to check");
        }
        ok
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn eight_lanes_look_up_the_scalar_bits() {
        if !has_avx2() {
            return;
        }
        let mut rng = crate::util::rng(3);
        use rand::Rng;
        for nodes in [2, 5, 33, 97] {
            let g = lanes_grid(nodes);
            let h = g.spacing();
            let mut pts: Vec<[f32; 3]> = vec![
                [0.0, 0.0, 0.0],
                [-0.0, -1.0, 1.0],
                [1.0, 1.0, 1.0],
                [-1.0, -1.0, -1.0],
                [5.0, -7.0, 0.3],
                [f32::INFINITY, 0.1, f32::NEG_INFINITY],
                [f32::NAN, 0.0, 0.0],
                [0.0, f32::NAN, 0.0],
                [0.2, 0.3, f32::NAN],
                [-1.0 + 3.0 * h, -1.0 + h, 1.0 - h],
                [f32::MAX, f32::MIN, f32::MIN_POSITIVE],
            ];
            for _ in 0..2000 {
                pts.push([rng.random_range(-1.2f32..1.2), rng.random_range(-1.2f32..1.2), rng.random_range(-1.2f32..1.2)]);
            }
            for chunk in pts.chunks(8) {
                let lanes = unsafe { lanes::at_lanes(&g, chunk) };
                for (p, v) in chunk.iter().zip(lanes) {
                    let s = g.at(*p);
                    assert!(s.to_bits() == v.to_bits() || (s.is_nan() && v.is_nan()), "{nodes} nodes at {p:?}: lanes {v} vs scalar {s}");
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn eight_lanes_march_the_scalar_bits() {
        if !has_avx2() {
            return;
        }
        let mut rng = crate::util::rng(17);
        use rand::Rng;
        // Rays from the floor and the ball (hits, leaving, self-hits), rays from outside the
        // sphere (some missing it), unnormalised and zero directions, origins on the NaN node.
        let (mut origins, mut dirs) = (Vec::new(), Vec::new());
        for i in 0..1500 {
            let o = match i % 4 {
                0 => [rng.random_range(-0.8f32..0.8), -0.3, rng.random_range(-0.8f32..0.8)],
                1 => {
                    let a: f32 = rng.random_range(0.0..std::f32::consts::TAU);
                    [0.2 + 0.2 * a.cos(), -0.05 + 0.2 * a.sin(), 0.0]
                }
                2 => [rng.random_range(-2.0f32..2.0), rng.random_range(-2.0f32..2.0), rng.random_range(-2.0f32..2.0)],
                _ => [0.0, 1.0 - rng.random_range(0.0f32..0.1), -0.33],
            };
            let mut d: [f32; 3] = [rng.random_range(-1.0..1.0), rng.random_range(-0.2..1.0), rng.random_range(-1.0..1.0)];
            if i % 5 == 0 {
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
                d = d.map(|c| c / l);
            }
            if i % 97 == 0 {
                d = [0.0; 3];
            }
            origins.push(o);
            dirs.push(d);
        }
        let rays = crate::render::Rays { origins, dirs };
        let mut checked = [0usize; 3];
        for nodes in [2, 9, 65] {
            let g = lanes_grid(nodes);
            for (steps, threshold, start_offset) in [(1, 5e-4, 0.01), (2, 5e-4, 0.01), (48, 5e-4, 0.01), (48, 0.0, 0.02), (48, 0.3, 0.01), (10, f32::NAN, 0.01), (48, 5e-4, 3.0)] {
                let m = March { start_offset, steps, threshold, bound: 1.0 };
                // Chunks of odd lengths at odd offsets, as `march_each` hands out and shorter.
                for (first, len) in [(0, rays.len()), (3, 1), (5, 7), (100, 37), (1001, 499)] {
                    let mut a = vec![(false, 0.0f32, 0usize); len];
                    let mut b = vec![(true, 1.0f32, 99usize); len];
                    march_scalar(&g, &rays, first, &m, &mut a);
                    unsafe { lanes::march_avx2(&g, &rays, first, &m, &mut b) };
                    for (j, (x, y)) in a.iter().zip(&b).enumerate() {
                        assert!(x.0 == y.0 && x.1.to_bits() == y.1.to_bits() && x.2 == y.2, "{nodes} nodes, {m:?}, ray {}: scalar {x:?} vs lanes {y:?}", first + j);
                        checked[0] += x.0 as usize;
                        checked[1] += (!x.0 && x.2 == steps) as usize;
                        checked[2] += (x.2 == 0) as usize;
                    }
                }
            }
        }
        // Every outcome was met: hits, rays out of steps, rays missing the sphere.
        assert!(checked.iter().all(|&c| c > 20), "{checked:?}");
    }

    /// A ball with a small one beside it (under three cells across at 65 nodes): camera rays and
    /// rays grazing the big ball, traced on the field alone and through its grid's bound. The
    /// bound's margin is `h√3` for the exact SDF and grows past it where a ripple steeper than
    /// 1-Lipschitz is added; both traces hit the same rays (but for a grazing ray passing within
    /// the threshold of the surface, which sphere tracing counts as a hit when it gets there in
    /// its steps) at the same depths, the bounded one for a fraction of the field evaluations.
    #[test]
    fn a_grid_bound_finds_the_fields_surface_for_a_fraction_of_its_evaluations() {
        use crate::render::{trace, TraceConfig, TraceMode};
        let balls = |q: &[f32]| ((q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - 0.4).min(((q[0] - 0.6).powi(2) + q[1] * q[1] + q[2] * q[2]).sqrt() - 0.04);
        let exact = move |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(balls).collect()) };
        let rippled = move |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| balls(q) + 0.04 * (100.0 * q[0]).sin() * (100.0 * q[1]).sin() * (100.0 * q[2]).sin()).collect()) };
        // Camera rays from z = 3 over [-0.8, 0.8]², then rays tangent to the big ball at a
        // closest distance of 0.4 + d, d over ±0.01.
        let mut rays = crate::render::Rays::default();
        for y in 0..48 {
            for x in 0..48 {
                let (px, py) = (-0.8 + 1.6 * x as f32 / 47.0, -0.8 + 1.6 * y as f32 / 47.0);
                let d = [px * 0.3, py * 0.3, -3.0];
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                rays.origins.push([0.0, 0.0, 3.0]);
                rays.dirs.push(d.map(|c| c / l));
            }
        }
        for k in 0..400 {
            let d = -0.01 + 0.02 * k as f32 / 399.0;
            let a = k as f32 * 0.7;
            rays.origins.push([(0.4 + d) * a.cos(), (0.4 + d) * a.sin(), 2.0]);
            rays.dirs.push([0.0, 0.0, -1.0]);
        }
        let cfg = TraceConfig::new(TraceMode::Refined);
        for (name, field) in [("exact", &exact as &dyn SdfBatch), ("rippled", &rippled)] {
            let g = SdfGrid::sample(field, 1.0, 65).unwrap();
            let b = GridBounded::new(field, &g).unwrap().expect("a finite field has a bound");
            let h = g.spacing();
            if name == "exact" {
                assert_eq!(b.bound.margin, 3f32.sqrt() * h, "an SDF's margin is the Lipschitz bound");
            } else {
                assert!(b.bound.margin > 3f32.sqrt() * h, "the ripple's gap widens the margin: {} vs {}", b.bound.margin, 3f32.sqrt() * h);
                // Sphere tracing does not hold on a field this steep, with or without a bound.
                continue;
            }
            let plain = trace(field, &rays, &cfg).unwrap();
            let bounded = trace(&b, &rays, &cfg).unwrap();
            let (mut hits, mut grazing) = (0, 0);
            for i in 0..rays.len() {
                // The field's smallest value along the ray (densely sampled): a ray passing
                // within the threshold of the surface may differ.
                let (o, d) = (rays.origins[i], rays.dirs[i]);
                let along: Vec<f32> = (0..4000).flat_map(|j| {
                    let t = 5.0 * j as f32 / 3999.0;
                    [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]
                }).collect();
                let closest = field.sdf(&along).unwrap().into_iter().fold(f32::INFINITY, f32::min);
                let near_miss = closest > -2.0 * cfg.threshold && closest < 2.0 * cfg.threshold;
                if plain.hit[i] != bounded.hit[i] {
                    assert!(near_miss, "{name} ray {i}: hit {} vs {}, closest {closest}", plain.hit[i], bounded.hit[i]);
                    grazing += 1;
                } else if plain.hit[i] {
                    hits += 1;
                    assert!(near_miss || (plain.t[i] - bounded.t[i]).abs() < 2e-3, "{name} ray {i}: t {} vs {}", plain.t[i], bounded.t[i]);
                }
            }
            assert!(hits > 900 && grazing < 20, "{name}: {hits} hits, {grazing} grazing differences");
            eprintln!("{name}: margin {} (h√3 = {}), {} vs {} evaluations, {grazing} grazing differences", b.bound.margin, 3f32.sqrt() * h, bounded.evaluations, plain.evaluations);
            assert!(bounded.evaluations * 5 < plain.evaluations * 3, "{name}: {} vs {} evaluations", bounded.evaluations, plain.evaluations);
        }
        // A field that is not finite at the check points has no bound.
        let broken = |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| if q[0] > 0.5 { f32::NAN } else { balls(q) }).collect()) };
        let g = SdfGrid::sample(&broken, 1.0, 33).unwrap();
        assert!(GridBounded::new(&broken, &g).unwrap().is_none());
    }
}
