//! scripts/make_scene.py is deterministic: two runs at a tiny size give byte-identical files
//! (render_log.json, which holds wall-clock times, excepted). Needs Blender's `bpy` through PII_PYTHON.

use std::path::{Path, PathBuf};
use std::process::Command;

fn python() -> String {
    std::env::var("PII_PYTHON").unwrap_or_else(|_| {
        panic!("PII_PYTHON is not set: run the tests with `bash scripts/test.sh` (it points PII_PYTHON at the venv with bpy)")
    })
}

fn run(out: &Path) {
    run_scene(out, "spot");
}

fn run_scene(out: &Path, scene: &str) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/make_scene.py");
    let st = Command::new(python())
        .arg(&script)
        .args(["--scene", scene, "--width", "32", "--height", "32", "--train", "2", "--test", "1"])
        .args(["--samples", "4", "--gt-samples", "2", "--env-width", "64", "--threads", "2", "--out"])
        .arg(out)
        .output()
        .expect("cannot start PII_PYTHON");
    assert!(st.status.success(), "make_scene.py failed:\n{}", String::from_utf8_lossy(&st.stderr));
}

fn files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p.strip_prefix(dir).unwrap().to_path_buf());
            }
        }
    }
    out.sort();
    out
}

#[test]
fn make_scene_is_deterministic_and_readable() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    run(a.path());
    run(b.path());
    let (fa, fb) = (files(a.path()), files(b.path()));
    assert_eq!(fa, fb);
    for f in fa.iter().filter(|f| f.file_name().unwrap() != "render_log.json") {
        let (x, y) = (std::fs::read(a.path().join(f)).unwrap(), std::fs::read(b.path().join(f)).unwrap());
        assert!(x == y, "{} differs between runs", f.display());
    }
    for needed in ["transforms_train.json", "test/r_000_albedo.png", "test/r_000_roughness.png", "test/r_000_normal.png", "env/train.exr", "gt/mesh.obj"] {
        assert!(fa.contains(&PathBuf::from(needed)), "{needed} missing");
    }
    assert!(!fa.contains(&PathBuf::from("test/r_000_metallic.png")), "a dielectric scene has no metallic pass");
    let scene = pii_bake::scene::load(a.path(), &Default::default()).unwrap();
    assert_eq!(scene.views.len(), 3);
}

#[test]
fn the_metal_scene_has_a_metallic_pass_with_metal_and_dielectric_in_view() {
    let d = tempfile::tempdir().unwrap();
    run_scene(d.path(), "metal");
    let img = image::open(d.path().join("test/r_000_metallic.png")).unwrap().to_rgba8();
    let covered: Vec<u8> = img.pixels().filter(|p| p[3] == 255).map(|p| p[0]).collect();
    let metal = covered.iter().filter(|&&m| m > 200).count();
    let dielectric = covered.iter().filter(|&&m| m < 55).count();
    assert!(metal * 10 > covered.len() && dielectric * 10 > covered.len(), "{metal} metal, {dielectric} dielectric of {} pixels", covered.len());
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(d.path().join("scene.json")).unwrap()).unwrap();
    assert!(meta["test_gt"]["metallic"].is_string(), "{}", meta["test_gt"]);
    assert!(d.path().join("gt/metallic_spot.png").is_file());
}

#[test]
fn the_bunny_scene_is_the_scan_at_the_scenes_scale_with_texture_everywhere() {
    let d = tempfile::tempdir().unwrap();
    run_scene(d.path(), "bunny");
    // The scan (35 947 vertices, ears included), scaled from ~0.16 m to the other scenes' ~1.6 m.
    let gt = pii_bake::eval::mesh::Mesh::read(&d.path().join("gt/mesh.obj")).unwrap();
    assert!(gt.positions.len() > 30_000, "{} vertices", gt.positions.len());
    let extent = (0..3).map(|k| gt.positions.iter().map(|p| p[k]).fold(f64::NEG_INFINITY, f64::max) - gt.positions.iter().map(|p| p[k]).fold(f64::INFINITY, f64::min)).fold(0.0, f64::max);
    assert!((1.2..2.2).contains(&extent), "largest extent {extent} m");
    // Both checker colours show in the albedo pass (smart-projected UVs carry the texture).
    let img = image::open(d.path().join("test/r_000_albedo.png")).unwrap().to_rgba8();
    let covered: Vec<_> = img.pixels().filter(|p| p[3] == 255).collect();
    let green = covered.iter().filter(|p| p[1] as i32 > p[0] as i32 + 20).count();
    let beige = covered.iter().filter(|p| p[0] as i32 > p[2] as i32 + 15 && p[0] >= p[1]).count();
    assert!(green * 10 > covered.len() && beige * 10 > covered.len(), "{green} green, {beige} beige of {} pixels", covered.len());
    let scene = pii_bake::scene::load(d.path(), &Default::default()).unwrap();
    assert_eq!(scene.views.len(), 3);
}
