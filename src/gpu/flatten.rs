//! The DP-map in the flat, pointer-free form the likelihood shader reads.
//!
//! Cells are grouped into bricks (2-D: 16×16, 3-D: 8×8×8, as in the DP-map)
//! found through an open-addressing hash table; each brick has a slot with
//! `cells + 1` offsets into one entry array, so a cell's observation list
//! is `entries[h[i]..h[i + 1]]`. Each brick owns a region of the entry array
//! with room to grow (`caps`), so that [`super::mirror`] can rewrite one
//! brick in place when the map changes. Entries keep their ancestry node id,
//! and the depth-first numbering travels separately: re-numbering the tree
//! (every step) re-uploads `2 × nodes` words, not the map.

use crate::dpmap::DpMap;
use crate::raycast::CellKey;

/// The brick-table hash; the shader's `brick_hash` is the same function.
#[inline]
pub(crate) fn brick_hash(b: [i32; 3]) -> u32 {
    (b[0] as u32).wrapping_mul(73_856_093)
        ^ (b[1] as u32).wrapping_mul(19_349_663)
        ^ (b[2] as u32).wrapping_mul(83_492_791)
}

/// A flattened map: the arrays bound to the shader, and the layout of the
/// entry array.
#[derive(Debug, Clone, Default)]
pub(crate) struct FlatMap {
    /// `[bx, by, bz, slot]`, slot −1 for an empty table position; length a
    /// power of two, at most half full.
    pub table: Vec<[i32; 4]>,
    /// Per slot, `cells_per_brick + 1` offsets into `entries`; the first is
    /// the start of the brick's region.
    pub headers: Vec<u32>,
    /// The bricks' regions; a cell's entries in storage order, a brick's
    /// cells in row-major local order. Positions outside every brick's
    /// lists (room to grow, abandoned regions) are never read.
    pub entries: Vec<Entry>,
    /// Per slot: entries reserved for the brick from the start of its region.
    pub caps: Vec<u32>,
    /// Entries in the bricks' lists (the rest of `entries` is room or garbage).
    pub live: usize,
    /// Brick side as a power of two.
    pub brick_bits: u32,
    /// `2^(brick_bits · D)`.
    pub cells_per_brick: usize,
}

/// One observation of the flat map.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Entry {
    /// Ancestry node id.
    pub node: u32,
    /// Stop density, stops per cell length (0 for a cell never seen to stop a beam).
    pub density: f64,
}

impl Entry {
    /// Bit-for-bit equality (what the device would read), unlike `==` on f64.
    pub fn same(&self, o: &Entry) -> bool {
        self.node == o.node && self.density.to_bits() == o.density.to_bits()
    }
}

/// An f64 as two f32s whose (f64) sum is the value to ~48 bits; `hi` alone
/// is the value rounded to f32. The shader joins them with `wide`.
pub(crate) fn split(x: f64) -> [f32; 2] {
    let hi = x as f32;
    [hi, (x - hi as f64) as f32]
}

/// Appends `entries` as the shader reads them: `(node, density as f32
/// bits)` pairs, or with `wide`, `(node, density hi, density lo, 0)`
/// quadruples (see [`split`]).
pub(crate) fn entry_words(entries: &[Entry], wide: bool, out: &mut Vec<u32>) {
    out.reserve(entries.len() * if wide { 4 } else { 2 });
    for e in entries {
        let [hi, lo] = split(e.density);
        out.push(e.node);
        out.push(hi.to_bits());
        if wide {
            out.extend([lo.to_bits(), 0]);
        }
    }
}

/// Room reserved for a brick of `n` entries when it is (re)placed: bricks
/// along the current scan grow every step, and half again as much keeps
/// most of them in place for several steps.
pub(crate) fn room(n: usize) -> usize {
    n + n / 2 + 8
}

/// A brick key of the map as the table stores it (z = 0 in 2-D).
pub(crate) fn key3<const D: usize>(b: CellKey<D>) -> [i32; 3] {
    let mut k = [0i32; 3];
    k[..D].copy_from_slice(&b);
    k
}

/// Writes `key → slot` at the first free position of its probe sequence;
/// returns the position.
pub(crate) fn table_insert(table: &mut [[i32; 4]], key: [i32; 3], slot: u32) -> usize {
    let m = table.len() - 1;
    let mut s = brick_hash(key) as usize & m;
    while table[s][3] >= 0 {
        s = (s + 1) & m;
    }
    table[s] = [key[0], key[1], key[2], slot as i32];
    s
}

/// A table of `2^k ≥ 2 · slots` positions (at least 16) holding `keys[i] → i`.
pub(crate) fn build_table(keys: impl ExactSizeIterator<Item = [i32; 3]>) -> Vec<[i32; 4]> {
    let size = (2 * keys.len()).next_power_of_two().max(16);
    let mut table = vec![[0, 0, 0, -1]; size];
    for (i, k) in keys.enumerate() {
        table_insert(&mut table, k, i as u32);
    }
    table
}

