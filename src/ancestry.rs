//! The ancestry tree of DP-SLAM (dissertation ch. 4–5).
//!
//! Every particle generation adds one node per surviving particle, as a child
//! of the node of the particle it was sampled from. A particle's map is the
//! union of the observations made by the nodes on its path to the root, the
//! most recent one winning in each cell.
//!
//! Maintenance keeps the tree O(particles): childless nodes that no particle
//! holds are removed (with their observations, by the caller), and a node with
//! a single child absorbs that child (unless the caller holds it back:
//! [`AncestryTree::collapse`]). Both are reported as [`Change`]s so that
//! the DP-map can apply the same edits to its observation lists. Node ids of
//! removed nodes are recycled.
//!
//! For O(1) ancestry queries the tree is numbered in depth-first order once per
//! iteration ([`AncestryTree::number`]): `a` is an ancestor-or-self of `b` iff
//! `enter[a] ≤ enter[b] ≤ exit[a]`. The same two arrays are the flat,
//! pointer-free form of the tree that the GPU path reads.

use smallvec::SmallVec;

/// Index of a node in the tree's arena.
pub type NodeId = u32;

/// Marks "no node" (the root's parent).
pub const NO_NODE: NodeId = NodeId::MAX;

/// The root's id in every tree: [`AncestryTree::new`] makes it first, and it
/// is never removed or renamed (the DP-map relies on it, see `dpmap`).
pub const ROOT: NodeId = 0;

#[derive(Debug, Clone)]
struct Node<T> {
    parent: NodeId,
    children: SmallVec<[NodeId; 4]>,
    alive: bool,
    /// What the node recorded, oldest first (e.g. the poses of its generations).
    payload: Vec<T>,
}

/// An edit made by [`AncestryTree::maintain`], to be mirrored by the map.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Change {
    /// The node was deleted: its observations must be deleted.
    Removed(NodeId),
    /// `child` was merged into its parent `into`: the child's observations now
    /// belong to `into` and replace `into`'s own where both have one.
    Merged {
        /// The merged node.
        child: NodeId,
        /// Its parent, which takes over its observations.
        into: NodeId,
    },
}

/// Depth-first numbering of the live tree: the flat form used for ancestry tests.
#[derive(Debug, Clone, Default)]
pub struct Numbering {
    /// Pre-order index of each node (indexed by [`NodeId`]; dead nodes: `u32::MAX`).
    pub enter: Vec<u32>,
    /// Largest pre-order index in each node's subtree.
    pub exit: Vec<u32>,
}

impl Numbering {
    /// Whether `a` is an ancestor of `b` or `b` itself.
    #[inline]
    pub fn is_ancestor_or_self(&self, a: NodeId, b: NodeId) -> bool {
        let eb = self.enter[b as usize];
        self.enter[a as usize] <= eb && eb <= self.exit[a as usize]
    }
}

/// The ancestry tree. `T` is the per-node payload (poses of the trajectory).
#[derive(Debug, Clone)]
pub struct AncestryTree<T> {
    nodes: Vec<Node<T>>,
    free: Vec<NodeId>,
    root: NodeId,
    live: usize,
}

impl<T: Clone> AncestryTree<T> {
    /// A tree holding only the root, with `payload` as the root's first record.
    pub fn new(payload: Vec<T>) -> Self {
        Self {
            nodes: vec![Node {
                parent: NO_NODE,
                children: SmallVec::new(),
                alive: true,
                payload,
            }],
            free: Vec::new(),
            root: ROOT,
            live: 1,
        }
    }

    /// The root node.
    pub fn root(&self) -> NodeId {
        self.root
    }

    /// Number of live nodes.
    pub fn len(&self) -> usize {
        self.live
    }

    /// Whether only the root is left.
    pub fn is_empty(&self) -> bool {
        self.live <= 1
    }

    /// Size of the id space (largest id + 1), for arrays indexed by node.
    pub fn capacity(&self) -> usize {
        self.nodes.len()
    }

