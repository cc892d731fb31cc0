//! The asset writer: [`export_asset`] turns any [`SdfField`] + [`MaterialField`] (analytic now,
//! the trained model later) into a folder holding
//!
//! | file | what |
//! | --- | --- |
//! | `<name>.glb` | glTF 2.0, embedded sRGB albedo PNG + linear ORM PNG (G = roughness, B = metallic) |
//! | `asset.usda`, `payload.usda` | the USD component (see [`usd`]) |
//! | `textures/albedo.png`, `textures/orm.png` | the textures USD references |
//! | `lookdev.usda` | the asset under a DomeLight on `env.exr` |
//! | `env.exr`, `env_sgs.json` | the environment (latlong, OpenEXR/USD convention) and its SG lobes |
//! | `<name>.usdz` | optional single-file package |
//! | `.thumbs/256x256/<file>.png` | previews of the .glb and the USD asset |
//! | `export_report.json` | what was chosen (resolution, bound, texture size) and the timings |
//!
//! Positions are in metres: `p_m = p_scene · metres_per_unit + scene_offset_m`, then moved so the
//! asset's origin is its bottom centre (the shift is in the report). Every file is written to a
//! temporary name and renamed.

pub mod bench;
pub mod cli;
pub mod gltf;
pub mod thumbnail;
pub mod usd;
pub mod usdz;

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::backend::{Backend, BackendError};
use crate::bake::{self, BakeStats};
use crate::image_io;
use crate::mesh::field::{MaterialField, SdfField};
use crate::mesh::uv::{self, UvError};
use crate::mesh::{self, MeshConfig, MeshError, MeshStats};
use crate::scene::normalise::CaptureUnits;
use crate::sg::env::{EnvSgs, LatlongConvention, SgLobe};
use crate::util::{atomic_write, DataError};

/// Texture size: chosen from the surface area and the material's detail, or fixed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum TextureSize {
    Auto,
    Fixed(u32),
}

impl std::str::FromStr for TextureSize {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(Self::Auto);
        }
        let n: u32 = s
            .parse()
            .map_err(|_| format!("{s:?} is neither `auto` nor a number"))?;
        if !n.is_power_of_two() || !(16..=8192).contains(&n) {
            return Err(format!(
                "texture size {n} must be a power of two in 16..=8192"
            ));
        }
        Ok(Self::Fixed(n))
    }
}

/// The asset flags every command that writes an asset shares (`bake`, `export`), one meaning each.
#[derive(Clone, Debug, clap::Args)]
pub struct AssetArgs {
    /// Output folder for the asset.
    #[arg(long)]
    pub out: std::path::PathBuf,
    /// Marching grid nodes along the longest side of the object's box (default: chosen from the
    /// source: the photos' pixel footprint for a trained or preview bake, 256 for an analytic field).
    #[arg(long)]
    pub resolution: Option<usize>,
    /// Simplification error bound, in normalised scene units (the unit sphere the object is scaled
    /// into) (default: half a marching cell; a preview bake uses one hull voxel).
    #[arg(long)]
    pub error_bound: Option<f32>,
    /// Texture size: `auto` (from surface area and the detail the source holds) or a power of two.
    #[arg(long, default_value = "auto")]
    pub texture: TextureSize,
    /// Asset name ([a-z][a-z0-9_-]*); default: from the scene folder's (or the shape's) name.
    #[arg(long)]
    pub name: Option<String>,
    /// Metres per world unit of the source (the capture's units; an analytic field's units).
    /// Default for a capture: read from the object's size, metres unless the object spans more
    /// than 20 world units, then millimetres (DTU's calibration); reported. An analytic field: 1.
    #[arg(long, value_parser = parse_positive_metres)]
    pub metres_per_unit: Option<f64>,
    /// The asset's height in metres (its extent along +Y): scales the asset to it, for captures
    /// whose units are arbitrary (COLMAP, LLFF, nerfstudio) and objects whose size is known.
    #[arg(long, value_parser = parse_positive_metres, conflicts_with = "metres_per_unit")]
    pub height: Option<f64>,
    /// Also write a .usdz package.
    #[arg(long)]
    pub usdz: bool,
    /// Largest angle (degrees, 1–90) the simplification may leave between a face's normal and the
    /// surface's: a smaller one keeps more triangles where a tool draws the mesh flat-shaded
    /// (default: no limit; the shading normals are held within 10° either way).
    #[arg(long, value_parser = parse_face_tolerance)]
    pub face_tolerance: Option<f32>,
}

