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

/// The command-line spelling (`cpu`, `gpu`, `auto`), as serde writes it.
impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        value_name(self, f)
    }
}

/// Writes a `ValueEnum`'s command-line name.
fn value_name(v: &impl clap::ValueEnum, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
    match v.to_possible_value() {
        Some(p) => f.write_str(p.get_name()),
        None => Err(std::fmt::Error),
    }
}

/// The arithmetic of the GPU likelihood shader (see `crate::gpu`).
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
pub enum GpuPrecision {
    /// f64 where the adapter supports it (`SHADER_F64`), else f32.
    #[default]
    Auto,
    /// f32: fastest on consumer GPUs (f64 there runs at 1/32–1/64 rate);
    /// scores within ~2e-4 nats of the CPU's.
    F32,
    /// f64: scores equal the CPU's to ~1e-12, so runs follow the CPU's
    /// trajectory; an error where the adapter lacks `SHADER_F64`.
    F64,
}

/// The command-line spelling (`auto`, `f32`, `f64`), as serde writes it.
impl std::fmt::Display for GpuPrecision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        value_name(self, f)
    }
}

impl GpuPrecision {
    /// The choice in `DPSLAM_GPU_PRECISION` (`auto`, `f32` or `f64`), else `Auto`.
    pub fn from_env() -> Result<Self> {
        use clap::ValueEnum;
        match std::env::var("DPSLAM_GPU_PRECISION") {
            Err(_) => Ok(Self::Auto),
            Ok(v) => Self::from_str(&v, true).map_err(|_| {
                crate::Error::Gpu(format!(
                    "DPSLAM_GPU_PRECISION is {v:?}: expected auto, f32 or f64"
                ))
            }),
        }
    }
}

/// Whether this build has the GPU path (crate feature `gpu`).
pub const GPU_COMPILED: bool = cfg!(feature = "gpu");

/// A scorer for `backend` and a description of the backend actually used:
/// `"cpu"`, or `"gpu"` followed by the precision and the adapter (e.g.
/// `"gpu f64 on llvmpipe (…)"`), or `"cpu (auto: REASON)"` when `auto`
/// found no usable GPU.
///
/// Errors ([`crate::Error::Gpu`]) only for [`Backend::Gpu`] when this build lacks
/// the `gpu` feature or no Vulkan adapter can be opened (with
/// `WGPU_BACKEND=gl` none ever can: this build compiles in Vulkan only).
pub fn make_scorer<const D: usize, P: Pose<D>>(
    backend: Backend,
) -> Result<(Box<dyn Scorer<D, P>>, String)> {
    match backend {
        Backend::Cpu => Ok((Box::new(CpuScorer::<D>::new()), "cpu".into())),
        Backend::Gpu => gpu_scorer::<D, P>(),
        Backend::Auto => match gpu_scorer::<D, P>() {
            Ok(s) => Ok(s),
            Err(e) => {
                eprintln!("dpslam: {e}; using the CPU backend");
                // run.json keeps why `auto` ended on the CPU, not only the console.
                let used = format!("cpu (auto: {e})");
                Ok((Box::new(CpuScorer::<D>::new()), used))
            }
        },
    }
}

#[cfg(feature = "gpu")]
fn gpu_scorer<const D: usize, P: Pose<D>>() -> Result<(Box<dyn Scorer<D, P>>, String)> {
    let s = crate::gpu::GpuScorer::<D>::new()?;
    let name = format!("gpu {} on {}", s.precision(), s.adapter());
    Ok((Box::new(s), name))
}

#[cfg(not(feature = "gpu"))]
fn gpu_scorer<const D: usize, P: Pose<D>>() -> Result<(Box<dyn Scorer<D, P>>, String)> {
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
        assert_eq!((s.name(), used.as_str()), ("cpu", "cpu"));
        let (s, used) = make_scorer::<2, Pose2>(Backend::Auto).unwrap();
        assert!(used.starts_with(s.name()), "{used}");
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
        let names: Vec<String> = GpuPrecision::value_variants()
            .iter()
            .map(|p| {
                assert_eq!(GpuPrecision::from_str(&p.to_string(), false).unwrap(), *p);
                assert_eq!(serde_json::to_string(p).unwrap(), format!("\"{p}\""));
                p.to_string()
            })
            .collect();
        assert_eq!(names, ["auto", "f32", "f64"]);
    }
}
