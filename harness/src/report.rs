//! Benchmark results as Markdown: the per-dataset table and `docs/RESULTS.md`.

use super::scaling::ScalingReport;
use dpslam::eval::relations::RelationsReport;
use serde::Serialize;

/// Kümmerle et al. 2009 (Auton. Robots 27(4), Table 1), mean translational
/// relations error, m: (dataset, scan matching, RBPF = GMapping with 50
/// particles, graph mapping).
pub const PUBLISHED: [(&str, f64, f64, f64); 3] = [
    ("mit-csail", 0.106, 0.049, 0.004),
    ("aces-raw", 0.173, 0.060, 0.044),
    ("fr079-raw", 0.258, 0.061, 0.056),
];

/// How the truth trajectory was paired with the estimate for ATE.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Matching {
    /// By time stamp (within the ATE tolerance).
    Time,
    /// By scan index: both files hold one pose per input scan, in input order.
    /// Used where the log's time stamps cannot tell scans apart.
    ScanIndex,
}

/// The outcome of mapping one benchmark dataset.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunResult {
    /// Dataset name (also the run folder's name).
    pub name: String,
    /// What the input is, e.g. "raw log + relations".
    pub kind: String,
    /// Laser scans in the input.
    pub scans: usize,
    /// Scans the filter processed.
    pub scans_processed: usize,
    /// Particles.
    pub particles: usize,
    /// Relations error of the estimate (where relations exist).
    pub relations: Option<RelationsReport>,
    /// Relations error of the raw odometry.
    pub odometry_relations: Option<RelationsReport>,
    /// ATE RMSE of the estimate, m (where a truth trajectory exists).
    pub ate_rmse_m: Option<f64>,
    /// ATE RMSE of the odometry, m.
    pub odometry_ate_rmse_m: Option<f64>,
    /// How truth and estimate were paired for ATE.
    pub matching: Option<Matching>,
    /// Wall-clock time of the mapping run, s.
    pub wall_time_s: f64,
    /// Time span of the log, s (`None` where its time stamps are unusable).
    pub data_duration_s: Option<f64>,
    /// Peak resident memory of the process during this run, MiB.
    pub peak_memory_mib: Option<f64>,
    /// DP-map size at the end of the run, MiB.
    pub map_memory_mib: f64,
    /// Map image, relative to the results document.
    pub map_image: Option<String>,
    /// Trajectory plot, relative to the results document.
    pub trajectory_plot: Option<String>,
    /// Remarks (subset used, time stamps, ...).
    pub note: Option<String>,
}

impl RunResult {
    /// Data duration / wall time (> 1: faster than real time).
    pub fn real_time_factor(&self) -> Option<f64> {
        self.data_duration_s
            .filter(|_| self.wall_time_s > 0.0)
            .map(|d| d / self.wall_time_s)
    }
}

/// A dataset that was not run, and why.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Skipped {
    /// Dataset name.
    pub name: String,
    /// Why it was skipped.
    pub reason: String,
}

/// Everything `docs/RESULTS.md` reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AccuracyReport {
    /// `--quick`: a short subset, a smoke test rather than a result.
    pub quick: bool,
    /// The command line that produced the report.
    pub command: String,
    /// dpslam version.
    pub version: String,
    /// Worker threads.
    pub threads: usize,
    /// Seed of the odometry noise of the perturbed logs.
    pub noise_seed: u64,
    /// Noise model of the perturbed logs, in `--noise` spec form.
    pub noise: String,
    /// How peak memory was measured.
    pub memory_note: String,
    /// Wall time of the whole benchmark, s.
    pub total_wall_s: f64,
    /// One entry per dataset run.
    pub runs: Vec<RunResult>,
    /// Datasets not run.
    pub skipped: Vec<Skipped>,
    /// Path of the time-per-iteration plot relative to the document, if any.
    pub scaling_plot: Option<String>,
    /// The particle-scaling measurement of this run, if it ran.
    pub scaling: Option<ScalingReport>,
}

