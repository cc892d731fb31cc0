//! LLFF: `poses_bounds.npy` (N×17: a row-major 3×5 matrix [R | position | (H, W, focal)] then near, far)
//! + `images/` (+ optional `masks/`, matched by file stem; soft masks are kept as weights in [0, 1]).
//!
//! The 3×4 pose is camera-to-world with columns [down, right, backwards, position]; converted to OpenCV
//! axes (x = right, y = down, z = −backwards). The principal point is the image centre. When the images
//! are a different size than the (H, W) stored (e.g. `images_4/`), the focal length is scaled by the
//! width ratio (the aspect ratio must match). Splits follow the NeRF LLFF loader: every 8th view
//! (index % 8 == 0) is `test`, the rest `train`.

use std::path::Path;

use glam::{DMat3, DVec3};

use super::normalise::BoundHint;
use super::{check_rotation, image_size, list_images, world_from_camera, Camera, RawView, Split};
use crate::util::DataError;

pub const LLFF_HOLD: usize = 8;

fn bad(path: &Path, what: impl Into<String>) -> DataError {
    DataError::new(path, what.into())
}

pub(crate) fn read(path: &Path) -> Result<(Vec<RawView>, BoundHint), DataError> {
    let (root, npy) = if path.is_file() {
        (path.parent().unwrap_or(Path::new(".")).to_path_buf(), path.to_path_buf())
    } else {
        (path.to_path_buf(), path.join("poses_bounds.npy"))
    };
    let bytes = crate::util::read_bounded(&npy, super::idr::MAX_NPY_BYTES)?;
    let (shape, v) = super::idr::npy_f64(&npy, "poses_bounds", &bytes, super::idr::MAX_NPY_BYTES / 8)?;
    if shape.len() != 2 || shape[1] != 17 || shape[0] == 0 {
        return Err(bad(&npy, format!("shape {shape:?}, expected N x 17")));
    }
    let n = shape[0] as usize;
    let image_dir = root.join("images");
    let images = list_images(&image_dir)?;
    if images.len() != n {
        return Err(bad(&image_dir, format!("{} images for {n} poses in {}", images.len(), npy.display())));
    }
    let mask_dir = root.join("masks");
    let masks = if mask_dir.is_dir() { Some(list_images(&mask_dir)?) } else { None };
    let mut views = Vec::with_capacity(n);
    for (i, image_path) in images.into_iter().enumerate() {
        let row = &v[i * 17..(i + 1) * 17];
        if row.iter().any(|x| !x.is_finite()) {
            return Err(bad(&npy, format!("pose {i} has non-finite values")));
        }
        let col = |c: usize| DVec3::new(row[c], row[5 + c], row[10 + c]);
        let (down, right, back, pos) = (col(0), col(1), col(2), col(3));
        let (h0, w0, focal) = (row[4], row[9], row[14]);
        let r_cv = DMat3::from_cols(right, down, -back);
        check_rotation(&npy, &format!("pose {i}"), r_cv, 1e-3)?;
        let (w, h) = image_size(&image_path)?;
        if !(w0 > 0.0 && h0 > 0.0 && focal > 0.0) {
            return Err(bad(&npy, format!("pose {i}: bad H, W, focal ({h0}, {w0}, {focal})")));
        }
        let ratio = w as f64 / w0;
        if ((h as f64 / h0) - ratio).abs() > 0.01 * ratio {
            return Err(bad(
                &image_path,
                format!("image is {w}x{h}, which does not match the aspect of {w0}x{h0} in {}", npy.display()),
            ));
        }
        let f = focal * ratio;
        if !(f.is_finite() && f > 0.0) {
            return Err(bad(&npy, format!("pose {i}: focal {focal} for a {w0}x{h0} image gives focal {f} at {w}x{h}")));
        }
        let camera = Camera {
            width: w,
            height: h,
            fx: f,
            fy: f,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
            distortion: None,
            world_from_camera: world_from_camera(r_cv, pos),
        };
        let stem = image_path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let mask_path = match &masks {
            Some(m) => Some(
                m.iter()
                    .find(|p| p.file_stem().is_some_and(|s| s.to_string_lossy() == stem))
                    .cloned()
                    .ok_or_else(|| bad(&mask_dir, format!("no mask for image {}", image_path.display())))?,
            ),
            None => None,
        };
        let split = if i % LLFF_HOLD == 0 { Split::Test } else { Split::Train };
        views.push(RawView { name: stem, split, camera, image_path, mask_path, alpha_mask: false, sources: vec![npy.clone()] });
    }
    Ok((views, BoundHint::default()))
}
