//! Mesh topology: connected components, hole closing, and the closed-and-oriented check.

use std::collections::HashMap;

use super::Mesh;

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let p = parent[parent[i as usize] as usize];
        parent[i as usize] = p;
        i = p;
    }
    i
}

/// Keep every connected component (through shared vertices) with at least `min_fraction` of the
/// largest one's triangles: the parts of an object (a ball resting in a bowl without touching it)
/// stay, specks far smaller than any part go. Returns the mesh (unused vertices dropped) and the
/// number of components found. A `min_fraction` of 1 keeps the largest component alone.
pub fn main_components(mesh: &Mesh, min_fraction: f32) -> (Mesh, usize) {
    let n = mesh.positions.len();
    let mut parent: Vec<u32> = (0..n as u32).collect();
    for t in mesh.triangles() {
        let r0 = find(&mut parent, t[0]);
        for &v in &t[1..] {
            let r = find(&mut parent, v);
            if r != r0 {
                parent[r as usize] = r0;
            }
        }
    }
    let mut count: HashMap<u32, usize> = HashMap::new();
    for t in mesh.triangles() {
        *count.entry(find(&mut parent, t[0])).or_default() += 1;
    }
    let components = count.len();
    let Some((&best, &most)) = count
        .iter()
        .max_by_key(|(&r, &c)| (c, std::cmp::Reverse(r)))
    else {
        return (mesh.clone(), 0);
    };
    let keep = |root: u32| root == best || count[&root] as f64 >= min_fraction as f64 * most as f64;
    let mut indices = Vec::with_capacity(mesh.indices.len());
    for t in mesh.triangles() {
        if keep(find(&mut parent, t[0])) {
            indices.extend_from_slice(&t);
        }
    }
    let mut out = Mesh {
        positions: mesh.positions.clone(),
        indices,
    };
    out.compact();
    (out, components)
}

/// Merge vertices with bit-identical positions and drop the triangles that collapse (a repeated
/// vertex). Returns the number of triangles dropped.
pub fn weld_exact(mesh: &mut Mesh) -> usize {
    let mut first: HashMap<[u32; 3], u32> = HashMap::new();
    let remap: Vec<u32> = mesh
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| *first.entry(p.map(f32::to_bits)).or_insert(i as u32))
        .collect();
    let before = mesh.triangle_count();
    let mut indices = Vec::with_capacity(mesh.indices.len());
    for t in mesh.triangles() {
        let t = t.map(|v| remap[v as usize]);
        if t[0] != t[1] && t[1] != t[2] && t[0] != t[2] {
            indices.extend_from_slice(&t);
        }
    }
    mesh.indices = indices;
    mesh.compact();
    before - mesh.triangle_count()
}

/// All directed edges `(a << 32) | b`, sorted.
fn sorted_directed_edges(mesh: &Mesh) -> Vec<u64> {
    use rayon::prelude::*;
    let mut e: Vec<u64> = Vec::with_capacity(mesh.indices.len());
    for t in mesh.triangles() {
        for k in 0..3 {
            e.push(((t[k] as u64) << 32) | t[(k + 1) % 3] as u64);
        }
    }
    e.par_sort_unstable();
    e
}

fn reverse(e: u64) -> u64 {
    e.rotate_right(32)
}

/// Directed boundary edges: (a, b) used by a triangle whose reverse (b, a) is not.
pub fn boundary_edges(mesh: &Mesh) -> Vec<(u32, u32)> {
    let e = sorted_directed_edges(mesh);
    let mut out: Vec<(u32, u32)> = e
        .iter()
        .filter(|&&x| e.binary_search(&reverse(x)).is_err())
        .map(|&x| ((x >> 32) as u32, x as u32))
        .collect();
    out.dedup();
    out
}

