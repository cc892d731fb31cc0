//! End-to-end export of analytic assets: the Khronos glTF-Validator reports 0 errors and 0
//! warnings, usd-core's validators (scripts/usd_check.py) report no error on asset.usda,
//! lookdev.usda and the .usdz, the textures follow the conventions, and bad output folders
//! give clear errors.

use std::path::Path;
use std::process::Command;

mod common;
use common::{assert_gltf_valid, assert_usd_valid, python, run};

use pii_bake::backend::Backend;
use pii_bake::export::{export_asset, ExportConfig, ExportError, TextureSize};
use pii_bake::mesh::field::{AnalyticMaterial, AnalyticSdf, AnalyticShape};
use pii_bake::mesh::MeshConfig;

fn export(
    shape: AnalyticShape,
    material: AnalyticMaterial,
    dir: &Path,
) -> pii_bake::export::ExportReport {
    let cfg = ExportConfig {
        name: shape.name().to_string(),
        mesh: MeshConfig {
            resolution: 64,
            error_bound: None,
            ..Default::default()
        },
        texture: TextureSize::Fixed(256),
        usdz: true,
        metres_per_unit: 0.25,
        env_width: 64,
        ..Default::default()
    };
    export_asset(
        &Backend::cpu(),
        &AnalyticSdf::new(shape),
        &material,
        None,
        &cfg,
        dir,
    )
    .unwrap()
}

#[test]
fn exported_assets_pass_gltf_and_usd_validators() {
    let dir = tempfile::tempdir().unwrap();
    let mut glbs = Vec::new();
    let mut usds = Vec::new();
    for (shape, material) in [
        (AnalyticShape::Bowl, AnalyticMaterial::Checker),
        (AnalyticShape::Torus, AnalyticMaterial::Gradient),
    ] {
        let out = dir.path().join(shape.name());
        let report = export(shape, material, &out);
        for f in &report.files {
            assert!(out.join(f).is_file(), "{} missing", f.display());
        }
        // Metres and origin at the bottom centre.
        let (lo, hi) = report.bounds_m;
        assert!(
            lo[1].abs() < 1e-6 && (lo[0] + hi[0]).abs() < 1e-5 && (lo[2] + hi[2]).abs() < 1e-5,
            "{lo:?} {hi:?}"
        );
        assert!(
            hi[0] - lo[0] < 0.25 * 2.0 && hi[0] - lo[0] > 0.25 * 0.9,
            "scaled by metres_per_unit"
        );
        assert!(report.mesh.watertight);
        glbs.push(out.join(format!("{}.glb", shape.name())));
        for f in ["asset.usda", "lookdev.usda"] {
            usds.push(out.join(f));
        }
        usds.push(out.join(format!("{}.usdz", shape.name())));
        check_textures(&out);
        let thumb =
            image::open(out.join(format!(".thumbs/256x256/{}.glb.png", shape.name()))).unwrap();
        assert_eq!((thumb.width(), thumb.height()), (256, 256));
    }
    assert_gltf_valid(&glbs);
    assert_usd_valid(&usds);
}

/// Power-of-two textures; ORM has R = 1, B = 0; no iCCP/gAMA chunks.
fn check_textures(out: &Path) {
    for name in ["albedo.png", "orm.png"] {
        let p = out.join("textures").join(name);
        let bytes = std::fs::read(&p).unwrap();
        for chunk in [b"iCCP", b"gAMA"] {
            assert!(
                !bytes.windows(4).any(|w| w == chunk),
                "{name} has a {} chunk",
                String::from_utf8_lossy(chunk)
            );
        }
        let img = image::load_from_memory(&bytes).unwrap().to_rgb8();
        assert!(img.width().is_power_of_two() && img.width() == img.height());
        if name == "orm.png" {
            assert!(
                img.pixels().all(|p| p[0] == 255 && p[2] == 0),
                "ORM must have R = 1 and B = 0"
            );
            let g: Vec<u8> = img.pixels().map(|p| p[1]).collect();
            assert!(g.iter().min() != g.iter().max(), "roughness varies");
        }
    }
}

