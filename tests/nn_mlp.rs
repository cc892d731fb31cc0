//! MLP kernel family: cpu backward (parameters and inputs) vs central finite differences in f64
//! for every activation, the skip connection and weight norm; WGSL (lavapipe) vs the cpu twin;
//! no NaN/Inf at extreme inputs; bad configurations are errors.

use pii_bake::backend::{Backend, BackendError, Tensor};
use pii_bake::nn::mlp::{cpu_backward, cpu_forward, Activation, Init, Mlp, MlpConfig};
use pii_bake::testing::{assert_close, assert_finite, check_grad, Tolerance};
use rand::Rng;

fn config(
    activation: Activation,
    output_activation: Activation,
    skip: bool,
    weight_norm: bool,
) -> MlpConfig {
    MlpConfig {
        in_dim: 3,
        widths: vec![7, 9, 6],
        out_dim: 2,
        activation,
        output_activation,
        skip_layers: if skip { vec![2] } else { vec![] },
        weight_norm,
    }
}

fn random(n: usize, scale: f64, seed: u64) -> Vec<f64> {
    let mut r = pii_bake::util::rng(seed);
    (0..n).map(|_| r.random_range(-scale..scale)).collect()
}

/// Parameters: the seeded init plus noise (so biases and gains are not all trivial).
fn params(mlp: &Mlp, seed: u64) -> Vec<f64> {
    let p = mlp.init(Init::Default, seed);
    let noise = random(p.len(), 0.1, seed + 1);
    p.iter().zip(noise).map(|(&v, e)| v as f64 + e).collect()
}

/// L = Σ w·y: checks dL/dparams and dL/dx against central differences in f64.
fn check_fd(cfg: MlpConfig, what: &str) {
    let mlp = Mlp::new(cfg).unwrap();
    let rows = 5;
    let p = params(&mlp, 11);
    let x = random(rows * mlp.in_dim(), 1.0, 12);
    let w = random(rows * mlp.out_dim(), 1.0, 13);
    let loss = |p: &[f64], x: &[f64]| -> f64 {
        let (y, _) = cpu_forward(&mlp, p, x, false).unwrap();
        y.iter().zip(&w).map(|(a, b)| a * b).sum()
    };
    let (_, cache) = cpu_forward(&mlp, &p, &x, true).unwrap();
    let (dp, dx) = cpu_backward(&mlp, &p, &cache, &w).unwrap();
    let h = 1e-6;
    check_grad(
        &format!("{what}: dL/dparams"),
        &p,
        &dp,
        h,
        Tolerance::F64_GRAD,
        |pp| loss(pp, &x),
    );
    check_grad(
        &format!("{what}: dL/dx"),
        &x,
        &dx,
        h,
        Tolerance::F64_GRAD,
        |xx| loss(&p, xx),
    );
}

fn activations() -> Vec<(&'static str, Activation)> {
    vec![
        ("none", Activation::None),
        ("relu", Activation::Relu),
        ("leaky_relu", Activation::LeakyRelu(0.2)),
        ("softplus_b2", Activation::Softplus { beta: 2.0 }),
        ("softplus_b100", Activation::Softplus { beta: 100.0 }),
        ("sigmoid", Activation::Sigmoid),
    ]
}

#[test]
fn backward_matches_finite_differences_for_every_activation() {
    for (name, act) in activations() {
        check_fd(
            config(act, Activation::None, false, false),
            &format!("hidden {name}"),
        );
        check_fd(
            config(Activation::Softplus { beta: 3.0 }, act, false, false),
            &format!("output {name}"),
        );
    }
}

#[test]
fn backward_matches_finite_differences_with_skip_and_weight_norm() {
    let sp = Activation::Softplus { beta: 100.0 };
    check_fd(config(sp, Activation::None, true, false), "skip");
    check_fd(config(sp, Activation::None, false, true), "weight norm");
    check_fd(
        config(sp, Activation::Sigmoid, true, true),
        "skip + weight norm",
    );
    // Two skips; then no hidden layers at all (a single linear layer).
    let mut c = config(Activation::Relu, Activation::None, false, true);
    c.widths = vec![6, 8, 8, 7];
    c.skip_layers = vec![2, 4];
    check_fd(c, "two skips");
    let mut c = config(Activation::Relu, Activation::Sigmoid, false, true);
    c.widths = vec![];
    check_fd(c, "single layer");
}

