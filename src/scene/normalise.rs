//! Normalisation of a scene into the unit sphere (object-centred), and the detected up axis.
//!
//! `x_norm = (x_world − center) · scale`. How `center` and `scale` are found, in order of preference:
//! 1. a bound the format states (IDR/DTU `scale_mat`: the unit sphere it maps is used as is; a generated
//!    scene's `scene.json` bound: radius × 1.1 maps to 1);
//! 2. the visual hull of the masks (64³ voxels in a cube around the point closest to all optical axes;
//!    a voxel survives if at least half of the views see it and every view that sees it puts it inside
//!    its mask (≥ 0.5); a view whose frame it falls outside, where the object is cropped, does not
//!    count): the hull's bounding-box centre, and its bounding radius × 1.1 maps to 1;
//! 3. no masks: the point closest to all optical axes, and the largest sphere around it that every
//!    camera sees whole (distance · sin(half the smaller field of view)).

use std::path::Path;

use glam::{DMat3, DMat4, DVec3};
use serde::Serialize;

use super::View;
use crate::util::DataError;

/// World → normalised frame: translation and uniform scale (no rotation).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Normalisation {
    /// World point that maps to the origin.
    pub center: DVec3,
    /// World units → normalised units.
    pub scale: f64,
    /// Detected up direction in the world (mean camera up, unit).
    pub up_axis: DVec3,
    /// The world axis the up direction is closest to, like "+Z" (or "none" if it is far from every axis).
    pub up_axis_name: String,
    /// How center and scale were found.
    pub method: String,
}

impl Normalisation {
    pub fn to_normalised(&self, p: DVec3) -> DVec3 {
        (p - self.center) * self.scale
    }
    pub fn to_world(&self, p: DVec3) -> DVec3 {
        p / self.scale + self.center
    }
    /// The 4×4 matrix normalised → world.
    pub fn world_from_normalised(&self) -> DMat4 {
        DMat4::from_translation(self.center) * DMat4::from_scale(DVec3::splat(1.0 / self.scale))
    }
    /// A world_from_camera matrix re-expressed in the normalised frame (rotation kept, centre moved).
    pub fn camera_to_normalised(&self, world_from_camera: DMat4) -> DMat4 {
        let mut m = world_from_camera;
        let c = self.to_normalised(m.w_axis.truncate());
        m.w_axis = c.extend(1.0);
        m
    }
}

/// Widest sphere (diameter in the capture's world units) read as metres when no unit is given:
/// a photographed object of up to about 18 m fits a sphere of 20 m with the normalisation's margin,
/// and one of 2 cm or more measured in millimetres (DTU's calibration, structured-light scanners)
/// spans more than 20 units. Between the two ranges nothing is ambiguous; outside them (a building
/// in metres, a grain in millimetres) `--metres-per-unit` sets the unit.
pub const METRES_MAX_SPAN: f64 = 20.0;

/// The capture's length unit, as the asset's metres per world unit, and why.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct CaptureUnits {
    pub metres_per_unit: f64,
    /// `metres`, `millimetres` (both read from the object's size) or `given` (`--metres-per-unit`).
    pub unit: String,
    /// One line for the user: the size it was read from and how to override it.
    pub why: String,
}

impl CaptureUnits {
    /// The unit `--metres-per-unit` gives.
    pub fn given(metres_per_unit: f64) -> Self {
        Self { metres_per_unit, unit: "given".into(), why: format!("{metres_per_unit} m per world unit (--metres-per-unit)") }
    }

    /// The unit read from the object's size: `scale` is the normalisation's (world units →
    /// normalised units, the object inside the unit sphere), so the sphere spans `2 / scale` world
    /// units. Metres up to [`METRES_MAX_SPAN`], millimetres beyond.
    pub fn from_scale(scale: f64) -> Self {
        let span = 2.0 / scale;
        if span.is_finite() && span > METRES_MAX_SPAN {
            Self {
                metres_per_unit: 1e-3,
                unit: "millimetres".into(),
                why: format!(
                    "the object's sphere spans {span:.1} world units, too large for metres (over {METRES_MAX_SPAN}): read as millimetres, {:.3} m (--metres-per-unit sets the unit)",
                    span * 1e-3
                ),
            }
        } else {
            Self {
                metres_per_unit: 1.0,
                unit: "metres".into(),
                why: format!(
                    "the object's sphere spans {span:.3} world units: read as metres (--metres-per-unit sets the unit; a capture posed by COLMAP has no true scale: --height sets the asset's height)"
                ),
            }
        }
    }
}

/// What a reader knows about the object's extent (world frame).
#[derive(Clone, Debug, Default)]
pub(crate) struct BoundHint {
    /// Centre and radius of a sphere holding the object.
    pub sphere: Option<(DVec3, f64)>,
    /// True if `sphere` already includes a margin (IDR scale_mat): it maps to radius 1 exactly.
    pub exact_unit_sphere: bool,
    /// Where the bound came from.
    pub source: String,
}

pub const MARGIN: f64 = 1.1;
const HULL_RES: usize = 64;

