//! Time per filter iteration against the number of particles.
//!
//! For each particle count, a filter is warmed up on the first scans of a log
//! (so the map and the ancestry tree are not trivially small), then the next
//! steps are timed one by one. DP-SLAM's claim is cost linear in particles:
//! the report gives the least-squares line, the log-log exponent and the ratio
//! of the largest to the smallest count's time (10× particles should cost
//! about 10×; the project's target is ≤ 11× for 3000 vs 300).

use super::plot::{PALETTE, Plot, Series};
use super::rig::prepare_log;
use dpslam::config::Config;
use dpslam::filter::PhaseTimes;
use dpslam::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What to time.
#[derive(Debug, Clone)]
pub struct ScalingOptions {
    /// Input log (2-D, any format `map2d` reads).
    pub log: PathBuf,
    /// Particle counts, each timed separately.
    pub particles: Vec<usize>,
    /// Processed scans used to build the map before timing.
    pub warmup_scans: usize,
    /// Steps timed after the warm-up.
    pub timed_steps: usize,
    /// Filter, laser and motion settings (`filter.particles` is overridden).
    pub cfg: Config,
}

/// Timing of one particle count.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScalingPoint {
    /// Particles.
    pub particles: usize,
    /// Mean wall time of one step, s.
    pub mean_step_s: f64,
    /// Fastest step, s.
    pub min_step_s: f64,
    /// Mean step time per particle, µs.
    pub per_particle_us: f64,
    /// Wall time of the warm-up, s (not part of the step times).
    pub warmup_s: f64,
    /// Mean wall time of each phase of a timed step, s: where a
    /// super-linear cost comes from.
    pub phases: PhaseTimes,
    /// Mean samples per timed step that reached the full traces.
    pub mean_full_traces: f64,
}

/// The scaling measurement.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScalingReport {
    /// Input log.
    pub log: PathBuf,
    /// Processed scans used to build the map before timing.
    pub warmup_scans: usize,
    /// Steps timed per particle count.
    pub timed_steps: usize,
    /// Worker threads.
    pub threads: usize,
    /// One point per particle count, in the order asked.
    pub points: Vec<ScalingPoint>,
    /// Least-squares slope of step time against particles, ms per particle.
    pub slope_ms_per_particle: f64,
    /// Intercept of that line, ms (fixed cost per step).
    pub intercept_ms: f64,
    /// Least-squares slope of log(time) against log(particles): 1 is linear.
    pub loglog_exponent: f64,
    /// Step time at 3000 particles / at 300, where both were timed.
    pub ratio_3000_300: Option<f64>,
    /// Step time at the largest count / at the smallest.
    pub ratio_largest_smallest: f64,
    /// Particles at the largest count / at the smallest.
    pub particle_ratio: f64,
}

