//! The wgpu backend: headless device creation, adapter choice, typed storage buffers, a cached
//! kernel (compute pipeline) launcher with explicit bind-group layouts, batched dispatch, and a
//! per-kernel GPU time profile through timestamp queries where the adapter supports them
//! ([`GpuContext::set_kernel_profile`]).
//!
//! Kernel binding convention (all WGSL kernels follow it, see ARCHITECTURE.md):
//! `@group(0) @binding(0)` is a `var<uniform>` params struct when the kernel has one; storage
//! buffers follow at bindings 1, 2, ... in the order given in [`KernelSpec::storage`].
//! Large 1-D launches use [`groups_1d`], which spreads workgroups over x and y; kernels then
//! compute the linear index with `linear_index(gid, nwg, WG)` from `shaders/lib/index.wgsl`.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use super::{BackendError, NO_ADAPTER_HINT};

/// Options for creating a [`GpuContext`].
#[derive(Clone, Debug, Default)]
pub struct GpuOptions {
    /// Force an adapter: its index in [`list_adapters`] or a case-insensitive name substring.
    pub adapter: Option<String>,
    /// Accept software adapters (lavapipe/llvmpipe, WARP). Off for `--backend auto`.
    pub allow_software: bool,
    /// Request wgpu's validation layer (tests).
    pub validation: bool,
}

/// A GPU adapter as seen by [`list_adapters`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct AdapterSummary {
    pub index: usize,
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub driver: String,
    pub software: bool,
}

fn is_software(info: &wgpu::AdapterInfo) -> bool {
    let name = info.name.to_lowercase();
    info.device_type == wgpu::DeviceType::Cpu
        || name.contains("llvmpipe")
        || name.contains("lavapipe")
        || name.contains("swiftshader")
}

fn rank(info: &wgpu::AdapterInfo) -> u32 {
    match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

fn instance(validation: bool) -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
    desc.flags = if validation { wgpu::InstanceFlags::debugging() } else { wgpu::InstanceFlags::empty() };
    wgpu::Instance::new(desc)
}

fn enumerate(inst: &wgpu::Instance) -> Vec<wgpu::Adapter> {
    let mut adapters = pollster::block_on(inst.enumerate_adapters(wgpu::Backends::all()));
    adapters.sort_by_key(|a| rank(&a.get_info()));
    adapters
}

/// Every adapter wgpu can see, best first (discrete, integrated, virtual, other, software).
pub fn list_adapters() -> Vec<AdapterSummary> {
    enumerate(&instance(false))
        .iter()
        .enumerate()
        .map(|(index, a)| {
            let i = a.get_info();
            AdapterSummary {
                index,
                software: is_software(&i),
                name: i.name,
                backend: format!("{:?}", i.backend),
                device_type: format!("{:?}", i.device_type),
                driver: format!("{} {}", i.driver, i.driver_info),
            }
        })
        .collect()
}

/// A storage buffer of 4-byte elements (f32, u32 or Pod structs of them) with its element count.
/// A clone is another handle to the same buffer, not a copy. The wgpu buffer may be larger than
/// `len` elements (a recycled one of its size class, see [`Pool`]); kernels are bound to the first
/// `len` elements only, and copies and reads use that many.
#[derive(Clone)]
pub struct GpuBuffer {
    pub buffer: wgpu::Buffer,
    pub len: usize,
    /// Set for a buffer from the context's pool: it goes back there when the last handle drops.
    home: Option<Arc<Home>>,
}

impl std::fmt::Debug for GpuBuffer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuBuffer").field("len", &self.len).field("bytes", &self.buffer.size()).field("pooled", &self.home.is_some()).finish()
    }
}

impl GpuBuffer {
    /// The bytes kernels, copies and reads see (`len` elements, at least one: wgpu rejects
    /// empty bindings).
    fn bytes(&self) -> u64 {
        (self.len.max(1) * 4) as u64
    }
}

/// Buffers made and dropped again by the hundred in a training step (field evaluations' rows
/// and activations, readback staging) are kept for reuse instead of being freed: on an NVIDIA
/// H200 making them was 6.6 ms of a 32 ms stage-1 step (427 buffers). Free buffers are kept by
/// size class (eight per octave, so a buffer is at most 1/8 larger than asked) and usage, up to
/// [`POOL_BYTES`], the least recently freed dropped first.
///
/// Reuse is ordered by the command stream: a buffer comes back when its last [`GpuBuffer`]
/// handle drops, perhaps while commands recorded earlier still use it, and its next owner's
/// first write (a zero fill recorded into the open encoder, a copy, a dispatch, or a queue
/// write after a flush as [`GpuContext::write`] does) comes after those commands on the queue.
#[derive(Default)]
struct Pool {
    free: HashMap<(u64, bool), Vec<(u64, wgpu::Buffer)>>,
    /// Free buffers by the order they came back: (sequence number, key).
    order: std::collections::BTreeMap<u64, (u64, bool)>,
    seq: u64,
    bytes: u64,
}

/// Most bytes of free buffers a context keeps. Over the example's first stage-1 steps on
/// lavapipe the pool held 530 MB at 512 MiB (full, and still missing some sizes each step) and
/// 780 MB at 2 GiB; a device then holds at most this much more than its busiest moment needed.
const POOL_BYTES: u64 = 1 << 30;

/// The size class of a buffer of `bytes`: the least m·2^k ≥ bytes with 8 ≤ m < 16, at least 256.
fn size_class(bytes: u64) -> u64 {
    let b = bytes.max(256);
    let k = (63 - b.leading_zeros()).saturating_sub(3);
    b.div_ceil(1 << k) << k
}

impl Pool {
    fn take(&mut self, key: (u64, bool)) -> Option<wgpu::Buffer> {
        let (seq, b) = self.free.get_mut(&key)?.pop()?;
        self.order.remove(&seq);
        self.bytes -= key.0;
        Some(b)
    }

    fn put(&mut self, key: (u64, bool), b: wgpu::Buffer) {
        if key.0 > POOL_BYTES {
            return;
        }
        while self.bytes + key.0 > POOL_BYTES {
            let Some((_, old)) = self.order.pop_first() else { break };
            if let Some(v) = self.free.get_mut(&old) {
                if !v.is_empty() {
                    v.remove(0);
                    self.bytes -= old.0;
                }
            }
        }
        self.seq += 1;
        self.order.insert(self.seq, key);
        self.free.entry(key).or_default().push((self.seq, b));
        self.bytes += key.0;
    }
}

