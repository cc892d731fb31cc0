//! Stage 1: geometry from photos. An SDF field and a radiance net trained from posed, masked
//! photos (IDR), on either compute backend through one loop.
//!
//! One iteration, `rays` pixels drawn uniformly over the training views (the draw is seeded by
//! `(seed, step)`, so a resumed run draws what an uninterrupted one would):
//! 1. trace every ray through the current field ([`crate::render::trace`], no gradient);
//! 2. *surface rays* (hit and inside the mask): colour `c = R(x, PE4(−v), ∇f(x), feature(x))`,
//!    L1 against the photo (sRGB values, as IDR);
//! 3. *mask rays* (the others): BCE on `sigmoid(−α·f(x_m))` against the mask, weight
//!    `mask_weight/α`, α doubled at fixed fractions of the run. `x_m` is the min-SDF point along
//!    a ray that missed (from the tracer's sampler); for a ray that hit outside the mask it is the
//!    min-SDF point along the ray in the paper preset (IDR) and the hit itself in the fast preset
//!    ([`Stage1Config::out_of_mask_min_sdf`]: IDR's point lies deep inside the object, where a
//!    hash grid's local cells only grow interior bubbles; the hit moves the wrong silhouette);
//! 4. eikonal `(|∇f| − 1)²` at uniform points in the bounding cube and at the surface points;
//! 5. one batched first-order backward through the field ([`SdfField::value_and_grad`]: normals
//!    are central differences, so no second-order pass is needed) and the radiance net, then Adam.
//!
//! The surface point is differentiable by implicit differentiation,
//! `x(θ) = x0 − v·(f(x0;θ) − f(x0;θ0))/(∇f(x0)·v)`: the colour's total derivative along the ray,
//! `∂c/∂x·v` (through the radiance net's position input, the feature and the normal), is taken by
//! a forward difference of the whole forward, `(c(x0 + ε v) − c(x0))/ε` (the loss computes `c(x0)`
//! anyway; the central difference this replaced cost 11% more field evaluations per step and gave
//! the same Chamfer, NC and held-out PSNR within seed noise on the example and the bowl), and
//! `dL/dc · ∂c/∂x·v · (−1/(∇f·v))`
//! is added to `dL/df(x0)`. Everything stays first-order, and the whole pixel's gradient matches
//! central differences of re-traced renders (tested).
//!
//! On the cpu backend the parameters and Adam live on the host. On wgpu, where every field
//! evaluation runs on the device ([`SdfField::evaluates_on_device`]: the fast preset's hash grid,
//! or the paper preset's parameter-free encoding), the SDF's parameters and Adam moments stay
//! there ([`Stage1Config::device_optimiser`]), and so do the appearance grid's (encoded and
//! differentiated there, [`Model::pin_appearance`]): the gradients are checked and applied on the
//! device and the host copy is refreshed only when read ([`Trainer::sync_host`], checkpoints).
//! The radiance MLP keeps a host Adam. Either way, a step whose gradient holds NaN/Inf anywhere is
//! skipped and counted, never applied.

use std::path::{Path, PathBuf};

use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::backend::gpu::GpuBuffer;
use crate::backend::{Backend, BackendError, Tensor};
use crate::nn::adam::{adam_update_host, host_grad_norm, AdamConfig, AdamItem, AdamState};
use crate::nn::encoding::{encoding_forward_cpu, EncodingConfig};
use crate::nn::field::{Encoder, FieldEncoding, FieldOutputGrads, FieldOutputs, PositionEncoder, SdfField, SdfFieldConfig};
use crate::nn::mlp::{Activation, Init, Mlp, MlpConfig};
use crate::nn::params::ParamStore;
use crate::render::grid::SdfGrid;
use crate::render::{min_sdf_along, sphere_interval, trace, Rays, SdfBatch, TraceConfig, TraceMode};
use crate::scene::{Camera, View};
use crate::util::DataError;

/// Speed/accuracy preset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Hash grid + 2×64 SDF MLP, 2×64 radiance net: minutes on a CPU, seconds on a GPU.
    Fast,
    /// The paper's networks: PE6 + 8×512 SDF (skip, weight norm), 4×512 radiance net.
    Paper,
}

impl Preset {
    pub fn name(self) -> &'static str {
        match self {
            Preset::Fast => "fast",
            Preset::Paper => "paper",
        }
    }
}

/// How the SDF starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InitMode {
    /// Geometric (sphere) initialisation, as the paper.
    Sphere,
    /// Sphere init, then fit to the visual hull's signed distance before photometric training.
    Hull,
}

/// Sizes the scene decides, and why (reported).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneSizes {
    /// Mean photo pixel footprint at the object (normalised units).
    pub pixel_footprint: f32,
    /// Finest hash-grid resolution (cells over [-1, 1]): one cell per pixel footprint, clamped.
    pub grid_finest: u32,
    pub grid_log2_table: u32,
    /// Visual hull resolution for the hull init.
    pub hull_resolution: usize,
    /// Marching grid nodes along the longest side at export.
    pub mesh_resolution: usize,
    pub train_views: usize,
    pub train_pixels: usize,
    pub held_out_views: usize,
}

/// Fewest stage-1 steps of the fast preset: what a capture of up to 2M photo pixels gets (the
/// bundled example, 960k pixels, takes two passes over its pixels in them).
pub const FAST_MIN_ITERATIONS: u64 = 500;
/// Most stage-1 steps the fast preset chooses for a large capture (3× the fewest: the bound on
/// this project's 2-core machine is about 12 minutes of stage-1 training on DTU scan37).
pub const FAST_MAX_ITERATIONS: u64 = 1500;

/// Stage-1 steps of the fast preset for a scene: enough for `rays` per step to pass over every
/// training pixel once, within [`FAST_MIN_ITERATIONS`]..=[`FAST_MAX_ITERATIONS`].
///
/// At a fixed 500 steps a real capture saw each pixel a third of a time or less (DTU scan37's
/// 5.9M pixels: 0.35 passes; the Ethiopian head's 15M: 0.14) and ended under-fitted: DTU's
/// training-view PSNR was still climbing at the last step. Side by side (`train --iterations`,
/// cpu, this 2-core box), DTU scan37 500 -> 1500 steps: 18.74 -> 21.23 dB, mask IoU 0.971 ->
/// 0.982, the thin scissors and the clamp whole instead of broken; the Ethiopian head (capped)
/// 24.09 -> 25.03 dB on its held-out views, mask IoU 0.981 -> 0.983. The synthetic scenes (960k
/// pixels) keep 500.
pub fn fast_iterations(train_pixels: usize, rays: usize) -> u64 {
    (train_pixels as u64).div_ceil(rays.max(1) as u64).clamp(FAST_MIN_ITERATIONS, FAST_MAX_ITERATIONS)
}

/// Everything that defines a stage-1 run (saved beside every checkpoint).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stage1Config {
    pub preset: Preset,
    pub field: SdfFieldConfig,
    pub radiance_widths: Vec<usize>,
    /// Frequencies of the view-direction encoding (input included).
    pub view_freqs: u32,
    pub trace: TraceConfig,
    pub init: InitMode,
    pub hull_fit_steps: u64,
    /// Steps of the fit to a given mesh (`train --init-mesh`): it is the geometry, kept as fitted
    /// with `lr_field = 0`, so it is fitted closer than the hull (which training then reshapes).
    #[serde(default = "default_mesh_fit_steps")]
    pub mesh_fit_steps: u64,
    /// Points per hull-fit step (half near the hull's surface, half uniform).
    #[serde(default = "default_hull_fit_points")]
    pub hull_fit_points: usize,
    /// The hull fit's learning rate decays exponentially from `hull_fit_lr` to this fraction of it.
    #[serde(default = "default_hull_fit_lr")]
    pub hull_fit_lr: f32,
    #[serde(default = "default_hull_fit_lr_final")]
    pub hull_fit_lr_final: f32,
    /// Rounds of photo-consistency carving of the hull's concavities before the hull fit
    /// (`photo::carve_concavities`, on a grid of at most 96 voxels a side; 0 = the plain visual hull).
    #[serde(default)]
    pub concavity_rounds: usize,
    pub rays: usize,
    pub iterations: u64,
    pub lr_field: f32,
    pub lr_radiance: f32,
    /// Learning rate at the end of the run relative to the start (exponential decay).
    pub lr_final_factor: f32,
    pub eikonal_weight: f32,
    pub eikonal_points: usize,
    pub mask_weight: f32,
    pub alpha_init: f32,
    /// α doubles at these fractions of the run (IDR: 250/500/750/1000/1250 of 2000 epochs).
    pub alpha_doublings: Vec<f32>,
    /// Samples along a mask ray that hit outside the mask.
    pub mask_samples: usize,
    /// For a ray that hits outside the mask, the mask term's point: the min-SDF point along the
    /// ray (IDR; deep inside the object, which moves a global MLP's whole shape) or, when false,
    /// the hit itself (moves the surface where the silhouette is wrong: what a local hash grid needs).
    pub out_of_mask_min_sdf: bool,
    /// Fraction of each batch drawn from the masks' foreground pixels (the rest: all pixels).
    pub foreground_fraction: f32,
    /// Eikonal points jittered around the surface points (normal deviation, normalised units).
    pub near_surface_sigma: f32,
    /// Normal smoothness: weight of `|∇f(x) − ∇f(x + δ)|²` between each surface point and its
    /// jittered eikonal point (δ ~ N(0, near_surface_sigma²)); zero for a true SDF of a flat
    /// surface, it penalises curvature and the bumps a sparsely fed hash grid grows.
    #[serde(default)]
    pub smoothness_weight: f32,
    /// Weight of the multi-view photo-consistency term ([`super::multiview`]): each surface
    /// point's patch in its own photo against the nearest other photos, its slope along the ray
    /// moving the point. 0: off (run files without the field).
    #[serde(default)]
    pub photo_consistency: f32,
    /// The photo-consistency weight falls linearly to 0 at this fraction of the run (patches of
    /// 3×3 pixels place a surface to about a pixel; the colour loss takes it further).
    #[serde(default = "one")]
    pub photo_consistency_end: f32,
    /// Scale of the colour loss's gradient through the normal the radiance net is given (1: the
    /// true gradient; 0: detached, the colour then reaches the SDF only through the surface point
    /// and the feature). Through the numerical normal's stencil this path is amplified by
    /// 1/(2·grad_step), so a hash grid learns texture as normal bumps rather than as features.
    #[serde(default = "one")]
    pub normal_gradient_scale: f32,
    /// The colour loss moves the surface point along the ray (implicit differentiation). Off:
    /// the colour reaches the SDF only through the normal and the feature.
    #[serde(default = "yes")]
    pub colour_moves_point: bool,
    /// The colour moves only the surface points a ray meets at `−∇f·v` above this (the cosine
    /// of the angle between the ray and the surface's normal): the point's move along the ray,
    /// `−v/(∇f·v)`, grows without bound toward grazing, and the few photos that see a part only
    /// at a grazing angle then push it around with their noise. Run files without it read
    /// IDR-like 0.05.
    #[serde(default = "default_grazing_cos")]
    pub grazing_cos: f32,
    /// Coarse to fine (hash grid): this fraction of the levels is active at the start (and in
    /// the hull fit), all of them from `coarse_to_fine_end` of the run on (linear in between).
    pub coarse_levels: f32,
    pub coarse_to_fine_end: f32,
    /// The SDF is held fixed for this fraction of the run while the radiance net learns the
    /// colours (before that, colour gradients only move the surface at random). Those steps
    /// compute the colour term alone (`radiance_loss_and_grad`), except the last
    /// `warmup_priming_steps` of them.
    pub radiance_warmup: f32,
    /// The last this many steps of the radiance warm-up are whole steps (the SDF's gradient
    /// computed, its rate 0), which prime the SDF's Adam moments before its training starts:
    /// none after a hull fit, every one from a sphere (the preset's figures). Run files without
    /// it computed every warm-up step whole.
    #[serde(default = "default_warmup_priming_steps")]
    pub warmup_priming_steps: u64,
    /// The radiance net's feature comes from its own hash grid (the SDF grid's sizes), trained at
    /// the radiance net's rate, instead of from the SDF network's feature output (IDR's, which the
    /// colour loss then trains inside the SDF's own hash entries: texture learnt as geometry).
    #[serde(default)]
    pub appearance_grid: bool,
    /// This fraction of the run (from step 0) renders each ray by NeuS's volume rendering
    /// ([`crate::render::volume`]) instead of at its first hit: colour and mask then reach every
    /// sample along the ray. 0 = surface rendering throughout (the default, and run files
    /// without the field): measured on the bowl (0.25, 2000 iterations), it raised held-out PSNR
    /// 26.96 -> 28.10 dB but not the geometry (Chamfer 1.420% -> 1.516%; the moat between ball
    /// and floor stays filled) at about 1.5x stage 1's time.
    #[serde(default)]
    pub volume_fraction: f32,
    /// Rays per volume-rendered step (0 = `rays`).
    #[serde(default)]
    pub volume_rays: usize,
    /// Uniform samples per ray that place the importance samples (forward only).
    #[serde(default = "default_volume_coarse")]
    pub volume_coarse: usize,
    /// Importance samples per ray that are rendered (value, gradient and radiance each).
    #[serde(default = "default_volume_fine")]
    pub volume_fine: usize,
    /// The logistic sharpness `s` at the start and at the end of the volume phase (geometric in
    /// between), in units of 1 / pixel footprint: `1/s` is the width the surface is spread over.
    #[serde(default = "default_volume_sharpness")]
    pub volume_sharpness: [f32; 2],
    /// Weight of the BCE between the rendered opacity and the mask.
    #[serde(default = "default_volume_mask_weight")]
    pub volume_mask_weight: f32,
    /// Adam leaves entries whose gradient is exactly 0 untouched
    /// ([`AdamConfig::skip_zero_gradients`]): most hash-table entries, which no ray of a step
    /// reaches. Run files without the field read false and resume as they ran.
    #[serde(default)]
    pub sparse_adam: bool,
    /// On wgpu, keep the SDF's and the appearance grid's parameters and Adam moments on the
    /// device and run Adam there (see the module docs): a step then neither reads the grids'
    /// dense gradients back nor uploads their parameters. Where some evaluation would read the
    /// host copy (an encoding that runs on the host), the host path is used whatever this says.
    #[serde(default = "yes")]
    pub device_optimiser: bool,
    /// Camera pose refinement ([`super::pose`]): each training view's pose is corrected with
    /// the SDF, at this Adam rate in pixels at the object per step (decaying with the run's
    /// rate), from the SDF's first trained step ([`POSE_LR`] in the presets). 0: the poses as
    /// read (`--fixed-poses`, and run files without the field).
    #[serde(default)]
    pub pose_lr: f32,
    /// The pose refinement's colour slopes across the ray are taken at every this-many-th surface
    /// ray ([`RayGrads::across_every`]; 1: all, each costing two more colour evaluations).
    #[serde(default = "default_pose_across_every")]
    pub pose_across_every: u32,
    /// After this fraction of the iterations, a hull-initialised run whose refinement has moved a
    /// view by more than half a hull voxel carves the hull again through the refined poses and
    /// fits the SDF to it ([`POSE_RECARVE_AT`] in the presets; `train::cli::recarve_hull_from_poses`).
    /// 0: never (a mesh init, and run files without the field).
    #[serde(default)]
    pub pose_recarve_at: f32,
    pub seed: u64,
    pub checkpoint_every: u64,
    pub downscale: usize,
    /// The scene was read with `--keep-all-views` (stage 2 reads it the same way).
    #[serde(default)]
    pub keep_all_views: bool,
    pub sizes: SceneSizes,
}

