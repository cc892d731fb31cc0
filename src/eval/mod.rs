//! Metrics: masked PSNR/SSIM, scale-aligned albedo PSNR, roughness MSE, environment error after scale
//! alignment, Chamfer distance and normal consistency. The `eval` command (in [`cli`]) applies them to a
//! ground-truth scene and a folder of predictions.
//!
//! Conventions (as in the inverse-rendering papers we compare with):
//! - Colour images (novel views, relit views, albedo) are compared **sRGB-encoded, clamped to [0, 1]**,
//!   the space the PNGs are stored in; inputs to these functions are linear and encoded here.
//! - Masks are weights in [0, 1] (the ground truth's alpha). PSNR uses the mask-weighted MSE over RGB;
//!   SSIM is computed on both images composited over black by the mask, and averaged over pixels with
//!   mask ≥ 0.5 (valid 11×11 windows only).
//! - PSNR is capped at [`PSNR_CAP`] dB (identical images).
//! - Albedo: per-channel least-squares scale `s_c = Σ w·gt·pred / Σ w·pred²` (linear, all views together),
//!   then PSNR of the scaled prediction.
//! - Roughness: mask-weighted MSE of the linear values.

pub mod cli;
pub mod mesh;

use crate::image_io::linear_to_srgb;

/// PSNR reported for identical inputs (MSE = 0).
pub const PSNR_CAP: f64 = 100.0;

/// PSNR in dB of a mean squared error with peak 1.
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse <= 0.0 {
        return PSNR_CAP;
    }
    (-10.0 * mse.log10()).min(PSNR_CAP)
}

/// Mask-weighted MSE over `channels`-channel pixels (`weights` has one value per pixel; `None` = all 1).
pub fn weighted_mse(a: &[f32], b: &[f32], channels: usize, weights: Option<&[f32]>) -> f64 {
    assert_eq!(a.len(), b.len(), "weighted_mse: lengths differ");
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (i, (pa, pb)) in a.chunks_exact(channels).zip(b.chunks_exact(channels)).enumerate() {
        let w = weights.map_or(1.0, |w| w[i] as f64);
        if w <= 0.0 {
            continue;
        }
        for c in 0..channels {
            let d = pa[c] as f64 - pb[c] as f64;
            num += w * d * d;
        }
        den += w * channels as f64;
    }
    if den > 0.0 {
        num / den
    } else {
        0.0
    }
}

/// Masked PSNR of values already in display space ([0, 1]).
pub fn psnr(a: &[f32], b: &[f32], channels: usize, weights: Option<&[f32]>) -> f64 {
    psnr_from_mse(weighted_mse(a, b, channels, weights))
}

/// sRGB-encode linear RGB (clamped to [0, 1]).
pub fn encode_srgb(rgb: &[f32]) -> Vec<f32> {
    rgb.iter().map(|v| linear_to_srgb(*v)).collect()
}

/// Masked PSNR of two linear RGB images compared in sRGB space.
pub fn psnr_srgb(pred: &[f32], gt: &[f32], mask: Option<&[f32]>) -> f64 {
    psnr(&encode_srgb(pred), &encode_srgb(gt), 3, mask)
}

pub const SSIM_WINDOW: usize = 11;
pub const SSIM_SIGMA: f64 = 1.5;
pub const SSIM_K1: f64 = 0.01;
pub const SSIM_K2: f64 = 0.03;

