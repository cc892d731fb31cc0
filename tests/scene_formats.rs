//! COLMAP (.bin and .txt) and nerfstudio transforms.json written from known cameras: the readers must
//! reproduce the cameras' projections of known 3D points (distortion included).

use std::io::Write;
use std::path::Path;

use glam::{DMat3, DQuat, DVec2, DVec3};
use pii_bake::image_io::write_png8;
use pii_bake::scene::{load, Downscale, Format, ReadOptions, Split};

const W: usize = 32;
const H: usize = 24;
const FX: f64 = 30.0;
const FY: f64 = 31.0;
const CX: f64 = 15.5;
const CY: f64 = 12.25;
const DIST: [f64; 4] = [-0.05, 0.01, 0.002, -0.001]; // k1 k2 p1 p2

/// Three cameras on a circle of radius 4 around the origin, looking at it: (R world->camera, t), OpenCV.
fn known_cameras() -> Vec<(DMat3, DVec3)> {
    (0..3)
        .map(|i| {
            let a = i as f64 * 2.0;
            let c = DVec3::new(4.0 * a.cos(), 4.0 * a.sin(), 0.7);
            let z = (-c).normalize();
            let x = z.cross(DVec3::Z).normalize();
            let y = z.cross(x);
            let r_wc = DMat3::from_cols(x, y, z);
            let r_cw = r_wc.transpose();
            (r_cw, -(r_cw * c))
        })
        .collect()
}

/// Reference projection, written independently of the library (COLMAP's OPENCV model).
fn reference_project(r_cw: DMat3, t: DVec3, p: DVec3, distort: bool) -> DVec2 {
    let q = r_cw * p + t;
    let (mut x, mut y) = (q.x / q.z, q.y / q.z);
    if distort {
        let [k1, k2, p1, p2] = DIST;
        let r2 = x * x + y * y;
        let rad = 1.0 + k1 * r2 + k2 * r2 * r2;
        let (xd, yd) = (x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y);
        x = xd;
        y = yd;
    }
    DVec2::new(FX * x + CX, FY * y + CY)
}

fn write_images(root: &Path) {
    std::fs::create_dir_all(root.join("images")).unwrap();
    for i in 0..3 {
        write_png8(&root.join(format!("images/im{i}.png")), W, H, 3, &vec![0.5; W * H * 3], true).unwrap();
    }
}

fn write_colmap_txt(root: &Path, distort: bool) {
    let m = root.join("sparse/0");
    std::fs::create_dir_all(&m).unwrap();
    let cam = if distort {
        format!("1 OPENCV {W} {H} {FX} {FY} {CX} {CY} {} {} {} {}\n", DIST[0], DIST[1], DIST[2], DIST[3])
    } else {
        format!("1 PINHOLE {W} {H} {FX} {FY} {CX} {CY}\n")
    };
    std::fs::write(m.join("cameras.txt"), format!("# Camera list\n{cam}")).unwrap();
    let mut s = String::from("# Image list with two lines of data per image\n");
    for (i, (r, t)) in known_cameras().iter().enumerate() {
        let q = DQuat::from_mat3(r);
        s += &format!("{} {} {} {} {} {} {} {} 1 im{i}.png\n", i + 1, q.w, q.x, q.y, q.z, t.x, t.y, t.z);
        s += if i == 1 { "\n" } else { "10.0 12.0 -1 3.5 4.5 7\n" }; // an image with no 2D points
    }
    std::fs::write(m.join("images.txt"), s).unwrap();
}

fn write_colmap_bin(root: &Path, distort: bool) {
    let m = root.join("sparse/0");
    std::fs::create_dir_all(&m).unwrap();
    let mut c = Vec::new();
    c.extend_from_slice(&1u64.to_le_bytes());
    c.extend_from_slice(&1i32.to_le_bytes());
    c.extend_from_slice(&(if distort { 4i32 } else { 1i32 }).to_le_bytes());
    c.extend_from_slice(&(W as u64).to_le_bytes());
    c.extend_from_slice(&(H as u64).to_le_bytes());
    let mut params = vec![FX, FY, CX, CY];
    if distort {
        params.extend_from_slice(&DIST);
    }
    for p in params {
        c.extend_from_slice(&p.to_le_bytes());
    }
    std::fs::write(m.join("cameras.bin"), &c).unwrap();
    let mut b = Vec::new();
    b.extend_from_slice(&3u64.to_le_bytes());
    for (i, (r, t)) in known_cameras().iter().enumerate() {
        let q = DQuat::from_mat3(r);
        b.extend_from_slice(&(i as i32 + 1).to_le_bytes());
        for v in [q.w, q.x, q.y, q.z, t.x, t.y, t.z] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&1i32.to_le_bytes());
        b.write_all(format!("im{i}.png\0").as_bytes()).unwrap();
        b.extend_from_slice(&1u64.to_le_bytes());
        for v in [10.0f64, 12.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&(-1i64).to_le_bytes());
    }
    std::fs::write(m.join("images.bin"), &b).unwrap();
}

