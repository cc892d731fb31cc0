//! The `bench brdf` command: how well each SG form of the BRDF ([`BrdfModel`]) reproduces
//! Cycles' Principled BSDF, the renderer that makes `make_scene.py`'s ground truth and that
//! renders the asset in Blender. Per map, the map is fitted with SG lobes and re-rendered as a
//! latlong EXR; `scripts/brdf_spheres.py` renders a unit sphere under that re-render in Cycles for
//! every (metallic, roughness), so the light is the same on both sides and only the BRDF differs.
//! Each model then shades the same sphere under the lobes, and the bench records, per image:
//! display-referred PSNR (clamped to [0, 1], gamma 2.2) at the true roughness, the energy ratio
//! (ours / Cycles, linear), and the roughness the model fits best (grid of 0.05) with its PSNR.
//! Writes `bench-brdf.{csv,json}` atomically and `bench-brdf.svg` (PSNR at the true roughness
//! against roughness, one series per model and metallic), prints the table.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::Context as _;
use glam::DMat3;
use rayon::prelude::*;

use crate::context::Context;
use crate::sg::env::{write_latlong_exr, EnvSgs, LatlongConvention, SgLobe};
use crate::sg::shade::{BrdfModel, Sg};
use crate::train::stage2::shade_f64;
use crate::util::atomic_write;

const SCRIPT: &str = include_str!("../../scripts/brdf_spheres.py");
/// The script's orthographic camera: the image spans [-1.1, 1.1]².
const ORTHO_HALF: f64 = 1.1;
/// Pixels further than this from the sphere's centre (unit radius) are left out: the silhouette's
/// pixels are partly background.
const DISK: f64 = 0.97;

#[derive(Debug, clap::Args)]
pub struct BenchBrdfArgs {
    /// Latlong .exr maps (Blender World layout). Default: the courtyard and envmap6 maps of
    /// $PII_SHARED_DATA/envmaps (else ../shared/data/envmaps).
    #[arg(long)]
    pub maps: Vec<PathBuf>,
    /// Roughness values rendered, comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])]
    pub roughness: Vec<f64>,
    /// Metallic values rendered, comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = vec![1.0, 0.0])]
    pub metallic: Vec<f64>,
    /// Base colour (linear RGB), comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = vec![0.8, 0.6, 0.4])]
    pub base: Vec<f64>,
    /// SG lobes fitted to each map.
    #[arg(long, default_value_t = 128)]
    pub lobes: usize,
    /// Sphere image width and height (pixels).
    #[arg(long, default_value_t = 96)]
    pub size: usize,
    /// Cycles samples per pixel.
    #[arg(long, default_value_t = 128)]
    pub samples: usize,
    /// Output folder.
    #[arg(long, default_value = "bench-brdf")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct BrdfRow {
    pub map: String,
    pub metallic: f64,
    pub roughness: f64,
    pub model: BrdfModel,
    pub psnr_true_roughness: f64,
    pub energy_ratio: f64,
    pub best_roughness: f64,
    pub psnr_best_roughness: f64,
}

fn default_maps() -> Vec<PathBuf> {
    let root = std::env::var_os("PII_SHARED_DATA").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("../shared/data")).join("envmaps");
    vec![root.join("blender_studiolights/courtyard.exr"), root.join("invrender/envmap6.exr")]
}

/// One sphere pixel: its normal (the run frame, +Y up) and Cycles' linear RGB.
struct Pixel {
    n: [f64; 3],
    rgb: [f64; 3],
}

fn sphere_pixels(path: &Path) -> anyhow::Result<Vec<Pixel>> {
    let img = crate::image_io::read_image_linear(path)?;
    let (w, h) = (img.width, img.height);
    let mut out = Vec::new();
    for j in 0..h {
        for i in 0..w {
            // Blender's frame: x right, z up, the camera on −Y; ours (+Y up) = (b.x, b.z, −b.y).
            let x = (i as f64 + 0.5) / w as f64 * 2.0 * ORTHO_HALF - ORTHO_HALF;
            let z = ORTHO_HALF - (j as f64 + 0.5) / h as f64 * 2.0 * ORTHO_HALF;
            let r2 = x * x + z * z;
            if r2 > DISK * DISK {
                continue;
            }
            let o = (j * w + i) * img.channels;
            out.push(Pixel { n: [x, z, (1.0 - r2).sqrt()], rgb: [0, 1, 2].map(|c| img.data[o + c] as f64) });
        }
    }
    if out.is_empty() {
        anyhow::bail!("{}: no sphere pixels", path.display());
    }
    Ok(out)
}

