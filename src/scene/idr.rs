//! IDR / DTU / NeuS: `cameras_sphere.npz` (or `cameras.npz`) + `image/` + `mask/`.
//!
//! `world_mat_i` = K[R|t] (world → image, 4×4, last row 0 0 0 1) and `scale_mat_i` maps the unit sphere
//! to the world. P = world_mat · scale_mat maps the unit sphere to pixels; we decompose `world_mat` into
//! K, R, t by an RQ decomposition (positive focal lengths, depth > 0, overall sign of P fixed by det) and
//! take the normalisation from `scale_mat_0` (the normalised frame is exactly IDR's unit sphere). OpenCV
//! integer pixel coordinates are pixel centres, so cx, cy get +0.5 (module docs of `scene`).
//! Images and masks pair with the cameras by sorted file order.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};

use super::normalise::BoundHint;
use super::{list_images, image_size, world_from_camera, Camera, RawView, Split};
use crate::util::DataError;

fn bad(path: &Path, what: impl Into<String>) -> DataError {
    DataError::new(path, what.into())
}

/// Largest npy array (in bytes, header included) the scene readers accept: a camera matrix is
/// ~200 bytes, `poses_bounds.npy` 136 bytes per view.
pub(crate) const MAX_NPY_BYTES: u64 = 64 << 20;

/// An npy array held in memory (`bytes`) as f64 values with its shape. The header's declared
/// length, and the shape × item size it declares, are checked against the bytes that are there
/// before anything is allocated; at most `max_values` values are accepted.
pub(crate) fn npy_f64(path: &Path, name: &str, bytes: &[u8], max_values: u64) -> Result<(Vec<u64>, Vec<f64>), DataError> {
    // Pre-header: magic, version, header length (u16 in v1, u32 in v2/v3).
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(bad(path, format!("{name}: not an npy array (no \\x93NUMPY magic)")));
    }
    let (pre, header_len) = match bytes[6] {
        1 => (10usize, u16::from_le_bytes([bytes[8], bytes[9]]) as usize),
        2 | 3 if bytes.len() >= 12 => (12usize, u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize),
        v => return Err(bad(path, format!("{name}: unsupported npy version {v}"))),
    };
    let data_start = pre.checked_add(header_len).filter(|&e| e <= bytes.len()).ok_or_else(|| {
        bad(path, format!("{name}: npy header declares {header_len} bytes but the array holds only {}", bytes.len() - pre))
    })?;
    let f = npyz::NpyFile::new(bytes).map_err(|e| bad(path, format!("{name}: malformed npy: {e}")))?;
    let shape = f.shape().to_vec();
    let item = match f.dtype() {
        npyz::DType::Plain(ts) => {
            let ts = ts.to_string();
            if ts.ends_with("f8") {
                8u64
            } else if ts.ends_with("f4") {
                4
            } else {
                return Err(bad(path, format!("{name}: dtype {ts} is not float32/float64")));
            }
        }
        _ => return Err(bad(path, format!("{name}: not a plain float array"))),
    };
    let values = shape.iter().try_fold(1u64, |a, &d| a.checked_mul(d));
    let avail = (bytes.len() - data_start) as u64;
    match values {
        Some(n) if n <= max_values && n.checked_mul(item).is_some_and(|b| b <= avail) => {}
        _ => {
            return Err(bad(
                path,
                format!(
                    "{name}: shape {shape:?} declares {} values of {item} bytes but the array holds {avail} bytes of data (at most {max_values} values accepted)",
                    values.map_or("more than 2^64".to_string(), |n| n.to_string())
                ),
            ))
        }
    }
    let vals = if item == 8 {
        f.into_vec::<f64>().map_err(|e| bad(path, format!("{name}: {e}")))?
    } else {
        f.into_vec::<f32>().map_err(|e| bad(path, format!("{name}: {e}")))?.into_iter().map(f64::from).collect()
    };
    if vals.len() as u64 != values.unwrap_or(0) {
        return Err(bad(path, format!("{name}: read {} values for shape {shape:?}", vals.len())));
    }
    Ok((shape, vals))
}

type Npz = npyz::npz::NpzArchive<std::io::BufReader<std::fs::File>>;