/// One brick of `map`, flattened: `rel[i]..rel[i + 1]` index local cell
/// `i`'s entries in `out` (row-major local index, as the shader computes
/// it), `rel[0] = 0`. Densities are `hits / distance · cell` (stops per
/// cell length), 0 where `hits ≤ 0`, as in `LaserModel::stop_probability`.
pub(crate) fn flatten_brick<const D: usize>(
    map: &DpMap<D>,
    b: CellKey<D>,
    rel: &mut Vec<u32>,
    out: &mut Vec<Entry>,
) {
    let bits = DpMap::<D>::brick_bits();
    let mask = (1i32 << bits) - 1;
    let cpb = DpMap::<D>::brick_cells();
    let local = |k: CellKey<D>| {
        (0..D).fold(0usize, |l, i| {
            l | (((k[i] & mask) as usize) << (bits as usize * i))
        })
    };
    let cell = map.cell_size();
    rel.clear();
    rel.resize(cpb + 1, 0);
    map.for_each_cell_in_brick(b, |k, list| rel[local(k) + 1] = list.len() as u32);
    for i in 0..cpb {
        rel[i + 1] += rel[i];
    }
    out.clear();
    out.resize(rel[cpb] as usize, Entry::default());
    map.for_each_cell_in_brick(b, |k, list| {
        let at = rel[local(k)] as usize;
        for (o, e) in out[at..at + list.len()].iter_mut().zip(list) {
            let density = if e.hits <= 0.0 {
                0.0
            } else {
                e.hits as f64 / e.distance as f64 * cell
            };
            *o = Entry {
                node: e.node,
                density,
            };
        }
    });
}

impl FlatMap {
    /// `table.len() − 1`.
    pub fn table_mask(&self) -> u32 {
        (self.table.len() - 1) as u32
    }

    /// Flattens `map`, each brick with [`room`] for its entries.
    pub fn build<const D: usize>(map: &DpMap<D>) -> Self {
        let cpb = DpMap::<D>::brick_cells();
        let keys = map.bricks_changed_since(0);
        let mut f = Self {
            table: build_table(keys.iter().map(|&b| key3(b))),
            headers: Vec::with_capacity(keys.len() * (cpb + 1)),
            entries: Vec::with_capacity(room(map.entry_count())),
            caps: Vec::with_capacity(keys.len()),
            live: 0,
            brick_bits: DpMap::<D>::brick_bits(),
            cells_per_brick: cpb,
        };
        let (mut rel, mut list) = (Vec::new(), Vec::new());
        for b in keys {
            flatten_brick(map, b, &mut rel, &mut list);
            let base = f.entries.len() as u32;
            let cap = room(list.len());
            f.headers.extend(rel.iter().map(|r| base + r));
            f.entries.extend_from_slice(&list);
            f.entries.resize(base as usize + cap, Entry::default());
            f.caps.push(cap as u32);
            f.live += list.len();
        }
        f
    }

    /// The slot of brick `key`, if the table has it.
    pub fn find_slot(&self, key: [i32; 3]) -> Option<u32> {
        let m = self.table_mask() as usize;
        let mut s = brick_hash(key) as usize & m;
        loop {
            let t = self.table[s];
            if t[3] < 0 {
                return None;
            }
            if t[..3] == key {
                return Some(t[3] as u32);
            }
            s = (s + 1) & m;
        }
    }

    /// Bytes a device copy of these arrays needs with `entry_bytes` per
    /// entry, room and garbage left out: what uploading a freshly built,
    /// gap-free map would cost.
    pub fn packed_bytes(&self, entry_bytes: usize) -> u64 {
        (self.live * entry_bytes + self.headers.len() * 4 + self.table.len() * 16) as u64
    }

    /// The list of cell `k` as the shader finds it.
    #[cfg(test)]
    pub fn list<const D: usize>(&self, k: [i32; D]) -> &[Entry] {
        let bits = self.brick_bits;
        let mask = (1i32 << bits) - 1;
        let mut bk = [0i32; 3];
        let mut local = 0usize;
        for i in 0..D {
            bk[i] = k[i] >> bits;
            local |= ((k[i] & mask) as usize) << (bits as usize * i);
        }
        match self.find_slot(bk) {
            None => &[],
            Some(s) => {
                let h = s as usize * (self.cells_per_brick + 1) + local;
                &self.entries[self.headers[h] as usize..self.headers[h + 1] as usize]
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_cell_list_is_found_with_its_entries() {
        let mut m = DpMap::<3>::new(0.5);
        let mut want = Vec::new();
        for i in 0..400i32 {
            let k = [i % 23 - 11, (i * 7) % 31 - 15, -(i % 5)];
            let node = (i % 4) as u32;
            m.insert(node, k, (i % 3) as f32, 1.0 + i as f32);
            want.push((k, node));
        }
        let f = FlatMap::build(&m);
        assert_eq!(f.live, m.entry_count());
        assert!(f.entries.len() >= f.live);
        for (k, node) in want {
            let list = f.list(k);
            assert_eq!(list.len(), m.cell(k).len());
            let e = m.cell(k).iter().find(|e| e.node == node).unwrap();
            let density = if e.hits <= 0.0 {
                0.0
            } else {
                e.hits as f64 / e.distance as f64 * 0.5
            };
            assert!(list.contains(&Entry { node, density }));
        }
        assert!(f.list([100, 100, 100]).is_empty());
        let f2 = FlatMap::build(&DpMap::<2>::new(0.1));
        assert!(f2.list([0, 0]).is_empty());
        assert!(f2.headers.is_empty() && f2.entries.is_empty());
    }

    #[test]
    fn split_halves_rejoin_to_about_48_bits() {
        for x in [0.0, 1.0 / 3.0, 1e-7, 12345.678901234, -2.5e-3, 0.1 / 35.0] {
            let [hi, lo] = split(x);
            assert_eq!(hi, x as f32);
            let back = hi as f64 + lo as f64;
            assert!((back - x).abs() <= x.abs() * 2f64.powi(-47), "{x}: {back}");
        }
        let e = [Entry {
            node: 7,
            density: 0.1,
        }];
        let [hi, lo] = split(0.1);
        let mut w = Vec::new();
        entry_words(&e, false, &mut w);
        assert_eq!(w, [7, hi.to_bits()]);
        w.clear();
        entry_words(&e, true, &mut w);
        assert_eq!(w, [7, hi.to_bits(), lo.to_bits(), 0]);
    }
}