    /// Whether `n` is a live node.
    pub fn is_alive(&self, n: NodeId) -> bool {
        self.nodes.get(n as usize).is_some_and(|x| x.alive)
    }

    /// Parent of `n` ([`NO_NODE`] for the root).
    pub fn parent(&self, n: NodeId) -> NodeId {
        self.nodes[n as usize].parent
    }

    /// Children of `n`.
    pub fn children(&self, n: NodeId) -> &[NodeId] {
        &self.nodes[n as usize].children
    }

    /// Payload records of `n`, oldest first.
    pub fn payload(&self, n: NodeId) -> &[T] {
        &self.nodes[n as usize].payload
    }

    /// Adds a child of `parent` holding `payload`; reuses a freed id if any.
    pub fn add_child(&mut self, parent: NodeId, payload: T) -> NodeId {
        self.add_child_records(parent, vec![payload])
    }

    /// Adds a child of `parent` holding the records `payload`, oldest first
    /// (e.g. every pose of a trajectory segment); reuses a freed id if any.
    pub fn add_child_records(&mut self, parent: NodeId, payload: Vec<T>) -> NodeId {
        debug_assert!(self.is_alive(parent));
        let node = Node {
            parent,
            children: SmallVec::new(),
            alive: true,
            payload,
        };
        let id = match self.free.pop() {
            Some(id) => {
                self.nodes[id as usize] = node;
                id
            }
            None => {
                self.nodes.push(node);
                (self.nodes.len() - 1) as NodeId
            }
        };
        self.nodes[parent as usize].children.push(id);
        self.live += 1;
        id
    }

    fn free_node(&mut self, n: NodeId) {
        let node = &mut self.nodes[n as usize];
        node.alive = false;
        node.children = SmallVec::new();
        node.payload = Vec::new();
        node.parent = NO_NODE;
        self.free.push(n);
        self.live -= 1;
    }

    /// Prunes and collapses the tree so that its leaves are exactly the nodes
    /// in `held` (the current particles' nodes). Entries of `held` are rewritten
    /// when a held node is merged into its parent. Returns the edits in the
    /// order they were made; the map must apply them in that order.
    pub fn maintain(&mut self, held: &mut [NodeId]) -> Vec<Change> {
        let mut changes = self.remove_dead(held);
        changes.extend(self.collapse(held, |_| true));
        changes
    }

    /// Per node id: whether a particle holds it.
    fn held_mask(&self, held: &[NodeId]) -> Vec<bool> {
        let mut is_held = vec![false; self.nodes.len()];
        for &h in held {
            is_held[h as usize] = true;
        }
        is_held
    }

    /// The first half of [`AncestryTree::maintain`]: removes the childless
    /// nodes that `held` does not hold, and the parents that leaves childless.
    pub fn remove_dead(&mut self, held: &[NodeId]) -> Vec<Change> {
        let mut changes = Vec::new();
        let is_held = self.held_mask(held);
        // Prune: childless, unheld nodes die, and may leave their parents childless.
        let mut stack: Vec<NodeId> = (0..self.nodes.len() as NodeId)
            .filter(|&n| {
                let x = &self.nodes[n as usize];
                x.alive && x.children.is_empty() && !is_held[n as usize] && n != self.root
            })
            .collect();
        while let Some(n) = stack.pop() {
            let parent = self.nodes[n as usize].parent;
            changes.push(Change::Removed(n));
            self.free_node(n);
            let siblings = &mut self.nodes[parent as usize].children;
            if let Some(i) = siblings.iter().position(|&c| c == n) {
                siblings.swap_remove(i);
            }
            if siblings.is_empty() && !is_held[parent as usize] && parent != self.root {
                stack.push(parent);
            }
        }
        changes
    }

