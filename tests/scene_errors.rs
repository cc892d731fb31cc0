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

/// An LLFF scene of one 8×8 image whose `poses_bounds.npy` has the given header and data.
fn llff_with_npy(dir: &Path, header_shape: &str, values: usize) -> PathBuf {
    std::fs::create_dir(dir.join("images")).unwrap();
    png(&dir.join("images/000.png"), 8, 8, 3, 0.5);
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {header_shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend(std::iter::repeat_n(0u8, values * 8));
    let p = dir.join("poses_bounds.npy");
    std::fs::write(&p, bytes).unwrap();
    p
}

#[test]
fn npy_shape_larger_than_the_file_is_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    llff_with_npy(dir.path(), "(99999999999, 17)", 17);
    let e = err_of(dir.path());
    assert!(e.contains("poses_bounds.npy") && e.contains("99999999999") && e.contains("136 bytes"), "{e}");
}

#[test]
fn npy_header_length_past_the_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = llff_with_npy(dir.path(), "(1, 17)", 17);
    let mut b = std::fs::read(&p).unwrap();
    b[8..10].copy_from_slice(&60000u16.to_le_bytes());
    std::fs::write(&p, b).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("poses_bounds.npy") && e.contains("declares 60000 bytes"), "{e}");
}

#[test]
fn colmap_counts_past_the_file_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("sparse/0");
    std::fs::create_dir_all(&model).unwrap();
    std::fs::create_dir(dir.path().join("images")).unwrap();
    // 2^62 cameras declared in a 56-byte file
    let mut cams = (1u64 << 62).to_le_bytes().to_vec();
    cams.extend_from_slice(&[0u8; 48]);
    std::fs::write(model.join("cameras.bin"), cams).unwrap();
    std::fs::write(model.join("images.bin"), 0u64.to_le_bytes()).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("cameras.bin") && e.contains(&(1u64 << 62).to_string()) && e.contains("cameras"), "{e}");
    // a camera with a 2^40-pixel-wide image
    let mut cams = 1u64.to_le_bytes().to_vec();
    cams.extend_from_slice(&1i32.to_le_bytes());
    cams.extend_from_slice(&1i32.to_le_bytes());
    cams.extend_from_slice(&(1u64 << 40).to_le_bytes());
    cams.extend_from_slice(&8u64.to_le_bytes());
    for v in [10.0f64, 10.0, 4.0, 4.0] {
        cams.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(model.join("cameras.bin"), cams).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("cameras.bin") && e.contains(&format!("{}x8", 1u64 << 40)), "{e}");
}

#[test]
fn png_declaring_a_huge_size_is_refused_before_decoding() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    // IHDR width/height → 60000 × 60000 (past the pixel limit), chunk CRC fixed.
    let p = dir.path().join("r_0.png");
    let mut b = std::fs::read(&p).unwrap();
    b[16..20].copy_from_slice(&60000u32.to_be_bytes());
    b[20..24].copy_from_slice(&60000u32.to_be_bytes());
    let mut h = crc32fast::Hasher::new();
    h.update(&b[12..29]);
    let crc = h.finalize();
    b[29..33].copy_from_slice(&crc.to_be_bytes());
    std::fs::write(&p, &b).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("r_0.png") && e.contains("60000x60000"), "{e}");
    // within the limits but far more pixels than the file can hold
    b[16..20].copy_from_slice(&8000u32.to_be_bytes());
    b[20..24].copy_from_slice(&8000u32.to_be_bytes());
    let mut h = crc32fast::Hasher::new();
    h.update(&b[12..29]);
    let crc = h.finalize();
    b[29..33].copy_from_slice(&crc.to_be_bytes());
    std::fs::write(&p, &b).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("r_0.png") && e.contains("8000x8000") && e.contains("file holds only"), "{e}");
}

#[test]
fn declared_sizes_and_values_in_transforms_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path());
    let m = r#"[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"#;
    for (extra, want) in [
        (r#", "w": 1e308, "h": 8, "fl_x": 10"#, "is not an integer"),
        (r#", "w": 8, "h": -0, "fl_x": 10"#, "is not an integer"),
        (r#", "w": 8, "h": 8, "fl_x": 10, "cx": 1e308, "cy": 1e309"#, "malformed JSON"),
        (r#", "k1": 1e308, "k2": -1e308, "fl_x": 10, "p1": 1e308"#, ""),
        (r#", "camera_angle_y": 7"#, "camera_angle_y"),
    ] {
        write_transforms(dir.path(), m, extra);
        match load(dir.path(), &ReadOptions::default()) {
            Err(e) => {
                let e = e.to_string();
                assert!(e.contains("transforms_train.json") && e.contains(want), "{extra}: {e}");
            }
            Ok(_) => assert!(want.is_empty(), "{extra}: accepted"),
        }
    }
}

#[test]
fn scene_with_no_colmap_images_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("sparse/0");
    std::fs::create_dir_all(&model).unwrap();
    std::fs::create_dir(dir.path().join("images")).unwrap();
    std::fs::write(model.join("cameras.txt"), "1 PINHOLE 8 8 10 10 4 4\n").unwrap();
    std::fs::write(model.join("images.txt"), "# nothing\n").unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("images.txt") && e.contains("no images"), "{e}");
}
