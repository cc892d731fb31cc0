//! `pii-bake relight <run-or-asset> --env <map.exr>... [--cameras <scene>] --out <dir>`: render a
//! trained stage-2 model under other HDR environments from a scene's test cameras.
//!
//! Each map is fitted with SG lobes (`fit-env`'s fit, `--lobes` per map) and rotated into the
//! model's normalised frame. A pixel is traced onto the stage-1 surface and shaded with the
//! learned material under the map's lobes; a lobe blocked by the object is replaced by one-bounce
//! light (the learned material at the secondary hit, lit by the same map). The folder is laid out
//! for `eval --gt <scene> --pred <dir>`:
//! - `test/<view>_relit_<map stem>.png` per map,
//! - `test/<view>.png` (the learned light, i.e. novel-view synthesis), `test/<view>_albedo.png`
//!   (sRGB) and `test/<view>_roughness.png` (linear values),
//! - `env.exr` (the learned environment, in `--convention`), `relight_report.json`.
//!
//! PNGs are RGBA: alpha = the rendered silhouette.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DVec3};

use super::material::{load_stage1, render_view, RenderedView};
use super::stage2::{Stage2Trainer, CHECKPOINT2};
use crate::context::Context;
use crate::scene::{ReadOptions, Split, View};
use crate::sg::env::{read_latlong_exr, write_latlong_exr, LatlongConvention};
use crate::sg::fit::{fit_sgs, FitConfig, FitTarget};
use crate::sg::shade::Sg;
use crate::util::DataError;

#[derive(Debug, clap::Args)]
pub struct RelightArgs {
    /// A run folder with stages 1 and 2 (`train --stage all`), or an asset folder written by
    /// `bake` (its `run/` is used).
    pub run: PathBuf,
    /// HDR latlong environment map(s) (.exr) to relight with; repeatable.
    #[arg(long, required = true)]
    pub env: Vec<PathBuf>,
    /// Scene whose test cameras to render (default: the run's own scene).
    #[arg(long)]
    pub cameras: Option<PathBuf>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// SG lobes fitted to each map.
    #[arg(long, default_value_t = 64)]
    pub lobes: usize,
    /// Latlong layout of the maps and of the written env.exr (`blender`: Blender's World, the
    /// layout `scripts/make_scene.py` renders with).
    #[arg(long, value_enum, default_value_t = LatlongConvention::Blender)]
    pub convention: LatlongConvention,
    /// Render at most this many views (0 = all test views).
    #[arg(long, default_value_t = 0)]
    pub max_views: usize,
    /// Sub-pixels per axis: each pixel averages s×s camera rays (straight alpha = the covered
    /// fraction, colour = the mean over covered sub-pixels), as a renderer's pixel filter does.
    #[arg(long, default_value_t = 2)]
    pub samples: usize,
}

/// The run folder behind a run-or-asset path.
fn resolve_run(p: &Path) -> Result<PathBuf, DataError> {
    if p.join(CHECKPOINT2).is_file() {
        return Ok(p.to_path_buf());
    }
    if p.join("run").join(CHECKPOINT2).is_file() {
        return Ok(p.join("run"));
    }
    if !p.exists() {
        return Err(DataError::new(p, "not found"));
    }
    Err(DataError::new(p, "no stage-2 run here (expected material.safetensors, or run/material.safetensors in a bake's asset folder): train it with `pii-bake train <scene> --out <run> --stage all`"))
}

/// Write a view rendered at `s`× the pixels per axis (every pixel rendered) as a straight-alpha
/// RGBA image: alpha = covered fraction of each pixel's s×s sub-pixels, colour = their mean value.
fn write_view(path: &Path, img: &RenderedView, s: usize, value: impl Fn(usize) -> [f32; 3], srgb: bool) -> Result<(), DataError> {
    let (w, h) = (img.width / s, img.height / s);
    let mut sum = vec![0.0f32; w * h * 4];
    for (k, &p) in img.pixel_index.iter().enumerate() {
        if img.hit[k] {
            let (x, y) = (p % img.width / s, p / img.width / s);
            let o = 4 * (y * w + x);
            let c = value(k);
            for i in 0..3 {
                sum[o + i] += c[i].clamp(0.0, 1.0);
            }
            sum[o + 3] += 1.0;
        }
    }
    let covered = (s * s) as f32;
    for px in sum.chunks_exact_mut(4) {
        if px[3] > 0.0 {
            let n = px[3];
            px[..3].iter_mut().for_each(|v| *v /= n);
            px[3] = n / covered;
        }
    }
    crate::image_io::write_png8(path, w, h, 4, &sum, srgb)
}

