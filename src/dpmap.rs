//! The DP-map: one shared grid whose cells hold observation lists keyed by
//! ancestry node (dissertation ch. 4–5), generic over dimension.
//!
//! Storage is sparse and grows with the area (volume) observed: cells live in
//! hashed bricks (2-D: 16×16 cells, 3-D: 8×8×8 voxels) allocated on first
//! touch, so there is no fixed map size. Each cell holds an unordered list of
//! [`Entry`]s `(node, hits, distance)`. A particle sees, in each cell, the
//! entry of its **deepest** ancestor-or-self: with the tree's depth-first
//! numbering that is the containing entry with the largest `enter`.
//!
//! Linear time (ch. 5) rests on two indexes:
//! - every node keeps the list of cells where it has an entry, so that
//!   deleting dead nodes or merging only-children into their parents visits
//!   only their cells: each such cell's list is rewritten once per prune, in
//!   one pass, however many of its entries die or merge ([`DpMap::apply`]);
//! - the **map cache** ([`ViewCache`]): per iteration, the first lookup of a
//!   long-listed cell resolves the list once for all particles into breakpoints
//!   over the depth-first order; later lookups by any particle are a binary
//!   search. This replaces the release's per-iteration `observationArray`.
//!
//! The map mirrors the ancestry tree's edits ([`DpMap::apply`]).

use crate::ancestry::{Change, NodeId, Numbering, ROOT};
use crate::raycast::CellKey;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// One node's cumulative observation of one cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Entry {
    /// The ancestry node that made the observation.
    pub node: NodeId,
    /// Number of laser beams that stopped in the cell (cumulative over the lineage).
    pub hits: f32,
    /// Total length of laser path through the cell, metres (cumulative, with prior).
    pub distance: f32,
}

mod cell_list;
pub use cell_list::CellList;

/// A node with no entries yet and its observations, one per cell:
/// `(cell, hits, path length m)` (see [`DpMap::insert_fresh_nodes`]).
pub type FreshNode<const D: usize> = (NodeId, Vec<(CellKey<D>, f32, f32)>);

const fn brick_bits(d: usize) -> u32 {
    if d <= 2 { 4 } else { 3 }
}

/// Lists at most this long are scanned directly; longer ones go through the
/// cache. Either gives the same entry. A scan costs the list's length per
/// look-up; the cache costs a breakpoint build per cell and version (per
/// thread), then a few loads per look-up, so it pays only where many
/// candidates look at the same cell: the limit depends on how many a
/// thread scores per map version ([`ViewCache::expect_candidates`]). On
/// all of mit-csail (50 particles, 500 candidates a step) 24 took 0.92× the
/// CPU time of 6 and peaked at 245 against 282 MiB (fewer cells resolved);
/// 48 was no faster than 24. At 3000 particles (30 000 candidates) 8 took
/// 0.91–0.93× the CPU time of 24, 4 and 14 were within 4 % of 8; at 300
/// particles 8 and 24 were within the noise; on all of mit-csail 8 was
/// 1.04× slower than 24 and peaked 16 MiB higher.
const DIRECT_SCAN_MAX: usize = 24;
/// The limit where a thread scores at least [`MANY_CANDIDATES`] candidates.
const DIRECT_SCAN_MAX_MANY: usize = 8;
/// Candidates per thread and map version from which the cache's build is
/// shared by enough look-ups to serve lists longer than
/// [`DIRECT_SCAN_MAX_MANY`].
const MANY_CANDIDATES: usize = 4096;

/// A brick of `side^D` cells.
#[derive(Debug, Clone)]
struct Brick {
    cells: Box<[CellList]>,
    /// Bit `i`: cell `i`'s list holds an entry of the root and no entry with
    /// hits, so every particle sees there a cell no beam has stopped in.
    /// Tracing a beam needs no more than that (its stop probability is 0),
    /// and most cells a beam crosses are such: the bit spares the look-up
    /// of their lists ([`MapView::lookup_for_trace`]). Kept by every edit of
    /// a list's nodes or hits ([`DpMap::edit_cell`], and the appends of
    /// [`DpMap::insert_fresh_nodes`]).
    clear: [u64; 8],
    /// Bit `i`: cell `i`'s list holds an entry with hits (the scan
    /// matcher's field is built from these cells only; most cells have
    /// none). Kept with `clear`.
    hit: [u64; 8],
    /// The map version of the last op that reached one of its cells through
    /// `cell_mut` or `edit_cell`: lets mirrors of the map (the GPU's) copy
    /// only what changed.
    stamp: u64,
}

impl Brick {
    fn new(cells: usize) -> Self {
        debug_assert!(cells <= 64 * 8, "a brick's bitmasks cover 512 cells");
        Self {
            cells: vec![CellList::new(); cells].into_boxed_slice(),
            clear: [0; 8],
            hit: [0; 8],
            stamp: 0,
        }
    }

    #[inline]
    fn is_clear(&self, i: usize) -> bool {
        (self.clear[i >> 6] >> (i & 63)) & 1 != 0
    }

    /// Recomputes cell `i`'s clear and hit bits from its list.
    fn refresh(&mut self, i: usize) {
        let list = &self.cells[i];
        let hit = list.iter().any(|e| e.hits > 0.0);
        let clear = !hit && list.iter().any(|e| e.node == ROOT);
        let (word, bit) = (i >> 6, 1u64 << (i & 63));
        for (set, bits) in [(clear, &mut self.clear), (hit, &mut self.hit)] {
            if set {
                bits[word] |= bit;
            } else {
                bits[word] &= !bit;
            }
        }
    }
}

