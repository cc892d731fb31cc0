//! `pii-bake train` (stage 1: geometry), `export --run` and the trained `bake`: the command-line
//! side of [`super::stage1`] — scene → data, presets sized to the scene, the visual-hull init,
//! the loop with progress, checkpoints, Ctrl-C and `--resume`, held-out evaluation, and the
//! export of a trained run (SDF → mesh, radiance preview → textures).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context as _;
use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

use super::hull::signed_distance;
use super::preview::{asset_rotation, smooth, ViewAdapter};
use super::stage1::{scene_key, InitMode, Model, Preset, Stage1Config, StepStats, TrainData, Trainer, CHECKPOINT};
use crate::backend::gpu::KernelTime;
use crate::backend::{Backend, BackendError};
use crate::context::Context;
use crate::export::{AssetArgs, ExportReport};
use crate::mesh::field::{Aabb, MaterialField, MaterialSamples, SdfField as MeshSdf, SdfSamples};
use crate::mesh::MeshConfig;
use crate::render::{trace, Rays, TraceConfig, TraceMode};
use crate::scene::{Downscale, ReadOptions, Scene, Split, View};
use crate::util::DataError;

/// Which stage to train.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Stage {
    /// Stage 1: SDF + radiance net.
    Geometry,
    /// Stage 2 on the stage-1 run in `--out`: SG environment, material autoencoder, indirect light.
    Material,
    /// Both stages, one after the other.
    All,
}

/// Training options shared by `train` and `bake` (each command has its own `--preset`).
#[derive(Debug, Clone, clap::Args)]
pub struct TrainOptions {
    /// Sphere tracing: `refined` (threshold 1e-3 + Newton step) or `classic` (5e-5, IDR's code).
    #[arg(long, value_enum, default_value_t = TraceMode::Refined)]
    pub tracing: TraceMode,
    /// SDF initialisation: `hull` (fit to the visual hull of the masks first) or `sphere`.
    #[arg(long, value_enum, default_value_t = InitMode::Hull)]
    pub init: InitMode,
    /// Photometric iterations (default: the preset's).
    #[arg(long)]
    pub iterations: Option<u64>,
    /// Rays per iteration (default: the preset's).
    #[arg(long)]
    pub rays: Option<usize>,
    /// Seed for initialisation and ray sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write a checkpoint every N iterations (default: the preset's).
    #[arg(long)]
    pub checkpoint_every: Option<u64>,
    /// Image downscale: `auto` (full size unless the photos are larger than the model resolves:
    /// longest side over 1536 pixels or over 67 megapixels in all, `scene::auto_downscale`) or an
    /// integer factor.
    #[arg(long, default_value_t = Downscale::Auto)]
    pub downscale: Downscale,
    /// Train on every view, even one whose silhouette contradicts the others (a wrong pose or
    /// mask); by default such a view is left out and named.
    #[arg(long)]
    pub keep_all_views: bool,
    /// Keep the camera poses as read. By default stage 1 refines each training view's pose with
    /// the SDF (poses a pixel or more off, as structure from motion leaves on a hard capture,
    /// otherwise erode the surface), writes them to the run's `poses.json` and stage 2 trains
    /// through them; exact poses (rendered scenes, calibrated rigs) pay a little for it.
    #[arg(long)]
    pub fixed_poses: bool,
    /// Steps of the init's fit to the hull or to `--init-mesh` (default: the preset's, 200 for the
    /// hull, 600 for a mesh).
    #[arg(long)]
    pub init_steps: Option<u64>,
    /// Fit the SDF to this mesh (.obj/.ply, in the scene's frame: a scan or a ground-truth mesh)
    /// instead of the visual hull; add `--geometry-set lr_field=0` to keep that geometry exactly
    /// and train only the appearance (materials for an existing mesh, or stage 2 on known geometry).
    #[arg(long, value_name = "MESH")]
    pub init_mesh: Option<PathBuf>,
    /// Stage-1 setting overrides for a new run, KEY=VALUE (any field of run.json's config, e.g.
    /// `--geometry-set normal_gradient_scale=0.3`), repeatable.
    #[arg(long = "geometry-set", value_name = "KEY=VALUE")]
    pub geometry_set: Vec<String>,
}

#[derive(Debug, clap::Args)]
pub struct TrainArgs {
    /// Scene folder (transforms.json, IDR/DTU cameras_sphere.npz, LLFF poses_bounds.npy or COLMAP).
    pub scene: PathBuf,
    /// Run folder: checkpoints, run.json, loss_curve.csv, train_report.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Stage to train.
    #[arg(long, value_enum, default_value_t = Stage::Geometry)]
    pub stage: Stage,
    /// Network preset: `fast` (hash grid, CPU-friendly) or `paper` (IDR's 8×512 networks)
    /// (default: the preset of the stage-1 run in `--out` where stage 2 trains on it or a run
    /// resumes, else fast).
    #[arg(long, value_enum)]
    pub preset: Option<Preset>,
    #[command(flatten)]
    pub opts: TrainOptions,
    #[command(flatten)]
    pub material: super::material::MaterialOptions,
    /// Continue the run in `--out` from its last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Stop at this step with a checkpoint, keeping the schedule of the full run (`--resume`
    /// continues it exactly): for time-boxed sessions.
    #[arg(long)]
    pub stop_at: Option<u64>,
}

/// What `export --run` needs from a run besides its checkpoint (written to `run.json`'s side).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunScene {
    pub scene: PathBuf,
    pub format: String,
    /// World units → normalised units.
    pub scale: f64,
    /// Normalised → asset frame (column-major 3×3).
    pub rotation: [f64; 9],
    pub key: String,
}

const RUN_SCENE: &str = "scene.json";
const LOSS_CURVE: &str = "loss_curve.csv";

/// A finished stage-1 run.
pub struct Stage1Run {
    pub trainer: Trainer,
    pub run_scene: RunScene,
    pub report: serde_json::Value,
}

/// The finest grid the concavity carving runs on.
const CONCAVITY_RES: usize = 96;

/// The hull a hull-initialised stage 1 fits: the visual hull of the masks (seen by at least half
/// of the views), its concavities carved by photo-consistency (`cfg.concavity_rounds`), as a
/// smoothed signed distance grid. None when the masks leave no voxel.
pub fn hull_init_grid(views: &[&View], cfg: &Stage1Config) -> Option<(super::hull::Grid3, HullInit)> {
    let cameras: Vec<&crate::scene::Camera> = views.iter().map(|v| &v.camera).collect();
    posed_hull_init_grid(views, &cameras, cfg)
}

/// [`hull_init_grid`] with every view seen through the camera of the same index in `cameras`
/// (the poses stage 1 has refined, [`recarve_hull_from_poses`]).
pub fn posed_hull_init_grid(views: &[&View], cameras: &[&crate::scene::Camera], cfg: &Stage1Config) -> Option<(super::hull::Grid3, HullInit)> {
    let adapters: Vec<ViewAdapter> = views.iter().zip(cameras).map(|(v, c)| ViewAdapter::posed(v, c)).collect();
    let inside = super::preview::adapters_hull(&adapters, cfg.sizes.hull_resolution);
    carved_hull_grid(&adapters, inside, cfg)
}

/// The rest of [`posed_hull_init_grid`] from its visual hull `inside` (carved through
/// `adapters` at `cfg.sizes.hull_resolution`): the concavities carved, the signed distance.
fn carved_hull_grid(adapters: &[ViewAdapter], mut inside: Vec<bool>, cfg: &Stage1Config) -> Option<(super::hull::Grid3, HullInit)> {
    let res = cfg.sizes.hull_resolution;
    let visual_hull = |res: usize| super::preview::adapters_hull(adapters, res);
    if !inside.contains(&true) {
        return None;
    }
    let mut concavities = super::photo::ConcavityReport::default();
    if cfg.concavity_rounds > 0 {
        let pv: Vec<&dyn super::photo::PhotoView> = adapters.iter().map(|a| a as &dyn super::photo::PhotoView).collect();
        let cc = super::photo::ConcavityCarve { rounds: cfg.concavity_rounds, ..Default::default() };
        // On a grid of at most CONCAVITY_RES voxels a side (its cost grows with the cube of the
        // resolution); a finer hull loses the voxels whose coarse voxel was carved.
        let cres = res.min(CONCAVITY_RES);
        if cres == res {
            concavities = super::photo::carve_concavities(&pv, &mut inside, res, 1.0, &cc);
        } else {
            let coarse_hull = visual_hull(cres);
            let mut coarse = coarse_hull.clone();
            concavities = super::photo::carve_concavities(&pv, &mut coarse, cres, 1.0, &cc);
            let mut removed = 0;
            for (id, b) in inside.iter_mut().enumerate() {
                if !*b {
                    continue;
                }
                // The coarse voxel holding this voxel's centre.
                let q = |a: usize| (((2 * a + 1) * cres) / (2 * res)).min(cres - 1);
                let cid = (q(id / (res * res)) * cres + q((id / res) % res)) * cres + q(id % res);
                if coarse_hull[cid] && !coarse[cid] {
                    *b = false;
                    removed += 1;
                }
            }
            concavities.carved_voxels = removed;
        }
    }
    let voxels_inside = inside.iter().filter(|b| **b).count();
    Some((smooth(signed_distance(&inside, res, 1.0)), HullInit { voxels_inside, concavities }))
}

