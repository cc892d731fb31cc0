//! Stage 2: light, material and physics-based indirect illumination on a stage-1 geometry.
//!
//! The model (all in the normalised frame of stage 1):
//! - **environment**: K SG lobes `G(ω; ξ, λ, μ)`, stored as `[ξ raw (3), ln λ, μ raw (3)]` per lobe
//!   (`ξ` normalised where used, `μ = |raw|`; `ln μ` with [`Stage2Config::log_amplitude`]). Init: Fibonacci axes, `λ = 10 + |20·N(0,1)|`, white
//!   amplitudes scaled so the total energy `Σ μ·2π/λ·(1 − e^{−2λ})` is `0.8·2π` (the paper's);
//! - **material autoencoder**: `PE10(x) → widths (LeakyReLU 0.2) → latent z` and decoders
//!   `z → albedo (3), roughness (1)`, sigmoid outputs: two decoders (`separate`, synthetic data) or
//!   one that shares its layers (`shared`, real captures); roughness is the sigmoid mapped onto
//!   shading's range `[R_MIN, 1]` ([`roughness_from_decoder`]). Latent smoothness: L1 between the
//!   material decoded from `z` and from `z + N(0, σ²)`; KL sparsity of `mean σ(z)` toward ρ;
//! - **indirect light** (`--indirect ours`): from each surface point x a ray toward every lobe
//!   axis ξ_k above its horizon is traced (the stage-1 SDF, sphere tracing from t = 0.01 until
//!   it hits or leaves, at most `secondary_steps`: 48, not the paper's 10, which miss most
//!   occluders). Where it hits x' (normal n'), `F_ind(PE10(x'), PE4(n'))` → K sigmoid weights,
//!   L1-normalised, mix the environment lobes into the lobe that replaces lobe k:
//!   axis ξ_k, `λ = Σ w_j λ_j`, `μ = ρ·Σ w_j μ_j`, ρ the occluder's reflectance from 3 more sigmoid
//!   outputs of F_ind (ours, not the paper's: its mixture is never dimmer than its dimmest lobe,
//!   where a dark occluder re-emits less than any). Baselines on the same data: `none` (no
//!   occlusion at all, PhySG-like; with [`RoughnessMode::Constant`] one roughness for the object),
//!   `uniform` (`w_j = 1/K`, NeRV-like) and `mii` (MII/InvRender: blocked lobes are dropped and an
//!   MLP at x gives 24 indirect SGs, fitted by L1 to the stage-1 radiance arriving along every
//!   lobe axis above the horizon, 0 where the environment is visible, and trained by the render
//!   loss too);
//! - **light–albedo balance** (ours, [`Stage2Config::balance_lr_factor`]): one log-scale `g`, the
//!   light's amplitudes times `e^g` and the albedo and every ρ times `e^−g` (the decoded albedo
//!   capped at 1), learnt with its exact gradient `Σ ∂L/∂μ·μ − Σ ∂L/∂a·a − Σ ∂L/∂ρ·ρ` and folded
//!   into the amplitudes and [`Stage2Model::albedo_scale`] after each step. Diffuse light is the
//!   same all along it, so the specular (a dielectric's fixed F0) alone moves it: without it the
//!   light and the albedo stay wherever the paper's start puts them.
//!
//! Shading is [`crate::sg::shade`]'s closed form (F0 = 0.04, glTF's dielectric), output sRGB-encoded and compared
//! with the photo by L1 (as stage 1 and PhySG). Geometry is frozen (the public code): primary
//! surface points, their normals and every secondary hit are traced **once** into a
//! [`SurfaceCache`]; a lobe whose axis has moved by more than `retrace_degrees` since it was traced
//! is re-traced for all cached points (lazily, per lobe). With the geometry frozen, secondary rays
//! march on the SDF sampled once on a grid at the asset's mesh cell
//! ([`Stage2Config::secondary_grid_nodes`]) and only their hits go back to the network, which puts
//! them on its own surface: on the example the cache's field evaluations (cache and re-traces over
//! 2400 steps) fall 110M -> 8.9M and albedo / relit PSNR stay within the seed noise.
//!
//! The backward is exact and first-order: forward-mode duals ([`crate::sg::shade::Dual`]) per
//! lobe through the shading's two channel-free factors ([`PointShading`]), reverse through the
//! mixture, the weight normalisation and the MLPs (`Backend::mlp_backward`). It is checked against
//! central differences in the tests.

use std::f64::consts::PI;
use std::path::Path;

use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::stage1::{adam_host, checked_tensor, Model as Stage1Model, Preset, TrainData};
use crate::backend::{Backend, BackendError, Tensor};
use crate::nn::adam::{host_grad_norm, AdamConfig, AdamState};
use crate::nn::encoding::{encoding_backward_cpu, encoding_forward_cpu, EncodingConfig};
use crate::nn::field::{Encoder, FieldEncoding, PositionEncoder};
use crate::nn::mlp::{Activation, Init, Mlp, MlpConfig};
use crate::nn::params::ParamStore;
use crate::nn::simd::SimdLevel;
use crate::render::grid::SdfGrid;
use crate::render::{trace, trace_secondary, Rays, TraceConfig};
use crate::sg::env::{EnvSgs, SgLobe};
use crate::sg::lanes;
use crate::sg::shade::{normalize, sg_eval, BrdfModel, BrdfSg, Dual, Scalar, Sg, F0, LAMBDA_MIN, R_MIN};
use crate::util::DataError;

/// How light blocked by the object itself is modelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum IndirectMode {
    /// The paper's: blocked lobes are replaced by F_ind's mixture of the environment at the hit.
    Ours,
    /// No occlusion, no indirect light (PhySG-like).
    None,
    /// Blocked lobes replaced by the uniform mixture of the environment (NeRV-like).
    Uniform,
    /// MII/InvRender: blocked lobes are dropped and an MLP at x gives `mii_lobes` indirect SGs,
    /// fitted to the stage-1 radiance seen along every lobe axis (see [`mii_fit`]).
    Mii,
}

impl IndirectMode {
    pub fn name(self) -> &'static str {
        match self {
            IndirectMode::Ours => "ours",
            IndirectMode::None => "none",
            IndirectMode::Uniform => "uniform",
            IndirectMode::Mii => "mii",
        }
    }
}

/// Whether boundary lights pass gradient (see [`boundary_visibility`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BoundaryMode {
    /// Ours: the lobe axis (and with it the light) learns from where the silhouette of the
    /// occluder cuts it.
    #[default]
    Flowing,
    /// The public code's: the boundary lights are in the colour but pass no gradient.
    Detached,
}

/// Material decoder layout (supplementary §5.2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DecoderMode {
    /// One decoder for albedo and one for roughness (synthetic data).
    Separate,
    /// One decoder with both outputs (real captures: roughness cannot saturate alone).
    Shared,
}

/// `1 − R_MIN`: the roughness decoder's sigmoid spans `[R_MIN, 1]`.
const ROUGHNESS_SPAN: f32 = (1.0 - R_MIN) as f32;

/// Roughness from the roughness decoder's sigmoid output `y`: `R_MIN + (1 − R_MIN)·y`. Shading
/// clamps roughness to `[R_MIN, 1]` (`sg::shade`); a raw sigmoid below `R_MIN` sat in that clamp
/// with zero gradient and never left it (glossy scene: every point's roughness was learnt as
/// 0 against ground truth 0.05–0.15), and the textures exported what shading never used.
pub fn roughness_from_decoder(y: f32) -> f32 {
    R_MIN as f32 + ROUGHNESS_SPAN * y
}

/// Material channels of the training's per-point buffers: albedo 0..3, roughness 3, metallic 4
/// (0 where not modelled).
const MAT: usize = 5;

/// Where roughness comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RoughnessMode {
    /// The material field's: one roughness per surface point.
    #[default]
    Field,
    /// One learned roughness for the whole object (PhySG-like baselines): the roughness decoder's
    /// output at a fixed latent (every entry [`CONSTANT_LATENT`]), so it needs no parameters of its
    /// own.
    Constant,
}

/// The latent entries the roughness decoder reads under [`RoughnessMode::Constant`] (not 0: with
/// zero biases every first-layer unit would sit on LeakyReLU's kink).
pub const CONSTANT_LATENT: f32 = 0.5;

/// Stage-2 configuration: sizes, weights, learning rates.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Stage2Config {
    pub preset: Preset,
    pub lobes: usize,
    pub indirect: IndirectMode,
    pub decoder: DecoderMode,
    #[serde(default)]
    pub roughness: RoughnessMode,
    /// Frequencies of the PE of x' fed to F_ind (and of x where the material uses PE).
    pub pos_freqs: u32,
    pub dir_freqs: u32,
    /// The material field's position encoding: the paper's `PE(pos_freqs)` or a hash grid sized
    /// from the scene's pixel footprint (as stage 1's). See [`Stage2Config::with_material_grid`].
    #[serde(default = "default_material_encoding")]
    pub material_encoding: FieldEncoding,
    pub material_widths: Vec<usize>,
    pub latent_dim: usize,
    pub decoder_widths: Vec<usize>,
    pub indirect_widths: Vec<usize>,
    /// F_ind (`ours`) also gives the occluder's reflectance ρ (3 more sigmoid outputs): the lobe
    /// replacing a blocked one carries `ρ·Σ w_j μ_j`, so light re-emitted by a dark occluder can be
    /// dimmer than the dimmest environment lobe (the paper's mixture alone cannot be). Off in runs
    /// from before it.
    #[serde(default)]
    pub occluder_reflectance: bool,
    /// Indirect SGs per point of the `mii` baseline (MII/InvRender: 24).
    #[serde(default = "default_mii_lobes")]
    pub mii_lobes: usize,
    /// Weight of the `mii` baseline's fit of its SGs to the stage-1 radiance.
    #[serde(default = "default_mii_weight")]
    pub mii_weight: f32,
    /// Surface points cached from the training pixels.
    pub points: usize,
    /// Points per iteration.
    pub batch: usize,
    pub iterations: u64,
    pub lr_material: f32,
    pub lr_light: f32,
    /// The light is known (`--known-env`: an HDR map of the capture's lighting, fitted with SG lobes)
    /// and keeps its shape: the material, the indirect light and one exposure are learnt.
    #[serde(default)]
    pub light_fixed: bool,
    /// The lobe axes learn at `lr_light` times this (each move past `retrace_degrees` costs a
    /// re-trace of that lobe; the fast preset's axes learn faster than the rest of the light).
    pub axis_lr_factor: f32,
    pub lr_indirect: f32,
    /// The learning rates decay exponentially to this factor at the last iteration.
    pub lr_final_factor: f32,
    /// Adam leaves the material encoding's entries whose gradient is exactly 0 untouched (the hash
    /// grid's unreached entries; [`AdamConfig::skip_zero_gradients`]); the other tensors stay
    /// dense. Run files without the field read false and resume as they ran.
    #[serde(default)]
    pub sparse_adam: bool,
    pub smooth_weight: f32,
    pub smooth_sigma: f32,
    pub kl_weight: f32,
    pub kl_rho: f32,
    pub secondary_offset: f32,
    /// Sphere-tracing steps of a secondary ray at most (it stops once it hits or leaves the unit
    /// sphere, so most take a few).
    pub secondary_steps: usize,
    pub secondary_threshold: f32,
    /// Re-trace a lobe's secondary rays once its axis has moved this far (degrees).
    pub retrace_degrees: f32,
    /// Secondary rays march on the frozen SDF sampled at this many nodes per axis over the
    /// bounding cube ([`crate::render::grid::SdfGrid`]), and only their hits are placed on the
    /// network's surface; 0 = every step a network evaluation (as with `--refine-geometry`, whose
    /// SDF changes). Set from the scene by `material::stage2_config`; run files written before
    /// this field read 0.
    #[serde(default)]
    pub secondary_grid_nodes: usize,
    /// Shading normals: central differences of the stage-1 field with its gradient step times this.
    pub normal_step_factor: f32,
    /// Boundary lights: whether the visibility ramp of grazing hits passes gradient (ours) or is
    /// detached (the public code's). See [`boundary_visibility`].
    #[serde(default)]
    pub boundary: BoundaryMode,
    /// A secondary hit is a boundary light when `|n'·ω| <` this (the supplementary's 0.0349, sin 2°);
    /// it is also the half-width in radians of the visibility ramp across the silhouette.
    #[serde(default = "default_boundary_epsilon")]
    pub boundary_epsilon: f32,
    /// Refine the stage-1 SDF jointly with light and material (`--refine-geometry`; the paper's
    /// timing table) instead of freezing it (the public code). See [`loss_and_grad_geometry`].
    #[serde(default)]
    pub refine_geometry: bool,
    /// The SDF's Adam rate when refining (0: stage 1's final rate, resolved when the run starts).
    #[serde(default)]
    pub lr_geometry: f32,
    /// Eikonal weight on the refined SDF (at the batch's points and uniform points).
    #[serde(default = "default_geometry_eikonal")]
    pub geometry_eikonal_weight: f32,
    /// Uniform eikonal points per iteration when refining.
    #[serde(default = "default_geometry_eikonal_points")]
    pub geometry_eikonal_points: usize,
    /// When refining, the surface cache (primary points and every secondary hit) is re-traced on
    /// the moved surface every this many iterations.
    #[serde(default = "default_geometry_retrace")]
    pub geometry_retrace_every: u64,
    pub seed: u64,
    pub checkpoint_every: u64,
    /// The backend that runs the training steps (`cpu` or `wgpu`), once chosen: under `--backend
    /// auto` on a GPU the run times a few steps on each and keeps the faster
    /// (`material::StepBackend`); recorded here so a resumed run keeps it. None: not chosen yet
    /// (or the run's own backend where there is no choice). Under `--backend auto` with a GPU,
    /// `--material-set step_backend=cpu` (or `wgpu`) forces it.
    #[serde(default)]
    pub step_backend: Option<String>,
    /// Store the light's amplitudes as `ln μ` (Adam's steps then relative, as for `ln λ`) instead
    /// of `μ` itself (`μ = |raw|`, the default). A step of `lr_light` moves a linear amplitude by
    /// at most about that much, so over a run no lobe passes an amplitude of a few tens; in log
    /// form a lobe can sharpen as far as its energy allows. Measured (`train --stage material`,
    /// 32 lobes, ours, 4 relit views, seeds 0 / 1; albedo PSNR, relit as rendered): glossy albedo
    /// 22.89 / 22.99 -> 23.37 / 23.46 dB (its sharpest lobe λ 63 -> 90, μ 4.7 -> 15.7; light
    /// irradiance error 0.107 / 0.099 -> 0.073 / 0.063); but bowl 18.58 / 18.37 -> 18.31 / 18.22 dB
    /// and example 27.30 / 27.53 -> 27.02 / 27.23 dB (relit envmap6 27.68 / 27.56 -> 27.81 / 28.01).
    /// The learnt amplitudes stay far below the linear form's reach on all three (bowl and
    /// example: at most 2–5), so the default stays linear; a glossy capture can turn it on.
    #[serde(default)]
    pub log_amplitude: bool,
    /// Rescale each lobe's stored axis to unit length after every step. The axes are normalised
    /// where used, so Adam's steps (orthogonal to the axis, on average) lengthen them and slow
    /// their angular rate over a run (raw norms reach 2–3.5 at `axis_lr_factor` 3); unit axes keep
    /// the rate `axis_lr_factor` sets. On for new runs (figures at `axis_lr_factor` in
    /// [`Stage2Config::new`]); run files without the field read false and resume as they ran.
    #[serde(default)]
    pub unit_axes: bool,
    /// Model metallic surfaces: a fifth material channel `m` (sigmoid, written by the roughness
    /// decoder, or the shared one), shading with `F0 = mix(0.04, albedo, m)` and the diffuse term
    /// scaled by `1 − m` (glTF's metallic-roughness model, which the asset's ORM texture carries).
    /// A dielectric-only model cannot make a metal's coloured highlights: the light takes their
    /// colour and the albedo the opposite tint.
    ///
    /// Its output starts near 0.5 (the decoder's biases start at 0), so the photos decide either
    /// way. Measured (`train --stage material`, seed 0) against an output bias of −4 (m = 0.018, a
    /// dielectric prior): the Ethiopian head (bronze) turned metal from 0.5 (mean m 0.90, held-out
    /// PSNR 22.50 dB, its learnt light 2.0× between channels, no longer flagged) and only in part
    /// from 0.018 (mean 0.15, 22.46 dB, 2.8×); the dielectric example went back to m ≈ 0.0006 from
    /// 0.5 (albedo 27.23 / relit 27.79 / 26.64 dB; from 0.018: 27.24 / 27.67 / 26.43) and the bowl
    /// to 0.029 either way (19.81 / 20.97 / 23.96 against 19.92 / 21.06 / 24.19).
    ///
    /// Run files without the field read false (dielectric) and resume as they ran.
    #[serde(default)]
    pub metallic: bool,
    /// The SG form of the BRDF ([`BrdfModel`]). Run files without the field read `physg` (the
    /// form they were trained with) and resume as they ran.
    #[serde(default)]
    pub brdf: BrdfModel,
    /// With the calibrated BRDF: the fraction of the iterations shaded with PhySG's form first.
    /// From the first step the calibrated form lets a rough surface keep its specular energy, and
    /// the light, still far from the truth, drives it there: the bowl ended at roughness 1 with
    /// metallic 0.44 and a training PSNR of 26.1 dB, where PhySG's form first reaches 27.8 dB
    /// (roughness 0.59, metallic 0.01). Measured (`train --stage material`, 32 lobes, metallic
    /// on, seed 0; albedo PSNR after scale · relit PSNR under both maps), PhySG's form → the
    /// calibrated one from step 0 → after a warm-up of 0.5:
    /// - metal: 18.57 · 19.47 / 20.59 → 19.50 · 21.57 / 22.19 → 18.94 · 21.50 / 21.96 dB
    ///   (roughness MSE 0.146 → 0.021 → 0.023);
    /// - spot: 27.64 · 27.93 / 26.89 → 27.52 · 28.21 / 27.21 → 27.63 · 28.47 / 27.33;
    /// - example: 27.23 · 27.79 / 26.64 → 27.21 · 28.36 / 27.20 → 27.24 · 28.34 / 27.10;
    /// - glossy: 22.93 · 27.29 / 21.35 → 23.85 · 26.99 / 21.38 → 23.72 · 26.73 / 21.22;
    /// - bowl: 19.81 · 20.97 / 23.96 → 19.31 · 19.28 / 22.25 → 19.56 · 20.72 / 23.34;
    /// - the Ethiopian head, held-out PSNR: 22.50 (metallic 0.90) → 22.37 (0.69) → 22.43 (0.97).
    /// The exported asset in Cycles against held-out photos (the bake's Blender check, 4 views),
    /// PhySG's form → after the warm-up: spot 25.78 → 26.20 dB, bowl 24.24 → 24.40 dB, the
    /// Ethiopian head 20.87 → 21.52 dB.
    /// A warm-up of 0.25 / 0.75 instead: bowl 19.16 · 20.46 / 23.24 and 19.73 · 20.88 / 23.46,
    /// glossy 23.82 · 26.56 / 21.14 and 23.64 · 26.97 / 21.36; at 0.75 the metal scene falls to
    /// 18.55 · 20.19 / 21.25 (roughness MSE 0.064) and the head stays at 22.43, so 0.5.
    /// With the light–albedo balance ([`Self::balance_lr_factor`]) the warm-up still pays: without
    /// it (0) the bunny 25.62 · 28.01 / 26.93 -> 25.20 · 27.64 / 26.61, the bowl 19.81 · 20.91 /
    /// 23.43 -> 18.96 · 20.20 / 23.23, the example 27.30 · 28.42 / 27.11 -> 27.32 · 28.28 / 27.01.
    /// Run files without the field read 0 and resume as they ran.
    #[serde(default)]
    pub brdf_warmup: f32,
    /// The light–albedo balance: one log-scale `g` that multiplies every light amplitude by `e^g`
    /// and the albedo (and the occluders' reflectance) by `e^−g` learns at `lr_light` times this
    /// (0: off). Moving along it leaves every diffuse term unchanged, so only the specular
    /// (a dielectric's fixed F0) decides it; without it the light and the albedo settle wherever
    /// the light's start puts them, and a light that starts too dim for the object is made up by
    /// a too bright albedo and a roughness that falls to its floor to brighten the highlights.
    /// Not with a known light (`light_fixed`) or the `mii` baseline. Run files without the field
    /// read 0 and resume as they ran.
    #[serde(default)]
    pub balance_lr_factor: f32,
}