/// Map versions are unique across all maps of the process, so that a cache
/// keyed by version can never confuse two maps (e.g. a filter and its clone
/// after each changed its map).
fn next_version() -> u64 {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
    NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

/// A map identity no other map of the process has had (see [`DpMap::id`]).
fn next_id() -> u64 {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
    NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

/// The shared observation grid.
#[derive(Debug)]
pub struct DpMap<const D: usize> {
    cell: f64,
    bricks: FxHashMap<CellKey<D>, Brick>,
    /// Per node: the cells where it has an entry (each once, in no set
    /// order). Positions inside the cells' lists are not kept: a list is
    /// scanned where one is needed, which is cheaper than keeping a hash
    /// index per node up to date through every insert, move and merge.
    index: Vec<Vec<CellKey<D>>>,
    entries: usize,
    version: u64,
    id: u64,
}

/// A clone is a new map: same contents, versions and brick stamps, but its
/// own [`DpMap::id`], so that a mirror of the original never takes the clone
/// (which may then change independently) for the map it mirrors.
impl<const D: usize> Clone for DpMap<D> {
    fn clone(&self) -> Self {
        Self {
            cell: self.cell,
            bricks: self.bricks.clone(),
            index: self.index.clone(),
            entries: self.entries,
            version: self.version,
            id: next_id(),
        }
    }
}

/// Cell `k` as (its brick's key, its index inside the brick): the map's
/// storage order is by brick key, then by index.
#[inline]
pub(crate) fn split<const D: usize>(k: CellKey<D>) -> (CellKey<D>, usize) {
    let bits = brick_bits(D);
    let mask = (1i32 << bits) - 1;
    let mut b = [0i32; D];
    let mut idx = 0usize;
    for i in 0..D {
        b[i] = k[i] >> bits;
        // Morton (Z-order) interleave inside the brick: a ray's neighbouring
        // cells share cache lines along every axis, not just along x.
        let local = (k[i] & mask) as usize;
        for bit in 0..bits as usize {
            idx |= ((local >> bit) & 1) << (bit * D + i);
        }
    }
    (b, idx)
}

/// Sort key for bulk edits: cells in the order the map stores them (by brick,
/// then Morton index inside the brick), so consecutive edits share bricks
/// and cache lines. One integer (for up to three dimensions), so that a sort
/// computes it once per cell rather than once per comparison.
#[inline]
pub fn storage_order<const D: usize>(k: CellKey<D>) -> u128 {
    const { assert!(D <= 3, "storage_order packs at most three coordinates") };
    let (brick, idx) = split(k);
    // Flipping the sign bit orders i32 as u32; the brick's coordinates come
    // first, most significant first, then the index inside it.
    brick.iter().fold(0u128, |key, &c| {
        (key << 32) | u128::from(c as u32 ^ 0x8000_0000)
    }) << 32
        | idx as u128
}

/// Inverse of [`split`]: the cell at index `idx` of brick `b`.
#[inline]
pub(crate) fn join<const D: usize>(b: CellKey<D>, idx: usize) -> CellKey<D> {
    let bits = brick_bits(D);
    let local = unsplit_local::<D>(idx);
    std::array::from_fn(|a| (b[a] << bits) + local[a] as i32)
}

/// Inverse of the in-brick part of [`split`]: local coordinates of index `idx`.
#[inline]
fn unsplit_local<const D: usize>(idx: usize) -> [usize; D] {
    let bits = brick_bits(D) as usize;
    let mut local = [0usize; D];
    for (i, l) in local.iter_mut().enumerate() {
        for bit in 0..bits {
            *l |= ((idx >> (bit * D + i)) & 1) << bit;
        }
    }
    local
}

/// The entry a particle with pre-order index `p` sees: the containing entry
/// with the largest `enter` (the deepest ancestor).
#[inline]
fn resolve(list: &[Entry], enter: &[u32], exit: &[u32], p: u32) -> Option<Entry> {
    let mut best: Option<(u32, Entry)> = None;
    for e in list {
        let n = e.node as usize;
        let en = enter[n];
        if en <= p && p <= exit[n] && best.is_none_or(|b| en > b.0) {
            best = Some((en, *e));
        }
    }
    best.map(|b| b.1)
}

/// What one batch of [`Change`]s does to a node's entries ([`DpMap::apply`]).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fate {
    Keep,
    Drop,
    /// Merged into `node`; of several merges into one node, the later
    /// (`rank`, its place in the batch) holds the newer observation.
    Into {
        node: NodeId,
        rank: u32,
    },
}

/// The indices of the set bits of `words` (bit `i` of word `w` is index
/// `64 w + i`), in increasing order.
fn set_bits(words: &[u64]) -> impl Iterator<Item = usize> + '_ {
    words.iter().enumerate().flat_map(|(w, &word)| {
        let mut bits = word;
        std::iter::from_fn(move || {
            (bits != 0).then(|| {
                let i = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                64 * w + i
            })
        })
    })
}

/// The work item of brick `b` in `work` (a default one, appended, on the
/// brick's first use); `slot` maps bricks to their places in `work`.
fn brick_work<'w, const D: usize, T: Default>(
    work: &'w mut Vec<(CellKey<D>, T)>,
    slot: &mut FxHashMap<CellKey<D>, usize>,
    b: CellKey<D>,
) -> &'w mut T {
    let s = *slot.entry(b).or_insert_with(|| {
        work.push((b, T::default()));
        work.len() - 1
    });
    &mut work[s].1
}

impl<const D: usize> DpMap<D> {
    /// An empty map with cells of `cell` metres.
    pub fn new(cell: f64) -> Self {
        Self {
            cell,
            bricks: FxHashMap::default(),
            index: Vec::new(),
            entries: 0,
            version: next_version(),
            id: next_id(),
        }
    }

    /// Cell edge length in metres.
    pub fn cell_size(&self) -> f64 {
        self.cell
    }

    /// Number of stored entries over all cells.
    pub fn entry_count(&self) -> usize {
        self.entries
    }

    /// Number of allocated bricks.
    pub fn brick_count(&self) -> usize {
        self.bricks.len()
    }

    /// Cells per brick.
    pub fn brick_cells() -> usize {
        1usize << (brick_bits(D) as usize * D)
    }

    /// Changes whenever the map changes, to a value no other map of the
    /// process has had (for caches). Versions only increase, within a map
    /// and across the process.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// This map's identity: unique in the process, new for every
    /// [`DpMap::new`] and every clone, kept while the map is edited or moved.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// The bricks (keys: cell key >> brick bits per axis) whose cells an op
    /// of a version after `version` may have changed; with `version` 0,
    /// every brick. O(bricks). Bricks are never freed, so a brick seen once
    /// stays; one listed here may hold the same lists as before (an op that
    /// visited it without a net change).
    pub fn bricks_changed_since(&self, version: u64) -> Vec<CellKey<D>> {
        self.bricks
            .iter()
            .filter(|(_, b)| b.stamp > version)
            .map(|(k, _)| *k)
            .collect()
    }

    /// Cell side of a brick as a power of two (2-D: 4, i.e. 16 cells; 3-D: 3).
    pub fn brick_bits() -> u32 {
        brick_bits(D)
    }

    /// Approximate heap bytes used by the map and its indexes.
    pub fn memory_bytes(&self) -> usize {
        let per_brick = Self::brick_cells() * std::mem::size_of::<CellList>()
            + std::mem::size_of::<(CellKey<D>, Brick)>();
        let spilled: usize = self
            .bricks
            .values()
            .flat_map(|b| b.cells.iter())
            .map(|c| c.heap_bytes())
            .sum();
        let index: usize = self
            .index
            .iter()
            .map(|m| m.capacity() * (std::mem::size_of::<(CellKey<D>, u32)>() + 1))
            .sum();
        self.bricks.len() * per_brick + spilled + index
    }

    /// The observation list of cell `k` (empty if never observed).
    #[inline]
    pub fn cell(&self, k: CellKey<D>) -> &[Entry] {
        let (b, i) = split(k);
        match self.bricks.get(&b) {
            Some(brick) => &brick.cells[i],
            None => &[],
        }
    }

    /// A list whose entries' path lengths an op edits, and nothing else
    /// (their nodes and hits stay: the brick's clear and hit bits stay true). Called
    /// after the op has taken a new version, which stamps the brick.
    fn cell_mut(&mut self, k: CellKey<D>) -> &mut CellList {
        let (b, i) = split(k);
        &mut self.brick_mut(b).cells[i]
    }

    /// Every other edit of a list goes through here: `edit` may change the
    /// list in any way; the cell's clear and hit bits are then recomputed. Called
    /// after the op has taken a new version, which stamps the brick.
    fn edit_cell<R>(&mut self, k: CellKey<D>, edit: impl FnOnce(&mut CellList) -> R) -> R {
        let (b, i) = split(k);
        let brick = self.brick_mut(b);
        let r = edit(&mut brick.cells[i]);
        brick.refresh(i);
        r
    }

    /// Brick `b` (allocated on first use), stamped with the current version.
    fn brick_mut(&mut self, b: CellKey<D>) -> &mut Brick {
        let n = Self::brick_cells();
        let brick = self.bricks.entry(b).or_insert_with(|| Brick::new(n));
        brick.stamp = self.version;
        brick
    }

    fn node_index(&mut self, n: NodeId) -> &mut Vec<CellKey<D>> {
        let i = n as usize;
        if self.index.len() <= i {
            self.index.resize_with(i + 1, Vec::new);
        }
        &mut self.index[i]
    }