/// Where a pooled buffer goes back to (the pool is gone with its context: then it is freed).
struct Home {
    buffer: wgpu::Buffer,
    key: (u64, bool),
    pool: std::sync::Weak<Mutex<Pool>>,
}

impl Drop for Home {
    fn drop(&mut self) {
        if let Some(pool) = self.pool.upgrade() {
            if let Ok(mut p) = pool.lock() {
                p.put(self.key, self.buffer.clone());
            }
        }
    }
}

/// How a kernel binds a storage buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Access {
    Read,
    ReadWrite,
}

/// A kernel's binding layout: an optional uniform params block at binding 0, then storage
/// buffers at bindings 1.. in order.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct KernelSpec {
    pub uniform: bool,
    pub storage: Vec<Access>,
}

impl KernelSpec {
    pub fn new(uniform: bool, storage: &[Access]) -> Self {
        Self { uniform, storage: storage.to_vec() }
    }
}

/// A compiled compute pipeline with its layout.
pub struct Kernel {
    pub label: String,
    pub pipeline: wgpu::ComputePipeline,
    pub layout: wgpu::BindGroupLayout,
    pub spec: KernelSpec,
}

/// One bound storage resource of a dispatch.
pub enum Bind<'a> {
    Buffer(&'a GpuBuffer),
    Raw(&'a wgpu::Buffer),
}

impl<'a> From<&'a GpuBuffer> for Bind<'a> {
    fn from(b: &'a GpuBuffer) -> Self {
        Bind::Buffer(b)
    }
}

/// The headless wgpu device and everything kernels share.
pub struct GpuContext {
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    pub features: wgpu::Features,
    /// Compiled kernels by label, then entry point (looked up without allocating: every launch asks).
    kernels: Mutex<HashMap<String, HashMap<String, Arc<Kernel>>>>,
    counters: Counters,
    /// Batches submitted ([`Batch::submit`]) but not yet on the queue.
    pending: Mutex<Pending>,
    /// Free buffers kept for reuse.
    pool: Arc<Mutex<Pool>>,
    /// The uniform arena (see [`Pending`]) and its offset alignment.
    arena: wgpu::Buffer,
    uniform_align: usize,
    /// The upload arena (see [`GpuContext::upload`]).
    upload_arena: wgpu::Buffer,
    /// Whether dispatches are recorded for the kernel profile (read without the `pending` lock
    /// by every launch).
    profiling: std::sync::atomic::AtomicBool,
}

/// Dispatches per query set of the kernel profile (two timestamps each; a set's resolved
/// timestamps take 16 KiB, a multiple of the 256-byte resolve alignment).
const PROFILE_SET: usize = 1024;

/// The kernel profile's state (see [`GpuContext::set_kernel_profile`]): the open encoder's
/// profiled dispatches and the totals of every submission resolved so far.
#[derive(Default)]
struct Profile {
    /// Query sets of `PROFILE_SET` dispatches, reused by each submission.
    sets: Vec<wgpu::QuerySet>,
    /// The open encoder's profiled dispatches' kernel labels, in recording order (dispatch `i`
    /// writes timestamps `2i`, `2i + 1` of the whole, set `i / PROFILE_SET`).
    labels: Vec<String>,
    totals: HashMap<String, KernelTime>,
}

/// One kernel's launches and GPU time (seconds between its pass's two timestamps), summed.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct KernelTime {
    pub kernel: String,
    pub launches: f64,
    pub seconds: f64,
}

/// `later − earlier` per kernel, divided by `steps`, the costliest first (kernels that did not
/// run in between are left out).
pub fn kernel_times_per(later: &[KernelTime], earlier: &[KernelTime], steps: u64) -> Vec<KernelTime> {
    let n = steps.max(1) as f64;
    let mut out: Vec<KernelTime> = later
        .iter()
        .map(|k| {
            let e = earlier.iter().find(|e| e.kernel == k.kernel).cloned().unwrap_or_default();
            KernelTime { kernel: k.kernel.clone(), launches: (k.launches - e.launches) / n, seconds: (k.seconds - e.seconds) / n }
        })
        .filter(|k| k.launches > 0.0)
        .collect();
    out.sort_by(|a, b| b.seconds.total_cmp(&a.seconds).then_with(|| a.kernel.cmp(&b.kernel)));
    out
}

/// Batches queued before they are submitted together: a queue submission costs tens of µs of
/// host time on a discrete GPU, and a training step records hundreds of small batches.
const PENDING_MAX: usize = 64;

/// One command of a [`Batch`], kept until the batch is submitted and then recorded into the
/// context's open encoder.
enum Command {
    Dispatch {
        pipeline: wgpu::ComputePipeline,
        bind_group: wgpu::BindGroup,
        /// The params block, padded to 16 bytes: written into the uniform arena when queued.
        uniform: Option<Vec<u8>>,
        groups: [u32; 3],
        /// The kernel's label while the kernel profile is on: the dispatch gets its own pass,
        /// timed.
        profiled: Option<String>,
    },
    Copy { src: wgpu::Buffer, src_offset: u64, dst: wgpu::Buffer, size: u64 },
    /// Zero the first `size` bytes of a recycled buffer.
    Clear { buffer: wgpu::Buffer, size: u64 },
}

