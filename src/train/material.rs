//! The command-line side of [`super::stage2`]: `train --stage material` on a stage-1 run (the
//! surface cache, the loop with progress, checkpoints, Ctrl-C and `--resume`, held-out
//! evaluation), the renderer of a trained stage-2 model (under its learned light or another
//! environment: `relight`), and the export of a stage-2 run (albedo/roughness from the material
//! field, the learned environment).

use std::path::Path;
use std::time::Instant;

use anyhow::Context as _;
use glam::DMat3;
use rayon::prelude::*;

use super::cli::{covered_psnr, masked_srgb_error, read_curve, read_run_scene, subsampled_rays, train_views, training_progress, write_curve, RunScene, TrainedSdf};
use super::stage1::{scene_key, Model as Stage1Model, Preset, TrainData, Trainer, CHECKPOINT};
use super::stage2::{shade_f64, Materials, BoundaryMode, DecoderMode, IndirectMode, RoughnessMode, Stage2Config, Stage2Model, Stage2Stats, Stage2Trainer, SurfaceCache, CHECKPOINT2};
use crate::backend::{Backend, BackendError};
use crate::context::Context;
use crate::export::{AssetArgs, ExportReport};
use crate::mesh::field::{MaterialField, MaterialSamples};
use crate::render::{trace, Rays, SdfBatch, TraceConfig};
use crate::scene::{Camera, Downscale, Format, ReadOptions, View};
use crate::sg::env::LatlongConvention;
use crate::sg::shade::{BrdfModel, Sg};
use crate::util::DataError;

/// Stage-2 options shared by `train --stage material` and `bake`.
#[derive(Debug, Clone, clap::Args)]
pub struct MaterialOptions {
    /// Environment SG lobes (default: the preset's, 32 fast / 128 paper; lobes that end with no
    /// energy are reported).
    #[arg(long)]
    pub lobes: Option<usize>,
    /// Indirect light: `ours` (F_ind at the secondary hit), `none` (PhySG-like; pair it with
    /// `--roughness constant`), `uniform` (NeRV-like), `mii` (MII/InvRender: an MLP at x gives 24
    /// indirect SGs fitted to the stage-1 radiance; blocked lobes dropped).
    #[arg(long, value_enum, default_value_t = IndirectMode::Ours)]
    pub indirect: IndirectMode,
    /// Material decoders (default: `separate` for synthetic transforms.json scenes, `shared` for
    /// real captures).
    #[arg(long, value_enum)]
    pub decoder: Option<DecoderMode>,
    /// Roughness: `field` (per point, the paper's) or `constant` (one learned value for the object,
    /// the PhySG-like baseline's).
    #[arg(long, value_enum, default_value_t = RoughnessMode::Field)]
    pub roughness: RoughnessMode,
    /// A metallic channel (glTF's metallic-roughness: a metal's highlights take its albedo's colour
    /// and it has no diffuse), `on` by default; `off` models dielectrics only (the paper's).
    #[arg(long, value_enum, default_value_t = MetallicMode::On)]
    pub metallic: MetallicMode,
    /// The BRDF's SG form: `calibrated` (the default: matched to Cycles' Principled BSDF, which
    /// renders the asset in Blender, after a warm-up with PhySG's form) or `physg` (the paper's,
    /// PhySG's closed form, throughout). See `BrdfModel`.
    #[arg(long, value_enum, default_value_t = BrdfModel::Calibrated)]
    pub brdf: BrdfModel,
    /// Boundary lights (secondary hits that graze the occluder): `flowing` passes their gradient to
    /// the light (ours), `detached` keeps them in the colour without gradient (the public code).
    #[arg(long, value_enum, default_value_t = BoundaryMode::Flowing)]
    pub boundary: BoundaryMode,
    /// Refine the stage-1 SDF jointly with light and material (the paper's timing table) instead of
    /// freezing it (the public code's); the export then meshes the refined SDF.
    #[arg(long)]
    pub refine_geometry: bool,
    /// Stage-2 iterations (default: the preset's).
    #[arg(long)]
    pub material_iterations: Option<u64>,
    /// Stage-2 surface points per iteration (default: the preset's).
    #[arg(long)]
    pub material_batch: Option<usize>,
    /// Stage-2 setting overrides, KEY=VALUE (any field of the stage-2 config), repeatable.
    #[arg(long = "material-set")]
    pub material_set: Vec<String>,
    #[command(flatten)]
    pub known_env: KnownEnv,
}

/// Whether stage 2 models metals ([`Stage2Config::metallic`]). On by default, whatever the
/// scene: measured (`train --stage material`, seed 0; albedo PSNR after scale / relit PSNR under
/// the scene's two maps), on against off:
/// - `make_scene.py --scene metal` (spot with metal patches): 18.57 / 19.47 / 20.59 against
///   16.05 / 18.45 / 18.11 dB, held-out 23.49 against 20.95 dB, metallic MSE 0.22 against 0.50;
/// - the Ethiopian head (bronze): held-out 22.50 against 22.08 dB, its learnt light 2.0× between
///   channels against 4.0× (flagged), its albedo no longer blue; DTU scan37: training views
///   15.81 against 15.29 dB;
/// - the dielectric scenes, where the learnt metallic ends near 0 (mean 0.0006–0.03): spot
///   27.64 / 27.93 / 26.89 against 27.53 / 27.74 / 26.63, example 27.23 / 27.79 / 26.64 against
///   27.35 / 27.85 / 26.77, glossy 22.93 / 27.29 / 21.35 against 23.16 / 27.31 / 21.37, bowl
///   19.81 / 20.97 / 23.96 against 20.32 / 21.24 / 24.46 (the one that pays: 0.3–0.5 dB).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum MetallicMode {
    On,
    Off,
}

/// The capture's recorded lighting for stage 2, shared by `train`, `bake` and `bench material`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct KnownEnv {
    /// The capture's lighting, when it was recorded (an on-set HDRI: a latlong .exr in the
    /// scene's world frame): it is fitted with the stage's SG lobes and its shape and colour kept
    /// (one exposure is learnt, which can still trade with the albedo's brightness); the stage-2
    /// override `light_fixed=false` only starts the light from it. A learnt light also absorbs what
    /// the shading model leaves out: on the bundled example a fixed map is worse than none (README)
    #[arg(long = "known-env", value_name = "MAP.exr")]
    pub map: Option<std::path::PathBuf>,
    /// Latlong layout of `--known-env` (`open-exr-usd`: +Y up, centre along +Z; `blender`: a
    /// Blender World's).
    #[arg(long = "known-env-convention", value_enum, default_value_t = LatlongConvention::OpenExrUsd)]
    pub convention: LatlongConvention,
}

impl Default for MaterialOptions {
    fn default() -> Self {
        Self { lobes: None, indirect: IndirectMode::Ours, decoder: None, roughness: RoughnessMode::Field, metallic: MetallicMode::On, brdf: BrdfModel::Calibrated, boundary: BoundaryMode::Flowing, refine_geometry: false, material_iterations: None, material_batch: None, material_set: Vec::new(), known_env: KnownEnv::default() }
    }
}

