//! Photo projection: the colour a surface point shows in the input photos.
//!
//! For a point on the surface of an SDF grid, every view that faces it (n·v above a threshold) and
//! sees it (a march toward the camera through the SDF meets no surface) contributes its pixel
//! colour, weighted by the squared cosine so frontal views dominate. `bake --preview` uses it as
//! the (lit, not de-lit) colour of the preview asset; training uses the same visibility test to
//! pick supervision rays.
//!
//! [`carve_concavities`] uses the photos the other way round: where the colours the views record
//! along a ray agree better deeper inside the visual hull than at its surface, the hull is too
//! full there (a concavity no silhouette shows) and is carved before stage 1 fits it.

use super::hull::Grid3;

/// What photo projection needs from a view.
pub trait PhotoView: Sync {
    /// Pixel coordinates of a normalised-space point (None if behind the camera).
    fn project(&self, p: [f32; 3]) -> Option<[f32; 2]>;
    /// Camera centre in normalised space.
    fn centre(&self) -> [f32; 3];
    /// Linear RGB at pixel coordinates (bilinear), None outside the image or off the mask.
    fn colour_at(&self, px: [f32; 2]) -> Option<[f32; 3]>;
    /// The 3×3 pixel patch around `px` (None if any pixel is off the image or the mask). A
    /// provided method, so its nine lookups are static calls into the implementation.
    fn patch(&self, px: [f32; 2]) -> Option<[[f32; 3]; 9]> {
        patch_of(px, |q| self.colour_at(q))
    }
}

/// The 3×3 patch around `px` from a pixel lookup, row by row (None if any lookup is): the one
/// definition of a patch's pixels, for [`PhotoView::patch`] and implementations that look pixels
/// up faster than through `colour_at`.
#[inline(always)]
pub(crate) fn patch_of(px: [f32; 2], lookup: impl Fn([f32; 2]) -> Option<[f32; 3]>) -> Option<[[f32; 3]; 9]> {
    let mut out = [[0.0; 3]; 9];
    for (k, o) in out.iter_mut().enumerate() {
        let (dx, dy) = ((k % 3) as f32 - 1.0, (k / 3) as f32 - 1.0);
        *o = lookup([px[0] + dx, px[1] + dy])?;
    }
    Some(out)
}

/// What a colour lookup reads of a view's pixels (photo consistency samples millions of 3×3
/// patches): the mask's size and values, and an interleaved image (`stride` values per pixel).
pub(crate) struct Pixels<'a> {
    width: usize,
    height: usize,
    mask: Option<&'a [f32]>,
    data: &'a [f32],
    image_width: usize,
    image_height: usize,
    stride: usize,
    /// The image channel of R, G and B (all 0 for a one-channel image).
    channels: [usize; 3],
    /// The mask as [`solid_bits`] (where colour lookups read it instead of `mask`).
    solid: Option<&'a [u64]>,
}

/// A mask as bits, row-major, set where a colour lookup keeps the pixel (the mask not below 0.5;
/// NaN kept, as [`Pixels::colour_at`] reads the mask): a bit a pixel where the mask has 32. Photo
/// consistency samples millions of patches at random places of every view, and its lookups
/// waited on the mask's cache misses.
pub(crate) fn solid_bits(mask: &[f32]) -> Vec<u64> {
    let mut bits = vec![0u64; mask.len().div_ceil(64)];
    for (i, &m) in mask.iter().enumerate() {
        if !(m < 0.5) {
            bits[i / 64] |= 1 << (i % 64);
        }
    }
    bits
}

impl<'a> Pixels<'a> {
    /// `width`×`height`: the view's (and its mask's) size; the image, `image_width`×
    /// `image_height` pixels of `stride` values.
    #[inline(always)]
    pub(crate) fn new(width: usize, height: usize, mask: Option<&'a [f32]>, data: &'a [f32], image_width: usize, image_height: usize, stride: usize) -> Self {
        Self { width, height, mask, data, image_width, image_height, stride, channels: [0, 1, 2].map(|k: usize| k.min(stride - 1)), solid: None }
    }

