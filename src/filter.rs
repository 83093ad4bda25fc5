//! The DP-SLAM particle filter, generic over dimension.
//!
//! One step ([`ParticleFilter::step`]) reads like the algorithm:
//! predict → weigh → resample → update → prune.
//!
//! - **predict**: every particle draws `samples_per_particle` poses from the
//!   motion model (its own RNG stream, seeded from the run seed, the step and
//!   the particle index, so results do not depend on thread count).
//! - **weigh**: samples are scored against their parent particle's view of the
//!   DP-map, first with the release's quick endpoint-window score and then
//!   with the full trace, each over `passes` interleaved beam subsets, culling
//!   samples that fall `cull_threshold` nats behind the best (ch. 9).
//! - **resample**: the next particle set is drawn from the surviving samples.
//! - **update**: each new particle gets an ancestry node, child of its parent
//!   particle's node, holding its observation of the scan.
//! - **prune**: dead branches are removed and only-children collapsed, in the
//!   tree and in the map alike.

use crate::ancestry::{AncestryTree, NodeId, Numbering};
use crate::config::{FilterConfig, MapConfig, ReportedPose, Resampling};
use crate::dpmap::DpMap;
use crate::geometry::Pose;
use crate::laser_model::{LaserModel, Trace};
use crate::motion_model::MotionModel;
use crate::proposal::{MatchContext, Proposal, ScanRegistration};
use crate::raycast::CellKey;
use crate::scan::Scan;
use crate::scorer::{
    BeamSubset, Candidate, CellSums, CpuScorer, ScoreContext, Scorer, map_in_preorder,
};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::sync::Arc;

/// A pose recorded in the ancestry tree: the robot pose (map frame) at input scan `scan`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stamp<P> {
    /// Index of the scan in the input (0-based).
    pub scan: u32,
    /// Robot pose in the map frame.
    pub pose: P,
}

// Defined below the filter: scan registration sees particles too.
pub use crate::particle::Particle;

/// A candidate pose drawn from a particle in the current step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample<P> {
    /// Robot pose in the map frame.
    pub pose: P,
    /// Index of the particle it was drawn from.
    pub parent: usize,
}

/// The outcome of [`ParticleFilter::predict`].
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction<P> {
    /// The drawn samples, per particle in order (`samples_per_particle`
    /// each, or the matched count where a scan match succeeded).
    pub samples: Vec<Sample<P>>,
    /// Per sample, `ln p_motion − ln q` (nats) to add to its scan
    /// log-likelihood ([`Proposal::log_ratio`]); empty for the motion
    /// proposal, whose weights are the likelihoods.
    pub log_ratio: Vec<f64>,
    /// Particles whose samples came from a scan match.
    pub matched: usize,
}

/// The outcome of [`ParticleFilter::weigh`].
#[derive(Debug, Clone, PartialEq)]
pub struct Weights {
    /// Scan log-likelihood per sample; culled samples have −∞.
    pub scores: Vec<f64>,
    /// Samples left after the quick culling passes.
    pub after_quick: usize,
    /// Samples left after the full passes.
    pub after_full: usize,
    /// Wall time of the quick passes, s.
    pub quick_s: f64,
    /// Wall time of the full passes, s.
    pub full_s: f64,
}

/// Everything one filter step consumes.
#[derive(Debug, Clone)]
pub struct StepInput<'a, const D: usize, P: Pose<D>> {
    /// Odometry motion since the last processed scan, in the previous robot
    /// frame (the motion model's mean; identity without odometry).
    pub odometry: P,
    /// Where the samples come from.
    pub proposal: Proposal<P>,
    /// The scan taken at the new pose.
    pub scan: &'a Scan<D, P>,
    /// Index of the scan in the input (0-based), recorded in the tree.
    pub index: u32,
}

impl<'a, const D: usize, P: Pose<D>> StepInput<'a, D, P> {
    /// A step whose samples come from the motion model around `odometry`.
    pub fn motion(odometry: P, scan: &'a Scan<D, P>, index: u32) -> Self {
        Self {
            odometry,
            proposal: Proposal::Motion,
            scan,
            index,
        }
    }
}

/// What one step did, for logs and run statistics.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct StepStats {
    /// Samples drawn.
    pub samples: usize,
    /// Samples left after the quick culling passes.
    pub after_quick: usize,
    /// Samples left after the full passes.
    pub after_full: usize,
    /// Log-likelihood of the best sample.
    pub best_log_likelihood: f64,
    /// Distinct parent particles among the new particles.
    pub distinct_parents: usize,
    /// Whether the particle set was drawn anew from all samples
    /// (`filter.resample_below`); false: each particle kept one of its own.
    pub resampled: bool,
    /// Particles whose samples came from a scan match this step.
    pub matched: usize,
    /// Live ancestry nodes after pruning.
    pub tree_nodes: usize,
    /// Entries in the DP-map after pruning.
    pub map_entries: usize,
    /// Wall time of each phase of the step.
    pub times: PhaseTimes,
}

/// Wall time (s) of the phases of one filter step, for profiles.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct PhaseTimes {
    /// Drawing the samples.
    pub predict_s: f64,
    /// Weighing: the quick (endpoint-window) culling passes.
    pub weigh_quick_s: f64,
    /// Weighing: the full-trace passes.
    pub weigh_full_s: f64,
    /// Resampling.
    pub resample_s: f64,
    /// Map update (new nodes and their observations).
    pub update_s: f64,
    /// Pruning the tree and the map.
    pub prune_s: f64,
}

impl PhaseTimes {
    /// Each phase's time divided by `n` (e.g. per step).
    pub fn per(self, n: f64) -> Self {
        Self {
            predict_s: self.predict_s / n,
            weigh_quick_s: self.weigh_quick_s / n,
            weigh_full_s: self.weigh_full_s / n,
            resample_s: self.resample_s / n,
            update_s: self.update_s / n,
            prune_s: self.prune_s / n,
        }
    }
}

impl std::ops::AddAssign for PhaseTimes {
    fn add_assign(&mut self, o: Self) {
        self.predict_s += o.predict_s;
        self.weigh_quick_s += o.weigh_quick_s;
        self.weigh_full_s += o.weigh_full_s;
        self.resample_s += o.resample_s;
        self.update_s += o.update_s;
        self.prune_s += o.prune_s;
    }
}

/// SplitMix64 finaliser: decorrelates seeds derived from small integers.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// An RNG stream for (run seed, step, stream index).
pub fn stream(seed: u64, step: u64, index: u64) -> Pcg64 {
    Pcg64::seed_from_u64(mix(seed ^ mix(step ^ mix(index))))
}

/// Stream index used for resampling (particle streams use 0..N).
const RESAMPLE_STREAM: u64 = u64::MAX;

