//! The optional wgpu compute path for scan likelihoods (feature `gpu`).
//!
//! [`GpuScorer`] implements [`Scorer`] like [`CpuScorer`] and is tested
//! against it (`tests/gpu.rs`). One call is one compute dispatch with one
//! invocation per (candidate, beam) running `shaders/likelihood.wgsl`: it
//! walks the beam (Amanatides–Woo, in cell units relative to the sensor's
//! cell), resolves each crossed cell for the candidate's particle from the
//! flattened DP-map (`flatten`) and the depth-first numbering, and writes
//! the beam likelihood. The host reads the per-beam values back once,
//! applies the floor and the log in f64 and sums them per candidate.
//!
//! **Precision** ([`GpuPrecision`]): where the adapter has `SHADER_F64` the
//! shader works in f64 throughout (its own f64 `exp`, since Vulkan has
//! none), and scores equal the CPU's to ~1e-12; that is what makes whole
//! runs reproduce the CPU's trajectory, because a resampling draw can turn
//! on a 1e-4 nat difference (docs/GPU.md). Elsewhere it works in f32 and
//! scores agree to ~2e-4 nats. Host values travel as (hi, lo) f32 pairs
//! (`flatten::split`) so both modes read the same buffers.
//!
//! Uploads per call: the candidates (144 B each), the beams of the subset
//! (64 B each) and 64 B of parameters. The map is mirrored on the host
//! (`mirror`) and only the bricks changed since the last call are
//! flattened and copied, when [`DpMap::version`] changes (once per filter
//! step, not once per culling pass); the numbering only when it changes.
//! Buffers only grow.
//!
//! **Large maps:** the entry array is split over up to [`ENTRY_CHUNKS`]
//! storage bindings and the cell headers over up to [`HEADER_CHUNKS`], each
//! of a power-of-two number of elements that fits one binding, so the
//! shader finds element `i` in chunk `i >> shift` at `i & mask`. Only a map
//! beyond all chunks together is refused.

pub(crate) mod flatten;
pub(crate) mod mirror;

use crate::ancestry::Numbering;
pub use crate::config::GpuPrecision;
use crate::dpmap::DpMap;
use crate::geometry::Pose;
use crate::laser_model::Trace;
use crate::scorer::{BeamSubset, Candidate, CpuScorer, ScoreContext, Scorer, Transfers};
use crate::{Error, Result};
use bytemuck::{Pod, Zeroable};
use mirror::{Delta, Mirror};
use std::ops::Range;
use std::sync::{Arc, Mutex};

const SHADER_BODY: &str = include_str!("../../shaders/likelihood.wgsl");
const PRELUDE_F32: &str = include_str!("../../shaders/real_f32.wgsl");
const PRELUDE_F64: &str = include_str!("../../shaders/real_f64.wgsl");
const WORKGROUP: u32 = 64;

/// Storage bindings the entry array may be split over (`entries0..3` in the
/// shader).
pub const ENTRY_CHUNKS: usize = 4;
/// Storage bindings the cell headers may be split over (`headers0..1`).
pub const HEADER_CHUNKS: usize = 2;
/// Storage buffers the shader binds: candidates, beams, brick table,
/// numbering, output, and the header and entry chunks.
const STORAGE_BINDINGS: u32 = 5 + (ENTRY_CHUNKS + HEADER_CHUNKS) as u32;
/// Shader binding numbers of the header and entry chunks.
const HEADER_BINDINGS: [u32; HEADER_CHUNKS] = [4, 8];
const ENTRY_BINDINGS: [u32; ENTRY_CHUNKS] = [5, 9, 10, 11];
/// The smallest binding limit [`GpuOptions::max_binding`] accepts, bytes.
pub const MIN_MAX_BINDING: u64 = 256;

/// How to open a [`GpuScorer`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GpuOptions {
    /// Shader arithmetic.
    pub precision: GpuPrecision,
    /// Caps the size of each storage binding holding the map (entry and
    /// header chunks, brick table), bytes, below the adapter's own limit;
    /// at least [`MIN_MAX_BINDING`]. For tests of maps split over several
    /// bindings; `None`: the adapter's limit.
    pub max_binding: Option<u64>,
}

