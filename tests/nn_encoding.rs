//! Encodings: cpu backward vs central finite differences in f64, exact reproduction of linear
//! functions by the dense levels, WGSL (lavapipe) vs cpu, extreme inputs, bad configurations.

use pii_bake::backend::{Backend, Tensor};
use pii_bake::nn::encoding::{
    encoding_backward_cpu, encoding_forward_cpu, frequency_backward_cpu, frequency_forward_cpu,
    EncodingConfig,
};
use pii_bake::testing::{assert_close, assert_finite, check_grad, Tolerance};
use rand::Rng;

fn gpu() -> Backend {
    Backend::wgpu_for_tests().unwrap_or_else(|e| {
        panic!("the test command (bash scripts/test.sh) installs lavapipe; no adapter: {e}")
    })
}

fn uniform(n: usize, lo: f64, hi: f64, seed: u64) -> Vec<f64> {
    let mut r = pii_bake::util::rng(seed);
    (0..n).map(|_| r.random_range(lo..hi)).collect()
}

fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

/// Small grid with dense coarse levels and hashed fine levels (table 2^7 = 128 entries:
/// resolutions 2, 3, 4 are dense (27, 64, 125 vertices), 6 and 10 are hashed).
fn small_grid() -> EncodingConfig {
    EncodingConfig::HashGrid {
        levels: 5,
        features_per_level: 2,
        log2_table_size: 7,
        base_resolution: 2,
        per_level_scale: 1.5,
        bound: 1.5,
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[test]
fn grid_levels_mix_dense_and_hashed() {
    let lv = small_grid().grid_levels();
    assert_eq!(
        lv.iter().map(|l| l.resolution).collect::<Vec<_>>(),
        vec![2, 3, 4, 6, 10]
    );
    assert_eq!(
        lv.iter().map(|l| l.dense).collect::<Vec<_>>(),
        vec![true, true, true, false, false]
    );
}

#[test]
fn frequency_order_and_values() {
    let x = [0.3f64, -0.7];
    let out = frequency_forward_cpu(2, true, &x, 2);
    let expected = [
        0.3,
        -0.7,
        0.3f64.sin(),
        (-0.7f64).sin(),
        0.3f64.cos(),
        (-0.7f64).cos(),
        0.6f64.sin(),
        (-1.4f64).sin(),
        0.6f64.cos(),
        (-1.4f64).cos(),
    ];
    assert_close("pe order", &out, &expected, Tolerance::F64_GRAD);
    assert_eq!(EncodingConfig::frequency(6).out_dim(3), 39);
}

#[test]
fn frequency_backward_matches_finite_differences() {
    for include_input in [true, false] {
        let (n, d, nf) = (5, 3, 6);
        let x = uniform(n * d, -1.0, 1.0, 1);
        let od = d * (include_input as usize + 2 * nf as usize);
        let r = uniform(n * od, -1.0, 1.0, 2);
        let dx = frequency_backward_cpu(nf, include_input, &x, d, &r);
        check_grad("pe d_x", &x, &dx, 1e-6, Tolerance::F64_GRAD, |x| {
            dot(&frequency_forward_cpu(nf, include_input, x, d), &r)
        });
    }
}

#[test]
fn hash_grid_backward_matches_finite_differences() {
    let cfg = small_grid();
    let np = cfg.num_params();
    let od = cfg.out_dim(3);
    let params = uniform(np, -1.0, 1.0, 3);
    // Points inside the cube and some outside (clamped: their gradient is 0 there).
    let mut x = uniform(8 * 3, -1.4, 1.4, 4);
    x.extend_from_slice(&[
        2.5, 0.1234, -0.2171, -0.3137, -7.0, 0.4419, 0.2213, 0.3391, 1.9,
    ]);
    let n = x.len() / 3;
    let r = uniform(n * od, -1.0, 1.0, 5);
    let (dp, dx) = encoding_backward_cpu(&cfg, &params, &x, 3, &r, true);
    let dx = dx.unwrap();
    // The output is linear in the parameters: any step gives the exact gradient.
    check_grad(
        "grid d_params",
        &params,
        &dp,
        1e-3,
        Tolerance::F64_GRAD,
        |p| dot(&encoding_forward_cpu(&cfg, p, &x, 3), &r),
    );
    // Piecewise trilinear in x: a small step stays inside the cells of these seeded points.
    check_grad(
        "grid d_x",
        &x,
        &dx,
        1e-7,
        Tolerance::new(1e-5, 1e-6),
        |xs| dot(&encoding_forward_cpu(&cfg, &params, xs, 3), &r),
    );
    // The outside coordinates (index 8·3 + 0, 9·3 + 1, 10·3 + 2) really get zero gradient.
    assert_eq!([dx[24], dx[28], dx[32]], [0.0, 0.0, 0.0]);
    assert!(
        dx[25] != 0.0 && dx[26] != 0.0,
        "inside coordinates of a clamped point keep their gradient"
    );
}

/// A dense level whose table holds a linear function of the vertex position reproduces that
/// function exactly (trilinear interpolation is exact for linear functions).
#[test]
fn dense_level_interpolates_linear_functions_exactly() {
    let bound = 2.0f64;
    let cfg = EncodingConfig::HashGrid {
        levels: 1,
        features_per_level: 1,
        log2_table_size: 10,
        base_resolution: 7,
        per_level_scale: 1.0,
        bound: bound as f32,
    };
    let res = 7usize;
    let f = |p: [f64; 3]| 0.5 * p[0] - 1.25 * p[1] + 2.0 * p[2] + 0.3;
    let mut params = vec![0.0f64; cfg.num_params()];
    for k in 0..=res {
        for j in 0..=res {
            for i in 0..=res {
                let pos = |v: usize| -bound + 2.0 * bound * v as f64 / res as f64;
                params[i + j * (res + 1) + k * (res + 1) * (res + 1)] = f([pos(i), pos(j), pos(k)]);
            }
        }
    }
    let x = uniform(20 * 3, -2.0, 2.0, 6);
    let out = encoding_forward_cpu(&cfg, &params, &x, 3);
    let expected: Vec<f64> = x.chunks(3).map(|p| f([p[0], p[1], p[2]])).collect();
    assert_close("linear", &out, &expected, Tolerance::new(1e-12, 1e-12));
    // Outside the cube: the value on the boundary.
    let out = encoding_forward_cpu(&cfg, &params, &[5.0, 0.5, -9.0], 3);
    assert_close(
        "clamped",
        &out,
        &[f([2.0, 0.5, -2.0])],
        Tolerance::new(1e-12, 1e-12),
    );
}

#[test]
fn extreme_inputs_stay_finite_on_cpu_and_wgsl() {
    let cfg = small_grid();
    let params: Vec<f32> = to_f32(&uniform(cfg.num_params(), -1.0, 1.0, 7));
    let x: Vec<f32> = vec![
        1e6,
        -1e6,
        3e38,
        -3e38,
        1e-30,
        0.0,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
        1.5,
        -1.5,
        1e6,
    ];
    let n = x.len() / 3;
    let pe = EncodingConfig::frequency(6);
    let pe_x: Vec<f32> = vec![1e6, -1e6, 1e5, 3e4, -2e4, 1e3];
    for b in [Backend::cpu(), gpu()] {
        let (p, xt) = (b.upload(&params), b.upload(&x));
        let out = b.encoding_forward(&cfg, &p, &xt, n).unwrap();
        assert_finite(
            &format!("{} grid forward", b.name()),
            &b.to_vec(&out).unwrap(),
        );
        let d_out = b.upload(&vec![1.0; n * cfg.out_dim(3)]);
        let (dp, dx) = b.encoding_backward(&cfg, &p, &xt, n, &d_out, true).unwrap();
        assert_finite(
            &format!("{} grid d_params", b.name()),
            &b.to_vec(&dp).unwrap(),
        );
        assert_finite(
            &format!("{} grid d_x", b.name()),
            &b.to_vec(&dx.unwrap()).unwrap(),
        );

        let (e, xt) = (b.upload(&[]), b.upload(&pe_x));
        let out = b.encoding_forward(&pe, &e, &xt, 2).unwrap();
        assert_finite(
            &format!("{} pe forward", b.name()),
            &b.to_vec(&out).unwrap(),
        );
        let d_out = b.upload(&vec![1.0; 2 * pe.out_dim(3)]);
        let (_, dx) = b.encoding_backward(&pe, &e, &xt, 2, &d_out, true).unwrap();
        assert_finite(
            &format!("{} pe d_x", b.name()),
            &b.to_vec(&dx.unwrap()).unwrap(),
        );
    }
}

fn run(
    b: &Backend,
    cfg: &EncodingConfig,
    p: &[f32],
    x: &[f32],
    d: &[f32],
    n: usize,
) -> [Vec<f32>; 3] {
    let (pt, xt, dt) = (b.upload(p), b.upload(x), b.upload(d));
    let out = b.encoding_forward(cfg, &pt, &xt, n).unwrap();
    let (dp, dx) = b.encoding_backward(cfg, &pt, &xt, n, &dt, true).unwrap();
    [
        b.to_vec(&out).unwrap(),
        b.to_vec(&dp).unwrap(),
        b.to_vec(&dx.unwrap()).unwrap(),
    ]
}

/// WGSL on lavapipe vs the cpu backend on seeded random inputs. Tolerance: `GPU_VS_CPU`
/// (rel 2e-3, abs 1e-4); sin/cos and summation order differ by a few ulp, and the hash-grid
/// parameter gradient is accumulated with atomics in arbitrary order.
#[test]
fn wgsl_matches_cpu() {
    let g = gpu();
    let c = Backend::cpu();
    let configs = [
        EncodingConfig::frequency(6),
        EncodingConfig::Frequency {
            n_freqs: 4,
            include_input: false,
        },
        small_grid(),
        EncodingConfig::HashGrid {
            levels: 8,
            features_per_level: 4,
            log2_table_size: 12,
            base_resolution: 4,
            per_level_scale: 1.7,
            bound: 1.0,
        },
    ];
    for (ci, cfg) in configs.iter().enumerate() {
        let n = 777;
        let in_dim = 3;
        let x = to_f32(&uniform(n * in_dim, -1.2, 1.2, 10 + ci as u64));
        let p = to_f32(&uniform(cfg.num_params(), -1.0, 1.0, 20 + ci as u64));
        let d = to_f32(&uniform(n * cfg.out_dim(in_dim), -1.0, 1.0, 30 + ci as u64));
        let want = run(&c, cfg, &p, &x, &d, n);
        let got = run(&g, cfg, &p, &x, &d, n);
        for (k, what) in ["forward", "d_params", "d_x"].iter().enumerate() {
            assert_eq!(got[k].len(), want[k].len(), "{what} length, config {ci}");
            assert_close(
                &format!("config {ci} {what}"),
                &got[k],
                &want[k],
                Tolerance::GPU_VS_CPU,
            );
        }
    }
}

#[test]
fn skipping_dx_and_empty_batches() {
    for b in [Backend::cpu(), gpu()] {
        let cfg = small_grid();
        let p = b.upload(&vec![0.5; cfg.num_params()]);
        let x = b.upload(&[0.1, 0.2, 0.3]);
        let d = b.upload(&vec![1.0; cfg.out_dim(3)]);
        let (dp, dx) = b.encoding_backward(&cfg, &p, &x, 1, &d, false).unwrap();
        assert!(dx.is_none());
        // Each level's 8 trilinear weights sum to 1 per feature: total = levels·F.
        let s: f32 = b.to_vec(&dp).unwrap().iter().sum();
        assert!(
            (s - cfg.out_dim(3) as f32).abs() < 1e-4,
            "{} sum of d_params {s}",
            b.name()
        );
        let empty = b.upload(&[]);
        let out = b.encoding_forward(&cfg, &p, &empty, 0).unwrap();
        assert_eq!(out.len(), 0);
    }
}

#[test]
fn bad_configurations_and_shapes_are_errors() {
    let b = Backend::cpu();
    let cfg = small_grid();
    let x = b.upload(&[0.0; 6]);
    let wrong = b.upload(&[0.0; 3]);
    let err = b.encoding_forward(&cfg, &wrong, &x, 2).unwrap_err();
    assert!(err.to_string().contains("params"), "{err}");
    let p = b.upload(&vec![0.0; cfg.num_params()]);
    let err = b.encoding_forward(&cfg, &p, &x, 3).unwrap_err();
    assert!(err.to_string().contains("3-D"), "{err}");
    let err = b.encoding_forward(&cfg, &p, &x, 4).unwrap_err();
    assert!(err.to_string().contains("multiple"), "{err}");
    let zero_levels = EncodingConfig::HashGrid {
        levels: 0,
        features_per_level: 2,
        log2_table_size: 10,
        base_resolution: 4,
        per_level_scale: 2.0,
        bound: 1.0,
    };
    let empty: Tensor = b.upload(&[]);
    assert!(b
        .encoding_forward(&zero_levels, &empty, &x, 2)
        .unwrap_err()
        .to_string()
        .contains("levels"));
    let bad_bound = EncodingConfig::HashGrid {
        levels: 2,
        features_per_level: 2,
        log2_table_size: 10,
        base_resolution: 4,
        per_level_scale: 2.0,
        bound: f32::NAN,
    };
    assert!(bad_bound
        .validate(3)
        .unwrap_err()
        .to_string()
        .contains("bound"));
    let nothing = EncodingConfig::Frequency {
        n_freqs: 0,
        include_input: false,
    };
    assert!(b.encoding_forward(&nothing, &empty, &x, 2).is_err());
    let d = b.upload(&[0.0; 5]);
    let err = b.encoding_backward(&cfg, &p, &x, 2, &d, true).unwrap_err();
    assert!(err.to_string().contains("d_out"), "{err}");
}

/// The cpu hash grid runs level-major over large parallel chunks: a batch spanning several chunks
/// (and a ragged last one) gives, row for row, exactly what each point gives alone.
#[test]
fn hash_grid_batches_equal_single_points() {
    let cfg = small_grid();
    let n = 20_011;
    let (params64, x64) = (uniform(cfg.num_params(), -1.0, 1.0, 11), uniform(3 * n, -1.6, 1.6, 12));
    let d_out64 = uniform(n * cfg.out_dim(3), -1.0, 1.0, 13);
    let (params, x, d_out) = (to_f32(&params64), to_f32(&x64), to_f32(&d_out64));
    let out = encoding_forward_cpu(&cfg, &params, &x, 3);
    let (_, dx) = encoding_backward_cpu(&cfg, &params, &x, 3, &d_out, true);
    let dx = dx.expect("dx asked for");
    let od = cfg.out_dim(3);
    for i in (0..n).step_by(97).chain([n - 1]) {
        let xi = &x[3 * i..3 * i + 3];
        assert_eq!(&encoding_forward_cpu(&cfg, &params, xi, 3)[..], &out[i * od..(i + 1) * od], "row {i}");
        let (_, dxi) = encoding_backward_cpu(&cfg, &params, xi, 3, &d_out[i * od..(i + 1) * od], true);
        assert_eq!(&dxi.unwrap()[..], &dx[3 * i..3 * i + 3], "row {i}");
    }
    // The parameter gradient of the whole batch is the sum of the points' own gradients (each
    // level scatters every point), on the same batch in f64 to a rounding's width.
    let (dp, _) = encoding_backward_cpu(&cfg, &params64, &x64, 3, &d_out64, false);
    let mut sum = vec![0.0; cfg.num_params()];
    for i in 0..n {
        let (dpi, _) = encoding_backward_cpu(&cfg, &params64, &x64[3 * i..3 * i + 3], 3, &d_out64[i * od..(i + 1) * od], false);
        sum.iter_mut().zip(&dpi).for_each(|(s, g)| *s += g);
    }
    for (e, (a, b)) in dp.iter().zip(&sum).enumerate() {
        assert!((a - b).abs() <= 1e-9 * (1.0 + b.abs()), "entry {e}: {a} vs {b}");
    }
}
