//! SDF and material field interfaces, grid evaluation, marching cubes, cleanup, simplification, UV unwrap.