/// The bytes of array `name` of an npz (its zip entry read with a cap, whatever size the entry
/// declares), or None if there is no such array.
fn npz_entry(path: &Path, npz: &mut Npz, name: &str) -> Result<Option<Vec<u8>>, DataError> {
    use std::io::Read;
    let zip = npz.zip_archive();
    let Some(entry) = zip.file_names().find(|f| npyz::npz::array_name_from_file_name(f) == Some(name)).map(str::to_owned) else {
        return Ok(None);
    };
    let f = zip.by_name(&entry).map_err(|e| bad(path, format!("malformed npz ({name}): {e}")))?;
    if f.size() > MAX_NPY_BYTES {
        return Err(bad(path, format!("{name}: npz entry declares {} bytes, more than the {MAX_NPY_BYTES} accepted", f.size())));
    }
    let mut buf = Vec::new();
    f.take(MAX_NPY_BYTES + 1).read_to_end(&mut buf).map_err(|e| bad(path, format!("malformed npz ({name}): {e}")))?;
    if buf.len() as u64 > MAX_NPY_BYTES {
        return Err(bad(path, format!("{name}: npz entry holds more than the {MAX_NPY_BYTES} bytes accepted")));
    }
    Ok(Some(buf))
}

fn mat4(path: &Path, npz: &mut Npz, name: &str) -> Result<Option<DMat4>, DataError> {
    let Some(bytes) = npz_entry(path, npz, name)? else {
        return Ok(None);
    };
    let (shape, v) = npy_f64(path, name, &bytes, 16)?;
    if shape != [4, 4] && shape != [3, 4] {
        return Err(bad(path, format!("{name} has shape {shape:?}, expected 4x4")));
    }
    if v.iter().any(|x| !x.is_finite()) {
        return Err(bad(path, format!("{name} has non-finite values")));
    }
    let mut rows = [[0.0, 0.0, 0.0, 1.0]; 4];
    rows[3] = [0.0, 0.0, 0.0, 1.0];
    for r in 0..shape[0] as usize {
        rows[r] = [v[r * 4], v[r * 4 + 1], v[r * 4 + 2], v[r * 4 + 3]];
    }
    Ok(Some(DMat4::from_cols_array_2d(&rows).transpose()))
}

/// RQ decomposition of a 3×3 projection M = K·R (K upper triangular with positive diagonal, R orthonormal).
/// Returns None if M is singular.
pub fn rq3(m: DMat3) -> Option<(DMat3, DMat3)> {
    let (m1, m2, m3) = (m.row(0), m.row(1), m.row(2));
    let k33 = m3.length();
    if k33 < 1e-12 {
        return None;
    }
    let r3 = m3 / k33;
    let k23 = m2.dot(r3);
    let u2 = m2 - k23 * r3;
    let k22 = u2.length();
    if k22 < 1e-12 * k33 {
        return None;
    }
    let r2 = u2 / k22;
    let (k13, k12) = (m1.dot(r3), m1.dot(r2));
    let u1 = m1 - k13 * r3 - k12 * r2;
    let k11 = u1.length();
    if k11 < 1e-12 * k33 {
        return None;
    }
    let r1 = u1 / k11;
    let k = DMat3::from_cols(DVec3::new(k11, 0.0, 0.0), DVec3::new(k12, k22, 0.0), DVec3::new(k13, k23, k33));
    let r = DMat3::from_cols(r1, r2, r3).transpose();
    Some((k, r))
}

/// Decompose a world→image 3×4 projection (given as a 4×4 with the 3×4 on top) into intrinsics and a
/// world_from_camera (OpenCV axes). Returns (fx, fy, cx, cy (OpenCV: integer = pixel centre), skew, matrix).
pub fn decompose_projection(p: DMat4) -> Option<(f64, f64, f64, f64, f64, DMat4)> {
    let mut m = DMat3::from_mat4(p);
    let mut p4 = p.w_axis.truncate();
    if m.determinant() < 0.0 {
        m = -m;
        p4 = -p4;
    }
    let (k, r) = rq3(m)?;
    let t = k.inverse() * p4;
    let s = k.z_axis.z;
    let k = k * (1.0 / s);
    let rot_wc = r.transpose();
    let c = -(rot_wc * t);
    Some((k.x_axis.x, k.y_axis.y, k.z_axis.x, k.z_axis.y, k.y_axis.x, world_from_camera(rot_wc, c)))
}

fn first_dir(root: &Path, names: &[&str]) -> Option<PathBuf> {
    names.iter().map(|n| root.join(n)).find(|p| p.is_dir())
}