/// The starting rate of a trained SDF's refit to the hull carved again through refined poses,
/// as a fraction of the hull fit's: on the example under `bench train --pose-noise 0.5` the
/// preset's rate diverged (half the voxels on the wrong side) and the fit landed only when it
/// started again at a quarter of it.
const RECARVE_FIT_RATE: f32 = 0.25;

/// The least change of the plain carve, in voxels changed per voxel of its surface
/// ([`surface_change_voxels`]; a ball grown by one voxel reads 1.5), for which
/// [`recarve_hull_from_poses`] carves the hull again. Measured where a view moved by over half a
/// hull voxel: the example under `bench train --pose-noise 0.5` reads 0.92 at step 200 and gains
/// from the new hull (field Chamfer 0.419% -> 0.354%); the painted sphere with one of eight views
/// turned 2° (the test) reads 0.39, its hull 4.4% short of the true poses' in volume; the
/// Ethiopian head, whose poses refine by 0.28 px on average but one view by 3.0 px, reads 0.13,
/// and carving it again changed nothing (held-out 24.01 -> 23.99 dB, mask IoU 0.9812 -> 0.9809)
/// for 85-106 s of carving and fitting on its 192³ hull.
const RECARVE_MIN_SURFACE_CHANGE: f64 = 0.25;

/// Carve the hull again through the poses stage 1 has refined and fit the SDF to it, once, when
/// the run is due ([`Stage1Config::pose_recarve_at`] of the iterations, a hull init, poses
/// refined), the refinement has moved some view by more than half a hull voxel in its photo (less
/// cannot change the carve), and the plain carve through the refined poses differs from the one
/// through the poses as read by [`RECARVE_MIN_SURFACE_CHANGE`] or more. Misregistered poses
/// carve an eroded hull, every view's error cutting into it, and the run's start pays for it to
/// its end (figures in [`super::stage1::POSE_RECARVE_AT`]).
///
/// Returns what it decided (recorded in the trainer, so in its checkpoint) at the call that
/// decided, None at every other. `views` are the training views the trainer's data was built
/// from, in order.
pub fn recarve_hull_from_poses(backend: &Backend, trainer: &mut Trainer, views: &[&View], progress: impl FnMut(u64, f64)) -> anyhow::Result<Option<serde_json::Value>> {
    if !recarve_due(trainer) {
        return Ok(None);
    }
    let cfg = trainer.cfg.clone();
    let Some(poses) = trainer.poses() else { return Ok(None) };
    if poses.views() != views.len() {
        anyhow::bail!("stage 1: the run's pose refinement holds {} views, the scene {}", poses.views(), views.len());
    }
    let t = Instant::now();
    let footprint = cfg.sizes.pixel_footprint.max(1e-12) as f64;
    // How far each view's refined camera moves the object in its image (a turn and a shift that
    // cancel there move nothing the carve sees).
    let cameras: Vec<crate::scene::Camera> = views.iter().enumerate().map(|(k, v)| poses.camera(&v.camera, k)).collect();
    let (largest, view) = cameras
        .iter()
        .zip(views)
        .enumerate()
        .filter_map(|(k, (c, v))| super::pose::reprojection_error_px(c, &v.camera).map(|e| (e, k)))
        .fold((0.0, 0), |a, b| if b.0 > a.0 { b } else { a });
    // `hull_init_grid` carves the cube [-1, 1]³.
    let res = cfg.sizes.hull_resolution;
    let half_voxel_px = 0.5 * (2.0 / res as f64) / footprint;
    let mut rec = serde_json::json!({
        "step": trainer.step, "largest_correction_px": largest, "largest_correction_view": views.get(view).map(|v| v.name.clone()),
        "half_voxel_px": half_voxel_px, "resolution": res, "recarved": false,
    });
    if largest > half_voxel_px {
        // A view moved that far may still cut little of the hull (many views agree where it
        // would have cut): the plain carve through both poses tells, before the photo-consistency
        // carve and the fit (which on the Ethiopian head's 192³ hull take 85-106 s on 2 cores).
        let read: Vec<ViewAdapter> = views.iter().map(|v| ViewAdapter::new(v)).collect();
        let refined: Vec<ViewAdapter> = views.iter().zip(&cameras).map(|(v, c)| ViewAdapter::posed(v, c)).collect();
        let (before, after) = (super::preview::adapters_hull(&read, res), super::preview::adapters_hull(&refined, res));
        let moved = surface_change_voxels(&before, &after, res);
        rec["hull_surface_change_voxels"] = moved.into();
        if moved < RECARVE_MIN_SURFACE_CHANGE {
            rec["reason"] = format!("the carve through them changes {moved:.2} voxels per voxel of the hull's surface (under {RECARVE_MIN_SURFACE_CHANGE}): the hull kept").into();
        } else if let Some((grid, hull)) = carved_hull_grid(&refined, after, &cfg) {
            let loss = trainer.fit_to_grid_from(backend, &grid, cfg.hull_fit_steps, RECARVE_FIT_RATE * cfg.hull_fit_lr, progress)?;
            rec["recarved"] = true.into();
            rec["voxels_inside"] = hull.voxels_inside.into();
            rec["concavities"] = serde_json::to_value(&hull.concavities)?;
            rec["fit_steps"] = cfg.hull_fit_steps.into();
            rec["fit_loss"] = loss.into();
            rec["fit_rate"] = trainer.fit_rate.into();
        } else {
            rec["reason"] = "the masks seen through the refined poses leave no voxel: the hull kept".into();
        }
    }
    rec["seconds"] = t.elapsed().as_secs_f64().into();
    trainer.hull_recarve = Some(rec.clone());
    Ok(Some(rec))
}

/// How far a carve's surface moved from `before` to `after` (two carves of the same `res`³ grid),
/// in voxels on average: the voxels that changed side over the voxels on `before`'s surface
/// (inside, with a face neighbour outside or on the grid's border).
pub fn surface_change_voxels(before: &[bool], after: &[bool], res: usize) -> f64 {
    let changed = before.iter().zip(after).filter(|(a, b)| a != b).count();
    let at = |i: usize, j: usize, k: usize| before[(k * res + j) * res + i];
    let mut surface = 0usize;
    for k in 0..res {
        for j in 0..res {
            for i in 0..res {
                if !at(i, j, k) {
                    continue;
                }
                let border = [i, j, k].iter().any(|&a| a == 0 || a + 1 == res);
                if border || !at(i - 1, j, k) || !at(i + 1, j, k) || !at(i, j - 1, k) || !at(i, j + 1, k) || !at(i, j, k - 1) || !at(i, j, k + 1) {
                    surface += 1;
                }
            }
        }
    }
    if surface == 0 {
        return if changed == 0 { 0.0 } else { f64::INFINITY };
    }
    changed as f64 / surface as f64
}

/// Whether [`recarve_hull_from_poses`] has a decision to make at the trainer's step (from
/// [`Stage1Config::pose_recarve_at`] of the run on, once the poses have been updated).
pub fn recarve_due(trainer: &Trainer) -> bool {
    let cfg = &trainer.cfg;
    let at = ((cfg.pose_recarve_at as f64 * cfg.iterations as f64).round() as u64).max(1);
    cfg.init == InitMode::Hull && cfg.pose_recarve_at > 0.0 && trainer.hull_recarve.is_none() && trainer.poses().is_some_and(|p| p.steps > 0) && trainer.step >= at
}

/// A line for the progress log of what [`recarve_hull_from_poses`] decided.
pub fn recarve_line(rec: &serde_json::Value) -> String {
    let f = |k: &str| rec[k].as_f64().unwrap_or(f64::NAN);
    if rec["recarved"].as_bool() == Some(true) {
        format!(
            "stage 1: the refined poses moved {} by {:.2} px in its photo (over half a hull voxel, {:.2} px) and the carve through them changes {:.2} voxels per voxel of the hull's surface: hull carved again through them ({} voxels inside) and the SDF refitted ({} steps, loss {:.4}) [{:.1} s]",
            rec["largest_correction_view"].as_str().unwrap_or("a view"),
            f("largest_correction_px"),
            f("half_voxel_px"),
            f("hull_surface_change_voxels"),
            rec["voxels_inside"],
            rec["fit_steps"],
            f("fit_loss"),
            f("seconds")
        )
    } else {
        match rec["reason"].as_str() {
            Some(why) => format!("stage 1: the refined poses moved {} by {:.2} px in its photo, but {why}", rec["largest_correction_view"].as_str().unwrap_or("a view"), f("largest_correction_px")),
            None => format!("stage 1: the refined poses moved no view by more than half a hull voxel ({:.2} px at most, {:.2} px a half voxel): the hull stands", f("largest_correction_px"), f("half_voxel_px")),
        }
    }
}

/// What [`hull_init_grid`] built.
#[derive(Clone, Debug, Default)]
pub struct HullInit {
    pub voxels_inside: usize,
    pub concavities: super::photo::ConcavityReport,
}

pub fn train_views(scene: &Scene) -> (Vec<&View>, Vec<&View>) {
    let mut train: Vec<&View> = scene.views_in(Split::Train).collect();
    let mut held: Vec<&View> = scene.views_in(Split::Test).collect();
    if held.is_empty() {
        held = scene.views_in(Split::Val).collect();
    }
    if train.is_empty() {
        train = scene.views.iter().collect();
        held.clear();
    }
    (train, held)
}

