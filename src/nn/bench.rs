//! The `bench nn` command: MLP throughput (points/s, GFLOP/s) for the paper's SDF network and the
//! fast network, forward and forward+backward, on each available backend, with the wgpu/cpu
//! ratio and the cpu MLP's GFLOP/s against a plain GEMM reference measured in the same run.
//! Prints a table and writes JSON atomically.
//!
//! What is timed: the whole field per point — `Backend::encoding_forward` (frequency PE or hash
//! grid) and `Backend::mlp_forward`, plus for forward+backward `mlp_backward` and the encoding's
//! parameter backward (the hash table scatter) — with parameters and inputs resident on the
//! backend. GFLOP/s figures count the MLP's FLOPs only (the encodings are memory-bound).
//!
//! On wgpu it also measures what a launch costs beyond its kernel: the host's CPU time per
//! queued launch of a one-workgroup kernel (the calling thread's CPU time, so a software
//! adapter's own threads are not counted) and a readback's round trip. A training step's
//! overhead is about its launches times the first plus its waits times the second (the
//! training reports count both, `gpu_per_step`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use rayon::prelude::*;

use crate::backend::{Backend, BackendChoice};
use crate::context::Context;
use crate::nn::encoding::EncodingConfig;
use crate::nn::field::SdfFieldConfig;
use crate::nn::mlp::{Init, Mlp, Real};
use crate::util::thread_cpu_seconds;

#[derive(Debug, clap::Args)]
pub struct BenchNnArgs {
    /// Batch sizes (points), comma separated.
    #[arg(long, value_delimiter = ',', default_values_t = vec![1usize << 16, 1 << 17, 1 << 18])]
    pub batches: Vec<usize>,
    /// Timed repetitions per measurement (after a one-sub-batch warm-up); the best is reported.
    #[arg(long, default_value_t = 2)]
    pub iters: usize,
    /// JSON output path.
    #[arg(long, default_value = "bench-nn.json")]
    pub out: PathBuf,
    /// Networks to run: paper, fast.
    #[arg(long, value_delimiter = ',', default_values_t = vec!["paper".to_string(), "fast".to_string()])]
    pub networks: Vec<String>,
    /// The cpu backend runs a batch in sub-batches of this many points (bounds the memory kept
    /// for the backward; a trainer would do the same).
    #[arg(long, default_value_t = 8192)]
    pub cpu_sub_batch: usize,
    /// Rows of the GEMM reference (`[rows, 512]·[512, 512]`).
    #[arg(long, default_value_t = 16384)]
    pub gemm_rows: usize,
    /// Largest batch run on a software adapter (lavapipe); larger ones are skipped.
    #[arg(long, default_value_t = 4096)]
    pub software_max_batch: usize,
    /// Launches per timed round of the launch-overhead measurement (wgpu only).
    #[arg(long, default_value_t = 3000)]
    pub launches: usize,
}

/// What a launch and a readback cost on the host, beyond the kernels (see the module doc).
#[derive(Debug, Clone, serde::Serialize)]
struct LaunchCost {
    device: String,
    launches: usize,
    /// CPU time of the launching thread per queued launch (wall time where the platform has no
    /// per-thread CPU clock), best round.
    host_us_per_launch: f64,
    host_clock: &'static str,
    /// Wall time per launch while recording (includes a software adapter's threads competing).
    wall_us_per_launch: f64,
    /// One launch, then a 4-byte readback, waited for: the best of the rounds.
    round_trip_us: f64,
}

