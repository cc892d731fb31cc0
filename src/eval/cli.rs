//! The `eval` command: metrics of a prediction folder against a ground-truth scene.
//!
//! ```text
//! pii-bake eval --gt <scene> --pred <dir> [--out metrics.json] [--mesh-samples 100000]
//! ```
//! The ground truth is a scene written by `scripts/make_scene.py` (or any folder with the same layout);
//! the prediction folder mirrors its file names. For every frame `<name>` of `transforms_test.json`:
//!
//! | metric | ground truth | prediction |
//! | --- | --- | --- |
//! | novel view PSNR/SSIM (masked by GT alpha) | `test/<name>.png` | `test/<name>.png` or `.exr` |
//! | relit view PSNR/SSIM, per environment `<env>` | `test/<name>_relit_<env>.png` | same name (`.png`/`.exr`) |
//! | albedo PSNR after per-channel LS scale (all views together) | `test/<name>_albedo.png` | same name |
//! | roughness MSE (GT alpha-weighted) | `test/<name>_roughness.png` | same name |
//! | metallic MSE (GT alpha-weighted), where the GT has it | `test/<name>_metallic.png` (linear) | same name; none = a dielectric model's 0 |
//! | normal mean angular error, degrees (pixels both cover) | `test/<name>_normal.png` (world n·0.5+0.5, linear) | same name |
//!
//! and once: environment error after per-channel scale alignment, GT `env/train.exr` vs `env.exr` (same
//! latlong convention, resampled to the GT size if needed; `--gt-env/--pred-env` override), and Chamfer
//! distance + normal consistency, GT `gt/mesh.obj` vs `mesh.obj` or `mesh.ply` (same world frame;
//! `--gt-mesh/--pred-mesh` override). A metric whose prediction file is missing is skipped and listed
//! under `missing`. A prediction rendered at 1/N of the ground truth's size (`relight --downscale N`,
//! the size `scene::downscale` gives: each side divided by N, rounded down) is scored against the
//! ground truth box-filtered by N, colour and data weighted by alpha, and the report says so
//! (`downscale`: N, 1 at full size); any other size, or a folder that mixes factors, is an error.
//! PNGs are sRGB colour (roughness PNGs are linear values); EXRs are linear.

use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use super::mesh::{compare_meshes, Mesh};
use super::{apply_scale, env_error, ls_scale_rgb, psnr_srgb, resample_latlong, ssim_srgb, weighted_mse};
use crate::context::Context;
use crate::image_io::{read_image_linear, read_mask, ImageF32};
use crate::util::{atomic_write, DataError};

#[derive(Debug, clap::Args)]
pub struct EvalArgs {
    /// Ground-truth scene folder (layout of scripts/make_scene.py).
    #[arg(long)]
    pub gt: PathBuf,
    /// Prediction folder mirroring the ground truth's file names (see `eval` docs).
    #[arg(long)]
    pub pred: PathBuf,
    /// Write the metrics JSON here (atomically).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Points sampled on each mesh for Chamfer / normal consistency.
    #[arg(long, default_value_t = 100_000)]
    pub mesh_samples: usize,
    #[arg(long)]
    pub gt_mesh: Option<PathBuf>,
    #[arg(long)]
    pub pred_mesh: Option<PathBuf>,
    #[arg(long)]
    pub gt_env: Option<PathBuf>,
    #[arg(long)]
    pub pred_env: Option<PathBuf>,
}

