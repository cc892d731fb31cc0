//! Stage 1's multi-view photo-consistency term: the photos compared with each other at the traced
//! surface, not only with the radiance net's colour.
//!
//! The colour loss compares each pixel with what the radiance net says the surface shows there;
//! a surface in the wrong place is then partly explained by the net (a view-dependent colour, a
//! texture painted onto a bump) and the geometry stops moving. Here the 3×3 patch a training ray
//! sees in its own photo is compared with the patches that the point it hit projects to in the
//! nearest other photos (the mean of the `best` closest matches, so views that are occluded there
//! or show a highlight do not count, as [`super::photo::carve_concavities`] scores them). The cost's
//! slope along the ray, by central differences, moves the surface point the way the colour
//! moves it (implicit differentiation, `dx/df = −v/(∇f·v)`). A textureless surface scores alike
//! at every depth and gets no push.

use glam::{DMat4, DVec3};

use super::stage1::TrainData;

/// How many of the nearest photos (by direction from the frame's centre) a reference photo is
/// compared with.
pub const NEIGHBOURS: usize = 8;

/// The term's settings ([`super::stage1::Stage1Config::photo_consistency`]).
#[derive(Clone, Copy, Debug)]
pub struct PhotoConsistency {
    pub weight: f32,
    /// The cost is the mean of this many best-matching neighbour patches.
    pub best: usize,
    /// Central-difference step along the ray (normalised units).
    pub depth_step: f32,
}

/// The training photos' cameras as the term projects into them.
#[derive(Debug)]
pub struct MultiView {
    camera_from_world: Vec<DMat4>,
    centres: Vec<[f32; 3]>,
    neighbours: Vec<Vec<usize>>,
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn normalize(a: [f32; 3]) -> [f32; 3] {
    let l = dot(a, a).sqrt().max(1e-20);
    [a[0] / l, a[1] / l, a[2] / l]
}

impl MultiView {
    pub fn new(data: &TrainData) -> Self {
        let centres: Vec<[f32; 3]> = data.views.iter().map(|v| v.camera.center().as_vec3().to_array()).collect();
        let neighbours = (0..centres.len())
            .map(|r| {
                let d = normalize(centres[r]);
                let mut o: Vec<usize> = (0..centres.len()).filter(|&v| v != r).collect();
                o.sort_by(|&a, &b| dot(normalize(centres[b]), d).total_cmp(&dot(normalize(centres[a]), d)));
                o.truncate(NEIGHBOURS);
                o
            })
            .collect();
        Self { camera_from_world: data.views.iter().map(|v| v.camera.world_from_camera.inverse()).collect(), centres, neighbours }
    }

    fn project(&self, data: &TrainData, v: usize, p: [f32; 3]) -> Option<[f32; 2]> {
        let q = data.views[v].camera.project_camera_point(self.camera_from_world[v].transform_point3(DVec3::from(p.map(f64::from))))?;
        Some([q.x as f32, q.y as f32])
    }

    /// The 3×3 patch around continuous pixel coordinates `px` (pixel centres at +0.5), bilinear,
    /// in the training photos' sRGB; None if any pixel is off the image or off the mask.
    fn patch(data: &TrainData, v: usize, px: [f32; 2]) -> Option<[[f32; 3]; 9]> {
        let view = &data.views[v];
        let (w, h) = (view.camera.width, view.camera.height);
        super::photo::patch_of(px, |q| {
            if !(q[0] >= 0.0 && q[1] >= 0.0 && (q[0] as usize) < w && (q[1] as usize) < h) {
                return None;
            }
            if view.mask[q[1] as usize * w + q[0] as usize] < 0.5 {
                return None;
            }
            let fx = (q[0] - 0.5).clamp(0.0, (w - 1) as f32);
            let fy = (q[1] - 0.5).clamp(0.0, (h - 1) as f32);
            let (x0, y0) = (fx as usize, fy as usize);
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (tx, ty) = (fx - x0 as f32, fy - y0 as f32);
            let at = |x: usize, y: usize, c: usize| view.rgb[3 * (y * w + x) + c];
            Some([0, 1, 2].map(|c| {
                (at(x0, y0, c) * (1.0 - tx) + at(x1, y0, c) * tx) * (1.0 - ty) + (at(x0, y1, c) * (1.0 - tx) + at(x1, y1, c) * tx) * ty
            }))
        })
    }

