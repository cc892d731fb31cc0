//! How many training photos see each part of the trained surface. Where fewer than three do, the
//! photos hold little parallax for the geometry and few looks at the material (a view count the
//! tool should report, not hide: an 8-photo capture or a capture from one side leaves much of the
//! object so). The surface is sampled with one point per grid cell it crosses (the stage-1
//! SDF sampled on [`SdfGrid`], about equal areas); a photo sees a point when the point faces it,
//! projects inside its image and the ray toward its camera leaves the object unblocked.

use glam::DVec3;
use rayon::prelude::*;

use crate::backend::BackendError;
use crate::render::grid::SdfGrid;
use crate::render::{trace_secondary, Rays};
use crate::scene::Camera;

/// A point faces a camera when `n·ω` to it exceeds this (about 84° from the normal at most:
/// grazing views see nothing of a surface's texture).
const FACING_COS: f64 = 0.1;

/// Stage 1 flags its result weak when more than this fraction of the surface is seen by fewer
/// than three training photos (the views multi-view stereo, and the concavity carving's
/// photo-consistency, want at the least). Measured (fraction below three): the bundled example
/// 6.7%, `make_scene.py`'s bowl 5.1% and glossy scene 21.1%, all 24 photos; the Ethiopian head
/// 8.1% (its unseen base); the example cut to 8 photos 45.3%, with its geometry at the visual
/// hull's accuracy (Chamfer 0.18% → 0.62% of size) and nothing flagged before.
pub const WEAK_BELOW_THREE: f64 = 0.25;

/// Sphere-tracing steps toward each camera (the ray stops once it hits or leaves the bound).
const OCCLUSION_STEPS: usize = 64;

/// The coverage of the trained surface by the training photos.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SurfaceCoverage {
    /// Surface points sampled (one per grid cell the surface crosses).
    pub surface_points: usize,
    /// Fraction of the surface seen by 0, 1, 2 and 3 or more training photos.
    pub seen_by: [f64; 4],
    /// Median number of photos that see a surface point.
    pub median_views: f64,
    /// The grid the surface was sampled on (nodes per axis).
    pub grid_nodes: usize,
}

impl SurfaceCoverage {
    /// Fraction of the surface fewer than three photos see.
    pub fn below_three(&self) -> f64 {
        self.seen_by[0] + self.seen_by[1] + self.seen_by[2]
    }

    /// Too few photos see too much of the surface: more than [`WEAK_BELOW_THREE`] of it below three.
    pub fn weak(&self) -> bool {
        self.below_three() > WEAK_BELOW_THREE
    }

    /// The report's record (stage 1's `coverage`, `info`'s estimate).
    pub fn to_json(&self, seconds: f64) -> serde_json::Value {
        serde_json::json!({ "surface_points": self.surface_points, "seen_by_0": self.seen_by[0], "seen_by_1": self.seen_by[1], "seen_by_2": self.seen_by[2], "seen_by_3_or_more": self.seen_by[3], "below_three": self.below_three(), "median_views": self.median_views, "grid_nodes": self.grid_nodes, "weak": self.weak(), "seconds": seconds })
    }
}

/// Central-difference gradient of the grid's trilinear field at `p` (step `h`).
fn gradient(grid: &SdfGrid, p: [f32; 3], h: f32) -> [f32; 3] {
    let mut g = [0.0f32; 3];
    for a in 0..3 {
        let (mut lo, mut hi) = (p, p);
        lo[a] -= h;
        hi[a] += h;
        g[a] = (grid.at(hi) - grid.at(lo)) / (2.0 * h);
    }
    g
}

/// One point on the surface per grid cell whose corners change sign, with its unit normal: the
/// cell's centre moved onto the zero level set by Newton steps along the gradient (kept if it ends
/// within the cell's reach and on the surface to a tenth of a cell).
pub fn surface_points(grid: &SdfGrid) -> Vec<([f32; 3], [f32; 3])> {
    let n = grid.nodes();
    let h = grid.spacing();
    (0..n - 1)
        .into_par_iter()
        .flat_map_iter(|z| {
            let mut out = Vec::new();
            for y in 0..n - 1 {
                for x in 0..n - 1 {
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for c in 0..8 {
                        let v = grid.node_value(x + (c & 1), y + ((c >> 1) & 1), z + (c >> 2));
                        lo = lo.min(v);
                        hi = hi.max(v);
                    }
                    if !(lo < 0.0 && hi > 0.0) {
                        continue;
                    }
                    let o = grid.node_position(x, y, z);
                    let centre = [o[0] + 0.5 * h, o[1] + 0.5 * h, o[2] + 0.5 * h];
                    let mut p = centre;
                    for _ in 0..3 {
                        let g = gradient(grid, p, 0.5 * h);
                        let g2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2];
                        if !(g2 > 1e-12) {
                            break;
                        }
                        let f = grid.at(p);
                        for a in 0..3 {
                            p[a] -= f * g[a] / g2;
                        }
                    }
                    let moved = (0..3).map(|a| (p[a] - centre[a]).abs()).fold(0.0f32, f32::max);
                    let g = gradient(grid, p, 0.5 * h);
                    let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
                    if moved <= h && grid.at(p).abs() <= 0.1 * h && len > 1e-6 {
                        out.push((p, [g[0] / len, g[1] / len, g[2] / len]));
                    }
                }
            }
            out
        })
        .collect()
}