/// The GT-alpha-weighted MSE of a one-value map (`rel`: `test/<name>_<what>`, linear PNG values).
/// A missing prediction is listed under `missing` (None), or with `missing_is_zero` scored as 0
/// everywhere at the ground truth's size.
fn value_map_mse(gt: &Path, pred: &Path, rel: &str, missing_is_zero: bool, found: &mut Found) -> Result<Option<f64>, DataError> {
    let gp = gt.join(format!("{rel}.png"));
    let (gw, gh, gv) = read_mask(&gp)?;
    let alpha = read_image_linear(&gp)?.alpha();
    let (pv, n) = match find_pred(&pred.join(rel)) {
        Some(pp) => {
            let (pw, ph, pv) = read_mask(&pp)?;
            let n = found.factor((pw, ph), (gw, gh), &pp, &gp)?;
            (pv, n)
        }
        None if missing_is_zero => (vec![0.0; gv.len()], 1),
        None => {
            found.missing.push(rel.to_string());
            return Ok(None);
        }
    };
    let (gv, alpha) = downscale_weighted(gv, 1, (gw, gh), alpha, n);
    Ok(Some(weighted_mse(&pv, &gv, 1, alpha.as_deref())))
}

fn find_pred(base: &Path) -> Option<PathBuf> {
    ["png", "exr"].iter().map(|e| base.with_extension(e)).find(|p| p.is_file())
}

/// What scoring a folder collects beside the metrics: the predictions it did not find, and the one
/// factor its images were rendered at (`gt` side / `pred` side).
#[derive(Default)]
struct Found {
    missing: Vec<String>,
    downscale: Option<usize>,
}

impl Found {
    /// The factor N with `pred = gt / N` on both sides (rounded down, as `scene::downscale` and
    /// `Camera::downscaled` size an image), checked to be the folder's one factor.
    fn factor(&mut self, pred: (usize, usize), gt: (usize, usize), pred_path: &Path, gt_path: &Path) -> Result<usize, DataError> {
        let n = if pred.0 > 0 { gt.0 / pred.0 } else { 0 };
        let fits = n >= 1 && pred.1 > 0 && (gt.0 / n, gt.1 / n) == pred;
        let size = |(w, h): (usize, usize)| format!("{w}x{h}");
        if !fits {
            return Err(DataError::new(
                pred_path,
                format!(
                    "prediction is {} but the ground truth {} is {}: render at its size or at 1/N of it (relight --downscale N)",
                    size(pred),
                    gt_path.display(),
                    size(gt)
                ),
            ));
        }
        match self.downscale {
            Some(m) if m != n => Err(DataError::new(
                pred_path,
                format!("prediction is 1/{n} of the ground truth {}'s size, but other predictions in the folder are 1/{m}", gt_path.display()),
            )),
            _ => {
                self.downscale = Some(n);
                Ok(n)
            }
        }
    }
}

/// `values` (`channels` per pixel, `width`×`height`) box-filtered by `n` as `scene::downscale`
/// reads photos, each value weighted by `alpha` where there is one (a silhouette pixel keeps the
/// colour of what covers it and takes the covered share as its alpha, as a render at that size
/// has it): `(values, alpha)` at 1/n, returned as they are for n = 1.
pub(crate) fn downscale_weighted(values: Vec<f32>, channels: usize, (width, height): (usize, usize), alpha: Option<Vec<f32>>, n: usize) -> (Vec<f32>, Option<Vec<f32>>) {
    if n == 1 {
        return (values, alpha);
    }
    let Some(alpha) = alpha else {
        return (crate::scene::downscale(&ImageF32 { width, height, channels, data: values }, n).data, None);
    };
    let c = channels + 1;
    let data = values.chunks_exact(channels).zip(&alpha).flat_map(|(v, &a)| v.iter().map(move |x| x * a).chain([a])).collect();
    let small = crate::scene::downscale(&ImageF32 { width, height, channels: c, data }, n);
    let mut out = Vec::with_capacity(small.data.len() / c * channels);
    let mut out_alpha = Vec::with_capacity(small.data.len() / c);
    for p in small.data.chunks_exact(c) {
        let a = p[channels];
        out.extend(p[..channels].iter().map(|x| if a > 0.0 { x / a } else { 0.0 }));
        out_alpha.push(a);
    }
    (out, Some(out_alpha))
}