pub fn run(args: &RelightArgs, ctx: &Context) -> anyhow::Result<()> {
    let t_total = Instant::now();
    crate::export::check_writable(&args.out)?;
    let run_dir = resolve_run(&args.run)?;
    let s1 = load_stage1(&run_dir, None)?;
    let (s2, _, _) = Stage2Trainer::load(&run_dir, Some(&s1.run_scene.key))?;
    let rotation = DMat3::from_cols_array(&s1.run_scene.rotation);
    let rt = rotation.transpose();
    if args.lobes == 0 || args.lobes > 512 {
        anyhow::bail!("--lobes must be in 1..=512");
    }
    if args.samples == 0 || args.samples > 8 {
        anyhow::bail!("--samples must be in 1..=8");
    }
    let ss = args.samples;
    // Fit every map first: a bad map fails before any rendering.
    let backend = ctx.backend()?;
    let mut maps: Vec<(String, Vec<Sg<f64>>, f64)> = Vec::new();
    for p in &args.env {
        let map = read_latlong_exr(p)?;
        let target = FitTarget::from_map(&map.rgb, map.width, map.height, args.convention, 128);
        let cfg = FitConfig { lobes: args.lobes, ..Default::default() };
        let pb = ctx.progress(cfg.iterations as u64, &format!("fitting {}", p.display()));
        let fit = fit_sgs(&backend, &target, &cfg, |i| pb.set_position(i as u64 + 1))?;
        pb.finish_and_clear();
        let lobes: Vec<Sg<f64>> = fit
            .env
            .lobes
            .iter()
            .map(|l| Sg { axis: (rt * DVec3::from(l.axis.map(f64::from))).to_array(), lambda: l.sharpness as f64, mu: l.amplitude.map(f64::from) })
            .collect();
        let stem = p.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "env".into());
        ctx.say(format!("relight: {} fitted with {} lobes [{:.1} s]", p.display(), lobes.len(), fit.seconds));
        maps.push((stem, lobes, fit.seconds));
    }
    let scene_path = args.cameras.clone().unwrap_or_else(|| s1.run_scene.scene.clone());
    let scene = crate::scene::load(&scene_path, &ReadOptions { downscale: 1 })?;
    let mut views: Vec<&View> = scene.views_in(Split::Test).collect();
    if views.is_empty() {
        views = scene.views_in(Split::Val).collect();
    }
    if views.is_empty() {
        ctx.say("the scene has no test views: rendering its training views");
        views = scene.views.iter().collect();
    }
    if args.max_views > 0 {
        views.truncate(args.max_views);
    }
    let test = args.out.join("test");
    std::fs::create_dir_all(&test).map_err(|e| DataError::new(&test, format!("cannot create: {e}")))?;
    let refined = super::material::stage2_geometry(&s1.trainer, &s2)?;
    let sdf = refined.as_ref().unwrap_or(&s1.trainer.model);
    let tc = &s1.trainer.cfg.trace;
    let pb = ctx.progress((views.len() * (1 + maps.len())) as u64, "relight");
    let mut n = 0;
    for v in &views {
        let cam = v.camera.supersampled(ss);
        let img = render_view(&backend, sdf, tc, &s2.model, &cam, 0, None)?;
        write_view(&test.join(format!("{}.png", v.name)), &img, ss, |k| img.rgb[k], true)?;
        write_view(&test.join(format!("{}_albedo.png", v.name)), &img, ss, |k| img.albedo[k], true)?;
        write_view(&test.join(format!("{}_roughness.png", v.name)), &img, ss, |k| [img.roughness[k]; 3], false)?;
        n += 1;
        pb.set_position(n);
        for (stem, lobes, _) in &maps {
            let r = render_view(&backend, sdf, tc, &s2.model, &cam, 0, Some(lobes))?;
            write_view(&test.join(format!("{}_relit_{stem}.png", v.name)), &r, ss, |k| r.rgb[k], true)?;
            n += 1;
            pb.set_position(n);
        }
    }
    pb.finish_and_clear();
    write_latlong_exr(&s2.model.env_sgs(rotation), &args.out.join("env.exr"), 256, args.convention)?;
    let report = serde_json::json!({
        "run": run_dir.display().to_string(),
        "cameras": scene_path.display().to_string(),
        "views": views.iter().map(|v| v.name.clone()).collect::<Vec<_>>(),
        "maps": maps.iter().map(|(s, l, t)| serde_json::json!({ "name": s, "lobes": l.len(), "fit_seconds": t })).collect::<Vec<_>>(),
        "convention": args.convention,
        "samples_per_pixel": ss * ss,
        "indirect": "one bounce: a blocked lobe is replaced by the learned material at the secondary hit lit by the same map",
        "seconds": t_total.elapsed().as_secs_f64(),
    });
    crate::util::atomic_write(&args.out.join("relight_report.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    ctx.emit("relight", report);
    ctx.say(format!(
        "relight: {} views x ({} maps + learned light) in {} [{:.1} s]; score with `pii-bake eval --gt {} --pred {}`",
        views.len(),
        maps.len(),
        args.out.display(),
        t_total.elapsed().as_secs_f64(),
        scene_path.display(),
        args.out.display()
    ));
    Ok(())
}