impl Stage1Config {
    /// The preset's configuration sized for `views` (the training views, normalised frame).
    pub fn for_scene(preset: Preset, mode: TraceMode, init: InitMode, views: &[&View], held_out: usize, downscale: usize) -> Self {
        let footprint = pixel_footprint(views);
        let grid_finest = ((2.0 / footprint.max(1e-6)).round() as u32).clamp(64, 1024);
        let grid_log2_table = ((2.0 * (grid_finest as f64).powi(2)).log2().ceil() as u32).clamp(14, 19);
        let hull_resolution = (((2.0 / footprint.max(1e-6)) / 2.0).round() as usize).clamp(64, 192);
        let mesh_resolution = (((1.6 / footprint.max(1e-6)) / 1.5).round() as usize).clamp(96, 384);
        let sizes = SceneSizes {
            pixel_footprint: footprint,
            grid_finest,
            grid_log2_table,
            hull_resolution,
            mesh_resolution,
            train_views: views.len(),
            train_pixels: views.iter().map(|v| v.camera.width * v.camera.height).sum(),
            held_out_views: held_out,
        };
        // The fast preset spends its sampler where sphere tracing says the answer is, and gives
        // sphere tracing 20 steps so fewer rays fall back to sampling their whole segment.
        // `bench train --variant fast-refined-hull --set trace=...` (cpu, 2000 iterations), IDR's
        // sampler -> local 16 samples + 20 steps: field evaluations per step 69.5k -> 38.4k on the
        // example (steps 1.34x faster side by side, 0.127 -> 0.095 s), Chamfer / NC example 0.164% / 0.984 ->
        // 0.169% / 0.984, glossy 0.254% / 0.973 -> 0.261% / 0.973, bowl 1.425% / 0.925 ->
        // 1.420% / 0.925. The paper preset keeps IDR's tracing.
        let trace = TraceConfig { sphere_steps: 20, local_samples: 16, ..TraceConfig::new(mode) };
        // The fast preset; the paper preset changes the networks and their training below.
        let mut field = SdfFieldConfig::fast();
        field.encoding = FieldEncoding::hash_grid(grid_finest, grid_log2_table);
        field.grad_step = (0.5 * footprint).clamp(5e-4, 5e-3);
        let fast_rays = 4096;
        let fast = Self {
            preset,
            field,
            radiance_widths: vec![64, 64],
            view_freqs: 4,
            trace,
            init,
            hull_fit_steps: 200,
            // 200 -> 600 steps on the scenes' ground-truth meshes (96^3 distance grid, frozen
            // geometry): fit loss bowl 0.0089 -> 0.0029, example 0.0011 -> 0.0006; held-out mask IoU
            // bowl 0.912 -> 0.992 (its thin walls), example 0.992 -> 0.996.
            mesh_fit_steps: default_mesh_fit_steps(),
            hull_fit_points: default_hull_fit_points(),
            hull_fit_lr: default_hull_fit_lr(),
            // Run files written before this field existed read it as 1.0 (the constant rate they
            // were trained with, `default_hull_fit_lr_final`).
            hull_fit_lr_final: 0.1,
            concavity_rounds: 4,
            // 4096 rays x 500 steps at twice the rates, not 1024 x 2000: the same rays in a quarter
            // of the steps. `bench train --variant fast-refined-hull` (cpu, this 2-core box), field
            // Chamfer / NC / held-out dB, shipped mesh Chamfer / face NC, 1024 x 2000 -> 4096 x 500:
            // example 0.166% / 0.9838 / 28.47, 0.171% / 0.9804 -> 0.165% / 0.9842 / 28.19, 0.170% /
            // 0.9809; glossy 0.252% / 0.9734 / 22.34, 0.253% / 0.9710 -> 0.252% / 0.9737 / 22.35,
            // 0.263% / 0.9714; bowl 1.368% / 0.9208 / 27.68, 1.379% / 0.9187 -> 1.369% / 0.9222 /
            // 27.43, 1.369% / 0.9216; example seed 1 0.159% / 0.9844 / 28.78, 0.165% / 0.9807 ->
            // 0.158% / 0.9848 / 28.69, 0.164% / 0.9812. Stage-1 training of the example 197.5 ->
            // 138.0 s side by side (the per-step work that does not grow with the rays: eikonal
            // points, Adam, the training thread's glue), and a GPU step, bound by launches and
            // round trips rather than arithmetic, is paid 500 times instead of 2000. At 4096 x 500
            // with the old rates the example reached 0.177% / 27.93 dB, at 8192 x 250 0.191% /
            // 27.21 dB.
            rays: fast_rays,
            // Earlier, at 1024 rays: `bench train --variant fast-refined-hull --set iterations=N`
            // (cpu), 1000 -> 2000, Chamfer / NC: example 0.190% / 0.983 -> 0.164% / 0.984, glossy
            // 0.295% / 0.971 -> 0.254% / 0.973, bowl 1.433% / 0.924 -> 1.425% / 0.925; on the example's stage 2
            // (`bench material`, 32 lobes, ours, 4 views) albedo 25.54 -> 25.82 dB, normal error
            // 3.96 -> 3.61 degrees, novel view 28.45 -> 28.64 dB, relit 26.28 / 27.67 -> 26.10 / 27.62
            // (after per-channel scale 27.37 / 28.80 -> 27.55 / 29.08). About 1.1 epochs -> 2.2 of
            // the example's 960k photo pixels at 1024 rays. Larger captures get more steps:
            // [`fast_iterations`].
            iterations: fast_iterations(sizes.train_pixels, fast_rays),
            lr_field: 4e-4,
            lr_radiance: 1e-2,
            lr_final_factor: 0.1,
            eikonal_weight: 0.1,
            eikonal_points: 512,
            mask_weight: 100.0,
            alpha_init: 50.0,
            alpha_doublings: vec![0.125, 0.25, 0.375, 0.5, 0.625],
            mask_samples: 32,
            out_of_mask_min_sdf: false,
            foreground_fraction: 0.5,
            near_surface_sigma: 0.02,
            // The hash grid grows bumps where photos disagree (the bowl's shading normals 11.4
            // degrees off the truth at 0.0). Measured with a default `train --stage geometry`, then
            // stage 2 (`train --stage material`, 32 lobes, ours), `relight` (4 views) and `eval`,
            // weight 0 -> 0.05 -> 0.2: bowl normal error 11.43 -> 9.51 -> 8.51 degrees, stage-1
            // held-out 27.36 -> 27.44 -> 27.20 dB, albedo 17.19 -> 18.58 -> 18.48 dB, relit city /
            // studio 18.43 / 21.96 -> 19.82 / 23.11 -> 19.94 / 23.26 dB, novel view 28.52 -> 29.07
            // -> 28.67 dB; example normal error 3.63 -> 3.28 -> 3.43 degrees, stage-1 held-out
            // 28.16 -> 28.34 -> 28.30 dB, albedo 27.29 -> 27.30 -> 27.12 dB, relit envmap6 / sunset
            // 27.89 / 26.78 -> 27.68 / 26.47 -> 27.60 / 26.34 dB as rendered (29.53 / 28.66 ->
            // 29.70 / 29.01 -> 29.58 / 28.72 after one scale per channel), roughness MSE 0.034 ->
            // 0.032 -> 0.041; glossy (0.05) normal error 5.61 -> 5.02 degrees, albedo 22.68 ->
            // 22.89 dB, relit 26.85 / 21.06 -> 27.04 / 21.22 dB. Stage 2 at seed 1 on the same
            // stage-1 runs, 0 -> 0.05: bowl albedo 17.27 -> 18.37 dB, relit 18.37 / 22.01 -> 19.59 /
            // 22.93 dB; example albedo 27.67 -> 27.53 dB (flat within seeds). Geometry, `bench train --variant
            // fast-refined-hull --set smoothness_weight=W` side by side, 0 -> 0.05, field Chamfer /
            // NC, shipped mesh Chamfer / face NC / triangles: example 0.169% / 0.9839, 0.173% /
            // 0.9805 / 3700 -> 0.172% / 0.9852, 0.179% / 0.9813 / 3184; bowl 1.363% / 0.9202,
            // 1.371% / 0.9193 / 17016 -> 1.390% / 0.9376, 1.390% / 0.9366 / 8992; glossy (0.05)
            // 0.253% / 0.9772, 0.253% / 0.9750. (normal_gradient_scale 0.3 instead, on the bowl:
            // normal error 13.3 degrees, held-out 26.42 dB.) The paper preset's MLP is smooth by
            // construction: 0 there.
            smoothness_weight: 0.05,
            // `bench train --variant fast-refined-hull` (cpu, seed 0, the preset's steps), off ->
            // weight 4 fading out at half the run, field Chamfer / NC, shipped mesh Chamfer / face
            // NC, held-out dB: bowl 1.354% / 0.9399, 1.352% / 0.9388, 28.19 -> 1.243% / 0.9410,
            // 1.252% / 0.9386, 28.61; the example cut to 8 photos 0.604% / 0.9511, 0.600% /
            // 0.9487, 22.03 -> 0.565% / 0.9526, 0.563% / 0.9502, 22.48; example 0.165% / 0.9858,
            // 0.173% / 0.9824, 28.53 -> 0.174% / 0.9853, 0.183% / 0.9821, 28.69; glossy 0.224% /
            // 0.9797, 0.230% / 0.9778, 22.39 -> 0.232% / 0.9795, 0.238% / 0.9778, 22.42 (the last
            // two within a seed's spread: the example at seed 1 reads 0.158%). Held to the end (`--set
            // photo_consistency_end=1`) it pulls finished surfaces toward its own pixel-scale
            // optimum: example 0.196%, bowl 1.201%. Real captures (`train --stage geometry
            // --iterations 500`), held-out (DTU: training-view) PSNR / mask IoU: the Ethiopian head
            // 24.04 / 0.9802 -> 24.10 / 0.9814, DTU scan37 19.22 / 0.9680 -> 19.89 / 0.9679.
            photo_consistency: 4.0,
            photo_consistency_end: 0.5,
            // 0.3 measured better geometry on three scenes (1000 iterations, Chamfer / NC / mask
            // IoU / stage-1 held-out dB, 1.0 → 0.3): example 0.499%/0.968/0.968/20.0 →
            // 0.361%/0.976/0.976/19.6, bowl 3.50%/0.913/0.981/18.9 → 3.41%/0.914/0.987/18.3,
            // glossy 0.473%/0.946/0.974/19.2 → 0.442%/0.949/0.977/18.8; but the default bake's
            // stage-2 held-out PSNR on the example fell 21.65 → 18.99 dB with it, so 1.0 stays.
            normal_gradient_scale: 1.0,
            colour_moves_point: true,
            // `bench train --variant fast-refined-hull` (cpu, seed 0, default steps), 0.05 -> 0.2,
            // field Chamfer / NC, shipped mesh Chamfer / face NC, held-out dB: example 0.172% /
            // 0.9852, 0.179% / 0.9813, 28.34 -> 0.165% / 0.9858, 0.173% / 0.9824, 28.53; glossy
            // 0.253% / 0.9772, 0.248% / 0.9753, 22.27 -> 0.224% / 0.9797, 0.230% / 0.9778, 22.39;
            // bowl 1.390% / 0.9376, 1.393% / 0.9356, 27.44 -> 1.354% / 0.9399, 1.352% / 0.9388,
            // 28.19. 0.35 on the example: 0.171% / 0.9858, 0.182% / 0.9814, 28.41. Real captures
            // (`train --stage geometry --iterations 500`), held-out (DTU: training-view) PSNR / mask
            // IoU: the Ethiopian head 24.04 dB / 0.9800 -> 24.04 / 0.9802, DTU scan37 19.11 /
            // 0.9669 -> 19.22 / 0.9680.
            grazing_cos: 0.2,
            // Coarse to fine from a sphere; a hull fit has already set every level.
            coarse_levels: if init == InitMode::Hull { 1.0 } else { 0.5 },
            coarse_to_fine_end: 0.5,
            radiance_warmup: 0.1,
            // Colour-only warm-up steps, side by side against whole ones (`bench train`, cpu,
            // the preset's 500 steps): from the hull the figures are level (example field
            // 0.176% / NC 0.9849 against 0.177% / 0.9848, bowl 1.261% / 0.9398 against 1.260% /
            // 0.9386) and the 50 warm-up steps take 4.9 s against 11–14 s. From a sphere the
            // whole warm-up's SDF gradients are what damp its first Adam steps: without them the
            // example ends at 1.54 / 1.32 / 1.07% against 1.28 / 1.09 / 0.93% (seeds 0 / 1 / 2),
            // and the last 10 steps alone do not restore it (1.59 / 1.27%), so a sphere primes
            // on every warm-up step.
            warmup_priming_steps: if init == InitMode::Hull { 0 } else { u64::MAX },
            // Measured (1000 iterations, `bench train --variant fast-refined-hull`): on the example
            // Chamfer 0.499% → 0.190%, NC 0.968 → 0.983, held-out 20.0 → 25.5 dB, mask IoU
            // 0.968 → 0.989 (the hull: 0.301% / 0.978).
            appearance_grid: true,
            volume_fraction: 0.0,
            volume_rays: 0,
            volume_coarse: default_volume_coarse(),
            volume_fine: default_volume_fine(),
            volume_sharpness: default_volume_sharpness(),
            volume_mask_weight: default_volume_mask_weight(),
            // `bench train --variant fast-refined-hull [--set sparse_adam=false]` (cpu, 2000
            // iterations), dense -> sparse: example Chamfer / NC 0.174% / 0.9830 -> 0.166% / 0.9838
            // (the shipped mesh 0.179% / 0.9799 -> 0.171% / 0.9804), bowl 1.423% / 0.9195 ->
            // 1.374% / 0.9205. Stage 1 on 2^19 tables (from a sphere, interleaved runs): the
            // Ethiopian head 7.1 -> 9.1 it/s, a 1600² capture read at 1/2 4.1 -> 5.3 it/s.
            sparse_adam: true,
            device_optimiser: true,
            // Camera poses refined with the SDF (`POSE_LR`'s figures; `--fixed-poses` keeps them).
            pose_lr: POSE_LR,
            pose_across_every: 4,
            pose_recarve_at: POSE_RECARVE_AT,
            seed: 0,
            // About 14 s of this 2-core box's training between checkpoints (50 steps of 4096 rays).
            checkpoint_every: 50,
            downscale,
            keep_all_views: false,
            sizes,
        };
        match preset {
            Preset::Fast => fast,
            Preset::Paper => Self {
                field: SdfFieldConfig::paper(),
                radiance_widths: vec![512; 4],
                rays: 2048,
                iterations: 2000,
                lr_field: 1e-4,
                lr_radiance: 1e-4,
                lr_final_factor: 0.25,
                eikonal_points: 1024,
                mask_samples: 100,
                out_of_mask_min_sdf: true,
                checkpoint_every: 50,
                // The hash grid's 5e-3 sends this MLP positive everywhere: on the example (the
                // preset's 200 steps at 2048 points) stage 1 then traced no surface at all
                // (`surface_rays` 0 in every step), and on an H200 `bench train` ended with "no
                // inside anywhere". Fitted to an ellipsoid's distance grid (64^3, 1024 points,
                // 100 steps, decaying to 0.1 of the rate), final loss: 5e-3 diverges by step 10
                // (0.027 -> 0.066, its centre at +1.07 after 40 steps), 2e-3 0.0078 (recovering
                // from a rise to 0.067), 1e-3 0.0025, 5e-4 0.0022, 2e-4 0.0023.
                hull_fit_lr: 5e-4,
                appearance_grid: false,
                smoothness_weight: 0.0,
                // Not measured on the paper preset: IDR's losses alone.
                photo_consistency: 0.0,
                grazing_cos: 0.05,
                trace: TraceConfig::new(mode),
                ..fast
            },
        }
    }

    pub fn validate(&self) -> Result<(), BackendError> {
        self.trace.validate()?;
        let bad = |m: &str| Err(BackendError::Config(format!("stage 1: {m}")));
        if self.rays == 0 || self.iterations == 0 {
            return bad("rays and iterations must be > 0");
        }
        // lr_field 0 freezes the SDF (a given geometry: `train --init-mesh`); the radiance net always learns.
        if !(self.lr_field.is_finite() && self.lr_field >= 0.0 && self.lr_radiance.is_finite() && self.lr_radiance > 0.0) {
            return bad("learning rates must be > 0 (lr_field >= 0: 0 keeps the geometry as initialised)");
        }
        if self.checkpoint_every == 0 {
            return bad("checkpoint_every (the checkpoint interval, --checkpoint-every) must be > 0");
        }
        if !(self.grazing_cos.is_finite() && (0.0..1.0).contains(&self.grazing_cos)) {
            return bad("grazing_cos must be in [0, 1)");
        }
        if !(self.normal_gradient_scale.is_finite() && (0.0..=1.0).contains(&self.normal_gradient_scale)) {
            return bad("normal_gradient_scale must be in [0, 1]");
        }
        if !(self.photo_consistency.is_finite() && self.photo_consistency >= 0.0 && self.photo_consistency_end > 0.0 && self.photo_consistency_end <= 1.0) {
            return bad("photo_consistency must be >= 0 and photo_consistency_end in (0, 1]");
        }
        if !((0.0..=1.0).contains(&self.volume_fraction)
            && self.volume_coarse >= 2
            && self.volume_fine >= 2
            && self.volume_sharpness.iter().all(|s| s.is_finite() && *s > 0.0)
            && self.volume_mask_weight.is_finite()
            && self.volume_mask_weight >= 0.0)
        {
            return bad("volume rendering: volume_fraction in [0, 1], at least 2 coarse and 2 fine samples, sharpness > 0, mask weight >= 0");
        }
        if self.hull_fit_points == 0 || !(self.hull_fit_lr.is_finite() && self.hull_fit_lr > 0.0) || !(self.hull_fit_lr_final > 0.0 && self.hull_fit_lr_final <= 1.0) {
            return bad("hull fit: points must be > 0, its learning rate > 0 and its final factor in (0, 1]");
        }
        if !(self.pose_recarve_at.is_finite() && (0.0..1.0).contains(&self.pose_recarve_at)) {
            return bad("pose_recarve_at must be in [0, 1) (a fraction of the iterations; 0: never)");
        }
        let non_negative = [
            ("eikonal_weight", self.eikonal_weight),
            ("mask_weight", self.mask_weight),
            ("smoothness_weight", self.smoothness_weight),
            ("near_surface_sigma", self.near_surface_sigma),
            ("pose_lr", self.pose_lr),
        ];
        if let Some(name) = first_failing(&non_negative, |v| v.is_finite() && v >= 0.0) {
            return bad(&format!("{name} must be finite and >= 0"));
        }
        if !(self.alpha_init.is_finite() && self.alpha_init > 0.0) {
            return bad("alpha_init (the mask loss's sharpness) must be finite and > 0");
        }
        let fractions = [
            ("lr_final_factor", self.lr_final_factor),
            ("coarse_levels", self.coarse_levels),
            ("coarse_to_fine_end", self.coarse_to_fine_end),
            ("foreground_fraction", self.foreground_fraction),
        ];
        if let Some(name) = first_failing(&fractions, |v| (0.0..=1.0).contains(&v)) {
            return bad(&format!("{name} must be in [0, 1]"));
        }
        if !(0.0..1.0).contains(&self.radiance_warmup) || self.alpha_doublings.iter().any(|d| !(0.0..=1.0).contains(d)) {
            return bad("radiance_warmup must be in [0, 1) and every alpha_doublings entry in [0, 1] (fractions of the iterations)");
        }
        Ok(())
    }

