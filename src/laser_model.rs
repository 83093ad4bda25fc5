//! The stochastic laser-penetration model (dissertation ch. 3), generic over
//! dimension.
//!
//! Each cell has a density ρ = hits / distance (stops per metre of laser path
//! through it). A beam crossing length `l` of a cell stops there with
//! probability `1 − exp(−ρ·l)`; unseen cells use a prior density. The
//! likelihood of a measured range `r` is
//! `Σ_cells P(reach)·P(stop)·exp(−err²/(2σ²))`, `err` = distance from the
//! cell to the measured endpoint, normalised by the probability that the beam
//! stopped at all within the trace, and floored (background noise). Max-range
//! ("no return") beams instead score the probability of passing the trace.

use crate::config::LaserConfig;
use crate::raycast::{CellKey, RayWalk, cell_of};

/// Read access to one particle's view of the map.
pub trait Occupancy<const D: usize> {
    /// `(hits, distance m)` of cell `k`, or `None` if this particle never saw it.
    fn lookup(&mut self, k: CellKey<D>) -> Option<(f32, f32)>;

    /// As [`Occupancy::lookup`], for tracing a beam: where the cell has no
    /// hits, the path length may be left out (`Some((0.0, 0.0))`): the
    /// stop probability is 0 whatever it is. Occupancies that can tell such
    /// cells apart cheaply answer them here without a full look-up.
    fn lookup_for_trace(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        self.lookup(k)
    }
}

impl<const D: usize> Occupancy<D> for crate::dpmap::MapView<'_, D> {
    #[inline]
    fn lookup(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        crate::dpmap::MapView::lookup(self, k)
    }

    #[inline]
    fn lookup_for_trace(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        crate::dpmap::MapView::lookup_for_trace(self, k)
    }
}

impl<const D: usize> Occupancy<D> for crate::dpmap::CachedView<'_, '_, D> {
    #[inline]
    fn lookup(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        self.view.lookup_cached(self.cache, k)
    }

    #[inline]
    fn lookup_for_trace(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        self.view.lookup_for_trace_cached(self.cache, k)
    }
}

/// Which part of the beam to trace.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trace {
    /// Sensor to endpoint + `trace_past`: the full likelihood.
    Full,
    /// A short window around the endpoint: the culling heuristic of the release.
    Quick,
}

/// The penetration model with all lengths in metres.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserModel {
    /// Cell size, m.
    pub cell: f64,
    /// Range-error variance σ², m².
    pub variance: f64,
    /// Lower bound of a beam's likelihood.
    pub floor: f64,
    /// Trace length past the endpoint, m.
    pub trace_past: f64,
    /// Errors at or beyond this (m) contribute nothing.
    pub max_error: f64,
    /// Prior density of unseen cells, stops per metre.
    pub prior_density: f64,
    /// Prior distance of a new entry, m.
    pub prior_distance: f64,
    /// Quick trace window before the endpoint, m.
    pub quick_before: f64,
    /// Quick trace window after the endpoint, m.
    pub quick_after: f64,
    /// Usable range, m: "no return" beams are traced to here.
    pub max_range: f64,
    /// Longest gap (m) between consecutive returns that
    /// [`LaserModel::surface_update`] fills; 0: off.
    pub fill_gap: f64,
    /// How far (m) the neighbouring returns may lie off a filled pair's line.
    pub fill_tolerance: f64,
    /// Hits added to each filled cell.
    pub fill_hits: f32,
}

impl LaserModel {
    /// The model for `cfg` on a grid of `cell` metres with usable range `max_range` (m).
    pub fn new(cfg: &LaserConfig, cell: f64, max_range: f64) -> Self {
        Self {
            cell,
            variance: cfg.variance,
            floor: cfg.beam_floor,
            trace_past: cfg.trace_past_cells * cell,
            max_error: cfg.max_error_cells * cell,
            prior_density: 1.0 / cfg.prior_stop_every,
            prior_distance: cfg.prior_distance_cells * cell,
            quick_before: cfg.quick_before_cells * cell,
            quick_after: cfg.quick_after_cells * cell,
            max_range,
            fill_gap: cfg.surface_fill_gap,
            fill_tolerance: cfg.surface_fill_tolerance,
            fill_hits: cfg.surface_fill_hits as f32,
        }
    }

