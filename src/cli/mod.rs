//! The command line: clap definitions, global options, logging, exit codes.
//! Each subcommand's arguments and `run` live in the module that owns the work
//! (`scene::cli`, `sg::cli`, `export::cli`, ...); this file only wires them.

use std::process::ExitCode;

use clap::{CommandFactory, Parser, Subcommand};

use crate::backend::BackendChoice;
pub use crate::context::Context;

pub mod devices;

#[derive(Debug, Parser)]
#[command(name = "pii-bake", version, about = "Posed photos -> relightable production asset (glTF, USD, HDR environment)")]
pub struct Cli {
    #[command(flatten)]
    pub global: GlobalArgs,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, clap::Args)]
pub struct GlobalArgs {
    /// Compute backend: auto (a real GPU if present, else cpu), cpu, or wgpu (any adapter, lavapipe included).
    #[arg(long, global = true, value_enum, default_value_t = BackendChoice::Auto, env = "PII_BACKEND")]
    pub backend: BackendChoice,
    /// Force a GPU adapter by index or name substring (see `pii-bake devices`).
    #[arg(long, global = true, env = "PII_ADAPTER")]
    pub adapter: Option<String>,
    /// Write JSON Lines (objects with a `type` field) to stdout for pipelines.
    #[arg(long, global = true)]
    pub json: bool,
    /// More log output (-v info, -vv debug, -vvv trace). RUST_LOG overrides.
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
    /// Only errors on stderr.
    #[arg(short, long, global = true)]
    pub quiet: bool,
    /// Time every wgpu kernel with GPU timestamps; training reports then list each kernel's launches
    /// and GPU time per step (`gpu_kernels_per_step`). A diagnosis: each launch gets its own pass
    /// and each submission waits, so the run is slower than unprofiled.
    #[arg(long, global = true)]
    pub profile_kernels: bool,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// List GPU adapters and the backend `auto` would pick.
    Devices,
    /// Read a scene and print what was found (format, views, intrinsics, normalisation).
    Info(crate::scene::cli::InfoArgs),
    /// Metrics against ground truth (PSNR/SSIM, albedo, roughness, environment, Chamfer).
    Eval(crate::eval::cli::EvalArgs),
    /// Fit K spherical Gaussians to an HDR latlong environment map.
    FitEnv(crate::sg::cli::FitEnvArgs),
    /// Photos → asset (.glb/.usda/.exr): trains stage 1 (geometry) and stage 2 (light, material,
    /// indirect light) and exports them; `--preset preview` ships the visual hull without training.
    Bake(crate::train::preview::BakeArgs),
    /// Train a stage of the inverse-rendering model into a run folder (checkpoints, resume).
    Train(crate::train::cli::TrainArgs),
    /// Render a trained run under other HDR environments from a scene's test cameras (for `eval`).
    Relight(crate::train::relight::RelightArgs),
    /// Export an asset (mesh, UVs, baked textures, glTF/USD/EXR) from a trained run or an analytic field.
    Export(crate::export::cli::ExportArgs),
    /// Benchmarks: write figures (JSON/CSV) and charts.
    #[command(subcommand)]
    Bench(BenchCommand),
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Neural-field throughput (points/s) per backend.
    Nn(crate::nn::bench::BenchNnArgs),
    /// Environment SG fitting: lobes vs error vs time, with a chart.
    Env(crate::sg::bench::BenchEnvArgs),
    /// The SG BRDF forms against Cycles' Principled BSDF on a sphere (needs Python with bpy), with a chart.
    Brdf(crate::sg::bench_brdf::BenchBrdfArgs),
    /// Stage-1 training: Chamfer against wall time per variant (preset × tracing × init), with a chart.
    Train(crate::train::bench::BenchTrainArgs),
    /// Stage-2 training on a stage-1 run: accuracy against wall time per variant (lobes × indirect), with a chart.
    Material(crate::train::bench_material::BenchMaterialArgs),
    /// Asset back end timings (grid, marching cubes, simplify, unwrap, bake).
    Export(crate::export::bench::BenchExportArgs),
}

fn init_logging(g: &GlobalArgs) {
    let default = if g.quiet {
        "error"
    } else {
        match g.verbose {
            0 => "warn",
            1 => "info",
            2 => "debug",
            _ => "trace",
        }
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    // Colour only on a terminal: a pipeline's log file gets plain text, not escape codes.
    use std::io::IsTerminal;
    let ansi = std::io::stderr().is_terminal();
    let _ = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(ansi).with_target(false).try_init();
}

impl Cli {
    /// A combination of flags that clap's declarations cannot refuse (see each command's
    /// `usage_problem`).
    fn usage_problem(&self) -> Option<String> {
        match &self.command {
            Command::Train(a) => a.usage_problem(),
            _ => None,
        }
    }
}

/// Exit code for data/runtime errors. Usage errors exit with clap's 2.
pub const EXIT_DATA: u8 = 1;
pub const EXIT_USAGE: u8 = 2;

/// Run the CLI: parse, dispatch, print the error chain once, map it to an exit code.
pub fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() { ExitCode::from(EXIT_USAGE) } else { ExitCode::SUCCESS };
        }
    };
    if let Some(problem) = cli.usage_problem() {
        let _ = Cli::command().error(clap::error::ErrorKind::ArgumentConflict, problem).print();
        return ExitCode::from(EXIT_USAGE);
    }
    init_logging(&cli.global);
    crate::util::keep_freed_memory();
    // Mesa's Vulkan drivers print "error: XDG_RUNTIME_DIR is invalid or not set" to stderr while
    // wgpu probes adapters on a headless machine; the variable only locates display sockets,
    // which we never open. Give this process a harmless value rather than alarm the user.
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        std::env::set_var("XDG_RUNTIME_DIR", std::env::temp_dir());
    }
    let g = &cli.global;
    let ctx = Context { backend_choice: g.backend, adapter: g.adapter.clone(), json: g.json, quiet: g.quiet, profile_kernels: g.profile_kernels };
    match run(&cli.command, &ctx) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let chain: Vec<String> = e.chain().map(|c| c.to_string()).collect();
            eprintln!("error: {}", chain.join(": "));
            ExitCode::from(EXIT_DATA)
        }
    }
}

pub fn run(cmd: &Command, ctx: &Context) -> anyhow::Result<()> {
    match cmd {
        Command::Devices => devices::run(ctx),
        Command::Info(a) => crate::scene::cli::run(a, ctx).and_then(|scene| crate::train::cli::info_coverage(&scene, ctx)),
        Command::Eval(a) => crate::eval::cli::run(a, ctx),
        Command::FitEnv(a) => crate::sg::cli::run(a, ctx),
        Command::Bake(a) => crate::train::preview::run(a, ctx),
        Command::Train(a) => crate::train::cli::run(a, ctx),
        Command::Export(a) => crate::export::cli::run(a, ctx),
        Command::Relight(a) => crate::train::relight::run(a, ctx),
        Command::Bench(BenchCommand::Nn(a)) => crate::nn::bench::run(a, ctx),
        Command::Bench(BenchCommand::Env(a)) => crate::sg::bench::run(a, ctx),
        Command::Bench(BenchCommand::Brdf(a)) => crate::sg::bench_brdf::run(a, ctx),
        Command::Bench(BenchCommand::Export(a)) => crate::export::bench::run(a, ctx),
        Command::Bench(BenchCommand::Train(a)) => crate::train::bench::run(a, ctx),
        Command::Bench(BenchCommand::Material(a)) => crate::train::bench_material::run(a, ctx),
    }
}