/// The particle filter with its shared DP-map. Cloning copies the map, the
/// tree and the particles and shares the (immutable) models.
#[derive(Clone)]
pub struct ParticleFilter<const D: usize, P: Pose<D>> {
    cfg: FilterConfig,
    laser: LaserModel,
    motion: Arc<dyn MotionModel<D, P>>,
    tree: AncestryTree<Stamp<P>>,
    map: DpMap<D>,
    /// Copies of each node's sample in use (the shared free-space update's scale).
    copies: Copies,
    numbering: Numbering,
    particles: Vec<Particle<P>>,
    /// Accumulated log weight of each particle (nats, best 0) under
    /// selective resampling (`filter.resample_below` < 1); all 0 after a
    /// resampling.
    log_weights: Vec<f64>,
    best: usize,
    /// The particle of the step before that the best one descends from
    /// (its index then; `None` before the first step).
    best_origin: Option<usize>,
    seed: u64,
    steps: u64,
    /// Share free-space updates of cells all see as free (see `MapConfig`).
    shared_free_space: bool,
    /// How many new particles contribute to the shared free-space update (0: all).
    free_space_particles: usize,
    /// Computes scan likelihoods (CPU by default).
    scorer: Arc<dyn Scorer<D, P>>,
    /// Weigh with the quick culling passes before the full ones.
    quick_culling: bool,
    /// The map update's per-thread map caches: the CPU scorer's own while
    /// it scores (the update reads the map version the weigh step resolved,
    /// so its lookups hit cells already cached, and one set of caches is
    /// held instead of two), a set of their own behind another scorer.
    caches: Arc<CpuScorer<D>>,
    /// Registers scans for [`Proposal::ScanMatched`] (none: motion model).
    matcher: Option<Arc<dyn ScanRegistration<D, P>>>,
    /// Samples per particle whose scan match succeeded (0: `samples_per_particle`).
    matched_samples: usize,
}

impl<const D: usize, P: Pose<D>> ParticleFilter<D, P> {
    /// A filter whose particles all start at `initial` (map frame) with the
    /// first scan already in the map (recorded at input index `scan_index`).
    pub fn new(
        cfg: FilterConfig,
        laser: LaserModel,
        motion: Box<dyn MotionModel<D, P>>,
        seed: u64,
        initial: P,
        scan: &Scan<D, P>,
        scan_index: u32,
    ) -> Self {
        Self::seeded(
            cfg,
            laser,
            motion,
            seed,
            initial,
            scan_index,
            [(initial, scan)],
        )
    }

    /// A filter whose particles all start at `initial` (map frame, the pose
    /// of input scan `scan_index`) on a map that already holds `seeds`
    /// (scans at map poses, e.g. the end of an earlier stretch of the log).
    pub fn seeded<'s>(
        cfg: FilterConfig,
        laser: LaserModel,
        motion: Box<dyn MotionModel<D, P>>,
        seed: u64,
        initial: P,
        scan_index: u32,
        seeds: impl IntoIterator<Item = (P, &'s Scan<D, P>)>,
    ) -> Self
    where
        Scan<D, P>: 's,
    {
        let (tree, map, numbering) = plant(&laser, initial, scan_index, seeds);
        let root = tree.root();
        let particles = vec![
            Particle {
                pose: initial,
                node: root
            };
            cfg.particles
        ];
        let cpu = Arc::new(CpuScorer::<D>::new());
        Self {
            cfg,
            laser,
            motion: Arc::from(motion),
            tree,
            map,
            copies: Copies::planted(particles.len()),
            numbering,
            log_weights: vec![0.0; particles.len()],
            particles,
            best: 0,
            best_origin: None,
            seed,
            steps: 0,
            shared_free_space: true,
            free_space_particles: 0,
            scorer: cpu.clone(),
            quick_culling: true,
            caches: cpu,
            matcher: None,
            matched_samples: 0,
        }
    }

    /// Starts over, keeping the models, the scorer and the settings: a new
    /// map holding only `seeds`, all particles at `initial` (the pose of
    /// input scan `scan_index`), step count 0 and RNG seed `seed`.
    pub fn restart<'s>(
        &mut self,
        seed: u64,
        initial: P,
        scan_index: u32,
        seeds: impl IntoIterator<Item = (P, &'s Scan<D, P>)>,
    ) where
        Scan<D, P>: 's,
    {
        (self.tree, self.map, self.numbering) = plant(&self.laser, initial, scan_index, seeds);
        self.copies = Copies::planted(self.cfg.particles).counting(self.copies.enabled);
        self.particles = vec![
            Particle {
                pose: initial,
                node: self.tree.root(),
            };
            self.cfg.particles
        ];
        self.log_weights = vec![0.0; self.cfg.particles];
        self.best = 0;
        self.seed = seed;
        self.steps = 0;
    }

    /// Sets how the map update records free space, from the map settings:
    /// the release's every-particle-every-cell update or the shared
    /// free-space update (`shared_free_space`, the default), and how many of
    /// the new particles feed the latter (`free_space_particles`, 0 = all;
    /// until this is called, all), and whether their in-place shares are
    /// divided by the owner's copies in use (`per_copy_shares`).
    pub fn set_map_update(&mut self, map: &MapConfig) {
        self.shared_free_space = map.shared_free_space;
        self.free_space_particles = map.free_space_particles;
        self.copies.enabled = map.per_copy_shares;
    }

    /// Whether [`ParticleFilter::weigh`] runs the quick (endpoint-window)
    /// culling passes before the full ones (the release does; default on).
    /// They pay only when they cull: where samples come from a scan
    /// matcher's Gaussian nearly all survive them.
    pub fn set_quick_culling(&mut self, on: bool) {
        self.quick_culling = on;
    }

    /// Samples drawn per particle from the next step on.
    pub fn set_samples_per_particle(&mut self, k: usize) {
        self.cfg.samples_per_particle = k.max(1);
    }

    /// Samples drawn by a particle whose [`Proposal::ScanMatched`] step
    /// matched (0, the default: `samples_per_particle`); particles whose
    /// match failed draw `samples_per_particle` from the motion model.
    pub fn set_matched_samples_per_particle(&mut self, k: usize) {
        self.matched_samples = k;
    }

    /// Replaces the scan scorer (e.g. with the GPU backend).
    pub fn set_scorer(&mut self, scorer: Box<dyn Scorer<D, P>>) {
        self.scorer = Arc::from(scorer);
    }

    /// Replaces the scan scorer with one that others score with too (the
    /// high level of hierarchical SLAM shares the low level's backend).
    pub fn set_shared_scorer(&mut self, scorer: Arc<dyn Scorer<D, P>>) {
        self.scorer = scorer;
    }

    /// The scan scorer in use, to score with elsewhere.
    pub fn shared_scorer(&self) -> Arc<dyn Scorer<D, P>> {
        self.scorer.clone()
    }

    /// Sets the scan registration that [`Proposal::ScanMatched`] steps use.
    pub fn set_scan_matcher(&mut self, matcher: Box<dyn ScanRegistration<D, P>>) {
        self.matcher = Some(Arc::from(matcher));
    }

    /// The scan scorer in use.
    pub fn scorer(&self) -> &dyn Scorer<D, P> {
        self.scorer.as_ref()
    }

