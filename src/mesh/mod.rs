//! SDF and material field interfaces, grid evaluation, iso-surface extraction, cleanup,
//! simplification, UV unwrap.
//!
//! [`build_mesh`] runs the geometry half of the export: grid → marching tetrahedra → largest
//! component → hole closing → simplification to an absolute error bound ([`simplify_sdf`]:
//! quadric edge collapses, each one checked against the field) → vertex normals from the SDF
//! gradient.

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
    /// (`bound_cells` cells).
    pub error_bound: Option<f32>,
    /// The error bound in grid cells when `error_bound` is `None`.
    pub bound_cells: f32,
    /// Components with fewer than this fraction of the largest one's triangles are dropped as
    /// specks; larger ones are parts of the object and kept.
    pub min_component_fraction: f32,
    /// Largest angle (degrees) allowed between the interpolated vertex normals and the SDF
    /// gradient inside triangles: keeps flat faces next to rounded edges from shading bent.
    pub normal_tolerance_deg: f32,
    /// Largest angle (degrees) allowed between a triangle's face normal and the SDF gradient at
    /// its samples: how faceted the mesh may look where it is drawn flat-shaded (and what its
    /// face normal consistency measures).
    pub face_tolerance_deg: f32,
}

impl Default for MeshConfig {
    fn default() -> Self {
        Self {
            resolution: 256,
            error_bound: None,
            bound_cells: 0.5,
            min_component_fraction: MIN_COMPONENT_FRACTION,
            normal_tolerance_deg: 10.0,
            face_tolerance_deg: DEFAULT_FACE_TOLERANCE_DEG,
        }
    }
}

/// [`MeshConfig::face_tolerance_deg`]'s default: no limit beyond the fold check. Measured on the
/// bundled example's trained SDF (`bench train --asset-face-tolerance`, 96³ grid, bound 1/8 cell;
/// triangles, face normal consistency against the ground truth, with shading normals): no limit
/// 3184, 0.9813 / 0.9860; 20° 3466, 0.9821 / 0.9863; 15° 4110, 0.9824 / 0.9862; 12° 5146,
/// 0.9830 / 0.9865; 10° 6812, 0.9832 / 0.9862; 8° 9876, 0.9838 / 0.9864 (classic tracing's SDF
/// alike: 3142 → 9930, 0.9821 → 0.9844). Faces gain little for many more triangles (the field's
/// own zero level scores 0.9852 there), and a .glb or USD draws the shading normals, which the
/// 10° normal tolerance already holds, so the limit is `--face-tolerance`'s to set.
pub const DEFAULT_FACE_TOLERANCE_DEG: f32 = 90.0;

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
    /// Largest quadric (QEM) RMS error of a collapse kept (scene units): an estimate; the
    /// measured deviation is what is bounded.
    pub simplify_error: f32,
    /// The bound every collapse was checked against (the error bound).
    pub simplify_target: f32,
    /// Largest |sdf| over the result's vertices, edge midpoints and centroids (scene units):
    /// at most the error bound, unless the unsimplified mesh was already further off.
    pub measured_deviation: f32,
    /// Triangles facing against the SDF gradient after simplification (never more than the
    /// unsimplified mesh had).
    pub folded_triangles: usize,
    /// Largest angle between the shading normals and the SDF gradient on the result (degrees).
    pub normal_angle_deg: f32,
    /// Largest angle between a face normal and the SDF gradient on the result (degrees; held
    /// within [`MeshConfig::face_tolerance_deg`] or the unsimplified mesh's own).
    pub face_angle_deg: f32,
    /// The mesh the field-checked collapses started from, measured the same way: the
    /// unsimplified (closed, largest-component) mesh, or meshoptimizer's pre-pass of it.
    pub unsimplified: Deviation,
    /// Triangles after meshoptimizer's pre-pass (0: not used; see [`build_mesh`]).
    pub presimplified_triangles: usize,
    /// Rounds of independent collapses.
    pub simplify_rounds: usize,
    /// Collapses the field check turned down.
    pub simplify_rejected: usize,
    /// Points the field was evaluated at while simplifying.
    pub simplify_field_points: usize,
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
/// error estimate. [`build_mesh`] does not use it: nothing but its quadrics guides it, so on
/// thin sheets it moves vertices across the sheet and breaks the bound or the topology
/// ([`simplify_sdf`] checks every collapse against the field instead).
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

/// Where [`surface_deviation`] samples a triangle besides its vertices (barycentric weights):
/// the centroid, then the midpoints of the edges 01, 12 and 20.
const SAMPLE_WEIGHTS: [[f32; 3]; 4] = [
    [1.0 / 3.0; 3],
    [0.5, 0.5, 0.0],
    [0.0, 0.5, 0.5],
    [0.5, 0.0, 0.5],
];

/// The point of triangle `p` at barycentric weights `w` (the same arithmetic everywhere, so a
/// sample checked during simplification is bit for bit the one [`surface_deviation`] measures).
fn tri_point(p: [[f32; 3]; 3], w: [f32; 3]) -> [f32; 3] {
    [0, 1, 2].map(|k| w[0] * p[0][k] + w[1] * p[1][k] + w[2] * p[2][k])
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
    /// Largest angle (degrees) at those samples between the face normal and the SDF gradient.
    pub face_angle_deg: f32,
}

/// Measure `mesh` against the field (see [`Deviation`]).
pub fn surface_deviation(
    backend: &Backend,
    sdf: &dyn SdfField,
    mesh: &Mesh,
) -> Result<Deviation, BackendError> {
    let nv = mesh.positions.len();
    let mut pts = mesh.positions.clone();
    for t in mesh.triangles() {
        let p = t.map(|i| mesh.positions[i as usize]);
        for w in SAMPLE_WEIGHTS {
            pts.push(tri_point(p, w));
        }
    }
    let (values, grads) = eval_field(backend, sdf, &pts)?;
    let vn: Vec<[f32; 3]> = grads[..nv].iter().map(|&g| normalize(g)).collect();
    let mut dev = Deviation {
        distance: values[..nv]
            .iter()
            .fold(0.0f32, |w, &x| w.max(abs_or_inf(x))),
        ..Default::default()
    };
    let (mut min_cos, mut min_face) = (1.0f32, 1.0f32);
    for (t, tri) in mesh.triangles().enumerate() {
        let c = tri_check(
            tri.map(|i| mesh.positions[i as usize]),
            tri.map(|i| vn[i as usize]),
            [0.0; 3],
            |j| (values[nv + 4 * t + j], grads[nv + 4 * t + j]),
        );
        dev.distance = dev.distance.max(c.dev);
        dev.folded += c.folded as usize;
        min_cos = min_cos.min(c.cos);
        min_face = min_face.min(c.face_cos);
    }
    dev.normal_angle_deg = cos_to_deg(min_cos);
    dev.face_angle_deg = cos_to_deg(min_face);
    Ok(dev)
}