/// Whether `camera` sees each point (facing it, inside its image; occlusion is checked apart).
fn facing(camera: &Camera, points: &[([f32; 3], [f32; 3])]) -> Vec<Option<([f32; 3], f32)>> {
    let c = camera.center();
    points
        .iter()
        .map(|&(p, nrm)| {
            let pd = DVec3::from(p.map(f64::from));
            let d = c - pd;
            let dist = d.length();
            let w = d / dist.max(1e-12);
            if DVec3::from(nrm.map(f64::from)).dot(w) <= FACING_COS {
                return None;
            }
            let px = camera.project(pd)?;
            let inside = px.x >= 0.0 && px.y >= 0.0 && px.x < camera.width as f64 && px.y < camera.height as f64;
            inside.then(|| (w.as_vec3().to_array(), dist as f32))
        })
        .collect()
}

/// How many of `cameras` see each surface point of the SDF sampled on `grid`.
pub fn surface_coverage(grid: &SdfGrid, cameras: &[&Camera]) -> Result<SurfaceCoverage, BackendError> {
    let points = surface_points(grid);
    let h = grid.spacing();
    let mut count = vec![0u32; points.len()];
    for camera in cameras {
        let facing = facing(camera, &points);
        let idx: Vec<usize> = (0..points.len()).filter(|&i| facing[i].is_some()).collect();
        let rays = Rays {
            origins: idx.iter().map(|&i| points[i].0).collect(),
            dirs: idx.iter().map(|&i| facing[i].map_or([0.0; 3], |f| f.0)).collect(),
        };
        // Leave the point's own cell before looking for what blocks the ray.
        let (hit, t, _) = trace_secondary(grid, &rays, 1.5 * h, OCCLUSION_STEPS, 0.05 * h, 1.0)?;
        for (j, &i) in idx.iter().enumerate() {
            let dist = facing[i].map_or(0.0, |f| f.1);
            if !(hit[j] && t[j] < dist) {
                count[i] += 1;
            }
        }
    }
    let total = points.len().max(1) as f64;
    let mut seen_by = [0.0f64; 4];
    for &c in &count {
        seen_by[(c as usize).min(3)] += 1.0 / total;
    }
    let mut sorted = count.clone();
    sorted.sort_unstable();
    let median_views = sorted.get(sorted.len() / 2).map_or(0.0, |&v| v as f64);
    Ok(SurfaceCoverage { surface_points: points.len(), seen_by, median_views, grid_nodes: grid.nodes() })
}

/// Voxels a side of the visual hull [`hull_coverage`] counts on (at 64³ the estimate lies within
/// 3 points of stage 1's count on the trained surface on six captures, README).
const HULL_ESTIMATE_RES: usize = 64;

