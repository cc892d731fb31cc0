//! Spherical Gaussians: SG algebra, BRDF-as-SG shading, environment SGs <-> latlong EXR, SG fitting.

pub mod bench;
pub mod bench_brdf;
pub mod cli;
pub mod env;
pub mod fit;
pub mod lanes;
pub mod shade;
pub mod shade_gpu;
