//! Scan scoring backends: the likelihood of a scan for many candidate poses,
//! each against its own particle's view of the DP-map.
//!
//! Weighing is where the time goes (candidates × beams × cells per beam), so
//! it sits behind one trait: [`CpuScorer`] (rayon) is the reference, and the
//! optional GPU path (`gpu` feature) implements the same contract and is
//! tested against it.

use crate::ancestry::{NodeId, Numbering};
use crate::dpmap::{CachedView, DpMap, ViewCache};
use crate::geometry::Pose;
use crate::laser_model::{LaserModel, Trace};
use crate::raycast::CellKey;
use crate::scan::Scan;
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::sync::Mutex;

/// A pose to score and the ancestry node whose map view scores it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate<P> {
    /// The particle's most recent ancestry node.
    pub node: NodeId,
    /// Robot pose in the map frame.
    pub pose: P,
}

/// The beams a pass scores: `first, first + stride, first + 2·stride, …`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BeamSubset {
    /// First beam index.
    pub first: usize,
    /// Step between beams (≥ 1).
    pub stride: usize,
}

impl BeamSubset {
    /// Every beam.
    pub const ALL: BeamSubset = BeamSubset {
        first: 0,
        stride: 1,
    };

    /// The items of `all` (a scan's beams) that this subset scores, in order.
    pub fn select<'a, T>(&self, all: &'a [T]) -> impl Iterator<Item = &'a T> + 'a {
        all.iter().skip(self.first).step_by(self.stride.max(1))
    }
}

/// What every candidate of one scoring call shares.
pub struct ScoreContext<'a, const D: usize, P: Pose<D>> {
    /// The shared DP-map.
    pub map: &'a DpMap<D>,
    /// Depth-first numbering of the ancestry tree, current for `map`.
    pub numbering: &'a Numbering,
    /// The laser model.
    pub laser: &'a LaserModel,
    /// The scan (beams in the sensor frame).
    pub scan: &'a Scan<D, P>,
}

/// A device scorer's traffic over its life (see [`Scorer::transfers`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Transfers {
    /// Successful scoring calls.
    pub calls: u64,
    /// Calls that uploaded some of the map (after a map change: once per
    /// filter step).
    pub map_syncs: u64,
    /// Of those, full uploads of a rebuilt layout (the first call, another
    /// map, too much garbage in the entry array).
    pub map_rebuilds: u64,
    /// Map bytes uploaded over all syncs.
    pub map_bytes: u64,
    /// Sum over the syncs of the map's packed size on the device: what
    /// uploading the whole map at every sync would have cost, bytes.
    pub map_packed_bytes: u64,
    /// Bricks flattened again by incremental syncs (a brick the map changed).
    pub map_bricks_rewritten: u64,
    /// Of those, bricks placed in a new region: new bricks, and bricks that
    /// outgrew their room.
    pub map_bricks_moved: u64,
    /// Other bytes uploaded: numbering, candidates, beams, parameters.
    pub other_upload_bytes: u64,
    /// Bytes read back.
    pub readback_bytes: u64,
}

/// Computes scan log-likelihoods for candidate poses.
pub trait Scorer<const D: usize, P: Pose<D>>: Send + Sync {
    /// Backend name for logs ("cpu", "gpu").
    fn name(&self) -> &'static str;

    /// Device traffic so far; `None` for scorers without a device.
    fn transfers(&self) -> Option<Transfers> {
        None
    }

    /// Problems met while scoring that the run should report (e.g. a device
    /// error after which the GPU scorer fell back to the CPU); empty when
    /// none.
    fn warnings(&self) -> Vec<String> {
        Vec::new()
    }

    /// For each candidate, the sum over the beams of `subset` of the beam
    /// log-likelihood ([`LaserModel::beam_log_likelihood`] with `trace`).
    fn score(
        &self,
        ctx: &ScoreContext<'_, D, P>,
        candidates: &[Candidate<P>],
        subset: BeamSubset,
        trace: Trace,
    ) -> Vec<f64>;
}

/// The reference scorer: candidates in parallel with rayon, one map cache
/// per worker thread (and one [`CellSums`] for the map update's traces).
pub struct CpuScorer<const D: usize> {
    caches: Vec<Mutex<ViewCache<D>>>,
    sums: Vec<Mutex<CellSums<D>>>,
}

/// The slot of the current rayon worker in `slots` (one per worker, then one
/// for threads outside the pool).
fn this_threads<T>(slots: &[Mutex<T>]) -> std::sync::MutexGuard<'_, T> {
    let last = slots.len() - 1;
    let i = rayon::current_thread_index().map_or(last, |i| i.min(last));
    slots[i].lock().unwrap_or_else(|e| e.into_inner())
}

