//! `pii-bake bench material`: stage-2 speed against accuracy on one stage-1 run. For each variant
//! (lobe count × indirect mode) stage 2 is trained from the same stage-1 checkpoint into its own
//! run folder; the figures are the stage's wall time (cache and training), iterations/s, the
//! cache's field evaluations against what tracing every batch would cost, and held-out PSNR
//! under the learned light. Where the scene has ground truth (`scripts/make_scene.py`'s layout:
//! `test/<view>_albedo.png` and relight maps in `env/`), each variant is also relit and scored by
//! `eval` (albedo PSNR, relit PSNR per map, roughness MSE, environment error). Writes
//! `bench-material.{csv,json,svg}` (the chart: PSNR against stage-2 wall time, one point per
//! variant).

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::material::{train_stage2, KnownEnv, MaterialOptions};
use super::stage1::{Preset, CHECKPOINT, RUN_CONFIG};
use super::stage2::{BoundaryMode, IndirectMode};
use crate::context::Context;

#[derive(Debug, clap::Args)]
pub struct BenchMaterialArgs {
    /// A stage-1 run folder (`pii-bake train <scene> --out <run>`); its scene is the one measured.
    #[arg(long)]
    pub run: PathBuf,
    /// Output folder for the CSV/JSON/SVG and the variants' run folders.
    #[arg(long, default_value = "bench-out/material")]
    pub out: PathBuf,
    /// Lobe counts to measure.
    #[arg(long, num_args = 1.., default_values_t = vec![8usize, 32])]
    pub lobes: Vec<usize>,
    /// Indirect modes to measure.
    #[arg(long, value_enum, num_args = 1.., default_values_t = vec![IndirectMode::Ours, IndirectMode::None, IndirectMode::Uniform, IndirectMode::Mii])]
    pub indirect: Vec<IndirectMode>,
    /// Boundary-light modes to measure (the ablation: `flowing detached`).
    #[arg(long, value_enum, num_args = 1.., default_values_t = vec![BoundaryMode::Flowing])]
    pub boundary: Vec<BoundaryMode>,
    /// Geometry in stage 2 (the ablation: `frozen refined`).
    #[arg(long, value_enum, num_args = 1.., default_values_t = vec![GeometryVariant::Frozen])]
    pub geometry: Vec<GeometryVariant>,
    /// Stage-2 iterations per variant (default: the preset's).
    #[arg(long)]
    pub iterations: Option<u64>,
    /// Network preset (default: the stage-1 run's).
    #[arg(long, value_enum)]
    pub preset: Option<Preset>,
    /// Test views relit and scored per variant where the scene has ground truth (0 = skip).
    #[arg(long, default_value_t = 2)]
    pub relight_views: usize,
    /// Stage-2 setting overrides, KEY=VALUE, applied to every variant.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Train every variant under a known light (as `train --known-env`; a scene from
    /// `scripts/make_scene.py` has its training light in `env/train.exr`, Blender layout).
    #[command(flatten)]
    pub known_env: KnownEnv,
}

/// Stage 2's geometry, as a bench variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum GeometryVariant {
    /// Stage 1's SDF, frozen (the public code).
    Frozen,
    /// Refined jointly (`--refine-geometry`).
    Refined,
}

#[derive(Clone, Debug, Serialize)]
pub struct MaterialRow {
    pub variant: String,
    pub lobes: usize,
    pub indirect: String,
    pub boundary: String,
    pub geometry: String,
    pub backend: String,
    pub iterations: u64,
    pub seconds_cache: f64,
    pub seconds_train: f64,
    pub it_per_s: f64,
    pub cache_evaluations: f64,
    /// Field evaluations tracing every batch's secondary rays would cost over the run.
    pub per_batch_evaluations: f64,
    pub blocked_fraction: f64,
    pub heldout_psnr: f64,
    pub albedo_psnr: f64,
    pub relit_psnr: f64,
    /// The relit PSNR after one scale per channel (what the albedo's and the light's shared
    /// scale, which the photos cannot fix, costs the figure before it).
    pub relit_aligned_psnr: f64,
    /// Relit PSNR under each relight map (by the map's file stem), as rendered and aligned.
    pub relit_maps: std::collections::BTreeMap<String, RelitFigures>,
    /// `eval`'s novel-view PSNR of the relit folder's views under the learned light.
    pub novel_view_psnr: f64,
    pub roughness_mse: f64,
    /// `eval`'s metallic MSE where the scene's ground truth has metallic views (NaN elsewhere).
    pub metallic_mse: f64,
    pub env_relative_l2: f64,
    /// `eval`'s environment irradiance error (see [`crate::eval::EnvError::irradiance_error`]).
    pub env_irradiance_error: f64,
}

/// One relight map's scores of a variant.
#[derive(Clone, Debug, Serialize)]
pub struct RelitFigures {
    pub psnr: f64,
    pub psnr_aligned: f64,
}

