//! Keeping a [`FlatMap`] in step with a changing [`DpMap`], so that the
//! device copy is rewritten only where the map changed.
//!
//! Every brick keeps its slot (its headers) for the life of the mirror and
//! a region of the entry array with room to grow. On [`Mirror::sync`] with
//! the map it mirrors (same [`DpMap::id`]), only the bricks the map stamped
//! after the last sync ([`DpMap::bricks_changed_since`]) are flattened
//! again; each is written in place, or, when it outgrew its room, into a new
//! region at the end (the old one becomes garbage). What differs from the
//! previous contents comes back as coalesced element ranges ([`Delta`]) for
//! the device to copy. A different map, garbage over half the entry array,
//! or bricks gone from the map (which the DP-map never does) rebuild the
//! whole layout instead.
//!
//! The lists equal a fresh [`FlatMap::build`]'s, order included: both
//! flatten a brick with `flatten_brick`. (Order would not matter anyway: the
//! shader takes the containing entry with the largest `enter`, and a node
//! has at most one entry per cell, so there are no ties.)

use super::flatten::{self, Entry, FlatMap, build_table, flatten_brick, key3, room};
use crate::dpmap::DpMap;
use std::ops::Range;

/// Gaps of at most this many elements between two dirty ranges are copied
/// too: one larger copy is cheaper than two small ones.
const MERGE_GAP: usize = 16;

/// What changed in the mirror's arrays since the previous sync, in elements
/// of each array (table positions, header words, entries).
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct Delta {
    /// The layout was rebuilt: every array is new, copy all of it.
    pub full: bool,
    /// Changed table positions (all of the table when it grew).
    pub table: Vec<Range<usize>>,
    /// Changed header words.
    pub headers: Vec<Range<usize>>,
    /// Changed entries.
    pub entries: Vec<Range<usize>>,
}

impl Delta {
    fn full() -> Self {
        Self {
            full: true,
            ..Default::default()
        }
    }

    /// Whether the device copy is current already.
    pub fn is_empty(&self) -> bool {
        !self.full && self.table.is_empty() && self.headers.is_empty() && self.entries.is_empty()
    }

    fn coalesce(&mut self) {
        for r in [&mut self.table, &mut self.headers, &mut self.entries] {
            coalesce(r);
        }
    }
}

/// Sorts `ranges` and merges those that overlap or lie within
/// [`MERGE_GAP`] of each other.
fn coalesce(ranges: &mut Vec<Range<usize>>) {
    ranges.retain(|r| !r.is_empty());
    ranges.sort_unstable_by_key(|r| r.start);
    let mut out: Vec<Range<usize>> = Vec::with_capacity(ranges.len());
    for r in ranges.drain(..) {
        match out.last_mut() {
            Some(last) if r.start <= last.end + MERGE_GAP => last.end = last.end.max(r.end),
            _ => out.push(r),
        }
    }
    *ranges = out;
}

/// Pushes onto `out` the runs of positions `at + i`, `i < new.len()`, where
/// `new` differs from `old` (the previous contents of the same positions;
/// positions past the end of `old` differ). A list that grew or shrank
/// shifts what follows it, so after an insertion the rest of a brick
/// differs; in-place edits (free-space evidence, renamed nodes) leave short
/// runs.
fn changed_runs<T>(
    old: &[T],
    new: &[T],
    same: impl Fn(&T, &T) -> bool,
    at: usize,
    out: &mut Vec<Range<usize>>,
) {
    let m = old.len().min(new.len());
    let mut i = 0;
    while i < m {
        if same(&old[i], &new[i]) {
            i += 1;
            continue;
        }
        let start = i;
        while i < m && !same(&old[i], &new[i]) {
            i += 1;
        }
        out.push(at + start..at + i);
    }
    if new.len() > m {
        out.push(at + m..at + new.len());
    }
}

