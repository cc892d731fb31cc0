//! `pii-bake eval` on the bundled example scene: a prediction equal to the ground truth scores perfectly;
//! known perturbations give the expected figures.

use std::path::{Path, PathBuf};

use pii_bake::image_io::{linear_to_srgb, read_image_linear, srgb_to_linear, write_exr_rgb};

fn example() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/example")
}

fn test_names() -> Vec<String> {
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(example().join("transforms_test.json")).unwrap()).unwrap();
    v["frames"].as_array().unwrap().iter().map(|f| f["file_path"].as_str().unwrap().rsplit('/').next().unwrap().to_string()).collect()
}

fn eval(pred: &Path) -> serde_json::Value {
    let out = pred.join("metrics.json");
    let st = assert_cmd::Command::cargo_bin("pii-bake")
        .unwrap()
        .args(["eval", "--mesh-samples", "5000", "--gt"])
        .arg(example())
        .arg("--pred")
        .arg(pred)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap()
}

fn f(v: &serde_json::Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

#[test]
fn identical_prediction_is_perfect() {
    let pred = tempfile::tempdir().unwrap();
    let p = pred.path();
    std::fs::create_dir(p.join("test")).unwrap();
    for e in std::fs::read_dir(example().join("test")).unwrap() {
        let e = e.unwrap().path();
        std::fs::copy(&e, p.join("test").join(e.file_name().unwrap())).unwrap();
    }
    std::fs::copy(example().join("gt/mesh.obj"), p.join("mesh.obj")).unwrap();
    // the environment at twice the intensity: scale alignment removes it
    let env = read_image_linear(&example().join("env/train.exr")).unwrap();
    let doubled: Vec<f32> = env.rgb().iter().map(|v| v * 2.0).collect();
    write_exr_rgb(&p.join("env.exr"), env.width, env.height, &doubled).unwrap();
    let m = eval(p);
    let n = test_names().len() as u64;
    assert_eq!(m["novel_view"]["views"], n);
    assert_eq!(f(&m["novel_view"]["psnr"]), 100.0);
    assert!((f(&m["novel_view"]["ssim"]) - 1.0).abs() < 1e-12);
    let relit = m["relit"].as_object().unwrap();
    assert_eq!(relit.len(), 2, "two relighting environments");
    for v in relit.values() {
        assert_eq!(f(&v["psnr"]), 100.0);
        assert_eq!(f(&v["psnr_aligned"]), 100.0);
    }
    assert_eq!(f(&m["albedo"]["psnr_aligned"]), 100.0);
    assert_eq!(f(&m["roughness"]["mse"]), 0.0);
    assert!(f(&m["env"]["relative_l2"]) < 1e-6, "{}", m["env"]);
    assert!(f(&m["env"]["irradiance_error"]) < 1e-6, "{}", m["env"]);
    assert!((f(&m["env"]["scale"][0]) - 0.5).abs() < 1e-6);
    // Distances to the other surface: zero up to rounding for identical meshes.
    assert!(f(&m["mesh"]["chamfer"]) < 1e-9, "{}", m["mesh"]);
    assert!((f(&m["mesh"]["normal_consistency"]) - 1.0).abs() < 1e-12);
    assert_eq!(m["missing"].as_array().unwrap().len(), 0, "{}", m["missing"]);
    assert!(m.get("metallic").is_none(), "the example has no metallic ground truth");
}

#[test]
fn metallic_is_scored_where_the_ground_truth_has_it_and_a_dielectric_prediction_counts_as_0() {
    // A ground truth with metallic views (each view's roughness PNG standing in for its metallic map).
    let gt = tempfile::tempdir().unwrap();
    let g = gt.path();
    std::fs::create_dir(g.join("test")).unwrap();
    std::fs::copy(example().join("transforms_test.json"), g.join("transforms_test.json")).unwrap();
    let (pred, none) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    std::fs::create_dir(pred.path().join("test")).unwrap();
    std::fs::create_dir(none.path().join("test")).unwrap();
    let mut mean_sq = 0.0;
    for name in test_names() {
        let rough = example().join(format!("test/{name}_roughness.png"));
        std::fs::copy(&rough, g.join(format!("test/{name}_metallic.png"))).unwrap();
        std::fs::copy(&rough, g.join(format!("test/{name}_roughness.png"))).unwrap();
        std::fs::copy(&rough, pred.path().join(format!("test/{name}_metallic.png"))).unwrap();
        std::fs::copy(&rough, none.path().join(format!("test/{name}_roughness.png"))).unwrap();
        // The GT-alpha-weighted mean of m² (a 0 prediction's error).
        let img = image::open(&rough).unwrap().to_rgba8();
        let (mut s, mut w) = (0.0, 0.0);
        for px in img.pixels() {
            let (m, a) = (px[0] as f64 / 255.0, px[3] as f64 / 255.0);
            s += a * m * m;
            w += a;
        }
        mean_sq += s / w / test_names().len() as f64;
    }
    let run = |pred: &Path| -> serde_json::Value {
        let out = pred.join("metrics.json");
        let st = assert_cmd::Command::cargo_bin("pii-bake").unwrap().args(["eval", "--gt"]).arg(g).arg("--pred").arg(pred).arg("--out").arg(&out).output().unwrap();
        assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap()
    };
    let m = run(pred.path());
    assert_eq!(f(&m["metallic"]["mse"]), 0.0, "{}", m["metallic"]);
    assert_eq!(m["metallic"]["views"], test_names().len() as u64);
    let m = run(none.path());
    let got = f(&m["metallic"]["mse"]);
    assert!((got - mean_sq).abs() < 1e-3 * mean_sq && got > 0.01, "{got} vs {mean_sq}");
    assert!(m["metallic"]["predicted"].as_str().unwrap().contains("dielectric"), "{}", m["metallic"]);
}

#[test]
fn known_error_on_novel_views_gives_expected_psnr() {
    // Every sRGB value off by exactly 0.02 (sign chosen to stay in [0, 1]): PSNR = 20 log10(1 / 0.02).
    let pred = tempfile::tempdir().unwrap();
    let p = pred.path();
    let sigma = 0.02f32;
    for name in test_names() {
        let g = read_image_linear(&example().join(format!("test/{name}.png"))).unwrap();
        let rgb: Vec<f32> = g
            .rgb()
            .iter()
            .map(|v| {
                let s = linear_to_srgb(*v);
                srgb_to_linear(if s + sigma <= 1.0 { s + sigma } else { s - sigma })
            })
            .collect();
        write_exr_rgb(&p.join(format!("test/{name}.exr")), g.width, g.height, &rgb).unwrap();
    }
    let m = eval(p);
    let expected = 20.0 * (1.0 / sigma as f64).log10();
    let got = f(&m["novel_view"]["psnr"]);
    assert!((got - expected).abs() < 0.1, "{got} vs {expected}");
    assert!(f(&m["novel_view"]["ssim"]) < 1.0);
    assert!(m.get("albedo").is_none(), "no albedo prediction, no albedo metric");
    assert!(!m["missing"].as_array().unwrap().is_empty());
}

#[test]
fn relit_views_are_also_scored_after_a_per_channel_scale() {
    // Relit predictions at half the ground truth's linear intensity: the raw PSNR sees it, the
    // aligned one (one least-squares scale per channel over the views) does not.
    let pred = tempfile::tempdir().unwrap();
    let p = pred.path();
    for name in test_names() {
        let g = read_image_linear(&example().join(format!("test/{name}_relit_envmap6.png"))).unwrap();
        let half: Vec<f32> = g.rgb().iter().map(|v| 0.5 * v).collect();
        write_exr_rgb(&p.join(format!("test/{name}_relit_envmap6.exr")), g.width, g.height, &half).unwrap();
    }
    let m = eval(p);
    let r = &m["relit"]["envmap6"];
    assert!(f(&r["psnr"]) < 30.0, "{r}");
    assert!(f(&r["psnr_aligned"]) > 60.0, "{r}");
    assert!((f(&r["scale"][0]) - 2.0).abs() < 1e-3, "{r}");
}

#[test]
fn wrong_size_prediction_names_the_file() {
    let pred = tempfile::tempdir().unwrap();
    let name = &test_names()[0];
    write_exr_rgb(&pred.path().join(format!("test/{name}.exr")), 7, 5, &[0.5; 7 * 5 * 3]).unwrap();
    let out = assert_cmd::Command::cargo_bin("pii-bake")
        .unwrap()
        .args(["eval", "--gt"])
        .arg(example())
        .arg("--pred")
        .arg(pred.path())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains(&format!("{name}.exr")) && e.contains("7x5"), "{e}");
}
