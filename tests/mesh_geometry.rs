//! Geometry of the extracted and simplified meshes against the analytic surfaces: two-sided
//! Hausdorff distance within the grid spacing, simplified mesh within its error bound,
//! watertight and consistently outward; and the bad-input cases (no surface, surface touching
//! the box).

use pii_bake::backend::Backend;
use pii_bake::mesh::field::{Aabb, AnalyticSdf, AnalyticShape};
use pii_bake::mesh::grid::GridSpec;
use pii_bake::mesh::{build_mesh, build_mesh_with, extract, sample_grid, topology, Mesh, MeshConfig, MeshError};

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn f64v(p: [f32; 3]) -> [f64; 3] {
    [p[0] as f64, p[1] as f64, p[2] as f64]
}

/// Distance from p to triangle abc (closest point by region tests).
fn point_triangle(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let n = cross(sub(b, a), sub(c, a));
    let nn = dot(n, n);
    if nn > 1e-30 {
        // Inside the prism over the triangle: distance to the plane.
        let inside = [(a, b), (b, c), (c, a)]
            .iter()
            .all(|&(u, v)| dot(cross(sub(v, u), sub(p, u)), n) >= 0.0);
        if inside {
            return dot(sub(p, a), n).abs() / nn.sqrt();
        }
    }
    let seg = |u: [f64; 3], v: [f64; 3]| {
        let d = sub(v, u);
        let t = (dot(sub(p, u), d) / dot(d, d).max(1e-30)).clamp(0.0, 1.0);
        let q = [u[0] + t * d[0], u[1] + t * d[1], u[2] + t * d[2]];
        dot(sub(p, q), sub(p, q)).sqrt()
    };
    seg(a, b).min(seg(b, c)).min(seg(c, a))
}

/// Mesh → surface: the largest |sdf| over vertices, edge midpoints and centroids (the analytic
/// shapes are exact distance fields up to the bowl's smooth union).
fn mesh_to_surface(shape: AnalyticShape, m: &Mesh) -> f64 {
    let mut worst = 0.0f64;
    for t in m.triangles() {
        let [a, b, c] = t.map(|i| f64v(m.positions[i as usize]));
        for w in [
            [1.0, 0.0, 0.0],
            [0.5, 0.5, 0.0],
            [0.0, 0.5, 0.5],
            [0.5, 0.0, 0.5],
            [1.0 / 3.0; 3],
        ] {
            let p = [0, 1, 2].map(|k| w[0] * a[k] + w[1] * b[k] + w[2] * c[k]);
            worst = worst.max(shape.sdf(p).abs());
        }
    }
    worst
}

/// Surface → mesh: the largest distance from `n` surface samples (random points projected onto
/// the surface with Newton steps) to the mesh.
fn surface_to_mesh(shape: AnalyticShape, m: &Mesh, n: usize) -> f64 {
    use rand::Rng;
    let mut rng = pii_bake::util::rng(7);
    let mut worst = 0.0f64;
    let mut done = 0;
    while done < n {
        let mut p = [
            rng.random_range(-0.9..0.9),
            rng.random_range(-0.9..0.9),
            rng.random_range(-0.9..0.9),
        ];
        for _ in 0..20 {
            let g = shape.grad(p);
            let f = shape.sdf(p);
            let gg = dot(g, g).max(1e-12);
            p = [
                p[0] - f * g[0] / gg,
                p[1] - f * g[1] / gg,
                p[2] - f * g[2] / gg,
            ];
        }
        if shape.sdf(p).abs() > 1e-7 {
            continue;
        }
        done += 1;
        let d = m
            .triangles()
            .map(|t| {
                let [a, b, c] = t.map(|i| f64v(m.positions[i as usize]));
                point_triangle(p, a, b, c)
            })
            .fold(f64::INFINITY, f64::min);
        worst = worst.max(d);
    }
    worst
}