/// `info`'s estimate of stage 1's coverage report, from the masks' visual hull and the training
/// photos (see [`super::coverage::hull_coverage`]): warns before a long bake what stage 1 would
/// flag after it.
pub fn info_coverage(scene: &Scene, ctx: &Context) -> anyhow::Result<()> {
    let (views, _) = train_views(scene);
    let t = Instant::now();
    let Some(c) = super::coverage::hull_coverage(&views)? else {
        ctx.say("coverage (est.)   - (needs a mask on every training view, and masks that leave a visual hull)");
        return Ok(());
    };
    let mut rec = c.to_json(t.elapsed().as_secs_f64());
    rec["of"] = "the masks' visual hull".into();
    rec["train_views"] = views.len().into();
    ctx.emit("coverage_estimate", rec);
    let s = c.seen_by.map(|v| 100.0 * v);
    ctx.say(format!(
        "coverage (est.)   the masks' visual hull is seen by 0 / 1 / 2 / 3+ training photos over {:.1}% / {:.1}% / {:.1}% / {:.1}% of its surface (median {})",
        s[0], s[1], s[2], s[3], c.median_views
    ));
    if let Some(w) = hull_coverage_warning(&c, views.len()) {
        ctx.say(format!("  WARNING         {w}"));
    }
    Ok(())
}

/// The warning for a visual hull that too few photos see ([`info_coverage`], and a new stage-1
/// run before it trains), or None.
fn hull_coverage_warning(c: &super::coverage::SurfaceCoverage, photos: usize) -> Option<String> {
    c.weak().then(|| {
        format!(
            "{:.0}% of the masks' visual hull is seen by fewer than three of the {photos} training photos: stage 1 will likely flag the result weak; photograph the object from more sides",
            100.0 * c.below_three()
        )
    })
}

/// Set by Ctrl-C; the loop checkpoints and stops.
pub fn interrupt_flag() -> Arc<AtomicBool> {
    static FLAG: std::sync::OnceLock<Arc<AtomicBool>> = std::sync::OnceLock::new();
    FLAG.get_or_init(|| {
        let f = Arc::new(AtomicBool::new(false));
        let g = f.clone();
        if let Err(e) = ctrlc::set_handler(move || g.store(true, Ordering::SeqCst)) {
            tracing::warn!("cannot install a Ctrl-C handler ({e}): an interrupted run loses work since its last checkpoint");
        }
        f
    })
    .clone()
}

/// The figures of a stage's training that only the invocation which trained the steps measured:
/// its per-step costs and the backend that ran them (stage 2's `step_backend`: which one it chose).
pub(crate) const PER_STEP_FIGURES: [&str; 6] = ["backend", "step_backend", "gpu_per_step", "gpu_kernels_per_step", "host_encoding_seconds_per_step", "training_thread_cpu_seconds_per_step"];

/// Make a stage's report, written by an invocation that resumed the run at `step0`, speak for the
/// whole run: `report_path` still holds the report of the invocation before (written when it
/// ended; an interrupted one writes none). Its `once` entries (made at the run's start, such as
/// the initialisation's report) and `seconds.<once_seconds>` fill those this invocation left empty.
/// Where that report ended at `step0`, the earlier steps' training time adds to this one's, so
/// `it_per_s` is the rate over every timed step (`timed_steps`), and an invocation that trained no
/// step (a finished run baked or trained again) keeps the per-step figures of the one that did,
/// instead of a rate of 0. Otherwise (steps trained by an interrupted invocation, whose time is
/// unknown) the rate is this invocation's alone.
pub(crate) fn span_the_whole_run(report: &mut serde_json::Value, report_path: &Path, step0: u64, once: &[&str], once_seconds: &[&str]) {
    use serde_json::{json, Value};
    let step = report["steps"].as_u64().unwrap_or(step0);
    let mut timed = step.saturating_sub(step0);
    // An invocation that trained no step only saved its checkpoint: no training time.
    let mut train = if timed > 0 { report["seconds"]["train"].as_f64().unwrap_or(0.0) } else { 0.0 };
    let earlier: Option<Value> = (step0 > 0).then(|| std::fs::read(report_path).ok().and_then(|b| serde_json::from_slice(&b).ok())).flatten();
    if let Some(e) = earlier.filter(|e| e["stage"] == report["stage"]) {
        for k in once {
            if report[*k].is_null() {
                report[*k] = e[*k].clone();
            }
        }
        for k in once_seconds {
            if report["seconds"][*k].as_f64().unwrap_or(0.0) == 0.0 && !e["seconds"][*k].is_null() {
                report["seconds"][*k] = e["seconds"][*k].clone();
            }
        }
        if e["steps"].as_u64() == Some(step0) {
            // A report from before `timed_steps` timed its own invocation's steps at `it_per_s`.
            let earlier_timed = e["timed_steps"].as_u64().unwrap_or_else(|| (e["it_per_s"].as_f64().unwrap_or(0.0) * e["seconds"]["train"].as_f64().unwrap_or(0.0)).round() as u64);
            timed += earlier_timed;
            train += e["seconds"]["train"].as_f64().unwrap_or(0.0);
            if step == step0 {
                for k in PER_STEP_FIGURES {
                    if let Some(v) = e.get(k) {
                        report[k] = v.clone();
                    }
                }
            }
        }
    }
    report["timed_steps"] = json!(timed);
    report["seconds"]["train"] = json!(train);
    report["it_per_s"] = json!(if train > 0.0 { timed as f64 / train } else { 0.0 });
    if step0 > 0 {
        report["resumed_at"] = json!(step0);
    }
}

/// When a training loop writes its checkpoint (and loss curve), and how it stops on Ctrl-C: one
/// rule for stage 1 and stage 2, so a killed run loses at most `every` steps and an interrupted
/// one says how to go on.
pub(crate) struct CheckpointRule {
    pub stop: Arc<AtomicBool>,
    /// Steps between checkpoints.
    pub every: u64,
    /// The step this invocation stops at (a checkpoint is written there too).
    pub end: u64,
    /// The run's whole length, for the interruption message.
    pub iterations: u64,
    /// What a step is called in the message ("step", "stage-2 step").
    pub step_name: &'static str,
    pub checkpoint: PathBuf,
    /// The command that continues the run.
    pub resume: String,
}

impl CheckpointRule {
    /// After step `step`: `save` when a checkpoint is due (the interval, the end, Ctrl-C); after
    /// Ctrl-C the progress bar is left as it is and the error names the checkpoint and `resume`.
    pub(crate) fn after_step(&self, step: u64, pb: &indicatif::ProgressBar, save: impl FnOnce() -> anyhow::Result<()>) -> anyhow::Result<()> {
        let interrupted = self.stop.load(Ordering::SeqCst);
        if step % self.every == 0 || step == self.end || interrupted {
            save()?;
        }
        if interrupted {
            pb.abandon();
            anyhow::bail!(
                "interrupted at {} {step} of {}: checkpoint written to {}; continue with `{}`",
                self.step_name,
                self.iterations,
                self.checkpoint.display(),
                self.resume
            );
        }
        Ok(())
    }
}

/// The lines of a loss-curve CSV up to step `upto` (a resumed run keeps them), read within `max_bytes`.
pub(crate) fn read_curve(path: &Path, upto: u64, max_bytes: u64) -> Vec<String> {
    crate::util::read_text_bounded(path, max_bytes)
        .map(|s| {
            s.lines()
                .skip(1)
                .filter(|l| l.split(',').next().and_then(|x| x.parse::<u64>().ok()).is_some_and(|st| st <= upto))
                .map(str::to_owned)
                .collect()
        })
        .unwrap_or_default()
}

fn curve_line(s: &StepStats, secs: f64) -> String {
    format!(
        "{},{:.6e},{:.6e},{:.6e},{:.6e},{:.3},{},{},{},{:.4e},{},{:.4},{:.6e},{:.6e}",
        s.step, s.loss, s.rgb, s.eikonal, s.mask, s.psnr, s.surface_rays, s.mask_rays, s.alpha, s.lr_field, s.applied, secs, s.smoothness, s.photo
    )
}

/// Write a loss-curve CSV (`header` line, then `lines`) atomically.
pub(crate) fn write_curve(path: &Path, header: &str, lines: &[String]) -> Result<(), DataError> {
    let mut s = format!("{header}\n");
    let columns = header.split(',').count();
    for l in lines {
        s.push_str(l);
        // A run resumed from a curve written before a column was added: its earlier lines get
        // that column empty, so every line has the header's fields.
        for _ in l.split(',').count()..columns {
            s.push(',');
        }
        s.push('\n');
    }
    crate::util::atomic_write(path, s.as_bytes())
}

const CURVE_HEADER: &str = "step,loss,rgb,eikonal,mask,psnr,surface_rays,mask_rays,alpha,lr,applied,seconds,smoothness,photo";

/// The training loop's progress bar (position, rate and ETA; the caller sets the message).
pub(crate) fn training_progress(ctx: &Context, len: u64, label: &str) -> indicatif::ProgressBar {
    let pb = ctx.progress(len, label);
    if let Ok(style) = indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {per_sec} eta {eta}") {
        pb.set_style(style.progress_chars("=> "));
    }
    pb
}