    /// The photo-consistency weight at `step` ([`Stage1Config::photo_consistency_end`]).
    pub fn photo_consistency_at(&self, step: u64) -> f32 {
        let frac = step as f32 / self.iterations.max(1) as f32;
        let end = self.photo_consistency_end;
        if end <= 0.0 {
            return 0.0;
        }
        self.photo_consistency * (1.0 - frac / end).max(0.0)
    }

    /// α at `step`.
    pub fn alpha_at(&self, step: u64) -> f32 {
        let frac = step as f32 / self.iterations.max(1) as f32;
        self.alpha_init * 2f32.powi(self.alpha_doublings.iter().filter(|&&d| frac >= d).count() as i32)
    }

    /// Hash-grid levels active at `step` (None: the encoding has no levels, or all are active).
    pub fn active_levels_at(&self, step: u64) -> Option<usize> {
        let FieldEncoding::HashGrid { levels, .. } = self.field.encoding else {
            return None;
        };
        let frac = step as f32 / self.iterations.max(1) as f32;
        let t = if self.coarse_to_fine_end > 0.0 { (frac / self.coarse_to_fine_end).min(1.0) } else { 1.0 };
        let start = (self.coarse_levels.clamp(0.0, 1.0) * levels as f32).ceil().max(1.0);
        let n = (start + t * (levels as f32 - start)).floor() as usize;
        (n < levels).then_some(n)
    }

    /// Whether `step` is volume rendered, and the logistic sharpness `s` (normalised units) then.
    pub fn volume_at(&self, step: u64) -> Option<f32> {
        let end = self.volume_fraction * self.iterations as f32;
        if (step as f32) >= end {
            return None;
        }
        let t = step as f32 / end.max(1.0);
        let [a, b] = self.volume_sharpness;
        Some(a * (b / a).powf(t) / self.sizes.pixel_footprint.max(1e-6))
    }

    /// Learning-rate factor at `step` (exponential from 1 to `lr_final_factor`).
    pub fn lr_factor(&self, step: u64) -> f32 {
        let frac = (step as f32 / self.iterations.max(1) as f32).min(1.0);
        self.lr_final_factor.powf(frac)
    }

    /// The SDF field's configuration (no feature output when the appearance has its own grid).
    pub fn sdf_field(&self) -> SdfFieldConfig {
        let mut f = self.field.clone();
        if self.appearance_grid {
            f.feature_dim = 0;
        }
        f
    }

    /// The appearance grid's encoder (the scene's grid sizes, as the SDF's; no raw position), if any.
    pub fn appearance_encoder(&self) -> Option<PositionEncoder> {
        if !self.appearance_grid {
            return None;
        }
        let mut e = FieldEncoding::hash_grid(self.sizes.grid_finest, self.sizes.grid_log2_table).encoder();
        e.raw_xyz = false;
        Some(e)
    }

    /// Features the radiance net reads per point.
    pub fn feature_dim(&self) -> usize {
        self.appearance_encoder().map_or(self.field.feature_dim, |e| e.out_dim())
    }

    pub fn radiance_mlp(&self) -> MlpConfig {
        let view_dim = 3 * (1 + 2 * self.view_freqs as usize);
        MlpConfig {
            in_dim: 3 + view_dim + 3 + self.feature_dim(),
            widths: self.radiance_widths.clone(),
            out_dim: 3,
            activation: Activation::Relu,
            output_activation: Activation::Sigmoid,
            skip_layers: vec![],
            weight_norm: false,
        }
    }
}

fn one() -> f32 {
    1.0
}
fn yes() -> bool {
    true
}
fn default_volume_coarse() -> usize {
    64
}
fn default_volume_fine() -> usize {
    32
}
/// `bench train` on the bowl with `volume_fraction` 0.25 (cpu, 2000 iterations), sharpness
/// [0.25, 2] / [1, 4] / [2, 8]: Chamfer 1.677% / 1.562% / 1.516%, held-out 26.82 / 27.98 /
/// 28.10 dB (surface rendering throughout: 1.420%, 26.96 dB).
fn default_volume_sharpness() -> [f32; 2] {
    [2.0, 8.0]
}
fn default_volume_mask_weight() -> f32 {
    1.0
}
fn default_pose_across_every() -> u32 {
    1
}
fn default_warmup_priming_steps() -> u64 {
    u64::MAX
}
fn default_grazing_cos() -> f32 {
    0.05
}
fn default_mesh_fit_steps() -> u64 {
    600
}
fn default_hull_fit_points() -> usize {
    2048
}
fn default_hull_fit_lr() -> f32 {
    5e-3
}
fn default_hull_fit_lr_final() -> f32 {
    1.0
}

/// `KEY=VALUE` overrides of top-level config fields (VALUE parsed as JSON, else a string).
pub fn apply_overrides(cfg: Stage1Config, overrides: &[String]) -> Result<Stage1Config, BackendError> {
    let out = override_fields(cfg, overrides)?;
    out.validate()?;
    Ok(out)
}

/// The name of the first `(name, value)` setting that `ok` refuses (a config's `validate` names it).
pub(crate) fn first_failing(settings: &[(&'static str, f32)], ok: impl Fn(f32) -> bool) -> Option<&'static str> {
    settings.iter().find(|(_, v)| !ok(*v)).map(|(name, _)| *name)
}

/// `KEY=VALUE` overrides of any serialisable config's top-level fields (VALUE parsed as JSON, else
/// a string); the caller validates the result.
pub fn override_fields<C: Serialize + serde::de::DeserializeOwned>(cfg: C, overrides: &[String]) -> Result<C, BackendError> {
    if overrides.is_empty() {
        return Ok(cfg);
    }
    let mut v = serde_json::to_value(&cfg).map_err(|e| BackendError::Config(e.to_string()))?;
    for o in overrides {
        let Some((k, val)) = o.split_once('=') else {
            return Err(BackendError::Config(format!("override {o:?}: expected KEY=VALUE")));
        };
        let slot = v.get_mut(k).ok_or_else(|| BackendError::Config(format!("override {o:?}: no setting named {k:?}")))?;
        *slot = serde_json::from_str(val).unwrap_or_else(|_| serde_json::Value::String(val.to_string()));
    }
    serde_json::from_value(v).map_err(|e| BackendError::Config(format!("overrides {overrides:?}: {e}")))
}

/// Mean photo pixel footprint (normalised units) at the distance of the scene centre.
pub fn pixel_footprint(views: &[&View]) -> f32 {
    if views.is_empty() {
        return 0.01;
    }
    (views.iter().map(|v| v.camera.center().length() / v.camera.fx.max(1e-9)).sum::<f64>() / views.len() as f64) as f32
}

/// One training view: camera, sRGB colour and mask.
#[derive(Clone, Debug)]
pub struct TrainView {
    pub camera: Camera,
    /// sRGB-encoded RGB, 3 per pixel.
    pub rgb: Vec<f32>,
    pub mask: Vec<f32>,
    pub path: PathBuf,
}

/// The pixels training draws from.
#[derive(Clone, Debug)]
pub struct TrainData {
    pub views: Vec<TrainView>,
    offsets: Vec<usize>,
    /// Global indices of the foreground pixels (mask ≥ 0.5).
    foreground: Vec<u32>,
}

/// A batch of pixels.
#[derive(Clone, Debug, Default)]
pub struct Batch {
    pub rays: Rays,
    pub rgb: Vec<[f32; 3]>,
    pub mask: Vec<f32>,
    /// Each ray's training view and pixel (continuous coordinates of its centre); empty where a
    /// batch was not drawn from [`TrainData`].
    pub view: Vec<u32>,
    pub pixel: Vec<[f32; 2]>,
}

impl TrainData {
    /// Views with masks; the error names the first image without a mask, and a view whose
    /// camera does not see the bounding sphere.
    pub fn new(views: &[&View], bound: f32) -> Result<Self, DataError> {
        let mut out = Vec::with_capacity(views.len());
        for v in views {
            let Some(mask) = &v.mask else {
                return Err(DataError::new(
                    &v.image_path,
                    "no mask for this view: stage 1 needs an object mask per photo (an alpha channel, or a mask image in the scene's mask folder: mask/, masks/ or per-frame mask_path)",
                ));
            };
            let c = &v.camera;
            // The camera must see the bounding sphere: test a coarse grid of its pixels.
            let mut sees = false;
            'grid: for j in 0..9 {
                for i in 0..9 {
                    let (o, d) = c.ray((i as f64 + 0.5) * c.width as f64 / 9.0, (j as f64 + 0.5) * c.height as f64 / 9.0);
                    if sphere_interval(o.as_vec3().to_array(), d.as_vec3().to_array(), bound).is_some() {
                        sees = true;
                        break 'grid;
                    }
                }
            }
            if !sees {
                return Err(DataError::new(
                    &v.image_path,
                    "this camera does not see the object's bounding sphere (check the poses and the scene normalisation)",
                ));
            }
            let rgb: Vec<f32> = v.image.rgb().iter().map(|&x| crate::image_io::linear_to_srgb(x.clamp(0.0, 1.0))).collect();
            out.push(TrainView { camera: c.clone(), rgb, mask: mask.clone(), path: v.image_path.clone() });
        }
        if out.is_empty() {
            return Err(DataError::new(Path::new("."), "no training views"));
        }
        let mut offsets = vec![0usize];
        let mut foreground = Vec::new();
        for v in &out {
            let base = *offsets.last().unwrap();
            foreground.extend(v.mask.iter().enumerate().filter(|(_, m)| **m >= 0.5).map(|(i, _)| (base + i) as u32));
            offsets.push(base + v.camera.width * v.camera.height);
        }
        if offsets.last().copied().unwrap_or(0) > u32::MAX as usize {
            return Err(DataError::new(&out[0].path, "more than 4 billion training pixels: use --downscale"));
        }
        Ok(Self { views: out, offsets, foreground })
    }

    /// Masked (foreground) training pixels.
    pub fn foreground_pixels(&self) -> usize {
        self.foreground.len()
    }

    pub fn pixels(&self) -> usize {
        *self.offsets.last().unwrap()
    }

    /// `n` pixels: a `foreground` fraction drawn uniformly from the masks' foreground pixels, the
    /// rest uniformly from all pixels (the silhouette and the background keep the mask term fed).
    pub fn sample(&self, rng: &mut impl Rng, n: usize, foreground: f32) -> Batch {
        let total = self.pixels();
        let mut b = Batch::default();
        for _ in 0..n {
            let g = if !self.foreground.is_empty() && rng.random_range(0.0f32..1.0) < foreground {
                self.foreground[rng.random_range(0..self.foreground.len())] as usize
            } else {
                rng.random_range(0..total)
            };
            let vi = self.offsets.partition_point(|&o| o <= g) - 1;
            let v = &self.views[vi];
            let p = g - self.offsets[vi];
            let (x, y) = (p % v.camera.width, p / v.camera.width);
            let (o, d) = v.camera.ray(x as f64 + 0.5, y as f64 + 0.5);
            b.rays.origins.push(o.as_vec3().to_array());
            b.rays.dirs.push(d.as_vec3().to_array());
            b.rgb.push([v.rgb[3 * p], v.rgb[3 * p + 1], v.rgb[3 * p + 2]]);
            b.mask.push(v.mask[p]);
            b.view.push(vi as u32);
            b.pixel.push([x as f32 + 0.5, y as f32 + 0.5]);
        }
        b
    }
}

/// The two networks and their parameters.
#[derive(Debug)]
pub struct Model {
    pub field: SdfField,
    pub radiance: Mlp,
    pub view_encoding: EncodingConfig,
    /// The appearance grid ([`Stage1Config::appearance_grid`]); its parameters lead
    /// `radiance_params`.
    pub appearance: Option<PositionEncoder>,
    pub sdf_params: Vec<f32>,
    /// `[appearance grid, radiance MLP]`.
    pub radiance_params: Vec<f32>,
    /// The SDF last sampled on a grid ([`Model::sdf_grid`]) and the parameters it was sampled at.
    grid_memo: std::sync::Mutex<Option<(Vec<f32>, std::sync::Arc<SdfGrid>)>>,
    /// The appearance grid's device copy while a wgpu training step keeps its parameters there
    /// ([`Model::pin_appearance`]): the grid is then encoded and differentiated on the device,
    /// and the host copy in `radiance_params` is not read.
    appearance_device: std::sync::Mutex<Option<GpuBuffer>>,
}

/// [`Model::pin_appearance`]'s borrow: dropping it returns the model to its host copy.
pub(crate) struct AppearancePin<'a>(&'a Model);

impl Drop for AppearancePin<'_> {
    fn drop(&mut self) {
        *self.0.appearance_device.lock().unwrap_or_else(|e| e.into_inner()) = None;
    }
}

impl Model {
    pub fn new(cfg: &Stage1Config) -> Result<Self, BackendError> {
        let field = SdfField::new(cfg.sdf_field())?;
        let radiance = Mlp::new(cfg.radiance_mlp())?;
        let sdf_params = field.init(cfg.seed);
        let appearance = cfg.appearance_encoder();
        let mut radiance_params = appearance.as_ref().map(|e| e.init(cfg.seed.wrapping_add(29))).unwrap_or_default();
        radiance_params.extend(radiance.init(Init::Default, cfg.seed.wrapping_add(17)));
        Ok(Self { field, radiance, view_encoding: EncodingConfig::frequency(cfg.view_freqs), appearance, sdf_params, radiance_params, grid_memo: Default::default(), appearance_device: Default::default() })
    }

    /// The SDF sampled at `nodes³` nodes over the bounding cube `[-1, 1]³` (stage 2's secondary
    /// rays march on it), and the seconds sampling took (0 when the grid was sampled before at the
    /// same parameters, bit for bit, and is reused: the stage-2 cache and every render of a run
    /// share one).
    pub fn sdf_grid(&self, backend: &Backend, nodes: usize) -> Result<(std::sync::Arc<SdfGrid>, f64), BackendError> {
        let mut memo = self.grid_memo.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((p, g)) = memo.as_ref() {
            if g.nodes() == nodes && crate::util::same_bits(p, &self.sdf_params) {
                return Ok((g.clone(), 0.0));
            }
        }
        let t0 = std::time::Instant::now();
        let g = std::sync::Arc::new(SdfGrid::sample(&|p: &[f32]| self.sdf(backend, p), 1.0, nodes)?);
        *memo = Some((self.sdf_params.clone(), g.clone()));
        Ok((g, t0.elapsed().as_secs_f64()))
    }

    /// Take `from`'s sampled grid ([`Self::sdf_grid`]) when it was sampled at this model's SDF
    /// parameters, bit for bit: stage 2 loads the stage-1 model the same process has just trained
    /// and sampled (for its coverage), and need not sample it again.
    pub fn share_sdf_grid(&self, from: &Model) {
        let theirs = from.grid_memo.lock().unwrap_or_else(|e| e.into_inner()).clone();
        if let Some((p, g)) = theirs {
            if crate::util::same_bits(&p, &self.sdf_params) {
                *self.grid_memo.lock().unwrap_or_else(|e| e.into_inner()) = Some((p, g));
            }
        }
    }