fn launch_cost(g: &crate::backend::GpuContext, device: String, launches: usize, iters: usize) -> anyhow::Result<LaunchCost> {
    use crate::backend::gpu::util_kernels::axpy;
    let n = launches.max(1);
    let (x, y) = (g.upload_f32("bench.x", &[1.0; 64]), g.zeros_f32("bench.y", 64));
    for _ in 0..64 {
        axpy(g, 1.0, &x, &y)?;
    }
    g.read_f32(&y)?;
    let (mut host, mut wall, mut trip) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    let clock = if thread_cpu_seconds().is_some() { "thread CPU time" } else { "wall time" };
    for _ in 0..iters.max(3) {
        let (t, c) = (Instant::now(), thread_cpu_seconds());
        for _ in 0..n {
            axpy(g, 1.0, &x, &y)?;
        }
        let w = t.elapsed().as_secs_f64();
        let c = match (c, thread_cpu_seconds()) {
            (Some(a), Some(b)) => b - a,
            _ => w,
        };
        g.read_f32(&y)?;
        host = host.min(c / n as f64);
        wall = wall.min(w / n as f64);
        let t = Instant::now();
        axpy(g, 1.0, &x, &y)?;
        g.read_f32(&y)?;
        trip = trip.min(t.elapsed().as_secs_f64());
    }
    let v = g.read_f32(&y)?;
    let want = (64 + iters.max(3) * (n + 1)) as f32;
    if v[0] != want {
        anyhow::bail!("launch benchmark: y = {} after the launches, expected {want}", v[0]);
    }
    Ok(LaunchCost {
        device,
        launches: n,
        host_us_per_launch: host * 1e6,
        host_clock: clock,
        wall_us_per_launch: wall * 1e6,
        round_trip_us: trip * 1e6,
    })
}

#[derive(Debug, Clone, serde::Serialize)]
struct Row {
    network: String,
    backend: String,
    device: String,
    batch: usize,
    forward_points_per_s: f64,
    forward_gflops: f64,
    forward_backward_points_per_s: f64,
    forward_backward_gflops: f64,
}

/// The cpu hash grid's AVX2 lane code against its scalar twin, same inputs, same run.
#[derive(Debug, Clone, serde::Serialize)]
struct GridLanes {
    network: String,
    batch: usize,
    /// Scalar time over lane time (best of the rounds), per pass.
    forward_speedup: f64,
    parameter_gradient_speedup: f64,
    input_gradient_speedup: f64,
    /// Lane time per point, ns (forward, parameter gradient, input gradient).
    lane_ns_per_point: [f64; 3],
}

/// Times the three cpu hash-grid passes through the lane code and the scalar code, alternating
/// within each round, and checks they agree bit for bit. None where the lane code does not run.
fn grid_lanes(network: &str, cfg: &EncodingConfig, batch: usize, iters: usize) -> anyhow::Result<Option<GridLanes>> {
    use crate::nn::encoding as enc;
    let Some(g) = enc::hash_grid_lanes(cfg) else {
        return Ok(None);
    };
    let np = cfg.num_params();
    let mut rng = crate::util::rng(4);
    let params = uniform(&mut rng, np, 1e-2);
    let x = uniform(&mut rng, batch * 3, g.bound());
    let d_out = uniform(&mut rng, batch * cfg.out_dim(3), 1.0);
    let mut best = [[f64::INFINITY; 2]; 3];
    for _ in 0..iters.max(2) {
        let mut outs: [[Vec<f32>; 2]; 3] = Default::default();
        for (pass, o) in outs.iter_mut().enumerate() {
            for (lanes, out) in o.iter_mut().enumerate() {
                let t = Instant::now();
                *out = match (pass, lanes == 1) {
                    (0, true) => enc::hash_grid_forward_cpu(cfg, &params, &x),
                    (0, false) => enc::hash_grid_forward_scalar(&g, &params, &x),
                    (1, true) => enc::hash_grid_backward_params_cpu(cfg, &x, &d_out),
                    (1, false) => enc::hash_grid_backward_params_scalar(&g, np, &x, &d_out),
                    (_, true) => enc::hash_grid_backward_x_cpu(cfg, &params, &x, &d_out),
                    (_, false) => enc::hash_grid_backward_x_scalar(&g, &params, &x, &d_out),
                };
                best[pass][lanes] = best[pass][lanes].min(t.elapsed().as_secs_f64());
            }
        }
        for (pass, [a, b]) in outs.iter().enumerate() {
            if a.len() != b.len() || a.iter().zip(b).any(|(p, q)| p.to_bits() != q.to_bits()) {
                anyhow::bail!("{network} hash grid, batch {batch}: the lane code and the scalar code disagree in pass {pass}");
            }
        }
    }
    let speedup = |p: usize| best[p][0] / best[p][1];
    Ok(Some(GridLanes {
        network: network.into(),
        batch,
        forward_speedup: speedup(0),
        parameter_gradient_speedup: speedup(1),
        input_gradient_speedup: speedup(2),
        lane_ns_per_point: [0, 1, 2].map(|p| best[p][1] / batch as f64 * 1e9),
    }))
}