/// Every `step`-th pixel of `camera` (row-major) so that at most `max_pixels` are rendered (0 =
/// all): the rays and each one's pixel index in the full image.
pub fn subsampled_rays(camera: &crate::scene::Camera, max_pixels: usize) -> (Rays, Vec<usize>) {
    let c = camera;
    let step = if max_pixels == 0 { 1 } else { (((c.width * c.height) as f64 / max_pixels as f64).sqrt().ceil() as usize).max(1) };
    let mut rays = Rays::default();
    let mut idx = Vec::new();
    for y in (0..c.height).step_by(step) {
        for x in (0..c.width).step_by(step) {
            let (o, d) = c.ray(x as f64 + 0.5, y as f64 + 0.5);
            rays.origins.push(o.as_vec3().to_array());
            rays.dirs.push(d.as_vec3().to_array());
            idx.push(y * c.width + x);
        }
    }
    (rays, idx)
}

/// Whether pixel `p` is on the view's photo mask (no mask: every pixel).
pub fn on_mask(v: &View, p: usize) -> bool {
    v.mask.as_ref().map_or(true, |m| m[p] >= 0.5)
}

/// What the held-out PSNR in the stage-1 and stage-2 reports is computed over.
/// What a training loop's steps cost beyond their arithmetic, from a snapshot taken as the loop
/// starts: the GPU's launches, waits and traffic (`gpu_per_step`, wgpu only), the host's
/// encoding time (`host_encoding_seconds_per_step`) and the training thread's own CPU time
/// (`training_thread_cpu_seconds_per_step`: the host work that neither rayon's workers nor a
/// GPU take over, the serial glue a GPU step waits on), each as a mean per step.
pub(crate) struct StepCosts {
    gpu: Option<crate::backend::gpu::GpuCounters>,
    kernels: Vec<KernelTime>,
    encoding: f64,
    thread_cpu: Option<f64>,
}

/// [`StepCosts::per_step`].
pub(crate) struct PerStep {
    pub gpu: Option<crate::backend::gpu::GpuCounters>,
    /// Each kernel's launches and GPU time per step, the costliest first, under `--profile-kernels`.
    pub kernels: Option<Vec<KernelTime>>,
    pub encoding_seconds: f64,
    pub thread_cpu_seconds: Option<f64>,
}

impl PerStep {
    /// One line on the profiled kernels of a step (`--profile-kernels`): their GPU time in all
    /// and the costliest few, or None where nothing was profiled.
    pub(crate) fn kernel_line(&self, stage: &str) -> Option<String> {
        let k = self.kernels.as_ref()?;
        let total: f64 = k.iter().map(|k| k.seconds).sum();
        let launches: f64 = k.iter().map(|k| k.launches).sum();
        let top: Vec<String> =
            k.iter().take(6).map(|k| format!("{} {:.3} ms ({:.0}%, {:.1} launches)", k.kernel, k.seconds * 1e3, 100.0 * k.seconds / total.max(1e-30), k.launches)).collect();
        Some(format!("{stage}: GPU kernel time {:.3} ms over {launches:.1} launches per step (profiled); costliest: {}", total * 1e3, top.join(", ")))
    }
}

impl StepCosts {
    pub(crate) fn start(backend: &Backend) -> Self {
        Self {
            gpu: backend.gpu().map(|g| g.counters()),
            kernels: backend.gpu().map(|g| g.kernel_times()).unwrap_or_default(),
            encoding: crate::nn::field::host_encoding_seconds(),
            thread_cpu: crate::util::thread_cpu_seconds(),
        }
    }

    /// The means over the `steps` since [`StepCosts::start`] (on the thread that started it).
    pub(crate) fn per_step(&self, backend: &Backend, steps: u64) -> PerStep {
        let n = steps.max(1) as f64;
        let kernels = backend.gpu().map(|g| crate::backend::gpu::kernel_times_per(&g.kernel_times(), &self.kernels, steps));
        PerStep {
            gpu: self.gpu.zip(backend.gpu()).map(|(c0, g)| g.counters().per(&c0, steps)),
            kernels: kernels.filter(|k| !k.is_empty()),
            encoding_seconds: (crate::nn::field::host_encoding_seconds() - self.encoding) / n,
            thread_cpu_seconds: self.thread_cpu.zip(crate::util::thread_cpu_seconds()).map(|(a, b)| (b - a) / n),
        }
    }
}

pub const HELD_OUT_PSNR_PIXELS: &str = "covered by both the photo's mask and the render (the silhouette is scored by stage 1's mask IoU)";

/// Squared sRGB error, summed over the channels, of a rendered colour at pixel `p` of the view's
/// photo, when the pixel is on the photo's mask (no mask: every pixel).
pub fn masked_srgb_error(v: &View, p: usize, col: [f32; 3]) -> Option<f64> {
    on_mask(v, p).then(|| {
        (0..3)
            .map(|ch| {
                let gt = crate::image_io::linear_to_srgb(v.image.data[p * v.image.channels + ch].clamp(0.0, 1.0));
                ((col[ch] - gt) as f64).powi(2)
            })
            .sum()
    })
}

