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
use crate::raycast::{CellKey, RayWalk};

/// Read access to one particle's view of the map.
pub trait Occupancy<const D: usize> {
    /// `(hits, distance m)` of cell `k`, or `None` if this particle never saw it.
    fn lookup(&mut self, k: CellKey<D>) -> Option<(f32, f32)>;
}

impl<const D: usize> Occupancy<D> for crate::dpmap::MapView<'_, D> {
    #[inline]
    fn lookup(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        crate::dpmap::MapView::lookup(self, k)
    }
}

impl<const D: usize> Occupancy<D> for crate::dpmap::CachedView<'_, '_, D> {
    #[inline]
    fn lookup(&mut self, k: CellKey<D>) -> Option<(f32, f32)> {
        self.view.lookup_cached(self.cache, k)
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
            let p = reach * self.stop_probability(view.lookup(c.cell), len);
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