fn gaussian_kernel() -> Vec<f64> {
    let r = (SSIM_WINDOW / 2) as f64;
    let k: Vec<f64> = (0..SSIM_WINDOW).map(|i| (-((i as f64 - r).powi(2)) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp()).collect();
    let s: f64 = k.iter().sum();
    k.into_iter().map(|v| v / s).collect()
}

/// Separable 'valid' Gaussian filter of a single-channel image: output (w−10)×(h−10).
fn blur_valid(x: &[f64], w: usize, h: usize, k: &[f64]) -> Vec<f64> {
    let n = k.len();
    let (ow, oh) = (w + 1 - n, h + 1 - n);
    let mut tmp = vec![0.0; ow * h];
    for y in 0..h {
        for ox in 0..ow {
            tmp[y * ow + ox] = (0..n).map(|i| k[i] * x[y * w + ox + i]).sum();
        }
    }
    let mut out = vec![0.0; ow * oh];
    for oy in 0..oh {
        for ox in 0..ow {
            out[oy * ow + ox] = (0..n).map(|i| k[i] * tmp[(oy + i) * ow + ox]).sum();
        }
    }
    out
}

/// SSIM (Wang et al. 2004: 11×11 Gaussian window σ = 1.5, K1 = 0.01, K2 = 0.03, peak 1) of two
/// `channels`-channel images in display space, averaged over channels and over the valid window centres
/// whose `weights` (one per pixel) are ≥ 0.5 (all centres if `weights` is None).
/// Returns None if the image is smaller than the window or no centre qualifies.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize, channels: usize, weights: Option<&[f32]>) -> Option<f64> {
    assert_eq!(a.len(), width * height * channels);
    assert_eq!(b.len(), a.len());
    if width < SSIM_WINDOW || height < SSIM_WINDOW {
        return None;
    }
    let k = gaussian_kernel();
    let (c1, c2) = (SSIM_K1 * SSIM_K1, SSIM_K2 * SSIM_K2);
    let (ow, oh) = (width + 1 - SSIM_WINDOW, height + 1 - SSIM_WINDOW);
    let r = SSIM_WINDOW / 2;
    let centres: Vec<usize> = (0..ow * oh)
        .filter(|&i| weights.is_none_or(|w| w[(i / ow + r) * width + i % ow + r] >= 0.5))
        .collect();
    if centres.is_empty() {
        return None;
    }
    let mut total = 0.0;
    for c in 0..channels {
        let x: Vec<f64> = (0..width * height).map(|i| a[i * channels + c] as f64).collect();
        let y: Vec<f64> = (0..width * height).map(|i| b[i * channels + c] as f64).collect();
        let mx = blur_valid(&x, width, height, &k);
        let my = blur_valid(&y, width, height, &k);
        let sxx = blur_valid(&x.iter().map(|v| v * v).collect::<Vec<_>>(), width, height, &k);
        let syy = blur_valid(&y.iter().map(|v| v * v).collect::<Vec<_>>(), width, height, &k);
        let sxy = blur_valid(&x.iter().zip(&y).map(|(p, q)| p * q).collect::<Vec<_>>(), width, height, &k);
        let mut s = 0.0;
        for &i in &centres {
            let (vx, vy, cxy) = (sxx[i] - mx[i] * mx[i], syy[i] - my[i] * my[i], sxy[i] - mx[i] * my[i]);
            s += ((2.0 * mx[i] * my[i] + c1) * (2.0 * cxy + c2)) / ((mx[i] * mx[i] + my[i] * my[i] + c1) * (vx + vy + c2));
        }
        total += s / centres.len() as f64;
    }
    Some(total / channels as f64)
}

/// Masked SSIM of two linear RGB images: sRGB-encoded, composited over black by the mask.
pub fn ssim_srgb(pred: &[f32], gt: &[f32], width: usize, height: usize, mask: Option<&[f32]>) -> Option<f64> {
    let comp = |img: &[f32]| -> Vec<f32> {
        encode_srgb(img).chunks_exact(3).enumerate().flat_map(|(i, p)| {
            let m = mask.map_or(1.0, |m| m[i]);
            [p[0] * m, p[1] * m, p[2] * m]
        }).collect()
    };
    ssim(&comp(pred), &comp(gt), width, height, 3, mask)
}

/// Per-channel least-squares scale aligning `pred` to `gt` (RGB, mask-weighted): `s_c = Σ w·g·p / Σ w·p²`.
/// Accumulates over several images: pass pairs.
pub fn ls_scale_rgb<'a>(pairs: impl IntoIterator<Item = (&'a [f32], &'a [f32], Option<&'a [f32]>)>) -> [f64; 3] {
    let (mut num, mut den) = ([0.0f64; 3], [0.0f64; 3]);
    for (pred, gt, w) in pairs {
        for (i, (p, g)) in pred.chunks_exact(3).zip(gt.chunks_exact(3)).enumerate() {
            let w = w.map_or(1.0, |w| w[i] as f64);
            for c in 0..3 {
                num[c] += w * g[c] as f64 * p[c] as f64;
                den[c] += w * p[c] as f64 * p[c] as f64;
            }
        }
    }
    [0, 1, 2].map(|c| if den[c] > 0.0 { num[c] / den[c] } else { 1.0 })
}

pub fn apply_scale(rgb: &[f32], s: [f64; 3]) -> Vec<f32> {
    rgb.iter().enumerate().map(|(i, v)| (*v as f64 * s[i % 3]) as f32).collect()
}

