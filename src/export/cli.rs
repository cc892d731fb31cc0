//! The `export` command: a test-pattern asset from an analytic field, through the same
//! [`super::export_asset`] the trained model uses.

use std::path::PathBuf;

use crate::context::Context;
use crate::mesh::field::{AnalyticMaterial, AnalyticSdf, AnalyticShape};
use crate::mesh::MeshConfig;

use super::{AssetArgs, ExportConfig};

#[derive(Debug, clap::Args)]
#[command(group(clap::ArgGroup::new("source").required(true).args(["analytic", "run"])))]
pub struct ExportArgs {
    /// A trained run folder (`pii-bake train ... --out <run-dir>`): mesh the SDF, textures from
    /// the radiance net (a radiance preview: lighting not removed).
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// Analytic shape to export (a test-pattern asset for checking an import chain).
    #[arg(long, value_enum)]
    pub analytic: Option<AnalyticShape>,
    /// Analytic material pattern.
    #[arg(long, value_enum, default_value_t = AnalyticMaterial::Checker)]
    pub material: AnalyticMaterial,
    #[command(flatten)]
    pub asset: AssetArgs,
    /// Environment SG JSON to ship with an analytic asset (default: a neutral test environment).
    #[arg(long)]
    pub env_json: Option<PathBuf>,
}

pub fn run(args: &ExportArgs, ctx: &Context) -> anyhow::Result<()> {
    if let Some(run_dir) = &args.run {
        let report = crate::train::cli::export_run(run_dir, &args.asset, ctx)?;
        ctx.emit("export", serde_json::to_value(&report)?);
        return Ok(());
    }
    let Some(analytic) = args.analytic else {
        anyhow::bail!("give --run <run-dir> or --analytic <shape>");
    };
    crate::export::check_writable(&args.asset.out)?;
    let backend = ctx.backend()?;
    let env = match &args.env_json {
        Some(p) => Some(crate::sg::env::EnvSgs::read_json(p)?),
        None => None,
    };
    let cfg = ExportConfig {
        name: args
            .asset
            .name
            .clone()
            .unwrap_or_else(|| analytic.name().to_string()),
        mesh: MeshConfig {
            resolution: args.asset.resolution.unwrap_or(256),
            error_bound: args.asset.error_bound,
            face_tolerance_deg: args.asset.face_tolerance_deg(),
            ..Default::default()
        },
        texture: args.asset.texture,
        metres_per_unit: args.asset.metres_per_unit.unwrap_or(1.0) as f32,
        height_m: args.asset.height.map(|h| h as f32),
        usdz: args.asset.usdz,
        provenance: serde_json::json!({ "analytic": analytic.name(), "material": args.material.name() }),
        ..Default::default()
    };
    let sdf = AnalyticSdf::new(analytic);
    let report = super::export_asset_with(
        &backend,
        &sdf,
        &args.material,
        env.as_ref(),
        &cfg,
        &args.asset.out,
        &ctx.spinner("export"),
    )?;
    ctx.emit("export", serde_json::to_value(&report)?);
    ctx.say(format!(
        "wrote {} to {}: {} triangles (bound {:.4} scene units), {} charts, {}² textures, {:.2} s",
        report.name,
        args.asset.out.display(),
        report.mesh.triangles,
        report.mesh.error_bound,
        report.uv_charts,
        report.texture_size,
        report.seconds_total
    ));
    Ok(())
}