/// |v|, or infinity where the field returned NaN or infinity (no bound holds there).
fn abs_or_inf(v: f32) -> f32 {
    if v.is_finite() {
        v.abs()
    } else {
        f32::INFINITY
    }
}

fn cos_to_deg(c: f32) -> f32 {
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

/// Values and gradients of the field at `points`, in batches.
fn eval_field(
    backend: &Backend,
    sdf: &dyn SdfField,
    points: &[[f32; 3]],
) -> Result<(Vec<f32>, Vec<[f32; 3]>), BackendError> {
    let mut values = Vec::with_capacity(points.len());
    let mut grads = Vec::with_capacity(points.len());
    for part in points.chunks(1 << 18) {
        let s = sdf.eval(backend, part)?;
        values.extend(s.values);
        grads.extend(s.gradients);
    }
    Ok((values, grads))
}

/// What the field says about one triangle (see [`Deviation`]).
#[derive(Clone, Copy, Debug)]
struct TriCheck {
    /// Largest |sdf| over its vertices (as passed in) and its samples.
    dev: f32,
    /// Smallest cosine between the interpolated vertex normals and the gradient at the samples.
    cos: f32,
    /// Smallest cosine between the face normal and the gradient at the samples.
    face_cos: f32,
    /// The face normal points against the gradient at the centroid.
    folded: bool,
}

/// Check one triangle: corner positions `p`, unit vertex normals `n`, |sdf| at the corners, and
/// `sample(j)` = (value, gradient) at [`SAMPLE_WEIGHTS`]`[j]`.
fn tri_check(
    p: [[f32; 3]; 3],
    n: [[f32; 3]; 3],
    corner_abs: [f32; 3],
    sample: impl Fn(usize) -> (f32, [f32; 3]),
) -> TriCheck {
    let face = cross(sub(p[1], p[0]), sub(p[2], p[0]));
    let unit_face = normalize(face);
    let mut c = TriCheck {
        dev: corner_abs[0].max(corner_abs[1]).max(corner_abs[2]),
        cos: 1.0,
        face_cos: 1.0,
        folded: false,
    };
    for (j, w) in SAMPLE_WEIGHTS.iter().enumerate() {
        let (v, g) = sample(j);
        c.dev = c.dev.max(abs_or_inf(v));
        if j == 0 && dot(face, g) < 0.0 {
            c.folded = true;
        }
        let ni = normalize([0, 1, 2].map(|k| w[0] * n[0][k] + w[1] * n[1][k] + w[2] * n[2][k]));
        let gu = normalize(g);
        c.cos = c.cos.min(dot(ni, gu));
        c.face_cos = c.face_cos.min(dot(unit_face, gu));
    }
    c
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

// ---- simplification checked against the field ----------------------------------------------

/// Settings of [`simplify_sdf`].
#[derive(Clone, Copy, Debug)]
pub struct SdfSimplifyConfig {
    /// Largest |sdf| a collapse may leave at a vertex, edge midpoint or centroid (scene units).
    pub bound: f32,
    /// Largest angle (degrees) a collapse may leave between the interpolated vertex normals and
    /// the SDF gradient at those samples.
    pub normal_tolerance_deg: f32,
    /// Largest angle (degrees) a collapse may leave between a face normal and the SDF gradient
    /// at those samples.
    pub face_tolerance_deg: f32,
}

/// What [`simplify_sdf`] did.
#[derive(Clone, Debug, Default)]
pub struct SdfSimplifyReport {
    /// The input measured as [`surface_deviation`] would.
    pub input: Deviation,
    /// Rounds of independent collapses.
    pub rounds: usize,
    pub collapses: usize,
    /// Collapses the field check turned down (the geometric pre-checks not counted).
    pub rejected: usize,
    /// Points the field was evaluated at.
    pub field_points: usize,
    /// Largest quadric (QEM) RMS error of a collapse kept (scene units).
    pub qem_error: f32,
}

/// Area-weighted plane quadric: symmetric A (6), b (3), c, total weight.
#[derive(Clone, Copy, Default)]
struct Quadric([f64; 11]);

impl Quadric {
    fn plane(n: [f64; 3], d: f64, w: f64) -> Self {
        let [x, y, z] = n;
        Quadric([
            w * x * x,
            w * x * y,
            w * x * z,
            w * y * y,
            w * y * z,
            w * z * z,
            w * x * d,
            w * y * d,
            w * z * d,
            w * d * d,
            w,
        ])
    }
    fn add(&self, o: &Self) -> Self {
        let mut r = *self;
        for (a, b) in r.0.iter_mut().zip(o.0) {
            *a += b;
        }
        r
    }
    /// Weighted mean squared distance of `p` to the planes.
    fn error(&self, p: [f64; 3]) -> f64 {
        let q = &self.0;
        let [x, y, z] = p;
        let v = q[0] * x * x
            + q[3] * y * y
            + q[5] * z * z
            + 2.0 * (q[1] * x * y + q[2] * x * z + q[4] * y * z)
            + 2.0 * (q[6] * x + q[7] * y + q[8] * z)
            + q[9];
        (v / q[10].max(1e-300)).max(0.0)
    }
    /// Minimiser of the mean error plus `eps`·|p − m|²: the QEM optimum, kept at `m` along
    /// directions the planes leave free (flat and cylindrical regions).
    fn optimum(&self, m: [f64; 3], eps: f64) -> Option<[f64; 3]> {
        let q = &self.0;
        let w = q[10];
        if w <= 0.0 {
            return None;
        }
        let a = [
            [q[0] / w + eps, q[1] / w, q[2] / w],
            [q[1] / w, q[3] / w + eps, q[4] / w],
            [q[2] / w, q[4] / w, q[5] / w + eps],
        ];
        let r = [
            -q[6] / w + eps * m[0],
            -q[7] / w + eps * m[1],
            -q[8] / w + eps * m[2],
        ];
        let det = |a: [[f64; 3]; 3]| {
            a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
                - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
                + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
        };
        let d = det(a);
        if d.abs() < 1e-18 {
            return None;
        }
        // Cramer's rule.
        let mut x = [0.0; 3];
        for (k, xk) in x.iter_mut().enumerate() {
            let mut ak = a;
            for (row, rv) in ak.iter_mut().zip(r) {
                row[k] = rv;
            }
            *xk = det(ak) / d;
        }
        x.iter().all(|v| v.is_finite()).then_some(x)
    }
}

fn f64v(p: [f32; 3]) -> [f64; 3] {
    p.map(f64::from)
}

/// 4√3·area / (sum of squared edge lengths): 1 for an equilateral triangle, 0 for a degenerate one.
fn tri_quality(p: [[f32; 3]; 3]) -> f32 {
    let n = norm(cross(sub(p[1], p[0]), sub(p[2], p[0])));
    let l2: f32 = (0..3)
        .map(|k| {
            let e = sub(p[(k + 1) % 3], p[k]);
            dot(e, e)
        })
        .sum();
    if l2 > 0.0 {
        2.0 * 3f32.sqrt() * n / l2
    } else {
        0.0
    }
}

/// Squared distance from `q` to triangle `p`.
fn point_tri_dist2(q: [f32; 3], p: [[f32; 3]; 3]) -> f32 {
    let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
    let nn = dot(n, n);
    if nn > 1e-30 {
        let inside = (0..3).all(|k| {
            let (u, v) = (p[k], p[(k + 1) % 3]);
            dot(cross(sub(v, u), sub(q, u)), n) >= 0.0
        });
        if inside {
            let d = dot(sub(q, p[0]), n);
            return d * d / nn;
        }
    }
    (0..3)
        .map(|k| {
            let (u, v) = (p[k], p[(k + 1) % 3]);
            let d = sub(v, u);
            let t = (dot(sub(q, u), d) / dot(d, d).max(1e-30)).clamp(0.0, 1.0);
            let e = sub(q, [u[0] + t * d[0], u[1] + t * d[1], u[2] + t * d[2]]);
            dot(e, e)
        })
        .fold(f32::INFINITY, f32::min)
}

/// A field sample: value and gradient.
type Sample = (f32, [f32; 3]);

/// A collapse chosen for this round: `b` merges into `a`, which moves to `pos`; `fan` are the
/// triangles that survive it (they lose `b` for `a`).
struct Collapse {
    a: u32,
    b: u32,
    dying: [u32; 2],
    fan: Vec<u32>,
    /// Where `a` goes, and the quadric error there.
    pos: [f32; 3],
    cost: f64,
}

/// Where a collapse's field samples sit in the round's batch: the new vertex at `vertex`; per
/// fan triangle the centroid and the three edge midpoints ([`NO_POINT`]: the edge does not
/// touch the new vertex, so its midpoint and sample are unchanged).
struct FanPoints {
    vertex: usize,
    tri: Vec<[u32; 4]>,
}
const NO_POINT: u32 = u32::MAX;

impl FanPoints {
    /// Move the indices by `off` (the batch this part lands in).
    fn shift(&mut self, off: usize) {
        self.vertex += off;
        for idx in &mut self.tri {
            for i in idx.iter_mut().filter(|i| **i != NO_POINT) {
                *i += off as u32;
            }
        }
    }
}

/// A collapse that passed: the field at the new vertex and on the new fan.
struct Accepted {
    normal: [f32; 3],
    abs: f32,
    checks: Vec<TriCheck>,
    mids: Vec<[Sample; 3]>,
}

/// Quadric edge collapse where every collapse is checked against the field before it is kept.
struct FieldDecimator {
    pos: Vec<[f32; 3]>,
    /// Unit SDF gradient at each vertex (the shading normal the export ships).
    vn: Vec<[f32; 3]>,
    /// |sdf| at each vertex.
    vabs: Vec<f32>,
    quad: Vec<Quadric>,
    vtris: Vec<Vec<u32>>,
    /// On an edge that is not shared by exactly two consistently oriented triangles.
    locked: Vec<bool>,
    /// Round after which the vertex's star last changed.
    stamp: Vec<u32>,
    tris: Vec<[u32; 3]>,
    tdead: Vec<bool>,
    /// The field's verdict on each triangle as it is now.
    tcheck: Vec<TriCheck>,
    /// The field at each triangle's edge midpoints (edges 01, 12, 20): an edge a collapse does
    /// not touch keeps its midpoint bit for bit, so only the edges at the new vertex and the
    /// centroids are evaluated again.
    tmid: Vec<[Sample; 3]>,
    alive_vertices: usize,
}

/// Vertices with more neighbours than half this (a fan of over 32 triangles) are not moved.
const MAX_RING: usize = 64;
/// Candidates whose quadric RMS error exceeds this many bounds are not tried.
const QEM_SLACK: f64 = 2.0;
/// Triangle quality ([`tri_quality`]) a collapse may leave: at least MIN_QUALITY (about a 1:20
/// needle) where the triangles it replaces are at least that good, never below NEEDLE (1:200).
const MIN_QUALITY: f32 = 0.05;
const NEEDLE: f32 = 0.005;
/// Below this quality a triangle's normal is not trusted.
const SLIVER: f32 = 1e-3;
/// Positions (quadric optimum, either end) a collapse may offer the field before it is given up
/// until something around it changes.
const FIELD_TRIES: u8 = 3;

impl FieldDecimator {
    /// The neighbours of `v`, sorted, in `buf`; `None` past [`MAX_RING`] (such a vertex stays).
    fn ring<'b>(&self, v: u32, buf: &'b mut [u32; MAX_RING]) -> Option<&'b [u32]> {
        let mut n = 0;
        for &t in &self.vtris[v as usize] {
            for u in self.tris[t as usize] {
                if u != v {
                    *buf.get_mut(n)? = u;
                    n += 1;
                }
            }
        }
        let r = &mut buf[..n];
        r.sort_unstable();
        let mut m = 0;
        for i in 0..n {
            if i == 0 || r[i] != r[i - 1] {
                r[m] = r[i];
                m += 1;
            }
        }
        Some(&buf[..m])
    }

    /// The topology and geometry checks of collapsing `b` into `a` (no field evaluation):
    /// the link condition (keeps the mesh a closed manifold), no face turning over, no new
    /// sliver, and the removed vertices staying within `bound` of the new fan. The positions
    /// tried are the quadric optimum and the two ends, cheapest first; the `skip` first that
    /// pass were turned down by the field before.
    fn plan(
        &self,
        a: u32,
        b: u32,
        opt: Option<[f32; 3]>,
        q: &Quadric,
        bound: f32,
        skip: u8,
    ) -> Option<Collapse> {
        let (mut bufa, mut bufb) = ([0; MAX_RING], [0; MAX_RING]);
        let (ra, rb) = (self.ring(a, &mut bufa)?, self.ring(b, &mut bufb)?);
        let common = ra.iter().filter(|v| rb.binary_search(v).is_ok()).count();
        let mut dying = [u32::MAX; 2];
        let mut nd = 0;
        for &t in &self.vtris[a as usize] {
            if self.tris[t as usize].contains(&b) {
                if nd == 2 {
                    return None;
                }
                dying[nd] = t;
                nd += 1;
            }
        }
        if common != 2 || nd != 2 || ra.len() + rb.len() < 8 {
            return None;
        }
        let fan: Vec<u32> = self.vtris[a as usize]
            .iter()
            .chain(&self.vtris[b as usize])
            .copied()
            .filter(|t| !dying.contains(t))
            .collect();
        let (pa, pb) = (self.pos[a as usize], self.pos[b as usize]);
        let mut cands: Vec<([f32; 3], f64)> = Vec::with_capacity(3);
        for p in opt.into_iter().chain([pa, pb]) {
            if !cands.iter().any(|c| c.0 == p) {
                cands.push((p, q.error(f64v(p))));
            }
        }
        cands.sort_by(|x, y| x.1.total_cmp(&y.1));
        let bound2 = bound * bound;
        // The worst new triangle: at least MIN_QUALITY; past the worst one it replaces, half
        // of it but no needle thinner than NEEDLE. (No worse at all would leave the tiny
        // triangles and slivers marching tetrahedra makes on a face just off the grid nodes
        // stuck: any collapse there makes some sliver a little thinner.)
        let q_old = self.vtris[a as usize]
            .iter()
            .chain(&self.vtris[b as usize])
            .map(|&t| tri_quality(self.tris[t as usize].map(|v| self.pos[v as usize])))
            .fold(f32::INFINITY, f32::min);
        let q_floor = if q_old <= NEEDLE {
            q_old
        } else {
            MIN_QUALITY.min((0.5 * q_old).max(NEEDLE))
        };
        let valid = |p: [f32; 3], cost: f64| {
            if cost.sqrt() > QEM_SLACK * bound as f64 {
                return false;
            }
            let (mut near_a, mut near_b) = (f32::INFINITY, f32::INFINITY);
            for &t in &fan {
                let tri = self.tris[t as usize];
                let old = tri.map(|v| self.pos[v as usize]);
                let new = tri.map(|v| {
                    if v == a || v == b {
                        p
                    } else {
                        self.pos[v as usize]
                    }
                });
                let (no, nn) = (
                    cross(sub(old[1], old[0]), sub(old[2], old[0])),
                    cross(sub(new[1], new[0]), sub(new[2], new[0])),
                );
                // A face may not turn over (a sliver's normal is noise: the field's fold
                // check judges the new face there).
                if dot(no, nn) <= 0.0 && tri_quality(old) > SLIVER {
                    return false;
                }
                if tri_quality(new) < q_floor {
                    return false;
                }
                near_a = near_a.min(point_tri_dist2(pa, new));
                near_b = near_b.min(point_tri_dist2(pb, new));
            }
            near_a <= bound2 && near_b <= bound2
        };
        let mut seen = 0u8;
        for (p, cost) in cands {
            if valid(p, cost) {
                if seen == skip {
                    return Some(Collapse {
                        a,
                        b,
                        dying,
                        fan,
                        pos: p,
                        cost,
                    });
                }
                seen += 1;
            }
        }
        None
    }

    /// A fan triangle's corners after the collapse, and which corner is the new vertex.
    fn fan_corners(&self, c: &Collapse, t: u32) -> ([[f32; 3]; 3], usize) {
        let tri = self.tris[t as usize];
        let m = (0..3)
            .find(|&k| tri[k] == c.a || tri[k] == c.b)
            .expect("a fan triangle holds a or b");
        let mut p = tri.map(|v| self.pos[v as usize]);
        p[m] = c.pos;
        (p, m)
    }

    /// Append the collapse's new samples to `pts`.
    fn fan_points(&self, c: &Collapse, pts: &mut Vec<[f32; 3]>) -> FanPoints {
        let vertex = pts.len();
        pts.push(c.pos);
        let mut ring: Vec<(u32, u32)> = Vec::with_capacity(c.fan.len());
        let tri = c
            .fan
            .iter()
            .map(|&t| {
                let (corners, m) = self.fan_corners(c, t);
                let vs = self.tris[t as usize];
                let mut idx = [NO_POINT; 4];
                idx[0] = pts.len() as u32;
                pts.push(tri_point(corners, SAMPLE_WEIGHTS[0]));
                for e in 0..3 {
                    let (s0, s1) = (e, (e + 1) % 3);
                    if s0 != m && s1 != m {
                        continue;
                    }
                    let u = vs[if s0 == m { s1 } else { s0 }];
                    idx[1 + e] = match ring.iter().find(|r| r.0 == u) {
                        Some(r) => r.1,
                        None => {
                            let i = pts.len() as u32;
                            pts.push(tri_point(corners, SAMPLE_WEIGHTS[1 + e]));
                            ring.push((u, i));
                            i
                        }
                    };
                }
                idx
            })
            .collect();
        FanPoints { vertex, tri }
    }

    /// The field's verdict on a planned collapse: every new triangle within the bound (or no
    /// worse than the triangle it was), not folded unless it was, its normals within the
    /// tolerance (or no worse).
    fn judge(
        &self,
        c: &Collapse,
        fp: &FanPoints,
        values: &[f32],
        grads: &[[f32; 3]],
        bound: f32,
        cos_tol: f32,
        face_cos_tol: f32,
    ) -> Option<Accepted> {
        let o = fp.vertex;
        let (np, ap) = (normalize(grads[o]), abs_or_inf(values[o]));
        let mut acc = Accepted {
            normal: np,
            abs: ap,
            checks: Vec::with_capacity(c.fan.len()),
            mids: Vec::with_capacity(c.fan.len()),
        };
        for (&t, idx) in c.fan.iter().zip(&fp.tri) {
            let (corners, m) = self.fan_corners(c, t);
            let tri = self.tris[t as usize];
            let mut normals = tri.map(|v| self.vn[v as usize]);
            let mut abs = tri.map(|v| self.vabs[v as usize]);
            normals[m] = np;
            abs[m] = ap;
            let sample = |j: usize| match idx[j] {
                NO_POINT => self.tmid[t as usize][j - 1],
                i => (values[i as usize], grads[i as usize]),
            };
            let chk = tri_check(corners, normals, abs, sample);
            let old = self.tcheck[t as usize];
            if chk.dev > bound.max(old.dev)
                || chk.cos < cos_tol.min(old.cos)
                || chk.face_cos < face_cos_tol.min(old.face_cos)
                || (chk.folded && !old.folded)
            {
                return None;
            }
            acc.checks.push(chk);
            acc.mids.push([sample(1), sample(2), sample(3)]);
        }
        Some(acc)
    }

    fn apply(&mut self, c: &Collapse, acc: Accepted, round: u32) {
        let (a, b) = (c.a, c.b);
        for &t in &c.dying {
            self.tdead[t as usize] = true;
            for v in self.tris[t as usize] {
                self.vtris[v as usize].retain(|&x| x != t);
            }
        }
        let moved = std::mem::take(&mut self.vtris[b as usize]);
        for &t in &moved {
            for v in self.tris[t as usize].iter_mut() {
                if *v == b {
                    *v = a;
                }
            }
        }
        self.vtris[a as usize].extend(moved);
        self.pos[a as usize] = c.pos;
        self.vn[a as usize] = acc.normal;
        self.vabs[a as usize] = acc.abs;
        self.quad[a as usize] = self.quad[a as usize].add(&self.quad[b as usize]);
        self.alive_vertices -= 1;
        for ((&t, chk), mids) in c.fan.iter().zip(acc.checks).zip(acc.mids) {
            self.tcheck[t as usize] = chk;
            self.tmid[t as usize] = mids;
        }
        for &t in &self.vtris[a as usize] {
            for v in self.tris[t as usize] {
                self.stamp[v as usize] = round + 1;
            }
        }
    }
}