#[test]
fn extracted_and_simplified_meshes_are_close_closed_and_outward() {
    let backend = Backend::cpu();
    for shape in AnalyticShape::ALL {
        let sdf = AnalyticSdf::new(shape);
        let grid = GridSpec::over(&sdf.bounds, 64);
        let h = grid.spacing as f64;
        let (values, touched) = sample_grid(&backend, &sdf, &grid).unwrap();
        assert!(!touched, "{}", shape.name());
        let raw = extract::marching_tetrahedra(&grid, &values);
        topology::check_closed(&raw)
            .unwrap_or_else(|e| panic!("{}: extracted mesh not closed: {e}", shape.name()));
        let (m2s, s2m) = (
            mesh_to_surface(shape, &raw),
            surface_to_mesh(shape, &raw, 150),
        );
        assert!(
            m2s < h && s2m < h,
            "{}: extracted Hausdorff {m2s} / {s2m} vs spacing {h}",
            shape.name()
        );

        let bound = 0.5 * grid.spacing;
        let res = build_mesh(
            &backend,
            &sdf,
            &MeshConfig {
                resolution: 64,
                error_bound: Some(bound),
                ..Default::default()
            },
        )
        .unwrap();
        let m = &res.mesh;
        topology::check_closed(m)
            .unwrap_or_else(|e| panic!("{}: simplified mesh not closed: {e}", shape.name()));
        assert!(res.stats.watertight && res.stats.components >= 1);
        assert!(
            m.triangle_count() < raw.triangle_count() / 3,
            "{}: {} triangles",
            shape.name(),
            m.triangle_count()
        );
        // Within the bound on top of the extraction error (meshoptimizer's error is a quadric
        // estimate, so allow the extraction error measured above).
        let m2s_simpl = mesh_to_surface(shape, m);
        let s2m_simpl = surface_to_mesh(shape, m, 150);
        let limit = bound as f64 + m2s.max(s2m) + 1e-4;
        assert!(
            m2s_simpl <= limit && s2m_simpl <= limit,
            "{}: simplified {m2s_simpl} / {s2m_simpl} > {limit}",
            shape.name()
        );
        // Outward: face normals agree with the SDF gradient. Near the bowl's crease (ball meets
        // wall) a few tiny triangles may fold; they must be a negligible share of the area.
        let (mut inward_area, mut total_area, mut inward) = (0.0f64, 0.0f64, 0usize);
        for t in m.triangles() {
            let [a, b, c] = t.map(|i| f64v(m.positions[i as usize]));
            let n = cross(sub(b, a), sub(c, a));
            let centroid = [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0);
            let area = 0.5 * dot(n, n).sqrt();
            total_area += area;
            if dot(n, shape.grad(centroid)) < 0.0 {
                inward += 1;
                inward_area += area;
            }
        }
        assert!(
            inward_area < 1e-3 * total_area && inward * 200 <= m.triangle_count(),
            "{}: {inward} inward triangles",
            shape.name()
        );
        assert_eq!(
            inward,
            res.stats.folded_triangles,
            "{}: the report counts the folded triangles",
            shape.name()
        );
        assert!(res
            .normals
            .iter()
            .all(|n| ((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) - 1.0).abs() < 1e-4));
        eprintln!(
            "{}: spacing {h:.4}, extracted Hausdorff {m2s:.2e}/{s2m:.2e} ({} tris), simplified {m2s_simpl:.2e}/{s2m_simpl:.2e} ({} tris)",
            shape.name(),
            raw.triangle_count(),
            m.triangle_count()
        );
    }
}