/// Counters of the syncs so far (for tests and reports).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct MirrorStats {
    /// Full rebuilds of the layout.
    pub rebuilds: u64,
    /// Syncs that updated bricks in place.
    pub updates: u64,
    /// Bricks flattened again by updates.
    pub bricks_rewritten: u64,
    /// Bricks placed in a new region: new ones, and those that outgrew their room.
    pub bricks_moved: u64,
    /// Bricks that got a new slot.
    pub bricks_added: u64,
}

/// A [`FlatMap`] that follows one [`DpMap`] through its versions.
#[derive(Debug, Default)]
pub(crate) struct Mirror {
    flat: FlatMap,
    /// `(DpMap::id, DpMap::version)` of the last sync.
    synced: Option<(u64, u64)>,
    /// Entries in regions bricks have left.
    garbage: usize,
    stats: MirrorStats,
    scratch_rel: Vec<u32>,
    scratch_list: Vec<Entry>,
}

impl Mirror {
    /// The mirrored arrays.
    pub fn flat(&self) -> &FlatMap {
        &self.flat
    }

    /// Counters of the syncs so far.
    pub fn stats(&self) -> MirrorStats {
        self.stats
    }

    /// Forgets the map, so that the next sync rebuilds.
    pub fn reset(&mut self) {
        self.synced = None;
    }

    /// Brings the arrays in step with `map` and says what changed.
    pub fn sync<const D: usize>(&mut self, map: &DpMap<D>) -> Delta {
        let delta = match self.synced {
            Some((id, v)) if id == map.id() && v == map.version() => return Delta::default(),
            Some((id, v)) if id == map.id() => self.update(map, v),
            _ => None,
        };
        let delta = delta.unwrap_or_else(|| {
            self.flat = FlatMap::build(map);
            self.garbage = 0;
            self.stats.rebuilds += 1;
            Delta::full()
        });
        self.synced = Some((map.id(), map.version()));
        delta
    }

    /// Rewrites the bricks changed since `since`; `None` when the layout
    /// must be rebuilt instead.
    fn update<const D: usize>(&mut self, map: &DpMap<D>, since: u64) -> Option<Delta> {
        let mut d = Delta::default();
        let (mut rel, mut list) = (
            std::mem::take(&mut self.scratch_rel),
            std::mem::take(&mut self.scratch_list),
        );
        for b in map.bricks_changed_since(since) {
            flatten_brick(map, b, &mut rel, &mut list);
            let key = key3(b);
            let slot = match self.flat.find_slot(key) {
                Some(s) => s as usize,
                None => self.add_slot(key, &mut d),
            };
            self.write_brick(slot, &rel, &list, &mut d);
        }
        self.scratch_rel = rel;
        self.scratch_list = list;
        let f = &self.flat;
        if f.caps.len() != map.brick_count() || 2 * self.garbage > f.entries.len() {
            return None;
        }
        self.stats.updates += 1;
        d.coalesce();
        Some(d)
    }

    /// A new slot for brick `key` with an empty region (the brick's first
    /// write moves it to one of its size).
    fn add_slot(&mut self, key: [i32; 3], d: &mut Delta) -> usize {
        let f = &mut self.flat;
        let slot = f.caps.len();
        let cpb = f.cells_per_brick;
        let base = f.entries.len() as u32;
        f.caps.push(0);
        f.headers.resize(f.headers.len() + cpb + 1, base);
        d.headers.push(slot * (cpb + 1)..(slot + 1) * (cpb + 1));
        if 2 * (slot + 1) > f.table.len() {
            let keys: Vec<(u32, [i32; 3])> = f
                .table
                .iter()
                .filter(|t| t[3] >= 0)
                .map(|t| (t[3] as u32, [t[0], t[1], t[2]]))
                .chain(std::iter::once((slot as u32, key)))
                .collect();
            let mut ordered = vec![[0i32; 3]; keys.len()];
            for (s, k) in keys {
                ordered[s as usize] = k;
            }
            f.table = build_table(ordered.into_iter());
            d.table.push(0..f.table.len());
        } else {
            let at = flatten::table_insert(&mut f.table, key, slot as u32);
            d.table.push(at..at + 1);
        }
        self.stats.bricks_added += 1;
        slot
    }

