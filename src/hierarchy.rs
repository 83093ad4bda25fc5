//! Hierarchical SLAM (dissertation ch. 8; Eliazar & Parr, NIPS 2005).
//!
//! A single particle filter accumulates drift over long runs: its particles
//! coalesce a few generations back (ch. 7), so a long loop is closed by
//! whatever few hypotheses survived. Hierarchical SLAM splits the work:
//!
//! - **Low level**: the ordinary filter ([`ParticleFilter`]) runs over a
//!   window of `window` processed scans, on a map that starts from the second
//!   half of the previous window. Its surviving particles are a sample of the
//!   robot's trajectory through the window, relative to the window's start.
//! - **High level**: a second particle filter whose particles each own a map
//!   of the whole run (one more DP-map with its own ancestry tree). Once per
//!   window it draws, for each particle, trajectories from the low level's
//!   sample, perturbs their start (drift that the low level could not see),
//!   scores every scan of the window along them against the particle's map
//!   with a wider laser model, resamples, and adds the chosen windows' scans
//!   to the maps. This is the same predict → weigh → resample → update →
//!   prune cycle as the low level, with a window's trajectory in place of a
//!   pose.
//!
//! Both levels share one implementation of the start ([`plant`]), of
//! weighing in culling passes ([`cull`]), resampling ([`draw`]), the map
//! update and pruning ([`grow`], [`prune`]), and one scorer: the backend
//! chosen for the low level scores the high level too.

use crate::ancestry::{AncestryTree, NodeId, Numbering};
use crate::config::{Config, HierarchyConfig, Resampling};
use crate::dpmap::DpMap;
use crate::filter::{
    Copies, Culling, MapUpdate, Particle, ParticleFilter, Stamp, StepInput, StepStats, cull, draw,
    grow, offspring, plant, prune, stream,
};
use crate::geometry::Pose;
use crate::laser_model::{LaserModel, Trace};
use crate::motion_model::MotionModel;
use crate::scan::Scan;
use crate::scorer::{Candidate, CpuScorer, ScoreContext, Scorer};
use std::sync::Arc;

/// What one high-level step (one window) did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct WindowStats {
    /// Scans in the window (after its start scan).
    pub scans: usize,
    /// Trajectories scored.
    pub samples: usize,
    /// Left after the quick culling round.
    pub after_quick: usize,
    /// Distinct high-level parents among the new high-level particles.
    pub distinct_parents: usize,
}

/// One drawn window trajectory: its high-level parent and its poses (map
/// frame), one per scan of the window after the start.
struct Segment<P> {
    parent: usize,
    poses: Vec<P>,
}

/// The high-level filter: particles over whole windows, each with a map of
/// the whole run in one shared DP-map. Its step is the low level's, built
/// from the same pieces ([`cull`], [`draw`], [`grow`], [`offspring`],
/// [`prune`]) with a window's trajectory in place of a pose.
struct HighLevel<const D: usize, P: Pose<D>> {
    cfg: HierarchyConfig,
    /// Trajectories this many nats behind the best are culled (`[filter]`).
    cull_threshold: f64,
    resampling: Resampling,
    laser: LaserModel,
    perturb: Box<dyn MotionModel<D, P>>,
    tree: AncestryTree<Stamp<P>>,
    map: DpMap<D>,
    /// Copies of each node's window in use (the shared free-space update's scale).
    copies: Copies,
    numbering: Numbering,
    particles: Vec<Particle<P>>,
    best: usize,
    update: MapUpdate,
    /// The low level's scorer: `--backend` reaches both levels.
    scorer: Arc<dyn Scorer<D, P>>,
    /// The map update's per-thread map caches.
    caches: CpuScorer<D>,
    seed: u64,
    steps: u64,
}

impl<const D: usize, P: Pose<D>> HighLevel<D, P> {
    /// Predict: `samples_per_particle` trajectories per particle, each one of
    /// the low level's (chosen on the particle's own RNG stream) started at
    /// the particle's pose moved by the perturbation model.
    fn predict(&self, windows: &[Vec<P>]) -> Vec<Segment<P>> {
        use rand::RngExt;
        let k = self.cfg.samples_per_particle;
        let mut out = Vec::with_capacity(self.particles.len() * k);
        for (i, p) in self.particles.iter().enumerate() {
            let mut rng = stream(self.seed, self.steps, i as u64);
            for _ in 0..k {
                let w = &windows[rng.random_range(0..windows.len())];
                let start = self.perturb.sample(&p.pose, &P::identity(), &mut rng);
                out.push(Segment {
                    parent: i,
                    poses: w.iter().map(|r| start.compose(r)).collect(),
                });
            }
        }
        out
    }

