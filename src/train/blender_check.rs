//! The Blender check of a bake: `scripts/blender_verify.py` (embedded in the binary) renders the
//! exported .glb in Cycles under the asset's `env.exr` from held-out cameras, and scores each
//! render against the held-out photo inside its mask (PSNR/SSIM). It runs through the Python
//! named by `PII_PYTHON` (default `python3`), which needs Blender as a module (`bpy`); where there
//! is none the check is reported as skipped, never as a failed bake.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use glam::{DMat3, DVec3};

use crate::context::Context;
use crate::scene::View;

/// The render check, embedded so an installed binary needs no source tree.
const SCRIPT: &str = include_str!("../../scripts/blender_verify.py");

/// Cycles samples per pixel of the Blender check by default (see `BlenderCheckOptions`).
const DEFAULT_BLENDER_SAMPLES: usize = 128;

/// Options of the Blender check (flattened into `bake`).
#[derive(clap::Args, Clone, Debug)]
pub struct BlenderCheckOptions {
    /// Skip rendering the asset in Blender (Cycles) against held-out photos.
    #[arg(long)]
    pub no_blender_check: bool,
    /// Held-out views the Blender check renders.
    #[arg(long, default_value_t = 2)]
    pub blender_views: usize,
    /// Cycles samples per pixel of the Blender check. Cycles' noise lowers the score: the bundled
    /// example's bake, 2 views at 96 px, 32 -> 128 -> 512 samples: 26.27 -> 26.75 -> 26.82 dB
    /// (6 -> 10 -> 21 s on a 2-core machine), so 128.
    #[arg(long, default_value_t = DEFAULT_BLENDER_SAMPLES)]
    pub blender_samples: usize,
    /// Skip the relit part of the check: where the scene has ground-truth renders under other
    /// light (`scene.json`'s `env.relight` maps and `test/<view>_relit_<map>.png`, as
    /// `scripts/make_scene.py` writes them), the check also renders the .glb under each map from
    /// the same held-out cameras and scores it against them.
    #[arg(long)]
    pub no_blender_relight: bool,
}

impl Default for BlenderCheckOptions {
    fn default() -> Self {
        Self { no_blender_check: false, blender_views: 2, blender_samples: DEFAULT_BLENDER_SAMPLES, no_blender_relight: false }
    }
}

/// Normalised scene frame → asset frame (metres, +Y up, origin at the bottom centre).
#[derive(Clone, Copy, Debug)]
pub struct AssetFrame {
    pub rotation: DMat3,
    /// Metres per normalised unit.
    pub scale: f64,
    pub shift: DVec3,
}

impl AssetFrame {
    fn point(&self, p: DVec3) -> DVec3 {
        self.rotation * p * self.scale + self.shift
    }
}

/// The camera record blender_verify.py reads, in the asset frame.
pub fn camera_json(view: &View, frame: &AssetFrame) -> serde_json::Value {
    let c = &view.camera;
    let center = c.center();
    let pos = frame.point(center);
    let target = frame.point(center + c.forward());
    let up_a = frame.rotation * c.up();
    let fov = c.fov_x();
    // The principal point as Blender's lens shift (in units of the image's larger side; the
    // optical axis lands at pixel (w/2 − shift_x·s, h/2 + shift_y·s)): DTU scan37's sits 5–6 px
    // off centre, and a centred Blender camera then scored the asset against shifted photos.
    let s = c.width.max(c.height).max(1) as f64;
    serde_json::json!({
        "name": view.name,
        "position": pos.to_array(),
        "target": target.to_array(),
        "up": up_a.to_array(),
        "fov_deg": fov.to_degrees(),
        "width": c.width,
        "height": c.height,
        "shift_x": (0.5 * c.width as f64 - c.cx) / s,
        "shift_y": (c.cy - 0.5 * c.height as f64) / s,
    })
}