/// A ground-truth image brought to the prediction's size `pred` (see `Found::factor`); RGBA is
/// filtered with its colour weighted by alpha.
fn fit_image(gt: ImageF32, pred: (usize, usize), found: &mut Found, pred_path: &Path, gt_path: &Path) -> Result<ImageF32, DataError> {
    let n = found.factor(pred, (gt.width, gt.height), pred_path, gt_path)?;
    if n == 1 {
        return Ok(gt);
    }
    if gt.channels != 4 {
        return Ok(crate::scene::downscale(&gt, n));
    }
    let (rgb, alpha) = downscale_weighted(gt.rgb(), 3, (gt.width, gt.height), gt.alpha(), n);
    let alpha = alpha.unwrap_or_default();
    let data = rgb.chunks_exact(3).zip(&alpha).flat_map(|(c, &a)| [c[0], c[1], c[2], a]).collect();
    Ok(ImageF32 { width: pred.0, height: pred.1, channels: 4, data })
}

pub(crate) fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Test frame names from the ground truth's transforms_test.json.
fn test_names(gt: &Path) -> Result<Vec<String>, DataError> {
    let p = gt.join("transforms_test.json");
    let v = crate::util::read_json_value(&p)?;
    let frames = v.get("frames").and_then(Value::as_array).ok_or_else(|| DataError::new(&p, "no \"frames\" array"))?;
    frames
        .iter()
        .map(|f| {
            f.get("file_path")
                .and_then(Value::as_str)
                .and_then(|s| Path::new(s).file_stem().map(|x| x.to_string_lossy().into_owned()))
                .ok_or_else(|| DataError::new(&p, "a frame has no file_path"))
        })
        .collect()
}

/// Relighting environments listed as GT files `test/<first>_relit_<env>.png`.
fn relight_envs(gt: &Path, first: &str) -> Vec<String> {
    let prefix = format!("{first}_relit_");
    let mut envs: Vec<String> = std::fs::read_dir(gt.join("test"))
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    let stem = e.path().file_stem()?.to_string_lossy().into_owned();
                    stem.strip_prefix(&prefix).map(str::to_string)
                })
                .collect()
        })
        .unwrap_or_default();
    envs.sort();
    envs.dedup();
    envs
}

struct ViewScores {
    psnr: Vec<f64>,
    ssim: Vec<f64>,
    per_view: Vec<Value>,
    /// Linear RGB of prediction and ground truth with the mask, per view (kept for alignment).
    images: Vec<ViewImages>,
}

/// One view's linear prediction, ground truth and mask.
type ViewImages = (Vec<f32>, Vec<f32>, Option<Vec<f32>>);

/// One per-channel least-squares scale over all views and each view's PSNR after it: how albedo is
/// scored, and relit images beside their raw PSNR (judged up to the light/albedo scale ambiguity).
fn scale_aligned_psnr(views: &[ViewImages]) -> ([f64; 3], Vec<f64>) {
    let s = ls_scale_rgb(views.iter().map(|(p, g, m)| (&p[..], &g[..], m.as_deref())));
    (s, views.iter().map(|(p, g, m)| psnr_srgb(&apply_scale(p, s), g, m.as_deref())).collect())
}

/// A test view's ground truth `<gt>/<rel>.png` and its prediction `<pred>/<rel>` (`.png`/`.exr`),
/// each with its path, read as linear, the ground truth at its own size: `(prediction, ground
/// truth)`. None, with `rel` listed as missing, where there is no prediction.
fn read_pair(gt: &Path, pred: &Path, rel: String, found: &mut Found) -> Result<Option<[(ImageF32, PathBuf); 2]>, DataError> {
    let gp = gt.join(format!("{rel}.png"));
    let Some(pp) = find_pred(&pred.join(&rel)) else {
        found.missing.push(rel);
        return Ok(None);
    };
    let g = read_image_linear(&gp)?;
    let p = read_image_linear(&pp)?;
    Ok(Some([(p, pp), (g, gp)]))
}