    /// Weigh: each trajectory's log-likelihood, the sum over the window's
    /// scans along it; first with the quick endpoint score, culling
    /// trajectories `cull_threshold` nats behind the best, then the full
    /// trace on the rest. Culled trajectories get −∞.
    fn weigh(&self, segments: &[Segment<P>], scans: &[&Scan<D, P>]) -> (Vec<f64>, usize) {
        let contexts: Vec<ScoreContext<'_, D, P>> = scans
            .iter()
            .map(|scan| ScoreContext {
                map: &self.map,
                numbering: &self.numbering,
                laser: &self.laser,
                scan,
            })
            .collect();
        // One pass: a trajectory is culled on the whole window, never on
        // some of its scans.
        let w = cull(
            self.scorer.as_ref(),
            &contexts,
            segments.len(),
            |i, j| Candidate {
                node: self.particles[segments[i].parent].node,
                pose: segments[i].poses[j],
            },
            |_| 0.0,
            Culling {
                traces: &[Trace::Quick, Trace::Full],
                passes: 1,
                threshold: self.cull_threshold,
            },
        );
        (w.scores, w.after_quick)
    }

    /// One window: predict → weigh → resample → update → prune. `scans`
    /// are the window's scans after its start, `indices` their input
    /// indices, `windows` the low level's trajectories through them
    /// (relative to the window's start, one pose per scan).
    fn step(&mut self, scans: &[&Scan<D, P>], indices: &[u32], windows: &[Vec<P>]) -> WindowStats {
        self.steps += 1;
        let segments = self.predict(windows);
        let (scores, after_quick) = self.weigh(&segments, scans);
        let mut rng = stream(self.seed, self.steps, u64::MAX);
        let chosen = draw(&scores, self.cfg.particles, self.resampling, &mut rng);
        let origins: Vec<usize> = chosen.iter().map(|&c| segments[c].parent).collect();
        let parents: Vec<NodeId> = origins.iter().map(|&p| self.particles[p].node).collect();
        let nodes = grow(
            &mut self.map,
            &mut self.tree,
            &self.numbering,
            &self.caches,
            &self.laser,
            self.update,
            &mut self.copies,
            &parents,
            &chosen,
            &origins,
            |i| {
                let seg = &segments[chosen[i]];
                seg.poses.iter().copied().zip(scans.iter().copied())
            },
            |i| {
                let seg = &segments[chosen[i]];
                indices
                    .iter()
                    .zip(&seg.poses)
                    .map(|(&scan, &pose)| Stamp { scan, pose })
                    .collect()
            },
        );
        (self.particles, self.best) = offspring(&chosen, &scores, nodes, |c| {
            *segments[c].poses.last().expect("a window has scans")
        });
        let mut distinct: Vec<usize> = chosen.iter().map(|&c| segments[c].parent).collect();
        distinct.dedup();
        prune(
            &mut self.tree,
            &mut self.map,
            &mut self.copies,
            &mut self.numbering,
            &mut self.particles,
        );
        WindowStats {
            scans: scans.len(),
            samples: segments.len(),
            after_quick,
            distinct_parents: distinct.len(),
        }
    }
}

/// Two-level DP-SLAM: a low-level [`ParticleFilter`] over windows of scans
/// and a high-level filter over windows (see the module docs).
pub struct HierarchicalFilter<const D: usize, P: Pose<D>> {
    low: ParticleFilter<D, P>,
    high: HighLevel<D, P>,
    /// The open window: its start scan (index 0, at the low level's origin)
    /// and the scans processed since, with their input indices.
    window: Vec<(u32, Scan<D, P>)>,
    windows: Vec<WindowStats>,
    seed: u64,
}

impl<const D: usize, P: Pose<D>> HierarchicalFilter<D, P> {
    /// A hierarchical filter with the settings of `cfg` (`[hierarchy]`,
    /// `[filter]`, `[map]`) whose low level is `low`, just built on the
    /// first scan `scan` (input index `scan_index`) at the origin. The high
    /// level scores with the low level's scorer and laser model, the latter
    /// at `hierarchy.variance`, and draws the drift between windows from
    /// `perturb` (applied to a particle's pose with a zero motion).
    pub fn new(
        low: ParticleFilter<D, P>,
        cfg: &Config,
        perturb: Box<dyn MotionModel<D, P>>,
        scan: &Scan<D, P>,
        scan_index: u32,
    ) -> Self {
        let laser = LaserModel {
            variance: cfg.hierarchy.variance,
            ..low.laser().clone()
        };
        let origin = P::identity();
        // The high level starts like the low level: the first scan in its
        // root, every particle at the origin.
        let (tree, map, numbering) = plant(&laser, origin, scan_index, [(origin, scan)]);
        let particles = vec![
            Particle {
                pose: origin,
                node: tree.root(),
            };
            cfg.hierarchy.particles
        ];
        let high = HighLevel {
            cfg: cfg.hierarchy.clone(),
            cull_threshold: cfg.filter.cull_threshold,
            resampling: cfg.filter.resampling,
            update: MapUpdate {
                shared: cfg.map.shared_free_space,
                sharers: cfg.map.free_space_particles,
            },
            laser,
            perturb,
            tree,
            map,
            copies: Copies::planted(cfg.hierarchy.particles).counting(cfg.map.per_copy_shares),
            numbering,
            particles,
            best: 0,
            scorer: low.shared_scorer(),
            caches: CpuScorer::new(),
            seed: cfg.seed ^ 0x6869_6768, // "high": its streams differ from the low level's
            steps: 0,
        };
        Self {
            low,
            high,
            window: vec![(scan_index, scan.clone())],
            windows: Vec::new(),
            seed: cfg.seed,
        }
    }