fn copy_stage1(src: &Path, dst: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dst)?;
    for f in [CHECKPOINT, RUN_CONFIG, "scene.json", "train_report.json"] {
        let p = src.join(f);
        if p.is_file() {
            std::fs::copy(&p, dst.join(f))?;
        }
    }
    for f in [super::stage2::CHECKPOINT2, super::stage2::RUN_CONFIG2, "material_curve.csv"] {
        let _ = std::fs::remove_file(dst.join(f));
    }
    Ok(())
}

pub fn run(args: &BenchMaterialArgs, ctx: &Context) -> anyhow::Result<()> {
    crate::export::check_writable(&args.out)?;
    let s1 = super::material::load_stage1(&args.run, None)?;
    let scene = s1.run_scene.scene.clone();
    let backend = ctx.backend()?;
    let maps: Vec<PathBuf> = std::fs::read_dir(scene.join("env"))
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|e| e == "exr") && p.file_stem().is_some_and(|s| s != "train")).collect())
        .unwrap_or_default();
    let has_gt = scene.join("transforms_test.json").is_file() && !maps.is_empty();
    let preset = args.preset.or_else(|| super::cli::run_preset(&args.run)).unwrap_or(Preset::Fast);
    let mut rows = Vec::new();
    for &k in &args.lobes {
        let combos = args.indirect.iter().flat_map(|m| args.boundary.iter().flat_map(move |b| args.geometry.iter().map(move |g| (*m, *b, *g))));
        for (mode, boundary, geometry) in combos {
            let detached = boundary == BoundaryMode::Detached;
            let refined = geometry == GeometryVariant::Refined;
            let variant = format!("k{k}-{}{}{}", mode.name(), if detached { "-detached" } else { "" }, if refined { "-refined" } else { "" });
            let dir = args.out.join("runs").join(&variant);
            copy_stage1(&args.run, &dir)?;
            ctx.say(format!("bench material: {variant}"));
            let opts = MaterialOptions { lobes: Some(k), indirect: mode, boundary, refine_geometry: refined, material_iterations: args.iterations, material_set: args.overrides.clone(), known_env: args.known_env.clone(), ..Default::default() };
            let r = train_stage2(&scene, preset, &opts, 0, &dir, false, None, None, &backend, ctx)?;
            let rep = &r.report;
            let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
            let cfg = r.trainer.cfg();
            let mut row = MaterialRow {
                variant: variant.clone(),
                lobes: k,
                indirect: mode.name().to_string(),
                boundary: if detached { "detached" } else { "flowing" }.to_string(),
                geometry: if refined { "refined" } else { "frozen" }.to_string(),
                backend: backend.describe(),
                iterations: r.trainer.step,
                seconds_cache: f(&rep["seconds"]["cache"]),
                seconds_train: f(&rep["seconds"]["train"]),
                it_per_s: f(&rep["it_per_s"]),
                cache_evaluations: f(&rep["cache"]["field_evaluations"]),
                // Without the cache every step would trace its secondary rays at the cost measured per ray.
                per_batch_evaluations: if mode == IndirectMode::None { 0.0 } else { cfg.secondary_rays_per_batch() as f64 * f(&rep["cache"]["steps_per_secondary_ray"]) * r.trainer.step as f64 },
                blocked_fraction: f(&rep["cache"]["blocked_fraction"]),
                heldout_psnr: f(&rep["eval"]["psnr"]),
                albedo_psnr: f64::NAN,
                relit_psnr: f64::NAN,
                relit_aligned_psnr: f64::NAN,
                relit_maps: Default::default(),
                novel_view_psnr: f64::NAN,
                roughness_mse: f64::NAN,
                metallic_mse: f64::NAN,
                env_relative_l2: f64::NAN,
                env_irradiance_error: f64::NAN,
            };
            if has_gt && args.relight_views > 0 {
                let rel = dir.join("relit");
                let ra = super::relight::RelightArgs { run: dir.clone(), env: maps.clone(), cameras: None, out: rel.clone(), lobes: 32, convention: crate::sg::env::LatlongConvention::Blender, max_views: args.relight_views, samples: 2, downscale: crate::scene::Downscale::By(1) };
                super::relight::run(&ra, ctx)?;
                let metrics = dir.join("metrics.json");
                let ea = crate::eval::cli::EvalArgs { gt: scene.clone(), pred: rel, out: Some(metrics.clone()), mesh_samples: 1000, gt_mesh: None, pred_mesh: None, gt_env: None, pred_env: None };
                crate::eval::cli::run(&ea, ctx)?;
                let m = crate::util::read_json_value(&metrics)?;
                row.albedo_psnr = f(&m["albedo"]["psnr_aligned"]);
                row.roughness_mse = f(&m["roughness"]["mse"]);
                row.metallic_mse = f(&m["metallic"]["mse"]);
                row.env_relative_l2 = f(&m["env"]["relative_l2"]);
                row.env_irradiance_error = f(&m["env"]["irradiance_error"]);
                if let Some(o) = m["relit"].as_object() {
                    row.relit_maps = o.iter().map(|(k, v)| (k.clone(), RelitFigures { psnr: f(&v["psnr"]), psnr_aligned: f(&v["psnr_aligned"]) })).collect();
                }
                // The means over the maps, of the finite figures.
                let mean_relit = |g: fn(&RelitFigures) -> f64| -> f64 {
                    let v: Vec<f64> = row.relit_maps.values().map(g).filter(|v| v.is_finite()).collect();
                    crate::eval::cli::mean(&v).unwrap_or(f64::NAN)
                };
                row.relit_psnr = mean_relit(|r| r.psnr);
                row.relit_aligned_psnr = mean_relit(|r| r.psnr_aligned);
                row.novel_view_psnr = f(&m["novel_view"]["psnr"]);
            }
            ctx.emit("bench_material", serde_json::to_value(&row)?);
            rows.push(row);
        }
    }
    let mut csv = String::from("variant,lobes,indirect,boundary,geometry,backend,iterations,seconds_cache,seconds_train,it_per_s,cache_evaluations,per_batch_evaluations,blocked_fraction,heldout_psnr,novel_view_psnr,albedo_psnr,relit_psnr,relit_aligned_psnr,relit_per_map,roughness_mse,metallic_mse,env_relative_l2,env_irradiance_error\n");
    for r in &rows {
        csv.push_str(&format!(
            "{},{},{},{},{},\"{}\",{},{:.3},{:.3},{:.3},{},{},{:.5},{:.3},{:.3},{:.3},{:.3},{:.3},{},{:.5},{:.5},{:.5},{:.5}\n",
            r.variant, r.lobes, r.indirect, r.boundary, r.geometry, r.backend, r.iterations, r.seconds_cache, r.seconds_train, r.it_per_s, r.cache_evaluations, r.per_batch_evaluations, r.blocked_fraction, r.heldout_psnr, r.novel_view_psnr, r.albedo_psnr, r.relit_psnr, r.relit_aligned_psnr, relit_cell(&r.relit_maps), r.roughness_mse, r.metallic_mse, r.env_relative_l2, r.env_irradiance_error
        ));
    }
    crate::util::atomic_write(&args.out.join("bench-material.csv"), csv.as_bytes())?;
    let json = serde_json::json!({ "run": args.run.display().to_string(), "scene": scene.display().to_string(), "ground_truth": has_gt, "rows": rows });
    crate::util::atomic_write(&args.out.join("bench-material.json"), serde_json::to_string_pretty(&json)?.as_bytes())?;
    crate::util::atomic_write(&args.out.join("bench-material.svg"), chart(&rows)?.as_bytes())?;
    ctx.emit("bench_material_done", json);
    ctx.say(format!("wrote {}/bench-material.{{csv,json,svg}}", args.out.display()));
    Ok(())
}