impl Stage2Config {
    /// The preset's configuration. `foreground_pixels`: masked training pixels (the cache never
    /// holds more points than there are pixels to explain).
    pub fn new(preset: Preset, foreground_pixels: usize) -> Self {
        // Fast preset, 1200 -> 2400 iterations (`bench material`, 32 lobes, ours, 2 relit views; albedo /
        // relit PSNR / roughness MSE): example 26.32 / 27.14 / 0.041 -> 26.57 / 27.51 / 0.027, bowl
        // 16.18 / 18.03 / 0.037 -> 16.64 / 18.18 / 0.047, textureless bowl 17.57 / 21.11 / 0.049 ->
        // 17.39 / 21.85 / 0.061; relit gains on all three, for ~110 s more in the example's bake.
        // Not more for a large capture (unlike stage 1's steps): the Ethiopian head (15M pixels)
        // 2400 -> 4800 steps, training PSNR 23.6 -> 24.2 dB but held-out 22.33 -> 22.14 dB. Nor
        // fewer, larger steps (what a GPU's per-step cost would want): the example at 600 x 4096
        // points and twice the learning rates, albedo 27.35 -> 22.08 dB, relit 28.33 -> 27.47 dB
        // (`bench material --lobes 32 --indirect ours`, cpu, 2-core box; 16% less training time).
        let (lobes, widths, ind, points, batch, iterations) = match preset {
            Preset::Fast => (32, vec![128; 3], vec![128; 2], 131_072, 1024, 2400),
            Preset::Paper => (128, vec![256; 3], vec![512; 4], 262_144, 2048, 3000),
        };
        Self {
            preset,
            lobes,
            indirect: IndirectMode::Ours,
            decoder: DecoderMode::Separate,
            roughness: RoughnessMode::Field,
            pos_freqs: 10,
            dir_freqs: 4,
            material_encoding: default_material_encoding(),
            material_widths: widths,
            latent_dim: 32,
            decoder_widths: vec![64],
            indirect_widths: ind,
            // `bench material` (32 lobes, ours, 48 secondary steps, 2 relit views), albedo / relit
            // PSNR without -> with: textureless bowl seed 0 16.91 / 20.87 -> 17.57 / 21.11 dB, seed 1
            // 16.29 / 20.42 -> 17.00 / 21.08; bowl seed 0 16.26 / 18.07 -> 16.18 / 18.03, seed 1
            // 16.26 / 17.90 -> 16.46 / 17.92 (roughness MSE 0.042 -> 0.037, 0.071 -> 0.062);
            // example 26.29 / 27.16 -> 26.32 / 27.14.
            occluder_reflectance: true,
            mii_lobes: default_mii_lobes(),
            mii_weight: default_mii_weight(),
            points: points.min(foreground_pixels.max(1)),
            batch,
            iterations,
            lr_material: 5e-3,
            lr_light: 3e-2,
            light_fixed: false,
            // `bench material` (32 lobes, ours, 2400 iterations, seed 0), albedo / relit PSNR /
            // roughness MSE, 0.1 -> 0.3: bowl 16.64 / 18.18 / 0.047 -> 17.48 / 18.84 / 0.038,
            // example 26.57 / 27.51 / 0.027 -> 26.71 / 27.65 / 0.023, textureless bowl 17.39 /
            // 21.85 / 0.061 -> 17.97 / 22.13 / 0.061. Faster axes cost more re-traced lobes (bowl
            // 38 -> 98, 43 -> 108 s; the example's stage-2 training 202 -> 265 s).
            // 0.3 -> 1 -> 3, on stage-1 runs with normal smoothness (`train --stage material`, 4
            // relit views; albedo / relit as rendered, both maps / light irradiance error): bowl
            // 18.58 / 19.82, 23.11 / 0.135 -> 19.76 / 20.80, 23.98 / 0.108 -> 20.36 / 21.25,
            // 24.53 / 0.092 (more lobes gather around the low sun: within 30° of the brightest 8 -> 12
            // -> 16, holding 58 -> 66 -> 71% of the energy); example
            // 27.30 / 27.68, 26.47 / 0.072 -> 27.03 / 27.95, 26.84 / 0.069 -> 27.43 / 27.78,
            // 26.70 / 0.064; glossy 22.89 / 27.04, 21.22 / 0.107 -> 23.14 / 27.23, 21.33 / 0.092 ->
            // 23.18 / 27.33, 21.36 / 0.080; spot 27.50 / 27.80, 26.67 -> 27.45 / 28.01, 26.97 ->
            // 24.55 / 25.80, 24.95: at 3 one seed of the spot's two fits its photos 2.6 dB worse
            // (held-out 28.23 -> 25.60 dB; seed 1: 28.40 dB, albedo 27.93), so 1, which no run
            // fitted worse. Seed 1, 0.3 -> 1: bowl 18.37 / 19.59, 22.93 -> 19.63 / 20.68, 23.87;
            // example 27.53 / 27.56, 26.31 -> 27.53 / 27.73, 26.61 (-> 3: 27.30 / 27.79, 26.63); spot
            // at 1: 27.69 / 27.68, 26.64 (held-out 28.45 dB). Re-traced lobes: bowl 96 -> 225
            // -> 323, example 101 -> 239 -> 354; the example's stage 2 alone on the 2-core box, 0.3
            // -> 3: 53.0 -> 60.9 s (re-tracing 4.0 -> 13.3 s). Then with `unit_axes` (the axes
            // rescaled to unit length after each step, so Adam's steps no longer lengthen them
            // and slow their turning), 1 -> unit 1 -> unit 2, albedo / relit as rendered, both
            // maps: bowl 19.76 / 20.80, 23.98 -> 19.88 / 20.94, 24.08 -> 20.32 / 21.24, 24.46 (seed
            // 1: 19.63 / 20.68, 23.87 -> unit 2: 20.69 / 21.52, 24.78); example 27.03 / 27.95, 26.84
            // -> 27.22 / 27.84, 26.65 -> 27.35 / 27.85, 26.77 (seed 1: 27.53 / 27.73, 26.61 ->
            // 27.44 / 27.89, 26.80); spot 27.45 / 28.01, 26.97 -> 27.62 / 27.86, 26.76 -> 27.53 /
            // 27.74, 26.63 (seed 1: 27.69 / 27.68, 26.64 -> 27.89 / 27.57, 26.46; held-out 28.32 /
            // 28.40 dB, neither seed fitting worse); glossy 23.14 / 27.23, 21.33 -> 23.25 / 27.27,
            // 21.33 -> 23.16 / 27.31, 21.37. So unit axes at 2: the bowl +0.6 / +1.1 dB albedo, the
            // spot's relighting -0.1..-0.3 dB.
            axis_lr_factor: 2.0,
            lr_indirect: 2e-3,
            lr_final_factor: 0.1,
            // `bench material` (32 lobes, ours, 2400 iterations), dense -> sparse, albedo / relit
            // PSNR: example 26.62 / 28.32, 26.90 -> 26.66 / 28.27, 26.85 dB (23.0 -> 24.3 it/s on
            // its 2^16 table), bowl 17.41 / 16.59, 21.08 -> 17.44 / 16.63, 21.06 dB.
            sparse_adam: true,
            smooth_weight: 0.1,
            smooth_sigma: 0.01,
            kl_weight: 0.01,
            kl_rho: 0.05,
            secondary_offset: 0.01,
            // The paper's 10 steps from t = 0.01 leave most occluders unfound: a ray that leaves its
            // surface at an angle α advances only as far as the field lets it, about
            // 0.01·(1 + sin α)^n after n steps, so one crossing a bowl's cavity (or passing close to
            // the object) is still on its way after 10 and counts as open, and the blocked light
            // it should replace lights the point. `bench material` (32 lobes, ours, 2 relit views;
            // 10 -> 48 steps): blocked pairs bowl 2.6% -> 20.2%, textureless bowl 2.2% -> 20.3%,
            // example 1.0% -> 6.9%; albedo PSNR bowl 15.20 -> 16.26 dB, textureless 14.40 -> 16.91,
            // example 25.34 -> 26.29; relit bowl 17.17 -> 18.07, textureless 19.58 -> 20.87,
            // example 27.17 -> 27.16; roughness MSE bowl 0.116 -> 0.042, textureless 0.114 ->
            // 0.045, example 0.042 -> 0.042.
            secondary_steps: 48,
            secondary_threshold: 5e-4,
            // A lobe is re-traced once its axis has moved this far (an SG lobe of the learnt
            // light spans 10-20 degrees). `train --stage material` (32 lobes, 2400 steps, seed 0),
            // 8 -> 12 degrees, albedo / relit PSNR (two maps): example 27.24 / 28.34, 27.10 ->
            // 27.25 / 28.39, 27.22 dB, re-traced lobes 430 -> 246; bowl 19.56 / 20.72, 23.34 ->
            // 19.80 / 20.98, 23.58; spot 27.63 / 28.47, 27.33 -> 27.58 / 28.47, 27.36; glossy
            // 23.72 / 26.73, 21.22 -> 23.69 / 26.63, 21.19. Side by side on the 2-core machine,
            // stage 2 ran 19.6 -> 21.8 it/s on the example and 14.1 -> 16.7 it/s on the bowl.
            retrace_degrees: 12.0,
            secondary_grid_nodes: 0,
            // Shading normals over 6 gradient steps (central differences 2·6·grad_step apart: the
            // hash-grid SDF's cell-scale bumps averaged out). `bench material` (32 lobes, ours, 4
            // relit views, relight with the silhouette fringe traced), factor 3 -> 6 -> 10:
            // example albedo 25.01 -> 25.54 -> 25.98 dB, relit sunset / envmap6 26.28 / 27.77 ->
            // 26.28 / 27.67 -> 26.07 / 27.40 (after per-channel scale 26.85 / 28.52 -> 27.37 / 28.80
            // -> 27.78 / 28.94), normal error 4.57 -> 3.96 -> 3.63 degrees; glossy (2 views) 3 -> 6:
            // albedo 22.97 -> 23.15, relit 25.89 / 20.50 -> 26.10 / 20.67, novel view 23.93 ->
            // 24.05, normal error 5.76 -> 5.12 degrees. 10 costs the example's relit PSNR as rendered.
            // (Earlier, 1 -> 3 on the example: albedo +0.31 dB.)
            normal_step_factor: 6.0,
            boundary: BoundaryMode::Flowing,
            boundary_epsilon: default_boundary_epsilon(),
            refine_geometry: false,
            lr_geometry: 0.0,
            geometry_eikonal_weight: default_geometry_eikonal(),
            geometry_eikonal_points: default_geometry_eikonal_points(),
            geometry_retrace_every: default_geometry_retrace(),
            seed: 0,
            checkpoint_every: 100,
            step_backend: None,
            log_amplitude: false,
            unit_axes: true,
            metallic: false,
            brdf: BrdfModel::Calibrated,
            brdf_warmup: 0.5,
            // Measured (`train --stage material`, 32 lobes, ours, 4 relit views; albedo PSNR after
            // scale · relit PSNR as rendered under both maps · roughness MSE), off -> 0.3: the bunny
            // (`make_scene.py --scene bunny`, a darker object under a sun brighter than the paper's
            // start) seed 0 24.91 · 17.42 / 17.72 · 0.251 (roughness at its floor, flagged) ->
            // 25.62 · 28.01 / 26.93 · 0.016, seed 1 24.78 · 17.63 / 17.93 · 0.251 -> 25.45 · 28.35 /
            // 27.19 · 0.016 (its light's energy 7.0 -> 11.6, the sky's about 12; albedo scale 0.63
            // -> 1.06 of the truth); the example seed 0 27.29 · 28.44 / 27.11 -> 27.43 · 28.39 /
            // 27.10 (27.30 · 28.42 / 27.11 once the cap at 1 was tracked for the perturbed latent
            // too: the example's balance sits at the cap), seed 1 27.61 · 28.06 / 26.77 -> 27.55 · 28.27 / 27.00; bowl 19.25 · 20.48 /
            // 22.99 -> 19.81 · 20.91 / 23.43; glossy 23.94 · 26.47 / 21.20 -> 23.98 · 26.54 / 21.20;
            // metal 18.31 · 21.08 / 21.30 -> 18.33 · 21.06 / 21.32; spot 27.56 · 28.40 / 27.17 ->
            // 27.67 · 28.39 / 27.22; textureless 22.22 · 22.93 / 22.85 · 0.029 -> 21.82 · 25.22 /
            // 24.88 · 0.021 (its albedo's scale 0.79 -> 1.02 of the truth); held-out PSNR of the real captures: the Ethiopian head 22.46 ->
            // 22.43 dB, DTU scan37 (training views) 15.88 -> 16.16 dB. At 1 (seed 1): bunny 25.69 ·
            // 28.27 / 27.10, example 27.62 · 28.16 / 26.87, so the slower rate. Under PhySG's form
            // (the warm-up) the balance reads the highlights as asking for more light than under
            // the calibrated one, and turns back part of the way after it (bunny: light × 2.1 at
            // step 1200, × 1.6 at the end). One balance per colour channel (the light's colour
            // against the albedo's) was tried and not kept: bunny 25.49 · 27.85 / 26.76, example
            // 27.38 · 28.43 / 27.15, bowl 19.49 · 20.88 / 23.49, glossy 24.03 · 26.96 / 21.50 (the
            // albedo's tint after it as before, e.g. the example's per-channel scale 1.05 / 0.92 / 0.87).
            balance_lr_factor: 0.3,
        }
    }

    /// Whether the light–albedo balance is learnt ([`Self::balance_lr_factor`]).
    pub fn learns_balance(&self) -> bool {
        self.balance_lr_factor > 0.0 && !self.light_fixed && self.indirect != IndirectMode::Mii
    }

    /// The BRDF form step `step` shades with ([`Self::brdf_warmup`]).
    pub fn brdf_at(&self, step: u64) -> BrdfModel {
        if self.brdf == BrdfModel::Calibrated && (step as f64) < self.brdf_warmup as f64 * self.iterations as f64 {
            BrdfModel::Physg
        } else {
            self.brdf
        }
    }