/// `read_pair` with the ground truth brought to the prediction's size (`fit_image`).
fn read_fitted(gt: &Path, pred: &Path, rel: String, found: &mut Found) -> Result<Option<(ImageF32, ImageF32)>, DataError> {
    let Some([(p, pp), (g, gp)]) = read_pair(gt, pred, rel, found)? else {
        return Ok(None);
    };
    let g = fit_image(g, (p.width, p.height), found, &pp, &gp)?;
    Ok(Some((p, g)))
}

fn score_views(gt: &Path, pred: &Path, names: &[String], suffix: &str, found: &mut Found) -> Result<ViewScores, DataError> {
    let mut s = ViewScores { psnr: vec![], ssim: vec![], per_view: vec![], images: vec![] };
    for name in names {
        let Some((p, g)) = read_fitted(gt, pred, format!("test/{name}{suffix}"), found)? else {
            continue;
        };
        let mask = g.alpha();
        let (prgb, grgb) = (p.rgb(), g.rgb());
        let ps = psnr_srgb(&prgb, &grgb, mask.as_deref());
        let ss = ssim_srgb(&prgb, &grgb, g.width, g.height, mask.as_deref());
        s.psnr.push(ps);
        if let Some(v) = ss {
            s.ssim.push(v);
        }
        s.per_view.push(json!({"name": name, "psnr": ps, "ssim": ss}));
        s.images.push((prgb, grgb, mask));
    }
    Ok(s)
}

