//! The `fit-env` command: fit K spherical Gaussians to an HDR latlong EXR and write the SGs
//! (JSON), their re-render (EXR, input resolution and convention), a comparison PNG and a report.

use std::path::{Path, PathBuf};

use anyhow::Context as _;

use crate::context::Context;
use crate::sg::env::{read_latlong_exr, render_latlong, write_latlong_exr, LatlongConvention};
use crate::sg::fit::{auto_choice, fit_ladder, AutoTolerance, FitConfig, FitTarget, Rung, DEFAULT_IRRADIANCE_TOLERANCE, DEFAULT_TOLERANCE, LOBE_LADDER};
use crate::util::atomic_write;

#[derive(Debug, clap::Args)]
pub struct FitEnvArgs {
    /// Latlong HDR environment map (.exr, 2:1).
    pub map: PathBuf,
    /// Lobe count, or `auto`: the smallest of 8, 16, 32, 64, 128 whose relative log-space error is within --tolerance and whose diffuse-irradiance error is within --irradiance-tolerance.
    #[arg(long, default_value = "auto")]
    pub lobes: String,
    /// `--lobes auto` tolerance on the solid-angle-weighted relative L2 error of log1p(radiance) of the full-res re-render (relative_log_l2).
    #[arg(long, default_value_t = DEFAULT_TOLERANCE)]
    pub tolerance: f64,
    /// `--lobes auto` tolerance on the relative L2 error, over all normals, of the diffuse irradiance the fit casts (irradiance_error).
    #[arg(long, default_value_t = DEFAULT_IRRADIANCE_TOLERANCE)]
    pub irradiance_tolerance: f64,
    /// Adam iterations per fit.
    #[arg(long, default_value_t = FitConfig::default().iterations)]
    pub iterations: usize,
    /// Adam base learning rate (decays to 10% over the run).
    #[arg(long, default_value_t = FitConfig::default().lr)]
    pub lr: f32,
    /// Width of the area-averaged map the loss sees (height = width / 2).
    #[arg(long, default_value_t = FitConfig::default().fit_width)]
    pub fit_width: usize,
    /// Weight of the loss's energy term (keeps the map's mean radiance; 0 turns it off).
    #[arg(long, default_value_t = FitConfig::default().energy_weight)]
    pub energy_weight: f64,
    /// Seed of the λ initialisation.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Latlong layout of the input (and of the written re-render).
    #[arg(long, value_enum, default_value_t = LatlongConvention::OpenExrUsd)]
    pub convention: LatlongConvention,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
}

/// Parse `--lobes`: `auto` → the ladder, else one positive count.
pub fn parse_lobes(s: &str) -> anyhow::Result<Option<usize>> {
    if s.eq_ignore_ascii_case("auto") {
        return Ok(None);
    }
    match s.parse::<usize>() {
        Ok(k) if k > 0 => Ok(Some(k)),
        _ => anyhow::bail!("--lobes must be a positive integer or `auto`, got `{s}`"),
    }
}

/// The numeric flags `fit-env` and `bench env` share, checked before any work.
pub fn check_fit_flags(tolerance: &AutoTolerance, cfg: &FitConfig) -> anyhow::Result<()> {
    for (flag, v) in [("--tolerance", tolerance.log_l2), ("--irradiance-tolerance", tolerance.irradiance)] {
        if !(v.is_finite() && v > 0.0) {
            anyhow::bail!("{flag} must be > 0, got {v}");
        }
    }
    if !(cfg.energy_weight.is_finite() && cfg.energy_weight >= 0.0) {
        anyhow::bail!("--energy-weight must be >= 0, got {}", cfg.energy_weight);
    }
    if cfg.iterations == 0 || cfg.fit_width < 4 {
        anyhow::bail!("--iterations must be > 0 and --fit-width >= 4");
    }
    Ok(())
}

pub fn run(args: &FitEnvArgs, ctx: &Context) -> anyhow::Result<()> {
    let fixed = parse_lobes(&args.lobes)?;
    let tolerance = AutoTolerance { log_l2: args.tolerance, irradiance: args.irradiance_tolerance };
    let base = FitConfig { lobes: 0, iterations: args.iterations, lr: args.lr, seed: args.seed, fit_width: args.fit_width, energy_weight: args.energy_weight };
    check_fit_flags(&tolerance, &base)?;
    crate::util::ensure_writable_dir(&args.out)?;
    let map = read_latlong_exr(&args.map)?;
    if map.clamped_negatives > 0 {
        tracing::warn!("{}: clamped {} negative values (min {}) to 0", args.map.display(), map.clamped_negatives, map.min_value);
    }
    let backend = ctx.backend()?;
    let ladder: Vec<usize> = match fixed {
        Some(k) => vec![k],
        None => LOBE_LADDER.to_vec(),
    };
    ctx.say(format!(
        "fit-env: {} ({}x{}, {:?}) on {}, lobes {}",
        args.map.display(),
        map.width,
        map.height,
        args.convention,
        backend.describe(),
        args.lobes
    ));
    let mut pb = None::<(usize, indicatif::ProgressBar)>;
    let rungs = fit_ladder(
        &backend,
        &map.rgb,
        map.width,
        map.height,
        args.convention,
        &ladder,
        &tolerance,
        &base,
        fixed.is_none(),
        |r| {
            ctx.emit("rung", serde_json::to_value(r).unwrap_or_default());
            ctx.say(format!(
                "  K = {:>3}: relative L2 {:.4}, log L2 {:.4}, irradiance {:.4}, energy {:.3}, {:.2} s{}",
                r.lobes,
                r.relative_l2,
                r.relative_log_l2,
                r.irradiance_error,
                r.energy_ratio,
                r.fit_seconds,
                if r.within_tolerance { " (within tolerance)" } else { "" }
            ));
        },
        |k, i| {
            if pb.as_ref().is_none_or(|(pk, _)| *pk != k) {
                if let Some((_, p)) = pb.take() {
                    p.finish_and_clear();
                }
                pb = Some((k, ctx.progress(args.iterations as u64, &format!("K={k}"))));
            }
            if let Some((_, p)) = &pb {
                p.set_position(i as u64 + 1);
            }
        },
    )?;
    if let Some((_, p)) = pb.take() {
        p.finish_and_clear();
    }
    let chosen = match fixed {
        Some(_) => rungs.last(),
        None => auto_choice(&rungs),
    }
    .context("no fit was run")?;
    write_outputs(args, &map.rgb, map.width, map.height, chosen, &rungs, backend.name(), ctx)
}

