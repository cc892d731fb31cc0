//! The wgpu launcher of `shaders/sg_shade.wgsl` (BRDF-as-SG shading, forward and backward);
//! the cpu reference and the formulas are in [`super::shade`].

use crate::backend::gpu::{groups_1d, shaders, Access, GpuContext, KernelSpec};
use crate::backend::{BackendError, Tensor};

use super::shade::{LOBE_STRIDE, POINT_STRIDE};

/// The WGSL kernel family of this module.
pub const SG_SHADE_WGSL: &str = include_str!("../../shaders/sg_shade.wgsl");
const WG: u32 = 64;

/// Mirrors `ShadeParams` in `shaders/sg_shade.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ShadeParams {
    /// Points.
    pub n: u32,
    /// Lobes.
    pub k: u32,
    pub _pad0: u32,
    pub _pad1: u32,
}
const _: () = assert!(std::mem::size_of::<ShadeParams>() == 16);

fn params(points: &Tensor, lobes: &Tensor) -> Result<ShadeParams, BackendError> {
    let u = |v: usize, what: &str| u32::try_from(v).map_err(|_| BackendError::Shape(format!("{what} ({v}) exceeds u32")));
    Ok(ShadeParams { n: u(points.len() / POINT_STRIDE, "points")?, k: u(lobes.len() / LOBE_STRIDE, "lobes")?, _pad0: 0, _pad1: 0 })
}

pub(super) fn forward(g: &GpuContext, points: &Tensor, lobes: &Tensor) -> Result<Tensor, BackendError> {
    let p = params(points, lobes)?;
    let out = g.zeros_f32("sg_shade.out", p.n as usize * 3);
    if p.n == 0 {
        return Ok(Tensor::Device(out));
    }
    let src = shaders::with_lib(SG_SHADE_WGSL);
    let spec = KernelSpec::new(true, &[Access::Read, Access::Read, Access::ReadWrite]);
    let k = g.kernel("sg_shade", &src, "shade_forward", &spec)?;
    g.dispatch(&k, Some(bytemuck::bytes_of(&p)), &[points.device()?.into(), lobes.device()?.into(), (&out).into()], groups_1d(p.n as usize, WG))?;
    Ok(Tensor::Device(out))
}

pub(super) fn backward(g: &GpuContext, points: &Tensor, lobes: &Tensor, d_out: &Tensor) -> Result<(Tensor, Tensor), BackendError> {
    let p = params(points, lobes)?;
    let (n, k) = (p.n as usize, p.k as usize);
    let d_points = g.zeros_f32("sg_shade.d_points", n * POINT_STRIDE);
    let d_lobes = g.zeros_f32("sg_shade.d_lobes", k * LOBE_STRIDE);
    if n == 0 || k == 0 {
        return Ok((Tensor::Device(d_points), Tensor::Device(d_lobes)));
    }
    let partial = g.zeros_f32("sg_shade.partial", n * k * LOBE_STRIDE);
    let src = shaders::with_lib(SG_SHADE_WGSL);
    let ub = bytemuck::bytes_of(&p);
    let spec = KernelSpec::new(true, &[Access::Read, Access::Read, Access::Read, Access::ReadWrite, Access::ReadWrite]);
    let kb = g.kernel("sg_shade", &src, "shade_backward", &spec)?;
    let kr = g.kernel("sg_shade", &src, "reduce_lobes", &KernelSpec::new(true, &[Access::Read, Access::ReadWrite]))?;
    let mut b = g.batch("sg_shade.backward");
    b.dispatch(
        &kb,
        Some(ub),
        &[points.device()?.into(), lobes.device()?.into(), d_out.device()?.into(), (&d_points).into(), (&partial).into()],
        groups_1d(n, WG),
    )?;
    b.dispatch(&kr, Some(ub), &[(&partial).into(), (&d_lobes).into()], groups_1d(k * LOBE_STRIDE, WG))?;
    b.submit()?;
    Ok((Tensor::Device(d_points), Tensor::Device(d_lobes)))
}
