//! Thin parts through `build_mesh`: sheets thinner than a few grid cells (the visual hull's
//! background sheets, thin parts of a trained SDF) simplify to a small mesh that stays within the
//! error bound, unfolded and closed, and the sheet keeps both its sides. meshoptimizer alone
//! (the old path) moved vertices across such sheets: over the bound with folded faces (the bent
//! sheet), or no closed result at all and the unsimplified mesh shipped (the rippled sheet).

use pii_bake::backend::{Backend, BackendError};
use pii_bake::mesh::field::{Aabb, SdfField, SdfSamples};
use pii_bake::mesh::grid::GridSpec;
use pii_bake::mesh::{build_mesh, topology, Mesh, MeshConfig, MeshResult};

/// An analytic field from a distance function (central-difference gradient).
struct Field<F: Fn([f32; 3]) -> f32 + Send + Sync> {
    name: &'static str,
    bounds: Aabb,
    sdf: F,
}

impl<F: Fn([f32; 3]) -> f32 + Send + Sync> SdfField for Field<F> {
    fn name(&self) -> String {
        self.name.into()
    }
    fn bounds(&self) -> Aabb {
        self.bounds
    }
    fn eval(&self, _backend: &Backend, points: &[[f32; 3]]) -> Result<SdfSamples, BackendError> {
        let e = 1e-4f32;
        let values = points.iter().map(|&p| (self.sdf)(p)).collect();
        let gradients = points
            .iter()
            .map(|&p| {
                [0, 1, 2].map(|k| {
                    let (mut a, mut b) = (p, p);
                    a[k] += e;
                    b[k] -= e;
                    ((self.sdf)(a) - (self.sdf)(b)) / (2.0 * e)
                })
            })
            .collect();
        Ok(SdfSamples { values, gradients })
    }
}

/// A cylindrical shell segment: the arc of radius `r` around +Y over angles |θ| <= `alpha` from
/// +Z, thickened to `t`, over |y| <= `h`. Exact distance.
#[derive(Clone, Copy)]
struct BentSheet {
    r: f32,
    alpha: f32,
    t: f32,
    h: f32,
}

impl BentSheet {
    fn sdf(&self, [x, y, z]: [f32; 3]) -> f32 {
        let th = x.atan2(z);
        let to_arc = if th.abs() <= self.alpha {
            ((x * x + z * z).sqrt() - self.r).abs()
        } else {
            let (ex, ez) = (
                self.r * self.alpha.sin() * th.signum(),
                self.r * self.alpha.cos(),
            );
            ((x - ex).powi(2) + (z - ez).powi(2)).sqrt()
        };
        let (wx, wy) = (to_arc - 0.5 * self.t, y.abs() - self.h);
        wx.max(wy).min(0.0) + (wx.max(0.0).powi(2) + wy.max(0.0).powi(2)).sqrt()
    }
    /// A point on one face of the sheet (`side` ±1: outer/inner), away from its rims.
    fn face_point(&self, side: f32, u: f32, v: f32) -> [f32; 3] {
        let (th, y) = (0.8 * self.alpha * u, 0.8 * self.h * v);
        let rr = self.r + side * 0.5 * self.t;
        [rr * th.sin(), y, rr * th.cos()]
    }
}

