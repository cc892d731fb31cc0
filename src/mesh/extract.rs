//! Iso-surface extraction from grid values: marching tetrahedra on the Freudenthal (Kuhn)
//! split of every cube into six tetrahedra around its main diagonal.
//!
//! Why tetrahedra rather than the 256-case cube table: the split is one global
//! triangulation of the grid (neighbouring cubes cut their shared face along the same
//! diagonal), so the surface is watertight and manifold by construction with no ambiguous
//! cases and no third-party tables; vertices live on grid edges and are shared through an
//! edge-keyed map (no duplicates). It makes about twice the triangles of marching cubes,
//! which the simplification step removes anyway.

use std::collections::HashMap;

use super::grid::GridSpec;
use super::Mesh;

/// The 7 edge directions of the Freudenthal triangulation from a node (dx, dy, dz).
const DIRS: [[usize; 3]; 7] = [
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 1, 0],
    [1, 0, 1],
    [0, 1, 1],
    [1, 1, 1],
];

fn dir_id(d: [usize; 3]) -> usize {
    DIRS.iter().position(|&e| e == d).expect("Freudenthal edge")
}

/// The six tetrahedra of a cube: corners as offsets, each path 000 → 111 along a permutation
/// of the axes.
const TETS: [[[usize; 3]; 4]; 6] = [
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]],
    [[0, 0, 0], [1, 0, 0], [1, 0, 1], [1, 1, 1]],
    [[0, 0, 0], [0, 1, 0], [1, 1, 0], [1, 1, 1]],
    [[0, 0, 0], [0, 1, 0], [0, 1, 1], [1, 1, 1]],
    [[0, 0, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1]],
    [[0, 0, 0], [0, 0, 1], [0, 1, 1], [1, 1, 1]],
];

/// Extract the zero level set of `values` (negative inside) on `grid`. Triangles are
/// counter-clockwise seen from outside (normals point toward increasing values).
/// Values exactly 0 count as outside, so no vertex lands on two edges' shared node by accident.
pub fn marching_tetrahedra(grid: &GridSpec, values: &[f32]) -> Mesh {
    assert_eq!(values.len(), grid.len(), "grid values");
    let [nx, ny, nz] = grid.dims;
    let inside = |v: f32| v < 0.0;
    let mut edge_vertex: HashMap<u64, u32> = HashMap::new();
    let mut positions: Vec<[f32; 3]> = Vec::new();
    let mut indices: Vec<u32> = Vec::new();

    // The vertex on the grid edge between nodes a and b (a < b in index order).
    let mut vertex = |a: [usize; 3], b: [usize; 3], positions: &mut Vec<[f32; 3]>| -> u32 {
        let (lo, hi) = if grid.index(a[0], a[1], a[2]) < grid.index(b[0], b[1], b[2]) {
            (a, b)
        } else {
            (b, a)
        };
        let d = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
        let key = grid.index(lo[0], lo[1], lo[2]) as u64 * 7 + dir_id(d) as u64;
        *edge_vertex.entry(key).or_insert_with(|| {
            let va = values[grid.index(lo[0], lo[1], lo[2])];
            let vb = values[grid.index(hi[0], hi[1], hi[2])];
            // Snap to the end nodes when within 1e-4 of them: such vertices then coincide exactly
            // and are welded below instead of leaving slivers of zero area.
            let t = (va / (va - vb)).clamp(0.0, 1.0);
            let t = if t < 1e-4 {
                0.0
            } else if t > 1.0 - 1e-4 {
                1.0
            } else {
                t
            };
            let pa = grid.node(lo[0], lo[1], lo[2]);
            let pb = grid.node(hi[0], hi[1], hi[2]);
            positions.push([
                pa[0] + t * (pb[0] - pa[0]),
                pa[1] + t * (pb[1] - pa[1]),
                pa[2] + t * (pb[2] - pa[2]),
            ]);
            (positions.len() - 1) as u32
        })
    };

    for z in 0..nz - 1 {
        for y in 0..ny - 1 {
            for x in 0..nx - 1 {
                // Quick reject: no sign change among the 8 corners.
                let mut n_in = 0;
                for c in 0..8 {
                    let (dx, dy, dz) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
                    n_in += inside(values[grid.index(x + dx, y + dy, z + dz)]) as usize;
                }
                if n_in == 0 || n_in == 8 {
                    continue;
                }
                for tet in &TETS {
                    let nodes = tet.map(|o| [x + o[0], y + o[1], z + o[2]]);
                    let vals = nodes.map(|n| values[grid.index(n[0], n[1], n[2])]);
                    let ins: Vec<usize> = (0..4).filter(|&i| inside(vals[i])).collect();
                    let outs: Vec<usize> = (0..4).filter(|&i| !inside(vals[i])).collect();
                    // Each triangle corner is a tet edge (pair of corner ids).
                    let mut tris: Vec<[(usize, usize); 3]> = Vec::new();
                    match ins.len() {
                        1 | 3 => {
                            let (apex, o) = if ins.len() == 1 {
                                (ins[0], &outs)
                            } else {
                                (outs[0], &ins)
                            };
                            tris.push([(apex, o[0]), (apex, o[1]), (apex, o[2])]);
                        }
                        2 => {
                            let (a, b, c, d) = (ins[0], ins[1], outs[0], outs[1]);
                            // The quad ac-ad-bd-bc, split along ac-bd.
                            tris.push([(a, c), (a, d), (b, d)]);
                            tris.push([(a, c), (b, d), (b, c)]);
                        }
                        _ => continue,
                    }
                    // Orientation is decided on the triangle through the edge midpoints, which is
                    // never degenerate and faces the same way as the interpolated one: its normal
                    // must point from the inside corners to the outside ones.
                    let node_pos = |i: usize| grid.node(nodes[i][0], nodes[i][1], nodes[i][2]);
                    let centroid = |set: &[usize]| -> [f32; 3] {
                        let mut c = [0.0f32; 3];
                        for &i in set {
                            let p = node_pos(i);
                            for k in 0..3 {
                                c[k] += p[k] / set.len() as f32;
                            }
                        }
                        c
                    };
                    let (ci, co) = (centroid(&ins), centroid(&outs));
                    let out_dir = [co[0] - ci[0], co[1] - ci[1], co[2] - ci[2]];
                    for t in tris {
                        let mid = t.map(|(i, j)| {
                            let (a, b) = (node_pos(i), node_pos(j));
                            [
                                (a[0] + b[0]) * 0.5,
                                (a[1] + b[1]) * 0.5,
                                (a[2] + b[2]) * 0.5,
                            ]
                        });
                        let n =
                            super::cross(super::sub(mid[1], mid[0]), super::sub(mid[2], mid[0]));
                        let flip = super::dot(n, out_dir) < 0.0;
                        let v = t.map(|(i, j)| vertex(nodes[i], nodes[j], &mut positions));
                        if flip {
                            indices.extend_from_slice(&[v[0], v[2], v[1]]);
                        } else {
                            indices.extend_from_slice(&v);
                        }
                    }
                }
            }
        }
    }
    let mut mesh = Mesh { positions, indices };
    super::topology::weld_exact(&mut mesh);
    mesh
}