/// Close every boundary loop with a fan around a new vertex at the loop's centroid, oriented
/// like its neighbours. Returns the number of holes closed.
pub fn close_holes(mesh: &mut Mesh) -> usize {
    let edges = boundary_edges(mesh);
    if edges.is_empty() {
        return 0;
    }
    let mut next: HashMap<u32, u32> = HashMap::new();
    for &(a, b) in &edges {
        next.entry(a).or_insert(b);
    }
    let mut used: HashMap<u32, bool> = HashMap::new();
    let mut holes = 0;
    for &(start, _) in &edges {
        if used.contains_key(&start) {
            continue;
        }
        // Walk the loop start → next → ... → start.
        let mut lp = vec![start];
        used.insert(start, true);
        let mut cur = start;
        let closed = loop {
            let Some(&n) = next.get(&cur) else {
                break false;
            };
            if n == start {
                break true;
            }
            if used.contains_key(&n) {
                break false;
            }
            used.insert(n, true);
            lp.push(n);
            cur = n;
        };
        if !closed || lp.len() < 3 {
            continue;
        }
        let mut c = [0.0f32; 3];
        for &v in &lp {
            let p = mesh.positions[v as usize];
            for k in 0..3 {
                c[k] += p[k] / lp.len() as f32;
            }
        }
        let ci = mesh.positions.len() as u32;
        mesh.positions.push(c);
        for i in 0..lp.len() {
            let (a, b) = (lp[i], lp[(i + 1) % lp.len()]);
            // The boundary edge runs a → b in an existing triangle; the fill runs b → a.
            mesh.indices.extend_from_slice(&[b, a, ci]);
        }
        holes += 1;
    }
    holes
}

/// Closed, manifold and consistently oriented: every directed edge appears once and its
/// reverse appears once. The error says what is wrong and how often.
pub fn check_closed(mesh: &Mesh) -> Result<(), String> {
    if mesh.indices.is_empty() {
        return Err("the mesh has no triangles".into());
    }
    let degenerate = mesh
        .triangles()
        .filter(|t| t[0] == t[1] || t[1] == t[2] || t[0] == t[2])
        .count();
    let e = sorted_directed_edges(mesh);
    let repeated = e.windows(2).filter(|w| w[0] == w[1]).count();
    let open = e
        .iter()
        .filter(|&&x| e.binary_search(&reverse(x)).is_err())
        .count();
    if degenerate + repeated + open > 0 {
        return Err(format!(
            "{open} boundary edges, {repeated} edges used twice in one direction (non-manifold or flipped), \
             {degenerate} triangles with a repeated vertex"
        ));
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests_support {
    use super::Mesh;

    /// An octahedron of radius 1 centred at (offset, 0, 0), CCW outward.
    pub(crate) fn octahedron_at(offset: f32) -> Mesh {
        let p = |x: f32, y: f32, z: f32| [x + offset, y, z];
        let positions = vec![
            p(1., 0., 0.),
            p(-1., 0., 0.),
            p(0., 1., 0.),
            p(0., -1., 0.),
            p(0., 0., 1.),
            p(0., 0., -1.),
        ];
        let indices = vec![
            0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4, 2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5,
        ];
        Mesh { positions, indices }
    }

    pub(crate) fn octahedron() -> Mesh {
        octahedron_at(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use super::tests_support::octahedron_at as octahedron;

    #[test]
    fn octahedron_is_closed_and_outward() {
        let m = octahedron(0.0);
        check_closed(&m).unwrap();
        for t in m.triangles() {
            let n = crate::mesh::tri_normal(&m.positions, t);
            let c = m.positions[t[0] as usize];
            assert!(crate::mesh::dot(n, c) > 0.0, "inward triangle {t:?}");
        }
    }

    #[test]
    fn largest_component_and_hole_closing() {
        let a = octahedron(0.0);
        let b = octahedron(5.0);
        // Two components; make b smaller by dropping one face (then it is open too).
        let mut m = a.clone();
        let off = m.positions.len() as u32;
        m.positions.extend(&b.positions);
        m.indices.extend(b.indices[..21].iter().map(|i| i + off));
        let (big, n) = main_components(&m, 1.0);
        assert_eq!(n, 2);
        assert_eq!((big.triangle_count(), big.positions.len()), (8, 6));
        check_closed(&big).unwrap();
        // The 7-triangle part is 7/8 of the largest: kept at a 10% threshold, dropped at 90%.
        assert_eq!(main_components(&m, 0.1).0.triangle_count(), 15);
        assert_eq!(main_components(&m, 0.9).0.triangle_count(), 8);
        // Remove two adjacent faces of the octahedron: one hole with a 4-edge boundary.
        let mut holed = a.clone();
        holed.indices.drain(0..6);
        assert!(check_closed(&holed).is_err());
        assert_eq!(close_holes(&mut holed), 1);
        check_closed(&holed).unwrap();
        let mut flipped = a.clone();
        flipped.indices.swap(0, 1);
        assert!(
            check_closed(&flipped).is_err(),
            "a flipped triangle must be caught"
        );
    }
}