#[test]
fn the_usd_checker_catches_a_broken_asset() {
    // Guards the validator wiring itself: a payload without upAxis and with a missing texture fails.
    let dir = tempfile::tempdir().unwrap();
    export(
        AnalyticShape::Sphere,
        AnalyticMaterial::Gradient,
        dir.path(),
    );
    let payload = std::fs::read_to_string(dir.path().join("payload.usda")).unwrap();
    let broken = payload
        .replace("    upAxis = \"Y\"\n", "")
        .replace("textures/albedo.png", "textures/missing.png");
    std::fs::write(dir.path().join("broken.usda"), broken).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/usd_check.py");
    let (ok, text) = run(Command::new(python())
        .arg(&script)
        .arg(dir.path().join("broken.usda")));
    assert!(!ok, "{text}");
    assert!(
        text.contains("UpAxis") && text.contains("missing.png"),
        "{text}"
    );
}

#[test]
fn unwritable_output_folder_is_a_clear_error_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let blocker = dir.path().join("not-a-folder");
    std::fs::write(&blocker, b"x").unwrap();
    let out = blocker.join("asset");
    let err = export_asset(
        &Backend::cpu(),
        &AnalyticSdf::new(AnalyticShape::Sphere),
        &AnalyticMaterial::Checker,
        None,
        &ExportConfig::default(),
        &out,
    )
    .unwrap_err();
    assert!(matches!(err, ExportError::Data(_)), "{err}");
    assert!(
        err.to_string().contains("not-a-folder") && err.to_string().contains("output folder"),
        "{err}"
    );
    // A failed export leaves no spinner running.
    let pb = indicatif::ProgressBar::hidden();
    let err = pii_bake::export::export_asset_with(
        &Backend::cpu(),
        &AnalyticSdf::new(AnalyticShape::Sphere),
        &AnalyticMaterial::Checker,
        None,
        &ExportConfig::default(),
        &out,
        &pb,
    )
    .unwrap_err();
    assert!(err.to_string().contains("not-a-folder"), "{err}");
    assert!(pb.is_finished());
    let bad_name = ExportConfig {
        name: "Bad Name".into(),
        ..Default::default()
    };
    let err = export_asset(
        &Backend::cpu(),
        &AnalyticSdf::new(AnalyticShape::Sphere),
        &AnalyticMaterial::Checker,
        None,
        &bad_name,
        dir.path(),
    )
    .unwrap_err();
    assert!(err.to_string().contains("[a-z]"), "{err}");
}

#[test]
fn cli_exports_a_test_pattern_and_rejects_bad_flags() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("box");
    assert_cmd::Command::cargo_bin("pii-bake")
        .unwrap()
        .args([
            "--backend",
            "cpu",
            "export",
            "--analytic",
            "rounded-box",
            "--resolution",
            "48",
            "--texture",
            "256",
            "--out",
        ])
        .arg(&out)
        .assert()
        .success();
    assert!(out.join("rounded-box.glb").is_file() && out.join("asset.usda").is_file());
    assert_cmd::Command::cargo_bin("pii-bake")
        .unwrap()
        .args([
            "export",
            "--analytic",
            "sphere",
            "--texture",
            "300",
            "--out",
        ])
        .arg(&out)
        .assert()
        .code(2);
    // `--face-tolerance`: outside 1..=90 degrees a usage error naming the range; within it the
    // report holds every face to it (or to the unsimplified mesh's own lean, if that is worse).
    let o = assert_cmd::Command::cargo_bin("pii-bake").unwrap().args(["export", "--analytic", "sphere", "--face-tolerance", "95", "--out"]).arg(&out).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("must be in 1..=90"), "{}", String::from_utf8_lossy(&o.stderr));
    let torus = dir.path().join("torus");
    assert_cmd::Command::cargo_bin("pii-bake")
        .unwrap()
        .args(["--backend", "cpu", "export", "--analytic", "torus", "--resolution", "40", "--texture", "64", "--face-tolerance", "12", "--out"])
        .arg(&torus)
        .assert()
        .success();
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(torus.join("export_report.json")).unwrap()).unwrap();
    let (face, own) = (report["mesh"]["face_angle_deg"].as_f64().unwrap(), report["mesh"]["unsimplified"]["face_angle_deg"].as_f64().unwrap());
    assert!(face <= 12f64.max(own) + 1e-3, "faces lean {face}° (unsimplified {own}°)");
}