impl GpuOptions {
    /// The options of the configuration's `[gpu]` section.
    pub fn from_config(gpu: &crate::config::GpuConfig) -> Self {
        Self {
            precision: gpu.precision,
            max_binding: (gpu.max_binding > 0).then_some(gpu.max_binding),
        }
    }
}

/// The shader source for `precision` (`F32` or `F64`): a prelude that
/// defines the scalar type, then the shared body.
fn shader_source(precision: GpuPrecision) -> String {
    let prelude = match precision {
        GpuPrecision::F64 => PRELUDE_F64,
        _ => PRELUDE_F32,
    };
    format!("{prelude}\n{SHADER_BODY}")
}

/// Shader parameters (`Params` in the WGSL); `[f32; 2]` are (hi, lo) pairs.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    n_cand: u32,
    n_beams: u32,
    brick_bits: u32,
    table_mask: u32,
    dim: u32,
    entry_shift: u32,
    header_shift: u32,
    _pad: u32,
    two_var: [f32; 2],
    max_error: [f32; 2],
    prior: [f32; 2],
    _pad2: [f32; 2],
}

/// One candidate (`Cand` in the WGSL); each `[[f32; 4]; 2]` is (hi, lo).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuCand {
    cell: [i32; 4],
    frac: [[f32; 4]; 2],
    rot: [[[f32; 4]; 2]; 3],
}

/// One beam (`Beam` in the WGSL); each `[[f32; 4]; 2]` is (hi, lo).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuBeam {
    dir: [[f32; 4]; 2],
    span: [[f32; 4]; 2],
}

/// Splits each component of `v` into the (hi, lo) halves of `flatten::split`.
fn split4(v: [f64; 4]) -> [[f32; 4]; 2] {
    let mut out = [[0.0f32; 4]; 2];
    for (i, x) in v.into_iter().enumerate() {
        let [hi, lo] = flatten::split(x);
        out[0][i] = hi;
        out[1][i] = lo;
    }
    out
}

/// A device buffer that only grows.
struct GrowBuffer {
    buf: wgpu::Buffer,
    usage: wgpu::BufferUsages,
    label: &'static str,
}

impl GrowBuffer {
    fn new(device: &wgpu::Device, label: &'static str, usage: wgpu::BufferUsages) -> Self {
        Self {
            buf: Self::alloc(device, label, usage, 256),
            usage,
            label,
        }
    }

    fn alloc(
        device: &wgpu::Device,
        label: &'static str,
        usage: wgpu::BufferUsages,
        size: u64,
    ) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    }

    /// Makes room for `size` bytes (doubling); returns whether the buffer
    /// was replaced, which drops its contents.
    fn reserve(&mut self, device: &wgpu::Device, size: u64) -> bool {
        if size <= self.buf.size() {
            return false;
        }
        let cap = size.next_power_of_two().max(256);
        self.buf = Self::alloc(device, self.label, self.usage, cap);
        true
    }

    fn upload(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, bytes: &[u8]) {
        self.reserve(device, bytes.len() as u64);
        queue.write_buffer(&self.buf, 0, bytes);
    }
}

/// A device array of 4-byte words split over up to `chunks.len()` storage
/// buffers of `2^shift` elements (`elem` bytes each), so that the shader
/// finds element `i` in chunk `i >> shift` at `i & (2^shift − 1)`. Unused
/// chunks keep a tiny buffer, so every binding always has one.
struct Chunked {
    chunks: Vec<GrowBuffer>,
    shift: u32,
    elem: u64,
    what: &'static str,
    /// Chunks holding elements.
    used: usize,
}