/// A Markdown table cell: `|` and line breaks would break the row.
fn cell(s: &str) -> String {
    s.replace('|', "\\|").replace(['\n', '\r'], " ")
}

fn opt(v: Option<f64>, decimals: usize) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.decimals$}"),
        _ => "–".to_string(),
    }
}

fn rel_trans(r: &Option<RelationsReport>) -> String {
    r.as_ref().map_or("–".into(), |r| {
        format!("{:.3} ± {:.3}", r.trans_mean_m, r.trans_std_m)
    })
}

fn rel_rot(r: &Option<RelationsReport>) -> String {
    r.as_ref().map_or("–".into(), |r| {
        format!("{:.2} ± {:.2}", r.rot_mean_deg, r.rot_std_deg)
    })
}

/// Renders rows as a Markdown table (header, separator, one row each).
pub fn markdown_table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut out = String::new();
    let line = |cells: &mut dyn Iterator<Item = String>| {
        let mut s = String::from("|");
        for c in cells {
            s.push(' ');
            s.push_str(&cell(&c));
            s.push_str(" |");
        }
        s.push('\n');
        s
    };
    out += &line(&mut header.iter().map(|h| h.to_string()));
    out += &line(&mut header.iter().map(|_| "---".to_string()));
    for r in rows {
        let mut cells = r.clone();
        cells.resize(header.len(), String::new());
        out += &line(&mut cells.into_iter());
    }
    out
}

/// Column titles of [`results_table`].
pub const RESULT_COLUMNS: [&str; 15] = [
    "dataset",
    "scans (processed)",
    "particles",
    "relations trans m",
    "relations rot °",
    "odometry relations trans m",
    "odometry relations rot °",
    "ATE RMSE m",
    "odometry ATE RMSE m",
    "wall s",
    "data s",
    "real-time factor",
    "peak memory MiB",
    "map MiB",
    "map",
];

/// The per-dataset results table: one row per run, columns [`RESULT_COLUMNS`].
pub fn results_table(runs: &[RunResult]) -> String {
    let rows: Vec<Vec<String>> = runs
        .iter()
        .map(|r| {
            let mut ate = opt(r.ate_rmse_m, 3);
            if r.matching == Some(Matching::ScanIndex) {
                ate.push_str(" (by index)");
            }
            vec![
                r.name.clone(),
                format!("{} ({})", r.scans, r.scans_processed),
                r.particles.to_string(),
                rel_trans(&r.relations),
                rel_rot(&r.relations),
                rel_trans(&r.odometry_relations),
                rel_rot(&r.odometry_relations),
                ate,
                opt(r.odometry_ate_rmse_m, 3),
                format!("{:.1}", r.wall_time_s),
                opt(r.data_duration_s, 1),
                opt(r.real_time_factor(), 2),
                opt(r.peak_memory_mib, 0),
                format!("{:.0}", r.map_memory_mib),
                r.map_image
                    .as_ref()
                    .map_or("–".into(), |p| format!("[map]({p})")),
            ]
        })
        .collect();
    markdown_table(&RESULT_COLUMNS, &rows)
}

/// Ours beside Kümmerle et al. 2009's published figures (mean translational
/// relations error, m) for each raw log that was run.
pub fn published_table(runs: &[RunResult]) -> String {
    let rows: Vec<Vec<String>> = PUBLISHED
        .iter()
        .filter_map(|&(name, sm, rbpf, graph)| {
            let r = runs.iter().find(|r| r.name == name)?;
            Some(vec![
                name.to_string(),
                rel_trans(&r.relations),
                rel_rot(&r.relations),
                format!("{sm:.3}"),
                format!("{rbpf:.3}"),
                format!("{graph:.3}"),
            ])
        })
        .collect();
    markdown_table(
        &[
            "raw log",
            "ours: relations trans m",
            "ours: rot °",
            "scan matching (published)",
            "RBPF, GMapping 50 particles (published)",
            "graph mapping (published)",
        ],
        &rows,
    )
}