/// Train stage 1 on `scene_path` into `run_dir` (see the module docs).
pub fn train_stage1(
    scene_path: &Path,
    preset: Preset,
    opts: &TrainOptions,
    run_dir: &Path,
    resume: bool,
    stop_at: Option<u64>,
    backend: &Backend,
    ctx: &Context,
) -> anyhow::Result<Stage1Run> {
    let t_total = Instant::now();
    crate::export::check_writable(run_dir)?;
    // A resumed run reads the scene as its first run did (its downscale, the views it left out),
    // whatever this command's flags say: other views would not be the run's.
    let resuming = resume && run_dir.join(CHECKPOINT).is_file();
    let loaded = if resuming { Some(Trainer::load(run_dir, None)?) } else { None };
    let (downscale, keep_all_views) = match &loaded {
        Some((t, _)) => (Downscale::By(t.cfg.downscale.max(1)), t.cfg.keep_all_views),
        None => (opts.downscale, opts.keep_all_views),
    };
    // `auto` on a resumed run is whatever the run resolved it to: only a different factor given
    // by hand is worth a note.
    let asked = match opts.downscale {
        Downscale::Auto => downscale,
        given => given,
    };
    if loaded.is_some() && (downscale, keep_all_views) != (asked, opts.keep_all_views) {
        ctx.say(format!("resuming as the run started: --downscale {downscale}{}", if keep_all_views { " --keep-all-views" } else { "" }));
    }
    let scene = crate::scene::load(scene_path, &ReadOptions { downscale, keep_all_views })?;
    if let Some(note) = &scene.downscale_note {
        ctx.say(note.clone());
    }
    let (views, held) = train_views(&scene);
    if views.is_empty() {
        return Err(DataError::new(scene_path, "the scene has no views").into());
    }
    let data = TrainData::new(&views, 1.0)?;
    let key = scene_key(&scene, &views);
    let rotation = asset_rotation(&scene);
    let run_scene = RunScene {
        scene: scene_path.canonicalize().unwrap_or_else(|_| scene_path.to_path_buf()),
        format: scene.format.name().to_string(),
        scale: scene.normalisation.scale,
        rotation: rotation.to_cols_array(),
        key: key.clone(),
    };

    let mut curve: Vec<String> = Vec::new();
    let mut seconds_init = 0.0;
    let mut hull_report = serde_json::Value::Null;
    let mut mesh_report = serde_json::Value::Null;
    let mut trainer = if let Some((mut t, trained_on)) = loaded {
        super::stage1::check_scene(run_dir, &trained_on, &key)?;
        super::stage1::check_preset(&run_dir.join(CHECKPOINT), t.cfg.preset, preset)?;
        if let Some(n) = opts.iterations {
            t.cfg.iterations = n;
        }
        if !opts.geometry_set.is_empty() {
            ctx.say("resuming: --geometry-set applies to a new run; this run keeps the settings it started with".to_string());
        }
        curve = read_curve(&run_dir.join(LOSS_CURVE), t.step, 256 << 20);
        ctx.say(format!("resuming {} at step {} of {}", run_dir.display(), t.step, t.cfg.iterations));
        t
    } else {
        if resume {
            ctx.say(format!("no checkpoint in {}: starting a new run", run_dir.display()));
        }
        // Before minutes of training, what stage 1 will likely flag after them (about 0.1-1 s).
        if let Some(w) = super::coverage::hull_coverage(&views)?.and_then(|c| hull_coverage_warning(&c, views.len())) {
            ctx.say(format!("WARNING: {w}"));
        }
        let mut cfg = Stage1Config::for_scene(preset, opts.tracing, opts.init, &views, held.len(), scene.downscale);
        cfg.seed = opts.seed;
        cfg.keep_all_views = opts.keep_all_views;
        if opts.fixed_poses {
            cfg.pose_lr = 0.0;
        }
        if let Some(n) = opts.iterations {
            cfg.iterations = n;
        }
        if let Some(n) = opts.rays {
            cfg.rays = n;
        }
        if let Some(n) = opts.checkpoint_every {
            cfg.checkpoint_every = n;
        }
        if let Some(n) = opts.init_steps {
            cfg.hull_fit_steps = n;
            cfg.mesh_fit_steps = n;
        }
        if opts.init_mesh.is_some() {
            // The given mesh is the start, not a hull to carve again.
            cfg.pose_recarve_at = 0.0;
        }
        let cfg = super::stage1::apply_overrides(cfg, &opts.geometry_set)?;
        let mut t = Trainer::new(cfg.clone())?;
        if let Some(mesh_path) = &opts.init_mesh {
            let ti = Instant::now();
            // `read` refuses a mesh without faces, naming the file.
            let mut mesh = crate::eval::mesh::Mesh::read(mesh_path)?;
            for p in &mut mesh.positions {
                *p = scene.normalisation.to_normalised(*p);
            }
            let outside = mesh.positions.iter().filter(|p| p.abs().max_element() > cfg.trace.bound as f64).count();
            if outside * 10 > mesh.positions.len() {
                return Err(DataError::new(
                    mesh_path,
                    format!("{outside} of {} vertices lie outside the scene's bounding cube: the mesh is not in the scene's frame (or not this scene's)", mesh.positions.len()),
                )
                .into());
            }
            let res = cfg.sizes.mesh_resolution.clamp(96, 192);
            let grid = super::hull::mesh_signed_distance(&mesh, res, cfg.trace.bound);
            let inside = grid.data.iter().filter(|d| **d < 0.0).count();
            if inside == 0 {
                return Err(DataError::new(mesh_path, "no grid voxel lies inside the mesh (is it closed?)").into());
            }
            let pb = ctx.progress(cfg.mesh_fit_steps, "mesh init");
            let err = t.fit_to_grid(backend, &grid, cfg.mesh_fit_steps, |s, _| pb.set_position(s + 1))?;
            pb.finish_and_clear();
            seconds_init = ti.elapsed().as_secs_f64();
            mesh_report = serde_json::json!({ "mesh": mesh_path.display().to_string(), "triangles": mesh.triangles.len(), "resolution": res, "voxels_inside": inside, "fit_steps": cfg.mesh_fit_steps, "fit_loss": err, "fit_rate": t.fit_rate, "seconds": seconds_init });
            ctx.say(format!("mesh init: {} ({} triangles) as a {res}^3 signed distance, {} fit steps, loss {err:.5} [{seconds_init:.1} s]", mesh_path.display(), mesh.triangles.len(), cfg.mesh_fit_steps));
        } else if cfg.init == InitMode::Hull {
            let ti = Instant::now();
            if views.iter().any(|v| v.mask.is_none()) {
                anyhow::bail!("the hull init needs masks");
            }
            let res = cfg.sizes.hull_resolution;
            let Some((grid, hull)) = hull_init_grid(&views, &cfg) else {
                return Err(DataError::new(scene_path, "the masks carve away every voxel of the unit cube: the cameras and masks do not agree on an object (check poses and masks)").into());
            };
            if hull.concavities.carved_voxels > 0 {
                ctx.say(format!(
                    "hull init: photo-consistency carved {} voxels of concavities the masks cannot see ({} of {} rays found a deeper consistent surface, {} rounds)",
                    hull.concavities.carved_voxels, hull.concavities.deeper_rays, hull.concavities.rays, hull.concavities.rounds
                ));
            }
            let n_in = hull.voxels_inside;
            let pb = ctx.progress(cfg.hull_fit_steps, "hull init");
            let err = t.fit_to_grid(backend, &grid, cfg.hull_fit_steps, |s, _| pb.set_position(s + 1))?;
            pb.finish_and_clear();
            seconds_init = ti.elapsed().as_secs_f64();
            hull_report = serde_json::json!({ "resolution": res, "voxels_inside": n_in, "concavities": hull.concavities, "fit_steps": cfg.hull_fit_steps, "fit_loss": err, "fit_rate": t.fit_rate, "seconds": seconds_init });
            ctx.say(format!("hull init: {res}^3 hull, {} fit steps, loss {err:.4} [{seconds_init:.1} s]", cfg.hull_fit_steps));
        }
        t
    };
    crate::util::atomic_write(&run_dir.join(RUN_SCENE), serde_json::to_string_pretty(&run_scene)?.as_bytes())?;
    let cfg = trainer.cfg.clone();
    ctx.say(format!(
        "stage 1 ({} preset, {} tracing, {} init) on {}: {} views, {} pixels, {} rays x {} iterations{}; sizes from the scene: pixel footprint {:.4}, hash grid finest {} (2^{} table), mesh {} nodes",
        cfg.preset.name(),
        cfg.trace.mode.name(),
        if opts.init_mesh.is_some() && !resuming { "mesh" } else { match cfg.init { InitMode::Hull => "hull", InitMode::Sphere => "sphere" } },
        scene_path.display(),
        views.len(),
        data.pixels(),
        cfg.rays,
        cfg.iterations,
        if cfg.preset == Preset::Fast && cfg.iterations == super::stage1::fast_iterations(cfg.sizes.train_pixels, cfg.rays) {
            format!(" (from the pixels: one pass of the rays over them, kept within {}..{})", super::stage1::FAST_MIN_ITERATIONS, super::stage1::FAST_MAX_ITERATIONS)
        } else {
            String::new()
        },
        cfg.sizes.pixel_footprint,
        cfg.sizes.grid_finest,
        cfg.sizes.grid_log2_table,
        cfg.sizes.mesh_resolution
    ));

    let pb = training_progress(ctx, cfg.iterations, "stage 1");
    pb.set_position(trainer.step);
    let t_loop = Instant::now();
    let step0 = trainer.step;
    let costs = StepCosts::start(backend);
    let mut last = StepStats::default();
    let end = stop_at.unwrap_or(cfg.iterations).min(cfg.iterations);
    let rule = CheckpointRule {
        stop: interrupt_flag(),
        every: cfg.checkpoint_every,
        end,
        iterations: cfg.iterations,
        step_name: "step",
        checkpoint: run_dir.join(CHECKPOINT),
        resume: format!("pii-bake train {} --out {} --resume", scene_path.display(), run_dir.display()),
    };
    let save = |trainer: &mut Trainer, curve: &[String]| -> anyhow::Result<()> {
        trainer.save(run_dir, &key)?;
        write_curve(&run_dir.join(LOSS_CURVE), CURVE_HEADER, curve)?;
        Ok(())
    };
    while trainer.step < end {
        let ts = Instant::now();
        let s = trainer.train_step(backend, &data)?;
        if recarve_due(&trainer) {
            let n = cfg.hull_fit_steps;
            if let Some(rec) = recarve_hull_from_poses(backend, &mut trainer, &views, |k, _| pb.set_message(format!("refitting the SDF to the hull carved through the refined poses: {}/{n}", k + 1)))? {
                ctx.say(recarve_line(&rec));
            }
        }
        curve.push(curve_line(&s, ts.elapsed().as_secs_f64()));
        let its = (trainer.step - step0) as f64 / t_loop.elapsed().as_secs_f64().max(1e-9);
        pb.set_position(trainer.step);
        let smooth = if cfg.smoothness_weight > 0.0 { format!(" smooth {:.4}", s.smoothness) } else { String::new() };
        let photo = if cfg.photo_consistency > 0.0 { format!(" photo {:.4}", s.photo) } else { String::new() };
        if s.radiance_warmup {
            pb.set_message(format!("loss {:.4} (rgb; radiance warm-up, the SDF held) psnr {:.1} {:.2} it/s", s.loss, s.psnr, its));
        } else {
            pb.set_message(format!("loss {:.4} (rgb {:.4} eik {:.4} mask {:.4}{smooth}{photo}) psnr {:.1} {:.2} it/s", s.loss, s.rgb, s.eikonal, s.mask, s.psnr, its));
        }
        ctx.emit("progress", serde_json::json!({ "stage": "geometry", "iterations": cfg.iterations, "it_per_s": its, "skipped": trainer.skipped, "stats": s }));
        last = s;
        rule.after_step(trainer.step, &pb, || save(&mut trainer, &curve))?;
    }
    pb.finish_and_clear();
    if trainer.step == step0 {
        save(&mut trainer, &curve)?;
    }
    let seconds_train = t_loop.elapsed().as_secs_f64();
    let its = (trainer.step - step0) as f64 / seconds_train.max(1e-9);

    // The training steps' costs, before the evaluation's renders add theirs.
    let per_step = costs.per_step(backend, trainer.step - step0);
    // Held-out views (or, without them, a few training views), rendered at a bounded size.
    let t_eval = Instant::now();
    let mut eval_views: Vec<&View> = if held.is_empty() { views.iter().step_by((views.len() / 4).max(1)).take(4).copied().collect() } else { held.iter().take(8).copied().collect() };
    // Training views are seen through their refined poses, where the run refines them.
    let refined_eval: Vec<View> = match trainer.poses() {
        Some(p) if held.is_empty() => eval_views
            .iter()
            .map(|v| {
                let k = views.iter().position(|w| std::ptr::eq(*w, *v)).unwrap_or(0);
                View { camera: p.camera(&v.camera, k), ..(*v).clone() }
            })
            .collect(),
        _ => Vec::new(),
    };
    if !refined_eval.is_empty() {
        eval_views = refined_eval.iter().collect();
    }
    trainer.sync_host()?;
    let ev = evaluate_views(backend, trainer.model(), &cfg.trace, &eval_views, 128 * 128)?;
    // How many training photos see each part of the surface, on the grid stage 2 marches on (a
    // bake or `--stage all` hands it to stage 2: `Model::share_sdf_grid`).
    let t_cov = Instant::now();
    let (grid, _) = trainer.model().sdf_grid(backend, super::material::secondary_grid_nodes(&cfg.sizes))?;
    // The cameras as refined where the run refines them (written beside the checkpoint for
    // stage 2), else as read.
    let refined: Vec<crate::scene::Camera> = match trainer.poses() {
        Some(p) => views.iter().enumerate().map(|(v, view)| p.camera(&view.camera, v)).collect(),
        None => views.iter().map(|v| v.camera.clone()).collect(),
    };
    let pose_report = match trainer.poses() {
        Some(p) => Some(super::pose::write_poses(run_dir, p, &views, &refined, cfg.sizes.pixel_footprint, &Trainer::view_distances(&data))?),
        None => None,
    };
    let cameras: Vec<&crate::scene::Camera> = refined.iter().collect();
    let coverage = super::coverage::surface_coverage(&grid, &cameras)?;
    let mut flags: Vec<String> = Vec::new();
    if ev.mask_iou < 0.8 {
        let poses = if trainer.poses().is_some() { "poses" } else { "poses (without --fixed-poses, stage 1 corrects poses a few pixels off)" };
        flags.push(format!("mask IoU {:.3} < 0.8: check masks, {poses} and view count", ev.mask_iou));
    }
    if trainer.skipped * 10 > trainer.step.max(1) {
        flags.push(format!("{} of {} steps skipped for non-finite gradients", trainer.skipped, trainer.step));
    }
    if coverage.weak() {
        flags.push(format!(
            "{:.0}% of the surface is seen by fewer than three training photos ({} photos): its shape and material there rest on too few views; photograph it from more sides",
            100.0 * coverage.below_three(),
            views.len()
        ));
    }
    let weak = !flags.is_empty();
    let mut report = serde_json::json!({
        "stage": "geometry",
        "preset": cfg.preset,
        "tracing": cfg.trace.mode,
        "init": cfg.init,
        "backend": backend.describe(),
        "scene": { "path": scene_path.display().to_string(), "format": scene.format.name(), "train_views": views.len(), "held_out_views": held.len(), "key": key, "silhouettes": scene.silhouettes },
        "sizes": cfg.sizes,
        "config": cfg,
        "steps": trainer.step,
        "skipped_steps": trainer.skipped,
        "last": last,
        "it_per_s": its,
        "gpu_per_step": per_step.gpu,
        "gpu_kernels_per_step": per_step.kernels,
        "host_encoding_seconds_per_step": per_step.encoding_seconds,
        "training_thread_cpu_seconds_per_step": per_step.thread_cpu_seconds,
        "hull_init": hull_report,
        "mesh_init": mesh_report,
        "pose_refinement": pose_report,
        "hull_recarve": trainer.hull_recarve,
        "eval": { "views": if held.is_empty() { "training views (the scene has no held-out split)" } else { "held-out views" }, "psnr_pixels": HELD_OUT_PSNR_PIXELS, "psnr": ev.psnr, "mask_iou": ev.mask_iou, "per_view": ev.per_view, "seconds": t_eval.elapsed().as_secs_f64() },
        "coverage": coverage.to_json(t_cov.elapsed().as_secs_f64()),
        "flags": flags,
        "weak_result": weak,
        "seconds": { "init": seconds_init, "train": seconds_train, "total": t_total.elapsed().as_secs_f64() },
    });
    span_the_whole_run(&mut report, &run_dir.join("train_report.json"), step0, &["hull_init", "mesh_init"], &["init"]);
    let its = report["it_per_s"].as_f64().unwrap_or(its);
    crate::util::atomic_write(&run_dir.join("train_report.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    if let Some(line) = per_step.kernel_line("stage 1") {
        ctx.say(line);
    }
    ctx.say(format!(
        "stage 1: {} steps ({} skipped) at {:.2} it/s; {}: PSNR {:.2} dB, mask IoU {:.3}{}",
        trainer.step,
        trainer.skipped,
        its,
        if held.is_empty() { "training views" } else { "held-out views" },
        ev.psnr,
        ev.mask_iou,
        if weak { format!(" — WEAK RESULT: {}", flags.join("; ")) } else { String::new() }
    ));
    if let Some(p) = &pose_report {
        ctx.say(format!(
            "stage 1: camera poses refined ({} views): mean correction {:.3}° and {:.2} px of shift (max {:.3}° / {:.2} px), in {}",
            p["views"], p["mean_rotation_deg"].as_f64().unwrap_or(0.0), p["mean_translation_px"].as_f64().unwrap_or(0.0), p["max_rotation_deg"].as_f64().unwrap_or(0.0), p["max_translation_px"].as_f64().unwrap_or(0.0), super::pose::POSES
        ));
    }
    ctx.say(format!(
        "stage 1: surface seen by 0 / 1 / 2 / 3+ training photos: {:.0}% / {:.0}% / {:.0}% / {:.0}% (median {})",
        100.0 * coverage.seen_by[0],
        100.0 * coverage.seen_by[1],
        100.0 * coverage.seen_by[2],
        100.0 * coverage.seen_by[3],
        coverage.median_views
    ));
    Ok(Stage1Run { trainer, run_scene, report })
}

/// Held-out metrics of a stage-1 model.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ViewEval {
    pub psnr: f64,
    pub mask_iou: f64,
    pub per_view: Vec<serde_json::Value>,
}