impl Command {
    /// Record into the open encoder; `offset` is the dispatch's params block in the uniform
    /// arena. Consecutive dispatches share one compute pass (wgpu orders them inside it: a
    /// dispatch that reads what an earlier one wrote gets its barrier); a copy, a profiled
    /// dispatch (its own pass, timestamped at both ends) or a submission ends it.
    fn record(&self, ctx: &GpuContext, p: &mut Pending, offset: u32) {
        let Pending { encoder, pass, profile, .. } = p;
        let enc = encoder.get_or_insert_with(|| ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("queued") }));
        match self {
            Command::Dispatch { pipeline, bind_group, groups, profiled, uniform } => {
                let mut own;
                let pass = match (profiled, profile.as_mut()) {
                    (Some(label), Some(prof)) => {
                        *pass = None;
                        let i = prof.labels.len();
                        if i / PROFILE_SET == prof.sets.len() {
                            prof.sets.push(ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
                                label: Some("kernel profile"),
                                ty: wgpu::QueryType::Timestamp,
                                count: 2 * PROFILE_SET as u32,
                            }));
                        }
                        let j = (i % PROFILE_SET) as u32;
                        let timestamp_writes = Some(wgpu::ComputePassTimestampWrites {
                            query_set: &prof.sets[i / PROFILE_SET],
                            beginning_of_pass_write_index: Some(2 * j),
                            end_of_pass_write_index: Some(2 * j + 1),
                        });
                        own = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(label), timestamp_writes }).forget_lifetime();
                        prof.labels.push(label.clone());
                        &mut own
                    }
                    _ => pass.get_or_insert_with(|| {
                        enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("queued"), timestamp_writes: None }).forget_lifetime()
                    }),
                };
                pass.set_pipeline(pipeline);
                let offsets = [offset];
                pass.set_bind_group(0, bind_group, if uniform.is_some() { &offsets[..] } else { &[] });
                pass.dispatch_workgroups(groups[0], groups[1], groups[2]);
            }
            Command::Copy { src, src_offset, dst, size } => {
                *pass = None;
                enc.copy_buffer_to_buffer(src, *src_offset, dst, 0, *size)
            }
            Command::Clear { buffer, size } => {
                *pass = None;
                enc.clear_buffer(buffer, 0, Some(*size))
            }
        }
    }
}

/// Work submitted but not yet on the queue: one open command encoder that every submitted batch
/// records into (one command buffer per queue submission: making, finishing and submitting a
/// command buffer per batch was most of a launch's host time), and how many batches it holds.
///
/// The dispatches' params blocks go into one uniform buffer, the arena, bound with a dynamic
/// offset: `uniforms` holds what the open encoder's dispatches read from it, written with one
/// queue write just before the encoder is submitted (a write lands after the earlier
/// submissions' reads and before this one's), instead of a buffer made per launch.
#[derive(Default)]
struct Pending {
    /// The open compute pass of `encoder` (ended before anything else is recorded into it, and
    /// before it is finished).
    pass: Option<wgpu::ComputePass<'static>>,
    encoder: Option<wgpu::CommandEncoder>,
    batches: usize,
    uniforms: Vec<u8>,
    /// What the open encoder's copies into recycled upload buffers read from the upload arena,
    /// written with one queue write before the encoder is submitted, as `uniforms` is.
    uploads: Vec<u8>,
    /// The kernel profile, while it is on.
    profile: Option<Profile>,
}

/// Bytes of the uniform arena: 16384 params blocks at the usual 256-byte offset alignment.
const ARENA_BYTES: u64 = 4 << 20;

/// Bytes of the upload arena; an upload of more than a quarter of it gets a buffer of its own.
const UPLOAD_ARENA_BYTES: u64 = 16 << 20;

/// The largest params block a kernel may have (a uniform arena slot).
const MAX_UNIFORM_BYTES: usize = 256;

/// Host↔device traffic and synchronisation counted since the context was made: what a training
/// step costs beyond its kernels (each wait is a round trip to the device).
#[derive(Default)]
struct Counters {
    dispatches: AtomicU64,
    submits: AtomicU64,
    waits: AtomicU64,
    wait_ns: AtomicU64,
    reads: AtomicU64,
    read_bytes: AtomicU64,
    uploads: AtomicU64,
    upload_bytes: AtomicU64,
    /// Host time spent making buffers (outputs, uploads, readback staging), and how many.
    buffers: AtomicU64,
    buffer_ns: AtomicU64,
    /// Buffers taken from the pool instead of made.
    reused: AtomicU64,
    /// Host time spent making each launch's bind group (validation scope included).
    bind_ns: AtomicU64,
    /// Host time spent recording queued batches and submitting them.
    queue_ns: AtomicU64,
}

/// A snapshot of [`GpuContext::counters`]; `later.per(&earlier, steps)` gives the mean per step between them.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct GpuCounters {
    pub dispatches: f64,
    pub submits: f64,
    pub waits: f64,
    pub wait_seconds: f64,
    pub reads: f64,
    pub read_bytes: f64,
    pub uploads: f64,
    pub upload_bytes: f64,
    /// Buffers made, and the host's time making them (where a step's host time goes besides
    /// its waits: buffers, bind groups, recording and submitting).
    pub buffers: f64,
    pub buffer_seconds: f64,
    /// Buffers taken from the context's pool of freed ones instead (not counted in `buffers`).
    pub reused_buffers: f64,
    pub bind_group_seconds: f64,
    pub queue_seconds: f64,
}

impl GpuCounters {
    /// The mean per step of what happened between `earlier` and `self`.
    pub fn per(&self, earlier: &GpuCounters, steps: u64) -> GpuCounters {
        let n = steps.max(1) as f64;
        GpuCounters {
            dispatches: (self.dispatches - earlier.dispatches) / n,
            submits: (self.submits - earlier.submits) / n,
            waits: (self.waits - earlier.waits) / n,
            wait_seconds: (self.wait_seconds - earlier.wait_seconds) / n,
            reads: (self.reads - earlier.reads) / n,
            read_bytes: (self.read_bytes - earlier.read_bytes) / n,
            uploads: (self.uploads - earlier.uploads) / n,
            upload_bytes: (self.upload_bytes - earlier.upload_bytes) / n,
            buffers: (self.buffers - earlier.buffers) / n,
            buffer_seconds: (self.buffer_seconds - earlier.buffer_seconds) / n,
            reused_buffers: (self.reused_buffers - earlier.reused_buffers) / n,
            bind_group_seconds: (self.bind_group_seconds - earlier.bind_group_seconds) / n,
            queue_seconds: (self.queue_seconds - earlier.queue_seconds) / n,
        }
    }
}

/// Workgroup counts for `n` invocations of a 1-D kernel with workgroup size `wg`, spread over x
/// and y when x would exceed the 65535 limit.
pub fn groups_1d(n: usize, wg: u32) -> [u32; 3] {
    let groups = n.div_ceil(wg as usize).max(1);
    const MAX: usize = 65535;
    if groups <= MAX {
        [groups as u32, 1, 1]
    } else {
        let y = groups.div_ceil(MAX);
        let x = groups.div_ceil(y);
        [x as u32, y as u32, 1]
    }
}

