//! Grid ray traversal (Amanatides & Woo 1987), generic over dimension.
//!
//! Walks every cell a ray segment crosses, in order, with the entry and exit
//! distance along the ray. Used identically by the 2-D grid and the 3-D voxel
//! grid: the laser model sums over these segments and the map update adds
//! their lengths to the cells' `distance`.

/// Integer index of a grid cell (2-D: `[ix, iy]`, 3-D: `[ix, iy, iz]`).
pub type CellKey<const D: usize> = [i32; D];

/// The cell containing `p` (metres) on a grid of `cell` metres.
#[inline]
pub fn cell_of<const D: usize>(p: [f64; D], cell: f64) -> CellKey<D> {
    let mut k = [0i32; D];
    for i in 0..D {
        k[i] = (p[i] / cell).floor() as i32;
    }
    k
}

/// Centre of cell `k` in metres.
#[inline]
pub fn cell_centre<const D: usize>(k: CellKey<D>, cell: f64) -> [f64; D] {
    let mut p = [0.0; D];
    for i in 0..D {
        p[i] = (k[i] as f64 + 0.5) * cell;
    }
    p
}

/// One cell crossed by a ray: the cell and the distances (metres, along the
/// ray from its origin) at which the ray enters and leaves it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Crossing<const D: usize> {
    /// The cell.
    pub cell: CellKey<D>,
    /// Distance from the ray origin where the ray enters the cell (m).
    pub t_in: f64,
    /// Distance from the ray origin where the ray leaves the cell, or the end
    /// of the segment (m).
    pub t_out: f64,
}

/// Iterator over the cells crossed by the segment `origin + t·dir`, `t ∈ [t0, t1]`.
#[derive(Debug, Clone)]
pub struct RayWalk<const D: usize> {
    cell: CellKey<D>,
    step: [i32; D],
    t_next: [f64; D],
    t_delta: [f64; D],
    t: f64,
    t_end: f64,
}

impl<const D: usize> RayWalk<D> {
    /// Starts a walk from `origin` (m) along unit vector `dir`, covering ray
    /// distances `t0..t1` (m), on a grid of `cell` metres.
    pub fn new(origin: [f64; D], dir: [f64; D], t0: f64, t1: f64, cell: f64) -> Self {
        let mut start = [0.0; D];
        for i in 0..D {
            start[i] = origin[i] + dir[i] * t0;
        }
        let k = cell_of(start, cell);
        let mut step = [0i32; D];
        let mut t_next = [f64::INFINITY; D];
        let mut t_delta = [f64::INFINITY; D];
        for i in 0..D {
            if dir[i] > 0.0 {
                step[i] = 1;
                t_delta[i] = cell / dir[i];
                t_next[i] = t0 + ((k[i] + 1) as f64 * cell - start[i]) / dir[i];
            } else if dir[i] < 0.0 {
                step[i] = -1;
                t_delta[i] = -cell / dir[i];
                t_next[i] = t0 + (k[i] as f64 * cell - start[i]) / dir[i];
            }
        }
        Self {
            cell: k,
            step,
            t_next,
            t_delta,
            t: t0,
            t_end: t1,
        }
    }
}

impl<const D: usize> Iterator for RayWalk<D> {
    type Item = Crossing<D>;

    #[inline]
    fn next(&mut self) -> Option<Crossing<D>> {
        if self.t >= self.t_end {
            return None;
        }
        let mut axis = 0;
        for i in 1..D {
            if self.t_next[i] < self.t_next[axis] {
                axis = i;
            }
        }
        let t_out = self.t_next[axis].min(self.t_end);
        let out = Crossing {
            cell: self.cell,
            t_in: self.t,
            t_out,
        };
        self.t = t_out;
        self.cell[axis] += self.step[axis];
        self.t_next[axis] += self.t_delta[axis];
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_aligned_2d_walk_crosses_each_cell_once() {
        let w: Vec<_> = RayWalk::new([0.05, 0.05], [1.0, 0.0], 0.0, 0.35, 0.1).collect();
        let cells: Vec<_> = w.iter().map(|c| c.cell).collect();
        assert_eq!(cells, vec![[0, 0], [1, 0], [2, 0], [3, 0]]);
        assert!((w[0].t_out - 0.05).abs() < 1e-12);
        assert!((w[3].t_out - 0.35).abs() < 1e-12);
    }

    #[test]
    fn lengths_sum_to_segment_length_in_2d_and_3d() {
        let d2 = {
            let a: f64 = 0.7;
            [a.cos(), a.sin()]
        };
        let s: f64 = RayWalk::new([0.013, -0.2], d2, 0.0, 3.3, 0.05)
            .map(|c| c.t_out - c.t_in)
            .sum();
        assert!((s - 3.3).abs() < 1e-9);
        let n = (1.0f64 + 4.0 + 9.0).sqrt();
        let d3 = [1.0 / n, -2.0 / n, 3.0 / n];
        let w: Vec<_> = RayWalk::new([0.01, 0.02, 0.03], d3, 0.5, 2.0, 0.1).collect();
        let s: f64 = w.iter().map(|c| c.t_out - c.t_in).sum();
        assert!((s - 1.5).abs() < 1e-9);
        // consecutive cells are face neighbours: exactly one axis changes by one
        for p in w.windows(2) {
            let diff: i32 = (0..3).map(|i| (p[1].cell[i] - p[0].cell[i]).abs()).sum();
            assert_eq!(diff, 1);
        }
        // each crossing's midpoint lies in its cell
        for c in w.iter().filter(|c| c.t_out - c.t_in > 1e-9) {
            let t = 0.5 * (c.t_in + c.t_out);
            let p = [0.01 + d3[0] * t, 0.02 + d3[1] * t, 0.03 + d3[2] * t];
            assert_eq!(cell_of(p, 0.1), c.cell);
        }
    }

    #[test]
    fn negative_direction_and_cell_of() {
        assert_eq!(cell_of([-0.01, 0.0], 0.1), [-1, 0]);
        let cells: Vec<_> = RayWalk::new([0.05, 0.05], [-1.0, 0.0], 0.0, 0.2, 0.1)
            .map(|c| c.cell)
            .collect();
        assert_eq!(cells, vec![[0, 0], [-1, 0], [-2, 0]]);
    }
}
