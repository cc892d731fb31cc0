//! Adam on the cpu backend and in WGSL (lavapipe): a hand-computed first step, an f64 reference
//! over several steps (bias correction, global-norm clipping, decoupled weight decay, a schedule),
//! and the NaN/Inf guard (a non-finite gradient never reaches the parameters).

use pii_bake::backend::Backend;
use pii_bake::nn::adam::{adam_update_host, host_grad_norm, AdamConfig, AdamItem, AdamState, LrSchedule};
use pii_bake::testing::{assert_close, Tolerance};
use rand::Rng;

fn gpu() -> Backend {
    Backend::wgpu_for_tests().unwrap_or_else(|e| {
        panic!("the test command (bash scripts/test.sh) installs lavapipe; no adapter: {e}")
    })
}

fn backends() -> [Backend; 2] {
    [Backend::cpu(), gpu()]
}

fn uniform(n: usize, lo: f32, hi: f32, seed: u64) -> Vec<f32> {
    let mut r = pii_bake::util::rng(seed);
    (0..n).map(|_| r.random_range(lo..hi)).collect()
}

/// The textbook update in f64 (see the formula in `nn::adam`).
struct Reference {
    p: Vec<f64>,
    m: Vec<f64>,
    v: Vec<f64>,
    t: i32,
}

impl Reference {
    #[allow(clippy::needless_range_loop)] // four arrays indexed together: clearest with an index
    fn step(&mut self, cfg: &AdamConfig, g: &[f32], lr: f64) {
        let norm = g.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
        let s = match cfg.grad_clip_norm {
            Some(c) if norm > c as f64 => c as f64 / norm,
            _ => 1.0,
        };
        self.t += 1;
        let (b1, b2) = (cfg.beta1 as f64, cfg.beta2 as f64);
        for i in 0..self.p.len() {
            if cfg.skip_zero_gradients && g[i] == 0.0 {
                continue;
            }
            let gi = g[i] as f64 * s;
            self.m[i] = b1 * self.m[i] + (1.0 - b1) * gi;
            self.v[i] = b2 * self.v[i] + (1.0 - b2) * gi * gi;
            let mh = self.m[i] / (1.0 - b1.powi(self.t));
            let vh = self.v[i] / (1.0 - b2.powi(self.t));
            self.p[i] -=
                lr * (mh / (vh.sqrt() + cfg.eps as f64) + cfg.weight_decay as f64 * self.p[i]);
        }
    }
}

#[test]
fn first_step_moves_each_parameter_by_lr_against_its_gradient_sign() {
    // Step 1: m̂ = g and v̂ = g², so the update is lr·g/(|g| + eps) ≈ lr·sign(g), plus lr·wd·p.
    let cfg = AdamConfig {
        lr: 0.01,
        weight_decay: 0.5,
        ..Default::default()
    };
    let p0 = [1.0f32, -2.0, 0.5, 3.0];
    let g = [0.3f32, -4.0, 1e-3, -0.02];
    let expected: Vec<f32> = p0
        .iter()
        .zip(&g)
        .map(|(p, g)| p - 0.01 * (g.signum() + 0.5 * p))
        .collect();
    for b in backends() {
        let mut p = b.upload(&p0);
        let mut st = AdamState::new(&b, 4);
        let rep = b
            .adam_step(&cfg, &mut st, &mut p, &b.upload(&g), cfg.lr)
            .unwrap();
        assert!(rep.applied && rep.step == 1 && st.step == 1);
        assert_close(
            &format!("{} step 1", b.name()),
            &b.to_vec(&p).unwrap(),
            &expected,
            Tolerance::new(1e-6, 1e-6),
        );
        let m: Vec<f32> = g.iter().map(|g| 0.1 * g).collect();
        assert_close(
            "m after step 1",
            &b.to_vec(&st.m).unwrap(),
            &m,
            Tolerance::new(1e-6, 0.0),
        );
    }
}

