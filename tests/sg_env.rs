//! Environment SGs: EXR reading (compressions, the real maps, bad files), the fit loss gradient
//! (finite differences in src/sg/fit.rs; WGSL vs cpu here), round-trip fits in both latlong
//! conventions, and the `fit-env` / `bench env` commands.

use std::path::{Path, PathBuf};

use pii_bake::backend::Backend;
use pii_bake::sg::env::{read_latlong_exr, render_latlong, EnvSgs, LatlongConvention, SgLobe};
use pii_bake::sg::fit::{fit_error, fit_sgs, gpu::FitKernels, init_params, loss_grad_f64, FitConfig, FitTarget, DEFAULT_IRRADIANCE_TOLERANCE};
use pii_bake::testing::{assert_close, Tolerance};
use rand::Rng;

fn shared_data() -> PathBuf {
    let p = std::env::var("PII_SHARED_DATA").map(PathBuf::from).unwrap_or_else(|_| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data")));
    if p.exists() {
        p
    } else {
        PathBuf::from("/work/shared/data")
    }
}

fn unit(v: [f32; 3]) -> [f32; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

fn known_env() -> EnvSgs {
    EnvSgs {
        lobes: vec![
            SgLobe { axis: unit([0.3, 0.8, -0.5]), sharpness: 40.0, amplitude: [20.0, 15.0, 8.0] },
            SgLobe { axis: unit([-0.6, 0.1, 0.7]), sharpness: 4.0, amplitude: [0.3, 0.5, 0.9] },
            SgLobe { axis: unit([0.2, -0.9, 0.1]), sharpness: 2.0, amplitude: [0.2, 0.15, 0.1] },
            SgLobe { axis: unit([0.9, 0.2, 0.3]), sharpness: 12.0, amplitude: [1.0, 0.8, 0.6] },
        ],
    }
}

fn write_exr(path: &Path, w: usize, h: usize, rgb: &[f32], compression: exr::prelude::Compression) {
    use exr::prelude::*;
    let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
        let i = (p.y() * w + p.x()) * 3;
        (rgb[i], rgb[i + 1], rgb[i + 2])
    });
    let enc = Encoding { compression, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
    Image::from_layer(Layer::new((w, h), LayerAttributes::named("rgb"), enc, channels)).write().to_file(path).unwrap();
}

#[test]
fn exr_compressions_round_trip() {
    use exr::prelude::Compression::*;
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (32, 16);
    let mut rng = pii_bake::util::rng(7);
    let rgb: Vec<f32> = (0..w * h * 3).map(|_| rng.random_range(0.0f32..1.0).powi(4) * 1000.0).collect();
    for c in [Uncompressed, RLE, ZIP1, ZIP16, PIZ] {
        let p = dir.path().join(format!("{c:?}.exr"));
        write_exr(&p, w, h, &rgb, c);
        let m = read_latlong_exr(&p).unwrap_or_else(|e| panic!("{c:?}: {e}"));
        assert_eq!((m.width, m.height), (w, h));
        assert_eq!(m.rgb, rgb, "{c:?} must be lossless for f32");
    }
    // Lossy or rounding codecs: PXR24 keeps 24 bits of a float (relative error <= 2^-15); DWA
    // (what the Blender maps shipped as upstream) is lossy: on this worst case for a DCT codec
    // (white noise over 3 decades) the exr crate's DWA stays within 5% per value.
    for (c, tol) in [(PXR24, Tolerance::new(1e-4, 1e-6)), (DWAA(None), Tolerance::new(5e-2, 1e-2)), (DWAB(None), Tolerance::new(5e-2, 1e-2))] {
        let p = dir.path().join(format!("{c:?}.exr"));
        write_exr(&p, w, h, &rgb, c);
        let m = read_latlong_exr(&p).unwrap_or_else(|e| panic!("{c:?}: {e}"));
        assert_eq!((m.width, m.height), (w, h));
        assert_close(&format!("{c:?}"), &m.rgb, &rgb, tol);
    }
    // Tiny negatives (DWA ringing) are clamped to 0 and counted.
    let mut neg = rgb.clone();
    neg[5] = -0.003;
    let p = dir.path().join("neg.exr");
    write_exr(&p, w, h, &neg, ZIP16);
    let m = read_latlong_exr(&p).unwrap();
    assert_eq!((m.clamped_negatives, m.rgb[5]), (1, 0.0));
    assert!((m.min_value + 0.003).abs() < 1e-7);
}

#[test]
fn real_envmaps_all_read() {
    let root = shared_data().join("envmaps");
    let expected = [
        ("blender_studiolights/city.exr", 1024, 512),
        ("blender_studiolights/courtyard.exr", 1024, 512),
        ("blender_studiolights/forest.exr", 1024, 512),
        ("blender_studiolights/interior.exr", 1024, 512),
        ("blender_studiolights/night.exr", 1024, 512),
        ("blender_studiolights/studio.exr", 1024, 512),
        ("blender_studiolights/sunrise.exr", 1024, 512),
        ("blender_studiolights/sunset.exr", 1024, 512),
        ("invrender/envmap12.exr", 1024, 512),
        ("invrender/envmap3.exr", 500, 250),
        ("invrender/envmap6.exr", 1024, 512),
    ];
    for (name, w, h) in expected {
        let m = read_latlong_exr(&root.join(name)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((m.width, m.height), (w, h), "{name}");
        assert!(m.rgb.iter().all(|v| v.is_finite() && *v >= 0.0), "{name}");
        let max = m.rgb.iter().copied().fold(0.0f32, f32::max);
        assert!(max > 1.0, "{name}: max {max}");
    }
}

#[test]
fn bad_files_are_data_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.exr");
    let rgb = vec![0.5f32; 16 * 8 * 3];
    write_exr(&good, 16, 8, &rgb, exr::prelude::Compression::ZIP16);
    let bytes = std::fs::read(&good).unwrap();
    let truncated = dir.path().join("truncated.exr");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let not_exr = dir.path().join("not_exr.exr");
    std::fs::write(&not_exr, b"this is not an OpenEXR file").unwrap();
    let nan = dir.path().join("nan_pixels.exr");
    let mut bad = rgb.clone();
    bad[40] = f32::NAN;
    write_exr(&nan, 16, 8, &bad, exr::prelude::Compression::ZIP16);
    let inf = dir.path().join("inf_pixels.exr");
    bad[40] = f32::INFINITY;
    write_exr(&inf, 16, 8, &bad, exr::prelude::Compression::ZIP16);
    let aspect = dir.path().join("square.exr");
    write_exr(&aspect, 8, 8, &vec![0.5f32; 8 * 8 * 3], exr::prelude::Compression::ZIP16);
    let missing = dir.path().join("missing.exr");
    for (p, what) in [
        (&truncated, ""),
        (&not_exr, ""),
        (&nan, "non-finite"),
        (&inf, "non-finite"),
        (&aspect, "2:1"),
        (&missing, "not found"),
    ] {
        let e = read_latlong_exr(p).expect_err(&p.display().to_string()).to_string();
        let name = p.file_name().unwrap().to_str().unwrap();
        assert!(e.contains(name), "error must name the file: {e}");
        assert!(e.contains(what), "{e}");
    }
}

#[test]
fn wgsl_gradient_matches_cpu() {
    let gpu = Backend::wgpu_for_tests().unwrap_or_else(|e| panic!("the test command (bash scripts/test.sh) installs lavapipe; no adapter: {e}"));
    let ctx = gpu.gpu().unwrap().clone();
    let mut rng = pii_bake::util::rng(11);
    let (w, h) = (64, 32);
    let rgb: Vec<f32> = (0..w * h * 3).map(|_| rng.random_range(0.0f32..1.0).powi(3) * 50.0).collect();
    let target = FitTarget::from_map(&rgb, w, h, LatlongConvention::OpenExrUsd, 64);
    // (lobes, range of ln λ): the last case puts λ on both sides of the energy term's series
    // branch (0.05 in WGSL, 1e-3 in the cpu twin).
    for (lobes, ln_lambda) in [(1usize, 0.0f32..4.0), (5, 0.0..4.0), (13, 0.0..4.0), (4, -8.0..-1.5)] {
        let params: Vec<f32> = (0..lobes * 7)
            .map(|i| match i % 7 {
                0..=2 => rng.random_range(-1.0f32..1.0),
                3 => rng.random_range(ln_lambda.clone()),
                _ => rng.random_range(-2.0f32..2.0),
            })
            .collect();
        let p64: Vec<f64> = params.iter().map(|&v| v as f64).collect();
        let (loss, g) = loss_grad_f64(&p64, &target);
        let k = FitKernels::new(&ctx, &target, lobes).unwrap();
        let (gl, gg) = k.gradient_host(&params).unwrap();
        let gmax = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        // f32 sums over 2048 pixels vs f64: 2e-3 relative, plus 1e-4 of the largest component.
        let tol = Tolerance::new(2e-3, 1e-4 * gmax);
        assert_close(&format!("sg_fit gradient, {lobes} lobes"), &gg, &g, tol);
        assert_close("sg_fit loss", &[gl], &[loss], Tolerance::new(1e-4, 0.0));
    }
}

fn fit_known(conv: LatlongConvention, env: &EnvSgs, lobes: usize, iterations: usize) -> (EnvSgs, f64) {
    let (w, h) = (128, 64);
    let rgb = render_latlong(env, w, h, conv);
    let target = FitTarget::from_map(&rgb, w, h, conv, 64);
    let cfg = FitConfig { lobes, iterations, ..FitConfig::default() };
    let r = fit_sgs(&Backend::cpu(), &target, &cfg, |_| {}).unwrap();
    assert_eq!(r.skipped_steps, 0);
    let err = fit_error(&r.env, &rgb, w, h, conv);
    // A map that is exactly representable keeps its energy.
    assert!((err.energy_ratio - 1.0).abs() < 0.1, "{conv:?}: energy ratio {}", err.energy_ratio);
    (r.env, err.relative_l2)
}

#[test]
fn fit_recovers_known_sgs_in_both_conventions() {
    for conv in [LatlongConvention::OpenExrUsd, LatlongConvention::Blender] {
        let (_, err) = fit_known(conv, &known_env(), 4, 300);
        eprintln!("{conv:?}: relative L2 {err}");
        assert!(err < 0.15, "{conv:?}: relative L2 {err}");
    }
}

#[test]
fn one_lobe_fit_finds_the_axis_in_both_conventions() {
    let truth = SgLobe { axis: unit([0.4, 0.6, -0.7]), sharpness: 30.0, amplitude: [50.0, 40.0, 30.0] };
    for conv in [LatlongConvention::OpenExrUsd, LatlongConvention::Blender] {
        let (env, err) = fit_known(conv, &EnvSgs { lobes: vec![truth] }, 1, 300);
        let a = env.lobes[0].axis;
        let cos = (a[0] * truth.axis[0] + a[1] * truth.axis[1] + a[2] * truth.axis[2]).clamp(-1.0, 1.0);
        let deg = cos.acos().to_degrees();
        eprintln!("{conv:?}: axis off by {deg:.3} deg, lambda {}, error {err}", env.lobes[0].sharpness);
        assert!(deg < 2.0, "{conv:?}: axis off by {deg} degrees");
    }
}

fn sun_map(w: usize, h: usize, sun: (usize, usize)) -> Vec<f32> {
    // A sky graded from 0.5 (zenith) to 0.05 (nadir) and a 2x2-pixel sun of 2e4: the sun holds
    // most of the energy in a few pixels, the case the log loss alone gets wrong.
    let mut rgb = vec![0.0f32; w * h * 3];
    for y in 0..h {
        let v = 0.5 - 0.45 * y as f32 / h as f32;
        for x in 0..w {
            rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[v * 0.8, v * 0.9, v]);
        }
    }
    for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let i = ((sun.1 + dy) * w + sun.0 + dx) * 3;
        rgb[i..i + 3].copy_from_slice(&[2e4, 1.8e4, 1.5e4]);
    }
    rgb
}

