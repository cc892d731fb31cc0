//! The `bench export` command: per-stage timings of the asset back end (grid evaluation,
//! extraction, cleanup, simplification, unwrap, bake, writers) at several grid resolutions and
//! texture sizes, plus the whole `export_asset` at the largest grid. Writes JSON.

use std::path::PathBuf;
use std::time::Instant;

use crate::context::Context;
use crate::mesh::field::{AnalyticMaterial, AnalyticSdf, AnalyticShape};
use crate::mesh::{self, MeshConfig};

use super::{export_asset, ExportConfig, TextureSize};

#[derive(Debug, clap::Args)]
pub struct BenchExportArgs {
    /// Write the figures here (JSON); default: print them.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Grid resolutions (nodes along the longest side).
    #[arg(long, value_delimiter = ',', default_values_t = [256usize, 512])]
    pub resolutions: Vec<usize>,
    /// Texture sizes.
    #[arg(long, value_delimiter = ',', default_values_t = [1024u32, 2048])]
    pub textures: Vec<u32>,
    /// Shape to mesh.
    #[arg(long, value_enum, default_value_t = AnalyticShape::Torus)]
    pub shape: AnalyticShape,
    /// Skip the whole-pipeline `export_asset` run at the largest grid.
    #[arg(long)]
    pub no_end_to_end: bool,
}

pub fn run(args: &BenchExportArgs, ctx: &Context) -> anyhow::Result<()> {
    if let Some(out) = &args.out {
        crate::util::ensure_writable_parent(out)?;
    }
    let backend = ctx.backend()?;
    let sdf = AnalyticSdf::new(args.shape);
    let material = AnalyticMaterial::Checker;
    let mut rows = Vec::new();
    for &res in &args.resolutions {
        let built = mesh::build_mesh(
            &backend,
            &sdf,
            &MeshConfig {
                resolution: res,
                error_bound: None,
                ..Default::default()
            },
        )?;
        let st = &built.stats;
        ctx.say(format!(
            "{res}^3: grid {:.3} s, extract {:.3} s ({} tris), cleanup {:.3} s, simplify {:.3} s ({} tris)",
            st.seconds_grid, st.seconds_extract, st.extracted_triangles, st.seconds_cleanup, st.seconds_simplify, st.triangles
        ));
        for &tex in &args.textures {
            let t = Instant::now();
            let uvm = mesh::uv::unwrap(&built.mesh, &built.normals, tex, (tex / 128).max(2))?;
            let unwrap_s = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let baked = crate::bake::bake(&backend, &sdf, &material, &uvm, tex as usize)?;
            let bake_s = t.elapsed().as_secs_f64();
            ctx.say(format!(
                "  {tex}^2: unwrap {unwrap_s:.3} s ({} charts), bake {bake_s:.3} s (raster {:.3}, fields {:.3}, dilate {:.3})",
                uvm.charts, baked.stats.seconds_raster, baked.stats.seconds_fields, baked.stats.seconds_dilate
            ));
            rows.push(serde_json::json!({
                "resolution": res,
                "texture": tex,
                "grid_s": st.seconds_grid,
                "extract_s": st.seconds_extract,
                "cleanup_s": st.seconds_cleanup,
                "simplify_s": st.seconds_simplify,
                "extracted_triangles": st.extracted_triangles,
                "triangles": st.triangles,
                "error_bound": st.error_bound,
                "measured_deviation": st.measured_deviation,
                "unwrap_s": unwrap_s,
                "charts": uvm.charts,
                "bake_s": bake_s,
                "bake_raster_s": baked.stats.seconds_raster,
                "bake_fields_s": baked.stats.seconds_fields,
                "bake_dilate_s": baked.stats.seconds_dilate,
            }));
        }
    }
    let mut end_to_end = serde_json::Value::Null;
    if let (false, Some(&res)) = (args.no_end_to_end, args.resolutions.iter().max()) {
        let dir = tempfile_dir()?;
        let cfg = ExportConfig {
            name: "bench".into(),
            mesh: MeshConfig {
                resolution: res,
                error_bound: None,
                ..Default::default()
            },
            texture: TextureSize::Fixed(args.textures.iter().copied().min().unwrap_or(1024)),
            ..Default::default()
        };
        let t = Instant::now();
        let report = export_asset(&backend, &sdf, &material, None, &cfg, &dir)?;
        let total = t.elapsed().as_secs_f64();
        ctx.say(format!(
            "export_asset at {res}^3, {}^2: {total:.2} s to a written .glb + USD",
            report.texture_size
        ));
        end_to_end = serde_json::json!({ "resolution": res, "texture": report.texture_size, "seconds": total });
        let _ = std::fs::remove_dir_all(&dir);
    }
    let doc = serde_json::json!({
        "bench": "export",
        "backend": backend.describe(),
        "shape": args.shape.name(),
        "material": material.name(),
        "threads": rayon::current_num_threads(),
        "release_build": !cfg!(debug_assertions),
        "rows": rows,
        "end_to_end": end_to_end,
    });
    let text = serde_json::to_string_pretty(&doc)?;
    match &args.out {
        Some(p) => crate::util::atomic_write(p, text.as_bytes())?,
        None => println!("{text}"),
    }
    ctx.emit("bench_export", doc);
    Ok(())
}

fn tempfile_dir() -> anyhow::Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("pii-bake-bench-export-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}
