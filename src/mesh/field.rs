//! The two fields the asset back end consumes, and analytic implementations with known answers.
//!
//! - [`SdfField`]: signed distance (negative inside) and its gradient at batches of points, in
//!   scene units (the object normalised into the unit sphere). The trained SDF network
//!   implements it later; so do the analytic shapes of [`AnalyticSdf`].
//! - [`MaterialField`]: albedo (linear RGB) and perceptual roughness at surface points.
//!
//! Both take the compute [`Backend`] so an implementation can run on the GPU; the analytic
//! shapes also have a grid kernel (`shaders/grid.wgsl`, see [`super::grid`]).

use crate::backend::{Backend, BackendError};

/// Axis-aligned box in scene units.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Aabb {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Aabb {
    /// The cube `[-h, h]³`.
    pub fn cube(h: f32) -> Self {
        Self {
            min: [-h; 3],
            max: [h; 3],
        }
    }
    pub fn extent(&self) -> [f32; 3] {
        [
            self.max[0] - self.min[0],
            self.max[1] - self.min[1],
            self.max[2] - self.min[2],
        ]
    }
}

/// SDF values and gradients at a batch of points.
#[derive(Clone, Debug, Default)]
pub struct SdfSamples {
    pub values: Vec<f32>,
    pub gradients: Vec<[f32; 3]>,
}

/// A signed distance field (negative inside), evaluable in batches on a backend.
pub trait SdfField: Send + Sync {
    /// A short name for reports.
    fn name(&self) -> String;
    /// The box the mesh is extracted from (scene units). Default: the unit cube around the unit
    /// sphere the scene is normalised into, with a small margin.
    fn bounds(&self) -> Aabb {
        Aabb::cube(1.05)
    }
    /// Values and gradients at `points` (scene units).
    fn eval(&self, backend: &Backend, points: &[[f32; 3]]) -> Result<SdfSamples, BackendError>;
    /// Values at the nodes of `grid`, x fastest then y then z. The default evaluates
    /// [`SdfField::eval`] slab by slab; implementations with a grid kernel override it.
    fn eval_grid(
        &self,
        backend: &Backend,
        grid: &super::grid::GridSpec,
    ) -> Result<Vec<f32>, BackendError> {
        let [nx, ny, nz] = grid.dims;
        let mut out = Vec::with_capacity(nx * ny * nz);
        let mut pts = Vec::with_capacity(nx * ny);
        for z in 0..nz {
            pts.clear();
            for y in 0..ny {
                for x in 0..nx {
                    pts.push(grid.node(x, y, z));
                }
            }
            out.extend(self.eval(backend, &pts)?.values);
        }
        Ok(out)
    }
}

/// Albedo and roughness at a batch of surface points.
#[derive(Clone, Debug, Default)]
pub struct MaterialSamples {
    /// Linear RGB in [0, 1].
    pub albedo: Vec<[f32; 3]>,
    /// Perceptual roughness in [0, 1] (α = R²).
    pub roughness: Vec<f32>,
    /// glTF metallic in [0, 1], one per point; empty for a dielectric-only field (no metallic
    /// texture is baked and the asset's metallic factor is 0).
    pub metallic: Vec<f32>,
}

/// A material field on the surface.
pub trait MaterialField: Send + Sync {
    fn name(&self) -> String;
    /// Albedo/roughness at surface `points` with unit `normals` (scene units).
    fn eval(
        &self,
        backend: &Backend,
        points: &[[f32; 3]],
        normals: &[[f32; 3]],
    ) -> Result<MaterialSamples, BackendError>;
    /// The smallest feature length of the pattern in scene units, when known (chooses the
    /// texture size). `None`: smooth at the scale of the object.
    fn feature_size(&self) -> Option<f32>;
}

// ---- analytic shapes -------------------------------------------------------------------------

/// Analytic test shapes. Every one fits in the unit sphere.
#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AnalyticShape {
    /// Sphere of radius 0.8.
    Sphere,
    /// Torus around +Y, major radius 0.55, minor 0.22.
    Torus,
    /// An open bowl (hollow hemisphere, radius 0.75, wall 0.08) with a ball resting inside.
    Bowl,
    /// Box 1.1 × 0.7 × 0.9 with edges rounded at radius 0.1.
    RoundedBox,
}

impl AnalyticShape {
    pub const ALL: [AnalyticShape; 4] = [Self::Sphere, Self::Torus, Self::Bowl, Self::RoundedBox];