/// The cpu backend's hidden activation loops built for AVX-512 against the AVX2 build, on one
/// sub-batch's pre-activations of a network's hidden layers, same inputs, same run.
#[derive(Debug, Clone, serde::Serialize)]
struct ActivationLanes {
    network: String,
    activation: String,
    /// Values per timed call (sub-batch rows × the hidden width).
    values: usize,
    /// AVX2 time over AVX-512 time (best of the rounds): forward, backward.
    forward_speedup: f64,
    backward_speedup: f64,
    /// AVX-512 time per value, ns (forward, backward).
    ns_per_value: [f64; 2],
}

/// Times the hidden activation's forward and backward at AVX2 and at AVX-512, alternating within
/// each round, and checks that they agree bit for bit. None on a CPU without AVX-512.
fn activation_lanes(network: &str, mlp: &Mlp, rows: usize, iters: usize) -> anyhow::Result<Option<ActivationLanes>> {
    use crate::nn::simd::SimdLevel;
    if SimdLevel::detected() < SimdLevel::Avx512 {
        return Ok(None);
    }
    let act = mlp.config.activation;
    let width = mlp.config.widths.first().copied().unwrap_or(1);
    let n = rows.max(1) * width;
    let mut rng = crate::util::rng(5);
    // Pre-activations of a trained network's hidden layers: mostly within a few 1/β of 0.
    let z = uniform(&mut rng, n, 0.1);
    let dh = uniform(&mut rng, n, 1.0);
    let levels = [SimdLevel::Avx2, SimdLevel::Avx512];
    let mut best = [[f64::INFINITY; 2]; 2];
    for _ in 0..iters.max(2) * 5 {
        let mut outs: [[Vec<f32>; 2]; 2] = Default::default();
        for (i, &level) in levels.iter().enumerate() {
            let t = Instant::now();
            outs[0][i] = act.forward_slice_at(level, &z);
            best[0][i] = best[0][i].min(t.elapsed().as_secs_f64());
            let t = Instant::now();
            outs[1][i] = act.backward_slice_at(level, &z, &dh);
            best[1][i] = best[1][i].min(t.elapsed().as_secs_f64());
        }
        for (pass, [a, b]) in outs.iter().enumerate() {
            if a.iter().zip(b).any(|(p, q)| p.to_bits() != q.to_bits()) {
                anyhow::bail!("{network} activation: the AVX-512 and the AVX2 loops disagree in pass {pass}");
            }
        }
    }
    Ok(Some(ActivationLanes {
        network: network.into(),
        activation: format!("{act:?}"),
        values: n,
        forward_speedup: best[0][0] / best[0][1],
        backward_speedup: best[1][0] / best[1][1],
        ns_per_value: [0, 1].map(|p| best[p][1] / n as f64 * 1e9),
    }))
}

/// The cpu backend's Adam step over a network's hash table (sparse: a third of the gradient's
/// entries zero) built for the widest vectors this CPU has against the baseline build.
#[derive(Debug, Clone, serde::Serialize)]
struct AdamLanes {
    network: String,
    level: crate::nn::simd::SimdLevel,
    entries: usize,
    /// Baseline time over the widest level's (best of the rounds).
    speedup: f64,
    ns_per_entry: f64,
}