    /// One filter step: predict → weigh → resample → update → prune.
    pub fn step(&mut self, input: &StepInput<'_, D, P>) -> StepStats {
        self.steps += 1;
        let mut times = PhaseTimes::default();
        let t = std::time::Instant::now();
        let Prediction {
            samples,
            log_ratio,
            matched,
        } = self.predict(&input.odometry, &input.proposal, input.scan);
        times.predict_s = t.elapsed().as_secs_f64();
        let log_ratio = self.with_carried_weights(&samples, log_ratio);
        let weights = self.weigh_corrected(&samples, &log_ratio, input.scan);
        times.weigh_quick_s = weights.quick_s;
        times.weigh_full_s = weights.full_s;
        let t = std::time::Instant::now();
        let (chosen, log_weights) = self.select(&samples, &weights.scores);
        let resampled = log_weights.is_none();
        times.resample_s = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let distinct_parents =
            self.update(&samples, &weights.scores, &chosen, input.scan, input.index);
        self.log_weights = log_weights.unwrap_or_else(|| vec![0.0; chosen.len()]);
        times.update_s = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        self.prune();
        times.prune_s = t.elapsed().as_secs_f64();
        StepStats {
            times,
            samples: samples.len(),
            after_quick: weights.after_quick,
            after_full: weights.after_full,
            best_log_likelihood: weights
                .scores
                .iter()
                .cloned()
                .fold(f64::NEG_INFINITY, f64::max),
            distinct_parents,
            resampled,
            matched,
            tree_nodes: self.tree.len(),
            map_entries: self.map.entry_count(),
        }
    }

    /// Predict: `samples_per_particle` poses per particle from `proposal`
    /// (for the odometry motion `odometry`, previous robot frame), each
    /// particle on its own RNG stream for this step. A
    /// [`Proposal::ScanMatched`] step first registers `scan` against each
    /// particle's view (the filter's [`ScanRegistration`]).
    pub fn predict(
        &self,
        odometry: &P,
        proposal: &Proposal<P>,
        scan: &Scan<D, P>,
    ) -> Prediction<P> {
        let k = self.cfg.samples_per_particle;
        let step = self.steps;
        let seed = self.seed;
        let motion = self.motion.as_ref();
        let per_particle: Option<Vec<Proposal<P>>> = match (proposal, &self.matcher) {
            (Proposal::ScanMatched, Some(m)) => {
                let groups: Vec<NodeId> =
                    self.particles.iter().map(|p| self.view_group(p)).collect();
                Some(m.propose(&MatchContext {
                    map: &self.map,
                    numbering: &self.numbering,
                    groups: &groups,
                    particles: &self.particles,
                    odometry,
                    scan,
                }))
            }
            _ => None,
        };
        let of = |i: usize| per_particle.as_ref().map_or(proposal, |v| &v[i]);
        // Samples of particle `i`: fewer where its own match is sharp.
        let count = |q: &Proposal<P>| match q {
            q if q.is_matched() && per_particle.is_some() && self.matched_samples > 0 => {
                self.matched_samples
            }
            _ => k,
        };
        // The motion proposal's densities cancel: its weights stay the bare
        // likelihoods, bit for bit as in the release.
        let weighted = !matches!(proposal, Proposal::Motion);
        let drawn: Vec<(Sample<P>, f64)> = self
            .particles
            .par_iter()
            .enumerate()
            .flat_map_iter(|(i, p)| {
                let mut rng = stream(seed, step, i as u64);
                let q = of(i);
                (0..count(q))
                    .map(|_| {
                        let pose = q.sample(motion, &p.pose, odometry, &mut rng);
                        let r = if weighted {
                            q.log_ratio(motion, &p.pose, odometry, &pose)
                        } else {
                            0.0
                        };
                        (Sample { pose, parent: i }, r)
                    })
                    .collect::<Vec<_>>()
            })
            .collect();
        let matched = per_particle.as_ref().map_or(
            usize::from(proposal.is_matched()) * self.particles.len(),
            |v| v.iter().filter(|q| q.is_matched()).count(),
        );
        let (samples, log_ratio): (Vec<_>, Vec<_>) = drawn.into_iter().unzip();
        Prediction {
            samples,
            log_ratio: if weighted { log_ratio } else { Vec::new() },
            matched,
        }
    }

    /// The key of `p`'s view group for a [`MatchContext`]: the parent of its
    /// ancestry node (particles with the same parent see the same map but
    /// for their own last observation), or the node itself at the root.
    fn view_group(&self, p: &Particle<P>) -> NodeId {
        match self.tree.parent(p.node) {
            crate::ancestry::NO_NODE => p.node,
            parent => parent,
        }
    }

    /// The best particle's scan match for `scan` from the odometry motion
    /// `odometry` (previous robot frame, since the last step), against its
    /// own map view: the matched motion (same frame) fused with the motion
    /// model, or `None` without a scan matcher or where the match fails. A
    /// Mixture gives its most probable part. Leaves the filter unchanged:
    /// for scans the filter skips ([`crate::config::FilterConfig::match_skipped`]).
    pub fn match_best(&self, odometry: &P, scan: &Scan<D, P>) -> Option<P> {
        let matcher = self.matcher.as_ref()?;
        let best = self.particles.get(self.best)?;
        // Before the first step, a field built here for the first
        // particle (the only view there is) is reused the same way.
        let origin = self.best_origin.unwrap_or(0);
        let proposal = match matcher.rematch(origin, &best.pose, odometry, scan) {
            Some(q) => q,
            None => matcher
                .propose(&MatchContext {
                    map: &self.map,
                    numbering: &self.numbering,
                    groups: &[self.view_group(best)],
                    particles: std::slice::from_ref(best),
                    odometry,
                    scan,
                })
                .into_iter()
                .next()?,
        };
        match proposal {
            Proposal::Matched { delta, .. } => Some(delta),
            Proposal::Mixture(parts) => parts
                .into_iter()
                .max_by(|a, b| a.0.total_cmp(&b.0))
                .map(|part| part.1),
            Proposal::Motion | Proposal::ScanMatched => None,
        }
    }

    /// Weigh: scores every sample against its parent particle's map view, in
    /// culling passes (quick, then full); culled samples get −∞.
    pub fn weigh(&self, samples: &[Sample<P>], scan: &Scan<D, P>) -> Weights {
        self.weigh_corrected(samples, &[], scan)
    }

    /// As [`ParticleFilter::weigh`], each sample's score starting from
    /// `log_ratio[i]` (nats; [`Prediction::log_ratio`], empty: 0) so that
    /// culling and resampling see the importance weight, not only the
    /// likelihood.
    pub fn weigh_corrected(
        &self,
        samples: &[Sample<P>],
        log_ratio: &[f64],
        scan: &Scan<D, P>,
    ) -> Weights {
        let passes = self.cfg.passes.min(scan.beams.len().max(1));
        let ctx = ScoreContext {
            map: &self.map,
            numbering: &self.numbering,
            laser: &self.laser,
            scan,
        };
        let traces: &[Trace] = if self.quick_culling {
            &[Trace::Quick, Trace::Full]
        } else {
            &[Trace::Full]
        };
        cull(
            self.scorer.as_ref(),
            &[ctx],
            samples.len(),
            |i, _| Candidate {
                node: self.particles[samples[i].parent].node,
                pose: samples[i].pose,
            },
            |i| log_ratio.get(i).copied().unwrap_or(0.0),
            Culling {
                traces,
                passes,
                threshold: self.cfg.cull_threshold,
            },
        )
    }