    /// Writes one brick's flattened lists (`rel`, `list` as from
    /// `flatten_brick`) into its slot and region.
    fn write_brick(&mut self, slot: usize, rel: &[u32], list: &[Entry], d: &mut Delta) {
        let f = &mut self.flat;
        let cpb = f.cells_per_brick;
        let h0 = slot * (cpb + 1);
        let old_base = f.headers[h0] as usize;
        let old_len = f.headers[h0 + cpb] as usize - old_base;
        let n = list.len();
        let base = if n > f.caps[slot] as usize {
            let base = f.entries.len();
            let cap = room(n);
            self.garbage += f.caps[slot] as usize;
            f.entries.resize(base + cap, Entry::default());
            f.caps[slot] = cap as u32;
            d.entries.push(base..base + n);
            self.stats.bricks_moved += 1;
            base
        } else {
            let old = &f.entries[old_base..old_base + old_len];
            changed_runs(old, list, Entry::same, old_base, &mut d.entries);
            old_base
        };
        f.entries[base..base + n].copy_from_slice(list);
        f.live = f.live + n - old_len;
        let new: Vec<u32> = rel.iter().map(|r| base as u32 + r).collect();
        let headers = &mut f.headers[h0..h0 + cpb + 1];
        changed_runs(headers, &new, |a, b| a == b, h0, &mut d.headers);
        headers.copy_from_slice(&new);
        self.stats.bricks_rewritten += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ancestry::{AncestryTree, NodeId};
    use rand::{RngExt, SeedableRng};

    /// A device copy of the arrays, kept current only by applying deltas.
    #[derive(Default)]
    struct Device {
        flat: FlatMap,
        bytes: usize,
    }

    impl Device {
        fn apply(&mut self, m: &FlatMap, d: &Delta) {
            /// Grows `dst` to `src`'s length with `poison` (a device's new
            /// space holds whatever it holds until a delta writes it), then
            /// copies `rs`; returns the elements copied.
            fn copy<T: Copy>(dst: &mut Vec<T>, src: &[T], rs: &[Range<usize>], poison: T) -> usize {
                dst.resize(src.len(), poison);
                let mut n = 0;
                for r in rs {
                    dst[r.clone()].copy_from_slice(&src[r.clone()]);
                    n += r.len();
                }
                n
            }
            let whole = |len: usize| std::iter::once(0..len).collect::<Vec<_>>();
            let (t, h, e) = if d.full {
                (
                    whole(m.table.len()),
                    whole(m.headers.len()),
                    whole(m.entries.len()),
                )
            } else {
                (d.table.clone(), d.headers.clone(), d.entries.clone())
            };
            let bad = Entry {
                node: u32::MAX,
                density: f64::NAN,
            };
            self.bytes = copy(&mut self.flat.table, &m.table, &t, [-9, -9, -9, 0]) * 16
                + copy(&mut self.flat.headers, &m.headers, &h, u32::MAX) * 4
                + copy(&mut self.flat.entries, &m.entries, &e, bad) * 16;
            self.flat.brick_bits = m.brick_bits;
            self.flat.cells_per_brick = m.cells_per_brick;
        }
    }

    /// Every cell's list in `got` equals its list in `want` (entries and
    /// order), and `got` has no other non-empty cells.
    fn assert_same_lists<const D: usize>(map: &DpMap<D>, want: &FlatMap, got: &FlatMap, at: &str) {
        let mut cells = 0;
        map.for_each_cell(|k, list| {
            let w = want.list(k);
            assert_eq!(w.len(), list.len(), "{at} {k:?}");
            let g = got.list(k);
            assert!(
                w.len() == g.len() && w.iter().zip(g).all(|(a, b)| a.same(b)),
                "{at} cell {k:?}: {g:?} != {w:?}"
            );
            cells += 1;
        });
        // Slots of `got` hold no list the map lacks.
        let cpb = got.cells_per_brick;
        let total: usize = (0..got.headers.len() / (cpb + 1))
            .map(|s| (got.headers[s * (cpb + 1) + cpb] - got.headers[s * (cpb + 1)]) as usize)
            .sum();
        assert_eq!(total, map.entry_count(), "{at}");
        assert!(cells > 0);
    }

    /// Random births, deaths, merges and free-space edits over many
    /// versions, as the filter makes them; after each version the mirror,
    /// and a device copy kept only through deltas, must list every cell as
    /// a fresh build does.
    fn random_edits<const D: usize>(seed: u64, gens: usize, spread: i32) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let mut t = AncestryTree::new(vec![()]);
        let mut m = DpMap::<D>::new(0.1);
        let n = 12;
        let mut held: Vec<NodeId> = vec![t.root(); n];
        let mut mirror = Mirror::default();
        let mut dev = Device::default();
        let mut partial_bytes = 0usize;
        let mut partial_full = 0usize;
        let mut centre = [0i32; D];
        for g in 0..gens {
            // The "robot" drifts, so new bricks appear and old ones rest.
            centre[0] += rng.random_range(0..=spread / 4);
            let pick: Vec<usize> = (0..n).map(|_| rng.random_range(0..n)).collect();
            let new_held: Vec<NodeId> = pick.iter().map(|&p| t.add_child(held[p], ())).collect();
            for (i, &node) in new_held.iter().enumerate() {
                let mut cells: Vec<([i32; D], f32, f32)> = Vec::new();
                for _ in 0..rng.random_range(5..40) {
                    let mut k = centre;
                    for v in k.iter_mut() {
                        *v += rng.random_range(-spread..spread);
                    }
                    if !cells.iter().any(|c| c.0 == k) {
                        cells.push((k, rng.random_range(0..3) as f32, 0.1 + g as f32));
                    }
                }
                if i % 3 == 0 {
                    for (k, h, d) in cells {
                        m.insert(node, k, h, d);
                    }
                } else {
                    m.insert_fresh(node, &cells);
                }
            }
            // Free-space evidence added to existing entries in place.
            for _ in 0..10 {
                let mut k = centre;
                for v in k.iter_mut() {
                    *v += rng.random_range(-spread..spread);
                }
                if let Some(e) = m.cell(k).first() {
                    let node = e.node;
                    assert!(m.add_distance(node, k, 0.25));
                }
            }
            held = new_held;
            let ch = t.maintain(&mut held);
            m.apply(&ch);
            // Some versions are skipped: a sync must catch up over several.
            if g % 4 == 3 {
                continue;
            }
            let d = mirror.sync(&m);
            dev.apply(mirror.flat(), &d);
            let fresh = FlatMap::build(&m);
            let at = format!("gen {g}");
            assert_same_lists(&m, &fresh, mirror.flat(), &at);
            assert_same_lists(&m, &fresh, &dev.flat, &at);
            assert_eq!(mirror.flat().live, m.entry_count());
            if !d.full {
                partial_bytes += dev.bytes;
                partial_full += mirror.flat().packed_bytes(16) as usize;
            }
            // In step: the next sync has nothing to do.
            assert!(mirror.sync(&m).is_empty());
        }
        let s = mirror.stats();
        eprintln!("{D}-D: {s:?}, incremental {partial_bytes} B of {partial_full} B");
        assert!(
            partial_bytes < partial_full / 2,
            "incremental syncs moved {partial_bytes} B, the whole map {partial_full} B"
        );
        // Most syncs patched in place, through every kind of brick change.
        assert!(s.updates as usize > gens / 2, "{s:?}");
        assert!(s.bricks_moved > 0 && s.bricks_added > 0, "{s:?}");
    }