#[test]
fn f32_twin_matches_f64_reference() {
    let mlp = Mlp::new(config(
        Activation::Softplus { beta: 100.0 },
        Activation::None,
        true,
        true,
    ))
    .unwrap();
    let p64 = params(&mlp, 3);
    // More rows than one rayon chunk, so the chunked gradient reduction is exercised.
    let x64 = random(2100 * 3, 1.0, 4);
    let w64 = random(2100 * 2, 1.0, 5);
    let f = |v: &[f64]| v.iter().map(|&a| a as f32).collect::<Vec<f32>>();
    let (y64, c64) = cpu_forward(&mlp, &p64, &x64, true).unwrap();
    let (y32, c32) = cpu_forward(&mlp, &f(&p64), &f(&x64), true).unwrap();
    let (dp64, dx64) = cpu_backward(&mlp, &p64, &c64, &w64).unwrap();
    let (dp32, dx32) = cpu_backward(&mlp, &f(&p64), &c32, &f(&w64)).unwrap();
    let tol = Tolerance::new(1e-3, 1e-4);
    assert_close("forward f32 vs f64", &y32, &y64, tol);
    assert_close(
        "dparams f32 vs f64",
        &dp32,
        &dp64,
        Tolerance::new(1e-3, 1e-3),
    );
    assert_close("dx f32 vs f64", &dx32, &dx64, tol);
}

fn gpu() -> Backend {
    Backend::wgpu_for_tests()
        .unwrap_or_else(|e| panic!("the test command installs lavapipe; no adapter: {e}"))
}

/// WGSL forward and backward vs the cpu backend, same f32 inputs.
fn check_gpu(gpu: &Backend, cfg: MlpConfig, rows: usize, what: &str) {
    let cpu = Backend::cpu();
    let mlp = Mlp::new(cfg).unwrap();
    let p: Vec<f32> = params(&mlp, 21).iter().map(|&v| v as f32).collect();
    let x: Vec<f32> = random(rows * mlp.in_dim(), 1.0, 22)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let dy: Vec<f32> = random(rows * mlp.out_dim(), 1.0, 23)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let run = |b: &Backend| -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (pt, xt, dyt) = (b.upload(&p), b.upload(&x), b.upload(&dy));
        let fwd = b.mlp_forward(&mlp, &pt, &xt, true).unwrap();
        let g = b.mlp_backward(&mlp, &pt, &fwd, &dyt).unwrap();
        (
            b.to_vec(&fwd.output).unwrap(),
            b.to_vec(&g.d_params).unwrap(),
            b.to_vec(&g.d_input).unwrap(),
        )
    };
    let (yc, dpc, dxc) = run(&cpu);
    let (yg, dpg, dxg) = run(gpu);
    let tol = Tolerance::GPU_VS_CPU;
    assert_close(&format!("{what}: forward"), &yg, &yc, tol);
    // Parameter gradients sum over the batch: allow absolute error growing with the row count.
    let ptol = Tolerance::new(tol.rel, tol.abs * rows as f64);
    assert_close(&format!("{what}: dL/dparams"), &dpg, &dpc, ptol);
    assert_close(&format!("{what}: dL/dx"), &dxg, &dxc, tol);
}