impl GpuContext {
    /// Create a headless device. Chooses the best adapter (or the forced one), requests the
    /// adapter's own limits (lavapipe: 32 KiB workgroup memory) and timestamp queries if present.
    pub fn new(opts: &GpuOptions) -> Result<Self, BackendError> {
        let inst = instance(opts.validation);
        let adapters = enumerate(&inst);
        if adapters.is_empty() {
            return Err(BackendError::NoAdapter(NO_ADAPTER_HINT.into()));
        }
        let chosen = match &opts.adapter {
            Some(want) => {
                let by_index = want.parse::<usize>().ok().and_then(|i| adapters.get(i));
                let by_name = || adapters.iter().find(|a| a.get_info().name.to_lowercase().contains(&want.to_lowercase()));
                by_index.or_else(by_name).ok_or_else(|| {
                    let names: Vec<String> =
                        adapters.iter().enumerate().map(|(i, a)| format!("{i}: {}", a.get_info().name)).collect();
                    BackendError::NoAdapter(format!("no adapter matches {want:?}; available: {}", names.join(", ")))
                })?
            }
            None => {
                let best = &adapters[0];
                if is_software(&best.get_info()) && !opts.allow_software {
                    return Err(BackendError::NoAdapter(format!(
                        "only a software adapter ({}) is available; it is slower than the cpu backend",
                        best.get_info().name
                    )));
                }
                best
            }
        };
        let adapter = chosen.clone();
        let info = adapter.get_info();
        let limits = adapter.limits();
        let wanted = wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS;
        let features = adapter.features() & wanted;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("pii-bake"),
            required_features: features,
            required_limits: limits.clone(),
            memory_hints: wgpu::MemoryHints::Performance,
            ..Default::default()
        }))
        .map_err(|e| BackendError::Device(format!("{} ({:?}): {e}", info.name, info.backend)))?;
        // Errors are captured per operation with error scopes; anything that escapes is logged,
        // never a panic.
        device.on_uncaptured_error(Arc::new(|e| tracing::error!("uncaptured wgpu error: {e}")));
        tracing::debug!("wgpu adapter: {} ({:?}, {:?})", info.name, info.backend, info.device_type);
        let arena = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("uniform arena"),
            size: ARENA_BYTES,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let uniform_align = (limits.min_uniform_buffer_offset_alignment as usize).max(16);
        let upload_arena = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("upload arena"),
            size: UPLOAD_ARENA_BYTES,
            usage: wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Self {
            adapter,
            device,
            queue,
            info,
            limits,
            features,
            kernels: Mutex::new(HashMap::new()),
            counters: Counters::default(),
            pending: Mutex::new(Pending::default()),
            pool: Arc::default(),
            arena,
            uniform_align,
            upload_arena,
            profiling: std::sync::atomic::AtomicBool::new(false),
        })
    }

    pub fn is_software(&self) -> bool {
        is_software(&self.info)
    }

    pub fn supports_timestamps(&self) -> bool {
        self.features.contains(wgpu::Features::TIMESTAMP_QUERY)
    }

    /// Turn the kernel profile on or off. While it is on, every dispatch gets its own compute
    /// pass timestamped at both ends, and each queue submission waits for its timestamps and adds
    /// them to its kernel's total ([`GpuContext::kernel_times`]). That is a diagnosis, not the
    /// production path: passes no longer share a dispatch's neighbours and every submission
    /// waits, so the step is slower than unprofiled (the profile's own waits are not counted in
    /// [`GpuContext::counters`], though the time they take is gone from the next counted wait).
    /// An error where the adapter has no timestamp queries.
    pub fn set_kernel_profile(&self, on: bool) -> Result<(), BackendError> {
        if on && !self.supports_timestamps() {
            return Err(BackendError::Device(format!("{} has no timestamp queries: kernels cannot be profiled on it", self.info.name)));
        }
        let mut p = self.pending.lock().expect("pending batches poisoned");
        self.submit_locked(&mut p)?;
        if on {
            p.profile.get_or_insert_with(Profile::default);
        } else {
            p.profile = None;
        }
        self.profiling.store(on, Ordering::Relaxed);
        Ok(())
    }

    /// Every profiled kernel's launches and GPU time since the profile was turned on, by label
    /// (`family::entry`); empty while it is off. [`kernel_times_per`] makes a step's share.
    pub fn kernel_times(&self) -> Vec<KernelTime> {
        let p = self.pending.lock().expect("pending batches poisoned");
        let mut v: Vec<KernelTime> = p.profile.as_ref().map(|p| p.totals.values().cloned().collect()).unwrap_or_default();
        v.sort_by(|a, b| a.kernel.cmp(&b.kernel));
        v
    }

    /// Totals since the context was made (see [`GpuCounters::per`]).
    pub fn counters(&self) -> GpuCounters {
        let c = &self.counters;
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed) as f64;
        GpuCounters {
            dispatches: g(&c.dispatches),
            submits: g(&c.submits),
            waits: g(&c.waits),
            wait_seconds: g(&c.wait_ns) * 1e-9,
            reads: g(&c.reads),
            read_bytes: g(&c.read_bytes),
            uploads: g(&c.uploads),
            upload_bytes: g(&c.upload_bytes),
            buffers: g(&c.buffers),
            buffer_seconds: g(&c.buffer_ns) * 1e-9,
            reused_buffers: g(&c.reused),
            bind_group_seconds: g(&c.bind_ns) * 1e-9,
            queue_seconds: g(&c.queue_ns) * 1e-9,
        }
    }

    fn count(&self, which: &AtomicU64, by: u64) {
        which.fetch_add(by, Ordering::Relaxed);
    }

    /// Add the host time since `t` to a counter.
    fn count_since(&self, which: &AtomicU64, t: Instant) {
        self.count(which, t.elapsed().as_nanos() as u64);
    }

    /// A buffer made by `make`, counted with the host time it took ([`GpuCounters::buffers`]).
    fn counted_buffer(&self, make: impl FnOnce() -> wgpu::Buffer) -> wgpu::Buffer {
        let t = Instant::now();
        let b = make();
        self.count(&self.counters.buffers, 1);
        self.count_since(&self.counters.buffer_ns, t);
        b
    }

    /// A new (uninitialised) buffer, counted.
    fn new_buffer(&self, desc: &wgpu::BufferDescriptor) -> wgpu::Buffer {
        self.counted_buffer(|| self.device.create_buffer(desc))
    }

    // ---- buffers -------------------------------------------------------------------------

    fn storage_usage() -> wgpu::BufferUsages {
        wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST
    }

    /// Upload 4-byte elements (f32, u32, i32 or Pod structs of them) as a storage buffer. A
    /// recycled buffer ([`Pool`]) is filled by a copy from the upload arena recorded into the
    /// open encoder (the arena is written when the encoder is submitted, as the uniform arena is),
    /// so after every command recorded so far and without a submission of its own; a new buffer
    /// (none free of its class, or more than a quarter of the arena) is made with its contents.
    pub fn upload<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> GpuBuffer {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        // wgpu rejects zero-sized bindings: keep at least one element.
        let padded = [0u8; 4];
        let contents = if bytes.is_empty() { &padded[..] } else { bytes };
        let size = contents.len() as u64;
        self.count(&self.counters.uploads, 1);
        self.count(&self.counters.upload_bytes, size);
        let key = (size_class(size), false);
        let copied = (size <= UPLOAD_ARENA_BYTES / 4).then(|| self.upload_by_copy(key, contents)).flatten();
        let buffer = match copied {
            Some(buffer) => buffer,
            None => self.counted_buffer(|| {
                let b = self.device.create_buffer(&wgpu::BufferDescriptor { label: Some(label), size: key.0, usage: Self::storage_usage(), mapped_at_creation: true });
                b.slice(..size).get_mapped_range_mut().expect("a buffer mapped at creation").copy_from_slice(contents);
                b.unmap();
                b
            }),
        };
        let home = Some(Arc::new(Home { buffer: buffer.clone(), key, pool: Arc::downgrade(&self.pool) }));
        GpuBuffer { buffer, len: bytes.len() / 4, home }
    }

    /// A recycled buffer of class `key` filled with `contents` by a copy from the upload arena,
    /// or `None` where none is free or the open encoder's uploads fill the arena already.
    fn upload_by_copy(&self, key: (u64, bool), contents: &[u8]) -> Option<wgpu::Buffer> {
        let mut p = self.pending.lock().expect("pending batches poisoned");
        if (p.uploads.len() + contents.len()) as u64 > UPLOAD_ARENA_BYTES {
            return None;
        }
        let buffer = self.pool.lock().ok()?.take(key)?;
        self.count(&self.counters.reused, 1);
        let src_offset = p.uploads.len() as u64;
        p.uploads.extend_from_slice(contents);
        Command::Copy { src: self.upload_arena.clone(), src_offset, dst: buffer.clone(), size: contents.len() as u64 }.record(self, &mut p, 0);
        Some(buffer)
    }

    pub fn upload_f32(&self, label: &str, data: &[f32]) -> GpuBuffer {
        self.upload(label, data)
    }

    pub fn upload_u32(&self, label: &str, data: &[u32]) -> GpuBuffer {
        self.upload(label, data)
    }

    /// A zero-filled buffer of `len` 4-byte elements: a recycled one, zeroed by a fill recorded
    /// into the open encoder (so after every command recorded so far), or a new one.
    pub fn zeros_f32(&self, label: &str, len: usize) -> GpuBuffer {
        let want = (len.max(1) * 4) as u64;
        let (buffer, key, reused) = self.pooled(label, want, false);
        if reused {
            let mut p = self.pending.lock().expect("pending batches poisoned");
            Command::Clear { buffer: buffer.clone(), size: want }.record(self, &mut p, 0);
        }
        let home = Some(Arc::new(Home { buffer: buffer.clone(), key, pool: Arc::downgrade(&self.pool) }));
        GpuBuffer { buffer, len, home }
    }

    /// A buffer of at least `bytes` for storage (`staging` false) or readback (`staging` true),
    /// from the pool when one of its class is free there (its contents stale; the flag says so),
    /// else new; with its pool key.
    fn pooled(&self, label: &str, bytes: u64, staging: bool) -> (wgpu::Buffer, (u64, bool), bool) {
        let key = (size_class(bytes), staging);
        let reused = self.pool.lock().ok().and_then(|mut p| p.take(key));
        let was_reused = reused.is_some();
        let buffer = match reused {
            Some(b) => {
                self.count(&self.counters.reused, 1);
                b
            }
            None => {
                let usage = if staging { wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST } else { Self::storage_usage() };
                self.new_buffer(&wgpu::BufferDescriptor { label: Some(label), size: key.0, usage, mapped_at_creation: false })
            }
        };
        (buffer, key, was_reused)
    }

    /// Overwrite a buffer's contents from the host.
    pub fn write<T: bytemuck::Pod>(&self, dst: &GpuBuffer, data: &[T]) -> Result<(), BackendError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        if bytes.len() != dst.len * 4 {
            return Err(BackendError::Shape(format!(
                "write of {} bytes into a buffer of {} elements",
                bytes.len(),
                dst.len
            )));
        }
        if !bytes.is_empty() {
            // A queued write lands before the next submission's commands: submit the batches
            // recorded before it first.
            self.flush()?;
            self.count(&self.counters.uploads, 1);
            self.count(&self.counters.upload_bytes, bytes.len() as u64);
            self.queue.write_buffer(&dst.buffer, 0, bytes);
        }
        Ok(())
    }

    /// Record a submitted batch's commands into the open encoder; submitted with the others at
    /// the next read, write or wait (or once [`PENDING_MAX`] batches are queued).
    fn defer(&self, commands: &[Command]) -> Result<(), BackendError> {
        let t = Instant::now();
        let r = self.defer_uncounted(commands);
        self.count_since(&self.counters.queue_ns, t);
        r
    }

    /// [`GpuContext::defer`] without adding its time to the queue counter.
    fn defer_uncounted(&self, commands: &[Command]) -> Result<(), BackendError> {
        let slot = |c: &Command| match c {
            Command::Dispatch { uniform: Some(u), .. } => u.len().div_ceil(self.uniform_align) * self.uniform_align,
            _ => 0,
        };
        let need: usize = commands.iter().map(slot).sum();
        if need as u64 > ARENA_BYTES {
            return Err(BackendError::Shape(format!("a batch of {} launches needs more than the {ARENA_BYTES}-byte uniform arena", commands.len())));
        }
        let mut p = self.pending.lock().expect("pending batches poisoned");
        if (p.uniforms.len() + need) as u64 > ARENA_BYTES {
            self.submit_locked_uncounted(&mut p)?;
        }
        for c in commands {
            let offset = p.uniforms.len();
            if let Command::Dispatch { uniform: Some(u), .. } = c {
                p.uniforms.extend_from_slice(u);
                p.uniforms.resize(offset + slot(c), 0);
            }
            c.record(self, &mut p, offset as u32);
        }
        p.batches += 1;
        if p.batches >= PENDING_MAX {
            return self.submit_locked_uncounted(&mut p);
        }
        Ok(())
    }

    /// Submit every queued batch (one queue submission). Returns without waiting.
    pub fn flush(&self) -> Result<(), BackendError> {
        let mut p = self.pending.lock().expect("pending batches poisoned");
        self.submit_locked(&mut p)
    }

    /// Submit the open encoder (`pending` held locked, so batches reach the queue in the order
    /// they were recorded). A validation error in any recorded pass surfaces here, naming it.
    fn submit_locked(&self, pending: &mut Pending) -> Result<(), BackendError> {
        let t = Instant::now();
        let r = self.submit_locked_uncounted(pending);
        self.count_since(&self.counters.queue_ns, t);
        r
    }

    /// [`GpuContext::submit_locked`] without adding its time to the queue counter (for callers
    /// whose own time is counted already).
    fn submit_locked_uncounted(&self, pending: &mut Pending) -> Result<(), BackendError> {
        pending.batches = 0;
        pending.pass = None;
        let Some(mut enc) = pending.encoder.take() else {
            return Ok(());
        };
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        if !pending.uniforms.is_empty() {
            self.queue.write_buffer(&self.arena, 0, &pending.uniforms);
            pending.uniforms.clear();
        }
        if !pending.uploads.is_empty() {
            self.queue.write_buffer(&self.upload_arena, 0, &pending.uploads);
            pending.uploads.clear();
        }
        let timestamps = pending.profile.as_ref().filter(|p| !p.labels.is_empty()).map(|p| self.resolve_profile(&mut enc, p));
        self.count(&self.counters.submits, 1);
        self.queue.submit([enc.finish()]);
        if let Some(err) = pollster::block_on(scope.pop()) {
            if let Some(p) = pending.profile.as_mut() {
                p.labels.clear();
            }
            return Err(BackendError::Validation { label: "submission".into(), message: err.to_string() });
        }
        match (timestamps, pending.profile.as_mut()) {
            (Some(staging), Some(prof)) => self.add_profile(&staging, prof),
            _ => Ok(()),
        }
    }

    /// Record the resolution of the open encoder's profile timestamps into a readable buffer.
    fn resolve_profile(&self, enc: &mut wgpu::CommandEncoder, prof: &Profile) -> wgpu::Buffer {
        let set_bytes = (2 * PROFILE_SET * 8) as u64;
        let size = prof.labels.len().div_ceil(PROFILE_SET) as u64 * set_bytes;
        let make = |label, usage| self.device.create_buffer(&wgpu::BufferDescriptor { label: Some(label), size, usage, mapped_at_creation: false });
        let resolved = make("kernel profile", wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC);
        let staging = make("kernel profile readback", wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST);
        for (k, set) in prof.sets.iter().enumerate().take(prof.labels.len().div_ceil(PROFILE_SET)) {
            let used = (prof.labels.len() - k * PROFILE_SET).min(PROFILE_SET) as u32;
            enc.resolve_query_set(set, 0..2 * used, &resolved, k as u64 * set_bytes);
        }
        enc.copy_buffer_to_buffer(&resolved, 0, &staging, 0, size);
        staging
    }

    /// Wait for a submission's profile timestamps and add each dispatch's time to its kernel.
    fn add_profile(&self, staging: &wgpu::Buffer, prof: &mut Profile) -> Result<(), BackendError> {
        let (tx, rx) = std::sync::mpsc::channel();
        staging.slice(..).map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| BackendError::Device(format!("poll failed: {e}")))?;
        rx.recv().map_err(|e| BackendError::Map(e.to_string()))?.map_err(|e| BackendError::Map(e.to_string()))?;
        let period = self.queue.get_timestamp_period() as f64 * 1e-9;
        {
            let view = staging.slice(..).get_mapped_range().map_err(|e| BackendError::Map(e.to_string()))?;
            let ticks: &[u64] = bytemuck::cast_slice(&view);
            for (i, label) in prof.labels.drain(..).enumerate() {
                let (set, j) = (i / PROFILE_SET, i % PROFILE_SET);
                let (t0, t1) = (ticks[set * 2 * PROFILE_SET + 2 * j], ticks[set * 2 * PROFILE_SET + 2 * j + 1]);
                let k = prof.totals.entry(label).or_insert_with_key(|l| KernelTime { kernel: l.clone(), ..Default::default() });
                k.launches += 1.0;
                k.seconds += t1.saturating_sub(t0) as f64 * period;
            }
        }
        staging.unmap();
        Ok(())
    }

    /// Read a buffer back to the host (blocks until the GPU is done with it).
    pub fn read<T: bytemuck::Pod>(&self, src: &GpuBuffer) -> Result<Vec<T>, BackendError> {
        Ok(self.read_many(&[src])?.remove(0))
    }

    /// Read several buffers back with one submission and one wait (a round trip each saved).
    pub fn read_many<T: bytemuck::Pod>(&self, srcs: &[&GpuBuffer]) -> Result<Vec<Vec<T>>, BackendError> {
        let mut copies = Vec::with_capacity(srcs.len());
        let mut staged = Vec::with_capacity(srcs.len());
        for src in srcs {
            let size = (src.len * 4) as u64;
            if size == 0 {
                staged.push(None);
                continue;
            }
            // Back to the pool once this read has unmapped it.
            let (staging, key, _) = self.pooled("readback", size, true);
            copies.push(Command::Copy { src: src.buffer.clone(), src_offset: 0, dst: staging.clone(), size });
            self.count(&self.counters.reads, 1);
            self.count(&self.counters.read_bytes, size);
            staged.push(Some((staging, size, key)));
        }
        if staged.iter().all(Option::is_none) {
            return Ok(srcs.iter().map(|_| Vec::new()).collect());
        }
        // The copies go with the queued batches: one submission.
        {
            let mut p = self.pending.lock().expect("pending batches poisoned");
            copies.iter().for_each(|c| c.record(self, &mut p, 0));
            self.submit_locked(&mut p)?;
        }
        let (tx, rx) = std::sync::mpsc::channel();
        for (s, size, _) in staged.iter().flatten() {
            let tx = tx.clone();
            s.slice(..*size).map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send(r);
            });
        }
        drop(tx);
        self.wait_idle()?;
        for r in rx.iter() {
            r.map_err(|e| BackendError::Map(e.to_string()))?;
        }
        let mut out = Vec::with_capacity(srcs.len());
        for s in &staged {
            match s {
                None => out.push(Vec::new()),
                Some((staging, size, key)) => {
                    {
                        let view = staging.slice(..*size).get_mapped_range().map_err(|e| BackendError::Map(e.to_string()))?;
                        out.push(bytemuck::cast_slice::<u8, T>(&view).to_vec());
                    }
                    staging.unmap();
                    if let Ok(mut p) = self.pool.lock() {
                        p.put(*key, staging.clone());
                    }
                }
            }
        }
        Ok(out)
    }

    pub fn read_f32(&self, src: &GpuBuffer) -> Result<Vec<f32>, BackendError> {
        self.read(src)
    }

    pub fn read_u32(&self, src: &GpuBuffer) -> Result<Vec<u32>, BackendError> {
        self.read(src)
    }

    /// Block until every recorded batch has finished.
    pub fn wait_idle(&self) -> Result<(), BackendError> {
        self.flush()?;
        let t = Instant::now();
        let r = self
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| BackendError::Device(format!("poll failed: {e}")));
        self.count(&self.counters.waits, 1);
        self.count(&self.counters.wait_ns, t.elapsed().as_nanos() as u64);
        r
    }

    // ---- kernels -------------------------------------------------------------------------

    /// Compile (once, then cached by `label` + `entry`) a compute kernel from WGSL source.
    /// Shader errors come back as [`BackendError::Shader`], never a panic.
    pub fn kernel(&self, label: &str, source: &str, entry: &str, spec: &KernelSpec) -> Result<Arc<Kernel>, BackendError> {
        if let Some(k) = self.kernels.lock().expect("kernel cache poisoned").get(label).and_then(|m| m.get(entry)) {
            return Ok(k.clone());
        }
        let key = format!("{label}::{entry}");
        // Validate with naga first: a readable error with source spans instead of a device error.
        validate_wgsl(label, source)?;
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let mut entries = Vec::new();
        if spec.uniform {
            entries.push(wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: None,
                },
                count: None,
            });
        }
        for (i, access) in spec.storage.iter().enumerate() {
            entries.push(wgpu::BindGroupLayoutEntry {
                binding: i as u32 + 1,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: *access == Access::Read },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            });
        }
        let layout =
            self.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some(label), entries: &entries });
        let pl = self.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(label),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = self.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(&key),
            layout: Some(&pl),
            module: &module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(BackendError::Shader { label: key, message: err.to_string() });
        }
        let k = Arc::new(Kernel { label: key.clone(), pipeline, layout, spec: spec.clone() });
        self.kernels.lock().expect("kernel cache poisoned").entry(label.to_string()).or_default().insert(entry.to_string(), k.clone());
        Ok(k)
    }

    /// Start recording a batch of dispatches into one command buffer.
    pub fn batch(&self, label: &str) -> Batch<'_> {
        Batch { ctx: self, commands: Vec::new(), label: label.to_string(), keep: Vec::new() }
    }

    /// Record and submit one dispatch (see [`Batch::submit`]). Validation errors come back as errors.
    pub fn dispatch(
        &self,
        kernel: &Kernel,
        uniform: Option<&[u8]>,
        storage: &[Bind<'_>],
        groups: [u32; 3],
    ) -> Result<(), BackendError> {
        let mut b = self.batch(&kernel.label);
        b.dispatch(kernel, uniform, storage, groups)?;
        b.submit()
    }
}