    /// Probability that a beam crossing `len` metres of a cell stops there.
    #[inline]
    pub fn stop_probability(&self, obs: Option<(f32, f32)>, len: f64) -> f64 {
        match obs {
            None => 1.0 - (-self.prior_density * len).exp(),
            Some((h, _)) if h <= 0.0 => 0.0,
            Some((h, d)) => stop_probability(h, d, len),
        }
    }

    /// Log-likelihood of one beam from `origin` along unit `dir` (map frame)
    /// with measured `range` (m); `no_return` beams have `range` = usable max.
    pub fn beam_log_likelihood<const D: usize, V: Occupancy<D>>(
        &self,
        view: &mut V,
        origin: [f64; D],
        dir: [f64; D],
        range: f64,
        no_return: bool,
        trace: Trace,
    ) -> f64 {
        let (t0, t1) = match (trace, no_return) {
            (Trace::Quick, true) => return 0.0,
            (Trace::Quick, false) => (
                (range - self.quick_before).max(0.0),
                range + self.quick_after,
            ),
            (Trace::Full, true) => (0.0, self.max_range),
            (Trace::Full, false) => (
                0.0,
                (range + self.trace_past).min(self.max_range.max(range)),
            ),
        };
        let two_var = 2.0 * self.variance;
        let mut reach = 1.0f64;
        let mut eval = 0.0f64;
        for c in RayWalk::new(origin, dir, t0, t1, self.cell) {
            let len = c.t_out - c.t_in;
            let p = reach * self.stop_probability(view.lookup_for_trace(c.cell), len);
            if p > 0.0 {
                let err = (0.5 * (c.t_in + c.t_out) - range).abs();
                if err < self.max_error {
                    eval += p * (-err * err / two_var).exp();
                }
                reach -= p;
            }
        }
        let l = if no_return {
            eval + reach
        } else if reach >= 1.0 {
            0.0
        } else {
            eval / (1.0 - reach)
        };
        l.max(self.floor).ln()
    }

    /// Adds one beam's observation to `acc` as `(cell, hits, distance m)`
    /// increments: path length through every crossed cell and, unless
    /// `no_return`, one hit in the endpoint cell.
    pub fn trace_update<const D: usize>(
        &self,
        origin: [f64; D],
        dir: [f64; D],
        range: f64,
        no_return: bool,
        mut acc: impl FnMut(CellKey<D>, f32, f32),
    ) {
        let end = range.min(self.max_range.max(range));
        let mut last = None;
        for c in RayWalk::new(origin, dir, 0.0, end, self.cell) {
            if let Some(k) = last.replace(c) {
                acc(k.cell, 0.0, (k.t_out - k.t_in) as f32);
            }
        }
        if let Some(k) = last {
            let hit = if no_return { 0.0 } else { 1.0 };
            acc(k.cell, hit, (k.t_out - k.t_in) as f32);
        }
    }

    /// Adds the surface between consecutive returns of one scan to `acc` as
    /// `(cell, hits, distance m)` increments: `fill_hits` hits, no path, in
    /// each cell strictly between the two endpoint cells. `ends` holds each beam's
    /// endpoint (map frame, m) in scan order, `None` for a "no return",
    /// which breaks the surface. A pair is filled when it lies at most
    /// `fill_gap` apart and, unless it is at most two cells apart, the
    /// returns on either side lie within `fill_tolerance` of its line: one
    /// straight surface sampled four times, not a doorway's two jambs.
    pub fn surface_update<const D: usize>(
        &self,
        ends: &[Option<[f64; D]>],
        mut acc: impl FnMut(CellKey<D>, f32, f32),
    ) {
        if self.fill_gap <= 0.0 {
            return;
        }
        let near = 2.0 * self.cell;
        for i in 0..ends.len().saturating_sub(1) {
            let (Some(a), Some(b)) = (ends[i], ends[i + 1]) else {
                continue;
            };
            let len = distance(a, b);
            if len <= 0.0 || len > self.fill_gap {
                continue;
            }
            let dir: [f64; D] = std::array::from_fn(|k| (b[k] - a[k]) / len);
            if len > near {
                let before = i.checked_sub(1).and_then(|j| ends[j]);
                let after = ends.get(i + 2).copied().flatten();
                let on_line = |q: Option<[f64; D]>| {
                    q.is_some_and(|q| off_line(q, a, dir) <= self.fill_tolerance)
                };
                if !(on_line(before) && on_line(after)) {
                    continue;
                }
            }
            let (first, last) = (cell_of(a, self.cell), cell_of(b, self.cell));
            for c in RayWalk::new(a, dir, 0.0, len, self.cell) {
                if c.cell != first && c.cell != last {
                    acc(c.cell, self.fill_hits, 0.0);
                }
            }
        }
    }
}