    /// Kernel id in `shaders/grid.wgsl` (`shape_sdf`).
    pub fn kernel_id(self) -> u32 {
        match self {
            Self::Sphere => 0,
            Self::Torus => 1,
            Self::Bowl => 2,
            Self::RoundedBox => 3,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Sphere => "sphere",
            Self::Torus => "torus",
            Self::Bowl => "bowl",
            Self::RoundedBox => "rounded-box",
        }
    }

    /// Signed distance at `p`. The same formulas as `shape_sdf` in `shaders/grid.wgsl`.
    pub fn sdf(self, p: [f64; 3]) -> f64 {
        let [x, y, z] = p;
        match self {
            Self::Sphere => (x * x + y * y + z * z).sqrt() - 0.8,
            Self::Torus => {
                let qx = (x * x + z * z).sqrt() - 0.55;
                (qx * qx + y * y).sqrt() - 0.22
            }
            Self::Bowl => {
                // Hollow sphere of radius r cut at height h (kept below), wall half-thickness t,
                // the rim rounded; plus a ball smoothly joined to the inner wall.
                let (r, h, t) = (0.75f64, 0.2f64, 0.04f64);
                let w = (r * r - h * h).sqrt();
                let qx = (x * x + z * z).sqrt();
                let qy = y;
                let bowl = if h * qx < w * qy {
                    ((qx - w).powi(2) + (qy - h).powi(2)).sqrt()
                } else {
                    ((qx * qx + qy * qy).sqrt() - r).abs()
                } - t;
                let ball = (x * x + (y + 0.44).powi(2) + z * z).sqrt() - 0.3;
                smin(bowl, ball, 0.1)
            }
            Self::RoundedBox => {
                let (bx, by, bz, rad) = (0.55f64, 0.35f64, 0.45f64, 0.1f64);
                let qx = x.abs() - bx + rad;
                let qy = y.abs() - by + rad;
                let qz = z.abs() - bz + rad;
                let outside =
                    (qx.max(0.0).powi(2) + qy.max(0.0).powi(2) + qz.max(0.0).powi(2)).sqrt();
                outside + qx.max(qy).max(qz).min(0.0) - rad
            }
        }
    }

    /// Gradient by central differences in f64 (h = 1e-5: exact to ~1e-9 on these smooth shapes
    /// away from their medial axes).
    pub fn grad(self, p: [f64; 3]) -> [f64; 3] {
        let h = 1e-5;
        let mut g = [0.0; 3];
        for (i, gi) in g.iter_mut().enumerate() {
            let mut a = p;
            let mut b = p;
            a[i] += h;
            b[i] -= h;
            *gi = (self.sdf(a) - self.sdf(b)) / (2.0 * h);
        }
        g
    }
}

/// Polynomial smooth minimum with blend width `k` (as in `shaders/grid.wgsl`).
pub fn smin(a: f64, b: f64, k: f64) -> f64 {
    let h = (k - (a - b).abs()).max(0.0) / k;
    a.min(b) - h * h * k * 0.25
}

/// An analytic shape as an [`SdfField`], optionally with custom bounds (tests use a box that
/// cuts the surface).
#[derive(Clone, Copy, Debug)]
pub struct AnalyticSdf {
    pub shape: AnalyticShape,
    pub bounds: Aabb,
}

impl AnalyticSdf {
    pub fn new(shape: AnalyticShape) -> Self {
        Self {
            shape,
            bounds: Aabb::cube(1.05),
        }
    }
}

impl SdfField for AnalyticSdf {
    fn name(&self) -> String {
        self.shape.name().to_string()
    }
    fn bounds(&self) -> Aabb {
        self.bounds
    }
    fn eval(&self, _backend: &Backend, points: &[[f32; 3]]) -> Result<SdfSamples, BackendError> {
        use rayon::prelude::*;
        let (values, gradients) = points
            .par_iter()
            .map(|p| {
                let p = [p[0] as f64, p[1] as f64, p[2] as f64];
                let g = self.shape.grad(p);
                (
                    self.shape.sdf(p) as f32,
                    [g[0] as f32, g[1] as f32, g[2] as f32],
                )
            })
            .unzip();
        Ok(SdfSamples { values, gradients })
    }
    fn eval_grid(
        &self,
        backend: &Backend,
        grid: &super::grid::GridSpec,
    ) -> Result<Vec<f32>, BackendError> {
        backend.grid_analytic_sdf(self.shape, grid)
    }
}

// ---- analytic materials ----------------------------------------------------------------------

/// Analytic albedo/roughness patterns (world-space, so they need no UVs).
#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AnalyticMaterial {
    /// A 3-D checker of 0.25-unit cells: red/rough 0.3 and cream/rough 0.8.
    Checker,
    /// Albedo blends blue → yellow with height; roughness 0.2 → 0.8 along +X.
    Gradient,
}

