//! Metrics: PSNR, SSIM, scale-aligned albedo, roughness MSE, environment error, Chamfer.

pub mod cli;
