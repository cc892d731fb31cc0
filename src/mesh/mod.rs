//! SDF and material field interfaces, grid evaluation, iso-surface extraction, cleanup,
//! simplification, UV unwrap.
//!
//! [`build_mesh`] runs the geometry half of the export: grid → marching tetrahedra → largest
//! component → hole closing → meshoptimizer simplification to an absolute error bound →
//! vertex normals from the SDF gradient.

pub mod extract;
pub mod field;
pub mod grid;
pub mod topology;
pub mod uv;

use std::time::Instant;

use crate::backend::{Backend, BackendError};
use field::SdfField;
use grid::GridSpec;

/// An indexed triangle mesh (counter-clockwise seen from outside).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub indices: Vec<u32>,
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
    pub fn triangles(&self) -> impl Iterator<Item = [u32; 3]> + '_ {
        self.indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]])
    }
    pub fn area(&self) -> f64 {
        self.triangles()
            .map(|t| 0.5 * norm(tri_normal(&self.positions, t)) as f64)
            .sum()
    }
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        bounds_of(&self.positions)
    }

    /// Drop vertices no triangle uses (keeps order).
    pub fn compact(&mut self) {
        let mut remap = vec![u32::MAX; self.positions.len()];
        let mut positions = Vec::new();
        for i in self.indices.iter_mut() {
            let r = &mut remap[*i as usize];
            if *r == u32::MAX {
                *r = positions.len() as u32;
                positions.push(self.positions[*i as usize]);
            }
            *i = *r;
        }
        self.positions = positions;
    }
}

/// Axis-aligned bounds (min, max) of points; (+inf, -inf) when empty.
pub fn bounds_of(points: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}

pub(crate) fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub(crate) fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub(crate) fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub(crate) fn norm(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}
/// Unit vector along `a` (+Y for a zero vector).
pub fn normalize(a: [f32; 3]) -> [f32; 3] {
    let n = norm(a);
    if n > 1e-20 {
        [a[0] / n, a[1] / n, a[2] / n]
    } else {
        [0.0, 1.0, 0.0]
    }
}
/// Unnormalised normal (twice the area) of triangle `t`.
pub(crate) fn tri_normal(p: &[[f32; 3]], t: [u32; 3]) -> [f32; 3] {
    let (a, b, c) = (p[t[0] as usize], p[t[1] as usize], p[t[2] as usize]);
    cross(sub(b, a), sub(c, a))
}

/// Why a mesh could not be built.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("the SDF {field} has no surface in the box {min:?}..{max:?} (it is {sign} everywhere there; grid min {vmin}, max {vmax})")]
    NoSurface {
        field: String,
        min: [f32; 3],
        max: [f32; 3],
        sign: &'static str,
        vmin: f32,
        vmax: f32,
    },
    #[error(
        "the SDF {field} returned {count} non-finite values on the grid (first at node {first:?})"
    )]
    NonFinite {
        field: String,
        count: usize,
        first: [usize; 3],
    },
    #[error("{0}")]
    Backend(#[from] BackendError),
    #[error("{0}")]
    Config(String),
    #[error("mesh resolution {0} is out of range (8..=2048)")]
    Resolution(usize),
}

/// Geometry settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MeshConfig {
    /// Grid nodes along the longest side of the field's box.
    pub resolution: usize,
    /// Simplification error bound in scene units; `None` derives it from the grid spacing
    /// (half a cell).
    pub error_bound: Option<f32>,
    /// Largest angle (degrees) allowed between the interpolated vertex normals and the SDF
    /// gradient inside triangles: keeps flat faces next to rounded edges from shading bent.
    pub normal_tolerance_deg: f32,
}

impl Default for MeshConfig {
    fn default() -> Self {
        Self {
            resolution: 256,
            error_bound: None,
            normal_tolerance_deg: 10.0,
        }
    }
}