const CURVE2: &str = "material_curve.csv";

/// A learnt light whose channels' energies differ by more than this factor is flagged. The
/// photos fix only albedo × light per channel; the eleven HDR maps shipped in `shared/data` stay
/// within 1.8× (night 1.76, the rest 1.03–1.32), the lights learnt on `make_scene.py`'s scenes and
/// the example within 1.55× and on DTU scan37 1.62×; the Ethiopian head's (bronze, whose coloured
/// highlights a dielectric model can only give the light) reached 4.4× with a blue albedo.
pub const TINTED_LIGHT_ABOVE: f64 = 2.5;

/// The report's flag for a learnt light tinted past [`TINTED_LIGHT_ABOVE`] (`energies`: per
/// channel, [`Stage2Model::channel_energies`]); `None` for a plausible or a dark light.
/// `metallic`: whether the run modelled metals (the likely causes differ).
pub fn tinted_light_flag(energies: [f64; 3], metallic: bool) -> Option<String> {
    let (lo, hi) = energies.iter().fold((f64::INFINITY, 0.0f64), |(a, b), &e| (a.min(e), b.max(e)));
    if !(hi > 0.0 && energies.iter().all(|e| e.is_finite())) || hi <= TINTED_LIGHT_ABOVE * lo {
        return None;
    }
    let g = energies[1].max(1e-12);
    let causes = if metallic {
        "a strongly coloured light, or a metal whose coloured highlights the metallic channel did not take, causes it"
    } else {
        "a metallic object (its coloured highlights are not modelled under `--metallic off`, so the light takes their colour) or a strongly coloured light causes it"
    };
    Some(format!(
        "the learnt light is strongly tinted (R:G:B energy {:.2} : 1 : {:.2}, beyond the {TINTED_LIGHT_ABOVE}× a real environment reaches): the albedo carries the opposite tint; {causes}",
        energies[0] / g,
        energies[2] / g
    ))
}

/// The report's flag for a mean roughness at either end of its range (below 0.05 or above 0.95);
/// `None` between. `light_fixed`: the run kept a recorded light (`--known-env`), whose shape and
/// colour the material cannot move: there a roughness of 1 is where what the light could not take
/// went (on the bundled example with the map it was rendered under: the exposure learnt to 1.22,
/// a metallic of 0.31 on a dielectric, albedo 21.4 dB against 27.3 with a learnt light), so the
/// flag says what to try.
pub fn roughness_flag(mean_roughness: f64, light_fixed: bool, metallic: bool) -> Option<String> {
    if !(mean_roughness < 0.05 || mean_roughness > 0.95) {
        return None;
    }
    let mut flag = format!("roughness saturated (mean {mean_roughness:.2})");
    if light_fixed && mean_roughness > 0.95 {
        flag.push_str(": under the fixed recorded light (`--known-env`) the material took up what the light could not; compare a bake without `--known-env`");
        if metallic {
            flag.push_str(" and one with `--metallic off`");
        }
    }
    Some(flag)
}

/// A finished stage-2 run.
pub struct Stage2Run {
    pub trainer: Stage2Trainer,
    pub report: serde_json::Value,
}

/// Everything stage 2 needs from a stage-1 run folder, checked.
pub struct Stage1Checked {
    pub trainer: Trainer,
    pub run_scene: RunScene,
}

/// Load the stage-1 run in `run_dir` (clear errors when it is missing or from another scene).
pub fn load_stage1(run_dir: &Path, key: Option<&str>) -> Result<Stage1Checked, DataError> {
    if !run_dir.join(CHECKPOINT).is_file() {
        return Err(DataError::new(
            &run_dir.join(CHECKPOINT),
            "stage 2 needs a stage-1 run here: train the geometry first (`pii-bake train <scene> --out <run-dir>`)",
        ));
    }
    let run_scene = read_run_scene(run_dir)?;
    if let Some(k) = key {
        super::stage1::check_scene(run_dir, &run_scene.key, k)?;
    }
    let (trainer, _) = Trainer::load(run_dir, Some(&run_scene.key))?;
    Ok(Stage1Checked { trainer, run_scene })
}

fn curve_line(s: &Stage2Stats, secs: f64) -> String {
    format!("{},{:.6},{:.6},{:.6},{:.6},{:.3},{},{},{:.4}", s.step, s.loss, s.rgb, s.smooth, s.kl, s.psnr, s.blocked, s.applied as u8, secs)
}

const CURVE2_HEADER: &str = "step,loss,rgb,smooth,kl,psnr,blocked,applied,seconds";

/// Masked training pixels per view.
fn foreground_per_view(data: &TrainData) -> f64 {
    data.foreground_pixels() as f64 / data.views.len().max(1) as f64
}

/// The fast preset's material grid: half stage 1's finest resolution, coarser where the cached
/// points (`points`) would leave fewer than [`MATERIAL_POINTS_PER_CELL`] in a finest cell.
pub fn material_grid_finest(sizes: &super::stage1::SceneSizes, points: usize, foreground_per_view: f64) -> u32 {
    let half = (sizes.grid_finest / 2).max(32);
    // Cauchy: a convex body's mean projected area is a quarter of its surface, so the surface is
    // about A = 4·(foreground pixels per view)·footprint², its finest cells (side 2/f) number
    // A·f²/4, and P cached points give 4P/(A·f²) = P/(fg·footprint²·f²) points per cell.
    let fp = f64::from(sizes.pixel_footprint).max(1e-6);
    let f = (points as f64 / (foreground_per_view.max(1.0) * MATERIAL_POINTS_PER_CELL)).sqrt() / fp;
    (f.floor() as u32).clamp(32, half)
}

/// Fewest cached surface points per finest cell of the fast preset's material grid (see
/// [`material_grid_finest`]). A real capture has far more pixels than the 2^17 points stage 2
/// caches, so half stage 1's finest resolution left its cells with one or two points each, which
/// each fitted on their own: a speckled albedo, roughness at 0 or 1 from point to point. The
/// Ethiopian head (57 views, 15M pixels; `train --stage material`, held-out PSNR), finest 256
/// (half stage 1's, ~2 points per cell) -> 128 (~7) -> 64 (~28): 21.03 -> 22.10 -> 22.25 dB. A
/// floor, not a target: the bundled example (~17 points per cell at its 90 cells) loses texture
/// coarser (albedo / relit as rendered, 90 -> 64: 27.35 / 27.85, 26.77 -> 24.60 / 25.68, 24.65 dB;
/// -> 128: 27.15 / 27.65, 26.52), and at 8 every `make_scene.py` scene and the example keep 90.
pub const MATERIAL_POINTS_PER_CELL: f64 = 8.0;

/// Latent smoothness weight of the fast preset's material grid.
pub const GRID_SMOOTH_WEIGHT: f32 = 1.0;