    pub fn validate(&self) -> Result<(), BackendError> {
        let bad = |m: &str| Err(BackendError::Config(format!("stage 2: {m}")));
        if !(0.0..1.0).contains(&self.brdf_warmup) {
            return bad("brdf_warmup must be in [0, 1)");
        }
        if self.lobes == 0 || self.lobes > 1024 {
            return bad("lobes must be in 1..=1024");
        }
        if !matches!(self.step_backend.as_deref(), None | Some("cpu") | Some("wgpu")) {
            return bad("step_backend must be cpu or wgpu");
        }
        if self.batch == 0 || self.points == 0 || self.latent_dim == 0 {
            return bad("batch, points and latent size must be > 0");
        }
        if self.checkpoint_every == 0 {
            return bad("checkpoint_every must be > 0");
        }
        let lrs = [self.lr_material, self.lr_light, self.lr_indirect, self.lr_final_factor, self.axis_lr_factor];
        if lrs.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
            return bad("learning rates must be finite and >= 0");
        }
        if self.indirect == IndirectMode::Mii && (self.mii_lobes == 0 || self.mii_lobes > 256) {
            return bad("mii_lobes must be in 1..=256");
        }
        if !(self.kl_rho > 0.0 && self.kl_rho < 1.0) {
            return bad("kl_rho must be in (0, 1)");
        }
        if !(self.boundary_epsilon >= 0.0 && self.boundary_epsilon < 1.0) {
            return bad("boundary_epsilon must be in [0, 1)");
        }
        if !(self.lr_geometry.is_finite() && self.lr_geometry >= 0.0 && self.geometry_eikonal_weight.is_finite() && self.geometry_eikonal_weight >= 0.0) {
            return bad("lr_geometry and geometry_eikonal_weight must be finite and >= 0");
        }
        if self.refine_geometry && self.geometry_retrace_every == 0 {
            return bad("geometry_retrace_every must be > 0");
        }
        let non_negative = [
            ("smooth_weight", self.smooth_weight),
            ("smooth_sigma", self.smooth_sigma),
            ("kl_weight", self.kl_weight),
            ("mii_weight", self.mii_weight),
            ("balance_lr_factor", self.balance_lr_factor),
            ("retrace_degrees", self.retrace_degrees),
        ];
        if let Some(name) = super::stage1::first_failing(&non_negative, |v| v.is_finite() && v >= 0.0) {
            return bad(&format!("{name} must be finite and >= 0"));
        }
        if !(0.0..=1.0).contains(&self.lr_final_factor) {
            return bad("lr_final_factor (the rate at the end over the start) must be in [0, 1]");
        }
        if !(self.normal_step_factor.is_finite() && self.normal_step_factor > 0.0) {
            return bad("normal_step_factor must be finite and > 0");
        }
        // Normalised units: the object lies inside the unit sphere.
        if !(self.secondary_offset > 0.0 && self.secondary_offset < 1.0 && self.secondary_threshold > 0.0 && self.secondary_threshold < 1.0) {
            return bad("secondary_offset and secondary_threshold must be in (0, 1) (normalised units)");
        }
        Ok(())
    }

    /// Secondary rays one batch would trace without the cache (about half the lobes are above a
    /// point's horizon).
    pub fn secondary_rays_per_batch(&self) -> usize {
        self.batch * self.lobes / 2
    }

    pub fn lr_factor(&self, step: u64) -> f32 {
        (self.lr_final_factor as f64).powf(step as f64 / self.iterations.max(1) as f64) as f32
    }

    /// The material field gets a hash grid with `finest` cells per axis over `[-1, 1]^3` and
    /// `2^log2_table` entries per level (stage 1's sizes for the scene), 16 levels × 2 features,
    /// base 16, fed beside the raw position.
    pub fn with_material_grid(mut self, finest: u32, log2_table: u32) -> Self {
        self.material_encoding = FieldEncoding::hash_grid(finest, log2_table);
        self
    }

    /// The material field's position encoder.
    pub fn material_encoder(&self) -> PositionEncoder {
        match self.material_encoding {
            FieldEncoding::Frequency { n_freqs } => {
                PositionEncoder { encoding: EncodingConfig::frequency(n_freqs as u32), raw_xyz: false, active_levels: None }
            }
            FieldEncoding::HashGrid { .. } => self.material_encoding.encoder(),
        }
    }

    fn pos_encoding(&self) -> EncodingConfig {
        EncodingConfig::frequency(self.pos_freqs)
    }
    fn dir_encoding(&self) -> EncodingConfig {
        EncodingConfig::frequency(self.dir_freqs)
    }

    pub fn encoder_mlp(&self) -> MlpConfig {
        MlpConfig {
            in_dim: self.material_encoder().out_dim(),
            widths: self.material_widths.clone(),
            out_dim: self.latent_dim,
            activation: Activation::LeakyRelu(0.2),
            output_activation: Activation::None,
            skip_layers: vec![],
            weight_norm: false,
        }
    }

    /// The decoders and the first material channel each writes (albedo 0..3, roughness 3,
    /// metallic 4 where [`Self::metallic`]).
    pub fn decoder_mlps(&self) -> Vec<(MlpConfig, usize)> {
        let dec = |out: usize| MlpConfig {
            in_dim: self.latent_dim,
            widths: self.decoder_widths.clone(),
            out_dim: out,
            activation: Activation::LeakyRelu(0.2),
            output_activation: Activation::Sigmoid,
            skip_layers: vec![],
            weight_norm: false,
        };
        let metal = self.metallic as usize;
        match self.decoder {
            DecoderMode::Separate => vec![(dec(3), 0), (dec(1 + metal), 3)],
            DecoderMode::Shared => vec![(dec(4 + metal), 0)],
        }
    }

    /// Material channels the decoders write: albedo (3), roughness, and metallic where modelled.
    pub fn material_channels(&self) -> usize {
        4 + self.metallic as usize
    }

    /// F_ind's reflectance outputs after its K weights: 3 with [`Stage2Config::occluder_reflectance`]
    /// in `ours`, else 0.
    pub fn reflectance_outputs(&self) -> usize {
        if self.indirect == IndirectMode::Ours && self.occluder_reflectance {
            3
        } else {
            0
        }
    }

    /// F_ind (`ours`): `[PE(x'), PE(n')] → K` sigmoid weights (and ρ, see
    /// [`Self::reflectance_outputs`]); the `mii` baseline's net: `PE(x) → mii_lobes × 7` raw SG
    /// parameters (axis, ln λ, μ as the light's).
    pub fn indirect_mlp(&self) -> MlpConfig {
        if self.indirect == IndirectMode::Mii {
            return MlpConfig {
                in_dim: self.pos_encoding().out_dim(3),
                widths: self.indirect_widths.clone(),
                out_dim: self.mii_lobes * LIGHT_STRIDE,
                activation: Activation::Relu,
                output_activation: Activation::None,
                skip_layers: vec![],
                weight_norm: false,
            };
        }
        MlpConfig {
            in_dim: self.pos_encoding().out_dim(3) + self.dir_encoding().out_dim(3),
            widths: self.indirect_widths.clone(),
            out_dim: self.lobes + self.reflectance_outputs(),
            activation: Activation::Relu,
            output_activation: Activation::Sigmoid,
            skip_layers: vec![],
            weight_norm: false,
        }
    }
}

/// Apply `KEY=VALUE` overrides (any field of [`Stage2Config`], JSON values).
pub fn apply_overrides(cfg: Stage2Config, overrides: &[String]) -> Result<Stage2Config, BackendError> {
    let c = super::stage1::override_fields(cfg, overrides)?;
    c.validate()?;
    Ok(c)
}

fn default_boundary_epsilon() -> f32 {
    0.0349
}

fn default_geometry_eikonal() -> f32 {
    0.1
}

fn default_geometry_eikonal_points() -> usize {
    256
}

fn default_geometry_retrace() -> u64 {
    200
}

fn default_mii_lobes() -> usize {
    24
}

fn default_mii_weight() -> f32 {
    1.0
}

fn default_material_encoding() -> FieldEncoding {
    FieldEncoding::Frequency { n_freqs: 10 }
}

/// A standard normal draw.
pub fn normal(rng: &mut impl Rng) -> f64 {
    use rand_distr::{Distribution, StandardNormal};
    StandardNormal.sample(rng)
}

/// A lobe with less than this fraction of the environment's energy is idle (reported; left out of
/// the exported environment).
pub const IDLE_LOBE_FRACTION: f64 = 1e-3;

/// Parameters per lobe in the light tensor.
pub const LIGHT_STRIDE: usize = 7;

/// The initial light: Fibonacci axes, λ = 10 + |20·N(0,1)|, white amplitudes with total energy 0.8·2π
/// (stored as `ln μ` where `log_amplitude`).
pub fn init_light(k: usize, seed: u64, log_amplitude: bool) -> Vec<f32> {
    let mut rng = crate::util::rng(seed ^ 0x5EED_0002);
    let axes = crate::sg::fit::fibonacci_sphere(k);
    let lambdas: Vec<f64> = (0..k).map(|_| 10.0 + (20.0 * normal(&mut rng)).abs()).collect();
    let energy: f64 = lambdas.iter().map(|&l| 2.0 * std::f64::consts::PI / l * (1.0 - (-2.0 * l).exp())).sum();
    let mu = 0.8 * 2.0 * std::f64::consts::PI / energy;
    let mut out = Vec::with_capacity(k * LIGHT_STRIDE);
    for (a, l) in axes.iter().zip(&lambdas) {
        out.extend_from_slice(a);
        out.push(l.ln() as f32);
        out.extend([amplitude_raw(mu, log_amplitude); 3]);
    }
    out
}

/// The effective lobes of a light tensor (axis as stored: shading normalises it); amplitudes stored
/// as `ln μ` where `log_amplitude`, else `μ = |raw|`.
pub fn light_lobes(light: &[f32], log_amplitude: bool) -> Vec<Sg<f64>> {
    light
        .chunks_exact(LIGHT_STRIDE)
        .map(|l| Sg {
            axis: [l[0] as f64, l[1] as f64, l[2] as f64],
            lambda: (l[3] as f64).exp().max(LAMBDA_MIN),
            mu: [4, 5, 6].map(|i| amplitude(l[i], log_amplitude)),
        })
        .collect()
}

/// A lobe amplitude from its stored value.
fn amplitude(raw: f32, log_amplitude: bool) -> f64 {
    if log_amplitude {
        (raw as f64).exp()
    } else {
        (raw as f64).abs()
    }
}

/// The stored value of amplitude `mu` (≥ 0). In log form amplitudes below e^-40 (zero
/// included: ln 0 = -inf) are stored as -40, so the stored value stays finite.
fn amplitude_raw(mu: f64, log_amplitude: bool) -> f32 {
    if log_amplitude {
        mu.ln().max(-40.0) as f32
    } else {
        mu as f32
    }
}

/// The unit vector of `a`, in f32.
pub fn unit_f32(a: [f64; 3]) -> [f32; 3] {
    normalize(a).map(|v| v as f32)
}

fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn f64x3(a: [f32; 3]) -> [f64; 3] {
    a.map(f64::from)
}

/// sRGB encoding with its derivative (0 outside (0, 1), where the encoding clamps).
fn srgb_with_derivative(x: f64) -> (f64, f64) {
    if x <= 0.0 {
        (0.0, 0.0)
    } else if x >= 1.0 {
        (1.0, 0.0)
    } else if x <= 0.003_130_8 {
        (12.92 * x, 12.92)
    } else {
        (1.055 * x.powf(1.0 / 2.4) - 0.055, 1.055 / 2.4 * x.powf(1.0 / 2.4 - 1.0))
    }
}

/// The material field's values at points ([`Stage2Model::material`]).
#[derive(Clone, Debug, Default)]
pub struct Materials {
    /// Linear, [0, 1].
    pub albedo: Vec<[f32; 3]>,
    /// Perceptual roughness, [`R_MIN`, 1].
    pub roughness: Vec<f32>,
    /// [0, 1]; 0 everywhere where the model is dielectric ([`Stage2Config::metallic`] off).
    pub metallic: Vec<f32>,
}

impl Materials {
    /// Point `i`'s `(albedo, roughness, metallic)` in f64 (shading's precision).
    pub fn at(&self, i: usize) -> ([f64; 3], f64, f64) {
        (self.albedo[i].map(f64::from), self.roughness[i] as f64, self.metallic[i] as f64)
    }
}

/// The stage-2 networks and light, parameters on the host.
#[derive(Clone, Debug)]
pub struct Stage2Model {
    pub cfg: Stage2Config,
    /// The material field's position encoder; its parameters (a hash grid's tables, or none)
    /// lead `enc_params`, the encoder MLP's follow.
    pub mat_enc: PositionEncoder,
    pub encoder: Mlp,
    pub decoders: Vec<(Mlp, usize)>,
    pub indirect: Mlp,
    pub enc_params: Vec<f32>,
    pub dec_params: Vec<Vec<f32>>,
    pub light: Vec<f32>,
    pub ind_params: Vec<f32>,
    /// The factor on the decoded albedo and the occluders' reflectance, `e^−g` of the light–albedo
    /// balance ([`Stage2Config::balance_lr_factor`]); 1 where it is not learnt.
    pub albedo_scale: f64,
}

impl Stage2Model {
    pub fn new(cfg: &Stage2Config) -> Result<Self, BackendError> {
        cfg.validate()?;
        let mat_enc = cfg.material_encoder();
        mat_enc.encoding.validate(3)?;
        let encoder = Mlp::new(cfg.encoder_mlp())?;
        let decoders: Vec<(Mlp, usize)> = cfg.decoder_mlps().into_iter().map(|(c, o)| Mlp::new(c).map(|m| (m, o))).collect::<Result<_, _>>()?;
        let indirect = Mlp::new(cfg.indirect_mlp())?;
        let mut enc_params = mat_enc.init(cfg.seed.wrapping_add(100));
        enc_params.extend(encoder.init(Init::Default, cfg.seed.wrapping_add(101)));
        let dec_params = decoders.iter().enumerate().map(|(i, (m, _))| m.init(Init::Default, cfg.seed.wrapping_add(202 + i as u64))).collect();
        let ind_params = indirect.init(Init::Default, cfg.seed.wrapping_add(303));
        let light = init_light(cfg.lobes, cfg.seed, cfg.log_amplitude);
        Ok(Self { cfg: cfg.clone(), mat_enc, encoder, decoders, indirect, enc_params, dec_params, light, ind_params, albedo_scale: 1.0 })
    }

    pub fn num_params(&self) -> usize {
        self.enc_params.len() + self.dec_params.iter().map(Vec::len).sum::<usize>() + self.light.len() + self.ind_params.len()
    }

    pub fn lobes(&self) -> Vec<Sg<f64>> {
        light_lobes(&self.light, self.cfg.log_amplitude)
    }

    /// Set the light to `lobes` (normalised frame), one per configured lobe.
    pub fn set_light(&mut self, lobes: &[Sg<f64>]) -> Result<(), BackendError> {
        if lobes.len() != self.cfg.lobes {
            return Err(BackendError::Config(format!("stage 2: {} lobes given for a light of {}", lobes.len(), self.cfg.lobes)));
        }
        if lobes.iter().any(|l| !(l.lambda > 0.0 && l.lambda.is_finite() && l.axis.iter().chain(&l.mu).all(|v| v.is_finite()) && l.mu.iter().all(|&m| m >= 0.0))) {
            return Err(BackendError::Config("stage 2: a given light lobe is not finite, has sharpness <= 0 or a negative amplitude".into()));
        }
        let log = self.cfg.log_amplitude;
        self.light = lobes
            .iter()
            .flat_map(|l| {
                let a = unit_f32(l.axis);
                let m = l.mu.map(|v| amplitude_raw(v, log));
                [a[0], a[1], a[2], (l.lambda.max(LAMBDA_MIN) as f32).ln(), m[0], m[1], m[2]]
            })
            .collect();
        Ok(())
    }

    /// Unit lobe axes (normalised frame).
    pub fn axes(&self) -> Vec<[f32; 3]> {
        self.light.chunks_exact(LIGHT_STRIDE).map(|l| normalize(f64x3([l[0], l[1], l[2]])).map(|v| v as f32)).collect()
    }

    /// The light's energy per colour channel (each lobe's `μ_c·∫G`), idle lobes included.
    pub fn channel_energies(&self) -> [f64; 3] {
        self.lobes().iter().fold([0.0; 3], |e, l| {
            let s = crate::sg::shade::sg_integral(l.lambda);
            [0, 1, 2].map(|c| e[c] + l.mu[c] * s)
        })
    }

    /// Each lobe's energy, `mean(μ)·∫G` over the sphere.
    pub fn lobe_energies(&self) -> Vec<f64> {
        self.lobes().iter().map(|l| (l.mu[0] + l.mu[1] + l.mu[2]) / 3.0 * crate::sg::shade::sg_integral(l.lambda)).collect()
    }

    /// Lobes carrying less than [`IDLE_LOBE_FRACTION`] of the total energy (they light nothing).
    pub fn idle_lobes(&self) -> Vec<usize> {
        let e = self.lobe_energies();
        let total: f64 = e.iter().sum();
        if !(total > 0.0) {
            return Vec::new(); // a dark (or broken) light: nothing to rank, keep every lobe
        }
        (0..e.len()).filter(|&k| e[k] < IDLE_LOBE_FRACTION * total).collect()
    }

    /// The environment in the asset frame (`rotation`: normalised → asset), idle lobes left out:
    /// the exported light is sized to what the scene's light needs.
    pub fn env_sgs(&self, rotation: glam::DMat3) -> EnvSgs {
        let idle = self.idle_lobes();
        EnvSgs {
            lobes: self
                .lobes()
                .iter()
                .enumerate()
                .filter(|(k, _)| !idle.contains(k))
                .map(|(_, l)| {
                    let a = rotation * glam::DVec3::from(normalize(l.axis));
                    SgLobe { axis: a.as_vec3().to_array(), sharpness: l.lambda as f32, amplitude: l.mu.map(|v| v as f32) }
                })
                .collect(),
        }
    }

    fn encode_pos(&self, x: &[[f32; 3]]) -> Vec<f32> {
        encoding_forward_cpu(&self.cfg.pos_encoding(), &[], bytemuck::cast_slice(x), 3)
    }

    /// `enc_params` split into (position encoder, encoder MLP).
    fn enc_split(&self) -> (&[f32], &[f32]) {
        self.enc_params.split_at(self.mat_enc.num_params())
    }

    fn encode_material(&self, x: &[[f32; 3]]) -> Vec<f32> {
        self.mat_enc.forward(self.enc_split().0, bytemuck::cast_slice(x))
    }

    /// The decoder that writes roughness and the column it writes it to. The decoder's sigmoid
    /// output `y` is the roughness `R_MIN + (1 − R_MIN)·y` ([`roughness_from_decoder`]).
    fn roughness_decoder(&self) -> (usize, usize) {
        let i = self.decoders.iter().position(|(m, o)| (*o..*o + m.out_dim()).contains(&3)).unwrap_or(0);
        (i, 3 - self.decoders[i].1)
    }

    /// With [`RoughnessMode::Constant`]: the object's roughness (the roughness decoder at the fixed
    /// latent)
    /// and that forward pass (kept for the backward).
    fn constant_roughness(&self, backend: &Backend, train: bool) -> Result<Option<(f32, crate::nn::mlp::MlpForward)>, BackendError> {
        if self.cfg.roughness != RoughnessMode::Constant {
            return Ok(None);
        }
        let (i, col) = self.roughness_decoder();
        let (m, _) = &self.decoders[i];
        let f = backend.mlp_forward(m, &backend.upload(&self.dec_params[i]), &backend.from_vec(vec![CONSTANT_LATENT; self.cfg.latent_dim]), train)?;
        let r = roughness_from_decoder(backend.to_vec(&f.output)?[col]);
        Ok(Some((r, f)))
    }

    /// Albedo (linear, [0, 1]), roughness and metallic (0 where not modelled) at points: forward
    /// only, in chunks.
    pub fn material(&self, backend: &Backend, x: &[[f32; 3]]) -> Result<Materials, BackendError> {
        let mut albedo = Vec::with_capacity(x.len());
        let mut rough = Vec::with_capacity(x.len());
        let mut metal = Vec::with_capacity(x.len());
        let constant = self.constant_roughness(backend, false)?.map(|(r, _)| r);
        let enc_p = backend.upload(self.enc_split().1);
        let dec_p: Vec<_> = self.dec_params.iter().map(|p| backend.upload(p)).collect();
        for c in x.chunks(1 << 14) {
            let enc = self.encode_material(c);
            let z = backend.mlp_forward(&self.encoder, &enc_p, &backend.from_vec(enc), false)?;
            let mut mat = vec![0.0f32; c.len() * MAT];
            for ((m, o), p) in self.decoders.iter().zip(&dec_p) {
                let out = backend.to_vec(&backend.mlp_forward(m, p, &z.output, false)?.output)?;
                let od = m.out_dim();
                for i in 0..c.len() {
                    mat[MAT * i + o..MAT * i + o + od].copy_from_slice(&out[od * i..od * (i + 1)]);
                }
            }
            let a_s = self.albedo_scale as f32;
            for m in mat.chunks_exact(MAT) {
                albedo.push([m[0], m[1], m[2]].map(|v| (a_s * v).min(1.0)));
                rough.push(constant.unwrap_or(roughness_from_decoder(m[3])));
                metal.push(m[4]);
            }
        }
        Ok(Materials { albedo, roughness: rough, metallic: metal })
    }