#[test]
fn sun_map_fit_keeps_energy_and_irradiance() {
    let (w, h) = (256, 128);
    let conv = LatlongConvention::Blender;
    let rgb = sun_map(w, h, (170, 40));
    let target = FitTarget::from_map(&rgb, w, h, conv, 64);
    let cfg = FitConfig { lobes: 8, iterations: 150, ..FitConfig::default() };
    let r = fit_sgs(&Backend::cpu(), &target, &cfg, |_| {}).unwrap();
    let err = fit_error(&r.env, &rgb, w, h, conv);
    eprintln!("sun map, K = 8: {err:?}");
    assert!((err.energy_ratio - 1.0).abs() < 0.05, "energy ratio {}", err.energy_ratio);
    assert!(err.irradiance_error < DEFAULT_IRRADIANCE_TOLERANCE, "irradiance error {}", err.irradiance_error);
    // The brightest lobe sits on the sun (within one fit pixel, 5.6 deg at width 64).
    let sun = pii_bake::sg::env::latlong_dir(conv, 171, 41, w, h);
    let bright = r.env.lobes.iter().max_by(|a, b| a.amplitude[0].total_cmp(&b.amplitude[0])).unwrap();
    let deg = bright.axis.iter().zip(&sun).map(|(a, b)| a * b).sum::<f32>().clamp(-1.0, 1.0).acos().to_degrees();
    assert!(deg < 5.6, "brightest lobe {deg} deg from the sun");
}