/// The mesh and what happened on the way, for the export report.
#[derive(Clone, Debug)]
pub struct MeshResult {
    /// The simplified, closed mesh in scene units, CCW outward.
    pub mesh: Mesh,
    /// Unit vertex normals from the SDF gradient.
    pub normals: Vec<[f32; 3]>,
    pub stats: MeshStats,
}

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct MeshStats {
    pub grid: Option<GridSpec>,
    pub touched_bounds: bool,
    pub extracted_triangles: usize,
    pub components: usize,
    pub dropped_triangles: usize,
    pub holes_closed: usize,
    pub error_bound: f32,
    /// meshoptimizer's own error estimate for the result (scene units).
    pub simplify_error: f32,
    /// The target handed to meshoptimizer last (tightened until the measured deviation holds).
    pub simplify_target: f32,
    /// Largest |sdf| over the result's vertices, edge midpoints and centroids (scene units).
    pub measured_deviation: f32,
    /// Triangles facing against the SDF gradient after simplification (0 unless the retries ran out).
    pub folded_triangles: usize,
    /// Largest angle between the shading normals and the SDF gradient on the result (degrees).
    pub normal_angle_deg: f32,
    pub triangles: usize,
    pub vertices: usize,
    pub watertight: bool,
    pub seconds_grid: f64,
    pub seconds_extract: f64,
    pub seconds_cleanup: f64,
    pub seconds_simplify: f64,
}

/// Evaluate the grid and check it has a surface. Nodes on the box's faces that are inside
/// the surface are pushed outside (by a quarter cell), so a surface that touches the box is
/// capped there rather than left open; `touched` reports it.
pub fn sample_grid(
    backend: &Backend,
    sdf: &dyn SdfField,
    grid: &GridSpec,
) -> Result<(Vec<f32>, bool), MeshError> {
    let mut values = sdf.eval_grid(backend, grid)?;
    let [nx, ny, nz] = grid.dims;
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        let count = values.iter().filter(|v| !v.is_finite()).count();
        return Err(MeshError::NonFinite {
            field: sdf.name(),
            count,
            first: [i % nx, (i / nx) % ny, i / (nx * ny)],
        });
    }
    let (vmin, vmax) = values
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let bounds = sdf.bounds();
    let no_surface = |sign| MeshError::NoSurface {
        field: sdf.name(),
        min: bounds.min,
        max: bounds.max,
        sign,
        vmin,
        vmax,
    };
    if vmin >= 0.0 {
        return Err(no_surface("positive (outside)"));
    }
    if vmax < 0.0 {
        return Err(no_surface("negative (inside)"));
    }
    let mut touched = false;
    let cap = 0.25 * grid.spacing;
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let on_face =
                    x == 0 || y == 0 || z == 0 || x == nx - 1 || y == ny - 1 || z == nz - 1;
                if !on_face {
                    continue;
                }
                let v = &mut values[grid.index(x, y, z)];
                if *v < 0.0 {
                    *v = cap;
                    touched = true;
                }
            }
        }
    }
    Ok((values, touched))
}

/// Simplify to an absolute error bound (scene units) with meshoptimizer; the triangle count
/// follows from the bound. Returns the mesh (unused vertices dropped) and meshoptimizer's
/// error estimate.
pub fn simplify(mesh: &Mesh, error_bound: f32) -> (Mesh, f32) {
    simplify_with(mesh, error_bound, meshopt::SimplifyOptions::None)
}

/// [`simplify`] with extra meshoptimizer options.
pub fn simplify_with(
    mesh: &Mesh,
    error_bound: f32,
    extra: meshopt::SimplifyOptions,
) -> (Mesh, f32) {
    let bytes: &[u8] = bytemuck::cast_slice(&mesh.positions);
    let adapter = match meshopt::VertexDataAdapter::new(bytes, 12, 0) {
        Ok(a) => a,
        Err(_) => return (mesh.clone(), 0.0),
    };
    let mut err = 0.0f32;
    let indices = meshopt::simplify(
        &mesh.indices,
        &adapter,
        0,
        error_bound,
        meshopt::SimplifyOptions::ErrorAbsolute | extra,
        Some(&mut err),
    );
    let indices = meshopt::optimize_vertex_cache(&indices, mesh.positions.len());
    let mut out = Mesh {
        positions: mesh.positions.clone(),
        indices,
    };
    out.compact();
    (out, err)
}

