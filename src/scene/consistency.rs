//! Silhouette agreement between views: finds the views whose mask contradicts all the others.
//!
//! The visual hull keeps a point only where *every* view's mask covers it, so one view with a wrong
//! pose (a failed registration) or a wrong mask cuts a slab out of the object: the hull, the
//! initialisation fitted to it, the normalisation's bound and the mask loss all inherit the cut.
//! Here every voxel of a grid around the object counts the views that see it as background. A voxel
//! that exactly one view rejects while the others accept it is that view's *solo carve*. With good
//! poses and masks a view carves alone only thin slivers where the silhouettes meet (a few tenths of
//! a percent of the hull); a view that is off carves a slab. A view whose solo carve exceeds
//! [`SOLO_CARVE_ABOVE`] of the hull (and [`SOLO_CARVE_OVER_MEDIAN`] × the views' median) is taken out,
//! worst first, and the rest are checked again.

use glam::{DMat4, DVec3};
use rayon::prelude::*;
use serde::Serialize;

use super::View;

/// A view is excluded when it alone carves more than this fraction of the hull the views agree on...
pub const SOLO_CARVE_ABOVE: f64 = 0.05;
/// ...and more than this multiple of the median view's solo carve.
pub const SOLO_CARVE_OVER_MEDIAN: f64 = 10.0;
/// At most this fraction of the views is excluded: beyond it the capture as a whole disagrees, and
/// the outliers cannot be told from the rest.
const MAX_EXCLUDED_FRACTION: f64 = 0.25;
/// Voxels per side of the grid over the object's box.
const RES: usize = 96;
/// Voxels per side of the coarse grid that finds the box.
const COARSE_RES: usize = 64;

/// A view taken out of the scene.
#[derive(Clone, Debug, Serialize)]
pub struct ExcludedView {
    pub name: String,
    pub image: String,
    /// Fraction of the agreed hull this view alone carves away.
    pub solo_carve: f64,
}

/// What the check found.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SilhouetteCheck {
    /// Views with a mask that took part.
    pub views: usize,
    /// The median view's solo carve (fraction of the agreed hull), after exclusions.
    pub median_solo_carve: f64,
    /// The largest solo carve among the views kept, and its view.
    pub worst_kept: Option<(String, f64)>,
    pub excluded: Vec<ExcludedView>,
    /// Set when the views disagree too widely to single any out (nothing was excluded).
    pub note: Option<String>,
}

/// What view `v` (with its inverse pose `cam_from_world`) says of world point `p`: -1 it does not
/// see it (behind the camera or outside the image), 0 background, 1 foreground (mask >= 0.5).
pub(crate) fn verdict(v: &View, cam_from_world: &DMat4, p: DVec3) -> i8 {
    let q = cam_from_world.transform_point3(p);
    let Some(px) = v.camera.project_camera_point(q) else { return -1 };
    if px.x < 0.0 || px.y < 0.0 || px.x >= v.camera.width as f64 || px.y >= v.camera.height as f64 {
        return -1;
    }
    i8::from(v.mask_at(px.x, px.y) >= 0.5)
}

/// Centre of voxel `i` (x fastest, then y, then z) of a `res`³ grid over the cube `centre ± half`.
pub(crate) fn voxel_centre(i: usize, res: usize, centre: DVec3, half: f64) -> DVec3 {
    let (x, y, z) = (i % res, (i / res) % res, i / (res * res));
    centre - DVec3::splat(half) + DVec3::new(x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5) * (2.0 * half / res as f64)
}

/// Per voxel of a `res`³ grid over the cube `centre ± half`: (views that see it, views that reject
/// it, the first view that rejects it).
pub(crate) fn count(views: &[&View], prs: &[DMat4], centre: DVec3, half: f64, res: usize) -> Vec<(u16, u16, u16)> {
    (0..res * res * res)
        .into_par_iter()
        .map(|i| {
            let p = voxel_centre(i, res, centre, half);
            let (mut seen, mut bg, mut first) = (0u16, 0u16, u16::MAX);
            for (k, (v, pr)) in views.iter().zip(prs).enumerate() {
                match verdict(v, pr, p) {
                    -1 => {}
                    0 => {
                        seen += 1;
                        bg += 1;
                        if first == u16::MAX {
                            first = k as u16;
                        }
                    }
                    _ => seen += 1,
                }
            }
            (seen, bg, first)
        })
        .collect()
}

