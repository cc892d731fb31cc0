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
//!   (sRGB), `test/<view>_roughness.png` (linear values), `test/<view>_metallic.png` (linear,
//!   where the model has a metallic channel) and `test/<view>_normal.png` (the shading normal in
//!   the scene's world frame, n·0.5 + 0.5, linear),
//! - `env.exr` (the learned environment, in `--convention`), `relight_report.json`.
//!
//! PNGs are RGBA: alpha = the rendered silhouette.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DVec3};

use super::material::{load_stage1, render_view_lit, RenderedView};
use super::stage2::{Stage2Trainer, CHECKPOINT2};
use crate::backend::{Backend, BackendError};
use crate::context::Context;
use crate::render::{trace, Rays, SdfBatch, TraceConfig};
use crate::scene::Camera;
use crate::scene::{Downscale, ReadOptions, Split, View};
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
    /// Render at 1/N of the cameras' size (`auto`: the factor the run was trained at, beyond
    /// which a render shows no more detail). Full size is the default; a smaller render is a quick
    /// look at a large capture, which `eval` scores against the ground truth filtered to its size.
    #[arg(long, default_value_t = Downscale::By(1))]
    pub downscale: Downscale,
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

/// Cycles' default pixel filter (the renderer `scripts/make_scene.py` and the Blender check use):
/// Blackman-Harris over 1.5 pixels, separable in x and y.
pub const FILTER_WIDTH: f64 = 1.5;

/// The Blackman-Harris window of total width `width` at offset `d` from its centre (0 outside).
pub fn blackman_harris(d: f64, width: f64) -> f64 {
    let x = d / width + 0.5;
    if !(0.0..=1.0).contains(&x) {
        return 0.0;
    }
    let t = std::f64::consts::TAU * x;
    (0.35875 - 0.48829 * t.cos() + 0.14128 * (2.0 * t).cos() - 0.01168 * (3.0 * t).cos()).max(0.0)
}

/// How a view rendered at `s`× the pixels per axis becomes output pixels: each pixel's alpha and
/// the rendered sub-pixels its (straight) colour averages.
///
/// Interior and background pixels take alpha from their own s×s sub-pixels. Pixels on the
/// silhouette (a 3×3 neighbourhood that is neither all covered nor all empty) take it from
/// `edge_rays`² primary rays over the pixel filter's support, weighted by it (the coverage a
/// renderer's pixel filter gives: a few sub-pixels would miss the thin slivers of surface that
/// make the soft fringe of a photo's silhouette). Their colour is the mean of their own covered
/// sub-pixels or, where none is covered, of their neighbours' (the surface the fringe shows).
pub struct Footprint {
    pub width: usize,
    pub height: usize,
    pub alpha: Vec<f32>,
    /// Per output pixel: indices into the rendered view's per-ray arrays.
    pub members: Vec<Vec<usize>>,
    /// Silhouette pixels whose alpha was traced densely.
    pub edge_pixels: usize,
}

