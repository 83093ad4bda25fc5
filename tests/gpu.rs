//! The GPU scorer against the CPU reference, on Mesa lavapipe (software
//! Vulkan: `apt-get install -y mesa-vulkan-drivers libvulkan1`) or any GPU.
//!
//! Per candidate, the summed beam log-likelihoods must agree within 1e-3
//! (absolute) in f32 mode and within 1e-9 in f64 mode, on real DP-maps
//! built by the filter: several ancestry nodes, unknown cells, "no return"
//! beams, beams leaving the mapped area, quick and full traces, all beams
//! and strided subsets. lavapipe has f64 shaders, so CI runs both modes.
//!
//! The no-adapter error is tested by asking for backends this build does not
//! compile in (`Backends::GL` in-process, `WGPU_BACKEND=gl` for the binary).
//!
//! The end-to-end tests (`--ignored`, run by `.ci/run`) map the first 300
//! scans of mit-csail and the 3-D simulator with `--backend gpu` (default
//! precision: f64 on lavapipe) and `--backend cpu` and compare the
//! trajectories.
#![cfg(feature = "gpu")]

use dpslam::backend::{Backend, make_scorer};
use dpslam::filter::StepInput;
use dpslam::geometry::{Pose, Pose2, Pose3};
use dpslam::gpu::{ENTRY_CHUNKS, GpuOptions, GpuPrecision, GpuScorer, HEADER_CHUNKS};
use dpslam::laser_model::Trace;
use dpslam::scorer::{BeamSubset, CpuScorer, Scorer};
use dpslam_bench::fixtures::{Fixture, FixturePose, FixtureSpec, fixture2d, fixture3d};

/// Largest per-candidate |gpu − cpu| allowed in each precision.
fn tolerance(p: GpuPrecision) -> f64 {
    match p {
        GpuPrecision::F64 => 1e-9,
        _ => 1e-3,
    }
}

/// The GPU scorer in `precision`; `None` (test skipped, with a note) when
/// there is no adapter or it lacks that precision, unless
/// `DPSLAM_REQUIRE_GPU` is set (CI sets it: there the GPU tests must run).
fn gpu<const D: usize>(precision: GpuPrecision) -> Option<GpuScorer<D>> {
    gpu_with(GpuOptions {
        precision,
        max_binding: None,
    })
}

/// As [`gpu`], with `options`.
fn gpu_with<const D: usize>(options: GpuOptions) -> Option<GpuScorer<D>> {
    let precision = options.precision;
    match GpuScorer::with_options(options) {
        Ok(g) => {
            if precision != GpuPrecision::Auto {
                assert_eq!(g.precision(), precision);
            }
            Some(g)
        }
        Err(e) if std::env::var_os("DPSLAM_REQUIRE_GPU").is_none() => {
            eprintln!("skipped: {e} (install mesa-vulkan-drivers for lavapipe)");
            None
        }
        Err(e) => panic!("{e} (DPSLAM_REQUIRE_GPU is set)"),
    }
}

/// Scores `fx` on both backends; returns the largest per-candidate difference.
fn compare<const D: usize, P: Pose<D>>(
    fx: &Fixture<D, P>,
    g: &GpuScorer<D>,
    subset: BeamSubset,
    trace: Trace,
) -> f64 {
    let tol = tolerance(g.precision());
    let ctx = fx.context();
    let cpu = CpuScorer::<D>::new().score(&ctx, &fx.candidates, subset, trace);
    let gpu = g
        .try_score(&ctx, &fx.candidates, subset, trace)
        .expect("GPU scoring");
    assert_eq!(cpu.len(), gpu.len());
    let mut worst = 0.0f64;
    for (i, (c, g)) in cpu.iter().zip(&gpu).enumerate() {
        assert!(
            c.is_finite() && g.is_finite(),
            "candidate {i}: cpu {c}, gpu {g}"
        );
        let d = (c - g).abs();
        assert!(
            d <= tol,
            "candidate {i} ({trace:?}, {subset:?}): cpu {c}, gpu {g}, diff {d}"
        );
        worst = worst.max(d);
    }
    // The comparison means something only if the scores differ between candidates.
    let (lo, hi) = cpu
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    assert!(hi - lo > 1.0, "scores barely vary ({lo}..{hi})");
    worst
}