/// Published and measured reference points for mit-csail (relations error).
pub fn anchors_table() -> String {
    let rows = [
        [
            "GMapping (Kümmerle et al. 2009)",
            "0.049 ± 0.049",
            "–",
            "–",
            "–",
            "published",
        ],
        [
            "graph mapping (Kümmerle et al. 2009)",
            "0.004 ± 0.009",
            "–",
            "–",
            "–",
            "published",
        ],
        [
            "scan matching (Kümmerle et al. 2009)",
            "0.106 ± 0.325",
            "–",
            "–",
            "–",
            "published",
        ],
        [
            "DP-SLAM 0.1.1, 50 + 50 particles",
            "0.043 ± 0.038",
            "0.56",
            "unfinished after 1 h",
            "> 776",
            "measured, first 178 s only (DPSLAM.md)",
        ],
        [
            "GMapping, 30 particles",
            "0.056 ± 0.060",
            "3.4",
            "125",
            "95",
            "measured (DPSLAM.md)",
        ],
        [
            "GMapping, 100 particles",
            "0.057 ± 0.058",
            "3.4",
            "411",
            "357",
            "measured (DPSLAM.md)",
        ],
    ];
    let rows: Vec<Vec<String>> = rows
        .iter()
        .map(|r| r.iter().map(|s| s.to_string()).collect())
        .collect();
    markdown_table(
        &[
            "program on mit-csail",
            "relations trans m",
            "rot °",
            "wall s",
            "peak MiB",
            "source",
        ],
        &rows,
    )
}

/// The whole `docs/RESULTS.md`.
pub fn results_markdown(r: &AccuracyReport) -> String {
    let mut s = String::from("# Benchmark results\n\n");
    s += "Generated by `dpslam bench accuracy` (see docs/BENCHMARKS.md); do not edit by hand.\n\n";
    if r.quick {
        s += "**Quick run (`--quick`)**: short subsets of the logs, a smoke test of the \
              harness, not a result to quote.\n\n";
    }
    s += &format!(
        "- command: `{}`\n- dpslam {}, {} worker threads, total wall time {:.0} s\n\
         - perturbed logs: odometry noise `{}`, seed {} (`dpslam perturb` model)\n\
         - peak memory: {}\n\
         - relations: Kümmerle et al. 2009 metric, mean ± std; ATE: RMSE after SE(2) alignment\n\
         - real-time factor: data duration / wall time (> 1 is faster than real time)\n\n",
        r.command, r.version, r.threads, r.total_wall_s, r.noise, r.noise_seed, r.memory_note
    );
    s += "## Results\n\n";
    s += &results_table(&r.runs);
    let notes: Vec<String> = r
        .runs
        .iter()
        .filter_map(|x| x.note.as_ref().map(|n| format!("- {}: {}", x.name, n)))
        .collect();
    if !notes.is_empty() {
        s += "\nNotes:\n\n";
        s += &notes.join("\n");
        s.push('\n');
    }
    if !r.skipped.is_empty() {
        s += "\nNot run:\n\n";
        for k in &r.skipped {
            s += &format!("- {}: {}\n", k.name, k.reason);
        }
    }
    if r.runs
        .iter()
        .any(|x| PUBLISHED.iter().any(|p| p.0 == x.name))
    {
        s += "\n## Raw logs beside Kümmerle et al. 2009\n\n";
        s += "Mean translational relations error, m; published figures from \
              Kümmerle et al., Auton. Robots 27(4), 2009, Table 1. A `--quick` run \
              scores only the relations inside its subset.\n\n";
        s += &published_table(&r.runs);
    }
    s += "\n## Anchors (mit-csail)\n\n";
    s += &anchors_table();
    s += "\nThe mit-csail log lasts 424 s: a wall time above that is slower than real time.\n";
    s += "\n## Trajectories\n\n";
    s += "Blue: estimate (best particle); red: truth; grey: odometry. Estimate and \
          odometry are aligned to the truth (SE(2), as for ATE); without truth, odometry \
          is aligned to the estimate. Axes in metres.\n\n";
    for x in &r.runs {
        if let Some(p) = &x.trajectory_plot {
            s += &format!("### {}\n\n![{} trajectory]({p})", x.name, x.name);
            if let Some(m) = &x.map_image {
                s += &format!(" ![{} map]({m})", x.name);
            }
            s += "\n\n";
        }
    }
    if r.scaling.is_some() || r.scaling_plot.is_some() {
        s += "## Time per iteration vs particles\n\n";
    }
    if let Some(sc) = &r.scaling {
        s += &scaling_section(sc);
    }
    if let Some(p) = &r.scaling_plot {
        s += &format!(
            "![time per iteration]({p})\n\n\
             x: particles, y: seconds per filter step (`dpslam bench scaling`, run by \
             `bench accuracy` unless `--no-scaling`).\n"
        );
    }
    s
}