    /// The second half of [`AncestryTree::maintain`]: a node whose only
    /// child `c` passes `absorb(c)` absorbs it (repeatedly, down the
    /// chain); entries of `held` are rewritten to the absorbing node. The
    /// filter holds back a child that several particles' copies still use
    /// (`filter::Copies`): such a node keeps an only child.
    pub fn collapse(
        &mut self,
        held: &mut [NodeId],
        absorb: impl Fn(NodeId) -> bool,
    ) -> Vec<Change> {
        let mut changes = Vec::new();
        let mut is_held = self.held_mask(held);
        // Collapse: a node with one child absorbs it. Children are created after
        // their parents, so visiting parents before children is a pre-order walk.
        let mut order = Vec::with_capacity(self.live);
        let mut stack = vec![self.root];
        while let Some(n) = stack.pop() {
            order.push(n);
            stack.extend(self.nodes[n as usize].children.iter().copied());
        }
        for n in order {
            if !self.nodes[n as usize].alive {
                continue;
            }
            while self.nodes[n as usize].children.len() == 1 {
                let c = self.nodes[n as usize].children[0];
                if !absorb(c) {
                    break;
                }
                let child = std::mem::take(&mut self.nodes[c as usize]);
                for &g in &child.children {
                    self.nodes[g as usize].parent = n;
                }
                let node = &mut self.nodes[n as usize];
                node.children = child.children;
                node.payload.extend(child.payload);
                // `take` left a default (dead) node behind; count it as freed.
                self.nodes[c as usize].parent = NO_NODE;
                self.free.push(c);
                self.live -= 1;
                if is_held[c as usize] {
                    for h in held.iter_mut().filter(|h| **h == c) {
                        *h = n;
                    }
                    is_held[n as usize] = true;
                }
                changes.push(Change::Merged { child: c, into: n });
            }
        }
        changes
    }

    /// Numbers the live tree in depth-first pre-order.
    pub fn number(&self, out: &mut Numbering) {
        out.enter.clear();
        out.enter.resize(self.nodes.len(), u32::MAX);
        out.exit.clear();
        out.exit.resize(self.nodes.len(), 0);
        let mut counter = 0u32;
        // (node, children visited) pairs; exit is set when the node is popped.
        let mut stack: Vec<(NodeId, bool)> = vec![(self.root, false)];
        while let Some((n, done)) = stack.pop() {
            if done {
                out.exit[n as usize] = counter - 1;
                continue;
            }
            out.enter[n as usize] = counter;
            counter += 1;
            stack.push((n, true));
            for &c in self.nodes[n as usize].children.iter().rev() {
                stack.push((c, false));
            }
        }
    }

    /// Payload records on the path from the root to `leaf`, oldest first.
    pub fn lineage(&self, leaf: NodeId) -> Vec<T> {
        let mut path = Vec::new();
        let mut n = leaf;
        while n != NO_NODE {
            path.push(n);
            n = self.nodes[n as usize].parent;
        }
        path.iter()
            .rev()
            .flat_map(|&n| self.nodes[n as usize].payload.iter().cloned())
            .collect()
    }

    /// Depth of the deepest leaf (root = 0).
    pub fn depth(&self) -> usize {
        let mut best = 0;
        let mut stack = vec![(self.root, 0usize)];
        while let Some((n, d)) = stack.pop() {
            best = best.max(d);
            for &c in &self.nodes[n as usize].children {
                stack.push((c, d + 1));
            }
        }
        best
    }
}

