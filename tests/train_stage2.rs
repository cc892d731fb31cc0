//! Stage 2 at tiny sizes: the whole loss (shading, environment, indirect mixture through F_ind,
//! material autoencoder with its smoothness and KL terms) against central differences on the cpu
//! backend; wgpu (lavapipe) against cpu on one step's gradients; NaN never reaching parameters; a
//! tiny run that learns an albedo under a known light.

use pii_bake::backend::Backend;
use pii_bake::nn::field::Encoder;
use pii_bake::sg::shade::Sg;
use pii_bake::train::stage1::Preset;
use pii_bake::train::stage2::{boundary_visibility, loss_and_grad, loss_and_grad_geometry, BoundaryMode, DecoderMode, IndirectMix, IndirectMode, RoughnessMode, Stage2Batch, Stage2Config, Stage2Grads, Stage2Model, Stage2Trainer, Stage2Weights};

fn tiny(indirect: IndirectMode, decoder: DecoderMode) -> Stage2Config {
    let mut c = Stage2Config::new(Preset::Fast, 1000);
    c.lobes = 5;
    c.indirect = indirect;
    c.decoder = decoder;
    c.pos_freqs = 2;
    c.dir_freqs = 1;
    c.material_widths = vec![8, 8];
    c.latent_dim = 4;
    c.decoder_widths = vec![6];
    c.indirect_widths = vec![8];
    c.seed = 3;
    c
}

fn norm(v: [f32; 3]) -> [f32; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|x| x / l)
}

/// Five points on a sphere of radius 0.5 seen from +z, two with blocked lobes.
fn batch() -> Stage2Batch {
    let mut b = Stage2Batch::default();
    let pts = [[0.1f32, 0.2, 0.44], [-0.3, 0.1, 0.38], [0.0, -0.25, 0.43], [0.35, -0.1, 0.34], [-0.1, -0.1, 0.48]];
    let targets = [[0.6f32, 0.4, 0.3], [0.2, 0.5, 0.7], [0.45, 0.45, 0.45], [0.8, 0.3, 0.2], [0.3, 0.6, 0.35]];
    for (i, p) in pts.iter().enumerate() {
        b.x.push(*p);
        b.n.push(norm(*p));
        b.v.push(norm([0.05, 0.1, 1.0]));
        b.target.push(targets[i]);
        b.hits.push(Vec::new());
    }
    b.hits[0] = vec![(1, [0.2, 0.4, 0.1], norm([0.3, 0.9, 0.2])), (3, [0.5, 0.0, 0.1], norm([1.0, 0.1, 0.1]))];
    b.hits[3] = vec![(0, [-0.2, 0.3, 0.2], norm([-0.4, 0.6, 0.5]))];
    // The `mii` baseline's supervision: radiance along two directions per point (0 = unblocked).
    b.mii_targets = (0..pts.len()).map(|i| vec![(norm([0.3, 0.9, 0.2]), [0.2 + 0.1 * i as f32, 0.3, 0.1]), (norm([-0.5, 0.2, 0.8]), [0.0; 3])]).collect();
    b
}

fn weights() -> Stage2Weights {
    // A wide latent perturbation keeps the smoothness term's L1 away from its kink.
    Stage2Weights { smooth: 0.1, sigma: 0.3, kl: 0.05, rho: 0.05 }
}

fn grads(b: &Backend, m: &Stage2Model) -> Stage2Grads {
    grads_on(b, m, &batch())
}

fn grads_on(b: &Backend, m: &Stage2Model, batch: &Stage2Batch) -> Stage2Grads {
    loss_and_grad(b, m, batch, &weights(), 7).unwrap()
}

fn check_group(what: &str, analytic: &[f32], len: usize, model: &Stage2Model, set: &dyn Fn(&mut Stage2Model, usize, f32)) {
    check_group_on(&batch(), what, analytic, len, model, set)
}

fn check_group_on(batch: &Stage2Batch, what: &str, analytic: &[f32], len: usize, model: &Stage2Model, set: &dyn Fn(&mut Stage2Model, usize, f32)) {
    let b = Backend::cpu();
    let grads = |b: &Backend, m: &Stage2Model| grads_on(b, m, batch);
    let mut checked = 0;
    for idx in (0..len).step_by((len / 30).max(1)) {
        let h = 1e-3f32;
        let mut mp = model.clone();
        set(&mut mp, idx, h);
        let mut mm = model.clone();
        set(&mut mm, idx, -h);
        let fd = (grads(&b, &mp).stats.loss - grads(&b, &mm).stats.loss) / (2.0 * h as f64);
        let a = analytic[idx] as f64;
        let err = (a - fd).abs() / (2e-5 + 0.03 * fd.abs().max(a.abs()));
        assert!(err <= 1.0, "{what} param {idx}: analytic {a:.6e} vs central difference {fd:.6e}");
        checked += 1;
    }
    assert!(checked >= len.min(20), "{what}: {checked} checked");
}

fn check_all(indirect: IndirectMode, decoder: DecoderMode) {
    check_config(tiny(indirect, decoder));
}

fn check_config(cfg: Stage2Config) {
    let indirect = cfg.indirect;
    let b = Backend::cpu();
    let model = Stage2Model::new(&cfg).unwrap();
    let g = grads(&b, &model);
    assert!(g.stats.rgb > 0.0 && g.stats.smooth > 0.0 && g.stats.kl > 0.0, "{:?}", g.stats);
    let expect_blocked = if indirect == IndirectMode::None { 0 } else { 3 };
    assert_eq!(g.stats.blocked, expect_blocked);
    check_group("light", &g.d_light, model.light.len(), &model, &|m, i, h| m.light[i] += h);
    check_group("encoder", &g.d_enc, model.enc_params.len(), &model, &|m, i, h| m.enc_params[i] += h);
    for d in 0..model.dec_params.len() {
        check_group(&format!("decoder{d}"), &g.d_dec[d], model.dec_params[d].len(), &model, &|m, i, h| m.dec_params[d][i] += h);
    }
    if matches!(indirect, IndirectMode::Ours | IndirectMode::Mii) {
        assert!(g.d_ind.iter().any(|v| v.abs() > 1e-7), "F_ind gets a gradient");
        assert_eq!(g.stats.indirect_fit > 0.0, indirect == IndirectMode::Mii);
        check_group("indirect", &g.d_ind, model.ind_params.len(), &model, &|m, i, h| m.ind_params[i] += h);
    } else {
        assert!(g.d_ind.iter().all(|v| *v == 0.0));
    }
}

#[test]
fn whole_loss_gradient_matches_central_differences_with_indirect() {
    check_all(IndirectMode::Ours, DecoderMode::Separate);
    // A run from before F_ind gave the occluder's reflectance: K outputs only.
    let mut old = tiny(IndirectMode::Ours, DecoderMode::Separate);
    old.occluder_reflectance = false;
    assert_eq!(old.indirect_mlp().out_dim, old.lobes);
    check_config(old);
    // The amplitudes stored as logs (`log_amplitude`).
    let mut log = tiny(IndirectMode::Ours, DecoderMode::Separate);
    log.log_amplitude = true;
    check_config(log);
}

/// `tiny` with the metallic channel. It starts near m = 0.5, where both its specular and diffuse
/// paths carry weight, so the check sees its gradient at full size.
fn tiny_metal(decoder: DecoderMode) -> Stage2Config {
    let mut c = tiny(IndirectMode::Ours, decoder);
    c.metallic = true;
    c
}

#[test]
fn metallic_gradient_matches_central_differences_and_old_runs_read_dielectric() {
    use pii_bake::sg::shade::BrdfModel;
    let b = Backend::cpu();
    for (decoder, brdf) in [(DecoderMode::Separate, BrdfModel::Physg), (DecoderMode::Shared, BrdfModel::Physg), (DecoderMode::Separate, BrdfModel::Calibrated)] {
        let mut cfg = tiny_metal(decoder);
        cfg.brdf = brdf;
        assert_eq!(cfg.material_channels(), 5);
        let model = Stage2Model::new(&cfg).unwrap();
        let metal = model.material(&b, &batch().x).unwrap().metallic;
        assert!(metal.iter().all(|&m| m > 0.2 && m < 0.8), "{metal:?}");
        let g = grads(&b, &model);
        check_group("light", &g.d_light, model.light.len(), &model, &|m, i, h| m.light[i] += h);
        check_group("encoder", &g.d_enc, model.enc_params.len(), &model, &|m, i, h| m.enc_params[i] += h);
        for d in 0..model.dec_params.len() {
            check_group(&format!("decoder{d}"), &g.d_dec[d], model.dec_params[d].len(), &model, &|m, i, h| m.dec_params[d][i] += h);
        }
        check_group("indirect", &g.d_ind, model.ind_params.len(), &model, &|m, i, h| m.ind_params[i] += h);
    }
    // Off: four channels, metallic 0 everywhere; a run file without the field reads off.
    let off = tiny(IndirectMode::Ours, DecoderMode::Shared);
    assert_eq!(off.decoder_mlps()[0].0.out_dim, 4);
    assert!(Stage2Model::new(&off).unwrap().material(&b, &batch().x).unwrap().metallic.iter().all(|&m| m == 0.0));
    let mut v = serde_json::to_value(&off).unwrap();
    v.as_object_mut().unwrap().remove("metallic");
    assert!(!serde_json::from_value::<Stage2Config>(v.clone()).unwrap().metallic);
    // Runs from before the calibrated BRDF read (and resume) with the form they were trained with.
    v.as_object_mut().unwrap().remove("brdf");
    v.as_object_mut().unwrap().remove("brdf_warmup");
    let old = serde_json::from_value::<Stage2Config>(v).unwrap();
    assert_eq!(old.brdf, BrdfModel::Physg);
    assert_eq!(old.brdf_warmup, 0.0, "runs from before the warm-up resume without it");
}