impl Chunked {
    /// Chunks of the largest power of two of elements within `max_binding`
    /// bytes, and small enough that every element has a u32 index.
    fn new(
        device: &wgpu::Device,
        what: &'static str,
        chunks: usize,
        elem: u64,
        max_binding: u64,
    ) -> Self {
        let per = (max_binding / elem).max(1);
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        Self {
            chunks: (0..chunks)
                .map(|_| GrowBuffer::new(device, what, usage))
                .collect(),
            shift: per
                .ilog2()
                .min(32 - chunks.next_power_of_two().ilog2())
                .min(31),
            elem,
            what,
            used: 0,
        }
    }

    fn per_chunk(&self) -> usize {
        1 << self.shift
    }

    /// Brings the device copy of a `len`-element host array up to date:
    /// writes `dirty` (sorted, disjoint element ranges), or everything when
    /// `full`. A chunk that must grow is replaced and written whole. `words`
    /// appends the host words of an element range to its vector. Returns the
    /// bytes written; an error, before writing anything, when all chunks
    /// together cannot hold `len` elements.
    fn sync(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        len: usize,
        full: bool,
        dirty: &[Range<usize>],
        words: &mut dyn FnMut(Range<usize>, &mut Vec<u32>),
    ) -> Result<u64> {
        let per = self.per_chunk();
        let need = len.div_ceil(per);
        if need > self.chunks.len() {
            let chunk = per as u64 * self.elem;
            return Err(Error::Gpu(format!(
                "{} of the map: {} ({len} × {} B), more than the {} bindings of {} that this \
                 adapter allows hold ({}): use --backend cpu for maps this large",
                self.what,
                size(len as u64 * self.elem),
                self.elem,
                self.chunks.len(),
                size(chunk),
                size(chunk * self.chunks.len() as u64)
            )));
        }
        let mut scratch = Vec::new();
        let mut written = 0u64;
        for (c, buf) in self.chunks.iter_mut().enumerate().take(need) {
            let span = c * per..((c + 1) * per).min(len);
            let grew = buf.reserve(device, span.len() as u64 * self.elem);
            let whole = [span.clone()];
            let ranges = if full || grew { &whole[..] } else { dirty };
            for r in ranges {
                let r = r.start.max(span.start)..r.end.min(span.end);
                if r.is_empty() {
                    continue;
                }
                scratch.clear();
                words(r.clone(), &mut scratch);
                let bytes = bytemuck::cast_slice::<u32, u8>(&scratch);
                queue.write_buffer(&buf.buf, (r.start - span.start) as u64 * self.elem, bytes);
                written += bytes.len() as u64;
            }
        }
        self.used = need;
        Ok(written)
    }
}

/// What a map sync did.
#[derive(Debug, Clone, Copy, Default)]
struct MapSync {
    map_bytes: u64,
    numbering_bytes: u64,
    rebuilt: bool,
}

/// Device state behind the scorer's lock.
struct State {
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    max_binding: u64,
    max_groups: u32,
    params: wgpu::Buffer,
    cands: GrowBuffer,
    beams: GrowBuffer,
    table: Chunked,
    headers: Chunked,
    entries: Chunked,
    numbering: GrowBuffer,
    out: GrowBuffer,
    staging: GrowBuffer,
    precision: GpuPrecision,
    /// The host copy of the map the device holds.
    mirror: Mirror,
    numbering_copy: Option<Numbering>,
    totals: Transfers,
    /// Validation or device errors reported asynchronously by wgpu.
    errors: Arc<Mutex<Option<String>>>,
    /// Scratch space for the host-side structs.
    scratch_cands: Vec<GpuCand>,
    scratch_beams: Vec<GpuBeam>,
}

/// Statistics of the last call, for benchmarks and logs.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CallStats {
    /// Bytes written to the device by the call: map, numbering, candidates,
    /// beams and parameters.
    pub upload_bytes: u64,
    /// Of `upload_bytes`, the map's (table, headers, entries): 0 when the
    /// device copy was current, the changed bricks after a map edit.
    pub map_bytes: u64,
    /// The map's size on the device without room to grow or garbage: what
    /// uploading all of it would cost (bytes).
    pub map_packed_bytes: u64,
    /// Bytes read back.
    pub readback_bytes: u64,
    /// Whether any of the map was uploaded.
    pub map_uploaded: bool,
    /// Whether the map's layout was rebuilt and uploaded whole (first call,
    /// another map, too much garbage).
    pub map_rebuilt: bool,
    /// Storage bindings holding the map's entries (at most [`ENTRY_CHUNKS`]).
    pub entry_chunks: u32,
    /// Storage bindings holding the map's cell headers (at most [`HEADER_CHUNKS`]).
    pub header_chunks: u32,
    /// Compute dispatches.
    pub dispatches: u32,
}