/// Nodes per axis of the grid stage 2's secondary rays march on ([`Stage2Config::secondary_grid_nodes`]):
/// over the bounding cube (2 units), a cell of 1.5 pixel footprints, the cell the exported mesh is
/// extracted at (`SceneSizes::mesh_resolution`), so the occluders the rays see are the asset's.
/// Bowl (32 lobes, the cache as first traced), network / 121 nodes / 181 nodes (one footprint):
/// blocked pairs 20.2 / 19.8 / 20.0 %, boundary lights 2.86 / 2.15 / 2.42 % of them, cache 41.0 /
/// 11.4 / 16.1 s, 30 steps' re-tracing 9.4 / 1.8 / 2.1 s.
pub fn secondary_grid_nodes(sizes: &super::stage1::SceneSizes) -> usize {
    ((2.0 / (1.5 * sizes.pixel_footprint.max(1e-6))).round() as usize + 1).clamp(64, 256)
}

/// The stage-2 configuration for a scene and the options, with the reasons for its sizes.
/// `sizes`: stage 1's sizes for the scene (the fast preset's material grid takes its resolution and
/// table size from them).
pub fn stage2_config(preset: Preset, format: Format, data: &TrainData, sizes: &super::stage1::SceneSizes, opts: &MaterialOptions, seed: u64) -> anyhow::Result<(Stage2Config, serde_json::Value)> {
    let mut cfg = Stage2Config::new(preset, data.foreground_pixels());
    // The fast preset's material grid, chosen once for the config and its reason.
    let (cached_points, finest) = (cfg.points, material_grid_finest(sizes, cfg.points, foreground_per_view(data)));
    if preset == Preset::Fast {
        // Measured on the example (1200 iterations, the appearance-grid stage 1): PE10 held-out
        // 19.05 dB with the roughness saturated at 1, albedo 20.26 dB, relit 22.62 dB, roughness
        // MSE 0.209; the grid 25.60 / 20.72 / 23.87 dB, MSE 0.075.
        // Half stage 1's finest resolution (each cell then averages about 2×2 pixel footprints
        // per view, not the photos' noise) and latent smoothness 1.0 rather than the paper's 0.1
        // (which was set for a PE10 MLP, smooth by construction; a hash grid has no such prior).
        // `bench material`, 32 lobes, ours: example held-out / albedo / relit / roughness MSE
        // 25.63 / 20.64 / 23.84 / 0.078 -> 25.82 / 21.08 / 24.30 / 0.052; glossy 22.05 / 21.93 /
        // 21.43 / 0.017 -> 22.35 / 22.53 / 21.25 / 0.011.
        // Tried and not kept: a spatial albedo prior (L1 between the albedos of each batch point
        // and its nearest batch neighbour within 0.1 of the bounding radius, weighted by how alike
        // their photos' chromaticity and luminance are, divided by the batch's mean albedo so it
        // cannot pay the light to take the albedo's scale). `bench material` (32 lobes, ours, 4
        // relit views), weight 0 -> 0.1 -> 0.3, albedo / relit as rendered (mean of both maps):
        // example 27.10 / 27.62 -> 27.98 / 25.96 -> 29.13 / 24.83 dB (the albedo turns whiter,
        // which the light takes back: relit after one scale per channel 29.0 -> 29.3 -> 29.3);
        // bowl 17.22 / 20.13 -> 15.14 / 18.38; textureless bowl 21.67 / 23.38 -> 20.05 / 22.48 ->
        // 18.00 / 20.49. Plain differences (no mean) let the albedo fall to a third and the light
        // grow (example relit 13.8 dB at 0.3).
        cfg = cfg.with_material_grid(finest, sizes.grid_log2_table);
        cfg.smooth_weight = GRID_SMOOTH_WEIGHT;
    }
    cfg.secondary_grid_nodes = secondary_grid_nodes(sizes);
    cfg.seed = seed;
    cfg.indirect = opts.indirect;
    cfg.roughness = opts.roughness;
    cfg.boundary = opts.boundary;
    cfg.refine_geometry = opts.refine_geometry;
    let synthetic = matches!(format, Format::Transforms);
    cfg.decoder = opts.decoder.unwrap_or(if synthetic { DecoderMode::Separate } else { DecoderMode::Shared });
    cfg.metallic = opts.metallic == MetallicMode::On;
    cfg.brdf = opts.brdf;
    if let Some(k) = opts.lobes {
        cfg.lobes = k;
    }
    if let Some(n) = opts.material_iterations {
        cfg.iterations = n;
    }
    if let Some(n) = opts.material_batch {
        cfg.batch = n;
    }
    cfg.light_fixed = opts.known_env.map.is_some();
    let cfg = super::stage2::apply_overrides(cfg, &opts.material_set)?;
    let why = serde_json::json!({
        "light": match &opts.known_env.map {
            Some(p) if cfg.light_fixed => format!("known: {} ({:?} layout) fitted with the lobes, its shape kept, one exposure learnt", p.display(), opts.known_env.convention),
            Some(p) => format!("learnt from the photos, starting from {} ({:?} layout) fitted with the lobes", p.display(), opts.known_env.convention),
            None => "learnt from the photos".to_string(),
        },
        "lobes": if opts.lobes.is_some() { "forced by --lobes".to_string() } else { format!("{} preset default; lobes left with no energy are reported after training", preset.name()) },
        "metallic": match opts.metallic {
            MetallicMode::On => "on (the default): a metal's highlights take its albedo's colour; `--metallic off` models dielectrics only",
            MetallicMode::Off => "off (`--metallic off`): dielectrics only",
        },
        "brdf": match opts.brdf {
            BrdfModel::Physg => "physg (`--brdf physg`): the paper's SG BRDF (PhySG's closed form) throughout",
            BrdfModel::Calibrated => "calibrated (the default): the SG BRDF matched to Cycles' Principled BSDF (which renders the asset in Blender), after a warm-up with PhySG's form; `--brdf physg` keeps the paper's",
        },
        "decoder": if opts.decoder.is_some() { "forced by --decoder".to_string() } else if synthetic { "separate: a synthetic (transforms.json) scene".to_string() } else { "shared: a real capture (supplementary §5.2)".to_string() },
        "points": format!("min(preset cap, {} masked training pixels)", data.foreground_pixels()),
        "material_encoding": if preset == Preset::Fast { format!("hash grid, finest {} cells (half stage 1's {} at most, and at least {MATERIAL_POINTS_PER_CELL} of its {} cached points per cell), 2^{} entries per level (stage 1's), latent smoothness {}", finest, sizes.grid_finest, cached_points, sizes.grid_log2_table, GRID_SMOOTH_WEIGHT) } else { format!("PE{} (the paper's)", cfg.pos_freqs) },
    });
    Ok((cfg, why))
}