    /// `(features the radiance net reads, appearance-grid parameters)`.
    fn radiance_split_dims(&self) -> (usize, usize) {
        match &self.appearance {
            Some(e) => (e.out_dim(), e.num_params()),
            None => (self.field.config.feature_dim, 0),
        }
    }

    /// `(appearance grid, radiance MLP)` parameters.
    pub fn radiance_split(&self) -> (&[f32], &[f32]) {
        self.radiance_params.split_at(self.appearance.as_ref().map_or(0, |e| e.num_params()))
    }

    /// The radiance net's gradient of a step that reached no surface.
    fn zero_radiance_grad(&self) -> RadianceGrad {
        let (grid, mlp) = self.radiance_split();
        (Tensor::Host(vec![0.0; grid.len()]), vec![0.0; mlp.len()])
    }

    /// The features the radiance net reads at `x` (`range` of the field outputs `o`).
    fn features(&self, backend: &Backend, x: &[[f32; 3]], o: &FieldOutputs, range: std::ops::Range<usize>) -> Result<Vec<f32>, BackendError> {
        match (&self.appearance, self.appearance_copy(backend)) {
            (Some(e), Some(p)) => {
                let f = backend.encoding_forward(&e.encoding, &p, &backend.upload(bytemuck::cast_slice(x)), x.len())?;
                backend.to_vec(&f)
            }
            (Some(e), None) => Ok(e.forward(self.radiance_split().0, bytemuck::cast_slice(x))),
            (None, _) => {
                let fd = self.field.config.feature_dim;
                Ok(o.feature[fd * range.start..fd * range.end].to_vec())
            }
        }
    }

    /// Whether the appearance grid can live on the device alone: it has parameters and the
    /// plain encoding (no raw position, every level) that the device twin computes.
    pub fn appearance_on_device(&self, backend: &Backend) -> bool {
        backend.gpu().is_some() && self.appearance.as_ref().is_some_and(|e| e.num_params() > 0 && !e.raw_xyz && e.active_levels.is_none())
    }

    /// Encode and differentiate the appearance grid with the device copy `params` while the
    /// returned borrow lives (the trainer's device optimiser holds the only current copy).
    pub(crate) fn pin_appearance(&self, params: &GpuBuffer) -> AppearancePin<'_> {
        *self.appearance_device.lock().unwrap_or_else(|e| e.into_inner()) = Some(params.clone());
        AppearancePin(self)
    }

    fn appearance_copy(&self, backend: &Backend) -> Option<Tensor> {
        backend.gpu()?;
        self.appearance_device.lock().unwrap_or_else(|e| e.into_inner()).clone().map(Tensor::Device)
    }

    /// SDF values at flattened points.
    pub fn sdf(&self, backend: &Backend, pts: &[f32]) -> Result<Vec<f32>, BackendError> {
        // Large batches in slices keep the MLP's working set bounded.
        const CHUNK: usize = 1 << 16;
        let mut out = Vec::with_capacity(pts.len() / 3);
        for c in pts.chunks(3 * CHUNK) {
            out.extend(self.field.sdf(backend, &self.sdf_params, c)?);
        }
        Ok(out)
    }

    /// The SDF as the tracer reads it: [`Model::sdf`]'s host batches and, where the field
    /// encodes on the device (the fast preset on wgpu), the same field evaluated there, so
    /// `render::trace` runs its loops on the device. The parameters are pinned on the device
    /// while it lives, so neither path compares them with their device copy per call.
    pub fn sdf_batch<'a>(&'a self, backend: &'a Backend) -> Result<ModelSdf<'a>, BackendError> {
        let pin = self.field.pin(backend, &self.sdf_params)?;
        Ok(ModelSdf { model: self, backend, device: self.field.on_device_eval(backend, &self.sdf_params)?, _pin: pin })
    }

    fn radiance_input(&self, backend: &Backend, x: &[[f32; 3]], dirs: &[[f32; 3]], o: &FieldOutputs, range: std::ops::Range<usize>) -> Result<Vec<f32>, BackendError> {
        let feat = self.features(backend, x, o, range.clone())?;
        let fd = feat.len() / x.len().max(1);
        let view: Vec<f32> = dirs.iter().flat_map(|d| [-d[0], -d[1], -d[2]]).collect();
        let venc = encoding_forward_cpu(&self.view_encoding, &[], &view, 3);
        let vd = venc.len() / dirs.len().max(1);
        let mut input = Vec::with_capacity(x.len() * self.radiance.in_dim());
        for (k, i) in range.enumerate() {
            input.extend_from_slice(&x[k]);
            input.extend_from_slice(&venc[k * vd..(k + 1) * vd]);
            input.extend_from_slice(&o.gradient[3 * i..3 * i + 3]);
            input.extend_from_slice(&feat[fd * k..fd * (k + 1)]);
        }
        Ok(input)
    }

    /// Backward of the radiance net run (`fwd`) at the points `x` (the first `x.len()` field
    /// outputs) for the colour gradient `dc` `[n, 3]`: returns the gradient of the radiance
    /// parameters, `(appearance grid, MLP)` (the grid's on the device while it is pinned there),
    /// and adds the normal (scaled by `normal_scale`) and feature gradients to `g`.
    fn radiance_backward(
        &self,
        backend: &Backend,
        rad_params: &crate::backend::Tensor,
        fwd: &crate::nn::mlp::MlpForward,
        dc: Vec<f32>,
        x: &[[f32; 3]],
        normal_scale: f32,
        g: &mut FieldOutputGrads,
        d_view: Option<&mut Vec<f32>>,
    ) -> Result<RadianceGrad, BackendError> {
        let ns = x.len();
        let fd = self.field.config.feature_dim;
        let grads = backend.mlp_backward(&self.radiance, rad_params, fwd, &backend.from_vec(dc))?;
        let (din, d_mlp) = backend.to_vec2(&grads.d_input, &grads.d_params)?;
        let id = self.radiance.in_dim();
        let rfd = self.radiance_split_dims().0;
        let vd = id - 6 - rfd;
        let mut d_feat = vec![0f32; if self.appearance.is_some() { ns * rfd } else { 0 }];
        if let Some(dv) = d_view {
            *dv = (0..ns).flat_map(|k| din[k * id + 3..k * id + 3 + vd].iter().copied()).collect();
        }
        for k in 0..ns {
            let row = &din[k * id..(k + 1) * id];
            if normal_scale != 0.0 {
                for a in 0..3 {
                    g.gradient[3 * k + a] += normal_scale * row[3 + vd + a];
                }
            }
            match self.appearance {
                Some(_) => d_feat[k * rfd..(k + 1) * rfd].copy_from_slice(&row[6 + vd..]),
                None => g.feature[k * fd..(k + 1) * fd].copy_from_slice(&row[6 + vd..]),
            }
        }
        let d_grid = match (&self.appearance, self.appearance_copy(backend)) {
            (Some(e), Some(p)) => {
                let xt = backend.upload(bytemuck::cast_slice(x));
                backend.encoding_backward(&e.encoding, &p, &xt, ns, &backend.from_vec(d_feat), false)?.0
            }
            (Some(e), None) => Tensor::Host(e.backward_params(self.radiance_split().0, bytemuck::cast_slice(x), &d_feat)),
            (None, _) => Tensor::Host(Vec::new()),
        };
        Ok((d_grid, d_mlp))
    }

    /// Colour (sRGB, [0, 1]) at surface points seen along `dirs`: forward only.
    pub fn colour(&self, backend: &Backend, x: &[[f32; 3]], dirs: &[[f32; 3]]) -> Result<Vec<[f32; 3]>, BackendError> {
        if x.is_empty() {
            return Ok(Vec::new());
        }
        let o = self.field.eval_with_gradient(backend, &self.sdf_params, bytemuck::cast_slice(x))?;
        let si = self.radiance_input(backend, x, dirs, &o, 0..x.len())?;
        let fwd = backend.mlp_forward(&self.radiance, &backend.upload(self.radiance_split().1), &backend.from_vec(si), false)?;
        let out = backend.to_vec(&fwd.output)?;
        Ok(out.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }
}

/// [`Model::sdf_batch`].
pub struct ModelSdf<'a> {
    model: &'a Model,
    backend: &'a Backend,
    device: Option<crate::nn::field::DeviceField<'a>>,
    _pin: crate::nn::field::PinnedParams<'a>,
}

impl SdfBatch for ModelSdf<'_> {
    fn sdf(&self, points: &[f32]) -> Result<Vec<f32>, BackendError> {
        self.model.sdf(self.backend, points)
    }

    fn device(&self) -> Option<&dyn crate::render::DeviceSdf> {
        self.device.as_ref().map(|d| d as &dyn crate::render::DeviceSdf)
    }
}

/// Loss parts and figures of one step.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct StepStats {
    pub step: u64,
    pub loss: f64,
    pub rgb: f64,
    pub eikonal: f64,
    pub mask: f64,
    #[serde(default)]
    pub smoothness: f64,
    #[serde(default)]
    pub photo: f64,
    /// PSNR (sRGB) on the surface rays of the batch.
    pub psnr: f64,
    pub surface_rays: usize,
    pub mask_rays: usize,
    pub alpha: f32,
    pub lr_field: f32,
    pub applied: bool,
    pub grad_norm: f64,
    pub field_evaluations: usize,
    /// A colour-only step of the radiance warm-up ([`Stage1Config::radiance_warmup`]): the SDF
    /// held, the colour term alone computed (`eikonal` and `mask` are 0: not part of the step's
    /// loss). The warm-up's priming steps are whole (`lr_field` 0) and not flagged.
    #[serde(default)]
    pub radiance_warmup: bool,
}

/// The gradient of one step's loss (and its parts), before the optimiser.
#[derive(Clone, Debug)]
pub struct StepGrad {
    pub stats: StepStats,
    pub d_sdf: Vec<f32>,
    pub d_radiance: Vec<f32>,
}

/// Loss weights and switches of one step.
#[derive(Clone, Copy, Debug)]
pub struct LossSettings {
    pub alpha: f32,
    pub eikonal_weight: f32,
    pub mask_weight: f32,
    pub eikonal_points: usize,
    pub mask_samples: usize,
    /// Eikonal points jittered around each surface point (0 = none).
    pub near_surface_sigma: f32,
    /// See [`Stage1Config::smoothness_weight`] (needs `near_surface_sigma > 0`).
    pub smoothness_weight: f32,
    /// See [`Stage1Config::normal_gradient_scale`].
    pub normal_gradient_scale: f32,
    /// See [`Stage1Config::colour_moves_point`].
    pub colour_moves_point: bool,
    /// See [`Stage1Config::grazing_cos`].
    pub grazing_cos: f32,
    /// Also apply the eikonal term at the traced surface points (held fixed, as IDR).
    pub surface_eikonal: bool,
    /// See [`Stage1Config::out_of_mask_min_sdf`].
    pub out_of_mask_min_sdf: bool,
}

/// The pose refinement's rate in the presets (pixels at the object per step,
/// [`Stage1Config::pose_lr`]; `--fixed-poses` keeps the poses as read). `bench train --variant
/// fast-refined-hull` (cpu, the preset's 500 steps; seed 0 unless named), field Chamfer / held-out
/// PSNR with the poses as read -> refined (the shared motion taken out, the slopes across the
/// ray at every 4th ray):
/// - misregistered photos: the example under `--pose-noise 0.5` (training poses 2.39 px off)
///   0.911% -> 0.419%, the poses left 0.43 px off; before the shared motion was taken out and at
///   every ray, with the training poses turned ~0.5° / ~1° and shifted at random (2.0 px off),
///   0.813% -> 0.606% (held-out 21.39 -> 23.82 dB) and 1.387% -> 0.849%;
/// - photos whose poses are exact pay a little: the example 0.176% / 28.73 dB -> 0.178% / 28.65
///   dB; the bowl 1.261% / 28.35 dB -> 1.296% / 28.20 dB (seed 1: 1.225% / 28.56 -> 1.244% /
///   28.37); a real capture with good poses, the Ethiopian head (`train --iterations 500`),
///   held-out 24.09 -> 24.01 dB, mask IoU 0.9809 -> 0.9812, its views moved 0.31 px on average.
///
/// The rate: 0.02 and 0.05 end the example under `--pose-noise 0.5` at 0.432% and 0.440%
/// (before the shared motion was taken out), the exact example at 0.187% and 0.186%. The
/// refinement costs 6% more field evaluations per step (129.7k against 122.7k on the example).
pub const POSE_LR: f32 = 0.02;

/// When a hull-initialised run carves its hull again through the refined poses
/// ([`Stage1Config::pose_recarve_at`], a fraction of the iterations). The hull carved through
/// misregistered poses is eroded wherever one view's silhouette is off: the example under
/// `bench train --pose-noise 0.5` carves a 1.41% hull (0.31% through the true poses), and the
/// run that fits it ends at 0.419% field Chamfer. Fitted to the true poses' hull, the same noisy
/// run ends at 0.260%, so the start costs most of the gap to the exact run's 0.178%.
/// Carved again at step 100 / 200 of 500 (a hull of 0.737% / 0.463%), it ends at 0.352% /
/// 0.347% (the latter cut at step 485 by the bench's time budget; run through, 0.354%); the later
/// carve sees better poses and leaves more than half the run to train from it. Exact poses never
/// carve again (the checks in `train::cli::recarve_hull_from_poses`).
pub const POSE_RECARVE_AT: f32 = 0.4;

/// Step size of the forward difference for `∂c/∂x·v`.
const RAY_EPS: f32 = 1e-3;

/// The loss and its gradient for one batch (see the module docs). `extra_eikonal`: uniform
/// points for the eikonal term (flattened).
pub fn loss_and_grad(
    backend: &Backend,
    model: &Model,
    trace_cfg: &TraceConfig,
    batch: &Batch,
    eik_points: &[[f32; 3]],
    ls: &LossSettings,
    jitter: f32,
) -> Result<StepGrad, BackendError> {
    let (stats, d_sdf, d_radiance) = loss_and_grad_tensors(backend, model, trace_cfg, batch, eik_points, ls, jitter, None, None)?;
    Ok(StepGrad { stats, d_sdf: sdf_grad_to_host(backend, d_sdf)?, d_radiance: radiance_grad_to_host(backend, d_radiance)? })
}

/// The gradient of a step's loss in each ray's origin and direction (pose refinement,
/// [`super::pose`]): zero for a ray whose terms do not depend on it. The colour's gradient in
/// the surface point is a forward difference of the whole forward along the ray and two
/// directions across it ([`RAY_EPS`]), pushed through the implicit surface point
/// (`∂x/∂o = I − v∇fᵀ/(∇f·v)`, `∂x/∂v = t·∂x/∂o`, gated at grazing hits as the SDF's is) plus the
/// radiance net's view input; the mask term's through its point at its distance along the ray.
/// The photo-consistency term contributes nothing.
#[derive(Clone, Debug, Default)]
pub struct RayGrads {
    pub origin: Vec<[f32; 3]>,
    pub dir: Vec<[f32; 3]>,
    /// An input: the slopes across the ray (two more colour evaluations per point) are taken at
    /// every this-many-th surface ray only and scaled by it, an unbiased estimate of their sum
    /// at a fraction of the cost ([`Stage1Config::pose_across_every`]); 0 or 1: every ray.
    pub across_every: usize,
}

impl RayGrads {
    fn zeros(n: usize, across_every: usize) -> Self {
        Self { origin: vec![[0.0; 3]; n], dir: vec![[0.0; 3]; n], across_every }
    }
}

/// [`loss_and_grad`] and the loss's gradient in each ray ([`RayGrads`]).
pub fn loss_and_ray_grads(
    backend: &Backend,
    model: &Model,
    trace_cfg: &TraceConfig,
    batch: &Batch,
    eik_points: &[[f32; 3]],
    ls: &LossSettings,
    jitter: f32,
) -> Result<(StepGrad, RayGrads), BackendError> {
    let mut rg = RayGrads::default();
    let (stats, d_sdf, d_radiance) = loss_and_grad_tensors(backend, model, trace_cfg, batch, eik_points, ls, jitter, None, Some(&mut rg))?;
    Ok((StepGrad { stats, d_sdf: sdf_grad_to_host(backend, d_sdf)?, d_radiance: radiance_grad_to_host(backend, d_radiance)? }, rg))
}

/// Two unit vectors across the unit vector `d`.
fn across(d: [f32; 3]) -> [[f32; 3]; 2] {
    let d = glam::Vec3::from(d);
    let a = d.any_orthonormal_pair();
    [a.0.to_array(), a.1.to_array()]
}