pub(crate) fn compute(path: &Path, views: &[View], hint: &BoundHint) -> Result<Normalisation, DataError> {
    let (up_axis, up_axis_name) = up_axis(views);
    let (center, scale, method) = if let Some((c, r)) = hint.sphere {
        if hint.exact_unit_sphere {
            (c, 1.0 / r, hint.source.clone())
        } else {
            (c, 1.0 / (r * MARGIN), format!("{}, radius x {MARGIN}", hint.source))
        }
    } else {
        let (axes, half) = search_cube(views, hint);
        if views.iter().all(|v| v.mask.is_some()) {
            let (c, r) = visual_hull_bound(path, views, axes, half)?;
            (c, 1.0 / (r * MARGIN), format!("visual hull of the masks ({HULL_RES}^3), radius x {MARGIN}"))
        } else {
            let r = views
                .iter()
                .map(|v| {
                    let fov = v.camera.fov_x().min(2.0 * (v.camera.height as f64 / (2.0 * v.camera.fy)).atan());
                    (v.camera.center() - axes).length() * (0.5 * fov).sin()
                })
                .fold(f64::INFINITY, f64::min);
            (axes, 1.0 / r, "point closest to the optical axes; largest sphere every camera sees whole".into())
        }
    };
    if !(scale.is_finite() && scale > 0.0 && center.is_finite()) {
        return Err(DataError::new(path, format!("cannot normalise the scene (centre {center}, scale {scale})")));
    }
    Ok(Normalisation { center, scale, up_axis, up_axis_name, method })
}

/// A cube (centre, half size; world frame) that holds the object: the bound the format states, or
/// around the point closest to all optical axes, reaching 95% of the way to the nearest camera.
pub(crate) fn search_cube(views: &[View], hint: &BoundHint) -> (DVec3, f64) {
    if let Some((c, r)) = hint.sphere {
        return (c, if hint.exact_unit_sphere { r } else { r * MARGIN });
    }
    let start = closest_point_to_axes(views);
    (start, 0.95 * views.iter().map(|v| (v.camera.center() - start).length()).fold(f64::INFINITY, f64::min))
}

/// Mean camera up (−y of OpenCV axes), and the nearest world axis name.
pub fn up_axis(views: &[View]) -> (DVec3, String) {
    let sum: DVec3 = views.iter().map(|v| v.camera.up()).sum();
    let up = if sum.length() > 1e-9 { sum.normalize() } else { DVec3::Z };
    let names = [(DVec3::X, "+X"), (-DVec3::X, "-X"), (DVec3::Y, "+Y"), (-DVec3::Y, "-Y"), (DVec3::Z, "+Z"), (-DVec3::Z, "-Z")];
    let (axis, name) = names.iter().max_by(|a, b| a.0.dot(up).total_cmp(&b.0.dot(up))).copied().unwrap_or((DVec3::Z, "+Z"));
    let name = if axis.dot(up) > 0.8 { name.to_string() } else { "none".to_string() };
    (up, name)
}

/// Least-squares point closest to all optical axes (falls back to the mean camera centre + the mean
/// view direction when the axes are nearly parallel).
pub fn closest_point_to_axes(views: &[View]) -> DVec3 {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for v in views {
        let d = v.camera.forward();
        let p = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * v.camera.center();
    }
    let n = views.len().max(1) as f64;
    if a.determinant().abs() / (n * n * n) > 1e-6 {
        a.inverse() * b
    } else {
        let c: DVec3 = views.iter().map(|v| v.camera.center()).sum::<DVec3>() / n;
        let f: DVec3 = views.iter().map(|v| v.camera.forward()).sum::<DVec3>().normalize_or_zero();
        c + f
    }
}

/// Bounding sphere (centre, radius) of the visual hull in the cube `start ± half`, world frame.
fn visual_hull_bound(path: &Path, views: &[View], start: DVec3, half: f64) -> Result<(DVec3, f64), DataError> {
    let vs: Vec<&View> = views.iter().collect();
    let prs: Vec<DMat4> = views.iter().map(|v| v.camera.world_from_camera.inverse()).collect();
    let step = 2.0 * half / HULL_RES as f64;
    let min_seen = (views.len() / 2).max(1) as u16;
    // A view that does not see a voxel (outside its frame: the object may be cropped there)
    // neither keeps nor rejects it; any view that rejects it carves it.
    let kept: Vec<DVec3> = super::consistency::count(&vs, &prs, start, half, HULL_RES)
        .into_iter()
        .enumerate()
        .filter(|&(_, (seen, bg, _))| bg == 0 && seen >= min_seen)
        .map(|(i, _)| super::consistency::voxel_centre(i, HULL_RES, start, half))
        .collect();
    if kept.is_empty() {
        return Err(DataError::new(path, "the masks' visual hull is empty: masks and cameras disagree"));
    }
    let lo = kept.iter().fold(DVec3::splat(f64::INFINITY), |a, p| a.min(*p));
    let hi = kept.iter().fold(DVec3::splat(f64::NEG_INFINITY), |a, p| a.max(*p));
    let c = 0.5 * (lo + hi);
    let r = kept.iter().map(|p| (*p - c).length()).fold(0.0, f64::max) + 0.87 * step;
    Ok((c, r))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capture_units_read_metres_or_millimetres_from_the_objects_span() {
        // A 2.4 m sphere (the example, in Blender metres) and one of 18 m stay metres.
        for span in [2.4, 18.0, METRES_MAX_SPAN] {
            let u = CaptureUnits::from_scale(2.0 / span);
            assert_eq!((u.metres_per_unit, u.unit.as_str()), (1.0, "metres"), "span {span}");
        }
        // DTU scan37's 512-unit sphere is half a metre in millimetres; so is anything past 20.
        for span in [512.0, 20.5, 1e5] {
            let u = CaptureUnits::from_scale(2.0 / span);
            assert_eq!((u.metres_per_unit, u.unit.as_str()), (1e-3, "millimetres"), "span {span}");
            assert!(u.why.contains("--metres-per-unit"), "{}", u.why);
        }
        let g = CaptureUnits::given(0.01);
        assert_eq!((g.metres_per_unit, g.unit.as_str()), (0.01, "given"));
    }
}
