//! Choosing the scan-likelihood backend: the CPU reference or the optional
//! wgpu compute path (crate feature `gpu`).
//!
//! [`make_scorer`] is what the 2-D and 3-D pipelines call with the user's
//! `--backend`. `gpu` is strict (an error when it cannot run: no `gpu`
//! feature, no Vulkan adapter); `auto` tries the GPU and falls back to the
//! CPU, saying so on stderr. Scores agree between backends to f32 precision
//! (see `tests/gpu.rs`), so the choice changes speed, not results beyond
//! rounding.

pub mod bench;

use crate::Result;
use crate::geometry::Pose;
use crate::scorer::{CpuScorer, Scorer};

/// Where scan likelihoods are computed.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// Rayon over the CPU cores (the reference).
    #[default]
    Cpu,
    /// wgpu compute on a Vulkan adapter; an error if there is none.
    Gpu,
    /// The GPU if one is usable, else the CPU (with a note on stderr).
    Auto,
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Backend::Cpu => "cpu",
            Backend::Gpu => "gpu",
            Backend::Auto => "auto",
        })
    }
}

/// Whether this build has the GPU path (crate feature `gpu`).
pub const GPU_COMPILED: bool = cfg!(feature = "gpu");

/// A scorer for `backend` and the name of the backend actually used
/// (`"cpu"` or `"gpu"`).
///
/// Errors ([`crate::Error::Gpu`]) only for [`Backend::Gpu`] when this build lacks
/// the `gpu` feature or no Vulkan adapter can be opened (with
/// `WGPU_BACKEND=gl` none ever can: this build compiles in Vulkan only).
pub fn make_scorer<const D: usize, P: Pose<D>>(
    backend: Backend,
) -> Result<(Box<dyn Scorer<D, P>>, &'static str)> {
    match backend {
        Backend::Cpu => Ok((Box::new(CpuScorer::<D>::new()), "cpu")),
        Backend::Gpu => gpu_scorer::<D, P>(),
        Backend::Auto => match gpu_scorer::<D, P>() {
            Ok(s) => Ok(s),
            Err(e) => {
                eprintln!("dpslam: {e}; using the CPU backend");
                Ok((Box::new(CpuScorer::<D>::new()), "cpu"))
            }
        },
    }
}

#[cfg(feature = "gpu")]
fn gpu_scorer<const D: usize, P: Pose<D>>() -> Result<(Box<dyn Scorer<D, P>>, &'static str)> {
    let s = crate::gpu::GpuScorer::<D>::new()?;
    Ok((Box::new(s), "gpu"))
}

#[cfg(not(feature = "gpu"))]
fn gpu_scorer<const D: usize, P: Pose<D>>() -> Result<(Box<dyn Scorer<D, P>>, &'static str)> {
    Err(crate::Error::Gpu(
        "this dpslam was built without the GPU path: rebuild with `--features gpu` or run with --backend cpu".into(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Pose2;

    #[test]
    fn cpu_is_always_available_and_auto_never_fails() {
        let (s, used) = make_scorer::<2, Pose2>(Backend::Cpu).unwrap();
        assert_eq!((s.name(), used), ("cpu", "cpu"));
        let (s, used) = make_scorer::<2, Pose2>(Backend::Auto).unwrap();
        assert_eq!(s.name(), used);
    }

    #[cfg(not(feature = "gpu"))]
    #[test]
    fn gpu_without_the_feature_is_a_clear_error() {
        let e = make_scorer::<2, Pose2>(Backend::Gpu)
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("--features gpu") && e.contains("--backend cpu"),
            "{e}"
        );
    }

    #[test]
    fn backend_names_round_trip() {
        use clap::ValueEnum;
        for b in Backend::value_variants() {
            assert_eq!(Backend::from_str(&b.to_string(), false).unwrap(), *b);
            let j = serde_json::to_string(b).unwrap();
            assert_eq!(j, format!("\"{b}\""));
        }
    }
}
