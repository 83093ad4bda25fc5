//! Where `map3d` gets its sweeps: a directory of sweep files, or the
//! `sensor_msgs/PointCloud2` messages of a bag.
//!
//! [`SweepSource`] is the one interface: a count, the sweep at an index (its
//! points in the sensor frame, and a prior pose when the input has one), and
//! the sweep's time stamp. For a bag, the prior is the odometry at the
//! cloud's header stamp (interpolated between the messages around it)
//! composed with the sensor mount from the static transforms, as in 2-D;
//! without odometry there is no prior (map3d then predicts with constant
//! velocity). x y z may be
//! float32 or float64 in either byte order; NaN points are dropped.

use super::messages::PointCloud2;
use super::scans2d::{Frames, TopicChoice};
use super::{Bag, RawMessage};
use crate::geometry::Pose3;
use crate::io::sweeps::{Sweep, list_sweeps, read_sweep};
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// The point-cloud message type.
pub const CLOUD_TYPE: &str = "sensor_msgs/PointCloud2";

/// The clouds of a bag.
pub struct BagSweeps {
    bag: Bag,
    topic: String,
    clouds: Vec<RawMessage>,
    stamps_ns: Vec<i64>,
    frames: Frames,
}

impl BagSweeps {
    /// Opens `path` and indexes its clouds (the topic chosen or guessed).
    pub fn open(path: &Path, choice: &TopicChoice) -> Result<Self> {
        let bag = Bag::open(path)?;
        let t = bag
            .choose_topic(
                "point cloud",
                "--scan-topic",
                choice.scan_topic.as_deref(),
                &[CLOUD_TYPE],
                true,
            )?
            .expect("required");
        let topic = bag.topics[t].name.clone();
        let clouds = bag.read(&[t])?;
        if clouds.is_empty() {
            return Err(Error::in_file(
                &bag.path,
                format!("topic {topic} has no messages: no point clouds"),
            ));
        }
        let mut stamps_ns = Vec::with_capacity(clouds.len());
        let mut frame = String::new();
        for m in &clouds {
            let c = bag.decode(m, PointCloud2::decode)?;
            if frame.is_empty() {
                frame = c.header.frame_id.clone();
            }
            stamps_ns.push(c.header.stamp_ns);
        }
        let frames = Frames::read(&bag, choice.odom_topic.as_deref(), &frame, false)?;
        Ok(BagSweeps {
            bag,
            topic,
            clouds,
            stamps_ns,
            frames,
        })
    }

    /// The topic read.
    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// Whether the bag has odometry for the clouds.
    pub fn has_odometry(&self) -> bool {
        self.frames.odometry.as_ref().is_some_and(|t| !t.is_empty())
    }

    fn read(&self, i: usize) -> Result<Sweep> {
        let m = &self.clouds[i];
        let c = self.bag.decode(m, PointCloud2::decode)?;
        let points = self.bag.decode(m, |_, _| c.xyz())?;
        if points.is_empty() {
            return Err(super::message_error(
                self.bag.file_for_messages(),
                &self.topic,
                m.index,
                "the cloud has no finite points",
            ));
        }
        let prior = self
            .frames
            .odometry
            .as_ref()
            .and_then(|t| t.at(c.header.stamp_ns))
            .map(|o| o * self.frames.mount.unwrap_or_else(Pose3::identity));
        Ok(Sweep {
            points,
            source: self.bag.path.clone(),
            prior,
        })
    }
}

/// The sweeps of a `map3d` run.
pub enum SweepSource {
    /// Sweep files, in order.
    Files(Vec<PathBuf>),
    /// A bag's point clouds.
    Bag(Box<BagSweeps>),
}

impl SweepSource {
    /// A bag (see [`super::is_bag`]) or a directory of sweep files.
    pub fn open(input: &Path, choice: &TopicChoice) -> Result<Self> {
        if super::is_bag(input) {
            Ok(SweepSource::Bag(Box::new(BagSweeps::open(input, choice)?)))
        } else {
            Ok(SweepSource::Files(list_sweeps(input)?))
        }
    }

    /// Number of sweeps.
    pub fn len(&self) -> usize {
        match self {
            SweepSource::Files(p) => p.len(),
            SweepSource::Bag(b) => b.clouds.len(),
        }
    }

    /// Whether there are no sweeps.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sweep `i`.
    pub fn read(&self, i: usize) -> Result<Sweep> {
        match self {
            SweepSource::Files(p) => read_sweep(&p[i]),
            SweepSource::Bag(b) => b.read(i),
        }
    }

    /// The time stamp of sweep `i` (s), when the input has one.
    pub fn stamp(&self, i: usize) -> Option<f64> {
        match self {
            SweepSource::Files(_) => None,
            SweepSource::Bag(b) => Some(super::messages::stamp_seconds(b.stamps_ns[i])),
        }
    }

    /// An error about sweep `i`: naming its file, or its bag, topic and
    /// message index.
    pub fn error_at(&self, i: usize, reason: String) -> Error {
        match self {
            SweepSource::Files(p) => Error::in_file(&p[i], reason),
            SweepSource::Bag(b) => super::message_error(
                b.bag.file_for_messages(),
                &b.topic,
                b.clouds[i].index,
                reason,
            ),
        }
    }

    /// What sweep `i` is, for messages: its file, or bag, topic and index.
    pub fn describe(&self, i: usize) -> String {
        match self {
            SweepSource::Files(p) => p[i].display().to_string(),
            SweepSource::Bag(b) => {
                format!("{} topic {} message {i}", b.bag.path.display(), b.topic)
            }
        }
    }
}
