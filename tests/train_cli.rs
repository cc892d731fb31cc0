//! `pii-bake train` / `export --run` / trained `bake` through the binary, at tiny sizes: a run
//! interrupted and resumed follows the straight run's loss curve, Ctrl-C checkpoints, the run
//! exports to a valid asset, and bad inputs (no masks, cameras that miss the object, corrupt or
//! mismatched checkpoints, unwritable folders) give one clear error naming the file.

use std::path::Path;

mod common;

use common::{example, pii, text, turn_camera};

const TINY: [&str; 8] = ["--rays", "96", "--downscale", "4", "--init", "sphere", "--seed", "5"];

fn train(run: &Path, extra: &[&str]) -> std::process::Output {
    let ex = example();
    let mut a = vec!["train", ex.to_str().unwrap(), "--out", run.to_str().unwrap()];
    a.extend_from_slice(&TINY);
    a.extend_from_slice(extra);
    pii(&a)
}

/// The loss curve without the timing column; every line has the header's fields.
fn curve(run: &Path) -> Vec<String> {
    let csv = std::fs::read_to_string(run.join("loss_curve.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let secs = header.iter().position(|h| *h == "seconds").expect("a seconds column");
    csv.lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            assert_eq!(f.len(), header.len(), "{l}");
            f.iter().enumerate().filter(|(i, _)| *i != secs).map(|(_, v)| *v).collect::<Vec<_>>().join(",")
        })
        .collect()
}