impl Footprint {
    /// `img`: `camera` rendered at `s`× (every sub-pixel); `f`: the SDF it was traced on.
    pub fn new(f: &dyn SdfBatch, tc: &TraceConfig, camera: &Camera, img: &RenderedView, s: usize, edge_rays: usize) -> Result<Self, BackendError> {
        let (w, h) = (img.width / s, img.height / s);
        let mut own: Vec<Vec<usize>> = vec![Vec::new(); w * h];
        for (k, &p) in img.pixel_index.iter().enumerate() {
            if img.hit[k] {
                let (x, y) = (p % img.width / s, p / img.width / s);
                own[y * w + x].push(k);
            }
        }
        let covered = (s * s) as f32;
        let mut alpha: Vec<f32> = own.iter().map(|m| m.len() as f32 / covered).collect();
        let neighbours = |i: usize, r: isize| {
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            (-r..=r).flat_map(move |dy| (-r..=r).map(move |dx| (x + dx, y + dy))).filter(|&(x, y)| x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h).map(move |(x, y)| y as usize * w + x as usize)
        };
        let edge: Vec<usize> = (0..w * h)
            .filter(|&i| {
                let (mut any, mut all) = (false, true);
                for j in neighbours(i, 1) {
                    any |= alpha[j] > 0.0;
                    all &= alpha[j] >= 1.0;
                }
                any && !all
            })
            .collect();
        if edge_rays > 0 && !edge.is_empty() {
            let n = edge_rays;
            let offsets: Vec<f64> = (0..n).map(|i| ((i as f64 + 0.5) / n as f64 - 0.5) * FILTER_WIDTH).collect();
            let weights: Vec<f64> = offsets.iter().map(|&o| blackman_harris(o, FILTER_WIDTH)).collect();
            let mut rays = Rays::default();
            for &i in &edge {
                let (px, py) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
                for oy in &offsets {
                    for ox in &offsets {
                        let (o, d) = camera.ray(px + ox, py + oy);
                        rays.origins.push(o.as_vec3().to_array());
                        rays.dirs.push(d.as_vec3().to_array());
                    }
                }
            }
            let tr = trace(f, &rays, tc)?;
            for (e, &i) in edge.iter().enumerate() {
                let (mut num, mut den) = (0.0, 0.0);
                for (a, wy) in weights.iter().enumerate() {
                    for (b, wx) in weights.iter().enumerate() {
                        let wt = wx * wy;
                        den += wt;
                        if tr.hit[e * n * n + a * n + b] {
                            num += wt;
                        }
                    }
                }
                alpha[i] = if den > 0.0 { (num / den) as f32 } else { 0.0 };
            }
        }
        let mut members = own.clone();
        for &i in &edge {
            if alpha[i] > 0.0 && own[i].is_empty() {
                members[i] = neighbours(i, 1).flat_map(|j| own[j].iter().copied()).collect();
                if members[i].is_empty() {
                    alpha[i] = 0.0;
                }
            }
        }
        Ok(Self { width: w, height: h, alpha, members, edge_pixels: edge.len() })
    }

    /// Write one rendered quantity as a straight-alpha RGBA PNG.
    pub fn write(&self, path: &Path, value: impl Fn(usize) -> [f32; 3], srgb: bool) -> Result<(), DataError> {
        let mut px = vec![0.0f32; self.width * self.height * 4];
        for (i, m) in self.members.iter().enumerate() {
            if self.alpha[i] <= 0.0 || m.is_empty() {
                continue;
            }
            let o = 4 * i;
            for &k in m {
                let c = value(k);
                for ch in 0..3 {
                    px[o + ch] += c[ch].clamp(0.0, 1.0) / m.len() as f32;
                }
            }
            px[o + 3] = self.alpha[i];
        }
        crate::image_io::write_png8(path, self.width, self.height, 4, &px, srgb)
    }
}

/// Primary rays per axis for a silhouette pixel's alpha.
pub const EDGE_RAYS: usize = 8;