/// Check the views with masks (world frame; `start` is a point inside the object, `half` the half
/// size of a cube around it that holds the object). Returns the indices (into `views`) to exclude:
/// none when `exclude` is false (`--keep-all-views`), the outliers then named in the note.
pub fn check(views: &[View], start: DVec3, half: f64, exclude: bool) -> (Vec<usize>, SilhouetteCheck) {
    let idx: Vec<usize> = (0..views.len()).filter(|&i| views[i].mask.is_some()).collect();
    let mut report = SilhouetteCheck { views: idx.len(), ..Default::default() };
    if idx.len() < 4 {
        return (Vec::new(), report);
    }
    let mut kept = idx.clone();
    let mut excluded: Vec<usize> = Vec::new();
    let max_excluded = if exclude { ((idx.len() as f64) * MAX_EXCLUDED_FRACTION).floor() as usize } else { 0 };
    loop {
        let vs: Vec<&View> = kept.iter().map(|&i| &views[i]).collect();
        let prs: Vec<DMat4> = vs.iter().map(|v| v.camera.world_from_camera.inverse()).collect();
        // Only voxels that at least half of the views see count: the object is in nearly every
        // frame, while far corners of the search cube are seen by a few views and rejected by
        // fewer, which would pass for agreement.
        let min_seen = (vs.len() / 2).max(2) as u16;
        // The box: voxels that at most a fifth of the views reject (so a few bad views cannot cut it).
        let tol = (vs.len() / 5).max(1) as u16;
        let coarse = count(&vs, &prs, start, half, COARSE_RES);
        let cstep = 2.0 * half / COARSE_RES as f64;
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for (i, &(seen, bg, _)) in coarse.iter().enumerate() {
            if seen >= min_seen && bg <= tol {
                let p = voxel_centre(i, COARSE_RES, start, half);
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        if !lo.is_finite() {
            report.note = Some("the masks share no region: no view could be singled out".into());
            report.excluded.clear();
            return (Vec::new(), report);
        }
        let centre = 0.5 * (lo + hi);
        let fine_half = 0.5 * (hi - lo).max_element() + cstep;
        let fine = count(&vs, &prs, centre, fine_half, RES);
        let agreed = fine.iter().filter(|&&(seen, bg, _)| seen >= min_seen && bg <= 1).count().max(1);
        let mut solo = vec![0usize; vs.len()];
        for &(seen, bg, first) in &fine {
            if seen >= min_seen && bg == 1 {
                solo[first as usize] += 1;
            }
        }
        let frac: Vec<f64> = solo.iter().map(|&s| s as f64 / agreed as f64).collect();
        let mut sorted = frac.clone();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        let (worst, &wf) = frac.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap_or((0, &0.0));
        let outlier = wf > SOLO_CARVE_ABOVE && wf > SOLO_CARVE_OVER_MEDIAN * median;
        if outlier && excluded.len() < max_excluded {
            let i = kept.remove(worst);
            report.excluded.push(ExcludedView {
                name: views[i].name.clone(),
                image: views[i].image_path.display().to_string(),
                solo_carve: wf,
            });
            excluded.push(i);
            continue;
        }
        if outlier {
            let n = frac.iter().filter(|&&f| f > SOLO_CARVE_ABOVE && f > SOLO_CARVE_OVER_MEDIAN * median).count();
            let why = if exclude {
                format!("more than {:.0}% of the views would go, so none more was excluded", 100.0 * MAX_EXCLUDED_FRACTION)
            } else {
                "kept (--keep-all-views)".to_string()
            };
            report.note = Some(format!(
                "{n} view(s) disagree with the others (worst: {} carves {:.1}% of the hull alone); {why}",
                vs[worst].name,
                100.0 * wf
            ));
        }
        report.median_solo_carve = median;
        report.worst_kept = Some((vs[worst].name.clone(), wf));
        return (excluded, report);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image_io::ImageF32;
    use crate::scene::{Camera, Split};
    use glam::DMat3;

    /// Two overlapping balls: a capsule-like object, not centred on the origin.
    const BALLS: [([f64; 3], f64); 2] = [([0.1, 0.0, 0.0], 0.5), ([-0.35, 0.2, 0.1], 0.35)];

    fn hits(o: DVec3, d: DVec3) -> bool {
        BALLS.iter().any(|&(c, r)| {
            let oc = o - DVec3::from(c);
            let b = oc.dot(d);
            b * b - (oc.length_squared() - r * r) >= 0.0 && -b > 0.0
        })
    }

    /// Camera at `eye` looking at the origin (OpenCV axes), world up +Z.
    fn camera(eye: DVec3, size: usize) -> Camera {
        let f = (-eye).normalize();
        let r = f.cross(DVec3::Z).normalize();
        let d = f.cross(r);
        let world_from_camera = DMat4::from_cols(r.extend(0.0), d.extend(0.0), f.extend(0.0), eye.extend(1.0));
        let s = size as f64;
        Camera { width: size, height: size, fx: 1.1 * s, fy: 1.1 * s, cx: s / 2.0, cy: s / 2.0, distortion: None, world_from_camera }
    }

    /// Twelve views on two rings; the mask is rendered with the true pose, then view `bad` (if
    /// any) gets its camera turned by `degrees` about its up axis, as a failed registration would.
    fn views(bad: Option<usize>, degrees: f64) -> Vec<View> {
        let size = 64;
        (0..12)
            .map(|i| {
                let az = i as f64 * std::f64::consts::TAU / 6.0 + if i >= 6 { 0.5 } else { 0.0 };
                let el: f64 = if i >= 6 { 0.6 } else { -0.1 };
                let eye = 3.5 * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let mut camera = camera(eye, size);
                let mut mask = vec![0.0f32; size * size];
                for y in 0..size {
                    for x in 0..size {
                        let (o, d) = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
                        mask[y * size + x] = if hits(o, d) { 1.0 } else { 0.0 };
                    }
                }
                if bad == Some(i) {
                    let up = -camera.world_from_camera.y_axis.truncate();
                    let turn = DMat4::from_mat3(DMat3::from_axis_angle(up, degrees.to_radians()));
                    let eye = camera.world_from_camera.w_axis;
                    camera.world_from_camera = turn * camera.world_from_camera;
                    camera.world_from_camera.w_axis = eye;
                }
                View {
                    name: format!("v{i:02}"),
                    split: Split::Train,
                    camera,
                    image: ImageF32::new(size, size, 3),
                    mask: Some(mask),
                    image_path: format!("v{i:02}.png").into(),
                }
            })
            .collect()
    }

    #[test]
    fn a_view_with_a_wrong_pose_is_excluded_and_good_views_are_kept() {
        let (drop, report) = check(&views(None, 0.0), DVec3::ZERO, 1.5, true);
        assert!(drop.is_empty(), "{report:?}");
        let worst = report.worst_kept.as_ref().unwrap().1;
        assert!(worst < 0.25 * SOLO_CARVE_ABOVE, "consistent views: worst solo carve {worst}");

        let (drop, report) = check(&views(Some(4), 6.0), DVec3::ZERO, 1.5, true);
        assert_eq!(drop, vec![4], "{report:?}");
        assert_eq!(report.excluded[0].name, "v04");
        assert!(report.excluded[0].solo_carve > SOLO_CARVE_ABOVE);
        assert!(report.worst_kept.as_ref().unwrap().1 < SOLO_CARVE_ABOVE, "{report:?}");
        assert!(report.note.is_none());

        // --keep-all-views: nothing excluded, the outlier named in the note.
        let (drop, report) = check(&views(Some(4), 6.0), DVec3::ZERO, 1.5, false);
        assert!(drop.is_empty() && report.excluded.is_empty(), "{report:?}");
        let note = report.note.unwrap();
        assert!(note.contains("v04") && note.contains("--keep-all-views"), "{note}");
    }

    #[test]
    fn views_without_masks_or_too_few_views_are_not_judged() {
        let mut vs = views(Some(4), 6.0);
        vs.truncate(3);
        let (drop, report) = check(&vs, DVec3::ZERO, 1.5, true);
        assert!(drop.is_empty() && report.worst_kept.is_none());
        let mut vs = views(Some(4), 6.0);
        for v in &mut vs {
            v.mask = None;
        }
        assert!(check(&vs, DVec3::ZERO, 1.5, true).0.is_empty());
    }
}