/// A batch of dispatches (and copies) submitted together, in order.
pub struct Batch<'a> {
    ctx: &'a GpuContext,
    commands: Vec<Command>,
    label: String,
    /// The buffers the commands use, held until they are recorded: a buffer whose last handle
    /// drops goes back to the pool, and its next owner's zero fill must come after them.
    keep: Vec<GpuBuffer>,
}

impl Batch<'_> {
    /// Record one dispatch. Checks the bindings against the kernel's spec.
    pub fn dispatch(
        &mut self,
        kernel: &Kernel,
        uniform: Option<&[u8]>,
        storage: &[Bind<'_>],
        groups: [u32; 3],
    ) -> Result<(), BackendError> {
        let ctx = self.ctx;
        if uniform.is_some() != kernel.spec.uniform || storage.len() != kernel.spec.storage.len() {
            return Err(BackendError::Shape(format!(
                "{}: expected {} uniform and {} storage bindings, got {} and {}",
                kernel.label,
                kernel.spec.uniform as u8,
                kernel.spec.storage.len(),
                uniform.is_some() as u8,
                storage.len()
            )));
        }
        let max = ctx.limits.max_compute_workgroups_per_dimension;
        if groups.iter().any(|&g| g > max) {
            return Err(BackendError::Shape(format!("{}: workgroup count {groups:?} exceeds the limit {max}", kernel.label)));
        }
        // Uniform blocks are padded to 16 bytes; the bind group reads one from the arena at the
        // offset the batch gets when it is queued.
        let ubytes = uniform.map(|u| {
            let mut bytes = u.to_vec();
            bytes.resize(bytes.len().div_ceil(16).max(1) * 16, 0);
            bytes
        });
        if let Some(u) = ubytes.as_ref().filter(|u| u.len() > MAX_UNIFORM_BYTES) {
            return Err(BackendError::Shape(format!("{}: a {}-byte params block (at most {MAX_UNIFORM_BYTES})", kernel.label, u.len())));
        }
        let mut entries = Vec::new();
        if let Some(u) = &ubytes {
            let size = std::num::NonZeroU64::new(u.len() as u64);
            let binding = wgpu::BufferBinding { buffer: &ctx.arena, offset: 0, size };
            entries.push(wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::Buffer(binding) });
        }
        for (i, b) in storage.iter().enumerate() {
            let resource = match b {
                Bind::Buffer(g) => {
                    self.keep.push((*g).clone());
                    let size = std::num::NonZeroU64::new(g.bytes());
                    wgpu::BindingResource::Buffer(wgpu::BufferBinding { buffer: &g.buffer, offset: 0, size })
                }
                Bind::Raw(r) => r.as_entire_binding(),
            };
            entries.push(wgpu::BindGroupEntry { binding: i as u32 + 1, resource });
        }
        let t = Instant::now();
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&kernel.label),
            layout: &kernel.layout,
            entries: &entries,
        });
        let err = pollster::block_on(scope.pop());
        ctx.count_since(&ctx.counters.bind_ns, t);
        if let Some(err) = err {
            return Err(BackendError::Validation { label: kernel.label.clone(), message: err.to_string() });
        }
        self.commands.push(Command::Dispatch {
            pipeline: kernel.pipeline.clone(),
            bind_group: bg,
            uniform: ubytes,
            groups,
            profiled: ctx.profiling.load(Ordering::Relaxed).then(|| kernel.label.clone()),
        });
        ctx.count(&ctx.counters.dispatches, 1);
        Ok(())
    }

    /// Copy `src` into `dst` (same length) as part of the batch.
    pub fn copy(&mut self, src: &GpuBuffer, dst: &GpuBuffer) -> Result<(), BackendError> {
        if src.len != dst.len {
            return Err(BackendError::Shape(format!("copy of {} elements into {}", src.len, dst.len)));
        }
        if src.len > 0 {
            self.keep.extend([src.clone(), dst.clone()]);
            self.commands.push(Command::Copy { src: src.buffer.clone(), src_offset: 0, dst: dst.buffer.clone(), size: (src.len * 4) as u64 });
        }
        Ok(())
    }

    /// Queue the batch, without waiting: its commands are recorded into the context's open
    /// encoder, which is submitted, in the order batches were queued, at the next read, write
    /// or wait (or every [`PENDING_MAX`] batches), so a later dispatch, write or
    /// [`GpuContext::read`] sees its results, and wgpu keeps the buffers it uses alive until it
    /// is done. Waiting here cost a round trip to the device per kernel launch, and a command
    /// buffer per batch tens of µs of host time: most of what a small training batch spends on
    /// a discrete GPU.
    pub fn submit(self) -> Result<(), BackendError> {
        if self.commands.is_empty() {
            return Ok(());
        }
        tracing::trace!("queued batch {} ({} commands)", self.label, self.commands.len());
        self.ctx.defer(&self.commands)
    }
}