    /// Scores both levels' scans with `scorer` (e.g. the GPU backend). Each
    /// level's map differs, so a device scorer uploads the other map when
    /// the levels take turns: twice per window.
    pub fn set_scorer(&mut self, scorer: Box<dyn Scorer<D, P>>) {
        let scorer: Arc<dyn Scorer<D, P>> = Arc::from(scorer);
        self.low.set_shared_scorer(scorer.clone());
        self.high.scorer = scorer;
    }

    /// One low-level step; closes the window (a high-level step) when it
    /// is full.
    pub fn step(&mut self, input: &StepInput<'_, D, P>) -> StepStats {
        let stats = self.low.step(input);
        self.window.push((input.index, input.scan.clone()));
        if self.window.len() > self.high.cfg.window {
            self.close_window();
        }
        stats
    }

    /// Closes the open window, if it holds scans after its start: call once
    /// after the last scan.
    pub fn finish(&mut self) {
        if self.window.len() > 1 {
            self.close_window();
        }
    }

    /// The high-level step for the open window, then a fresh low level
    /// seeded with the window's second half.
    fn close_window(&mut self) {
        let n = self.window.len() - 1;
        // Each low-level particle's poses for the window's scans after its
        // start, relative to the start (the low level's origin).
        let windows: Vec<Vec<P>> = self
            .low
            .particles()
            .iter()
            .map(|p| {
                let lineage = self.low.tree().lineage(p.node);
                lineage[lineage.len() - n..]
                    .iter()
                    .map(|s| s.pose)
                    .collect()
            })
            .collect();
        let scans: Vec<&Scan<D, P>> = self.window[1..].iter().map(|(_, s)| s).collect();
        let indices: Vec<u32> = self.window[1..].iter().map(|(i, _)| *i).collect();
        let stats = self.high.step(&scans, &indices, &windows);
        self.windows.push(stats);

        // The next window starts at the best low-level trajectory's end; its
        // map holds the second half of this window, in that frame.
        let best = self.low.best_trajectory();
        let tail = &best[best.len() - (n + 1)..];
        let end = tail[n].pose;
        let back = end.inverse();
        let seeds: Vec<(P, &Scan<D, P>)> = tail[n / 2..]
            .iter()
            .zip(&self.window[n / 2..])
            .map(|(st, (_, scan))| (back.compose(&st.pose), scan))
            .collect();
        let (last_index, last_scan) = self.window[n].clone();
        let seed = self.seed ^ (self.windows.len() as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        self.low
            .restart(seed, P::identity(), last_index, seeds.iter().copied());
        self.window = vec![(last_index, last_scan)];
    }

    /// The best trajectory (map frame): the best high-level particle's
    /// windows, then the open window along the low level's best particle.
    pub fn best_trajectory(&self) -> Vec<Stamp<P>> {
        let hp = &self.high.particles[self.high.best];
        let mut out = self.high.tree.lineage(hp.node);
        let open = self.low.best_trajectory();
        let n = self.window.len() - 1;
        out.extend(open[open.len() - n..].iter().map(|s| Stamp {
            scan: s.scan,
            pose: hp.pose.compose(&s.pose),
        }));
        out
    }

    /// The best pose now (map frame): the low level's best particle, placed
    /// by the best high-level particle.
    pub fn best_pose(&self) -> P {
        let hp = &self.high.particles[self.high.best];
        hp.pose
            .compose(&self.low.particles()[self.low.best_index()].pose)
    }

    /// The global (high-level) map.
    pub fn map(&self) -> &DpMap<D> {
        &self.high.map
    }

    /// The high-level ancestry numbering, current for [`Self::map`].
    pub fn numbering(&self) -> &Numbering {
        &self.high.numbering
    }

    /// The best high-level particle's node (its view of [`Self::map`]).
    pub fn best_node(&self) -> NodeId {
        self.high.particles[self.high.best].node
    }

    /// Live high-level ancestry nodes.
    pub fn tree_nodes(&self) -> usize {
        self.high.tree.len()
    }

    /// What each closed window's high-level step did.
    pub fn windows(&self) -> &[WindowStats] {
        &self.windows
    }

    /// The low-level filter.
    pub fn low(&self) -> &ParticleFilter<D, P> {
        &self.low
    }
}