    /// Adds `node`'s observation of cell `k` (one per node and cell; a second
    /// insert for the same pair overwrites the first).
    pub fn insert(&mut self, node: NodeId, k: CellKey<D>, hits: f32, distance: f32) {
        self.version = next_version();
        let added = self.edit_cell(k, |list| match list.iter_mut().find(|e| e.node == node) {
            Some(e) => {
                e.hits = hits;
                e.distance = distance;
                false
            }
            None => {
                list.push(Entry {
                    node,
                    hits,
                    distance,
                });
                true
            }
        });
        if added {
            self.node_index(node).push(k);
            self.entries += 1;
        }
    }

    /// Adds the observations of a node that has no entries yet (panics
    /// otherwise), one per cell: `(cell, hits, distance m)`. Cheaper than
    /// [`DpMap::insert`] one by one; best given in [`storage_order`].
    pub fn insert_fresh(&mut self, node: NodeId, cells: &[(CellKey<D>, f32, f32)]) {
        self.insert_fresh_nodes(&[(node, cells)]);
    }

    /// [`DpMap::insert_fresh`] for several nodes at once, in order (each
    /// node's cells unique and best in [`storage_order`]): a list of
    /// [`FreshNode`]s, or of `(node, &cells)`. The bricks are filled in
    /// parallel, each with its cells' entries in node order.
    pub fn insert_fresh_nodes<C>(&mut self, fresh: &[(NodeId, C)])
    where
        C: AsRef<[(CellKey<D>, f32, f32)]> + Sync,
    {
        self.version = next_version();
        type Run<'c, const D: usize> = (NodeId, &'c [(CellKey<D>, f32, f32)]);
        let mut work: Vec<(CellKey<D>, Vec<Run<'_, D>>)> = Vec::new();
        let mut slot: FxHashMap<CellKey<D>, usize> = FxHashMap::default();
        for (node, cells) in fresh {
            assert_eq!(self.node_entries(*node), 0, "node {node} is not fresh");
            for run in cells.as_ref().chunk_by(|x, y| split(x.0).0 == split(y.0).0) {
                brick_work(&mut work, &mut slot, split(run[0].0).0).push((*node, run));
            }
        }
        self.edit_bricks(work, |_, brick, runs| {
            for (node, run) in runs {
                for &(k, hits, distance) in run {
                    let i = split(k).1;
                    let list = &mut brick.cells[i];
                    debug_assert!(
                        list.iter().all(|e| e.node != node),
                        "node {node}: cells repeat"
                    );
                    list.push(Entry {
                        node,
                        hits,
                        distance,
                    });
                    // Another node's entry with no hits leaves the bit as it was.
                    if hits > 0.0 || node == ROOT {
                        brick.refresh(i);
                    }
                }
            }
        });
        for (node, cells) in fresh {
            let cells = cells.as_ref();
            self.entries += cells.len();
            *self.node_index(*node) = cells.iter().map(|c| c.0).collect();
        }
    }

    /// Takes each brick of `work` out of the map (a new one where there is
    /// none), lets `edit` change it (given its key and work item), one
    /// parallel task per brick, and puts it back stamped with the current
    /// version; returns the tasks' results in `work`'s order. Bricks share no list, so the
    /// result does not depend on the thread count.
    fn edit_bricks<W: Send, R: Send>(
        &mut self,
        work: Vec<(CellKey<D>, W)>,
        edit: impl Fn(CellKey<D>, &mut Brick, W) -> R + Sync,
    ) -> Vec<R> {
        let n = Self::brick_cells();
        let taken: Vec<(CellKey<D>, Brick, W)> = work
            .into_iter()
            .map(|(b, w)| {
                let brick = self.bricks.remove(&b).unwrap_or_else(|| Brick::new(n));
                (b, brick, w)
            })
            .collect();
        let done: Vec<(CellKey<D>, Brick, R)> = taken
            .into_par_iter()
            .map(|(b, mut brick, w)| {
                let r = edit(b, &mut brick, w);
                (b, brick, r)
            })
            .collect();
        done.into_iter()
            .map(|(b, mut brick, r)| {
                brick.stamp = self.version;
                self.bricks.insert(b, brick);
                r
            })
            .collect()
    }

    /// Where `node`'s entry sits in cell `k`'s list, if it has one.
    fn position_of(&self, node: NodeId, k: CellKey<D>) -> Option<usize> {
        self.cell(k).iter().position(|e| e.node == node)
    }

    /// Adds `distance` (m) to `node`'s existing entry in cell `k` in place,
    /// for free-space evidence shared by all of the node's descendants.
    /// Returns false if the node has no entry there.
    pub fn add_distance(&mut self, node: NodeId, k: CellKey<D>, distance: f32) -> bool {
        let Some(pos) = self.position_of(node, k) else {
            return false;
        };
        self.version = next_version();
        self.cell_mut(k)[pos].distance += distance;
        true
    }

    /// `node`'s entry in cell `k`, if it has one.
    pub fn entry_of(&self, node: NodeId, k: CellKey<D>) -> Option<Entry> {
        self.cell(k).iter().find(|e| e.node == node).copied()
    }

    /// Sets the path length (m) of each entry `(cell, position in the
    /// cell's list, m)`, positions as [`MapView::position`] finds them. They
    /// hold until a list loses an entry ([`DpMap::apply`]); appends do not
    /// move them.
    pub(crate) fn set_distances_at(
        &mut self,
        edits: impl IntoIterator<Item = (CellKey<D>, u32, f32)>,
    ) {
        self.version = next_version();
        for (k, pos, distance) in edits {
            self.cell_mut(k)[pos as usize].distance = distance;
        }
    }

    /// Sets the path length (m) of `node`'s existing entry in cell `k`.
    /// Returns false if the node has no entry there.
    pub fn set_distance(&mut self, node: NodeId, k: CellKey<D>, distance: f32) -> bool {
        let Some(pos) = self.position_of(node, k) else {
            return false;
        };
        self.version = next_version();
        self.cell_mut(k)[pos].distance = distance;
        true
    }

    /// Number of cells where `node` has an entry.
    pub fn node_entries(&self, node: NodeId) -> usize {
        self.index.get(node as usize).map_or(0, Vec::len)
    }

    /// A read-only view of the map as seen by the particle holding `leaf`.
    pub fn view<'a>(&'a self, numbering: &'a Numbering, leaf: NodeId) -> MapView<'a, D> {
        let leaf_enter = numbering.enter[leaf as usize];
        MapView {
            map: self,
            enter: &numbering.enter,
            exit: &numbering.exit,
            leaf_enter,
            sees_root: numbering.enter[ROOT as usize] <= leaf_enter
                && leaf_enter <= numbering.exit[ROOT as usize],
            last: None,
        }
    }