/// Stage 2's steps keep their parameters on the host and take the backend per step, so the
/// loop can run them where they are faster. On an NVIDIA H200 beside its 16 cores the cpu
/// backend ran the example's stage-2 steps at 79.6 it/s against 56.1 on wgpu (the shading runs on
/// the host either way and the networks are small), while a smaller CPU beside the same GPU
/// would turn that around: no fixed rule holds. Under `--backend auto` with a GPU the loop
/// times [`StepBackend::TIMED`] steps on each (after [`StepBackend::WARM`] untimed ones, which
/// pay for compiling kernels) and keeps the faster, recorded in the run's config
/// (`step_backend`) so a resumed run keeps it (one resumed before the choice times again from
/// where it resumed, so its first steps may run where the straight run's did not: the same
/// figures to float rounding, not bit for bit). `--backend wgpu` or `cpu`, `--refine-geometry`
/// (whose SDF lives with the run's backend) and `--profile-kernels` run every step on the run's
/// backend.
pub(crate) struct StepBackend {
    /// The run's backend and the cpu backend, while both are candidates.
    candidates: Vec<(&'static str, Backend)>,
    /// Seconds of each candidate's timed steps.
    timed: Vec<Vec<f64>>,
    /// The candidate being measured, or the one chosen.
    at: usize,
    steps_at: usize,
    chosen: bool,
    why: String,
}

impl StepBackend {
    /// Untimed steps on a candidate before it is timed.
    pub const WARM: usize = 2;
    /// Timed steps per candidate.
    pub const TIMED: usize = 6;

    pub fn new(backend: &Backend, ctx: &Context, cfg: &Stage2Config) -> Self {
        let one = |name: &'static str, b: Backend, why: String| Self { candidates: vec![(name, b)], timed: vec![Vec::new()], at: 0, steps_at: 0, chosen: true, why };
        let own = if backend.is_gpu() { "wgpu" } else { "cpu" };
        let eligible = matches!(ctx.backend_choice, crate::backend::BackendChoice::Auto) && backend.is_gpu() && !cfg.refine_geometry && !ctx.profile_kernels;
        match cfg.step_backend.as_deref() {
            Some("cpu") if eligible => return one("cpu", Backend::cpu(), "chosen earlier in this run (step_backend)".into()),
            Some(_) if eligible => return one(own, backend.clone(), "chosen earlier in this run (step_backend)".into()),
            _ => {}
        }
        if !eligible {
            let why = if !backend.is_gpu() {
                "the run's backend"
            } else if !matches!(ctx.backend_choice, crate::backend::BackendChoice::Auto) {
                "the run's backend (asked for by --backend)"
            } else if cfg.refine_geometry {
                "the run's backend (--refine-geometry keeps the SDF there)"
            } else {
                "the run's backend (--profile-kernels)"
            };
            return one(own, backend.clone(), why.into());
        }
        Self { candidates: vec![("wgpu", backend.clone()), ("cpu", Backend::cpu())], timed: vec![Vec::new(), Vec::new()], at: 0, steps_at: 0, chosen: false, why: String::new() }
    }

    /// The backend for the next step.
    pub fn current(&self) -> &Backend {
        &self.candidates[self.at].1
    }

    /// The chosen backend's name, once chosen.
    pub fn chosen(&self) -> Option<&'static str> {
        self.chosen.then_some(self.candidates[self.at].0)
    }

    /// Record a step's seconds on [`StepBackend::current`]. Returns a line to show once the
    /// choice is made.
    pub fn record(&mut self, seconds: f64) -> Option<String> {
        if self.chosen {
            return None;
        }
        self.steps_at += 1;
        if self.steps_at > Self::WARM {
            self.timed[self.at].push(seconds);
        }
        if self.steps_at < Self::WARM + Self::TIMED {
            return None;
        }
        if self.at + 1 < self.candidates.len() {
            self.at += 1;
            self.steps_at = 0;
            return None;
        }
        let per = self.per_step();
        self.at = if per[1] < per[0] { 1 } else { 0 };
        self.chosen = true;
        self.why = format!("the faster of {} timed steps on each", Self::TIMED);
        Some(format!(
            "stage 2: steps run on the {} backend ({:.1} ms per step on wgpu, {:.1} ms on cpu, {} timed steps each)",
            self.candidates[self.at].0,
            1e3 * per[0],
            1e3 * per[1],
            Self::TIMED
        ))
    }

    /// Each candidate's mean seconds per timed step (NaN where none was timed).
    fn per_step(&self) -> Vec<f64> {
        self.timed.iter().map(|t| if t.is_empty() { f64::NAN } else { t.iter().sum::<f64>() / t.len() as f64 }).collect()
    }

    /// What the report says: the backend chosen, why, and what was measured.
    pub fn report(&self) -> serde_json::Value {
        let per = self.per_step();
        let measured: serde_json::Map<String, serde_json::Value> =
            self.candidates.iter().zip(&per).filter(|(_, p)| p.is_finite()).map(|((n, _), p)| (n.to_string(), serde_json::json!(p))).collect();
        serde_json::json!({ "chosen": self.chosen(), "why": self.why, "seconds_per_step": measured })
    }
}