/// Simplify a closed mesh by quadric edge collapses, each one checked against the field before
/// it is kept: the fan it leaves must stay within `bound` of the surface (|sdf| at the new vertex
/// and at every new triangle's edge midpoints and centroid), keep its faces along the SDF
/// gradient (no folds) and its interpolated vertex normals within the normal tolerance of the
/// gradient. A triangle that broke one of these already may keep doing so, no worse. So
/// [`surface_deviation`] of the result is at most the larger of the bound and the input's, the
/// result has no more folded triangles than the input, and it stays closed (link condition).
///
/// This is what keeps thin sheets (the visual hull's background sheets, thin parts of a trained
/// SDF) within the bound: a collapse that drags one side of a sheet through the other leaves
/// faces against the gradient, or normals off it, and is refused; meshoptimizer's quadrics
/// cannot tell the two sides apart.
///
/// Collapses run in rounds: the cheapest independent collapses (no shared triangle or
/// neighbour), their field samples evaluated in one batch per round, so a GPU field sees few,
/// large batches. It stops when no collapse passes.
pub fn simplify_sdf(
    backend: &Backend,
    sdf: &dyn SdfField,
    mesh: &Mesh,
    cfg: &SdfSimplifyConfig,
) -> Result<(Mesh, SdfSimplifyReport), BackendError> {
    simplify_sdf_with(backend, sdf, mesh, cfg, &indicatif::ProgressBar::hidden())
}