    /// Colour lookups read the mask from `bits`, its [`solid_bits`] (the same pixels kept).
    #[inline(always)]
    pub(crate) fn with_solid(self, bits: Option<&'a [u64]>) -> Self {
        Self { solid: bits, ..self }
    }

    /// The index of the pixel holding continuous pixel coordinates; None off the image.
    #[inline(always)]
    fn pixel(&self, px: [f32; 2]) -> Option<usize> {
        if !(px[0] >= 0.0 && px[1] >= 0.0 && (px[0] as usize) < self.width && (px[1] as usize) < self.height) {
            return None;
        }
        Some(px[1] as usize * self.width + px[0] as usize)
    }

    /// The mask at continuous pixel coordinates (1 without a mask, as `View::mask_at`); None off
    /// the image.
    #[inline(always)]
    pub(crate) fn mask_at(&self, px: [f32; 2]) -> Option<f32> {
        let i = self.pixel(px)?;
        Some(self.mask.map_or(1.0, |m| m[i]))
    }

    /// The image at continuous pixel coordinates (pixel centres at +0.5), bilinear; None off
    /// the image or where the mask is below 0.5.
    #[inline(always)]
    pub(crate) fn colour_at(&self, px: [f32; 2]) -> Option<[f32; 3]> {
        let kept = match (self.solid, self.mask) {
            (Some(bits), Some(_)) => {
                let i = self.pixel(px)?;
                bits[i / 64] >> (i % 64) & 1 == 1
            }
            _ => !(self.mask_at(px)? < 0.5),
        };
        if !kept {
            return None;
        }
        let (w, h, c, data) = (self.image_width, self.image_height, self.stride, self.data);
        let fx = (px[0] - 0.5).clamp(0.0, (w - 1) as f32);
        let fy = (px[1] - 0.5).clamp(0.0, (h - 1) as f32);
        // Truncation is the floor of these clamped (non-negative) values, without a libm call.
        let (x0, y0) = (fx as usize, fy as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (tx, ty) = (fx - x0 as f32, fy - y0 as f32);
        let (r0, r1) = (y0 * w, y1 * w);
        let mut out = [0.0; 3];
        for (o, &k) in out.iter_mut().zip(&self.channels) {
            let at = |row: usize, x: usize| data[(row + x) * c + k];
            let top = at(r0, x0) * (1.0 - tx) + at(r0, x1) * tx;
            let bottom = at(r1, x0) * (1.0 - tx) + at(r1, x1) * tx;
            *o = top * (1.0 - ty) + bottom * ty;
        }
        Some(out)
    }

    /// The 3×3 patch around `px` ([`patch_of`]) with the image, mask and sizes gathered once.
    #[inline(always)]
    pub(crate) fn patch(&self, px: [f32; 2]) -> Option<[[f32; 3]; 9]> {
        patch_of(px, |q| self.colour_at(q))
    }
}

pub(crate) fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub(crate) fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub(crate) fn normalize(a: [f32; 3]) -> [f32; 3] {
    let l = dot(a, a).sqrt().max(1e-20);
    [a[0] / l, a[1] / l, a[2] / l]
}

/// For each camera centre, the indices of the `k` others nearest to it by direction from the
/// frame's centre (the closest first).
pub(crate) fn nearest_by_direction(centres: &[[f32; 3]], k: usize) -> Vec<Vec<usize>> {
    (0..centres.len())
        .map(|r| {
            let d = normalize(centres[r]);
            let mut o: Vec<usize> = (0..centres.len()).filter(|&v| v != r).collect();
            o.sort_by(|&a, &b| dot(normalize(centres[b]), d).total_cmp(&dot(normalize(centres[a]), d)));
            o.truncate(k);
            o
        })
        .collect()
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

struct RayOutcome {
    view: usize,
    p: [f32; 3],
    dir: [f32; 3],
    c_surf: f32,
    c_deep: f32,
    t_deep: f32,
}

/// Views each reference view is matched against (the closest in direction).
const NEIGHBOURS: usize = 23;

/// Depth (voxels) behind a photo-consistent surface that its ray votes to keep.
const KEEP_DEPTH: f32 = 4.0;

/// Settings of [`carve_concavities`].
#[derive(Clone, Copy, Debug)]
pub struct ConcavityCarve {
    /// Rounds of carving (each re-derives the surface and its visibility from the last).
    pub rounds: usize,
    /// Views a candidate depth is scored in: the `best_views` lowest colour costs count.
    pub best_views: usize,
    /// A deeper candidate must have at most this fraction of the surface's colour cost.
    pub ratio: f32,
    /// Free-space votes (from distinct rays) a voxel needs to be carved.
    pub min_votes: u32,
    /// ... from at least this many distinct views (a coincidence in one photo opens nothing).
    pub min_views: u32,
    /// Voxels in front of a deeper consistent surface its ray leaves uncarved (the deeper
    /// depth is found to the nearest voxel); the deep scan starts one voxel beyond it.
    pub margin: f32,
}

impl Default for ConcavityCarve {
    fn default() -> Self {
        Self { rounds: 4, best_views: 3, ratio: 0.5, min_votes: 3, min_views: 2, margin: 1.0 }
    }
}

/// What [`carve_concavities`] did.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct ConcavityReport {
    pub rounds: usize,
    /// (surface voxel, view) rays scored.
    pub rays: usize,
    /// Rays that found a deeper, more photo-consistent surface.
    pub deeper_rays: usize,
    /// Voxels carved (of the grid the caller passed; `train::cli::hull_init_grid` reports those
    /// of its finer hull when it carved a coarser one).
    pub carved_voxels: usize,
    /// Carved voxels the final majority filter put back.
    pub restored_voxels: usize,
    /// Kept voxels dropped as floaters cut off from the hull.
    pub dropped_fragments: usize,
}

/// Photo-consistency cost of `p` against the reference colour patch, given as its square roots
/// (`ref_sqrt`, see [`sqrt_patch`]): the mean of the `best` lowest per-view patch costs (|√a − √b|,
/// mean over a 3×3 pixel patch and channels), skipping `reference` and views that do not show `p`
/// on their mask. None when fewer than `best` views show it.
fn consistency(views: &[&dyn PhotoView], reference: usize, others: &[usize], ref_sqrt: &[[f32; 3]; 9], p: [f32; 3], best: usize, costs: &mut Vec<f32>) -> Option<f32> {
    costs.clear();
    let to_ref = sub(views[reference].centre(), p);
    for &vi in others {
        let v = views[vi];
        // Only views on the reference camera's side of the point can see the same surface.
        if dot(sub(v.centre(), p), to_ref) <= 0.0 {
            continue;
        }
        let Some(px) = v.project(p) else { continue };
        let Some(c) = v.patch(px) else { continue };
        let mut e = 0.0;
        for (a, b) in c.iter().zip(ref_sqrt) {
            for ch in 0..3 {
                e += (a[ch].max(0.0).sqrt() - b[ch]).abs();
            }
        }
        costs.push(e / 27.0);
    }
    if costs.len() < best {
        return None;
    }
    costs.sort_by(|a, b| a.total_cmp(b));
    Some(costs[..best].iter().sum::<f32>() / best as f32)
}

/// `√max(c, 0)` of every channel of a patch (the colour space [`consistency`] compares in).
fn sqrt_patch(patch: &[[f32; 3]; 9]) -> [[f32; 3]; 9] {
    patch.map(|c| c.map(|v| v.max(0.0).sqrt()))
}

/// Carve the concavities a visual hull cannot see (the inside of a bowl, a cup, the gap under an
/// arm): multi-view photo-consistency along the rays that see the hull's surface.
///
/// For every surface voxel of `inside` and every view that faces and sees it, the ray from that
/// camera through the voxel is scored at depths around the surface and deeper inside the hull:
/// each depth's cost is how well the other views' 3×3 patches there match the reference patch
/// (the mean of the `best_views` best matches, so views occluded at that point do not count).
/// Where a deeper depth is clearly more consistent than the surface (cost below `ratio` × the
/// surface's), the voxels in front of it (less `margin` voxels) get a free-space vote. A voxel
/// is carved when at least `min_votes` rays voted it free and more rays voted it free than found
/// it a consistent surface. Textureless surfaces score alike at every depth and are kept: the
/// rule only removes what the photos contradict. Each round re-derives the surface, so a
/// concavity is opened layer by layer.
pub fn carve_concavities(views: &[&dyn PhotoView], inside: &mut [bool], res: usize, bound: f32, cfg: &ConcavityCarve) -> ConcavityReport {
    use rayon::prelude::*;
    let mut report = ConcavityReport::default();
    let idx = |i: usize, j: usize, k: usize| (k * res + j) * res + i;
    let hull: Vec<bool> = inside.to_vec();
    // After the first round only the surface near what was carved can see anything new.
    let mut near_change: Option<Vec<bool>> = None;
    let mut typical: Option<f32> = None;
    // Each reference view is matched against its NEIGHBOURS closest views (by direction from the
    // centre of the frame), which bounds the cost on captures with many views.
    let neighbours = nearest_by_direction(&views.iter().map(|v| v.centre()).collect::<Vec<_>>(), NEIGHBOURS);
    for _ in 0..cfg.rounds {
        report.rounds += 1;
        let sdf = super::hull::signed_distance(inside, res, bound);
        let h = sdf.spacing();
        let occupied = |p: [f32; 3]| -> Option<usize> {
            let g = |a: f32| ((a + bound) / h).floor();
            let (i, j, k) = (g(p[0]), g(p[1]), g(p[2]));
            let r = res as f32;
            if i < 0.0 || j < 0.0 || k < 0.0 || i >= r || j >= r || k >= r {
                return None;
            }
            let id = idx(i as usize, j as usize, k as usize);
            inside[id].then_some(id)
        };
        let surface: Vec<usize> = (0..inside.len())
            .filter(|&id| {
                // Inside, with a face on the outside or on the grid's border.
                inside[id] && near_change.as_ref().map_or(true, |n| n[id]) && (on_border(id, res) || neighbours6(id, res).any(|n| !inside[n]))
            })
            .collect();
        // Every (surface voxel, view) ray: its start, direction and costs.
        let outcomes: Vec<RayOutcome> = surface
            .par_iter()
            .flat_map_iter(|&id| {
                let (i, j, k) = (id % res, (id / res) % res, id / (res * res));
                let p = sdf.centre(i, j, k);
                let n = normalize(sdf.gradient(p));
                let mut costs = Vec::with_capacity(views.len());
                let mut out = Vec::new();
                for (r, v) in views.iter().enumerate() {
                    let c = v.centre();
                    let to_cam = normalize(sub(c, p));
                    if dot(to_cam, n) < 0.1 || !visible(&sdf, p, n, c) {
                        continue;
                    }
                    let Some(px) = v.project(p) else { continue };
                    let Some(patch) = v.patch(px) else { continue };
                    let patch = sqrt_patch(&patch);
                    let dir = [-to_cam[0], -to_cam[1], -to_cam[2]];
                    let at = |t: f32| [p[0] + dir[0] * t * h, p[1] + dir[1] * t * h, p[2] + dir[2] * t * h];
                    // Around the surface: −1 … +1 voxels.
                    let mut c_surf = f32::INFINITY;
                    for t in [-1.0f32, -0.5, 0.0, 0.5, 1.0] {
                        if let Some(e) = consistency(views, r, &neighbours[r], &patch, at(t), cfg.best_views, &mut costs) {
                            c_surf = c_surf.min(e);
                        }
                    }
                    if !c_surf.is_finite() {
                        continue;
                    }
                    // Deeper, while inside the hull.
                    let (mut c_deep, mut t_deep) = (f32::INFINITY, 0.0f32);
                    let mut t = cfg.margin + 1.0;
                    while occupied(at(t)).is_some() {
                        if let Some(e) = consistency(views, r, &neighbours[r], &patch, at(t), cfg.best_views, &mut costs) {
                            if e < c_deep {
                                c_deep = e;
                                t_deep = t;
                            }
                        }
                        t += 1.0;
                    }
                    out.push(RayOutcome { view: r, p, dir, c_surf, c_deep, t_deep });
                }
                out
            })
            .collect();
        // The scene's typical cost of a surface where it is: the median over the first round's
        // rays (most of a hull's surface is the object's). Only a surface at least that
        // consistent votes to be kept; a worse one that nothing deeper explains votes for nothing.
        if typical.is_none() {
            let mut c: Vec<f32> = outcomes.iter().map(|o| o.c_surf).collect();
            c.sort_by(|a, b| a.total_cmp(b));
            typical = c.get(c.len() / 2).copied();
        }
        let tau = typical.unwrap_or(0.0);
        let mut free_votes = vec![0u32; inside.len()];
        let mut keep_votes = vec![0u32; inside.len()];
        // The views (bit view mod 64) whose rays voted a voxel free.
        let mut free_views = vec![0u64; inside.len()];
        report.rays += outcomes.len();
        for o in &outcomes {
            let at = |t: f32| [o.p[0] + o.dir[0] * t * h, o.p[1] + o.dir[1] * t * h, o.p[2] + o.dir[2] * t * h];
            let free = o.c_deep < cfg.ratio * o.c_surf;
            let (votes, t0, t1) = if free {
                report.deeper_rays += 1;
                // Free space in front of the deeper surface, less the margin.
                (&mut free_votes, -0.5f32, o.t_deep - cfg.margin)
            } else if o.c_surf <= tau {
                // A consistent surface: it and the solid just behind it stay.
                (&mut keep_votes, -0.5f32, KEEP_DEPTH)
            } else {
                continue;
            };
            let (mut t, mut last) = (t0, usize::MAX);
            while t <= t1 {
                if let Some(v) = occupied(at(t)) {
                    if v != last {
                        votes[v] += 1;
                        if free {
                            free_views[v] |= 1 << (o.view % 64);
                        }
                        last = v;
                    }
                }
                t += 0.25;
            }
        }
        let voted: Vec<bool> = (0..inside.len())
            .map(|id| inside[id] && free_votes[id] >= cfg.min_votes && free_views[id].count_ones() >= cfg.min_views && free_votes[id] > keep_votes[id])
            .collect();
        // Free space is reached from outside: only voted voxels connected to the outside through
        // voted voxels are carved (no bubbles inside the solid).
        let changed = reachable_from_outside(inside, &voted, res);
        let mut carved = 0;
        for (b, &c) in inside.iter_mut().zip(&changed) {
            if c {
                *b = false;
                carved += 1;
            }
        }
        report.carved_voxels += carved;
        if carved == 0 {
            break;
        }
        near_change = Some(dilate(&changed, res, 3));
    }
    if report.carved_voxels > 0 {
        report.restored_voxels = majority_filter(inside, &hull, res);
        report.dropped_fragments = drop_fragments(inside, &hull, res, 0.01);
    }
    report
}

/// The `voted` voxels that a 6-connected path through voted or outside voxels joins to the
/// outside of `inside` (the grid's border counts as outside).
fn reachable_from_outside(inside: &[bool], voted: &[bool], res: usize) -> Vec<bool> {
    let mut seen = vec![false; inside.len()];
    let mut stack: Vec<usize> = Vec::new();
    for id in 0..inside.len() {
        if !inside[id] || (voted[id] && on_border(id, res)) {
            seen[id] = true;
            stack.push(id);
        }
    }
    while let Some(id) = stack.pop() {
        for n in neighbours6(id, res) {
            if !seen[n] && voted[n] {
                seen[n] = true;
                stack.push(n);
            }
        }
    }
    (0..inside.len()).map(|id| inside[id] && voted[id] && seen[id]).collect()
}

/// Voxels within `r` steps (26-neighbourhood) of a marked one.
fn dilate(mark: &[bool], res: usize, r: usize) -> Vec<bool> {
    let mut cur = mark.to_vec();
    for _ in 0..r {
        let prev = cur.clone();
        for (id, c) in cur.iter_mut().enumerate() {
            if *c {
                continue;
            }
            *c = neighbours26(id, res).any(|n| prev[n]);
        }
    }
    cur
}

/// Is voxel `id` on a face of the grid?
fn on_border(id: usize, res: usize) -> bool {
    [id % res, (id / res) % res, id / (res * res)].iter().any(|&a| a == 0 || a + 1 == res)
}

/// The face neighbours of voxel `id` inside the grid.
fn neighbours6(id: usize, res: usize) -> impl Iterator<Item = usize> {
    offset_neighbours(id, res, [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)].into_iter())
}