/// Compute every metric available; returns the JSON report.
pub fn evaluate(args: &EvalArgs) -> Result<Value, DataError> {
    let (gt, pred) = (&args.gt, &args.pred);
    if !pred.is_dir() {
        return Err(DataError::new(pred, "prediction folder not found"));
    }
    let names = test_names(gt)?;
    let mut found = Found::default();
    let mut report = serde_json::Map::new();
    report.insert("gt".into(), json!(gt.display().to_string()));
    report.insert("pred".into(), json!(pred.display().to_string()));
    report.insert("test_views".into(), json!(names.len()));

    let nv = score_views(gt, pred, &names, "", &mut found)?;
    if !nv.psnr.is_empty() {
        report.insert("novel_view".into(), json!({"views": nv.psnr.len(), "psnr": mean(&nv.psnr), "ssim": mean(&nv.ssim), "per_view": nv.per_view}));
    }
    let mut relit = serde_json::Map::new();
    if let Some(first) = names.first() {
        for env in relight_envs(gt, first) {
            let r = score_views(gt, pred, &names, &format!("_relit_{env}"), &mut found)?;
            if !r.psnr.is_empty() {
                let (scale, aligned) = scale_aligned_psnr(&r.images);
                relit.insert(env, json!({"views": r.psnr.len(), "psnr": mean(&r.psnr), "ssim": mean(&r.ssim), "psnr_aligned": mean(&aligned), "scale": scale, "per_view": r.per_view}));
            }
        }
    }
    if !relit.is_empty() {
        report.insert("relit".into(), Value::Object(relit));
    }

    // Albedo: one per-channel scale over all views, then PSNR per view.
    let mut albedo = Vec::new();
    for name in &names {
        let Some((p, g)) = read_fitted(gt, pred, format!("test/{name}_albedo"), &mut found)? else {
            continue;
        };
        albedo.push((p.rgb(), g.rgb(), g.alpha()));
    }
    if !albedo.is_empty() {
        let (s, ps) = scale_aligned_psnr(&albedo);
        report.insert("albedo".into(), json!({"views": ps.len(), "scale": s, "psnr_aligned": mean(&ps), "per_view_psnr": ps}));
    }

    let mut rough = Vec::new();
    for name in &names {
        if let Some(e) = value_map_mse(gt, pred, &format!("test/{name}_roughness"), false, &mut found)? {
            rough.push(e);
        }
    }
    if !rough.is_empty() {
        report.insert("roughness".into(), json!({"views": rough.len(), "mse": mean(&rough), "per_view_mse": rough}));
    }

    // Metallic: where the ground truth has it (a scene with metals); a prediction without it is a
    // dielectric model's, scored as 0 everywhere.
    let mut metal = Vec::new();
    let mut metal_predicted = true;
    for name in &names {
        let rel = format!("test/{name}_metallic");
        if !gt.join(format!("{rel}.png")).is_file() {
            continue;
        }
        metal_predicted &= find_pred(&pred.join(&rel)).is_some();
        if let Some(e) = value_map_mse(gt, pred, &rel, true, &mut found)? {
            metal.push(e);
        }
    }
    if !metal.is_empty() {
        let predicted = if metal_predicted { "the prediction's metallic views" } else { "none predicted (a dielectric model): scored as 0" };
        report.insert("metallic".into(), json!({"views": metal.len(), "mse": mean(&metal), "per_view_mse": metal, "predicted": predicted}));
    }

    let mut normal = Vec::new();
    for name in &names {
        // Optional in the ground truth (scenes written before make_scene's normal pass lack it).
        let rel = format!("test/{name}_normal");
        if !gt.join(format!("{rel}.png")).is_file() {
            continue;
        }
        let Some([(p, pp), (g, gp)]) = read_pair(gt, pred, rel, &mut found)? else {
            continue;
        };
        // Filtered as stored (n·0.5 + 0.5 is linear in n; the angle renormalises the mean).
        let n = found.factor((p.width, p.height), (g.width, g.height), &pp, &gp)?;
        let (gn, ga) = downscale_weighted(stored_values(&g, &gp), 3, (g.width, g.height), g.alpha(), n);
        if let Some(e) = normal_error_degrees((&stored_values(&p, &pp), p.alpha()), (&gn, ga)) {
            normal.push(e);
        }
    }
    if !normal.is_empty() {
        report.insert("normal".into(), json!({"views": normal.len(), "mae_degrees": mean(&normal), "per_view_mae_degrees": normal}));
    }

    let gt_env = args.gt_env.clone().unwrap_or_else(|| gt.join("env").join("train.exr"));
    let pred_env = args.pred_env.clone().unwrap_or_else(|| pred.join("env.exr"));
    if pred_env.is_file() {
        let g = read_image_linear(&gt_env)?;
        let p = read_image_linear(&pred_env)?;
        let (g3, mut p3) = (g.rgb(), p.rgb());
        if (p.width, p.height) != (g.width, g.height) {
            p3 = resample_latlong(&p3, p.width, p.height, g.width, g.height);
        }
        let e = env_error(&p3, &g3, g.width, g.height);
        report.insert("env".into(), serde_json::to_value(e).unwrap_or(Value::Null));
    } else {
        found.missing.push(pred_env.display().to_string());
    }

    let gt_mesh = args.gt_mesh.clone().unwrap_or_else(|| gt.join("gt").join("mesh.obj"));
    let pred_mesh = args.pred_mesh.clone().or_else(|| ["mesh.obj", "mesh.ply"].iter().map(|n| pred.join(n)).find(|p| p.is_file()));
    match pred_mesh {
        Some(pm) => {
            let m = compare_meshes(&Mesh::read(&pm)?, &Mesh::read(&gt_mesh)?, args.mesh_samples, 0);
            report.insert("mesh".into(), serde_json::to_value(m).unwrap_or(Value::Null));
        }
        None => found.missing.push("mesh.obj / mesh.ply".into()),
    }
    if let Some(n) = found.downscale {
        report.insert("downscale".into(), json!(n));
    }
    report.insert("missing".into(), json!(found.missing));
    Ok(Value::Object(report))
}

/// An image's RGB as stored in the file: `read_image_linear` decodes PNGs as sRGB, so data PNGs
/// (normal maps) are re-encoded; EXRs are returned as read.
fn stored_values(img: &ImageF32, path: &Path) -> Vec<f32> {
    let exr = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    if exr { img.rgb() } else { super::encode_srgb(&img.rgb()) }
}