    /// Mirrors the ancestry tree's edits, as if applied one by one in
    /// order: a removed node's entries go; a child merged into its parent
    /// hands its entries to the parent, replacing the parent's own where
    /// both have one.
    ///
    /// The edits are applied in batches, each as large as it can be while
    /// one pass per cell still gives the sequential result (a batch ends
    /// before an edit that removes or merges a node an earlier edit of the
    /// batch merged into). A prune's edits (all removals, then merges into
    /// nodes that stay) are one batch: each cell any of them touches is
    /// rewritten once, in storage order.
    pub fn apply(&mut self, changes: &[Change]) {
        self.version = next_version();
        let top = changes
            .iter()
            .map(|c| match *c {
                Change::Removed(n) => n,
                Change::Merged { child, into } => child.max(into),
            })
            .max()
            .map_or(0, |n| n as usize + 1)
            .max(self.index.len());
        let mut fate = vec![Fate::Keep; top];
        let mut targeted = vec![false; top];
        let mut batch: Vec<NodeId> = Vec::new();
        for (rank, c) in changes.iter().enumerate() {
            let (node, f) = match *c {
                Change::Removed(n) => (n, Fate::Drop),
                Change::Merged { child, into } => (
                    child,
                    Fate::Into {
                        node: into,
                        rank: rank as u32,
                    },
                ),
            };
            let target_moves =
                matches!(f, Fate::Into { node: t, .. } if fate[t as usize] != Fate::Keep);
            if target_moves || targeted[node as usize] {
                self.rewrite(&batch, &fate);
                for b in batch.drain(..) {
                    if let Fate::Into { node: t, .. } = fate[b as usize] {
                        targeted[t as usize] = false;
                    }
                    fate[b as usize] = Fate::Keep;
                }
            }
            if let Fate::Into { node: t, .. } = f {
                targeted[t as usize] = true;
            }
            fate[node as usize] = f;
            batch.push(node);
        }
        self.rewrite(&batch, &fate);
    }

    /// Rewrites every cell where a node of `batch` has an entry, by `fate`
    /// (every target of a merge is kept): dropped entries go; of the
    /// entries merged into one node, the latest takes that node's own
    /// entry's values, or becomes its entry where it has none.
    fn rewrite(&mut self, batch: &[NodeId], fate: &[Fate]) {
        // The touched cells, brick by brick, as bit masks over the brick's
        // cells: one hash look-up per run of a node's cells in one brick
        // (a node's cells come in storage order), no sort of the cells.
        let mut slot: FxHashMap<CellKey<D>, usize> = FxHashMap::default();
        let mut work: Vec<(CellKey<D>, [u64; 8])> = Vec::new();
        for &n in batch {
            let Some(m) = self.index.get_mut(n as usize) else {
                continue;
            };
            for run in std::mem::take(m).chunk_by(|x, y| split(*x).0 == split(*y).0) {
                let mask = brick_work(&mut work, &mut slot, split(run[0]).0);
                for &k in run {
                    let i = split(k).1;
                    mask[i >> 6] |= 1 << (i & 63);
                }
            }
        }
        // Bricks in key order: the relabelled cells reach their nodes'
        // lists in storage order.
        work.sort_unstable_by_key(|w| w.0);
        let done = self.edit_bricks(work, |b, brick, mask| {
            // Per target node met in the cell at hand: (its own entry's
            // position, the latest merged entry's rank and position).
            let mut targets: Vec<(NodeId, Option<usize>, u32, usize)> = Vec::new();
            let mut relabelled: Vec<(NodeId, CellKey<D>)> = Vec::new();
            let mut removed = 0;
            for i in set_bits(&mask) {
                let k = join(b, i);
                let list = &mut brick.cells[i];
                targets.clear();
                for (r, e) in list.iter().enumerate() {
                    if let Fate::Into { node, rank } = fate[e.node as usize] {
                        match targets.iter_mut().find(|t| t.0 == node) {
                            Some(t) if t.2 < rank => (t.2, t.3) = (rank, r),
                            Some(_) => {}
                            None => targets.push((node, None, rank, r)),
                        }
                    }
                }
                if !targets.is_empty() {
                    for (r, e) in list.iter().enumerate() {
                        if let Some(t) = targets.iter_mut().find(|t| t.0 == e.node) {
                            t.1 = Some(r);
                        }
                    }
                    for &(node, own, _, latest) in &targets {
                        match own {
                            Some(o) => {
                                let (hits, distance) = (list[latest].hits, list[latest].distance);
                                list[o].hits = hits;
                                list[o].distance = distance;
                            }
                            None => {
                                list[latest].node = node;
                                relabelled.push((node, k));
                            }
                        }
                    }
                }
                let before = list.len();
                let mut w = 0;
                for r in 0..before {
                    let e = list[r];
                    if fate[e.node as usize] == Fate::Keep {
                        list[w] = e;
                        w += 1;
                    }
                }
                list.truncate(w);
                list.give_back_spare();
                removed += before - w;
                brick.refresh(i);
            }
            (removed, relabelled)
        });
        for (removed, relabelled) in done {
            self.entries -= removed;
            for (node, k) in relabelled {
                self.node_index(node).push(k);
            }
        }
    }

    /// Calls `f` for every allocated cell with its key and list.
    pub fn for_each_cell(&self, mut f: impl FnMut(CellKey<D>, &[Entry])) {
        for (b, brick) in &self.bricks {
            Self::visit_brick(*b, brick, &mut f);
        }
    }

    /// Calls `f` for every non-empty cell of brick `b` (a key of
    /// [`DpMap::bricks_changed_since`]) with its key and list, in storage
    /// order; nothing if the brick was never allocated.
    pub fn for_each_cell_in_brick(&self, b: CellKey<D>, mut f: impl FnMut(CellKey<D>, &[Entry])) {
        if let Some(brick) = self.bricks.get(&b) {
            Self::visit_brick(b, brick, &mut f);
        }
    }

    /// As [`DpMap::for_each_cell_in_brick`], for the cells with an entry
    /// with hits only (any particle's): found from the brick's bits, without
    /// reading the other cells' lists.
    pub fn for_each_hit_cell_in_brick(
        &self,
        b: CellKey<D>,
        mut f: impl FnMut(CellKey<D>, &[Entry]),
    ) {
        let Some(brick) = self.bricks.get(&b) else {
            return;
        };
        for i in set_bits(&brick.hit) {
            f(join(b, i), &brick.cells[i]);
        }
    }

    fn visit_brick(b: CellKey<D>, brick: &Brick, f: &mut impl FnMut(CellKey<D>, &[Entry])) {
        let bits = brick_bits(D);
        for (i, list) in brick.cells.iter().enumerate() {
            if list.is_empty() {
                continue;
            }
            let local = unsplit_local::<D>(i);
            let mut k = [0i32; D];
            for (a, kk) in k.iter_mut().enumerate() {
                *kk = (b[a] << bits) + local[a] as i32;
            }
            f(k, list);
        }
    }

    /// Histogram of list lengths: `counts[i]` = cells with `i` entries (last bucket: ≥).
    pub fn list_length_histogram(&self, buckets: usize) -> Vec<usize> {
        let mut h = vec![0; buckets.max(1)];
        let last = h.len() - 1;
        self.for_each_cell(|_, l| h[l.len().min(last)] += 1);
        h
    }

    /// Inclusive bounds `(min, max)` of the allocated cells, or `None` if empty.
    pub fn bounds(&self) -> Option<(CellKey<D>, CellKey<D>)> {
        let mut lo = [i32::MAX; D];
        let mut hi = [i32::MIN; D];
        let mut any = false;
        self.for_each_cell(|k, _| {
            any = true;
            for i in 0..D {
                lo[i] = lo[i].min(k[i]);
                hi[i] = hi[i].max(k[i]);
            }
        });
        any.then_some((lo, hi))
    }
}

/// One breakpoint of a resolved cell (see [`ViewCache`]).
#[derive(Debug, Clone, Copy)]
#[repr(C, align(16))]
struct Break {
    start: u32,
    entry: Entry,
}

const UNKNOWN: Entry = Entry {
    node: crate::ancestry::NO_NODE,
    hits: 0.0,
    distance: 0.0,
};