    /// Each sample's starting score (nats): `log_ratio` (empty: 0) plus,
    /// under selective resampling, its particle's carried log weight, so
    /// that culling, the reported mean and the draw see the particle's
    /// whole weight. Unchanged when every carried weight is 0.
    fn with_carried_weights(&self, samples: &[Sample<P>], log_ratio: Vec<f64>) -> Vec<f64> {
        if self.log_weights.iter().all(|&w| w == 0.0) {
            return log_ratio;
        }
        samples
            .iter()
            .enumerate()
            .map(|(j, s)| log_ratio.get(j).copied().unwrap_or(0.0) + self.log_weights[s.parent])
            .collect()
    }

    /// Which samples become the next particles (ascending sample indices)
    /// and the particles' carried log weights, in the same order: `None`
    /// where the set was resampled ([`ParticleFilter::resample`]; every
    /// weight restarts at 0), which it is every step unless
    /// `filter.resample_below` < 1. Otherwise, while the effective number
    /// of particles stays at or above that fraction and no particle lost
    /// all its samples to culling, each particle keeps one of its own
    /// samples, drawn by `exp(score)`, and carries the log of its samples'
    /// mean weight (its carried weight included; best 0).
    pub fn select(&self, samples: &[Sample<P>], scores: &[f64]) -> (Vec<usize>, Option<Vec<f64>>) {
        let n = self.particles.len();
        if self.cfg.resample_below >= 1.0 || n == 0 {
            return (self.resample(scores), None);
        }
        // Samples are drawn particle by particle: each one's are a run.
        let mut runs = vec![(usize::MAX, 0usize); n];
        for (j, s) in samples.iter().enumerate() {
            let r = &mut runs[s.parent];
            r.0 = r.0.min(j);
            r.1 += 1;
        }
        let marginal: Vec<f64> = runs
            .iter()
            .map(|&(first, count)| match count {
                0 => f64::NEG_INFINITY,
                _ => {
                    crate::motion_model::log_sum_exp(&scores[first..first + count])
                        - (count as f64).ln()
                }
            })
            .collect();
        if marginal.iter().any(|m| !m.is_finite()) {
            return (self.resample(scores), None);
        }
        let top = marginal.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let w: Vec<f64> = marginal.iter().map(|m| (m - top).exp()).collect();
        let sum: f64 = w.iter().sum();
        let squares: f64 = w.iter().map(|v| v * v).sum();
        if sum * sum / squares < self.cfg.resample_below * n as f64 {
            return (self.resample(scores), None);
        }
        let mut rng = stream(self.seed, self.steps, RESAMPLE_STREAM);
        let chosen = runs
            .iter()
            .map(|&(first, count)| {
                first
                    + draw(
                        &scores[first..first + count],
                        1,
                        Resampling::Multinomial,
                        &mut rng,
                    )[0]
            })
            .collect();
        (chosen, Some(marginal.iter().map(|m| m - top).collect()))
    }

    /// Resample: indices of the samples that become the next particles,
    /// ascending, drawn by weight `exp(score − best)`.
    pub fn resample(&self, scores: &[f64]) -> Vec<usize> {
        let mut rng = stream(self.seed, self.steps, RESAMPLE_STREAM);
        draw(scores, self.cfg.particles, self.cfg.resampling, &mut rng)
    }

    /// Update: each chosen sample becomes a particle with a new ancestry node
    /// (child of its parent particle's node) holding its observation of
    /// `scan`. Returns the number of distinct parent particles.
    pub fn update(
        &mut self,
        samples: &[Sample<P>],
        scores: &[f64],
        chosen: &[usize],
        scan: &Scan<D, P>,
        scan_index: u32,
    ) -> usize {
        let origins: Vec<usize> = chosen.iter().map(|&j| samples[j].parent).collect();
        let parents: Vec<NodeId> = origins.iter().map(|&p| self.particles[p].node).collect();
        let update = MapUpdate {
            shared: self.shared_free_space,
            sharers: self.free_space_particles,
        };
        let reported: Vec<P> = match self.cfg.report {
            ReportedPose::Sample => chosen.iter().map(|&j| samples[j].pose).collect(),
            ReportedPose::PosteriorMean => {
                let groups =
                    view_means(samples, scores, |j| self.particles[samples[j].parent].node);
                parents.iter().map(|n| groups[n]).collect()
            }
        };
        let nodes = grow(
            &mut self.map,
            &mut self.tree,
            &self.numbering,
            &self.caches,
            &self.laser,
            update,
            &mut self.copies,
            &parents,
            chosen,
            &origins,
            |i| [(samples[chosen[i]].pose, scan)],
            |i| {
                vec![Stamp {
                    scan: scan_index,
                    pose: reported[i],
                }]
            },
        );
        (self.particles, self.best) = offspring(chosen, scores, nodes, |j| samples[j].pose);
        self.best_origin = origins.get(self.best).copied();
        let mut parents: Vec<usize> = chosen.iter().map(|&j| samples[j].parent).collect();
        parents.dedup();
        parents.len()
    }

    /// Prune: removes dead branches and merges only-children, in the tree and
    /// the map alike, then renumbers the tree for the next step.
    pub fn prune(&mut self) {
        prune(
            &mut self.tree,
            &mut self.map,
            &mut self.copies,
            &mut self.numbering,
            &mut self.particles,
        );
    }

    /// The current particles.
    pub fn particles(&self) -> &[Particle<P>] {
        &self.particles
    }

    /// Each particle's carried log weight (nats, best 0; all 0 after a
    /// resampling, so always all 0 with `filter.resample_below` ≥ 1), in
    /// the order of [`ParticleFilter::particles`].
    pub fn log_weights(&self) -> &[f64] {
        &self.log_weights
    }

    /// Index of the particle whose sample scored best in the last step.
    pub fn best_index(&self) -> usize {
        self.best
    }

    /// The best particle's trajectory: one stamp per processed scan, in order.
    pub fn best_trajectory(&self) -> Vec<Stamp<P>> {
        self.tree.lineage(self.particles[self.best].node)
    }

    /// The shared DP-map.
    pub fn map(&self) -> &DpMap<D> {
        &self.map
    }

    /// The ancestry tree.
    pub fn tree(&self) -> &AncestryTree<Stamp<P>> {
        &self.tree
    }

    /// The current depth-first numbering of the tree (valid between steps).
    pub fn numbering(&self) -> &Numbering {
        &self.numbering
    }

