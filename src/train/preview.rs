//! `bake --preset preview`: photos → asset without training (visual hull + photo colour).
//!
//! `bake --preset preview`: no training, seconds instead of minutes; what it does, it says in its
//! output and report:
//!
//! 1. read the scene (any supported format), train split;
//! 2. geometry: the visual hull of the masks ([`super::hull`]) as a signed distance grid;
//! 3. colour: each surface point's photo colour ([`super::photo`]), cos²-weighted over the views
//!    that face and see it — **lit** colour (lighting baked in), not de-lit albedo;
//!    roughness: a constant;
//! 4. environment: uniform white (radiance 1), so that a renderer lighting the asset with the
//!    shipped EXR reproduces the photos' colours on diffuse parts;
//! 5. [`crate::export::export_asset`]: mesh, UVs, textures, .glb/.usda/.exr, thumbnails;
//! 6. when the scene folder holds a ground-truth mesh (`gt/mesh.obj`, our generated scenes), the
//!    Chamfer distance and normal consistency of the asset against it.
//!
//! Frames: everything is computed in the scene's normalised frame (unit sphere); the asset frame
//! is that frame rotated so the detected up axis becomes glTF's +Y, scaled to metres
//! (`--metres-per-unit` world units → metres), origin at the bottom centre (by the export).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use glam::{DMat3, DMat4, DQuat, DVec3};

use super::hull::{carve, signed_distance, Grid3, MaskView};
use super::photo::{project_colour, solid_bits, PhotoView, Pixels};
use crate::backend::{Backend, BackendError};
use crate::context::Context;
use crate::mesh::field::{Aabb, MaterialField, MaterialSamples, SdfField, SdfSamples};
use crate::mesh::MeshConfig;
use crate::scene::{ReadOptions, Scene, Split, View};
use crate::sg::env::{EnvSgs, SgLobe};
use crate::util::DataError;

/// What `bake` ships.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BakePreset {
    /// Stage 1 with the fast networks (hash grid): minutes on a CPU.
    Fast,
    /// Stage 1 with the paper's networks (8×512): for a GPU.
    Paper,
    /// No training: the visual hull of the masks with the photos' colour (seconds).
    Preview,
}

#[derive(Debug, clap::Args)]
pub struct BakeArgs {
    /// Scene folder (transforms.json, IDR/DTU cameras_sphere.npz, LLFF poses_bounds.npy or COLMAP).
    pub scene: PathBuf,
    #[command(flatten)]
    pub asset: crate::export::AssetArgs,
    /// `fast` (default) or `paper`: train stages 1 and 2 and export them; `preview`: the visual hull, no training.
    #[arg(long, value_enum, default_value_t = BakePreset::Fast)]
    pub preset: BakePreset,
    #[command(flatten)]
    pub train: super::cli::TrainOptions,
    #[command(flatten)]
    pub material: super::material::MaterialOptions,
    /// Stop after stage 1 and ship its radiance preview (lighting baked in, constant roughness).
    #[arg(long)]
    pub geometry_only: bool,
    #[command(flatten)]
    pub blender: super::blender_check::BlenderCheckOptions,
    /// Run folder for the training checkpoints (default: <out>/run); an existing run there resumes.
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// Preview: visual-hull grid resolution (voxels per side of the normalised cube [-1, 1]^3).
    #[arg(long, default_value_t = 128)]
    pub hull_resolution: usize,
    /// Constant perceptual roughness of the preview and `--geometry-only` materials (stage 2 estimates it).
    #[arg(long, default_value_t = 0.5)]
    pub preview_roughness: f32,
    /// Preview: a voxel must be seen by at least this fraction of the views to stay in the hull.
    #[arg(long, default_value_t = 0.5)]
    pub min_view_fraction: f32,
}