/// Times one Adam step over `entries` at the baseline build and at the detected level,
/// alternating, and checks the same bits. None where the CPU has no wider level.
fn adam_lanes(network: &str, entries: usize, iters: usize) -> anyhow::Result<Option<AdamLanes>> {
    use crate::nn::simd::SimdLevel;
    let level = SimdLevel::detected();
    if level == SimdLevel::Scalar || entries == 0 {
        return Ok(None);
    }
    let cfg = crate::nn::adam::AdamConfig { skip_zero_gradients: true, ..crate::nn::adam::AdamConfig::with_lr(1e-2) };
    let mut rng = crate::util::rng(6);
    let mut grads = uniform(&mut rng, entries, 1e-3);
    for g in grads.iter_mut().step_by(3) {
        *g = 0.0;
    }
    let p0 = uniform(&mut rng, entries, 1e-2);
    let mut best = [f64::INFINITY; 2];
    for _ in 0..iters.max(2) {
        let mut outs: [Vec<f32>; 2] = Default::default();
        for (i, l) in [SimdLevel::Scalar, level].into_iter().enumerate() {
            let (mut p, mut m, mut v) = (p0.clone(), vec![0.0; entries], vec![0.0; entries]);
            let t = Instant::now();
            crate::nn::adam::update_host_at(l, &cfg, &mut p, &grads, &mut m, &mut v);
            best[i] = best[i].min(t.elapsed().as_secs_f64());
            outs[i] = p;
        }
        if outs[0].iter().zip(&outs[1]).any(|(a, b)| a.to_bits() != b.to_bits()) {
            anyhow::bail!("{network} Adam: the {level:?} loop and the baseline loop disagree");
        }
    }
    Ok(Some(AdamLanes { network: network.into(), level, entries, speedup: best[0] / best[1], ns_per_entry: best[1] / entries as f64 * 1e9 }))
}

#[derive(Debug, Clone, serde::Serialize)]
struct Ratio {
    network: String,
    batch: usize,
    forward_wgpu_over_cpu: f64,
    forward_backward_wgpu_over_cpu: f64,
}

/// A benchmarked network: the field's encoding and its MLP.
struct Net {
    encoding: EncodingConfig,
    mlp: Mlp,
    note: &'static str,
}

fn network(name: &str) -> anyhow::Result<Net> {
    let (cfg, note) = match name {
        "paper" => (
            SdfFieldConfig::paper(),
            "PE 6 freqs (39-d input), 8x512, skip at 4, Softplus 100, weight norm",
        ),
        "fast" => (
            SdfFieldConfig::fast(),
            "hash grid 16 levels x 2 features, 2^19 entries (+xyz, 35-d input), 2x64 MLP, Softplus 100",
        ),
        other => anyhow::bail!("unknown network {other:?} (expected paper or fast)"),
    };
    Ok(Net {
        encoding: cfg.encoding.encoding_config(),
        mlp: Mlp::new(cfg.mlp_config(cfg.encoding.encoded_dim()))?,
        note,
    })
}

fn best_of(iters: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<f64> {
    let mut best = f64::INFINITY;
    for _ in 0..iters.max(1) {
        let t = Instant::now();
        f()?;
        best = best.min(t.elapsed().as_secs_f64());
    }
    Ok(best)
}

/// Seconds for one forward and one forward+backward of the whole field (encoding + MLP) over
/// `batch` points: encoding forward, MLP forward; then MLP backward and the encoding's parameter
/// backward (the hash table's gradient scatter). As a trainer would, the encoding runs once over
/// the whole batch and the cpu MLP in sub-batches of `sub` points (bounding the memory its
/// backward keeps). The concatenation of raw xyz with the grid features is a copy, not timed.
fn time_field(
    b: &Backend,
    net: &Net,
    batch: usize,
    sub: usize,
    iters: usize,
) -> anyhow::Result<(f64, f64)> {
    let mlp = &net.mlp;
    let params = mlp.init(Init::Default, 1);
    let enc_params = net.encoding.init_params(1);
    let enc_dim = net.encoding.out_dim(3);
    let mut rng = crate::util::rng(2);
    let sub = if b.is_gpu() {
        batch
    } else {
        sub.min(batch).max(1)
    };
    let pts = uniform(&mut rng, batch * 3, 1.0);
    let x = uniform(&mut rng, sub * mlp.in_dim(), 1.0);
    let d_enc = uniform(&mut rng, batch * enc_dim, 1.0);
    let dy = vec![1e-3f32; sub * mlp.out_dim()];
    let (pt, et, ptst, det) = (b.upload(&params), b.upload(&enc_params), b.upload(&pts), b.upload(&d_enc));
    // MLP inputs for sub-batches of `rows` points: full ones, and the shorter last one.
    let mlp_io = |rows: usize| (b.upload(&x[..rows * mlp.in_dim()]), b.upload(&dy[..rows * mlp.out_dim()]));
    let full = mlp_io(sub);
    let last_rows = batch - (batch.div_ceil(sub) - 1) * sub;
    let last = (last_rows != sub).then(|| mlp_io(last_rows));
    let reps = batch.div_ceil(sub);
    let pass = |backward: bool, reps: usize| -> anyhow::Result<()> {
        b.encoding_forward(&net.encoding, &et, &ptst, batch)?;
        for i in 0..reps {
            let (xt, dyt) = match &last {
                Some(l) if i + 1 == reps => l,
                _ => &full,
            };
            let f = b.mlp_forward(mlp, &pt, xt, backward)?;
            if backward {
                b.mlp_backward(mlp, &pt, &f, dyt)?;
            }
        }
        if backward && net.encoding.num_params() > 0 {
            b.encoding_backward(&net.encoding, &et, &ptst, batch, &det, false)?;
        }
        b.sync()?;
        Ok(())
    };
    // Warm-up (kernel compilation, allocator): one MLP sub-batch forward + backward.
    pass(true, 1)?;
    let fwd = best_of(iters, || pass(false, reps))?;
    let fb = best_of(iters, || pass(true, reps))?;
    Ok((fwd, fb))
}

/// `n` numbers drawn uniformly from [−bound, bound): the benchmarks' inputs and parameters.
fn uniform(rng: &mut impl rand::Rng, n: usize, bound: f32) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-bound..bound)).collect()
}