/// PSNR of a squared error summed over `weight` channel samples; 0 dB when no pixel is covered by
/// both the photo and the render (nothing of the object is where the photo shows it).
pub fn covered_psnr(squared_error: f64, weight: f64) -> f64 {
    if weight > 0.0 {
        crate::eval::psnr_from_mse(squared_error / weight)
    } else {
        0.0
    }
}

/// Render `views` (each downscaled to at most `max_pixels`) and compare with their photos: PSNR
/// (sRGB) over the pixels that both the photo's mask and the render cover, and IoU of the hit mask
/// against the photo's mask. The silhouette is scored by the IoU alone: one ray per pixel centre
/// against a 0.5 mask threshold makes a sub-pixel shift of the outline swing a PSNR that counted
/// its fringe by several dB (example: −3 dB on a view whose `eval` novel-view PSNR rose 0.7 dB).
pub fn evaluate_views(backend: &Backend, model: &Model, tc: &TraceConfig, views: &[&View], max_pixels: usize) -> Result<ViewEval, BackendError> {
    let mut out = ViewEval::default();
    let (mut se, mut w, mut inter, mut uni) = (0.0f64, 0.0f64, 0usize, 0usize);
    for v in views {
        let (rays, idx) = subsampled_rays(&v.camera, max_pixels);
        let img = render_rays(backend, model, tc, &rays)?;
        let (mut vse, mut vw, mut vi, mut vu) = (0.0f64, 0.0f64, 0usize, 0usize);
        for (k, &p) in idx.iter().enumerate() {
            let (hit, col) = img[k];
            let inm = on_mask(v, p);
            if let Some(e) = hit.then(|| masked_srgb_error(v, p, col)).flatten() {
                vse += e;
                vw += 3.0;
            }
            vi += (hit && inm) as usize;
            vu += (hit || inm) as usize;
        }
        let psnr = covered_psnr(vse, vw);
        let iou = vi as f64 / vu.max(1) as f64;
        out.per_view.push(serde_json::json!({ "view": v.name, "psnr": psnr, "mask_iou": iou, "pixels": idx.len() }));
        se += vse;
        w += vw;
        inter += vi;
        uni += vu;
    }
    out.psnr = covered_psnr(se, w);
    out.mask_iou = inter as f64 / uni.max(1) as f64;
    Ok(out)
}

/// Trace and shade rays: (hit, sRGB colour) per ray, in chunks.
pub fn render_rays(backend: &Backend, model: &Model, tc: &TraceConfig, rays: &Rays) -> Result<Vec<(bool, [f32; 3])>, BackendError> {
    let mut out = Vec::with_capacity(rays.len());
    let chunk = 8192;
    let f = model.sdf_batch(backend)?;
    for start in (0..rays.len()).step_by(chunk) {
        let end = (start + chunk).min(rays.len());
        let r = Rays { origins: rays.origins[start..end].to_vec(), dirs: rays.dirs[start..end].to_vec() };
        let tr = trace(&f, &r, tc)?;
        let hits: Vec<usize> = (0..r.len()).filter(|&i| tr.hit[i]).collect();
        let x: Vec<[f32; 3]> = hits.iter().map(|&i| tr.points[i]).collect();
        let d: Vec<[f32; 3]> = hits.iter().map(|&i| r.dirs[i]).collect();
        let c = model.colour(backend, &x, &d)?;
        let mut res = vec![(false, [0.0f32; 3]); r.len()];
        for (k, &i) in hits.iter().enumerate() {
            res[i] = (true, c[k]);
        }
        out.extend(res);
    }
    Ok(out)
}

/// The preset of the stage-1 run in `run_dir` (its `run.json`), if there is one to read.
pub fn run_preset(run_dir: &Path) -> Option<Preset> {
    let v = crate::util::read_json_value(&run_dir.join(super::stage1::RUN_CONFIG)).ok()?;
    serde_json::from_value(v.get("config")?.get("preset")?.clone()).ok()
}

impl TrainArgs {
    /// Flags that would be silently ignored: `--stage material` trains no stage-1 step, so
    /// `--iterations` and `--rays` (stage 1's) say nothing to it; stage 2 takes
    /// `--material-iterations` and `--material-batch`. A usage error (exit 2), checked before
    /// anything runs.
    pub fn usage_problem(&self) -> Option<String> {
        if self.stage != Stage::Material {
            return None;
        }
        let given: Vec<&str> = [(self.opts.iterations.is_some(), "--iterations"), (self.opts.rays.is_some(), "--rays")]
            .into_iter()
            .filter_map(|(g, f)| g.then_some(f))
            .collect();
        (!given.is_empty()).then(|| {
            format!(
                "{} {} stage 1's steps and `--stage material` trains only stage 2: use --material-iterations / --material-batch",
                given.join(" and "),
                if given.len() == 1 { "sets" } else { "set" }
            )
        })
    }
}