pub(crate) fn read(path: &Path) -> Result<(Vec<RawView>, BoundHint), DataError> {
    let (root, npz_path) = if path.is_file() {
        (path.parent().unwrap_or(Path::new(".")).to_path_buf(), path.to_path_buf())
    } else {
        let p = ["cameras_sphere.npz", "cameras.npz"].iter().map(|n| path.join(n)).find(|p| p.is_file());
        (path.to_path_buf(), p.ok_or_else(|| bad(path, "no cameras_sphere.npz"))?)
    };
    let mut npz = npyz::npz::NpzArchive::open(&npz_path).map_err(|e| bad(&npz_path, format!("malformed npz: {e}")))?;
    let mut count = 0;
    while npz.array_names().any(|n| n == format!("world_mat_{count}")) {
        count += 1;
    }
    if count == 0 {
        return Err(bad(&npz_path, "no world_mat_0 in the npz"));
    }
    let image_dir = first_dir(&root, &["image", "images", "rgb"]).ok_or_else(|| bad(&root, "no image/ folder"))?;
    let images = list_images(&image_dir)?;
    if images.len() != count {
        return Err(bad(&image_dir, format!("{} images for {count} cameras in {}", images.len(), npz_path.display())));
    }
    let masks = match first_dir(&root, &["mask", "masks"]) {
        Some(d) => {
            let m = list_images(&d)?;
            if m.len() != count {
                return Err(bad(&d, format!("{} masks for {count} cameras in {}", m.len(), npz_path.display())));
            }
            Some(m)
        }
        None => None,
    };
    let mut views = Vec::with_capacity(count);
    let mut hint = BoundHint::default();
    for (i, image_path) in images.into_iter().enumerate() {
        let wm_name = format!("world_mat_{i}");
        let wm = mat4(&npz_path, &mut npz, &wm_name)?.ok_or_else(|| bad(&npz_path, format!("no {wm_name}")))?;
        if i == 0 {
            let sm = mat4(&npz_path, &mut npz, "scale_mat_0")?.unwrap_or(DMat4::IDENTITY);
            let (sx, sy, sz) = (sm.x_axis.x, sm.y_axis.y, sm.z_axis.z);
            if !(sx > 0.0 && (1.0 / sx).is_finite() && (sx - sy).abs() <= 1e-6 * sx && (sx - sz).abs() <= 1e-6 * sx) {
                return Err(bad(&npz_path, format!("scale_mat_0 is not a uniform positive scale ({sx}, {sy}, {sz})")));
            }
            hint = BoundHint {
                sphere: Some((sm.w_axis.truncate(), sx)),
                exact_unit_sphere: true,
                source: "scale_mat_0 (IDR unit sphere)".into(),
            };
        }
        let last = wm.row(3);
        if (last - glam::DVec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > 1e-6 {
            return Err(bad(&npz_path, format!("{wm_name}: last row is {last}, expected 0 0 0 1")));
        }
        let (fx, fy, cx, cy, skew, w2c) =
            decompose_projection(wm).ok_or_else(|| bad(&npz_path, format!("{wm_name}: singular camera matrix")))?;
        if skew.abs() > 1e-3 * fx {
            return Err(bad(&npz_path, format!("{wm_name}: skew {skew:.4} is not supported")));
        }
        let (w, h) = image_size(&image_path)?;
        let camera = Camera { width: w, height: h, fx, fy, cx: cx + 0.5, cy: cy + 0.5, distortion: None, world_from_camera: w2c };
        let name = image_path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let mask_path = masks.as_ref().map(|m| m[i].clone());
        views.push(RawView { name, split: Split::Train, camera, image_path, mask_path, alpha_mask: false, sources: vec![npz_path.clone()] });
    }
    Ok((views, hint))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decomposition_recovers_a_known_camera() {
        let k = DMat3::from_cols(DVec3::new(700.0, 0.0, 0.0), DVec3::new(0.0, 720.0, 0.0), DVec3::new(200.0, 150.0, 1.0));
        let r = DMat3::from_rotation_z(0.4) * DMat3::from_rotation_x(1.1);
        let c = DVec3::new(1.0, -2.0, 3.0);
        let t = -(r * c);
        let m = k * r;
        let mut p = DMat4::from_mat3(m);
        p.w_axis = (k * t).extend(1.0);
        // an arbitrary negative overall scale must not matter
        let p = p * -2.5;
        let mut p = p;
        p.w_axis.w = 1.0;
        p.x_axis.w = 0.0;
        p.y_axis.w = 0.0;
        p.z_axis.w = 0.0;
        let (fx, fy, cx, cy, skew, w2c) = decompose_projection(p).unwrap();
        let got = [fx, fy, cx, cy, skew];
        crate::testing::assert_close("K", &got, &[700.0, 720.0, 200.0, 150.0, 0.0], crate::testing::Tolerance::new(1e-9, 1e-9));
        let c2 = w2c.w_axis.truncate();
        assert!((c2 - c).length() < 1e-9, "{c2}");
        let r2 = DMat3::from_mat4(w2c).transpose();
        assert!((r2.x_axis - r.x_axis).length() < 1e-9 && (r2.z_axis - r.z_axis).length() < 1e-9);
    }
}