/// Train stage 2 on the stage-1 run in `run_dir`.
/// `trained`: the stage-1 model this process has just trained into `run_dir`, if any, whose
/// sampled SDF grid stage 2 then takes instead of sampling it again.
#[allow(clippy::too_many_arguments)]
pub fn train_stage2(scene_path: &Path, preset: Preset, opts: &MaterialOptions, seed: u64, run_dir: &Path, resume: bool, stop_at: Option<u64>, trained: Option<&Stage1Model>, backend: &Backend, ctx: &Context) -> anyhow::Result<Stage2Run> {
    let t_total = Instant::now();
    crate::export::check_writable(run_dir)?;
    let s1 = load_stage1(run_dir, None)?;
    let downscale = s1.trainer.cfg.downscale.max(1);
    let mut scene = crate::scene::load(scene_path, &ReadOptions { downscale: Downscale::By(downscale), keep_all_views: s1.trainer.cfg.keep_all_views })?;
    // The training views' poses as stage 1 refined them, where it did.
    let refined = super::pose::apply_run_poses(run_dir, &mut scene.views)?;
    if refined > 0 {
        ctx.say(format!("stage 2: training through the {refined} camera poses stage 1 refined ({})", super::pose::POSES));
    }
    let (views, held) = train_views(&scene);
    let key = scene_key(&scene, &views);
    if key != s1.run_scene.key {
        return Err(DataError::new(&run_dir.join(CHECKPOINT), format!("the stage-1 run here was trained on another scene ({}), not {} ({key})", s1.run_scene.key, scene_path.display())).into());
    }
    super::stage1::check_preset(&run_dir.join(CHECKPOINT), s1.trainer.cfg.preset, preset)?;
    let data = TrainData::new(&views, 1.0)?;
    let (mut cfg, why) = stage2_config(preset, scene.format, &data, &s1.trainer.cfg.sizes, opts, seed)?;
    let mut curve = Vec::new();
    let resuming = resume && run_dir.join(CHECKPOINT2).is_file();
    if cfg.refine_geometry && cfg.lr_geometry <= 0.0 {
        // Continue at the rate stage 1 ended with.
        cfg.lr_geometry = s1.trainer.cfg.lr_field * s1.trainer.cfg.lr_final_factor;
    }
    let (mut trainer, traced) = if resuming {
        let (mut t, _, traced) = Stage2Trainer::load(run_dir, Some(&key))?;
        super::stage1::check_preset(&run_dir.join(CHECKPOINT2), t.cfg().preset, preset)?;
        if let Some(n) = opts.material_iterations {
            t.model.cfg.iterations = n;
        }
        curve = read_curve(&run_dir.join(CURVE2), t.step, 64 << 20);
        ctx.say(format!("resuming stage 2 in {} at step {} of {}", run_dir.display(), t.step, t.cfg().iterations));
        (t, traced)
    } else {
        let mut t = Stage2Trainer::new(&cfg)?;
        if let Some(map) = &opts.known_env.map {
            // The map is in the scene's world frame; the model's is the run's normalised one.
            let to_run = DMat3::from_cols_array(&s1.run_scene.rotation).transpose();
            let (lobes, secs) = super::relight::fit_map_lobes(backend, map, opts.known_env.convention, cfg.lobes, to_run, ctx)?;
            t.model.set_light(&lobes).map_err(|e| DataError::new(map, e.to_string()))?;
            let kept = if cfg.light_fixed { "its shape kept, one exposure learnt" } else { "the starting light (light_fixed=false: then learnt)" };
            ctx.say(format!("stage 2: the light is known: {} fitted with {} lobes [{secs:.1} s], {kept}", map.display(), lobes.len()));
        }
        (t, Vec::new())
    };
    if resuming && trainer.cfg().light_fixed != cfg.light_fixed {
        let had = if trainer.cfg().light_fixed { "a known (fixed) light" } else { "a learnt light" };
        return Err(DataError::new(&run_dir.join(CHECKPOINT2), format!("this stage-2 run has {had}: resume it with the same --known-env choice")).into());
    }
    cfg = trainer.cfg().clone();
    let tc = s1.trainer.cfg.trace.clone();
    // The geometry: stage 1's SDF, refined in place with `--refine-geometry` (a resumed run
    // continues from its refined SDF).
    let mut s1 = s1;
    trainer.geometry_into(s1.trainer.model_mut()?).map_err(|e| DataError::new(&run_dir.join(CHECKPOINT2), e.to_string()))?;
    let mut geom = s1.trainer.into_model()?;
    if let Some(m) = trained {
        geom.share_sdf_grid(m);
    }

    // The surface cache: primary points once; secondary hits per lobe (all re-traced every
    // `geometry_retrace_every` iterations while the geometry is refined).
    let tcache = Instant::now();
    // A resumed frozen run re-traces along the axes it had traced; a refined one rebuilds the cache
    // on its refined surface along the current axes, as the run it continues did at its last
    // rebuild (so a run stopped at a rebuild step resumes exactly).
    let axes0 = if traced.len() == cfg.lobes && !cfg.refine_geometry { traced } else { trainer.model.axes() };
    let mut cache = build_cache(backend, &geom, &tc, &data, &cfg, axes0, ctx)?;
    if cache.len() < 16 {
        return Err(DataError::new(scene_path, format!("only {} masked training pixels reach the stage-1 surface: the geometry does not match the masks (retrain stage 1)", cache.len())).into());
    }
    let seconds_cache = tcache.elapsed().as_secs_f64();
    let mut geometry_retraces = 0usize;
    ctx.say(format!(
        "stage 2 ({} preset, indirect {}, {} decoder): {} lobes, {} cached surface points, {:.1}% of (point, lobe above the horizon) pairs blocked, {:.2}% of the blocked ones boundary lights (boundary gradient {}); cache traced once in {:.1} s ({} field evaluations) — without it every iteration would trace {} rays",
        cfg.preset.name(),
        cfg.indirect.name(),
        match cfg.decoder { DecoderMode::Separate => "separate", DecoderMode::Shared => "shared" },
        cfg.lobes,
        cache.len(),
        100.0 * cache.blocked_fraction(),
        100.0 * cache.boundary_fraction(cfg.boundary_epsilon),
        match cfg.boundary { BoundaryMode::Flowing => "flowing", BoundaryMode::Detached => "detached" },
        seconds_cache,
        cache.evaluations,
        cfg.secondary_rays_per_batch()
    ));

    let pb = training_progress(ctx, cfg.iterations, "stage 2");
    pb.set_position(trainer.step);
    let t_loop = Instant::now();
    let step0 = trainer.step;
    let costs = super::cli::StepCosts::start(backend);
    let mut step_backend = StepBackend::new(backend, ctx, &cfg);
    let end = stop_at.unwrap_or(cfg.iterations).min(cfg.iterations);
    let rule = super::cli::CheckpointRule {
        stop: super::cli::interrupt_flag(),
        every: cfg.checkpoint_every,
        end,
        iterations: cfg.iterations,
        step_name: "stage-2 step",
        checkpoint: run_dir.join(CHECKPOINT2),
        resume: format!("pii-bake train {} --out {} --stage material --resume", scene_path.display(), run_dir.display()),
    };
    let save = |trainer: &Stage2Trainer, cache: &SurfaceCache, geom: &Stage1Model, curve: &[String]| -> anyhow::Result<()> {
        trainer.save_with(run_dir, &key, &cache.traced_axes, Some(geom))?;
        write_curve(&run_dir.join(CURVE2), CURVE2_HEADER, curve)?;
        Ok(())
    };
    let mut last = Stage2Stats::default();
    let mut retrace_s = 0.0;
    while trainer.step < end {
        let ts = Instant::now();
        let tr = Instant::now();
        if cfg.refine_geometry && trainer.step > step0 && trainer.step % cfg.geometry_retrace_every == 0 {
            cache = build_cache(backend, &geom, &tc, &data, &cfg, trainer.model.axes(), ctx)?;
            geometry_retraces += 1;
        }
        cache.refresh(backend, &geom, &cfg, &trainer.model.axes())?;
        retrace_s += tr.elapsed().as_secs_f64();
        let t_step = Instant::now();
        let s = trainer.train_step_with(step_backend.current(), &cache, Some(&mut geom))?;
        if let Some(line) = step_backend.record(t_step.elapsed().as_secs_f64()) {
            pb.suspend(|| ctx.say(line));
            trainer.model.cfg.step_backend = step_backend.chosen().map(str::to_string);
        }
        curve.push(curve_line(&s, ts.elapsed().as_secs_f64()));
        let its = (trainer.step - step0) as f64 / t_loop.elapsed().as_secs_f64().max(1e-9);
        pb.set_position(trainer.step);
        pb.set_message(format!("loss {:.4} (rgb {:.4} smooth {:.4} kl {:.4}) psnr {:.1} {:.2} it/s", s.loss, s.rgb, s.smooth, s.kl, s.psnr, its));
        ctx.emit("progress", serde_json::json!({ "stage": "material", "iterations": cfg.iterations, "it_per_s": its, "skipped": trainer.skipped, "stats": s }));
        last = s;
        rule.after_step(trainer.step, &pb, || save(&trainer, &cache, &geom, &curve))?;
    }
    pb.finish_and_clear();
    if trainer.step == step0 {
        save(&trainer, &cache, &geom, &curve)?;
    }
    let seconds_train = t_loop.elapsed().as_secs_f64();
    let its = (trainer.step - step0) as f64 / seconds_train.max(1e-9);

    // The training steps' costs, before the evaluation's renders add theirs.
    let per_step = costs.per_step(backend, trainer.step - step0);
    // Held-out views rendered with the learned light and material.
    let t_eval = Instant::now();
    let eval_views: Vec<&View> = if held.is_empty() { views.iter().step_by((views.len() / 3).max(1)).take(3).copied().collect() } else { held.iter().take(4).copied().collect() };
    let mut per_view = Vec::new();
    let (mut se, mut wsum) = (0.0f64, 0.0f64);
    for v in &eval_views {
        let img = render_view(backend, &geom, &tc, &trainer.model, &v.camera, 80 * 80, None)?;
        let (mut vse, mut vw) = (0.0, 0.0);
        // Over the pixels that the photo's mask and the render both cover (as `evaluate_views`).
        for (k, &p) in img.pixel_index.iter().enumerate().filter(|&(k, _)| img.hit[k]) {
            if let Some(e) = masked_srgb_error(v, p, img.rgb[k].map(crate::image_io::linear_to_srgb)) {
                vse += e;
                vw += 3.0;
            }
        }
        per_view.push(serde_json::json!({ "view": v.name, "psnr": covered_psnr(vse, vw) }));
        se += vse;
        wsum += vw;
    }
    let psnr = covered_psnr(se, wsum);
    let idle = trainer.model.idle_lobes().len();
    let mats = trainer.model.material(backend, &cache.x[..cache.len().min(4096)])?;
    let (alb, rough) = (&mats.albedo, &mats.roughness);
    let mean_metal = mats.metallic.iter().map(|&m| m as f64).sum::<f64>() / mats.metallic.len().max(1) as f64;
    let metal_fraction = mats.metallic.iter().filter(|&&m| m > 0.5).count() as f64 / mats.metallic.len().max(1) as f64;
    let mean_rough = rough.iter().map(|&r| r as f64).sum::<f64>() / rough.len().max(1) as f64;
    let mean_alb: Vec<f64> = (0..3).map(|c| alb.iter().map(|a| a[c] as f64).sum::<f64>() / alb.len().max(1) as f64).collect();
    let finite = trainer.model.light.iter().chain(&trainer.model.enc_params).all(|v| v.is_finite());
    let mut flags = Vec::new();
    if psnr < 20.0 {
        let which = if held.is_empty() { "training-view" } else { "held-out" };
        flags.push(format!("{which} PSNR {psnr:.1} dB < 20 dB: light/material separation is weak (glossy or textureless object, few views?)"));
    }
    if trainer.skipped * 10 > trainer.step.max(1) {
        flags.push(format!("{} of {} steps skipped for non-finite gradients", trainer.skipped, trainer.step));
    }
    if !finite {
        flags.push("non-finite parameters".to_string());
    }
    flags.extend(roughness_flag(mean_rough, cfg.light_fixed, cfg.metallic));
    let channel_energy = trainer.model.channel_energies();
    if !cfg.light_fixed {
        flags.extend(tinted_light_flag(channel_energy, cfg.metallic));
    }
    // A one-colour object: nothing in the photos tells its albedo from the shading on it.
    let texture = crate::scene::texture::photo_texture(&views);
    if let Some(t) = texture.filter(|&t| t < crate::scene::texture::TEXTURELESS_BELOW) {
        flags.push(format!(
            "the photos show little texture (contrast {t:.3} < {}): a textureless object, whose albedo keeps shading that light and material cannot be told apart by",
            crate::scene::texture::TEXTURELESS_BELOW
        ));
    }
    let mut report = serde_json::json!({
        "stage": "material",
        "preset": cfg.preset,
        "backend": backend.describe(),
        "step_backend": step_backend.report(),
        "config": cfg,
        "sizes": { "lobes": cfg.lobes, "lobes_without_energy": idle, "points": cache.len(), "batch": cfg.batch, "parameters": trainer.model.num_params(), "why": why },
        "cache": { "points": cache.len(), "blocked_fraction": cache.blocked_fraction(), "boundary_fraction": cache.boundary_fraction(cfg.boundary_epsilon), "field_evaluations": cache.evaluations, "seconds": seconds_cache, "lobes_retraced": cache.retraced, "seconds_retracing": retrace_s,
                   "secondary_rays": cache.secondary_rays, "steps_per_secondary_ray": cache.steps_per_secondary_ray(),
                   "secondary_march": match &cache.grid {
                       Some(g) => serde_json::json!({ "on": "the SDF sampled on a grid, hits placed on the network's surface", "nodes": g.nodes(), "spacing": g.spacing(), "seconds_sampling": cache.grid_seconds }),
                       None => serde_json::json!({ "on": "the network at every step" }),
                   },
                   "rays_per_iteration_without_cache": cfg.secondary_rays_per_batch() },
        "geometry": if cfg.refine_geometry {
            serde_json::json!({ "refined": true, "lr": cfg.lr_geometry, "eikonal_weight": cfg.geometry_eikonal_weight, "cache_rebuilds": geometry_retraces, "retrace_every": cfg.geometry_retrace_every, "last_eikonal": last.eikonal })
        } else {
            serde_json::json!({ "refined": false, "why": "frozen at stage 1's SDF (the public code); `--refine-geometry` refines it jointly" })
        },
        "steps": trainer.step,
        "skipped_steps": trainer.skipped,
        "last": last,
        "it_per_s": its,
        "gpu_per_step": per_step.gpu,
        "gpu_kernels_per_step": per_step.kernels,
        "host_encoding_seconds_per_step": per_step.encoding_seconds,
        "training_thread_cpu_seconds_per_step": per_step.thread_cpu_seconds,
        "material": { "mean_albedo": mean_alb, "mean_roughness": mean_rough, "metallic": if cfg.metallic { serde_json::json!({ "mean": mean_metal, "fraction_above_half": metal_fraction }) } else { serde_json::Value::Null } },
        "photo_texture": texture,
        "environment": {
            "total_energy": trainer.model.lobe_energies().iter().sum::<f64>(),
            "channel_energy": channel_energy,
            "lobes_exported": cfg.lobes - idle,
            "idle_lobe_fraction": super::stage2::IDLE_LOBE_FRACTION,
            "known": cfg.light_fixed,
            "exposure": if cfg.light_fixed { serde_json::json!(trainer.exposure) } else { serde_json::Value::Null },
            "balance": if cfg.learns_balance() {
                serde_json::json!({ "albedo_scale": trainer.model.albedo_scale, "light_factor": 1.0 / trainer.model.albedo_scale, "lr_factor": cfg.balance_lr_factor })
            } else {
                serde_json::Value::Null
            },
        },
        "eval": { "views": if held.is_empty() { "training views (the scene has no held-out split)" } else { "held-out views" }, "psnr_pixels": super::cli::HELD_OUT_PSNR_PIXELS, "psnr": psnr, "per_view": per_view, "seconds": t_eval.elapsed().as_secs_f64() },
        "weak_result": !flags.is_empty(),
        "flags": flags,
        "seconds": { "cache": seconds_cache, "train": seconds_train, "total": t_total.elapsed().as_secs_f64() },
    });
    super::cli::span_the_whole_run(&mut report, &run_dir.join("material_report.json"), step0, &[], &[]);
    let its = report["it_per_s"].as_f64().unwrap_or(its);
    crate::util::atomic_write(&run_dir.join("material_report.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    if let Some(line) = per_step.kernel_line("stage 2") {
        ctx.say(line);
    }
    ctx.say(format!(
        "stage 2: {} steps ({} skipped) at {:.2} it/s; {}: PSNR {:.2} dB ({} light and learned material); {} of {} lobes without energy{}",
        trainer.step,
        trainer.skipped,
        its,
        if held.is_empty() { "training views" } else { "held-out views" },
        psnr,
        if cfg.light_fixed { format!("known light at {:.3}× the map's exposure", trainer.exposure) } else { "learned".to_string() },
        idle,
        cfg.lobes,
        if flags.is_empty() { String::new() } else { format!(" — WEAK RESULT: {}", flags.join("; ")) }
    ));
    if cfg.refine_geometry {
        trainer.refined_sdf = Some(geom.sdf_params.clone());
    }
    Ok(Stage2Run { trainer, report })
}

// ---- rendering a trained model -------------------------------------------------------------

/// A rendered view: per rendered pixel (row-major, every `step`-th pixel) the pixel index in the
/// full image, and for hits the linear colour, albedo, roughness.
#[derive(Clone, Debug, Default)]
pub struct RenderedView {
    pub width: usize,
    pub height: usize,
    pub pixel_index: Vec<usize>,
    pub hit: Vec<bool>,
    pub rgb: Vec<[f32; 3]>,
    pub albedo: Vec<[f32; 3]>,
    pub roughness: Vec<f32>,
    /// Metallic (0 where the model is dielectric).
    pub metallic: Vec<f32>,
    /// The shading normal (the model's normalised frame), facing the camera.
    pub normal: Vec<[f32; 3]>,
}

/// Render `camera` at no more than `max_pixels` pixels (every `step`-th pixel, as `evaluate_views`),
/// or at full size with `max_pixels = 0`. `env`: another environment (normalised frame) to
/// relight with; None = the learned one with the learned indirect light.
/// Trace the surface cache on `sdf` and every lobe along `axes` (with a progress bar).
fn build_cache(backend: &Backend, sdf: &Stage1Model, tc: &TraceConfig, data: &TrainData, cfg: &Stage2Config, axes: Vec<[f32; 3]>, ctx: &Context) -> Result<SurfaceCache, BackendError> {
    let mut cache = SurfaceCache::build(backend, sdf, tc, data, cfg.points, cfg.seed, super::stage2::normal_step(sdf, cfg))?;
    if cache.len() >= 16 && cfg.indirect != IndirectMode::None {
        let pb = ctx.progress(cfg.lobes as u64, "tracing toward lobes");
        for (k, a) in axes.iter().enumerate() {
            cache.trace_lobe(backend, sdf, cfg, k, *a)?;
            pb.set_position(k as u64 + 1);
        }
        pb.finish_and_clear();
    }
    Ok(cache)
}

/// The geometry a stage-2 run shades: stage 1's SDF, or its refinement (`--refine-geometry`).
pub fn stage2_geometry(s1: &Trainer, s2: &Stage2Trainer) -> anyhow::Result<Option<Stage1Model>> {
    if s2.refined_sdf.is_none() {
        return Ok(None);
    }
    let mut m = Stage1Model::new(&s1.cfg)?;
    m.radiance_params.clone_from(&s1.model().radiance_params);
    s2.geometry_into(&mut m)?;
    Ok(Some(m))
}

pub fn render_view(backend: &Backend, sdf: &Stage1Model, tc: &TraceConfig, model: &Stage2Model, camera: &Camera, max_pixels: usize, env: Option<&[Sg<f64>]>) -> Result<RenderedView, BackendError> {
    Ok(render_view_lit(backend, sdf, tc, model, camera, max_pixels, &[env])?.remove(0))
}

/// [`render_view`] under several lights at once (None = the learned one): the camera rays are
/// traced, and their normals and material evaluated, once for all of them. The views share their
/// pixels and hits and differ in `rgb`.
pub fn render_view_lit(backend: &Backend, sdf: &Stage1Model, tc: &TraceConfig, model: &Stage2Model, camera: &Camera, max_pixels: usize, envs: &[Option<&[Sg<f64>]>]) -> Result<Vec<RenderedView>, BackendError> {
    let (rays, pixel_index) = subsampled_rays(camera, max_pixels);
    let mut out = RenderedView { width: camera.width, height: camera.height, pixel_index, ..Default::default() };
    let n = rays.len();
    out.hit = vec![false; n];
    out.albedo = vec![[0.0; 3]; n];
    out.roughness = vec![0.0; n];
    out.metallic = vec![0.0; n];
    out.normal = vec![[0.0; 3]; n];
    let mut rgbs = vec![vec![[0.0f32; 3]; n]; envs.len()];
    let f = sdf.sdf_batch(backend)?;
    // The secondary rays' grid, where there is one, bounds the field: tracing skips what it
    // proves empty and finds the same surface.
    let grid = super::stage2::secondary_grid(backend, sdf, &model.cfg)?;
    let bounded = crate::render::grid::bounded(&f, grid.as_ref().map(|g| g.0.as_ref()))?;
    let tf: &dyn SdfBatch = bounded.as_ref().map_or(&f, |b| b);
    for start in (0..n).step_by(8192) {
        let end = (start + 8192).min(n);
        let r = Rays { origins: rays.origins[start..end].to_vec(), dirs: rays.dirs[start..end].to_vec() };
        let tr = trace(tf, &r, tc)?;
        let idx: Vec<usize> = (0..r.len()).filter(|&i| tr.hit[i]).collect();
        let mut c = SurfaceCache { x: idx.iter().map(|&i| tr.points[i]).collect(), v: idx.iter().map(|&i| r.dirs[i].map(|v| -v)).collect(), ..Default::default() };
        c.target = vec![[0.0; 3]; c.x.len()];
        c.n = super::stage2::normals_at(backend, sdf, &c.x, super::stage2::normal_step(sdf, &model.cfg))?;
        for i in 0..c.x.len() {
            let d = c.n[i][0] * c.v[i][0] + c.n[i][1] * c.v[i][1] + c.n[i][2] * c.v[i][2];
            if d < 0.0 {
                c.n[i] = c.n[i].map(|v| -v);
            }
        }
        let mats = model.material(backend, &c.x)?;
        for (e, env) in envs.iter().enumerate() {
            let rgb = match env {
                None => {
                    let cfg = &model.cfg;
                    c.refresh(backend, sdf, cfg, &model.axes())?;
                    let all: Vec<usize> = (0..c.len()).collect();
                    super::stage2::render_points(backend, model, &c.batch(&all, cfg.lobes))?
                }
                Some(lobes) => relight_points(backend, sdf, model, &c, &mats, lobes)?,
            };
            for (k, &i) in idx.iter().enumerate() {
                rgbs[e][start + i] = rgb[k];
            }
        }
        for (k, &i) in idx.iter().enumerate() {
            let g = start + i;
            out.hit[g] = true;
            out.albedo[g] = mats.albedo[k];
            out.roughness[g] = mats.roughness[k];
            out.metallic[g] = mats.metallic[k];
            out.normal[g] = c.n[k];
        }
    }
    Ok(rgbs.into_iter().map(|rgb| RenderedView { rgb, ..out.clone() }).collect())
}

/// Shade points under another environment: direct light from its lobes; a lobe blocked by the
/// object is replaced by one-bounce light, the radiance the hit point x' (its learned material,
/// lit by the same environment, unoccluded) sends back toward x, spread over the lobe's extent.
fn relight_points(backend: &Backend, sdf: &Stage1Model, model: &Stage2Model, c: &SurfaceCache, mats: &Materials, lobes: &[Sg<f64>]) -> Result<Vec<[f32; 3]>, BackendError> {
    let cfg = &model.cfg;
    let grid = super::stage2::secondary_grid(backend, sdf, cfg)?;
    let (mut hx, mut owner) = (Vec::new(), Vec::new());
    for (j, l) in lobes.iter().enumerate() {
        let a = super::stage2::unit_f32(l.axis);
        let idx: Vec<usize> = (0..c.len()).filter(|&i| c.n[i][0] * a[0] + c.n[i][1] * a[1] + c.n[i][2] * a[2] > 0.0).collect();
        let rays = Rays { origins: idx.iter().map(|&i| c.x[i]).collect(), dirs: vec![a; idx.len()] };
        for (q, x) in super::stage2::secondary_hits(backend, sdf, cfg, grid.as_ref().map(|g| g.0.as_ref()), &rays)?.hits {
            hx.push(x);
            owner.push((idx[q], j));
        }
    }
    let hn = super::stage2::normals_at(backend, sdf, &hx, super::stage2::normal_step(sdf, cfg))?;
    let hm = model.material(backend, &hx)?;
    let bounce: Vec<[f32; 3]> = (0..hx.len())
        .into_par_iter()
        .map(|h| {
            let j = owner[h].1;
            let v = super::stage2::unit_f32(lobes[j].axis).map(|x| -x as f64);
            let (a, r, m) = hm.at(h);
            let (sp, df) = shade_f64(cfg.brdf, a, r, m, hn[h].map(f64::from), v, lobes);
            [0, 1, 2].map(|ch| (sp[ch].max(0.0) + df[ch].max(0.0)) as f32)
        })
        .collect();
    let mut blocked: Vec<Vec<(usize, [f32; 3])>> = vec![Vec::new(); c.len()];
    for (h, &(i, j)) in owner.iter().enumerate() {
        blocked[i].push((j, bounce[h]));
    }
    Ok((0..c.len())
        .into_par_iter()
        .map(|i| {
            let mut li = lobes.to_vec();
            for &(j, l) in &blocked[i] {
                li[j] = Sg { axis: lobes[j].axis, lambda: lobes[j].lambda, mu: l.map(f64::from) };
            }
            let (a, r, m) = mats.at(i);
            let (sp, df) = shade_f64(cfg.brdf, a, r, m, c.n[i].map(f64::from), c.v[i].map(f64::from), &li);
            [0, 1, 2].map(|ch| (sp[ch].max(0.0) + df[ch].max(0.0)) as f32)
        })
        .collect())
}

// ---- export ---------------------------------------------------------------------------------

/// The stage-2 material field as the asset back end's material (asset frame in, de-lit albedo and
/// roughness out).
pub struct LearnedMaterial<'a> {
    pub model: &'a Stage2Model,
    pub rotation: DMat3,
    pub feature: f32,
}

