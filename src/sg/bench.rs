//! The `bench env` command: for every latlong .exr under a folder, fit each K of a lobe ladder
//! and record the errors of the full-res re-render (relative L2, log-space L2, energy kept,
//! diffuse-irradiance error), the fit time and the K that `fit-env --lobes auto` would choose.
//! Writes CSV + JSON atomically and two SVG charts, log-space error and irradiance error (log y)
//! against fit time, one series per map, one point per K; prints the table.

use std::path::{Path, PathBuf};

use anyhow::Context as _;

use crate::context::Context;
use crate::sg::env::{read_latlong_exr, LatlongConvention};
use crate::sg::fit::{auto_choice, fit_ladder, AutoTolerance, FitConfig, Rung, DEFAULT_IRRADIANCE_TOLERANCE, DEFAULT_TOLERANCE, LOBE_LADDER};
use crate::util::atomic_write;

/// Adam iterations per fit in the bench (fit-env's default is larger; see `FitConfig`).
pub const BENCH_ITERATIONS: usize = 200;

#[derive(Debug, clap::Args)]
pub struct BenchEnvArgs {
    /// Folder searched (recursively) for .exr maps. Default: $PII_SHARED_DATA/envmaps, else ../shared/data/envmaps.
    #[arg(long)]
    pub maps: Option<PathBuf>,
    /// Output folder for bench-env.csv, bench-env.json, bench-env.svg (log-space error vs time) and bench-env-irradiance.svg.
    #[arg(long, default_value = "bench-env")]
    pub out: PathBuf,
    /// Lobe counts, comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = LOBE_LADDER.to_vec())]
    pub lobes: Vec<usize>,
    /// Adam iterations per fit.
    #[arg(long, default_value_t = BENCH_ITERATIONS)]
    pub iterations: usize,
    /// Width of the area-averaged map the loss sees.
    #[arg(long, default_value_t = FitConfig::default().fit_width)]
    pub fit_width: usize,
    /// Tolerance `auto` uses (relative log-space L2 of the full-res re-render, see fit-env).
    #[arg(long, default_value_t = DEFAULT_TOLERANCE)]
    pub tolerance: f64,
    /// Irradiance tolerance `auto` uses (see fit-env).
    #[arg(long, default_value_t = DEFAULT_IRRADIANCE_TOLERANCE)]
    pub irradiance_tolerance: f64,
    /// Weight of the fit loss's energy term (see fit-env).
    #[arg(long, default_value_t = FitConfig::default().energy_weight)]
    pub energy_weight: f64,
    /// Latlong layout of the maps (the shipped maps are Blender's).
    #[arg(long, value_enum, default_value_t = LatlongConvention::Blender)]
    pub convention: LatlongConvention,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct BenchRow {
    pub map: String,
    pub width: usize,
    pub height: usize,
    pub lobes: usize,
    pub relative_l2: f64,
    pub relative_log_l2: f64,
    pub energy_ratio: f64,
    pub irradiance_error: f64,
    pub fit_seconds: f64,
    pub iterations: usize,
    pub backend: String,
    pub auto_lobes: usize,
}

fn default_maps() -> PathBuf {
    match std::env::var_os("PII_SHARED_DATA") {
        Some(d) => PathBuf::from(d).join("envmaps"),
        None => PathBuf::from("../shared/data/envmaps"),
    }
}

fn find_exr(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    for e in std::fs::read_dir(dir)? {
        let p = e?.path();
        if p.is_dir() {
            find_exr(&p, out)?;
        } else if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("exr")) {
            out.push(p);
        }
    }
    Ok(())
}

