//! The optional wgpu compute path for scan likelihoods (feature `gpu`).
//!
//! [`GpuScorer`] implements [`Scorer`] like [`CpuScorer`] and is tested
//! against it (`tests/gpu.rs`). One call is one compute dispatch with one
//! invocation per (candidate, beam) running `shaders/likelihood.wgsl`: it
//! walks the beam (Amanatides–Woo, in cell units relative to the sensor's
//! cell), resolves each crossed cell for the candidate's particle from the
//! flattened DP-map ([`flatten`]) and the depth-first numbering, and writes
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
//! (64 B each) and 64 B of parameters. The map is flattened and uploaded
//! only when [`DpMap::version`] changes (once per filter step, not once per
//! culling pass); the numbering only when it changes. Buffers only grow.

pub(crate) mod flatten;

use crate::ancestry::Numbering;
pub use crate::backend::GpuPrecision;
use crate::dpmap::DpMap;
use crate::geometry::Pose;
use crate::laser_model::Trace;
use crate::scorer::{BeamSubset, Candidate, CpuScorer, ScoreContext, Scorer};
use crate::{Error, Result};
use bytemuck::{Pod, Zeroable};
use flatten::FlatMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

const SHADER_BODY: &str = include_str!("../../shaders/likelihood.wgsl");
const PRELUDE_F32: &str = include_str!("../../shaders/real_f32.wgsl");
const PRELUDE_F64: &str = include_str!("../../shaders/real_f64.wgsl");
const WORKGROUP: u32 = 64;

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
    _pad: [u32; 3],
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

    /// Makes room for `size` bytes (doubling), dropping the old contents.
    fn reserve(&mut self, device: &wgpu::Device, size: u64) {
        if size > self.buf.size() {
            let cap = size.next_power_of_two().max(256);
            self.buf = Self::alloc(device, self.label, self.usage, cap);
        }
    }

    fn upload(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, bytes: &[u8]) {
        self.reserve(device, bytes.len() as u64);
        queue.write_buffer(&self.buf, 0, bytes);
    }
}

/// What the uploaded map was built from.
#[derive(Debug, Clone, Copy, PartialEq)]
struct MapKey {
    addr: usize,
    version: u64,
    entries: usize,
    bricks: usize,
    cell: f64,
}

impl MapKey {
    fn of<const D: usize>(map: &DpMap<D>) -> Self {
        Self {
            addr: map as *const DpMap<D> as usize,
            version: map.version(),
            entries: map.entry_count(),
            bricks: map.brick_count(),
            cell: map.cell_size(),
        }
    }
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
    table: GrowBuffer,
    headers: GrowBuffer,
    entries: GrowBuffer,
    numbering: GrowBuffer,
    out: GrowBuffer,
    staging: GrowBuffer,
    precision: GpuPrecision,
    map_key: Option<MapKey>,
    map_brick_bits: u32,
    map_table_mask: u32,
    numbering_copy: Option<Numbering>,
    /// Validation or device errors reported asynchronously by wgpu.
    errors: Arc<Mutex<Option<String>>>,
    /// Scratch space for the host-side structs.
    scratch_cands: Vec<GpuCand>,
    scratch_beams: Vec<GpuBeam>,
}

/// Statistics of the last call, for benchmarks and logs.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CallStats {
    /// Bytes written to the device by the call (map included when re-uploaded).
    pub upload_bytes: u64,
    /// Bytes read back.
    pub readback_bytes: u64,
    /// Whether the map was flattened and uploaded.
    pub map_uploaded: bool,
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
    warned: AtomicBool,
    last: Mutex<CallStats>,
}

fn bind(i: u32, b: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding: i,
        resource: b.as_entire_binding(),
    }
}

fn gpu_err(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Gpu(format!("{what}: {e}"))
}

impl<const D: usize> GpuScorer<D> {
    /// A scorer on the first Vulkan adapter; `WGPU_BACKEND` (e.g. `gl`)
    /// overrides the backends searched, `WGPU_ADAPTER_NAME` picks an adapter,
    /// `DPSLAM_GPU_PRECISION` the precision (default `auto`).
    pub fn new() -> Result<Self> {
        Self::with_precision(GpuPrecision::from_env()?)
    }

    /// A scorer on the first Vulkan adapter (as [`GpuScorer::new`]) with the
    /// given precision.
    pub fn with_precision(precision: GpuPrecision) -> Result<Self> {
        Self::open(wgpu::Backends::VULKAN.with_env(), precision)
    }

    /// A scorer on the first adapter of `backends` (this build compiles in
    /// Vulkan only, so any other choice finds no adapter).
    pub fn with_backends(backends: wgpu::Backends) -> Result<Self> {
        Self::open(backends, GpuPrecision::Auto)
    }