    fn indirect_input(&self, hx: &[[f32; 3]], hn: &[[f32; 3]]) -> Vec<f32> {
        let pe = self.encode_pos(hx);
        let de = encoding_forward_cpu(&self.cfg.dir_encoding(), &[], bytemuck::cast_slice(hn), 3);
        let (pd, dd) = (pe.len() / hx.len().max(1), de.len() / hn.len().max(1));
        let mut input = Vec::with_capacity(hx.len() * (pd + dd));
        for i in 0..hx.len() {
            input.extend_from_slice(&pe[pd * i..pd * (i + 1)]);
            input.extend_from_slice(&de[dd * i..dd * (i + 1)]);
        }
        input
    }

    /// The `mii` baseline's raw SG rows `[n, mii_lobes·7]` at points, and the forward pass.
    fn mii_forward(&self, backend: &Backend, params: &Tensor, x: &[[f32; 3]], train: bool) -> Result<(Vec<f32>, crate::nn::mlp::MlpForward), BackendError> {
        let f = backend.mlp_forward(&self.indirect, params, &backend.from_vec(self.encode_pos(x)), train)?;
        Ok((backend.to_vec(&f.output)?, f))
    }

    /// The `mii` baseline's indirect SGs at points (empty rows in other modes): forward only.
    pub fn mii_lobes_at(&self, backend: &Backend, x: &[[f32; 3]]) -> Result<Vec<Vec<Sg<f64>>>, BackendError> {
        if self.cfg.indirect != IndirectMode::Mii {
            return Ok(vec![Vec::new(); x.len()]);
        }
        let mut out = Vec::with_capacity(x.len());
        let params = backend.upload(&self.ind_params);
        for c in x.chunks(1 << 13) {
            let (raw, _) = self.mii_forward(backend, &params, c, false)?;
            out.extend(raw.chunks_exact(self.cfg.mii_lobes * LIGHT_STRIDE).map(|r| light_lobes(r, false)));
        }
        Ok(out)
    }

    /// F_ind's mixture at hits: forward only.
    pub fn indirect_mix(&self, backend: &Backend, hx: &[[f32; 3]], hn: &[[f32; 3]]) -> Result<IndirectMix, BackendError> {
        let k = self.cfg.lobes;
        if self.cfg.indirect != IndirectMode::Ours {
            return Ok(IndirectMix::uniform(k).scaled(self.albedo_scale));
        }
        let mut sig = Vec::with_capacity(hx.len() * (k + self.cfg.reflectance_outputs()));
        let params = backend.upload(&self.ind_params);
        for (cx, cn) in hx.chunks(1 << 13).zip(hn.chunks(1 << 13)) {
            let inp = self.indirect_input(cx, cn);
            sig.extend(backend.to_vec(&backend.mlp_forward(&self.indirect, &params, &backend.from_vec(inp), false)?.output)?);
        }
        Ok(IndirectMix::from_sigmoid(&sig, k, self.cfg.reflectance_outputs()).0.scaled(self.albedo_scale))
    }
}

/// F_ind's output at the secondary hits (slots): the normalised mixture weights `[slots, K]` and the
/// occluder's reflectance ρ per slot. `uniform` holds one row of weights for every slot; ρ is 1
/// where F_ind gives none (`uniform`, or [`Stage2Config::occluder_reflectance`] off).
#[derive(Clone, Debug)]
pub struct IndirectMix {
    lobes: usize,
    /// `[slots, K]`, or one row `[K]` shared by every slot.
    weights: Vec<f32>,
    /// Per slot; empty: ρ = 1.
    reflectance: Vec<[f32; 3]>,
    /// The factor on every slot's ρ (the model's [`Stage2Model::albedo_scale`]).
    scale: f64,
}

impl IndirectMix {
    /// Uniform weights `1/K` and ρ = 1 at every slot.
    pub fn uniform(k: usize) -> Self {
        Self { lobes: k, weights: vec![1.0 / k as f32; k], reflectance: Vec::new(), scale: 1.0 }
    }

    /// Every slot's ρ times `scale`.
    pub fn scaled(self, scale: f64) -> Self {
        Self { scale, ..self }
    }

    /// From F_ind's sigmoid rows (K weights, then `r` reflectance outputs, 0 or 3): the weights
    /// L1-normalised, and the sums they were divided by.
    pub fn from_sigmoid(sig: &[f32], k: usize, r: usize) -> (Self, Vec<f64>) {
        let rows = sig.chunks_exact(k + r);
        let sums: Vec<f64> = rows.clone().map(|row| row[..k].iter().map(|&v| v as f64).sum::<f64>().max(1e-12)).collect();
        let weights = rows.clone().zip(&sums).flat_map(|(row, &s)| row[..k].iter().map(move |&v| (v as f64 / s) as f32)).collect();
        let reflectance = if r == 3 { rows.map(|row| [row[k], row[k + 1], row[k + 2]]).collect() } else { Vec::new() };
        (Self { lobes: k, weights, reflectance, scale: 1.0 }, sums)
    }

    /// Slot `s`'s weights.
    pub fn row(&self, s: usize) -> &[f32] {
        let s = if self.weights.len() == self.lobes { 0 } else { s };
        &self.weights[s * self.lobes..(s + 1) * self.lobes]
    }

    /// Slot `s`'s reflectance.
    pub fn rho(&self, s: usize) -> [f64; 3] {
        self.reflectance.get(s).map_or([self.scale; 3], |r| r.map(|v| self.scale * v as f64))
    }

    /// The lobe replacing lobe `kk` at slot `s` (see [`mix_lobe`]).
    pub fn lobe(&self, lobes: &[Sg<f64>], kk: usize, s: usize) -> Sg<f64> {
        mix_lobe(lobes, kk, self.row(s), self.rho(s))
    }
}

/// The lobe replacing lobe `k` at a blocked direction: axis ξ_k, `λ = Σ w_j λ_j`, `μ = ρ·Σ w_j μ_j`.
pub fn mix_lobe(lobes: &[Sg<f64>], k: usize, w: &[f32], rho: [f64; 3]) -> Sg<f64> {
    let mut lam = 0.0;
    let mut mu = [0.0; 3];
    for (j, l) in lobes.iter().enumerate() {
        let wj = w[j] as f64;
        lam += wj * l.lambda;
        for c in 0..3 {
            mu[c] += wj * l.mu[c];
        }
    }
    Sg { axis: lobes[k].axis, lambda: lam.max(LAMBDA_MIN), mu: [0, 1, 2].map(|c| rho[c] * mu[c]) }
}

/// The lobes lighting one point: the environment with each blocked lobe `(k, slot)` replaced
/// (`ours`/`uniform`: by `mix`'s mixture of the environment at that slot, see [`mix_lobe`];
/// `mii`: dropped), followed by the point's `mii` SGs (`extra`, empty in other modes), followed by
/// one copy of the environment lobe per boundary light (`vis[slot] > 0`, see
/// [`boundary_visibility`]): its amplitude times `v`, the replacement's times `1 − v`. `vis` may be
/// empty (no boundary lights).
pub fn point_lobes(mode: IndirectMode, lobes: &[Sg<f64>], blocked: &[(usize, usize)], mix: &IndirectMix, extra: &[Sg<f64>], vis: &[f64]) -> Vec<Sg<f64>> {
    let mut li = lobes.to_vec();
    let mut copies = Vec::new();
    for &(kk, s) in blocked {
        li[kk] = match mode {
            IndirectMode::Mii => Sg { mu: [0.0; 3], ..lobes[kk] },
            _ => mix.lobe(lobes, kk, s),
        };
        let v = vis.get(s).copied().unwrap_or(0.0);
        if v > 0.0 {
            li[kk].mu = li[kk].mu.map(|m| m * (1.0 - v));
            copies.push(Sg { mu: lobes[kk].mu.map(|m| m * v), ..lobes[kk] });
        }
    }
    li.extend_from_slice(extra);
    li.extend(copies);
    li
}

/// Boundary lights (the supplementary's Leibniz/Reynolds term for a visibility that jumps where
/// the occluder's silhouette crosses a lobe axis). A secondary hit with `|n'·ξ0| < ε` (ξ0 the unit
/// axis the ray was traced along, n' the occluder's outward normal at the hit) grazes the
/// occluder: the ray lies on its silhouette. There lobe k lights the point with
/// `v·(environment lobe) + (1 − v)·(replacement lobe)`, `v` the visibility ramp across the
/// silhouette, `v = clamp(½ + n'·(ξ − ξ0)/(2ε))`: ½ on the traced axis, 1 once the axis has turned
/// ε away from the occluder, 0 once it has turned ε into it (a box filter of half-width ε
/// radians over the hard visibility). The value is the same in both [`BoundaryMode`]s; `Flowing`
/// passes `∂v/∂ξ = (I − ξξᵀ)n'/(2ε)`, so the axis learns `(L_env − L_ind)·∂v/∂ξ`, the boundary term
/// a hard visibility test (and the detached public code) never sees.
///
/// With the geometry refined (`--refine-geometry`), the occluder moves too: `offset` is the
/// angle it has receded from the ray since the trace, `(f(x';θ) − f(x';θ_traced))/|x' − x|`, added
/// to `n'·(ξ − ξ0)`.
///
/// Returns `(v, ∂v/∂(stored axis), ∂v/∂offset)` for a boundary light, None otherwise (`ε = 0`
/// turns them off).
pub fn boundary_visibility(raw_axis: [f64; 3], traced: [f32; 3], n2: [f32; 3], offset: f64, eps: f64, mode: BoundaryMode) -> Option<(f64, [f64; 3], f64)> {
    let a0 = normalize(f64x3(traced));
    let n = f64x3(n2);
    if eps <= 0.0 || !(dot3(n, a0).abs() < eps) {
        return None;
    }
    let len = dot3(raw_axis, raw_axis).sqrt().max(1e-12);
    let xi = raw_axis.map(|v| v / len);
    let (nx, n0) = (dot3(n, xi), dot3(n, a0));
    let s = 0.5 + (nx - n0 + offset) / (2.0 * eps);
    let mut d = [0.0; 3];
    let mut d_off = 0.0;
    if mode == BoundaryMode::Flowing && s > 0.0 && s < 1.0 {
        for a in 0..3 {
            d[a] = (n[a] - xi[a] * nx) / (2.0 * eps * len);
        }
        d_off = 1.0 / (2.0 * eps);
    }
    Some((s.clamp(0.0, 1.0), d, d_off))
}

/// [`boundary_visibility`] for every slot `(point, lobe k, x', n')` of a batch (`(0, 0, 0)` where
/// the hit is not a boundary light or the batch does not know the traced axes); `offsets` per
/// slot (empty: 0).
fn slot_visibility(model: &Stage2Model, lobes: &[Sg<f64>], traced: &[[f32; 3]], slots: &[(usize, [f32; 3])], offsets: &[f64]) -> Vec<(f64, [f64; 3], f64)> {
    let eps = model.cfg.boundary_epsilon as f64;
    slots
        .iter()
        .enumerate()
        .map(|(s, &(kk, n2))| {
            let off = offsets.get(s).copied().unwrap_or(0.0);
            traced.get(kk).and_then(|t| boundary_visibility(lobes[kk].axis, *t, n2, off, eps, model.cfg.boundary)).unwrap_or((0.0, [0.0; 3], 0.0))
        })
        .collect()
}

/// Gradient with respect to a stored lobe `[ξ raw (3), ln λ, amplitude (3)]` from the gradient `g`
/// with respect to the effective lobe (λ = exp(raw) floored at `LAMBDA_MIN`; μ = exp(raw) where
/// `log_amplitude`, else μ = |raw|).
fn stored_lobe_grad(raw: &[f32], lambda: f64, g: &[f64; 7], log_amplitude: bool) -> [f64; 7] {
    let mut out = *g;
    out[3] = if (raw[3] as f64).exp() > LAMBDA_MIN { g[3] * lambda } else { 0.0 };
    for c in 0..3 {
        let d_mu = if log_amplitude { (raw[4 + c] as f64).exp() } else { (raw[4 + c] as f64).signum() };
        out[4 + c] = g[4 + c] * d_mu;
    }
    out
}

/// The `mii` baseline's fit (InvRender's supervision of its indirect SGs): L1 between the sum of
/// a point's SGs along each direction and the radiance the stage-1 field sends back from there
/// (0 where the direction sees the environment), summed over `targets` and scaled by `scale`.
/// Returns the loss and its gradient with respect to the effective lobes.
pub fn mii_fit(lobes: &[Sg<f64>], targets: &[([f32; 3], [f32; 3])], scale: f64) -> (f64, Vec<[f64; 7]>) {
    type D = Dual<7>;
    let cst = |x: f64| D { v: x, d: [0.0; 7] };
    // Each lobe as duals in its 7 effective parameters, axis normalised as the shading does.
    let duals: Vec<Sg<D>> = lobes
        .iter()
        .map(|l| Sg {
            axis: normalize([D::var(l.axis[0], 0), D::var(l.axis[1], 1), D::var(l.axis[2], 2)]),
            lambda: D::var(l.lambda, 3),
            mu: [D::var(l.mu[0], 4), D::var(l.mu[1], 5), D::var(l.mu[2], 6)],
        })
        .collect();
    let mut loss = 0.0;
    let mut g = vec![[0.0f64; 7]; lobes.len()];
    for (dir, t) in targets {
        let w = f64x3(*dir).map(cst);
        let vals: Vec<[D; 3]> = duals.iter().map(|l| sg_eval(l, w)).collect();
        for c in 0..3 {
            let err = vals.iter().map(|v| v[c].v).sum::<f64>() - t[c] as f64;
            loss += scale * err.abs();
            let dp = scale * err.signum();
            for (gj, v) in g.iter_mut().zip(&vals) {
                gj.iter_mut().zip(&v[c].d).for_each(|(a, d)| *a += dp * d);
            }
        }
    }
    (loss, g)
}

/// A metallic surface's per-channel weights `(ks, kd)` from its [`energy_gaps`]:
/// `ks_c = m·(E(a_c) − E(F0))` in the BRDF's energy measure ([`BrdfSg::energy`]; PhySG's form:
/// `m·(a_c − F0)`), `kd_c = (1 − m)·a_c/π`.
/// The specular sum is `Σ μ_c·(F_s + ks_c·F_e)` (Principled BSDF's linear blend of a dielectric
/// and a metal of reflectance `a`), the diffuse `Σ μ_c·kd_c·F_d`.
fn metal_weights<S: Scalar>(gaps: [S; 3], albedo: [f64; 3], metal: f64) -> ([S; 3], [f64; 3]) {
    (gaps.map(|g| g * S::c(metal)), diffuse_weights(albedo, metal))
}

/// [`metal_weights`]' diffuse side, `(1 − m)·a_c/π`.
fn diffuse_weights(albedo: [f64; 3], metal: f64) -> [f64; 3] {
    albedo.map(|a| (1.0 - metal) * a * (1.0 / PI))
}

/// `E(a_c) − E(F0)` per channel ([`BrdfSg::energy`]): a full metal's specular beyond the
/// dielectric's, per unit of `F_e`.
fn energy_gaps<S: Scalar>(brdf: &BrdfSg<S>, albedo: [f64; 3]) -> [S; 3] {
    let e0 = brdf.energy(S::c(F0));
    albedo.map(|a| brdf.energy(S::c(a)) - e0)
}

/// Outgoing radiance (linear) at one point: the specular and diffuse sums of
/// [`crate::sg::shade::lobe_contribution`] before their clamps, the BRDF's side formed once
/// ([`BrdfSg`]); with `metal` > 0 a blend of the dielectric and a metal of reflectance `albedo`,
/// the diffuse term scaled by `1 − metal` ([`Stage2Config::metallic`]).
pub fn shade_f64(model: BrdfModel, albedo: [f64; 3], rough: f64, metal: f64, n: [f64; 3], v: [f64; 3], lobes: &[Sg<f64>]) -> ([f64; 3], [f64; 3]) {
    let brdf = BrdfSg::with_model(model, n, v, rough);
    let (ks, kd) = metal_weights(energy_gaps(&brdf, albedo), albedo, metal);
    let mut spec = [0.0; 3];
    let mut diff = [0.0; 3];
    let factors = lanes::lobe_factors(SimdLevel::detected(), &brdf.map(Dual::<0>::c), lobes, None);
    for (l, [fs, fe, fd]) in lobes.iter().zip(factors) {
        for c in 0..3 {
            spec[c] += l.mu[c] * (fs.v + ks[c] * fe.v);
            diff[c] += l.mu[c] * kd[c] * fd.v;
        }
    }
    (spec, diff)
}

/// One point's shading under its lobes, kept for its gradient: per lobe the factors of
/// [`crate::sg::shade::lobe_factors`] as duals in (R, ξ (3), λ), the BRDF's side formed once.
/// Amplitude and albedo enter linearly, so five tangents give the whole gradient (not eleven
/// through every channel). `spec`/`diff` are [`shade_f64`]'s sums, computed the same way.
pub struct PointShading {
    pub spec: [f64; 3],
    pub diff: [f64; 3],
    /// Per lobe `[F_s, F_e, F_d]` ([`BrdfSg::lobe_factors_f0`], [`LANES`](lanes::LANES) lobes
    /// at a time).
    factors: Vec<[Dual<5>; 3]>,
    /// The metal weights `ks_c` as duals in R ([`metal_weights`]), `∂ks_c/∂a_c`, and
    /// `E(a_c) − E(F0)` (`∂ks_c/∂m`).
    ks: [Dual<5>; 3],
    dks_da: [f64; 3],
    energy_gap: [f64; 3],
}

/// A point's `PointShading::grad`: `(d albedo, d roughness, d metallic, per lobe [d axis (3), d λ, d μ (3)])`.
pub type ShadingGrad = ([f64; 3], f64, f64, Vec<[f64; 7]>);