impl MaterialField for LearnedMaterial<'_> {
    fn name(&self) -> String {
        format!("learned material (stage 2 autoencoder, {} decoder)", match self.model.cfg.decoder { DecoderMode::Separate => "separate", DecoderMode::Shared => "shared" })
    }
    fn eval(&self, backend: &Backend, points: &[[f32; 3]], _normals: &[[f32; 3]]) -> Result<MaterialSamples, BackendError> {
        let rt = self.rotation.transpose();
        let x: Vec<[f32; 3]> = points.iter().map(|&q| (rt * glam::DVec3::from(q.map(f64::from))).as_vec3().to_array()).collect();
        let m = self.model.material(backend, &x)?;
        let metallic = if self.model.cfg.metallic { m.metallic } else { Vec::new() };
        Ok(MaterialSamples { albedo: m.albedo, roughness: m.roughness, metallic })
    }
    fn feature_size(&self) -> Option<f32> {
        Some(self.feature)
    }
}

/// Export a stage-1 geometry with a stage-2 material and environment.
pub fn export_stage2(backend: &Backend, s1: &Trainer, s2: &Stage2Trainer, rs: &RunScene, asset: &AssetArgs, default_name: &str, ctx: &Context) -> anyhow::Result<ExportReport> {
    let rotation = DMat3::from_cols_array(&rs.rotation);
    let cfg = &s1.cfg;
    let refined = stage2_geometry(s1, s2)?;
    let sdf = TrainedSdf::new(backend, refined.as_ref().unwrap_or(s1.model()), rotation).context("meshing the trained SDF")?;
    let material = LearnedMaterial { model: &s2.model, rotation, feature: 16.0 * cfg.sizes.pixel_footprint };
    let mesh = crate::mesh::MeshConfig { face_tolerance_deg: asset.face_tolerance_deg(), ..super::cli::trained_mesh_config(&cfg.sizes, asset.resolution, asset.error_bound) };
    let provenance = serde_json::json!({
        "method": "stage 1 (trained SDF) + stage 2 (SG environment, material autoencoder, indirect light)",
        "scene": rs.scene.display().to_string(),
        "format": rs.format,
        "preset": cfg.preset,
        "indirect": s2.model.cfg.indirect,
        "lobes": s2.model.cfg.lobes,
        "steps": { "geometry": s1.step, "material": s2.step },
    });
    let ecfg = asset.capture_export_config(rs.scale, mesh, default_name, provenance, ctx);
    let env = s2.model.env_sgs(rotation);
    let t = Instant::now();
    let report = crate::export::export_asset_with(backend, &sdf, &material, Some(&env), &ecfg, &asset.out, &ctx.spinner("export"))?;
    ctx.say(format!(
        "export: {} triangles (error bound {:.4} normalised units, watertight {}), {} UV charts, {}² albedo/roughness{} textures from the material field, learned environment ({} lobes), files in {} [{:.2} s]",
        report.mesh.triangles,
        report.mesh.error_bound,
        report.mesh.watertight,
        report.uv_charts,
        report.texture_size,
        if s2.model.cfg.metallic { "/metallic" } else { "" },
        env.lobes.len(),
        asset.out.display(),
        t.elapsed().as_secs_f64()
    ));
    Ok(report)
}