#[test]
fn bowl_keeps_the_ball_joined_and_drops_nothing() {
    let res = build_mesh(
        &Backend::cpu(),
        &AnalyticSdf::new(AnalyticShape::Bowl),
        &MeshConfig {
            resolution: 64,
            error_bound: None,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(
        res.stats.components, 1,
        "the ball is fused to the bowl by the smooth union"
    );
    assert_eq!(res.stats.holes_closed, 0);
}

#[test]
fn meshing_says_what_it_did_and_ends_with_the_triangles_it_shipped() {
    // Export's spinner reads these messages; the last one gives the figures of the mesh built.
    let cfg = MeshConfig {
        resolution: 64,
        error_bound: None,
        ..Default::default()
    };
    let sdf = AnalyticSdf::new(AnalyticShape::Bowl);
    let pb = indicatif::ProgressBar::hidden();
    let res = build_mesh_with(&Backend::cpu(), &sdf, &cfg, &pb).unwrap();
    let s = &res.stats;
    assert!(s.simplify_rounds > 0 && s.triangles < s.extracted_triangles, "{s:?}");
    assert_eq!(
        pb.message(),
        format!(
            "meshed: {} → {} triangles in {} simplification rounds",
            s.extracted_triangles, s.triangles, s.simplify_rounds
        )
    );
    // Watching changes nothing.
    let plain = build_mesh(&Backend::cpu(), &sdf, &cfg).unwrap();
    assert_eq!(plain.mesh, res.mesh);
}

#[test]
fn no_surface_in_the_box_is_a_clear_error() {
    // A box far outside the sphere: positive everywhere.
    let sdf = AnalyticSdf {
        shape: AnalyticShape::Sphere,
        bounds: Aabb {
            min: [2.0; 3],
            max: [3.0; 3],
        },
    };
    let err = build_mesh(
        &Backend::cpu(),
        &sdf,
        &MeshConfig {
            resolution: 16,
            error_bound: None,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(matches!(err, MeshError::NoSurface { .. }), "{err}");
    assert!(
        err.to_string().contains("no surface") && err.to_string().contains("sphere"),
        "{err}"
    );
    // A box entirely inside: negative everywhere.
    let inside = AnalyticSdf {
        shape: AnalyticShape::Sphere,
        bounds: Aabb::cube(0.2),
    };
    let err = build_mesh(
        &Backend::cpu(),
        &inside,
        &MeshConfig {
            resolution: 16,
            error_bound: None,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(err.to_string().contains("negative"), "{err}");
}

#[test]
fn surface_touching_the_box_is_capped_closed() {
    // The sphere (r = 0.8) cut by the box y ≤ 0.5: the mesh is closed with a cap near y = 0.5.
    let sdf = AnalyticSdf {
        shape: AnalyticShape::Sphere,
        bounds: Aabb {
            min: [-1.0; 3],
            max: [1.0, 0.5, 1.0],
        },
    };
    let res = build_mesh(
        &Backend::cpu(),
        &sdf,
        &MeshConfig {
            resolution: 48,
            error_bound: None,
            ..Default::default()
        },
    )
    .unwrap();
    assert!(res.stats.touched_bounds);
    topology::check_closed(&res.mesh).unwrap();
    let (_, hi) = res.mesh.bounds();
    let h = res.stats.grid.unwrap().spacing;
    assert!(hi[1] <= 0.5 && hi[1] > 0.5 - h, "cap at {}", hi[1]);
}

/// A field that returns NaN inside a ball (a broken network, say).
struct NanField;

impl pii_bake::mesh::field::SdfField for NanField {
    fn name(&self) -> String {
        "nan-field".into()
    }
    fn eval(
        &self,
        _backend: &Backend,
        points: &[[f32; 3]],
    ) -> Result<pii_bake::mesh::field::SdfSamples, pii_bake::backend::BackendError> {
        let values = points
            .iter()
            .map(|p| {
                let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                if r < 0.3 {
                    f32::NAN
                } else {
                    r - 0.5
                }
            })
            .collect();
        Ok(pii_bake::mesh::field::SdfSamples {
            values,
            gradients: vec![[0.0, 1.0, 0.0]; points.len()],
        })
    }
}

#[test]
fn non_finite_field_values_are_a_clear_error() {
    // Through the default (batched) grid evaluation of a non-analytic field.
    let err = build_mesh(
        &Backend::cpu(),
        &NanField,
        &MeshConfig {
            resolution: 24,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(matches!(err, MeshError::NonFinite { .. }), "{err}");
    assert!(
        err.to_string().contains("nan-field") && err.to_string().contains("non-finite"),
        "{err}"
    );
}

/// Separate balls: a body, a part (a quarter of its radius: 6% of its area) and a speck (0.5%).
struct Balls(Vec<([f32; 3], f32)>);

impl pii_bake::mesh::field::SdfField for Balls {
    fn name(&self) -> String {
        "balls".into()
    }
    fn eval(&self, _: &Backend, points: &[[f32; 3]]) -> Result<pii_bake::mesh::field::SdfSamples, pii_bake::backend::BackendError> {
        let (mut values, mut gradients) = (Vec::new(), Vec::new());
        for p in points {
            let (d, g) = self
                .0
                .iter()
                .map(|(c, r)| {
                    let v = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
                    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-9);
                    (l - r, v.map(|x| x / l))
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap();
            values.push(d);
            gradients.push(g);
        }
        Ok(pii_bake::mesh::field::SdfSamples { values, gradients })
    }
}

#[test]
fn separate_parts_are_kept_and_specks_dropped() {
    let body = ([-0.3f32, 0.0, 0.0], 0.5f32);
    let part = ([0.55f32, 0.0, 0.0], 0.125f32);
    let speck = ([0.0f32, 0.75, 0.0], 0.035f32);
    let res = build_mesh(&Backend::cpu(), &Balls(vec![body, part, speck]), &MeshConfig { resolution: 96, ..Default::default() }).unwrap();
    let st = &res.stats;
    assert_eq!(st.components, 3, "{st:?}");
    assert!(st.dropped_triangles > 0 && st.watertight, "{st:?}");
    // Every kept vertex lies on the body or the part, and both are there.
    let near = |c: [f32; 3], r: f32, p: [f32; 3]| (((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt() - r).abs() < 0.02;
    let on_part = res.mesh.positions.iter().filter(|p| near(part.0, part.1, **p)).count();
    assert!(on_part >= 8, "the part was dropped: {on_part} vertices on it");
    assert!(res.mesh.positions.iter().all(|p| near(body.0, body.1, *p) || near(part.0, part.1, *p)), "a speck vertex survived");
    topology::check_closed(&res.mesh).unwrap();
}

#[test]
fn a_face_tolerance_bounds_every_face_against_the_surface_normal() {
    // `--face-tolerance`: no face of the simplified mesh leans further than the limit from the
    // field's gradient at its samples; the mesh keeps more triangles for it and stays closed.
    let backend = Backend::cpu();
    let sdf = AnalyticSdf::new(AnalyticShape::Torus);
    let cfg = MeshConfig { resolution: 64, error_bound: None, ..Default::default() };
    let free = build_mesh(&backend, &sdf, &cfg).unwrap();
    let free_dev = pii_bake::mesh::surface_deviation(&backend, &sdf, &free.mesh).unwrap();
    let tight = build_mesh(&backend, &sdf, &MeshConfig { face_tolerance_deg: 8.0, ..cfg.clone() }).unwrap();
    let dev = pii_bake::mesh::surface_deviation(&backend, &sdf, &tight.mesh).unwrap();
    topology::check_closed(&tight.mesh).unwrap();
    assert!(free_dev.face_angle_deg > 8.0, "the test needs a free mesh that leans further: {free_dev:?}");
    assert!(dev.face_angle_deg <= 8.0 + 1e-3, "{dev:?}");
    assert!(tight.stats.triangles > free.stats.triangles, "{} vs {}", tight.stats.triangles, free.stats.triangles);
    assert!(dev.distance <= free_dev.distance.max(tight.stats.error_bound) + 1e-6, "{dev:?}");
}
