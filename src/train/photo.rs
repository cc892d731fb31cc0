//! Photo projection: the colour a surface point shows in the input photos.
//!
//! For a point on the surface of an SDF grid, every view that faces it (n·v above a threshold) and
//! sees it (a march toward the camera through the SDF meets no surface) contributes its pixel
//! colour, weighted by the squared cosine so frontal views dominate. `bake --preview` uses it as
//! the (lit, not de-lit) colour of the preview asset; training uses the same visibility test to
//! pick supervision rays.

use super::hull::Grid3;

/// What photo projection needs from a view.
pub trait PhotoView: Sync {
    /// Pixel coordinates of a normalised-space point (None if behind the camera).
    fn project(&self, p: [f32; 3]) -> Option<[f32; 2]>;
    /// Camera centre in normalised space.
    fn centre(&self) -> [f32; 3];
    /// Linear RGB at pixel coordinates (bilinear), None outside the image or off the mask.
    fn colour_at(&self, px: [f32; 2]) -> Option<[f32; 3]>;
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

/// Is the segment from surface point `p` (normal `n`) to `target` free of the SDF's surface?
/// Sphere-traces from just above the surface; a step that finds the SDF below −½ voxel is a hit.
pub fn visible(sdf: &Grid3, p: [f32; 3], n: [f32; 3], target: [f32; 3]) -> bool {
    let h = sdf.spacing();
    let start = [p[0] + n[0] * 1.5 * h, p[1] + n[1] * 1.5 * h, p[2] + n[2] * 1.5 * h];
    let to = sub(target, start);
    let len = dot(to, to).sqrt();
    let dir = normalize(to);
    let exit = (3.0f32).sqrt() * sdf.bound;
    let mut t = 0.0;
    for _ in 0..256 {
        let q = [start[0] + dir[0] * t, start[1] + dir[1] * t, start[2] + dir[2] * t];
        if t >= len || dot(q, q).sqrt() > exit {
            return true;
        }
        let d = sdf.sample(q);
        if d < -0.5 * h {
            return false;
        }
        t += d.abs().max(0.5 * h);
    }
    true
}

/// The cos²-weighted mean colour of point `p` (normal `n`) over the views that face and see it,
/// with the total weight; None if no view sees it.
pub fn project_colour(views: &[&dyn PhotoView], sdf: &Grid3, p: [f32; 3], n: [f32; 3], min_cos: f32) -> Option<([f32; 3], f32)> {
    let mut acc = [0.0f32; 3];
    let mut wsum = 0.0f32;
    for v in views {
        let c = v.centre();
        let dir = normalize(sub(c, p));
        let cos = dot(dir, n);
        if cos < min_cos {
            continue;
        }
        let Some(px) = v.project(p) else { continue };
        let Some(rgb) = v.colour_at(px) else { continue };
        if !visible(sdf, p, n, c) {
            continue;
        }
        let w = cos * cos;
        for a in 0..3 {
            acc[a] += w * rgb[a];
        }
        wsum += w;
    }
    (wsum > 0.0).then(|| ([acc[0] / wsum, acc[1] / wsum, acc[2] / wsum], wsum))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::hull::signed_distance;

    /// An orthographic camera looking along −axis_dir from far away, showing a colour that
    /// depends on the view so we can tell views apart.
    struct FlatView {
        dir: [f32; 3],
        colour: [f32; 3],
    }
    impl PhotoView for FlatView {
        fn project(&self, _p: [f32; 3]) -> Option<[f32; 2]> {
            Some([0.0, 0.0])
        }
        fn centre(&self) -> [f32; 3] {
            [self.dir[0] * 10.0, self.dir[1] * 10.0, self.dir[2] * 10.0]
        }
        fn colour_at(&self, _px: [f32; 2]) -> Option<[f32; 3]> {
            Some(self.colour)
        }
    }

    fn two_balls() -> Grid3 {
        // Ball A at x = -0.4 and ball B at x = +0.4, radius 0.25 each.
        let (res, bound) = (64, 1.0);
        let g = Grid3::new(res, bound, 0.0);
        let inside: Vec<bool> = (0..res * res * res)
            .map(|i| {
                let c = g.centre(i % res, (i / res) % res, i / (res * res));
                let da = ((c[0] + 0.4).powi(2) + c[1] * c[1] + c[2] * c[2]).sqrt();
                let db = ((c[0] - 0.4).powi(2) + c[1] * c[1] + c[2] * c[2]).sqrt();
                da < 0.25 || db < 0.25
            })
            .collect();
        signed_distance(&inside, res, bound)
    }

    #[test]
    fn occluded_views_do_not_contribute() {
        let sdf = two_balls();
        // Point on ball A's right side (facing ball B), normal +x.
        let p = [-0.15, 0.0, 0.0];
        let n = [1.0, 0.0, 0.0];
        assert!(!visible(&sdf, p, n, [10.0, 0.0, 0.0]), "ball B blocks the +x view");
        assert!(visible(&sdf, p, n, [10.0, 10.0, 0.0]), "the diagonal view is free");
        let right = FlatView { dir: [1.0, 0.0, 0.0], colour: [1.0, 0.0, 0.0] };
        let diag = FlatView { dir: normalize([1.0, 1.0, 0.0]), colour: [0.0, 1.0, 0.0] };
        let views: [&dyn PhotoView; 2] = [&right, &diag];
        let (rgb, w) = project_colour(&views, &sdf, p, n, 0.2).unwrap();
        assert_eq!(rgb, [0.0, 1.0, 0.0], "only the unoccluded view counts");
        assert!((w - 0.5).abs() < 0.02, "cos² weight of a 45° view: {w}");
        // Facing away: nothing.
        assert!(project_colour(&views, &sdf, [-0.65, 0.0, 0.0], [-1.0, 0.0, 0.0], 0.2).is_none());
    }
}