/// A view in the normalised frame, as hull carving and photo projection see it.
pub struct ViewAdapter<'a> {
    view: &'a View,
    /// The camera points are projected through: the view's own, or one put in its place (a
    /// refined pose, [`ViewAdapter::posed`]).
    camera: crate::scene::Camera,
    centre: [f32; 3],
    /// The inverse of the camera's pose, formed once (carving projects millions of points).
    camera_from_world: DMat4,
    /// The mask's [`solid_bits`], formed once (photo consistency's patches read it).
    solid: Option<Vec<u64>>,
}

impl<'a> ViewAdapter<'a> {
    pub fn new(view: &'a View) -> Self {
        Self::posed(view, &view.camera)
    }

    /// The view's photo and mask seen through `camera` in place of its own (same size and
    /// intrinsics: a refined pose).
    pub fn posed(view: &'a View, camera: &crate::scene::Camera) -> Self {
        Self {
            view,
            camera: camera.clone(),
            centre: camera.center().as_vec3().to_array(),
            camera_from_world: camera.world_from_camera.inverse(),
            solid: view.mask.as_deref().map(solid_bits),
        }
    }
}

impl MaskView for ViewAdapter<'_> {
    fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
        let q = self.camera.project_camera_point(self.camera_from_world.transform_point3(DVec3::from(p.map(f64::from))))?;
        Some([q.x as f32, q.y as f32])
    }
    fn mask_at(&self, px: [f32; 2]) -> Option<f32> {
        pixels(self.view).mask_at(px)
    }
}

impl PhotoView for ViewAdapter<'_> {
    fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
        MaskView::project(self, p)
    }
    fn centre(&self) -> [f32; 3] {
        self.centre
    }
    fn colour_at(&self, px: [f32; 2]) -> Option<[f32; 3]> {
        pixels(self.view).with_solid(self.solid.as_deref()).colour_at(px)
    }
    /// The nine lookups of [`PhotoView::patch`] with the image, mask and sizes gathered once.
    fn patch(&self, px: [f32; 2]) -> Option<[[f32; 3]; 9]> {
        pixels(self.view).with_solid(self.solid.as_deref()).patch(px)
    }
}

/// A view's image and mask as [`Pixels`] reads them.
#[inline(always)]
fn pixels(view: &View) -> Pixels<'_> {
    let image = &view.image;
    Pixels::new(view.camera.width, view.camera.height, view.mask.as_deref(), &image.data, image.width, image.height, image.channels)
}

/// Normalised frame → asset frame: the rotation taking the detected up axis to +Y (exact axis
/// when the up direction is near one, so a Z-up capture maps as Blender's importer expects:
/// (x, y, z) → (x, z, −y)).
pub fn asset_rotation(scene: &Scene) -> DMat3 {
    let n = &scene.normalisation;
    let up = match n.up_axis_name.as_str() {
        "+X" => DVec3::X,
        "-X" => -DVec3::X,
        "+Y" => DVec3::Y,
        "-Y" => -DVec3::Y,
        "+Z" => DVec3::Z,
        "-Z" => -DVec3::Z,
        _ => n.up_axis.normalize_or(DVec3::Y),
    };
    DMat3::from_quat(DQuat::from_rotation_arc(up, DVec3::Y))
}

/// The visual hull of `views`' masks as stage 1's hull initialisation carves it: the voxels of the
/// unit cube (`res` a side) inside the mask of at least half of the views.
pub fn masks_hull(views: &[&View], res: usize) -> Vec<bool> {
    let adapters: Vec<ViewAdapter> = views.iter().map(|v| ViewAdapter::new(v)).collect();
    adapters_hull(&adapters, res)
}

/// [`masks_hull`] of views seen through the given adapters (their cameras: refined poses).
pub fn adapters_hull(adapters: &[ViewAdapter], res: usize) -> Vec<bool> {
    let mv: Vec<&dyn MaskView> = adapters.iter().map(|a| a as &dyn MaskView).collect();
    carve(&mv, res, 1.0, 0.5, (adapters.len() / 2).max(1))
}