pub fn run(args: &TrainArgs, ctx: &Context) -> anyhow::Result<()> {
    let backend = ctx.backend()?;
    // Stage 2 and a resumed run follow the run's preset unless `--preset` says otherwise (then
    // a mismatch is an error naming the checkpoint).
    let follows_run = args.resume || args.stage != Stage::Geometry;
    let preset = args.preset.or_else(|| follows_run.then(|| run_preset(&args.out)).flatten()).unwrap_or(Preset::Fast);
    match args.stage {
        Stage::Geometry => {
            let r = train_stage1(&args.scene, preset, &args.opts, &args.out, args.resume, args.stop_at, &backend, ctx)?;
            ctx.emit("train", r.report);
        }
        Stage::Material => {
            let r = super::material::train_stage2(&args.scene, preset, &args.material, args.opts.seed, &args.out, args.resume, args.stop_at, None, &backend, ctx)?;
            ctx.emit("train", r.report);
        }
        Stage::All => {
            let r1 = train_stage1(&args.scene, preset, &args.opts, &args.out, true, None, &backend, ctx)?;
            ctx.emit("train", r1.report.clone());
            let r = super::material::train_stage2(&args.scene, preset, &args.material, args.opts.seed, &args.out, args.resume, args.stop_at, Some(r1.trainer.model()), &backend, ctx)?;
            ctx.emit("train", r.report);
        }
    }
    ctx.say(format!("run written to {} (export it with `pii-bake export --run {} --out <asset-dir>`)", args.out.display(), args.out.display()));
    Ok(())
}

// ---- export of a trained run --------------------------------------------------------------

fn rot(m: &DMat3, v: [f32; 3]) -> [f32; 3] {
    (*m * DVec3::from(v.map(f64::from))).as_vec3().to_array()
}

/// The simplification error bound of a trained mesh, in cells of the scene's mesh grid (about
/// 0.2 pixel footprints at the scene-derived resolution). Chosen by what the shipped mesh keeps of
/// the field's accuracy, `bench train --asset-bound-cells 0.5 0.25 0.125` (cpu, 2000 iterations,
/// 96^3, Chamfer / NC of the simplified mesh against the field's 0.169% / 0.984 on the example and
/// 0.249% / 0.974 on glossy): 0.5 cells (the analytic exports' bound) 0.235% / 0.971 and 0.312% /
/// 0.968 at 1.4k / 3.7k triangles; 0.25 cells 0.189% / 0.977 and 0.268% / 0.971; 0.125 cells
/// 0.174% / 0.980 and 0.254% / 0.972 at 3.7k / 6.8k triangles. A 160^3 grid adds 50% more
/// triangles for 0.002% of Chamfer.
pub const TRAINED_BOUND_CELLS: f32 = 0.125;

/// How `export` meshes a trained SDF: the scene's resolution and [`TRAINED_BOUND_CELLS`] unless
/// the asset flags say otherwise.
pub fn trained_mesh_config(sizes: &super::stage1::SceneSizes, resolution: Option<usize>, error_bound: Option<f32>) -> MeshConfig {
    MeshConfig { resolution: resolution.unwrap_or(sizes.mesh_resolution), error_bound, bound_cells: TRAINED_BOUND_CELLS, ..Default::default() }
}

/// The trained SDF as the asset back end's field, in the asset frame.
pub struct TrainedSdf<'a> {
    pub model: &'a Model,
    pub rotation: DMat3,
    pub bounds: Aabb,
}

impl<'a> TrainedSdf<'a> {
    /// Wrap `model`; the mesh box is the box of the inside nodes of a coarse grid, plus a margin.
    pub fn new(backend: &Backend, model: &'a Model, rotation: DMat3) -> Result<Self, BackendError> {
        let res = 64usize;
        let h = 2.0 / res as f32;
        let mut pts = Vec::with_capacity(res * res * res * 3);
        for k in 0..res {
            for j in 0..res {
                for i in 0..res {
                    pts.extend([-1.0 + (i as f32 + 0.5) * h, -1.0 + (j as f32 + 0.5) * h, -1.0 + (k as f32 + 0.5) * h]);
                }
            }
        }
        let v = model.sdf(backend, &pts)?;
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for (n, &s) in v.iter().enumerate() {
            if s < 0.0 {
                for a in 0..3 {
                    lo[a] = lo[a].min(pts[3 * n + a]);
                    hi[a] = hi[a].max(pts[3 * n + a]);
                }
            }
        }
        if !lo[0].is_finite() {
            return Err(BackendError::Config("the trained SDF has no inside anywhere in the unit cube (an empty model)".into()));
        }
        let margin = 2.0 * h;
        let (mut blo, mut bhi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for corner in 0..8 {
            let p = [0, 1, 2].map(|a| if corner >> a & 1 == 1 { (hi[a] + margin).min(1.05) } else { (lo[a] - margin).max(-1.05) });
            let q = rot(&rotation, p);
            for a in 0..3 {
                blo[a] = blo[a].min(q[a]);
                bhi[a] = bhi[a].max(q[a]);
            }
        }
        Ok(Self { model, rotation, bounds: Aabb { min: blo, max: bhi } })
    }
}

impl MeshSdf for TrainedSdf<'_> {
    fn name(&self) -> String {
        format!("trained SDF ({} preset, {} parameters)", if self.model.field.config.weight_norm { "paper" } else { "fast" }, self.model.sdf_params.len())
    }
    fn bounds(&self) -> Aabb {
        self.bounds
    }
    fn eval(&self, backend: &Backend, points: &[[f32; 3]]) -> Result<SdfSamples, BackendError> {
        let rt = self.rotation.transpose();
        let local: Vec<[f32; 3]> = points.iter().map(|&q| rot(&rt, q)).collect();
        let mut values = Vec::with_capacity(points.len());
        let mut gradients = Vec::with_capacity(points.len());
        for c in local.chunks(1 << 14) {
            let o = self.model.field.eval_with_gradient(backend, &self.model.sdf_params, bytemuck::cast_slice(c))?;
            values.extend(o.sdf);
            gradients.extend(o.gradient.chunks_exact(3).map(|g| rot(&self.rotation, [g[0], g[1], g[2]])));
        }
        Ok(SdfSamples { values, gradients })
    }
    fn eval_grid(&self, backend: &Backend, grid: &crate::mesh::grid::GridSpec) -> Result<Vec<f32>, BackendError> {
        let [nx, ny, nz] = grid.dims;
        let rt = self.rotation.transpose();
        let mut pts = Vec::with_capacity(nx * ny * nz * 3);
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    pts.extend(rot(&rt, grid.node(x, y, z)));
                }
            }
        }
        self.model.sdf(backend, &pts)
    }
}

/// The radiance net seen head-on (view direction = the normal), sRGB → linear: a *radiance
/// preview* with the photos' lighting baked in; roughness constant. Stage 2 replaces it.
pub struct RadiancePreview<'a> {
    pub model: &'a Model,
    pub rotation: DMat3,
    pub roughness: f32,
    pub feature: f32,
}

impl MaterialField for RadiancePreview<'_> {
    fn name(&self) -> String {
        format!("radiance preview (stage-1 radiance net seen along the normal: lighting baked in), constant roughness {}", self.roughness)
    }
    fn eval(&self, backend: &Backend, points: &[[f32; 3]], normals: &[[f32; 3]]) -> Result<MaterialSamples, BackendError> {
        let rt = self.rotation.transpose();
        let x: Vec<[f32; 3]> = points.iter().map(|&q| rot(&rt, q)).collect();
        // The radiance net's view input is −ray direction: looking along −n sees the point head-on.
        let d: Vec<[f32; 3]> = normals.iter().map(|&n| rot(&rt, [-n[0], -n[1], -n[2]])).collect();
        let mut albedo = Vec::with_capacity(points.len());
        for (xc, dc) in x.chunks(1 << 14).zip(d.chunks(1 << 14)) {
            let c = self.model.colour(backend, xc, dc)?;
            albedo.extend(c.into_iter().map(|c| c.map(|v| crate::image_io::srgb_to_linear(v.clamp(0.0, 1.0)))));
        }
        Ok(MaterialSamples { albedo, roughness: vec![self.roughness; points.len()], metallic: Vec::new() })
    }
    fn feature_size(&self) -> Option<f32> {
        Some(self.feature)
    }
}

/// Read a run folder's scene record.
pub fn read_run_scene(run_dir: &Path) -> Result<RunScene, DataError> {
    let p = run_dir.join(RUN_SCENE);
    if !p.is_file() {
        return Err(DataError::new(&p, "no run scene record here (is this a `pii-bake train` run folder?)"));
    }
    let v = crate::util::read_json_value(&p)?;
    let rs: RunScene = serde_json::from_value(v).map_err(|e| DataError::new(&p, format!("not a run scene record: {e}")))?;
    if !(rs.scale.is_finite() && rs.scale > 0.0) {
        return Err(DataError::new(&p, format!("scale {} must be a positive number", rs.scale)));
    }
    let m = DMat3::from_cols_array(&rs.rotation);
    let orthonormal = rs.rotation.iter().all(|v| v.is_finite()) && (m * m.transpose() - DMat3::IDENTITY).to_cols_array().iter().all(|v| v.abs() < 1e-6);
    if !orthonormal || (m.determinant() - 1.0).abs() > 1e-6 {
        return Err(DataError::new(&p, "rotation is not a rotation matrix"));
    }
    Ok(rs)
}