/// Scores candidates on a GPU through wgpu (Vulkan), for `D` = 2 or 3.
///
/// Agrees with [`CpuScorer`] to ~1e-12 in f64 mode and ~2e-4 nats in f32
/// mode (see [`GpuPrecision`]; the per-candidate sum is f64 in both).
/// Through the [`Scorer`] trait a failing device falls back to the CPU for
/// that call and says so once on stderr; [`GpuScorer::try_score`] reports
/// the error instead.
pub struct GpuScorer<const D: usize> {
    state: Mutex<State>,
    fallback: CpuScorer<D>,
    adapter: String,
    /// The first device error, after which calls fell back to the CPU.
    failure: std::sync::Mutex<Option<String>>,
    last: Mutex<CallStats>,
}

fn bind(i: u32, b: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding: i,
        resource: b.as_entire_binding(),
    }
}

/// A byte count for messages: MiB from 1 MiB on, else KiB.
fn size(bytes: u64) -> String {
    if bytes >= 1 << 20 {
        format!("{:.1} MiB", bytes as f64 / 1048576.0)
    } else {
        format!("{:.1} KiB", bytes as f64 / 1024.0)
    }
}

fn gpu_err(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Gpu(format!("{what}: {e}"))
}

impl<const D: usize> GpuScorer<D> {
    /// A scorer on the first Vulkan adapter with the default options
    /// (precision `auto`, the adapter's binding limit); wgpu's
    /// `WGPU_BACKEND` (e.g. `gl`) overrides the backends searched and
    /// `WGPU_ADAPTER_NAME` picks an adapter.
    pub fn new() -> Result<Self> {
        Self::with_options(GpuOptions::default())
    }

    /// A scorer on the first Vulkan adapter (as [`GpuScorer::new`]) with the
    /// given precision.
    pub fn with_precision(precision: GpuPrecision) -> Result<Self> {
        Self::with_options(GpuOptions {
            precision,
            max_binding: None,
        })
    }

    /// A scorer on the first Vulkan adapter (as [`GpuScorer::new`]) with
    /// the given options.
    pub fn with_options(options: GpuOptions) -> Result<Self> {
        Self::open(wgpu::Backends::VULKAN.with_env(), options)
    }

    /// A scorer on the first adapter of `backends` (this build compiles in
    /// Vulkan only, so any other choice finds no adapter).
    pub fn with_backends(backends: wgpu::Backends) -> Result<Self> {
        Self::open(backends, GpuOptions::default())
    }