/// Where one resolved cell's breakpoints lie in the cache's arrays, the
/// breakpoint the last lookup landed on, and that breakpoint's answer with
/// the pre-order range it covers: the next particle in pre-order usually
/// falls in the same range, and then the look-up ends at the hash map's
/// bucket without touching the breakpoints (at 3000 particles that load
/// missed the cache on most look-ups).
#[derive(Debug, Clone, Copy)]
struct Span {
    first: u32,
    len: u32,
    cursor: u32,
    /// `[lo, hi)`: the pre-order indices that see `entry` (the cursor's
    /// breakpoint up to the next).
    lo: u32,
    hi: u32,
    entry: Entry,
}

impl Span {
    /// Moves the cursor to breakpoint `at` of `br` (this span's slice).
    #[inline]
    fn land(&mut self, br: &[Break], at: usize) {
        self.cursor = at as u32;
        self.lo = br[at].start;
        self.hi = br.get(at + 1).map_or(u32::MAX, |b| b.start);
        self.entry = br[at].entry;
    }
}

/// The per-iteration map cache: cells resolved once for all particles.
/// Valid for one map version and numbering; one per worker thread.
///
/// A resolved cell is a run of breakpoints over the pre-order: from
/// `start` on (until the next breakpoint) particles see `entry`
/// (`node == NO_NODE`: unknown). A breakpoint is 16 bytes, so the cursor's
/// breakpoint and the next one share a cache line. Scorers visit candidates in
/// pre-order, so each cell keeps a cursor at its last answer: the next
/// particle's answer is almost always there or a step or two ahead, which
/// makes a lookup O(1) amortised instead of a binary search over
/// O(particles) breakpoints (the release's `observationArray` had O(1) by
/// an array per cell and particle; this keeps O(entries) memory).
#[derive(Debug)]
pub struct ViewCache<const D: usize> {
    version: u64,
    /// Lists up to this long are scanned, not resolved (`DIRECT_SCAN_MAX`).
    direct_scan_max: usize,
    /// Cell → its resolved span, answer included.
    cells: FxHashMap<CellKey<D>, Span>,
    breaks: Vec<Break>,
    scratch: Vec<(u32, u32, Entry)>,
    stack: Vec<(u32, Entry)>,
}

impl<const D: usize> Default for ViewCache<D> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const D: usize> ViewCache<D> {
    /// An empty cache.
    pub fn new() -> Self {
        Self {
            version: u64::MAX,
            direct_scan_max: DIRECT_SCAN_MAX,
            cells: FxHashMap::default(),
            breaks: Vec::new(),
            scratch: Vec::new(),
            stack: Vec::new(),
        }
    }

    /// Tells the cache how many candidates its thread is about to score
    /// against the current map version: with many, more cells are worth
    /// resolving (see `DIRECT_SCAN_MAX`). Only speed depends on it; every
    /// look-up gives the same entry either way.
    pub fn expect_candidates(&mut self, per_thread: usize) {
        self.direct_scan_max = if per_thread >= MANY_CANDIDATES {
            DIRECT_SCAN_MAX_MANY
        } else {
            DIRECT_SCAN_MAX
        };
    }

    fn sync(&mut self, version: u64) {
        if self.version != version {
            self.version = version;
            // Keep room for about twice what the last version used: one
            // large step (a loop closing, a burst of disagreement) must not
            // pin its memory for the rest of the run.
            let (cells, breaks) = (self.cells.len(), self.breaks.len());
            self.cells.clear();
            self.breaks.clear();
            const KEEP_MIN: usize = 1 << 12;
            if self.breaks.capacity() > 4 * breaks.max(KEEP_MIN) {
                self.breaks.shrink_to(2 * breaks.max(KEEP_MIN));
            }
            if self.cells.capacity() > 4 * cells.max(KEEP_MIN) {
                self.cells.shrink_to(2 * cells.max(KEEP_MIN));
            }
        }
    }

    fn push_break(&mut self, first: usize, start: u32, entry: Entry) {
        if self.breaks.len() > first
            && let Some(last) = self.breaks.last_mut()
            && last.start == start
        {
            last.entry = entry;
            return;
        }
        self.breaks.push(Break { start, entry });
    }

    /// Resolves `list` into breakpoints over the pre-order.
    fn build(&mut self, list: &[Entry], enter: &[u32], exit: &[u32]) -> Span {
        let first = self.breaks.len();
        let mut iv = std::mem::take(&mut self.scratch);
        iv.clear();
        iv.extend(list.iter().map(|e| {
            let n = e.node as usize;
            (enter[n], exit[n], *e)
        }));
        // Laminar intervals: sorting by (start, −end) visits them in tree order.
        // Stable sort: lists are appended in particle order, which is nearly
        // pre-order, and the stable sort runs in O(n) on such presorted runs.
        iv.sort_by(|a, b| a.0.cmp(&b.0).then(b.1.cmp(&a.1)));
        let mut stack = std::mem::take(&mut self.stack);
        stack.clear();
        self.push_break(first, 0, UNKNOWN);
        for &(a, b, e) in &iv {
            while let Some(&(end, _)) = stack.last() {
                if end >= a {
                    break;
                }
                stack.pop();
                let below = stack.last().map_or(UNKNOWN, |t| t.1);
                self.push_break(first, end + 1, below);
            }
            stack.push((b, e));
            self.push_break(first, a, e);
        }
        while let Some((end, _)) = stack.pop() {
            let below = stack.last().map_or(UNKNOWN, |t| t.1);
            if end < u32::MAX {
                self.push_break(first, end + 1, below);
            }
        }
        self.scratch = iv;
        self.stack = stack;
        let mut span = Span {
            first: first as u32,
            len: (self.breaks.len() - first) as u32,
            cursor: 0,
            lo: 0,
            hi: 0,
            entry: UNKNOWN,
        };
        span.land(&self.breaks[first..], 0);
        span
    }

    /// The entry pre-order index `p` sees in the resolved cell `span`
    /// (whose breakpoints lie in `breaks`); moves the span's cursor there.
    #[inline]
    fn find(breaks: &[Break], span: &mut Span, p: u32) -> Entry {
        if span.lo <= p && p < span.hi {
            return span.entry;
        }
        let br = &breaks[span.first as usize..(span.first + span.len) as usize];
        let c = span.cursor as usize;
        // `span.lo` is `br[c].start`, kept in the bucket: no load here.
        let i = if span.lo <= p {
            // Gallop forward from the cursor: a cell not visited by the last
            // few particles lags behind by a few breakpoints, rarely more.
            let mut lo = c;
            let mut step = 1;
            let mut hi = loop {
                let probe = lo + step;
                if probe >= br.len() {
                    break br.len();
                }
                if br[probe].start > p {
                    break probe;
                }
                lo = probe;
                step *= 2;
            };
            hi = hi.max(lo + 1);
            lo + br[lo..hi].partition_point(|b| b.start <= p) - 1
        } else {
            br[..c].partition_point(|b| b.start <= p) - 1
        };
        prefetch(br.get(i + 4));
        span.land(br, i);
        span.entry
    }
}