/// The face, edge and corner neighbours of voxel `id` inside the grid.
fn neighbours26(id: usize, res: usize) -> impl Iterator<Item = usize> {
    offset_neighbours(id, res, (0..27i64).filter(|&d| d != 13).map(|d| (d % 3 - 1, (d / 3) % 3 - 1, d / 9 - 1)))
}

/// The voxels at `offsets` from voxel `id` that lie inside the grid.
fn offset_neighbours(id: usize, res: usize, offsets: impl Iterator<Item = (i64, i64, i64)>) -> impl Iterator<Item = usize> {
    let (i, j, k) = ((id % res) as i64, ((id / res) % res) as i64, (id / (res * res)) as i64);
    let r = res as i64;
    offsets.filter_map(move |(a, b, c)| {
        let (x, y, z) = (i + a, j + b, k + c);
        (x >= 0 && y >= 0 && z >= 0 && x < r && y < r && z < r).then(|| ((z * r + y) * r + x) as usize)
    })
}

/// One majority pass over the hull's voxels: a voxel takes the state of at least 20 of its 26
/// neighbours (carved speckles on a kept surface come back, kept speckles in carved space go).
/// Returns how many voxels came back.
fn majority_filter(inside: &mut [bool], hull: &[bool], res: usize) -> usize {
    let prev = inside.to_vec();
    let mut restored = 0;
    for id in 0..inside.len() {
        // Only where carving happened (voxels of the hull within one step of a carved one).
        if !hull[id] || (prev[id] && !neighbours26(id, res).any(|n| hull[n] && !prev[n])) {
            continue;
        }
        let occ = neighbours26(id, res).filter(|&n| prev[n]).count();
        if !prev[id] && occ >= 20 {
            inside[id] = true;
            restored += 1;
        } else if prev[id] && occ <= 6 {
            inside[id] = false;
        }
    }
    restored
}