/// GFLOP/s of a plain GEMM (`[rows, 512]·[512, 512]`, the `gemm` crate's packed kernels)
/// split over rayon in 1024-row chunks: the "well-vectorised GEMM" the cpu MLP is compared with.
fn gemm_reference_gflops(rows: usize, iters: usize) -> anyhow::Result<f64> {
    let (rows, k, n, chunk) = (rows.max(1), 512usize, 512usize, 1024usize);
    let mut rng = crate::util::rng(3);
    let a = uniform(&mut rng, rows * k, 1.0);
    let w = uniform(&mut rng, k * n, 1.0);
    let mut c = vec![0f32; rows * n];
    let secs = best_of(iters.max(3) + 1, || {
        c.par_chunks_mut(chunk * n)
            .zip(a.par_chunks(chunk * k))
            .for_each(|(cc, ac)| {
                f32::gemm(ac.len() / k, k, n, ac, k, 1, &w, n, 1, 0.0, cc);
            });
        Ok(())
    })?;
    Ok(2.0 * (rows * k * n) as f64 / secs / 1e9)
}

pub fn run(args: &BenchNnArgs, ctx: &Context) -> anyhow::Result<()> {
    if args.batches.is_empty() || args.batches.contains(&0) {
        anyhow::bail!("--batches needs positive batch sizes");
    }
    crate::util::ensure_writable_parent(&args.out)?;
    let mut backends = vec![Backend::cpu()];
    match ctx.backend_choice {
        BackendChoice::Cpu => {}
        BackendChoice::Auto | BackendChoice::Wgpu => {
            match Backend::select(ctx.backend_choice, ctx.adapter.as_deref()) {
                Ok(b) if b.is_gpu() => backends.push(b),
                Ok(_) => ctx.say(
                    "no real GPU: cpu only (use --backend wgpu to include a software adapter)",
                ),
                Err(e) if ctx.backend_choice == BackendChoice::Wgpu => return Err(e.into()),
                Err(e) => tracing::info!("wgpu unavailable: {e}"),
            }
        }
    }
    let gemm_ref = gemm_reference_gflops(args.gemm_rows, args.iters)?;
    ctx.say(format!(
        "GEMM reference ([{},512]x[512,512], {} threads): {gemm_ref:.1} GFLOP/s",
        args.gemm_rows,
        rayon::current_num_threads()
    ));
    let mut launch = Vec::new();
    for b in &backends {
        if let Some(g) = b.gpu() {
            let c = launch_cost(g, b.describe(), args.launches, args.iters)?;
            ctx.say(format!(
                "launch overhead on {}: {:.2} µs host per launch ({}), {:.2} µs wall, round trip {:.0} µs",
                c.device, c.host_us_per_launch, c.host_clock, c.wall_us_per_launch, c.round_trip_us
            ));
            launch.push(c);
        }
    }
    let mut rows: Vec<Row> = Vec::new();
    let mut lanes = Vec::new();
    let mut act_lanes = Vec::new();
    let mut adam_lanes_out = Vec::new();
    let mut notes = serde_json::Map::new();
    ctx.say(format!(
        "{:<6} {:<60} {:>8} {:>14} {:>9} {:>14} {:>9}",
        "net", "backend", "batch", "fwd pts/s", "GFLOP/s", "fwd+bwd pts/s", "GFLOP/s"
    ));
    for name in &args.networks {
        let net = network(name)?;
        let mlp = &net.mlp;
        notes.insert(
            name.clone(),
            serde_json::json!({ "network": net.note, "mlp_params": mlp.num_params(),
            "encoding_params": net.encoding.num_params(),
            "mlp_forward_flops_per_point": 2 * mlp.macs_per_point() }),
        );
        let flops = 2.0 * mlp.macs_per_point() as f64;
        for b in &backends {
            let software = b.gpu().is_some_and(|g| g.is_software());
            for &batch in &args.batches {
                if software && batch > args.software_max_batch {
                    ctx.say(format!("{name:<6} {:<60} {batch:>8} skipped (software adapter; --software-max-batch)", b.describe()));
                    continue;
                }
                let (tf, tfb) = time_field(b, &net, batch, args.cpu_sub_batch, args.iters)
                    .with_context(|| format!("{name} on {} at batch {batch}", b.describe()))?;
                let row = Row {
                    network: name.clone(),
                    backend: b.name().into(),
                    device: b.describe(),
                    batch,
                    forward_points_per_s: batch as f64 / tf,
                    forward_gflops: flops * batch as f64 / tf / 1e9,
                    forward_backward_points_per_s: batch as f64 / tfb,
                    // The backward is two GEMMs per layer (dW and dX): ~3x the forward's FLOPs.
                    forward_backward_gflops: 3.0 * flops * batch as f64 / tfb / 1e9,
                };
                ctx.say(format!(
                    "{:<6} {:<60} {:>8} {:>14.3e} {:>9.1} {:>14.3e} {:>9.1}",
                    name,
                    row.device,
                    batch,
                    row.forward_points_per_s,
                    row.forward_gflops,
                    row.forward_backward_points_per_s,
                    row.forward_backward_gflops
                ));
                ctx.emit("bench_nn", serde_json::to_value(&row)?);
                rows.push(row);
            }
        }
        for &batch in &args.batches {
            if let Some(r) = grid_lanes(name, &net.encoding, batch, args.iters)? {
                ctx.say(format!(
                    "cpu hash grid, AVX2 lanes / scalar, {name} batch {batch}: forward {:.2}x, parameter gradient {:.2}x, input gradient {:.2}x (same bits)",
                    r.forward_speedup, r.parameter_gradient_speedup, r.input_gradient_speedup
                ));
                lanes.push(r);
            }
        }
        if let Some(r) = activation_lanes(name, mlp, args.cpu_sub_batch, args.iters)? {
            ctx.say(format!(
                "cpu activation ({}), AVX-512 / AVX2 loops, {name}, {} values: forward {:.2}x, backward {:.2}x (same bits)",
                r.activation, r.values, r.forward_speedup, r.backward_speedup
            ));
            act_lanes.push(r);
        }
        if let Some(r) = adam_lanes(name, net.encoding.num_params(), args.iters)? {
            ctx.say(format!(
                "cpu Adam step, {:?} / baseline loop, {name}, {} entries (a third with zero gradients, kept): {:.2}x (same bits)",
                r.level, r.entries, r.speedup
            ));
            adam_lanes_out.push(r);
        }
    }
    // Stage 2's shading (not a network, but the other half of its host step): the per-lobe SG
    // factors for 32 lobes, packs of lanes against the scalar duals.
    let sg_lanes = crate::sg::lanes::bench_lobe_factors(32, 256, args.iters * 3)?;
    if let Some(r) = &sg_lanes {
        ctx.say(format!(
            "cpu SG lobe factors (stage 2's shading, duals in 5 tangents), {:?} packs / scalar, {} lobes: {:.2}x, {:.0} ns per lobe (same bits)",
            r.level, r.lobes, r.speedup, r.ns_per_lobe
        ));
    }
    // Stage 2's secondary rays march on a sampled SDF grid (121³ is its default).
    let march_lanes = crate::render::grid::bench_march(121, 1 << 14, args.iters * 3)?;
    if let Some(r) = &march_lanes {
        ctx.say(format!(
            "cpu grid march (stage 2's secondary rays, {}³ grid, {:.1} steps a ray), eight-ray lanes / scalar, one thread: {:.2}x, {:.1} vs {:.1} ns a step (same bits)",
            r.nodes, r.steps_per_ray, r.speedup, r.ns_per_step_lanes, r.ns_per_step_scalar
        ));
    }
    let mut ratios = Vec::new();
    for g in rows.iter().filter(|r| r.backend == "wgpu") {
        if let Some(c) = rows
            .iter()
            .find(|r| r.backend == "cpu" && r.network == g.network && r.batch == g.batch)
        {
            ratios.push(Ratio {
                network: g.network.clone(),
                batch: g.batch,
                forward_wgpu_over_cpu: g.forward_points_per_s / c.forward_points_per_s,
                forward_backward_wgpu_over_cpu: g.forward_backward_points_per_s
                    / c.forward_backward_points_per_s,
            });
        }
    }
    for r in &ratios {
        ctx.say(format!(
            "wgpu/cpu {} batch {}: forward {:.2}x, forward+backward {:.2}x",
            r.network, r.batch, r.forward_wgpu_over_cpu, r.forward_backward_wgpu_over_cpu
        ));
    }
    let cpu_vs_gemm: Vec<serde_json::Value> = rows
        .iter()
        .filter(|r| r.backend == "cpu")
        .map(|r| {
            serde_json::json!({ "network": r.network, "batch": r.batch,
                "forward_fraction_of_gemm": r.forward_gflops / gemm_ref,
                "forward_backward_fraction_of_gemm": r.forward_backward_gflops / gemm_ref })
        })
        .collect();
    for v in &cpu_vs_gemm {
        ctx.say(format!(
            "cpu MLP / GEMM reference, {} batch {}: forward {:.2}, forward+backward {:.2}",
            v["network"].as_str().unwrap_or(""),
            v["batch"],
            v["forward_fraction_of_gemm"].as_f64().unwrap_or(f64::NAN),
            v["forward_backward_fraction_of_gemm"]
                .as_f64()
                .unwrap_or(f64::NAN)
        ));
    }
    let report = serde_json::json!({
        "what": "SDF field throughput (encoding + MLP, forward and forward+backward incl. the encoding's parameter gradient); GFLOP/s count the MLP only; best of --iters after a warm-up",
        "profile": if cfg!(debug_assertions) { "dev" } else { "release" },
        "cpu_threads": rayon::current_num_threads(),
        "cpu_sub_batch": args.cpu_sub_batch,
        "gemm_reference_gflops": gemm_ref,
        "gemm_reference_shape": [args.gemm_rows, 512, 512],
        "networks": notes,
        "results": rows,
        "wgpu_over_cpu": ratios,
        "cpu_vs_gemm_reference": cpu_vs_gemm,
        "launch_overhead": launch,
        "cpu_hash_grid_lanes_over_scalar": lanes,
        "cpu_activation_avx512_over_avx2": act_lanes,
        "cpu_adam_step_over_baseline": adam_lanes_out,
        "cpu_sg_lobe_factors_over_scalar": sg_lanes,
        "cpu_grid_march_lanes_over_scalar": march_lanes,
    });
    crate::util::atomic_write(&args.out, serde_json::to_string_pretty(&report)?.as_bytes())?;
    ctx.say(format!("wrote {}", args.out.display()));
    Ok(())
}