    /// The laser model in use.
    pub fn laser(&self) -> &LaserModel {
        &self.laser
    }
}

/// A one-node ancestry tree holding `seeds` (scans at map poses) in a new
/// map, its root recording input scan `scan_index` at `initial` (map
/// frame); with its numbering. Every filter starts from one.
pub fn plant<'s, const D: usize, P: Pose<D>>(
    laser: &LaserModel,
    initial: P,
    scan_index: u32,
    seeds: impl IntoIterator<Item = (P, &'s Scan<D, P>)>,
) -> (AncestryTree<Stamp<P>>, DpMap<D>, Numbering)
where
    Scan<D, P>: 's,
{
    let tree = AncestryTree::new(vec![Stamp {
        scan: scan_index,
        pose: initial,
    }]);
    let root = tree.root();
    let mut map = DpMap::new(laser.cell);
    let mut numbering = Numbering::default();
    tree.number(&mut numbering);
    let mut view = map.view(&numbering, root);
    let mut sums = CellSums::default();
    let first = observe(
        laser,
        &mut sums,
        |k| view.entry(k),
        |_, _| None,
        seeds,
        false,
        false,
    );
    map.insert_fresh(root, &first.new);
    (tree, map, numbering)
}

/// How [`cull`] weighs samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Culling<'t> {
    /// The rounds, in order: each starts every surviving sample's score
    /// afresh and scores it with its trace (the release: quick, then full).
    pub traces: &'t [Trace],
    /// Passes per round (≥ 1): pass `k` scores beams `k, k + passes, …` of
    /// every scan, then culls.
    pub passes: usize,
    /// Samples this many nats behind the best are culled after each pass.
    pub threshold: f64,
}

/// Weighs `n` samples in culling passes (ch. 9): the log-likelihood of
/// `scans` (one context each) for sample `i` at `candidate(i, j)` for scan
/// `j`, on top of `start(i)` (nats). A sample falls out once it is
/// `threshold` behind the best after a pass; culled samples get −∞.
///
/// Both levels of hierarchical SLAM weigh with it: the low level one scan
/// per sample in several passes, the high level a window of scans per
/// trajectory in one pass.
pub fn cull<const D: usize, P: Pose<D>, S: Scorer<D, P> + ?Sized>(
    scorer: &S,
    scans: &[ScoreContext<'_, D, P>],
    n: usize,
    candidate: impl Fn(usize, usize) -> Candidate<P>,
    start: impl Fn(usize) -> f64,
    culling: Culling<'_>,
) -> Weights {
    let mut scores = vec![0.0f64; n];
    let mut alive: Vec<usize> = (0..n).collect();
    // Without a quick round nothing is culled before the full one.
    let mut after_quick = n;
    let mut secs = [0.0f64; 2];
    for &trace in culling.traces {
        let t = std::time::Instant::now();
        for &i in &alive {
            scores[i] = start(i);
        }
        for pass in 0..culling.passes {
            let subset = BeamSubset {
                first: pass,
                stride: culling.passes,
            };
            for (j, ctx) in scans.iter().enumerate() {
                let candidates: Vec<Candidate<P>> =
                    alive.iter().map(|&i| candidate(i, j)).collect();
                let partial = scorer.score(ctx, &candidates, subset, trace);
                for (&i, s) in alive.iter().zip(partial) {
                    scores[i] += s;
                }
            }
            let best = alive
                .iter()
                .map(|&i| scores[i])
                .fold(f64::NEG_INFINITY, f64::max);
            let threshold = best - culling.threshold;
            alive.retain(|&i| scores[i] >= threshold);
        }
        let round = usize::from(trace == Trace::Full);
        if trace == Trace::Quick {
            after_quick = alive.len();
        }
        secs[round] += t.elapsed().as_secs_f64();
    }
    let mut out = vec![f64::NEG_INFINITY; n];
    for &i in &alive {
        out[i] = scores[i];
    }
    Weights {
        scores: out,
        after_quick,
        after_full: alive.len(),
        quick_s: secs[0],
        full_s: secs[1],
    }
}

/// Draws `n` of the samples by weight `exp(score − best)` (culled samples
/// have −∞ and weight 0); returns their indices, ascending.
pub fn draw(scores: &[f64], n: usize, resampling: Resampling, rng: &mut Pcg64) -> Vec<usize> {
    let best = scores.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let weights: Vec<f64> = scores.iter().map(|s| (s - best).exp()).collect();
    let total: f64 = weights.iter().sum();
    let mut cumulative = Vec::with_capacity(weights.len());
    let mut acc = 0.0;
    for w in &weights {
        acc += w / total;
        cumulative.push(acc);
    }
    let pick = |u: f64| {
        cumulative
            .partition_point(|&c| c < u)
            .min(weights.len() - 1)
    };
    let mut chosen: Vec<usize> = match resampling {
        Resampling::Multinomial => (0..n).map(|_| pick(rng.random::<f64>())).collect(),
        Resampling::Systematic => {
            let u0 = rng.random::<f64>() / n as f64;
            (0..n).map(|i| pick(u0 + i as f64 / n as f64)).collect()
        }
    };
    chosen.sort_unstable();
    chosen
}

/// Per parent view (the samples whose particles sit on one ancestry node,
/// `view_of(j)`: draws from one proposal against one map view), the
/// importance-weighted mean pose, weights `exp(score − best)` (culled
/// samples weigh nothing). The mean is taken in the body frame of the
/// view's best sample ([`Pose::perturbation_to`]), which is exact enough
/// for samples centimetres and fractions of a degree apart, and summed in
/// sample order, so it is the same on every thread count. A view whose
/// samples were all culled keeps its first sample.
pub fn view_means<const D: usize, P: Pose<D>>(
    samples: &[Sample<P>],
    scores: &[f64],
    view_of: impl Fn(usize) -> NodeId,
) -> FxHashMap<NodeId, P> {
    let mut best: FxHashMap<NodeId, (f64, usize)> = FxHashMap::default();
    for (j, &score) in scores.iter().enumerate().take(samples.len()) {
        let b = best.entry(view_of(j)).or_insert((score, j));
        if score > b.0 {
            *b = (score, j);
        }
    }
    let mut sums: FxHashMap<NodeId, (f64, Vec<f64>)> = FxHashMap::default();
    for (j, s) in samples.iter().enumerate() {
        let (top, at) = best[&view_of(j)];
        let w = (scores[j] - top).exp();
        if w.is_nan() || w <= 0.0 {
            continue;
        }
        let xi = samples[at].pose.perturbation_to(&s.pose);
        let acc = sums.entry(view_of(j)).or_insert((0.0, vec![0.0; P::DOF]));
        acc.0 += w;
        for (a, x) in acc.1.iter_mut().zip(xi) {
            *a += w * x;
        }
    }
    best.into_iter()
        .map(|(view, (_, at))| {
            let anchor = samples[at].pose;
            let pose = match sums.get(&view) {
                Some((total, xi)) => {
                    let mean: Vec<f64> = xi.iter().map(|x| x / total).collect();
                    anchor.perturbed(&P::identity(), &mean)
                }
                None => anchor,
            };
            (view, pose)
        })
        .collect()
}

/// Which copies of each ancestry node's sample are still in use, to scale
/// the shared free-space update's in-place shares (see [`grow`]).
///
/// Resampling copies a sample into every particle that picks it, and the
/// copies share one node. With one node per copy (before 47e8d60) each copy
/// had its own entries, fed only by its own descendants' in-place shares;
/// on the shared node the descendants of all k copies feed the same
/// entries, so cells accrued free path length up to k times faster and the
/// scan-matched filter lost fr079-raw (docs/PROPOSAL-2D.md). [`grow`]
/// divides each in-place share by its owner's [`Copies::count`], the
/// number of copies with something alive below them: the shared entry then
/// grows as the mean of the per-copy entries it stands for.
///
/// A copy is in use while a particle sits on it or a live child descends
/// from it, so [`prune`] recounts every node from the particles' copy
/// indices and the children's labels (which copy of their parent they
/// came from): counts fall as copies' subtrees die, as the per-copy
/// entries did. Prune merges an only child into its parent only once the
/// child has one copy in use: with several, the one copy of the parent
/// that is left (a child is one sample of one particle) had several
/// children before, and merging would give the parent's cells the child's
/// count (one count per node, not per entry). So every node's count is
/// that of the per-copy tree. The root of a new map is one node for all
/// particles, as it always was: one copy.
#[derive(Debug, Clone)]
pub struct Copies {
    /// Off: every node counts as one copy (the shares pool, merges are
    /// never held back; `map.per_copy_shares = false`).
    enabled: bool,
    /// Per node: copies in use (1 for nodes not yet counted).
    count: Vec<u32>,
    /// Per node: which copy of its parent node it descends from.
    label: Vec<u32>,
    /// Per particle: which copy of its node it is.
    of_particle: Vec<u32>,
}

impl Copies {
    /// A new map's: `particles` particles on the root, all one copy of it.
    pub fn planted(particles: usize) -> Self {
        Self {
            enabled: true,
            count: vec![1],
            label: vec![0],
            of_particle: vec![0; particles],
        }
    }

    /// The same, counting copies only if `on`.
    pub fn counting(mut self, on: bool) -> Self {
        self.enabled = on;
        self
    }

    /// Copies of `node`'s sample in use (at least 1).
    pub fn count(&self, node: NodeId) -> u32 {
        if !self.enabled {
            return 1;
        }
        self.count.get(node as usize).copied().unwrap_or(1).max(1)
    }

    /// Records the nodes [`grow`] made: particle `i` is copy `i - first` of
    /// `nodes[i]`, where `first` is the first particle on that node, and a
    /// new node descends from the copy its first particle's parent
    /// particle `origins[i]` was.
    fn grown(&mut self, nodes: &[NodeId], origins: &[usize]) {
        if !self.enabled {
            return;
        }
        let mut of_particle = Vec::with_capacity(nodes.len());
        let mut first = 0;
        for (i, &node) in nodes.iter().enumerate() {
            if i == 0 || node != nodes[i - 1] {
                first = i;
                let n = node as usize + 1;
                if self.count.len() < n {
                    self.count.resize(n, 1);
                    self.label.resize(n, 0);
                }
                self.label[node as usize] = self.of_particle[origins[i]];
                self.count[node as usize] =
                    nodes[i..].iter().take_while(|&&m| m == node).count() as u32;
            }
            of_particle.push((i - first) as u32);
        }
        self.of_particle = of_particle;
    }

    /// Recounts every live node after pruning: the distinct copies of it
    /// that particles (`held`, their nodes) sit on or children descend from.
    fn recount<T: Clone>(&mut self, tree: &AncestryTree<T>, held: &[NodeId]) {
        if !self.enabled {
            return;
        }
        let cap = tree.capacity();
        self.count.resize(cap, 1);
        self.label.resize(cap, 0);
        let mut used: Vec<(NodeId, u32)> = held
            .iter()
            .zip(&self.of_particle)
            .map(|(&n, &c)| (n, c))
            .collect();
        for c in 0..cap as NodeId {
            if tree.is_alive(c) && c != tree.root() {
                used.push((tree.parent(c), self.label[c as usize]));
            }
        }
        used.sort_unstable();
        used.dedup();
        for (n, _) in used.iter().filter(|(n, _)| tree.is_alive(*n)) {
            self.count[*n as usize] = 0;
        }
        for (n, _) in used {
            if tree.is_alive(n) {
                self.count[n as usize] += 1;
            }
        }
    }
}

/// How [`grow`] records free space (see `MapConfig`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapUpdate {
    /// Share free-space updates of cells all see as free.
    pub shared: bool,
    /// How many new nodes feed that shared update (0: all).
    pub sharers: usize,
}