    #[test]
    fn incremental_mirror_lists_every_cell_as_a_fresh_build_in_2d() {
        random_edits::<2>(5, 120, 20);
    }

    #[test]
    fn incremental_mirror_lists_every_cell_as_a_fresh_build_in_3d() {
        random_edits::<3>(9, 80, 10);
    }

    #[test]
    fn a_brick_that_keeps_growing_leaves_garbage_until_a_rebuild() {
        let mut m = DpMap::<2>::new(0.1);
        let mut mirror = Mirror::default();
        // A resting brick, and one that every version adds a node to.
        m.insert(0, [100, 100], 1.0, 1.0);
        let mut rebuilt_at = None;
        for v in 1..200u32 {
            for x in 0..4 {
                m.insert(v, [x, (v % 16) as i32], 1.0, v as f32);
            }
            let d = mirror.sync(&m);
            assert_same_lists(&m, &FlatMap::build(&m), mirror.flat(), &format!("v {v}"));
            if v > 1 && d.full {
                rebuilt_at = Some(v);
                break;
            }
            // In place: only the grown brick's entries and headers, never the resting one's.
            let resting = mirror.flat().find_slot([6, 6, 0]).unwrap() as usize;
            let cpb = mirror.flat().cells_per_brick;
            let h = resting * (cpb + 1)..(resting + 1) * (cpb + 1);
            assert!(
                d.headers
                    .iter()
                    .all(|r| r.end <= h.start || r.start >= h.end)
            );
            assert!(d.table.is_empty() || v == 1);
        }
        let s = mirror.stats();
        assert!(rebuilt_at.is_some(), "{s:?}");
        assert!(s.bricks_moved >= 3, "{s:?}");
        // The rebuild packed the array again.
        let f = mirror.flat();
        assert!(
            f.entries.len() <= room(f.live) + room(1),
            "{}",
            f.entries.len()
        );
    }