fn check_projections(root: &Path, distort: bool) {
    let scene = load(root, &ReadOptions::default()).unwrap();
    assert_eq!(scene.format, Format::Colmap);
    assert_eq!(scene.views.len(), 3);
    let points = [DVec3::ZERO, DVec3::new(0.3, -0.2, 0.25), DVec3::new(-0.4, 0.1, -0.3)];
    for (v, (r, t)) in scene.views.iter().zip(known_cameras()) {
        assert_eq!((v.camera.width, v.camera.height), (W, H));
        assert_eq!(v.split, Split::Train);
        for p in points {
            let got = v.camera.project(scene.normalisation.to_normalised(p)).unwrap();
            let want = reference_project(r, t, p, distort);
            assert!((got - want).length() < 1e-9, "{}: {got} vs {want}", v.name);
            // and the ray through that pixel passes through the point
            let (o, d) = v.camera.ray(got.x, got.y);
            let pn = scene.normalisation.to_normalised(p);
            assert!((pn - o).cross(d).length() < 1e-7, "ray misses the point");
        }
    }
    // The normalisation centres the scene on the point closest to the optical axes (the origin here).
    assert!(scene.normalisation.center.length() < 1e-9, "{:?}", scene.normalisation);
    assert_eq!(scene.normalisation.up_axis_name, "+Z");
}

#[test]
fn colmap_txt_and_bin_pinhole_and_opencv() {
    for distort in [false, true] {
        let d = tempfile::tempdir().unwrap();
        write_images(d.path());
        write_colmap_txt(d.path(), distort);
        check_projections(d.path(), distort);
        let d = tempfile::tempdir().unwrap();
        write_images(d.path());
        write_colmap_bin(d.path(), distort);
        check_projections(d.path(), distort);
    }
}

#[test]
fn colmap_truncated_bin_names_the_file() {
    let d = tempfile::tempdir().unwrap();
    write_images(d.path());
    write_colmap_bin(d.path(), false);
    let p = d.path().join("sparse/0/images.bin");
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 30]).unwrap();
    let e = load(d.path(), &ReadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("images.bin") && e.contains("truncated"), "{e}");
}

#[test]
fn nerfstudio_transforms_with_distortion_masks_and_splits() {
    let d = tempfile::tempdir().unwrap();
    write_images(d.path());
    let mut frames = Vec::new();
    for (i, (r, t)) in known_cameras().iter().enumerate() {
        // camera-to-world with OpenGL axes: columns (x, -y, -z) of the OpenCV camera
        let r_wc = r.transpose();
        let c = -(r_wc * *t);
        let cols = [r_wc.x_axis, -r_wc.y_axis, -r_wc.z_axis, c];
        let m: Vec<Vec<f64>> = (0..3).map(|row| cols.iter().map(|v| v[row]).collect()).chain([vec![0.0, 0.0, 0.0, 1.0]]).collect();
        let mut mask = vec![0.0f32; W * H];
        mask[..W * H / 2].iter_mut().for_each(|v| *v = 1.0);
        write_png8(&d.path().join(format!("m{i}.png")), W, H, 1, &mask, false).unwrap();
        frames.push(serde_json::json!({"file_path": format!("images/im{i}.png"), "mask_path": format!("m{i}.png"), "transform_matrix": m}));
    }
    let doc = serde_json::json!({
        "camera_model": "OPENCV", "fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H,
        "k1": DIST[0], "k2": DIST[1], "p1": DIST[2], "p2": DIST[3],
        "frames": frames, "test_filenames": ["images/im2.png"],
    });
    std::fs::write(d.path().join("transforms.json"), serde_json::to_string(&doc).unwrap()).unwrap();
    let scene = load(d.path(), &ReadOptions::default()).unwrap();
    assert_eq!(scene.format, Format::Transforms);
    assert_eq!(scene.views_in(Split::Test).map(|v| v.name.as_str()).collect::<Vec<_>>(), ["im2"]);
    assert_eq!(scene.views_in(Split::Train).count(), 2);
    for (v, (r, t)) in scene.views.iter().zip(known_cameras()) {
        assert!(v.camera.distortion.is_some());
        assert_eq!(v.mask_coverage(), Some(0.5));
        for p in [DVec3::ZERO, DVec3::new(0.3, -0.2, 0.25)] {
            let got = v.camera.project(scene.normalisation.to_normalised(p)).unwrap();
            let want = reference_project(r, t, p, true);
            assert!((got - want).length() < 1e-6, "{}: {got} vs {want}", v.name);
        }
    }
    // --downscale 2 on 32x24: intrinsics halve exactly
    let half = load(d.path(), &ReadOptions { downscale: Downscale::By(2), ..Default::default() }).unwrap();
    assert_eq!((half.views[0].camera.width, half.views[0].camera.height), (16, 12));
    assert_eq!(half.views[0].camera.cx, CX / 2.0);
}