/// Before any training (`info`): [`surface_coverage`] of the masks' visual hull (voxels seen
/// inside the mask of at least half of `views`, as stage 1's hull initialisation carves it) by
/// `views`' cameras. An estimate of what stage 1 will report: a hull has none of the object's
/// concavities, so its surface is usually seen by more photos than the object's. `None` when a
/// view has no mask or the masks leave no voxel.
pub fn hull_coverage(views: &[&crate::scene::View]) -> Result<Option<SurfaceCoverage>, BackendError> {
    if views.is_empty() || views.iter().any(|v| v.mask.is_none()) {
        return Ok(None);
    }
    let res = HULL_ESTIMATE_RES;
    let inside = super::preview::masks_hull(views, res);
    if !inside.contains(&true) {
        return Ok(None);
    }
    let hull = super::preview::smooth(super::hull::signed_distance(&inside, res, 1.0));
    let f = |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| hull.sample([q[0], q[1], q[2]])).collect()) };
    let grid = SdfGrid::sample(&f, 1.0, res + 1)?;
    let cameras: Vec<&Camera> = views.iter().map(|v| &v.camera).collect();
    surface_coverage(&grid, &cameras).map(Some)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat4;

    /// A camera at `eye` looking at the origin (OpenCV axes: +z forward, +y down), 64×64, 60° wide.
    fn camera(eye: DVec3) -> Camera {
        let fwd = (-eye).normalize();
        let up_hint = if fwd.z.abs() > 0.9 { DVec3::Y } else { DVec3::Z };
        let right = fwd.cross(up_hint).normalize();
        let down = fwd.cross(right);
        let m = DMat4::from_cols(right.extend(0.0), down.extend(0.0), fwd.extend(0.0), eye.extend(1.0));
        let f = 32.0 / (30f64.to_radians()).tan();
        Camera { width: 64, height: 64, fx: f, fy: f, cx: 32.0, cy: 32.0, distortion: None, world_from_camera: m }
    }

    fn sphere_grid(r: f32) -> SdfGrid {
        let f = |p: &[f32]| -> Result<Vec<f32>, BackendError> { Ok(p.chunks_exact(3).map(|q| (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - r).collect()) };
        SdfGrid::sample(&f, 1.0, 49).unwrap()
    }

    #[test]
    fn surface_points_lie_on_a_sphere_with_its_normals() {
        let pts = surface_points(&sphere_grid(0.5));
        assert!(pts.len() > 500, "{}", pts.len());
        for (p, n) in &pts {
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            assert!((r - 0.5).abs() < 0.01, "{r}");
            let cos = (p[0] * n[0] + p[1] * n[1] + p[2] * n[2]) / r;
            assert!(cos > 0.999, "{cos}");
        }
    }

    #[test]
    fn one_camera_sees_under_half_a_sphere_two_opposite_ones_twice_that_and_six_all_of_it() {
        let grid = sphere_grid(0.5);
        let front = camera(DVec3::new(0.0, 0.0, 3.0));
        let c = surface_coverage(&grid, &[&front]).unwrap();
        // A camera 3 away sees the cap within acos(r/d) of it, less what faces it at a grazing
        // angle: a bit under half.
        assert!(c.seen_by[1] > 0.35 && c.seen_by[1] < 0.5, "{c:?}");
        assert!((c.seen_by[0] + c.seen_by[1] - 1.0).abs() < 1e-9 && c.below_three() > 0.99);
        let back = camera(DVec3::new(0.0, 0.0, -3.0));
        let c2 = surface_coverage(&grid, &[&front, &back]).unwrap();
        // Opposite caps: each point seen by one of them at most, twice the one camera's share.
        assert!((c2.seen_by[1] - 2.0 * c.seen_by[1]).abs() < 0.02 && c2.seen_by[2] == 0.0, "{c2:?} vs {c:?}");
        // Six cameras on the axes: every point seen by about two or more.
        let six: Vec<Camera> = [DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y, DVec3::Z, -DVec3::Z].iter().map(|&d| camera(3.0 * d)).collect();
        let refs: Vec<&Camera> = six.iter().collect();
        let c6 = surface_coverage(&grid, &refs).unwrap();
        assert!(c6.seen_by[0] < 0.01 && c6.median_views >= 2.0, "{c6:?}");
    }

    #[test]
    fn a_point_behind_another_part_is_not_seen() {
        // Two spheres in a row along z: the camera on +z sees the near one, and of the far one
        // only the rim the near one does not hide.
        let f = |p: &[f32]| -> Result<Vec<f32>, BackendError> {
            Ok(p.chunks_exact(3)
                .map(|q| {
                    let a = (q[0] * q[0] + q[1] * q[1] + (q[2] - 0.45).powi(2)).sqrt() - 0.3;
                    let b = (q[0] * q[0] + q[1] * q[1] + (q[2] + 0.45).powi(2)).sqrt() - 0.3;
                    a.min(b)
                })
                .collect())
        };
        let grid = SdfGrid::sample(&f, 1.0, 65).unwrap();
        let cam = camera(DVec3::new(0.0, 0.0, 4.0));
        let pts = surface_points(&grid);
        let c = surface_coverage(&grid, &[&cam]).unwrap();
        // Without occlusion the two caps facing +z would both be seen (about 0.45 of each); the
        // far sphere's cap is hidden behind the near one.
        let facing_near = pts.iter().filter(|(p, n)| p[2] > 0.0 && n[2] > 0.1).count() as f64 / pts.len() as f64;
        assert!(c.seen_by[1] < facing_near + 0.05, "{c:?} vs {facing_near}");
        assert!(c.seen_by[1] > facing_near - 0.05, "{c:?} vs {facing_near}");
    }
}