/// How far a mesh is from the field's surface.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Deviation {
    /// Largest |sdf| over the vertices, edge midpoints and centroids (scene units): the distance
    /// to the surface wherever the field is a true distance.
    pub distance: f32,
    /// Triangles whose face normal points against the SDF gradient at their centroid.
    pub folded: usize,
    /// Largest angle (degrees) at those samples between the shading normal (the vertex normals
    /// interpolated) and the SDF gradient.
    pub normal_angle_deg: f32,
}

/// Measure `mesh` against the field (see [`Deviation`]).
pub fn surface_deviation(
    backend: &Backend,
    sdf: &dyn SdfField,
    mesh: &Mesh,
) -> Result<Deviation, BackendError> {
    const W: [[f32; 3]; 4] = [
        [1.0 / 3.0; 3],
        [0.5, 0.5, 0.0],
        [0.0, 0.5, 0.5],
        [0.5, 0.0, 0.5],
    ];
    let nv = mesh.positions.len();
    let mut pts = mesh.positions.clone();
    for t in mesh.triangles() {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
        for w in W {
            pts.push([0, 1, 2].map(|k| w[0] * a[k] + w[1] * b[k] + w[2] * c[k]));
        }
    }
    let mut values = Vec::with_capacity(pts.len());
    let mut grads = Vec::with_capacity(pts.len());
    for part in pts.chunks(1 << 18) {
        let s = sdf.eval(backend, part)?;
        values.extend(s.values);
        grads.extend(s.gradients);
    }
    let mut dev = Deviation {
        distance: values.iter().fold(0.0f32, |w, x| w.max(x.abs())),
        ..Default::default()
    };
    let vn: Vec<[f32; 3]> = grads[..nv].iter().map(|&g| normalize(g)).collect();
    let mut min_cos = 1.0f32;
    for (t, tri) in mesh.triangles().enumerate() {
        for (j, w) in W.iter().enumerate() {
            let g = grads[nv + 4 * t + j];
            if j == 0 && dot(tri_normal(&mesh.positions, tri), g) < 0.0 {
                dev.folded += 1;
            }
            let n = normalize(
                [0, 1, 2].map(|k| (0..3).map(|c| w[c] * vn[tri[c] as usize][k]).sum::<f32>()),
            );
            min_cos = min_cos.min(dot(n, normalize(g)));
        }
    }
    dev.normal_angle_deg = min_cos.clamp(-1.0, 1.0).acos().to_degrees();
    Ok(dev)
}

/// Unit normals at `points` from the SDF gradient.
pub fn sdf_normals(
    backend: &Backend,
    sdf: &dyn SdfField,
    points: &[[f32; 3]],
) -> Result<Vec<[f32; 3]>, BackendError> {
    Ok(sdf
        .eval(backend, points)?
        .gradients
        .into_iter()
        .map(normalize)
        .collect())
}