/// [`simplify_sdf`], each round's triangle count in `progress`'s message.
pub fn simplify_sdf_with(
    backend: &Backend,
    sdf: &dyn SdfField,
    mesh: &Mesh,
    cfg: &SdfSimplifyConfig,
    progress: &indicatif::ProgressBar,
) -> Result<(Mesh, SdfSimplifyReport), BackendError> {
    use rayon::prelude::*;

    let bound = cfg.bound;
    let cos_tol = cfg.normal_tolerance_deg.to_radians().cos();
    let face_cos_tol = cfg.face_tolerance_deg.to_radians().cos();
    let nv = mesh.positions.len();
    let tris: Vec<[u32; 3]> = mesh.triangles().collect();
    let mut report = SdfSimplifyReport::default();
    progress.set_message(format!("simplifying {} triangles: the field at their samples", tris.len()));

    // The field at every vertex, centroid and edge midpoint of the input (each edge once).
    // Edges are found as (min << 32 | max, slot 3t + k) sorted; an edge not shared by exactly two
    // triangles in opposite directions (open, non-manifold or flipped) locks its vertices.
    let mut pts = mesh.positions.clone();
    let mut tidx: Vec<[u32; 4]> = vec![[0; 4]; tris.len()];
    for (t, tri) in tris.iter().enumerate() {
        tidx[t][0] = pts.len() as u32;
        pts.push(tri_point(
            tri.map(|i| mesh.positions[i as usize]),
            SAMPLE_WEIGHTS[0],
        ));
    }
    let mut locked = vec![false; nv];
    {
        let mut edges: Vec<(u64, u32)> = tris
            .iter()
            .enumerate()
            .flat_map(|(t, tri)| {
                (0..3).map(move |k| {
                    let (a, b) = (tri[k] as u64, tri[(k + 1) % 3] as u64);
                    ((a.min(b) << 32) | a.max(b), (3 * t + k) as u32)
                })
            })
            .collect();
        edges.par_sort_unstable();
        let forward = |slot: u32| {
            let tri = tris[slot as usize / 3];
            let k = slot as usize % 3;
            tri[k] < tri[(k + 1) % 3]
        };
        for group in edges.chunk_by(|x, y| x.0 == y.0) {
            let (key, slot) = group[0];
            let (t, e) = (slot as usize / 3, slot as usize % 3);
            let p = tris[t].map(|i| mesh.positions[i as usize]);
            let i = pts.len() as u32;
            pts.push(tri_point(p, SAMPLE_WEIGHTS[1 + e]));
            for &(_, s) in group {
                tidx[s as usize / 3][1 + s as usize % 3] = i;
            }
            if group.len() != 2 || forward(group[0].1) == forward(group[1].1) {
                locked[(key >> 32) as usize] = true;
                locked[(key & 0xffff_ffff) as usize] = true;
            }
        }
    }
    let (values, grads) = eval_field(backend, sdf, &pts)?;
    report.field_points += pts.len();
    drop(pts);
    let vn: Vec<[f32; 3]> = grads[..nv].iter().map(|&g| normalize(g)).collect();
    let vabs: Vec<f32> = values[..nv].iter().map(|&v| abs_or_inf(v)).collect();
    let sample = |i: u32| (values[i as usize], grads[i as usize]);
    let tcheck: Vec<TriCheck> = tris
        .iter()
        .zip(&tidx)
        .map(|(tri, idx)| {
            tri_check(
                tri.map(|i| mesh.positions[i as usize]),
                tri.map(|i| vn[i as usize]),
                tri.map(|i| vabs[i as usize]),
                |j| sample(idx[j]),
            )
        })
        .collect();
    let tmid: Vec<[Sample; 3]> = tidx
        .iter()
        .map(|idx| [sample(idx[1]), sample(idx[2]), sample(idx[3])])
        .collect();
    drop((values, grads, tidx));
    report.input = Deviation {
        distance: tcheck.iter().fold(0.0f32, |w, c| w.max(c.dev)),
        folded: tcheck.iter().filter(|c| c.folded).count(),
        normal_angle_deg: cos_to_deg(tcheck.iter().fold(1.0f32, |w, c| w.min(c.cos))),
        face_angle_deg: cos_to_deg(tcheck.iter().fold(1.0f32, |w, c| w.min(c.face_cos))),
    };

    let mut quad = vec![Quadric::default(); nv];
    let mut vtris = vec![Vec::new(); nv];
    for (t, tri) in tris.iter().enumerate() {
        let p = tri.map(|i| f64v(mesh.positions[i as usize]));
        let e1 = [0, 1, 2].map(|k| p[1][k] - p[0][k]);
        let e2 = [0, 1, 2].map(|k| p[2][k] - p[0][k]);
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len > 0.0 {
            let u = n.map(|x| x / len);
            let d = -(u[0] * p[0][0] + u[1] * p[0][1] + u[2] * p[0][2]);
            let q = Quadric::plane(u, d, 0.5 * len);
            for &v in tri {
                quad[v as usize] = quad[v as usize].add(&q);
            }
        }
        for &v in tri {
            vtris[v as usize].push(t as u32);
        }
    }
    let alive_vertices = vtris.iter().filter(|t| !t.is_empty()).count();
    let mut dec = FieldDecimator {
        pos: mesh.positions.clone(),
        vn,
        vabs,
        quad,
        vtris,
        locked,
        stamp: vec![0; nv],
        tdead: vec![false; tris.len()],
        tris,
        tcheck,
        tmid,
        alive_vertices,
    };

    // Per triangle edge slot 3t + k (the edge tris[t][k] → tris[t][(k + 1) % 3]): the round the
    // edge was last turned down and how many of its positions the field had turned down then
    // (REFUSED: all, or the topology/geometry checks). Stale once a star around it changes.
    const REFUSED: u8 = u8::MAX;
    let mut memo: Vec<(u32, u8)> = vec![(0, 0); 3 * dec.tris.len()];
    let mut mark = vec![false; nv];
    let mut max_cost = 0.0f64;
    let mut alive: Vec<u32> = (0..dec.tris.len() as u32).collect();
    // Per slot: the round the quadric optimum was computed in (0: never), its error, the point.
    let mut qcache: Vec<(u32, f32, [f32; 3])> = vec![(0, 0.0, [0.0; 3]); 3 * dec.tris.len()];
    let cost_limit = ((QEM_SLACK * bound as f64).powi(2)) as f32;
    for round in 1u32.. {
        alive.retain(|&t| !dec.tdead[t as usize]);
        progress.set_message(format!(
            "simplifying: {} → {} triangles (round {round}, {} collapses turned down by the field)",
            dec.tris.len(),
            alive.len(),
            report.rejected
        ));
        // Each candidate edge once (a < b along a triangle), never one at a locked vertex.
        let (tris, locked) = (&dec.tris, &dec.locked);
        let edges = move |t: u32| {
            let tri = tris[t as usize];
            (0..3u32).filter_map(move |k| {
                let (a, b) = (tri[k as usize], tri[(k as usize + 1) % 3]);
                let ok = a < b && !locked[a as usize] && !locked[b as usize];
                ok.then_some((3 * t + k, a, b))
            })
        };
        // The field positions already turned down for an edge (REFUSED: give up for now).
        let skip = |slot: u32, a: u32, b: u32| {
            let (r, tried) = memo[slot as usize];
            let newest = dec.stamp[a as usize].max(dec.stamp[b as usize]);
            if newest > r {
                0
            } else {
                tried
            }
        };
        // The quadric optimum of each candidate, kept from an earlier round while the stars
        // around the edge are unchanged.
        let fresh: Vec<(u32, f32, [f32; 3])> = alive
            .par_iter()
            .with_min_len(1 << 12)
            .flat_map_iter(|&t| edges(t))
            .filter_map(|(slot, a, b)| {
                let rc = qcache[slot as usize].0;
                let newest = dec.stamp[a as usize].max(dec.stamp[b as usize]);
                if (rc != 0 && newest <= rc) || skip(slot, a, b) == REFUSED {
                    return None;
                }
                let q = dec.quad[a as usize].add(&dec.quad[b as usize]);
                let (pa, pb) = (f64v(dec.pos[a as usize]), f64v(dec.pos[b as usize]));
                let m = [0, 1, 2].map(|k| 0.5 * (pa[k] + pb[k]));
                let len2: f64 = (0..3).map(|k| (pb[k] - pa[k]).powi(2)).sum();
                Some(
                    match q
                        .optimum(m, 1e-3)
                        .filter(|o| (0..3).map(|k| (o[k] - m[k]).powi(2)).sum::<f64>() <= len2)
                    {
                        Some(o) => {
                            let of = o.map(|x| x as f32);
                            (slot, q.error(f64v(of)) as f32, of)
                        }
                        None => (slot, q.error(pa).min(q.error(pb)) as f32, [f32::NAN; 3]),
                    },
                )
            })
            .collect();
        for (slot, cost, opt) in fresh {
            qcache[slot as usize] = (round, cost, opt);
        }
        // Edges between vertices of folded triangles go first: collapsing one is what removes
        // a fold the input came with.
        let folded: Vec<u32> = alive
            .iter()
            .copied()
            .filter(|&t| dec.tcheck[t as usize].folded)
            .collect();
        for &t in &folded {
            for v in dec.tris[t as usize] {
                mark[v as usize] = true;
            }
        }
        // Candidates as (cost bits << 32 | slot, a << 32 | b): costs are ≥ 0, so their f32 bits
        // sort like the values. Each round looks at the cheapest ones only: past about half the
        // vertex count nearly all are blocked by a cheaper neighbour anyway.
        let near_fold = &mark;
        let mut cands: Vec<(u64, u64)> = alive
            .par_iter()
            .with_min_len(1 << 12)
            .flat_map_iter(|&t| edges(t))
            .filter_map(|(slot, a, b)| {
                let mut cost = qcache[slot as usize].1;
                if cost > cost_limit || skip(slot, a, b) == REFUSED {
                    return None;
                }
                if near_fold[a as usize] && near_fold[b as usize] {
                    cost = 0.0;
                }
                Some((
                    (cost.to_bits() as u64) << 32 | slot as u64,
                    (a as u64) << 32 | b as u64,
                ))
            })
            .collect();
        for &t in &folded {
            for v in dec.tris[t as usize] {
                mark[v as usize] = false;
            }
        }
        let keep = cands.len().min((dec.alive_vertices / 2).max(1 << 12));
        if keep < cands.len() {
            cands.select_nth_unstable(keep);
            cands.truncate(keep);
        }
        cands.par_sort_unstable();
        // Greedy independent set: no two chosen collapses share a triangle or a vertex around
        // one, so they can be checked against the same state and applied in any order.
        let mut chosen: Vec<(u32, u32, u32)> = Vec::new();
        let mut marked: Vec<u32> = Vec::new();
        let budget = dec.alive_vertices.saturating_sub(4);
        for &(key, ab) in &cands {
            let (a, b) = ((ab >> 32) as u32, ab as u32);
            if chosen.len() >= budget {
                break;
            }
            if mark[a as usize] || mark[b as usize] {
                continue;
            }
            for v in [a, b] {
                for &t in &dec.vtris[v as usize] {
                    for u in dec.tris[t as usize] {
                        if !mark[u as usize] {
                            mark[u as usize] = true;
                            marked.push(u);
                        }
                    }
                }
            }
            chosen.push((key as u32, a, b));
        }
        for v in marked {
            mark[v as usize] = false;
        }
        if chosen.is_empty() {
            break;
        }
        let planned: Vec<Option<Collapse>> = chosen
            .par_iter()
            .with_min_len(256)
            .map(|&(slot, a, b)| {
                let q = dec.quad[a as usize].add(&dec.quad[b as usize]);
                let opt = qcache[slot as usize].2;
                let opt = (!opt[0].is_nan()).then_some(opt);
                dec.plan(a, b, opt, &q, bound, skip(slot, a, b))
            })
            .collect();
        // One batch of field samples for the whole round.
        let live: Vec<&Collapse> = planned.iter().flatten().collect();
        let parts: Vec<(Vec<[f32; 3]>, FanPoints)> = live
            .par_iter()
            .with_min_len(256)
            .map(|c| {
                let mut p = Vec::with_capacity(1 + 2 * c.fan.len());
                let f = dec.fan_points(c, &mut p);
                (p, f)
            })
            .collect();
        let mut pts: Vec<[f32; 3]> = Vec::with_capacity(parts.iter().map(|p| p.0.len()).sum());
        let fans: Vec<FanPoints> = parts
            .into_iter()
            .map(|(p, mut f)| {
                let off = pts.len();
                pts.extend(p);
                f.shift(off);
                f
            })
            .collect();
        let (values, grads) = eval_field(backend, sdf, &pts)?;
        report.field_points += pts.len();
        let verdicts: Vec<Option<Accepted>> = live
            .par_iter()
            .zip(&fans)
            .with_min_len(256)
            .map(|(c, fp)| dec.judge(c, fp, &values, &grads, bound, cos_tol, face_cos_tol))
            .collect();
        report.rounds += 1;
        let mut verdicts = verdicts.into_iter();
        let skips: Vec<u8> = chosen
            .iter()
            .map(|&(slot, a, b)| skip(slot, a, b))
            .collect();
        for ((&(slot, ..), plan), skip) in chosen.iter().zip(&planned).zip(skips) {
            let Some(c) = plan else {
                memo[slot as usize] = (round, REFUSED);
                continue;
            };
            match verdicts.next().expect("one verdict per plan") {
                Some(acc) => {
                    max_cost = max_cost.max(c.cost);
                    dec.apply(c, acc, round);
                    report.collapses += 1;
                }
                None => {
                    let tried = if skip + 1 >= FIELD_TRIES {
                        REFUSED
                    } else {
                        skip + 1
                    };
                    memo[slot as usize] = (round, tried);
                    report.rejected += 1;
                }
            }
        }
        tracing::trace!(
            "simplify round {round}: {} vertices, {} candidates, {} chosen, {} collapses so far",
            dec.alive_vertices,
            cands.len(),
            chosen.len(),
            report.collapses
        );
    }
    report.qem_error = max_cost.sqrt() as f32;
    let mut out = Mesh {
        positions: dec.pos,
        indices: dec
            .tris
            .iter()
            .zip(&dec.tdead)
            .filter(|(_, &d)| !d)
            .flat_map(|(t, _)| *t)
            .collect(),
    };
    out.compact();
    Ok((out, report))
}