#[test]
fn a_metal_tints_its_highlights_with_its_albedo_and_loses_its_diffuse() {
    use pii_bake::sg::shade::F0;
    use pii_bake::train::stage2::{shade_f64, PointShading};
    use pii_bake::sg::shade::BrdfModel;
    // Both BRDF forms: the paper's and the one calibrated to Cycles.
    for model in [BrdfModel::Physg, BrdfModel::Calibrated] {
        let lobes = vec![Sg { axis: [0.2, 1.0, 0.3], lambda: 20.0, mu: [2.0, 2.0, 2.0] }, Sg { axis: [-0.5, 0.5, 0.1], lambda: 1.0, mu: [0.4, 0.4, 0.4] }];
        let (n, v) = ([0.0, 1.0, 0.0], [0.3, 0.9, 0.2]);
        let albedo = [0.9, 0.6, 0.2];
        let rough = 0.3;
        let (s0, d0) = shade_f64(model, albedo, rough, 0.0, n, v, &lobes);
        let (s1, d1) = shade_f64(model, albedo, rough, 1.0, n, v, &lobes);
        for c in 0..3 {
            // A full metal: no diffuse; its specular scaled by albedo/F0 (a grey light: the highlight takes the albedo's colour).
            assert_eq!(d1[c], 0.0);
            assert!(s1[c] > s0[c] * 3.0, "channel {c}: {} vs {}", s1[c], s0[c]);
        }
        assert!(s1[0] > s1[1] && s1[1] > s1[2], "{s1:?}");
        assert!(s0[0] == s0[1] && s0[1] == s0[2], "a dielectric's highlight is the light's colour: {s0:?}");
        // Halfway: linear in m between the two.
        let (sh, dh) = shade_f64(model, albedo, rough, 0.5, n, v, &lobes);
        for c in 0..3 {
            assert!((sh[c] - 0.5 * (s0[c] + s1[c])).abs() < 1e-12 && (dh[c] - 0.5 * d0[c]).abs() < 1e-12);
        }
        // The training's shading (duals) agrees and its metallic / albedo gradients are the
        // central differences of the render.
        let d_out = [0.7, -0.2, 0.4];
        let m = 0.35;
        let ps = PointShading::new(model, albedo, rough, m, n, v, &lobes);
        let (ss, sd) = shade_f64(model, albedo, rough, m, n, v, &lobes);
        for c in 0..3 {
            assert!((ps.spec[c] - ss[c]).abs() < 1e-12 && (ps.diff[c] - sd[c]).abs() < 1e-12);
        }
        let (da, _, dm, _) = ps.grad(albedo, m, &lobes, d_out);
        let f = |a: [f64; 3], m: f64| {
            let (s, d) = shade_f64(model, a, rough, m, n, v, &lobes);
            (0..3).map(|c| d_out[c] * (s[c] + d[c])).sum::<f64>()
        };
        let h = 1e-6;
        let fd_m = (f(albedo, m + h) - f(albedo, m - h)) / (2.0 * h);
        assert!((dm - fd_m).abs() <= 1e-6 * fd_m.abs().max(1.0), "d metallic {dm} vs {fd_m}");
        for c in 0..3 {
            let (mut p, mut q) = (albedo, albedo);
            p[c] += h;
            q[c] -= h;
            let fd = (f(p, m) - f(q, m)) / (2.0 * h);
            assert!((da[c] - fd).abs() <= 1e-6 * fd.abs().max(1.0), "d albedo {c}: {} vs {fd}", da[c]);
        }
        assert!(F0 < albedo[2], "the test's albedo is above F0 in every channel");
    }
}

#[test]
fn roughness_light_and_normal_gradients_match_central_differences_in_both_brdf_forms() {
    use pii_bake::sg::shade::BrdfModel;
    use pii_bake::train::stage2::{shade_f64, shade_normal_grad, PointShading};
    let lobes = vec![
        Sg { axis: [0.2, 1.0, 0.3], lambda: 12.0, mu: [1.5, 1.2, 0.9] },
        Sg { axis: [-0.6, 0.5, 0.1], lambda: 2.0, mu: [0.4, 0.5, 0.6] },
        Sg { axis: [0.5, 0.3, -0.4], lambda: 40.0, mu: [0.8, 0.8, 0.8] },
    ];
    let (n, v) = ([0.05, 1.0, 0.1], [0.35, 0.85, 0.25]);
    let (albedo, m) = ([0.7, 0.5, 0.3], 0.4);
    let d_out = [0.6, -0.3, 0.5];
    let h = 1e-6;
    let close = |a: f64, b: f64, what: &str| assert!((a - b).abs() <= 1e-5 * b.abs().max(1e-2), "{what}: {a} vs central differences {b}");
    for model in [BrdfModel::Physg, BrdfModel::Calibrated] {
        for rough in [0.15, 0.45, 0.85] {
            let f = |r: f64, n: [f64; 3], l: &[Sg<f64>]| {
                let (s, d) = shade_f64(model, albedo, r, m, n, v, l);
                (0..3).map(|c| d_out[c] * (s[c].max(0.0) + d[c].max(0.0))).sum::<f64>()
            };
            let ps = PointShading::new(model, albedo, rough, m, n, v, &lobes);
            let (_, dr, _, dl) = ps.grad(albedo, m, &lobes, d_out);
            close(dr, (f(rough + h, n, &lobes) - f(rough - h, n, &lobes)) / (2.0 * h), &format!("{model:?} R {rough}: d roughness"));
            for (k, g) in dl.iter().enumerate() {
                // Axis (3), sharpness, amplitude (3).
                for p in 0..7 {
                    let bump = |e: f64| {
                        let mut l = lobes.clone();
                        match p {
                            0..=2 => l[k].axis[p] += e,
                            3 => l[k].lambda += e,
                            _ => l[k].mu[p - 4] += e,
                        }
                        f(rough, n, &l)
                    };
                    close(g[p], (bump(h) - bump(-h)) / (2.0 * h), &format!("{model:?} R {rough}: lobe {k} parameter {p}"));
                }
            }
            let (spec, diff) = shade_f64(model, albedo, rough, m, n, v, &lobes);
            let dn = shade_normal_grad(model, albedo, rough, m, n, v, &lobes, spec, diff, d_out);
            for a in 0..3 {
                let (mut p, mut q) = (n, n);
                p[a] += h;
                q[a] -= h;
                close(dn[a], (f(rough, p, &lobes) - f(rough, q, &lobes)) / (2.0 * h), &format!("{model:?} R {rough}: d normal {a}"));
            }
        }
    }
}

#[test]
fn light_amplitudes_stored_as_logs_read_back_and_runs_without_the_field_read_linear() {
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    assert!(!cfg.log_amplitude, "linear amplitudes by default");
    cfg.log_amplitude = true;
    let mut m = Stage2Model::new(&cfg).unwrap();
    let mut lobes = m.lobes();
    // A sun-like lobe thousands of times brighter than the others, and a dark channel.
    lobes[1].mu = [3000.0, 2500.0, 0.0];
    lobes[1].lambda = 2000.0;
    m.set_light(&lobes).unwrap();
    assert!((m.light[7 + 4] - 3000f32.ln()).abs() < 1e-6 && m.light[7 + 6] == -40.0, "{:?}", &m.light[7..14]);
    let back = m.lobes();
    assert!((back[1].mu[0] / 3000.0 - 1.0).abs() < 1e-5 && (back[1].mu[1] / 2500.0 - 1.0).abs() < 1e-5 && back[1].mu[2] < 1e-15, "{:?}", back[1]);
    assert!((back[1].lambda / 2000.0 - 1.0).abs() < 1e-5);
    // The initial light has the same energy in either form.
    let mut old = cfg.clone();
    old.log_amplitude = false;
    let lin = Stage2Model::new(&old).unwrap();
    for (a, b) in lin.lobes().iter().zip(&Stage2Model::new(&cfg).unwrap().lobes()) {
        assert!(a.mu.iter().zip(&b.mu).all(|(x, y)| (x / y - 1.0).abs() < 1e-5), "{a:?} vs {b:?}");
    }
    // A run written before the field existed reads μ raw.
    let mut json = serde_json::to_value(&cfg).unwrap();
    json.as_object_mut().unwrap().remove("log_amplitude");
    let read: Stage2Config = serde_json::from_value(json).unwrap();
    assert!(!read.log_amplitude);
    // A negative amplitude is refused.
    lobes[0].mu[0] = -1.0;
    assert!(m.set_light(&lobes).is_err());
}