fn check_fixture<const D: usize, P: Pose<D>>(fx: &Fixture<D, P>, g: &GpuScorer<D>) {
    let nodes: std::collections::BTreeSet<_> = fx.candidates.iter().map(|c| c.node).collect();
    assert!(nodes.len() >= 2, "one map view only");
    assert!(
        fx.scan.beams.iter().any(|b| b.no_return),
        "no max-range beam"
    );
    for trace in [Trace::Full, Trace::Quick] {
        for subset in [
            BeamSubset::ALL,
            BeamSubset {
                first: 2,
                stride: 9,
            },
        ] {
            let d = compare(fx, g, subset, trace);
            eprintln!(
                "{D}-D {} {trace:?} {subset:?}: max |gpu - cpu| = {d:.2e}",
                g.precision()
            );
        }
    }
}

#[test]
fn gpu_matches_cpu_in_2d() {
    let mut fx = fixture2d(&FixtureSpec {
        particles: 6,
        steps: 4,
        candidates: 70,
        beams: 181,
        seed: 11,
    });
    let Some(g) = gpu::<2>(GpuPrecision::F64) else {
        return;
    };
    check_fixture(&fx, &g);
    if let Some(g32) = gpu::<2>(GpuPrecision::F32) {
        check_fixture(&fx, &g32);
    }
    // One map upload serves every later call on the same map version.
    let ctx = fx.context();
    g.try_score(&ctx, &fx.candidates, BeamSubset::ALL, Trace::Full)
        .unwrap();
    assert!(!g.last_call().map_uploaded);
    // A filter step changes the map and the numbering: the next call must see both.
    let delta = Pose2::new(nalgebra::Vector2::new(0.25, 0.02), 0.0);
    let scan = fx.scan.clone();
    fx.filter.step(&StepInput::motion(delta, &scan, 99));
    let particles = fx.filter.particles().to_vec();
    for (i, c) in fx.candidates.iter_mut().enumerate() {
        c.node = particles[i % particles.len()].node;
    }
    compare(&fx, &g, BeamSubset::ALL, Trace::Full);
    let s = g.last_call();
    // Only the changed bricks, in place.
    assert!(s.map_uploaded && !s.map_rebuilt, "{s:?}");
    assert!(s.map_bytes < s.map_packed_bytes, "{s:?}");
}

/// Scores `fx` with the map's bindings capped at each of `limits` (bytes,
/// descending) until the map no longer fits; every split must score as the
/// CPU does. Returns the most entry and header chunks seen.
fn split_sweep<const D: usize, P: Pose<D>>(
    fx: &Fixture<D, P>,
    precision: GpuPrecision,
    limits: impl Iterator<Item = u64>,
) -> (u32, u32) {
    let (mut entries, mut headers) = (0, 0);
    for limit in limits {
        let Some(g) = gpu_with::<D>(GpuOptions {
            precision,
            max_binding: Some(limit),
        }) else {
            return (0, 0);
        };
        let ctx = fx.context();
        let subset = BeamSubset {
            first: 1,
            stride: 3,
        };
        if let Err(e) = g.try_score(&ctx, &fx.candidates, subset, Trace::Full) {
            // Beyond what all chunks hold: a clear refusal, naming sizes.
            let msg = e.to_string();
            assert!(
                matches!(e, dpslam::Error::Gpu(_))
                    && msg.contains("iB (")
                    && msg.contains("bindings")
                    && msg.contains("--backend cpu"),
                "{msg}"
            );
            eprintln!("{D}-D {precision} limit {limit} B: {msg}");
            assert!(entries > 1, "refused before the map was split");
            return (entries, headers);
        }
        let s = g.last_call();
        let d = compare(fx, &g, subset, Trace::Full);
        eprintln!(
            "{D}-D {precision} limit {limit} B: {} entry and {} header chunks, map {} B, \
             max |gpu - cpu| = {d:.2e}",
            s.entry_chunks, s.header_chunks, s.map_packed_bytes
        );
        assert!(
            s.entry_chunks as usize <= ENTRY_CHUNKS && s.header_chunks as usize <= HEADER_CHUNKS
        );
        entries = entries.max(s.entry_chunks);
        headers = headers.max(s.header_chunks);
    }
    panic!("the smallest limit still held the map");
}

