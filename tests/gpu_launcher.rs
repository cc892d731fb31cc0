//! The wgpu launcher on whatever adapter exists (lavapipe in CI): upload, dispatch, readback,
//! batching, shape checks, and agreement with the cpu computation.

use pii_bake::backend::gpu::{groups_1d, util_kernels, Access, Bind, KernelSpec};
use pii_bake::backend::Backend;
use pii_bake::testing::{assert_close, Tolerance};

fn gpu() -> std::sync::Arc<pii_bake::backend::GpuContext> {
    match Backend::wgpu_for_tests() {
        Ok(Backend::Gpu(g)) => g,
        Ok(_) => unreachable!(),
        Err(e) => panic!("the test command installs lavapipe; no adapter: {e}"),
    }
}

#[test]
fn axpy_matches_cpu_over_a_2d_launch() {
    let g = gpu();
    // More than 65535 workgroups of 256 forces the x/y spread.
    let n = 65536 * 256 + 1000;
    let x: Vec<f32> = (0..n).map(|i| ((i % 1000) as f32) * 0.001).collect();
    let y: Vec<f32> = (0..n).map(|i| ((i % 7) as f32) - 3.0).collect();
    let xb = g.upload_f32("x", &x);
    let yb = g.upload_f32("y", &y);
    util_kernels::axpy(&g, 2.5, &xb, &yb).unwrap();
    let out = g.read_f32(&yb).unwrap();
    let expected: Vec<f32> = x.iter().zip(&y).map(|(a, b)| 2.5 * a + b).collect();
    assert_close("axpy", &out, &expected, Tolerance::F32_KERNEL);
    assert_eq!(groups_1d(n, 256)[1], 2);
}

#[test]
fn wrong_binding_count_is_an_error() {
    let g = gpu();
    let src = pii_bake::backend::gpu::shaders::with_lib(pii_bake::backend::gpu::shaders::UTIL);
    let k = g.kernel("util", &src, "axpy", &KernelSpec::new(true, &[Access::Read, Access::ReadWrite])).unwrap();
    let x = g.upload_f32("x", &[1.0]);
    let err = g.dispatch(&k, None, &[Bind::Buffer(&x)], [1, 1, 1]).unwrap_err();
    assert!(err.to_string().contains("expected 1 uniform"), "{err}");
}

#[test]
fn tensors_round_trip_on_both_backends() {
    for b in [Backend::cpu(), Backend::Gpu(gpu())] {
        let t = b.upload(&[1.0, -2.0, 3.5]);
        assert_eq!(b.to_vec(&t).unwrap(), vec![1.0, -2.0, 3.5], "{}", b.name());
        let z = b.zeros(5);
        assert_eq!(b.to_vec(&z).unwrap(), vec![0.0; 5]);
    }
}

#[test]
fn several_buffers_read_back_with_one_wait() {
    let g = gpu();
    let a: Vec<f32> = (0..1000).map(|i| i as f32 * 0.5).collect();
    let b = vec![-3.0f32, 7.0];
    let (ab, bb, empty) = (g.upload_f32("a", &a), g.upload_f32("b", &b), g.upload_f32("empty", &[]));
    // After a dispatch that writes one of them: the read sees the queue's work.
    let c = g.upload_f32("c", &[1.0f32, 1.0]);
    util_kernels::axpy(&g, 2.0, &c, &bb).unwrap();
    let w0 = g.counters().waits;
    let out = g.read_many::<f32>(&[&ab, &empty, &bb]).unwrap();
    assert_eq!(g.counters().waits - w0, 1.0);
    assert_eq!(out, vec![a.clone(), vec![], vec![-1.0, 9.0]]);
    // The backend's pair and host tensors pass through.
    let be = Backend::Gpu(g.clone());
    let host = pii_bake::backend::Tensor::Host(vec![4.0]);
    let (x, y) = be.to_vec2(&host, &pii_bake::backend::Tensor::Device(ab)).unwrap();
    assert_eq!((x, y), (vec![4.0], a));
}