impl PointShading {
    pub fn new(model: BrdfModel, albedo: [f64; 3], rough: f64, metal: f64, n: [f64; 3], v: [f64; 3], lobes: &[Sg<f64>]) -> Self {
        type D = Dual<5>;
        let cst = |x: f64| D { v: x, d: [0.0; 5] };
        let brdf = BrdfSg::with_model(model, n.map(cst), v.map(cst), D::var(rough, 0));
        let gaps = energy_gaps(&brdf, albedo);
        let (ks, kd) = metal_weights(gaps, albedo, metal);
        let dks_da = albedo.map(|a| metal * brdf.energy_slope(a));
        let energy_gap = gaps.map(|g| g.v);
        // The lobe's axis is tangents 1..4, its sharpness tangent 4.
        let factors = lanes::lobe_factors(SimdLevel::detected(), &brdf, lobes, Some(1));
        let mut out = Self { spec: [0.0; 3], diff: [0.0; 3], factors, ks, dks_da, energy_gap };
        for (l, [fs, fe, fd]) in lobes.iter().zip(&out.factors) {
            for c in 0..3 {
                out.spec[c] += l.mu[c] * (fs.v + ks[c].v * fe.v);
                out.diff[c] += l.mu[c] * kd[c] * fd.v;
            }
        }
        out
    }

    /// Gradient of `Σ_c d_out_c · L_c` ([`ShadingGrad`]) at the `albedo` and `metal` the shading
    /// was formed with. A channel whose specular or diffuse sum is clamped passes no gradient
    /// through it.
    pub fn grad(&self, albedo: [f64; 3], metal: f64, lobes: &[Sg<f64>], d_out: [f64; 3]) -> ShadingGrad {
        let ws = [0, 1, 2].map(|c| if self.spec[c] > 0.0 { d_out[c] } else { 0.0 });
        let wd = [0, 1, 2].map(|c| if self.diff[c] > 0.0 { d_out[c] } else { 0.0 });
        let ks = self.ks.map(|k| k.v);
        let kd = diffuse_weights(albedo, metal);
        let mut da = [0.0; 3];
        let (mut dr, mut dm) = (0.0, 0.0);
        // Per channel Σ_l μ_c·F_e: what the metal weights' own derivatives multiply.
        let mut fe_sum = [0.0; 3];
        let mut dl = Vec::with_capacity(lobes.len());
        for (l, [fs, fe, fd]) in lobes.iter().zip(&self.factors) {
            let (mut cs, mut ce, mut cd) = (0.0, 0.0, 0.0);
            let mut g = [0.0f64; 7];
            for c in 0..3 {
                cs += ws[c] * l.mu[c];
                ce += ws[c] * l.mu[c] * ks[c];
                cd += wd[c] * l.mu[c] * kd[c];
                fe_sum[c] += l.mu[c] * fe.v;
                g[4 + c] = ws[c] * (fs.v + ks[c] * fe.v) + wd[c] * kd[c] * fd.v;
                da[c] += wd[c] * l.mu[c] * (1.0 - metal) * (1.0 / PI) * fd.v;
                dm += -wd[c] * l.mu[c] * albedo[c] * (1.0 / PI) * fd.v;
            }
            let d: [f64; 5] = std::array::from_fn(|i| cs * fs.d[i] + ce * fe.d[i] + cd * fd.d[i]);
            dr += d[0];
            g[..4].copy_from_slice(&d[1..]);
            dl.push(g);
        }
        for c in 0..3 {
            // ks_c = m·(E(a_c) − E(F0)): through the albedo, the metallic and (calibrated) R.
            da[c] += ws[c] * fe_sum[c] * self.dks_da[c];
            dm += ws[c] * fe_sum[c] * self.energy_gap[c];
            dr += ws[c] * fe_sum[c] * self.ks[c].d[0];
        }
        (da, dr, dm, dl)
    }
}

/// Gradient of `Σ_c d_out_c · L_c` for one point with respect to the shading normal (the
/// geometry refinement's path; masks as [`PointShading::grad`]).
#[allow(clippy::too_many_arguments)]
pub fn shade_normal_grad(model: BrdfModel, albedo: [f64; 3], rough: f64, metal: f64, n: [f64; 3], v: [f64; 3], lobes: &[Sg<f64>], spec: [f64; 3], diff: [f64; 3], d_out: [f64; 3]) -> [f64; 3] {
    let ws = [0, 1, 2].map(|c| if spec[c] > 0.0 { d_out[c] } else { 0.0 });
    let wd = [0, 1, 2].map(|c| if diff[c] > 0.0 { d_out[c] } else { 0.0 });
    type D = Dual<3>;
    let cst = |x: f64| D { v: x, d: [0.0; 3] };
    // The BRDF's side once per point (as `PointShading`), the normal's tangents through it.
    let brdf = BrdfSg::with_model(model, [D::var(n[0], 0), D::var(n[1], 1), D::var(n[2], 2)], v.map(cst), cst(rough));
    let (ks, kd) = metal_weights(energy_gaps(&brdf, albedo), albedo, metal);
    let mut dn = [0.0; 3];
    let factors = lanes::lobe_factors(SimdLevel::detected(), &brdf, lobes, None);
    for (l, [fs, fe, fd]) in lobes.iter().zip(factors) {
        // spec_c = μ_c·(F_s + ks_c·F_e), diff_c = μ_c·kd_c·F_d; ks_c depends on n through n·v.
        for c in 0..3 {
            let s = fs + ks[c] * fe;
            for (a, d) in dn.iter_mut().enumerate() {
                *d += ws[c] * l.mu[c] * s.d[a] + wd[c] * l.mu[c] * kd[c] * fd.d[a];
            }
        }
    }
    dn
}

/// One training batch of cached surface points.
#[derive(Clone, Debug, Default)]
pub struct Stage2Batch {
    pub x: Vec<[f32; 3]>,
    pub n: Vec<[f32; 3]>,
    /// Surface → camera, unit.
    pub v: Vec<[f32; 3]>,
    /// The photo, sRGB-encoded.
    pub target: Vec<[f32; 3]>,
    /// Per point: the blocked lobes and their hits `(k, x', n')`.
    pub hits: Vec<Vec<(usize, [f32; 3], [f32; 3])>>,
    /// `mii` only, per point: every lobe axis above the horizon and the linear radiance arriving
    /// along it from the object (the stage-1 colour at the hit; 0 where it is not blocked).
    pub mii_targets: Vec<Vec<([f32; 3], [f32; 3])>>,
    /// Per lobe: the unit axis its hits were traced along (empty: no boundary lights).
    pub traced_axes: Vec<[f32; 3]>,
    /// Per point, beside `hits`: the SDF at each hit when it was traced (`--refine-geometry`; empty
    /// elsewhere).
    pub hit_sdf: Vec<Vec<f32>>,
    /// Per slot (the batch's hits in order): the boundary lights' occluder offset (see
    /// [`boundary_visibility`]; empty: 0).
    pub boundary_offset: Vec<f64>,
}

impl Stage2Batch {
    pub fn len(&self) -> usize {
        self.x.len()
    }
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

/// Loss weights of one step.
#[derive(Clone, Copy, Debug)]
pub struct Stage2Weights {
    pub smooth: f32,
    pub sigma: f32,
    pub kl: f32,
    pub rho: f32,
}

/// Loss parts and figures of one step.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct Stage2Stats {
    pub step: u64,
    pub loss: f64,
    pub rgb: f64,
    pub smooth: f64,
    pub kl: f64,
    /// The `mii` baseline's fit of its indirect SGs (0 in other modes).
    pub indirect_fit: f64,
    /// The refined SDF's eikonal term (`--refine-geometry`; 0 otherwise).
    #[serde(default)]
    pub eikonal: f64,
    pub psnr: f64,
    /// Blocked (point, lobe) pairs in the batch.
    pub blocked: usize,
    /// Of those, boundary lights (grazing hits, see [`boundary_visibility`]).
    #[serde(default)]
    pub boundary: usize,
    pub applied: bool,
    pub grad_norm: f64,
}

/// Gradients of one step.
#[derive(Clone, Debug, Default)]
pub struct Stage2Grads {
    pub stats: Stage2Stats,
    pub d_enc: Vec<f32>,
    pub d_dec: Vec<Vec<f32>>,
    pub d_light: Vec<f32>,
    pub d_ind: Vec<f32>,
    /// The refined SDF's parameters (`--refine-geometry`; empty otherwise).
    pub d_sdf: Vec<f32>,
    /// The batch's render (linear RGB), for figures.
    pub rgb: Vec<[f32; 3]>,
    /// With [`loss_and_grad_with`]'s `geometry` flag: per point the gradient with respect to the
    /// shading normal and the colour term's gradient with respect to the point's position
    /// (through the material and the `mii` SGs at it; the normal and the hits held), per slot
    /// with respect to the boundary offset.
    pub d_normal: Vec<[f64; 3]>,
    pub d_point: Vec<[f64; 3]>,
    pub d_offset: Vec<f64>,
    /// dL/dg of the light–albedo balance ([`Stage2Config::balance_lr_factor`]; 0 where not learnt).
    pub d_balance: f64,
}

/// Loss and exact gradients of one batch (see the module docs). `noise_seed` draws the latent
/// perturbation of the smoothness term.
pub fn loss_and_grad(backend: &Backend, model: &Stage2Model, batch: &Stage2Batch, w: &Stage2Weights, noise_seed: u64) -> Result<Stage2Grads, BackendError> {
    loss_and_grad_with(backend, model, batch, w, noise_seed, false)
}