/// Outgoing radiance of a sphere pixel (view along +Z of our frame) under `lobes`: stage 2's
/// shading ([`shade_f64`]) with its clamps.
fn shade(model: BrdfModel, base: [f64; 3], rough: f64, metal: f64, n: [f64; 3], lobes: &[Sg<f64>]) -> [f64; 3] {
    let (spec, diff) = shade_f64(model, base, rough, metal, n, [0.0, 0.0, 1.0], lobes);
    [0, 1, 2].map(|c| spec[c].max(0.0) + diff[c].max(0.0))
}

/// (display-referred MSE, energy ratio ours / Cycles).
fn compare(model: BrdfModel, base: [f64; 3], rough: f64, metal: f64, px: &[Pixel], lobes: &[Sg<f64>]) -> (f64, f64) {
    let tm = |x: f64| x.clamp(0.0, 1.0).powf(1.0 / 2.2);
    let (se, ours, theirs) = px
        .par_iter()
        .map(|p| {
            let o = shade(model, base, rough, metal, p.n, lobes);
            (0..3).fold((0.0, 0.0, 0.0), |(a, b, c), k| (a + (tm(o[k]) - tm(p.rgb[k])).powi(2), b + o[k], c + p.rgb[k]))
        })
        .reduce(|| (0.0, 0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    (se / (3 * px.len()) as f64, ours / theirs.max(1e-12))
}

fn psnr(mse: f64) -> f64 {
    -10.0 * mse.max(1e-12).log10()
}

pub fn run(args: &BenchBrdfArgs, ctx: &Context) -> anyhow::Result<()> {
    if args.base.len() != 3 || args.base.iter().any(|b| !(0.0..=1.0).contains(b)) {
        anyhow::bail!("--base needs three values in [0, 1]");
    }
    if args.roughness.is_empty() || args.roughness.iter().chain(&args.metallic).any(|v| !(0.0..=1.0).contains(v)) {
        anyhow::bail!("--roughness and --metallic need values in [0, 1]");
    }
    let base = [args.base[0], args.base[1], args.base[2]];
    crate::util::ensure_writable_dir(&args.out)?;
    let maps = if args.maps.is_empty() { default_maps() } else { args.maps.clone() };
    let backend = ctx.backend()?;
    let script = args.out.join("brdf_spheres.py");
    atomic_write(&script, SCRIPT.as_bytes())?;
    let py = crate::train::blender_check::python();
    let list = |v: &[f64]| v.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join(",");
    let mut rows = Vec::new();
    for map in &maps {
        let stem = map.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "map".into());
        let (lobes, _) = crate::train::relight::fit_map_lobes(&backend, map, LatlongConvention::Blender, args.lobes, DMat3::IDENTITY, ctx)?;
        let env = EnvSgs { lobes: lobes.iter().map(|l| SgLobe { axis: l.axis.map(|x| x as f32), sharpness: l.lambda as f32, amplitude: l.mu.map(|x| x as f32) }).collect() };
        let dir = args.out.join(&stem);
        std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        let env_path = dir.join("env_sg.exr");
        write_latlong_exr(&env, &env_path, 512, LatlongConvention::Blender)?;
        ctx.say(format!("bench brdf: {} fitted with {} lobes; rendering {} spheres in Cycles with {py}", map.display(), lobes.len(), args.roughness.len() * args.metallic.len()));
        let out = Command::new(&py)
            .arg(&script)
            .arg("--env")
            .arg(&env_path)
            .arg("--out")
            .arg(&dir)
            .args(["--roughness", &list(&args.roughness), "--metallic", &list(&args.metallic), "--base", &list(&args.base)])
            .args(["--size", &args.size.to_string(), "--samples", &args.samples.to_string()])
            .output()
            .with_context(|| format!("cannot run {py} (set PII_PYTHON to a Python with bpy)"))?;
        if !out.status.success() {
            let err = String::from_utf8_lossy(&out.stderr);
            anyhow::bail!("{py} {}: failed:\n{}", script.display(), err.lines().rev().take(8).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join("\n"));
        }
        for &m in &args.metallic {
            for &r in &args.roughness {
                let px = sphere_pixels(&dir.join(format!("m{m:.2}_r{r:.2}.exr")))?;
                for model in [BrdfModel::Physg, BrdfModel::Calibrated] {
                    let (mse, energy) = compare(model, base, r, m, &px, &lobes);
                    let (best_mse, best_r) = (1..=20).map(|k| k as f64 * 0.05).map(|rr| (compare(model, base, rr, m, &px, &lobes).0, rr)).fold((f64::INFINITY, 0.0), |a, b| if b.0 < a.0 { b } else { a });
                    rows.push(BrdfRow { map: stem.clone(), metallic: m, roughness: r, model, psnr_true_roughness: psnr(mse), energy_ratio: energy, best_roughness: best_r, psnr_best_roughness: psnr(best_mse) });
                }
            }
        }
    }
    let mut csv = String::from("map,metallic,roughness,model,psnr_true_roughness,energy_ratio,best_roughness,psnr_best_roughness\n");
    println!("{:<12} {:>5} {:>5} {:<11} {:>9} {:>7} {:>7} {:>9}", "map", "metal", "R", "model", "PSNR@R", "energy", "best R", "PSNR@best");
    for r in &rows {
        let model = serde_json::to_value(r.model)?.as_str().unwrap_or_default().to_string();
        csv.push_str(&format!("{},{},{},{},{:.3},{:.4},{:.2},{:.3}\n", r.map, r.metallic, r.roughness, model, r.psnr_true_roughness, r.energy_ratio, r.best_roughness, r.psnr_best_roughness));
        println!("{:<12} {:>5.2} {:>5.2} {:<11} {:>9.2} {:>7.3} {:>7.2} {:>9.2}", r.map, r.metallic, r.roughness, model, r.psnr_true_roughness, r.energy_ratio, r.best_roughness, r.psnr_best_roughness);
    }
    atomic_write(&args.out.join("bench-brdf.csv"), csv.as_bytes())?;
    let doc = serde_json::json!({ "base": base, "lobes": args.lobes, "size": args.size, "samples": args.samples, "rows": rows });
    atomic_write(&args.out.join("bench-brdf.json"), serde_json::to_string_pretty(&doc)?.as_bytes())?;
    atomic_write(&args.out.join("bench-brdf.svg"), chart(&rows)?.as_bytes())?;
    ctx.say(format!("bench brdf: wrote {}/bench-brdf.{{csv,json,svg}}", args.out.display()));
    Ok(())
}

fn chart(rows: &[BrdfRow]) -> anyhow::Result<String> {
    use plotters::prelude::*;
    let e = |e: &dyn std::fmt::Display| anyhow::anyhow!("chart: {e}");
    let ymin = rows.iter().map(|r| r.psnr_true_roughness).fold(f64::INFINITY, f64::min).min(30.0) - 2.0;
    let ymax = rows.iter().map(|r| r.psnr_true_roughness).fold(f64::NEG_INFINITY, f64::max).max(ymin + 5.0) + 2.0;
    // One series per (map, model, metallic).
    let mut keys: Vec<(String, BrdfModel, u64)> = rows.iter().map(|r| (r.map.clone(), r.model, r.metallic.to_bits())).collect();
    keys.sort_by(|a, b| (a.0.as_str(), a.1 as u8, a.2).cmp(&(b.0.as_str(), b.1 as u8, b.2)));
    keys.dedup();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 600)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(&x))?;
        let mut chart = ChartBuilder::on(&root)
            .caption("SG shading vs Cycles (Principled BSDF) on a sphere: PSNR at the true roughness", ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..1.0, ymin..ymax)
            .map_err(|x| e(&x))?;
        chart.configure_mesh().x_desc("roughness").y_desc("PSNR (dB)").draw().map_err(|x| e(&x))?;
        for (i, (map, model, metal)) in keys.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let pts: Vec<(f64, f64)> = rows.iter().filter(|r| &r.map == map && r.model == *model && r.metallic.to_bits() == *metal).map(|r| (r.roughness, r.psnr_true_roughness)).collect();
            let style = if *model == BrdfModel::Calibrated { color.stroke_width(2) } else { color.stroke_width(1) };
            chart
                .draw_series(LineSeries::new(pts, style))
                .map_err(|x| e(&x))?
                .label(format!("{map}, {model:?}, metallic {}", f64::from_bits(*metal)))
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(|x| e(&x))?;
        root.present().map_err(|x| e(&x))?;
    }
    Ok(svg)
}
