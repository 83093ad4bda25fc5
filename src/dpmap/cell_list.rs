//! A cell's observation list in 16 bytes.
//!
//! Most allocated cells hold no entry or one (bricks are allocated whole,
//! and particles mostly agree), and the bricks' lists are the largest part
//! of the map: a list is therefore one entry stored inline, or a pointer to
//! a heap list that carries its own length and capacity ([`ThinVec`]). The
//! length is also kept inline, in the padding beside the pointer: a lookup
//! that only needs to know whether a list is long (the view cache's test)
//! then reads the brick alone, not the heap list's header, which on large
//! particle sets is a cache miss per cell.
//! `SmallVec<[Entry; 1]>`, the general-purpose answer, takes 24 bytes a
//! cell; on mit-csail that was 40 MB of the map's peak.

use super::Entry;
use std::ops::{Deref, DerefMut};
use thin_vec::ThinVec;

/// A cell's observation list (unordered); dereferences to `[Entry]`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CellList(Repr);

#[derive(Debug, Clone, Default, PartialEq)]
enum Repr {
    #[default]
    Empty,
    One(Entry),
    /// Never shorter than two entries: shorter lists go back inline. The
    /// `u32` is the vector's length, kept equal to it by every method that
    /// changes it.
    Many(u32, ThinVec<Entry>),
}

const _: () = assert!(std::mem::size_of::<CellList>() == 16);

impl CellList {
    /// An empty list (no allocation).
    pub const fn new() -> Self {
        Self(Repr::Empty)
    }

    /// Appends `e`.
    pub fn push(&mut self, e: Entry) {
        match &mut self.0 {
            Repr::Empty => self.0 = Repr::One(e),
            Repr::One(a) => {
                let mut v = ThinVec::with_capacity(2);
                v.push(*a);
                v.push(e);
                self.0 = Repr::Many(2, v);
            }
            Repr::Many(n, v) => {
                v.push(e);
                *n = v.len() as u32;
            }
        }
    }

    /// Number of entries, read from the list itself (no heap access).
    #[inline]
    pub fn len(&self) -> usize {
        match &self.0 {
            Repr::Empty => 0,
            Repr::One(_) => 1,
            Repr::Many(n, _) => *n as usize,
        }
    }

    /// Whether the list holds no entry.
    #[inline]
    pub fn is_empty(&self) -> bool {
        matches!(self.0, Repr::Empty)
    }

    /// Removes entry `i` by moving the last entry into its place; panics if
    /// `i` is out of bounds.
    pub fn swap_remove(&mut self, i: usize) -> Entry {
        let e = match &mut self.0 {
            Repr::Empty => panic!("swap_remove({i}) on an empty cell list"),
            Repr::One(a) => {
                assert_eq!(i, 0, "swap_remove({i}) on a one-entry cell list");
                let a = *a;
                self.0 = Repr::Empty;
                return a;
            }
            Repr::Many(n, v) => {
                let e = v.swap_remove(i);
                *n = v.len() as u32;
                e
            }
        };
        self.go_inline_if_short();
        e
    }

    /// Keeps the first `len` entries.
    pub fn truncate(&mut self, len: usize) {
        match &mut self.0 {
            Repr::Empty => {}
            Repr::One(_) => {
                if len == 0 {
                    self.0 = Repr::Empty;
                }
            }
            Repr::Many(n, v) => {
                v.truncate(len);
                *n = v.len() as u32;
                self.go_inline_if_short();
            }
        }
    }

    /// Whether the entries live on the heap.
    pub fn spilled(&self) -> bool {
        matches!(self.0, Repr::Many(..))
    }

    /// Entries the list holds without reallocating.
    pub fn capacity(&self) -> usize {
        match &self.0 {
            Repr::Empty | Repr::One(_) => 1,
            Repr::Many(_, v) => v.capacity(),
        }
    }

    /// Heap bytes held (0 when inline), header included.
    pub fn heap_bytes(&self) -> usize {
        match &self.0 {
            Repr::Empty | Repr::One(_) => 0,
            Repr::Many(_, v) => {
                2 * std::mem::size_of::<usize>() + v.capacity() * size_of::<Entry>()
            }
        }
    }

    /// Lists swell to O(particles) where particles disagree and shrink back
    /// once they agree: gives the memory back when the list uses a quarter
    /// of its capacity, or the map would grow with time rather than area.
    pub fn give_back_spare(&mut self) {
        if let Repr::Many(_, v) = &mut self.0
            && v.len() * 4 <= v.capacity()
        {
            v.shrink_to_fit();
        }
    }

    fn go_inline_if_short(&mut self) {
        if let Repr::Many(_, v) = &self.0 {
            match v.len() {
                0 => self.0 = Repr::Empty,
                1 => self.0 = Repr::One(v[0]),
                _ => {}
            }
        }
    }
}

impl Deref for CellList {
    type Target = [Entry];

    fn deref(&self) -> &[Entry] {
        match &self.0 {
            Repr::Empty => &[],
            Repr::One(e) => std::slice::from_ref(e),
            Repr::Many(_, v) => v,
        }
    }
}

impl DerefMut for CellList {
    fn deref_mut(&mut self) -> &mut [Entry] {
        match &mut self.0 {
            Repr::Empty => &mut [],
            Repr::One(e) => std::slice::from_mut(e),
            Repr::Many(_, v) => v,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn e(node: u32) -> Entry {
        Entry {
            node,
            hits: node as f32,
            distance: 0.5 * node as f32,
        }
    }

    fn nodes(l: &CellList) -> Vec<u32> {
        // The inline length always agrees with the entries.
        let entries: &[Entry] = l;
        assert_eq!(l.len(), entries.len());
        assert_eq!(l.is_empty(), entries.is_empty());
        l.iter().map(|e| e.node).collect()
    }

    #[test]
    fn grows_from_inline_to_heap_and_back() {
        let mut l = CellList::new();
        assert!(l.is_empty() && !l.spilled());
        l.push(e(1));
        assert_eq!(nodes(&l), [1]);
        assert!(!l.spilled(), "one entry stays inline");
        for n in 2..=40 {
            l.push(e(n));
        }
        assert!(l.spilled());
        assert_eq!(nodes(&l), (1..=40).collect::<Vec<_>>());
        assert_eq!(l.swap_remove(0), e(1));
        assert_eq!(nodes(&l)[..2], [40, 2]);
        l[1].hits = 7.0;
        assert_eq!(l[1].hits, 7.0);
        l.truncate(2);
        assert_eq!(nodes(&l), [40, 2]);
        l.give_back_spare();
        assert!(l.capacity() < 40, "spare capacity given back");
        assert_eq!(l.swap_remove(0), e(40));
        assert_eq!(nodes(&l), [2]);
        assert!(
            !l.spilled() && l.heap_bytes() == 0,
            "one entry goes back inline"
        );
        assert_eq!(l.swap_remove(0).node, 2);
        assert!(l.is_empty());
        l.push(e(3));
        l.push(e(4));
        l.truncate(0);
        assert!(l.is_empty() && !l.spilled());
    }
}