/// [`loss_and_grad`]; with `geometry` it also returns the gradients with respect to the shading
/// normals and the boundary offsets (what [`loss_and_grad_geometry`] chains into the SDF).
pub fn loss_and_grad_with(backend: &Backend, model: &Stage2Model, batch: &Stage2Batch, w: &Stage2Weights, noise_seed: u64, geometry: bool) -> Result<Stage2Grads, BackendError> {
    let b = batch.len();
    let k = model.cfg.lobes;
    let ld = model.cfg.latent_dim;
    if b == 0 {
        return Err(BackendError::Shape("stage 2: empty batch".into()));
    }
    // Material: encoder → latent → decoders, on z and on z + ε.
    let enc_p = backend.upload(model.enc_split().1);
    let zf = backend.mlp_forward(&model.encoder, &enc_p, &backend.from_vec(model.encode_material(&batch.x)), true)?;
    let z = backend.to_vec(&zf.output)?;
    let mut rng = crate::util::rng(noise_seed);
    let zp: Vec<f32> = z.iter().map(|&v| v + w.sigma * normal(&mut rng) as f32).collect();
    let zp_t = backend.from_vec(zp);
    let mut mat = vec![0.0f32; b * MAT];
    let mut matp = vec![0.0f32; b * MAT];
    let mut dec_fwd = Vec::new();
    for ((m, o), p) in model.decoders.iter().zip(&model.dec_params) {
        let pt = backend.upload(p);
        let f0 = backend.mlp_forward(m, &pt, &zf.output, true)?;
        let f1 = backend.mlp_forward(m, &pt, &zp_t, true)?;
        let (o0, o1) = backend.to_vec2(&f0.output, &f1.output)?;
        let od = m.out_dim();
        for i in 0..b {
            mat[MAT * i + o..MAT * i + o + od].copy_from_slice(&o0[od * i..od * (i + 1)]);
            matp[MAT * i + o..MAT * i + o + od].copy_from_slice(&o1[od * i..od * (i + 1)]);
        }
        dec_fwd.push((pt, f0, f1));
    }
    for i in 0..b {
        mat[MAT * i + 3] = roughness_from_decoder(mat[MAT * i + 3]);
        matp[MAT * i + 3] = roughness_from_decoder(matp[MAT * i + 3]);
    }
    // The balance's factor on the albedo, capped at 1 (where capped, no gradient reaches the decoder).
    let a_s = model.albedo_scale as f32;
    let (mut capped, mut capped_p) = (vec![false; b * MAT], vec![false; b * MAT]);
    for i in 0..b {
        for c in 0..3 {
            let j = MAT * i + c;
            capped[j] = a_s * mat[j] > 1.0;
            capped_p[j] = a_s * matp[j] > 1.0;
            mat[j] = (a_s * mat[j]).min(1.0);
            matp[j] = (a_s * matp[j]).min(1.0);
        }
    }
    let constant = model.constant_roughness(backend, true)?;
    if let Some((r, _)) = &constant {
        for i in 0..b {
            mat[MAT * i + 3] = *r;
            matp[MAT * i + 3] = *r;
        }
    }

    // Indirect slots: every (point, blocked lobe) of the batch.
    let lobes = model.lobes();
    let mode = model.cfg.indirect;
    let brdf = model.cfg.brdf;
    let mut slot_of: Vec<Vec<(usize, usize)>> = vec![Vec::new(); b];
    let (mut hx, mut hn) = (Vec::new(), Vec::new());
    if mode != IndirectMode::None {
        for (i, hs) in batch.hits.iter().enumerate() {
            for &(kk, x2, n2) in hs {
                slot_of[i].push((kk, hx.len()));
                hx.push(x2);
                hn.push(n2);
            }
        }
    }
    let slots = hx.len();
    let slot_lobes: Vec<(usize, [f32; 3])> = slot_of.iter().flatten().map(|&(kk, sl)| (kk, hn[sl])).collect();
    let vis = slot_visibility(model, &lobes, &batch.traced_axes, &slot_lobes, &batch.boundary_offset);
    let vis_v: Vec<f64> = vis.iter().map(|v| v.0).collect();
    let ind_p = backend.upload(&model.ind_params);
    let rk = model.cfg.reflectance_outputs();
    let (ind_fwd, mix, sums) = if mode == IndirectMode::Ours && slots > 0 {
        let f = backend.mlp_forward(&model.indirect, &ind_p, &backend.from_vec(model.indirect_input(&hx, &hn)), true)?;
        let (mix, sums) = IndirectMix::from_sigmoid(&backend.to_vec(&f.output)?, k, rk);
        (Some(f), mix.scaled(model.albedo_scale), sums)
    } else {
        (None, IndirectMix::uniform(k).scaled(model.albedo_scale), Vec::new())
    };
    // The `mii` baseline's SGs at every point.
    let (mii_raw, mii_fwd) = match mode {
        IndirectMode::Mii => {
            let (raw, f) = model.mii_forward(backend, &ind_p, &batch.x, true)?;
            (raw, Some(f))
        }
        _ => (Vec::new(), None),
    };
    let mstride = model.cfg.mii_lobes * LIGHT_STRIDE;
    let mii_sgs: Vec<Vec<Sg<f64>>> = if mii_fwd.is_some() { mii_raw.chunks_exact(mstride).map(|r| light_lobes(r, false)).collect() } else { vec![Vec::new(); b] };
    let fit_targets: usize = batch.mii_targets.iter().map(Vec::len).sum();
    let fit_scale = model.cfg.mii_weight as f64 / (3.0 * fit_targets.max(1) as f64);

    // Shading, loss and its gradient per point.
    struct PointOut {
        rgb: [f64; 3],
        loss: f64,
        se: f64,
        da: [f64; 3],
        dr: f64,
        dm: f64,
        dl: Vec<[f64; 7]>,
        fit: f64,
        d_fit: Vec<[f64; 7]>,
        dn: [f64; 3],
    }
    let inv3b = 1.0 / (3.0 * b as f64);
    let per: Vec<PointOut> = (0..b)
        .into_par_iter()
        .map(|i| {
            let li = point_lobes(mode, &lobes, &slot_of[i], &mix, &mii_sgs[i], &vis_v);
            let a = [mat[MAT * i] as f64, mat[MAT * i + 1] as f64, mat[MAT * i + 2] as f64];
            let (r, m) = (mat[MAT * i + 3] as f64, mat[MAT * i + 4] as f64);
            let (n, v) = (f64x3(batch.n[i]), f64x3(batch.v[i]));
            let shading = PointShading::new(brdf, a, r, m, n, v, &li);
            let (spec, diff) = (shading.spec, shading.diff);
            let mut rgb = [0.0; 3];
            let mut d_out = [0.0; 3];
            let (mut loss, mut se) = (0.0, 0.0);
            for c in 0..3 {
                rgb[c] = spec[c].max(0.0) + diff[c].max(0.0);
                let (enc, de) = srgb_with_derivative(rgb[c]);
                let e = enc - batch.target[i][c] as f64;
                loss += e.abs() * inv3b;
                se += e * e;
                d_out[c] = e.signum() * inv3b * de;
            }
            let (da, dr, dm, dl) = shading.grad(a, m, &li, d_out);
            let dn = if geometry { shade_normal_grad(brdf, a, r, m, n, v, &li, spec, diff, d_out) } else { [0.0; 3] };
            let (fit, d_fit) = match (mii_fwd.is_some(), batch.mii_targets.get(i)) {
                (true, Some(t)) => mii_fit(&mii_sgs[i], t, fit_scale),
                _ => (0.0, Vec::new()),
            };
            PointOut { rgb, loss, se, da, dr, dm, dl, fit, d_fit, dn }
        })
        .collect();

    // Light and mixture gradients.
    let mut d_light = vec![0.0f64; k * LIGHT_STRIDE];
    let mut d_sig = vec![0.0f32; slots * (k + rk)];
    let mut loss_rgb = 0.0;
    let mut se = 0.0;
    let mut d_mat = vec![0.0f32; b * MAT];
    let mut d_mii = vec![0.0f32; mii_raw.len()];
    let mut d_mii_rgb = vec![0.0f32; if geometry { mii_raw.len() } else { 0 }];
    let mut fit = 0.0;
    let mut d_offset = if geometry { vec![0.0f64; slots] } else { Vec::new() };
    // dL/dg of the light–albedo balance, `Σ dL/dμ·μ − Σ dL/da·a − Σ dL/dρ·ρ` (the light's part
    // is added once `d_light` is complete).
    let mut d_balance = 0.0f64;
    for (i, p) in per.iter().enumerate() {
        loss_rgb += p.loss;
        fit += p.fit;
        // The `mii` SGs follow the environment's K lobes; the render and the fit both reach them.
        for (j, l) in mii_sgs[i].iter().enumerate() {
            let raw = &mii_raw[i * mstride + j * LIGHT_STRIDE..i * mstride + (j + 1) * LIGHT_STRIDE];
            let mut g = p.dl[k + j];
            if let Some(f) = p.d_fit.get(j) {
                g.iter_mut().zip(f).for_each(|(a, b)| *a += b);
            }
            let st = stored_lobe_grad(raw, l.lambda, &g, false);
            for (q, v) in st.iter().enumerate() {
                d_mii[i * mstride + j * LIGHT_STRIDE + q] = *v as f32;
            }
            if geometry {
                for (q, v) in stored_lobe_grad(raw, l.lambda, &p.dl[k + j], false).iter().enumerate() {
                    d_mii_rgb[i * mstride + j * LIGHT_STRIDE + q] = *v as f32;
                }
            }
        }
        se += p.se;
        for c in 0..3 {
            d_mat[MAT * i + c] = p.da[c] as f32;
            if !capped[MAT * i + c] {
                d_balance -= p.da[c] * mat[MAT * i + c] as f64;
            }
        }
        d_mat[MAT * i + 3] = p.dr as f32;
        // (No decoder reads channel 4 of a dielectric model.)
        d_mat[MAT * i + 4] = p.dm as f32;
        let mut replaced = vec![usize::MAX; k];
        for &(kk, s) in &slot_of[i] {
            replaced[kk] = s;
        }
        // Boundary lights: the environment copies follow the `mii` SGs in the point's lobes; the
        // replacement keeps `1 − v` of its amplitude.
        let mut keep = vec![1.0f64; k];
        let mut copy = k + mii_sgs[i].len();
        for &(kk, s) in &slot_of[i] {
            let (v, dv, dvo) = vis[s];
            if v <= 0.0 {
                continue;
            }
            let (g, gm) = (&p.dl[copy], &p.dl[kk]);
            copy += 1;
            let l = &lobes[kk];
            for a in 0..3 {
                d_light[kk * LIGHT_STRIDE + a] += g[a];
            }
            d_light[kk * LIGHT_STRIDE + 3] += g[3];
            let mix_mu = if mode == IndirectMode::Mii { [0.0; 3] } else { mix.lobe(&lobes, kk, s).mu };
            let mut d_v = 0.0;
            for c in 0..3 {
                d_light[kk * LIGHT_STRIDE + 4 + c] += v * g[4 + c];
                d_v += g[4 + c] * l.mu[c] - gm[4 + c] * mix_mu[c];
            }
            for a in 0..3 {
                d_light[kk * LIGHT_STRIDE + a] += d_v * dv[a];
            }
            if let Some(d) = d_offset.get_mut(s) {
                *d = d_v * dvo;
            }
            keep[kk] = 1.0 - v;
        }
        for (kk, g) in p.dl.iter().take(k).enumerate() {
            let s = replaced[kk];
            if s != usize::MAX && mode == IndirectMode::Mii {
                continue; // dropped: no light from this lobe reaches the point
            }
            // The axis is lobe k's own parameter in both cases.
            for a in 0..3 {
                d_light[kk * LIGHT_STRIDE + a] += g[a];
            }
            if s == usize::MAX {
                d_light[kk * LIGHT_STRIDE + 3] += g[3];
                for c in 0..3 {
                    d_light[kk * LIGHT_STRIDE + 4 + c] += g[4 + c];
                }
            } else {
                // μ = keep·ρ·Σ w_j μ_j.
                let (wrow, rho) = (mix.row(s), mix.rho(s));
                let kp = keep[kk];
                let gm: [f64; 3] = [0, 1, 2].map(|c| kp * rho[c] * g[4 + c]);
                let mut dw = vec![0.0f64; k];
                let mut sum_mu = [0.0f64; 3];
                for (j, l) in lobes.iter().enumerate() {
                    let wj = wrow[j] as f64;
                    d_light[j * LIGHT_STRIDE + 3] += wj * g[3];
                    for c in 0..3 {
                        d_light[j * LIGHT_STRIDE + 4 + c] += wj * gm[c];
                        sum_mu[c] += wj * l.mu[c];
                    }
                    dw[j] = g[3] * l.lambda + gm[0] * l.mu[0] + gm[1] * l.mu[1] + gm[2] * l.mu[2];
                }
                // ρ = scale·ρ_F: dL/dρ_F = scale·dL/dρ.
                for c in 0..3 {
                    d_balance -= kp * g[4 + c] * sum_mu[c] * rho[c];
                }
                if mode == IndirectMode::Ours {
                    let row = s * (k + rk);
                    let wdw: f64 = (0..k).map(|j| wrow[j] as f64 * dw[j]).sum();
                    for j in 0..k {
                        d_sig[row + j] = ((dw[j] - wdw) / sums[s]) as f32;
                    }
                    for c in 0..rk {
                        d_sig[row + k + c] = (model.albedo_scale * kp * g[4 + c] * sum_mu[c]) as f32;
                    }
                }
            }
        }
    }
    // The colour term alone, before the smoothness adds to the material's gradient.
    let d_mat_rgb = if geometry { d_mat.clone() } else { Vec::new() };
    for (j, l) in lobes.iter().enumerate() {
        d_balance += (0..3).map(|c| d_light[j * LIGHT_STRIDE + 4 + c] * l.mu[c]).sum::<f64>();
    }
    // Effective → stored parameters: λ = exp(raw) (floored), μ = |raw|.
    let mut d_light_f = vec![0.0f32; k * LIGHT_STRIDE];
    for (j, l) in lobes.iter().enumerate() {
        let r = j * LIGHT_STRIDE..(j + 1) * LIGHT_STRIDE;
        let g: [f64; 7] = d_light[r.clone()].try_into().unwrap_or([0.0; 7]);
        for (q, v) in stored_lobe_grad(&model.light[r], l.lambda, &g, model.cfg.log_amplitude).iter().enumerate() {
            d_light_f[j * LIGHT_STRIDE + q] = *v as f32;
        }
    }
    let d_ind = match (&ind_fwd, &mii_fwd) {
        (Some(f), _) => backend.to_vec(&backend.mlp_backward(&model.indirect, &ind_p, f, &backend.from_vec(d_sig))?.d_params)?,
        (None, Some(f)) => backend.to_vec(&backend.mlp_backward(&model.indirect, &ind_p, f, &backend.from_vec(d_mii))?.d_params)?,
        _ => vec![0.0; model.ind_params.len()],
    };

    // Latent smoothness (L1 between the material of z and of z + ε), mean over channels.
    let mut d_matp = vec![0.0f32; b * MAT];
    let mut smooth = 0.0f64;
    for i in 0..b {
        for c in 0..model.cfg.material_channels() {
            let nrm = if c < 3 { 3.0 * b as f64 } else { b as f64 };
            let e = (matp[MAT * i + c] - mat[MAT * i + c]) as f64;
            smooth += w.smooth as f64 * e.abs() / nrm;
            if c < 3 {
                // e = a_p − a: each side moves by −itself along g unless capped.
                let j = MAT * i + c;
                let de = -(if capped_p[j] { 0.0 } else { matp[j] as f64 }) + if capped[j] { 0.0 } else { mat[j] as f64 };
                d_balance += w.smooth as f64 * e.signum() * de / nrm;
            }
            let g = (w.smooth as f64 * e.signum() / nrm) as f32;
            d_matp[MAT * i + c] = g;
            d_mat[MAT * i + c] -= g;
        }
    }
    // A constant roughness takes every point's roughness gradient; the per-point paths get none.
    let d_const: f32 = if constant.is_some() {
        let mut sum = 0.0f64;
        for i in 0..b {
            sum += d_mat[MAT * i + 3] as f64 + d_matp[MAT * i + 3] as f64;
            d_mat[MAT * i + 3] = 0.0;
            d_matp[MAT * i + 3] = 0.0;
        }
        sum as f32 * ROUGHNESS_SPAN
    } else {
        0.0
    };
    // Through the roughness remap and the balance's factor on the albedo to the decoders' outputs.
    for i in 0..b {
        d_mat[MAT * i + 3] *= ROUGHNESS_SPAN;
        d_matp[MAT * i + 3] *= ROUGHNESS_SPAN;
        for c in 0..3 {
            let j = MAT * i + c;
            d_mat[j] *= if capped[j] { 0.0 } else { a_s };
            d_matp[j] *= if capped_p[j] { 0.0 } else { a_s };
        }
    }
    // Decoders backward on both paths; latent gradients sum.
    let mut dz = vec![0.0f32; b * ld];
    let mut d_dec = Vec::with_capacity(model.decoders.len());
    for ((m, o), (pt, f0, f1)) in model.decoders.iter().zip(&dec_fwd) {
        let od = m.out_dim();
        let pick = |src: &[f32]| -> Vec<f32> { (0..b).flat_map(|i| src[MAT * i + o..MAT * i + o + od].to_vec()).collect() };
        let g0 = backend.mlp_backward(m, pt, f0, &backend.from_vec(pick(&d_mat)))?;
        let g1 = backend.mlp_backward(m, pt, f1, &backend.from_vec(pick(&d_matp)))?;
        // Both paths' parameter and latent gradients with one wait.
        let mut read = backend.to_vecs(&[&g0.d_params, &g1.d_params, &g0.d_input, &g1.d_input])?.into_iter();
        let mut next = || read.next().unwrap_or_default();
        let (p0, p1, x0, x1) = (next(), next(), next(), next());
        d_dec.push(p0.iter().zip(&p1).map(|(a, c)| a + c).collect::<Vec<f32>>());
        if let (Some((_, fc)), true) = (&constant, (*o..*o + od).contains(&3)) {
            let mut d = vec![0.0f32; od];
            d[3 - o] = d_const;
            let gc = backend.to_vec(&backend.mlp_backward(m, pt, fc, &backend.from_vec(d))?.d_params)?;
            d_dec.last_mut().into_iter().for_each(|dd| dd.iter_mut().zip(&gc).for_each(|(a, c)| *a += c));
        }
        for i in 0..b * ld {
            dz[i] += x0[i] + x1[i];
        }
    }
    // KL sparsity of mean σ(z) toward ρ.
    let rho = w.rho as f64;
    let mut kl = 0.0;
    for j in 0..ld {
        let mean: f64 = (0..b).map(|i| 1.0 / (1.0 + (-(z[i * ld + j] as f64)).exp())).sum::<f64>() / b as f64;
        let rh = mean.clamp(1e-6, 1.0 - 1e-6);
        kl += (rho * (rho / rh).ln() + (1.0 - rho) * ((1.0 - rho) / (1.0 - rh)).ln()) / ld as f64;
        let dmean = w.kl as f64 * (-rho / rh + (1.0 - rho) / (1.0 - rh)) / ld as f64;
        for i in 0..b {
            let s = 1.0 / (1.0 + (-(z[i * ld + j] as f64)).exp());
            dz[i * ld + j] += (dmean * s * (1.0 - s) / b as f64) as f32;
        }
    }
    let ge = backend.mlp_backward(&model.encoder, &enc_p, &zf, &backend.from_vec(dz))?;
    let (ge_input, ge_params) = backend.to_vec2(&ge.d_input, &ge.d_params)?;
    let mut d_enc = if model.mat_enc.num_params() > 0 {
        model.mat_enc.backward_params(model.enc_split().0, bytemuck::cast_slice(&batch.x), &ge_input)
    } else {
        Vec::new()
    };
    d_enc.extend(ge_params);
    // The colour term's gradient with respect to the points: back through the decoders on the
    // unperturbed latent, the encoder and the position encoding, and for `mii` through its SGs.
    let mut d_point = Vec::new();
    if geometry {
        let mut dz = vec![0.0f32; b * ld];
        for ((m, o), (pt, f0, _)) in model.decoders.iter().zip(&dec_fwd) {
            let od = m.out_dim();
            let rows: Vec<f32> = (0..b)
                .flat_map(|i| (*o..*o + od).map(move |c| (i, c)))
                .map(|(i, c)| match (c, &constant) {
                    (3, Some(_)) => 0.0,
                    (3, None) => d_mat_rgb[MAT * i + 3] * ROUGHNESS_SPAN,
                    (0..3, _) if capped[MAT * i + c] => 0.0,
                    (0..3, _) => d_mat_rgb[MAT * i + c] * a_s,
                    _ => d_mat_rgb[MAT * i + c],
                })
                .collect();
            let g = backend.to_vec(&backend.mlp_backward(m, pt, f0, &backend.from_vec(rows))?.d_input)?;
            dz.iter_mut().zip(&g).for_each(|(a, c)| *a += c);
        }
        let ge = backend.mlp_backward(&model.encoder, &enc_p, &zf, &backend.from_vec(dz))?;
        let xs: &[f32] = bytemuck::cast_slice(&batch.x);
        let mut dx = model.mat_enc.backward_x(model.enc_split().0, xs, &backend.to_vec(&ge.d_input)?);
        if let Some(f) = &mii_fwd {
            let g = backend.to_vec(&backend.mlp_backward(&model.indirect, &ind_p, f, &backend.from_vec(d_mii_rgb))?.d_input)?;
            let dm = encoding_backward_cpu(&model.cfg.pos_encoding(), &[], xs, 3, &g, true).1.unwrap_or_default();
            dx.iter_mut().zip(&dm).for_each(|(a, c)| *a += c);
        }
        d_point = dx.chunks_exact(3).map(|d| [d[0] as f64, d[1] as f64, d[2] as f64]).collect();
    }

    if !model.cfg.learns_balance() {
        d_balance = 0.0;
    }
    let loss = loss_rgb + smooth + w.kl as f64 * kl + fit;
    let stats = Stage2Stats {
        loss,
        rgb: loss_rgb,
        smooth,
        kl,
        indirect_fit: fit,
        psnr: crate::eval::psnr_from_mse(se / (3.0 * b as f64)),
        blocked: slots,
        boundary: vis_v.iter().filter(|&&v| v > 0.0).count(),
        ..Default::default()
    };
    let rgb = per.iter().map(|p| p.rgb.map(|v| v as f32)).collect();
    let d_normal = if geometry { per.iter().map(|p| p.dn).collect() } else { Vec::new() };
    Ok(Stage2Grads { stats, d_enc, d_dec, d_light: d_light_f, d_ind, d_sdf: Vec::new(), rgb, d_normal, d_point, d_offset, d_balance })
}

// ---- the surface cache ---------------------------------------------------------------------

/// Primary surface points of training pixels and their secondary hits toward every lobe,
/// traced once on the frozen stage-1 geometry (see the module docs).
#[derive(Clone, Debug, Default)]
pub struct SurfaceCache {
    pub x: Vec<[f32; 3]>,
    pub n: Vec<[f32; 3]>,
    pub v: Vec<[f32; 3]>,
    pub target: Vec<[f32; 3]>,
    /// The unit axis each lobe's secondary rays were traced along.
    pub traced_axes: Vec<[f32; 3]>,
    /// `[point][lobe]` → index into `lobe_hits[lobe]`, or `u32::MAX` (not blocked / below the horizon).
    pub hit_index: Vec<u32>,
    pub lobe_hits: Vec<Vec<([f32; 3], [f32; 3])>>,
    /// `mii` only: beside each hit of `lobe_hits`, the linear stage-1 colour it sends back along
    /// the ray (the `mii` baseline's supervision).
    pub lobe_radiance: Vec<Vec<[f32; 3]>>,
    /// Whether `lobe_radiance` was traced (the `mii` baseline).
    pub radiance_traced: bool,
    /// `--refine-geometry` only: beside each hit of `lobe_hits`, the SDF there when it was traced.
    pub lobe_hit_sdf: Vec<Vec<f32>>,
    /// Secondary rays traced per lobe (points with the lobe above their horizon).
    pub lobe_traced: Vec<usize>,
    /// Field evaluations spent tracing (primary, secondary, normals).
    pub evaluations: usize,
    /// Secondary rays traced, and the steps they took (field evaluations, or grid lookups when
    /// they march on `grid`).
    pub secondary_rays: usize,
    pub secondary_evaluations: usize,
    /// Lobes re-traced since the cache was built.
    pub retraced: usize,
    /// The frozen SDF sampled for the secondary rays (`Stage2Config::secondary_grid_nodes`,
    /// [`Stage1Model::sdf_grid`]: sampled once per SDF and shared), and the seconds this cache
    /// spent sampling it.
    pub grid: Option<std::sync::Arc<SdfGrid>>,
    pub grid_seconds: f64,
}

/// The grid stage 2's secondary rays march on ([`Stage2Config::secondary_grid_nodes`]; None with
/// `--refine-geometry`, whose SDF moves, or when the config asks for the network): the SDF's
/// shared sample ([`Stage1Model::sdf_grid`]) and the seconds sampling it took now (0 if reused).
pub fn secondary_grid(backend: &Backend, sdf: &Stage1Model, cfg: &Stage2Config) -> Result<Option<(std::sync::Arc<SdfGrid>, f64)>, BackendError> {
    if cfg.secondary_grid_nodes < 2 || cfg.refine_geometry {
        return Ok(None);
    }
    sdf.sdf_grid(backend, cfg.secondary_grid_nodes).map(Some)
}

/// What [`secondary_hits`] found.
pub struct SecondaryHits {
    /// `(ray, hit point)` for every blocked ray.
    pub hits: Vec<(usize, [f32; 3])>,
    /// Steps marched (grid lookups or field evaluations) and field evaluations spent.
    pub steps: usize,
    pub evaluations: usize,
}

/// Secondary rays from their origins (cached surface points) along their directions: which the
/// surface blocks and where ([`trace_secondary`] with the config's offset, steps and threshold).
/// With `grid` they march on it, and each hit goes onto the network's own surface (the grid's
/// trilinear surface is off by ~h²κ/8): a sphere-tracing step of the network, then a secant step
/// through the two values (whatever the field's slope along the ray).
pub fn secondary_hits(backend: &Backend, sdf: &Stage1Model, cfg: &Stage2Config, grid: Option<&SdfGrid>, rays: &Rays) -> Result<SecondaryHits, BackendError> {
    let f = |p: &[f32]| sdf.sdf(backend, p);
    let march: &dyn crate::render::SdfBatch = match grid {
        Some(g) => g,
        None => &f,
    };
    let (hit, mut t, steps) = trace_secondary(march, rays, cfg.secondary_offset, cfg.secondary_steps, cfg.secondary_threshold, 1.0)?;
    let hit_rays: Vec<usize> = (0..rays.len()).filter(|&j| hit[j]).collect();
    let mut evaluations = if grid.is_none() { steps } else { 0 };
    if grid.is_some() && !hit_rays.is_empty() {
        let net = |t: &[f32]| -> Result<Vec<f32>, BackendError> {
            let pts: Vec<[f32; 3]> = hit_rays.iter().map(|&j| rays.at(j, t[j])).collect();
            sdf.sdf(backend, bytemuck::cast_slice(&pts))
        };
        let f0 = net(&t)?;
        let t0 = t.clone();
        for (&j, &v) in hit_rays.iter().zip(&f0) {
            if v.is_finite() {
                t[j] += v;
            }
        }
        let f1 = net(&t)?;
        evaluations += 2 * hit_rays.len();
        for ((&j, &a), &c) in hit_rays.iter().zip(&f0).zip(&f1) {
            if a.is_finite() && c.is_finite() && (c - a).abs() > 1e-9 {
                let ts = t[j] - c * (t[j] - t0[j]) / (c - a);
                t[j] = ts.clamp(t0[j] - 2.0 * a.abs(), t0[j] + 2.0 * a.abs());
            }
        }
    }
    let hits = hit_rays.into_iter().map(|j| (j, rays.at(j, t[j]))).collect();
    Ok(SecondaryHits { hits, steps, evaluations })
}