#[test]
fn matches_reference_over_steps_with_clipping_weight_decay_and_schedule() {
    let n = 3000;
    let cfg = AdamConfig {
        lr: 0.05,
        beta1: 0.8,
        beta2: 0.95,
        eps: 1e-6,
        weight_decay: 0.01,
        grad_clip_norm: Some(5.0),
        skip_zero_gradients: false,
    };
    let sched = LrSchedule::Exponential {
        decay_rate: 0.5,
        decay_steps: 2,
    };
    let p0 = uniform(n, -1.0, 1.0, 1);
    // Step 0 and 2: gradients with norm ~ 0.03·sqrt(n/3) ≈ 0.9 (not clipped); steps 1 and 3: ~30 (clipped).
    let grads: Vec<Vec<f32>> = (0..4)
        .map(|s| {
            uniform(n, -1.0, 1.0, 10 + s)
                .iter()
                .map(|g| g * if s % 2 == 0 { 0.03 } else { 1.0 })
                .collect()
        })
        .collect();
    let mut reference = Reference {
        p: p0.iter().map(|&x| x as f64).collect(),
        m: vec![0.0; n],
        v: vec![0.0; n],
        t: 0,
    };
    let mut norms = Vec::new();
    for (s, g) in grads.iter().enumerate() {
        reference.step(&cfg, g, sched.lr_at(cfg.lr, s as u64) as f64);
        norms.push(g.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt());
    }
    for b in backends() {
        let mut p = b.upload(&p0);
        let mut st = AdamState::new(&b, n);
        for (s, g) in grads.iter().enumerate() {
            let lr = sched.lr_at(cfg.lr, st.step);
            let rep = b
                .adam_step(&cfg, &mut st, &mut p, &b.upload(g), lr)
                .unwrap();
            assert!(rep.applied);
            assert!(
                (rep.grad_norm as f64 - norms[s]).abs() < 1e-4 * norms[s],
                "{} norm {}",
                b.name(),
                rep.grad_norm
            );
            let clipped = norms[s] > 5.0;
            assert_eq!(
                rep.clip_scale < 1.0,
                clipped,
                "step {s}: clip scale {}",
                rep.clip_scale
            );
        }
        assert_eq!(st.step, 4);
        let tol = Tolerance::new(1e-5, 1e-6);
        assert_close(
            &format!("{} params", b.name()),
            &b.to_vec(&p).unwrap(),
            &reference.p,
            tol,
        );
        assert_close(
            &format!("{} m", b.name()),
            &b.to_vec(&st.m).unwrap(),
            &reference.m,
            tol,
        );
        assert_close(
            &format!("{} v", b.name()),
            &b.to_vec(&st.v).unwrap(),
            &reference.v,
            Tolerance::new(1e-5, 1e-9),
        );
    }
}

#[test]
fn non_finite_gradients_never_reach_the_parameters() {
    let cfg = AdamConfig {
        grad_clip_norm: Some(1.0),
        weight_decay: 0.1,
        ..Default::default()
    };
    let n = 1000;
    let p0 = uniform(n, -1.0, 1.0, 3);
    let g0 = uniform(n, -1.0, 1.0, 4);
    for b in backends() {
        let mut p = b.upload(&p0);
        let mut st = AdamState::new(&b, n);
        b.adam_step(&cfg, &mut st, &mut p, &b.upload(&g0), 1e-2)
            .unwrap();
        let (p1, m1, v1) = (
            b.to_vec(&p).unwrap(),
            b.to_vec(&st.m).unwrap(),
            b.to_vec(&st.v).unwrap(),
        );
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut g = g0.clone();
            g[517] = bad;
            g[3] = bad;
            let rep = b
                .adam_step(&cfg, &mut st, &mut p, &b.upload(&g), 1e-2)
                .unwrap();
            assert!(!rep.applied, "{}: step with {bad} applied", b.name());
            assert_eq!(rep.non_finite, 2);
            assert_eq!((rep.step, st.step), (1, 1));
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                bits(&b.to_vec(&p).unwrap()),
                bits(&p1),
                "{}: params changed by a {bad} gradient",
                b.name()
            );
            assert_eq!(bits(&b.to_vec(&st.m).unwrap()), bits(&m1));
            assert_eq!(bits(&b.to_vec(&st.v).unwrap()), bits(&v1));
        }
        // A finite step afterwards proceeds as step 2.
        let rep = b
            .adam_step(&cfg, &mut st, &mut p, &b.upload(&g0), 1e-2)
            .unwrap();
        assert!(rep.applied && rep.step == 2);
        assert!(b.to_vec(&p).unwrap().iter().all(|x| x.is_finite()));
    }
}