impl AnalyticMaterial {
    pub const CHECKER_CELL: f64 = 0.25;

    pub fn name(self) -> &'static str {
        match self {
            Self::Checker => "checker",
            Self::Gradient => "gradient",
        }
    }

    /// Albedo (linear RGB) and roughness at `p`.
    pub fn eval_point(self, p: [f64; 3]) -> ([f32; 3], f32) {
        match self {
            Self::Checker => {
                let c = Self::CHECKER_CELL;
                let parity = ((p[0] / c).floor() + (p[1] / c).floor() + (p[2] / c).floor()) as i64;
                if parity.rem_euclid(2) == 0 {
                    ([0.8, 0.1, 0.1], 0.3)
                } else {
                    ([0.9, 0.9, 0.85], 0.8)
                }
            }
            Self::Gradient => {
                let t = ((p[1] + 1.0) * 0.5).clamp(0.0, 1.0) as f32;
                let s = ((p[0] + 1.0) * 0.5).clamp(0.0, 1.0) as f32;
                let a = [0.1, 0.2, 0.8];
                let b = [0.9, 0.7, 0.1];
                (
                    [
                        a[0] + (b[0] - a[0]) * t,
                        a[1] + (b[1] - a[1]) * t,
                        a[2] + (b[2] - a[2]) * t,
                    ],
                    0.2 + 0.6 * s,
                )
            }
        }
    }
}

impl MaterialField for AnalyticMaterial {
    fn name(&self) -> String {
        AnalyticMaterial::name(*self).to_string()
    }
    /// Evaluated on the host on both backends (a few flops per point).
    fn eval(
        &self,
        _backend: &Backend,
        points: &[[f32; 3]],
        normals: &[[f32; 3]],
    ) -> Result<MaterialSamples, BackendError> {
        if points.len() != normals.len() {
            return Err(BackendError::Shape(format!(
                "{} points but {} normals",
                points.len(),
                normals.len()
            )));
        }
        let (albedo, roughness) = points
            .iter()
            .map(|p| self.eval_point([p[0] as f64, p[1] as f64, p[2] as f64]))
            .unzip();
        Ok(MaterialSamples { albedo, roughness, metallic: Vec::new() })
    }
    fn feature_size(&self) -> Option<f32> {
        match self {
            Self::Checker => Some(Self::CHECKER_CELL as f32),
            Self::Gradient => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{check_grad, Tolerance};

    #[test]
    fn analytic_gradients_match_finite_differences_and_are_unit() {
        let pts = [
            [0.31, -0.2, 0.5],
            [0.7, 0.1, -0.05],
            [-0.2, -0.6, 0.33],
            [0.52, 0.28, 0.1],
        ];
        for shape in AnalyticShape::ALL {
            for p in pts {
                let g = shape.grad(p);
                check_grad(
                    shape.name(),
                    &p,
                    &g,
                    1e-4,
                    Tolerance::new(1e-4, 1e-6),
                    |q| shape.sdf([q[0], q[1], q[2]]),
                );
                let n = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
                // An SDF has |∇f| = 1 (the smooth union of the bowl bends it slightly).
                assert!(
                    (n - 1.0).abs() < 0.05,
                    "{}: |grad| = {n} at {p:?}",
                    shape.name()
                );
            }
        }
        assert!((AnalyticShape::Sphere.sdf([0.0, 0.8, 0.0])).abs() < 1e-12);
        assert!(
            AnalyticShape::Torus.sdf([0.55, 0.0, 0.0]) < 0.0
                && AnalyticShape::Torus.sdf([0.0; 3]) > 0.0
        );
        assert!(
            AnalyticShape::Bowl.sdf([0.0, -0.44, 0.0]) < 0.0,
            "ball inside the bowl"
        );
        assert!(
            AnalyticShape::Bowl.sdf([0.0, 0.0, 0.0]) > 0.0,
            "the bowl is open"
        );
    }

    #[test]
    fn materials_are_in_range() {
        for m in [AnalyticMaterial::Checker, AnalyticMaterial::Gradient] {
            for p in [[0.1, 0.2, 0.3], [-0.9, 0.8, -0.1], [0.6, -0.7, 0.0]] {
                let (a, r) = m.eval_point(p);
                assert!(a.iter().all(|c| (0.0..=1.0).contains(c)) && (0.0..=1.0).contains(&r));
            }
        }
        let (a, _) = AnalyticMaterial::Checker.eval_point([0.1, 0.1, 0.1]);
        let (b, _) = AnalyticMaterial::Checker.eval_point([0.3, 0.1, 0.1]);
        assert_ne!(a, b);
    }
}