impl AssetArgs {
    /// [`MeshConfig::face_tolerance_deg`] from `--face-tolerance` (its default where not given).
    pub fn face_tolerance_deg(&self) -> f32 {
        self.face_tolerance.unwrap_or(MeshConfig::default().face_tolerance_deg)
    }

    /// The capture's unit: `--metres-per-unit` where given, else read from the object's size
    /// ([`CaptureUnits::from_scale`], `scale` the scene normalisation's world → normalised factor).
    /// With `--height`, the unit read from the object's size stands until the export measures the
    /// mesh and scales it ([`ExportConfig::height_m`]).
    pub fn capture_units(&self, scale: f64) -> CaptureUnits {
        match (self.metres_per_unit, self.height) {
            (Some(m), _) => CaptureUnits::given(m),
            (None, Some(h)) => CaptureUnits { unit: "height".into(), why: format!("scaled to a height of {h} m (--height)"), ..CaptureUnits::from_scale(scale) },
            (None, None) => CaptureUnits::from_scale(scale),
        }
    }

    /// The export of a capture's asset: `mesh`, the asset flags (name, texture, .usdz), and the
    /// capture's scale ([`AssetArgs::capture_units`] for a scene normalised by `scale`, or
    /// `--height`; said on `ctx`). `default_name` names the asset where `--name` does not.
    pub fn capture_export_config(&self, scale: f64, mesh: MeshConfig, default_name: &str, provenance: serde_json::Value, ctx: &crate::context::Context) -> ExportConfig {
        let units = self.capture_units(scale);
        ctx.say(format!("units: {}", units.why));
        ExportConfig {
            name: self.name.clone().unwrap_or_else(|| default_name.to_string()),
            mesh,
            texture: self.texture,
            metres_per_unit: (units.metres_per_unit / scale) as f32,
            capture_units: Some(units),
            height_m: self.height.map(|h| h as f32),
            usdz: self.usdz,
            provenance,
            ..Default::default()
        }
    }
}

/// `--metres-per-unit` and `--height`: a positive, finite number of metres.
pub(crate) fn parse_positive_metres(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| format!("`{s}` is not a number of metres"))?;
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(format!("must be a positive number of metres, got {v}"))
    }
}

pub(crate) fn parse_face_tolerance(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|_| format!("face tolerance `{s}` is not a number of degrees"))?;
    if (1.0..=90.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!("face tolerance {v}° must be in 1..=90"))
    }
}

/// Everything the export needs besides the fields.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ExportConfig {
    /// Asset name `[a-z][a-z0-9_-]*` (file names, USD prim names).
    pub name: String,
    pub mesh: MeshConfig,
    pub texture: TextureSize,
    /// Scene units → metres (undoes the scene normalisation).
    pub metres_per_unit: f32,
    /// The capture's length unit this scale came from (a capture's export; none for an analytic
    /// field), reported with the config.
    pub capture_units: Option<CaptureUnits>,
    /// Scale the asset to this height (metres, its +Y extent) instead of by `metres_per_unit`; the
    /// report's config gives the scale it came to (and `capture_units` the metres per world unit).
    pub height_m: Option<f32>,
    /// Added after scaling (metres), before the origin is moved to the bottom centre.
    pub scene_offset_m: [f32; 3],
    /// Also write `<name>.usdz`.
    pub usdz: bool,
    /// Width of the environment EXR (height = width / 2).
    pub env_width: usize,
    /// Recorded in the glTF `asset.extras` and the report (source images, settings, ...).
    pub provenance: serde_json::Value,
}

impl ExportConfig {
    /// Metres per world unit of the capture as exported (after `height_m` scaled it; 1 for an
    /// export without a capture): what maps the capture's own meshes (ground truth) to the asset.
    pub fn metres_per_world_unit(&self) -> f64 {
        self.capture_units.as_ref().map_or(1.0, |u| u.metres_per_unit)
    }
}