/// Asks the CPU to start loading `b`'s cache line. Successive particles in
/// pre-order walk each cell's breakpoints forward, four to a line; the next
/// line is wanted a few particles later, by which time it has arrived. With
/// thousands of cells interleaved, the hardware prefetcher cannot see these
/// streams itself.
#[inline(always)]
fn prefetch(b: Option<&Break>) {
    #[cfg(target_arch = "x86_64")]
    if let Some(b) = b {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: a prefetch is a hint: it reads nothing and cannot fault,
        // and SSE is part of the x86_64 baseline.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((b as *const Break).cast::<i8>()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = b;
}

/// The map as one particle sees it: for each cell, the entry of its deepest
/// ancestor. Cheap to create; keeps a one-brick cache because ray walks visit
/// neighbouring cells.
#[derive(Clone)]
pub struct MapView<'a, const D: usize> {
    map: &'a DpMap<D>,
    enter: &'a [u32],
    exit: &'a [u32],
    leaf_enter: u32,
    /// Whether the root is this particle's ancestor (it always is in a
    /// numbering of the tree the map mirrors): only then do the bricks'
    /// clear bits speak for this view.
    sees_root: bool,
    last: Option<(CellKey<D>, &'a Brick)>,
}

impl<'a, const D: usize> MapView<'a, D> {
    /// The brick holding cell `k` and the cell's index in it.
    #[inline]
    fn brick(&mut self, k: CellKey<D>) -> Option<(&'a Brick, usize)> {
        let (b, i) = split(k);
        let brick = match self.last {
            Some((lb, brick)) if lb == b => brick,
            _ => {
                let brick = self.map.bricks.get(&b)?;
                self.last = Some((b, brick));
                brick
            }
        };
        Some((brick, i))
    }

    #[inline]
    fn list(&mut self, k: CellKey<D>) -> Option<&'a CellList> {
        self.brick(k).map(|(brick, i)| &brick.cells[i])
    }

    /// `(hits, distance)` of the cell as this particle sees it; `None` if unknown.
    #[inline]
    pub fn lookup(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        self.entry(k).map(|e| (e.hits, e.distance))
    }

    /// The entry this particle sees in cell `k`; `None` if unknown.
    #[inline]
    pub fn entry(&mut self, k: CellKey<D>) -> Option<Entry> {
        let list = self.list(k)?;
        resolve(list, self.enter, self.exit, self.leaf_enter)
    }

    /// Where `node`'s entry sits in cell `k`'s list, if it has one there
    /// (whether or not this particle sees it).
    #[inline]
    pub(crate) fn position(&mut self, k: CellKey<D>, node: NodeId) -> Option<u32> {
        let list = self.list(k)?;
        list.iter().position(|e| e.node == node).map(|p| p as u32)
    }

    /// As [`MapView::lookup`], resolving long lists through `cache`.
    #[inline]
    pub fn lookup_cached(&mut self, cache: &mut ViewCache<D>, k: CellKey<D>) -> Option<(f32, f32)> {
        self.entry_cached(cache, k).map(|e| (e.hits, e.distance))
    }

    /// As [`MapView::lookup`] for tracing a beam, where only whether the
    /// cell has hits matters when it has none: `Some((0.0, 0.0))` may stand
    /// for an entry with no hits and any path length. Such cells are most
    /// of what a beam crosses, and this answers them from the brick's clear
    /// bits without reading their lists.
    #[inline]
    pub fn lookup_for_trace(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        let (brick, i) = self.brick(k)?;
        if self.sees_root && brick.is_clear(i) {
            return Some((0.0, 0.0));
        }
        resolve(&brick.cells[i], self.enter, self.exit, self.leaf_enter)
            .map(|e| (e.hits, e.distance))
    }

    /// As [`MapView::lookup_for_trace`], resolving long lists through `cache`.
    #[inline]
    pub fn lookup_for_trace_cached(
        &mut self,
        cache: &mut ViewCache<D>,
        k: CellKey<D>,
    ) -> Option<(f32, f32)> {
        let (brick, i) = self.brick(k)?;
        if self.sees_root && brick.is_clear(i) {
            return Some((0.0, 0.0));
        }
        self.resolve_cached(cache, k, &brick.cells[i])
            .map(|e| (e.hits, e.distance))
    }

    /// As [`MapView::entry`], resolving long lists through `cache`.
    #[inline]
    pub fn entry_cached(&mut self, cache: &mut ViewCache<D>, k: CellKey<D>) -> Option<Entry> {
        let list = self.list(k)?;
        self.resolve_cached(cache, k, list)
    }

    /// The entry this particle sees in `list`, cell `k`'s list.
    #[inline]
    fn resolve_cached(
        &self,
        cache: &mut ViewCache<D>,
        k: CellKey<D>,
        list: &[Entry],
    ) -> Option<Entry> {
        if list.len() <= cache.direct_scan_max {
            return resolve(list, self.enter, self.exit, self.leaf_enter);
        }
        cache.sync(self.map.version);
        let e = match cache.cells.get_mut(&k) {
            Some(span) => ViewCache::<D>::find(&cache.breaks, span, self.leaf_enter),
            None => {
                let mut span = cache.build(list, self.enter, self.exit);
                let e = ViewCache::<D>::find(&cache.breaks, &mut span, self.leaf_enter);
                cache.cells.insert(k, span);
                e
            }
        };
        (e.node != crate::ancestry::NO_NODE).then_some(e)
    }
}