#[allow(clippy::too_many_arguments)]
fn write_outputs(
    args: &FitEnvArgs,
    rgb: &[f32],
    width: usize,
    height: usize,
    chosen: &Rung,
    rungs: &[Rung],
    backend: &str,
    ctx: &Context,
) -> anyhow::Result<()> {
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create output folder", out.display()))?;
    let sg_json = out.join("env_sg.json");
    let exr = out.join("env_fit.exr");
    let png = out.join("env_compare.png");
    let report = out.join("fit_report.json");
    // All or nothing: if one output cannot be written, the ones this run wrote are removed.
    let written = (|| -> anyhow::Result<()> {
        chosen.env.write_json(&sg_json)?;
        write_latlong_exr(&chosen.env, &exr, width, args.convention)?;
        write_comparison_png(&png, rgb, width, height, chosen, args.convention)
    })();
    if let Err(e) = written {
        for p in [&sg_json, &exr, &png] {
            let _ = std::fs::remove_file(p);
        }
        return Err(e);
    }
    let auto_ok = rungs.iter().any(|r| r.within_tolerance);
    let doc = serde_json::json!({
        "map": args.map.display().to_string(),
        "width": width,
        "height": height,
        "convention": args.convention,
        "backend": backend,
        "lobes_arg": args.lobes,
        "lobes": chosen.lobes,
        "tolerance": args.tolerance,
        "irradiance_tolerance": args.irradiance_tolerance,
        "tolerance_on": "relative_log_l2 <= tolerance and irradiance_error <= irradiance_tolerance",
        "tolerance_met": chosen.within_tolerance,
        "auto_note": if parse_lobes(&args.lobes).ok().flatten().is_none() && !auto_ok {
            "no rung met the tolerance: the largest K was kept"
        } else { "" },
        "relative_l2": chosen.relative_l2,
        "relative_log_l2": chosen.relative_log_l2,
        "energy_ratio": chosen.energy_ratio,
        "irradiance_error": chosen.irradiance_error,
        "iterations": chosen.iterations,
        "fit_seconds": chosen.fit_seconds,
        "total_seconds": rungs.iter().map(|r| r.fit_seconds).sum::<f64>(),
        "loss": "solid-angle-weighted L2 of log1p(radiance), per channel, on the area-averaged map, + energy_weight * squared log ratio of the fit's mean radiance (closed form) to the map's",
        "energy_weight": args.energy_weight,
        "fit_width": args.fit_width,
        "lr": args.lr,
        "seed": args.seed,
        "rungs": rungs,
        "outputs": { "sg_json": sg_json, "exr": exr, "png": png },
    });
    atomic_write(&report, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    ctx.emit("fit_env", doc);
    ctx.say(format!(
        "chose K = {} (relative L2 {:.4}, log L2 {:.4}, irradiance {:.4}, energy kept {:.3}{}); wrote {}, {}, {}, {}",
        chosen.lobes,
        chosen.relative_l2,
        chosen.relative_log_l2,
        chosen.irradiance_error,
        chosen.energy_ratio,
        if chosen.within_tolerance { "" } else { ", tolerance not met" },
        sg_json.display(),
        exr.display(),
        png.display(),
        report.display()
    ));
    Ok(())
}

/// Reinhard x/(1+x) then sRGB happens in the PNG encoder.
fn tonemap(v: f32) -> f32 {
    let v = v.max(0.0);
    v / (1.0 + v)
}

/// input | fit | error side by side at 256×128 each (error = |log1p fit − log1p input|, grey).
fn write_comparison_png(path: &Path, rgb: &[f32], width: usize, height: usize, chosen: &Rung, conv: LatlongConvention) -> anyhow::Result<()> {
    let pw = 256.min(width);
    let small = FitTarget::from_map(rgb, width, height, conv, pw);
    let (pw, ph) = (small.width, small.height);
    let fit = render_latlong(&chosen.env, pw, ph, conv);
    let mut img = vec![0.0f32; 3 * pw * ph * 3];
    for y in 0..ph {
        for x in 0..pw {
            let i = (y * pw + x) * 3;
            let row = y * 3 * pw;
            for c in 0..3 {
                let (t, f) = (small.rgb[i + c].max(0.0), fit[i + c].max(0.0));
                img[(row + x) * 3 + c] = tonemap(t);
                img[(row + pw + x) * 3 + c] = tonemap(f);
            }
            let e = (0..3).map(|c| (fit[i + c].max(0.0).ln_1p() - small.rgb[i + c].max(0.0).ln_1p()).abs()).sum::<f32>() / 3.0;
            for c in 0..3 {
                img[(row + 2 * pw + x) * 3 + c] = e.min(1.0);
            }
        }
    }
    crate::image_io::write_png8(path, 3 * pw, ph, 3, &img, true)?;
    Ok(())
}