/// The photo with its mask as alpha (sRGB PNG), the reference the render is scored against.
fn write_reference(view: &View, path: &Path) -> anyhow::Result<()> {
    let (w, h) = (view.camera.width, view.camera.height);
    let mut data = vec![0.0f32; w * h * 4];
    for i in 0..w * h {
        data[4 * i..4 * i + 3].copy_from_slice(&view.image.data[3 * i..3 * i + 3]);
        data[4 * i + 3] = view.mask.as_ref().map_or(1.0, |m| m[i]);
    }
    crate::image_io::write_png8(path, w, h, 4, &data, true)?;
    Ok(())
}

/// The scene's relight maps that have ground-truth renders: `scene.json`'s `env.relight`
/// (name → latlong EXR in Blender's World convention, as `scripts/make_scene.py` writes it), the
/// maps whose file exists and whose name is plain (it names folders and files). None for a scene
/// without that record (a real capture).
pub fn relight_maps(scene_dir: &Path) -> Vec<(String, PathBuf)> {
    let Some(v) = std::fs::read(scene_dir.join("scene.json")).ok().and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok()) else {
        return Vec::new();
    };
    if v["env"]["convention"].as_str().is_some_and(|c| c != "blender") {
        return Vec::new();
    }
    let plain = |n: &str| !n.is_empty() && n.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    let Some(maps) = v["env"]["relight"].as_object() else {
        return Vec::new();
    };
    maps.iter()
        .filter_map(|(name, p)| Some((name.clone(), scene_dir.join(p.as_str()?))))
        .filter(|(name, p)| plain(name) && p.is_file())
        .collect()
}

/// The ground-truth render of `view` under a relight map (`test/<view>_relit_<map>.png`, sRGB
/// RGBA), brought to the view's size as `eval` brings it (box filter, colour weighted by alpha)
/// and written as the reference `path`.
fn write_relit_reference(gt: &Path, view: &View, path: &Path) -> anyhow::Result<()> {
    let img = crate::image_io::read_image_linear(gt)?;
    let (w, h) = (view.camera.width, view.camera.height);
    let n = img.width / w.max(1);
    if img.channels != 4 || n == 0 || (img.width / n, img.height / n) != (w, h) {
        anyhow::bail!("{}: expected an RGBA render of {w}x{h} or N times that, found {} channels at {}x{}", gt.display(), img.channels, img.width, img.height);
    }
    let (rgb, alpha) = crate::eval::cli::downscale_weighted(img.rgb(), 3, (img.width, img.height), img.alpha(), n);
    let alpha = alpha.unwrap_or_else(|| vec![1.0; w * h]);
    let data: Vec<f32> = rgb.chunks_exact(3).zip(&alpha).flat_map(|(c, &a)| [c[0], c[1], c[2], a]).collect();
    crate::image_io::write_png8(path, w, h, 4, &data, true)?;
    Ok(())
}

pub(crate) fn python() -> String {
    std::env::var("PII_PYTHON").unwrap_or_else(|_| "python3".to_string())
}

fn skipped(why: String) -> serde_json::Value {
    serde_json::json!({ "status": "skipped", "why": why })
}

/// Run the check on the asset in `asset_dir`. `views`: the held-out views (`held_out` false when
/// the scene has none and training views stand in); `scene_dir`: where the relit ground truth is
/// looked for (held-out views only). Returns the report section.
pub fn run(asset_dir: &Path, scene_dir: &Path, views: &[&View], held_out: bool, frame: &AssetFrame, opts: &BlenderCheckOptions, ctx: &Context) -> serde_json::Value {
    if opts.no_blender_check {
        return skipped("--no-blender-check".into());
    }
    if views.is_empty() || opts.blender_views == 0 {
        return skipped("no views to render".into());
    }
    let t = Instant::now();
    match run_inner(asset_dir, scene_dir, views, held_out, frame, opts, ctx) {
        Ok(mut v) => {
            v["seconds"] = serde_json::json!(t.elapsed().as_secs_f64());
            v
        }
        Err(e) => {
            let mut msg = format!("{e:#}");
            if msg.contains("No module named 'bpy'") {
                msg = format!("{} has no bpy module: install Blender as a module (`pip install bpy==5.0.1`, Python 3.11) or point PII_PYTHON at a Python that has it", python());
            }
            if msg.contains("has no bpy module") || msg.contains("cannot run") {
                ctx.say(format!("Blender check skipped: {msg}"));
                skipped(msg)
            } else {
                ctx.say(format!("Blender check FAILED: {msg}"));
                serde_json::json!({ "status": "failed", "why": msg, "seconds": t.elapsed().as_secs_f64() })
            }
        }
    }
}

