//! Meshes for evaluation: OBJ and PLY (ascii, binary little/big endian) reading, area-uniform surface
//! sampling, a triangle BVH for exact closest-point queries, Chamfer distance and normal consistency.
//!
//! Definitions (on `n` area-uniform samples per mesh, seeded; distances to the other *surface*, so
//! the figure has no sampling floor, see [`TriBvh`]):
//! - accuracy = mean over prediction samples of the distance to the ground-truth surface;
//! - completeness = the same from ground-truth samples to the predicted surface;
//! - chamfer = (accuracy + completeness) / 2 (units of the meshes' frame);
//! - normal consistency = mean of |n_a · n_b| between each sample's normal and the nearest
//!   triangle's, both directions averaged (1 = perfect);
//! - shading normal consistency = the same with a mesh's vertex normals interpolated across its
//!   triangles wherever it has them (what a renderer shades a .glb with), face normals elsewhere;
//!   reported only when one of the two meshes has vertex normals.

use std::path::Path;

use glam::DVec3;
use rand::Rng;

use crate::util::DataError;

#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub positions: Vec<DVec3>,
    pub triangles: Vec<[u32; 3]>,
    /// Unit vertex normals for shading (one per position), or empty: face normals only.
    pub normals: Vec<DVec3>,
}

fn bad(path: &Path, what: impl Into<String>) -> DataError {
    DataError::new(path, what.into())
}

impl Mesh {
    /// Read an .obj or .ply file (polygons are fan-triangulated).
    pub fn read(path: &Path) -> Result<Mesh, DataError> {
        let ext = path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default();
        let m = match ext.as_str() {
            "obj" => read_obj(path)?,
            "ply" => read_ply(path)?,
            _ => return Err(bad(path, "unsupported mesh format (expected .obj or .ply)")),
        };
        if m.triangles.is_empty() {
            return Err(bad(path, "mesh has no faces"));
        }
        let n = m.positions.len() as u32;
        if let Some(t) = m.triangles.iter().find(|t| t.iter().any(|&i| i >= n)) {
            return Err(bad(path, format!("face {t:?} refers to a vertex past the {n} vertices")));
        }
        if m.positions.iter().any(|p| !p.is_finite()) {
            return Err(bad(path, "mesh has non-finite vertex positions"));
        }
        let area = m.area();
        if !(area.is_finite() && area > 0.0) {
            return Err(bad(path, format!("mesh surface area is {area}: no triangle with a finite, non-zero area")));
        }
        Ok(m)
    }

    /// From an indexed f32 triangle list (the mesh and asset back end's layout).
    pub fn from_indexed(positions: &[[f32; 3]], indices: &[u32]) -> Mesh {
        Mesh {
            positions: positions.iter().map(|p| DVec3::from(p.map(f64::from))).collect(),
            triangles: indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect(),
            normals: Vec::new(),
        }
    }

    /// The same mesh with shading normals (one per vertex, as the asset's NORMAL attribute);
    /// a count that does not match the vertices leaves it without.
    pub fn with_normals(mut self, normals: &[[f32; 3]]) -> Mesh {
        self.normals = if normals.len() == self.positions.len() { normals.iter().map(|n| DVec3::from(n.map(f64::from)).normalize_or_zero()).collect() } else { Vec::new() };
        self
    }

    /// The normal a renderer shades triangle `t` with at barycentric (u, v) (weights of its second
    /// and third corner): the interpolated vertex normals, or the face normal without them.
    fn shading_normal(&self, t: usize, u: f64, v: f64) -> DVec3 {
        let tri = &self.triangles[t];
        if self.normals.is_empty() {
            return self.tri_cross(tri).normalize_or_zero();
        }
        let n = |k: usize| self.normals[tri[k] as usize];
        (n(0) * (1.0 - u - v) + n(1) * u + n(2) * v).normalize_or_zero()
    }