    fn open(backends: wgpu::Backends, options: GpuOptions) -> Result<Self> {
        let precision = options.precision;
        if !(D == 2 || D == 3) {
            return Err(Error::Gpu(format!(
                "the GPU scorer supports 2-D and 3-D maps, not {D}-D"
            )));
        }
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = backends;
        let instance = wgpu::Instance::new(desc);
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| {
            Error::Gpu(format!(
                "no Vulkan adapter found ({e}): install mesa-vulkan-drivers (software Vulkan) \
                 or a GPU driver, or run with --backend cpu"
            ))
        })?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        if limits.max_storage_buffers_per_shader_stage < STORAGE_BINDINGS {
            return Err(Error::Gpu(format!(
                "the adapter {} binds at most {} storage buffers per shader stage; the \
                 likelihood shader needs {STORAGE_BINDINGS}: run with --backend cpu",
                info.name, limits.max_storage_buffers_per_shader_stage
            )));
        }
        let max_binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let map_binding = match options.max_binding {
            Some(b) if b < MIN_MAX_BINDING => {
                return Err(Error::Gpu(format!(
                    "a map binding limit of {b} B is below the smallest allowed, \
                     {MIN_MAX_BINDING} B"
                )));
            }
            Some(b) => b.min(max_binding),
            None => max_binding,
        };
        let has_f64 = adapter.features().contains(wgpu::Features::SHADER_F64);
        let precision = match precision {
            GpuPrecision::Auto if has_f64 => GpuPrecision::F64,
            GpuPrecision::Auto => GpuPrecision::F32,
            GpuPrecision::F64 if !has_f64 => {
                return Err(Error::Gpu(format!(
                    "the adapter {} has no f64 shader support: use DPSLAM_GPU_PRECISION=f32 \
                     (or auto)",
                    info.name
                )));
            }
            p => p,
        };
        let required_features = if precision == GpuPrecision::F64 {
            wgpu::Features::SHADER_F64
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("dpslam"),
            required_features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| gpu_err("cannot open the GPU device", e))?;
        let errors: Arc<Mutex<Option<String>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let mut slot = sink.lock().unwrap_or_else(|p| p.into_inner());
            slot.get_or_insert_with(|| e.to_string());
        }));
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("likelihood.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shader_source(precision).into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("likelihood"),
            layout: None,
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_err("the likelihood shader does not compile", e));
        }
        let layout = pipeline.get_bind_group_layout(0);
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let params = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("params"),
            size: std::mem::size_of::<Params>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let entry_bytes = if precision == GpuPrecision::F64 {
            16
        } else {
            8
        };
        let state = State {
            cands: GrowBuffer::new(&device, "candidates", storage),
            beams: GrowBuffer::new(&device, "beams", storage),
            table: Chunked::new(&device, "the brick table", 1, 16, map_binding),
            headers: Chunked::new(&device, "the cell headers", HEADER_CHUNKS, 4, map_binding),
            entries: Chunked::new(
                &device,
                "the entries",
                ENTRY_CHUNKS,
                entry_bytes,
                map_binding,
            ),
            numbering: GrowBuffer::new(&device, "numbering", storage),
            out: GrowBuffer::new(
                &device,
                "beam log-likelihoods",
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            ),
            staging: GrowBuffer::new(
                &device,
                "readback",
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ),
            params,
            max_binding,
            max_groups: limits.max_compute_workgroups_per_dimension,
            device,
            queue,
            pipeline,
            layout,
            precision,
            mirror: Mirror::default(),
            numbering_copy: None,
            totals: Transfers::default(),
            errors,
            scratch_cands: Vec::new(),
            scratch_beams: Vec::new(),
        };
        Ok(Self {
            state: Mutex::new(state),
            fallback: CpuScorer::new(),
            adapter: format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type),
            failure: std::sync::Mutex::new(None),
            last: Mutex::default(),
        })
    }

    /// The adapter in use, e.g. "llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan, Cpu)".
    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    /// The precision the shader runs in: `F32` or `F64`, never `Auto`.
    pub fn precision(&self) -> GpuPrecision {
        self.state
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .precision
    }

    /// Transfers and dispatches of the last successful call.
    pub fn last_call(&self) -> CallStats {
        *self.last.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Device traffic of all successful calls so far.
    pub fn totals(&self) -> Transfers {
        let st = self.state.lock().unwrap_or_else(|p| p.into_inner());
        let m = st.mirror.stats();
        Transfers {
            map_bricks_rewritten: m.bricks_rewritten,
            map_bricks_moved: m.bricks_moved,
            ..st.totals
        }
    }

    /// Forgets the uploaded map, so that the next call rebuilds and uploads
    /// all of it (after a device error, or to time a first call).
    pub fn invalidate(&self) {
        self.state
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .mirror
            .reset();
    }

    /// As [`Scorer::score`], but a device failure is an error instead of a
    /// fallback to the CPU.
    pub fn try_score<P: Pose<D>>(
        &self,
        ctx: &ScoreContext<'_, D, P>,
        candidates: &[Candidate<P>],
        subset: BeamSubset,
        trace: Trace,
    ) -> Result<Vec<f64>> {
        let mut st = self.state.lock().unwrap_or_else(|p| p.into_inner());
        let (sums, stats) = st.score(ctx, candidates, subset, trace)?;
        *self.last.lock().unwrap_or_else(|p| p.into_inner()) = stats;
        Ok(sums)
    }
}