#[test]
fn irradiance_error_measures_scale_and_rotation() {
    let (w, h) = (128, 64);
    let conv = LatlongConvention::OpenExrUsd;
    let env = known_env();
    let rgb = render_latlong(&env, w, h, conv);
    let same = fit_error(&env, &rgb, w, h, conv);
    assert!(same.irradiance_error < 1e-5 && (same.energy_ratio - 1.0).abs() < 1e-5, "{same:?}");
    // 10% brighter everywhere: irradiance 10% off at every normal.
    let brighter = EnvSgs { lobes: env.lobes.iter().map(|l| SgLobe { amplitude: l.amplitude.map(|a| a * 1.1), ..*l }).collect() };
    let e = fit_error(&brighter, &rgb, w, h, conv);
    assert!((e.irradiance_error - 0.1).abs() < 1e-4 && (e.energy_ratio - 1.1).abs() < 1e-4, "{e:?}");
    // The same lobes mirrored through the origin: same energy, irradiance far off.
    let mirrored = EnvSgs { lobes: env.lobes.iter().map(|l| SgLobe { axis: l.axis.map(|a| -a), ..*l }).collect() };
    let e = fit_error(&mirrored, &rgb, w, h, conv);
    assert!((e.energy_ratio - 1.0).abs() < 1e-3 && e.irradiance_error > 0.5, "{e:?}");
}