/// The per-map relit figures as one CSV cell: `map=psnr/aligned` joined by `;`.
fn relit_cell(maps: &std::collections::BTreeMap<String, RelitFigures>) -> String {
    maps.iter().map(|(k, v)| format!("{k}={:.3}/{:.3}", v.psnr, v.psnr_aligned)).collect::<Vec<_>>().join(";")
}

fn chart(rows: &[MaterialRow]) -> anyhow::Result<String> {
    use plotters::prelude::*;
    let e = |e: &dyn std::fmt::Display| anyhow::anyhow!("chart: {e}");
    let series: [(&str, fn(&MaterialRow) -> f64); 3] = [("held-out PSNR (learned light)", |r| r.heldout_psnr), ("relit PSNR (mean over maps)", |r| r.relit_psnr), ("albedo PSNR (scale-aligned)", |r| r.albedo_psnr)];
    let all: Vec<(f64, f64)> = rows.iter().flat_map(|r| series.iter().map(move |(_, g)| (r.seconds_cache + r.seconds_train, g(r)))).filter(|p| p.1.is_finite()).collect();
    let tmax = all.iter().map(|p| p.0).fold(1.0, f64::max) * 1.1;
    let ymin = all.iter().map(|p| p.1).fold(f64::INFINITY, f64::min).min(30.0) - 1.0;
    let ymax = all.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max).max(ymin + 2.0) + 1.0;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 600)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(&x))?;
        let mut chart = ChartBuilder::on(&root)
            .caption("stage 2: accuracy vs wall time (cache + training), one point per variant", ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..tmax, ymin..ymax)
            .map_err(|x| e(&x))?;
        chart.configure_mesh().x_desc("stage-2 wall time (s)").y_desc("PSNR (dB)").draw().map_err(|x| e(&x))?;
        for (i, (name, g)) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let pts: Vec<(f64, f64, String)> = rows.iter().map(|r| (r.seconds_cache + r.seconds_train, g(r), r.variant.clone())).filter(|p| p.1.is_finite()).collect();
            if pts.is_empty() {
                continue;
            }
            chart
                .draw_series(pts.iter().map(|(x, y, _)| Circle::new((*x, *y), 4, color.filled())))
                .map_err(|x| e(&x))?
                .label(*name)
                .legend(move |(x, y)| Circle::new((x + 8, y), 4, color.filled()));
            chart.draw_series(pts.iter().map(|(x, y, l)| Text::new(l.clone(), (*x, *y), ("sans-serif", 11)))).map_err(|x| e(&x))?;
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(|x| e(&x))?;
        root.present().map_err(|x| e(&x))?;
    }
    Ok(svg)
}
