//! Checks made before a run starts, so that a run that cannot finish fails
//! in a second instead of after the whole log: the output folder must be
//! writable, and the particles must fit in memory.

use crate::config::Config;
use crate::{Error, Result};
use std::path::Path;

/// Fails unless `out` can become the run folder: it is a folder, or can be
/// created (its nearest existing ancestor is a writable folder). Writes and
/// removes a hidden probe file; creates nothing else.
pub fn check_out_dir(out: &Path) -> Result<()> {
    let mut probe_in = out;
    loop {
        match std::fs::metadata(probe_in) {
            Ok(m) if m.is_dir() => break,
            Ok(_) => {
                let what = if probe_in == out {
                    "exists and is not a folder: choose another --out".to_string()
                } else {
                    format!(
                        "cannot create the output folder {}: {} is a file, not a folder",
                        out.display(),
                        probe_in.display()
                    )
                };
                return Err(Error::in_file(probe_in, what));
            }
            Err(_) => match probe_in.parent() {
                Some(p) if !p.as_os_str().is_empty() => probe_in = p,
                _ => {
                    probe_in = Path::new(".");
                    break;
                }
            },
        }
    }
    let probe = probe_in.join(format!(".dpslam-write-test-{}", std::process::id()));
    match std::fs::File::create(&probe) {
        Ok(_) => {
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) => Err(Error::Invalid(format!(
            "cannot write the output folder {}: {}: {e}",
            out.display(),
            probe_in.display()
        ))),
    }
}

/// Bytes per particle a 2-D run reaches within its first scans: the
/// particle, its ancestry node and the map entries only it holds. Measured:
/// 100 000 particles on the first 12 scans of the simulated loop passed
/// 23 GiB (≈ 240 KB each) before the kernel stopped them; the default 50
/// particles need a few MB of it. A lower bound, so that no run that could
/// fit is refused; the map comes on top.
pub const BYTES_PER_PARTICLE: u64 = 128 * 1024;
/// Bytes per sample drawn at each step (pose, score, indices).
pub const BYTES_PER_SAMPLE: u64 = 48;

/// The memory a run's particles need before any map, bytes.
pub fn particle_memory(cfg: &Config) -> u64 {
    let p = cfg.filter.particles as u64;
    let s = cfg.filter.samples_per_particle.max(1) as u64;
    p.saturating_mul(BYTES_PER_PARTICLE)
        .saturating_add(p.saturating_mul(s).saturating_mul(BYTES_PER_SAMPLE))
}

/// Memory this machine can give (Linux `MemAvailable`, bytes; `None` where
/// unknown).
pub fn available_memory() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Refuses a configuration whose particles alone cannot fit in `available`
/// bytes (the map comes on top), saying why.
pub fn check_memory(cfg: &Config, available: Option<u64>) -> Result<()> {
    let need = particle_memory(cfg);
    let Some(avail) = available else {
        return Ok(());
    };
    if need > avail {
        let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
        return Err(Error::Config(format!(
            "{} particles × {} samples need about {:.1} GiB before any map \
             ({} KiB per particle + {BYTES_PER_SAMPLE} B per sample), \
             and this machine has {:.1} GiB available: use fewer particles (--particles) \
             or samples (filter.samples_per_particle)",
            cfg.filter.particles,
            cfg.filter.samples_per_particle,
            gib(need),
            BYTES_PER_PARTICLE / 1024,
            gib(avail)
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_in_the_way_of_the_output_folder_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("f");
        std::fs::write(&f, "x").unwrap();
        let e = check_out_dir(&f).unwrap_err().to_string();
        assert!(e.contains("is not a folder"), "{e}");
        let e = check_out_dir(&f.join("sub/run")).unwrap_err().to_string();
        assert!(e.contains("is a file, not a folder"), "{e}");
        let ok = dir.path().join("new/run");
        check_out_dir(&ok).unwrap();
        assert!(
            !dir.path().join("new").exists(),
            "the check creates nothing"
        );
        check_out_dir(dir.path()).unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn particles_that_cannot_fit_are_refused_saying_why() {
        let mut cfg = Config::default();
        check_memory(&cfg, Some(1 << 30)).unwrap();
        cfg.filter.particles = 100_000_000;
        let e = check_memory(&cfg, Some(8 << 30)).unwrap_err().to_string();
        assert!(
            e.contains("100000000 particles") && e.contains("GiB available"),
            "{e}"
        );
        check_memory(&cfg, None).unwrap();
        // 50 particles × 10 samples: under 10 MB.
        assert!(particle_memory(&Config::default()) < 10 << 20);
        // 100 000 particles do not fit in 8 GiB (they passed 23 GiB).
        cfg.filter.particles = 100_000;
        assert!(check_memory(&cfg, Some(8 << 30)).is_err());
    }
}