/// One separable [1, 2, 1]/4 pass per axis over the distance grid: rounds off the voxel
/// staircase of the carved hull (which otherwise makes the mesh bumpy and hard to simplify)
/// while keeping the zero level within a fraction of a voxel.
pub fn smooth(mut g: Grid3) -> Grid3 {
    use rayon::prelude::*;
    let res = g.res;
    for stride in [1, res, res * res] {
        let src = g.data.clone();
        g.data.par_iter_mut().enumerate().for_each(|(i, v)| {
            let t = (i / stride) % res;
            if t > 0 && t + 1 < res {
                *v = 0.25 * src[i - stride] + 0.5 * src[i] + 0.25 * src[i + stride];
            }
        });
    }
    g
}

/// The visual-hull distance grid as an [`SdfField`] in the asset frame.
pub struct HullSdf {
    pub grid: Grid3,
    /// Normalised → asset frame.
    pub rotation: DMat3,
    pub bounds: Aabb,
}

fn rot(m: &DMat3, v: [f32; 3]) -> [f32; 3] {
    (*m * DVec3::from(v.map(f64::from))).as_vec3().to_array()
}

impl HullSdf {
    /// Wrap `grid`; the mesh box is the inside voxels' box, rotated, with a 2-voxel margin.
    pub fn new(grid: Grid3, rotation: DMat3) -> Option<Self> {
        let res = grid.res;
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for (idx, &d) in grid.data.iter().enumerate() {
            if d < 0.0 {
                let c = grid.centre(idx % res, (idx / res) % res, idx / (res * res));
                for a in 0..3 {
                    lo[a] = lo[a].min(c[a]);
                    hi[a] = hi[a].max(c[a]);
                }
            }
        }
        if !lo[0].is_finite() {
            return None;
        }
        let margin = 2.0 * grid.spacing();
        let (mut blo, mut bhi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for corner in 0..8 {
            let p = [0, 1, 2].map(|a| if corner >> a & 1 == 1 { hi[a] + margin } else { lo[a] - margin });
            let q = rot(&rotation, p);
            for a in 0..3 {
                blo[a] = blo[a].min(q[a]);
                bhi[a] = bhi[a].max(q[a]);
            }
        }
        Some(Self { grid, rotation, bounds: Aabb { min: blo, max: bhi } })
    }

}

impl SdfField for HullSdf {
    fn name(&self) -> String {
        format!("visual hull of the masks ({}^3 distance grid)", self.grid.res)
    }
    fn bounds(&self) -> Aabb {
        self.bounds
    }
    fn eval(&self, _backend: &Backend, points: &[[f32; 3]]) -> Result<SdfSamples, BackendError> {
        use rayon::prelude::*;
        let to_normalised = self.rotation.transpose();
        let (values, gradients) = points
            .par_iter()
            .map(|&q| {
                let p = rot(&to_normalised, q);
                (self.grid.sample(p), rot(&self.rotation, self.grid.gradient(p)))
            })
            .unzip();
        Ok(SdfSamples { values, gradients })
    }
}

/// Photo colour (lit) and a constant roughness, as a [`MaterialField`] in the asset frame.
pub struct PhotoMaterial<'a> {
    pub views: Vec<&'a dyn PhotoView>,
    pub hull: &'a HullSdf,
    pub roughness: f32,
    /// Colour for points no view sees (the mean projected colour).
    pub fallback: [f32; 3],
    /// The "smallest feature" handed to the texture-size choice, in asset-frame units
    /// (`run` sets 16 photo pixel footprints: one texel per footprint).
    pub feature: f32,
}

impl PhotoMaterial<'_> {
    fn colour(&self, p: [f32; 3], n: [f32; 3]) -> Option<[f32; 3]> {
        project_colour(&self.views, &self.hull.grid, p, n, 0.1).map(|(c, _)| c.map(|v| v.clamp(0.0, 1.0)))
    }
}