/// Adds the ancestry nodes of the new particles: particle `i` copies sample
/// `sources[i]` and is a child of `parents[i]` recording `payload(i)`, with
/// its observation of `views(i)` (scans at map poses) made against the
/// parent's view of the map, and was drawn from the particle `origins[i]`
/// of the previous generation (for `copies`). Returns each particle's node.
///
/// Particles that copy the same sample (runs of equal `sources`: [`draw`]
/// returns the chosen samples in ascending order) are the same particle:
/// they share one node, so the sample is traced once and its entries stored
/// once. After this step every view of the map is the same as with one
/// node per copy (the copies' entries would be equal, and the free-space
/// shares below are still added once per copy, in order). Later steps
/// differ only under `MapUpdate::shared`: the copies' descendants then pool
/// their in-place shares on the one node's entries, where each copy's
/// subtree used to feed its own; so each share added in place is divided by
/// the owner's [`Copies::count`], which keeps the entry at the mean of the
/// per-copy entries (without it new cells accrued free path up to k times
/// faster and fr079-raw was lost, docs/PROPOSAL-2D.md). With a sharp
/// proposal most of the chosen samples are copies: this is most of the map
/// update's work and memory.
///
/// Observations go in chunks of distinct samples (in index order), each
/// chunk traced in parallel. The new entries wait for all observations
/// (they are made against the parents' views), but the free-space parts are
/// folded as each chunk ends into the running path length of each (owner,
/// cell): one value per pair instead of one per particle, and the same
/// float additions, in the same order, as adding each particle's share in
/// place. That fold runs in parallel too, one [`FreeShard`] of the cells
/// per task: a cell's additions all happen in one shard, in observation
/// order, so the sums do not depend on the thread count.
#[allow(clippy::too_many_arguments)]
pub fn grow<'s, const D: usize, P: Pose<D>, T: Clone, V>(
    map: &mut DpMap<D>,
    tree: &mut AncestryTree<T>,
    numbering: &Numbering,
    caches: &CpuScorer<D>,
    laser: &LaserModel,
    update: MapUpdate,
    copies: &mut Copies,
    parents: &[NodeId],
    sources: &[usize],
    origins: &[usize],
    views: impl Fn(usize) -> V + Sync,
    mut payload: impl FnMut(usize) -> Vec<T>,
) -> Vec<NodeId>
where
    V: IntoIterator<Item = (P, &'s Scan<D, P>)>,
    Scan<D, P>: 's,
{
    let n = parents.len();
    debug_assert_eq!(sources.len(), n);
    debug_assert_eq!(origins.len(), n);
    let sharers = match update.sharers {
        0 => n,
        m => m.min(n),
    };
    // Exactly `sharers` of the indices 0..n pass, evenly spread.
    let shares = |i: usize| (i * sharers) % n < sharers;
    let share = 1.0 / sharers.max(1) as f32;
    // The first particle of each run of copies, and where its run ends.
    let firsts: Vec<usize> = (0..n)
        .filter(|&i| i == 0 || sources[i] != sources[i - 1])
        .collect();
    let run_end = |r: usize| firsts.get(r + 1).copied().unwrap_or(n);
    let chunk = (8 * rayon::current_num_threads()).max(16);
    let mut new_entries: Vec<Vec<(CellKey<D>, f32, f32)>> = Vec::with_capacity(firsts.len());
    let mut free: Vec<FreeShard<D>> = (0..FREE_SHARDS).map(|_| FreeShard::default()).collect();
    for lo in (0..firsts.len()).step_by(chunk) {
        let hi = (lo + chunk).min(firsts.len());
        let shared_map: &DpMap<D> = map;
        let observations: Vec<Observation<D>> = map_in_preorder(
            hi - lo,
            |r| numbering.enter[parents[firsts[lo + r]] as usize],
            |r| {
                let i = firsts[lo + r];
                let mut cache = caches.thread_cache();
                let mut view = shared_map.view(numbering, parents[i]);
                let mut lists = shared_map.view(numbering, parents[i]);
                observe(
                    laser,
                    &mut caches.thread_sums(),
                    |k| view.entry_cached(&mut cache, k),
                    |k, owner| lists.position(k, owner),
                    views(i),
                    update.shared,
                    (i..run_end(lo + r)).any(shares),
                )
            },
        );
        let copies: &Copies = copies;
        free.par_iter_mut().enumerate().for_each(|(s, shard)| {
            for (r, obs) in (lo..hi).zip(&observations) {
                for _copy in (firsts[r]..run_end(r)).filter(|&i| shares(i)) {
                    for f in obs.free_in(s) {
                        shard.add(f, f.path * share / copies.count(f.owner) as f32);
                    }
                }
            }
        });
        new_entries.extend(observations.into_iter().map(|obs| obs.new));
    }
    // The owners' entries were found before any edit; the new nodes'
    // entries below only append to lists, so the positions hold either way.
    map.set_distances_at(free.iter().flat_map(|shard| shard.edits()));
    let mut nodes = Vec::with_capacity(n);
    let mut fresh = Vec::with_capacity(new_entries.len());
    for (r, new) in new_entries.into_iter().enumerate() {
        let i = firsts[r];
        let node = tree.add_child_records(parents[i], payload(i));
        fresh.push((node, new));
        nodes.extend(std::iter::repeat_n(node, run_end(r) - i));
    }
    map.insert_fresh_nodes(&fresh);
    copies.grown(&nodes, origins);
    nodes
}

/// How many shards [`grow`] folds free space in (any number gives the same
/// sums; enough to balance a few threads).
const FREE_SHARDS: usize = 16;

/// The shard of cell `k`: by brick of 8^D cells, so that one shard's
/// entries stay in few of the map's bricks.
fn free_shard<const D: usize>(k: CellKey<D>) -> usize {
    let h = k.iter().fold(0u64, |h, &c| {
        (h.rotate_left(5) ^ u64::from((c >> 3) as u32)).wrapping_mul(0x517c_c1b7_2722_0a95)
    });
    (h >> 32) as usize % FREE_SHARDS
}

/// The running path length (m) of each (owner, cell) in one shard of the
/// cells, with where the owner's entry sits in its cell's list.
#[derive(Default)]
struct FreeShard<const D: usize> {
    sums: FxHashMap<(NodeId, CellKey<D>), (u32, f32)>,
}

impl<const D: usize> FreeShard<D> {
    /// Adds `d` metres to the entry `f` is about, starting from the path
    /// length it had in the map the first time the pair is seen.
    fn add(&mut self, f: &FreeShare<D>, d: f32) {
        self.sums
            .entry((f.owner, f.cell))
            .or_insert((f.position, f.before))
            .1 += d;
    }

    /// `(cell, position in its list, path length m)` for each pair.
    fn edits(&self) -> impl Iterator<Item = (CellKey<D>, u32, f32)> + '_ {
        self.sums.iter().map(|(&(_, k), &(pos, d))| (k, pos, d))
    }
}

