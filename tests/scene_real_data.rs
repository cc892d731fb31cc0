//! Readers on the real data in shared/data: DTU scan 37 (IDR npz) and the NeRD Ethiopian head (LLFF).

mod common;

use common::shared_data;
use glam::DVec3;
use pii_bake::scene::{load, normalise, Downscale, ReadOptions, Split};


#[test]
fn dtu_scan37_cameras_masks_and_unit_sphere() {
    let scene = load(&shared_data().join("dtu_scan37"), &ReadOptions::default()).unwrap();
    assert_eq!(scene.views.len(), 49);
    assert_eq!(scene.views_in(Split::Train).count(), 49);
    for v in &scene.views {
        assert_eq!((v.camera.width, v.camera.height), (400, 300), "{}", v.name);
        assert!(v.mask.is_some());
        // SOURCE.md: fx 723.083, fy 720.794, cx 205.426, cy 154.393 (OpenCV, integer = pixel centre).
        assert!((v.camera.fx - 723.083).abs() < 0.05 && (v.camera.fy - 720.794).abs() < 0.05, "{:?}", v.camera);
        assert!((v.camera.cx - 205.926).abs() < 0.05 && (v.camera.cy - 154.893).abs() < 0.05, "{:?}", v.camera);
        // The unit sphere's centre lands inside the mask in every view.
        let p = v.camera.project(DVec3::ZERO).expect("in front of the camera");
        assert!(v.mask_at(p.x, p.y) >= 0.5, "view {}: centre projects to {p} outside the mask", v.name);
        // Cameras sit outside the unit sphere, looking at it.
        assert!(v.camera.center().length() > 1.5);
        let (o, d) = v.camera.ray(p.x, p.y);
        assert!((o + d * o.length()).length() < 1e-6 * o.length() + 1e-9, "ray through the projection of the origin");
    }
    assert!(scene.normalisation.method.contains("scale_mat"));
    // Downscaling by 2 keeps intrinsics exact and the projection inside the mask.
    let half = load(&shared_data().join("dtu_scan37"), &ReadOptions { downscale: Downscale::By(2), ..Default::default() }).unwrap();
    for (a, b) in scene.views.iter().zip(&half.views) {
        assert_eq!((b.camera.width, b.camera.height), (200, 150));
        assert!((b.camera.fx * 2.0 - a.camera.fx).abs() < 1e-9 && (b.camera.cx * 2.0 - a.camera.cx).abs() < 1e-9);
        let p = b.camera.project(DVec3::ZERO).unwrap();
        assert!(b.mask_at(p.x, p.y) >= 0.5);
    }
}

#[test]
fn nerd_ethiopian_head_llff() {
    let scene = load(&shared_data().join("nerd_ethiopian_head"), &ReadOptions::default()).unwrap();
    assert_eq!(scene.views.len(), 66);
    assert_eq!(scene.views_in(Split::Test).count(), 9, "every 8th view is held out");
    let n = &scene.normalisation;
    let axes = normalise::closest_point_to_axes(&scene.views);
    for v in &scene.views {
        assert_eq!((v.camera.width, v.camera.height), (512, 512));
        assert!((v.camera.fx - 965.5776).abs() < 1e-3 && v.camera.cx == 256.0 && v.camera.cy == 256.0);
        // SOURCE.md: the point nearest to all optical axes projects inside the mask in 66/66 views.
        let p = v.camera.project(axes).unwrap();
        assert!(v.mask_at(p.x, p.y) >= 0.5, "view {}: {p}", v.name);
        // SOURCE.md: camera distance 4.13-4.37 (world units) from that point.
        let d = (v.camera.center() - axes).length() / n.scale;
        assert!((4.12..=4.38).contains(&d), "view {}: distance {d}", v.name);
        let cov = v.mask_coverage().unwrap();
        assert!(cov > 0.1 && cov < 0.5, "{cov}");
    }
    // The visual hull's sphere maps inside the unit sphere and every camera sees the origin.
    assert!(n.method.contains("visual hull"));
    assert!(scene.views.iter().all(|v| v.camera.center().length() > 2.0));
}