#[test]
fn mismatched_sizes_and_bad_settings_are_errors() {
    let b = Backend::cpu();
    let mut p = b.upload(&[1.0; 4]);
    let mut st = AdamState::new(&b, 4);
    let err = b
        .adam_step(
            &AdamConfig::default(),
            &mut st,
            &mut p,
            &b.upload(&[1.0; 3]),
            1e-3,
        )
        .unwrap_err();
    assert!(err.to_string().contains("grads 3"), "{err}");
    let err = b
        .adam_step(
            &AdamConfig::default(),
            &mut st,
            &mut p,
            &b.upload(&[1.0; 4]),
            f32::NAN,
        )
        .unwrap_err();
    assert!(err.to_string().contains("learning rate"), "{err}");
    let bad = AdamConfig {
        eps: 0.0,
        ..Default::default()
    };
    assert!(b
        .adam_step(&bad, &mut st, &mut p, &b.upload(&[1.0; 4]), 1e-3)
        .is_err());
    assert_eq!(b.to_vec(&p).unwrap(), vec![1.0; 4]);
}

/// A group step clips by the global norm over all tensors (= one step on the concatenation) and a
/// non-finite value in one tensor's gradient leaves every tensor untouched.
#[test]
fn group_step_uses_the_global_norm_and_skips_as_a_whole() {
    let cfg = AdamConfig {
        lr: 0.02,
        grad_clip_norm: Some(2.0),
        weight_decay: 0.05,
        ..Default::default()
    };
    let (na, nb) = (700, 1300);
    let (pa, pb) = (uniform(na, -1.0, 1.0, 40), uniform(nb, -1.0, 1.0, 41));
    let (ga, gb) = (uniform(na, -1.0, 1.0, 42), uniform(nb, -0.1, 0.1, 43));
    let concat = |a: &[f32], b: &[f32]| a.iter().chain(b).copied().collect::<Vec<f32>>();
    let mut reference = Reference {
        p: concat(&pa, &pb).iter().map(|&x| x as f64).collect(),
        m: vec![0.0; na + nb],
        v: vec![0.0; na + nb],
        t: 0,
    };
    for _ in 0..2 {
        reference.step(&cfg, &concat(&ga, &gb), cfg.lr as f64);
    }
    for b in backends() {
        let (mut ta, mut tb) = (b.upload(&pa), b.upload(&pb));
        let (mut sa, mut sb) = (AdamState::new(&b, na), AdamState::new(&b, nb));
        let (gat, gbt) = (b.upload(&ga), b.upload(&gb));
        for _ in 0..2 {
            let mut items = [
                AdamItem {
                    params: &mut ta,
                    grads: &gat,
                    state: &mut sa,
                },
                AdamItem {
                    params: &mut tb,
                    grads: &gbt,
                    state: &mut sb,
                },
            ];
            let rep = b.adam_step_group(&cfg, &mut items, cfg.lr).unwrap();
            assert!(rep.applied && rep.clip_scale < 1.0, "{}: {rep:?}", b.name());
        }
        let got = concat(&b.to_vec(&ta).unwrap(), &b.to_vec(&tb).unwrap());
        assert_close(
            &format!("{} group params", b.name()),
            &got,
            &reference.p,
            Tolerance::new(1e-5, 1e-6),
        );
        assert_eq!((sa.step, sb.step), (2, 2));

        let mut bad = gb.clone();
        bad[1000] = f32::NAN;
        let bad = b.upload(&bad);
        let (before_a, before_b) = (b.to_vec(&ta).unwrap(), b.to_vec(&tb).unwrap());
        let mut items = [
            AdamItem {
                params: &mut ta,
                grads: &gat,
                state: &mut sa,
            },
            AdamItem {
                params: &mut tb,
                grads: &bad,
                state: &mut sb,
            },
        ];
        let rep = b.adam_step_group(&cfg, &mut items, cfg.lr).unwrap();
        assert!(!rep.applied && rep.non_finite == 1);
        assert_eq!(
            b.to_vec(&ta).unwrap(),
            before_a,
            "{}: the finite tensor moved",
            b.name()
        );
        assert_eq!(b.to_vec(&tb).unwrap(), before_b);
        assert_eq!((sa.step, sb.step), (2, 2));
    }
}