pub fn run(args: &BenchEnvArgs, ctx: &Context) -> anyhow::Result<()> {
    let dir = args.maps.clone().unwrap_or_else(default_maps);
    let mut files = Vec::new();
    find_exr(&dir, &mut files).with_context(|| format!("{}: cannot list maps", dir.display()))?;
    files.sort();
    if files.is_empty() {
        anyhow::bail!("{}: no .exr maps found", dir.display());
    }
    if args.lobes.is_empty() || args.lobes.contains(&0) {
        anyhow::bail!("--lobes must list positive counts");
    }
    let base = FitConfig { lobes: 0, iterations: args.iterations, fit_width: args.fit_width, energy_weight: args.energy_weight, ..FitConfig::default() };
    let tolerance = AutoTolerance { log_l2: args.tolerance, irradiance: args.irradiance_tolerance };
    crate::sg::cli::check_fit_flags(&tolerance, &base)?;
    crate::util::ensure_writable_dir(&args.out)?;
    let backend = ctx.backend()?;
    let pb = ctx.progress((files.len() * args.lobes.len()) as u64, "bench env");
    let mut rows = Vec::new();
    for f in &files {
        let name = f.strip_prefix(&dir).unwrap_or(f).with_extension("").display().to_string();
        let map = read_latlong_exr(f)?;
        let rungs: Vec<Rung> = fit_ladder(
            &backend,
            &map.rgb,
            map.width,
            map.height,
            args.convention,
            &args.lobes,
            &tolerance,
            &base,
            false,
            |_| pb.inc(1),
            |_, _| {},
        )?;
        let auto = auto_choice(&rungs).map_or(0, |r| r.lobes);
        for r in &rungs {
            let row = BenchRow {
                map: name.clone(),
                width: map.width,
                height: map.height,
                lobes: r.lobes,
                relative_l2: r.relative_l2,
                relative_log_l2: r.relative_log_l2,
                energy_ratio: r.energy_ratio,
                irradiance_error: r.irradiance_error,
                fit_seconds: r.fit_seconds,
                iterations: r.iterations,
                backend: backend.name().to_string(),
                auto_lobes: auto,
            };
            ctx.emit("bench_env", serde_json::to_value(&row)?);
            rows.push(row);
        }
    }
    pb.finish_and_clear();
    std::fs::create_dir_all(&args.out).with_context(|| format!("{}: cannot create output folder", args.out.display()))?;
    let csv = args.out.join("bench-env.csv");
    let json = args.out.join("bench-env.json");
    let svg = args.out.join("bench-env.svg");
    let svg_irr = args.out.join("bench-env-irradiance.svg");
    atomic_write(&csv, to_csv(&rows).as_bytes())?;
    let doc = serde_json::json!({
        "maps": dir.display().to_string(),
        "backend": backend.describe(),
        "iterations": args.iterations,
        "fit_width": args.fit_width,
        "tolerance": args.tolerance,
        "irradiance_tolerance": args.irradiance_tolerance,
        "energy_weight": args.energy_weight,
        "convention": args.convention,
        "error": "relative_l2: solid-angle-weighted relative L2 of the full-resolution re-render; relative_log_l2: the same on log1p(radiance), which auto_lobes uses; energy_ratio: solid-angle-integrated radiance of the fit over the map's; irradiance_error: relative L2 over all normals of the diffuse irradiance (SH order 2) of the fit against the map's",
        "rows": rows,
    });
    atomic_write(&json, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    atomic_write(&svg, chart_svg(&rows, ChartMetric::LogL2)?.as_bytes())?;
    atomic_write(&svg_irr, chart_svg(&rows, ChartMetric::Irradiance)?.as_bytes())?;
    ctx.say(table(&rows));
    ctx.say(format!("wrote {}, {}, {}, {}", csv.display(), json.display(), svg.display(), svg_irr.display()));
    Ok(())
}

pub fn to_csv(rows: &[BenchRow]) -> String {
    let mut s = String::from("map,width,height,lobes,relative_l2,relative_log_l2,energy_ratio,irradiance_error,fit_seconds,iterations,backend,auto_lobes\n");
    for r in rows {
        s += &format!(
            "{},{},{},{},{:.6},{:.6},{:.4},{:.4},{:.4},{},{},{}\n",
            r.map, r.width, r.height, r.lobes, r.relative_l2, r.relative_log_l2, r.energy_ratio, r.irradiance_error, r.fit_seconds, r.iterations, r.backend, r.auto_lobes
        );
    }
    s
}

fn table(rows: &[BenchRow]) -> String {
    let mut s = format!("{:<34} {:>4} {:>10} {:>10} {:>8} {:>8} {:>8} {:>5}\n", "map", "K", "rel L2", "log L2", "energy", "irr err", "time s", "auto");
    for r in rows {
        s += &format!(
            "{:<34} {:>4} {:>10.4} {:>10.4} {:>8.3} {:>8.4} {:>8.2} {:>5}\n",
            r.map, r.lobes, r.relative_l2, r.relative_log_l2, r.energy_ratio, r.irradiance_error, r.fit_seconds, r.auto_lobes
        );
    }
    s
}

/// The error a chart plots.
#[derive(Clone, Copy, Debug)]
pub enum ChartMetric {
    /// `relative_log_l2`: how the sky looks.
    LogL2,
    /// `irradiance_error`: what a diffuse asset relit by the fit sees.
    Irradiance,
}

impl ChartMetric {
    fn of(self, r: &BenchRow) -> f64 {
        match self {
            ChartMetric::LogL2 => r.relative_log_l2,
            ChartMetric::Irradiance => r.irradiance_error,
        }
    }
    fn label(self) -> &'static str {
        match self {
            ChartMetric::LogL2 => "relative log-space L2 error",
            ChartMetric::Irradiance => "relative diffuse-irradiance error",
        }
    }
}