impl<T> Default for Node<T> {
    fn default() -> Self {
        Self {
            parent: NO_NODE,
            children: SmallVec::new(),
            alive: false,
            payload: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Checks the structural invariants: every live non-root node is reachable,
    /// every internal non-root node has ≥ 2 children, leaves are exactly `held`.
    fn check_invariants(t: &AncestryTree<u32>, held: &[NodeId]) {
        let mut seen = 0;
        let mut stack = vec![t.root()];
        while let Some(n) = stack.pop() {
            seen += 1;
            let ch = t.children(n);
            if n != t.root() {
                assert!(ch.len() != 1, "node {n} has a single child");
                if ch.is_empty() {
                    assert!(held.contains(&n), "leaf {n} is not held");
                }
            }
            for &c in ch {
                assert_eq!(t.parent(c), n);
                stack.push(c);
            }
        }
        assert_eq!(seen, t.len());
        for &h in held {
            assert!(t.is_alive(h));
            assert!(t.children(h).is_empty());
        }
    }

    #[test]
    fn prune_removes_dead_branches_and_collapse_merges_only_children() {
        let mut t = AncestryTree::new(vec![0u32]);
        let r = t.root();
        let a = t.add_child(r, 1);
        let b = t.add_child(r, 1);
        let a1 = t.add_child(a, 2);
        let a2 = t.add_child(a, 2);
        let b1 = t.add_child(b, 2);
        // Only a1 and a2 survive: b and b1 die, then root has the single child a.
        let mut held = vec![a1, a2];
        let changes = t.maintain(&mut held);
        assert!(changes.contains(&Change::Removed(b1)));
        assert!(changes.contains(&Change::Removed(b)));
        assert!(changes.contains(&Change::Merged { child: a, into: r }));
        assert_eq!(t.len(), 3);
        assert_eq!(t.payload(r), &[0, 1]);
        assert_eq!(t.lineage(a1), vec![0, 1, 2]);
        check_invariants(&t, &held);
        // Removed-before-merged order for each node id.
        let pos_b1 = changes
            .iter()
            .position(|c| *c == Change::Removed(b1))
            .unwrap();
        let pos_b = changes
            .iter()
            .position(|c| *c == Change::Removed(b))
            .unwrap();
        assert!(pos_b1 < pos_b);
    }

    #[test]
    fn collapse_keeps_only_children_that_absorb_refuses() {
        let mut t = AncestryTree::new(vec![0u32]);
        let r = t.root();
        let a = t.add_child(r, 1);
        let a1 = t.add_child(a, 2);
        let mut held = vec![a1, a1];
        assert!(t.remove_dead(&held).is_empty());
        // `a` may not be absorbed, `a1` may: the chain keeps root → a.
        let ch = t.collapse(&mut held, |c| c != a);
        assert_eq!(ch, vec![Change::Merged { child: a1, into: a }]);
        assert_eq!(held, vec![a, a]);
        assert_eq!(t.children(r), &[a]);
        assert_eq!(t.lineage(a), vec![0, 1, 2]);
    }

    #[test]
    fn held_leaf_merged_into_parent_is_renamed() {
        let mut t = AncestryTree::new(vec![0u32]);
        let r = t.root();
        let a = t.add_child(r, 1);
        let b = t.add_child(r, 1);
        let a1 = t.add_child(a, 2);
        let b1 = t.add_child(b, 2);
        let mut held = vec![a1, b1];
        let ch = t.maintain(&mut held);
        // a and b each had one child: the children merge up, the particles now hold a and b.
        assert_eq!(held, vec![a, b]);
        assert!(ch.contains(&Change::Merged { child: a1, into: a }));
        assert_eq!(t.lineage(a), vec![0, 1, 2]);
        check_invariants(&t, &held);
        // ids are recycled
        let c = t.add_child(a, 3);
        assert!(c == a1 || c == b1);
    }

    #[test]
    fn random_generations_keep_tree_linear_in_particles() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut t = AncestryTree::new(vec![0u32]);
        let n = 20;
        let mut held = vec![t.root(); n];
        let mut num = Numbering::default();
        for g in 1..300u32 {
            let parents: Vec<NodeId> = (0..n).map(|_| held[rng.random_range(0..n)]).collect();
            held = parents.iter().map(|&p| t.add_child(p, g)).collect();
            t.maintain(&mut held);
            check_invariants(&t, &held);
            assert!(
                t.len() <= 2 * n,
                "tree has {} nodes for {n} particles",
                t.len()
            );
            // DFS numbering agrees with walking parents.
            t.number(&mut num);
            for &h in &held {
                let mut m = h;
                while m != NO_NODE {
                    assert!(num.is_ancestor_or_self(m, h));
                    m = t.parent(m);
                }
                for &o in &held {
                    if o != h {
                        assert!(!num.is_ancestor_or_self(o, h));
                    }
                }
                // one payload per generation on every lineage
                assert_eq!(t.lineage(h), (0..=g).collect::<Vec<_>>());
            }
        }
    }
}