    #[test]
    fn a_clone_or_another_map_is_rebuilt_not_patched() {
        let mut a = DpMap::<2>::new(0.1);
        a.insert(0, [1, 2], 1.0, 1.0);
        let mut mirror = Mirror::default();
        assert!(mirror.sync(&a).full);
        assert!(mirror.sync(&a).is_empty());
        // Same version, same contents, but another map: it may change on
        // its own from here on.
        let mut b = a.clone();
        assert_eq!(b.version(), a.version());
        assert!(mirror.sync(&b).full);
        b.insert(0, [40, 2], 1.0, 1.0);
        let d = mirror.sync(&b);
        assert!(
            !d.full && !d.entries.is_empty() && !d.table.is_empty(),
            "{d:?}"
        );
        assert_eq!(mirror.flat().list([40, 2]).len(), 1);
        assert!(mirror.sync(&a).full);
        assert!(mirror.flat().list([40, 2]).is_empty());
        mirror.reset();
        assert!(mirror.sync(&a).full);
    }

    #[test]
    fn changed_runs_are_found_and_coalesced() {
        let runs = |old: &[u32], new: &[u32]| {
            let mut out = Vec::new();
            changed_runs(old, new, |a, b| a == b, 100, &mut out);
            out.into_iter()
                .map(|r| (r.start, r.end))
                .collect::<Vec<_>>()
        };
        assert_eq!(runs(&[1, 2, 3, 4], &[1, 9, 3, 4]), [(101, 102)]);
        assert_eq!(
            runs(&[1, 2, 3, 4, 5], &[0, 2, 3, 0, 0]),
            [(100, 101), (103, 105)]
        );
        assert!(runs(&[1, 2, 3, 4], &[1, 2, 3, 4]).is_empty());
        assert_eq!(runs(&[1, 2, 3], &[1, 2, 3, 4, 5]), [(103, 105)]);
        // A shorter list: what follows its end is never read.
        assert_eq!(runs(&[1, 2, 3, 4], &[1, 3, 4]), [(101, 103)]);
        assert_eq!(runs(&[], &[7]), [(100, 101)]);
        // 2..6 overlaps 0..4; 40..50 is within MERGE_GAP of 30..32, 70..80 is not.
        let mut r = vec![40..50, 0..4, 2..6, 70..80, 6..6, 30..32];
        coalesce(&mut r);
        assert_eq!(r, vec![0..6, 30..50, 70..80]);
    }
}