#[test]
fn wgsl_matches_cpu_forward_and_backward() {
    let g = gpu();
    for (name, act) in activations() {
        check_gpu(
            &g,
            config(act, Activation::Sigmoid, false, false),
            37,
            &format!("hidden {name}"),
        );
        check_gpu(
            &g,
            config(Activation::Relu, act, false, false),
            37,
            &format!("output {name}"),
        );
    }
    let sp = Activation::Softplus { beta: 100.0 };
    check_gpu(&g, config(sp, Activation::None, true, false), 37, "skip");
    check_gpu(
        &g,
        config(sp, Activation::None, true, true),
        37,
        "skip + weight norm",
    );
    // Several 64x64 output tiles and K steps of 16 with ragged edges.
    let big = MlpConfig {
        in_dim: 21,
        widths: vec![70, 90, 67],
        out_dim: 5,
        activation: sp,
        output_activation: Activation::None,
        skip_layers: vec![2],
        weight_norm: true,
    };
    check_gpu(&g, big, 150, "multi-tile");
    // A batch long enough that dW = dZᵀ·U is split over K (partials + split_reduce).
    let long = MlpConfig {
        in_dim: 4,
        widths: vec![24],
        out_dim: 3,
        activation: Activation::Sigmoid,
        output_activation: Activation::None,
        skip_layers: vec![],
        weight_norm: true,
    };
    check_gpu(&g, long, 3001, "split-K");
}

#[test]
fn activations_are_overflow_safe() {
    for (name, act) in activations() {
        for z in [
            -3e38f32, -1e30, -1e4, -88.8, -20.0, 0.0, 20.0, 88.8, 1e4, 1e30, 3e38,
        ] {
            let y = act.forward(z);
            let d = act.derivative(z);
            assert!(
                y.is_finite() && d.is_finite(),
                "{name}({z}) = {y}, derivative {d}"
            );
        }
    }
    let sp = Activation::Softplus { beta: 100.0 };
    assert_eq!(sp.forward(1e30f32), 1e30);
    assert!(sp.forward(-1e30f32) < 1e-30);
    assert!(Activation::Sigmoid.forward(-1e30f32) < 1e-30);
    assert_eq!(Activation::Sigmoid.forward(1e30f32), 1.0);
}

#[test]
fn huge_inputs_give_finite_outputs_and_gradients_on_both_backends() {
    let cfg = MlpConfig {
        in_dim: 3,
        widths: vec![16, 16],
        out_dim: 2,
        activation: Activation::Softplus { beta: 100.0 },
        output_activation: Activation::Sigmoid,
        skip_layers: vec![1],
        weight_norm: true,
    };
    let mlp = Mlp::new(cfg).unwrap();
    let p = mlp.init(Init::Default, 5);
    let x: Vec<f32> = [1e6f32, -1e6, 3e5, -1e8, 1e8, 0.0, 1e4, 1e4, -1e4].to_vec();
    let dy = vec![1.0f32; 6];
    for b in [Backend::cpu(), gpu()] {
        let pt = b.upload(&p);
        let fwd = b.mlp_forward(&mlp, &pt, &b.upload(&x), true).unwrap();
        let g = b.mlp_backward(&mlp, &pt, &fwd, &b.upload(&dy)).unwrap();
        assert_finite(
            &format!("{}: output", b.name()),
            &b.to_vec(&fwd.output).unwrap(),
        );
        assert_finite(
            &format!("{}: dL/dparams", b.name()),
            &b.to_vec(&g.d_params).unwrap(),
        );
        assert_finite(
            &format!("{}: dL/dx", b.name()),
            &b.to_vec(&g.d_input).unwrap(),
        );
    }
}

fn config_err(c: MlpConfig) -> String {
    match Mlp::new(c) {
        Err(BackendError::Config(m)) => m,
        other => panic!("expected a config error, got {other:?}"),
    }
}

