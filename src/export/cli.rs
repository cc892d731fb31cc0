//! The `export` command: a test-pattern asset from an analytic field, through the same
//! [`super::export_asset`] the trained model uses.

use std::path::PathBuf;

use crate::cli::Context;
use crate::mesh::field::{AnalyticMaterial, AnalyticSdf, AnalyticShape};
use crate::mesh::MeshConfig;

use super::{ExportConfig, TextureSize};

#[derive(Debug, clap::Args)]
pub struct ExportArgs {
    /// Analytic shape to export (a test-pattern asset for checking an import chain).
    #[arg(long, value_enum)]
    pub analytic: AnalyticShape,
    /// Analytic material pattern.
    #[arg(long, value_enum, default_value_t = AnalyticMaterial::Checker)]
    pub material: AnalyticMaterial,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Grid nodes along the longest side of the box.
    #[arg(long, default_value_t = 256)]
    pub resolution: usize,
    /// Simplification error bound in scene units (default: half a grid cell).
    #[arg(long)]
    pub error_bound: Option<f32>,
    /// Texture size: `auto` (from surface area and pattern detail) or a power of two.
    #[arg(long, default_value = "auto")]
    pub texture: TextureSize,
    /// Also write a .usdz package.
    #[arg(long)]
    pub usdz: bool,
    /// Asset name ([a-z][a-z0-9_-]*); default: the shape's name.
    #[arg(long)]
    pub name: Option<String>,
    /// Metres per scene unit.
    #[arg(long, default_value_t = 1.0)]
    pub metres_per_unit: f32,
    /// Environment SG JSON to ship with the asset (default: a neutral test environment).
    #[arg(long)]
    pub env_json: Option<PathBuf>,
}

pub fn run(args: &ExportArgs, ctx: &Context) -> anyhow::Result<()> {
    let backend = ctx.backend()?;
    let env = match &args.env_json {
        Some(p) => Some(crate::sg::env::EnvSgs::read_json(p)?),
        None => None,
    };
    let cfg = ExportConfig {
        name: args
            .name
            .clone()
            .unwrap_or_else(|| args.analytic.name().to_string()),
        mesh: MeshConfig {
            resolution: args.resolution,
            error_bound: args.error_bound,
            ..Default::default()
        },
        texture: args.texture,
        metres_per_unit: args.metres_per_unit,
        usdz: args.usdz,
        provenance: serde_json::json!({ "analytic": args.analytic.name(), "material": args.material.name() }),
        ..Default::default()
    };
    let sdf = AnalyticSdf::new(args.analytic);
    let report = super::export_asset(
        &backend,
        &sdf,
        &args.material,
        env.as_ref(),
        &cfg,
        &args.out,
    )?;
    ctx.emit("export", serde_json::to_value(&report)?);
    ctx.say(format!(
        "wrote {} to {}: {} triangles (bound {:.4} scene units), {} charts, {}² textures, {:.2} s",
        report.name,
        args.out.display(),
        report.mesh.triangles,
        report.mesh.error_bound,
        report.uv_charts,
        report.texture_size,
        report.seconds_total
    ));
    Ok(())
}