impl MaterialField for PhotoMaterial<'_> {
    fn name(&self) -> String {
        format!(
            "photo projection over {} views (lit colour, lighting baked in), constant roughness {}",
            self.views.len(),
            self.roughness
        )
    }
    fn eval(
        &self,
        _backend: &Backend,
        points: &[[f32; 3]],
        normals: &[[f32; 3]],
    ) -> Result<MaterialSamples, BackendError> {
        use rayon::prelude::*;
        let rt = self.hull.rotation.transpose();
        let albedo = points
            .par_iter()
            .zip(normals)
            .map(|(&q, &nq)| self.colour(rot(&rt, q), rot(&rt, nq)).unwrap_or(self.fallback))
            .collect();
        Ok(MaterialSamples { albedo, roughness: vec![self.roughness; points.len()], metallic: Vec::new() })
    }
    fn feature_size(&self) -> Option<f32> {
        Some(self.feature)
    }
}

/// The uniform white environment shipped with a preview bake: one very broad lobe, radiance
/// 1.0 at the zenith and 0.98 at the nadir.
pub fn uniform_environment() -> EnvSgs {
    EnvSgs { lobes: vec![SgLobe { axis: [0.0, 1.0, 0.0], sharpness: 0.01, amplitude: [1.0; 3] }] }
}

fn asset_name(args: &BakeArgs) -> String {
    if let Some(n) = &args.asset.name {
        return n.clone();
    }
    name_from_path(&args.scene)
}

/// An asset name (`[a-z][a-z0-9_-]*`) from a scene folder's name.
pub fn name_from_path(scene: &Path) -> String {
    let stem = scene
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|s| s.to_string_lossy().to_lowercase()))
        .unwrap_or_default();
    let mut name: String = stem
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' })
        .collect();
    if !name.starts_with(|c: char| c.is_ascii_lowercase()) {
        name = format!("asset_{name}");
    }
    name.trim_end_matches('_').to_string()
}

/// Ground-truth mesh in the scene folder, if any (our generated scenes keep one in `gt/`).
fn ground_truth_mesh(scene_dir: &Path) -> Option<PathBuf> {
    ["gt/mesh.obj", "gt/mesh.ply"].iter().map(|r| scene_dir.join(r)).find(|p| p.is_file())
}

pub fn run(args: &BakeArgs, ctx: &Context) -> anyhow::Result<()> {
    crate::export::check_writable(&args.asset.out)?;
    match args.preset {
        BakePreset::Preview => run_preview(args, ctx),
        BakePreset::Fast | BakePreset::Paper => super::cli::bake_trained(args, ctx),
    }
}