fn sd_box(p: [f32; 3], c: [f32; 3], h: [f32; 3]) -> f32 {
    let q = [0, 1, 2].map(|k| (p[k] - c[k]).abs() - h[k]);
    let o = q.map(|x| x.max(0.0));
    (o[0] * o[0] + o[1] * o[1] + o[2] * o[2]).sqrt() + q[0].max(q[1]).max(q[2]).min(0.0)
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Distance from `p` to triangle `t` (closest point by region tests).
fn point_triangle(p: [f32; 3], t: [[f32; 3]; 3]) -> f32 {
    let n = cross(sub(t[1], t[0]), sub(t[2], t[0]));
    let nn = dot(n, n);
    if nn > 1e-30 {
        let inside = (0..3).all(|k| dot(cross(sub(t[(k + 1) % 3], t[k]), sub(p, t[k])), n) >= 0.0);
        if inside {
            return dot(sub(p, t[0]), n).abs() / nn.sqrt();
        }
    }
    (0..3)
        .map(|k| {
            let (u, v) = (t[k], t[(k + 1) % 3]);
            let d = sub(v, u);
            let s = (dot(sub(p, u), d) / dot(d, d).max(1e-30)).clamp(0.0, 1.0);
            let e = sub(p, [u[0] + s * d[0], u[1] + s * d[1], u[2] + s * d[2]]);
            dot(e, e).sqrt()
        })
        .fold(f32::INFINITY, f32::min)
}

/// The largest |sdf| over vertices, edge midpoints and centroids, and the triangles whose face
/// normal points against the gradient at the centroid, computed here from the field directly.
fn deviation_and_folds(sdf: &dyn SdfField, m: &Mesh) -> (f32, usize) {
    let mut pts = Vec::new();
    for t in m.triangles() {
        let [a, b, c] = t.map(|i| m.positions[i as usize]);
        for w in [
            [1.0, 0.0, 0.0],
            [0.5, 0.5, 0.0],
            [0.0, 0.5, 0.5],
            [0.5, 0.0, 0.5],
            [1.0 / 3.0; 3],
        ] {
            pts.push([0, 1, 2].map(|k| w[0] * a[k] + w[1] * b[k] + w[2] * c[k]));
        }
    }
    let s = sdf.eval(&Backend::cpu(), &pts).unwrap();
    let worst = s.values.iter().fold(0.0f32, |w, v| w.max(v.abs()));
    let folded = m
        .triangles()
        .enumerate()
        .filter(|&(i, t)| {
            let [a, b, c] = t.map(|i| m.positions[i as usize]);
            dot(cross(sub(b, a), sub(c, a)), s.gradients[5 * i + 4]) < 0.0
        })
        .count();
    (worst, folded)
}

fn mesh(sdf: &dyn SdfField, resolution: usize) -> (MeshResult, f32) {
    let bound = 0.5 * GridSpec::over(&sdf.bounds(), resolution).spacing;
    let res = build_mesh(
        &Backend::cpu(),
        sdf,
        &MeshConfig {
            resolution,
            error_bound: Some(bound),
            ..Default::default()
        },
    )
    .unwrap();
    let st = &res.stats;
    eprintln!(
        "{}: bound {bound:.4}, {} -> {} triangles, deviation {:.4} (unsimplified {:.4}), folded {} \
         (unsimplified {}), normals {:.1} deg, {} rounds, {} collapses turned down, {:.2} s",
        sdf.name(),
        st.extracted_triangles,
        st.triangles,
        st.measured_deviation,
        st.unsimplified.distance,
        st.folded_triangles,
        st.unsimplified.folded,
        st.normal_angle_deg,
        st.simplify_rounds,
        st.simplify_rejected,
        st.seconds_simplify
    );
    (res, bound)
}

/// Closed, far fewer triangles, and the report's figures are the field's own.
fn check_common(sdf: &dyn SdfField, res: &MeshResult) -> (f32, usize) {
    let st = &res.stats;
    topology::check_closed(&res.mesh)
        .unwrap_or_else(|e| panic!("{}: simplified mesh not closed: {e}", sdf.name()));
    assert!(
        st.watertight && st.components == 1,
        "{}: {st:?}",
        sdf.name()
    );
    assert!(
        st.triangles * 20 < st.extracted_triangles,
        "{}: {} of {} triangles left (the unsimplified mesh shipped?)",
        sdf.name(),
        st.triangles,
        st.extracted_triangles
    );
    let (dev, folded) = deviation_and_folds(sdf, &res.mesh);
    assert!(
        (dev - st.measured_deviation).abs() <= 1e-6 && folded == st.folded_triangles,
        "{}: the report says {} / {} folded, the field {dev} / {folded}",
        sdf.name(),
        st.measured_deviation,
        st.folded_triangles
    );
    (dev, folded)
}

#[test]
fn thin_bent_sheet_and_fin_simplify_within_the_bound() {
    // Thickness 2.6 grid cells (0.05 against a spacing of 0.019): resolved by the grid, but only
    // 2.6 error bounds thick, so a collapse across it is cheap for quadrics alone.
    let sheet = BentSheet {
        r: 0.7,
        alpha: 0.9,
        t: 0.05,
        h: 0.5,
    };
    let field = Field {
        name: "bent sheet",
        bounds: Aabb {
            min: [-0.9, -0.7, -0.2],
            max: [0.9, 0.7, 0.9],
        },
        sdf: move |p| sheet.sdf(p),
    };
    let (res, bound) = mesh(&field, 96);
    let st = &res.stats;
    assert!(
        st.unsimplified.distance <= bound && st.unsimplified.folded == 0,
        "the unsimplified sheet is within the bound and unfolded: {:?}",
        st.unsimplified
    );
    let (dev, folded) = check_common(&field, &res);
    assert!(dev <= bound, "deviation {dev} > bound {bound}");
    assert_eq!(folded, 0, "folded triangles");
    assert!(st.normal_angle_deg <= 10f32.max(st.unsimplified.normal_angle_deg) + 1e-3);
    // Both faces of the sheet are still there: every point on either face is near the mesh. A
    // sheet pulled together (or one side dragged through the other) leaves the faces t/2 = 2.6
    // bounds away from it.
    let tris: Vec<[[f32; 3]; 3]> = res
        .mesh
        .triangles()
        .map(|t| t.map(|i| res.mesh.positions[i as usize]))
        .collect();
    let mut worst = 0.0f32;
    for side in [-1.0, 1.0] {
        for i in 0..=10 {
            for j in 0..=10 {
                let p = sheet.face_point(side, i as f32 / 5.0 - 1.0, j as f32 / 5.0 - 1.0);
                let d = tris
                    .iter()
                    .map(|&t| point_triangle(p, t))
                    .fold(f32::INFINITY, f32::min);
                worst = worst.max(d);
            }
        }
    }
    assert!(
        worst <= 1.5 * bound,
        "a face of the sheet is {worst} from the mesh (bound {bound}, half thickness {})",
        0.5 * sheet.t
    );

    // A box with a thin fin (1.6 cells thick): sharp edges, a thin plate sticking out.
    let fin = Field {
        name: "box with a thin fin",
        bounds: Aabb::cube(1.0),
        sdf: |p| {
            sd_box(p, [-0.35, 0.0, 0.0], [0.3, 0.3, 0.3]).min(sd_box(
                p,
                [0.3, 0.0, 0.0],
                [0.4, 0.025, 0.25],
            ))
        },
    };
    let (res, bound) = mesh(&fin, 64);
    let (dev, folded) = check_common(&fin, &res);
    let before = res.stats.unsimplified;
    assert!(
        dev <= bound.max(before.distance) && folded <= before.folded,
        "{dev} / {folded} folded against the unsimplified {before:?}"
    );
}

#[test]
fn rippled_thin_sheet_is_simplified_not_shipped_whole() {
    // A thin sheet rippled in two directions, thickness 1.6 cells. meshoptimizer's result was
    // never closed at any target here, so the old path shipped the 36k-triangle mesh as is.
    let field = Field {
        name: "rippled sheet",
        bounds: Aabb::cube(1.0),
        sdf: |p: [f32; 3]| {
            let (a, k) = (0.15f32, 7.0f32);
            let y = p[1] - a * (k * p[0]).sin() * (0.5 * k * p[2]).cos();
            let slope = (1.0 + (a * k * (k * p[0]).cos()).powi(2)).sqrt();
            (y.abs() / slope - 0.025).max(sd_box(p, [0.0; 3], [0.7, 0.6, 0.6]))
        },
    };
    let (res, bound) = mesh(&field, 64);
    let (dev, folded) = check_common(&field, &res);
    let before = res.stats.unsimplified;
    assert!(before.distance <= bound, "{before:?}");
    assert!(dev <= bound, "deviation {dev} > bound {bound}");
    // This field is not an exact distance, and marching tetrahedra folds a few faces where the
    // sheet is thinnest; simplification may remove such folds but never adds one.
    assert!(
        folded <= before.folded,
        "{folded} folded, {} before",
        before.folded
    );
}