#[test]
fn queued_batches_keep_their_order_with_writes_and_reach_the_device_in_one_submission() {
    let g = gpu();
    let x = g.upload_f32("x", &[1.0f32, 2.0]);
    let y = g.upload_f32("y", &[0.0f32, 0.0]);
    let s0 = g.counters().submits;
    for _ in 0..3 {
        util_kernels::axpy(&g, 1.0, &x, &y).unwrap();
    }
    assert_eq!(g.counters().submits, s0, "batches are queued, not submitted one by one");
    assert_eq!(g.read_f32(&y).unwrap(), vec![3.0, 6.0]);
    assert_eq!(g.counters().submits - s0, 1.0, "the queued batches and the readback go in one submission");
    // A write after queued work lands after it, and work queued after the write sees it.
    util_kernels::axpy(&g, 1.0, &x, &y).unwrap();
    g.write(&y, &[10.0f32, 20.0]).unwrap();
    util_kernels::axpy(&g, 1.0, &x, &y).unwrap();
    assert_eq!(g.read_f32(&y).unwrap(), vec![11.0, 22.0]);
}

#[test]
fn dispatches_that_share_a_pass_and_the_uniform_arena_see_each_others_writes_and_their_own_params() {
    // Queued dispatches are recorded into one encoder and, back to back, one compute pass; their
    // params blocks sit side by side in one uniform buffer. A Fibonacci-like chain, each step
    // reading what the one before wrote with its own coefficient, checks both: a missing
    // barrier or a wrong arena offset changes the integers.
    let g = gpu();
    let k = g
        .kernel("util", shaders_util(), "axpy", &KernelSpec::new(true, &[Access::Read, Access::ReadWrite]))
        .unwrap();
    let (x, y) = (g.upload_f32("x", &[1.0f32; 64]), g.zeros_f32("y", 64));
    let (mut hx, mut hy) = (1.0f64, 0.0f64);
    let coef = |i: usize| [1.0f32, -1.0, 2.0, -1.0][i % 4];
    let mut step = 0usize;
    // 70 batches (past the 64 queued before a submission) of 3 dispatches, then one batch of
    // more than the arena's 16384 blocks minus what is queued, which needs a submission first.
    let mut run = |batch_len: usize, batches: usize, step: &mut usize| {
        for _ in 0..batches {
            let mut b = g.batch("chain");
            for _ in 0..batch_len {
                let a = coef(*step);
                let (src, dst) = if *step % 2 == 0 { (&x, &y) } else { (&y, &x) };
                let p = util_kernels::AxpyParams { n: 64, a, _pad: [0; 2] };
                b.dispatch(&k, Some(bytemuck::bytes_of(&p)), &[Bind::Buffer(src), Bind::Buffer(dst)], groups_1d(64, 256)).unwrap();
                if *step % 2 == 0 {
                    hy += a as f64 * hx;
                } else {
                    hx += a as f64 * hy;
                }
                *step += 1;
            }
            b.submit().unwrap();
        }
    };
    let s0 = g.counters().submits;
    run(3, 70, &mut step);
    run(16300, 1, &mut step);
    let (gx, gy) = (g.read_f32(&x).unwrap(), g.read_f32(&y).unwrap());
    assert!(g.counters().submits - s0 >= 3.0, "64 queued batches and a full arena each submit");
    assert!(hx.abs() < 1e6 && hy.abs() < 1e6 && hx.fract() == 0.0, "the chain stays exact in f32: {hx} {hy}");
    assert!(gx.iter().all(|&v| v as f64 == hx), "x: {} expected {hx}", gx[0]);
    assert!(gy.iter().all(|&v| v as f64 == hy), "y: {} expected {hy}", gy[0]);
}

fn shaders_util() -> &'static str {
    pii_bake::backend::gpu::shaders::with_lib(pii_bake::backend::gpu::shaders::UTIL)
}