/// A [`MapView`] paired with its thread's [`ViewCache`].
pub struct CachedView<'a, 'c, const D: usize> {
    /// The particle's view.
    pub view: MapView<'a, D>,
    /// The worker's cache.
    pub cache: &'c mut ViewCache<D>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_is_a_bijection_within_bricks() {
        let mut seen = std::collections::HashSet::new();
        for x in -20..20 {
            for y in -20..20 {
                let (b, i) = split([x, y]);
                assert!(i < DpMap::<2>::brick_cells());
                assert!(seen.insert((b, i)));
                let l = unsplit_local::<2>(i);
                assert_eq!(
                    [(b[0] << 4) + l[0] as i32, (b[1] << 4) + l[1] as i32],
                    [x, y]
                );
            }
        }
        let (b, i) = split([-9, 17, 5]);
        let l = unsplit_local::<3>(i);
        assert_eq!(
            [
                (b[0] << 3) + l[0] as i32,
                (b[1] << 3) + l[1] as i32,
                (b[2] << 3) + l[2] as i32
            ],
            [-9, 17, 5]
        );
    }
    use crate::ancestry::AncestryTree;

    fn sorted(mut v: Vec<CellKey<2>>) -> Vec<CellKey<2>> {
        v.sort_unstable();
        v
    }

    #[test]
    fn bricks_changed_since_lists_the_touched_bricks_and_clones_are_new_maps() {
        let mut m = DpMap::<2>::new(0.1);
        m.insert(0, [0, 0], 1.0, 1.0);
        m.insert(1, [40, 3], 1.0, 1.0);
        m.insert(2, [-1, 0], 1.0, 1.0);
        let v = m.version();
        assert!(m.bricks_changed_since(v).is_empty());
        assert_eq!(sorted(m.bricks_changed_since(0)), [[-1, 0], [0, 0], [2, 0]]);
        assert!(m.add_distance(1, [40, 3], 0.5));
        assert_eq!(m.bricks_changed_since(v), [[2, 0]]);
        // No entry there: nothing changes, nothing is stamped.
        assert!(!m.add_distance(1, [0, 0], 0.5));
        assert_eq!(m.bricks_changed_since(v), [[2, 0]]);
        let v = m.version();
        m.apply(&[Change::Merged { child: 2, into: 0 }, Change::Removed(1)]);
        assert!(m.version() > v);
        assert_eq!(sorted(m.bricks_changed_since(v)), [[-1, 0], [2, 0]]);
        assert!(m.cell([40, 3]).is_empty() && m.cell([-1, 0])[0].node == 0);
        let v = m.version();
        m.insert_fresh(5, &[([0, 1], 1.0, 1.0), ([16, 16], 0.0, 1.0)]);
        assert_eq!(sorted(m.bricks_changed_since(v)), [[0, 0], [1, 1]]);
        // A clone keeps contents, versions and stamps but is another map.
        let c = m.clone();
        assert_ne!(c.id(), m.id());
        assert_eq!(c.version(), m.version());
        assert_eq!(
            sorted(c.bricks_changed_since(v)),
            sorted(m.bricks_changed_since(v))
        );
        assert_ne!(DpMap::<2>::new(0.1).id(), DpMap::<2>::new(0.1).id());
    }

    #[test]
    fn each_particle_sees_its_latest_ancestor() {
        let mut t = AncestryTree::new(vec![()]);
        let r = t.root();
        let mut m = DpMap::<2>::new(0.1);
        m.insert(r, [0, 0], 0.0, 1.0);
        let a = t.add_child(r, ());
        let b = t.add_child(r, ());
        m.insert(a, [0, 0], 5.0, 1.0);
        m.insert(b, [1, -3], 2.0, 1.0);
        let mut num = Numbering::default();
        t.number(&mut num);
        let mut va = m.view(&num, a);
        let mut vb = m.view(&num, b);
        assert_eq!(va.lookup([0, 0]), Some((5.0, 1.0)));
        assert_eq!(vb.lookup([0, 0]), Some((0.0, 1.0)));
        assert_eq!(va.lookup([1, -3]), None);
        assert_eq!(vb.lookup([1, -3]), Some((2.0, 1.0)));
        assert_eq!(m.view(&num, r).lookup([0, 0]), Some((0.0, 1.0)));
    }

    #[test]
    fn removal_and_merge_keep_views_and_drop_entries() {
        let mut t = AncestryTree::new(vec![()]);
        let r = t.root();
        let mut m = DpMap::<3>::new(0.1);
        m.insert(r, [0, 0, 0], 1.0, 1.0);
        let a = t.add_child(r, ());
        let b = t.add_child(r, ());
        m.insert(a, [0, 0, 0], 2.0, 2.0);
        m.insert(b, [0, 0, 0], 3.0, 3.0);
        m.insert(b, [9, 9, -9], 3.0, 3.0);
        let a1 = t.add_child(a, ());
        m.insert(a1, [5, 5, 5], 4.0, 4.0);
        assert_eq!(m.entry_count(), 5);
        // b dies; root then has a single child a, which merges into root; a1 is held.
        let mut held = vec![a1];
        let ch = t.maintain(&mut held);
        m.apply(&ch);
        // root absorbed a's entry; a1 merged into root too (root had one child a1 then).
        assert_eq!(t.len(), 1);
        assert_eq!(held, vec![r]);
        assert_eq!(m.entry_count(), 2);
        assert_eq!(
            m.cell([0, 0, 0]),
            &[Entry {
                node: r,
                hits: 2.0,
                distance: 2.0
            }]
        );
        assert!(m.cell([9, 9, -9]).is_empty());
        let mut num = Numbering::default();
        t.number(&mut num);
        assert_eq!(m.view(&num, r).lookup([5, 5, 5]), Some((4.0, 4.0)));
    }

    /// The view from the ordered lists equals a brute-force deepest-ancestor search
    /// through random generations of births, deaths and merges.
    #[test]
    fn storage_order_sorts_by_brick_then_morton_index() {
        let mut keys2: Vec<CellKey<2>> = Vec::new();
        let mut keys3: Vec<CellKey<3>> = Vec::new();
        for x in [-70_000, -17, -16, -1, 0, 5, 15, 16, 300, i32::MAX] {
            for y in [-3, 0, 7, 8, -40_000] {
                keys2.push([x, y]);
                keys3.push([y, x, -y]);
            }
        }
        let mut a = keys2.clone();
        a.sort_by_key(|&k| split(k));
        keys2.sort_by_key(|&k| storage_order(k));
        assert_eq!(a, keys2);
        let mut a = keys3.clone();
        a.sort_by_key(|&k| split(k));
        keys3.sort_by_key(|&k| storage_order(k));
        assert_eq!(a, keys3);
    }

    #[test]
    fn batched_edits_land_where_single_ones_do() {
        let mut t = AncestryTree::new(vec![()]);
        let r = t.root();
        let (a, b) = (t.add_child(r, ()), t.add_child(r, ()));
        let cells = |x: i32| vec![([x, 0], 1.0, 2.0), ([x, 1], 0.0, 3.0), ([40, x], 1.0, 4.0)];
        let mut one = DpMap::<2>::new(0.1);
        one.insert_fresh(a, &cells(1));
        one.insert_fresh(b, &cells(2));
        let mut batch = DpMap::<2>::new(0.1);
        batch.insert_fresh_nodes(&[(a, cells(1)), (b, cells(2))]);
        let (mut x, mut y) = (Vec::new(), Vec::new());
        one.for_each_cell(|k, l| x.push((k, l.to_vec())));
        batch.for_each_cell(|k, l| y.push((k, l.to_vec())));
        assert_eq!(x, y);
        assert_eq!(batch.entry_count(), 6);
        assert_eq!(batch.node_entries(b), 3);
        // [40, 1] and [40, 2] share a brick and no list: b's entry is first.
        let mut num = Numbering::default();
        t.number(&mut num);
        let pos = batch.view(&num, r).position([40, 2], b).unwrap();
        assert_eq!(pos, 0);
        assert_eq!(batch.view(&num, r).position([40, 2], a), None);
        batch.set_distances_at([([40, 2], pos, 9.0)]);
        assert_eq!(batch.entry_of(b, [40, 2]).unwrap().distance, 9.0);
        assert_eq!(batch.entry_of(a, [40, 1]).unwrap().distance, 4.0);
    }

    /// One `apply` of a whole list of edits leaves every cell as the edits
    /// applied one at a time do, whatever the order of removals and merges
    /// (chains of merges into one node, merges into a node that is merged
    /// or removed later: the cases that split a batch).
    #[test]
    fn one_apply_equals_edits_one_at_a_time() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let cells: Vec<CellKey<2>> = vec![[0, 0], [1, 0], [0, 17], [-3, -40], [5, 5]];
        let mut split_batches = 0;
        for round in 0..300 {
            let nodes = 9;
            let mut batch = DpMap::<2>::new(0.1);
            for n in 0..nodes {
                for &k in &cells {
                    if n == ROOT || rng.random_range(0..3) > 0 {
                        batch.insert(n, k, rng.random_range(0..3) as f32, n as f32 + 0.5);
                    }
                }
            }
            let mut one = batch.clone();
            let mut alive: Vec<NodeId> = (1..nodes).collect();
            let mut targets: Vec<NodeId> = Vec::new();
            let mut changes = Vec::new();
            for _ in 0..rng.random_range(1..nodes) {
                let x = alive.swap_remove(rng.random_range(0..alive.len()));
                let into: Vec<NodeId> =
                    std::iter::once(ROOT).chain(alive.iter().copied()).collect();
                if targets.contains(&x) {
                    split_batches += 1;
                }
                if rng.random_range(0..3) == 0 {
                    changes.push(Change::Removed(x));
                } else {
                    let t = into[rng.random_range(0..into.len())];
                    targets.push(t);
                    changes.push(Change::Merged { child: x, into: t });
                }
            }
            batch.apply(&changes);
            for c in &changes {
                one.apply(std::slice::from_ref(c));
            }
            let sorted = |m: &DpMap<2>, k| {
                let mut l = m.cell(k).to_vec();
                l.sort_by_key(|e| e.node);
                l
            };
            for &k in &cells {
                assert_eq!(
                    sorted(&batch, k),
                    sorted(&one, k),
                    "round {round} {changes:?}"
                );
                for n in 0..nodes {
                    assert_eq!(batch.entry_of(n, k), one.entry_of(n, k));
                }
            }
            assert_eq!(batch.entry_count(), one.entry_count());
            for n in 0..nodes {
                assert_eq!(batch.node_entries(n), one.node_entries(n), "round {round}");
            }
        }
        assert!(split_batches > 50, "{split_batches} rounds split a batch");
    }

    #[test]
    fn trace_lookups_agree_with_full_ones_where_cells_stay_free() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let mut t = AncestryTree::new(vec![()]);
        let mut m = DpMap::<2>::new(0.1);
        let n = 24;
        let mut held = vec![t.root(); n];
        let mut num = Numbering::default();
        let mut cache = ViewCache::new();
        let (mut clear_answers, mut hit_answers) = (0, 0);
        for g in 0..120 {
            t.number(&mut num);
            let pick: Vec<usize> = (0..n).map(|_| rng.random_range(0..n)).collect();
            let mut updates = Vec::new();
            for &p in &pick {
                let mut v = m.view(&num, held[p]);
                let mut ups: Vec<(CellKey<2>, f32, f32)> = Vec::new();
                for _ in 0..12 {
                    let k = [rng.random_range(-5..5), rng.random_range(-5..5)];
                    if ups.iter().any(|u| u.0 == k) {
                        continue;
                    }
                    let (h, d) = v.lookup(k).unwrap_or((0.0, 0.0));
                    // Mostly free-space evidence: most cells never get a hit.
                    let hit = if rng.random_bool(0.1) { 1.0 } else { 0.0 };
                    ups.push((k, h + hit, d + 0.1));
                }
                ups.sort_by_key(|u| storage_order(u.0));
                updates.push(ups);
            }
            let new_held: Vec<NodeId> = pick.iter().map(|&p| t.add_child(held[p], ())).collect();
            for (i, (node, ups)) in new_held.iter().zip(&updates).enumerate() {
                // Both ways in: fresh nodes and entry by entry.
                if (g + i) % 2 == 0 {
                    m.insert_fresh(*node, ups);
                } else {
                    for &(k, h, d) in ups {
                        m.insert(*node, k, h, d);
                    }
                }
            }
            held = new_held;
            m.apply(&t.maintain(&mut held));
            t.number(&mut num);
            for brick in m.bricks.values() {
                for (i, list) in brick.cells.iter().enumerate() {
                    let clear = list.iter().any(|e| e.node == t.root())
                        && list.iter().all(|e| e.hits <= 0.0);
                    assert_eq!(brick.is_clear(i), clear, "gen {g}");
                    let hit = list.iter().any(|e| e.hits > 0.0);
                    assert_eq!((brick.hit[i >> 6] >> (i & 63)) & 1 == 1, hit, "gen {g}");
                }
            }
            for &leaf in &held {
                let mut v = m.view(&num, leaf);
                for x in -6..6 {
                    for y in -6..6 {
                        let k = [x, y];
                        let full = v.lookup(k);
                        for quick in [
                            v.lookup_for_trace(k),
                            v.lookup_for_trace_cached(&mut cache, k),
                        ] {
                            match (full, quick) {
                                (None, None) => {}
                                (Some((h, _)), Some(q)) if h > 0.0 => {
                                    assert_eq!(Some(q), full, "gen {g} cell {k:?}");
                                    hit_answers += 1;
                                }
                                (Some(_), Some((h, _))) => {
                                    assert!(h <= 0.0, "gen {g} cell {k:?}");
                                    clear_answers += usize::from(q_is_shortcut(&m, k));
                                }
                                _ => panic!("gen {g} cell {k:?}: {full:?} against {quick:?}"),
                            }
                        }
                    }
                }
            }
        }
        assert!(
            clear_answers > 1000,
            "the clear bits answered {clear_answers} look-ups"
        );
        assert!(hit_answers > 1000);
    }

    /// Whether the clear bit of `k` is set (the trace look-up's shortcut).
    fn q_is_shortcut(m: &DpMap<2>, k: CellKey<2>) -> bool {
        let (b, i) = split(k);
        m.bricks.get(&b).is_some_and(|brick| brick.is_clear(i))
    }

    #[test]
    fn views_match_brute_force_under_random_maintenance() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let mut t = AncestryTree::new(vec![()]);
        let r = t.root();
        let mut m = DpMap::<2>::new(0.1);
        let n = 48;
        let mut held = vec![r; n];
        let mut num = Numbering::default();
        // reference: for each (particle slot) a full private map
        let mut private: Vec<FxHashMap<CellKey<2>, (f32, f32)>> = vec![FxHashMap::default(); n];
        let mut cache = ViewCache::new();
        let mut longest = 0;
        for g in 0..150 {
            t.number(&mut num);
            // Both scan limits: short lists resolved in the cache too.
            cache.expect_candidates(if g % 2 == 0 { 0 } else { usize::MAX });
            let pick: Vec<usize> = (0..n).map(|_| rng.random_range(0..n)).collect();
            let mut new_private = Vec::new();
            let mut updates = Vec::new();
            for &p in pick.iter() {
                let mut mine = private[p].clone();
                let mut v = m.view(&num, held[p]);
                let mut ups = Vec::new();
                for _ in 0..5 {
                    let k = [rng.random_range(-6..6), rng.random_range(-6..6)];
                    if ups.iter().any(|(kk, _, _)| *kk == k) {
                        continue;
                    }
                    let (h, d) = v.lookup(k).unwrap_or((0.0, 0.0));
                    assert_eq!(
                        mine.get(&k).copied().unwrap_or((0.0, 0.0)),
                        (h, d),
                        "gen {g}"
                    );
                    let nv = (h + 1.0, d + g as f32);
                    mine.insert(k, nv);
                    ups.push((k, nv.0, nv.1));
                }
                updates.push(ups);
                new_private.push(mine);
            }
            let new_held: Vec<NodeId> = pick.iter().map(|&p| t.add_child(held[p], ())).collect();
            if g % 3 == 2 {
                let fresh: Vec<FreshNode<2>> = new_held.iter().copied().zip(updates).collect();
                m.insert_fresh_nodes(&fresh);
            } else {
                for (node, ups) in new_held.iter().zip(updates) {
                    if g % 3 == 0 {
                        m.insert_fresh(*node, &ups);
                    } else {
                        for (k, h, d) in ups {
                            m.insert(*node, k, h, d);
                        }
                    }
                }
            }
            held = new_held;
            private = new_private;
            m.for_each_cell(|_, l| longest = longest.max(l.len()));
            let ch = t.maintain(&mut held);
            m.apply(&ch);
            t.number(&mut num);
            for (p, mine) in private.iter().enumerate() {
                let mut v = m.view(&num, held[p]);
                for (k, val) in mine {
                    assert_eq!(v.lookup(*k), Some(*val), "gen {g} particle {p}");
                    assert_eq!(
                        v.lookup_cached(&mut cache, *k),
                        Some(*val),
                        "gen {g} particle {p}"
                    );
                }
                for x in -7..7 {
                    let k = [x, x / 2];
                    assert_eq!(v.lookup_cached(&mut cache, k), v.lookup(k));
                }
            }
            // The cache's cursors must also answer particles visited in
            // descending pre-order (every cursor moves backwards).
            let mut slots: Vec<usize> = (0..n).collect();
            slots.sort_by_key(|&p| std::cmp::Reverse(num.enter[held[p] as usize]));
            for p in slots {
                let mut v = m.view(&num, held[p]);
                for (k, val) in &private[p] {
                    assert_eq!(
                        v.lookup_cached(&mut cache, *k),
                        Some(*val),
                        "gen {g} particle {p}"
                    );
                }
            }
        }
        assert!(t.len() <= 2 * n);
        assert!(
            longest > DIRECT_SCAN_MAX,
            "the cache path was not exercised"
        );
    }
}