/// Environment-map error after per-channel least-squares scale alignment, solid-angle weighted
/// (sin θ per row of a latlong map). Both maps: linear RGB, same size and convention.
#[derive(Clone, Debug, serde::Serialize)]
pub struct EnvError {
    /// The per-channel scale applied to the prediction.
    pub scale: [f64; 3],
    /// Solid-angle-weighted MSE after alignment.
    pub mse: f64,
    /// ‖s·pred − gt‖ / ‖gt‖ (solid-angle weighted L2).
    pub relative_l2: f64,
    /// Solid-angle-weighted MSE of log(1 + x) after alignment (robust to the sun's dynamic range).
    pub log_mse: f64,
    /// Relative L2 over all normals of the diffuse irradiance each map casts, after its own
    /// per-channel scale alignment ([`crate::sg::fit::irradiance_error`]): how wrong a Lambertian
    /// surface lit by the prediction is. `relative_l2` of a map with a sun is nearly all the sun's
    /// few pixels (about 1 for any light that does not put a sun of the right size in the right
    /// pixels); this is what the light does to the shading.
    pub irradiance_error: f64,
}

pub fn env_error(pred: &[f32], gt: &[f32], width: usize, height: usize) -> EnvError {
    assert_eq!(pred.len(), width * height * 3);
    assert_eq!(gt.len(), pred.len());
    let w: Vec<f32> = (0..width * height)
        .map(|i| (std::f64::consts::PI * ((i / width) as f64 + 0.5) / height as f64).sin() as f32)
        .collect();
    let s = ls_scale_rgb([(pred, gt, Some(&w[..]))]);
    let aligned = apply_scale(pred, s);
    let mse = weighted_mse(&aligned, gt, 3, Some(&w));
    let gt_energy = weighted_mse(gt, &vec![0.0; gt.len()], 3, Some(&w));
    let log = |v: &[f32]| -> Vec<f32> { v.iter().map(|x| x.max(0.0).ln_1p()).collect() };
    let log_mse = weighted_mse(&log(&aligned), &log(gt), 3, Some(&w));
    let (sp, sg) = (crate::sg::fit::sh9_of_map(pred, width, height), crate::sg::fit::sh9_of_map(gt, width, height));
    let irradiance_error = crate::sg::fit::irradiance_error(&sp, &sg, crate::sg::fit::irradiance_scale(&sp, &sg));
    EnvError { scale: s, mse, relative_l2: if gt_energy > 0.0 { (mse / gt_energy).sqrt() } else { 0.0 }, log_mse, irradiance_error }
}