/// Mean angle in degrees between two normal maps given as (RGB = n·0.5 + 0.5, alpha) over the
/// pixels both cover (alpha ≥ 0.5 where an image has alpha); None where no pixel is covered by both.
pub fn normal_error_degrees(pred: (&[f32], Option<Vec<f32>>), gt: (&[f32], Option<Vec<f32>>)) -> Option<f64> {
    let ((pn, pa), (gn, ga)) = (pred, gt);
    let (mut sum, mut count) = (0.0f64, 0usize);
    for i in 0..pn.len() / 3 {
        let covered = |a: &Option<Vec<f32>>| a.as_ref().is_none_or(|a| a[i] >= 0.5);
        if !(covered(&pa) && covered(&ga)) {
            continue;
        }
        let unit = |v: &[f32]| {
            let d = glam::DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64) * 2.0 - 1.0;
            d.try_normalize()
        };
        if let (Some(a), Some(b)) = (unit(&pn[3 * i..3 * i + 3]), unit(&gn[3 * i..3 * i + 3])) {
            sum += a.dot(b).clamp(-1.0, 1.0).acos().to_degrees();
            count += 1;
        }
    }
    (count > 0).then(|| sum / count as f64)
}

pub fn run(args: &EvalArgs, ctx: &Context) -> anyhow::Result<()> {
    if let Some(out) = &args.out {
        crate::util::ensure_writable_parent(out)?;
    }
    let report = evaluate(args)?;
    if let Some(out) = &args.out {
        let text = serde_json::to_string_pretty(&report)?;
        atomic_write(out, text.as_bytes())?;
    }
    ctx.emit("eval", report.clone());
    let f = |v: &Value| v.as_f64().map_or("-".to_string(), |x| format!("{x:.4}"));
    if let Some(n) = report.get("downscale").and_then(Value::as_u64).filter(|&n| n > 1) {
        ctx.say(format!("images scored at 1/{n} of the ground truth's size (the ground truth box-filtered by {n})"));
    }
    if let Some(nv) = report.get("novel_view") {
        ctx.say(format!("novel view   PSNR {} dB  SSIM {}  ({} views)", f(&nv["psnr"]), f(&nv["ssim"]), nv["views"]));
    }
    if let Some(Value::Object(r)) = report.get("relit") {
        for (env, v) in r {
            ctx.say(format!("relit {env:<8} PSNR {} dB  SSIM {}  ({} dB after per-channel scale)", f(&v["psnr"]), f(&v["ssim"]), f(&v["psnr_aligned"])));
        }
    }
    if let Some(a) = report.get("albedo") {
        ctx.say(format!("albedo       PSNR {} dB after scale {}", f(&a["psnr_aligned"]), a["scale"]));
    }
    if let Some(r) = report.get("roughness") {
        ctx.say(format!("roughness    MSE {}", f(&r["mse"])));
    }
    if let Some(m) = report.get("metallic") {
        ctx.say(format!("metallic     MSE {} ({})", f(&m["mse"]), m["predicted"].as_str().unwrap_or("")));
    }
    if let Some(n) = report.get("normal") {
        ctx.say(format!("normal       mean angular error {} degrees", f(&n["mae_degrees"])));
    }
    if let Some(e) = report.get("env") {
        ctx.say(format!("environment  irradiance error {}  rel. L2 {}  log-MSE {} (scale {})", f(&e["irradiance_error"]), f(&e["relative_l2"]), f(&e["log_mse"]), e["scale"]));
    }
    if let Some(m) = report.get("mesh") {
        ctx.say(format!("mesh         Chamfer {}  normal consistency {}", f(&m["chamfer"]), f(&m["normal_consistency"])));
    }
    if let Some(Value::Array(m)) = report.get("missing") {
        if !m.is_empty() {
            ctx.say(format!("skipped (no prediction): {}", m.len()));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::{downscale_weighted, fit_image, normal_error_degrees, Found};
    use crate::image_io::ImageF32;

    #[test]
    fn a_prediction_at_one_nth_is_scored_against_the_ground_truth_filtered_by_n() {
        let (pp, gp) = (Path::new("pred.png"), Path::new("gt.png"));
        // 5x4 RGBA: a red object over the left half of a 2x2 block, transparent (black) beside it.
        let mut gt = ImageF32::new(5, 4, 4);
        for y in 0..4 {
            for x in 0..5 {
                let px = &mut gt.data[(y * 5 + x) * 4..(y * 5 + x + 1) * 4];
                if x % 2 == 0 {
                    px.copy_from_slice(&[0.8, 0.1, 0.2, 1.0]);
                }
            }
        }
        let mut found = Found::default();
        let small = fit_image(gt.clone(), (2, 2), &mut found, pp, gp).unwrap();
        assert_eq!((small.width, small.height, small.channels), (2, 2, 4));
        // Colour weighted by alpha keeps the object's colour; alpha is the covered share.
        for p in small.data.chunks_exact(4) {
            for (a, b) in p.iter().zip([0.8, 0.1, 0.2, 0.5]) {
                assert!((a - b).abs() < 1e-6, "{p:?}");
            }
        }
        assert_eq!(found.downscale, Some(2));
        // Full size passes through only in a folder at full size; other sizes are refused.
        assert!(found.factor((5, 4), (5, 4), pp, gp).unwrap_err().problem.contains("other predictions in the folder are 1/2"));
        assert_eq!(Found::default().factor((5, 4), (5, 4), pp, gp).unwrap(), 1);
        for bad in [(3, 2), (2, 3), (0, 0), (6, 4)] {
            let e = Found::default().factor(bad, (5, 4), pp, gp).unwrap_err();
            assert!(e.problem.contains("render at its size or at 1/N of it"), "{bad:?}: {}", e.problem);
        }
        // Without alpha, a plain box filter; an uncovered block has alpha 0 and colour 0.
        let (v, a) = downscale_weighted(vec![1.0, 3.0, 5.0, 7.0], 1, (2, 2), None, 2);
        assert_eq!((v, a), (vec![4.0], None));
        let (v, a) = downscale_weighted(vec![1.0, 3.0, 5.0, 7.0], 1, (2, 2), Some(vec![0.0; 4]), 2);
        assert_eq!((v, a), (vec![0.0], Some(vec![0.0])));
    }

    fn map(n: [f64; 3], pixels: usize) -> Vec<f32> {
        (0..pixels).flat_map(|_| n.map(|v| (v * 0.5 + 0.5) as f32)).collect()
    }

    #[test]
    fn normal_error_is_the_mean_angle_over_covered_pixels() {
        let up = map([0.0, 0.0, 1.0], 4);
        let side = map([1.0, 0.0, 0.0], 4);
        let tilted = map([0.0, 0.5f64.sqrt(), 0.5f64.sqrt()], 4);
        assert!(normal_error_degrees((&up, None), (&up, None)).unwrap().abs() < 1e-6);
        assert!((normal_error_degrees((&up, None), (&side, None)).unwrap() - 90.0).abs() < 1e-4);
        assert!((normal_error_degrees((&up, None), (&tilted, None)).unwrap() - 45.0).abs() < 1e-4);
        // Only pixels both maps cover count: the uncovered ones (wrong normals) are ignored.
        let mut mixed = up.clone();
        mixed[..6].copy_from_slice(&side[..6]);
        let alpha = Some(vec![0.0, 0.0, 1.0, 1.0]);
        assert!(normal_error_degrees((&mixed, alpha.clone()), (&up, None)).unwrap().abs() < 1e-6);
        assert!((normal_error_degrees((&mixed, None), (&up, None)).unwrap() - 45.0).abs() < 1e-4);
        assert!(normal_error_degrees((&mixed, Some(vec![0.0; 4])), (&up, None)).is_none());
    }
}