/// Parts below 1% of the largest component's triangles are specks. Measured on the exports at
/// hand: a trained SDF's floater was 24 of 274k triangles (0.009%); the ball resting (not
/// touching) in `make_scene.py`'s bowl is 40k of 304k (13%), and keeping only the largest
/// component shipped the bowl without its ball.
pub const MIN_COMPONENT_FRACTION: f32 = 0.01;

/// Meshes from this many triangles get meshoptimizer's pre-pass (see [`build_mesh`]).
const PRESIMPLIFY_MIN_TRIANGLES: usize = 200_000;

/// Grid → surface → its parts (specks dropped) → closed → simplified → normals.
pub fn build_mesh(
    backend: &Backend,
    sdf: &dyn SdfField,
    cfg: &MeshConfig,
) -> Result<MeshResult, MeshError> {
    build_mesh_with(backend, sdf, cfg, &indicatif::ProgressBar::hidden())
}

/// [`build_mesh`], saying what it is doing in `progress`'s message (the grid, the marching,
/// each simplification round's triangle count; last: the triangles meshed and shipped).
pub fn build_mesh_with(
    backend: &Backend,
    sdf: &dyn SdfField,
    cfg: &MeshConfig,
    progress: &indicatif::ProgressBar,
) -> Result<MeshResult, MeshError> {
    if !(8..=2048).contains(&cfg.resolution) {
        return Err(MeshError::Resolution(cfg.resolution));
    }
    let grid = GridSpec::over(&sdf.bounds(), cfg.resolution);
    let [gx, gy, gz] = grid.dims;
    progress.set_message(format!("meshing: the field on a {gx}×{gy}×{gz} grid"));
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
    progress.set_message("meshing: marching tetrahedra");
    let t = Instant::now();
    let raw = extract::marching_tetrahedra(&grid, &values);
    drop(values);
    stats.extracted_triangles = raw.triangle_count();
    stats.seconds_extract = t.elapsed().as_secs_f64();

    tracing::debug!("extracted mesh: closed {:?}", topology::check_closed(&raw));
    let t = Instant::now();
    let (mut mesh, components) = topology::main_components(&raw, cfg.min_component_fraction);
    stats.components = components;
    stats.dropped_triangles = raw.triangle_count() - mesh.triangle_count();
    stats.holes_closed = topology::close_holes(&mut mesh);
    stats.seconds_cleanup = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let bound = cfg.error_bound.unwrap_or(cfg.bound_cells * grid.spacing);
    if !(bound.is_finite() && bound > 0.0) {
        return Err(MeshError::Config(format!(
            "simplification error bound must be > 0, got {bound}"
        )));
    }
    let (tol, face_tol) = (cfg.normal_tolerance_deg, cfg.face_tolerance_deg);
    // A large mesh first loses most of its marching-tetrahedra triangles (far below the bound)
    // to meshoptimizer at a quarter of the bound, kept only where the field finds that result
    // closed, within the bound, unfolded and within the normal tolerance everywhere: on large
    // smooth surfaces it saves most of the field-checked collapses and their field evaluations.
    // On thin sheets and sharp creases it fails that check (or is not closed) and the
    // field-checked collapses start from the full mesh.
    let mut start = None;
    if mesh.triangle_count() >= PRESIMPLIFY_MIN_TRIANGLES {
        progress.set_message(format!("simplifying {} triangles: meshoptimizer pre-pass", mesh.triangle_count()));
        let pre = simplify(&mesh, 0.25 * bound).0;
        if pre.triangle_count() * 2 <= mesh.triangle_count() && topology::check_closed(&pre).is_ok()
        {
            let d = surface_deviation(backend, sdf, &pre)?;
            tracing::debug!(
                "meshoptimizer pre-pass: {} → {} triangles, {d:?}",
                mesh.triangle_count(),
                pre.triangle_count()
            );
            if d.distance <= bound && d.folded == 0 && d.normal_angle_deg <= tol && d.face_angle_deg <= face_tol {
                stats.presimplified_triangles = pre.triangle_count();
                start = Some(pre);
            }
        }
    }
    let from = start.unwrap_or(mesh);
    // Quadric edge collapses, each checked against the field itself (|sdf| at the new vertex,
    // edge midpoints and centroids; faces along the gradient; normals within the tolerance):
    // meshoptimizer's quadrics alone cannot tell the two sides of a thin sheet apart, and its
    // collapses across one leave the measured deviation far above the bound (see simplify_sdf).
    let (simplified, report) = simplify_sdf_with(
        backend,
        sdf,
        &from,
        &SdfSimplifyConfig {
            bound,
            normal_tolerance_deg: tol,
            face_tolerance_deg: face_tol,
        },
        progress,
    )?;
    let dev = surface_deviation(backend, sdf, &simplified)?;
    let input = report.input;
    let closed = topology::check_closed(&simplified);
    tracing::debug!(
        "simplified {} → {} triangles in {} rounds ({} collapses turned down by the field, {} field points): {dev:?}, closed {closed:?}",
        from.triangle_count(),
        simplified.triangle_count(),
        report.rounds,
        report.rejected,
        report.field_points
    );
    // The checks make the result no worse than the input on every count; anything else is a bug.
    let holds = closed.is_ok() == topology::check_closed(&from).is_ok()
        && dev.distance <= bound.max(input.distance)
        && dev.folded <= input.folded
        && dev.normal_angle_deg <= tol.max(input.normal_angle_deg) + 1e-3
        && dev.face_angle_deg <= face_tol.max(input.face_angle_deg) + 1e-3;
    let (mesh, dev) = if holds {
        let indices =
            meshopt::optimize_vertex_cache(&simplified.indices, simplified.positions.len());
        (
            Mesh {
                positions: simplified.positions,
                indices,
            },
            dev,
        )
    } else {
        tracing::warn!(
            "simplifying {} broke its own checks ({dev:?} vs the input's {input:?}, closed {closed:?}); exporting the unsimplified mesh",
            sdf.name()
        );
        (from, input)
    };
    // The checks above keep the result within max(bound, the unsimplified mesh's own deviation):
    // a deviation above the bound is then the marching grid's own (its linear interpolation at
    // thin parts and sharp bends, a fraction of a cell on trained fields at any resolution), not
    // the simplifier's. It is in the report (MeshStats::unsimplified) and logged at info level,
    // so that a warning on every trained export does not teach users to ignore warnings.
    if dev.distance > bound {
        tracing::info!(
            "the marching grid is itself {} off the field at its worst point (simplified: {}), above the error bound {bound}; the simplification added nothing beyond it",
            input.distance,
            dev.distance
        );
    }
    stats.seconds_simplify = t.elapsed().as_secs_f64();
    stats.error_bound = bound;
    stats.simplify_error = if holds { report.qem_error } else { 0.0 };
    stats.simplify_target = bound;
    stats.measured_deviation = dev.distance;
    stats.folded_triangles = dev.folded;
    stats.normal_angle_deg = dev.normal_angle_deg;
    stats.face_angle_deg = dev.face_angle_deg;
    stats.unsimplified = input;
    stats.simplify_rounds = report.rounds;
    stats.simplify_rejected = report.rejected;
    stats.simplify_field_points = report.field_points;
    stats.triangles = mesh.triangle_count();
    stats.vertices = mesh.positions.len();
    stats.watertight = topology::check_closed(&mesh).is_ok();
    let normals = sdf_normals(backend, sdf, &mesh.positions)?;
    progress.set_message(format!(
        "meshed: {} → {} triangles in {} simplification rounds",
        stats.extracted_triangles, stats.triangles, stats.simplify_rounds
    ));
    Ok(MeshResult {
        mesh,
        normals,
        stats,
    })
}