#[test]
fn maps_split_over_several_bindings_score_as_on_the_cpu() {
    let fx2 = fixture2d(&FixtureSpec {
        particles: 4,
        steps: 3,
        candidates: 21,
        beams: 120,
        seed: 4,
    });
    let fx3 = fixture3d(&FixtureSpec {
        particles: 3,
        steps: 2,
        candidates: 14,
        beams: 300,
        seed: 6,
    });
    // Chunks hold a power of two of elements, so halving the limit from
    // one chunk on passes through 2 and 3 or 4 chunks before the map no
    // longer fits.
    let halving = || (8..24).rev().map(|b| 1u64 << b);
    for p in [GpuPrecision::F64, GpuPrecision::F32] {
        let (e2, h2) = split_sweep(&fx2, p, halving());
        let (e3, h3) = split_sweep(&fx3, p, halving());
        // The 2-D map is mostly entries; the 3-D one has 513 header words
        // per brick and fills both header bindings first.
        assert!(e2 >= 3 && e3 >= 2, "{p}: at most {e2}, {e3} entry chunks");
        assert_eq!(
            h3 as usize, HEADER_CHUNKS,
            "{p}: at most {h2}, {h3} header chunks"
        );
    }
}

/// Filter steps on `fx` (the map changes: births, merges, removals,
/// free-space edits) scored with `options`; after each, the GPU must score
/// the new map as the CPU does, having uploaded only part of it, and at
/// most one step may rebuild the map instead.
fn incremental_steps<const D: usize, P: FixturePose<D>>(
    fx: &mut Fixture<D, P>,
    options: GpuOptions,
    stride: [f64; D],
    steps: u32,
) {
    let Some(g) = gpu_with::<D>(options) else {
        return;
    };
    compare(fx, &g, BeamSubset::ALL, Trace::Full);
    assert!(g.last_call().map_rebuilt);
    let (mut rebuilt, mut sent, mut whole, mut chunks) = (0, 0, 0, 0);
    for i in 0..steps {
        let scan = fx.scan.clone();
        fx.filter.step(&StepInput::motion(
            P::identity().moved(stride),
            &scan,
            100 + i,
        ));
        let particles = fx.filter.particles().to_vec();
        for (j, c) in fx.candidates.iter_mut().enumerate() {
            c.node = particles[j % particles.len()].node;
        }
        let d = compare(fx, &g, BeamSubset::ALL, Trace::Full);
        let s = g.last_call();
        eprintln!(
            "{D}-D step {i}: map {} of {} B, rebuilt {}, {} entry chunks, max |gpu - cpu| = {d:.2e}",
            s.map_bytes, s.map_packed_bytes, s.map_rebuilt, s.entry_chunks
        );
        assert!(s.map_uploaded, "step {i}: the changed map was not uploaded");
        chunks = chunks.max(s.entry_chunks);
        rebuilt += s.map_rebuilt as u64;
        if !s.map_rebuilt {
            sent += s.map_bytes;
            whole += s.map_packed_bytes;
        }
        // The next pass of the same step uploads nothing of the map.
        g.try_score(&fx.context(), &fx.candidates, BeamSubset::ALL, Trace::Quick)
            .unwrap();
        assert_eq!(g.last_call().map_bytes, 0);
    }
    assert!(chunks >= 2, "the entries never spanned two chunks");
    assert!(rebuilt <= 1, "{rebuilt} of {steps} steps rebuilt the map");
    assert!(sent < whole, "in-place syncs sent {sent} B of {whole} B");
    let t = g.totals();
    assert_eq!(t.map_syncs, steps as u64 + 1);
    assert_eq!(t.map_rebuilds, rebuilt + 1);
}

#[test]
fn incremental_map_syncs_after_filter_steps_score_as_on_the_cpu() {
    let spec = |particles, steps, candidates, beams, seed| FixtureSpec {
        particles,
        steps,
        candidates,
        beams,
        seed,
    };
    // Bindings of 1 MiB (2-D, f32) and 512 KiB (3-D, f64): the entries
    // span several chunks, so in-place writes land in several of them
    // (the 2-D fixture's packed map is about 2 MB).
    let options = |precision, max_binding| GpuOptions {
        precision,
        max_binding: Some(max_binding),
    };
    incremental_steps(
        &mut fixture2d(&spec(4, 3, 21, 120, 8)),
        options(GpuPrecision::F32, 1 << 20),
        [0.25, 0.02],
        6,
    );
    incremental_steps(
        &mut fixture3d(&spec(3, 2, 14, 300, 6)),
        options(GpuPrecision::F64, 512 << 10),
        [0.3, 0.02, 0.0],
        3,
    );
}

