//! Scenes in: dataset readers (transforms.json, cameras.npz, LLFF, COLMAP), images, masks,
//! normalisation into the unit sphere, rays.

pub mod cli;