/// Export a trained stage-1 model through `export_asset`.
pub fn export_stage1(backend: &Backend, trainer: &Trainer, rs: &RunScene, asset: &AssetArgs, default_name: &str, ctx: &Context) -> anyhow::Result<ExportReport> {
    let rotation = DMat3::from_cols_array(&rs.rotation);
    let cfg = &trainer.cfg;
    let sdf = TrainedSdf::new(backend, trainer.model(), rotation).context("meshing the trained SDF")?;
    let material = RadiancePreview { model: trainer.model(), rotation, roughness: 0.5, feature: 16.0 * cfg.sizes.pixel_footprint };
    let mesh = MeshConfig { face_tolerance_deg: asset.face_tolerance_deg(), ..trained_mesh_config(&cfg.sizes, asset.resolution, asset.error_bound) };
    let provenance = serde_json::json!({
        "method": "stage 1 (trained SDF + radiance preview); light/material not yet separated",
        "scene": rs.scene.display().to_string(),
        "format": rs.format,
        "preset": cfg.preset,
        "tracing": cfg.trace.mode,
        "steps": trainer.step,
    });
    let ecfg = asset.capture_export_config(rs.scale, mesh, default_name, provenance, ctx);
    let env = super::preview::uniform_environment();
    let t = Instant::now();
    let report = crate::export::export_asset_with(backend, &sdf, &material, Some(&env), &ecfg, &asset.out, &ctx.spinner("export"))?;
    ctx.say(format!(
        "export: {} triangles (error bound {:.4} normalised units, watertight {}), {} UV charts, {}² textures, files in {} [{:.2} s]",
        report.mesh.triangles,
        report.mesh.error_bound,
        report.mesh.watertight,
        report.uv_charts,
        report.texture_size,
        asset.out.display(),
        t.elapsed().as_secs_f64()
    ));
    Ok(report)
}

/// `export --run`: load the run's checkpoint and export it.
pub fn export_run(run_dir: &Path, asset: &AssetArgs, ctx: &Context) -> anyhow::Result<ExportReport> {
    crate::export::check_writable(&asset.out)?;
    let rs = read_run_scene(run_dir)?;
    let (trainer, key) = Trainer::load(run_dir, None)?;
    if key != rs.key {
        return Err(DataError::new(&run_dir.join(CHECKPOINT), format!("checkpoint scene {key} does not match the run's scene record {}", rs.key)).into());
    }
    let backend = ctx.backend()?;
    let name = crate::train::preview::name_from_path(&rs.scene);
    if run_dir.join(super::stage2::CHECKPOINT2).is_file() {
        let (s2, _, _) = super::stage2::Stage2Trainer::load(run_dir, Some(&rs.key))?;
        return super::material::export_stage2(&backend, &trainer, &s2, &rs, asset, &name, ctx);
    }
    ctx.say("this run has no stage-2 checkpoint: exporting the stage-1 radiance preview (lighting baked in)");
    export_stage1(&backend, &trainer, &rs, asset, &name, ctx)
}

/// `bake` with a training preset: stage 1 and stage 2 into the run folder (resuming what is
/// there), then the export, the ground-truth comparison when the scene has one, and
/// `bake_report.json`. `--geometry-only` stops after stage 1 and ships its radiance preview.
pub fn bake_trained(args: &super::preview::BakeArgs, ctx: &Context) -> anyhow::Result<()> {
    let t_total = Instant::now();
    let backend = ctx.backend()?;
    let preset = match args.preset {
        super::preview::BakePreset::Paper => Preset::Paper,
        _ => Preset::Fast,
    };
    if !(0.0..=1.0).contains(&args.preview_roughness) {
        anyhow::bail!("--preview-roughness must be in [0, 1], got {}", args.preview_roughness);
    }
    crate::export::check_writable(&args.asset.out)?;
    let run_dir = args.run.clone().unwrap_or_else(|| args.asset.out.join("run"));
    ctx.say(format!(
        "bake ({} preset): stage 1 (trained SDF geometry){}",
        preset.name(),
        if args.geometry_only { " only, with a radiance preview for textures (lighting baked in)" } else { " + stage 2 (SG environment, material, indirect light) + export" }
    ));
    let t1 = Instant::now();
    let run = train_stage1(&args.scene, preset, &args.train, &run_dir, true, None, &backend, ctx)?;
    let seconds_stage1 = t1.elapsed().as_secs_f64();
    let name = args.asset.name.clone().unwrap_or_else(|| super::preview::name_from_path(&args.scene));
    let mut stage2_report = serde_json::Value::Null;
    let mut seconds_stage2 = 0.0;
    let stage2 = if args.geometry_only {
        None
    } else {
        let t2 = Instant::now();
        let r2 = super::material::train_stage2(&args.scene, preset, &args.material, args.train.seed, &run_dir, true, None, Some(run.trainer.model()), &backend, ctx)?;
        seconds_stage2 = t2.elapsed().as_secs_f64();
        stage2_report = r2.report.clone();
        Some(r2.trainer)
    };
    let t = Instant::now();
    let report = match &stage2 {
        None => export_stage1(&backend, &run.trainer, &run.run_scene, &args.asset, &name, ctx)?,
        Some(s2) => super::material::export_stage2(&backend, &run.trainer, s2, &run.run_scene, &args.asset, &name, ctx)?,
    };
    let seconds_export = t.elapsed().as_secs_f64();
    // Read as the run was (a resumed bake keeps the flags it started with): its views, its frame.
    let mut scene = crate::scene::load(&args.scene, &ReadOptions { downscale: Downscale::By(run.trainer.cfg.downscale.max(1)), keep_all_views: run.trainer.cfg.keep_all_views })?;
    // A check on training views (a scene without held-out ones) sees them as stage 1 refined them.
    super::pose::apply_run_poses(&run_dir, &mut scene.views)?;
    let gt = super::preview::ground_truth_metrics(
        &args.scene,
        scene.normalisation.center,
        DMat3::from_cols_array(&run.run_scene.rotation),
        report.config.metres_per_world_unit(),
        &report,
        ctx,
    )?;
    let what = if args.geometry_only {
        serde_json::json!({
            "geometry": "trained SDF (stage 1), marching cubes",
            "albedo": "radiance preview: the stage-1 radiance net seen along the normal (lighting baked in, not de-lit)",
            "roughness": format!("constant {}", args.preview_roughness),
            "environment": "uniform white (radiance 1)",
        })
    } else {
        serde_json::json!({
            "geometry": "trained SDF (stage 1), marching cubes",
            "albedo": "stage-2 material autoencoder (de-lit; scale-ambiguous with the environment)",
            "roughness": "stage-2 material autoencoder",
            "environment": "stage-2 SG lobes, rendered to env.exr and listed in the SG JSON",
        })
    };
    let frame = super::blender_check::AssetFrame {
        rotation: DMat3::from_cols_array(&run.run_scene.rotation),
        scale: f64::from(report.config.metres_per_unit),
        shift: glam::DVec3::from(report.origin_shift_m.map(f64::from)),
    };
    let (train_v, held_v) = train_views(&scene);
    let blender = if held_v.is_empty() {
        super::blender_check::run(&args.asset.out, &args.scene, &train_v, false, &frame, &args.blender, ctx)
    } else {
        super::blender_check::run(&args.asset.out, &args.scene, &held_v, true, &frame, &args.blender, ctx)
    };
    let weak = run.report["weak_result"].as_bool().unwrap_or(false) || stage2_report["weak_result"].as_bool().unwrap_or(false);
    let summary = serde_json::json!({
        "method": format!("{}-{}", if args.geometry_only { "stage1" } else { "stage1+stage2" }, preset.name()),
        "what": what,
        "stages": [
            { "stage": "geometry", "seconds": seconds_stage1, "report": "run/train_report.json" },
            { "stage": "material", "seconds": seconds_stage2, "skipped": args.geometry_only, "report": "run/material_report.json" },
            { "stage": "export", "seconds": seconds_export },
        ],
        "scene": run.report["scene"].clone(),
        "training": run.report,
        "material": stage2_report,
        "weak_result": weak,
        "flags": run.report["flags"].as_array().into_iter().chain(stage2_report["flags"].as_array()).flatten().cloned().collect::<Vec<_>>(),
        "run": run_dir.display().to_string(),
        "seconds": { "stage1": seconds_stage1, "stage2": seconds_stage2, "export": seconds_export, "total": t_total.elapsed().as_secs_f64() },
        "export": report,
        "ground_truth": gt,
        "blender_check": blender,
    });
    super::preview::write_bake_report(&args.asset.out, &name, summary, t_total, ctx)
}

#[cfg(test)]
mod tests {
    use super::covered_psnr;

    #[test]
    fn covered_psnr_is_zero_when_nothing_is_covered_and_finite_otherwise() {
        // A render that misses the whole photo must not score a perfect (capped) PSNR.
        assert_eq!(covered_psnr(0.0, 0.0), 0.0);
        // Mean squared error 0.01 over three channel samples: 20 dB.
        assert!((covered_psnr(0.03, 3.0) - 20.0).abs() < 1e-9);
    }

    #[test]
    fn a_curve_resumed_from_before_a_new_column_keeps_every_line_as_wide_as_its_header() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.csv");
        super::write_curve(&p, "step,loss,new", &["1,0.5".to_string(), "2,0.4,0.1".to_string()]).unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "step,loss,new\n1,0.5,\n2,0.4,0.1\n");
    }
}
