//! Helpers shared by the integration tests that drive external checkers (the Khronos
//! glTF-Validator through node, usd-core through `PII_PYTHON`). `scripts/test.sh` sets both up.
#![allow(dead_code)] // each test binary uses a subset

use std::path::{Path, PathBuf};
use std::process::Command;

/// The venv Python with bpy and usd-core (`PII_PYTHON`, set by `scripts/test.sh`).
pub fn python() -> String {
    std::env::var("PII_PYTHON").unwrap_or_else(|_| {
        panic!("PII_PYTHON is not set: run the tests with `bash scripts/test.sh` (it sets up bpy/usd-core)")
    })
}

/// The glTF-Validator wrapper script.
pub fn validator() -> PathBuf {
    std::env::var("PII_GLTF_VALIDATOR")
        .map(PathBuf::from)
        .unwrap_or_else(|_| Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/gltf_validate.mjs"))
}

/// Run a command; (success, stdout + stderr).
pub fn run(cmd: &mut Command) -> (bool, String) {
    let out = cmd.output().unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    (out.status.success(), text)
}

/// The glTF-Validator reports 0 errors and 0 warnings on every file.
pub fn assert_gltf_valid(glbs: &[PathBuf]) {
    let (ok, text) = run(Command::new("node").arg(validator()).args(glbs));
    assert!(ok, "glTF-Validator: {text}");
    let reports: Vec<&str> = text.lines().filter(|l| l.starts_with('{')).collect();
    assert_eq!(reports.len(), glbs.len(), "one report per file: {text}");
    for line in reports {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!((v["errors"].as_u64(), v["warnings"].as_u64()), (Some(0), Some(0)), "{line}");
    }
}

/// usd-core's validators (scripts/usd_check.py) report no error on every layer/package.
pub fn assert_usd_valid(usds: &[PathBuf]) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/usd_check.py");
    let (ok, text) = run(Command::new(python()).arg(&script).args(usds));
    assert!(ok, "USD validation: {text}");
    assert_eq!(text.lines().filter(|l| l.contains("\"errors\": 0")).count(), usds.len(), "{text}");
}

/// Copy the files (not the subfolders) of `src` into `dst`, creating it.
pub fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_file() {
            std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
        }
    }
}

/// Turn the camera of `view` (a frame of the transforms file `tf` whose file_path ends with it)
/// `degrees` about its own up axis, its image and mask unchanged, as a failed registration leaves
/// it: its silhouette then cuts a slab off the other views' hull.
pub fn turn_camera(tf: &Path, view: &str, degrees: f64) {
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(tf).unwrap()).unwrap();
    let frame = j["frames"].as_array_mut().unwrap().iter_mut().find(|f| f["file_path"].as_str().unwrap().ends_with(view)).unwrap();
    let m: Vec<Vec<f64>> = serde_json::from_value(frame["transform_matrix"].clone()).unwrap();
    let up = glam::DVec3::new(m[0][1], m[1][1], m[2][1]).normalize();
    let turn = glam::DMat3::from_axis_angle(up, degrees.to_radians());
    let r = turn * glam::DMat3::from_cols_array_2d(&[[m[0][0], m[1][0], m[2][0]], [m[0][1], m[1][1], m[2][1]], [m[0][2], m[1][2], m[2][2]]]);
    let mut m2 = m.clone();
    for (c, col) in [r.x_axis, r.y_axis, r.z_axis].iter().enumerate() {
        for row in 0..3 {
            m2[row][c] = col[row];
        }
    }
    frame["transform_matrix"] = serde_json::json!(m2);
    std::fs::write(tf, serde_json::to_vec_pretty(&j).unwrap()).unwrap();
}

/// The real test material (`PII_SHARED_DATA`, else `../shared/data` beside the repository, else
/// `/work/shared/data`).
pub fn shared_data() -> PathBuf {
    let p = std::env::var("PII_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|_| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data")));
    if p.is_dir() {
        p
    } else {
        PathBuf::from("/work/shared/data")
    }
}

/// The bundled example scene.
pub fn example() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/example")
}

/// Run the `pii-bake` binary on the cpu backend.
pub fn pii(args: &[&str]) -> std::process::Output {
    assert_cmd::Command::cargo_bin("pii-bake")
        .unwrap()
        .env("XDG_RUNTIME_DIR", std::env::temp_dir())
        .args(["--backend", "cpu"])
        .args(args)
        .output()
        .unwrap()
}

/// A command's stdout + stderr.
pub fn text(o: &std::process::Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// Run `pii-bake --backend cpu --json <args>`, send it SIGINT once it prints a progress record
/// containing every string of `markers`, and return its output (stdout drained to the end).
pub fn interrupt_after_progress(args: &[&str], markers: &[&str]) -> std::process::Output {
    use std::io::BufRead;
    use std::process::Stdio;
    let mut child = Command::new(assert_cmd::cargo::cargo_bin("pii-bake"))
        .env("XDG_RUNTIME_DIR", std::env::temp_dir())
        .args(["--backend", "cpu", "--json"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let mut lines = std::io::BufReader::new(stdout).lines();
    loop {
        let l = lines.next().expect("progress records before the end").unwrap();
        if l.contains("\"type\":\"progress\"") && markers.iter().all(|m| l.contains(m)) {
            break;
        }
    }
    assert!(Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap().success());
    for _ in lines {}
    child.wait_with_output().unwrap()
}

/// The JSON chunk of a .glb (it follows the 12-byte header and the chunk's 8-byte header).
pub fn glb_json(path: &Path) -> serde_json::Value {
    let glb = std::fs::read(path).unwrap();
    let len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    serde_json::from_slice(&glb[20..20 + len]).unwrap()
}
