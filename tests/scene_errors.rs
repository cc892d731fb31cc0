//! Bad inputs: each gives one clear error naming the file (library and CLI).

use std::path::{Path, PathBuf};

use pii_bake::image_io::write_png8;
use pii_bake::scene::{load, ReadOptions};

fn png(path: &Path, w: usize, h: usize, channels: usize, value: f32) {
    write_png8(path, w, h, channels, &vec![value; w * h * channels], false).unwrap();
}

/// A valid NeRF-style scene: one 8×8 RGBA view (opaque centre) in `dir`.
fn good_scene(dir: &Path) -> PathBuf {
    let mut px = vec![0.0f32; 8 * 8 * 4];
    for y in 2..6 {
        for x in 2..6 {
            px[(y * 8 + x) * 4..(y * 8 + x) * 4 + 4].copy_from_slice(&[0.5, 0.5, 0.5, 1.0]);
        }
    }
    write_png8(&dir.join("r_0.png"), 8, 8, 4, &px, true).unwrap();
    write_transforms(dir, r#"[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"#, "");
    dir.join("transforms_train.json")
}

fn write_transforms(dir: &Path, matrix: &str, extra: &str) {
    let text = format!(
        r#"{{"camera_angle_x": 0.6, "frames": [{{"file_path": "./r_0"{extra}, "transform_matrix": {matrix}}}]}}"#
    );
    std::fs::write(dir.join("transforms_train.json"), text).unwrap();
}

fn err_of(path: &Path) -> String {
    load(path, &ReadOptions::default()).expect_err("must fail").to_string()
}

#[test]
fn good_scene_reads() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    let s = load(dir.path(), &ReadOptions::default()).unwrap();
    assert_eq!(s.views.len(), 1);
    assert_eq!(s.views[0].mask_coverage(), Some(16.0 / 64.0));
}

#[test]
fn missing_image_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    std::fs::remove_file(dir.path().join("r_0.png")).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("r_0") && e.contains("not found"), "{e}");
}

#[test]
fn mismatched_image_size_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    write_transforms(dir.path(), r#"[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"#, r#", "w": 16, "h": 8, "fl_x": 10"#);
    let e = err_of(dir.path());
    assert!(e.contains("r_0.png") && e.contains("8x8") && e.contains("16x8"), "{e}");
    // a mask of another size
    png(&dir.path().join("m.png"), 4, 4, 1, 1.0);
    write_transforms(dir.path(), r#"[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"#, r#", "mask_path": "m.png""#);
    let e = err_of(dir.path());
    assert!(e.contains("m.png") && e.contains("4x4"), "{e}");
}

#[test]
fn malformed_json_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    std::fs::write(dir.path().join("transforms_train.json"), "{\"frames\": [").unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("transforms_train.json") && e.contains("malformed JSON"), "{e}");
}

#[test]
fn non_rotation_matrix_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    write_transforms(dir.path(), r#"[[2,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"#, "");
    let e = err_of(dir.path());
    assert!(e.contains("transforms_train.json") && e.contains("not a rotation"), "{e}");
}

#[test]
fn empty_mask_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    png(&dir.path().join("m.png"), 8, 8, 1, 0.0);
    write_transforms(dir.path(), r#"[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"#, r#", "mask_path": "m.png""#);
    let e = err_of(dir.path());
    assert!(e.contains("m.png") && e.contains("empty"), "{e}");
}

#[test]
fn malformed_npz_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("image")).unwrap();
    png(&dir.path().join("image/000.png"), 8, 8, 3, 0.5);
    std::fs::write(dir.path().join("cameras_sphere.npz"), b"PK\x03\x04 this is not a zip").unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("cameras_sphere.npz") && e.contains("malformed npz"), "{e}");
}

#[test]
fn unsupported_distortion_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    write_transforms(dir.path(), r#"[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"#, r#", "camera_model": "OPENCV_FISHEYE""#);
    let e = err_of(dir.path());
    assert!(e.contains("OPENCV_FISHEYE") && e.contains("not supported"), "{e}");
}

#[test]
fn cli_prints_one_line_and_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    std::fs::write(dir.path().join("transforms_train.json"), "not json").unwrap();
    let out = assert_cmd::Command::cargo_bin("pii-bake").unwrap().arg("info").arg(dir.path()).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(stderr.contains("transforms_train.json"), "{stderr}");
}