#[test]
fn the_kernel_profile_times_each_kernel_without_changing_results() {
    let g = gpu();
    if !g.supports_timestamps() {
        let e = g.set_kernel_profile(true).unwrap_err();
        assert!(e.to_string().contains("no timestamp queries"), "{e}");
        eprintln!("{} has no timestamp queries: the profile's timing is not exercised here", g.info.name);
        return;
    }
    let n = 1 << 20;
    let x: Vec<f32> = (0..n).map(|i| (i % 97) as f32).collect();
    let (xb, yb) = (g.upload_f32("x", &x), g.upload_f32("y", &vec![1.0; n]));
    util_kernels::axpy(&g, 1.0, &xb, &yb).unwrap();
    assert!(g.kernel_times().is_empty(), "off: nothing is recorded");
    g.set_kernel_profile(true).unwrap();
    let before = g.kernel_times();
    // More dispatches than one query set holds, across several submissions.
    for _ in 0..1100 {
        util_kernels::axpy(&g, 0.5, &xb, &yb).unwrap();
    }
    let mid = g.read_f32(&yb).unwrap();
    util_kernels::axpy(&g, -1.0, &xb, &yb).unwrap();
    let out = g.read_f32(&yb).unwrap();
    let times = g.kernel_times();
    let per = pii_bake::backend::gpu::kernel_times_per(&times, &before, 1);
    assert_eq!(per.len(), 1, "{per:?}");
    assert_eq!((per[0].kernel.as_str(), per[0].launches), ("util::axpy", 1101.0));
    assert!(per[0].seconds > 0.0 && per[0].seconds < 60.0, "{per:?}");
    let expect = |k: f32| -> Vec<f32> { x.iter().map(|v| 1.0 + v + k * v).collect() };
    assert_close("profiled axpy", &mid, &expect(550.0), Tolerance::F32_KERNEL);
    assert_close("profiled axpy", &out, &expect(549.0), Tolerance::F32_KERNEL);
    g.set_kernel_profile(false).unwrap();
    util_kernels::axpy(&g, 1.0, &xb, &yb).unwrap();
    g.read_f32(&yb).unwrap();
    assert!(g.kernel_times().is_empty(), "off again: the profile is dropped");
}

#[test]
fn the_host_time_of_buffers_bind_groups_and_submissions_is_counted() {
    let g = gpu();
    let c0 = g.counters();
    let x = g.upload_f32("x", &[1.0f32, 2.0]);
    let y = g.upload_f32("y", &[0.0f32, 0.0]);
    let z = g.zeros_f32("z", 4);
    let c1 = g.counters();
    assert_eq!(c1.buffers - c0.buffers, 3.0, "two uploads and a zero buffer are three buffers made");
    assert!(c1.buffer_seconds > c0.buffer_seconds, "making them took host time");
    assert_eq!(c1.bind_group_seconds, c0.bind_group_seconds, "no launch yet, no bind group");
    for _ in 0..3 {
        util_kernels::axpy(&g, 1.0, &x, &y).unwrap();
    }
    let c2 = g.counters();
    assert!(c2.bind_group_seconds > c1.bind_group_seconds, "each launch makes a bind group");
    assert!(c2.queue_seconds > c1.queue_seconds, "queued batches are recorded");
    assert_eq!(g.read_f32(&y).unwrap(), vec![3.0, 6.0]);
    let c3 = g.counters();
    assert_eq!(c3.buffers - c2.buffers, 1.0, "a readback makes one staging buffer");
    assert!(c3.queue_seconds > c2.queue_seconds, "the submission is counted");
    // Per step: the means between two snapshots.
    let per = c3.per(&c0, 2);
    assert_eq!(per.buffers, 2.0);
    assert!((per.bind_group_seconds - (c3.bind_group_seconds - c0.bind_group_seconds) / 2.0).abs() < 1e-12);
    drop(z);
}