/// The particles made from the `chosen` samples: sample `chosen[i]` at
/// `pose(chosen[i])` (map frame) on the new node `nodes[i]` (from
/// [`grow`]); with the index of the best-scoring one (the first on ties).
pub fn offspring<P: Copy>(
    chosen: &[usize],
    scores: &[f64],
    nodes: Vec<NodeId>,
    pose: impl Fn(usize) -> P,
) -> (Vec<Particle<P>>, usize) {
    let mut best = (f64::NEG_INFINITY, 0);
    let mut next = Vec::with_capacity(chosen.len());
    for (i, (&j, node)) in chosen.iter().zip(nodes).enumerate() {
        if scores[j] > best.0 {
            best = (scores[j], i);
        }
        next.push(Particle {
            pose: pose(j),
            node,
        });
    }
    (next, best.1)
}

/// Removes dead branches and merges only-children, in the tree and the map
/// alike (the particles' nodes are kept and rewritten where merged), then
/// recounts the nodes' copies in use and renumbers the tree.
pub fn prune<const D: usize, T: Clone, P>(
    tree: &mut AncestryTree<T>,
    map: &mut DpMap<D>,
    copies: &mut Copies,
    numbering: &mut Numbering,
    particles: &mut [Particle<P>],
) {
    let mut held: Vec<NodeId> = particles.iter().map(|p| p.node).collect();
    let mut changes = tree.remove_dead(&held);
    // A child with several copies in use was several children before
    // copies shared a node: it stays a node of its own until one is left.
    // (So a particle's parent node, the scan matcher's group in `predict`,
    // is again, up to copies, the one it had with one node per copy.)
    copies.recount(tree, &held);
    changes.extend(tree.collapse(&mut held, |c| copies.count(c) <= 1));
    map.apply(&changes);
    copies.recount(tree, &held);
    for (p, h) in particles.iter_mut().zip(held) {
        p.node = h;
    }
    tree.number(numbering);
}

/// One pose's observation of a scan.
struct Observation<const D: usize> {
    /// New entries `(cell, hits, distance m)` for the observing particle's node.
    new: Vec<(CellKey<D>, f32, f32)>,
    /// Free-space path lengths to add in place, grouped by [`free_shard`].
    free: FreeShards<D>,
}