/// Euclidean distance between `a` and `b` (m).
fn distance<const D: usize>(a: [f64; D], b: [f64; D]) -> f64 {
    (0..D).map(|k| (b[k] - a[k]).powi(2)).sum::<f64>().sqrt()
}

/// Distance (m) of `q` from the line through `a` along unit `dir`.
fn off_line<const D: usize>(q: [f64; D], a: [f64; D], dir: [f64; D]) -> f64 {
    let w: [f64; D] = std::array::from_fn(|k| q[k] - a[k]);
    let t: f64 = (0..D).map(|k| w[k] * dir[k]).sum();
    (0..D)
        .map(|k| (w[k] - t * dir[k]).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Probability that a beam stops within `len` m of a cell that stopped
/// `hits` beams over `distance` m of laser path: `1 − exp(−ρ·len)` with
/// density ρ = hits / distance (stops per metre). The laser model and the
/// scan matcher's likelihood field both read a cell this way.
pub fn stop_probability(hits: f32, distance: f32, len: f64) -> f64 {
    1.0 - (-(hits as f64 / distance as f64) * len).exp()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rustc_hash::FxHashMap;

    struct Grid(FxHashMap<CellKey<2>, (f32, f32)>);
    impl Occupancy<2> for Grid {
        fn lookup(&mut self, k: CellKey<2>) -> Option<(f32, f32)> {
            self.0.get(&k).copied()
        }
    }

    fn model() -> LaserModel {
        LaserModel::new(&LaserConfig::default(), 0.1, 10.0)
    }

    /// A free corridor of known cells and one wall cell with density ρ.
    fn corridor(wall_x: i32, hits: f32, dist: f32) -> Grid {
        let mut g = FxHashMap::default();
        for x in 0..wall_x {
            g.insert([x, 0], (0.0, 1.0));
        }
        g.insert([wall_x, 0], (hits, dist));
        Grid(g)
    }

    #[test]
    fn single_wall_cell_matches_hand_computation() {
        let m = model();
        let mut g = corridor(20, 2.0, 0.2); // ρ = 10 /m, wall cell spans x ∈ [2.0, 2.1)
        // Beam along +x from the middle of cell 0, measured 2.05 m: the wall cell
        // is the only possible stop before 2.05 + 2 m (beyond it: unknown cells).
        let origin = [0.05, 0.05];
        let ll = m.beam_log_likelihood(&mut g, origin, [1.0, 0.0], 2.0, false, Trace::Full);
        // Hand computation: cells are [x·0.1, x·0.1+0.1) shifted by the origin 0.05.
        // The wall cell is crossed from t = 1.95 to 2.05 (len 0.1), midpoint 2.0 → err 0.
        let p_wall = 1.0 - (-10.0f64 * 0.1).exp();
        // Unknown cells after the wall (t from 2.05 to 4.0 = min(2+2, 10)).
        let mut reach = 1.0 - p_wall;
        let mut eval = p_wall; // err = 0
        let mut t = 2.05;
        while t < 4.0 - 1e-9 {
            let t_out = (t + 0.1f64).min(4.0);
            let p = reach * (1.0 - (-(1.0 / 8.0) * (t_out - t)).exp());
            let err: f64 = 0.5 * (t + t_out) - 2.0;
            if err < 2.0 {
                eval += p * (-err * err / (2.0 * m.variance)).exp();
            }
            reach -= p;
            t = t_out;
        }
        let expected = (eval / (1.0 - reach)).max(m.floor).ln();
        assert!((ll - expected).abs() < 1e-6, "{ll} vs {expected}");
        // A reading 0.5 m short of the wall is much less likely.
        let short = m.beam_log_likelihood(&mut g, origin, [1.0, 0.0], 1.5, false, Trace::Full);
        assert!(short < ll - 1.0);
        // Floor: never below the configured background.
        assert!(short >= m.floor.ln() - 1e-12);
    }

    #[test]
    fn no_return_beam_scores_passing_probability() {
        let m = model();
        // Entirely free known corridor to the max range: P(pass) = 1 → log 0.
        let mut g = corridor(200, 0.0, 1.0);
        let ll = m.beam_log_likelihood(&mut g, [0.05, 0.05], [1.0, 0.0], 10.0, true, Trace::Full);
        assert!(ll.abs() < 1e-12);
        // A solid wall in the way makes "no return" unlikely (down to the floor).
        let mut g = corridor(20, 100.0, 0.1);
        let ll = m.beam_log_likelihood(&mut g, [0.05, 0.05], [1.0, 0.0], 10.0, true, Trace::Full);
        assert!((ll - m.floor.ln()).abs() < 1e-9);
        // Quick trace ignores no-return beams.
        assert_eq!(
            m.beam_log_likelihood(&mut g, [0.05, 0.05], [1.0, 0.0], 10.0, true, Trace::Quick),
            0.0
        );
    }

    #[test]
    fn unknown_space_uses_prior_and_is_below_a_matching_wall() {
        let m = model();
        let mut empty = Grid(FxHashMap::default());
        let unknown = m.beam_log_likelihood(
            &mut empty,
            [0.05, 0.05],
            [1.0, 0.0],
            2.0,
            false,
            Trace::Full,
        );
        let mut g = corridor(20, 5.0, 0.1);
        let wall = m.beam_log_likelihood(&mut g, [0.05, 0.05], [1.0, 0.0], 2.0, false, Trace::Full);
        assert!(unknown.is_finite() && unknown < wall);
    }

    /// Collects `surface_update`'s increments for `ends` on a 0.1 m grid.
    fn filled(gap: f64, ends: &[Option<[f64; 2]>]) -> FxHashMap<CellKey<2>, (f32, f32)> {
        let cfg = LaserConfig {
            surface_fill_gap: gap,
            surface_fill_hits: 1.0,
            ..LaserConfig::default()
        };
        let m = LaserModel::new(&cfg, 0.1, 10.0);
        let mut acc: FxHashMap<CellKey<2>, (f32, f32)> = FxHashMap::default();
        m.surface_update(ends, |k, h, d| {
            let e = acc.entry(k).or_default();
            e.0 += h;
            e.1 += d;
        });
        acc
    }

    #[test]
    fn surface_fill_adds_hits_between_returns_on_one_line() {
        // Four returns 0.5 m apart on the wall y = 1.05 (cell row 10).
        let wall: Vec<_> = (0..4)
            .map(|i| Some([0.05 + 0.5 * i as f64, 1.05]))
            .collect();
        let acc = filled(1.0, &wall);
        // Pair 1 → 2 (x 0.55 → 1.05): the cells strictly between, x 6..=9.
        let mut cells: Vec<_> = acc.keys().copied().collect();
        cells.sort_unstable();
        assert_eq!(cells, (6..=9).map(|x| [x, 10]).collect::<Vec<_>>());
        assert!(acc.values().all(|&(h, d)| h == 1.0 && d == 0.0));
        // Off: nothing.
        assert!(filled(0.0, &wall).is_empty());
        // Further apart than the gap: nothing.
        assert!(filled(0.4, &wall).is_empty());
    }

    #[test]
    fn surface_fill_does_not_bridge_a_corner_a_doorway_or_a_no_return() {
        // The return after the pair lies 0.3 m off its line (a doorway's
        // far side): no fill.
        let door = [
            Some([0.05, 1.05]),
            Some([0.55, 1.05]),
            Some([1.05, 1.05]),
            Some([1.55, 1.35]),
        ];
        assert!(filled(1.0, &door).is_empty());
        // A "no return" breaks the surface: no pair has neighbours on both sides.
        let gap = [
            Some([0.05, 1.05]),
            Some([0.55, 1.05]),
            None,
            Some([1.05, 1.05]),
            Some([1.55, 1.05]),
        ];
        assert!(filled(1.0, &gap).is_empty());
        // Two returns at most two cells apart fill without neighbours.
        let close = [Some([0.05, 1.05]), Some([0.25, 1.05])];
        assert_eq!(filled(1.0, &close).keys().collect::<Vec<_>>(), [&[1, 10]]);
    }

    #[test]
    fn update_adds_path_length_and_one_hit() {
        let m = model();
        let mut acc: FxHashMap<CellKey<2>, (f32, f32)> = FxHashMap::default();
        m.trace_update([0.05, 0.05], [1.0, 0.0], 1.0, false, |k, h, d| {
            let e = acc.entry(k).or_default();
            e.0 += h;
            e.1 += d;
        });
        let total: f32 = acc.values().map(|v| v.1).sum();
        assert!((total - 1.0).abs() < 1e-5);
        let hits: Vec<_> = acc
            .iter()
            .filter(|(_, v)| v.0 > 0.0)
            .map(|(k, _)| *k)
            .collect();
        assert_eq!(hits, vec![[10, 0]]);
    }
}