#[test]
fn freed_buffers_are_reused_zeroed_and_only_after_the_commands_that_used_them() {
    // A context of its own: the counters below are this test's alone.
    let g = gpu();
    let n = 1000;
    let ones = g.upload_f32("ones", &vec![1.0f32; n]);
    let a = g.zeros_f32("a", n);
    util_kernels::axpy(&g, 3.0, &ones, &a).unwrap();
    assert!(g.read_f32(&a).unwrap().iter().all(|&v| v == 3.0));
    // y ← a is queued, not yet on the device, when `a` is dropped and its buffer handed out
    // again: the new owner's zero fill must come after that launch has read it.
    let y = g.zeros_f32("y", n);
    util_kernels::axpy(&g, 1.0, &a, &y).unwrap();
    drop(a);
    let c0 = g.counters();
    let b = g.zeros_f32("b", n);
    let c1 = g.counters();
    assert_eq!((c1.buffers - c0.buffers, c1.reused_buffers - c0.reused_buffers), (0.0, 1.0), "a's buffer is reused, none made");
    util_kernels::axpy(&g, 1.0, &ones, &b).unwrap();
    let out = g.read_many::<f32>(&[&y, &b]).unwrap();
    assert!(out[0].iter().all(|&v| v == 3.0), "the queued launch read a's contents, not the new owner's: {:?}", &out[0][..4]);
    assert!(out[1].iter().all(|&v| v == 1.0), "the reused buffer was zeroed first: {:?}", &out[1][..4]);

    // Within one batch: a buffer whose handle is dropped before the batch is queued stays the
    // batch's until it is recorded, so a buffer made meanwhile is not it.
    let src = pii_bake::backend::gpu::shaders::with_lib(pii_bake::backend::gpu::shaders::UTIL);
    let k = g.kernel("util", &src, "axpy", &KernelSpec::new(true, &[Access::Read, Access::ReadWrite])).unwrap();
    let p = util_kernels::AxpyParams { n: n as u32, a: 5.0, _pad: [0; 2] };
    let mut batch = g.batch("pool");
    let out2 = g.zeros_f32("out2", n);
    {
        let t = g.zeros_f32("t", n);
        batch.dispatch(&k, Some(bytemuck::bytes_of(&p)), &[(&ones).into(), (&t).into()], groups_1d(n, 256)).unwrap();
        batch.dispatch(&k, Some(bytemuck::bytes_of(&p)), &[(&t).into(), (&out2).into()], groups_1d(n, 256)).unwrap();
    }
    let c = g.zeros_f32("c", n);
    batch.submit().unwrap();
    util_kernels::axpy(&g, 1.0, &ones, &c).unwrap();
    let out = g.read_many::<f32>(&[&out2, &c]).unwrap();
    assert!(out[0].iter().all(|&v| v == 25.0), "t = 5, out2 = 5·t: {:?}", &out[0][..4]);
    assert!(out[1].iter().all(|&v| v == 1.0), "c is zero, then one: not the batch's t: {:?}", &out[1][..4]);

    // A buffer of a larger size class than asked reads back as exactly its elements, and a
    // second readback of the same size reuses the first's staging buffer.
    let d = g.upload_f32("d", &[2.0f32; 7]);
    let e = g.zeros_f32("e", 7);
    util_kernels::axpy(&g, 1.0, &d, &e).unwrap();
    assert_eq!(g.read_f32(&e).unwrap(), vec![2.0; 7]);
    let r0 = g.counters();
    assert_eq!(g.read_f32(&e).unwrap(), vec![2.0; 7]);
    let r1 = g.counters();
    assert_eq!((r1.buffers - r0.buffers, r1.reused_buffers - r0.reused_buffers), (0.0, 1.0));

    // An upload into a recycled buffer is a copy in the command stream: it lands after the
    // queued launch that read the buffer's earlier contents, and without a submission.
    let m = 3000;
    let u = g.upload_f32("u", &vec![1.0f32; m]);
    let y2 = g.zeros_f32("y2", m);
    util_kernels::axpy(&g, 1.0, &u, &y2).unwrap();
    drop(u);
    let u0 = g.counters();
    let v = g.upload_f32("v", &vec![9.0f32; m]);
    let u1 = g.counters();
    assert_eq!((u1.buffers - u0.buffers, u1.reused_buffers - u0.reused_buffers, u1.submits - u0.submits), (0.0, 1.0, 0.0));
    let out = g.read_many::<f32>(&[&y2, &v]).unwrap();
    assert!(out[0].iter().all(|&x| x == 1.0), "the queued launch read u's contents: {:?}", &out[0][..4]);
    assert!(out[1].iter().all(|&x| x == 9.0), "v holds its upload: {:?}", &out[1][..4]);
}