/// SG lobes fitted to the latlong map at `path` (`fit-env`'s fit, `lobes` of them), their axes
/// rotated by `to_frame` (a run's asset → normalised rotation), and the fit's seconds.
pub fn fit_map_lobes(backend: &Backend, path: &Path, convention: LatlongConvention, lobes: usize, to_frame: DMat3, ctx: &Context) -> anyhow::Result<(Vec<Sg<f64>>, f64)> {
    let map = read_latlong_exr(path)?;
    let target = FitTarget::from_map(&map.rgb, map.width, map.height, convention, 128);
    let cfg = FitConfig { lobes, ..Default::default() };
    let pb = ctx.progress(cfg.iterations as u64, &format!("fitting {}", path.display()));
    let fit = fit_sgs(backend, &target, &cfg, |i| pb.set_position(i as u64 + 1))?;
    pb.finish_and_clear();
    let sgs = fit
        .env
        .lobes
        .iter()
        .map(|l| Sg { axis: (to_frame * DVec3::from(l.axis.map(f64::from))).to_array(), lambda: l.sharpness as f64, mu: l.amplitude.map(f64::from) })
        .collect();
    Ok((sgs, fit.seconds))
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
        let (lobes, seconds) = fit_map_lobes(&backend, p, args.convention, args.lobes, rt, ctx)?;
        let stem = p.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "env".into());
        ctx.say(format!("relight: {} fitted with {} lobes [{seconds:.1} s]", p.display(), lobes.len()));
        maps.push((stem, lobes, seconds));
    }
    let scene_path = args.cameras.clone().unwrap_or_else(|| s1.run_scene.scene.clone());
    // The views the run left out are left out of the normalisation here too (the frame must be the run's).
    let downscale = match args.downscale {
        Downscale::Auto => s1.trainer.cfg.downscale.max(1),
        Downscale::By(n) => n.max(1),
    };
    let scene = crate::scene::load(&scene_path, &ReadOptions { downscale: Downscale::By(downscale), keep_all_views: s1.trainer.cfg.keep_all_views })?;
    let mut views: Vec<&View> = scene.views_in(Split::Test).collect();
    // A test camera the silhouette check left out of training is still one the caller asked for.
    let excluded: Vec<&View> = scene.excluded.iter().filter(|v| v.split == Split::Test).collect();
    if !excluded.is_empty() {
        let names: Vec<&str> = excluded.iter().map(|v| v.name.as_str()).collect();
        ctx.say(format!("relight: rendering test view(s) {} too, which the silhouette check left out of training (their pose or mask disagrees with the other views)", names.join(", ")));
        views.extend(excluded);
        views.sort_by(|a, b| a.name.cmp(&b.name));
    }
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
    let sdf = refined.as_ref().unwrap_or(s1.trainer.model());
    let tc = &s1.trainer.cfg.trace;
    let grid = super::stage2::secondary_grid(&backend, sdf, &s2.model.cfg)?;
    let pb = ctx.progress((views.len() * (1 + maps.len())) as u64, "relight");
    let mut n = 0;
    let mut edge_pixels = 0usize;
    // One trace of each view's camera rays serves the learned light (None) and every map.
    let lights: Vec<Option<&[Sg<f64>]>> = std::iter::once(None).chain(maps.iter().map(|(_, l, _)| Some(&l[..]))).collect();
    for v in &views {
        let cam = v.camera.supersampled(ss);
        let renders = render_view_lit(&backend, sdf, tc, &s2.model, &cam, 0, &lights)?;
        let img = &renders[0];
        let f = sdf.sdf_batch(&backend)?;
        let bounded = crate::render::grid::bounded(&f, grid.as_ref().map(|g| g.0.as_ref()))?;
        let fp = Footprint::new(bounded.as_ref().map_or(&f, |b| b), tc, &v.camera, img, ss, EDGE_RAYS)?;
        edge_pixels += fp.edge_pixels;
        fp.write(&test.join(format!("{}.png", v.name)), |k| img.rgb[k], true)?;
        fp.write(&test.join(format!("{}_albedo.png", v.name)), |k| img.albedo[k], true)?;
        fp.write(&test.join(format!("{}_roughness.png", v.name)), |k| [img.roughness[k]; 3], false)?;
        if s2.model.cfg.metallic {
            fp.write(&test.join(format!("{}_metallic.png", v.name)), |k| [img.metallic[k]; 3], false)?;
        }
        // The normalised frame is the scene's world frame translated and scaled: its normals are world normals.
        fp.write(&test.join(format!("{}_normal.png", v.name)), |k| img.normal[k].map(|c| c * 0.5 + 0.5), false)?;
        for ((stem, _, _), r) in maps.iter().zip(&renders[1..]) {
            fp.write(&test.join(format!("{}_relit_{stem}.png", v.name)), |k| r.rgb[k], true)?;
        }
        n += 1 + maps.len() as u64;
        pb.set_position(n);
    }
    pb.finish_and_clear();
    write_latlong_exr(&s2.model.env_sgs(rotation), &args.out.join("env.exr"), 256, args.convention)?;
    let report = serde_json::json!({
        "run": run_dir.display().to_string(),
        "cameras": scene_path.display().to_string(),
        "downscale": downscale,
        "views": views.iter().map(|v| v.name.clone()).collect::<Vec<_>>(),
        "maps": maps.iter().map(|(s, l, t)| serde_json::json!({ "name": s, "lobes": l.len(), "fit_seconds": t })).collect::<Vec<_>>(),
        "convention": args.convention,
        "samples_per_pixel": ss * ss,
        "pixel_filter": format!("silhouette pixels ({edge_pixels} in all): alpha from {EDGE_RAYS}x{EDGE_RAYS} rays under Blackman-Harris, {FILTER_WIDTH} px (Cycles' default)"),
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

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat4;

    #[test]
    fn blackman_harris_is_a_symmetric_window_over_its_width() {
        assert!((blackman_harris(0.0, FILTER_WIDTH) - 1.0).abs() < 1e-4);
        assert!(blackman_harris(0.75, FILTER_WIDTH) < 1e-3 && blackman_harris(0.76, FILTER_WIDTH) == 0.0);
        for d in [0.1, 0.3, 0.5, 0.7] {
            assert!((blackman_harris(d, FILTER_WIDTH) - blackman_harris(-d, FILTER_WIDTH)).abs() < 1e-12);
            assert!(blackman_harris(d, FILTER_WIDTH) < blackman_harris(d - 0.05, FILTER_WIDTH));
        }
    }

    /// A sphere of radius 0.5 seen by a pinhole camera 3 units away: with 2×2 sub-pixels the
    /// silhouette's soft fringe is lost (pixels a sliver of surface covers get no sample); the
    /// footprint's dense silhouette tracing recovers the disc's area and gives every covered pixel
    /// a colour.
    #[test]
    fn footprint_traces_the_silhouette_fringe() {
        let (w, h, s) = (24usize, 24usize, 2usize);
        let camera = Camera { width: w, height: h, fx: 40.0, fy: 40.0, cx: 12.0, cy: 12.0, distortion: None, world_from_camera: DMat4::from_translation(DVec3::new(0.0, 0.0, -3.0)) };
        let sphere = |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - 0.5).collect()) };
        let tc = TraceConfig::new(crate::render::TraceMode::Refined);
        let cam = camera.supersampled(s);
        let (rays, pixel_index) = crate::train::cli::subsampled_rays(&cam, 0);
        let tr = trace(&sphere, &rays, &tc).unwrap();
        let n = rays.len();
        let img = RenderedView { width: cam.width, height: cam.height, pixel_index, hit: tr.hit.clone(), rgb: vec![[0.5; 3]; n], albedo: vec![[0.5; 3]; n], roughness: vec![0.5; n], metallic: vec![0.0; n], normal: vec![[0.0, 0.0, 1.0]; n] };
        // The disc's area in pixels: the sphere's silhouette cone, half-angle asin(0.5 / 3).
        let r_px = 40.0 * (0.5f64 / 3.0).asin().tan();
        let area = std::f64::consts::PI * r_px * r_px;
        let coarse = Footprint::new(&sphere, &tc, &camera, &img, s, 0).unwrap();
        let fine = Footprint::new(&sphere, &tc, &camera, &img, s, 8).unwrap();
        let sum = |f: &Footprint| f.alpha.iter().map(|&a| a as f64).sum::<f64>();
        assert!(fine.edge_pixels > 20, "{}", fine.edge_pixels);
        assert!((sum(&fine) - area).abs() < 0.02 * area, "dense silhouette: {} px vs disc {area}", sum(&fine));
        let fringe = |f: &Footprint| f.alpha.iter().filter(|&&a| a > 0.0 && a < 0.25).count();
        assert!(fringe(&fine) > fringe(&coarse), "fine {} coarse {}", fringe(&fine), fringe(&coarse));
        // Every pixel with alpha has a colour to show.
        for (a, m) in fine.alpha.iter().zip(&fine.members) {
            assert_eq!(*a > 0.0, !m.is_empty());
        }
        // Written: alpha as computed, straight colour of the covered sub-pixels.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.png");
        fine.write(&path, |k| img.rgb[k], false).unwrap();
        let back = crate::image_io::read_image_linear(&path).unwrap();
        let alpha = back.alpha().unwrap();
        for (i, &a) in fine.alpha.iter().enumerate() {
            assert!((alpha[i] - a).abs() < 1.0 / 255.0 + 1e-6);
        }
    }
}