/// Bilinear resampling of a latlong RGB map to another size (u wraps, v clamps), for env comparison.
pub fn resample_latlong(src: &[f32], sw: usize, sh: usize, dw: usize, dh: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; dw * dh * 3];
    for y in 0..dh {
        let fy = ((y as f64 + 0.5) * sh as f64 / dh as f64 - 0.5).clamp(0.0, (sh - 1) as f64);
        let (y0, ty) = (fy.floor() as usize, fy - fy.floor());
        let y1 = (y0 + 1).min(sh - 1);
        for x in 0..dw {
            let fx = (x as f64 + 0.5) * sw as f64 / dw as f64 - 0.5;
            let fxf = fx.floor();
            let tx = fx - fxf;
            let x0 = (fxf as i64).rem_euclid(sw as i64) as usize;
            let x1 = (x0 + 1) % sw;
            for c in 0..3 {
                let g = |xx: usize, yy: usize| src[(yy * sw + xx) * 3 + c] as f64;
                let v = (1.0 - ty) * ((1.0 - tx) * g(x0, y0) + tx * g(x1, y0)) + ty * ((1.0 - tx) * g(x0, y1) + tx * g(x1, y1));
                out[(y * dw + x) * 3 + c] = v as f32;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise(n: usize, sigma: f64, seed: u64) -> Vec<f32> {
        use rand_distr::{Distribution, Normal};
        let mut rng = crate::util::rng(seed);
        let d = Normal::new(0.0, sigma).unwrap();
        (0..n).map(|_| d.sample(&mut rng) as f32).collect()
    }

    #[test]
    fn psnr_identical_and_known_noise() {
        let gt = vec![0.5f32; 200 * 200 * 3];
        assert_eq!(psnr(&gt, &gt, 3, None), PSNR_CAP);
        let n = noise(gt.len(), 0.05, 1);
        let pred: Vec<f32> = gt.iter().zip(&n).map(|(g, e)| g + e).collect();
        let expected = 20.0 * (1.0 / 0.05f64).log10();
        let got = psnr(&pred, &gt, 3, None);
        assert!((got - expected).abs() < 0.1, "{got} vs {expected}");
        // the mask excludes a corrupted half
        let mut pred2 = pred.clone();
        let half = pred2.len() / 2;
        pred2[..half].iter_mut().for_each(|v| *v = 1.0);
        let mask: Vec<f32> = (0..200 * 200).map(|i| if i * 3 < half { 0.0 } else { 1.0 }).collect();
        let got = psnr(&pred2, &gt, 3, Some(&mask));
        assert!((got - expected).abs() < 0.1, "masked {got} vs {expected}");
    }

    #[test]
    fn ssim_identical_and_constant_images() {
        let (w, h) = (32, 24);
        let a: Vec<f32> = (0..w * h * 3).map(|i| ((i * 37 % 101) as f32) / 100.0).collect();
        assert!((ssim(&a, &a, w, h, 3, None).unwrap() - 1.0).abs() < 1e-12);
        // Constant images a, b: SSIM = (2ab + C1) / (a² + b² + C1) exactly.
        let (x, y) = (0.3f32, 0.6f32);
        let got = ssim(&vec![x; w * h], &vec![y; w * h], w, h, 1, None).unwrap();
        let (x, y, c1) = (x as f64, y as f64, SSIM_K1 * SSIM_K1);
        let expected = (2.0 * x * y + c1) / (x * x + y * y + c1);
        assert!((got - expected).abs() < 1e-6, "{got} vs {expected}");
        // A constant offset keeps the structure term at 1: SSIM = luminance term, with local means.
        let noisy: Vec<f32> = a.iter().zip(noise(a.len(), 0.2, 3)).map(|(v, e)| v + e).collect();
        let s = ssim(&noisy, &a, w, h, 3, None).unwrap();
        assert!(s < 0.9, "noise must lower SSIM: {s}");
        assert!(ssim(&[0.5; 64], &[0.5; 64], 8, 8, 1, None).is_none(), "smaller than the window");
    }

    #[test]
    fn albedo_scale_alignment_recovers_scale() {
        let gt: Vec<f32> = (0..300).map(|i| 0.1 + 0.8 * ((i * 7 % 13) as f32 / 13.0)).collect();
        let k = [0.5, 2.0, 1.3];
        let pred: Vec<f32> = gt.iter().enumerate().map(|(i, v)| v / k[i % 3] as f32).collect();
        let s = ls_scale_rgb([(&pred[..], &gt[..], None)]);
        crate::testing::assert_close("scale", &s, &k, crate::testing::Tolerance::new(1e-6, 0.0));
        let aligned = apply_scale(&pred, s);
        assert!(psnr(&aligned, &gt, 3, None) > 90.0);
    }

    #[test]
    fn roughness_mse_known_offset() {
        let gt = vec![0.4f32; 100];
        assert_eq!(weighted_mse(&gt, &gt, 1, None), 0.0);
        let pred: Vec<f32> = gt.iter().map(|v| v + 0.1).collect();
        assert!((weighted_mse(&pred, &gt, 1, None) - 0.01).abs() < 1e-7);
    }

    #[test]
    fn env_error_is_scale_invariant_and_measures_noise() {
        let (w, h) = (64, 32);
        let gt: Vec<f32> = (0..w * h * 3).map(|i| 0.2 + ((i * 31 % 97) as f32) / 50.0).collect();
        let pred: Vec<f32> = gt.iter().enumerate().map(|(i, v)| v * [3.0, 0.5, 1.7][i % 3]).collect();
        let e = env_error(&pred, &gt, w, h);
        assert!(e.mse < 1e-10 && e.relative_l2 < 1e-5, "{e:?}");
        // additive zero-mean noise of sigma 0.1 (with no scale change) gives mse ~ 0.01
        let noisy: Vec<f32> = gt.iter().zip(noise(gt.len(), 0.1, 5)).map(|(v, n)| v + n).collect();
        let e = env_error(&noisy, &gt, w, h);
        assert!((e.mse - 0.01).abs() < 0.001, "{e:?}");
        // The irradiance error: 0 for a scaled copy, small for noise, large for a sun moved to
        // the other side of the sky, which the radiance error cannot tell from a sun a few
        // pixels off.
        let e = env_error(&pred, &gt, w, h);
        assert!(e.irradiance_error < 1e-6, "{e:?}");
        let sun = |u: usize| -> Vec<f32> {
            (0..w * h * 3).map(|i| { let (x, y) = ((i / 3) % w, (i / 3) / w); if y == h / 4 && (x == u || x == u + 1) { 500.0 } else { 0.5 } }).collect()
        };
        let (here, near, opposite) = (sun(8), sun(9), sun(8 + w / 2));
        let (n, o) = (env_error(&near, &here, w, h), env_error(&opposite, &here, w, h));
        assert!(n.relative_l2 > 0.8 && o.relative_l2 > 0.99, "{n:?} {o:?}");
        assert!(n.irradiance_error < 0.1 && o.irradiance_error > 0.5, "{n:?} {o:?}");
        let e = env_error(&noisy, &gt, w, h);
        assert!(e.irradiance_error < 0.01, "{e:?}");
        let r = resample_latlong(&gt, w, h, w, h);
        crate::testing::assert_close("resample identity", &r, &gt, crate::testing::Tolerance::new(1e-6, 1e-6));
    }
}