#[test]
fn bad_configs_and_shapes_are_errors() {
    let base = config(Activation::Relu, Activation::None, true, false);
    let mut c = base.clone();
    c.widths[1] = 0;
    assert!(config_err(c).contains("zero width"));
    let mut c = base.clone();
    c.in_dim = 0;
    assert!(config_err(c).contains("in_dim"));
    let mut c = base.clone();
    c.skip_layers = vec![7];
    assert!(config_err(c).contains("skip layer 7"));
    let mut c = base.clone();
    c.skip_layers = vec![0];
    assert!(config_err(c).contains("skip layer 0"));
    let mut c = base.clone();
    c.widths = vec![7, 3, 6];
    assert!(config_err(c).contains("must exceed in_dim"));
    let mut c = base.clone();
    c.activation = Activation::Softplus { beta: 0.0 };
    assert!(config_err(c).contains("beta"));

    let mlp = Mlp::new(base).unwrap();
    let p = mlp.init(Init::Default, 1);
    for b in [Backend::cpu(), gpu()] {
        let short = b.upload(&p[..p.len() - 1]);
        let x = b.upload(&[0.0; 6]);
        let err = b.mlp_forward(&mlp, &short, &x, true).unwrap_err();
        assert!(err.to_string().contains("parameters"), "{err}");
        let pt = b.upload(&p);
        let err = b
            .mlp_forward(&mlp, &pt, &b.upload(&[0.0; 7]), true)
            .unwrap_err();
        assert!(err.to_string().contains("multiple of in_dim"), "{err}");
        let fwd = b.mlp_forward(&mlp, &pt, &x, false).unwrap();
        let err = b
            .mlp_backward(&mlp, &pt, &fwd, &b.upload(&[0.0; 4]))
            .unwrap_err();
        assert!(err.to_string().contains("keep"), "{err}");
        let fwd = b.mlp_forward(&mlp, &pt, &x, true).unwrap();
        let err = b
            .mlp_backward(&mlp, &pt, &fwd, &b.upload(&[0.0; 5]))
            .unwrap_err();
        assert!(err.to_string().contains("dL/dy"), "{err}");
    }
    // A host tensor handed to the wgpu backend.
    let err = gpu()
        .mlp_forward(
            &mlp,
            &Tensor::Host(p.clone()),
            &Tensor::Host(vec![0.0; 6]),
            false,
        )
        .unwrap_err();
    assert!(err.to_string().contains("host tensor"), "{err}");
}

#[test]
fn bench_nn_writes_its_json() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("nn.json");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_pii-bake"))
        .args([
            "--backend",
            "cpu",
            "bench",
            "nn",
            "--batches",
            "64,100",
            "--iters",
            "1",
            "--gemm-rows",
            "256",
        ])
        .args(["--networks", "fast", "--cpu-sub-batch", "64", "--out"])
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success());
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let rows = v["results"].as_array().unwrap();
    assert_eq!(rows.len(), 2);
    for r in rows {
        assert_eq!(r["network"], "fast");
        assert!(r["forward_points_per_s"].as_f64().unwrap() > 0.0);
        assert!(r["forward_backward_gflops"].as_f64().unwrap() > 0.0);
    }
    assert!(v["gemm_reference_gflops"].as_f64().unwrap() > 0.0);
    assert_eq!(v["cpu_vs_gemm_reference"].as_array().unwrap().len(), 2);
    assert!(v["launch_overhead"].as_array().unwrap().is_empty(), "the cpu backend launches nothing");
    // On wgpu (lavapipe here) it also measures the host's cost per launch and a round trip; the
    // launches' sum is checked inside, so a lost launch is an error.
    let out = dir.path().join("nn-wgpu.json");
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_pii-bake"))
        .args(["--backend", "wgpu", "bench", "nn", "--batches", "64", "--iters", "1", "--gemm-rows", "64"])
        .args(["--networks", "fast", "--launches", "200", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let l = &v["launch_overhead"][0];
    assert_eq!(l["launches"], 200);
    for k in ["host_us_per_launch", "wall_us_per_launch", "round_trip_us"] {
        let x = l[k].as_f64().unwrap();
        assert!(x > 0.0 && x.is_finite(), "{k} = {x}");
    }
    // A bad network name is an error, not a panic.
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_pii-bake"))
        .args([
            "--backend",
            "cpu",
            "bench",
            "nn",
            "--networks",
            "huge",
            "--gemm-rows",
            "16",
            "--out",
        ])
        .arg(dir.path().join("x.json"))
        .output()
        .unwrap();
    assert_eq!(st.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&st.stderr).contains("unknown network"));
}
