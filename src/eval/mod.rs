//! Accuracy metrics: Kümmerle et al. 2009 relations and absolute trajectory error.

pub mod ate;
pub mod relations;