impl<const D: usize> Observation<D> {
    /// The free-space path lengths of cells in shard `s`.
    fn free_in(&self, s: usize) -> &[FreeShare<D>] {
        &self.free.0[s]
    }
}

/// Free shares grouped by [`free_shard`] as they are pushed, each shard
/// in push order (no sort: a sort of each particle's shares was 5 % of
/// mit-csail's CPU time).
struct FreeShards<const D: usize>([Vec<FreeShare<D>>; FREE_SHARDS]);

impl<const D: usize> FreeShards<D> {
    fn new() -> Self {
        Self(std::array::from_fn(|_| Vec::new()))
    }

    fn push(&mut self, f: FreeShare<D>) {
        self.0[free_shard(f.cell)].push(f);
    }
}

/// Free path through a cell that the observing particle sees as free, to be
/// added in place to the entry it sees there.
struct FreeShare<const D: usize> {
    /// The node whose entry the particle sees.
    owner: NodeId,
    cell: CellKey<D>,
    /// Where that entry sits in the cell's list.
    position: u32,
    /// Its path length (m) before this step.
    before: f32,
    /// The path length (m) the scans add.
    path: f32,
}

/// One particle's observation of scans (each at its map pose): for each
/// cell crossed, the path length and hits of these scans added to what the
/// particle sees (`entry_of`), or to the prior where it has never seen the
/// cell. With `shared_free`, a cell that the particle sees as free and the
/// scans only pass through is reported in `free` instead (if
/// `record_free`), to be added in place to the entry it sees, found at
/// `position_of(cell, owner)` in the cell's list.
fn observe<'s, const D: usize, P: Pose<D>>(
    laser: &LaserModel,
    sums: &mut CellSums<D>,
    mut entry_of: impl FnMut(CellKey<D>) -> Option<crate::dpmap::Entry>,
    mut position_of: impl FnMut(CellKey<D>, NodeId) -> Option<u32>,
    views: impl IntoIterator<Item = (P, &'s Scan<D, P>)>,
    shared_free: bool,
    record_free: bool,
) -> Observation<D>
where
    Scan<D, P>: 's,
{
    sums.clear();
    let filling = laser.fill_gap > 0.0;
    let mut ends = Vec::new();
    for (pose, scan) in views {
        let sensor = pose.compose(&scan.sensor);
        let origin = sensor.translation();
        let mut add = |k: CellKey<D>, h: f32, d: f32| sums.add(k, h, d);
        ends.clear();
        for b in &scan.beams {
            let dir = sensor.rotate(b.dir);
            laser.trace_update(origin, dir, b.range, b.no_return, &mut add);
            if filling {
                ends.push(
                    (!b.no_return).then(|| std::array::from_fn(|i| origin[i] + dir[i] * b.range)),
                );
            }
        }
        laser.surface_update(&ends, &mut add);
    }
    let prior = laser.prior_distance as f32;
    // The cells in the order the map stores them: the look-ups below walk
    // the map's memory in order instead of in hash order, and the new
    // entries come out in storage order, as their insertion wants them.
    sums.finish();
    let cells = &sums.ordered;
    let mut new = Vec::with_capacity(cells.len() / 4);
    let mut free = FreeShards::new();
    for &(k, (h, d)) in cells.iter() {
        match entry_of(k) {
            Some(e) if shared_free && e.hits <= 0.0 && h <= 0.0 => {
                if record_free && let Some(position) = position_of(k, e.node) {
                    free.push(FreeShare {
                        owner: e.node,
                        cell: k,
                        position,
                        before: e.distance,
                        path: d,
                    });
                }
            }
            Some(e) => new.push((k, e.hits + h, e.distance + d)),
            None => new.push((k, h, d + prior)),
        }
    }
    // Keys are unique and sorted: the map edits (and float sums) are the
    // same on every run and thread.
    Observation { new, free }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ancestry::Change;

    #[test]
    fn free_shares_group_by_shard_keeping_their_order() {
        let mut free = FreeShards::new();
        for i in 0..400 {
            free.push(FreeShare {
                owner: 1,
                cell: [i * 7 - 900, i % 13 - 6],
                position: 0,
                before: 0.0,
                path: i as f32,
            });
        }
        let obs = Observation {
            new: Vec::new(),
            free,
        };
        let mut seen = 0;
        for s in 0..FREE_SHARDS {
            let shard = obs.free_in(s);
            assert!(shard.iter().all(|f| free_shard(f.cell) == s));
            // Stable: each shard keeps the input order (here, by `path`).
            assert!(shard.windows(2).all(|w| w[0].path < w[1].path));
            seen += shard.len();
        }
        assert_eq!(seen, 400);
        assert!(
            (0..FREE_SHARDS)
                .filter(|&s| !obs.free_in(s).is_empty())
                .count()
                > 4
        );
    }

    #[test]
    fn copies_count_the_copies_in_use_and_hold_back_merges() {
        let mut tree = AncestryTree::new(vec![0u32]);
        let root = tree.root();
        let mut copies = Copies::planted(4);
        // Generation 1: sample a picked twice, b twice (all from the root).
        let a = tree.add_child(root, 1);
        let b = tree.add_child(root, 1);
        copies.grown(&[a, a, b, b], &[0, 1, 2, 3]);
        let mut held = vec![a, a, b, b];
        copies.recount(&tree, &held);
        assert_eq!(
            [copies.count(root), copies.count(a), copies.count(b)],
            [1, 2, 2]
        );
        // Generation 2: c from particle 0 (copy 0 of a), d three times from
        // particle 1 (copy 1 of a); b dies.
        let c = tree.add_child(a, 2);
        let d = tree.add_child(a, 2);
        copies.grown(&[c, d, d, d], &[0, 1, 1, 1]);
        held = vec![c, d, d, d];
        assert!(!tree.remove_dead(&held).is_empty());
        copies.recount(&tree, &held);
        assert_eq!(
            [copies.count(a), copies.count(c), copies.count(d)],
            [2, 1, 3]
        );
        // Generation 3: only d's copy 2 (particle 3) has offspring, one
        // sample picked four times: d has one copy in use, a one too.
        let e = tree.add_child(d, 3);
        copies.grown(&[e, e, e, e], &[3, 3, 3, 3]);
        held = vec![e; 4];
        tree.remove_dead(&held);
        copies.recount(&tree, &held);
        assert_eq!(
            [copies.count(a), copies.count(d), copies.count(e)],
            [1, 1, 4]
        );
        // d is absorbed (one copy), e is not (four copies, four children before).
        let merged = tree.collapse(&mut held, |n| copies.count(n) <= 1);
        assert!(merged.contains(&Change::Merged {
            child: a,
            into: root
        }));
        assert!(merged.contains(&Change::Merged {
            child: d,
            into: root
        }));
        assert_eq!(tree.children(root), &[e]);
        copies.recount(&tree, &held);
        assert_eq!([copies.count(root), copies.count(e)], [1, 4]);
    }
}