/// Drop the connected pieces (26-connected) that carving cut off a hull component and that hold
/// less than `fraction` of it: floaters left in carved space. Returns the voxels dropped.
fn drop_fragments(inside: &mut [bool], hull: &[bool], res: usize, fraction: f64) -> usize {
    let label = |occ: &[bool]| -> (Vec<u32>, Vec<usize>) {
        let mut lab = vec![u32::MAX; occ.len()];
        let mut sizes = Vec::new();
        let mut stack = Vec::new();
        for s in 0..occ.len() {
            if !occ[s] || lab[s] != u32::MAX {
                continue;
            }
            let l = sizes.len() as u32;
            lab[s] = l;
            stack.push(s);
            let mut n = 0;
            while let Some(v) = stack.pop() {
                n += 1;
                for w in neighbours26(v, res) {
                    if occ[w] && lab[w] == u32::MAX {
                        lab[w] = l;
                        stack.push(w);
                    }
                }
            }
            sizes.push(n);
        }
        (lab, sizes)
    };
    let (hl, hs) = label(hull);
    let (cl, cs) = label(inside);
    let mut dropped = 0;
    for id in 0..inside.len() {
        if inside[id] {
            let (c, h) = (cs[cl[id] as usize], hs[hl[id] as usize]);
            if c < h && (c as f64) < fraction * h as f64 {
                inside[id] = false;
                dropped += 1;
            }
        }
    }
    dropped
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
                let c = g.centre_of(i);
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

    /// A textured solid box with a square pit in its top face (a concavity no silhouette shows),
    /// photographed by pinhole cameras on rings around it; images are rendered once by sphere
    /// tracing its exact SDF.
    struct PitScene;
    impl PitScene {
        fn sdf(p: [f32; 3]) -> f32 {
            let bx = |p: [f32; 3], h: [f32; 3]| {
                let q = [p[0].abs() - h[0], p[1].abs() - h[1], p[2].abs() - h[2]];
                let out = (q[0].max(0.0).powi(2) + q[1].max(0.0).powi(2) + q[2].max(0.0).powi(2)).sqrt();
                out + q[0].max(q[1]).max(q[2]).min(0.0)
            };
            let pit = bx([p[0], p[1], p[2] - 0.5], [0.32, 0.32, 0.35]);
            bx(p, [0.5, 0.5, 0.5]).max(-pit)
        }
        fn colour(p: [f32; 3]) -> [f32; 3] {
            [
                0.5 + 0.4 * (37.0 * p[0] + 11.0 * p[1]).sin(),
                0.5 + 0.4 * (29.0 * p[1] + 17.0 * p[2]).sin(),
                0.5 + 0.4 * (23.0 * p[2] + 31.0 * p[0]).sin(),
            ]
        }
        fn hit(o: [f32; 3], d: [f32; 3]) -> Option<[f32; 3]> {
            let mut t = 0.0;
            for _ in 0..200 {
                let p = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
                let f = Self::sdf(p);
                if f < 1e-4 {
                    return Some(p);
                }
                t += f;
                if t > 10.0 {
                    break;
                }
            }
            None
        }
    }

    struct Pinhole {
        c: [f32; 3],
        f: [f32; 3],
        r: [f32; 3],
        u: [f32; 3],
        focal: f32,
        size: usize,
        /// Rendered colour per pixel, None off the object.
        img: Vec<Option<[f32; 3]>>,
    }
    impl Pinhole {
        fn new(elev: f32, azim: f32) -> Self {
            let (ce, se, ca, sa) = (elev.cos(), elev.sin(), azim.cos(), azim.sin());
            let c = [3.0 * ce * ca, 3.0 * ce * sa, 3.0 * se];
            let f = normalize([-c[0], -c[1], -c[2]]);
            let r = normalize([f[1], -f[0], 0.0]); // f × z
            let u = [r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]];
            let size = 112;
            let mut cam = Self { c, f, r, u, focal: 150.0, size, img: Vec::new() };
            cam.img = (0..size * size)
                .map(|i| {
                    let (x, y) = ((i % size) as f32 + 0.5, (i / size) as f32 + 0.5);
                    let h = 0.5 * size as f32;
                    let d = normalize([0, 1, 2].map(|a| cam.f[a] + (x - h) / cam.focal * cam.r[a] - (y - h) / cam.focal * cam.u[a]));
                    PitScene::hit(cam.c, d).map(PitScene::colour)
                })
                .collect();
            cam
        }
    }
    impl PhotoView for Pinhole {
        fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
            let d = sub(p, self.c);
            let z = dot(d, self.f);
            let h = 0.5 * self.size as f32;
            (z > 0.0).then(|| [h + self.focal * dot(d, self.r) / z, h - self.focal * dot(d, self.u) / z])
        }
        fn centre(&self) -> [f32; 3] {
            self.c
        }
        fn colour_at(&self, px: [f32; 2]) -> Option<[f32; 3]> {
            // Nearest pixel is enough for a smooth texture.
            let (x, y) = (px[0].floor(), px[1].floor());
            if x < 0.0 || y < 0.0 || x >= self.size as f32 || y >= self.size as f32 {
                return None;
            }
            self.img[y as usize * self.size + x as usize]
        }
    }

    #[test]
    fn photo_consistency_opens_a_pit_the_silhouettes_cannot_see_and_keeps_the_solid() {
        let views: Vec<Pinhole> = [1.1f32, 0.8, 0.45, 0.1, -0.3]
            .iter()
            .flat_map(|&e| (0..8).map(move |k| Pinhole::new(e, k as f32 * std::f32::consts::TAU / 8.0 + 0.3 * e)))
            .collect();
        let refs: Vec<&dyn PhotoView> = views.iter().map(|v| v as &dyn PhotoView).collect();
        let (res, bound) = (36, 1.0);
        let g = Grid3::new(res, bound, 0.0);
        // The hull the masks give: the whole box (the pit does not show in any silhouette).
        let centres: Vec<[f32; 3]> = (0..res * res * res).map(|i| g.centre_of(i)).collect();
        let box_only = |p: &[f32; 3]| p[0].abs() < 0.5 && p[1].abs() < 0.5 && p[2].abs() < 0.5;
        let mut inside: Vec<bool> = centres.iter().map(box_only).collect();
        let pit: Vec<usize> = (0..inside.len()).filter(|&i| inside[i] && PitScene::sdf(centres[i]) > 0.0).collect();
        let solid: Vec<usize> = (0..inside.len()).filter(|&i| inside[i] && PitScene::sdf(centres[i]) < 0.0).collect();
        assert!(pit.len() > 600, "the pit is {} voxels", pit.len());
        let report = carve_concavities(&refs, &mut inside, res, bound, &ConcavityCarve::default());
        // Carving stops a voxel short of the surface it finds (the trained SDF takes it from
        // there): count the pit more than a voxel from the solid.
        let h = g.spacing();
        let open_space: Vec<usize> = pit.iter().copied().filter(|&i| PitScene::sdf(centres[i]) > h).collect();
        let opened = open_space.iter().filter(|&&i| !inside[i]).count() as f64 / open_space.len() as f64;
        let lost = solid.iter().filter(|&&i| !inside[i]).count() as f64 / solid.len() as f64;
        assert!(opened > 0.87, "opened {:.1}% of the pit's open space ({report:?})", 100.0 * opened);
        assert!(lost < 0.01, "carved {:.2}% of the true solid ({report:?})", 100.0 * lost);
        assert!(report.deeper_rays > 0 && report.carved_voxels > 0);
    }

    #[test]
    fn a_convex_textured_box_loses_nothing() {
        // The same textured box without its pit: every surface is photo-consistent where it is.
        struct Solid(Pinhole);
        impl PhotoView for Solid {
            fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
                self.0.project(p)
            }
            fn centre(&self) -> [f32; 3] {
                self.0.c
            }
            fn colour_at(&self, px: [f32; 2]) -> Option<[f32; 3]> {
                self.0.colour_at(px)
            }
        }
        let views: Vec<Solid> = [0.9f32, 0.3, -0.3]
            .iter()
            .flat_map(|&e| (0..6).map(move |k| k as f32 * std::f32::consts::TAU / 6.0 + 0.2 * e).map(move |a| (e, a)))
            .map(|(e, a)| {
                let mut v = Pinhole::new(e, a);
                // Re-render the box without its pit.
                let h = 0.5 * v.size as f32;
                v.img = (0..v.size * v.size)
                    .map(|i| {
                        let (x, y) = ((i % v.size) as f32 + 0.5, (i / v.size) as f32 + 0.5);
                        let d = normalize([0, 1, 2].map(|k| v.f[k] + (x - h) / v.focal * v.r[k] - (y - h) / v.focal * v.u[k]));
                        let tb = |o: f32, d: f32| if d.abs() < 1e-9 { (f32::NEG_INFINITY, f32::INFINITY) } else { let (a, b) = ((-0.5 - o) / d, (0.5 - o) / d); (a.min(b), a.max(b)) };
                        let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
                        for k in 0..3 {
                            let (a, b) = tb(v.c[k], d[k]);
                            t0 = t0.max(a);
                            t1 = t1.min(b);
                        }
                        (t0 <= t1 && t0 > 0.0).then(|| PitScene::colour([0, 1, 2].map(|k| v.c[k] + d[k] * t0)))
                    })
                    .collect();
                Solid(v)
            })
            .collect();
        let refs: Vec<&dyn PhotoView> = views.iter().map(|v| v as &dyn PhotoView).collect();
        let (res, bound) = (32, 1.0);
        let g = Grid3::new(res, bound, 0.0);
        let mut inside: Vec<bool> = (0..res * res * res)
            .map(|i| {
                let p = g.centre_of(i);
                p[0].abs() < 0.5 && p[1].abs() < 0.5 && p[2].abs() < 0.5
            })
            .collect();
        let before = inside.iter().filter(|b| **b).count();
        let report = carve_concavities(&refs, &mut inside, res, bound, &ConcavityCarve::default());
        let after = inside.iter().filter(|b| **b).count();
        assert!(report.rays > 1000, "{report:?}");
        assert!(after as f64 >= 0.995 * before as f64, "{before} -> {after} voxels ({report:?})");
    }
}