#[test]
fn unit_axes_stay_unit_length_turn_as_the_raw_ones_and_old_runs_read_false() {
    let b = Backend::cpu();
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    assert!(cfg.unit_axes, "new runs keep their axes at unit length");
    let axes = |t: &Stage2Trainer| t.model.light.chunks_exact(7).map(|l| [l[0], l[1], l[2]]).collect::<Vec<_>>();
    let len = |a: &[f32; 3]| (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    let mut unit = Stage2Trainer::new(&cfg).unwrap();
    cfg.unit_axes = false;
    let mut raw = Stage2Trainer::new(&cfg).unwrap();
    assert_eq!(unit.model.light, raw.model.light, "the same start");
    // One step from the same state: the same directions, one of them rescaled.
    for t in [&mut unit, &mut raw] {
        let g = grads(&b, &t.model);
        assert!(t.apply(g).unwrap().0);
    }
    for (u, r) in axes(&unit).iter().zip(&axes(&raw)) {
        assert!((len(u) - 1.0).abs() < 1e-6, "unit axis of length {}", len(u));
        let cos = (u[0] * r[0] + u[1] * r[1] + u[2] * r[2]) / len(r);
        assert!(cos > 1.0 - 1e-6, "the same direction: cos {cos}");
    }
    // Over a run the raw axes lengthen; the unit ones stay unit.
    for step in 0..40 {
        for t in [&mut unit, &mut raw] {
            let g = loss_and_grad(&b, &t.model, &batch(), &weights(), step).unwrap();
            assert!(t.apply(g).unwrap().0);
        }
    }
    assert!(axes(&unit).iter().all(|a| (len(a) - 1.0).abs() < 1e-5));
    assert!(axes(&raw).iter().any(|a| len(a) > 1.0 + 1e-3), "{:?}", axes(&raw).iter().map(len).collect::<Vec<_>>());
    // A run written before the field existed reads false.
    let mut json = serde_json::to_value(&cfg).unwrap();
    json.as_object_mut().unwrap().remove("unit_axes");
    let read: Stage2Config = serde_json::from_value(json).unwrap();
    assert!(!read.unit_axes);
}

#[test]
fn a_dark_occluder_re_emits_less_than_the_dimmest_lobe() {
    let lobe = |mu: f64, z: f64| Sg { axis: [0.0, 0.0, z], lambda: 10.0, mu: [mu; 3] };
    let lobes = [lobe(2.0, 1.0), lobe(1.0, -1.0)];
    // F_ind's sigmoid row: two weights (normalised to 1/4, 3/4), then ρ per channel.
    let (mix, sums) = IndirectMix::from_sigmoid(&[0.2, 0.6, 0.5, 0.1, 1.0], 2, 3);
    assert!((sums[0] - 0.8).abs() < 1e-6 && (mix.row(0)[0] - 0.25).abs() < 1e-6);
    let r = mix.lobe(&lobes, 1, 0);
    let plain = 0.25 * 2.0 + 0.75 * 1.0;
    for (c, rho) in [0.5, 0.1, 1.0].iter().enumerate() {
        assert!((r.mu[c] - rho * plain).abs() < 1e-6, "channel {c}: {} vs {}", r.mu[c], rho * plain);
    }
    assert!(r.mu[1] < 1.0, "darker than the dimmest environment lobe");
    assert_eq!(r.axis, lobes[1].axis);
    // Without reflectance outputs (uniform, old runs) ρ is 1: the paper's mixture.
    let (plain_mix, _) = IndirectMix::from_sigmoid(&[0.2, 0.6], 2, 0);
    assert!((plain_mix.lobe(&lobes, 1, 0).mu[0] - plain).abs() < 1e-6);
}

#[test]
fn gradient_matches_for_baselines_and_shared_decoder() {
    check_all(IndirectMode::Uniform, DecoderMode::Shared);
    check_all(IndirectMode::None, DecoderMode::Separate);
}

#[test]
fn gradient_matches_for_the_mii_baseline() {
    // An MLP at x gives 24 SGs of indirect light; blocked lobes are dropped. Its fit to the
    // stage-1 radiance and the render both reach it.
    let mut c = tiny(IndirectMode::Mii, DecoderMode::Separate);
    c.mii_lobes = 3;
    check_config(c);
}

#[test]
fn gradient_matches_with_constant_roughness_and_hash_grid_material() {
    // PhySG-like baseline: one roughness for the object, both decoder layouts.
    for decoder in [DecoderMode::Separate, DecoderMode::Shared] {
        for metallic in [false, true] {
            let mut c = tiny(IndirectMode::None, decoder);
            c.roughness = RoughnessMode::Constant;
            // The metallic channel stays per point beside the constant roughness (same decoder).
            c.metallic = metallic;
            check_config(c);
        }
    }
    // The material field on a (tiny) hash grid: its tables lead the encoder's parameters.
    let mut c = tiny(IndirectMode::Ours, DecoderMode::Separate).with_material_grid(8, 6);
    // (seed 3 puts one decoder weight within 1e-3 of an L1 kink: a seed whose differences are clean)
    c.seed = 5;
    let m = Stage2Model::new(&c).unwrap();
    assert!(m.mat_enc.num_params() > 0 && m.enc_params.len() > m.encoder.num_params());
    check_config(c);
}

#[test]
fn constant_roughness_is_one_value_for_the_object() {
    let b = Backend::cpu();
    let mut c = tiny(IndirectMode::None, DecoderMode::Separate);
    c.roughness = RoughnessMode::Constant;
    let m = Stage2Model::new(&c).unwrap();
    let rough = m.material(&b, &batch().x).unwrap().roughness;
    assert!(rough.iter().all(|&r| r == rough[0] && r > 0.0 && r < 1.0), "{rough:?}");
    let mut f = m.clone();
    f.cfg.roughness = RoughnessMode::Field;
    let varying = f.material(&b, &batch().x).unwrap().roughness;
    assert!(varying.iter().any(|&r| r != varying[0]), "the field varies: {varying:?}");
}

#[test]
fn a_low_roughness_still_learns() {
    // The roughness decoder's sigmoid near 0.01 everywhere (last layer: weights scaled by 0.01,
    // bias logit(0.01); not exactly constant, which would sit on the smoothness L1's kink).
    // Shading clamps roughness to [R_MIN, 1]; the decoder's output is mapped onto that range, so
    // a low roughness is what shading uses, what the textures get, and it still has a gradient
    // (a raw sigmoid below R_MIN sat in the clamp with none, and glossy scenes learnt roughness 0).
    let b = Backend::cpu();
    let mut m = Stage2Model::new(&tiny(IndirectMode::None, DecoderMode::Separate)).unwrap();
    assert_eq!(m.decoders[1].0.out_dim(), 1, "the separate roughness decoder");
    let p = &mut m.dec_params[1];
    let n = p.len();
    let last_in = *tiny(IndirectMode::None, DecoderMode::Separate).decoder_widths.last().unwrap();
    p[n - 1 - last_in..n - 1].iter_mut().for_each(|w| *w *= 0.01);
    p[n - 1] = (0.01f32 / 0.99).ln();
    let rough = m.material(&b, &batch().x).unwrap().roughness;
    let r_min = pii_bake::sg::shade::R_MIN as f32;
    assert!(rough.iter().all(|&r| r > r_min && (r - (r_min + (1.0 - r_min) * 0.01)).abs() < 1e-3), "{rough:?}");
    let g = grads(&b, &m);
    // Through the clamp this was exactly 0 from shading.
    assert!(g.d_dec[1][n - 1].abs() > 1e-9, "the roughness bias gets a gradient: {}", g.d_dec[1][n - 1]);
    check_group("roughness decoder", &g.d_dec[1], n, &m, &|m, i, h| m.dec_params[1][i] += h);
}

#[test]
fn idle_lobes_are_left_out_of_the_exported_environment() {
    let mut m = Stage2Model::new(&tiny(IndirectMode::Ours, DecoderMode::Separate)).unwrap();
    assert!(m.idle_lobes().is_empty());
    assert_eq!(m.env_sgs(glam::DMat3::IDENTITY).lobes.len(), 5);
    // Lobe 2 goes dark: it is idle and not exported; the others keep their order.
    let mut lobes = m.lobes();
    lobes[2].mu = [0.0; 3];
    m.set_light(&lobes).unwrap();
    assert_eq!(m.idle_lobes(), vec![2]);
    let env = m.env_sgs(glam::DMat3::IDENTITY);
    assert_eq!(env.lobes.len(), 4);
    assert_eq!(env.lobes[2].axis, m.axes()[3]);
    // An all-dark light keeps every lobe rather than exporting none.
    lobes.iter_mut().for_each(|l| l.mu = [0.0; 3]);
    m.set_light(&lobes).unwrap();
    assert!(m.idle_lobes().is_empty());
}

#[test]
fn a_known_light_keeps_its_shape_and_learns_its_exposure() {
    // `light_fixed` (`--known-env`): photos rendered under light L, training started from 0.5·L
    // with the material frozen, so only the light can explain them: the axes and sharpness stay
    // bit for bit, every amplitude moves by one common factor, and that factor comes back to 2.
    for log_amplitude in [true, false] {
        known_light_run(log_amplitude);
    }
}

fn known_light_run(log_amplitude: bool) {
    let b = Backend::cpu();
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    cfg.log_amplitude = log_amplitude;
    cfg.light_fixed = true;
    cfg.lr_material = 0.0;
    cfg.lr_indirect = 0.0;
    cfg.lr_light = 0.02;
    cfg.lr_final_factor = 1.0;
    let truth = Stage2Model::new(&cfg).unwrap();
    let mut batch = batch();
    batch.target = grads_on(&b, &truth, &batch).rgb.iter().map(|c| c.map(pii_bake::image_io::linear_to_srgb)).collect();
    let mut t = Stage2Trainer::new(&cfg).unwrap();
    t.model = truth.clone();
    // Half the amplitudes, in the run's storage (set_light would also round the axes and ln λ).
    t.model.light.chunks_exact_mut(7).for_each(|l| l[4..7].iter_mut().for_each(|m| if log_amplitude { *m += 0.5f32.ln() } else { *m *= 0.5 }));
    for step in 0..300 {
        let g = loss_and_grad(&b, &t.model, &batch, &weights(), step).unwrap();
        assert!(t.apply(g).unwrap().0);
    }
    assert!((t.exposure - 2.0).abs() < 0.04, "learnt exposure {}", t.exposure);
    for ((l, l0), (g, g0)) in t.model.light.chunks_exact(7).zip(truth.light.chunks_exact(7)).zip(t.model.lobes().iter().zip(&truth.lobes())) {
        assert_eq!(l[..4], l0[..4], "axis and sharpness are the map's");
        for c in 0..3 {
            assert!((g.mu[c] / g0.mu[c] - 1.0).abs() < 0.02, "amplitude {} of {} after learning the exposure", g.mu[c], g0.mu[c]);
        }
    }
}

#[test]
fn blocked_lobes_change_the_render() {
    // With F_ind the blocked lobes are replaced: the loss differs from the unoccluded one.
    let b = Backend::cpu();
    let ours = Stage2Model::new(&tiny(IndirectMode::Ours, DecoderMode::Separate)).unwrap();
    let mut none = ours.clone();
    none.cfg.indirect = IndirectMode::None;
    let (a, c) = (grads(&b, &ours), grads(&b, &none));
    assert!((a.rgb[0][0] - c.rgb[0][0]).abs() > 1e-5 || (a.rgb[0][1] - c.rgb[0][1]).abs() > 1e-5);
    assert_eq!(a.rgb[1], c.rgb[1], "a point without blocked lobes renders the same");
}

#[test]
fn nan_gradients_never_reach_parameters() {
    let b = Backend::cpu();
    let mut t = Stage2Trainer::new(&tiny(IndirectMode::Ours, DecoderMode::Separate)).unwrap();
    let before = t.model.clone();
    let mut g = grads(&b, &t.model);
    g.d_light[2] = f32::NAN;
    let (applied, _) = t.apply(g).unwrap();
    assert!(!applied);
    assert_eq!(t.skipped, 1);
    assert_eq!(t.model.light, before.light);
    assert_eq!(t.model.enc_params, before.enc_params);
    let mut g = grads(&b, &t.model);
    g.d_ind[0] = f32::INFINITY;
    assert!(!t.apply(g).unwrap().0 && t.skipped == 2 && t.model.ind_params == before.ind_params);
    let g = grads(&b, &t.model);
    assert!(t.apply(g).unwrap().0);
    assert_ne!(t.model.light, before.light);
}

#[test]
fn wgpu_matches_cpu_on_one_steps_gradients() {
    let gpu = Backend::wgpu_for_tests().unwrap_or_else(|e| panic!("the test command installs lavapipe: {e}"));
    let cpu = Backend::cpu();
    // With the light–albedo balance learnt and its albedo scale away from 1.
    let mut model = Stage2Model::new(&tiny(IndirectMode::Ours, DecoderMode::Separate)).unwrap();
    assert!(model.cfg.learns_balance(), "new runs learn the balance");
    model.albedo_scale = 0.8;
    let (a, c) = (grads(&cpu, &model), grads(&gpu, &model));
    assert!(a.d_balance != 0.0 && (a.d_balance - c.d_balance).abs() <= 1e-3 * a.d_balance.abs(), "balance: cpu {} vs wgpu {}", a.d_balance, c.d_balance);
    assert!((a.stats.loss - c.stats.loss).abs() < 1e-5 * (1.0 + a.stats.loss.abs()), "{} vs {}", a.stats.loss, c.stats.loss);
    let close = |what: &str, x: &[f32], y: &[f32]| {
        let scale = x.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
        for (i, (p, q)) in x.iter().zip(y).enumerate() {
            assert!((p - q).abs() <= 1e-3 * scale + 1e-6, "{what}[{i}]: cpu {p} vs wgpu {q}");
        }
    };
    close("light", &a.d_light, &c.d_light);
    close("encoder", &a.d_enc, &c.d_enc);
    close("indirect", &a.d_ind, &c.d_ind);
    for d in 0..a.d_dec.len() {
        close("decoder", &a.d_dec[d], &c.d_dec[d]);
    }
}


/// The test batch with the traced axes known and point 3's hit of lobe 0 grazing the occluder
/// (`n'·ξ0 = 0`, a boundary light), traced along an axis 0.6° from lobe 0's current one.
fn boundary_batch(model: &Stage2Model) -> Stage2Batch {
    let mut b = batch();
    let axes = model.axes();
    let a = axes[0];
    // A direction perpendicular to the axis, and the traced axis turned slightly toward it.
    let p = norm([a[1] - a[2], a[2] - a[0], a[0] - a[1]]);
    let t0 = norm([a[0] + 0.01 * p[0], a[1] + 0.01 * p[1], a[2] + 0.01 * p[2]]);
    let q = [t0[1] * p[2] - t0[2] * p[1], t0[2] * p[0] - t0[0] * p[2], t0[0] * p[1] - t0[1] * p[0]];
    // n' ⟂ ξ0, mostly along p (so turning the axis moves it across the silhouette).
    let d = p[0] * t0[0] + p[1] * t0[1] + p[2] * t0[2];
    let n2 = norm([p[0] - d * t0[0] + 0.3 * q[0], p[1] - d * t0[1] + 0.3 * q[1], p[2] - d * t0[2] + 0.3 * q[2]]);
    b.hits[3] = vec![(0, [-0.2, 0.3, 0.2], n2)];
    b.traced_axes = axes;
    b.traced_axes[0] = t0;
    b
}

#[test]
fn boundary_visibility_ramps_across_the_silhouette() {
    let n2 = [0.0f32, 1.0, 0.0];
    let traced = [1.0f32, 0.0, 0.0];
    let eps = 0.0349;
    // On the traced axis: half visible; not a boundary light when the hit is not grazing.
    let (v, d, _) = boundary_visibility([2.0, 0.0, 0.0], traced, n2, 0.0, eps, BoundaryMode::Flowing).unwrap();
    assert!((v - 0.5).abs() < 1e-12);
    assert!((d[1] - 1.0 / (2.0 * eps * 2.0)).abs() < 1e-9 && d[0].abs() < 1e-12, "{d:?}");
    assert!(boundary_visibility([1.0, 0.0, 0.0], traced, [0.0, 0.1, 0.995], 0.0, eps, BoundaryMode::Flowing).is_some());
    assert!(boundary_visibility([1.0, 0.0, 0.0], traced, [0.1, 0.995, 0.0], 0.0, eps, BoundaryMode::Flowing).is_none());
    assert!(boundary_visibility([1.0, 0.0, 0.0], traced, n2, 0.0, 0.0, BoundaryMode::Flowing).is_none());
    // Turned past ε away from the occluder (along n'): fully visible, no gradient; into it: blocked.
    let turn = |a: f64| [a.cos(), a.sin(), 0.0];
    assert_eq!(boundary_visibility(turn(0.05), traced, n2, 0.0, eps, BoundaryMode::Flowing).unwrap(), (1.0, [0.0; 3], 0.0));
    assert_eq!(boundary_visibility(turn(-0.05), traced, n2, 0.0, eps, BoundaryMode::Flowing).unwrap(), (0.0, [0.0; 3], 0.0));
    let (v, _, dvo) = boundary_visibility(turn(0.01), traced, n2, 0.0, eps, BoundaryMode::Flowing).unwrap();
    assert!((dvo - 1.0 / (2.0 * eps)).abs() < 1e-9);
    assert!((v - (0.5 + 0.01f64.sin() / (2.0 * eps))).abs() < 1e-9);
    // Detached: the same value, no gradient.
    let (vd, dd, ddo) = boundary_visibility(turn(0.01), traced, n2, 0.0, eps, BoundaryMode::Detached).unwrap();
    assert_eq!((vd, dd, ddo), (v, [0.0; 3], 0.0));
    // A receding occluder (positive offset) opens the ray as turning the axis away from it does.
    let (vo, _, _) = boundary_visibility([1.0, 0.0, 0.0], traced, n2, 0.01f64.sin(), eps, BoundaryMode::Flowing).unwrap();
    assert!((vo - v).abs() < 1e-9);
}

#[test]
fn boundary_lights_pass_their_gradient_to_the_light() {
    let b = Backend::cpu();
    for mode in [IndirectMode::Ours, IndirectMode::Uniform, IndirectMode::Mii] {
        let mut cfg = tiny(mode, DecoderMode::Separate);
        cfg.mii_lobes = 3;
        let model = Stage2Model::new(&cfg).unwrap();
        let bb = boundary_batch(&model);
        let g = grads_on(&b, &model, &bb);
        assert_eq!(g.stats.boundary, 1, "{mode:?}");
        // The boundary light changes the render: the hard test would leave lobe 0 fully blocked.
        let mut hard = bb.clone();
        hard.traced_axes.clear();
        let gh = grads_on(&b, &model, &hard);
        assert_eq!(gh.stats.boundary, 0);
        assert!((g.stats.rgb - gh.stats.rgb).abs() > 1e-9, "{mode:?}: the boundary light is in the colour");
        // Flowing: every gradient, the axes' boundary term included, matches central differences.
        check_group_on(&bb, "light", &g.d_light, model.light.len(), &model, &|m, i, h| m.light[i] += h);
        if mode != IndirectMode::Uniform {
            check_group_on(&bb, "indirect", &g.d_ind, model.ind_params.len(), &model, &|m, i, h| m.ind_params[i] += h);
        }
        // Detached: the same loss; only lobe 0's axis loses the boundary term.
        let mut det = model.clone();
        det.cfg.boundary = BoundaryMode::Detached;
        let gd = grads_on(&b, &det, &bb);
        assert_eq!(gd.stats.loss, g.stats.loss);
        let diff: Vec<usize> = (0..g.d_light.len()).filter(|&i| (g.d_light[i] - gd.d_light[i]).abs() > 1e-7).collect();
        assert!(!diff.is_empty() && diff.iter().all(|&i| i < 3), "{mode:?}: the boundary term reaches lobe 0's axis only, got {diff:?}");
        assert_eq!(g.d_ind, gd.d_ind);
    }
}

/// A tiny stage-1 SDF: the geometric init's sphere of radius 0.5 (the batch's points lie on it).
fn tiny_sdf() -> pii_bake::train::stage1::Model {
    use pii_bake::nn::field::{FieldEncoding, SdfFieldConfig};
    use pii_bake::train::stage1::{InitMode, Stage1Config};
    let mut cfg = Stage1Config::for_scene(Preset::Fast, pii_bake::render::TraceMode::Classic, InitMode::Sphere, &[], 0, 1);
    cfg.field = SdfFieldConfig {
        encoding: FieldEncoding::Frequency { n_freqs: 2 },
        widths: vec![16, 16],
        skip_layers: vec![],
        activation: pii_bake::nn::mlp::Activation::Softplus { beta: 30.0 },
        weight_norm: false,
        feature_dim: 0,
        init_radius: 0.5,
        grad_step: 1e-2,
    };
    cfg.appearance_grid = false;
    cfg.radiance_widths = vec![8];
    cfg.view_freqs = 1;
    cfg.seed = 4;
    pii_bake::train::stage1::Model::new(&cfg).unwrap()
}

/// The tiny model with `--refine-geometry` that the geometry gradient checks differentiate.
fn refined_geometry_cfg(indirect: IndirectMode) -> Stage2Config {
    let mut cfg = tiny(indirect, DecoderMode::Separate);
    // PE2 material: PE10's 2^9 frequency would make the loss too wiggly along the ray for
    // central differences at any one step.
    cfg.material_encoding = pii_bake::nn::field::FieldEncoding::Frequency { n_freqs: 2 };
    // PhySG's form: the calibrated one makes this tiny SDF's loss too rough at the central
    // differences' scale (one-sided differences of ±0.2–0.4 at 3e-5 against a gradient of
    // 5e-3); its normal gradient is checked where the shading is formed
    // (`roughness_light_and_normal_gradients_match_central_differences_in_both_brdf_forms`).
    cfg.brdf = pii_bake::sg::shade::BrdfModel::Physg;
    cfg.refine_geometry = true;
    cfg.geometry_eikonal_points = 8;
    cfg
}

#[test]
fn refined_geometry_gradient_matches_central_differences() {
    // --refine-geometry: the SDF's gradient through the moved surface points, the shading normals,
    // the boundary light's receding occluder and the eikonal term, against central differences of
    // the whole loss (smoothness and KL off: they see the points fixed by design).
    let b = Backend::cpu();
    let sdf = tiny_sdf();
    let w = Stage2Weights { smooth: 0.0, sigma: 0.3, kl: 0.0, rho: 0.05 };
    for boundary in [BoundaryMode::Flowing, BoundaryMode::Detached] {
        let mut cfg = refined_geometry_cfg(IndirectMode::Ours);
        cfg.boundary = boundary;
        let model = Stage2Model::new(&cfg).unwrap();
        let mut bb = boundary_batch(&model);
        // The occluders' SDF when "traced": the boundary light starts half open.
        bb.hit_sdf = bb.hits.iter().map(|h| h.iter().map(|&(_, x2, _)| sdf.sdf(&b, &x2).unwrap()[0]).collect()).collect();
        let g = loss_and_grad_geometry(&b, &model, &bb, &w, 7, &sdf).unwrap();
        assert_eq!(g.stats.boundary, 1);
        assert!(g.stats.eikonal > 0.0 && g.d_sdf.len() == sdf.sdf_params.len());
        assert!(g.d_offset.iter().any(|v| v.abs() > 1e-9) == (boundary == BoundaryMode::Flowing), "{:?}", g.d_offset);
        let loss = |m: &pii_bake::train::stage1::Model| loss_and_grad_geometry(&b, &model, &bb, &w, 7, m).unwrap().stats.loss;
        if boundary == BoundaryMode::Detached {
            // The forward still moves the boundary light with the occluder; only its gradient is
            // cut: the same loss as flowing, a different SDF gradient (the central differences
            // follow the flowing one, checked above).
            let mut fl = model.clone();
            fl.cfg.boundary = BoundaryMode::Flowing;
            let gf = loss_and_grad_geometry(&b, &fl, &bb, &w, 7, &sdf).unwrap();
            assert_eq!(gf.stats.loss, g.stats.loss);
            assert!(gf.d_sdf.iter().zip(&g.d_sdf).any(|(p, q)| (p - q).abs() > 1e-6));
            continue;
        }
        let mut worst = 0.0f64;
        let step = (sdf.sdf_params.len() / 40).max(1);
        for i in (0..sdf.sdf_params.len()).step_by(step) {
            let fd = symmetric_slope(
                |d| {
                    let mut m = tiny_sdf();
                    m.sdf_params[i] += d;
                    loss(&m)
                },
                1e-3,
            );
            let a = g.d_sdf[i] as f64;
            let err = (a - fd).abs() / (1e-4 + 0.05 * fd.abs().max(a.abs()));
            worst = worst.max(err);
            assert!(err <= 1.0, "{boundary:?} sdf param {i}: analytic {a:.6e} vs central difference {fd:.6e}");
        }
        assert!(g.d_sdf.iter().any(|v| v.abs() > 1e-4));
        // The light's gradient of the same loss.
        for i in 0..model.light.len() {
            let h = 1e-3f32;
            let (mut mp, mut mm) = (model.clone(), model.clone());
            mp.light[i] += h;
            mm.light[i] -= h;
            let l = |m: &Stage2Model| loss_and_grad_geometry(&b, m, &bb, &w, 7, &sdf).unwrap().stats.loss;
            let fd = (l(&mp) - l(&mm)) / (2.0 * h as f64);
            let a = g.d_light[i] as f64;
            let err = (a - fd).abs() / (2e-5 + 0.03 * fd.abs().max(a.abs()));
            assert!(err <= 1.0, "{boundary:?} light param {i}: analytic {a:.6e} vs central difference {fd:.6e}");
        }
    }
}

#[test]
fn refined_geometry_ray_move_gradient_matches_central_differences() {
    // The SDF's output offset (its last parameter: checked below to shift every value by itself,
    // so it leaves every gradient, and so the normals and the eikonal term, alone) moves the
    // surface points along their rays and nothing else: with direct light only (no secondary
    // hits, no boundary light) the loss's slope along it is the ray-move term alone. The
    // whole-gradient check above sees that term only roughly: it is ~9 % of the largest checked
    // parameter's gradient there, so a tenth more of it stays under that check's 5 % tolerance
    // (measured by scaling the term: ×1.1 passed it, ×0 and ×2 failed). Here the slope is
    // -6.23e-3; the fit's reach is ±3e-3 (at ±1e-3 the f32 loss's rounding noise gives 1 %,
    // at ±3e-3 and ±1e-2 the analytic value is within 0.27 %), the tolerance 2 %.
    let b = Backend::cpu();
    let sdf = tiny_sdf();
    let last = sdf.sdf_params.len() - 1;
    let pts = [0.1f32, 0.2, 0.44, -0.3, 0.1, 0.38, 0.0, -0.25, 0.43, 0.7, -0.6, 0.1];
    let mut shifted = tiny_sdf();
    shifted.sdf_params[last] += 0.01;
    for (p, q) in sdf.sdf(&b, &pts).unwrap().iter().zip(shifted.sdf(&b, &pts).unwrap()) {
        assert!((q - p - 0.01).abs() < 1e-5, "the last SDF parameter is not the output offset: {p} -> {q}");
    }
    let w = Stage2Weights { smooth: 0.0, sigma: 0.3, kl: 0.0, rho: 0.05 };
    let model = Stage2Model::new(&refined_geometry_cfg(IndirectMode::None)).unwrap();
    let bb = batch();
    let g = loss_and_grad_geometry(&b, &model, &bb, &w, 7, &sdf).unwrap();
    let fd = symmetric_slope(
        |d| {
            let mut m = tiny_sdf();
            m.sdf_params[last] += d;
            loss_and_grad_geometry(&b, &model, &bb, &w, 7, &m).unwrap().stats.loss
        },
        3e-3,
    );
    let a = g.d_sdf[last] as f64;
    assert!(fd.abs() > 1e-3, "the ray move barely changes the loss here: {fd:.3e}");
    assert!((a - fd).abs() <= 0.02 * fd.abs(), "ray move: analytic {a:.6e} vs central difference {fd:.6e}");
}

/// The loss's slope at 0: the least-squares line through the 64 points ±h·k/32 (k = 1..32), 32
/// central differences in one. This tiny SDF's f32 loss (0.204) carries rounding noise of about
/// 3e-7 from one offset of 1e-4 to the next (a sweep of 41 offsets of one SDF parameter), so a
/// single central difference at ±1e-3 errs by up to 1.5e-4 against slopes of 2e-3, the check's
/// whole tolerance. The fit errs 3.3× less at the same reach (σ/(h·√(2n/3)) against σ/(h·√2)):
/// the worst of the 41 parameters' errors went from 1.01 of the tolerance to 0.57. A longer reach
/// does not help: at ±2e-3 the loss bends (a slope of 9.3e-3 against 8.4e-3). Symmetric offsets
/// cancel the curvature as a central difference does.
fn symmetric_slope(f: impl Fn(f32) -> f64, h: f32) -> f64 {
    const N: usize = 32;
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for k in 1..=N {
        let d = h * k as f32 / N as f32;
        num += d as f64 * (f(d) - f(-d));
        den += 2.0 * (d as f64) * (d as f64);
    }
    num / den
}

/// The paper preset's network at its geometric initialisation: close to the sphere r = 0.5.
fn sphere_sdf() -> pii_bake::train::stage1::Model {
    use pii_bake::train::stage1::{InitMode, Stage1Config};
    let mut cfg = Stage1Config::for_scene(Preset::Paper, pii_bake::render::TraceMode::Classic, InitMode::Sphere, &[], 0, 1);
    cfg.field.init_radius = 0.5;
    cfg.field.feature_dim = 0;
    cfg.radiance_widths = vec![8];
    pii_bake::train::stage1::Model::new(&cfg).unwrap()
}

#[test]
fn rays_leaving_near_the_tangent_plane_are_not_blocked_by_their_own_surface() {
    use pii_bake::train::stage2::SurfaceCache;
    let b = Backend::cpu();
    let sdf = sphere_sdf();
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    cfg.lobes = 1;
    // Points on the sphere r = 0.5 with a lobe 1.5° above their tangent plane: the start point is
    // within the hit threshold of their own surface, which must not count as an occluder. A point
    // outside the sphere looking at it is blocked.
    let mut cache = SurfaceCache::default();
    // (Points 0..8 on the ring; point 8 outside the sphere.)
    let a = 1.5f32.to_radians();
    for k in 0..8 {
        let phi = k as f32 * 0.7;
        let n = [phi.cos() * 0.6, phi.sin() * 0.6, -0.8f32];
        let n = norm(n);
        // On the field's zero level along n (bisection), as the primary tracer leaves points.
        let (mut lo, mut hi) = (0.3f32, 0.7f32);
        for _ in 0..40 {
            let m = 0.5 * (lo + hi);
            if sdf.sdf(&b, &n.map(|v| m * v)).unwrap()[0] < 0.0 {
                lo = m;
            } else {
                hi = m;
            }
        }
        cache.x.push(n.map(|v| lo * v));
        cache.n.push(n);
        cache.v.push(n);
        cache.target.push([0.5; 3]);
    }
    cache.x.push([0.0, 0.0, 0.9]);
    cache.n.push(norm([0.0, -1.0, -1.0]));
    cache.v.push([0.0, 0.0, 1.0]);
    cache.target.push([0.5; 3]);
    // Each ring point traces its own lobe: a tangent direction tilted 1.5° off the surface.
    for i in 0..8 {
        let n = cache.n[i];
        let t = norm([-n[1], n[0], 0.0]);
        let axis = norm([0, 1, 2].map(|q| t[q] * a.cos() + n[q] * a.sin()));
        let mut one = SurfaceCache { x: vec![cache.x[i]], n: vec![n], v: vec![n], target: vec![[0.5; 3]], ..Default::default() };
        one.trace_lobe(&b, &sdf, &cfg, 0, axis).unwrap();
        let pts: Vec<f32> = [0.0f32, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8].iter().flat_map(|t| [0, 1, 2].map(|q| cache.x[i][q] + t * axis[q])).collect();
        eprintln!("point {i}: f {:?} hits {:?}", sdf.sdf(&b, &pts).unwrap(), one.lobe_hits[0]);
        assert_eq!(one.lobe_traced[0], 1);
        assert!(one.lobe_hits[0].is_empty(), "point {i}: its own surface blocked a lobe 1.5° above the tangent plane");
    }
    let mut outside = SurfaceCache { x: vec![cache.x[8]], n: vec![cache.n[8]], v: vec![cache.v[8]], target: vec![[0.5; 3]], ..Default::default() };
    outside.trace_lobe(&b, &sdf, &cfg, 0, [0.0, 0.0, -1.0]).unwrap();
    assert_eq!(outside.lobe_hits[0].len(), 1, "the sphere blocks the outside point's lobe");
}

#[test]
fn colour_position_gradient_matches_central_differences() {
    // `--refine-geometry` moves each point along its ray by the colour term's position gradient
    // (`d_point`): through the material (PE or hash grid, with the raw position beside the grid)
    // and, for `mii`, its SGs at the point. Each point moved alone, against central differences of
    // the colour term.
    use pii_bake::nn::field::FieldEncoding;
    use pii_bake::train::stage2::loss_and_grad_with;
    let b = Backend::cpu();
    let w = weights();
    // The last case with the light–albedo balance's albedo scale away from 1.
    for (indirect, grid, albedo_scale) in [(IndirectMode::Ours, false, 1.0), (IndirectMode::Ours, true, 1.0), (IndirectMode::Mii, false, 1.0), (IndirectMode::Ours, true, 0.7)] {
        let mut cfg = tiny(indirect, DecoderMode::Separate);
        cfg.material_encoding = FieldEncoding::Frequency { n_freqs: 2 };
        if grid {
            cfg = cfg.with_material_grid(24, 12);
        }
        let mut model = Stage2Model::new(&cfg).unwrap();
        model.albedo_scale = albedo_scale;
        let bb = boundary_batch(&model);
        let g = loss_and_grad_with(&b, &model, &bb, &w, 7, true).unwrap();
        assert_eq!(g.d_point.len(), bb.len());
        let mut any = 0.0f64;
        for i in 0..bb.len() {
            for a in 0..3 {
                let h = 3e-4f32;
                let at = |d: f32| {
                    let mut m = bb.clone();
                    m.x[i][a] += d;
                    loss_and_grad_with(&b, &model, &m, &w, 7, true).unwrap().stats.rgb
                };
                let fd = (at(h) - at(-h)) / (2.0 * h as f64);
                let an = g.d_point[i][a];
                any = any.max(an.abs());
                let err = (an - fd).abs() / (2e-5 + 0.02 * fd.abs().max(an.abs()));
                assert!(err <= 1.0, "{indirect:?} grid {grid}: point {i} axis {a}: analytic {an:.6e} vs central difference {fd:.6e}");
            }
        }
        assert!(any > 1e-3, "{indirect:?} grid {grid}: the colour does not depend on the points");
    }
}

#[test]
fn secondary_rays_marching_on_the_sdf_grid_find_the_networks_occluders() {
    // Stage 2's secondary rays march on the frozen SDF sampled on a grid and hand their hits to the
    // network. Against tracing with the network at every step: the same rays blocked except a few
    // grazing the silhouette, the hit points on the network's surface and where the network puts
    // them.
    use pii_bake::train::stage2::SurfaceCache;
    let b = Backend::cpu();
    // The paper preset's geometric initialisation at a small width: close to the SDF of the sphere
    // r = 0.5 (the trained fields are eikonal; a field far from one overshoots either way).
    let sdf = {
        use pii_bake::train::stage1::{InitMode, Stage1Config};
        let mut c = Stage1Config::for_scene(Preset::Paper, pii_bake::render::TraceMode::Classic, InitMode::Sphere, &[], 0, 1);
        c.field.init_radius = 0.5;
        c.field.feature_dim = 0;
        c.field.widths = vec![64, 64, 64];
        c.field.skip_layers = vec![];
        c.radiance_widths = vec![8];
        pii_bake::train::stage1::Model::new(&c).unwrap()
    };
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    cfg.lobes = 1;
    // A 21×21 patch of points on the plane z = -0.7 under the sphere, a lobe tilted off the
    // vertical: about half of the rays meet it.
    let mut cache = SurfaceCache::default();
    for i in 0..21 {
        for j in 0..21 {
            cache.x.push([-0.5 + 0.05 * i as f32, -0.5 + 0.05 * j as f32, -0.7]);
            cache.n.push([0.0, 0.0, 1.0]);
            cache.v.push([0.0, 0.0, 1.0]);
            cache.target.push([0.5; 3]);
        }
    }
    let axis = norm([0.2, 0.1, 1.0]);
    let trace = |nodes: usize| {
        let mut c = cache.clone();
        let mut cf = cfg.clone();
        cf.secondary_grid_nodes = nodes;
        c.trace_lobe(&b, &sdf, &cf, 0, axis).unwrap();
        assert_eq!(c.grid.is_some(), nodes > 0);
        c
    };
    let (net, grid) = (trace(0), trace(65));
    let n = cache.len();
    let (mut both, mut differ) = (0, 0);
    for i in 0..n {
        match (net.hit_index[i], grid.hit_index[i]) {
            (u32::MAX, u32::MAX) => {}
            (a, g) if a != u32::MAX && g != u32::MAX => {
                both += 1;
                let (xa, xg) = (net.lobe_hits[0][a as usize].0, grid.lobe_hits[0][g as usize].0);
                // Both at the ray's first crossing of the network's zero level: the grid's hit on
                // it, the network's within its threshold (this field's slope along the rays is
                // 1.2 head-on, so tracing with it overshoots by up to 0.07; the secant step after
                // the grid does not depend on the slope).
                let o = cache.x[i];
                let f_at = |t: f32| sdf.sdf(&b, &[o[0] + t * axis[0], o[1] + t * axis[1], o[2] + t * axis[2]]).unwrap()[0];
                let mut hi = 0.01f32;
                while f_at(hi) > 0.0 {
                    hi += 0.01;
                }
                let mut lo = hi - 0.01;
                for _ in 0..30 {
                    let m = 0.5 * (lo + hi);
                    if f_at(m) > 0.0 {
                        lo = m;
                    } else {
                        hi = m;
                    }
                }
                let along = |x: [f32; 3]| (0..3).map(|q| (x[q] - o[q]) * axis[q]).sum::<f32>();
                assert!((along(xg) - lo).abs() < 2e-3, "point {i}: the grid's hit at t = {} (crossing at {lo})", along(xg));
                assert!((along(xa) - lo).abs() < 0.1, "point {i}: the network's hit {xa:?} at t = {} (crossing at {lo})", along(xa));
            }
            _ => differ += 1,
        }
    }
    assert!(both > n / 4, "{both} of {n} rays blocked");
    assert!(differ * 50 <= n, "{differ} of {n} rays blocked on one and open on the other");
    // One sample per SDF, shared by every cache and render of it; a changed SDF is sampled anew.
    let (g0, _) = sdf.sdf_grid(&b, 65).unwrap();
    let (g1, s1) = sdf.sdf_grid(&b, 65).unwrap();
    assert!(std::sync::Arc::ptr_eq(&g0, &g1) && s1 == 0.0);
    assert!(std::sync::Arc::ptr_eq(&g0, grid.grid.as_ref().unwrap()));
    let mut moved = sdf;
    moved.sdf_params[0] += 1e-3;
    let (g2, s2) = moved.sdf_grid(&b, 65).unwrap();
    assert!(!std::sync::Arc::ptr_eq(&g0, &g2) && s2 > 0.0);
}

#[test]
fn wgpu_matches_cpu_on_the_refined_geometry_gradient() {
    let gpu = Backend::wgpu_for_tests().unwrap_or_else(|e| panic!("the test command installs lavapipe: {e}"));
    let cpu = Backend::cpu();
    let sdf = tiny_sdf();
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    cfg.material_encoding = pii_bake::nn::field::FieldEncoding::Frequency { n_freqs: 2 };
    cfg.refine_geometry = true;
    cfg.geometry_eikonal_points = 8;
    let model = Stage2Model::new(&cfg).unwrap();
    let mut bb = boundary_batch(&model);
    bb.hit_sdf = bb.hits.iter().map(|h| h.iter().map(|&(_, x2, _)| sdf.sdf(&cpu, &x2).unwrap()[0]).collect()).collect();
    let w = weights();
    let (a, c) = (loss_and_grad_geometry(&cpu, &model, &bb, &w, 7, &sdf).unwrap(), loss_and_grad_geometry(&gpu, &model, &bb, &w, 7, &sdf).unwrap());
    assert!((a.stats.loss - c.stats.loss).abs() < 1e-5 * (1.0 + a.stats.loss.abs()), "{} vs {}", a.stats.loss, c.stats.loss);
    // PE2 material as in the central-difference test: with PE10 the colour's derivative along a ray
    // swings by its 2^9 frequency over the ulps by which the backends' Newton steps place a point
    // (2.4e-3 of the largest entry on lavapipe, 3.5e-2 on an H100), which is the loss's conditioning,
    // not a kernel's error. With PE2 the worst entry differs by 3.5e-5 of the largest on lavapipe.
    let scale = a.d_sdf.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
    let (i, worst) = a.d_sdf.iter().zip(&c.d_sdf).map(|(p, q)| (p - q).abs()).enumerate().fold((0, 0.0f32), |m, (i, d)| if d > m.1 { (i, d) } else { m });
    assert!(worst <= 1e-3 * scale + 1e-6, "d_sdf[{i}]: cpu {} vs wgpu {}, {:.2e} of the largest entry {scale}", a.d_sdf[i], c.d_sdf[i], worst / scale);
}

#[test]
fn training_and_rendering_shade_alike_and_match_the_per_lobe_closed_form() {
    use pii_bake::sg::shade::{lobe_contribution, BrdfModel, Surface};
    use pii_bake::train::stage2::{shade_f64, PointShading};
    // Lobes above, across and below the horizon, broad to sharp, unnormalised axes.
    let lobes: Vec<Sg<f64>> = [([0.2, 0.9, 0.1], 0.5), ([1.0, 0.1, 0.0], 8.0), ([0.0, -1.0, 0.3], 30.0), ([0.3, 0.5, 0.8], 200.0), ([-0.4, 0.2, -0.9], 2.0)]
        .iter()
        .enumerate()
        .map(|(k, &(axis, lambda))| Sg { axis, lambda, mu: [0.3 + 0.2 * k as f64, 0.5, 1.1 - 0.15 * k as f64] })
        .collect();
    let n = [0.1, 1.0, 0.2];
    // Roughness below the clamp, mid and rough; a frontal and a grazing view.
    for (rough, v) in [(0.005, [0.3, 0.8, 0.2]), (0.35, [0.3, 0.8, 0.2]), (1.0, [0.9, 0.05, -0.4]), (0.6, [0.95, 0.02, 0.1])] {
        let albedo = [0.8, 0.45, 0.1];
        let ps = PointShading::new(BrdfModel::Physg, albedo, rough, 0.0, n, v, &lobes);
        // The training's sums (duals) against the renderer's (f64) and the per-lobe closed form:
        // the same formula, so they differ only by f64 rounding (a dual divides by multiplying).
        let s = Surface { albedo, roughness: rough, normal: n, view: v };
        let (mut spec, mut diff) = ([0.0f64; 3], [0.0f64; 3]);
        for l in &lobes {
            let (sp, df) = lobe_contribution(&s, l);
            for c in 0..3 {
                spec[c] += sp[c];
                diff[c] += df[c];
            }
        }
        let (rs, rd) = shade_f64(BrdfModel::Physg, albedo, rough, 0.0, n, v, &lobes);
        for (what, a, b) in [("training", ps.spec, ps.diff), ("rendering", rs, rd)] {
            for c in 0..3 {
                assert!((a[c] - spec[c]).abs() <= 1e-12 * spec[c].abs().max(1e-3), "{what} spec {c} at R {rough}: {} vs {}", a[c], spec[c]);
                assert!((b[c] - diff[c]).abs() <= 1e-12 * diff[c].abs().max(1e-3), "{what} diff {c} at R {rough}: {} vs {}", b[c], diff[c]);
            }
        }
        assert!(ps.spec.iter().chain(&ps.diff).any(|&x| x > 1e-3), "the case must light the point");
    }
}

#[test]
fn the_material_grid_is_coarser_only_where_the_cached_points_would_spread_thin() {
    use pii_bake::train::material::{material_grid_finest, MATERIAL_POINTS_PER_CELL};
    use pii_bake::train::stage1::SceneSizes;
    let sizes = |footprint: f32, finest: u32| SceneSizes { pixel_footprint: footprint, grid_finest: finest, grid_log2_table: 16, hull_resolution: 64, mesh_resolution: 96, train_views: 24, train_pixels: 960_000, held_out_views: 4 };
    let points = 131_072;
    // The bundled example (7701 masked pixels per view, footprint 0.0111) and make_scene.py's
    // largest object (the bowl, 13918) keep half stage 1's 180 cells.
    assert_eq!(material_grid_finest(&sizes(0.011_125_5, 180), points, 7701.0), 90);
    assert_eq!(material_grid_finest(&sizes(0.011_125_5, 180), points, 13918.0), 90);
    // The Ethiopian head (73.4k masked pixels per view, footprint 0.0039): about 120, not 255,
    // and each finest cell then holds the floor's share of points (Cauchy's surface estimate).
    let head = material_grid_finest(&sizes(0.003_918, 511), points, 73_400.0);
    assert!((110..=130).contains(&head), "{head}");
    let area = 4.0 * 73_400.0 * 0.003_918f64.powi(2);
    let per_cell = points as f64 / (area * (head as f64).powi(2) / 4.0);
    assert!(per_cell >= MATERIAL_POINTS_PER_CELL && per_cell < 1.2 * MATERIAL_POINTS_PER_CELL, "{per_cell}");
    // Never below 32 cells, whatever the capture; never above half stage 1's.
    assert_eq!(material_grid_finest(&sizes(0.0005, 1024), 1000, 1e7), 32);
    assert_eq!(material_grid_finest(&sizes(0.05, 64), points, 10.0), 32);
}

#[test]
fn a_calibrated_run_warms_up_with_physgs_brdf() {
    use pii_bake::sg::shade::BrdfModel;
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    cfg.iterations = 10;
    cfg.brdf_warmup = 0.5;
    cfg.brdf = BrdfModel::Physg;
    // PhySG's runs shade with it throughout.
    assert!((0..10).all(|s| cfg.brdf_at(s) == BrdfModel::Physg));
    cfg.brdf = BrdfModel::Calibrated;
    let forms: Vec<BrdfModel> = (0..10).map(|s| cfg.brdf_at(s)).collect();
    assert_eq!(&forms[..5], &[BrdfModel::Physg; 5]);
    assert_eq!(&forms[5..], &[BrdfModel::Calibrated; 5]);
    cfg.brdf_warmup = 0.0;
    assert!((0..10).all(|s| cfg.brdf_at(s) == BrdfModel::Calibrated));
    // A warm-up that never ends is refused.
    cfg.brdf_warmup = 1.0;
    assert!(cfg.validate().unwrap_err().to_string().contains("brdf_warmup"));
    // The trainer shades its warm-up steps with PhySG's form: step for step the same losses as a
    // PhySG run until the warm-up ends, then its own; the run keeps its own form throughout.
    let b = Backend::cpu();
    let mut cache = pii_bake::train::stage2::SurfaceCache::default();
    let bt = batch();
    cache.x = bt.x.clone();
    cache.n = bt.n.clone();
    cache.v = bt.v.clone();
    cache.target = bt.target.clone();
    cfg.brdf_warmup = 0.5;
    cfg.batch = 4;
    let losses = |cfg: &Stage2Config| {
        let mut t = pii_bake::train::stage2::Stage2Trainer::new(cfg).unwrap();
        let l: Vec<f64> = (0..8).map(|_| t.train_step(&b, &cache).unwrap().loss).collect();
        assert_eq!(t.cfg().brdf, cfg.brdf);
        l
    };
    let warm = losses(&cfg);
    let mut p = cfg.clone();
    p.brdf = BrdfModel::Physg;
    let physg = losses(&p);
    assert_eq!(&warm[..5], &physg[..5]);
    assert!(warm[5..].iter().zip(&physg[5..]).all(|(a, b)| a != b), "{warm:?} vs {physg:?}");
    let mut cold = cfg.clone();
    cold.brdf_warmup = 0.0;
    assert_ne!(losses(&cold)[0], physg[0]);
}

/// The light–albedo balance `g` (light × e^g, albedo and occluder reflectance × e^−g): its
/// gradient matches central differences along that direction, with the albedo scaled (some of
/// it capped at 1) and with every indirect mode it applies to; the other parameters' gradients
/// still match with the scale in place.
#[test]
fn light_albedo_balance_gradient_matches_central_differences() {
    let b = Backend::cpu();
    let along = |m: &mut Stage2Model, h: f32| {
        let log = m.cfg.log_amplitude;
        m.light.chunks_exact_mut(7).for_each(|p| p[4..7].iter_mut().for_each(|v| if log { *v += h } else { *v *= h.exp() }));
        m.albedo_scale *= (-h as f64).exp();
    };
    for (indirect, metallic, log, scale) in [
        (IndirectMode::Ours, false, false, 0.8),
        (IndirectMode::Ours, true, false, 2.5),
        (IndirectMode::Ours, false, true, 0.6),
        (IndirectMode::Uniform, false, false, 0.9),
        (IndirectMode::None, true, false, 1.2),
    ] {
        let mut cfg = tiny(indirect, DecoderMode::Separate);
        cfg.metallic = metallic;
        cfg.log_amplitude = log;
        cfg.balance_lr_factor = 1.0;
        let mut model = Stage2Model::new(&cfg).unwrap();
        model.albedo_scale = scale;
        let albedo = model.material(&b, &batch().x).unwrap().albedo;
        if scale > 1.5 {
            assert!(albedo.iter().flatten().any(|&a| a == 1.0), "some albedo is capped at 1: {albedo:?}");
        }
        let g = grads(&b, &model);
        let h = 1e-3f32;
        let (mut mp, mut mm) = (model.clone(), model.clone());
        along(&mut mp, h);
        along(&mut mm, -h);
        let fd = (grads(&b, &mp).stats.loss - grads(&b, &mm).stats.loss) / (2.0 * h as f64);
        let what = format!("{indirect:?} metallic {metallic} log {log} scale {scale}");
        assert!(fd.abs() > 1e-5, "{what}: the loss moves along the balance ({fd:e})");
        assert!((g.d_balance - fd).abs() <= 2e-5 + 0.03 * fd.abs(), "{what}: analytic {:e} vs central difference {fd:e}", g.d_balance);
        check_group("light", &g.d_light, model.light.len(), &model, &|m, i, h| m.light[i] += h);
        for d in 0..model.dec_params.len() {
            check_group(&format!("decoder{d}"), &g.d_dec[d], model.dec_params[d].len(), &model, &|m, i, h| m.dec_params[d][i] += h);
        }
        if indirect == IndirectMode::Ours {
            check_group("indirect", &g.d_ind, model.ind_params.len(), &model, &|m, i, h| m.ind_params[i] += h);
        }
    }
    // Off (and with a known light, or the `mii` baseline): no gradient, nothing moves.
    for (factor, fixed, indirect) in [(0.0, false, IndirectMode::Ours), (1.0, true, IndirectMode::Ours), (1.0, false, IndirectMode::Mii)] {
        let mut cfg = tiny(indirect, DecoderMode::Separate);
        cfg.balance_lr_factor = factor;
        cfg.light_fixed = fixed;
        assert!(!cfg.learns_balance());
        assert_eq!(grads(&b, &Stage2Model::new(&cfg).unwrap()).d_balance, 0.0);
    }
}

/// A step of the balance moves the light and the albedo in opposite directions by the same
/// factor (the diffuse render unchanged), a checkpoint keeps where it stands, and a run file
/// from before the balance reads it off.
#[test]
fn the_balance_moves_light_and_albedo_together_and_is_checkpointed() {
    let b = Backend::cpu();
    let mut cfg = tiny(IndirectMode::Ours, DecoderMode::Separate);
    cfg.balance_lr_factor = 1.0;
    cfg.lr_material = 0.0;
    cfg.lr_indirect = 0.0;
    cfg.lr_light = 1e-2;
    let mut t = Stage2Trainer::new(&cfg).unwrap();
    let e0 = t.model.channel_energies()[0];
    let mut g = grads(&b, &t.model);
    g.d_light.iter_mut().for_each(|v| *v = 0.0);
    g.d_balance = -1.0; // the loss falls as the light brightens
    assert!(t.apply(g).unwrap().0);
    let ratio = t.model.channel_energies()[0] / e0;
    assert!(ratio > 1.005 && ratio < 1.02, "one Adam step of 1e-2 in log: {ratio}");
    assert!((t.model.albedo_scale * ratio - 1.0).abs() < 1e-5, "albedo scale {} × light ratio {ratio}", t.model.albedo_scale);
    // A non-finite balance gradient skips the step.
    let mut bad = grads(&b, &t.model);
    bad.d_balance = f64::NAN;
    let before = (t.model.light.clone(), t.model.albedo_scale);
    assert!(!t.apply(bad).unwrap().0);
    assert_eq!((t.model.light.clone(), t.model.albedo_scale), before);
    let dir = std::env::temp_dir().join(format!("pii_balance_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    t.save(&dir, "scene", &t.model.axes()).unwrap();
    let (back, _, _) = Stage2Trainer::load(&dir, Some("scene")).unwrap();
    assert_eq!(back.model.albedo_scale, t.model.albedo_scale);
    std::fs::remove_dir_all(&dir).ok();
    let mut v = serde_json::to_value(&cfg).unwrap();
    v.as_object_mut().unwrap().remove("balance_lr_factor");
    assert!(!serde_json::from_value::<Stage2Config>(v).unwrap().learns_balance());
}

/// Every setting `--material-set` can give a nonsensical value is refused before training, naming
/// it (each used to train on; a checkpoint interval of 0 panicked at the first step).
#[test]
fn nonsensical_material_settings_are_refused_by_name() {
    let base = Stage2Config::new(Preset::Fast, 1000);
    base.validate().expect("the preset is valid");
    for (key, value) in [
        ("checkpoint_every", "0"),
        ("smooth_weight", "-1"),
        ("smooth_sigma", "-1"),
        ("kl_weight", "-1"),
        ("mii_weight", "-1"),
        ("balance_lr_factor", "-1"),
        ("retrace_degrees", "-1"),
        ("normal_step_factor", "0"),
        ("secondary_offset", "-1"),
        ("secondary_offset", "1e30"),
        ("secondary_threshold", "0"),
        ("lr_final_factor", "1e30"),
    ] {
        let e = pii_bake::train::stage2::apply_overrides(base.clone(), &[format!("{key}={value}")]).expect_err(&format!("{key}={value} must be refused"));
        assert!(e.to_string().contains(key), "{key}={value}: {e}");
    }
    for key in ["smooth_weight", "kl_weight", "balance_lr_factor", "retrace_degrees", "lr_final_factor"] {
        pii_bake::train::stage2::apply_overrides(base.clone(), &[format!("{key}=0")]).unwrap_or_else(|e| panic!("{key}=0: {e}"));
    }
}
