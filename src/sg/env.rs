//! Environment lighting as spherical Gaussians, and latlong maps in the two conventions users meet.
//!
//! Our world frame is glTF's: right-handed, +Y up. A latlong pixel's direction:
//! - [`LatlongConvention::OpenExrUsd`]: row 0 = zenith (+Y), u = 0.5 looks along +Z, u = 0.25 along +X.
//! - [`LatlongConvention::Blender`]: Blender's world (+Z up) with u = 0.5 along Blender +X and
//!   u = 0.25 along Blender +Y; Blender's glTF importer maps our (x, y, z) to Blender (x, −z, y).

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::util::{atomic_write, DataError};

/// One SG lobe `G(ω) = μ·exp(λ(ω·ξ − 1))` in world space (+Y up).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SgLobe {
    /// Unit axis ξ.
    pub axis: [f32; 3],
    /// Sharpness λ > 0.
    pub sharpness: f32,
    /// RGB amplitude μ (linear radiance units).
    pub amplitude: [f32; 3],
}

impl SgLobe {
    pub fn eval(&self, dir: [f32; 3]) -> [f32; 3] {
        let d = self.axis[0] * dir[0] + self.axis[1] * dir[1] + self.axis[2] * dir[2];
        let g = (self.sharpness * (d - 1.0)).exp();
        [self.amplitude[0] * g, self.amplitude[1] * g, self.amplitude[2] * g]
    }
}

/// An environment: a sum of SG lobes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EnvSgs {
    pub lobes: Vec<SgLobe>,
}

impl EnvSgs {
    pub fn eval(&self, dir: [f32; 3]) -> [f32; 3] {
        self.lobes.iter().fold([0.0; 3], |acc, l| {
            let v = l.eval(dir);
            [acc[0] + v[0], acc[1] + v[1], acc[2] + v[2]]
        })
    }

    /// Write the SG parameters as JSON (`{"frame": .., "lobes": [{axis, sharpness, amplitude}]}`).
    pub fn write_json(&self, path: &Path) -> Result<(), DataError> {
        let doc = serde_json::json!({
            "frame": "world, right-handed, +Y up (glTF); G(w) = amplitude * exp(sharpness * (dot(w, axis) - 1))",
            "lobes": self.lobes,
        });
        let text = serde_json::to_string_pretty(&doc).map_err(|e| DataError::new(path, e.to_string()))?;
        atomic_write(path, text.as_bytes())
    }

    /// Read SG parameters written by [`EnvSgs::write_json`]. The file's size (at most
    /// [`MAX_ENV_JSON_BYTES`]) and lobe count (at most [`MAX_ENV_LOBES`]) are bounded; every lobe
    /// needs a finite non-zero axis (normalised on reading when it is not unit length), a finite sharpness > 0 and a finite
    /// amplitude, else a [`DataError`] naming the file and the lobe.
    pub fn read_json(path: &Path) -> Result<Self, DataError> {
        #[derive(Deserialize)]
        struct Doc {
            lobes: Vec<SgLobe>,
        }
        let text = crate::util::read_text_bounded(path, MAX_ENV_JSON_BYTES)?;
        let doc: Doc = serde_json::from_str(&text).map_err(|e| DataError::new(path, format!("not an SG environment JSON: {e}")))?;
        if doc.lobes.len() > MAX_ENV_LOBES {
            return Err(DataError::new(path, format!("{} lobes, more than the {MAX_ENV_LOBES} accepted", doc.lobes.len())));
        }
        let mut lobes = doc.lobes;
        for (i, l) in lobes.iter_mut().enumerate() {
            let n = l.axis.iter().map(|v| (*v as f64) * (*v as f64)).sum::<f64>().sqrt();
            if !(n.is_finite() && n > 1e-12) {
                return Err(DataError::new(path, format!("lobe {i}: axis {:?} is not a finite non-zero direction", l.axis)));
            }
            if (n - 1.0).abs() > 1e-5 {
                for a in &mut l.axis {
                    *a = (*a as f64 / n) as f32;
                }
            }
            if !(l.sharpness.is_finite() && l.sharpness > 0.0) {
                return Err(DataError::new(path, format!("lobe {i}: sharpness {} must be finite and > 0", l.sharpness)));
            }
            if l.amplitude.iter().any(|v| !v.is_finite()) {
                return Err(DataError::new(path, format!("lobe {i}: amplitude {:?} is not finite", l.amplitude)));
            }
        }
        Ok(Self { lobes })
    }
}

/// Largest SG environment JSON [`EnvSgs::read_json`] accepts, in bytes.
pub const MAX_ENV_JSON_BYTES: u64 = 16 << 20;
/// Most lobes [`EnvSgs::read_json`] accepts.
pub const MAX_ENV_LOBES: usize = 4096;

/// Which latlong layout a map uses (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum LatlongConvention {
    /// OpenEXR / USD DomeLight: +Y up, centre looks along +Z.
    #[default]
    OpenExrUsd,
    /// Blender World Environment Texture: +Z up, centre looks along +X.
    Blender,
}

/// World direction (+Y up) of the centre of pixel (x, y) of a `width`×`height` latlong map.
pub fn latlong_dir(conv: LatlongConvention, x: usize, y: usize, width: usize, height: usize) -> [f32; 3] {
    let u = (x as f32 + 0.5) / width as f32;
    let v = (y as f32 + 0.5) / height as f32;
    uv_to_dir(conv, u, v)
}

