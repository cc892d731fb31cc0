//! How much texture the photos show on the object: the figure behind the "textureless capture"
//! warning. Where the object is one flat colour, the photometric loss and photo-consistency see
//! only shading, so albedo and lighting are poorly separable (the albedo keeps the shading).
//!
//! The figure is a band-pass contrast of log luminance inside the masks: each view is box-averaged
//! so that the object spans about [`OBJECT_PIXELS`] pixels (one scale for every capture size), and
//! at each pixel whose 9×9 neighbourhood lies inside the mask, `|mean₃ₓ₃ − mean₉ₓ₉|` of
//! `ln(0.02 + luminance)` is taken; the figure is its 75th percentile over the views. Smooth
//! shading barely changes across 9 pixels; texture edges, creases and highlights do. The 3×3 mean
//! averages away pixel noise.

use super::View;

/// The object's extent (pixels) each view is box-averaged to before measuring.
pub const OBJECT_PIXELS: f64 = 150.0;

/// Views measured at most (evenly spaced).
const MAX_VIEWS: usize = 12;

/// Below this the photos count as textureless. Measured with `pii-bake info` (training views):
/// `make_scene.py`'s textureless bowl 0.043 (0.055 at `--downscale 2`); the bundled example
/// (spot, large plain patches) 0.195, the checkered bowl 0.214, glossy 0.390, DTU scan37 0.399,
/// the Ethiopian head 0.134 (0.125 / 0.173 at `--downscale 2` / `4`). 0.08 sits between the
/// textureless bowl and the least textured capture by a factor of about 1.7 each way.
pub const TEXTURELESS_BELOW: f64 = 0.08;

/// The 75th percentile of the band-pass contrast (see the module docs) over the views with a
/// mask, or None when no view has enough masked interior to measure.
pub fn photo_texture(views: &[&View]) -> Option<f64> {
    let with_mask: Vec<&View> = views.iter().copied().filter(|v| v.mask.is_some()).collect();
    let stride = with_mask.len().div_ceil(MAX_VIEWS).max(1);
    let mut vals: Vec<f32> = Vec::new();
    for v in with_mask.iter().step_by(stride) {
        view_contrast(v, &mut vals);
    }
    if vals.len() < 100 {
        return None;
    }
    let k = (vals.len() * 3) / 4;
    let (_, q, _) = vals.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    Some(*q as f64)
}

/// Append the band-pass contrast at every interior pixel of one view.
fn view_contrast(v: &View, out: &mut Vec<f32>) {
    let Some(mask) = v.mask.as_ref() else { return };
    let (w, h, ch) = (v.image.width, v.image.height, v.image.channels);
    if ch < 3 || w == 0 || h == 0 || mask.len() != w * h || v.image.data.len() != w * h * ch {
        return;
    }
    // The mask's bounding box sets the averaging factor.
    let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
    for (i, m) in mask.iter().enumerate() {
        if *m >= 0.5 {
            let (x, y) = (i % w, i / w);
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
        }
    }
    if x0 > x1 {
        return;
    }
    let extent = (x1 - x0).max(y1 - y0) as f64;
    let f = ((extent / OBJECT_PIXELS).round() as usize).max(1);
    let (sw, sh) = (w / f, h / f);
    if sw < 9 || sh < 9 {
        return;
    }
    let mut lum = vec![0f64; sw * sh];
    let mut m = vec![0f64; sw * sh];
    let inv = 1.0 / (f * f) as f64;
    for y in 0..sh * f {
        for x in 0..sw * f {
            let i = y * w + x;
            let p = &v.image.data[i * ch..i * ch + 3];
            let l = 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
            let j = (y / f) * sw + x / f;
            lum[j] += inv * if l.is_finite() { l.max(0.0) } else { 0.0 };
            m[j] += inv * mask[i] as f64;
        }
    }
    let log: Vec<f64> = lum.iter().map(|l| (0.02 + l).ln()).collect();
    let inside: Vec<f64> = m.iter().map(|&x| if x > 0.99 { 1.0 } else { 0.0 }).collect();
    let (b1, b4, bin) = (box_mean(&log, sw, sh, 1), box_mean(&log, sw, sh, 4), box_mean(&inside, sw, sh, 4));
    for j in 0..sw * sh {
        if bin[j] > 0.999 {
            out.push((b1[j] - b4[j]).abs() as f32);
        }
    }
}

/// Mean over the (2r+1)² window, the window clamped to the image (edge pixels repeated).
fn box_mean(x: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    let at = |xx: isize, yy: isize| x[(yy.clamp(0, h as isize - 1) as usize) * w + xx.clamp(0, w as isize - 1) as usize];
    let k = (2 * r + 1) as f64;
    let mut out = vec![0.0; w * h];
    for y in 0..h as isize {
        for xx in 0..w as isize {
            let mut s = 0.0;
            for dy in -(r as isize)..=r as isize {
                for dx in -(r as isize)..=r as isize {
                    s += at(xx + dx, y + dy);
                }
            }
            out[y as usize * w + xx as usize] = s / (k * k);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image_io::ImageF32;
    use crate::scene::{Camera, Split};

    /// A 200×200 view of a disc of radius 70 whose colour is `f(x, y)`.
    fn disc(mut f: impl FnMut(f32, f32) -> f32) -> View {
        let (w, h) = (200, 200);
        let mut image = ImageF32::new(w, h, 3);
        let mut mask = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = (x as f32 - 100.0, y as f32 - 100.0);
                if dx * dx + dy * dy < 70.0 * 70.0 {
                    mask[y * w + x] = 1.0;
                    let c = f(x as f32, y as f32);
                    image.data[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&[c, c, c]);
                }
            }
        }
        View { name: "v".into(), split: Split::Train, camera: Camera { width: w, height: h, fx: 200.0, fy: 200.0, cx: 100.0, cy: 100.0, distortion: None, world_from_camera: glam::DMat4::IDENTITY }, image, mask: Some(mask), image_path: "v.png".into() }
    }

    #[test]
    fn shading_alone_reads_textureless_and_a_checker_does_not() {
        // Smooth shading across the disc (a lit sphere's falloff) with pixel noise.
        let mut seed = 1u32;
        let mut noise = move || {
            seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
            (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let shaded = disc(|x, y| (0.1 + 0.6 * (1.0 - ((x - 80.0).powi(2) + (y - 80.0).powi(2)).sqrt() / 150.0)) * (1.0 + 0.1 * noise()));
        let checker = disc(|x, y| if ((x / 12.0).floor() + (y / 12.0).floor()) as i32 % 2 == 0 { 0.6 } else { 0.15 });
        let t_shaded = photo_texture(&[&shaded]).unwrap();
        let t_checker = photo_texture(&[&checker]).unwrap();
        assert!(t_shaded < TEXTURELESS_BELOW, "smooth shading with noise: {t_shaded}");
        assert!(t_checker > 2.0 * TEXTURELESS_BELOW, "checker: {t_checker}");
    }

    #[test]
    fn no_mask_no_figure() {
        let mut v = disc(|_, _| 0.5);
        v.mask = None;
        assert_eq!(photo_texture(&[&v]), None);
    }
}