    fn open(backends: wgpu::Backends, precision: GpuPrecision) -> Result<Self> {
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
        let state = State {
            cands: GrowBuffer::new(&device, "candidates", storage),
            beams: GrowBuffer::new(&device, "beams", storage),
            table: GrowBuffer::new(&device, "brick table", storage),
            headers: GrowBuffer::new(&device, "cell headers", storage),
            entries: GrowBuffer::new(&device, "entries", storage),
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
            max_binding: limits
                .max_storage_buffer_binding_size
                .min(limits.max_buffer_size),
            max_groups: limits.max_compute_workgroups_per_dimension,
            device,
            queue,
            pipeline,
            layout,
            precision,
            map_key: None,
            map_brick_bits: 0,
            map_table_mask: 0,
            numbering_copy: None,
            errors,
            scratch_cands: Vec::new(),
            scratch_beams: Vec::new(),
        };
        Ok(Self {
            state: Mutex::new(state),
            fallback: CpuScorer::new(),
            adapter: format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type),
            warned: AtomicBool::new(false),
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

    /// Forgets the uploaded map, so that the next call uploads it again (for
    /// callers that rebuild a map at the same address with the same version).
    pub fn invalidate(&self) {
        self.state.lock().unwrap_or_else(|p| p.into_inner()).map_key = None;
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
                "the {what} need {:.0} MiB, more than this adapter binds at once ({:.0} MiB): \
                 use --backend cpu for maps this large",
                bytes as f64 / 1048576.0,
                self.max_binding as f64 / 1048576.0
            )));
        }
        Ok(())
    }

    /// Uploads the map and numbering where they changed; returns the bytes written.
    fn sync_map<const D: usize>(
        &mut self,
        map: &DpMap<D>,
        numbering: &Numbering,
    ) -> Result<(u64, bool)> {
        let mut bytes = 0u64;
        let key = MapKey::of(map);
        let mut uploaded = false;
        if self.map_key != Some(key) {
            let flat = FlatMap::build(map);
            let words = flat.entry_words(self.precision == GpuPrecision::F64);
            let (t, h, e) = (
                bytemuck::cast_slice::<_, u8>(&flat.table),
                bytemuck::cast_slice::<_, u8>(&flat.headers),
                bytemuck::cast_slice::<_, u8>(&words),
            );
            self.fits("map's cell headers", h.len())?;
            self.fits("map's entries", e.len())?;
            self.fits("map's brick table", t.len())?;
            self.table.upload(&self.device, &self.queue, t);
            self.headers.upload(&self.device, &self.queue, h);
            self.entries.upload(&self.device, &self.queue, e);
            bytes += (t.len() + h.len() + e.len()) as u64;
            self.map_brick_bits = flat.brick_bits;
            self.map_table_mask = flat.table_mask();
            self.map_key = Some(key);
            uploaded = true;
        }
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
            bytes += b.len() as u64;
            self.numbering_copy = Some(numbering.clone());
        }
        Ok((bytes, uploaded))
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
        let beams: Vec<_> = ctx
            .scan
            .beams
            .iter()
            .skip(subset.first)
            .step_by(subset.stride.max(1))
            .collect();
        if candidates.is_empty() || beams.is_empty() {
            return Ok((vec![0.0; candidates.len()], CallStats::default()));
        }
        let (map_bytes, map_uploaded) = self.sync_map(ctx.map, ctx.numbering)?;

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
        let params = Params {
            n_cand,
            n_beams,
            brick_bits: self.map_brick_bits,
            table_mask: self.map_table_mask,
            dim: D as u32,
            _pad: [0; 3],
            two_var: flatten::split(2.0 * laser.variance / (cell * cell)),
            max_error: flatten::split(laser.max_error / cell),
            prior: flatten::split(laser.prior_density * cell),
            _pad2: [0.0; 2],
        };
        self.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let cb = bytemuck::cast_slice::<_, u8>(&gc);
        let bb = bytemuck::cast_slice::<_, u8>(&gb);
        let upload = map_bytes + (cb.len() + bb.len() + std::mem::size_of::<Params>()) as u64;
        self.cands.upload(&self.device, &self.queue, cb);
        self.beams.upload(&self.device, &self.queue, bb);
        self.scratch_cands = gc;
        self.scratch_beams = gb;
        self.out.reserve(&self.device, out_bytes);
        self.staging.reserve(&self.device, out_bytes);

        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("likelihood"),
            layout: &self.layout,
            entries: &[
                bind(0, &self.params),
                bind(1, &self.cands.buf),
                bind(2, &self.beams.buf),
                bind(3, &self.table.buf),
                bind(4, &self.headers.buf),
                bind(5, &self.entries.buf),
                bind(6, &self.numbering.buf),
                bind(7, &self.out.buf),
            ],
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
        Ok((
            sums,
            CallStats {
                upload_bytes: upload,
                readback_bytes: out_bytes,
                map_uploaded,
                dispatches: 1,
            },
        ))
    }
}

impl<const D: usize, P: Pose<D>> Scorer<D, P> for GpuScorer<D> {
    fn name(&self) -> &'static str {
        "gpu"
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
                if !self.warned.swap(true, Ordering::Relaxed) {
                    eprintln!("dpslam: {e}; scoring on the CPU instead");
                }
                // The device may be in any state now: rebuild the map next time.
                self.invalidate();
                self.fallback.score(ctx, candidates, subset, trace)
            }
        }
    }
}