/// Working memory for summing a traced scan per cell: kept per thread, so
/// that each trace reuses the last one's tables instead of growing new
/// ones (the map update traces every new particle's scan, every step).
///
/// The sums are kept by tiles of 64 cells: the map brick's quarters (2-D)
/// or eighths (3-D), which its storage order visits one after the other.
/// A trace step finds its tile by one comparison with the last step's (a
/// ray's cells come tile by tile), and the cells come out in the map's
/// storage order by sorting the tiles, not the cells. (A 2-D slot holds a
/// quarter of a brick's cells: less memory spent on the untouched cells
/// between a scan's far rays.)
#[derive(Debug, Default)]
pub struct CellSums<const D: usize> {
    /// Tile (brick key, tile in the brick) → its slot in `tiles`.
    slot_of: FxHashMap<(CellKey<D>, u32), u32>,
    /// Slots; the first `slot_of.len()` are in use (the rest keep their
    /// memory for the next trace).
    tiles: Vec<TileSums<D>>,
    /// The last step's tile and slot.
    last: Option<((CellKey<D>, u32), u32)>,
    /// The sums of [`CellSums::finish`], in storage order.
    pub(crate) ordered: Vec<(CellKey<D>, (f32, f32))>,
}

/// Cells per [`CellSums`] tile: the bits of a `u64`.
const TILE: usize = 64;

/// One tile's per-cell sums.
#[derive(Debug)]
struct TileSums<const D: usize> {
    /// Brick key and tile in the brick.
    key: (CellKey<D>, u32),
    /// Bit `i`: cell `i` has a sum (the others hold stale values).
    touched: u64,
    /// (hits, path length m) per cell of the tile.
    sums: [(f32, f32); TILE],
}

impl<const D: usize> CellSums<D> {
    /// Forgets the sums, keeping the memory.
    pub(crate) fn clear(&mut self) {
        self.slot_of.clear();
        self.last = None;
        self.ordered.clear();
    }

    /// Adds `(hits, path length m)` to cell `k`.
    #[inline]
    pub(crate) fn add(&mut self, k: CellKey<D>, hits: f32, distance: f32) {
        let (b, i) = crate::dpmap::split(k);
        // The top bits of the in-brick (Morton) index pick the tile.
        let key = (b, (i / TILE) as u32);
        let slot = match self.last {
            Some((lk, slot)) if lk == key => slot,
            _ => {
                let slot = self.slot(key);
                self.last = Some((key, slot));
                slot
            }
        };
        let tile = &mut self.tiles[slot as usize];
        let bit = 1u64 << (i % TILE);
        if tile.touched & bit == 0 {
            tile.touched |= bit;
            tile.sums[i % TILE] = (0.0, 0.0);
        }
        let e = &mut tile.sums[i % TILE];
        e.0 += hits;
        e.1 += distance;
    }

    /// The slot of tile `key`, taken on its first use.
    fn slot(&mut self, key: (CellKey<D>, u32)) -> u32 {
        let used = self.slot_of.len() as u32;
        let slot = *self.slot_of.entry(key).or_insert(used);
        if slot == used {
            if self.tiles.len() == used as usize {
                debug_assert_eq!(DpMap::<D>::brick_cells() % TILE, 0);
                self.tiles.push(TileSums {
                    key,
                    touched: 0,
                    sums: [(0.0, 0.0); TILE],
                });
            }
            let tile = &mut self.tiles[slot as usize];
            tile.key = key;
            tile.touched = 0;
        }
        slot
    }

    /// Puts the sums into `ordered`, in the map's storage order
    /// ([`crate::dpmap::storage_order`]): bricks by key, cells by index.
    pub(crate) fn finish(&mut self) {
        let used = &mut self.tiles[..self.slot_of.len()];
        used.sort_unstable_by_key(|t| t.key);
        self.ordered.clear();
        for tile in used.iter() {
            let (b, t) = tile.key;
            let mut bits = tile.touched;
            while bits != 0 {
                let i = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                self.ordered
                    .push((crate::dpmap::join(b, t as usize * TILE + i), tile.sums[i]));
            }
        }
        // The slots moved: the next trace starts afresh.
        self.slot_of.clear();
        self.last = None;
    }
}

impl<const D: usize> Default for CpuScorer<D> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const D: usize> CpuScorer<D> {
    /// A scorer with caches for the current rayon pool.
    pub fn new() -> Self {
        Self {
            caches: (0..=rayon::current_num_threads())
                .map(|_| Mutex::new(ViewCache::new()))
                .collect(),
            sums: (0..=rayon::current_num_threads())
                .map(|_| Mutex::new(CellSums::default()))
                .collect(),
        }
    }