/// Unit normals at points: central differences of the stage-1 field with step `step` (the
/// field's own gradient step times the config's `normal_step_factor`).
pub fn normals_at(backend: &Backend, sdf: &Stage1Model, x: &[[f32; 3]], step: f32) -> Result<Vec<[f32; 3]>, BackendError> {
    let mut out = Vec::with_capacity(x.len());
    for c in x.chunks(1 << 13) {
        let mut pts = Vec::with_capacity(c.len() * 18);
        for p in c {
            for a in 0..3 {
                for s in [1.0f32, -1.0] {
                    let mut q = *p;
                    q[a] += s * step;
                    pts.extend_from_slice(&q);
                }
            }
        }
        let v = sdf.sdf(backend, &pts)?;
        out.extend(v.chunks_exact(6).map(|d| normalize([(d[0] - d[1]) as f64, (d[2] - d[3]) as f64, (d[4] - d[5]) as f64]).map(|v| v as f32)));
    }
    Ok(out)
}

/// The normal step of a stage-2 configuration on a stage-1 model.
pub fn normal_step(sdf: &Stage1Model, cfg: &Stage2Config) -> f32 {
    sdf.field.config.grad_step * cfg.normal_step_factor
}

impl SurfaceCache {
    /// Trace `n` foreground training pixels (drawn with `seed`) onto the stage-1 surface.
    pub fn build(backend: &Backend, sdf: &Stage1Model, tc: &TraceConfig, data: &TrainData, n: usize, seed: u64, normal_step: f32) -> Result<Self, BackendError> {
        let mut rng = crate::util::rng(seed ^ 0xCAC4E);
        let batch = data.sample(&mut rng, n, 1.0);
        let mut c = SurfaceCache::default();
        let f = sdf.sdf_batch(backend)?;
        for start in (0..batch.rays.len()).step_by(8192) {
            let end = (start + 8192).min(batch.rays.len());
            let r = Rays { origins: batch.rays.origins[start..end].to_vec(), dirs: batch.rays.dirs[start..end].to_vec() };
            let tr = trace(&f, &r, tc)?;
            c.evaluations += tr.evaluations;
            for i in 0..r.len() {
                if tr.hit[i] && batch.mask[start + i] >= 0.5 {
                    c.x.push(tr.points[i]);
                    let d = r.dirs[i];
                    c.v.push([-d[0], -d[1], -d[2]]);
                    c.target.push(batch.rgb[start + i]);
                }
            }
        }
        c.n = normals_at(backend, sdf, &c.x, normal_step)?;
        c.evaluations += 6 * c.x.len();
        // Normals facing away from the camera (noise at silhouettes) are flipped toward it.
        for i in 0..c.x.len() {
            if dot3(f64x3(c.n[i]), f64x3(c.v[i])) < 0.0 {
                c.n[i] = c.n[i].map(|v| -v);
            }
        }
        Ok(c)
    }

    pub fn len(&self) -> usize {
        self.x.len()
    }
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Trace (or re-trace) lobe `k` along `axis` for every cached point.
    pub fn trace_lobe(&mut self, backend: &Backend, sdf: &Stage1Model, cfg: &Stage2Config, k: usize, axis: [f32; 3]) -> Result<(), BackendError> {
        let kk = cfg.lobes;
        if self.traced_axes.len() != kk || self.hit_index.len() != self.len() * kk {
            self.hit_index = vec![u32::MAX; self.len() * kk];
            self.lobe_hits = vec![Vec::new(); kk];
            self.lobe_radiance = vec![Vec::new(); kk];
            self.lobe_hit_sdf = vec![Vec::new(); kk];
            self.lobe_traced = vec![0; kk];
            self.traced_axes = vec![[0.0; 3]; kk];
        }
        let ax = f64x3(axis);
        let idx: Vec<usize> = (0..self.len()).filter(|&i| dot3(f64x3(self.n[i]), ax) > 0.0).collect();
        let rays = Rays { origins: idx.iter().map(|&i| self.x[i]).collect(), dirs: vec![axis; idx.len()] };
        let grid = secondary_grid(backend, sdf, cfg)?;
        if let Some((g, seconds)) = &grid {
            if *seconds > 0.0 {
                self.evaluations += g.evaluations();
                self.grid_seconds += seconds;
            }
            self.grid = Some(g.clone());
        }
        let mut hits = Vec::new();
        let mut hit_pts = Vec::new();
        for start in (0..rays.len()).step_by(1 << 15) {
            let end = (start + (1 << 15)).min(rays.len());
            let r = Rays { origins: rays.origins[start..end].to_vec(), dirs: rays.dirs[start..end].to_vec() };
            let sh = secondary_hits(backend, sdf, cfg, grid.as_ref().map(|g| g.0.as_ref()), &r)?;
            self.secondary_rays += r.len();
            self.secondary_evaluations += sh.steps;
            self.evaluations += sh.evaluations;
            for (j, x) in sh.hits {
                hits.push(idx[start + j]);
                hit_pts.push(x);
            }
        }
        let hn = normals_at(backend, sdf, &hit_pts, normal_step(sdf, cfg))?;
        self.evaluations += 6 * hit_pts.len();
        self.radiance_traced = cfg.indirect == IndirectMode::Mii;
        self.lobe_radiance[k] = if self.radiance_traced {
            // Seen from x looking along the axis: the stage-1 radiance net's view direction.
            let rgb = sdf.colour(backend, &hit_pts, &vec![axis; hit_pts.len()])?;
            self.evaluations += 7 * hit_pts.len();
            rgb.iter().map(|c| c.map(crate::image_io::srgb_to_linear)).collect()
        } else {
            Vec::new()
        };
        self.lobe_hit_sdf[k] = if cfg.refine_geometry && !hit_pts.is_empty() {
            self.evaluations += hit_pts.len();
            sdf.sdf(backend, bytemuck::cast_slice(&hit_pts))?
        } else {
            Vec::new()
        };
        for i in 0..self.len() {
            self.hit_index[i * kk + k] = u32::MAX;
        }
        for (h, &i) in hits.iter().enumerate() {
            self.hit_index[i * kk + k] = h as u32;
        }
        self.lobe_hits[k] = hit_pts.into_iter().zip(hn).collect();
        self.lobe_traced[k] = idx.len();
        self.traced_axes[k] = axis;
        Ok(())
    }

    /// Trace every lobe whose axis moved more than `cfg.retrace_degrees` since it was traced
    /// (all of them the first time). Returns how many were traced.
    pub fn refresh(&mut self, backend: &Backend, sdf: &Stage1Model, cfg: &Stage2Config, axes: &[[f32; 3]]) -> Result<usize, BackendError> {
        if cfg.indirect == IndirectMode::None {
            return Ok(0);
        }
        let first = self.traced_axes.len() != cfg.lobes || self.hit_index.len() != self.len() * cfg.lobes;
        let cos_tol = (cfg.retrace_degrees as f64).to_radians().cos();
        let mut n = 0;
        for (k, &a) in axes.iter().enumerate() {
            if first || dot3(f64x3(a), f64x3(self.traced_axes[k])) < cos_tol {
                self.trace_lobe(backend, sdf, cfg, k, a)?;
                n += 1;
            }
        }
        if !first {
            self.retraced += n;
        }
        Ok(n)
    }

    /// Field evaluations per secondary ray (each stops once it hits or leaves the bound).
    pub fn steps_per_secondary_ray(&self) -> f64 {
        self.secondary_evaluations as f64 / self.secondary_rays.max(1) as f64
    }

    /// Fraction of (point, lobe above the horizon) pairs that are blocked.
    pub fn blocked_fraction(&self) -> f64 {
        let blocked: usize = self.lobe_hits.iter().map(Vec::len).sum();
        blocked as f64 / self.lobe_traced.iter().sum::<usize>().max(1) as f64
    }

    /// Fraction of the blocked pairs that are boundary lights (`|n'·ξ0| < eps`, see
    /// [`boundary_visibility`]).
    pub fn boundary_fraction(&self, eps: f32) -> f64 {
        let grazing: usize = self
            .lobe_hits
            .iter()
            .zip(&self.traced_axes)
            .map(|(h, a)| h.iter().filter(|(_, n2)| dot3(f64x3(*n2), f64x3(*a)).abs() < eps as f64).count())
            .sum();
        grazing as f64 / self.lobe_hits.iter().map(Vec::len).sum::<usize>().max(1) as f64
    }

    /// The batch of cached points `idx`.
    pub fn batch(&self, idx: &[usize], lobes: usize) -> Stage2Batch {
        let mut b = Stage2Batch::default();
        let traced = self.hit_index.len() == self.len() * lobes;
        if traced {
            b.traced_axes = self.traced_axes.clone();
        }
        for &i in idx {
            b.x.push(self.x[i]);
            b.n.push(self.n[i]);
            b.v.push(self.v[i]);
            b.target.push(self.target[i]);
            let mut h = Vec::new();
            let mut hf = Vec::new();
            if traced {
                for k in 0..lobes {
                    let j = self.hit_index[i * lobes + k];
                    if j != u32::MAX {
                        let (x2, n2) = self.lobe_hits[k][j as usize];
                        h.push((k, x2, n2));
                        hf.push(self.lobe_hit_sdf[k].get(j as usize).copied().unwrap_or(0.0));
                    }
                }
            }
            b.hits.push(h);
            b.hit_sdf.push(hf);
            if traced && self.radiance_traced {
                let n = f64x3(self.n[i]);
                let t = (0..lobes)
                    .filter(|&k| dot3(n, f64x3(self.traced_axes[k])) > 0.0)
                    .map(|k| {
                        let j = self.hit_index[i * lobes + k];
                        let rad = if j == u32::MAX { [0.0; 3] } else { self.lobe_radiance[k][j as usize] };
                        (self.traced_axes[k], rad)
                    })
                    .collect();
                b.mii_targets.push(t);
            }
        }
        b
    }
}

// ---- the trainer ---------------------------------------------------------------------------

/// Stage-2 checkpoint file names inside a run folder (beside stage 1's).
pub const CHECKPOINT2: &str = "material.safetensors";
pub const RUN_CONFIG2: &str = "material.json";

/// The stage-2 model, its Adam state and step.
#[derive(Debug)]
pub struct Stage2Trainer {
    pub model: Stage2Model,
    adam_enc: AdamState,
    adam_dec: Vec<AdamState>,
    adam_light: AdamState,
    /// A known light's exposure (`light_fixed`): one log-scale of every lobe's amplitude.
    adam_exposure: AdamState,
    /// The light–albedo balance's log-scale ([`Stage2Config::balance_lr_factor`]).
    adam_balance: AdamState,
    adam_ind: AdamState,
    /// The refined SDF's Adam state (`--refine-geometry`; created with the first step).
    adam_sdf: Option<AdamState>,
    /// The refined SDF read from a checkpoint (`--refine-geometry`), to load into the stage-1
    /// model ([`Stage2Trainer::geometry_into`]).
    pub refined_sdf: Option<Vec<f32>>,
    pub step: u64,
    pub skipped: u64,
    /// A known light's learnt exposure (`light_fixed`): the factor on the map's fitted amplitudes.
    pub exposure: f64,
    host: Backend,
}

impl Stage2Trainer {
    pub fn new(cfg: &Stage2Config) -> Result<Self, BackendError> {
        let model = Stage2Model::new(cfg)?;
        let host = Backend::cpu();
        Ok(Self {
            adam_enc: AdamState::new(&host, model.enc_params.len()),
            adam_dec: model.dec_params.iter().map(|p| AdamState::new(&host, p.len())).collect(),
            adam_light: AdamState::new(&host, model.light.len()),
            adam_exposure: AdamState::new(&host, 1),
            adam_balance: AdamState::new(&host, 1),
            adam_ind: AdamState::new(&host, model.ind_params.len()),
            adam_sdf: None,
            refined_sdf: None,
            model,
            step: 0,
            skipped: 0,
            exposure: 1.0,
            host,
        })
    }

    pub fn cfg(&self) -> &Stage2Config {
        &self.model.cfg
    }

    pub fn weights(&self) -> Stage2Weights {
        let c = self.cfg();
        Stage2Weights { smooth: c.smooth_weight, sigma: c.smooth_sigma, kl: c.kl_weight, rho: c.kl_rho }
    }

    pub fn step_rng(&self, step: u64) -> rand::rngs::StdRng {
        crate::util::rng(self.cfg().seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(step).wrapping_add(0x2222))
    }

    /// Apply gradients; a step with any non-finite value is skipped and counted.
    pub fn apply(&mut self, g: Stage2Grads) -> Result<(bool, f64), BackendError> {
        self.apply_with(g, None)
    }

    /// [`Stage2Trainer::apply`], the SDF's gradient (if any) to `geometry`'s parameters.
    pub fn apply_with(&mut self, mut g: Stage2Grads, geometry: Option<&mut Stage1Model>) -> Result<(bool, f64), BackendError> {
        let all: Vec<&[f32]> = [&g.d_enc[..]].into_iter().chain(g.d_dec.iter().map(|d| &d[..])).chain([&g.d_light[..], &g.d_ind[..], &g.d_sdf[..]]).collect();
        let norm = match host_grad_norm(&all) {
            Some(n) if g.stats.loss.is_finite() && g.d_balance.is_finite() => n,
            _ => {
                self.skipped += 1;
                return Ok((false, f64::NAN));
            }
        };
        let f = self.cfg().lr_factor(self.step);
        let (lm, ll, li) = (self.cfg().lr_material * f, self.cfg().lr_light * f, self.cfg().lr_indirect * f);
        let cfg = AdamConfig { eps: 1e-15, ..AdamConfig::with_lr(lm) };
        let h = self.host.clone();
        // Sparse only where a step reaches few entries: the material hash grid (the small
        // tensors, light lobes among them, keep their momentum through a step without gradient).
        let enc_cfg = AdamConfig { skip_zero_gradients: self.cfg().sparse_adam, ..cfg.clone() };
        adam_host(&enc_cfg, &mut self.model.enc_params, std::mem::take(&mut g.d_enc), &mut self.adam_enc, lm)?;
        for ((p, d), s) in self.model.dec_params.iter_mut().zip(std::mem::take(&mut g.d_dec)).zip(&mut self.adam_dec) {
            adam_host(&cfg, p, d, s, lm)?;
        }
        // Per-entry learning rate for the axes: Adam's moments do not depend on the rate, so
        // scaling the axes' update is a step at `ll · axis_lr_factor`.
        if self.cfg().light_fixed {
            // A known map is rarely at the photos' exposure: its shape stays, one log-scale of
            // all amplitudes is learnt (dL/d ln s = Σ dL/dμ · μ: Σ dL/d(ln μ) where the amplitudes
            // are stored as logs, else Σ dL/dμ_raw · μ_raw).
            let d_light = std::mem::take(&mut g.d_light);
            let log = self.cfg().log_amplitude;
            let d_log_scale: f32 = self.model.light.chunks_exact(LIGHT_STRIDE).zip(d_light.chunks_exact(LIGHT_STRIDE)).map(|(p, d)| (4..7).map(|c| if log { d[c] } else { p[c] * d[c] }).sum::<f32>()).sum();
            let s = scale_amplitudes_step(&cfg, &mut self.model.light, log, d_log_scale, &mut self.adam_exposure, ll)?;
            self.exposure *= s as f64;
        } else {
            let before = self.model.light.clone();
            adam_host(&cfg, &mut self.model.light, std::mem::take(&mut g.d_light), &mut self.adam_light, ll)?;
            let (fa, unit) = (self.cfg().axis_lr_factor, self.cfg().unit_axes);
            for (p, b) in self.model.light.chunks_exact_mut(LIGHT_STRIDE).zip(before.chunks_exact(LIGHT_STRIDE)) {
                for a in 0..3 {
                    p[a] = b[a] + (p[a] - b[a]) * fa;
                }
                let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                if unit && n > 1e-6 {
                    p[..3].iter_mut().for_each(|v| *v /= n);
                }
            }
        }
        if self.cfg().learns_balance() {
            // The balance moves the light by e^Δg and the albedo (and ρ) by e^−Δg: folded into
            // the amplitudes and the model's albedo scale, its Adam state kept.
            let (lb, log) = (ll * self.cfg().balance_lr_factor, self.cfg().log_amplitude);
            let s = scale_amplitudes_step(&cfg, &mut self.model.light, log, g.d_balance as f32, &mut self.adam_balance, lb)?;
            self.model.albedo_scale /= s as f64;
        }
        if matches!(self.cfg().indirect, IndirectMode::Ours | IndirectMode::Mii) {
            adam_host(&cfg, &mut self.model.ind_params, std::mem::take(&mut g.d_ind), &mut self.adam_ind, li)?;
        }
        if let (Some(m), false) = (geometry, g.d_sdf.is_empty()) {
            let lg = self.cfg().lr_geometry * f;
            let state = self.adam_sdf.get_or_insert_with(|| AdamState::new(&h, m.sdf_params.len()));
            adam_host(&cfg, &mut m.sdf_params, g.d_sdf, state, lg)?;
        }
        Ok((true, norm))
    }

    /// One iteration on `batch` points drawn from the cache (seeded by `(seed, step)`).
    pub fn train_step(&mut self, backend: &Backend, cache: &SurfaceCache) -> Result<Stage2Stats, BackendError> {
        self.train_step_with(backend, cache, None)
    }

