//! `train --stage material`, `export --run` of a stage-2 run, `relight` and `eval` through the
//! binary, at tiny sizes: a stage-2 run interrupted and resumed follows the straight run's loss
//! curve; the export ships learned textures and environment; relight writes what `eval` scores;
//! bad inputs (no stage-1 run, a run from another scene or preset, a map that is not a latlong
//! HDR, an unwritable folder) give one clear error naming the file.

use std::path::Path;

mod common;

use common::{copy_dir, example, pii, shared_data, text};

fn stage1(run: &Path) {
    let ex = example();
    let o = pii(&["train", ex.to_str().unwrap(), "--out", run.to_str().unwrap(), "--rays", "96", "--downscale", "4", "--init", "hull", "--init-steps", "20", "--iterations", "3", "--seed", "2"]);
    assert!(o.status.success(), "{}", text(&o));
}

const TINY2: [&str; 12] = ["--stage", "material", "--lobes", "6", "--material-batch", "64", "--material-set", "points=600", "--material-set", "checkpoint_every=2", "--seed", "2"];

fn stage2(run: &Path, extra: &[&str]) -> std::process::Output {
    let ex = example();
    let mut a = vec!["train", ex.to_str().unwrap(), "--out", run.to_str().unwrap()];
    a.extend_from_slice(&TINY2);
    a.extend_from_slice(extra);
    pii(&a)
}

fn curve(run: &Path) -> Vec<String> {
    std::fs::read_to_string(run.join("material_curve.csv")).unwrap().lines().skip(1).map(|l| l.rsplit_once(',').unwrap().0.to_string()).collect()
}

/// A copy of the example scene (its files and its train/test/env/gt folders).
fn copy_example(dst: &Path) {
    copy_dir(&example(), dst);
    for sub in ["train", "test", "env", "gt"] {
        copy_dir(&example().join(sub), &dst.join(sub));
    }
}

/// Both stages at test size on `scene` into `run`.
fn train_all_tiny(scene: &Path, run: &Path) -> std::process::Output {
    pii(&[
        "train", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--stage", "all", "--rays", "96", "--downscale", "4", "--init-steps", "20", "--iterations", "3",
        "--lobes", "6", "--material-iterations", "4", "--material-batch", "64", "--material-set", "points=600",
    ])
}