/// The preview bake (see the module docs).
pub fn run_preview(args: &BakeArgs, ctx: &Context) -> anyhow::Result<()> {
    let t_total = Instant::now();
    if !(8..=1024).contains(&args.hull_resolution) {
        anyhow::bail!("--hull-resolution {} must be in 8..=1024", args.hull_resolution);
    }
    if !(0.0..=1.0).contains(&args.preview_roughness) {
        anyhow::bail!("--preview-roughness must be in [0, 1], got {}", args.preview_roughness);
    }
    let backend = ctx.backend()?;
    ctx.say(
        "preview bake (no training): geometry from the visual hull of the masks; colour projected from \
         the photos with lighting baked in; constant roughness; uniform white environment.",
    );

    // 1. Scene.
    let t = Instant::now();
    let scene = crate::scene::load(&args.scene, &ReadOptions { downscale: args.train.downscale, keep_all_views: args.train.keep_all_views })?;
    if let Some(note) = &scene.downscale_note {
        ctx.say(note.clone());
    }
    let mut views: Vec<&View> = scene.views_in(Split::Train).collect();
    if views.is_empty() {
        views = scene.views.iter().collect();
    }
    if views.is_empty() {
        return Err(DataError::new(&args.scene, "the scene has no views").into());
    }
    if let Some(v) = views.iter().find(|v| v.mask.is_none()) {
        return Err(DataError::new(
            &v.image_path,
            "no mask for this view (RGBA alpha or a mask file): the preview bake carves the visual hull from masks",
        )
        .into());
    }
    let seconds_read = t.elapsed().as_secs_f64();
    let res0 = (views[0].camera.width, views[0].camera.height);
    ctx.say(format!(
        "read {}: {} views ({}), {}x{}, up axis {} [{:.0} ms]",
        args.scene.display(),
        views.len(),
        scene.format.name(),
        res0.0,
        res0.1,
        scene.normalisation.up_axis_name,
        seconds_read * 1e3
    ));

    // 2. Visual hull.
    let t = Instant::now();
    let adapters: Vec<ViewAdapter> = views.iter().map(|v| ViewAdapter::new(v)).collect();
    let mask_views: Vec<&dyn MaskView> = adapters.iter().map(|a| a as &dyn MaskView).collect();
    let min_views = ((views.len() as f32 * args.min_view_fraction).ceil() as usize).max(1);
    let res = args.hull_resolution;
    let inside = carve(&mask_views, res, 1.0, 0.5, min_views);
    let voxels_inside = inside.iter().filter(|b| **b).count();
    if voxels_inside == 0 {
        return Err(DataError::new(
            &args.scene,
            "the masks carve away every voxel of the unit cube: the cameras and masks do not agree on an object (check poses, masks and --min-view-fraction)",
        )
        .into());
    }
    let grid = smooth(signed_distance(&inside, res, 1.0));
    let rotation = asset_rotation(&scene);
    let hull = HullSdf::new(grid, rotation).context("empty visual hull")?;
    let seconds_hull = t.elapsed().as_secs_f64();
    ctx.say(format!(
        "visual hull: {res}^3 voxels, {voxels_inside} inside ({:.1}%), each kept voxel seen by >= {min_views} views [{:.2} s]",
        100.0 * voxels_inside as f64 / inside.len() as f64,
        seconds_hull
    ));

    // 3. Material from the photos: one texel per photo pixel footprint at the mean camera
    //    distance (choose_texture_size puts 16 texels on a feature, so the feature is 16 footprints).
    let footprint = views
        .iter()
        .map(|v| v.camera.center().length() / v.camera.fx.max(1e-9))
        .sum::<f64>()
        / views.len() as f64;
    let fallback = {
        let (mut acc, mut n) = ([0.0f64; 3], 0usize);
        for v in &views {
            let m = v.mask.as_ref().expect("checked above");
            for (i, &mv) in m.iter().enumerate() {
                if mv >= 0.5 {
                    for (k, a) in acc.iter_mut().enumerate() {
                        *a += v.image.data[i * v.image.channels + k.min(v.image.channels - 1)] as f64;
                    }
                    n += 1;
                }
            }
        }
        acc.map(|a| (a / n.max(1) as f64).clamp(0.0, 1.0) as f32)
    };
    let material = PhotoMaterial {
        views: adapters.iter().map(|a| a as &dyn PhotoView).collect(),
        hull: &hull,
        roughness: args.preview_roughness,
        fallback,
        feature: 16.0 * footprint as f32,
    };

    // 4–5. Export.
    let name = asset_name(args);
    // The hull is known to a voxel: bound the simplification by one hull voxel.
    let mesh = MeshConfig {
        resolution: args.asset.resolution.unwrap_or(128),
        error_bound: Some(args.asset.error_bound.unwrap_or(2.0 / res as f32)),
        face_tolerance_deg: args.asset.face_tolerance_deg(),
        ..Default::default()
    };
    let provenance = serde_json::json!({
        "method": "preview bake (visual hull + photo projection, no training)",
        "scene": args.scene.display().to_string(),
        "format": scene.format.name(),
        "views": views.len(),
        "hull_resolution": res,
    });
    let cfg = args.asset.capture_export_config(scene.normalisation.scale, mesh, &name, provenance, ctx);
    let env = uniform_environment();
    let t = Instant::now();
    let report = crate::export::export_asset_with(&backend, &hull, &material, Some(&env), &cfg, &args.asset.out, &ctx.spinner("export"))?;
    let seconds_export = t.elapsed().as_secs_f64();
    ctx.say(format!(
        "export: {} triangles (error bound {:.4} normalised units, watertight {}), {} UV charts, {}² textures, files in {} [{:.2} s]",
        report.mesh.triangles,
        report.mesh.error_bound,
        report.mesh.watertight,
        report.uv_charts,
        report.texture_size,
        args.asset.out.display(),
        seconds_export
    ));

    // 6. Ground truth, when the scene has it.
    let gt_metrics = ground_truth_metrics(&args.scene, scene.normalisation.center, rotation, report.config.metres_per_world_unit(), &report, ctx)?;

    let summary = serde_json::json!({
        "method": "preview",
        "what": {
            "geometry": "visual hull of the masks (signed distance grid)",
            "albedo": "photo projection, cos²-weighted over visible views: lit colour, lighting baked in",
            "roughness": format!("constant {}", args.preview_roughness),
            "environment": "uniform white (radiance 1)",
            "not_done": "no training: geometry is the visual hull; light and material are not separated",
        },
        "scene": {
            "path": args.scene.display().to_string(),
            "format": scene.format.name(),
            "views": views.len(),
            "resolution": [res0.0, res0.1],
            "normalisation": scene.normalisation,
        },
        "hull": { "resolution": res, "voxels_inside": voxels_inside, "min_views": min_views },
        "seconds": {
            "read": seconds_read,
            "hull": seconds_hull,
            "export": seconds_export,
            "total": t_total.elapsed().as_secs_f64(),
        },
        "export": report,
        "ground_truth": gt_metrics,
    });
    write_bake_report(&args.asset.out, &name, summary, t_total, ctx)
}