impl State {
    fn check_errors(&self) -> Result<()> {
        match self.errors.lock().unwrap_or_else(|p| p.into_inner()).take() {
            Some(e) => Err(Error::Gpu(e)),
            None => Ok(()),
        }
    }

    fn fits(&self, what: &str, bytes: usize) -> Result<()> {
        if bytes as u64 > self.max_binding {
            return Err(Error::Gpu(format!(
                "the {what} need {}, more than this adapter binds at once ({}): \
                 use --backend cpu for maps this large",
                size(bytes as u64),
                size(self.max_binding)
            )));
        }
        Ok(())
    }

    /// Uploads what changed of the map and the numbering.
    fn sync_map<const D: usize>(
        &mut self,
        map: &DpMap<D>,
        numbering: &Numbering,
    ) -> Result<MapSync> {
        let delta = self.mirror.sync(map);
        let map_bytes = match self.upload_map(&delta) {
            Ok(b) => b,
            Err(e) => {
                // The device copy is not what the mirror says: start afresh.
                self.mirror.reset();
                return Err(e);
            }
        };
        let mut numbering_bytes = 0u64;
        let stale = self
            .numbering_copy
            .as_ref()
            .is_none_or(|n| n.enter != numbering.enter || n.exit != numbering.exit);
        if stale {
            let flat: Vec<[u32; 2]> = numbering
                .enter
                .iter()
                .zip(&numbering.exit)
                .map(|(&a, &b)| [a, b])
                .chain(std::iter::once([u32::MAX, 0]))
                .collect();
            let b = bytemuck::cast_slice::<_, u8>(&flat);
            self.fits("ancestry numbering", b.len())?;
            self.numbering.upload(&self.device, &self.queue, b);
            numbering_bytes = b.len() as u64;
            self.numbering_copy = Some(numbering.clone());
        }
        Ok(MapSync {
            map_bytes,
            numbering_bytes,
            rebuilt: delta.full,
        })
    }

    /// Copies the mirror's changes (`delta`) to the device; returns the bytes written.
    fn upload_map(&mut self, delta: &Delta) -> Result<u64> {
        if delta.is_empty() {
            return Ok(0);
        }
        let flat = self.mirror.flat();
        let wide = self.precision == GpuPrecision::F64;
        let (device, queue) = (&self.device, &self.queue);
        let full = delta.full;
        Ok(self.table.sync(
            device,
            queue,
            flat.table.len(),
            full,
            &delta.table,
            &mut |r, out| out.extend_from_slice(bytemuck::cast_slice(&flat.table[r])),
        )? + self.headers.sync(
            device,
            queue,
            flat.headers.len(),
            full,
            &delta.headers,
            &mut |r, out| out.extend_from_slice(&flat.headers[r]),
        )? + self.entries.sync(
            device,
            queue,
            flat.entries.len(),
            full,
            &delta.entries,
            &mut |r, out| flatten::entry_words(&flat.entries[r], wide, out),
        )?)
    }