    /// Barycentric (u, v) of the point `p` (on triangle `t`) for its second and third corners.
    fn barycentric(&self, t: usize, p: DVec3) -> (f64, f64) {
        let tri = &self.triangles[t];
        let (a, b, c) = (self.positions[tri[0] as usize], self.positions[tri[1] as usize], self.positions[tri[2] as usize]);
        let (e0, e1, e2) = (b - a, c - a, p - a);
        let (d00, d01, d11, d20, d21) = (e0.dot(e0), e0.dot(e1), e1.dot(e1), e2.dot(e0), e2.dot(e1));
        let den = d00 * d11 - d01 * d01;
        if den.abs() <= 1e-300 {
            return (0.0, 0.0);
        }
        ((d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den)
    }

    pub fn area(&self) -> f64 {
        self.triangles.iter().map(|t| self.tri_cross(t).length() * 0.5).sum()
    }

    fn tri_cross(&self, t: &[u32; 3]) -> DVec3 {
        let (a, b, c) = (self.positions[t[0] as usize], self.positions[t[1] as usize], self.positions[t[2] as usize]);
        (b - a).cross(c - a)
    }

    /// The point at barycentric (u, v) (weights of the second and third corner) of triangle `k`.
    fn point_at(&self, k: usize, u: f64, v: f64) -> DVec3 {
        let t = &self.triangles[k];
        let (a, b, c) = (self.positions[t[0] as usize], self.positions[t[1] as usize], self.positions[t[2] as usize]);
        a + (b - a) * u + (c - a) * v
    }

    /// `n` points uniformly distributed over the surface area, as (triangle, u, v) with
    /// [`Mesh::point_at`]'s barycentrics.
    fn sample_barycentric(&self, n: usize, seed: u64) -> Vec<(usize, f64, f64)> {
        let mut cdf = Vec::with_capacity(self.triangles.len());
        let mut acc = 0.0;
        for t in &self.triangles {
            acc += self.tri_cross(t).length();
            cdf.push(acc);
        }
        let mut rng = crate::util::rng(seed);
        let mut out = Vec::with_capacity(n);
        if acc <= 0.0 {
            return out;
        }
        for _ in 0..n {
            let r = rng.random::<f64>() * acc;
            let k = cdf.partition_point(|c| *c < r).min(self.triangles.len() - 1);
            let (mut u, mut v) = (rng.random::<f64>(), rng.random::<f64>());
            if u + v > 1.0 {
                u = 1.0 - u;
                v = 1.0 - v;
            }
            out.push((k, u, v));
        }
        out
    }
}

fn parse_index(path: &Path, line: usize, tok: &str, nverts: usize) -> Result<u32, DataError> {
    let s = tok.split('/').next().unwrap_or("");
    let i: i64 = s.parse().map_err(|_| bad(path, format!("line {line}: bad face index {tok:?}")))?;
    let idx = if i > 0 { i - 1 } else { nverts as i64 + i };
    if idx < 0 || idx >= nverts as i64 {
        return Err(bad(path, format!("line {line}: face index {i} out of range (1..={nverts})")));
    }
    Ok(idx as u32)
}

/// Largest mesh file the readers accept, in bytes.
pub const MAX_MESH_BYTES: u64 = 4 << 30;

pub fn read_obj(path: &Path) -> Result<Mesh, DataError> {
    let text = crate::util::read_text_bounded(path, MAX_MESH_BYTES)?;
    let mut m = Mesh::default();
    for (no, line) in text.lines().enumerate() {
        let mut toks = line.split_whitespace();
        match toks.next() {
            Some("v") => {
                let v: Vec<f64> = toks.take(3).map(|t| t.parse::<f64>()).collect::<Result<_, _>>().map_err(|_| bad(path, format!("line {}: bad vertex", no + 1)))?;
                if v.len() != 3 {
                    return Err(bad(path, format!("line {}: vertex needs 3 coordinates", no + 1)));
                }
                m.positions.push(DVec3::new(v[0], v[1], v[2]));
            }
            Some("f") => {
                let idx: Vec<u32> = toks.map(|t| parse_index(path, no + 1, t, m.positions.len())).collect::<Result<_, _>>()?;
                if idx.len() < 3 {
                    return Err(bad(path, format!("line {}: face with fewer than 3 vertices", no + 1)));
                }
                for k in 1..idx.len() - 1 {
                    m.triangles.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Ok(m)
}

#[derive(Clone, Copy, PartialEq)]
enum PlyFormat {
    Ascii,
    Le,
    Be,
}

fn ply_size(ty: &str) -> Option<usize> {
    Some(match ty {
        "char" | "uchar" | "int8" | "uint8" => 1,
        "short" | "ushort" | "int16" | "uint16" => 2,
        "int" | "uint" | "int32" | "uint32" | "float" | "float32" => 4,
        "double" | "float64" => 8,
        _ => return None,
    })
}

fn ply_read(ty: &str, b: &[u8], fmt: PlyFormat) -> f64 {
    macro_rules! rd {
        ($t:ty) => {{
            let a = b.try_into().expect("size checked");
            (if fmt == PlyFormat::Le { <$t>::from_le_bytes(a) } else { <$t>::from_be_bytes(a) }) as f64
        }};
    }
    match ty {
        "char" | "int8" => b[0] as i8 as f64,
        "uchar" | "uint8" => b[0] as f64,
        "short" | "int16" => rd!(i16),
        "ushort" | "uint16" => rd!(u16),
        "int" | "int32" => rd!(i32),
        "uint" | "uint32" => rd!(u32),
        "float" | "float32" => rd!(f32),
        _ => rd!(f64),
    }
}

enum Prop {
    Scalar(String, String),
    List(String, String, String),
}

pub fn read_ply(path: &Path) -> Result<Mesh, DataError> {
    let data = crate::util::read_bounded(path, MAX_MESH_BYTES)?;
    let end = data.windows(10).position(|w| w == b"end_header").ok_or_else(|| bad(path, "not a PLY file (no end_header)"))?;
    let header = String::from_utf8_lossy(&data[..end]).into_owned();
    let mut body = end + 10;
    if data.get(body) == Some(&b'\r') {
        body += 1;
    }
    if data.get(body) == Some(&b'\n') {
        body += 1;
    }
    if !header.starts_with("ply") {
        return Err(bad(path, "not a PLY file"));
    }
    let mut fmt = PlyFormat::Ascii;
    let mut elements: Vec<(String, usize, Vec<Prop>)> = Vec::new();
    for line in header.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            ["format", f, ..] => {
                fmt = match *f {
                    "ascii" => PlyFormat::Ascii,
                    "binary_little_endian" => PlyFormat::Le,
                    "binary_big_endian" => PlyFormat::Be,
                    _ => return Err(bad(path, format!("unknown PLY format {f}"))),
                }
            }
            ["element", name, n] => {
                let n = n.parse().map_err(|_| bad(path, format!("bad element count in {line:?}")))?;
                elements.push((name.to_string(), n, Vec::new()));
            }
            ["property", "list", ct, it, name] => {
                let e = elements.last_mut().ok_or_else(|| bad(path, "property before element"))?;
                e.2.push(Prop::List(ct.to_string(), it.to_string(), name.to_string()));
            }
            ["property", ty, name] => {
                let e = elements.last_mut().ok_or_else(|| bad(path, "property before element"))?;
                e.2.push(Prop::Scalar(ty.to_string(), name.to_string()));
            }
            _ => {}
        }
    }
    // Every property of every element takes at least one byte (binary) or two (an ascii value and
    // a separator): counts the body cannot hold are refused before the loops run.
    let body_len = (data.len() - body.min(data.len())) as u64;
    let mut needed: u64 = 0;
    for (name, count, props) in &elements {
        if props.is_empty() && *count > 0 {
            return Err(bad(path, format!("element {name} declares {count} items with no properties")));
        }
        needed = needed.saturating_add((*count as u64).saturating_mul(props.len() as u64));
    }
    if needed > body_len {
        return Err(bad(path, format!("header declares {needed} values but the body holds only {body_len} bytes")));
    }
    let mut m = Mesh::default();
    let text;
    let mut ascii_tokens = if fmt == PlyFormat::Ascii {
        text = String::from_utf8_lossy(&data[body..]).into_owned();
        Some(text.split_whitespace())
    } else {
        None
    };
    let mut pos = body;
    let trunc = || bad(path, "PLY data is truncated");
    let mut next = |ty: &str| -> Result<f64, DataError> {
        if let Some(toks) = ascii_tokens.as_mut() {
            let t = toks.next().ok_or_else(trunc)?;
            return t.parse::<f64>().map_err(|_| bad(path, format!("bad PLY value {t:?}")));
        }
        let n = ply_size(ty).ok_or_else(|| bad(path, format!("unknown PLY type {ty}")))?;
        if pos + n > data.len() {
            return Err(trunc());
        }
        let v = ply_read(ty, &data[pos..pos + n], fmt);
        pos += n;
        Ok(v)
    };
    for (name, count, props) in &elements {
        for _ in 0..*count {
            let mut xyz = [0.0; 3];
            for p in props {
                match p {
                    Prop::Scalar(ty, pn) => {
                        let v = next(ty)?;
                        match pn.as_str() {
                            "x" => xyz[0] = v,
                            "y" => xyz[1] = v,
                            "z" => xyz[2] = v,
                            _ => {}
                        }
                    }
                    Prop::List(ct, it, pn) => {
                        let k = next(ct)? as usize;
                        let idx: Vec<f64> = (0..k).map(|_| next(it)).collect::<Result<_, _>>()?;
                        if name == "face" && (pn == "vertex_indices" || pn == "vertex_index") && k >= 3 {
                            for j in 1..k - 1 {
                                m.triangles.push([idx[0] as u32, idx[j] as u32, idx[j + 1] as u32]);
                            }
                        }
                    }
                }
            }
            if name == "vertex" {
                m.positions.push(DVec3::from_array(xyz));
            }
        }
    }
    Ok(m)
}

/// A bounding-volume hierarchy over a mesh's triangles for exact nearest-surface queries.
///
/// Chamfer between two sets of surface *samples* has a floor: two independent area-uniform
/// samplings of the same surface lie on average `0.5·sqrt(area/n)` apart (the mean nearest-neighbour
/// distance of a planar Poisson set), about 0.5 % of the size of a typical object at 20k samples,
/// which hid any real difference below it. Distances are therefore taken from each sample to the
/// other mesh's *surface* (closest point on its triangles), which is exact.
pub struct TriBvh<'a> {
    mesh: &'a Mesh,
    /// Nodes: bounds and either children (`left`, `left + 1`) or a leaf range of `order`.
    nodes: Vec<BvhNode>,
    order: Vec<u32>,
}

#[derive(Clone, Copy, Debug)]
struct BvhNode {
    lo: DVec3,
    hi: DVec3,
    /// Leaf: first index into `order`; inner: the left child's index.
    first: u32,
    /// Leaf: triangle count (> 0); inner: 0.
    count: u32,
}

const BVH_LEAF: usize = 4;

impl<'a> TriBvh<'a> {
    pub fn new(mesh: &'a Mesh) -> Self {
        let centroid: Vec<DVec3> = mesh.triangles.iter().map(|t| (0..3).map(|k| mesh.positions[t[k] as usize]).sum::<DVec3>() / 3.0).collect();
        let mut bvh = TriBvh { mesh, nodes: Vec::with_capacity(2 * mesh.triangles.len() / BVH_LEAF + 1), order: (0..mesh.triangles.len() as u32).collect() };
        if !mesh.triangles.is_empty() {
            bvh.nodes.push(BvhNode { lo: DVec3::ZERO, hi: DVec3::ZERO, first: 0, count: 0 });
            bvh.build(0, 0, mesh.triangles.len(), &centroid);
        }
        bvh
    }

    fn build(&mut self, node: usize, start: usize, end: usize, centroid: &[DVec3]) {
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for &t in &self.order[start..end] {
            for &v in &self.mesh.triangles[t as usize] {
                let p = self.mesh.positions[v as usize];
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        if end - start <= BVH_LEAF {
            self.nodes[node] = BvhNode { lo, hi, first: start as u32, count: (end - start) as u32 };
            return;
        }
        let ext = hi - lo;
        let axis = if ext.x >= ext.y && ext.x >= ext.z { 0 } else if ext.y >= ext.z { 1 } else { 2 };
        let mid = (start + end) / 2;
        self.order[start..end].select_nth_unstable_by(mid - start, |a, b| centroid[*a as usize][axis].total_cmp(&centroid[*b as usize][axis]));
        let left = self.nodes.len();
        self.nodes.push(BvhNode { lo, hi, first: 0, count: 0 });
        self.nodes.push(BvhNode { lo, hi, first: 0, count: 0 });
        self.nodes[node] = BvhNode { lo, hi, first: left as u32, count: 0 };
        self.build(left, start, mid, centroid);
        self.build(left + 1, mid, end, centroid);
    }

    /// Index of the nearest triangle to `q` and the squared distance to it (None: no triangles).
    pub fn nearest(&self, q: DVec3) -> Option<(usize, f64)> {
        if self.nodes.is_empty() {
            return None;
        }
        let mut best = (usize::MAX, f64::INFINITY);
        let mut stack = vec![0usize];
        while let Some(n) = stack.pop() {
            let node = self.nodes[n];
            if box_dist2(q, node.lo, node.hi) >= best.1 {
                continue;
            }
            if node.count > 0 {
                for &t in &self.order[node.first as usize..(node.first + node.count) as usize] {
                    let d2 = self.tri_dist2(q, t as usize);
                    if d2 < best.1 {
                        best = (t as usize, d2);
                    }
                }
            } else {
                let (a, b) = (node.first as usize, node.first as usize + 1);
                // Visit the nearer child first (pushed last).
                let (da, db) = (box_dist2(q, self.nodes[a].lo, self.nodes[a].hi), box_dist2(q, self.nodes[b].lo, self.nodes[b].hi));
                if da <= db {
                    stack.extend([b, a]);
                } else {
                    stack.extend([a, b]);
                }
            }
        }
        (best.0 != usize::MAX).then_some(best)
    }

    fn tri_dist2(&self, q: DVec3, t: usize) -> f64 {
        let tri = self.mesh.triangles[t];
        let p = tri.map(|i| self.mesh.positions[i as usize]);
        (closest_on_triangle(q, p) - q).length_squared()
    }
}

fn box_dist2(q: DVec3, lo: DVec3, hi: DVec3) -> f64 {
    (lo - q).max(q - hi).max(DVec3::ZERO).length_squared()
}

/// The point of triangle `p` closest to `q` (Voronoi-region walk; degenerate triangles fall
/// back to their edges).
pub fn closest_on_triangle(q: DVec3, p: [DVec3; 3]) -> DVec3 {
    let (a, b, c) = (p[0], p[1], p[2]);
    let (ab, ac, ap) = (b - a, c - a, q - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = q - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let den = d1 - d3;
        return if den > 0.0 { a + ab * (d1 / den) } else { a };
    }
    let cp = q - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let den = d2 - d6;
        return if den > 0.0 { a + ac * (d2 / den) } else { a };
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let den = (d4 - d3) + (d5 - d6);
        return if den > 0.0 { b + (c - b) * ((d4 - d3) / den) } else { b };
    }
    let den = va + vb + vc;
    if den.abs() < 1e-300 || !den.is_finite() {
        // Degenerate: nearest of the three edges.
        let seg = |u: DVec3, v: DVec3| {
            let d = v - u;
            let t = ((q - u).dot(d) / d.length_squared().max(1e-300)).clamp(0.0, 1.0);
            u + d * t
        };
        return [seg(a, b), seg(b, c), seg(c, a)].into_iter().min_by(|x, y| (*x - q).length_squared().total_cmp(&(*y - q).length_squared())).unwrap_or(a);
    }
    a + ab * (vb / den) + ac * (vc / den)
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct MeshMetrics {
    pub samples: usize,
    pub accuracy: f64,
    pub completeness: f64,
    pub chamfer: f64,
    pub normal_consistency: f64,
    /// With shading normals where a mesh has vertex normals (None when neither has them).
    pub shading_normal_consistency: Option<f64>,
}

/// One direction, from samples `a` (face normals `af`, shading normals `an`) to the surface of
/// `b`: mean distance, mean |n·n'| between the face normals of the sample and of the nearest
/// triangle, and mean |n·n'| between the shading normals of the sample and of `b` at the nearest
/// point (NaN if either is empty).
fn directed(a: &[DVec3], af: &[DVec3], an: &[DVec3], b: &Mesh) -> (f64, f64, f64) {
    use rayon::prelude::*;
    if a.is_empty() || b.triangles.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    let tree = TriBvh::new(b);
    // Per-sample terms in sample order, summed sequentially: a parallel reduce would sum in
    // whatever order work stealing gives, and the figures would differ in their last bits
    // between runs of the same input.
    let terms: Vec<(f64, f64, f64)> = (0..a.len())
        .into_par_iter()
        .map(|i| {
            let p = a[i];
            let (j, d2) = tree.nearest(p).expect("non-empty mesh");
            let t = &b.triangles[j];
            let nb = b.tri_cross(t).normalize_or_zero();
            let face = af[i].dot(nb).abs();
            let shading = if b.normals.is_empty() {
                an[i].dot(nb).abs()
            } else {
                let q = closest_on_triangle(p, [b.positions[t[0] as usize], b.positions[t[1] as usize], b.positions[t[2] as usize]]);
                let (u, v) = b.barycentric(j, q);
                an[i].dot(b.shading_normal(j, u, v)).abs()
            };
            (d2.sqrt(), face, shading)
        })
        .collect();
    let (d, nc, sc) = terms.iter().fold((0.0, 0.0, 0.0), |x, y| (x.0 + y.0, x.1 + y.1, x.2 + y.2));
    let k = a.len() as f64;
    (d / k, nc / k, sc / k)
}

/// Chamfer distance and normal consistency between a predicted and a ground-truth mesh.
pub fn compare_meshes(pred: &Mesh, gt: &Mesh, samples: usize, seed: u64) -> MeshMetrics {
    let points = |m: &Mesh| -> (Vec<DVec3>, Vec<DVec3>, Vec<DVec3>) {
        let s = m.sample_barycentric(samples, seed);
        let p = s.iter().map(|&(k, u, v)| m.point_at(k, u, v)).collect();
        let f = s.iter().map(|&(k, _, _)| m.tri_cross(&m.triangles[k]).normalize_or_zero()).collect();
        let n = s.iter().map(|&(k, u, v)| m.shading_normal(k, u, v)).collect();
        (p, f, n)
    };
    let (pa, pf, ps) = points(pred);
    let (ga, gf, gs) = points(gt);
    let (acc, nc1, sc1) = directed(&pa, &pf, &ps, gt);
    let (comp, nc2, sc2) = directed(&ga, &gf, &gs, pred);
    let shading = (!pred.normals.is_empty() || !gt.normals.is_empty()).then_some(0.5 * (sc1 + sc2));
    MeshMetrics { samples, accuracy: acc, completeness: comp, chamfer: 0.5 * (acc + comp), normal_consistency: 0.5 * (nc1 + nc2), shading_normal_consistency: shading }
}

/// A UV sphere (for tests and benchmarks): `rings` × `segments`.
pub fn uv_sphere(radius: f64, rings: usize, segments: usize) -> Mesh {
    let mut m = Mesh::default();
    m.positions.push(DVec3::new(0.0, 0.0, radius));
    for r in 1..rings {
        let th = std::f64::consts::PI * r as f64 / rings as f64;
        for s in 0..segments {
            let ph = 2.0 * std::f64::consts::PI * s as f64 / segments as f64;
            m.positions.push(radius * DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()));
        }
    }
    m.positions.push(DVec3::new(0.0, 0.0, -radius));
    let ring = |r: usize, s: usize| (1 + (r - 1) * segments + s % segments) as u32;
    let last = (m.positions.len() - 1) as u32;
    for s in 0..segments {
        m.triangles.push([0, ring(1, s), ring(1, s + 1)]);
        m.triangles.push([last, ring(rings - 1, s + 1), ring(rings - 1, s)]);
    }
    for r in 1..rings - 1 {
        for s in 0..segments {
            let (a, b, c, d) = (ring(r, s), ring(r, s + 1), ring(r + 1, s), ring(r + 1, s + 1));
            m.triangles.push([a, c, b]);
            m.triangles.push([b, c, d]);
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bvh_matches_brute_force_closest_point() {
        let mut m = uv_sphere(1.0, 12, 24);
        // A degenerate (zero-area) and a sliver triangle must not break the query.
        let n = m.positions.len() as u32;
        m.positions.extend([DVec3::new(2.0, 0.0, 0.0), DVec3::new(2.0, 0.0, 0.0), DVec3::new(2.0, 1.0, 0.0), DVec3::new(2.0, 1.0, 1e-9)]);
        m.triangles.push([n, n + 1, n + 2]);
        m.triangles.push([n, n + 2, n + 3]);
        let bvh = TriBvh::new(&m);
        let mut rng = crate::util::rng(7);
        for _ in 0..500 {
            let q = DVec3::new(rng.random(), rng.random(), rng.random()) * 5.0 - 2.5;
            let (_, d2) = bvh.nearest(q).unwrap();
            let bf = m
                .triangles
                .iter()
                .map(|t| (closest_on_triangle(q, t.map(|i| m.positions[i as usize])) - q).length_squared())
                .fold(f64::INFINITY, f64::min);
            assert!((d2 - bf).abs() <= 1e-12 * (1.0 + bf), "{d2} vs {bf}");
        }
        // Closest points: a face interior, an edge and a vertex region of one triangle.
        let t = [DVec3::ZERO, DVec3::X, DVec3::Y];
        assert!((closest_on_triangle(DVec3::new(0.2, 0.2, 3.0), t) - DVec3::new(0.2, 0.2, 0.0)).length() < 1e-12);
        assert!((closest_on_triangle(DVec3::new(0.5, -1.0, 0.0), t) - DVec3::new(0.5, 0.0, 0.0)).length() < 1e-12);
        assert!((closest_on_triangle(DVec3::new(-1.0, -1.0, 1.0), t) - DVec3::ZERO).length() < 1e-12);
        assert!((closest_on_triangle(DVec3::new(1.0, 1.0, 0.0), t) - DVec3::new(0.5, 0.5, 0.0)).length() < 1e-12);
    }

    #[test]
    fn chamfer_has_no_sampling_floor() {
        // The same sphere tessellated twice: point-to-sample Chamfer would report ~0.5·sqrt(A/n)
        // (0.0089 here); the distance to the other surface is only the tessellations' difference.
        let a = uv_sphere(1.0, 96, 192);
        let b = uv_sphere(1.0, 95, 190);
        let m = compare_meshes(&a, &b, 20_000, 5);
        assert!(m.chamfer < 1e-3, "{m:?}");
    }

    #[test]
    fn identical_meshes_are_perfect_and_offset_spheres_measure_the_offset() {
        let a = uv_sphere(1.0, 48, 96);
        let m = compare_meshes(&a, &a, 20_000, 1);
        assert!(m.chamfer < 1e-12, "{m:?}");
        assert!((m.normal_consistency - 1.0).abs() < 1e-12);
        // radius 1 vs 1.05: every distance is ~0.05 (less the tessellation's sag)
        let b = uv_sphere(1.05, 48, 96);
        let m = compare_meshes(&b, &a, 20_000, 2);
        assert!((m.chamfer - 0.05).abs() < 0.005, "{m:?}");
        assert!(m.normal_consistency > 0.98, "{m:?}");
    }

    #[test]
    fn tilted_plane_normal_consistency_is_cos_angle() {
        let square = |tilt: f64| {
            let (c, s) = (tilt.cos(), tilt.sin());
            Mesh {
                positions: vec![
                    DVec3::new(-1.0, -c, -s),
                    DVec3::new(1.0, -c, -s),
                    DVec3::new(1.0, c, s),
                    DVec3::new(-1.0, c, s),
                ],
                triangles: vec![[0, 1, 2], [0, 2, 3]],
                normals: Vec::new(),
            }
        };
        let m = compare_meshes(&square(0.3), &square(0.0), 5_000, 3);
        assert!((m.normal_consistency - 0.3f64.cos()).abs() < 1e-9, "{m:?}");
        assert!(m.shading_normal_consistency.is_none(), "{m:?}");
        // Vertex normals equal to the face normal shade exactly as the faces do.
        let n = square(0.3).tri_cross(&[0, 1, 2]).normalize().as_vec3().to_array();
        let m2 = compare_meshes(&square(0.3).with_normals(&[n; 4]), &square(0.0), 5_000, 3);
        assert_eq!(m2.normal_consistency, m.normal_consistency);
        assert!((m2.shading_normal_consistency.unwrap() - 0.3f64.cos()).abs() < 1e-9, "{m2:?}");
    }

    #[test]
    fn shading_normals_score_a_coarse_smooth_mesh_as_it_renders() {
        // A 6×12 UV sphere with its radial vertex normals against a fine one: its flat faces score
        // NC 0.981, its interpolated normals 0.9998.
        let gt = uv_sphere(1.0, 64, 128);
        let coarse = uv_sphere(1.0, 6, 12);
        let radial: Vec<[f32; 3]> = coarse.positions.iter().map(|p| p.normalize().as_vec3().to_array()).collect();
        let faces = compare_meshes(&coarse, &gt, 20_000, 5);
        let smooth = compare_meshes(&coarse.clone().with_normals(&radial), &gt, 20_000, 5);
        assert_eq!(faces.normal_consistency, smooth.normal_consistency, "face normals ignore the vertex normals");
        assert_eq!(faces.chamfer, smooth.chamfer);
        let s = smooth.shading_normal_consistency.unwrap();
        assert!(faces.normal_consistency < 0.99 && s > 0.999 && s > faces.normal_consistency + 0.01, "faces {faces:?} smooth {smooth:?}");
        // Wrong vertex normals score as wrong (|n·n'| ignores orientation, so use one constant
        // direction): a normal along +z everywhere is far off on most of the sphere.
        let bad = compare_meshes(&coarse.with_normals(&vec![[0.0, 0.0, 1.0]; radial.len()]), &gt, 20_000, 5);
        assert!(bad.shading_normal_consistency.unwrap() < 0.6, "{bad:?}");
        // A normal count that does not match the vertices is dropped, not misread.
        let dropped = uv_sphere(1.0, 6, 12).with_normals(&radial[..3]);
        assert!(dropped.normals.is_empty());
    }

    #[test]
    fn obj_and_ply_readers_agree() {
        let dir = tempfile::tempdir().unwrap();
        let obj = dir.path().join("q.obj");
        std::fs::write(&obj, "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1/1 2/2 3/3 4/4\n").unwrap();
        let a = Mesh::read(&obj).unwrap();
        assert_eq!(a.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        let ply = dir.path().join("q.ply");
        let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
        for p in &a.positions {
            for c in p.to_array() {
                bytes.extend_from_slice(&(c as f32).to_le_bytes());
            }
        }
        bytes.push(4);
        for i in 0..4i32 {
            bytes.extend_from_slice(&i.to_le_bytes());
        }
        std::fs::write(&ply, &bytes).unwrap();
        let b = Mesh::read(&ply).unwrap();
        assert_eq!(b.triangles, a.triangles);
        assert_eq!(b.positions, a.positions);
        assert!((a.area() - 1.0).abs() < 1e-12);
        let ascii = dir.path().join("a.ply");
        std::fs::write(&ascii, "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n").unwrap();
        assert_eq!(Mesh::read(&ascii).unwrap().triangles.len(), 1);
        std::fs::write(dir.path().join("bad.obj"), "v 0 0 0\nf 1 2 3\n").unwrap();
        let e = Mesh::read(&dir.path().join("bad.obj")).unwrap_err().to_string();
        assert!(e.contains("bad.obj") && e.contains("out of range"), "{e}");
    }
}