#[test]
fn a_map_binding_limit_below_the_minimum_is_a_clear_error() {
    let e = GpuScorer::<2>::with_options(GpuOptions {
        precision: GpuPrecision::Auto,
        max_binding: Some(100),
    });
    match e {
        Err(e) => assert!(e.to_string().contains("100 B"), "{e}"),
        Ok(_) => panic!("a 100 B binding limit was accepted"),
    }
}

#[test]
fn gpu_matches_cpu_in_3d() {
    let fx = fixture3d(&FixtureSpec {
        particles: 4,
        steps: 3,
        candidates: 30,
        beams: 400,
        seed: 5,
    });
    for p in [GpuPrecision::F64, GpuPrecision::F32] {
        if let Some(g) = gpu::<3>(p) {
            check_fixture(&fx, &g);
        }
    }
}

#[test]
fn auto_precision_picks_one_and_a_bad_setting_is_a_clear_error() {
    let Some(g) = gpu::<2>(GpuPrecision::Auto) else {
        return;
    };
    assert_ne!(g.precision(), GpuPrecision::Auto);
    // The environment setting is parsed strictly (tested through the binary:
    // setting a variable in-process would race the other tests).
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .args(["map2d", "--backend", "gpu", "--out"])
        .arg(dir.path().join("run"))
        .env("DPSLAM_GPU_PRECISION", "f16")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("DPSLAM_GPU_PRECISION") && err.contains("f64"),
        "{err}"
    );
    assert!(
        !dir.path().join("run").exists(),
        "a failed run wrote output"
    );
}

#[test]
fn trait_path_equals_try_score_and_candidates_far_outside_score_finitely() {
    let fx = fixture2d(&FixtureSpec {
        particles: 3,
        steps: 2,
        candidates: 14,
        beams: 90,
        seed: 2,
    });
    let Some(g) = gpu::<2>(GpuPrecision::Auto) else {
        return;
    };
    let ctx = fx.context();
    let a = Scorer::<2, Pose2>::score(&g, &ctx, &fx.candidates, BeamSubset::ALL, Trace::Full);
    let b = g
        .try_score(&ctx, &fx.candidates, BeamSubset::ALL, Trace::Full)
        .unwrap();
    assert_eq!(a, b);
    // Candidates 6 and 13 were moved 6 m ahead: beams cross unmapped cells.
    // Everything beyond the map is unknown: still finite, and worse than in the map.
    assert!(a[6].is_finite() && a[6] < a[5]);
    // An empty call is a no-op.
    assert!(
        g.try_score(&ctx, &[], BeamSubset::ALL, Trace::Full)
            .unwrap()
            .is_empty()
    );
}

#[test]
fn make_scorer_gpu_opens_a_device_and_auto_prefers_it() {
    let (s, used) =
        make_scorer::<3, Pose3>(Backend::Gpu, &Default::default()).expect("lavapipe present");
    assert_eq!(s.name(), "gpu");
    // "gpu f64 on llvmpipe (…)": what run.json records.
    assert!(used.starts_with("gpu f") && used.contains(" on "), "{used}");
    let (_, used) = make_scorer::<2, Pose2>(Backend::Auto, &Default::default()).unwrap();
    assert!(used.starts_with("gpu"), "{used}");
}

#[test]
fn no_adapter_is_a_clear_error() {
    // This build compiles in Vulkan only, so GL finds no adapter, as a
    // machine without a Vulkan driver would.
    let e = GpuScorer::<2>::with_backends(wgpu::Backends::GL)
        .err()
        .expect("no GL adapter in a Vulkan-only build");
    assert!(matches!(e, dpslam::Error::Gpu(_)));
    let msg = e.to_string();
    assert!(
        msg.contains("no Vulkan adapter") && msg.contains("--backend cpu"),
        "{msg}"
    );
}

#[test]
fn map2d_with_backend_gpu_and_no_adapter_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .args(["map2d", "--backend", "gpu", "--out"])
        .arg(dir.path().join("run"))
        .env("WGPU_BACKEND", "gl")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no Vulkan adapter") && err.contains("--backend cpu"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(
        !dir.path().join("run").exists(),
        "a failed run wrote output"
    );
}