#[test]
fn resumed_run_follows_the_straight_run_and_exports() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let o = train(&a, &["--iterations", "6", "--checkpoint-every", "3"]);
    assert!(o.status.success(), "{}", text(&o));
    let out = text(&o);
    assert!(out.contains("stage 1") && out.contains("PSNR") && out.contains("mask IoU"), "{out}");
    let o = train(&b, &["--iterations", "6", "--checkpoint-every", "3", "--stop-at", "3"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = train(&b, &["--iterations", "6", "--checkpoint-every", "3", "--resume"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("resuming"), "{}", text(&o));
    let (ca, cb) = (curve(&a), curve(&b));
    assert_eq!(ca.len(), 6);
    // The normal-smoothness part (on in the fast preset) is in the curve, beside the others.
    let csv = std::fs::read_to_string(a.join("loss_curve.csv")).unwrap();
    let col = csv.lines().next().unwrap().split(',').position(|h| h == "smoothness").expect("a smoothness column");
    let smooth: Vec<f64> = csv.lines().skip(1).map(|l| l.split(',').nth(col).unwrap().parse().unwrap()).collect();
    assert!(smooth.iter().all(|v| v.is_finite() && *v >= 0.0) && smooth.iter().any(|v| *v > 0.0), "{smooth:?}");
    assert_eq!(ca, cb, "interrupted + resumed run must follow the straight run's loss curve");
    // The resumed run's report speaks for the whole run: both invocations' steps and time.
    let read = |p: &Path| -> serde_json::Value { serde_json::from_slice(&std::fs::read(p.join("train_report.json")).unwrap()).unwrap() };
    let rb = read(&b);
    assert_eq!((rb["steps"].as_u64(), rb["timed_steps"].as_u64(), rb["resumed_at"].as_u64()), (Some(6), Some(6), Some(3)), "{rb}");
    let rate = rb["it_per_s"].as_f64().unwrap();
    assert!((rate - 6.0 / rb["seconds"]["train"].as_f64().unwrap()).abs() < 1e-9 * rate && rate > 0.0, "{rb}");
    // Trained again when finished: no step to time, the run's figures kept (not a rate of 0).
    let o = train(&b, &["--iterations", "6", "--checkpoint-every", "3", "--resume"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(!text(&o).contains("at 0.00 it/s"), "{}", text(&o));
    let again = read(&b);
    assert_eq!((again["timed_steps"].as_u64(), again["it_per_s"].as_f64()), (Some(6), Some(rate)), "{again}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("train_report.json")).unwrap()).unwrap();
    assert_eq!(report["steps"], 6);
    assert!(report["sizes"]["grid_finest"].as_u64().unwrap() >= 64, "sizes are reported: {}", report["sizes"]);
    assert!(report["eval"]["mask_iou"].as_f64().unwrap() > 0.0);

    // Export the run.
    let asset = dir.path().join("asset");
    let o = pii(&["export", "--run", a.to_str().unwrap(), "--out", asset.to_str().unwrap(), "--resolution", "40", "--texture", "64", "--name", "spot"]);
    assert!(o.status.success(), "{}", text(&o));
    for f in ["spot.glb", "asset.usda", "env.exr", "textures/albedo.png"] {
        assert!(asset.join(f).is_file(), "{f} missing");
    }
    common::assert_gltf_valid(&[asset.join("spot.glb")]);

    // A corrupt checkpoint: a clear error naming it.
    std::fs::write(a.join("checkpoint.safetensors"), b"\x10\x00\x00\x00\x00\x00\x00\x00{not json").unwrap();
    let o = pii(&["export", "--run", a.to_str().unwrap(), "--out", dir.path().join("x").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("checkpoint.safetensors") && !text(&o).contains("panicked"), "{}", text(&o));

    // A run of another preset: refused by --resume.
    let o = train(&b, &["--iterations", "8", "--resume", "--preset", "paper"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("checkpoint.safetensors") && text(&o).contains("preset"), "{}", text(&o));
}

#[test]
fn ctrl_c_writes_a_checkpoint_and_resume_continues() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let ex = example();
    let args = [&["train", ex.to_str().unwrap(), "--out", run.to_str().unwrap(), "--iterations", "100000", "--checkpoint-every", "100000"][..], &TINY[..]].concat();
    let o = common::interrupt_after_progress(&args, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("interrupted") && err.contains("--resume"), "{err}");
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("run.json")).unwrap()).unwrap();
    let step = meta["step"].as_u64().unwrap();
    assert!(step >= 1);
    let n = (step + 2).to_string();
    let o = train(&run, &["--iterations", &n, "--resume"]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(curve(&run).len() as u64, step + 2);
}

/// A copy of the example (train split only) for damaging.
fn copy_example(dst: &Path) {
    let ex = example();
    std::fs::create_dir_all(dst.join("train")).unwrap();
    for f in ["transforms_train.json", "scene.json"] {
        std::fs::copy(ex.join(f), dst.join(f)).unwrap();
    }
    for e in std::fs::read_dir(ex.join("train")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), dst.join("train").join(e.file_name())).unwrap();
    }
}

#[test]
fn bad_scenes_and_folders_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    // Photos without masks: RGB PNGs with no alpha.
    let nomask = dir.path().join("nomask");
    copy_example(&nomask);
    for e in std::fs::read_dir(nomask.join("train")).unwrap() {
        let p = e.unwrap().path();
        let img = pii_bake::image_io::read_image_linear(&p).unwrap();
        pii_bake::image_io::write_png8(&p, img.width, img.height, 3, &img.rgb(), true).unwrap();
    }
    let o = pii(&["train", nomask.to_str().unwrap(), "--out", dir.path().join("r1").to_str().unwrap(), "--iterations", "1"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let t = text(&o);
    assert!(t.contains(".png") && t.contains("mask"), "{t}");
    // `info` still describes such a scene and says why it gives no coverage estimate.
    let o = pii(&["info", nomask.to_str().unwrap(), "--downscale", "4"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("coverage (est.)   - (needs a mask on every training view"), "{}", text(&o));

    // A camera that looks away from the object.
    let away = dir.path().join("away");
    copy_example(&away);
    let p = away.join("transforms_train.json");
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    let m = &mut j["frames"][0]["transform_matrix"];
    for r in 0..3 {
        for c in [0, 2] {
            let v = m[r][c].as_f64().unwrap();
            m[r][c] = serde_json::json!(-v);
        }
    }
    let name = j["frames"][0]["file_path"].as_str().unwrap().trim_start_matches("./").to_string();
    std::fs::write(&p, serde_json::to_vec(&j).unwrap()).unwrap();
    let o = pii(&["train", away.to_str().unwrap(), "--out", dir.path().join("r2").to_str().unwrap(), "--iterations", "1", "--downscale", "4"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let t = text(&o);
    assert!(t.contains(name.rsplit('/').next().unwrap()) && !t.contains("panicked"), "names the view {name}: {t}");

    // An unwritable run folder (below a regular file).
    let file = dir.path().join("plain-file");
    std::fs::write(&file, b"x").unwrap();
    let bad = file.join("run");
    let ex = example();
    let o = pii(&["train", ex.to_str().unwrap(), "--out", bad.to_str().unwrap(), "--iterations", "1"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains(bad.to_str().unwrap()), "{}", text(&o));

    // export --run on a folder that is not a run.
    let o = pii(&["export", "--run", dir.path().to_str().unwrap(), "--out", dir.path().join("a").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("scene.json") || text(&o).contains("checkpoint"), "{}", text(&o));

    // A run from another scene is refused by --resume.
    let other = dir.path().join("other");
    copy_example(&other);
    let p = other.join("transforms_train.json");
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    j["frames"].as_array_mut().unwrap().truncate(12);
    std::fs::write(&p, serde_json::to_vec(&j).unwrap()).unwrap();
    let run = dir.path().join("r3");
    let o = train(&run, &["--iterations", "1"]);
    assert!(o.status.success(), "{}", text(&o));
    let mut a = vec!["train", other.to_str().unwrap(), "--out", run.to_str().unwrap(), "--resume", "--iterations", "2"];
    a.extend_from_slice(&TINY);
    let o = pii(&a);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("another scene"), "{}", text(&o));
}

#[test]
fn bake_trains_both_stages_and_ships_them() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("asset");
    let ex = example();
    let o = pii(&[
        "bake", ex.to_str().unwrap(), "--out", out.to_str().unwrap(), "--iterations", "4", "--rays", "96", "--downscale", "4",
        "--init", "hull", "--init-steps", "10", "--resolution", "40", "--texture", "64", "--name", "spot",
        "--lobes", "4", "--material-iterations", "2", "--material-batch", "64", "--material-set", "points=500",
        "--blender-views", "1", "--blender-samples", "4",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("bake_report.json")).unwrap()).unwrap();
    assert_eq!(report["method"], "stage1+stage2-fast");
    assert_eq!(report["material"]["steps"], 2);
    assert_eq!(report["stages"].as_array().unwrap().len(), 3);
    assert_eq!(report["training"]["steps"], 4);
    assert!(report["training"]["hull_init"]["fit_steps"] == 10);
    // The hull's concavities were looked for by photo-consistency (the spot has none to speak of).
    let cc = &report["training"]["hull_init"]["concavities"];
    assert!(cc["rays"].as_u64().unwrap() > 0 && cc["rounds"].as_u64().unwrap() >= 1, "{cc}");
    assert!(report["ground_truth"]["metrics"]["chamfer"].as_f64().is_some(), "{}", report["ground_truth"]);
    // The example's 24 photos see most of its surface three times or more: no coverage flag.
    let cov = &report["training"]["coverage"];
    assert!(cov["below_three"].as_f64().unwrap() < 0.25 && cov["surface_points"].as_u64().unwrap() > 1000, "{cov}");
    assert!(report["flags"].as_array().unwrap().iter().all(|f| !f.as_str().unwrap().contains("fewer than three")), "{}", report["flags"]);
    // The Blender check rendered the .glb from a held-out camera and scored it against the photo.
    let bc = &report["blender_check"];
    assert_eq!(bc["status"], "ok", "{bc}");
    assert_eq!(bc["held_out"], true);
    let psnr = bc["mean_psnr"].as_f64().unwrap();
    assert!(psnr.is_finite() && psnr > 5.0, "{bc}");
    assert!(out.join("blender_check/glb_cam0.png").is_file() && out.join("blender_check/photos/ref_cam0.png").is_file());
    // The example has ground truth under two relight maps: the .glb was rendered under each from
    // the same held-out camera and scored against it, as rendered and after one scale per channel.
    let relit = bc["relit"].as_object().unwrap();
    assert_eq!(relit.keys().collect::<Vec<_>>(), ["envmap6", "sunset"], "{bc}");
    for (name, r) in relit {
        assert_eq!(r["status"], "ok", "{name}: {r}");
        for k in ["mean_psnr", "mean_psnr_aligned"] {
            assert!(r[k].as_f64().is_some_and(|v| v.is_finite() && v > 5.0), "{name} {k}: {r}");
        }
        assert_eq!(r["channel_scale"].as_array().map(Vec::len), Some(3), "{r}");
        // The reference is the ground truth brought to the view's size (the bake read at 1/4).
        let reference = pii_bake::image_io::read_image_linear(&out.join(format!("blender_check/relit/{name}/ref_cam0.png"))).unwrap();
        assert_eq!((reference.width, reference.height, reference.channels), (50, 50, 4));
        assert!(out.join(format!("blender_check/relit_{name}_cam0.png")).is_file());
    }
    assert!(out.join("spot.glb").is_file() && out.join("run/checkpoint.safetensors").is_file());
    common::assert_gltf_valid(&[out.join("spot.glb")]);
}

#[test]
fn geometry_set_reaches_the_run_config_and_bad_settings_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("r");
    let o = train(&run, &["--iterations", "2", "--geometry-set", "normal_gradient_scale=0.3", "--geometry-set", "smoothness_weight=0.05"]);
    assert!(o.status.success(), "{}", text(&o));
    let cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("run.json")).unwrap()).unwrap();
    assert_eq!(cfg["config"]["normal_gradient_scale"].as_f64(), Some(0.3f32 as f64), "{}", cfg["config"]);
    assert_eq!(cfg["config"]["smoothness_weight"].as_f64(), Some(0.05f32 as f64));
    for (set, says) in [("no_such_setting=1", "no setting named"), ("normal_gradient_scale=2", "[0, 1]"), ("hull_fit_points=0", "hull fit")] {
        let o = train(&dir.path().join("bad"), &["--iterations", "2", "--geometry-set", set]);
        assert!(!o.status.success(), "{set} was accepted");
        assert!(text(&o).contains(says), "{set}: {}", text(&o));
    }
}

#[test]
fn init_mesh_fits_a_given_mesh_and_refuses_one_from_another_frame() {
    let dir = tempfile::tempdir().unwrap();
    let gt = example().join("gt").join("mesh.obj");
    let run = dir.path().join("r");
    let o = train(&run, &["--iterations", "2", "--init-mesh", gt.to_str().unwrap(), "--init-steps", "40", "--geometry-set", "lr_field=0"]);
    assert!(o.status.success(), "{}", text(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("train_report.json")).unwrap()).unwrap();
    let mi = &report["mesh_init"];
    assert_eq!(mi["triangles"].as_u64(), Some(5856), "{mi}");
    assert!(mi["voxels_inside"].as_u64().unwrap() > 1000, "{mi}");
    assert!(mi["fit_loss"].as_f64().unwrap() < 0.05, "{mi}");
    assert!(report["hull_init"].is_null());
    // lr_field 0 is "keep the geometry": accepted; a negative rate is not.
    let o = train(&dir.path().join("neg"), &["--iterations", "2", "--geometry-set", "lr_field=-1"]);
    assert!(!o.status.success() && text(&o).contains("learning rates"), "{}", text(&o));
    // The same mesh in centimetres is not in the scene's frame: refused, naming the file.
    let obj = std::fs::read_to_string(&gt).unwrap();
    let scaled: String = obj
        .lines()
        .map(|l| match l.strip_prefix("v ") {
            Some(v) => format!("v {}\n", v.split_whitespace().map(|x| (x.parse::<f64>().unwrap() * 100.0).to_string()).collect::<Vec<_>>().join(" ")),
            None => format!("{l}\n"),
        })
        .collect();
    let cm = dir.path().join("centimetres.obj");
    std::fs::write(&cm, scaled).unwrap();
    let o = train(&dir.path().join("cm"), &["--iterations", "2", "--init-mesh", cm.to_str().unwrap()]);
    assert!(!o.status.success(), "a mesh 100x too large was accepted");
    assert!(text(&o).contains("centimetres.obj") && text(&o).contains("not in the scene's frame"), "{}", text(&o));
    let o = train(&dir.path().join("missing"), &["--iterations", "2", "--init-mesh", dir.path().join("nope.obj").to_str().unwrap()]);
    assert!(!o.status.success() && text(&o).contains("nope.obj"), "{}", text(&o));
}

#[test]
fn a_view_with_a_wrong_pose_is_excluded_named_and_reported() {
    // The example with training camera r_005 turned 5° about its up axis (the image and mask
    // unchanged), as a failed registration leaves it: its silhouette cuts a slab off the others'
    // hull. The scene drops it with a warning naming it, and the run's report records it.
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    copy_example(&scene);
    turn_camera(&scene.join("transforms_train.json"), "r_005", 5.0);

    let o = pii(&["--json", "info", scene.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let out = text(&o);
    assert!(out.contains("excluded view r_005") && out.contains("r_005.png") && out.contains("wrong pose"), "{out}");
    assert!(!out.contains('\x1b'), "no colour escape codes when the output is not a terminal: {out:?}");
    let run = dir.path().join("run");
    let tiny = ["--rays", "96", "--init-steps", "20", "--iterations", "3"];
    let o = pii(&[&["train", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--downscale", "4", "--stop-at", "2"][..], &tiny].concat());
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("excluded view r_005"), "{}", text(&o));
    // Resumed with other reading flags, the run reads the scene as it started (the same 23 views
    // at the same size), instead of taking 24 views for another scene.
    let o = pii(&[&["train", scene.to_str().unwrap(), "--out", run.to_str().unwrap(), "--resume", "--keep-all-views", "--downscale", "2"][..], &tiny].concat());
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("resuming as the run started: --downscale 4") && text(&o).contains("at step 2 of 3"), "{}", text(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("train_report.json")).unwrap()).unwrap();
    assert_eq!(report["scene"]["train_views"], 23, "{}", report["scene"]);
    let excluded = report["scene"]["silhouettes"]["excluded"].as_array().unwrap();
    assert_eq!(excluded.len(), 1, "{}", report["scene"]);
    assert_eq!(excluded[0]["name"], "r_005");
    assert!(excluded[0]["solo_carve"].as_f64().unwrap() > 0.05);
}

#[test]
fn a_seeded_run_gives_the_same_parameters_on_one_and_three_threads() {
    // Every reduction over the batch is summed in a fixed order (util::fold_ordered), so the
    // thread count cannot change the rounding: the parameters and Adam's moments come out
    // bit-identical. (With rayon's fold in the MLP backward they differed.)
    let dir = tempfile::tempdir().unwrap();
    let ex = example();
    let tensors = |threads: &str| {
        let run = dir.path().join(format!("t{threads}"));
        let o = assert_cmd::Command::cargo_bin("pii-bake")
            .unwrap()
            .env("RAYON_NUM_THREADS", threads)
            .args(["--backend", "cpu", "train", ex.to_str().unwrap(), "--out", run.to_str().unwrap(), "--stage", "geometry"])
            .args(["--rays", "128", "--downscale", "4", "--init-steps", "10", "--iterations", "4"])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", text(&o));
        let bytes = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
        let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        let mut out: Vec<(String, Vec<u8>)> = st.tensors().into_iter().map(|(k, v)| (k, v.data().to_vec())).collect();
        out.sort();
        (out, curve(&run))
    };
    let (a, ca) = tensors("1");
    let (b, cb) = tensors("3");
    assert_eq!(ca, cb, "loss curves");
    assert!(a.len() >= 2 && a.iter().map(|t| &t.0).eq(b.iter().map(|t| &t.0)));
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        assert!(x == y, "{name} differs between 1 and 3 threads");
    }
}

#[test]
fn profile_kernels_reports_each_kernels_gpu_time_per_step() {
    // On wgpu (lavapipe here, which has timestamp queries) every launch is timed: the report's
    // kernels account for every launch the step counted (results under the profile: gpu_launcher).
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let ex = example();
    let mut a = vec!["--backend", "wgpu", "--profile-kernels", "train", ex.to_str().unwrap(), "--out", run.to_str().unwrap()];
    a.extend_from_slice(&TINY);
    a.extend_from_slice(&["--stage", "geometry", "--iterations", "2"]);
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_pii-bake")).env("XDG_RUNTIME_DIR", std::env::temp_dir()).args(&a).output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("GPU kernel time") && text(&o).contains("mlp::gemm"), "{}", text(&o));
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("train_report.json")).unwrap()).unwrap();
    let kernels = r["gpu_kernels_per_step"].as_array().unwrap();
    let launches: f64 = kernels.iter().map(|k| k["launches"].as_f64().unwrap()).sum();
    assert_eq!(launches, r["gpu_per_step"]["dispatches"].as_f64().unwrap(), "{kernels:?}");
    let secs: Vec<f64> = kernels.iter().map(|k| k["seconds"].as_f64().unwrap()).collect();
    assert!(secs.iter().all(|s| s.is_finite() && *s >= 0.0) && secs.iter().sum::<f64>() > 0.0, "{secs:?}");
    assert!(secs.windows(2).all(|w| w[0] >= w[1]), "costliest first: {secs:?}");
    // The cpu backend has no kernels: a warning, and no profile in the report.
    let run = dir.path().join("cpu");
    let mut a = vec!["--profile-kernels", "train", ex.to_str().unwrap(), "--out", run.to_str().unwrap()];
    a.extend_from_slice(&TINY);
    a.extend_from_slice(&["--stage", "geometry", "--iterations", "1"]);
    let o = pii(&a);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("the cpu backend has none to time"), "{}", text(&o));
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("train_report.json")).unwrap()).unwrap();
    assert!(r["gpu_kernels_per_step"].is_null());
}

#[test]
fn bench_train_writes_its_figures_and_reports_a_failed_variant_instead_of_losing_the_others() {
    // A tiny bench: each file is written, the curve has the hull baseline and the variant's
    // points, and its summary row has the figures.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bench");
    let tiny = ["bench", "train", "--variant", "fast-refined-sphere", "--max-iterations", "2", "--eval-every", "1", "--mesh-resolution", "24", "--downscale", "4", "--rays", "64", "--reference-steps", "40", "--asset-resolution", "32", "--out"];
    let o = pii(&[&tiny[..], &[out.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("bench-train.json")).unwrap()).unwrap();
    let row = &j["summary"][0];
    assert!(row.get("error").is_none() && row["iterations"] == 2, "{row}");
    // The ground truth through the same field and asset pipeline: even 40 fit steps from a sphere
    // give a closer shape than 2 training steps do.
    let r = &j["ground_truth_reference"][0];
    assert_eq!(r["scene"], "example", "{r}");
    assert_eq!(r["fit_steps"], 40, "{r}");
    let (rc, vc) = (r["chamfer_rel"].as_f64().unwrap(), row["chamfer_rel"].as_f64().unwrap());
    assert!(rc.is_finite() && rc < vc, "reference {rc} vs variant {vc}: {r}");
    assert!(r["asset"]["triangles"].as_u64().unwrap() > 0 && r["asset"]["normal_consistency"].as_f64().unwrap() > 0.5, "{r}");
    let csv = std::fs::read_to_string(out.join("bench-train.csv")).unwrap();
    assert!(csv.contains("hull (preview)") && csv.lines().filter(|l| l.contains("fast-refined-sphere")).count() == 3, "{csv}");
    assert!(std::fs::read_to_string(out.join("bench-train.svg")).unwrap().contains("<svg"));
    // Time to accuracy: the variant is timed to 50%, 25% and 10% above the best it reached, so it
    // reaches each (the tightest no sooner than the loosest).
    let rows = j["time_to_accuracy"].as_array().unwrap();
    assert_eq!(rows.len(), 3, "{rows:?}");
    let secs: Vec<f64> = rows.iter().map(|r| r["seconds"].as_f64().unwrap()).collect();
    assert!(secs[0] <= secs[1] && secs[1] <= secs[2], "{rows:?}");
    let t = &rows[2];
    assert_eq!(t["margin"], 1.1, "{t}");
    assert_eq!(t["variant"], "fast-refined-sphere", "{t}");
    let best = j["points"].as_array().unwrap().iter().filter(|p| p["variant"] == "fast-refined-sphere").map(|p| p["chamfer_rel"].as_f64().unwrap()).fold(f64::INFINITY, f64::min);
    assert!((t["target_chamfer_rel"].as_f64().unwrap() - 1.1 * best).abs() < 1e-12 && t["seconds"].as_f64().is_some(), "{t}");
    let csv = std::fs::read_to_string(out.join("bench-train-time-to-accuracy.csv")).unwrap();
    assert!(csv.starts_with("scene,variant,target_chamfer_rel,margin,seconds_to_target") && csv.lines().nth(1).unwrap().starts_with("example,fast-refined-sphere,"), "{csv}");
    assert!(text(&o).contains("example: time to Chamfer <= "), "{}", text(&o));
    // A variant that fails is a row naming its error, and the files are still written; where
    // every variant failed the bench says so and exits non-zero.
    let out2 = dir.path().join("bench2");
    let mut bad = tiny.to_vec();
    let i = bad.iter().position(|a| *a == "64").unwrap();
    bad[i] = "0";
    let o = pii(&[&bad[..], &[out2.to_str().unwrap()]].concat());
    assert!(!o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("every variant failed") && text(&o).contains("fast-refined-sphere: failed"), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&std::fs::read(out2.join("bench-train.json")).unwrap()).unwrap();
    let err = j["summary"][0]["error"].as_str().unwrap();
    assert!(err.contains("rays"), "{err}");
}

#[test]
fn refined_poses_are_written_reported_and_trained_through_by_stage_two() {
    let dir = tempfile::tempdir().unwrap();
    let ex = example();
    let run_with = |run: &Path, pose_lr: &str| {
        pii(&[
            "train", ex.to_str().unwrap(), "--out", run.to_str().unwrap(), "--stage", "all", "--rays", "96", "--downscale", "4", "--init-steps", "20", "--iterations", "3",
            "--geometry-set", &format!("pose_lr={pose_lr}"), "--lobes", "4", "--material-iterations", "2", "--material-batch", "64", "--material-set", "points=500",
        ])
    };
    let run = dir.path().join("run");
    let o = run_with(&run, "0.5");
    assert!(o.status.success(), "{}", text(&o));
    let out = text(&o);
    assert!(out.contains("camera poses refined (24 views)") && out.contains("stage 2: training through the 24 camera poses stage 1 refined"), "{out}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("train_report.json")).unwrap()).unwrap();
    let p = &report["pose_refinement"];
    // 3 steps, the first the radiance warm-up's: two updates of up to half a pixel each.
    assert_eq!((p["views"].as_u64(), p["updates"].as_u64()), (Some(24), Some(2)), "{p}");
    let shift = p["max_translation_px"].as_f64().unwrap();
    assert!(shift > 0.1 && shift < 1.5, "{p}");
    let poses: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("poses.json")).unwrap()).unwrap();
    let views = poses["views"].as_array().unwrap();
    assert_eq!(views.len(), 24);
    assert!(views.iter().all(|v| v["world_from_camera"].as_array().unwrap().len() == 16 && v["name"].is_string()), "{}", views[0]);
    // The hull is carved again through the refined poses or kept, decided once, at the first step
    // with refined poses from 40% of the run on (step 2: step 1 is the warm-up's), and said.
    let h = &report["hull_recarve"];
    assert_eq!(h["step"].as_u64(), Some(2), "{h}");
    let moved = h["largest_correction_px"].as_f64().unwrap();
    assert_eq!(h["recarved"].as_bool(), Some(moved > h["half_voxel_px"].as_f64().unwrap()), "{h}");
    assert!(out.contains("stage 1: the refined poses moved"), "{out}");
    // Off: no poses file, nothing reported, and stage 2 reads the poses as they are.
    let off = dir.path().join("off");
    let o = run_with(&off, "0");
    assert!(o.status.success(), "{}", text(&o));
    assert!(!off.join("poses.json").exists() && !text(&o).contains("camera poses refined"), "{}", text(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(off.join("train_report.json")).unwrap()).unwrap();
    assert!(report["pose_refinement"].is_null() && report["hull_recarve"].is_null(), "{report}");
    // On by default at the preset's rate; `--fixed-poses` keeps the poses as read.
    for (name, flag, lr) in [("on", None, pii_bake::train::stage1::POSE_LR as f64), ("fixed", Some("--fixed-poses"), 0.0)] {
        let r = dir.path().join(name);
        let mut a = vec!["train", ex.to_str().unwrap(), "--out", r.to_str().unwrap(), "--stage", "geometry", "--rays", "96", "--downscale", "4", "--init-steps", "20", "--iterations", "2"];
        a.extend(flag);
        let o = pii(&a);
        assert!(o.status.success(), "{}", text(&o));
        let cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(r.join("run.json")).unwrap()).unwrap();
        assert_eq!(cfg["config"]["pose_lr"].as_f64(), Some(lr), "{name}");
        assert_eq!(r.join("poses.json").is_file(), lr > 0.0, "{name}");
    }
    // A poses file that names a view the scene lacks stops stage 2 with the file's name.
    let text_p = std::fs::read_to_string(run.join("poses.json")).unwrap().replace(views[0]["name"].as_str().unwrap(), "not-a-view");
    std::fs::write(run.join("poses.json"), text_p).unwrap();
    let o = pii(&["train", ex.to_str().unwrap(), "--out", run.to_str().unwrap(), "--stage", "material", "--lobes", "4", "--material-iterations", "1", "--material-batch", "64", "--material-set", "points=500"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("poses.json") && text(&o).contains("not-a-view") && !text(&o).contains("panicked"), "{}", text(&o));
}

#[test]
fn bench_train_misregisters_the_photos_and_reports_the_pose_error_before_and_after() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bench");
    let args = ["bench", "train", "--variant", "fast-refined-sphere", "--max-iterations", "3", "--eval-every", "3", "--mesh-resolution", "24", "--downscale", "4", "--rays", "64", "--reference-steps", "0", "--asset-resolution", "24", "--set", "pose_lr=0.5", "--pose-noise", "1", "--out", out.to_str().unwrap()];
    let o = pii(&args);
    assert!(o.status.success(), "{}", text(&o));
    let j: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("bench-train.json")).unwrap()).unwrap();
    let e = &j["summary"][0]["pose_error_px"];
    let (before, after) = (e["before"].as_f64().unwrap(), e["after"].as_f64().unwrap());
    // A 1° turn of a 150 px wide view at 1/4 is about a pixel; two refinement steps move it by
    // at most a pixel at the object.
    assert!(before > 0.2 && before < 5.0 && after.is_finite() && after != before, "{e}");
    assert_eq!(j["summary"][0]["pose_noise_deg"], 1.0);
    assert!(text(&o).contains("pose error"), "{}", text(&o));
    let mut bad = args.to_vec();
    let i = bad.iter().position(|a| *a == "--pose-noise").unwrap();
    bad[i + 1] = "20";
    let o = pii(&bad);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains("pose noise in degrees"), "{}", text(&o));
}