/// The SDF's parameter gradient as one host vector (one wait for both halves on wgpu).
fn sdf_grad_to_host(backend: &Backend, d: [Tensor; 2]) -> Result<Vec<f32>, BackendError> {
    let (mut a, b) = match d {
        [Tensor::Host(a), Tensor::Host(b)] => (a, b),
        [a, b] => backend.to_vec2(&a, &b)?,
    };
    a.extend(b);
    Ok(a)
}

/// The radiance net's gradient, `(appearance grid, MLP)`: the grid's where it was computed (the
/// device while [`Model::pin_appearance`] holds), the MLP's on the host.
type RadianceGrad = (Tensor, Vec<f32>);

/// [`RadianceGrad`] as one host vector, in `Model::radiance_params`' order.
fn radiance_grad_to_host(backend: &Backend, (grid, mlp): RadianceGrad) -> Result<Vec<f32>, BackendError> {
    let mut d = match grid {
        Tensor::Host(v) => v,
        t => backend.to_vec(&t)?,
    };
    d.extend(mlp);
    Ok(d)
}

/// A step's statistics and gradient: the SDF's `[encoding, MLP]` where the field computed it
/// ([`SdfField::value_and_grad_tensors`]) and the radiance net's.
type StepGradTensors = (StepStats, [Tensor; 2], RadianceGrad);

/// [`loss_and_grad`] with the grids' gradients left where they were computed (the device on
/// the device path).
#[allow(clippy::too_many_arguments)]
fn loss_and_grad_tensors(
    backend: &Backend,
    model: &Model,
    trace_cfg: &TraceConfig,
    batch: &Batch,
    eik_points: &[[f32; 3]],
    ls: &LossSettings,
    jitter: f32,
    photo: Option<PhotoTerm<'_>>,
    mut ray_grads: Option<&mut RayGrads>,
) -> Result<StepGradTensors, BackendError> {
    let nrays = batch.rays.len();
    let across_every = ray_grads.as_ref().map_or(1, |rg| rg.across_every.max(1));
    if let Some(rg) = ray_grads.as_deref_mut() {
        *rg = RayGrads::zeros(nrays, across_every);
    }
    let sdf_fn = model.sdf_batch(backend)?;
    let tr = trace(&sdf_fn, &batch.rays, trace_cfg)?;
    let mut evals = tr.evaluations;

    // Partition rays.
    let surf: Vec<usize> = (0..nrays).filter(|&i| tr.hit[i] && batch.mask[i] >= 0.5).collect();
    let mask_rays: Vec<usize> = (0..nrays).filter(|&i| !(tr.hit[i] && batch.mask[i] >= 0.5)).collect();

    // Min-SDF points: the tracer's for misses; sampled along the segment for hits outside the mask.
    let mut x_min: Vec<[f32; 3]> = mask_rays.iter().map(|&i| tr.points[i]).collect();
    let hit_out: Vec<usize> =
        if ls.out_of_mask_min_sdf { (0..mask_rays.len()).filter(|&k| tr.hit[mask_rays[k]]).collect() } else { Vec::new() };
    if !hit_out.is_empty() {
        let mut r = Rays::default();
        let (mut t0, mut t1) = (Vec::new(), Vec::new());
        for &k in &hit_out {
            let i = mask_rays[k];
            let (o, d) = (batch.rays.origins[i], batch.rays.dirs[i]);
            let (a, b) = sphere_interval(o, d, trace_cfg.bound).unwrap_or((0.0, 0.0));
            r.origins.push(o);
            r.dirs.push(d);
            t0.push(a);
            t1.push(b);
        }
        let (_, p) = min_sdf_along(&sdf_fn, &r, &t0, &t1, ls.mask_samples, jitter)?;
        evals += r.len() * ls.mask_samples;
        for (j, &k) in hit_out.iter().enumerate() {
            x_min[k] = p[j];
        }
    }

    // ∂c/∂x·v at the surface points: a forward difference of the whole forward along the ray,
    // `(c(x0 + ε v) − c(x0))/ε`, its `c(x0)` the colour the loss below computes anyway.
    let x0: Vec<[f32; 3]> = surf.iter().map(|&i| tr.points[i]).collect();
    let dirs: Vec<[f32; 3]> = surf.iter().map(|&i| batch.rays.dirs[i]).collect();
    let c_ahead: Vec<[f32; 3]> = if x0.is_empty() || !(ls.colour_moves_point || ray_grads.is_some()) {
        Vec::new()
    } else {
        let ahead: Vec<[f32; 3]> = x0.iter().zip(&dirs).map(|(p, d)| [0, 1, 2].map(|a| p[a] + RAY_EPS * d[a])).collect();
        evals += 7 * ahead.len();
        model.colour(backend, &ahead, &dirs)?
    };
    // For the rays' gradients, the colour a step across the ray in two directions.
    let across_dirs: Vec<[[f32; 3]; 2]> = if ray_grads.is_some() { dirs.iter().map(|&d| across(d)).collect() } else { Vec::new() };
    // Taken at every `across_every`-th surface point (k / across_every in these lists).
    let mut c_across: [Vec<[f32; 3]>; 2] = [Vec::new(), Vec::new()];
    if ray_grads.is_some() && !x0.is_empty() {
        let sel: Vec<usize> = (0..x0.len()).step_by(across_every).collect();
        let sel_dirs: Vec<[f32; 3]> = sel.iter().map(|&k| dirs[k]).collect();
        for (j, c) in c_across.iter_mut().enumerate() {
            let p: Vec<[f32; 3]> = sel.iter().map(|&k| [0, 1, 2].map(|a| x0[k][a] + RAY_EPS * across_dirs[k][j][a])).collect();
            evals += 7 * p.len();
            *c = model.colour(backend, &p, &sel_dirs)?;
        }
    }

    // Eikonal points: the caller's uniform ones, plus one jittered around each surface point
    // (keeps the fine levels of a hash grid smooth where the surface is).
    let mut eik_all: Vec<[f32; 3]> = eik_points.to_vec();
    if ls.near_surface_sigma > 0.0 {
        let mut rng = crate::util::rng(0x5EED ^ jitter.to_bits() as u64);
        let normal = rand_distr::Normal::new(0.0f32, ls.near_surface_sigma).map_err(|e| BackendError::Config(e.to_string()))?;
        for p in &x0 {
            eik_all.push([0, 1, 2].map(|a| p[a] + rand_distr::Distribution::sample(&normal, &mut rng)));
        }
    }
    let eik_points = &eik_all[..];
    // One batched value-and-grad over [surface; min-SDF; eikonal] points.
    let (ns, nm, ne) = (x0.len(), x_min.len(), eik_points.len());
    let mut pts: Vec<f32> = Vec::with_capacity(3 * (ns + nm + ne));
    pts.extend(x0.iter().flatten());
    pts.extend(x_min.iter().flatten());
    pts.extend(eik_points.iter().flatten());
    evals += 7 * (ns + nm + ne);
    let inv_b = 1.0 / nrays.max(1) as f64;
    let mut parts = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64); // rgb, eik, mask, sq err, smoothness, photo
    let mut d_radiance: Result<Option<RadianceGrad>, BackendError> = Ok(None);
    let rad_params = backend.upload(model.radiance_split().1);
    let (_, d_sdf) = model.field.value_and_grad_tensors(backend, &model.sdf_params, &pts, |o: &FieldOutputs| {
        let n = ns + nm + ne;
        let fd = model.field.config.feature_dim;
        let mut g = FieldOutputGrads { sdf: vec![0.0; n], gradient: vec![0.0; 3 * n], feature: vec![0.0; n * fd] };
        // ∇f·v at each surface point (the implicit surface point's denominator, for the colour
        // and the photo-consistency term).
        let gdotv: Vec<f32> = (0..ns).map(|k| (0..3).map(|a| o.gradient[3 * k + a] * dirs[k][a]).sum()).collect();
        // Colour.
        if ns > 0 {
            let r = (|| {
                let si = model.radiance_input(backend, &x0, &dirs, o, 0..ns)?;
                let fwd = backend.mlp_forward(&model.radiance, &rad_params, &backend.from_vec(si), true)?;
                let c = backend.to_vec(&fwd.output)?;
                let (l1, sq, dc) = colour_l1(&c, batch, &surf, inv_b);
                parts.0 += l1;
                parts.3 += sq;
                // Directional derivative of the loss in the point along `u`, from the colour
                // a step along it.
                let slope = |k: usize, cu: &[f32; 3]| (0..3).map(|ch| dc[3 * k + ch] * (cu[ch] - c[3 * k + ch]) / RAY_EPS).sum::<f32>();
                for k in 0..ns {
                    let gdotv = gdotv[k];
                    let s_term = c_ahead.get(k).map_or(0.0, |ca| slope(k, ca));
                    // Implicit differentiation: dx/df(x0) = −v/(∇f·v). Grazing or back-facing
                    // hits (∇f·v ≥ −grazing_cos) pass no gradient through the point.
                    if ls.colour_moves_point && gdotv < -ls.grazing_cos {
                        g.sdf[k] += -s_term / gdotv;
                    }
                    if let Some(rg) = ray_grads.as_deref_mut() {
                        if gdotv < -ls.grazing_cos {
                            // ∂L/∂x, then ∂L/∂o = (I − v∇fᵀ/(∇f·v))ᵀ ∂L/∂x, ∂L/∂v = t ∂L/∂o.
                            let (u, d) = (&across_dirs[k], dirs[k]);
                            let (a1, a2) = if k % across_every == 0 {
                                let (j, w) = (k / across_every, across_every as f32);
                                (w * slope(k, &c_across[0][j]), w * slope(k, &c_across[1][j]))
                            } else {
                                (0.0, 0.0)
                            };
                            let i = surf[k];
                            let o_i = batch.rays.origins[i];
                            let t: f32 = (0..3).map(|a| (x0[k][a] - o_i[a]) * d[a]).sum();
                            for a in 0..3 {
                                let gx = s_term * d[a] + a1 * u[0][a] + a2 * u[1][a];
                                let go = gx - o.gradient[3 * k + a] * s_term / gdotv;
                                rg.origin[i][a] += go;
                                rg.dir[i][a] += t * go;
                            }
                        }
                    }
                }
                let mut d_view = ray_grads.is_some().then(Vec::new);
                let r = model.radiance_backward(backend, &rad_params, &fwd, dc, &x0, ls.normal_gradient_scale, &mut g, d_view.as_mut())?;
                if let (Some(rg), Some(dv)) = (ray_grads.as_deref_mut(), d_view) {
                    // The view input is −v.
                    let view: Vec<f32> = dirs.iter().flat_map(|d| [-d[0], -d[1], -d[2]]).collect();
                    let dx = crate::nn::encoding::encoding_backward_cpu(&model.view_encoding, &[], &view, 3, &dv, true).1.unwrap_or_default();
                    for (k, &i) in surf.iter().enumerate() {
                        for a in 0..3 {
                            rg.dir[i][a] -= dx.get(3 * k + a).copied().unwrap_or(0.0);
                        }
                    }
                }
                Ok(Some(r))
            })();
            d_radiance = r;
        }
        // Mask BCE on sigmoid(−α f(x_min)), weight mask_weight/α, mean over all rays.
        let alpha = ls.alpha as f64;
        for k in 0..nm {
            let i = ns + k;
            let m = batch.mask[mask_rays[k]].clamp(0.0, 1.0) as f64;
            let z = -alpha * o.sdf[i] as f64;
            let bce = z.max(0.0) - z * m + (-z.abs()).exp().ln_1p();
            let w = ls.mask_weight as f64 / alpha * inv_b;
            parts.2 += w * bce;
            let sig = 1.0 / (1.0 + (-z).exp());
            let gs = (w * (sig - m) * -alpha) as f32;
            g.sdf[i] += gs;
            if let Some(rg) = ray_grads.as_deref_mut() {
                // The point moves with the ray's line (its samples are placed on the line, not
                // from the origin): ∂f/∂o = ∇f across the ray, ∂f/∂v = t times that.
                let r = mask_rays[k];
                let (o_r, d_r) = (batch.rays.origins[r], batch.rays.dirs[r]);
                let t: f32 = (0..3).map(|a| (x_min[k][a] - o_r[a]) * d_r[a]).sum();
                let along: f32 = (0..3).map(|a| o.gradient[3 * i + a] * d_r[a]).sum();
                for a in 0..3 {
                    let gf = gs * (o.gradient[3 * i + a] - along * d_r[a]);
                    rg.origin[r][a] += gf;
                    rg.dir[r][a] += t * gf;
                }
            }
        }
        // Eikonal at surface and uniform points.
        let eik_idx: Vec<usize> = (0..if ls.surface_eikonal { ns } else { 0 }).chain(ns + nm..n).collect();
        parts.1 += eikonal(&o.gradient, &eik_idx, ls.eikonal_weight, &mut g.gradient);
        // Normal smoothness between each surface point and its jittered point.
        if ls.smoothness_weight > 0.0 && ls.near_surface_sigma > 0.0 && ns > 0 {
            let pairs: Vec<(usize, usize)> = (0..ns).map(|k| (k, n - ns + k)).collect();
            parts.4 += normal_smoothness(&o.gradient, &pairs, ls.smoothness_weight, &mut g.gradient);
        }
        // Multi-view photo consistency at the surface points.
        if let Some(pt) = photo.filter(|_| ns > 0 && batch.view.len() == nrays) {
            let views: Vec<u32> = surf.iter().map(|&i| batch.view[i]).collect();
            let pixels: Vec<[f32; 2]> = surf.iter().map(|&i| batch.pixel[i]).collect();
            let (l, d) = pt.multiview.term(pt.data, &pt.settings, &views, &pixels, &x0, &dirs, &gdotv, ls.grazing_cos);
            parts.5 += l;
            for (k, v) in d.into_iter().enumerate() {
                g.sdf[k] += v;
            }
        }
        (parts.0 + parts.1 + parts.2 + parts.4 + parts.5, g)
    })?;
    let d_radiance = d_radiance?.unwrap_or_else(|| model.zero_radiance_grad());
    let mse = if ns > 0 { parts.3 / (3 * ns) as f64 } else { f64::NAN };
    let stats = StepStats {
        loss: parts.0 + parts.1 + parts.2 + parts.4 + parts.5,
        smoothness: parts.4,
        photo: parts.5,
        rgb: parts.0,
        eikonal: parts.1,
        mask: parts.2,
        psnr: if mse > 0.0 { -10.0 * mse.log10() } else { f64::NAN },
        surface_rays: ns,
        mask_rays: nm,
        alpha: ls.alpha,
        field_evaluations: evals,
        ..Default::default()
    };
    Ok((stats, d_sdf, d_radiance))
}

/// The L1 colour term of the surface rays `surf` of `batch`, whose colours are `c` `[n, 3]`,
/// weighted `inv_b` (one over the batch's rays): the loss, the squared error summed (for the
/// PSNR) and the loss's gradient in `c`.
fn colour_l1(c: &[f32], batch: &Batch, surf: &[usize], inv_b: f64) -> (f64, f64, Vec<f32>) {
    let (mut l1, mut sq) = (0.0f64, 0.0f64);
    let mut dc = vec![0f32; 3 * surf.len()];
    for (k, &i) in surf.iter().enumerate() {
        let gt = batch.rgb[i];
        for ch in 0..3 {
            let e = c[3 * k + ch] - gt[ch];
            l1 += e.abs() as f64 * inv_b;
            sq += (e * e) as f64;
            dc[3 * k + ch] = if e > 0.0 { inv_b as f32 } else if e < 0.0 { -(inv_b as f32) } else { 0.0 };
        }
    }
    (l1, sq, dc)
}