/// `skip_zero_gradients` (the hash grids' sparse update): an entry whose gradient is exactly 0
/// keeps its parameter and both moments (no decay, no weight decay), the others follow the
/// reference, on both backends; the host path the trainers take (`host_grad_norm` +
/// `adam_update_host`) gives the same bits as `adam_step` on the cpu backend.
#[test]
fn sparse_steps_leave_zero_gradient_entries_untouched() {
    let n = 3000;
    let cfg = AdamConfig { lr: 0.05, beta1: 0.8, beta2: 0.95, eps: 1e-6, weight_decay: 0.01, grad_clip_norm: None, skip_zero_gradients: true };
    let p0 = uniform(n, -1.0, 1.0, 3);
    // Entry i is reached on step s when (i + s) % 4 == 0 (a quarter per step, each a different
    // quarter), except the last 100, which no step reaches.
    let grads: Vec<Vec<f32>> = (0..4)
        .map(|s| uniform(n, -1.0, 1.0, 20 + s as u64).iter().enumerate().map(|(i, g)| if (i + s) % 4 == 0 && i < n - 100 { *g } else { 0.0 }).collect())
        .collect();
    let mut reference = Reference { p: p0.iter().map(|&x| x as f64).collect(), m: vec![0.0; n], v: vec![0.0; n], t: 0 };
    for g in &grads {
        reference.step(&cfg, g, cfg.lr as f64);
    }
    for b in backends() {
        let mut p = b.upload(&p0);
        let mut st = AdamState::new(&b, n);
        for g in &grads {
            assert!(b.adam_step(&cfg, &mut st, &mut p, &b.upload(g), cfg.lr).unwrap().applied);
        }
        let (p, m, v) = (b.to_vec(&p).unwrap(), b.to_vec(&st.m).unwrap(), b.to_vec(&st.v).unwrap());
        assert_close(&format!("{} params", b.name()), &p, &reference.p, Tolerance::new(1e-5, 1e-6));
        assert_close(&format!("{} m", b.name()), &m, &reference.m, Tolerance::new(1e-5, 1e-6));
        assert_close(&format!("{} v", b.name()), &v, &reference.v, Tolerance::new(1e-5, 1e-9));
        for i in n - 100..n {
            assert!(p[i] == p0[i] && m[i] == 0.0 && v[i] == 0.0, "{}: untouched entry {i} moved", b.name());
        }
        // An entry reached once, on step 0, keeps its moments from then on (no decay).
        let i = 4;
        assert!(m[i] != 0.0 && (m[i] as f64 - 0.2 * grads[0][i] as f64).abs() < 1e-6, "{}: m {}", b.name(), m[i]);
    }
    // Without the flag the zero-gradient entries decay (weight decay moves every parameter).
    let dense = AdamConfig { skip_zero_gradients: false, ..cfg.clone() };
    let cpu = Backend::cpu();
    let mut p = cpu.upload(&p0);
    let mut st = AdamState::new(&cpu, n);
    cpu.adam_step(&dense, &mut st, &mut p, &cpu.upload(&grads[0]), dense.lr).unwrap();
    assert!(cpu.to_vec(&p).unwrap()[n - 1] != p0[n - 1]);
    // The trainers' host path: the same bits as adam_step, and None for a non-finite gradient.
    let mut a = cpu.upload(&p0);
    let mut sa = AdamState::new(&cpu, n);
    let mut h = p0.clone();
    let mut sh = AdamState::new(&cpu, n);
    for g in &grads {
        cpu.adam_step(&cfg, &mut sa, &mut a, &cpu.upload(g), cfg.lr).unwrap();
        let norm = host_grad_norm(&[g]).unwrap();
        adam_update_host(&cfg, &mut sh, &mut h, g, cfg.lr, norm).unwrap();
    }
    assert!(pii_bake::util::same_bits(&cpu.to_vec(&a).unwrap(), &h));
    assert_eq!(sh.step, 4);
    let mut bad = grads[0].clone();
    bad[7] = f32::NAN;
    assert_eq!(host_grad_norm(&[&grads[1], &bad]), None);
    bad[7] = f32::INFINITY;
    assert_eq!(host_grad_norm(&[&bad]), None);
    let want = grads[1].iter().chain(&grads[2]).map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
    assert!((host_grad_norm(&[&grads[1], &grads[2]]).unwrap() - want).abs() < 1e-9 * want);
}
