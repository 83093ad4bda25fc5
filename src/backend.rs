//! Choosing the scan-likelihood backend: the CPU reference or the optional
//! wgpu compute path (crate feature `gpu`).
//!
//! [`make_scorer`] is what the 2-D and 3-D pipelines call with the user's
//! `--backend`. `gpu` is strict (an error when it cannot run: no `gpu`
//! feature, no Vulkan adapter); `auto` tries the GPU and falls back to the
//! CPU, saying so on stderr. In the GPU's default f64 mode scores agree
//! with the CPU's to ~1e-12 and runs give the same trajectory; in f32 mode
//! (adapters without f64, or [`GpuPrecision::F32`]) they agree to ~2e-4
//! nats (see `tests/gpu.rs`, docs/GPU.md).

use crate::Result;
use crate::config::GpuConfig;
use crate::geometry::Pose;
use crate::scorer::{CpuScorer, Scorer};

/// Where scan likelihoods are computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// Rayon over the CPU cores (the reference).
    #[default]
    Cpu,
    /// wgpu compute on a Vulkan adapter; an error if there is none.
    Gpu,
    /// The GPU if one is usable, else the CPU (the run's backend string
    /// says why).
    Auto,
}

/// The command-line spelling (`cpu`, `gpu`, `auto`), as serde writes it.
impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Backend::Cpu => "cpu",
            Backend::Gpu => "gpu",
            Backend::Auto => "auto",
        })
    }
}

pub use crate::config::GpuPrecision;

/// Whether this build has the GPU path (crate feature `gpu`).
pub const GPU_COMPILED: bool = cfg!(feature = "gpu");

/// A scorer for `backend` (the GPU opened with `gpu`) and a description of the backend actually used:
/// `"cpu"`, or `"gpu"` followed by the precision and the adapter (e.g.
/// `"gpu f64 on llvmpipe (…)"`), or `"cpu (auto: REASON)"` when `auto`
/// found no usable GPU.
///
/// Errors ([`crate::Error::Gpu`]) only for [`Backend::Gpu`] when this build lacks
/// the `gpu` feature or no Vulkan adapter can be opened (with
/// `WGPU_BACKEND=gl` none ever can: this build compiles in Vulkan only).
pub fn make_scorer<const D: usize, P: Pose<D>>(
    backend: Backend,
    gpu: &GpuConfig,
) -> Result<(Box<dyn Scorer<D, P>>, String)> {
    match backend {
        Backend::Cpu => Ok((Box::new(CpuScorer::<D>::new()), "cpu".into())),
        Backend::Gpu => gpu_scorer::<D, P>(gpu),
        Backend::Auto => match gpu_scorer::<D, P>(gpu) {
            Ok(s) => Ok(s),
            Err(e) => {
                // run.json keeps why `auto` ended on the CPU.
                let used = format!("cpu (auto: {e})");
                Ok((Box::new(CpuScorer::<D>::new()), used))
            }
        },
    }
}

#[cfg(feature = "gpu")]
fn gpu_scorer<const D: usize, P: Pose<D>>(
    gpu: &GpuConfig,
) -> Result<(Box<dyn Scorer<D, P>>, String)> {
    let s = crate::gpu::GpuScorer::<D>::with_options(crate::gpu::GpuOptions::from_config(gpu))?;
    let name = format!("gpu {} on {}", s.precision(), s.adapter());
    Ok((Box::new(s), name))
}

#[cfg(not(feature = "gpu"))]
fn gpu_scorer<const D: usize, P: Pose<D>>(
    _gpu: &GpuConfig,
) -> Result<(Box<dyn Scorer<D, P>>, String)> {
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
        let (s, used) = make_scorer::<2, Pose2>(Backend::Cpu, &GpuConfig::default()).unwrap();
        assert_eq!((s.name(), used.as_str()), ("cpu", "cpu"));
        let (s, used) = make_scorer::<2, Pose2>(Backend::Auto, &GpuConfig::default()).unwrap();
        assert!(used.starts_with(s.name()), "{used}");
    }

    #[cfg(not(feature = "gpu"))]
    #[test]
    fn gpu_without_the_feature_is_a_clear_error() {
        let e = make_scorer::<2, Pose2>(Backend::Gpu, &GpuConfig::default())
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("--features gpu") && e.contains("--backend cpu"),
            "{e}"
        );
    }

    #[test]
    fn backend_and_precision_names_round_trip() {
        for b in [Backend::Cpu, Backend::Gpu, Backend::Auto] {
            let j = serde_json::to_string(&b).unwrap();
            assert_eq!(j, format!("\"{b}\""));
        }
        let names: Vec<String> = GpuPrecision::ALL
            .iter()
            .map(|p| {
                assert_eq!(p.to_string().parse::<GpuPrecision>().unwrap(), *p);
                assert_eq!(serde_json::to_string(p).unwrap(), format!("\"{p}\""));
                p.to_string()
            })
            .collect();
        assert_eq!(names, ["auto", "f32", "f64"]);
        assert!("f16".parse::<GpuPrecision>().is_err());
    }
}