    fn score<const D: usize, P: Pose<D>>(
        &mut self,
        ctx: &ScoreContext<'_, D, P>,
        candidates: &[Candidate<P>],
        subset: BeamSubset,
        trace: Trace,
    ) -> Result<(Vec<f64>, CallStats)> {
        self.check_errors()?;
        let laser = ctx.laser;
        let cell = laser.cell;
        let beams: Vec<_> = subset.select(&ctx.scan.beams).collect();
        if candidates.is_empty() || beams.is_empty() {
            return Ok((vec![0.0; candidates.len()], CallStats::default()));
        }
        let sync = self.sync_map(ctx.map, ctx.numbering)?;

        // Trace spans exactly as `beam_log_likelihood` chooses them, in f64.
        let mut gb = std::mem::take(&mut self.scratch_beams);
        gb.clear();
        gb.extend(beams.iter().map(|b| {
            let span = match (trace, b.no_return) {
                (Trace::Quick, true) => None,
                (Trace::Quick, false) => Some((
                    (b.range - laser.quick_before).max(0.0),
                    b.range + laser.quick_after,
                )),
                (Trace::Full, true) => Some((0.0, laser.max_range)),
                (Trace::Full, false) => Some((
                    0.0,
                    (b.range + laser.trace_past).min(laser.max_range.max(b.range)),
                )),
            };
            let mut dir = [0.0f64; 4];
            dir[..D].copy_from_slice(&b.dir);
            dir[3] = b.range / cell;
            // The flags travel in `hi` only; their `lo` halves are 0.
            let span = match span {
                Some((t0, t1)) => [t0 / cell, t1 / cell, b.no_return as u8 as f64, 0.0],
                None => [0.0, 0.0, 1.0, 1.0],
            };
            GpuBeam {
                dir: split4(dir),
                span: split4(span),
            }
        }));

        let mut gc = std::mem::take(&mut self.scratch_cands);
        gc.clear();
        for c in candidates {
            let sensor = c.pose.compose(&ctx.scan.sensor);
            let origin = sensor.translation();
            let mut cellk = [0i32; 4];
            let mut frac = [0.0f64; 4];
            for i in 0..D {
                let o = origin[i] / cell;
                let k = o.floor();
                cellk[i] = k as i32;
                frac[i] = o - k;
            }
            let leaf =
                *ctx.numbering.enter.get(c.node as usize).ok_or_else(|| {
                    Error::Gpu(format!("candidate node {} is not numbered", c.node))
                })?;
            cellk[3] = leaf as i32;
            let mut rot = [[0.0f64; 4]; 3];
            rot[2][2] = 1.0;
            for col in 0..D {
                let mut e = [0.0f64; D];
                e[col] = 1.0;
                let v = sensor.rotate(e);
                for (row, r) in rot.iter_mut().enumerate().take(D) {
                    r[col] = v[row];
                }
            }
            gc.push(GpuCand {
                cell: cellk,
                frac: split4(frac),
                rot: rot.map(split4),
            });
        }

        let n_cand = candidates.len() as u32;
        let n_beams = gb.len() as u32;
        let total = n_cand as u64 * n_beams as u64;
        let wide = self.precision == GpuPrecision::F64;
        let out_bytes = total * if wide { 8 } else { 4 };
        if total > u32::MAX as u64 || out_bytes > self.max_binding {
            return Err(Error::Gpu(format!(
                "{n_cand} candidates × {n_beams} beams is too much for one call: split the candidates"
            )));
        }
        let flat = self.mirror.flat();
        let params = Params {
            n_cand,
            n_beams,
            brick_bits: flat.brick_bits,
            table_mask: flat.table_mask(),
            dim: D as u32,
            entry_shift: self.entries.shift,
            header_shift: self.headers.shift,
            _pad: 0,
            two_var: flatten::split(2.0 * laser.variance / (cell * cell)),
            max_error: flatten::split(laser.max_error / cell),
            prior: flatten::split(laser.prior_density * cell),
            _pad2: [0.0; 2],
        };
        self.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let cb = bytemuck::cast_slice::<_, u8>(&gc);
        let bb = bytemuck::cast_slice::<_, u8>(&gb);
        let upload = sync.map_bytes
            + sync.numbering_bytes
            + (cb.len() + bb.len() + std::mem::size_of::<Params>()) as u64;
        self.cands.upload(&self.device, &self.queue, cb);
        self.beams.upload(&self.device, &self.queue, bb);
        self.scratch_cands = gc;
        self.scratch_beams = gb;
        self.out.reserve(&self.device, out_bytes);
        self.staging.reserve(&self.device, out_bytes);

        let mut entries = vec![
            bind(0, &self.params),
            bind(1, &self.cands.buf),
            bind(2, &self.beams.buf),
            bind(3, &self.table.chunks[0].buf),
            bind(6, &self.numbering.buf),
            bind(7, &self.out.buf),
        ];
        for (c, at) in [
            (&self.headers, &HEADER_BINDINGS[..]),
            (&self.entries, &ENTRY_BINDINGS[..]),
        ] {
            entries.extend(at.iter().zip(&c.chunks).map(|(&i, b)| bind(i, &b.buf)));
        }
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("likelihood"),
            layout: &self.layout,
            entries: &entries,
        });
        let groups = total.div_ceil(WORKGROUP as u64) as u32;
        let gx = groups.min(self.max_groups.max(1));
        let gy = groups.div_ceil(gx);
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        enc.copy_buffer_to_buffer(&self.out.buf, 0, &self.staging.buf, 0, out_bytes);
        let index = self.queue.submit([enc.finish()]);

        let slice = self.staging.buf.slice(..out_bytes);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
            .map_err(|e| gpu_err("waiting for the GPU", e))?;
        rx.recv()
            .map_err(|e| gpu_err("reading back", e))?
            .map_err(|e| gpu_err("reading back", e))?;
        let floor = laser.floor;
        let sums = {
            let view = slice
                .get_mapped_range()
                .map_err(|e| gpu_err("reading back", e))?;
            let vals: Vec<f64> = if wide {
                bytemuck::try_cast_slice::<_, f64>(&view)
                    .map_err(|e| gpu_err("reading back", e))?
                    .to_vec()
            } else {
                bytemuck::try_cast_slice::<_, f32>(&view)
                    .map_err(|e| gpu_err("reading back", e))?
                    .iter()
                    .map(|&l| l as f64)
                    .collect()
            };
            vals.chunks_exact(n_beams as usize)
                .map(|c| c.iter().map(|&l| l.max(floor).ln()).sum())
                .collect()
        };
        self.staging.buf.unmap();
        self.check_errors()?;
        let stats = CallStats {
            upload_bytes: upload,
            map_bytes: sync.map_bytes,
            map_packed_bytes: self.mirror.flat().packed_bytes(self.entries.elem as usize),
            readback_bytes: out_bytes,
            map_uploaded: sync.map_bytes > 0,
            map_rebuilt: sync.rebuilt,
            entry_chunks: self.entries.used as u32,
            header_chunks: self.headers.used as u32,
            dispatches: 1,
        };
        let t = &mut self.totals;
        t.calls += 1;
        if stats.map_uploaded {
            t.map_syncs += 1;
            t.map_rebuilds += stats.map_rebuilt as u64;
            t.map_bytes += stats.map_bytes;
            t.map_packed_bytes += stats.map_packed_bytes;
        }
        t.other_upload_bytes += stats.upload_bytes - stats.map_bytes;
        t.readback_bytes += stats.readback_bytes;
        Ok((sums, stats))
    }
}

impl<const D: usize, P: Pose<D>> Scorer<D, P> for GpuScorer<D> {
    fn name(&self) -> &'static str {
        "gpu"
    }

    fn transfers(&self) -> Option<Transfers> {
        Some(self.totals())
    }

    fn warnings(&self) -> Vec<String> {
        let failure = self.failure.lock().unwrap_or_else(|p| p.into_inner());
        failure.iter().cloned().collect()
    }

    fn score(
        &self,
        ctx: &ScoreContext<'_, D, P>,
        candidates: &[Candidate<P>],
        subset: BeamSubset,
        trace: Trace,
    ) -> Vec<f64> {
        match self.try_score(ctx, candidates, subset, trace) {
            Ok(v) => v,
            Err(e) => {
                self.failure
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .get_or_insert_with(|| format!("{e}; scored on the CPU from then on"));
                // The device may be in any state now: rebuild the map next time.
                self.invalidate();
                self.fallback.score(ctx, candidates, subset, trace)
            }
        }
    }
}