impl Default for ExportConfig {
    fn default() -> Self {
        Self {
            name: "asset".into(),
            mesh: MeshConfig::default(),
            texture: TextureSize::Auto,
            metres_per_unit: 1.0,
            capture_units: None,
            height_m: None,
            scene_offset_m: [0.0; 3],
            usdz: false,
            env_width: 512,
            provenance: serde_json::json!({}),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("invalid export settings: {0}")]
    Config(String),
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Mesh(#[from] MeshError),
    #[error(transparent)]
    Uv(#[from] UvError),
    #[error(transparent)]
    Backend(#[from] BackendError),
}

/// The final geometry in metres with glTF UVs (what every writer sees).
#[derive(Clone, Debug, Default)]
pub struct AssetGeometry {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub uvs: Vec<[f32; 2]>,
    pub indices: Vec<u32>,
}

impl AssetGeometry {
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        mesh::bounds_of(&self.positions)
    }
}

/// What was written and chosen, with timings (also saved as `export_report.json`).
#[derive(Clone, Debug, serde::Serialize)]
pub struct ExportReport {
    pub name: String,
    pub sdf: String,
    pub material: String,
    pub backend: String,
    pub mesh: MeshStats,
    pub uv_charts: u32,
    pub uv_utilization: f32,
    pub texture_size: u32,
    pub texture_size_reason: String,
    pub bake: BakeStats,
    /// Translation applied (metres) to put the origin at the bottom centre.
    pub origin_shift_m: [f32; 3],
    pub bounds_m: ([f32; 3], [f32; 3]),
    pub files: Vec<PathBuf>,
    pub seconds_unwrap: f64,
    pub seconds_write: f64,
    pub seconds_total: f64,
    pub config: ExportConfig,
    /// The written geometry (metres, glTF frame), for callers that evaluate it; not in the JSON.
    #[serde(skip)]
    pub geometry: AssetGeometry,
}

/// A neutral test environment: a warm key light from the upper front right, a cool fill and a
/// broad sky, so relit renders show both the albedo and the roughness.
pub fn default_environment() -> EnvSgs {
    let n = |v: [f32; 3]| mesh::normalize(v);
    EnvSgs {
        lobes: vec![
            SgLobe {
                axis: n([0.5, 0.7, 0.5]),
                sharpness: 40.0,
                amplitude: [6.0, 5.5, 5.0],
            },
            SgLobe {
                axis: n([-0.6, 0.3, -0.4]),
                sharpness: 8.0,
                amplitude: [0.6, 0.7, 0.9],
            },
            SgLobe {
                axis: [0.0, 1.0, 0.0],
                sharpness: 1.0,
                amplitude: [0.5, 0.55, 0.6],
            },
            SgLobe {
                axis: [0.0, -1.0, 0.0],
                sharpness: 1.0,
                amplitude: [0.25, 0.22, 0.2],
            },
        ],
    }
}

fn valid_name(name: &str) -> bool {
    let mut c = name.chars();
    matches!(c.next(), Some('a'..='z'))
        && c.all(|ch| ch.is_ascii_lowercase() || ch.is_ascii_digit() || ch == '_' || ch == '-')
}

/// Fail early (before any heavy work) when `out_dir` cannot be created or written.
pub fn check_writable(out_dir: &Path) -> Result<(), DataError> {
    crate::util::ensure_writable_dir(out_dir)
}

/// The export entry point: mesh, unwrap, bake and write the asset folder (see the module docs).
/// `env`: the environment to ship (None → [`default_environment`]).
pub fn export_asset(
    backend: &Backend,
    sdf: &dyn SdfField,
    material: &dyn MaterialField,
    env: Option<&EnvSgs>,
    cfg: &ExportConfig,
    out_dir: &Path,
) -> Result<ExportReport, ExportError> {
    export_asset_with(backend, sdf, material, env, cfg, out_dir, &indicatif::ProgressBar::hidden())
}

/// [`export_asset`], each phase (meshing and every simplification round, unwrapping, baking,
/// writing) said in `progress`'s message; the bar is cleared when the export ends, however it ends.
pub fn export_asset_with(
    backend: &Backend,
    sdf: &dyn SdfField,
    material: &dyn MaterialField,
    env: Option<&EnvSgs>,
    cfg: &ExportConfig,
    out_dir: &Path,
    progress: &indicatif::ProgressBar,
) -> Result<ExportReport, ExportError> {
    struct ClearOnDrop<'a>(&'a indicatif::ProgressBar);
    impl Drop for ClearOnDrop<'_> {
        fn drop(&mut self) {
            self.0.finish_and_clear();
        }
    }
    let _clear = ClearOnDrop(progress);
    let t_total = Instant::now();
    if !valid_name(&cfg.name) {
        return Err(ExportError::Config(format!(
            "asset name {:?} must match [a-z][a-z0-9_-]*",
            cfg.name
        )));
    }
    if !(cfg.metres_per_unit.is_finite() && cfg.metres_per_unit > 0.0) {
        return Err(ExportError::Config(format!(
            "metres_per_unit must be > 0, got {}",
            cfg.metres_per_unit
        )));
    }
    if cfg.env_width < 8 {
        return Err(ExportError::Config(format!(
            "env_width {} is too small",
            cfg.env_width
        )));
    }
    check_writable(out_dir)?;

    // Geometry (scene units).
    let built = mesh::build_mesh_with(backend, sdf, &cfg.mesh, progress)?;
    let (lo, hi) = built.mesh.bounds();
    let resolved;
    let cfg = match cfg.height_m {
        None => cfg,
        Some(h) => {
            let span = hi[1] - lo[1];
            if !(h.is_finite() && h > 0.0 && span > 0.0) {
                return Err(ExportError::Config(format!("cannot scale a mesh {span} units tall to a height of {h} m")));
            }
            let mut c = cfg.clone();
            c.metres_per_unit = h / span;
            let factor = f64::from(c.metres_per_unit) / f64::from(cfg.metres_per_unit);
            if let Some(u) = &mut c.capture_units {
                u.metres_per_unit *= factor;
            }
            resolved = c;
            &resolved
        }
    };
    let object_size = (0..3).map(|k| (hi[k] - lo[k]) as f64).fold(0.0, f64::max);
    let (texture_size, reason) = match cfg.texture {
        TextureSize::Fixed(n) => (n, "fixed by the user".to_string()),
        TextureSize::Auto => {
            let area = built.mesh.area();
            let n = bake::choose_texture_size(area, object_size, material.feature_size());
            (
                n,
                format!(
                    "surface area {area:.4} scene units², object size {object_size:.3}, material feature size {:?}",
                    material.feature_size()
                ),
            )
        }
    };

    progress.set_message(format!("export: unwrapping {} triangles", built.mesh.triangle_count()));
    let t = Instant::now();
    let padding = (texture_size / 128).max(2);
    let uvm = uv::unwrap(&built.mesh, &built.normals, texture_size, padding)?;
    let seconds_unwrap = t.elapsed().as_secs_f64();

    progress.set_message(format!("export: baking {texture_size}² textures"));
    let baked = bake::bake(backend, sdf, material, &uvm, texture_size as usize)?;

    // Scene units → metres, origin at the bottom centre.
    let s = cfg.metres_per_unit;
    let mut positions: Vec<[f32; 3]> = uvm
        .positions
        .iter()
        .map(|p| [0, 1, 2].map(|k| p[k] * s + cfg.scene_offset_m[k]))
        .collect();
    let (mlo, mhi) = mesh::bounds_of(&positions);
    let shift = [-(mlo[0] + mhi[0]) * 0.5, -mlo[1], -(mlo[2] + mhi[2]) * 0.5];
    for p in &mut positions {
        for k in 0..3 {
            p[k] += shift[k];
        }
    }
    let geo = AssetGeometry {
        positions,
        normals: uvm.normals.clone(),
        uvs: uvm.uvs.clone(),
        indices: uvm.indices.clone(),
    };

    // Writers.
    progress.set_message("export: writing the asset");
    let t = Instant::now();
    let n = baked.size;
    let albedo_flat: Vec<f32> = baked.albedo.iter().flatten().copied().collect();
    let metallic = baked.metallic.is_some();
    let orm_flat: Vec<f32> = baked
        .roughness
        .iter()
        .enumerate()
        .flat_map(|(i, &r)| [1.0, r, baked.metallic.as_ref().map_or(0.0, |m| m[i])])
        .collect();
    let albedo_png = image_io::encode_png8(n, n, 3, &albedo_flat, true)
        .map_err(|e| DataError::new(out_dir, e))?;
    let orm_png =
        image_io::encode_png8(n, n, 3, &orm_flat, false).map_err(|e| DataError::new(out_dir, e))?;
    let material_name = format!("{}_mat", cfg.name.replace('-', "_"));
    let prim_name = cfg.name.replace('-', "_");
    let provenance = serde_json::json!({
        "generator": format!("pii-bake {}", env!("CARGO_PKG_VERSION")),
        "sdf": sdf.name(),
        "material": material.name(),
        "resolution": cfg.mesh.resolution,
        "error_bound_scene_units": built.stats.error_bound,
        "metres_per_unit": cfg.metres_per_unit,
        "texture_size": texture_size,
        "origin_shift_m": shift,
        "source": cfg.provenance,
    });
    let mut files: Vec<PathBuf> = Vec::new();
    let default_env = default_environment();
    let env = env.unwrap_or(&default_env);
    crate::sg::env::write_latlong_exr(
        env,
        &out_dir.join("env.exr"),
        cfg.env_width,
        LatlongConvention::OpenExrUsd,
    )?;
    files.push("env.exr".into());
    env.write_json(&out_dir.join("env_sgs.json"))?;
    files.push("env_sgs.json".into());
    let mut put = |rel: &str, bytes: &[u8]| -> Result<(), DataError> {
        let p = out_dir.join(rel);
        atomic_write(&p, bytes)?;
        files.push(PathBuf::from(rel));
        Ok(())
    };
    let glb_name = format!("{}.glb", cfg.name);
    let glb = gltf::glb_bytes(
        &geo,
        &albedo_png,
        &orm_png,
        metallic,
        &material_name,
        &prim_name,
        &provenance,
    )
    .map_err(|e| DataError::new(out_dir.join(&glb_name), e))?;
    put(&glb_name, &glb)?;
    put(usd::ALBEDO, &albedo_png)?;
    put(usd::ORM, &orm_png)?;
    let thumb_usd = format!(".thumbs/256x256/{}.png", usd::ASSET);
    let payload = usd::payload_layer(&prim_name, &material_name, &geo, metallic);
    let asset = usd::asset_layer(&prim_name, env!("CARGO_PKG_VERSION"), &thumb_usd);
    put(usd::PAYLOAD, payload.as_bytes())?;
    put(usd::ASSET, asset.as_bytes())?;
    put(
        usd::LOOKDEV,
        usd::lookdev_layer(&prim_name, "env.exr").as_bytes(),
    )?;

    let thumb = thumbnail::render(&geo, &baked.albedo, n, 256);
    let thumb_png =
        image_io::encode_png8(256, 256, 4, &thumb, true).map_err(|e| DataError::new(out_dir, e))?;
    put(&format!(".thumbs/256x256/{glb_name}.png"), &thumb_png)?;
    put(&thumb_usd, &thumb_png)?;
    if cfg.usdz {
        let usdz_name = format!("{}.usdz", cfg.name);
        let bytes = usdz::usdz_bytes(&[
            usdz::Entry {
                name: usd::ASSET,
                data: asset.as_bytes(),
            },
            usdz::Entry {
                name: usd::PAYLOAD,
                data: payload.as_bytes(),
            },
            usdz::Entry {
                name: usd::ALBEDO,
                data: &albedo_png,
            },
            usdz::Entry {
                name: usd::ORM,
                data: &orm_png,
            },
            usdz::Entry {
                name: &thumb_usd,
                data: &thumb_png,
            },
        ])
        .map_err(|e| DataError::new(out_dir.join(&usdz_name), e))?;
        put(&usdz_name, &bytes)?;
    }
    let seconds_write = t.elapsed().as_secs_f64();

    let mut report = ExportReport {
        name: cfg.name.clone(),
        sdf: sdf.name(),
        material: material.name(),
        backend: backend.describe(),
        mesh: built.stats,
        uv_charts: uvm.charts,
        uv_utilization: uvm.utilization,
        texture_size,
        texture_size_reason: reason,
        bake: baked.stats,
        origin_shift_m: shift,
        bounds_m: geo.bounds(),
        files: files.clone(),
        seconds_unwrap,
        seconds_write,
        seconds_total: t_total.elapsed().as_secs_f64(),
        config: cfg.clone(),
        geometry: AssetGeometry::default(),
    };
    report.files.push("export_report.json".into());
    let text = serde_json::to_string_pretty(&report)
        .map_err(|e| DataError::new(out_dir, e.to_string()))?;
    atomic_write(&out_dir.join("export_report.json"), text.as_bytes())?;
    report.geometry = geo;
    Ok(report)
}