    /// This worker thread's [`CellSums`].
    pub fn thread_sums(&self) -> std::sync::MutexGuard<'_, CellSums<D>> {
        this_threads(&self.sums)
    }

    /// This worker thread's map cache.
    pub fn thread_cache(&self) -> std::sync::MutexGuard<'_, ViewCache<D>> {
        this_threads(&self.caches)
    }

    /// Score of one candidate (see [`Scorer::score`]).
    pub fn score_one<P: Pose<D>>(
        &self,
        ctx: &ScoreContext<'_, D, P>,
        c: &Candidate<P>,
        subset: BeamSubset,
        trace: Trace,
    ) -> f64 {
        let mut cache = self.thread_cache();
        let mut view = CachedView {
            view: ctx.map.view(ctx.numbering, c.node),
            cache: &mut cache,
        };
        let sensor = c.pose.compose(&ctx.scan.sensor);
        let origin = sensor.translation();
        subset
            .select(&ctx.scan.beams)
            .map(|b| {
                ctx.laser.beam_log_likelihood(
                    &mut view,
                    origin,
                    sensor.rotate(b.dir),
                    b.range,
                    b.no_return,
                    trace,
                )
            })
            .sum()
    }
}

impl<const D: usize, P: Pose<D>> Scorer<D, P> for CpuScorer<D> {
    fn name(&self) -> &'static str {
        "cpu"
    }

    fn score(
        &self,
        ctx: &ScoreContext<'_, D, P>,
        candidates: &[Candidate<P>],
        subset: BeamSubset,
        trace: Trace,
    ) -> Vec<f64> {
        // Candidates in pre-order keep each worker's map-cache lookups
        // moving forward through every cell's breakpoints (see
        // `ViewCache`): O(1) each. Each worker takes a contiguous run of
        // that order and walks it beam by beam, every candidate of the run
        // through one beam before the next: the candidates' poses are
        // close, so their rays cross nearly the same cells, which the first
        // candidate brings into the CPU cache for the others. Blocks of 32
        // beams per candidate (one block's cells evicting the next
        // candidate's) made a step at 3000 particles 1.4× slower (`bench
        // scaling`: the full weigh 1.29–1.40 s against 0.77–0.90 s; 3000 vs
        // 300 particles 11.4–12.2× against 9.6–10.2×); at 50 particles the
        // two orders time the same. Each candidate's beam terms are still
        // added in beam order, so the scores are those of `score_one`, bit
        // for bit, whatever the runs.
        let n = candidates.len();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by_key(|&i| ctx.numbering.enter[candidates[i].node as usize]);
        let run = n
            .div_ceil(RUNS_PER_THREAD * rayon::current_num_threads().max(1))
            .max(1);
        let beams: Vec<&crate::scan::Beam<D>> = subset.select(&ctx.scan.beams).collect();
        let done: Vec<Vec<f64>> = order
            .par_chunks(run)
            .map(|ids| {
                let mut cache = self.thread_cache();
                cache.expect_candidates(n.div_ceil(rayon::current_num_threads().max(1)));
                let sensors: Vec<P> = ids
                    .iter()
                    .map(|&i| candidates[i].pose.compose(&ctx.scan.sensor))
                    .collect();
                let mut views: Vec<_> = ids
                    .iter()
                    .map(|&i| ctx.map.view(ctx.numbering, candidates[i].node))
                    .collect();
                let mut sums = vec![-0.0f64; ids.len()];
                for b in &beams {
                    for ((sensor, view), sum) in sensors.iter().zip(&mut views).zip(&mut sums) {
                        let mut cv = CachedView {
                            view: view.clone(),
                            cache: &mut cache,
                        };
                        *sum += ctx.laser.beam_log_likelihood(
                            &mut cv,
                            sensor.translation(),
                            sensor.rotate(b.dir),
                            b.range,
                            b.no_return,
                            trace,
                        );
                        *view = cv.view;
                    }
                }
                sums
            })
            .collect();
        let mut out = vec![0.0f64; n];
        for (&i, x) in order.iter().zip(done.into_iter().flatten()) {
            out[i] = x;
        }
        out
    }
}

/// Runs of candidates per worker thread: fewer runs share more cache hits,
/// more balance the load.
const RUNS_PER_THREAD: usize = 2;

/// `f(0..n)` in parallel, visiting the indices sorted by `preorder` (a node's
/// depth-first index; ties keep index order), results in index order.
///
/// Map lookups for particles in pre-order walk every cached cell's
/// breakpoints forward (see `ViewCache`), so each worker takes contiguous
/// runs of that order: 8 runs per worker still balance the load. The order
/// only changes speed: each `f(i)` is computed on its own.
pub fn map_in_preorder<T: Send>(
    n: usize,
    preorder: impl Fn(usize) -> u32,
    f: impl Fn(usize) -> T + Sync,
) -> Vec<T> {
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by_key(|&i| preorder(i));
    let run = (n / (8 * rayon::current_num_threads().max(1))).max(1);
    let done: Vec<T> = order.par_iter().with_min_len(run).map(|&i| f(i)).collect();
    let mut out: Vec<Option<T>> = (0..n).map(|_| None).collect();
    for (&i, x) in order.iter().zip(done) {
        out[i] = Some(x);
    }
    out.into_iter()
        .map(|x| x.expect("order is a permutation of 0..n"))
        .collect()
}
