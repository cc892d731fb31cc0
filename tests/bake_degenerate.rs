//! A degenerate (zero-area) triangle reaching the unwrap and the bake: handled, counted, and no
//! NaN in the textures.

use pii_bake::backend::Backend;
use pii_bake::bake;
use pii_bake::mesh::field::{AnalyticMaterial, AnalyticSdf, AnalyticShape};
use pii_bake::mesh::{normalize, uv, Mesh};
use pii_bake::testing::assert_finite;

#[test]
fn zero_area_triangle_is_handled_in_unwrap_and_bake() {
    // An octahedron of radius 0.8 (on the analytic sphere's surface at its vertices) plus a
    // zero-area triangle whose three corners are collinear.
    let r = 0.8f32;
    let mut positions = vec![
        [r, 0., 0.],
        [-r, 0., 0.],
        [0., r, 0.],
        [0., -r, 0.],
        [0., 0., r],
        [0., 0., -r],
    ];
    let mut indices = vec![
        0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4, 2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5,
    ];
    positions.extend([[0.1, 0.1, 0.7], [0.2, 0.2, 0.7], [0.3, 0.3, 0.7]]);
    indices.extend([6, 7, 8]);
    let mesh = Mesh { positions, indices };
    let normals: Vec<[f32; 3]> = mesh.positions.iter().map(|&p| normalize(p)).collect();
    let uvm = uv::unwrap(&mesh, &normals, 64, 2).unwrap();
    assert_eq!(uvm.indices.len(), mesh.indices.len(), "every triangle kept");
    let sdf = AnalyticSdf::new(AnalyticShape::Sphere);
    let baked = bake::bake(&Backend::cpu(), &sdf, &AnalyticMaterial::Gradient, &uvm, 64).unwrap();
    assert!(
        baked.stats.degenerate_uv_triangles >= 1,
        "{:?}",
        baked.stats
    );
    let flat: Vec<f32> = baked.albedo.iter().flatten().copied().collect();
    assert_finite("albedo", &flat);
    assert_finite("roughness", &baked.roughness);
    assert!(
        baked.stats.covered_texels > 64 * 64 / 8,
        "{:?}",
        baked.stats
    );
}