/// The scaling table and its fitted figures.
fn scaling_section(sc: &ScalingReport) -> String {
    let rows: Vec<Vec<String>> = sc
        .points
        .iter()
        .map(|p| {
            vec![
                p.particles.to_string(),
                format!("{:.3}", p.mean_step_s),
                format!("{:.3}", p.min_step_s),
                format!("{:.1}", p.per_particle_us),
            ]
        })
        .collect();
    let mut s = format!(
        "Log `{}`: {} processed scans build the map, then {} steps are timed per \
         particle count ({} worker threads).\n\n",
        sc.log.file_name().map_or_else(
            || sc.log.display().to_string(),
            |n| n.to_string_lossy().into_owned()
        ),
        sc.warmup_scans,
        sc.timed_steps,
        sc.threads
    );
    s += &markdown_table(
        &[
            "particles",
            "mean s per step",
            "fastest s",
            "µs per particle",
        ],
        &rows,
    );
    s += &format!(
        "\n- least-squares slope **{:.2} ms per particle**, intercept {:.0} ms\n\
         - log-log exponent {:.3} (1 = linear)\n",
        sc.slope_ms_per_particle, sc.intercept_ms, sc.loglog_exponent
    );
    if let Some(q) = sc.ratio_3000_300 {
        s += &format!("- 3000 vs 300 particles: **{q:.1}×** the time (linear: 10×)\n");
    }
    s.push('\n');
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scaling::{ScalingPoint, summarize};

    #[test]
    fn scaling_section_reports_the_measured_ratio_and_slope() {
        let points: Vec<ScalingPoint> = [(100, 0.3), (300, 0.9), (3000, 9.3)]
            .into_iter()
            .map(|(n, t)| ScalingPoint {
                particles: n,
                mean_step_s: t,
                min_step_s: t * 0.9,
                per_particle_us: t / n as f64 * 1e6,
                warmup_s: 1.0,
                phases: Default::default(),
                mean_full_traces: 0.0,
            })
            .collect();
        let (slope, intercept, exponent, ratio, largest, pr) = summarize(&points);
        let sc = ScalingReport {
            log: "data/sim2d/sim2d.clf".into(),
            warmup_scans: 20,
            timed_steps: 5,
            threads: 2,
            points,
            slope_ms_per_particle: slope,
            intercept_ms: intercept,
            loglog_exponent: exponent,
            ratio_3000_300: ratio,
            ratio_largest_smallest: largest,
            particle_ratio: pr,
        };
        let s = scaling_section(&sc);
        assert!(s.contains("sim2d.clf"), "{s}");
        assert!(s.contains("| 3000 | 9.300 |"), "{s}");
        // 9.3 / 0.9 = 10.33…
        assert!(s.contains("**10.3×**"), "{s}");
        assert!(
            s.contains(&format!("**{slope:.2} ms per particle**")),
            "{s}"
        );
    }
}