/// A checker whose light squares are metal (the learnt material's metallic channel, in a field
/// the test controls).
struct HalfMetal;

impl pii_bake::mesh::field::MaterialField for HalfMetal {
    fn name(&self) -> String {
        "checker, metal where x > 0".into()
    }
    fn eval(&self, backend: &Backend, points: &[[f32; 3]], normals: &[[f32; 3]]) -> Result<pii_bake::mesh::field::MaterialSamples, pii_bake::backend::BackendError> {
        let mut m = AnalyticMaterial::Checker.eval(backend, points, normals)?;
        m.metallic = points.iter().map(|p| if p[0] > 0.0 { 1.0 } else { 0.0 }).collect();
        Ok(m)
    }
    fn feature_size(&self) -> Option<f32> {
        AnalyticMaterial::Checker.feature_size()
    }
}

#[test]
fn a_metallic_material_reaches_the_orm_texture_the_glb_and_the_usd() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("metal");
    let cfg = ExportConfig {
        name: "metal".into(),
        mesh: MeshConfig { resolution: 48, error_bound: None, ..Default::default() },
        texture: TextureSize::Fixed(128),
        metres_per_unit: 0.25,
        env_width: 64,
        ..Default::default()
    };
    export_asset(&Backend::cpu(), &AnalyticSdf::new(AnalyticShape::Torus), &HalfMetal, None, &cfg, &out).unwrap();
    let orm = image::open(out.join("textures/orm.png")).unwrap().to_rgb8();
    let metal = orm.pixels().filter(|p| p[2] == 255).count() as f64 / orm.pixels().len() as f64;
    let dielectric = orm.pixels().filter(|p| p[2] == 0).count() as f64 / orm.pixels().len() as f64;
    assert!(metal > 0.2 && dielectric > 0.2 && metal + dielectric > 0.95, "ORM B: {metal:.2} metal, {dielectric:.2} dielectric");
    // The .glb's material reads metallic from the texture (factor 1).
    let json = common::glb_json(&out.join("metal.glb"));
    let pbr = &json["materials"][0]["pbrMetallicRoughness"];
    assert_eq!(pbr["metallicFactor"].as_f64(), Some(1.0), "{pbr}");
    assert!(pbr["metallicRoughnessTexture"].is_object());
    let payload = std::fs::read_to_string(out.join("payload.usda")).unwrap();
    assert!(payload.contains("inputs:metallic.connect = </metal/mtl/metal_mat/orm.outputs:b>") && payload.contains("float outputs:b"), "{payload}");
    assert_gltf_valid(&[out.join("metal.glb")]);
    assert_usd_valid(&[out.join("asset.usda")]);
    // A dielectric field keeps factor 0 (and B = 0: `check_textures`).
    let plain = dir.path().join("plain");
    export_asset(&Backend::cpu(), &AnalyticSdf::new(AnalyticShape::Torus), &AnalyticMaterial::Checker, None, &ExportConfig { name: "plain".into(), ..cfg }, &plain).unwrap();
    let json = common::glb_json(&plain.join("plain.glb"));
    assert_eq!(json["materials"][0]["pbrMetallicRoughness"]["metallicFactor"].as_f64().unwrap_or(0.0), 0.0);
    assert!(std::fs::read_to_string(plain.join("payload.usda")).unwrap().contains("float inputs:metallic = 0"));
}