fn run_inner(asset_dir: &Path, scene_dir: &Path, views: &[&View], held_out: bool, frame: &AssetFrame, opts: &BlenderCheckOptions, ctx: &Context) -> anyhow::Result<serde_json::Value> {
    let n = views.len().min(opts.blender_views);
    // Spread the chosen views over the available ones.
    let chosen: Vec<&View> = (0..n).map(|i| views[i * views.len() / n]).collect();
    let out = asset_dir.join("blender_check");
    let refs = out.join("photos");
    std::fs::create_dir_all(&refs).map_err(|e| anyhow::anyhow!("{}: cannot create: {e}", refs.display()))?;
    let cams: Vec<serde_json::Value> = chosen.iter().map(|v| camera_json(v, frame)).collect();
    let cams_path = out.join("cameras.json");
    crate::util::atomic_write(&cams_path, serde_json::to_string_pretty(&cams)?.as_bytes())?;
    for (i, v) in chosen.iter().enumerate() {
        write_reference(v, &refs.join(format!("ref_cam{i}.png")))?;
    }
    // The relit part: every relight map whose ground truth covers the chosen held-out views.
    let mut relight_args: Vec<std::ffi::OsString> = Vec::new();
    let mut relit = serde_json::Map::new();
    if held_out && !opts.no_blender_relight {
        for (name, env) in relight_maps(scene_dir) {
            let dir = out.join("relit").join(&name);
            std::fs::create_dir_all(&dir).map_err(|e| anyhow::anyhow!("{}: cannot create: {e}", dir.display()))?;
            let written: anyhow::Result<()> = chosen.iter().enumerate().try_for_each(|(i, v)| {
                write_relit_reference(&scene_dir.join("test").join(format!("{}_relit_{name}.png", v.name)), v, &dir.join(format!("ref_cam{i}.png")))
            });
            match written {
                Ok(()) => {
                    relight_args.extend(["--relight".into(), name.clone().into(), env.clone().into_os_string(), dir.into_os_string()]);
                    relit.insert(name, serde_json::json!({ "env": env.display().to_string() }));
                }
                Err(e) => {
                    ctx.say(format!("Blender check: not relit under {name}: {e:#}"));
                    relit.insert(name, serde_json::json!({ "env": env.display().to_string(), "status": "skipped", "why": format!("{e:#}") }));
                }
            }
        }
    }
    let script: PathBuf = std::env::temp_dir().join(format!("pii-bake-blender-verify-{}.py", std::process::id()));
    std::fs::write(&script, SCRIPT).map_err(|e| anyhow::anyhow!("{}: cannot write: {e}", script.display()))?;
    let py = python();
    let report_path = out.join("blender_report.json");
    ctx.say(format!(
        "Blender check: rendering the .glb in Cycles from {n} {} views ({} samples){} with {py}",
        if held_out { "held-out" } else { "training" },
        opts.blender_samples,
        if relight_args.is_empty() { String::new() } else { format!(", under its own light and {} relight maps", relight_args.len() / 4) }
    ));
    let result = Command::new(&py)
        .arg(&script)
        .args(["--asset-dir"])
        .arg(asset_dir)
        .arg("--cameras")
        .arg(&cams_path)
        .arg("--out")
        .arg(&out)
        .arg("--reference-dir")
        .arg(&refs)
        .args(["--samples", &opts.blender_samples.to_string(), "--skip-usd", "--film-transparent", "--json"])
        .arg(&report_path)
        .args(&relight_args)
        .output();
    let _ = std::fs::remove_file(&script);
    let output = result.map_err(|e| anyhow::anyhow!("cannot run {py} (set PII_PYTHON to a Python with bpy): {e}"))?;
    if !output.status.success() {
        let err = String::from_utf8_lossy(&output.stderr);
        let tail: String = err.lines().rev().take(6).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join("\n");
        anyhow::bail!("{py} scripts/blender_verify.py exited with {}: {tail}", output.status);
    }
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&report_path)?)?;
    let pair = report["pairs"].as_array().and_then(|p| p.iter().find(|p| p["pair"] == "glb_vs_reference")).cloned().unwrap_or_default();
    let psnr = pair["mean_psnr"].as_f64();
    let ssim = pair["min_ssim"].as_f64();
    ctx.say(format!(
        "Blender check: .glb in Cycles vs {} photos (masked): mean PSNR {} dB, min SSIM {}",
        if held_out { "held-out" } else { "training" },
        psnr.map_or("n/a".into(), |v| format!("{v:.2}")),
        ssim.map_or("n/a".into(), |v| format!("{v:.3}"))
    ));
    for (name, entry) in relit.iter_mut() {
        if entry.get("status").is_some() {
            continue;
        }
        let p = report["pairs"].as_array().and_then(|ps| ps.iter().find(|p| p["pair"] == format!("glb_relit_{name}_vs_reference"))).cloned().unwrap_or_default();
        let (psnr, aligned) = (p["mean_psnr"].as_f64(), p["mean_psnr_aligned"].as_f64());
        entry["status"] = serde_json::json!(if psnr.is_some() { "ok" } else { "failed" });
        entry["mean_psnr"] = serde_json::json!(psnr);
        entry["mean_psnr_aligned"] = serde_json::json!(aligned);
        entry["min_ssim"] = p["min_ssim"].clone();
        entry["channel_scale"] = p["channel_scale"].clone();
        entry["ground_truth"] = serde_json::json!(format!("test/<view>_relit_{name}.png"));
        ctx.say(format!(
            "Blender check: .glb in Cycles under {name} vs the ground truth relit: mean PSNR {} dB ({} dB after one scale per channel)",
            psnr.map_or("n/a".into(), |v| format!("{v:.2}")),
            aligned.map_or("n/a".into(), |v| format!("{v:.2}"))
        ));
    }
    Ok(serde_json::json!({
        "status": if psnr.is_some() { "ok" } else { "failed" },
        "views": chosen.iter().map(|v| v.name.clone()).collect::<Vec<_>>(),
        "held_out": held_out,
        "samples": opts.blender_samples,
        "mean_psnr": psnr,
        "min_psnr": pair["min_psnr"].as_f64(),
        "min_ssim": ssim,
        "report": "blender_check/blender_report.json",
        "relit": relit,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image_io::ImageF32;
    use crate::scene::{Camera, Split};
    use glam::DMat4;

    #[test]
    fn cameras_map_into_the_asset_frame() {
        // A camera at (0, 0, -3) looking along +z with image up = -y (OpenCV), 100×50 pixels.
        let camera = Camera { width: 100, height: 50, fx: 50.0, fy: 50.0, cx: 50.0, cy: 25.0, distortion: None, world_from_camera: DMat4::from_translation(DVec3::new(0.0, 0.0, -3.0)) };
        let view = View { name: "v".into(), split: Split::Test, camera, image: ImageF32::new(100, 50, 3), mask: None, image_path: "v.png".into() };
        // Asset frame: a quarter turn about +x, 2 m per unit, lifted by 1 m.
        let frame = AssetFrame { rotation: DMat3::from_rotation_x(std::f64::consts::FRAC_PI_2), scale: 2.0, shift: DVec3::new(0.0, 1.0, 0.0) };
        let j = camera_json(&view, &frame);
        let v = |k: &str| DVec3::from_slice(&j[k].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect::<Vec<_>>());
        let close = |a: DVec3, b: DVec3| assert!((a - b).length() < 1e-9, "{a} vs {b}");
        // R_x(90°) maps (0,0,-3) to (0,3,0); ×2, +1 in y.
        close(v("position"), DVec3::new(0.0, 7.0, 0.0));
        close(v("target") - v("position"), DVec3::new(0.0, -2.0, 0.0));
        close(v("up"), DVec3::new(0.0, 0.0, -1.0));
        assert!((j["fov_deg"].as_f64().unwrap() - 90.0).abs() < 1e-9);
        assert_eq!((j["width"].as_u64(), j["height"].as_u64()), (Some(100), Some(50)));
    }

    #[test]
    fn relight_maps_come_from_scene_json_and_only_usable_ones_are_kept() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        // No scene.json (a real capture): none.
        assert!(relight_maps(d).is_empty());
        std::fs::create_dir_all(d.join("env")).unwrap();
        for f in ["a.exr", "b.exr", "odd.exr"] {
            std::fs::write(d.join("env").join(f), b"x").unwrap();
        }
        let record = |convention: &str| {
            let j = serde_json::json!({ "env": { "convention": convention, "relight": {
                "a": "env/a.exr", "b": "env/b.exr", "missing": "env/missing.exr", "../odd": "env/odd.exr", "n": 3 } } });
            std::fs::write(d.join("scene.json"), j.to_string()).unwrap();
        };
        record("blender");
        // The missing file, the name that is not plain and the entry that is not a path are left out.
        let maps = relight_maps(d);
        assert_eq!(maps.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(), ["a", "b"]);
        assert_eq!(maps[1].1, d.join("env/b.exr"));
        // Maps in another convention are not read as Blender's.
        record("usd");
        assert!(relight_maps(d).is_empty());
        std::fs::write(d.join("scene.json"), b"{ not json").unwrap();
        assert!(relight_maps(d).is_empty());
    }

    #[test]
    fn a_relit_reference_is_the_ground_truth_box_filtered_to_the_view() {
        let dir = tempfile::tempdir().unwrap();
        let camera = Camera { width: 2, height: 1, fx: 2.0, fy: 2.0, cx: 1.0, cy: 0.5, distortion: None, world_from_camera: DMat4::IDENTITY };
        let view = View { name: "v".into(), split: Split::Test, camera, image: ImageF32::new(2, 1, 3), mask: None, image_path: "v.png".into() };
        // A 4×2 ground truth: the left 2×2 block half covered by a colour of linear 0.5, the right
        // one fully covered by 0.25.
        let mut gt = Vec::new();
        for y in 0..2 {
            for x in 0..4 {
                gt.extend_from_slice(&if x < 2 { if (x + y) % 2 == 0 { [0.5; 4] } else { [0.0; 4] } } else { [0.25, 0.25, 0.25, 1.0] });
            }
        }
        let gt_path = dir.path().join("gt.png");
        crate::image_io::write_png8(&gt_path, 4, 2, 4, &gt.iter().enumerate().map(|(i, &v)| if i % 4 == 3 { v * 2.0 } else { v }).collect::<Vec<_>>(), true).unwrap();
        let out = dir.path().join("ref.png");
        write_relit_reference(&gt_path, &view, &out).unwrap();
        let r = crate::image_io::read_image_linear(&out).unwrap();
        assert_eq!((r.width, r.height, r.channels), (2, 1, 4));
        // Left: the covered pixels' colour (not darkened by the uncovered ones), half alpha.
        assert!((r.data[0] - 0.5).abs() < 0.01 && (r.data[3] - 0.5).abs() < 0.01, "{:?}", r.data);
        assert!((r.data[4] - 0.25).abs() < 0.01 && (r.data[7] - 1.0).abs() < 0.01, "{:?}", r.data);
        // A ground truth that is not N times the view's size is refused, naming the file.
        let odd = dir.path().join("odd.png");
        crate::image_io::write_png8(&odd, 3, 2, 4, &[0.5; 24], true).unwrap();
        let e = format!("{:#}", write_relit_reference(&odd, &view, &out).unwrap_err());
        assert!(e.contains("odd.png") && e.contains("2x1"), "{e}");
    }
}