    /// [`Stage2Trainer::train_step`]; with `geometry` (and `refine_geometry` set) the SDF is
    /// refined too ([`loss_and_grad_geometry`]).
    pub fn train_step_with(&mut self, backend: &Backend, cache: &SurfaceCache, geometry: Option<&mut Stage1Model>) -> Result<Stage2Stats, BackendError> {
        if cache.is_empty() {
            return Err(BackendError::Config("stage 2: no cached surface points (the stage-1 surface is hit by no masked pixel)".into()));
        }
        let mut rng = self.step_rng(self.step);
        let idx: Vec<usize> = (0..self.cfg().batch).map(|_| rng.random_range(0..cache.len())).collect();
        let batch = cache.batch(&idx, self.cfg().lobes);
        let noise_seed = rng.random::<u64>();
        let refine = self.cfg().refine_geometry;
        // The BRDF of this step ([`Stage2Config::brdf_warmup`]): the model's own, PhySG's during a
        // calibrated run's warm-up.
        let run_brdf = self.model.cfg.brdf;
        self.model.cfg.brdf = self.cfg().brdf_at(self.step);
        let result = match geometry {
            Some(m) if refine => loss_and_grad_geometry(backend, &self.model, &batch, &self.weights(), noise_seed, m).map(|g| (g, Some(m))),
            _ => loss_and_grad(backend, &self.model, &batch, &self.weights(), noise_seed).map(|g| (g, None)),
        };
        self.model.cfg.brdf = run_brdf;
        let (g, geometry) = result?;
        let stats = g.stats.clone();
        let (applied, norm) = self.apply_with(g, geometry)?;
        self.step += 1;
        Ok(Stage2Stats { step: self.step, applied, grad_norm: norm, ..stats })
    }

    /// Load the refined SDF of this run (if any) into the stage-1 model it was refined from.
    pub fn geometry_into(&self, sdf: &mut Stage1Model) -> Result<(), BackendError> {
        if let Some(p) = &self.refined_sdf {
            if p.len() != sdf.sdf_params.len() {
                return Err(BackendError::Shape(format!("the refined SDF has {} values; the stage-1 model needs {}", p.len(), sdf.sdf_params.len())));
            }
            sdf.sdf_params.clone_from(p);
        }
        Ok(())
    }

    /// Save params + Adam state + config + step + the cache's traced axes into `dir`.
    pub fn save(&self, dir: &Path, scene_key: &str, traced_axes: &[[f32; 3]]) -> Result<(), DataError> {
        self.save_with(dir, scene_key, traced_axes, None)
    }

    /// [`Stage2Trainer::save`] with the refined SDF (`--refine-geometry`) and its Adam state.
    pub fn save_with(&self, dir: &Path, scene_key: &str, traced_axes: &[[f32; 3]], geometry: Option<&Stage1Model>) -> Result<(), DataError> {
        let mut st = ParamStore::new();
        let err = |e: BackendError| DataError::new(dir, e.to_string());
        let m = &self.model;
        st.insert("encoder", &[m.enc_params.len()], m.enc_params.clone()).map_err(err)?;
        for (i, p) in m.dec_params.iter().enumerate() {
            st.insert(&format!("decoder{i}"), &[p.len()], p.clone()).map_err(err)?;
            st.put_adam_state(&self.host, &format!("decoder{i}"), &self.adam_dec[i]).map_err(err)?;
        }
        st.insert("light", &[m.light.len()], m.light.clone()).map_err(err)?;
        st.insert("indirect", &[m.ind_params.len()], m.ind_params.clone()).map_err(err)?;
        let axes: Vec<f32> = traced_axes.iter().flatten().copied().collect();
        st.insert("traced_axes", &[axes.len()], axes).map_err(err)?;
        st.put_adam_state(&self.host, "encoder", &self.adam_enc).map_err(err)?;
        st.put_adam_state(&self.host, "light", &self.adam_light).map_err(err)?;
        st.put_adam_state(&self.host, "exposure", &self.adam_exposure).map_err(err)?;
        st.put_adam_state(&self.host, "balance", &self.adam_balance).map_err(err)?;
        st.put_adam_state(&self.host, "indirect", &self.adam_ind).map_err(err)?;
        if let Some(g) = geometry.filter(|_| m.cfg.refine_geometry) {
            st.insert("sdf", &[g.sdf_params.len()], g.sdf_params.clone()).map_err(err)?;
            if let Some(a) = &self.adam_sdf {
                st.put_adam_state(&self.host, "sdf", a).map_err(err)?;
            }
        }
        st.set_config(&m.cfg).map_err(|e| DataError::new(dir, e.to_string()))?;
        st.set_step(self.step);
        st.metadata.insert("scene".into(), scene_key.to_string());
        st.metadata.insert("skipped".into(), self.skipped.to_string());
        st.metadata.insert("exposure".into(), self.exposure.to_string());
        st.metadata.insert("albedo_scale".into(), self.model.albedo_scale.to_string());
        st.save(&dir.join(CHECKPOINT2))?;
        let cfg = serde_json::json!({ "stage": "material", "step": self.step, "scene": scene_key, "config": m.cfg });
        crate::util::atomic_write(&dir.join(RUN_CONFIG2), serde_json::to_string_pretty(&cfg).unwrap_or_default().as_bytes())
    }

    /// Load a stage-2 checkpoint. Returns the trainer, its scene key and the traced axes.
    pub fn load(dir: &Path, expect_scene: Option<&str>) -> Result<(Self, String, Vec<[f32; 3]>), DataError> {
        let path = dir.join(CHECKPOINT2);
        if !path.is_file() {
            return Err(DataError::new(&path, "no stage-2 checkpoint here (train one with `pii-bake train <scene> --out <run-dir> --stage material`)"));
        }
        let st = ParamStore::load(&path)?;
        let cfg: Stage2Config = st
            .config_json()
            .ok_or_else(|| DataError::new(&path, "checkpoint has no stage-2 configuration"))
            .and_then(|j| serde_json::from_str(j).map_err(|e| DataError::new(&path, format!("stage-2 configuration: {e}"))))?;
        let scene = st.metadata.get("scene").cloned().unwrap_or_default();
        if let Some(k) = expect_scene {
            if k != scene {
                return Err(DataError::new(&path, format!("this stage-2 run was trained on another scene ({scene}), not {k}")));
            }
        }
        let mut t = Stage2Trainer::new(&cfg).map_err(|e| DataError::new(&path, e.to_string()))?;
        let get = |name: &str, len: usize| checked_tensor(&st, &path, name, len, "this configuration needs", "");
        t.model.enc_params = get("encoder", t.model.enc_params.len())?;
        for i in 0..t.model.dec_params.len() {
            t.model.dec_params[i] = get(&format!("decoder{i}"), t.model.dec_params[i].len())?;
        }
        t.model.light = get("light", t.model.light.len())?;
        t.model.ind_params = get("indirect", t.model.ind_params.len())?;
        let axes = get("traced_axes", 3 * cfg.lobes).or_else(|_| get("traced_axes", 0))?;
        let traced: Vec<[f32; 3]> = axes.chunks_exact(3).map(|a| [a[0], a[1], a[2]]).collect();
        let host = t.host.clone();
        let e = |e: BackendError| DataError::new(&path, e.to_string());
        if let Some(s) = st.adam_state(&host, "encoder").map_err(e)? {
            t.adam_enc = s;
        }
        for i in 0..t.adam_dec.len() {
            if let Some(s) = st.adam_state(&host, &format!("decoder{i}")).map_err(e)? {
                t.adam_dec[i] = s;
            }
        }
        if let Some(s) = st.adam_state(&host, "light").map_err(e)? {
            t.adam_light = s;
        }
        if let Some(s) = st.adam_state(&host, "exposure").map_err(e)? {
            t.adam_exposure = s;
        }
        if let Some(s) = st.adam_state(&host, "balance").map_err(e)? {
            t.adam_balance = s;
        }
        if let Some(s) = st.adam_state(&host, "indirect").map_err(e)? {
            t.adam_ind = s;
        }
        if cfg.refine_geometry {
            if let Some(d) = st.data("sdf") {
                if d.iter().any(|v| !v.is_finite()) {
                    return Err(DataError::new(&path, "tensor \"sdf\" holds NaN/Inf values"));
                }
                t.refined_sdf = Some(d.to_vec());
                t.adam_sdf = st.adam_state(&host, "sdf").map_err(e)?;
            }
        }
        t.step = st.step().unwrap_or(0);
        t.skipped = st.metadata.get("skipped").and_then(|s| s.parse().ok()).unwrap_or(0);
        t.exposure = st.metadata.get("exposure").and_then(|s| s.parse().ok()).filter(|e: &f64| e.is_finite() && *e > 0.0).unwrap_or(1.0);
        // Checkpoints written before the balance read 1.
        t.model.albedo_scale = match st.metadata.get("albedo_scale") {
            None => 1.0,
            Some(v) => v.parse().ok().filter(|a: &f64| a.is_finite() && *a > 0.0).ok_or_else(|| DataError::new(&path, format!("albedo_scale {v:?} is not a positive number")))?,
        };
        Ok((t, scene, traced))
    }
}

/// One Adam step (its own state) on a log-scale of every light amplitude whose gradient is `d`,
/// folded into the stored amplitudes (added to `ln μ` where `log`, else a factor on `μ`). Returns
/// the step's factor `e^Δ` (a known light's exposure and the light–albedo balance).
fn scale_amplitudes_step(cfg: &AdamConfig, light: &mut [f32], log: bool, d: f32, state: &mut AdamState, lr: f32) -> Result<f32, BackendError> {
    let mut log_scale = vec![0.0f32];
    adam_host(cfg, &mut log_scale, vec![d], state, lr)?;
    let (ln_s, s) = (log_scale[0], log_scale[0].exp());
    light.chunks_exact_mut(LIGHT_STRIDE).for_each(|p| p[4..7].iter_mut().for_each(|m| if log { *m += ln_s } else { *m *= s }));
    Ok(s)
}

/// Render cached-style points (forward): linear RGB per point, given per-point blocked lobes.
pub fn render_points(backend: &Backend, model: &Stage2Model, batch: &Stage2Batch) -> Result<Vec<[f32; 3]>, BackendError> {
    Ok(render_points_f64(backend, model, batch)?.into_iter().map(|c| c.map(|v| v as f32)).collect())
}

fn render_points_f64(backend: &Backend, model: &Stage2Model, batch: &Stage2Batch) -> Result<Vec<[f64; 3]>, BackendError> {
    let mat = model.material(backend, &batch.x)?;
    let lobes = model.lobes();
    let (mut hx, mut hn, mut owner) = (Vec::new(), Vec::new(), Vec::new());
    if model.cfg.indirect != IndirectMode::None {
        for (i, hs) in batch.hits.iter().enumerate() {
            for &(kk, x2, n2) in hs {
                hx.push(x2);
                hn.push(n2);
                owner.push((i, kk));
            }
        }
    }
    let slot_lobes: Vec<(usize, [f32; 3])> = owner.iter().zip(&hn).map(|(&(_, kk), &n2)| (kk, n2)).collect();
    let vis: Vec<f64> = slot_visibility(model, &lobes, &batch.traced_axes, &slot_lobes, &batch.boundary_offset).iter().map(|v| v.0).collect();
    let mix = model.indirect_mix(backend, &hx, &hn)?;
    let mii = model.mii_lobes_at(backend, &batch.x)?;
    let mut per: Vec<Vec<(usize, usize)>> = vec![Vec::new(); batch.len()];
    for (s, &(i, kk)) in owner.iter().enumerate() {
        per[i].push((kk, s));
    }
    Ok((0..batch.len())
        .into_par_iter()
        .map(|i| {
            let li = point_lobes(model.cfg.indirect, &lobes, &per[i], &mix, &mii[i], &vis);
            let (a, r, m) = mat.at(i);
            let (sp, df) = shade_f64(model.cfg.brdf, a, r, m, f64x3(batch.n[i]), f64x3(batch.v[i]), &li);
            [0, 1, 2].map(|c| sp[c].max(0.0) + df[c].max(0.0))
        })
        .collect())
}

// ---- joint geometry refinement (`--refine-geometry`) ----------------------------------------

/// Stage 2's loss and gradients with the stage-1 SDF `sdf` refined jointly (its gradient in
/// `d_sdf`). The cached surface points `x0` were traced at an earlier SDF; at the current one each
/// point is the Newton step along its camera ray `r`, `x = x0 + r·s`, `s = −f(x0)/(∇f(x0)·r)`
/// (stage 1's implicit surface point; no move where `∇f·r ≥ −0.05`), shaded with the normal
/// `∇f(x0)/|∇f(x0)|` (turned toward the camera as the cache does). The loss reaches the SDF:
/// - through the shading normal (the exact gradient of the shading, [`shade_normal_grad`]);
/// - through the point's move along the ray: the colour term's derivative along `r` is its exact
///   position gradient (`Stage2Grads::d_point`: the material, and `mii`'s SGs, move with the point;
///   the smoothness and KL regularisers see the point fixed);
/// - through the boundary lights: a grazing occluder that recedes from the ray by
///   `f(x';θ) − f(x';θ_traced)` opens the ray (see [`boundary_visibility`]); with
///   `--boundary detached` this path is cut as the axis path is;
/// - plus the eikonal term at the batch's points and `geometry_eikonal_points` uniform ones.
///
/// Secondary hits `x'`, `n'` (F_ind's inputs) are held at their traced values between re-traces of
/// the cache (every `geometry_retrace_every` iterations).
pub fn loss_and_grad_geometry(backend: &Backend, model: &Stage2Model, batch: &Stage2Batch, w: &Stage2Weights, noise_seed: u64, sdf: &Stage1Model) -> Result<Stage2Grads, BackendError> {
    let b = batch.len();
    let field = &sdf.field;
    // The SDF's parameters stay put for the step: their device copy is used as is.
    let _pin = field.pin(backend, &sdf.sdf_params)?;
    // Secondary hits (their SDF gives each boundary light's offset) and uniform eikonal points
    // (drawn from the step's seed) join the surface points in one field evaluation, whose
    // outputs feed the whole step: the SDF is evaluated once per point.
    let mut owner = Vec::new();
    let mut hit_pts: Vec<f32> = Vec::new();
    let mut f0 = Vec::new();
    if model.cfg.indirect != IndirectMode::None {
        for (i, hs) in batch.hits.iter().enumerate() {
            for (j, &(_, x2, _)) in hs.iter().enumerate() {
                owner.push(i);
                hit_pts.extend_from_slice(&x2);
                f0.push(batch.hit_sdf.get(i).and_then(|h| h.get(j)).copied().unwrap_or(0.0) as f64);
            }
        }
    }
    let hit_t: Vec<f64> = owner
        .iter()
        .enumerate()
        .map(|(s, &i)| {
            let d: [f64; 3] = [0, 1, 2].map(|a| (hit_pts[3 * s + a] - batch.x[i][a]) as f64);
            dot3(d, d).sqrt().max(1e-3)
        })
        .collect();
    let mut rng = crate::util::rng(noise_seed ^ 0xE1C0);
    let bound = 1.0f32;
    let ne = model.cfg.geometry_eikonal_points;
    let mut pts: Vec<f32> = bytemuck::cast_slice(&batch.x).to_vec();
    pts.extend_from_slice(&hit_pts);
    for _ in 0..3 * ne {
        pts.push(rng.random_range(-bound..bound));
    }
    let nh = owner.len();
    let we = model.cfg.geometry_eikonal_weight;
    let mut step: Result<Option<Stage2Grads>, BackendError> = Ok(None);
    let (eik, d_sdf) = field.value_and_grad(backend, &sdf.sdf_params, &pts, |o| {
        let n = b + nh + ne;
        let mut g = crate::nn::field::FieldOutputGrads { sdf: vec![0.0; n], gradient: vec![0.0; 3 * n], feature: Vec::new() };
        // The moved points and the normals.
        let mut gb = batch.clone();
        let mut moves = Vec::with_capacity(b); // (s, g·r, |g|, sign) per point
        for i in 0..b {
            let gv = [0, 1, 2].map(|a| o.gradient[3 * i + a] as f64);
            let v = f64x3(batch.v[i]);
            let r = v.map(|c| -c);
            let gr = dot3(gv, r);
            let f = o.sdf[i] as f64;
            let s = if gr < -0.05 { -f / gr } else { 0.0 };
            let len = dot3(gv, gv).sqrt().max(1e-12);
            let sign = if dot3(gv, v) < 0.0 { -1.0 } else { 1.0 };
            gb.x[i] = [0, 1, 2].map(|a| (batch.x[i][a] as f64 + r[a] * s) as f32);
            gb.n[i] = gv.map(|c| (sign * c / len) as f32);
            moves.push((s, gr, len, sign));
        }
        // Boundary offsets: how far each hit's occluder has receded from its ray since the trace.
        gb.boundary_offset = (0..nh).map(|s| (o.sdf[b + s] as f64 - f0[s]) / hit_t[s]).collect();
        let out = match loss_and_grad_with(backend, model, &gb, w, noise_seed, true) {
            Ok(v) => v,
            Err(e) => {
                step = Err(e);
                return (0.0, g);
            }
        };
        // The colour term's derivative along each ray.
        let ds: Vec<f64> = (0..b).map(|i| -dot3(out.d_point[i], f64x3(batch.v[i]))).collect();
        for i in 0..b {
            let (s, gr, len, sign) = moves[i];
            let gv = [0, 1, 2].map(|a| o.gradient[3 * i + a] as f64);
            let r = f64x3(batch.v[i]).map(|c| -c);
            let dn = out.d_normal[i];
            let gh = gv.map(|c| c / len);
            let proj = dot3(gh, dn);
            for a in 0..3 {
                g.gradient[3 * i + a] += (sign * (dn[a] - gh[a] * proj) / len) as f32;
            }
            if gr < -0.05 {
                let f = -s * gr;
                g.sdf[i] += (ds[i] * (-1.0 / gr)) as f32;
                for a in 0..3 {
                    g.gradient[3 * i + a] += (ds[i] * f * r[a] / (gr * gr)) as f32;
                }
            }
        }
        for k in 0..nh {
            g.sdf[b + k] += (out.d_offset[k] / hit_t[k]) as f32;
        }
        let eik_idx: Vec<usize> = (0..b).chain(b + nh..n).collect();
        let loss = super::stage1::eikonal(&o.gradient, &eik_idx, we, &mut g.gradient);
        step = Ok(Some(out));
        (loss, g)
    })?;
    let mut out = step?.expect("the field's loss closure ran");
    out.stats.eikonal = eik;
    out.stats.loss += eik;
    out.d_sdf = d_sdf;
    Ok(out)
}