    /// The cost of point `p` against view `r`'s patch `reference`: the mean of the `best` lowest
    /// patch costs (mean |a − b| over the patch and channels) among `r`'s neighbours that lie on
    /// `r`'s side of the point and show it on their masks; None when fewer than `best` do.
    fn cost(&self, data: &TrainData, r: usize, reference: &[[f32; 3]; 9], p: [f32; 3], best: usize, costs: &mut Vec<f32>) -> Option<f32> {
        costs.clear();
        let to_ref = sub(self.centres[r], p);
        for &v in &self.neighbours[r] {
            if dot(sub(self.centres[v], p), to_ref) <= 0.0 {
                continue;
            }
            let Some(px) = self.project(data, v, p) else { continue };
            let Some(c) = Self::patch(data, v, px) else { continue };
            let mut e = 0.0;
            for (a, b) in c.iter().zip(reference) {
                for ch in 0..3 {
                    e += (a[ch] - b[ch]).abs();
                }
            }
            costs.push(e / 27.0);
        }
        if costs.len() < best || best == 0 {
            return None;
        }
        costs.sort_by(|a, b| a.total_cmp(b));
        Some(costs[..best].iter().sum::<f32>() / best as f32)
    }

    /// The term at the traced surface points: `points[k]`, hit by the ray of view `views[k]`
    /// through pixel `pixels[k]` along `dirs[k]`, with `gdotv[k] = ∇f·v`. Returns the loss (the
    /// weight times the mean cost over the points that have one) and its gradient with respect
    /// to `f(x0)` at each point (zero where the ray meets the surface at `−∇f·v ≤ grazing_cos`).
    #[allow(clippy::too_many_arguments)]
    pub fn term(&self, data: &TrainData, settings: &PhotoConsistency, views: &[u32], pixels: &[[f32; 2]], points: &[[f32; 3]], dirs: &[[f32; 3]], gdotv: &[f32], grazing_cos: f32) -> (f64, Vec<f32>) {
        use rayon::prelude::*;
        let eps = settings.depth_step;
        let per: Vec<Option<(f32, f32)>> = (0..points.len())
            .into_par_iter()
            .map_init(Vec::new, |costs, k| {
                let r = views[k] as usize;
                let reference = Self::patch(data, r, pixels[k])?;
                let at = |t: f32| [0, 1, 2].map(|a| points[k][a] + t * dirs[k][a]);
                let c0 = self.cost(data, r, &reference, points[k], settings.best, costs)?;
                let slope = match (self.cost(data, r, &reference, at(eps), settings.best, costs), self.cost(data, r, &reference, at(-eps), settings.best, costs)) {
                    (Some(a), Some(b)) => (a - b) / (2.0 * eps),
                    _ => 0.0,
                };
                Some((c0, slope))
            })
            .collect();
        let n = per.iter().flatten().count();
        let mut d = vec![0.0f32; points.len()];
        if n == 0 {
            return (0.0, d);
        }
        let w = settings.weight as f64 / n as f64;
        let mut loss = 0.0;
        for (k, c) in per.iter().enumerate() {
            let Some((c0, slope)) = c else { continue };
            loss += w * *c0 as f64;
            if gdotv[k] < -grazing_cos && slope.is_finite() {
                d[k] = (-(w as f32) * slope) / gdotv[k];
            }
        }
        (loss, d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image_io::ImageF32;
    use crate::scene::{Camera, Split, View};
    use glam::DVec4;

    /// A 48×48 pinhole camera at `eye` looking at the origin (OpenCV axes).
    fn camera(eye: DVec3) -> Camera {
        let f = (-eye).normalize();
        let r = f.cross(DVec3::Y).normalize();
        let d = f.cross(r);
        let m = DMat4::from_cols(r.extend(0.0), d.extend(0.0), f.extend(0.0), DVec4::new(eye.x, eye.y, eye.z, 1.0));
        Camera { width: 48, height: 48, fx: 60.0, fy: 60.0, cx: 24.0, cy: 24.0, distortion: None, world_from_camera: m }
    }

    /// Views of the plane z = 0 painted with `paint`, from above.
    fn plane_views(paint: impl Fn(f64, f64) -> [f32; 3]) -> Vec<View> {
        [DVec3::new(0.0, 0.0, 3.0), DVec3::new(0.7, 0.1, 2.9), DVec3::new(-0.6, 0.3, 2.9), DVec3::new(0.1, -0.7, 2.9), DVec3::new(0.4, 0.6, 2.9)]
            .iter()
            .enumerate()
            .map(|(i, &eye)| {
                let camera = camera(eye);
                let mut image = ImageF32::new(48, 48, 3);
                for y in 0..48 {
                    for x in 0..48 {
                        let (o, d) = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
                        let p = o + d * (-o.z / d.z);
                        image.data[3 * (y * 48 + x)..3 * (y * 48 + x) + 3].copy_from_slice(&paint(p.x, p.y));
                    }
                }
                View { name: format!("v{i}"), split: Split::Train, camera, image, mask: Some(vec![1.0; 48 * 48]), image_path: format!("v{i}.png").into() }
            })
            .collect()
    }

    #[test]
    fn the_cost_is_lowest_on_the_surface_and_its_slope_moves_the_point_onto_it() {
        let views = plane_views(|x, y| {
            [(0.5 + 0.4 * (9.0 * x).sin()) as f32, (0.5 + 0.4 * (11.0 * y).cos()) as f32, (0.5 + 0.3 * (7.0 * (x + y)).sin()) as f32]
        });
        let refs: Vec<&View> = views.iter().collect();
        let data = TrainData::new(&refs, 1.0).unwrap();
        let mv = MultiView::new(&data);
        let settings = PhotoConsistency { weight: 1.0, best: 2, depth_step: 0.01 };
        // The rays of view 0 through a few pixels near the centre; the plane's SDF is z, so
        // ∇f·v = v_z.
        for px in [[20.5f32, 22.5], [24.5, 24.5], [27.5, 21.5]] {
            let (o, d) = data.views[0].camera.ray(px[0] as f64, px[1] as f64);
            let t = -o.z / d.z;
            let at = |s: f64| (o + d * (t + s)).as_vec3().to_array();
            let dir = d.as_vec3().to_array();
            let run = |s: f64| mv.term(&data, &settings, &[0], &[px], &[at(s)], &[dir], &[dir[2]], 0.05);
            let (on, _) = run(0.0);
            let (beyond, d_beyond) = run(0.04);
            let (before, d_before) = run(-0.04);
            assert!(on < 0.5 * beyond.min(before), "cost on the surface {on} vs 0.04 beyond {beyond}, before {before}");
            // Beyond the surface the loss rises with depth: raising f there would take the point
            // deeper, so d/df > 0 (descent lowers f and lifts the surface toward the camera);
            // in front, the opposite.
            assert!(d_beyond[0] > 0.0 && d_before[0] < 0.0, "{} {}", d_beyond[0], d_before[0]);
            // A ray that meets the surface near grazing (−∇f·v = 0.1, below the threshold 0.2)
            // is not moved.
            let (_, d_grazing) = mv.term(&data, &settings, &[0], &[px], &[at(0.04)], &[dir], &[-0.1], 0.2);
            assert_eq!(d_grazing[0], 0.0);
        }
        // A textureless plane: every depth alike, no cost and no push.
        let flat = plane_views(|_, _| [0.4, 0.5, 0.6]);
        let refs: Vec<&View> = flat.iter().collect();
        let data = TrainData::new(&refs, 1.0).unwrap();
        let mv = MultiView::new(&data);
        let (o, d) = data.views[0].camera.ray(24.5, 24.5);
        let p = (o + d * (-o.z / d.z + 0.04)).as_vec3().to_array();
        let dir = d.as_vec3().to_array();
        let (l, g) = mv.term(&data, &settings, &[0], &[[24.5, 24.5]], &[p], &[dir], &[dir[2]], 0.05);
        assert!(l.abs() < 1e-6 && g[0].abs() < 1e-4, "{l} {}", g[0]);
    }
}