/// `--downscale auto` (the default) reads photos larger than the model resolves at the smallest
/// integer factor within `AUTO_MAX_SIDE`, says so, and leaves a given factor alone.
#[test]
fn auto_downscale_reads_large_photos_within_the_models_resolution() {
    let d = tempfile::tempdir().unwrap();
    // The known cameras at 50x the size: 1600 x 1200 photos, longest side above 1536.
    let k = 50.0;
    let (w, h) = (W * 50, H * 50);
    std::fs::create_dir_all(d.path().join("images")).unwrap();
    let mut frames = Vec::new();
    for (i, (r, t)) in known_cameras().iter().enumerate() {
        write_png8(&d.path().join(format!("images/im{i}.png")), w, h, 3, &vec![0.5; w * h * 3], true).unwrap();
        let mut mask = vec![0.0f32; w * h];
        mask[..w * h / 2].iter_mut().for_each(|v| *v = 1.0);
        write_png8(&d.path().join(format!("m{i}.png")), w, h, 1, &mask, false).unwrap();
        let r_wc = r.transpose();
        let c = -(r_wc * *t);
        let cols = [r_wc.x_axis, -r_wc.y_axis, -r_wc.z_axis, c];
        let m: Vec<Vec<f64>> = (0..3).map(|row| cols.iter().map(|v| v[row]).collect()).chain([vec![0.0, 0.0, 0.0, 1.0]]).collect();
        frames.push(serde_json::json!({"file_path": format!("images/im{i}.png"), "mask_path": format!("m{i}.png"), "transform_matrix": m}));
    }
    let doc = serde_json::json!({
        "camera_model": "OPENCV", "fl_x": FX * k, "fl_y": FY * k, "cx": CX * k, "cy": CY * k, "w": w, "h": h, "frames": frames,
    });
    std::fs::write(d.path().join("transforms.json"), serde_json::to_string(&doc).unwrap()).unwrap();

    let auto = load(d.path(), &ReadOptions::default()).unwrap();
    assert_eq!(auto.downscale, 2);
    assert_eq!((auto.views[0].camera.width, auto.views[0].camera.height), (800, 600));
    assert_eq!(auto.views[0].camera.fx, FX * k / 2.0);
    let note = auto.downscale_note.as_deref().expect("an automatic downscale is explained");
    assert!(note.contains("1/2") && note.contains("1600") && note.contains("--downscale 1"), "{note}");
    // The same silhouettes at half size: the same normalisation within a few half-size pixels.
    let full = load(d.path(), &ReadOptions { downscale: Downscale::By(1), ..Default::default() }).unwrap();
    assert_eq!((full.downscale, full.views[0].camera.width), (1, 1600));
    assert!(full.downscale_note.is_none());
    let (a, b) = (auto.normalisation.to_normalised(DVec3::ZERO), full.normalisation.to_normalised(DVec3::ZERO));
    assert!((a - b).length() < 0.02, "{a} vs {b}");
    // The bundled scenes' photos are within both limits: read at full size.
    assert_eq!(Downscale::Auto.resolve(&[(200, 200); 28]), 1);
    assert_eq!(Downscale::Auto.resolve(&[(512, 512); 66]), 1);
}