/// Write `bake_report.json` into the asset folder, emit it, and say what was written.
pub fn write_bake_report(out: &Path, name: &str, summary: serde_json::Value, t_total: Instant, ctx: &Context) -> anyhow::Result<()> {
    crate::util::atomic_write(&out.join("bake_report.json"), serde_json::to_string_pretty(&summary)?.as_bytes())?;
    ctx.emit("bake", summary);
    ctx.say(format!("wrote {}/{name}.glb, asset.usda, env.exr, bake_report.json in {:.1} s", out.display(), t_total.elapsed().as_secs_f64()));
    Ok(())
}

/// Chamfer distance and normal consistency of an exported asset against the scene's
/// ground-truth mesh (`gt/mesh.obj|ply`), in metres in the asset frame; `Null` without one.
pub fn ground_truth_metrics(
    scene_dir: &Path,
    center: DVec3,
    rotation: DMat3,
    metres_per_unit: f64,
    report: &crate::export::ExportReport,
    ctx: &Context,
) -> anyhow::Result<serde_json::Value> {
    let Some(gt_path) = ground_truth_mesh(scene_dir) else {
        return Ok(serde_json::Value::Null);
    };
    let t = Instant::now();
    let mut gt = crate::eval::mesh::Mesh::read(&gt_path)?;
    let c = center;
    let shift = DVec3::from(report.origin_shift_m.map(f64::from));
    for p in &mut gt.positions {
        *p = rotation * (*p - c) * metres_per_unit + shift;
    }
    let pred = crate::eval::mesh::Mesh::from_indexed(&report.geometry.positions, &report.geometry.indices).with_normals(&report.geometry.normals);
    let m = crate::eval::mesh::compare_meshes(&pred, &gt, 20_000, 1);
    let (lo, hi) = report.bounds_m;
    let size = (0..3).map(|k| (hi[k] - lo[k]) as f64).fold(0.0, f64::max);
    ctx.say(format!(
        "vs {}: Chamfer {:.4} m ({:.2}% of the object's size), normal consistency {:.3} (faces) / {:.3} (shading normals) [{:.2} s]",
        gt_path.display(),
        m.chamfer,
        100.0 * m.chamfer / size.max(1e-12),
        m.normal_consistency,
        m.shading_normal_consistency.unwrap_or(f64::NAN),
        t.elapsed().as_secs_f64()
    ));
    Ok(serde_json::json!({
        "gt_mesh": gt_path.display().to_string(),
        "metrics": m,
        "chamfer_over_object_size": m.chamfer / size.max(1e-12),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ball_hull(rotation: DMat3) -> HullSdf {
        let (res, r) = (40usize, 0.5f32);
        let g = Grid3::new(res, 1.0, 0.0);
        let inside: Vec<bool> = (0..res * res * res)
            .map(|i| {
                let c = g.centre_of(i);
                ((c[0] - 0.2).powi(2) + c[1] * c[1] + c[2] * c[2]).sqrt() < r
            })
            .collect();
        HullSdf::new(signed_distance(&inside, res, 1.0), rotation).unwrap()
    }

    /// A view's 3×3 patch from `ViewAdapter::patch` is, to the bit, nine lookups of a plain
    /// reference (the view's own `View::mask_at`, a floor-based bilinear lookup, through the
    /// provided `PhotoView::patch`), and its mask lookup is `View::mask_at` on the image: everywhere in the image, at its edges, across the mask's
    /// edge, off the image, for a soft mask value at 0.5, with and without a mask, for 1- and
    /// 3-channel images.
    #[test]
    fn a_views_patch_is_its_nine_pixel_lookups_to_the_bit() {
        struct Reference<'a>(&'a View);
        impl PhotoView for Reference<'_> {
            fn project(&self, _: [f32; 3]) -> Option<[f32; 2]> {
                None
            }
            fn centre(&self) -> [f32; 3] {
                [0.0; 3]
            }
            fn colour_at(&self, px: [f32; 2]) -> Option<[f32; 3]> {
                let (v, img) = (self.0, &self.0.image);
                let on_image = px[0] >= 0.0 && px[1] >= 0.0 && (px[0] as usize) < v.camera.width && (px[1] as usize) < v.camera.height;
                if !on_image || v.mask_at(px[0] as f64, px[1] as f64) < 0.5 {
                    return None;
                }
                let (w, h, c) = (img.width, img.height, img.channels);
                let fx = (px[0] - 0.5).clamp(0.0, (w - 1) as f32);
                let fy = (px[1] - 0.5).clamp(0.0, (h - 1) as f32);
                let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                let (tx, ty) = (fx - x0 as f32, fy - y0 as f32);
                let at = |x: usize, y: usize, k: usize| img.data[(y * w + x) * c + k.min(c - 1)];
                Some([0, 1, 2].map(|k| {
                    let top = at(x0, y0, k) * (1.0 - tx) + at(x1, y0, k) * tx;
                    let bottom = at(x0, y1, k) * (1.0 - tx) + at(x1, y1, k) * tx;
                    top * (1.0 - ty) + bottom * ty
                }))
            }
        }
        let (w, h) = (23usize, 17usize);
        for (channels, masked) in [(3usize, true), (3, false), (1, true)] {
            let mut image = crate::image_io::ImageF32::new(w, h, channels);
            for (i, v) in image.data.iter_mut().enumerate() {
                *v = ((i * 7919) % 1009) as f32 / 1009.0 - 0.1;
            }
            // Foreground left of column 15, a soft 0.5 column at 15 (kept: the test is ≥ 0.5), 0.2
            // elsewhere; inside, a NaN pixel (kept, as `mask < 0.5` is false) and one just under 0.5.
            let soft = |x: usize, y: usize| match (x, y) {
                (7, 9) => f32::NAN,
                (8, 9) => 0.49999997,
                _ if y <= 2 || x > 15 => 0.2,
                (15, _) => 0.5,
                _ => 1.0,
            };
            let mask = masked.then(|| (0..w * h).map(|i| soft(i % w, i / w)).collect());
            let camera = crate::scene::Camera { width: w, height: h, fx: 20.0, fy: 20.0, cx: 11.5, cy: 8.5, distortion: None, world_from_camera: DMat4::IDENTITY };
            let view = View { name: "v".into(), split: Split::Train, camera, image, mask, image_path: PathBuf::new() };
            let (fast, slow) = (ViewAdapter::new(&view), Reference(&view));
            let (mut some, mut none) = (0, 0);
            for i in 0..=60 {
                for j in 0..=44 {
                    let px = [i as f32 * 0.4 - 0.7 + 1e-3 * j as f32, j as f32 * 0.43 - 0.9];
                    let (a, b) = (fast.patch(px), slow.patch(px));
                    assert_eq!(a.map(|p| p.map(|c| c.map(f32::to_bits))), b.map(|p| p.map(|c| c.map(f32::to_bits))), "channels {channels}, mask {masked}, at {px:?}");
                    if a.is_some() { some += 1 } else { none += 1 }
                    let on_image = px[0] >= 0.0 && px[1] >= 0.0 && (px[0] as usize) < w && (px[1] as usize) < h;
                    let reference = on_image.then(|| view.mask_at(px[0] as f64, px[1] as f64));
                    assert_eq!(MaskView::mask_at(&fast, px).map(f32::to_bits), reference.map(f32::to_bits), "mask_at {px:?}");
                }
            }
            assert!(some > 200 && none > 200, "both outcomes exercised: {some} patches, {none} refused");
            assert_eq!(fast.patch([f32::NAN, 3.0]), None);
            for px in [[3.3f32, 4.6], [0.2, 16.9], [14.7, 9.1], [22.9, 5.0]] {
                let bits = |c: Option<[f32; 3]>| c.map(|c| c.map(f32::to_bits));
                assert_eq!(bits(fast.colour_at(px)), bits(slow.colour_at(px)), "colour_at {px:?}");
            }
        }
    }

    /// The grid field's gradient agrees with central differences of its own values, and a
    /// Z-up frame maps to Y-up as Blender's importer expects.
    #[test]
    fn hull_field_gradient_and_frame() {
        let rz = DMat3::from_quat(DQuat::from_rotation_arc(DVec3::Z, DVec3::Y));
        assert!((rz * DVec3::new(1.0, 2.0, 3.0) - DVec3::new(1.0, 3.0, -2.0)).length() < 1e-12);
        let hull = ball_hull(rz);
        let b = Backend::cpu();
        let pts = [[0.5f32, 0.1, 0.2], [0.2, 0.55, -0.1], [-0.1, -0.2, 0.3], [0.3, 0.3, 0.3]];
        let s = hull.eval(&b, &pts).unwrap();
        let e = 0.5 * hull.grid.spacing();
        for (i, p) in pts.iter().enumerate() {
            for a in 0..3 {
                let (mut pp, mut pm) = (*p, *p);
                pp[a] += e;
                pm[a] -= e;
                let v = hull.eval(&b, &[pp, pm]).unwrap().values;
                let fd = (v[0] - v[1]) / (2.0 * e);
                assert!((fd - s.gradients[i][a]).abs() < 0.05, "point {i} axis {a}: {} vs fd {fd}", s.gradients[i][a]);
            }
        }
        // The ball's centre (0.2, 0, 0) in the normalised frame is (0.2, 0, -0) in the asset frame.
        let c = hull.eval(&b, &[[0.2, 0.0, 0.0]]).unwrap().values[0];
        assert!((c + 0.5).abs() < 2.0 * hull.grid.spacing(), "sdf at the centre {c}");
        // Bounds hold the ball.
        assert!(hull.bounds.min[0] < -0.3 + 0.01 && hull.bounds.max[0] > 0.7 - 0.01, "{:?}", hull.bounds);
    }
}
