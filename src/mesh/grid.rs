//! SDF values on a regular grid: the spec, the cpu twin and the `shaders/grid.wgsl` kernel for
//! the analytic shapes (other fields use [`super::field::SdfField::eval_grid`]'s batched default).

use crate::backend::gpu::{groups_1d, shaders, Access, Bind, KernelSpec};
use crate::backend::{Backend, BackendError};

use super::field::{Aabb, AnalyticShape};

pub const GRID_WGSL: &str = include_str!("../../shaders/grid.wgsl");

/// A regular grid of nodes: node (x, y, z) sits at `min + spacing·(x, y, z)`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct GridSpec {
    pub min: [f32; 3],
    /// Node spacing (scene units), equal on all axes.
    pub spacing: f32,
    /// Nodes per axis.
    pub dims: [usize; 3],
}

impl GridSpec {
    /// A grid over `bounds` with `resolution` nodes along its longest axis (at least 2).
    pub fn over(bounds: &Aabb, resolution: usize) -> Self {
        let ext = bounds.extent();
        let longest = ext[0].max(ext[1]).max(ext[2]).max(1e-6);
        let spacing = longest / (resolution.max(2) - 1) as f32;
        let dims = ext.map(|e| ((e / spacing).round() as usize + 1).max(2));
        Self {
            min: bounds.min,
            spacing,
            dims,
        }
    }

    pub fn node(&self, x: usize, y: usize, z: usize) -> [f32; 3] {
        [
            self.min[0] + self.spacing * x as f32,
            self.min[1] + self.spacing * y as f32,
            self.min[2] + self.spacing * z as f32,
        ]
    }

    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn index(&self, x: usize, y: usize, z: usize) -> usize {
        (z * self.dims[1] + y) * self.dims[0] + x
    }
}

/// Mirrors `GridParams` in `shaders/grid.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GridParams {
    pub origin: [f32; 4],
    pub spacing: [f32; 4],
    pub dims: [u32; 4],
    pub shape: [u32; 4],
}
const _: () = assert!(std::mem::size_of::<GridParams>() == 64);

/// Largest slab (floats) one dispatch writes: keeps the storage binding under lavapipe's 128 MiB.
const MAX_SLAB_FLOATS: usize = 16 << 20;

impl Backend {
    /// Analytic SDF values at every node of `grid` (x fastest): the cpu twin or `grid.wgsl`.
    pub fn grid_analytic_sdf(
        &self,
        shape: AnalyticShape,
        grid: &GridSpec,
    ) -> Result<Vec<f32>, BackendError> {
        self.grid_analytic_sdf_slabs(shape, grid, MAX_SLAB_FLOATS)
    }

    /// [`Backend::grid_analytic_sdf`] with at most `max_slab_floats` values per GPU dispatch
    /// (whole z-planes; tests use small slabs to exercise the slab loop).
    pub fn grid_analytic_sdf_slabs(
        &self,
        shape: AnalyticShape,
        grid: &GridSpec,
        max_slab_floats: usize,
    ) -> Result<Vec<f32>, BackendError> {
        match self {
            Backend::Cpu(_) => Ok(grid_analytic_sdf_cpu(shape, grid)),
            Backend::Gpu(g) => {
                let [nx, ny, nz] = grid.dims;
                let plane = nx * ny;
                if plane > max_slab_floats {
                    return Err(BackendError::Shape(format!(
                        "grid plane of {nx}x{ny} nodes is too large"
                    )));
                }
                let slab = (max_slab_floats / plane).clamp(1, nz);
                let src = shaders::with_lib(GRID_WGSL);
                let k = g.kernel(
                    "grid",
                    &src,
                    "eval_grid",
                    &KernelSpec::new(true, &[Access::ReadWrite]),
                )?;
                let mut out = Vec::with_capacity(grid.len());
                let buf = g.zeros_f32("grid-slab", slab * plane);
                let mut z0 = 0;
                while z0 < nz {
                    let nzs = slab.min(nz - z0);
                    let o = grid.node(0, 0, z0);
                    let p = GridParams {
                        origin: [o[0], o[1], o[2], 0.0],
                        spacing: [grid.spacing, grid.spacing, grid.spacing, 0.0],
                        dims: [nx as u32, ny as u32, nzs as u32, z0 as u32],
                        shape: [shape.kernel_id(), 0, 0, 0],
                    };
                    let n = nzs * plane;
                    g.dispatch(
                        &k,
                        Some(bytemuck::bytes_of(&p)),
                        &[Bind::Buffer(&buf)],
                        groups_1d(n, 256),
                    )?;
                    let v = g.read_f32(&buf)?;
                    out.extend_from_slice(&v[..n]);
                    z0 += nzs;
                }
                Ok(out)
            }
        }
    }
}

/// The cpu twin of `eval_grid` (rayon over z-planes). Node positions are computed in f32 the
/// way the kernel does, the distance in f64.
pub fn grid_analytic_sdf_cpu(shape: AnalyticShape, grid: &GridSpec) -> Vec<f32> {
    use rayon::prelude::*;
    let [nx, ny, nz] = grid.dims;
    let mut out = vec![0.0f32; grid.len()];
    out.par_chunks_mut(nx * ny)
        .enumerate()
        .take(nz)
        .for_each(|(z, plane)| {
            for y in 0..ny {
                for x in 0..nx {
                    let p = grid.node(x, y, z);
                    plane[y * nx + x] = shape.sdf([p[0] as f64, p[1] as f64, p[2] as f64]) as f32;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_spec_covers_bounds() {
        let g = GridSpec::over(
            &Aabb {
                min: [-1.0, -0.5, -1.0],
                max: [1.0, 0.5, 1.0],
            },
            65,
        );
        assert_eq!(g.dims, [65, 33, 65]);
        assert!((g.spacing - 2.0 / 64.0).abs() < 1e-7);
        let last = g.node(64, 32, 64);
        assert!((last[0] - 1.0).abs() < 1e-5 && (last[1] - 0.5).abs() < 1e-5);
        assert_eq!(g.index(1, 2, 3), (3 * 33 + 2) * 65 + 1);
    }
}