/// The loss and the radiance net's gradient of one step of the radiance warm-up
/// ([`Stage1Config::radiance_warmup`]): with the SDF held, only the colour term reaches a
/// parameter that moves, so the step traces the batch, evaluates the field (value, numerical
/// normal, feature) at the surface points alone and runs the radiance net forward and back.
/// None of the SDF's backward, its mask and eikonal points, the colour ahead along the ray or
/// the photo-consistency term is computed: they would only feed the SDF's gradient. The colour
/// loss and its radiance gradient are [`loss_and_grad`]'s.
fn radiance_loss_and_grad(backend: &Backend, model: &Model, trace_cfg: &TraceConfig, batch: &Batch) -> Result<(StepStats, RadianceGrad), BackendError> {
    let nrays = batch.rays.len();
    let sdf_fn = model.sdf_batch(backend)?;
    let tr = trace(&sdf_fn, &batch.rays, trace_cfg)?;
    let surf: Vec<usize> = (0..nrays).filter(|&i| tr.hit[i] && batch.mask[i] >= 0.5).collect();
    let ns = surf.len();
    let mut stats = StepStats { surface_rays: ns, mask_rays: nrays - ns, field_evaluations: tr.evaluations + 7 * ns, radiance_warmup: true, psnr: f64::NAN, ..Default::default() };
    if ns == 0 {
        return Ok((stats, model.zero_radiance_grad()));
    }
    let x0: Vec<[f32; 3]> = surf.iter().map(|&i| tr.points[i]).collect();
    let dirs: Vec<[f32; 3]> = surf.iter().map(|&i| batch.rays.dirs[i]).collect();
    let o = model.field.eval_with_gradient(backend, &model.sdf_params, bytemuck::cast_slice(&x0))?;
    let rad_params = backend.upload(model.radiance_split().1);
    let si = model.radiance_input(backend, &x0, &dirs, &o, 0..ns)?;
    let fwd = backend.mlp_forward(&model.radiance, &rad_params, &backend.from_vec(si), true)?;
    let c = backend.to_vec(&fwd.output)?;
    let (l1, sq, dc) = colour_l1(&c, batch, &surf, 1.0 / nrays as f64);
    // The field's output gradients it also returns are dropped: the SDF is held.
    let fd = model.field.config.feature_dim;
    let mut g = FieldOutputGrads { sdf: vec![0.0; ns], gradient: vec![0.0; 3 * ns], feature: vec![0.0; ns * fd] };
    let d_radiance = model.radiance_backward(backend, &rad_params, &fwd, dc, &x0, 0.0, &mut g, None)?;
    let mse = sq / (3 * ns) as f64;
    stats.rgb = l1;
    stats.loss = l1;
    stats.psnr = if mse > 0.0 { -10.0 * mse.log10() } else { f64::NAN };
    Ok((stats, d_radiance))
}

/// What the multi-view photo-consistency term needs beside the batch.
#[derive(Clone, Copy)]
pub struct PhotoTerm<'a> {
    pub data: &'a TrainData,
    pub multiview: &'a super::multiview::MultiView,
    pub settings: super::multiview::PhotoConsistency,
}

/// Volume rendering of one step ([`Stage1Config::volume_fraction`]).
#[derive(Clone, Copy, Debug)]
pub struct VolumeSettings {
    /// Logistic sharpness `s` (normalised units).
    pub sharpness: f32,
    pub coarse: usize,
    pub fine: usize,
    pub mask_weight: f32,
    pub bound: f32,
}

/// Share of the importance density spread uniformly along the ray (a surface the coarse samples
/// missed can still appear).
const VOLUME_FLOOR: f64 = 0.1;

/// Where a volume-rendered batch is evaluated: the rays that meet the bounding sphere and
/// `fine` samples along each (sorted), placed from the current field. Not differentiated: the
/// loss is a function of the parameters at fixed samples.
#[derive(Clone, Debug, Default)]
pub struct VolumeSamples {
    /// Batch indices of the rays that meet the bounding sphere.
    pub live: Vec<usize>,
    /// `[live.len() · fine]` points and their ray directions.
    pub x: Vec<[f32; 3]>,
    pub dirs: Vec<[f32; 3]>,
    pub fine: usize,
    /// Field evaluations spent placing them.
    pub evaluations: usize,
}

/// Per ray, `coarse` stratified SDF samples over the bounding sphere's segment give NeuS weights
/// at the current sharpness, and `fine` importance samples are drawn from them
/// ([`crate::render::volume::importance_samples`], with [`VOLUME_FLOOR`] spread uniformly).
pub fn volume_samples(backend: &Backend, model: &Model, batch: &Batch, vs: &VolumeSettings, jitter: f32) -> Result<VolumeSamples, BackendError> {
    use crate::render::volume::{composite, importance_samples};
    let nrays = batch.rays.len();
    let spans: Vec<Option<(f32, f32)>> = (0..nrays).map(|i| sphere_interval(batch.rays.origins[i], batch.rays.dirs[i], vs.bound)).collect();
    let live: Vec<usize> = (0..nrays).filter(|&i| spans[i].is_some_and(|(a, b)| b > a)).collect();
    let nc = vs.coarse.max(2);
    let mut coarse_t = Vec::with_capacity(live.len() * nc);
    let mut coarse_p = Vec::with_capacity(3 * live.len() * nc);
    for &i in &live {
        let (a, b) = spans[i].unwrap_or_default();
        for j in 0..nc {
            let t = a + (b - a) * (j as f32 + jitter) / nc as f32;
            coarse_t.push(t);
            coarse_p.extend(batch.rays.at(i, t));
        }
    }
    let coarse_f = model.sdf(backend, &coarse_p)?;
    let nf = vs.fine.max(2);
    let zeros = vec![[0.0f64; 3]; nc];
    let mut x = Vec::with_capacity(live.len() * nf);
    let mut dirs = Vec::with_capacity(live.len() * nf);
    for (r, &i) in live.iter().enumerate() {
        let f: Vec<f64> = coarse_f[r * nc..(r + 1) * nc].iter().map(|&v| v as f64).collect();
        let w = composite(&f, &zeros, vs.sharpness as f64).weights;
        for t in importance_samples(&coarse_t[r * nc..(r + 1) * nc], &w, nf, VOLUME_FLOOR, jitter) {
            x.push(batch.rays.at(i, t));
            dirs.push(batch.rays.dirs[i]);
        }
    }
    Ok(VolumeSamples { live, x, dirs, fine: nf, evaluations: coarse_f.len() })
}

/// The loss and gradient of one batch rendered by volume rendering ([`crate::render::volume`])
/// at the samples `vsm` ([`volume_samples`]): the field's value, numerical gradient and the
/// radiance net run batched at every sample, and each ray's colour and opacity are composited.
/// Losses: L1 between colour and photo on rays inside the mask, BCE between opacity and mask
/// (`mask_weight`) on every ray, eikonal at the samples and at `eik_points`; all means over the
/// batch's rays, as [`loss_and_grad`]. Rays that miss the bounding sphere render nothing and
/// carry no gradient.
pub fn volume_loss_and_grad(
    backend: &Backend,
    model: &Model,
    batch: &Batch,
    vsm: &VolumeSamples,
    eik_points: &[[f32; 3]],
    ls: &LossSettings,
    vs: &VolumeSettings,
) -> Result<StepGrad, BackendError> {
    let (stats, d_sdf, d_radiance) = volume_loss_and_grad_tensors(backend, model, batch, vsm, eik_points, ls, vs)?;
    Ok(StepGrad { stats, d_sdf: sdf_grad_to_host(backend, d_sdf)?, d_radiance: radiance_grad_to_host(backend, d_radiance)? })
}

/// [`volume_loss_and_grad`] with the grids' gradients left where they were computed.
fn volume_loss_and_grad_tensors(
    backend: &Backend,
    model: &Model,
    batch: &Batch,
    vsm: &VolumeSamples,
    eik_points: &[[f32; 3]],
    ls: &LossSettings,
    vs: &VolumeSettings,
) -> Result<StepGradTensors, BackendError> {
    use crate::render::volume::{composite, composite_backward};
    let nrays = batch.rays.len();
    let s = vs.sharpness as f64;
    let (live, x, dirs, nf) = (&vsm.live, &vsm.x, &vsm.dirs, vsm.fine);
    let mut evals = vsm.evaluations;
    let np = x.len();
    let ne = eik_points.len();
    let mut pts: Vec<f32> = Vec::with_capacity(3 * (np + ne));
    pts.extend(x.iter().flatten());
    pts.extend(eik_points.iter().flatten());
    evals += 7 * (np + ne);
    let inv_b = 1.0 / nrays.max(1) as f64;
    let mut parts = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize); // rgb, eik, mask, sq err, colour rays
    let mut d_radiance: Result<Option<RadianceGrad>, BackendError> = Ok(None);
    let rad_params = backend.upload(model.radiance_split().1);
    let (_, d_sdf) = model.field.value_and_grad_tensors(backend, &model.sdf_params, &pts, |o: &FieldOutputs| {
        let n = np + ne;
        let fd = model.field.config.feature_dim;
        let mut g = FieldOutputGrads { sdf: vec![0.0; n], gradient: vec![0.0; 3 * n], feature: vec![0.0; n * fd] };
        if np > 0 {
            let r = (|| {
                let si = model.radiance_input(backend, x, dirs, o, 0..np)?;
                let fwd = backend.mlp_forward(&model.radiance, &rad_params, &backend.from_vec(si), true)?;
                let c = backend.to_vec(&fwd.output)?;
                let mut dc = vec![0f32; 3 * np];
                for (r, &i) in live.iter().enumerate() {
                    let range = r * nf..(r + 1) * nf;
                    let f: Vec<f64> = o.sdf[range.clone()].iter().map(|&v| v as f64).collect();
                    let col: Vec<[f64; 3]> = range.clone().map(|k| [0, 1, 2].map(|ch| c[3 * k + ch] as f64)).collect();
                    let fwd_r = composite(&f, &col, s);
                    let m = batch.mask[i].clamp(0.0, 1.0) as f64;
                    let mut d_colour = [0.0; 3];
                    if m >= 0.5 {
                        parts.4 += 1;
                        for ch in 0..3 {
                            let e = fwd_r.colour[ch] - batch.rgb[i][ch] as f64;
                            parts.0 += e.abs() * inv_b;
                            parts.3 += e * e;
                            d_colour[ch] = e.signum() * inv_b;
                        }
                    }
                    let op = fwd_r.opacity.clamp(1e-4, 1.0 - 1e-4);
                    let w = vs.mask_weight as f64 * inv_b;
                    parts.2 += -w * (m * op.ln() + (1.0 - m) * (1.0 - op).ln());
                    let inside = fwd_r.opacity > 1e-4 && fwd_r.opacity < 1.0 - 1e-4;
                    let d_opacity = if inside { w * (op - m) / (op * (1.0 - op)) } else { 0.0 };
                    let (d_f, d_c) = composite_backward(&f, &col, s, &fwd_r, d_colour, d_opacity);
                    for (j, k) in range.enumerate() {
                        g.sdf[k] += d_f[j] as f32;
                        for ch in 0..3 {
                            dc[3 * k + ch] = d_c[j][ch] as f32;
                        }
                    }
                }
                model.radiance_backward(backend, &rad_params, &fwd, dc, x, ls.normal_gradient_scale, &mut g, None).map(Some)
            })();
            d_radiance = r;
        }
        let eik_idx: Vec<usize> = (0..n).collect();
        parts.1 += eikonal(&o.gradient, &eik_idx, ls.eikonal_weight, &mut g.gradient);
        (parts.0 + parts.1 + parts.2, g)
    })?;
    let d_radiance = d_radiance?.unwrap_or_else(|| model.zero_radiance_grad());
    let mse = if parts.4 > 0 { parts.3 / (3 * parts.4) as f64 } else { f64::NAN };
    let stats = StepStats {
        loss: parts.0 + parts.1 + parts.2,
        rgb: parts.0,
        eikonal: parts.1,
        mask: parts.2,
        psnr: if mse > 0.0 { -10.0 * mse.log10() } else { f64::NAN },
        surface_rays: parts.4,
        mask_rays: nrays - parts.4,
        alpha: ls.alpha,
        field_evaluations: evals,
        ..Default::default()
    };
    Ok((stats, d_sdf, d_radiance))
}

/// The eikonal term `weight · mean over points i of (|g_i| − 1)²` over field gradients
/// (`gradients`: 3 per point); adds its derivative to `d_gradients` and returns the value.
pub fn eikonal(gradients: &[f32], idx: &[usize], weight: f32, d_gradients: &mut [f32]) -> f64 {
    let inv_e = 1.0 / idx.len().max(1) as f64;
    let mut loss = 0.0;
    for &i in idx {
        let gr = &gradients[3 * i..3 * i + 3];
        let len = ((gr[0] * gr[0] + gr[1] * gr[1] + gr[2] * gr[2]) as f64).sqrt();
        loss += weight as f64 * (len - 1.0).powi(2) * inv_e;
        let c = (weight as f64 * 2.0 * (len - 1.0) / len.max(1e-12) * inv_e) as f32;
        for a in 0..3 {
            d_gradients[3 * i + a] += c * gr[a];
        }
    }
    loss
}

/// Normal smoothness `weight · mean over pairs (a, b) of |g_a − g_b|²` over field gradients
/// (`gradients`: 3 per point); adds its derivative to `d_gradients` and returns the value.
pub fn normal_smoothness(gradients: &[f32], pairs: &[(usize, usize)], weight: f32, d_gradients: &mut [f32]) -> f64 {
    if pairs.is_empty() {
        return 0.0;
    }
    let w = weight as f64 / pairs.len() as f64;
    let mut loss = 0.0;
    for &(a, b) in pairs {
        let d: [f64; 3] = [0, 1, 2].map(|c| (gradients[3 * a + c] - gradients[3 * b + c]) as f64);
        loss += w * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        for c in 0..3 {
            let v = (2.0 * w * d[c]) as f32;
            d_gradients[3 * a + c] += v;
            d_gradients[3 * b + c] -= v;
        }
    }
    loss
}

/// A trainer: model, optimiser state, step counter.
#[derive(Debug)]
pub struct Trainer {
    pub cfg: Stage1Config,
    /// Its SDF parameters are stale while `device` holds newer ones: read through
    /// [`Trainer::model`] after [`Trainer::sync_host`].
    model: Model,
    adam_sdf: AdamState,
    adam_radiance: AdamState,
    pub step: u64,
    /// Steps skipped because their gradient held NaN/Inf.
    pub skipped: u64,
    host: Backend,
    device: Option<DeviceParams>,
    /// The photo-consistency term's cameras and filtered photos, while its weight is above zero.
    multiview: Option<super::multiview::MultiView>,
    /// The starting rate of the last [`Trainer::fit_to_grid`] that landed (None before any).
    pub fit_rate: Option<f32>,
    /// The training views' pose corrections ([`Stage1Config::pose_lr`] above 0).
    poses: Option<super::pose::PoseRefinement>,
    /// What `train::cli::recarve_hull_from_poses` decided, once it has (kept in the checkpoint,
    /// so a resumed run neither carves twice nor forgets that it carved).
    pub hull_recarve: Option<serde_json::Value>,
}

/// The parameters and Adam moments a wgpu run keeps on the device
/// ([`Stage1Config::device_optimiser`]): the SDF's, split as the field splits them,
/// `[encoding, MLP]`, and the appearance grid's where it has one.
#[derive(Debug)]
struct DeviceParams {
    backend: Backend,
    params: [Tensor; 2],
    adam: [AdamState; 2],
    /// The appearance grid (the first `appearance_len` radiance parameters) and its moments.
    appearance: Option<(Tensor, AdamState)>,
    appearance_len: usize,
    /// The moments of the radiance parameters the host updates
    /// (`radiance_params[appearance_len..]`).
    radiance_adam: AdamState,
    /// The host copies (`Model::sdf_params`, the appearance grid in `Model::radiance_params`,
    /// `Trainer::adam_sdf`, `Trainer::adam_radiance`) hold the device's values.
    host_current: bool,
}

/// The norm of one step's gradient on the device path, over its device and its host tensors;
/// `None` when any value is non-finite.
fn combined_norm(backend: &Backend, device: &[&Tensor], host: &[&[f32]]) -> Result<Option<f64>, BackendError> {
    let (sq_dev, bad_dev) = backend.adam_grad_stats(device)?;
    let Some(h) = host_grad_norm(host) else { return Ok(None) };
    let sq = sq_dev + h * h;
    Ok((bad_dev == 0 && sq.is_finite()).then(|| sq.sqrt()))
}

/// Queue Adam on the SDF's two device halves with `states` (the run's moments, or the hull
/// fit's own).
fn adam_sdf_on_device(
    backend: &Backend,
    cfg: &AdamConfig,
    [p0, p1]: &mut [Tensor; 2],
    grads: &[Tensor; 2],
    [a0, a1]: [&mut AdamState; 2],
    lr: f32,
    norm: f64,
) -> Result<(), BackendError> {
    let mut items = [AdamItem { params: p0, grads: &grads[0], state: a0 }, AdamItem { params: p1, grads: &grads[1], state: a1 }];
    backend.adam_apply(cfg, &mut items, lr, norm).map(|_| ())
}

/// Checkpoint file names inside a run folder.
pub const CHECKPOINT: &str = "checkpoint.safetensors";
pub const RUN_CONFIG: &str = "run.json";