/// Grid → surface → largest component → closed → simplified → normals.
pub fn build_mesh(
    backend: &Backend,
    sdf: &dyn SdfField,
    cfg: &MeshConfig,
) -> Result<MeshResult, MeshError> {
    if !(8..=2048).contains(&cfg.resolution) {
        return Err(MeshError::Resolution(cfg.resolution));
    }
    let grid = GridSpec::over(&sdf.bounds(), cfg.resolution);
    let mut stats = MeshStats {
        grid: Some(grid),
        ..Default::default()
    };
    let t = Instant::now();
    let (values, touched) = sample_grid(backend, sdf, &grid)?;
    backend.sync()?;
    stats.seconds_grid = t.elapsed().as_secs_f64();
    stats.touched_bounds = touched;
    if touched {
        tracing::warn!(
            "the surface of {} touches its box; the mesh is capped at the box",
            sdf.name()
        );
    }
    let t = Instant::now();
    let raw = extract::marching_tetrahedra(&grid, &values);
    drop(values);
    stats.extracted_triangles = raw.triangle_count();
    stats.seconds_extract = t.elapsed().as_secs_f64();

    tracing::debug!("extracted mesh: closed {:?}", topology::check_closed(&raw));
    let t = Instant::now();
    let (mut mesh, components) = topology::largest_component(&raw);
    stats.components = components;
    stats.dropped_triangles = raw.triangle_count() - mesh.triangle_count();
    stats.holes_closed = topology::close_holes(&mut mesh);
    stats.seconds_cleanup = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let bound = cfg.error_bound.unwrap_or(0.5 * grid.spacing);
    if !(bound.is_finite() && bound > 0.0) {
        return Err(MeshError::Config(format!(
            "simplification error bound must be > 0, got {bound}"
        )));
    }
    // meshoptimizer bounds vertex-to-plane distances, not how far the middle of a new, larger
    // triangle sags off a curved surface; so measure the real deviation against the field
    // (|sdf| at vertices, edge midpoints and centroids) and tighten its target until it holds.
    // Try a ladder of targets; take the first result that is within the bound, closed and
    // unfolded, else the closed result that comes nearest, else the unsimplified mesh.
    // One regularising pass over the full mesh at 0.3 of the bound: it removes the needle
    // triangles marching tetrahedra leaves, which otherwise make meshoptimizer fold the surface
    // at tight targets. The ladder then works on that smaller mesh (every candidate is still
    // measured against the field itself).
    let pre = {
        let p = simplify_with(&mesh, 0.3 * bound, meshopt::SimplifyOptions::Regularize).0;
        if topology::check_closed(&p).is_ok() {
            p
        } else {
            mesh.clone()
        }
    };
    let tol = cfg.normal_tolerance_deg;
    let excess = |d: &Deviation| {
        (
            // A few folded slivers (≤ 0.1 % of the triangles) are tolerated.
            d.folded.saturating_sub(pre.triangle_count() / 1000),
            ((d.distance - bound).max(0.0) * 1e6) as u64,
            ((d.normal_angle_deg - tol).max(0.0) * 1e3) as u64,
        )
    };
    let mut best: Option<(Mesh, f32, f32, Deviation)> = None;
    for factor in [0.6f32, 0.45, 0.38, 0.32] {
        let target = bound * factor;
        let (m, e) = simplify(&pre, target);
        let d = surface_deviation(backend, sdf, &m)?;
        let closed = topology::check_closed(&m);
        tracing::debug!("simplify target {target}: meshopt error {e}, {d:?}, closed {closed:?}");
        let closed = closed.is_ok();
        if !closed {
            continue;
        }
        let done = excess(&d) == (0, 0, 0);
        if best.as_ref().is_none_or(|b| excess(&d) < excess(&b.3)) {
            best = Some((m, e, target, d));
        }
        if done {
            break;
        }
    }
    let (mesh, err, target, dev) = match best {
        Some(b) => b,
        None => {
            tracing::warn!(
                "simplification kept breaking the surface of {}; exporting the unsimplified mesh",
                sdf.name()
            );
            let d = surface_deviation(backend, sdf, &mesh)?;
            (mesh, 0.0, 0.0, d)
        }
    };
    let (folded, normal_angle) = (dev.folded, dev.normal_angle_deg);
    let dev = dev.distance;
    if dev > bound {
        tracing::warn!("measured deviation {dev} exceeds the error bound {bound} (grid too coarse for the bound?)");
    }
    stats.seconds_simplify = t.elapsed().as_secs_f64();
    stats.error_bound = bound;
    stats.simplify_error = err;
    stats.simplify_target = target;
    stats.measured_deviation = dev;
    stats.folded_triangles = folded;
    stats.normal_angle_deg = normal_angle;
    stats.triangles = mesh.triangle_count();
    stats.vertices = mesh.positions.len();
    stats.watertight = topology::check_closed(&mesh).is_ok();
    let normals = sdf_normals(backend, sdf, &mesh.positions)?;
    Ok(MeshResult {
        mesh,
        normals,
        stats,
    })
}