#[test]
fn stage_two_resumes_exactly_exports_and_relights() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    stage1(&a);
    copy_dir(&a, &b);
    let o = stage2(&a, &["--material-iterations", "6"]);
    assert!(o.status.success(), "{}", text(&o));
    let out = text(&o);
    assert!(out.contains("stage 2") && out.contains("cached surface points") && out.contains("PSNR"), "{out}");
    let o = stage2(&b, &["--material-iterations", "6", "--stop-at", "3"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = stage2(&b, &["--material-iterations", "6", "--resume"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("resuming stage 2"), "{}", text(&o));
    let (ca, cb) = (curve(&a), curve(&b));
    assert_eq!(ca.len(), 6);
    assert_eq!(ca, cb, "a resumed stage-2 run follows the straight run");
    // The resumed run's report counts both invocations' steps; a finished run trained again keeps it.
    let read = |p: &Path| -> serde_json::Value { serde_json::from_slice(&std::fs::read(p.join("material_report.json")).unwrap()).unwrap() };
    let rb = read(&b);
    assert_eq!((rb["timed_steps"].as_u64(), rb["resumed_at"].as_u64()), (Some(6), Some(3)), "{rb}");
    let o = stage2(&b, &["--material-iterations", "6", "--resume"]);
    assert!(o.status.success() && !text(&o).contains("at 0.00 it/s"), "{}", text(&o));
    assert_eq!((read(&b)["timed_steps"].as_u64(), read(&b)["it_per_s"].as_f64()), (Some(6), rb["it_per_s"].as_f64()));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("material_report.json")).unwrap()).unwrap();
    assert_eq!(report["sizes"]["lobes"], 6);
    assert_eq!(report["config"]["decoder"], "separate", "a transforms.json scene is synthetic");
    assert_eq!(report["config"]["metallic"], true, "metals are modelled by default");
    assert!(report["sizes"]["why"]["metallic"].as_str().unwrap().starts_with("on"), "{}", report["sizes"]["why"]);
    assert!(report["material"]["metallic"]["mean"].as_f64().unwrap().is_finite());
    assert!(report["cache"]["points"].as_u64().unwrap() > 100);
    assert!(report["eval"]["psnr"].as_f64().unwrap().is_finite());
    // The fast preset's material grid: half stage 1's finest resolution, stage 1's table, and the
    // grid's latent smoothness.
    let run: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("run.json")).unwrap()).unwrap();
    let sizes = &run["config"]["sizes"];
    let grid = &report["config"]["material_encoding"]["HashGrid"];
    let finest = grid["base_resolution"].as_f64().unwrap() * grid["growth"].as_f64().unwrap().powi(grid["levels"].as_i64().unwrap() as i32 - 1);
    let want = (sizes["grid_finest"].as_f64().unwrap() / 2.0).floor().max(32.0);
    assert!((finest - want).abs() < 0.5, "material grid finest {finest}, want {want}: {grid}");
    assert_eq!(grid["log2_table_size"], sizes["grid_log2_table"]);
    assert_eq!(report["config"]["smooth_weight"].as_f64().unwrap(), 1.0);

    // Export: learned textures and the learned environment.
    let asset = dir.path().join("asset");
    let o = pii(&["export", "--run", a.to_str().unwrap(), "--out", asset.to_str().unwrap(), "--resolution", "40", "--texture", "64", "--name", "spot"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("from the material field"), "{}", text(&o));
    common::assert_gltf_valid(&[asset.join("spot.glb")]);

    // Relight one view under a shipped map; eval scores the folder.
    let rel = dir.path().join("relit");
    let env = example().join("env/sunset.exr");
    let o = pii(&["relight", a.to_str().unwrap(), "--env", env.to_str().unwrap(), "--lobes", "8", "--max-views", "1", "--out", rel.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    for f in ["test/r_000.png", "test/r_000_relit_sunset.png", "test/r_000_albedo.png", "test/r_000_roughness.png", "test/r_000_normal.png", "env.exr"] {
        assert!(rel.join(f).is_file(), "{f} missing: {}", text(&o));
    }
    let metrics = dir.path().join("metrics.json");
    let ex = example();
    let o = pii(&["eval", "--gt", ex.to_str().unwrap(), "--pred", rel.to_str().unwrap(), "--out", metrics.to_str().unwrap(), "--mesh-samples", "1000"]);
    assert!(o.status.success(), "{}", text(&o));
    let m = std::fs::read_to_string(&metrics).unwrap();
    assert!(m.contains("relit") && m.contains("albedo"), "{m}");
    // The shading normals are written in the scene's world frame (the GT normal pass's): a frame
    // mix-up (e.g. the asset's Y-up) shows as an error near 60 degrees; this tiny model is near 26.
    let mv: serde_json::Value = serde_json::from_str(&m).unwrap();
    let mae = mv["normal"]["mae_degrees"].as_f64().unwrap();
    assert!(mae < 40.0, "normal error {mae} degrees: {m}");
    // A quick look at half size.
    let half = dir.path().join("relit_half");
    let o = pii(&["relight", a.to_str().unwrap(), "--env", env.to_str().unwrap(), "--lobes", "8", "--max-views", "1", "--downscale", "2", "--out", half.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let (w, h) = image::image_dimensions(rel.join("test/r_000_relit_sunset.png")).unwrap();
    assert_eq!(image::image_dimensions(half.join("test/r_000_relit_sunset.png")).unwrap(), (w / 2, h / 2));
    // eval scores it against the ground truth filtered to half size: the same model, so the same
    // figures within what the smaller pixels forgive (this tiny model: 0.4-0.6 dB higher; the
    // filter itself is checked by eval::cli's unit test).
    let hm = dir.path().join("metrics_half.json");
    let o = pii(&["eval", "--gt", ex.to_str().unwrap(), "--pred", half.to_str().unwrap(), "--out", hm.to_str().unwrap(), "--mesh-samples", "1000"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("scored at 1/2"), "{}", text(&o));
    let hv: serde_json::Value = serde_json::from_slice(&std::fs::read(&hm).unwrap()).unwrap();
    assert_eq!(hv["downscale"], 2);
    assert_eq!(mv["downscale"], 1);
    for key in [["relit", "sunset", "psnr"], ["relit", "sunset", "psnr_aligned"], ["albedo", "psnr_aligned", ""], ["novel_view", "psnr", ""]] {
        let get = |v: &serde_json::Value| {
            let x = &v[key[0]][key[1]];
            (if key[2].is_empty() { x } else { &x[key[2]] }).as_f64().unwrap()
        };
        let (full, small) = (get(&mv), get(&hv));
        assert!((full - small).abs() < 1.5, "{key:?}: full size {full} dB, half size {small} dB");
    }
    let (full, small) = (mae, hv["normal"]["mae_degrees"].as_f64().unwrap());
    assert!((full - small).abs() < 3.0, "normal error: full size {full}, half size {small} degrees");
    let rough = |v: &serde_json::Value| v["roughness"]["mse"].as_f64().unwrap();
    assert!((rough(&mv) - rough(&hv)).abs() < 0.01 + 0.2 * rough(&mv), "roughness MSE {} vs {}", rough(&mv), rough(&hv));
    // A render at another size is refused, naming the file.
    let odd = half.join("test/r_000_albedo.png");
    image::RgbaImage::new(w / 3 + 1, h / 3).save(&odd).unwrap();
    let o = pii(&["eval", "--gt", ex.to_str().unwrap(), "--pred", half.to_str().unwrap(), "--mesh-samples", "1000"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("r_000_albedo.png") && text(&o).contains("render at its size or at 1/N of it"), "{}", text(&o));
}

#[test]
fn a_metallic_run_trains_exports_its_metallic_texture_and_relights_its_view() {
    let dir = tempfile::tempdir().unwrap();
    // Both stages and the export at test size: (the run, its stage-2 report, the asset folder).
    let train_export = |name: &str, metallic: &str, brdf: &[&str]| {
        let run = dir.path().join(name);
        stage1(&run);
        let o = stage2(&run, &[&["--material-iterations", "4", "--metallic", metallic], brdf].concat());
        assert!(o.status.success(), "{}", text(&o));
        let report: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("material_report.json")).unwrap()).unwrap();
        let asset = dir.path().join(format!("{name}_asset"));
        let o = pii(&["export", "--run", run.to_str().unwrap(), "--out", asset.to_str().unwrap(), "--resolution", "40", "--texture", "64", "--name", "spot"]);
        assert!(o.status.success(), "{}", text(&o));
        (run, report, asset)
    };
    let (run, report, asset) = train_export("on", "on", &[]);
    assert_eq!(report["config"]["metallic"], true);
    assert_eq!(report["config"]["brdf"], "calibrated", "the BRDF matched to Cycles by default");
    assert_eq!(report["config"]["brdf_warmup"], 0.5, "after PhySG's warm-up");
    assert!(report["sizes"]["why"]["brdf"].as_str().unwrap().contains("--brdf physg"), "{}", report["sizes"]["why"]);
    assert!(report["sizes"]["why"]["metallic"].as_str().unwrap().contains("--metallic off"), "{}", report["sizes"]["why"]);
    let m = &report["material"]["metallic"];
    assert!(m["mean"].as_f64().unwrap() > 0.2 && m["mean"].as_f64().unwrap() < 0.8, "starts at 0.5, neither metal nor dielectric: {m}");
    let json = common::glb_json(&asset.join("spot.glb"));
    assert_eq!(json["materials"][0]["pbrMetallicRoughness"]["metallicFactor"].as_f64(), Some(1.0));
    let orm = image::open(asset.join("textures/orm.png")).unwrap().to_rgb8();
    assert!(orm.pixels().any(|p| p[2] > 0), "the metallic channel reaches ORM B");
    common::assert_gltf_valid(&[asset.join("spot.glb")]);
    let rel = dir.path().join("relit");
    let env = example().join("env/sunset.exr");
    let o = pii(&["relight", run.to_str().unwrap(), "--env", env.to_str().unwrap(), "--lobes", "8", "--max-views", "1", "--downscale", "4", "--out", rel.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(rel.join("test/r_000_metallic.png").is_file(), "{}", text(&o));
    // `--metallic off`: four material channels, a dielectric asset, no metallic view; with the
    // paper's BRDF (`--brdf physg`) recorded in the run.
    let (_, report, asset) = train_export("off", "off", &["--brdf", "physg"]);
    assert_eq!(report["config"]["metallic"], false);
    assert_eq!(report["config"]["brdf"], "physg");
    assert!(report["material"]["metallic"].is_null());
    let orm = image::open(asset.join("textures/orm.png")).unwrap().to_rgb8();
    assert!(orm.pixels().all(|p| p[2] == 0), "a dielectric asset's ORM B is 0");
}

#[test]
fn a_test_view_left_out_of_training_is_still_relit() {
    // Test camera r_000 turned 6°: the silhouette check leaves it out of both stages, but relight
    // renders every test camera it is asked for, so eval finds the view.
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    copy_example(&scene);
    common::turn_camera(&scene.join("transforms_test.json"), "r_000", 6.0);
    let run = dir.path().join("run");
    let o = train_all_tiny(&scene, &run);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("excluded view r_000"), "{}", text(&o));
    let rel = dir.path().join("relit");
    let env = example().join("env/sunset.exr");
    let o = pii(&["relight", run.to_str().unwrap(), "--env", env.to_str().unwrap(), "--lobes", "8", "--max-views", "1", "--out", rel.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("rendering test view(s) r_000 too"), "{}", text(&o));
    for f in ["test/r_000.png", "test/r_000_relit_sunset.png", "test/r_000_albedo.png"] {
        assert!(rel.join(f).is_file(), "{f} missing: {}", text(&o));
    }
}

#[test]
fn stage_two_bad_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    // Stage 1's step flags on stage 2 (they were silently ignored: `--iterations 4800` trained
    // the preset's 2400 steps): a usage error naming the stage-2 flags, before anything runs.
    let empty = dir.path().join("empty");
    for flags in [&["--iterations", "5"][..], &["--rays", "64", "--iterations", "5"]] {
        let o = stage2(&empty, flags);
        assert_eq!(o.status.code(), Some(2), "{}", text(&o));
        assert!(text(&o).contains("--material-iterations") && text(&o).contains(flags[0]), "{}", text(&o));
        assert!(!empty.exists(), "nothing is written on a usage error");
    }

    // No stage-1 run.
    let o = stage2(&empty, &["--material-iterations", "1"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("checkpoint.safetensors") && text(&o).contains("train the geometry first"), "{}", text(&o));

    // A stage-1 run from another scene.
    let run = dir.path().join("run");
    stage1(&run);
    let other = dir.path().join("other_scene");
    copy_example(&other);
    let o = pii(&["train", other.to_str().unwrap(), "--out", run.to_str().unwrap(), "--stage", "material", "--material-iterations", "1", "--downscale", "4"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("another scene"), "{}", text(&o));

    // A stage-1 run of another preset: refused, naming its checkpoint; without `--preset` stage 2
    // follows the run's.
    assert_eq!(pii_bake::train::cli::run_preset(&run), Some(pii_bake::train::stage1::Preset::Fast));
    let o = stage2(&run, &["--material-iterations", "1", "--preset", "paper"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("checkpoint.safetensors") && text(&o).contains("fast preset, not paper"), "{}", text(&o));
    assert!(!run.join("material.safetensors").exists());

    // A checkpoint interval of 0 is refused before training (it used to panic at the first step's
    // checkpoint rule, dividing by it).
    let o = stage2(&run, &["--material-iterations", "1", "--material-set", "checkpoint_every=0"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("checkpoint_every must be > 0") && !text(&o).contains("panicked"), "{}", text(&o));
    assert!(!run.join("material.safetensors").exists());

    // Relight without a stage-2 run, with a map that is not a latlong HDR, into an unwritable folder.
    let rel = dir.path().join("rel");
    let env = example().join("env/sunset.exr");
    let o = pii(&["relight", run.to_str().unwrap(), "--env", env.to_str().unwrap(), "--out", rel.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("no stage-2 run here"), "{}", text(&o));
    let o = stage2(&run, &["--material-iterations", "1"]);
    assert!(o.status.success(), "{}", text(&o));
    let png = example().join("test/r_000.png");
    let o = pii(&["relight", run.to_str().unwrap(), "--env", png.to_str().unwrap(), "--out", rel.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("r_000.png") && text(&o).contains("exr"), "{}", text(&o));
    let square = dir.path().join("square.exr");
    pii_bake::image_io::write_exr_rgb(&square, 8, 8, &[0.5; 8 * 8 * 3]).unwrap();
    let o = pii(&["relight", run.to_str().unwrap(), "--env", square.to_str().unwrap(), "--out", rel.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("square.exr") && text(&o).contains("2:1"), "{}", text(&o));
    let blocker = dir.path().join("file");
    std::fs::write(&blocker, b"x").unwrap();
    let o = pii(&["relight", run.to_str().unwrap(), "--env", env.to_str().unwrap(), "--out", blocker.join("sub").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(!blocker.join("sub").exists());
}

#[test]
fn baselines_train_through_the_cli_and_resume() {
    // The MII/InvRender-like baseline (its SG net fitted to the stage-1 radiance) and the
    // PhySG-like one (no indirect, one roughness for the object), each stopped and resumed; the
    // first also with its boundary lights detached (the public code's).
    let dir = tempfile::tempdir().unwrap();
    let base = dir.path().join("base");
    stage1(&base);
    for (name, extra) in [("mii", vec!["--indirect", "mii", "--boundary", "detached"]), ("physg", vec!["--indirect", "none", "--roughness", "constant"])] {
        let (a, b) = (dir.path().join(format!("{name}_a")), dir.path().join(format!("{name}_b")));
        copy_dir(&base, &a);
        copy_dir(&base, &b);
        let mut args = extra.clone();
        args.extend(["--material-iterations", "4"]);
        let o = stage2(&a, &args);
        assert!(o.status.success(), "{name}: {}", text(&o));
        let o = stage2(&b, &[args.as_slice(), &["--stop-at", "2"]].concat());
        assert!(o.status.success(), "{name}: {}", text(&o));
        let o = stage2(&b, &[args.as_slice(), &["--resume"]].concat());
        assert!(o.status.success(), "{name}: {}", text(&o));
        assert_eq!(curve(&a), curve(&b), "{name}: a resumed run follows the straight run");
        let report: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("material_report.json")).unwrap()).unwrap();
        let cfg = &report["config"];
        assert_eq!(cfg["indirect"], if name == "mii" { "mii" } else { "none" });
        assert_eq!(cfg["roughness"], if name == "mii" { "field" } else { "constant" });
        assert_eq!(cfg["boundary"], if name == "mii" { "detached" } else { "flowing" });
        let bf = report["cache"]["boundary_fraction"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&bf), "{report}");
        assert!(report["eval"]["psnr"].as_f64().unwrap().is_finite(), "{report}");
    }
}

/// `bench material` on a tiny stage-1 run of the example (4 lobes, 2 steps, small batches) with
/// `variants` naming what to measure; returns the temporary folder and the bench's output folder.
fn bench_material(variants: &[&str]) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    stage1(&run);
    let out = dir.path().join("bench");
    let mut args = vec!["bench", "material", "--run", run.to_str().unwrap(), "--out", out.to_str().unwrap(), "--lobes", "4", "--iterations", "2", "--set", "points=400", "--set", "batch=32"];
    args.extend_from_slice(variants);
    let o = pii(&args);
    assert!(o.status.success(), "{}", text(&o));
    (dir, out)
}

#[test]
fn bench_material_writes_figures_per_variant() {
    let (_dir, out) = bench_material(&["--indirect", "ours", "none", "--boundary", "flowing", "detached", "--geometry", "frozen", "refined", "--relight-views", "0"]);
    let csv = std::fs::read_to_string(out.join("bench-material.csv")).unwrap();
    assert!(csv.lines().next().unwrap().contains(",novel_view_psnr,albedo_psnr,relit_psnr,relit_aligned_psnr,relit_per_map,roughness_mse,metallic_mse,"), "{csv}");
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(rows.len(), 8, "{csv}");
    let names: Vec<&str> = rows.iter().map(|r| r.split(',').next().unwrap()).collect();
    assert_eq!(names, ["k4-ours", "k4-ours-refined", "k4-ours-detached", "k4-ours-detached-refined", "k4-none", "k4-none-refined", "k4-none-detached", "k4-none-detached-refined"], "{csv}");
    assert!(rows[2].contains(",detached,frozen,") && rows[1].contains(",flowing,refined,"), "{csv}");
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("bench-material.json")).unwrap()).unwrap();
    let r = &json["rows"][0];
    assert!(r["it_per_s"].as_f64().unwrap() > 0.0 && r["heldout_psnr"].as_f64().unwrap().is_finite(), "{r}");
    assert!(r["cache_evaluations"].as_f64().unwrap() > 0.0);
    assert!(std::fs::read_to_string(out.join("bench-material.svg")).unwrap().contains("<svg"));
}

#[test]
fn bench_material_scores_every_relight_map_on_a_scene_with_ground_truth() {
    let (_dir, out) = bench_material(&["--indirect", "ours", "--relight-views", "1"]);
    // The example's relight maps: every map in env/ but the training light.
    let mut maps: Vec<String> = std::fs::read_dir(example().join("env"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "exr"))
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .filter(|s| s != "train")
        .collect();
    maps.sort();
    assert_eq!(maps.len(), 2);
    let csv = std::fs::read_to_string(out.join("bench-material.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let row: Vec<&str> = csv.lines().nth(1).unwrap().split(',').collect();
    // (The quoted backend cell holds no comma, so the cells line up with the header.)
    assert_eq!(row.len(), header.len(), "{csv}");
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("bench-material.json")).unwrap()).unwrap();
    let r = &json["rows"][0];
    let per_map = r["relit_maps"].as_object().unwrap();
    assert_eq!(per_map.keys().cloned().collect::<Vec<_>>(), maps, "{r}");
    let psnrs: Vec<f64> = per_map.values().map(|v| v["psnr"].as_f64().unwrap()).collect();
    for v in per_map.values() {
        assert!(v["psnr"].as_f64().unwrap().is_finite() && v["psnr_aligned"].as_f64().unwrap().is_finite(), "{r}");
    }
    // The mean over maps is the mean of these, and the CSV cell lists the same figures.
    let mean = psnrs.iter().sum::<f64>() / psnrs.len() as f64;
    assert!((r["relit_psnr"].as_f64().unwrap() - mean).abs() < 1e-9, "{r}");
    let col = header.iter().position(|h| *h == "relit_per_map").expect("relit_per_map column");
    let entries: Vec<&str> = row[col].split(';').collect();
    assert_eq!(entries.len(), 2, "{csv}");
    for (e, (name, v)) in entries.iter().zip(per_map) {
        assert_eq!(*e, format!("{name}={:.3}/{:.3}", v["psnr"].as_f64().unwrap(), v["psnr_aligned"].as_f64().unwrap()), "{csv}");
    }
    assert!(r["novel_view_psnr"].as_f64().unwrap().is_finite() && r["albedo_psnr"].as_f64().unwrap().is_finite(), "{r}");
    // The light's error as the shading sees it (diffuse irradiance over all normals), in both files.
    let irr = r["env_irradiance_error"].as_f64().unwrap();
    assert!(irr.is_finite() && irr >= 0.0, "{r}");
    let col = header.iter().position(|h| *h == "env_irradiance_error").expect("env_irradiance_error column");
    assert_eq!(row[col], format!("{irr:.5}"), "{csv}");
}

#[test]
fn eight_views_give_an_asset_and_finite_figures() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("eight");
    copy_example(&scene);
    let tf = scene.join("transforms_train.json");
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&tf).unwrap()).unwrap();
    let frames: Vec<serde_json::Value> = v["frames"].as_array().unwrap().iter().step_by(3).take(8).cloned().collect();
    assert_eq!(frames.len(), 8);
    v["frames"] = serde_json::Value::Array(frames);
    std::fs::write(&tf, serde_json::to_vec(&v).unwrap()).unwrap();
    // `info` estimates the coverage before any training, from the masks' visual hull (44% below
    // three for these 8 photos, 5% for the example's 24), and a new run warns before it trains.
    let est = coverage_estimate(&scene);
    assert_eq!(est["weak"], true, "{est}");
    assert_eq!(est["train_views"], 8, "{est}");
    assert!(est["below_three"].as_f64().unwrap() > 0.25, "{est}");
    let full = coverage_estimate(&example());
    assert_eq!(full["weak"], false, "{full}");
    assert!(full["below_three"].as_f64().unwrap() < 0.15, "{full}");
    let run = dir.path().join("run");
    let o = train_all_tiny(&scene, &run);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("WARNING: ") && text(&o).contains("visual hull is seen by fewer than three of the 8 training photos"), "{}", text(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("material_report.json")).unwrap()).unwrap();
    assert!(report["eval"]["psnr"].as_f64().unwrap().is_finite());
    assert!(report["weak_result"].is_boolean() && report["flags"].is_array());
    assert_eq!(report["skipped_steps"], 0);
    // Stage 1 counts the photos that see each part of the surface, and flags a surface that too
    // few photos see (the example's 24 photos leave 6.7% of it below three; these 8, 45%).
    let s1: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("train_report.json")).unwrap()).unwrap();
    let cov = &s1["coverage"];
    let below = cov["below_three"].as_f64().unwrap();
    assert!(below > 0.25 && below <= 1.0, "{cov}");
    let parts: f64 = ["seen_by_0", "seen_by_1", "seen_by_2", "seen_by_3_or_more"].iter().map(|k| cov[*k].as_f64().unwrap()).sum();
    assert!((parts - 1.0).abs() < 1e-9, "{cov}");
    assert_eq!(s1["weak_result"], true, "{s1}");
    assert!(s1["flags"].as_array().unwrap().iter().any(|f| f.as_str().unwrap().contains("fewer than three training photos")), "{}", s1["flags"]);
    assert!(text(&o).contains("WEAK RESULT") && text(&o).contains("fewer than three"), "{}", text(&o));
    let asset = dir.path().join("asset");
    let o = pii(&["export", "--run", run.to_str().unwrap(), "--out", asset.to_str().unwrap(), "--resolution", "32", "--texture", "64", "--name", "eight"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(asset.join("eight.glb").is_file() && asset.join("env.exr").is_file());
}

/// `info --json`'s coverage estimate of a scene.
fn coverage_estimate(scene: &Path) -> serde_json::Value {
    let o = pii(&["--json", "info", scene.to_str().unwrap(), "--downscale", "4"]);
    assert!(o.status.success(), "{}", text(&o));
    String::from_utf8_lossy(&o.stdout).lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()).find(|v| v["type"] == "coverage_estimate").expect("a coverage_estimate record")
}

/// `info --json`'s photo-texture record of a scene.
fn photo_texture(scene: &Path) -> serde_json::Value {
    let o = pii(&["--json", "info", scene.to_str().unwrap(), "--downscale", "4"]);
    assert!(o.status.success(), "{}", text(&o));
    let rec: serde_json::Value = String::from_utf8_lossy(&o.stdout).lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()).find(|v| v["type"] == "scene_info").expect("a scene_info record");
    rec["photo_texture"].clone()
}

#[test]
fn a_textureless_object_is_flagged_as_a_weak_result() {
    // The example with every training photo flattened to one colour inside its mask: the stage-2
    // report must flag it; the example as shipped is not textureless.
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("flat");
    copy_example(&scene);
    for e in std::fs::read_dir(scene.join("train")).unwrap() {
        let path = e.unwrap().path();
        if path.extension().and_then(|x| x.to_str()) != Some("png") {
            continue;
        }
        let img = pii_bake::image_io::read_image_linear(&path).unwrap();
        assert_eq!(img.channels, 4, "the example's photos carry their mask as alpha");
        let mut data = img.data.clone();
        for px in data.chunks_exact_mut(4) {
            px[..3].copy_from_slice(&[0.4, 0.35, 0.3]);
        }
        pii_bake::image_io::write_png8(&path, img.width, img.height, 4, &data, true).unwrap();
    }
    let shipped = photo_texture(&example());
    assert_eq!(shipped["textureless"], false, "{shipped}");
    let flat = photo_texture(&scene);
    assert_eq!(flat["textureless"], true, "{flat}");
    assert!(flat["contrast"].as_f64().unwrap() < shipped["contrast"].as_f64().unwrap() / 4.0, "{flat} vs {shipped}");

    let run = dir.path().join("run");
    let o = train_all_tiny(&scene, &run);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("WEAK RESULT") && text(&o).contains("little texture"), "{}", text(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("material_report.json")).unwrap()).unwrap();
    assert_eq!(report["weak_result"], true);
    assert!(report["flags"].as_array().unwrap().iter().any(|f| f.as_str().unwrap().contains("little texture")), "{}", report["flags"]);
    assert!(report["photo_texture"].as_f64().unwrap() < 0.08);
}

#[test]
fn ctrl_c_in_stage_two_writes_a_checkpoint_and_resume_continues() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    stage1(&run);
    let ex = example();
    let args = [&["train", ex.to_str().unwrap(), "--out", run.to_str().unwrap(), "--material-iterations", "100000"][..], &TINY2[..]].concat();
    let o = common::interrupt_after_progress(&args, &["\"material\""]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("interrupted at stage-2 step") && err.contains("--resume"), "{err}");
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("material.json")).unwrap()).unwrap();
    let step = meta["step"].as_u64().unwrap();
    assert!(step >= 1);
    let n = (step + 2).to_string();
    let o = stage2(&run, &["--material-iterations", &n, "--resume"]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(curve(&run).len() as u64, step + 2);
}