/// [`Trainer::fit_to_grid`] lands when at least this share of the target's voxels clear of its
/// surface (inside and outside weighted equally) end on the right side, or no fewer than before
/// it (a fit too short to land, not one that diverged).
pub const FIT_MIN_SIGN_AGREEMENT: f64 = 0.9;
/// [`Trainer::fit_to_grid`] starts again at a quarter of the rate at most this many times.
pub const FIT_RETRIES: usize = 2;

impl Trainer {
    pub fn new(cfg: Stage1Config) -> Result<Self, BackendError> {
        cfg.validate()?;
        let model = Model::new(&cfg)?;
        let host = Backend::cpu();
        let adam_sdf = AdamState::new(&host, model.sdf_params.len());
        let adam_radiance = AdamState::new(&host, model.radiance_params.len());
        Ok(Self { cfg, model, adam_sdf, adam_radiance, step: 0, skipped: 0, host, device: None, multiview: None, fit_rate: None, poses: None, hull_recarve: None })
    }

    /// The model. Its grids' parameters are the host copy: after training on wgpu call
    /// [`Trainer::sync_host`] first (reading a stale copy is a bug and panics).
    pub fn model(&self) -> &Model {
        assert!(self.device.as_ref().is_none_or(|d| d.host_current), "stage 1: the SDF's newest parameters are on the device; call Trainer::sync_host first");
        &self.model
    }

    /// The model to change: current on the host, which holds the only copy from here on.
    pub fn model_mut(&mut self) -> Result<&mut Model, BackendError> {
        self.host_only()?;
        Ok(&mut self.model)
    }

    /// Make the host copies current and the only ones (before the host changes them).
    fn host_only(&mut self) -> Result<(), BackendError> {
        self.sync_host()?;
        self.device = None;
        Ok(())
    }

    /// The model, current.
    pub fn into_model(mut self) -> Result<Model, BackendError> {
        self.sync_host()?;
        Ok(self.model)
    }

    /// The Adam steps applied to the SDF so far (the host copy's count: after training on wgpu
    /// call [`Trainer::sync_host`] first).
    pub fn sdf_adam_steps(&self) -> u64 {
        self.adam_sdf.step
    }

    /// Whether the newest parameters (the SDF's, the appearance grid's) are on the device only.
    pub fn host_is_stale(&self) -> bool {
        self.device.as_ref().is_some_and(|d| !d.host_current)
    }

    /// Bring the host copies of the device's parameters and Adam moments (the SDF's, the
    /// appearance grid's) up to date (one wait; nothing to do on the host path).
    pub fn sync_host(&mut self) -> Result<(), BackendError> {
        let Some(d) = self.device.as_mut().filter(|d| !d.host_current) else {
            return Ok(());
        };
        let empty = Tensor::Host(Vec::new());
        let (ga, gm, gv) = d.appearance.as_ref().map_or((&empty, &empty, &empty), |(p, a)| (p, &a.m, &a.v));
        let [p0, p1, m0, m1, v0, v1, pa, ma, va]: [Vec<f32>; 9] = d
            .backend
            .to_vecs(&[&d.params[0], &d.params[1], &d.adam[0].m, &d.adam[1].m, &d.adam[0].v, &d.adam[1].v, ga, gm, gv])?
            .try_into()
            .map_err(|_| BackendError::Map("device parameters: readback count".into()))?;
        let cat = |mut a: Vec<f32>, b: &[f32]| {
            a.extend_from_slice(b);
            a
        };
        self.model.sdf_params.copy_from_slice(&cat(p0, &p1));
        self.adam_sdf = AdamState { m: Tensor::Host(cat(m0, &m1)), v: Tensor::Host(cat(v0, &v1)), step: d.adam[0].step };
        self.model.radiance_params[..pa.len()].copy_from_slice(&pa);
        let r = &d.radiance_adam;
        self.adam_radiance = AdamState { m: Tensor::Host(cat(ma, r.m.host()?)), v: Tensor::Host(cat(va, r.v.host()?)), step: r.step };
        d.host_current = true;
        Ok(())
    }

    /// Whether this run keeps the SDF on `backend`'s device.
    fn on_device(&self, backend: &Backend) -> bool {
        self.cfg.device_optimiser && self.model.field.evaluates_on_device(backend)
    }