/// Fit error (`metric`, one of the two `auto` bounds; log y) against fit time, one series
/// per map. Plotters' SVG backend writes `<text>` elements: no system fonts are needed.
pub fn chart_svg(rows: &[BenchRow], metric: ChartMetric) -> anyhow::Result<String> {
    use plotters::prelude::*;
    let mut maps: Vec<&str> = rows.iter().map(|r| r.map.as_str()).collect();
    maps.dedup();
    let tmax = rows.iter().map(|r| r.fit_seconds).fold(0.0, f64::max).max(1e-3) * 1.05;
    let emin = rows.iter().map(|r| metric.of(r)).fold(f64::INFINITY, f64::min).max(1e-6) * 0.8;
    let emax = rows.iter().map(|r| metric.of(r)).fold(0.0, f64::max).max(emin * 2.0) * 1.25;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 600)).into_drawing_area();
        root.fill(&WHITE).map_err(|err| anyhow::anyhow!("chart: {err}"))?;
        let mut chart = ChartBuilder::on(&root)
            .caption("SG environment fit: error vs time (one point per K)", ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..tmax, (emin..emax).log_scale())
            .map_err(|err| anyhow::anyhow!("chart: {err}"))?;
        chart
            .configure_mesh()
            .x_desc("fit time (s)")
            .y_desc(metric.label())
            .y_label_formatter(&|v| format!("{v:.3}"))
            .x_label_formatter(&|v| format!("{v:.1}"))
            .draw()
            .map_err(|err| anyhow::anyhow!("chart: {err}"))?;
        for (i, m) in maps.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let pts: Vec<(f64, f64)> = rows.iter().filter(|r| r.map == *m).map(|r| (r.fit_seconds, metric.of(r))).collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), color.stroke_width(1)))
                .map_err(|err| anyhow::anyhow!("chart: {err}"))?
                .label(*m)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2)));
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, color.filled())))
                .map_err(|err| anyhow::anyhow!("chart: {err}"))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|err| anyhow::anyhow!("chart: {err}"))?;
        root.present().map_err(|err| anyhow::anyhow!("chart: {err}"))?;
    }
    Ok(svg)
}
