//! The DP-map in the flat, pointer-free form the likelihood shader reads.
//!
//! Cells are grouped into bricks (2-D: 16×16, 3-D: 8×8×8, as in the DP-map)
//! found through an open-addressing hash table; each brick has a dense array
//! of `cells + 1` offsets into one entry array, so a cell's observation list
//! is `entries[h[i]..h[i + 1]]`. Entries keep their ancestry node id, and the
//! depth-first numbering travels separately: re-numbering the tree (every
//! step) re-uploads `2 × nodes` words, not the map.

use crate::dpmap::DpMap;

/// Brick side as a power of two, per dimension.
pub(crate) fn brick_bits(dim: usize) -> u32 {
    if dim <= 2 { 4 } else { 3 }
}

/// The brick-table hash; the shader's `brick_hash` is the same function.
#[inline]
pub(crate) fn brick_hash(b: [i32; 3]) -> u32 {
    (b[0] as u32).wrapping_mul(73_856_093)
        ^ (b[1] as u32).wrapping_mul(19_349_663)
        ^ (b[2] as u32).wrapping_mul(83_492_791)
}

/// A flattened map: the arrays bound to the shader.
#[derive(Debug, Clone, Default)]
pub(crate) struct FlatMap {
    /// `[bx, by, bz, brick index]`, index −1 for an empty slot; length a power of two.
    pub table: Vec<[i32; 4]>,
    /// Per brick, `cells_per_brick + 1` offsets into `entries`.
    pub headers: Vec<u32>,
    /// One per observation, in cell order.
    pub entries: Vec<Entry>,
    /// Brick side as a power of two.
    pub brick_bits: u32,
}

/// One observation of the flat map.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Entry {
    /// Ancestry node id.
    pub node: u32,
    /// Stop density, stops per cell length (0 for a cell never seen to stop a beam).
    pub density: f64,
}

/// An f64 as two f32s whose (f64) sum is the value to ~48 bits; `hi` alone
/// is the value rounded to f32. The shader joins them with `wide`.
pub(crate) fn split(x: f64) -> [f32; 2] {
    let hi = x as f32;
    [hi, (x - hi as f64) as f32]
}

impl FlatMap {
    /// `table.len() − 1`.
    pub fn table_mask(&self) -> u32 {
        (self.table.len() - 1) as u32
    }

    /// Flattens `map`. Densities are `hits / distance · cell` (stops per cell
    /// length), 0 where `hits ≤ 0`, as in `LaserModel::stop_probability`.
    pub fn build<const D: usize>(map: &DpMap<D>) -> Self {
        let bits = brick_bits(D);
        let cpb = 1usize << (bits as usize * D);
        let mask = (1i32 << bits) - 1;
        let cell = map.cell_size();
        let mut brick_of: rustc_hash::FxHashMap<[i32; 3], u32> = Default::default();
        let mut keys: Vec<[i32; 3]> = Vec::new();
        // (slot = brick · cpb + local cell, entry), then a counting sort by slot.
        let mut tmp: Vec<(u32, Entry)> = Vec::with_capacity(map.entry_count());
        map.for_each_cell(|k, list| {
            let mut bk = [0i32; 3];
            let mut local = 0usize;
            for i in 0..D {
                bk[i] = k[i] >> bits;
                local |= ((k[i] & mask) as usize) << (bits as usize * i);
            }
            let b = *brick_of.entry(bk).or_insert_with(|| {
                keys.push(bk);
                (keys.len() - 1) as u32
            });
            let slot = (b as usize * cpb + local) as u32;
            for e in list {
                let density = if e.hits <= 0.0 {
                    0.0
                } else {
                    e.hits as f64 / e.distance as f64 * cell
                };
                tmp.push((
                    slot,
                    Entry {
                        node: e.node,
                        density,
                    },
                ));
            }
        });
        let slots = keys.len() * cpb;
        let mut start = vec![0u32; slots + 1];
        for &(s, _) in &tmp {
            start[s as usize + 1] += 1;
        }
        for i in 0..slots {
            start[i + 1] += start[i];
        }
        let mut cursor = start.clone();
        let mut entries = vec![Entry::default(); tmp.len()];
        for (s, e) in tmp {
            let c = &mut cursor[s as usize];
            entries[*c as usize] = e;
            *c += 1;
        }
        let mut headers = Vec::with_capacity(keys.len() * (cpb + 1));
        for b in 0..keys.len() {
            headers.extend_from_slice(&start[b * cpb..=(b + 1) * cpb]);
        }
        let size = (2 * keys.len()).next_power_of_two().max(16);
        let mut table = vec![[0, 0, 0, -1]; size];
        for (i, bk) in keys.iter().enumerate() {
            let mut s = brick_hash(*bk) as usize & (size - 1);
            while table[s][3] >= 0 {
                s = (s + 1) & (size - 1);
            }
            table[s] = [bk[0], bk[1], bk[2], i as i32];
        }
        if headers.is_empty() {
            // Zero-sized storage bindings are invalid; nothing ever reads this.
            headers.push(0);
        }
        if entries.is_empty() {
            entries.push(Entry::default());
        }
        Self {
            table,
            headers,
            entries,
            brick_bits: bits,
        }
    }

    /// The list of cell `k` as the shader finds it (for tests).
    /// The entries as the shader reads them: `(node, density as f32 bits)`
    /// pairs, or with `wide`, `(node, density hi, density lo, 0)` quadruples
    /// (see [`split`]).
    pub fn entry_words(&self, wide: bool) -> Vec<u32> {
        let mut w = Vec::with_capacity(self.entries.len() * if wide { 4 } else { 2 });
        for e in &self.entries {
            let [hi, lo] = split(e.density);
            w.push(e.node);
            w.push(hi.to_bits());
            if wide {
                w.extend([lo.to_bits(), 0]);
            }
        }
        w
    }

    #[cfg(test)]
    fn list<const D: usize>(&self, k: [i32; D]) -> &[Entry] {
        let bits = self.brick_bits;
        let mask = (1i32 << bits) - 1;
        let cpb = 1usize << (bits as usize * D);
        let mut bk = [0i32; 3];
        let mut local = 0usize;
        for i in 0..D {
            bk[i] = k[i] >> bits;
            local |= ((k[i] & mask) as usize) << (bits as usize * i);
        }
        let m = self.table_mask() as usize;
        let mut s = brick_hash(bk) as usize & m;
        loop {
            let t = self.table[s];
            if t[3] < 0 {
                return &[];
            }
            if t[..3] == bk {
                let h = t[3] as usize * (cpb + 1) + local;
                return &self.entries[self.headers[h] as usize..self.headers[h + 1] as usize];
            }
            s = (s + 1) & m;
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
        assert_eq!(f.entries.len(), m.entry_count());
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
    }

    #[test]
    fn split_halves_rejoin_to_about_48_bits() {
        for x in [0.0, 1.0 / 3.0, 1e-7, 12345.678901234, -2.5e-3, 0.1 / 35.0] {
            let [hi, lo] = split(x);
            assert_eq!(hi, x as f32);
            let back = hi as f64 + lo as f64;
            assert!((back - x).abs() <= x.abs() * 2f64.powi(-47), "{x}: {back}");
        }
        let f = FlatMap {
            entries: vec![Entry {
                node: 7,
                density: 0.1,
            }],
            ..Default::default()
        };
        let [hi, lo] = split(0.1);
        assert_eq!(f.entry_words(false), [7, hi.to_bits()]);
        assert_eq!(f.entry_words(true), [7, hi.to_bits(), lo.to_bits(), 0]);
    }
}
