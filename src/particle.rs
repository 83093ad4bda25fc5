//! The particle, apart from the filter so that what the filter uses (scan
//! registration, [`crate::proposal`]) can see particles without importing
//! the filter back. Public as [`crate::filter::Particle`].

use crate::ancestry::NodeId;

/// A particle: the current robot pose and the ancestry node holding its map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Particle<P> {
    /// Robot pose in the map frame.
    pub pose: P,
    /// Most recent ancestry node of this particle.
    pub node: NodeId,
}