    /// The SDF's parameters pinned for a step, until Adam changes them: on the device path to
    /// the device copies (the only current ones), else to their device copy if there is one.
    fn pin_sdf(&self, backend: &Backend, device: bool) -> Result<crate::nn::field::PinnedParams<'_>, BackendError> {
        match &self.device {
            Some(d) if device => self.model.field.pin_device(&self.model.sdf_params, [d.params[0].device()?, d.params[1].device()?]),
            _ => self.model.field.pin(backend, &self.model.sdf_params),
        }
    }

    /// The device copies, made from the host's on first use.
    fn device_params(&mut self, backend: &Backend) -> Result<&mut DeviceParams, BackendError> {
        if self.device.is_none() {
            let split = self.model.field.encoder.num_params();
            let (m, v) = (self.adam_sdf.m.host()?, self.adam_sdf.v.host()?);
            let halves = |x: &[f32]| {
                let (a, b) = x.split_at(split);
                [backend.upload(a), backend.upload(b)]
            };
            let ([m0, m1], [v0, v1]) = (halves(m), halves(v));
            let step = self.adam_sdf.step;
            // The appearance grid leads the radiance parameters; the rest stays on the host.
            let grid = if self.model.appearance_on_device(backend) { self.model.radiance_split().0.len() } else { 0 };
            let (rm, rv, rstep) = (self.adam_radiance.m.host()?, self.adam_radiance.v.host()?, self.adam_radiance.step);
            let appearance = (grid > 0).then(|| {
                let a = AdamState { m: backend.upload(&rm[..grid]), v: backend.upload(&rv[..grid]), step: rstep };
                (backend.upload(&self.model.radiance_params[..grid]), a)
            });
            let radiance_adam = AdamState { m: Tensor::Host(rm[grid..].to_vec()), v: Tensor::Host(rv[grid..].to_vec()), step: rstep };
            self.device = Some(DeviceParams {
                backend: backend.clone(),
                params: halves(&self.model.sdf_params),
                adam: [AdamState { m: m0, v: v0, step }, AdamState { m: m1, v: v1, step }],
                appearance,
                appearance_len: grid,
                radiance_adam,
                host_current: true,
            });
        }
        Ok(self.device.as_mut().expect("made above"))
    }

    fn adam(&self) -> AdamConfig {
        AdamConfig { eps: 1e-15, grad_clip_norm: None, skip_zero_gradients: self.cfg.sparse_adam, ..AdamConfig::with_lr(self.cfg.lr_field) }
    }

    /// Apply gradients (skipped and counted when any value is non-finite). No SDF gradient (a
    /// radiance warm-up step): the SDF and its moments are left as they are.
    pub fn apply(&mut self, d_sdf: Option<Vec<f32>>, d_radiance: Vec<f32>, lr_field: f32, lr_radiance: f32) -> Result<(bool, f64), BackendError> {
        // The host copies are updated: they become the only current ones.
        self.host_only()?;
        let grads: Vec<&[f32]> = d_sdf.as_deref().into_iter().chain([&d_radiance[..]]).collect();
        let Some(norm) = host_grad_norm(&grads) else {
            self.skipped += 1;
            return Ok((false, f64::NAN));
        };
        let cfg = self.adam();
        if let Some(d_sdf) = d_sdf {
            adam_host(&cfg, &mut self.model.sdf_params, d_sdf, &mut self.adam_sdf, lr_field)?;
        }
        adam_host(&cfg, &mut self.model.radiance_params, d_radiance, &mut self.adam_radiance, lr_radiance)?;
        Ok((true, norm))
    }

    /// The training views' pose corrections, where the run refines them
    /// ([`Stage1Config::pose_lr`]; None before its first step).
    pub fn poses(&self) -> Option<&super::pose::PoseRefinement> {
        self.poses.as_ref()
    }

    /// The pose corrections for `data`'s views, made where the run refines poses and has none
    /// yet; an error where they were saved for another number of views.
    fn poses_for(&mut self, data: &TrainData) -> Result<Option<&super::pose::PoseRefinement>, BackendError> {
        if self.cfg.pose_lr <= 0.0 || data.views.len() < 2 {
            return Ok(None);
        }
        let n = data.views.len();
        match &self.poses {
            Some(p) if p.views() != n => {
                return Err(BackendError::Config(format!("stage 1: the run's pose refinement holds {} views, the scene {n}", p.views())));
            }
            Some(_) => {}
            None => self.poses = Some(super::pose::PoseRefinement::new(&self.host, n)),
        }
        Ok(self.poses.as_ref())
    }

    /// Each training view's distance to the object's centre (the rotation's pixel scale).
    pub fn view_distances(data: &TrainData) -> Vec<f32> {
        data.views.iter().map(|v| v.camera.center().length() as f32).collect()
    }

    /// The rng of step `step` (independent of how the run was split into sessions).
    pub fn step_rng(&self, step: u64) -> rand::rngs::StdRng {
        crate::util::rng(self.cfg.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(step))
    }

    /// One photometric iteration.
    pub fn train_step(&mut self, backend: &Backend, data: &TrainData) -> Result<StepStats, BackendError> {
        let levels = self.cfg.active_levels_at(self.step);
        self.model.field.encoder.set_active_levels(levels);
        let mut rng = self.step_rng(self.step);
        let volume = self.cfg.volume_at(self.step);
        let nrays = match (volume, self.cfg.volume_rays) {
            (Some(_), n) if n > 0 => n,
            _ => self.cfg.rays,
        };
        let mut batch = data.sample(&mut rng, nrays, self.cfg.foreground_fraction);
        let refine_poses = match self.poses_for(data)? {
            Some(p) => {
                p.apply(&mut batch);
                true
            }
            None => false,
        };
        // The term's cameras and filtered photos while its weight is above zero; dropped once it
        // has faded out (the rest of the run computes nothing for it).
        let photo_weight = self.cfg.photo_consistency_at(self.step);
        if photo_weight <= 0.0 {
            self.multiview = None;
        } else if self.multiview.is_none() {
            self.multiview = Some(super::multiview::MultiView::new(data));
        }
        if let (Some(mv), Some(p)) = (self.multiview.as_mut(), self.poses.as_ref().filter(|p| p.steps > 0)) {
            let poses: Vec<glam::DMat4> = data.views.iter().enumerate().map(|(v, tv)| p.camera(&tv.camera, v).world_from_camera).collect();
            mv.set_poses(&poses);
        }
        let b = self.cfg.trace.bound;
        let eik: Vec<[f32; 3]> = (0..self.cfg.eikonal_points)
            .map(|_| [rng.random_range(-b..b), rng.random_range(-b..b), rng.random_range(-b..b)])
            .collect();
        let ls = LossSettings {
            alpha: self.cfg.alpha_at(self.step),
            eikonal_weight: self.cfg.eikonal_weight,
            mask_weight: self.cfg.mask_weight,
            eikonal_points: self.cfg.eikonal_points,
            mask_samples: self.cfg.mask_samples,
            near_surface_sigma: self.cfg.near_surface_sigma,
            smoothness_weight: self.cfg.smoothness_weight,
            normal_gradient_scale: self.cfg.normal_gradient_scale,
            colour_moves_point: self.cfg.colour_moves_point,
            grazing_cos: self.cfg.grazing_cos,
            surface_eikonal: true,
            out_of_mask_min_sdf: self.cfg.out_of_mask_min_sdf,
        };
        let jitter = rng.random_range(0.0f32..1.0);
        let device = self.on_device(backend);
        if device {
            self.device_params(backend)?;
        }
        let pin = self.pin_sdf(backend, device)?;
        let appearance_pin = match self.device.as_ref().and_then(|d| d.appearance.as_ref()) {
            Some((p, _)) if device => Some(self.model.pin_appearance(p.device()?)),
            _ => None,
        };
        // The radiance warm-up holds the SDF: its steps compute the colour term alone, but for
        // the last few, which prime the SDF's moments.
        let warm_end = (self.cfg.radiance_warmup * self.cfg.iterations as f32).ceil() as u64;
        let warm = self.step < warm_end;
        let colour_only = warm && self.step.saturating_add(self.cfg.warmup_priming_steps) < warm_end;
        let mut ray_grads: Option<RayGrads> = None;
        let (stats, d_sdf, d_radiance) = match volume {
            None if colour_only => {
                let (st, d_radiance) = radiance_loss_and_grad(backend, &self.model, &self.cfg.trace, &batch)?;
                (StepStats { alpha: ls.alpha, ..st }, None, d_radiance)
            }
            None => {
                let photo = self.multiview.as_ref().map(|mv| PhotoTerm {
                    data,
                    multiview: mv,
                    settings: super::multiview::PhotoConsistency { weight: photo_weight, best: super::multiview::BEST, depth_step: self.cfg.sizes.pixel_footprint },
                });
                let rg = (refine_poses && !warm).then(|| RayGrads { across_every: self.cfg.pose_across_every as usize, ..Default::default() });
                let mut rg = rg;
                let (st, d_sdf, d_radiance) = loss_and_grad_tensors(backend, &self.model, &self.cfg.trace, &batch, &eik, &ls, jitter, photo, rg.as_mut())?;
                ray_grads = rg;
                (st, Some(d_sdf), d_radiance)
            }
            Some(sharpness) => {
                let vs = VolumeSettings {
                    sharpness,
                    coarse: self.cfg.volume_coarse,
                    fine: self.cfg.volume_fine,
                    mask_weight: self.cfg.volume_mask_weight,
                    bound: b,
                };
                let vsm = volume_samples(backend, &self.model, &batch, &vs, jitter)?;
                let (st, d_sdf, d_radiance) = volume_loss_and_grad_tensors(backend, &self.model, &batch, &vsm, &eik, &ls, &vs)?;
                (st, Some(d_sdf), d_radiance)
            }
        };
        drop((pin, appearance_pin));
        let f = self.cfg.lr_factor(self.step);
        let (lf, lr) = (if warm { 0.0 } else { self.cfg.lr_field * f }, self.cfg.lr_radiance * f);
        // The views' pose gradient, checked with the rest: a non-finite value skips the step.
        let pose_grad = match (&ray_grads, &self.poses) {
            (Some(rg), Some(p)) => Some(p.view_gradient(&batch, rg)),
            _ => None,
        };
        let (applied, norm) = if !stats.loss.is_finite() || matches!(pose_grad, Some(None)) {
            self.skipped += 1;
            (false, f64::NAN)
        } else if device {
            self.apply_device(d_sdf, d_radiance, lf, lr)?
        } else {
            self.apply(d_sdf.map(|d| sdf_grad_to_host(backend, d)).transpose()?, radiance_grad_to_host(backend, d_radiance)?, lf, lr)?
        };
        if let (true, Some(Some(g)), Some(p)) = (applied, pose_grad, self.poses.as_mut()) {
            let centres: Vec<[f32; 3]> = data.views.iter().map(|v| v.camera.center().as_vec3().to_array()).collect();
            p.step(&g, self.cfg.pose_lr * f, self.cfg.sizes.pixel_footprint, &centres)?;
        }
        self.step += 1;
        Ok(StepStats { step: self.step, applied, grad_norm: norm, lr_field: lf, ..stats })
    }

    /// [`Trainer::apply`] with the SDF's and the appearance grid's gradients, parameters and
    /// moments on the device: one wait for the gradient's statistics (over every part, so a
    /// non-finite value anywhere skips the whole step), then Adam queued there and run on the
    /// host for the rest of the radiance net. No SDF gradient (a radiance warm-up step): the
    /// SDF and its moments are left as they are.
    fn apply_device(&mut self, d_sdf: Option<[Tensor; 2]>, (d_grid, d_mlp): RadianceGrad, lr_field: f32, lr_radiance: f32) -> Result<(bool, f64), BackendError> {
        let cfg = self.adam();
        let d = self.device.as_mut().ok_or_else(|| BackendError::Config("stage 1: no device copy of the SDF".into()))?;
        // The grid's gradient is on the device where the grid is (a step without surface rays
        // gives host zeros); otherwise it joins the host's part.
        let (d_grid, d_host) = match (d_grid, &d.appearance) {
            (Tensor::Host(v), Some(_)) => (Some(d.backend.upload(&v)), d_mlp),
            (t @ Tensor::Device(_), Some(_)) => (Some(t), d_mlp),
            (t, None) => (None, radiance_grad_to_host(&d.backend, (t, d_mlp))?),
        };
        let device_grads: Vec<&Tensor> = d_sdf.iter().flatten().chain(d_grid.as_ref()).collect();
        let Some(norm) = combined_norm(&d.backend, &device_grads, &[&d_host])? else {
            self.skipped += 1;
            return Ok((false, f64::NAN));
        };
        let DeviceParams { backend, params, adam: [a0, a1], appearance, appearance_len, radiance_adam, .. } = d;
        if let Some(d_sdf) = &d_sdf {
            adam_sdf_on_device(backend, &cfg, params, d_sdf, [a0, a1], lr_field, norm)?;
        }
        if let (Some((p, a)), Some(g)) = (appearance.as_mut(), d_grid.as_ref()) {
            backend.adam_apply(&cfg, &mut [AdamItem { params: p, grads: g, state: a }], lr_radiance, norm)?;
        }
        adam_host(&cfg, &mut self.model.radiance_params[*appearance_len..], d_host, radiance_adam, lr_radiance)?;
        d.host_current = false;
        Ok((true, norm))
    }

    /// Fit the SDF to a signed distance grid (the visual hull, a given mesh, the ground truth)
    /// for `steps` steps at `hull_fit_lr` decaying to `hull_fit_lr_final` of it: L1 on the
    /// distance within ±`clamp`, plus the eikonal term. Returns the final mean error.
    ///
    /// The fit is checked: where it has not landed on the grid's inside and outside
    /// ([`FIT_MIN_SIGN_AGREEMENT`], voxels clear of the surface) and ends worse than it began,
    /// the rate was too high for the network (a deep MLP at a hash grid's rate goes positive
    /// everywhere and never finds its surface again), so it starts again from the parameters it
    /// began with at a quarter of the rate, [`FIT_RETRIES`] times at most, then fails with an
    /// error that says what to set.
    /// [`Trainer::fit_rate`] is the rate that landed.
    pub fn fit_to_grid(&mut self, backend: &Backend, grid: &super::hull::Grid3, steps: u64, progress: impl FnMut(u64, f64)) -> Result<f64, BackendError> {
        self.fit_to_grid_from(backend, grid, steps, self.cfg.hull_fit_lr, progress)
    }

    /// [`Trainer::fit_to_grid`] starting at rate `lr` (a trained field refitted to a new hull
    /// starts lower: at the preset's rate its fit diverges and starts again).
    pub fn fit_to_grid_from(&mut self, backend: &Backend, grid: &super::hull::Grid3, steps: u64, lr: f32, mut progress: impl FnMut(u64, f64)) -> Result<f64, BackendError> {
        if steps == 0 {
            return Ok(f64::NAN);
        }
        let start = self.current_sdf_params()?;
        let before = self.sign_agreement(backend, grid)?;
        let mut lr = lr;
        let mut tried = Vec::new();
        loop {
            let loss = self.fit_at(backend, grid, steps, lr, &mut progress)?;
            let agreement = self.sign_agreement(backend, grid)?;
            // Landed, or at least not worse than where it began (a short fit, `--init-steps`).
            if agreement >= FIT_MIN_SIGN_AGREEMENT.min(before) {
                self.fit_rate = Some(lr);
                return Ok(loss);
            }
            tried.push(format!("{lr:.1e} ({:.0}% of voxels on the right side)", 100.0 * agreement));
            if tried.len() > FIT_RETRIES {
                return Err(BackendError::Config(format!(
                    "stage 1: the SDF's fit to its {}^3 target did not land at any rate tried: {}; set a lower rate with `--geometry-set hull_fit_lr=<rate>`",
                    grid.res,
                    tried.join(", ")
                )));
            }
            tracing::warn!("stage 1: the SDF's fit to its target diverged at rate {lr:.1e} ({:.0}% of voxels on the right side); fitting again from the start at {:.1e}", 100.0 * agreement, 0.25 * lr);
            self.host_only()?;
            self.model.sdf_params.copy_from_slice(&start);
            lr *= 0.25;
        }
    }

    /// The SDF's current parameters: the host copy, or the device's where that is newer (read
    /// back alone, without the Adam moments).
    fn current_sdf_params(&self) -> Result<Vec<f32>, BackendError> {
        match self.device.as_ref().filter(|d| !d.host_current) {
            Some(d) => {
                let (mut a, b) = d.backend.to_vec2(&d.params[0], &d.params[1])?;
                a.extend(b);
                Ok(a)
            }
            None => Ok(self.model.sdf_params.clone()),
        }
    }

    /// Of the voxels of `grid` at least two cells from its zero level, the fraction the SDF puts
    /// on the same side, inside and outside weighted equally (so a small object cannot pass on
    /// its outside alone). At most about 20k voxels, on a fixed stride.
    fn sign_agreement(&self, backend: &Backend, grid: &super::hull::Grid3) -> Result<f64, BackendError> {
        let h = grid.spacing();
        let stride = (grid.data.len() / 20_000).max(1);
        let idx: Vec<usize> = (0..grid.data.len()).step_by(stride).filter(|&i| grid.data[i].abs() >= 2.0 * h).collect();
        let pts: Vec<f32> = idx.iter().flat_map(|&i| grid.centre_of(i)).collect();
        // Evaluated with the current copy (the device's, pinned, where it is newer).
        let pin = self.pin_sdf(backend, self.on_device(backend))?;
        let f = self.model.sdf(backend, &pts)?;
        drop(pin);
        let (mut ok, mut n) = ([0usize; 2], [0usize; 2]);
        for (k, &i) in idx.iter().enumerate() {
            let side = usize::from(grid.data[i] > 0.0);
            n[side] += 1;
            if (f[k] > 0.0) == (side == 1) {
                ok[side] += 1;
            }
        }
        let frac = |s: usize| if n[s] == 0 { 1.0 } else { ok[s] as f64 / n[s] as f64 };
        Ok(0.5 * (frac(0) + frac(1)))
    }

    /// One fit ([`Trainer::fit_to_grid`]) at starting rate `lr0`.
    fn fit_at(&mut self, backend: &Backend, grid: &super::hull::Grid3, steps: u64, lr0: f32, progress: &mut impl FnMut(u64, f64)) -> Result<f64, BackendError> {
        let n = self.cfg.hull_fit_points.max(2);
        let clamp = 0.1f32;
        // Points near the hull's surface (voxels within two cells of the zero level) and uniform ones.
        let near: Vec<[f32; 3]> = (0..grid.data.len())
            .filter(|&i| grid.data[i].abs() < 2.0 * grid.spacing())
            .map(|i| grid.centre_of(i))
            .collect();
        let mut last = f64::NAN;
        // The fit sees every level: the hull's distance is known everywhere, so the fine levels
        // are constrained (coarse to fine only guards the sparse photometric phase).
        self.model.field.encoder.set_active_levels(None);
        // The fit has its own optimiser state: photometric training starts with fresh moments.
        // One state per parameter tensor: the device's two halves, or the host's whole vector.
        let device = self.on_device(backend);
        let mut fit_state: Vec<AdamState> = if device {
            self.device_params(backend)?.params.iter().map(|p| AdamState::new(backend, p.len())).collect()
        } else {
            // The host copy is trained: it becomes the only current one.
            self.host_only()?;
            vec![AdamState::new(&self.host, self.model.sdf_params.len())]
        };
        let h = grid.spacing();
        let b = self.cfg.trace.bound;
        for s in 0..steps {
            let mut rng = crate::util::rng(self.cfg.seed ^ 0xA5A5 ^ (s << 20));
            let pts: Vec<[f32; 3]> = (0..n)
                .map(|k| {
                    if k % 2 == 0 && !near.is_empty() {
                        let c = near[rng.random_range(0..near.len())];
                        [0, 1, 2].map(|a| c[a] + rng.random_range(-h..h))
                    } else {
                        [rng.random_range(-b..b), rng.random_range(-b..b), rng.random_range(-b..b)]
                    }
                })
                .collect();
            let target: Vec<f32> = pts.iter().map(|&p| grid.sample(p).clamp(-clamp, clamp)).collect();
            let w = self.cfg.eikonal_weight as f64;
            let pin = self.pin_sdf(backend, device)?;
            let (l, d) = self.model.field.value_and_grad_tensors(backend, &self.model.sdf_params, bytemuck::cast_slice(&pts), |o| {
                let mut g = FieldOutputGrads { sdf: vec![0.0; n], gradient: vec![0.0; 3 * n], feature: vec![] };
                let mut l = 0.0;
                for i in 0..n {
                    let e = o.sdf[i].clamp(-clamp, clamp) - target[i];
                    let inside = o.sdf[i].abs() < clamp || e * o.sdf[i] < 0.0;
                    l += e.abs() as f64 / n as f64;
                    if inside {
                        g.sdf[i] = e.signum() / n as f32;
                    }
                    let gr = &o.gradient[3 * i..3 * i + 3];
                    let len = ((gr[0] * gr[0] + gr[1] * gr[1] + gr[2] * gr[2]) as f64).sqrt();
                    l += w * (len - 1.0).powi(2) / n as f64;
                    let c = (w * 2.0 * (len - 1.0) / len.max(1e-12) / n as f64) as f32;
                    for a in 0..3 {
                        g.gradient[3 * i + a] = c * gr[a];
                    }
                }
                (l, g)
            })?;
            drop(pin);
            let lr = lr0 * self.cfg.hull_fit_lr_final.powf(s as f32 / steps.max(1) as f32);
            let cfg = self.adam();
            match (self.device.as_mut().filter(|_| device), &mut fit_state[..]) {
                (Some(dev), [a0, a1]) => {
                    let Some(norm) = combined_norm(backend, &[&d[0], &d[1]], &[])? else {
                        self.skipped += 1;
                        continue;
                    };
                    adam_sdf_on_device(backend, &cfg, &mut dev.params, &d, [a0, a1], lr, norm)?;
                    dev.host_current = false;
                }
                (_, [a]) => {
                    let d = sdf_grad_to_host(backend, d)?;
                    if !d.iter().all(|v| v.is_finite()) {
                        self.skipped += 1;
                        continue;
                    }
                    adam_host(&cfg, &mut self.model.sdf_params, d, a, lr)?;
                }
                _ => return Err(BackendError::Shape("hull fit: optimiser state does not match the parameters".into())),
            }
            last = l;
            progress(s, l);
        }
        Ok(last)
    }

    /// Save a checkpoint (params + Adam state + config + step) into `dir`, atomically.
    pub fn save(&mut self, dir: &Path, scene_key: &str) -> Result<(), DataError> {
        let mut st = ParamStore::new();
        let err = |e: BackendError| DataError::new(dir, e.to_string());
        self.sync_host().map_err(err)?;
        st.insert("sdf", &[self.model.sdf_params.len()], self.model.sdf_params.clone()).map_err(err)?;
        st.insert("radiance", &[self.model.radiance_params.len()], self.model.radiance_params.clone()).map_err(err)?;
        st.put_adam_state(&self.host, "sdf", &self.adam_sdf).map_err(err)?;
        st.put_adam_state(&self.host, "radiance", &self.adam_radiance).map_err(err)?;
        st.set_config(&self.cfg).map_err(|e| DataError::new(dir, e.to_string()))?;
        st.set_step(self.step);
        st.metadata.insert("scene".into(), scene_key.to_string());
        st.metadata.insert("skipped".into(), self.skipped.to_string());
        if let Some(p) = &self.poses {
            p.save(&self.host, &mut st).map_err(err)?;
        }
        if let Some(r) = &self.hull_recarve {
            st.metadata.insert("hull_recarve".into(), r.to_string());
        }
        st.save(&dir.join(CHECKPOINT))?;
        let cfg = serde_json::json!({ "stage": "geometry", "step": self.step, "scene": scene_key, "config": self.cfg });
        crate::util::atomic_write(&dir.join(RUN_CONFIG), serde_json::to_string_pretty(&cfg).unwrap_or_default().as_bytes())
    }

    /// Load a checkpoint written by [`Trainer::save`]. `expect`: the scene key the run must
    /// belong to (None: any). The config is the checkpoint's own.
    pub fn load(dir: &Path, expect_scene: Option<&str>) -> Result<(Self, String), DataError> {
        let path = dir.join(CHECKPOINT);
        if !path.is_file() {
            return Err(DataError::new(&path, "no stage-1 checkpoint here (train one with `pii-bake train <scene> --out <run-dir>`)"));
        }
        let st = ParamStore::load(&path)?;
        let cfg: Stage1Config = st
            .config_json()
            .ok_or_else(|| DataError::new(&path, "checkpoint has no run configuration"))
            .and_then(|j| serde_json::from_str(j).map_err(|e| DataError::new(&path, format!("checkpoint configuration: {e}"))))?;
        let scene = st.metadata.get("scene").cloned().unwrap_or_default();
        if let Some(k) = expect_scene {
            check_scene(dir, &scene, k)?;
        }
        let mut t = Trainer::new(cfg).map_err(|e| DataError::new(&path, e.to_string()))?;
        let needs = format!("this run's {} network needs", t.cfg.preset.name());
        let get = |name: &str, len: usize| checked_tensor(&st, &path, name, len, &needs, " (a checkpoint from another preset or version?)");
        t.model.sdf_params = get("sdf", t.model.sdf_params.len())?;
        t.model.radiance_params = get("radiance", t.model.radiance_params.len())?;
        let host = t.host.clone();
        if let Some(s) = st.adam_state(&host, "sdf").map_err(|e| DataError::new(&path, e.to_string()))? {
            t.adam_sdf = s;
        }
        if let Some(s) = st.adam_state(&host, "radiance").map_err(|e| DataError::new(&path, e.to_string()))? {
            t.adam_radiance = s;
        }
        t.step = st.step().unwrap_or(0);
        let levels = t.cfg.active_levels_at(t.step);
        t.model.field.encoder.set_active_levels(levels);
        t.skipped = st.metadata.get("skipped").and_then(|s| s.parse().ok()).unwrap_or(0);
        t.poses = super::pose::PoseRefinement::load(&host, &st).map_err(|e| DataError::new(&path, e))?;
        t.hull_recarve = match st.metadata.get("hull_recarve") {
            Some(r) => Some(serde_json::from_str(r).map_err(|e| DataError::new(&path, format!("checkpoint's hull_recarve record: {e}")))?),
            None => None,
        };
        Ok((t, scene))
    }
}

/// The error when the stage-1 run in `dir` was trained on scene key `trained_on`, not `expected`.
pub fn check_scene(dir: &Path, trained_on: &str, expected: &str) -> Result<(), DataError> {
    if trained_on == expected {
        return Ok(());
    }
    Err(DataError::new(&dir.join(CHECKPOINT), format!("this run was trained on another scene ({trained_on}), not {expected}")))
}

/// A run's checkpoint trained with another preset than the one asked for: the error names it and
/// says how to follow the run (stage 1 resumed, stage 2 on its stage 1, stage 2 resumed).
pub fn check_preset(checkpoint: &Path, trained: Preset, asked: Preset) -> Result<(), DataError> {
    if trained == asked {
        return Ok(());
    }
    Err(DataError::new(
        checkpoint,
        format!(
            "this run was trained with the {} preset, not {}: leave `--preset` out to follow it, or train a new run with `--preset {}`",
            trained.name(),
            asked.name(),
            asked.name()
        ),
    ))
}

/// A checkpoint tensor that must exist, hold `len` values and be finite; the errors name the file
/// (`needs`/`hint` word the length mismatch for the caller's model).
pub(crate) fn checked_tensor(st: &ParamStore, path: &Path, name: &str, len: usize, needs: &str, hint: &str) -> Result<Vec<f32>, DataError> {
    let d = st.data(name).ok_or_else(|| DataError::new(path, format!("checkpoint lacks tensor {name:?}")))?;
    if d.len() != len {
        return Err(DataError::new(path, format!("tensor {name:?} has {} values; {needs} {len}{hint}", d.len())));
    }
    if d.iter().any(|v| !v.is_finite()) {
        return Err(DataError::new(path, format!("tensor {name:?} holds NaN/Inf values")));
    }
    Ok(d.to_vec())
}

/// One Adam step on a host parameter vector.
pub(crate) fn adam_host(cfg: &AdamConfig, params: &mut [f32], grads: Vec<f32>, state: &mut AdamState, lr: f32) -> Result<(), BackendError> {
    // The callers have checked the gradients (finite); clipping, where configured, reads this
    // tensor's own norm.
    let norm = if cfg.grad_clip_norm.is_some() { host_grad_norm(&[&grads]).unwrap_or(f64::INFINITY) } else { 0.0 };
    adam_update_host(cfg, state, params, &grads, lr, norm).map(|_| ())
}

/// A key that names a scene and how it was read (folder, format, view names and sizes).
pub fn scene_key(scene: &crate::scene::Scene, views: &[&View]) -> String {
    let mut h = crc32fast::Hasher::new();
    for v in views {
        h.update(v.name.as_bytes());
        h.update(&(v.camera.width as u64).to_le_bytes());
        h.update(&(v.camera.height as u64).to_le_bytes());
    }
    let name = scene.source.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
    format!("{name}:{}:{:08x}", views.len(), h.finalize())
}