#[test]
fn refined_geometry_trains_resumes_and_exports_the_refined_surface() {
    // --refine-geometry: the SDF learns in stage 2, the cache is rebuilt on the moved surface, the
    // refined SDF is checkpointed (a run stopped at a rebuild step resumes exactly) and exported.
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    stage1(&a);
    copy_dir(&a, &b);
    let extra = ["--material-iterations", "4", "--refine-geometry", "--material-set", "geometry_retrace_every=2", "--material-set", "lr_geometry=1e-3"];
    let o = stage2(&a, &extra);
    assert!(o.status.success(), "{}", text(&o));
    let o = stage2(&b, &[extra.as_slice(), &["--stop-at", "2"]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let o = stage2(&b, &[extra.as_slice(), &["--resume"]].concat());
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(curve(&a), curve(&b), "a resumed refined run follows the straight run");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("material_report.json")).unwrap()).unwrap();
    let g = &report["geometry"];
    assert_eq!(g["refined"], true, "{g}");
    assert_eq!(g["cache_rebuilds"], 1, "{g}");
    assert!(report["last"]["eikonal"].as_f64().unwrap() > 0.0, "{}", report["last"]);
    // The refined SDF is in the stage-2 checkpoint and differs from stage 1's.
    let st = pii_bake::nn::params::ParamStore::load(&a.join("material.safetensors")).unwrap();
    let s1 = pii_bake::nn::params::ParamStore::load(&a.join("checkpoint.safetensors")).unwrap();
    let (r, o1) = (st.data("sdf").unwrap(), s1.data("sdf").unwrap());
    assert_eq!(r.len(), o1.len());
    assert!(r.iter().zip(o1).any(|(p, q)| p != q));
    let asset = dir.path().join("asset");
    let o = pii(&["export", "--run", a.to_str().unwrap(), "--out", asset.to_str().unwrap(), "--resolution", "32", "--texture", "64"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(asset.read_dir().unwrap().any(|e| e.unwrap().path().extension().is_some_and(|x| x == "glb")));
}

/// The brightest pixel's direction of a latlong map (world frame, +Y up) and the map's integral.
fn peak_and_energy(path: &Path, conv: pii_bake::sg::env::LatlongConvention) -> ([f32; 3], f64) {
    let m = pii_bake::sg::env::read_latlong_exr(path).unwrap();
    let (mut best, mut at, mut energy) = (-1.0f32, 0usize, 0.0f64);
    for p in 0..m.width * m.height {
        let v = (m.rgb[3 * p] + m.rgb[3 * p + 1] + m.rgb[3 * p + 2]) / 3.0;
        if v > best {
            (best, at) = (v, p);
        }
        let theta = ((p / m.width) as f64 + 0.5) / m.height as f64 * std::f64::consts::PI;
        energy += v as f64 * theta.sin() * (2.0 * std::f64::consts::PI / m.width as f64) * (std::f64::consts::PI / m.height as f64);
    }
    (pii_bake::sg::env::latlong_dir(conv, at % m.width, at / m.width, m.width, m.height), energy)
}

#[test]
fn a_known_light_is_fitted_into_the_run_frame_and_kept_fixed() {
    // `--known-env`: the capture's own light map, fitted with the stage's lobes in the run's
    // normalised frame; its shape is never trained, only one exposure. The learnt environment
    // (written back in the map's layout by relight) peaks where the map does and keeps its energy
    // (within 25%: a few steps of exposure); 1 and 3 iterations end with the same shape; with
    // `light_fixed=false` the map only starts the light; a resume must make the same choice; a
    // map that is not an EXR is named.
    use pii_bake::sg::env::LatlongConvention;
    let dir = tempfile::tempdir().unwrap();
    let map = example().join("env/train.exr");
    let known = ["--known-env", map.to_str().unwrap(), "--known-env-convention", "blender"];
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    stage1(&a);
    copy_dir(&a, &b);
    let o = stage2(&a, &[&known[..], &["--material-iterations", "3"]].concat());
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("the light is known"), "{}", text(&o));
    let o = stage2(&b, &[&known[..], &["--material-iterations", "1"]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let model = |run: &Path| pii_bake::train::stage2::Stage2Trainer::load(run, None).unwrap().0.model;
    let (ma, mb) = (model(&a), model(&b));
    let (la, lb) = (ma.lobes(), mb.lobes());
    // Its shape is kept (axes, sharpness); only one exposure scales every amplitude.
    let ratio = la[0].mu[0] / lb[0].mu[0];
    for (x, y) in la.iter().zip(&lb) {
        assert_eq!((x.axis, x.lambda), (y.axis, y.lambda), "axis and sharpness are the map's");
        assert!(x.mu.iter().zip(&y.mu).all(|(p, q)| (p / q / ratio - 1.0).abs() < 1e-4), "one exposure for all lobes: {x:?} vs {y:?}");
    }
    let initial = pii_bake::train::stage2::light_lobes(&pii_bake::train::stage2::init_light(6, 2, false), false);
    assert!(la.iter().zip(&initial).any(|(x, y)| x.axis != y.axis), "the known light replaced the initial one");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("material_report.json")).unwrap()).unwrap();
    assert_eq!(report["config"]["light_fixed"], true, "{report}");
    assert_eq!(report["environment"]["known"], true, "{report}");
    // The reported exposures are the factors on the map's fit: their ratio is the amplitudes'.
    let exposure = |run: &Path| -> f64 {
        let r: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("material_report.json")).unwrap()).unwrap();
        r["environment"]["exposure"].as_f64().unwrap()
    };
    assert!((exposure(&a) / exposure(&b) / ratio as f64 - 1.0).abs() < 1e-4, "{} {} {ratio}", exposure(&a), exposure(&b));

    let rel = dir.path().join("rel");
    let o = pii(&["relight", a.to_str().unwrap(), "--env", map.to_str().unwrap(), "--lobes", "6", "--max-views", "1", "--out", rel.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let (want, e_map) = peak_and_energy(&map, LatlongConvention::Blender);
    let (got, e_fit) = peak_and_energy(&rel.join("env.exr"), LatlongConvention::Blender);
    let cos = want.iter().zip(&got).map(|(x, y)| x * y).sum::<f32>();
    assert!(cos > 20f32.to_radians().cos(), "learnt light peaks {:.1}° from the map's peak", cos.clamp(-1.0, 1.0).acos().to_degrees());
    assert!((e_fit / e_map - 1.0).abs() < 0.25, "energy kept {:.3}", e_fit / e_map);

    // `--material-set light_fixed=false`: the map is only where the light starts; then it is learnt.
    let c = dir.path().join("c");
    copy_dir(&b, &c);
    let o = stage2(&c, &[&known[..], &["--material-iterations", "1", "--material-set", "light_fixed=false"]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let lc = model(&c).lobes();
    assert!(lc.iter().zip(&lb).any(|(x, y)| (x.axis, x.lambda) != (y.axis, y.lambda)), "a learnt light moves its axes or sharpness");
    let rc: serde_json::Value = serde_json::from_slice(&std::fs::read(c.join("material_report.json")).unwrap()).unwrap();
    assert!(rc["config"]["light_fixed"] == false && rc["environment"]["exposure"].is_null(), "{rc}");
    let o = stage2(&a, &["--material-iterations", "5", "--resume"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("material.safetensors") && text(&o).contains("--known-env"), "{}", text(&o));
    let png = example().join("train/r_000.png");
    let o = stage2(&b, &["--known-env", png.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(text(&o).contains("r_000.png") && text(&o).contains("exr"), "{}", text(&o));
}

#[test]
fn under_auto_with_a_gpu_stage_two_times_both_backends_keeps_the_faster_and_a_resume_keeps_it() {
    // lavapipe stands in for the GPU (PII_ADAPTER names it, so `auto` takes it). The run keeps
    // whichever backend its own timings found faster (lavapipe's steps are usually several times
    // slower, but the test asserts the rule, not the machine's speeds).
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    stage1(&a);
    copy_dir(&a, &b);
    let ex = example();
    let go = |run: &Path, backend: &str, extra: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_pii-bake"))
            .env("XDG_RUNTIME_DIR", std::env::temp_dir())
            .env("PII_ADAPTER", "llvmpipe")
            .args(["--backend", backend, "train", ex.to_str().unwrap(), "--out", run.to_str().unwrap()])
            .args(TINY2)
            .args(extra)
            .output()
            .unwrap()
    };
    let report = |run: &Path| -> serde_json::Value { serde_json::from_slice(&std::fs::read(run.join("material_report.json")).unwrap()).unwrap() };
    let o = go(&a, "auto", &["--material-iterations", "18", "--stop-at", "17"]);
    assert!(o.status.success(), "{}", text(&o));
    let sb = report(&a)["step_backend"].clone();
    let (gpu, cpu) = (sb["seconds_per_step"]["wgpu"].as_f64().unwrap(), sb["seconds_per_step"]["cpu"].as_f64().unwrap());
    assert!(cpu > 0.0 && gpu > 0.0, "both backends timed: {sb}");
    let faster = if cpu < gpu { "cpu" } else { "wgpu" };
    assert_eq!(sb["chosen"], faster, "{sb}");
    assert!(text(&o).contains(&format!("steps run on the {faster} backend")), "{}", text(&o));
    let saved: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("material.json")).unwrap()).unwrap();
    assert_eq!(saved["config"]["step_backend"], faster, "the choice is saved with the run");
    // A resumed run keeps the choice without timing again.
    let o = go(&a, "auto", &["--material-iterations", "18", "--resume"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(!text(&o).contains("timed steps each"), "{}", text(&o));
    let sb = &report(&a)["step_backend"];
    assert!(sb["chosen"] == faster && sb["why"].as_str().unwrap().contains("chosen earlier"), "{sb}");
    // Asked for by --backend: every step runs there and nothing is timed.
    let o = go(&b, "wgpu", &["--material-iterations", "3"]);
    assert!(o.status.success(), "{}", text(&o));
    let sb = &report(&b)["step_backend"];
    assert!(sb["chosen"] == "wgpu" && sb["why"].as_str().unwrap().contains("--backend") && sb["seconds_per_step"].as_object().unwrap().is_empty(), "{sb}");
}

#[test]
fn a_strongly_tinted_learnt_light_is_flagged_and_real_maps_are_not() {
    use pii_bake::train::material::{tinted_light_flag, TINTED_LIGHT_ABOVE};
    use pii_bake::train::stage2::{Stage2Config, Stage2Model};
    // A model's per-channel energy sums its lobes' μ_c·∫G.
    let mut cfg = Stage2Config::new(pii_bake::train::stage1::Preset::Fast, 1000);
    cfg.lobes = 4;
    let mut m = Stage2Model::new(&cfg).unwrap();
    let mut lobes = m.lobes();
    for l in &mut lobes {
        l.mu = [1.38, 1.0, 0.32];
        l.lambda = 10.0;
    }
    m.set_light(&lobes).unwrap();
    let e = m.channel_energies();
    let s = 4.0 * pii_bake::sg::shade::sg_integral(10.0f64);
    for (c, want) in [1.38, 1.0, 0.32].iter().enumerate() {
        assert!((e[c] / (want * s) - 1.0).abs() < 1e-4, "channel {c}: {e:?}");
    }
    // The Ethiopian head's learnt light (bronze) is flagged, with its ratios.
    let flag = tinted_light_flag(e, false).expect("a 4.3x tint is flagged");
    assert!(flag.contains("1.38 : 1 : 0.32") && flag.contains("--metallic off"), "dielectric: {flag}");
    let flag = tinted_light_flag(e, true).expect("flagged with metals modelled too");
    assert!(flag.contains("1.38 : 1 : 0.32") && flag.contains("did not take") && !flag.contains("--metallic off"), "metallic: {flag}");
    // Every HDR map shipped in shared/data, energy per channel over the sphere, is not.
    let dir = shared_data().join("envmaps");
    let mut maps = 0;
    for sub in ["blender_studiolights", "invrender"] {
        for f in std::fs::read_dir(dir.join(sub)).unwrap() {
            let path = f.unwrap().path();
            if path.extension().and_then(|x| x.to_str()) != Some("exr") {
                continue;
            }
            let map = pii_bake::sg::env::read_latlong_exr(&path).unwrap();
            // The solid-angle mean radiance per channel (the fit's energy target): energy / 4π.
            let e = pii_bake::sg::fit::FitTarget::from_map(&map.rgb, map.width, map.height, pii_bake::sg::env::LatlongConvention::OpenExrUsd, 8).mean;
            let ratio = e.iter().cloned().fold(0.0, f64::max) / e.iter().cloned().fold(f64::INFINITY, f64::min);
            assert!(ratio < TINTED_LIGHT_ABOVE && tinted_light_flag(e, false).is_none(), "{}: channels {ratio:.2}x apart", path.display());
            maps += 1;
        }
    }
    assert_eq!(maps, 11, "the eleven shipped maps");
    // A dark or broken light is not a tint.
    assert!(tinted_light_flag([0.0; 3], false).is_none() && tinted_light_flag([1.0, f64::NAN, 0.1], true).is_none());
}

#[test]
fn a_saturated_roughness_is_flagged_and_under_a_recorded_light_the_flag_says_what_to_try() {
    use pii_bake::train::material::roughness_flag;
    for r in [0.06, 0.5, 0.94] {
        assert!(roughness_flag(r, true, true).is_none(), "{r}");
    }
    for (r, fixed) in [(0.02, false), (0.02, true), (1.0, false)] {
        let f = roughness_flag(r, fixed, true).expect("saturated");
        assert!(f.starts_with("roughness saturated") && !f.contains("known-env"), "{f}");
    }
    let f = roughness_flag(0.999, true, true).expect("saturated");
    assert!(f.contains("(mean 1.00)") && f.contains("without `--known-env`") && f.contains("--metallic off"), "{f}");
    let f = roughness_flag(0.999, true, false).expect("saturated");
    assert!(f.contains("without `--known-env`") && !f.contains("--metallic off"), "{f}");
}