#[test]
fn init_is_deterministic_given_a_seed() {
    let rgb = render_latlong(&known_env(), 64, 32, LatlongConvention::OpenExrUsd);
    let t = FitTarget::from_map(&rgb, 64, 32, LatlongConvention::OpenExrUsd, 64);
    assert_eq!(init_params(&t, 16, 3), init_params(&t, 16, 3));
    assert_ne!(init_params(&t, 16, 3), init_params(&t, 16, 4));
}

fn cmd() -> assert_cmd::Command {
    let mut c = assert_cmd::Command::cargo_bin("pii-bake").unwrap();
    c.env("PII_BACKEND", "cpu");
    c
}

fn small_map(dir: &Path, name: &str) -> PathBuf {
    let p = dir.join(name);
    let rgb = render_latlong(&known_env(), 64, 32, LatlongConvention::OpenExrUsd);
    pii_bake::image_io::write_exr_rgb(&p, 64, 32, &rgb).unwrap();
    p
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

#[test]
fn fit_env_cli_writes_every_output() {
    let dir = tempfile::tempdir().unwrap();
    let map = small_map(dir.path(), "map.exr");
    let out = dir.path().join("out");
    let st = cmd().args(["fit-env", "--lobes", "4", "--iterations", "30", "--fit-width", "32", "--out"]).arg(&out).arg(&map).output().unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let rep = json(&out.join("fit_report.json"));
    assert_eq!(rep["lobes"], 4);
    assert_eq!(rep["iterations"], 30);
    assert_eq!(rep["backend"], "cpu");
    assert!(rep["relative_l2"].as_f64().unwrap().is_finite());
    assert!(rep["irradiance_error"].as_f64().unwrap().is_finite() && rep["energy_weight"].as_f64() == Some(pii_bake::sg::fit::DEFAULT_ENERGY_WEIGHT));
    let sg = EnvSgs::read_json(&out.join("env_sg.json")).unwrap();
    assert_eq!(sg.lobes.len(), 4);
    let exr = read_latlong_exr(&out.join("env_fit.exr")).unwrap();
    assert_eq!((exr.width, exr.height), (64, 32));
    let png = pii_bake::image_io::read_image_linear(&out.join("env_compare.png")).unwrap();
    assert_eq!((png.width, png.height), (3 * 64, 32));

    // Bad numbers are refused before any work, naming the flag.
    for (flag, v) in [("--energy-weight", "-1"), ("--irradiance-tolerance", "0"), ("--tolerance", "nan")] {
        let st = cmd().args(["fit-env", &format!("{flag}={v}"), "--out"]).arg(&out).arg(&map).output().unwrap();
        assert_eq!(st.status.code(), Some(1), "{flag} {v}");
        assert!(String::from_utf8_lossy(&st.stderr).contains(flag), "{}", String::from_utf8_lossy(&st.stderr));
    }

    // Missing and corrupt inputs: exit 1, one line naming the file.
    for bad in ["missing.exr", "corrupt.exr"] {
        let p = dir.path().join(bad);
        if bad == "corrupt.exr" {
            std::fs::write(&p, b"garbage").unwrap();
        }
        let st = cmd().args(["fit-env", "--lobes", "4", "--out"]).arg(&out).arg(&p).output().unwrap();
        assert_eq!(st.status.code(), Some(1));
        assert!(String::from_utf8_lossy(&st.stderr).contains(bad));
    }
}

#[test]
fn fit_env_auto_reports_every_rung() {
    let dir = tempfile::tempdir().unwrap();
    let map = small_map(dir.path(), "map.exr");
    // An irradiance tolerance no fit meets: every rung is tried, the largest is kept and flagged.
    let out = dir.path().join("strict");
    let st = cmd()
        .args(["--json", "fit-env", "--lobes", "auto", "--tolerance", "100", "--irradiance-tolerance", "1e-9", "--iterations", "10", "--fit-width", "32", "--out"])
        .arg(&out)
        .arg(&map)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&st.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let rungs: Vec<u64> = lines.iter().filter(|v| v["type"] == "rung").map(|v| v["lobes"].as_u64().unwrap()).collect();
    assert_eq!(rungs, [8, 16, 32, 64, 128]);
    let rep = json(&out.join("fit_report.json"));
    assert_eq!((rep["lobes"].as_u64(), rep["tolerance_met"].as_bool()), (Some(128), Some(false)));
    assert_eq!(rep["rungs"].as_array().unwrap().len(), 5);
    assert!(rep["rungs"][0]["irradiance_error"].as_f64().unwrap() > 1e-9);
    // Loose tolerances: the first rung meets them and the ladder stops there.
    let out = dir.path().join("loose");
    let st = cmd()
        .args(["fit-env", "--tolerance", "100", "--irradiance-tolerance", "100", "--iterations", "10", "--fit-width", "32", "--out"])
        .arg(&out)
        .arg(&map)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let rep = json(&out.join("fit_report.json"));
    assert_eq!((rep["lobes"].as_u64(), rep["tolerance_met"].as_bool()), (Some(8), Some(true)));
    assert_eq!(rep["rungs"].as_array().unwrap().len(), 1);
}

#[test]
fn bench_env_writes_csv_json_and_chart() {
    let dir = tempfile::tempdir().unwrap();
    let maps = dir.path().join("maps");
    std::fs::create_dir_all(maps.join("sub")).unwrap();
    small_map(&maps, "a.exr");
    small_map(&maps.join("sub"), "b.exr");
    let out = dir.path().join("bench");
    let st = cmd()
        .args(["bench", "env", "--lobes", "2,4", "--iterations", "5", "--fit-width", "16", "--maps"])
        .arg(&maps)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let csv = std::fs::read_to_string(out.join("bench-env.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 1 + 2 * 2, "{csv}");
    assert!(lines[0].starts_with("map,width,height,lobes,relative_l2"));
    assert!(lines[1].starts_with("a,64,32,2,") && lines[4].starts_with("sub/b,64,32,4,"), "{csv}");
    let rep = json(&out.join("bench-env.json"));
    assert_eq!(rep["rows"].as_array().unwrap().len(), 4);
    let svg = std::fs::read_to_string(out.join("bench-env.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("<text") && svg.contains("sub/b") && svg.contains("fit time (s)"), "{svg}");
    let svg = std::fs::read_to_string(out.join("bench-env-irradiance.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("irradiance") && svg.contains("sub/b"), "{svg}");
    let stdout = String::from_utf8_lossy(&st.stdout);
    assert!(stdout.contains("rel L2") && stdout.contains("sub/b"), "{stdout}");
    // The flags fit-env checks are checked here too, before any fit.
    let st = cmd().args(["bench", "env", "--energy-weight=-1", "--maps"]).arg(&maps).arg("--out").arg(&out).output().unwrap();
    assert_eq!(st.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&st.stderr).contains("--energy-weight"), "{}", String::from_utf8_lossy(&st.stderr));
}

#[test]
fn wgpu_fit_follows_the_cpu_fit() {
    let gpu = Backend::wgpu_for_tests().unwrap_or_else(|e| panic!("the test command (bash scripts/test.sh) installs lavapipe; no adapter: {e}"));
    let rgb = render_latlong(&known_env(), 64, 32, LatlongConvention::Blender);
    let target = FitTarget::from_map(&rgb, 64, 32, LatlongConvention::Blender, 64);
    let cfg = FitConfig { lobes: 8, iterations: 25, ..FitConfig::default() };
    let a = fit_sgs(&Backend::cpu(), &target, &cfg, |_| {}).unwrap();
    let b = fit_sgs(&gpu, &target, &cfg, |_| {}).unwrap();
    assert_eq!((a.skipped_steps, b.skipped_steps), (0, 0));
    let flat = |e: &EnvSgs| e.lobes.iter().flat_map(|l| [l.axis.to_vec(), vec![l.sharpness], l.amplitude.to_vec()].concat()).collect::<Vec<f32>>();
    // 25 Adam steps amplify f32-vs-f64 gradient differences a little: 1% relative, 1e-3 absolute.
    assert_close("wgpu fit vs cpu fit", &flat(&b.env), &flat(&a.env), Tolerance::new(1e-2, 1e-3));
    assert_close("final loss", &[b.final_loss], &[a.final_loss], Tolerance::new(1e-2, 0.0));
}
