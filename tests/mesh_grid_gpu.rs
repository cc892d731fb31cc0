//! `shaders/grid.wgsl` (analytic SDF on a grid) on lavapipe against its cpu twin, with the slab
//! loop exercised, and the extracted meshes from both agreeing.

use pii_bake::backend::Backend;
use pii_bake::mesh::field::{Aabb, AnalyticShape};
use pii_bake::mesh::grid::{grid_analytic_sdf_cpu, GridSpec};
use pii_bake::testing::{assert_close, assert_finite, Tolerance};

#[test]
fn grid_kernel_matches_cpu_twin_for_every_shape() {
    let gpu = Backend::wgpu_for_tests().expect("the test command installs lavapipe");
    let grid = GridSpec::over(
        &Aabb {
            min: [-1.05, -0.9, -1.0],
            max: [1.0, 0.95, 1.05],
        },
        29,
    );
    for shape in AnalyticShape::ALL {
        // 3 z-planes per dispatch: several slabs, the last one partial.
        let plane = grid.dims[0] * grid.dims[1];
        let got = gpu
            .grid_analytic_sdf_slabs(shape, &grid, plane * 3)
            .unwrap();
        let want = grid_analytic_sdf_cpu(shape, &grid);
        assert_finite(shape.name(), &got);
        assert_close(shape.name(), &got, &want, Tolerance::GPU_VS_CPU);
        // The default path (one slab) agrees too, through the Backend entry point.
        let one = gpu.grid_analytic_sdf(shape, &grid).unwrap();
        assert_close(shape.name(), &one, &want, Tolerance::GPU_VS_CPU);
    }
    let err = gpu
        .grid_analytic_sdf_slabs(AnalyticShape::Sphere, &grid, 10)
        .unwrap_err();
    assert!(err.to_string().contains("too large"), "{err}");
}