#[test]
fn map2d_with_backend_auto_and_no_adapter_falls_back_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    // The first 15 scans of the simulated loop: enough for a run.
    let src = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/sim2d/sim2d.clf"),
    )
    .unwrap();
    let mut scans = 0;
    let short: String = src
        .lines()
        .take_while(|l| {
            scans += usize::from(l.starts_with("FLASER"));
            scans <= 15
        })
        .map(|l| format!("{l}\n"))
        .collect();
    let log = dir.path().join("short.clf");
    std::fs::write(&log, short).unwrap();
    let run = dir.path().join("run");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpslam"))
        .args(["map2d", "--backend", "auto", "--particles", "5", "--out"])
        .arg(&run)
        .arg(&log)
        .env("WGPU_BACKEND", "gl")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("no Vulkan adapter") && err.contains("using the CPU backend"),
        "{err}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    let used = summary["backend"].as_str().unwrap();
    assert!(
        used.starts_with("cpu (auto: ") && used.contains("no Vulkan adapter"),
        "{used}"
    );
}

/// Positions `x y z` (m) of a TUM trajectory, in file order.
fn trajectory(path: &std::path::Path) -> Vec<[f64; 3]> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            [v[1], v[2], v[3]]
        })
        .collect()
}

/// Asserts that the two trajectories have the same length and positions
/// within 0.01 m of each other (3-D distance; z is 0 in 2-D).
fn assert_same_trajectory(cpu: &[[f64; 3]], gpu: &[[f64; 3]]) {
    assert_eq!(cpu.len(), gpu.len());
    let worst = cpu
        .iter()
        .zip(gpu)
        .map(|(a, b)| (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    eprintln!("max position difference gpu vs cpu: {worst:.4} m");
    assert!(worst <= 0.01, "max position difference {worst} m");
}

/// About 5 minutes on 2 cores with lavapipe: run with `--ignored`.
#[test]
#[ignore]
fn map2d_gpu_and_cpu_trajectories_agree_on_mit_csail_prefix() {
    let src = std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/datasets/carmen/mit-csail/mit-csail.clf"
    ));
    let Ok(text) = std::fs::read_to_string(src) else {
        eprintln!("skipped: {} not found", src.display());
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("prefix.clf");
    let mut kept = String::new();
    let mut scans = 0;
    for line in text.lines() {
        let is_scan = line.starts_with("FLASER") || line.starts_with("ROBOTLASER1");
        if is_scan {
            if scans == 300 {
                break;
            }
            scans += 1;
        }
        kept.push_str(line);
        kept.push('\n');
    }
    std::fs::write(&log, kept).unwrap();
    // In-process, not through the binary: a shared target folder may hold a
    // `dpslam` built without the feature.
    let cfg = dpslam::config::Config {
        seed: 7,
        ..Default::default()
    };
    let run = |backend: Backend| {
        let out = dir.path().join(backend.to_string());
        let t = std::time::Instant::now();
        dpslam::pipeline::map2d::run_map2d_with(&log, &out, &cfg, backend).unwrap();
        eprintln!("{backend}: {:.1} s", t.elapsed().as_secs_f64());
        trajectory(&out.join("trajectory.tum"))
    };
    let cpu = run(Backend::Cpu);
    let gpu = run(Backend::Gpu);
    assert_eq!(cpu.len(), 300);
    assert_same_trajectory(&cpu, &gpu);
}

/// The 3-D embedded default (`data/sim3d`) mapped on both backends, same
/// seed: the trajectories must agree within 0.01 m. A few minutes on
/// lavapipe: run with `--ignored` (`.ci/run` does).
///
/// This needs f64 scores: in f32 mode (spread ~1.4e-4 nats from the CPU's)
/// one multinomial resampling draw at sweep 19 lands on the other side of a
/// cumulative-weight boundary and the runs part by 0.22 m; see docs/GPU.md.
#[test]
#[ignore]
fn map3d_gpu_and_cpu_trajectories_agree_on_the_simulator() {
    let data = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/data/sim3d"));
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = dpslam::config::Config::default();
    cfg.filter.particles = dpslam::pipeline::map3d::DEFAULT_PARTICLES_3D;
    let run = |backend: Backend| {
        let out = dir.path().join(backend.to_string());
        let t = std::time::Instant::now();
        let opts = dpslam::pipeline::map3d::Map3dOptions {
            points: false,
            backend,
        };
        dpslam::pipeline::map3d::run_map3d_with(
            &data.join("sweeps"),
            &out,
            &cfg,
            Some(&data.join("odometry.tum")),
            &opts,
        )
        .unwrap();
        eprintln!("{backend}: {:.1} s", t.elapsed().as_secs_f64());
        trajectory(&out.join("trajectory.tum"))
    };
    let cpu = run(Backend::Cpu);
    let gpu = run(Backend::Gpu);
    assert_same_trajectory(&cpu, &gpu);
}