/// Least-squares line `y = a + b·x`; returns `(a, b)`.
pub fn fit_line(xs: &[f64], ys: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    let mx = xs.iter().sum::<f64>() / n;
    let my = ys.iter().sum::<f64>() / n;
    let sxy: f64 = xs.iter().zip(ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    (my - b * mx, b)
}

/// Fits the summary figures to measured points (at least one).
pub fn summarize(points: &[ScalingPoint]) -> (f64, f64, f64, Option<f64>, f64, f64) {
    let xs: Vec<f64> = points.iter().map(|p| p.particles as f64).collect();
    let ys: Vec<f64> = points.iter().map(|p| p.mean_step_s).collect();
    let (a, b) = fit_line(&xs, &ys);
    let lx: Vec<f64> = xs.iter().map(|x| x.ln()).collect();
    let ly: Vec<f64> = ys.iter().map(|y| y.max(1e-12).ln()).collect();
    let (_, exponent) = fit_line(&lx, &ly);
    let at = |n: usize| {
        points
            .iter()
            .find(|p| p.particles == n)
            .map(|p| p.mean_step_s)
    };
    let ratio = match (at(3000), at(300)) {
        (Some(hi), Some(lo)) if lo > 0.0 => Some(hi / lo),
        _ => None,
    };
    let lo = points
        .iter()
        .min_by_key(|p| p.particles)
        .expect("at least one point");
    let hi = points
        .iter()
        .max_by_key(|p| p.particles)
        .expect("at least one point");
    (
        b * 1e3,
        a * 1e3,
        exponent,
        ratio,
        hi.mean_step_s / lo.mean_step_s,
        hi.particles as f64 / lo.particles as f64,
    )
}

/// Times full filter steps for each particle count.
pub fn run_scaling(opts: &ScalingOptions) -> Result<ScalingReport> {
    if opts.particles.is_empty() || opts.particles.contains(&0) {
        return Err(Error::Config(
            "particle counts must be a non-empty list of positive numbers".into(),
        ));
    }
    if opts.timed_steps == 0 {
        return Err(Error::Config("at least one step must be timed".into()));
    }
    let log = prepare_log(&opts.log, &opts.cfg, opts.warmup_scans + opts.timed_steps)?;
    if log.steps.len() < opts.warmup_scans + opts.timed_steps {
        return Err(Error::Invalid(format!(
            "{}: {} processed scans after the first, {} warm-up + {} timed needed",
            opts.log.display(),
            log.steps.len(),
            opts.warmup_scans,
            opts.timed_steps
        )));
    }
    // Every count's filter is warmed up first, then the timed steps take
    // turns (scan 1 at each count, scan 2 at each count, ...): on a shared
    // machine whose speed drifts within a minute, timing one count after
    // the other put the drift into the ratio (the same build gave 8× to
    // 14× for 3000 vs 300); in turns, each count sees the same drift.
    let mut filters = Vec::with_capacity(opts.particles.len());
    for &n in &opts.particles {
        let t0 = Instant::now();
        let filter = log.warm_filter(n, opts.warmup_scans)?;
        filters.push((filter, t0.elapsed().as_secs_f64()));
    }
    let mut times = vec![Vec::with_capacity(opts.timed_steps); filters.len()];
    let mut phases = vec![PhaseTimes::default(); filters.len()];
    let mut full_traces = vec![0usize; filters.len()];
    for s in &log.steps[opts.warmup_scans..opts.warmup_scans + opts.timed_steps] {
        for (i, (filter, _)) in filters.iter_mut().enumerate() {
            let t = Instant::now();
            let stats = std::hint::black_box(filter.step(&s.input()));
            times[i].push(t.elapsed().as_secs_f64());
            phases[i] += stats.times;
            full_traces[i] += stats.after_quick;
        }
    }
    let mut points = Vec::with_capacity(opts.particles.len());
    for (i, ((&n, (_, warmup_s)), times)) in
        opts.particles.iter().zip(&filters).zip(&times).enumerate()
    {
        let mean = times.iter().sum::<f64>() / times.len() as f64;
        let min = times.iter().cloned().fold(f64::INFINITY, f64::min);
        eprintln!(
            "scaling: {n} particles: {:.1} ms per step (warm-up {warmup_s:.1} s)",
            mean * 1e3
        );
        points.push(ScalingPoint {
            particles: n,
            mean_step_s: mean,
            min_step_s: min,
            per_particle_us: mean / n as f64 * 1e6,
            warmup_s: *warmup_s,
            phases: phases[i].per(times.len() as f64),
            mean_full_traces: full_traces[i] as f64 / times.len() as f64,
        });
    }
    let (slope, intercept, exponent, ratio, ratio_ls, particle_ratio) = summarize(&points);
    Ok(ScalingReport {
        log: opts.log.clone(),
        warmup_scans: opts.warmup_scans,
        timed_steps: opts.timed_steps,
        threads: rayon::current_num_threads(),
        points,
        slope_ms_per_particle: slope,
        intercept_ms: intercept,
        loglog_exponent: exponent,
        ratio_3000_300: ratio,
        ratio_largest_smallest: ratio_ls,
        particle_ratio,
    })
}

/// Writes the time-per-iteration plot: measured points (blue, markers) and
/// the straight line through the origin and the smallest count's time
/// (grey), i.e. what perfectly linear scaling would give.
pub fn write_scaling_plot(report: &ScalingReport, path: &Path) -> Result<()> {
    let mut pts: Vec<[f64; 2]> = report
        .points
        .iter()
        .map(|p| [p.particles as f64, p.mean_step_s])
        .collect();
    pts.sort_by(|a, b| a[0].total_cmp(&b[0]));
    let (lo, hi) = (pts[0], pts[pts.len() - 1]);
    let linear = vec![[0.0, 0.0], [hi[0], lo[1] / lo[0] * hi[0]]];
    let mut plot = Plot::new(640, 420);
    plot.include_origin = true;
    plot.series.push(Series {
        label: "linear from the smallest count".into(),
        points: linear,
        color: PALETTE[2],
        markers: false,
    });
    plot.series.push(Series {
        label: "measured".into(),
        points: pts,
        color: PALETTE[0],
        markers: true,
    });
    plot.write_png(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(n: usize, s: f64) -> ScalingPoint {
        ScalingPoint {
            particles: n,
            mean_step_s: s,
            min_step_s: s,
            per_particle_us: s / n as f64 * 1e6,
            warmup_s: 0.0,
            phases: Default::default(),
            mean_full_traces: 0.0,
        }
    }

    #[test]
    fn linear_costs_give_exponent_one_and_ratio_ten() {
        let pts: Vec<_> = [100, 300, 1000, 3000]
            .into_iter()
            .map(|n| point(n, 0.002 + 1e-4 * n as f64))
            .collect();
        let (slope, intercept, exp, ratio, _, pr) = summarize(&pts);
        assert!((slope - 0.1).abs() < 1e-9, "{slope}");
        assert!((intercept - 2.0).abs() < 1e-9, "{intercept}");
        assert!(exp < 1.0 && exp > 0.8, "{exp}");
        assert!((ratio.unwrap() - 302.0 / 32.0).abs() < 1e-9);
        assert_eq!(pr, 30.0);
    }

    #[test]
    fn quadratic_costs_give_exponent_two() {
        let pts: Vec<_> = [100, 1000]
            .into_iter()
            .map(|n| point(n, (n * n) as f64))
            .collect();
        let (_, _, exp, ratio, rls, _) = summarize(&pts);
        assert!((exp - 2.0).abs() < 1e-9);
        assert_eq!(ratio, None);
        assert!((rls - 100.0).abs() < 1e-9);
    }
}
