//! A frozen SDF sampled once on a regular grid over the bounding cube. Stage 2's secondary rays
//! march on it (a trilinear lookup instead of a network evaluation) and only the rays that hit
//! go back to the network, which places their hit points on its own surface
//! (`train::stage2::SurfaceCache::trace_lobe`).

use rayon::prelude::*;

use super::{PointSdf, SdfBatch};
use crate::backend::BackendError;
use crate::mesh::field::Aabb;
use crate::mesh::grid::GridSpec;

/// SDF values at `nodes³` nodes spanning `[-bound, bound]³` (the mesher's [`GridSpec`] layout,
/// x fastest).
#[derive(Clone)]
pub struct SdfGrid {
    bound: f32,
    spec: GridSpec,
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
        Ok(Self { bound, spec, values })
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

    /// Trilinear interpolation at `p` (clamped into the cube).
    pub fn at(&self, p: [f32; 3]) -> f32 {
        let n = self.nodes();
        let mut i = [0usize; 3];
        let mut w = [0.0f32; 3];
        for a in 0..3 {
            let u = ((p[a] + self.bound) / self.spec.spacing).clamp(0.0, (n - 1) as f32);
            let i0 = (u as usize).min(n - 2);
            i[a] = i0;
            w[a] = u - i0 as f32;
        }
        let idx = |x: usize, y: usize, z: usize| self.spec.index(x, y, z);
        let v = &self.values;
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let (x, y, z) = (i[0], i[1], i[2]);
        let c00 = lerp(v[idx(x, y, z)], v[idx(x + 1, y, z)], w[0]);
        let c10 = lerp(v[idx(x, y + 1, z)], v[idx(x + 1, y + 1, z)], w[0]);
        let c01 = lerp(v[idx(x, y, z + 1)], v[idx(x + 1, y, z + 1)], w[0]);
        let c11 = lerp(v[idx(x, y + 1, z + 1)], v[idx(x + 1, y + 1, z + 1)], w[0]);
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
                    (q[1] + 0.3).min(((q[0] - 0.2).powi(2) + (q[1] + 0.05).powi(2) + q[2] * q[2]).sqrt() - 0.2)
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
}