/// World direction for latlong coordinates (u, v) in [0, 1]², v = 0 at the zenith.
pub fn uv_to_dir(conv: LatlongConvention, u: f32, v: f32) -> [f32; 3] {
    let theta = v * std::f32::consts::PI;
    let phi = 2.0 * std::f32::consts::PI * (0.5 - u);
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    match conv {
        // u = 0.5 → +Z, u = 0.25 → +X, up +Y.
        LatlongConvention::OpenExrUsd => [st * sp, ct, st * cp],
        // Blender frame b = (sinθ cosφ, sinθ sinφ, cosθ); ours = (b.x, b.z, −b.y).
        LatlongConvention::Blender => [st * cp, ct, -(st * sp)],
    }
}

/// Latlong (u, v) of a world direction; inverse of [`uv_to_dir`].
pub fn dir_to_uv(conv: LatlongConvention, d: [f32; 3]) -> (f32, f32) {
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-30);
    let (x, y, z) = (d[0] / n, d[1] / n, d[2] / n);
    let theta = y.clamp(-1.0, 1.0).acos();
    let phi = match conv {
        LatlongConvention::OpenExrUsd => x.atan2(z),
        LatlongConvention::Blender => (-z).atan2(x),
    };
    let u = (0.5 - phi / (2.0 * std::f32::consts::PI)).rem_euclid(1.0);
    (u, theta / std::f32::consts::PI)
}

/// Render the SG environment into a `width`×`height` RGB latlong image (linear float).
pub fn render_latlong(env: &EnvSgs, width: usize, height: usize, conv: LatlongConvention) -> Vec<f32> {
    use rayon::prelude::*;
    let mut out = vec![0.0f32; width * height * 3];
    out.par_chunks_mut(width * 3).enumerate().for_each(|(y, row)| {
        for x in 0..width {
            let c = env.eval(latlong_dir(conv, x, y, width, height));
            row[x * 3..x * 3 + 3].copy_from_slice(&c);
        }
    });
    out
}

/// Render the environment and write it as a float latlong EXR (2:1).
pub fn write_latlong_exr(env: &EnvSgs, path: &Path, width: usize, conv: LatlongConvention) -> Result<(), DataError> {
    let height = (width / 2).max(1);
    let rgb = render_latlong(env, width, height, conv);
    crate::image_io::write_exr_rgb(path, width, height, &rgb)
}

/// A latlong HDR environment read from an EXR: RGB (alpha dropped), linear, row 0 = zenith.
#[derive(Clone, Debug)]
pub struct LatlongMap {
    pub width: usize,
    pub height: usize,
    /// RGB, row-major from the top row.
    pub rgb: Vec<f32>,
    /// Values below zero that were clamped to 0 (DWA ringing), and the most negative one.
    pub clamped_negatives: usize,
    pub min_value: f32,
}

/// Read a latlong environment EXR (any compression the `exr` crate decodes: none, RLE, ZIP,
/// PIZ, PXR24, B44, DWAA/DWAB). Negative values are clamped to 0 and counted: shipped maps hold
/// DWA ringing (>= -0.004) and real negatives (InvRender envmap6, -0.27). NaN/Inf pixels and
/// non-2:1 maps are a [`DataError`] naming the file.
pub fn read_latlong_exr(path: &Path) -> Result<LatlongMap, DataError> {
    if !path.exists() {
        return Err(DataError::new(path, "file not found"));
    }
    if !path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr")) {
        return Err(DataError::new(path, "not an .exr file (fit-env reads latlong OpenEXR maps)"));
    }
    let img = crate::image_io::read_image_linear(path)?;
    let (w, h) = (img.width, img.height);
    if w != 2 * h {
        return Err(DataError::new(path, format!("a latlong map must be 2:1, this one is {w}x{h}")));
    }
    let mut rgb = img.rgb();
    if let Some(i) = rgb.iter().position(|v| !v.is_finite()) {
        let p = i / 3;
        return Err(DataError::new(path, format!("non-finite value {} at pixel ({}, {})", rgb[i], p % w, p / w)));
    }
    let mut clamped = 0;
    let mut min_value = f32::INFINITY;
    for v in &mut rgb {
        min_value = min_value.min(*v);
        if *v < 0.0 {
            *v = 0.0;
            clamped += 1;
        }
    }
    Ok(LatlongMap { width: w, height: h, rgb, clamped_negatives: clamped, min_value })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn documented_axes() {
        let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-5);
        let c = LatlongConvention::OpenExrUsd;
        assert!(close(uv_to_dir(c, 0.5, 0.5), [0.0, 0.0, 1.0]));
        assert!(close(uv_to_dir(c, 0.25, 0.5), [1.0, 0.0, 0.0]));
        assert!(close(uv_to_dir(c, 0.3, 0.0), [0.0, 1.0, 0.0]));
        let b = LatlongConvention::Blender;
        // Blender +X = ours +X; Blender +Y = ours −Z.
        assert!(close(uv_to_dir(b, 0.5, 0.5), [1.0, 0.0, 0.0]));
        assert!(close(uv_to_dir(b, 0.25, 0.5), [0.0, 0.0, -1.0]));
        for conv in [c, b] {
            for (u, v) in [(0.1, 0.2), (0.7, 0.9), (0.5, 0.5), (0.95, 0.4)] {
                let (u2, v2) = dir_to_uv(conv, uv_to_dir(conv, u, v));
                assert!((u - u2).abs() < 1e-4 && (v - v2).abs() < 1e-4, "{conv:?} {u},{v} -> {u2},{v2}");
            }
        }
    }
}