/// Parse and validate WGSL with naga (no device needed). Used at kernel creation and by the
/// CPU-only shader validation test.
pub fn validate_wgsl(label: &str, source: &str) -> Result<(), BackendError> {
    let module = naga::front::wgsl::parse_str(source)
        .map_err(|e| BackendError::Shader { label: label.into(), message: e.emit_to_string(source) })?;
    naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all())
        .validate(&module)
        .map_err(|e| BackendError::Shader { label: label.into(), message: e.emit_to_string(source) })?;
    Ok(())
}

/// WGSL sources. Each kernel family's file gets the shared library (`shaders/lib/`) prepended by
/// [`shaders::with_lib`]: the library is plain WGSL declarations, so there is no import syntax
/// and the resolver is this one concatenation.
pub mod shaders {
    pub const LIB: &str = concat!(
        include_str!("../../../shaders/lib/index.wgsl"),
        "\n",
        include_str!("../../../shaders/lib/math.wgsl"),
        "\n"
    );

    /// `source` with the shared library prepended.
    pub fn prepend_lib(source: &str) -> String {
        format!("{LIB}\n{source}")
    }

    /// A kernel family's source with the shared library prepended, made once per family (the
    /// launchers ask for it on every launch; [`super::GpuContext::kernel`] reads it only once).
    pub fn with_lib(family: &'static str) -> &'static str {
        static MADE: std::sync::Mutex<Vec<(usize, usize, &'static str)>> = std::sync::Mutex::new(Vec::new());
        let key = (family.as_ptr() as usize, family.len());
        let mut made = MADE.lock().expect("shader sources poisoned");
        if let Some(&(_, _, s)) = made.iter().find(|&&(p, n, _)| (p, n) == key) {
            return s;
        }
        let s: &'static str = Box::leak(prepend_lib(family).into_boxed_str());
        made.push((key.0, key.1, s));
        s
    }

    pub const UTIL: &str = include_str!("../../../shaders/util.wgsl");
}

/// Elementwise helpers (axpy) used by training; they also prove the launcher in tests.
pub mod util_kernels {
    use super::*;

    /// Mirrors `AxpyParams` in `shaders/util.wgsl`.
    #[repr(C)]
    #[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
    pub struct AxpyParams {
        pub n: u32,
        pub a: f32,
        pub _pad: [u32; 2],
    }
    const _: () = assert!(std::mem::size_of::<AxpyParams>() == 16);

    /// y ← a·x + y on the GPU.
    pub fn axpy(ctx: &GpuContext, a: f32, x: &GpuBuffer, y: &GpuBuffer) -> Result<(), BackendError> {
        if x.len != y.len {
            return Err(BackendError::Shape(format!("axpy: x has {} elements, y has {}", x.len, y.len)));
        }
        let src = shaders::with_lib(shaders::UTIL);
        let k = ctx.kernel("util", &src, "axpy", &KernelSpec::new(true, &[Access::Read, Access::ReadWrite]))?;
        let p = AxpyParams { n: x.len as u32, a, _pad: [0; 2] };
        ctx.dispatch(&k, Some(bytemuck::bytes_of(&p)), &[x.into(), y.into()], groups_1d(x.len, 256))
    }
}
