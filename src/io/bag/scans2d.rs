//! A bag as a 2-D laser log: `sensor_msgs/LaserScan` messages become
//! [`LaserScan2d`]s with the robot's odometry at each scan's header stamp.
//!
//! - **Scans**: the topic given (`--scan-topic`), else the bag's only
//!   LaserScan topic. Beam `i` is at `angle_min + i·angle_increment`;
//!   NaN, ±inf and readings outside `[range_min, range_max]` are "no return".
//!   Readings are f32 in the bag and are taken at their shortest decimal
//!   form (`46.56`, not `46.560001373…`), which is what the sensor meant
//!   and what a CARMEN log of the same data holds.
//! - **Odometry**: the topic given (`--odom-topic`: `nav_msgs/Odometry` or
//!   a tf topic), else the only `nav_msgs/Odometry` topic, else `/tf`'s
//!   transform from the odometry frame to the robot's base frame. The pose
//!   paired with a scan is the odometry interpolated at its stamp between
//!   the two messages around it ([`Track::at`]), the first or last one for
//!   scans outside the odometry's span.
//! - **Laser mount**: the static transforms (`/tf_static`, or `/tf` ones
//!   that never change) from the base frame to the scan's `frame_id`,
//!   projected on the plane. [`BagScans2d::sensor_offset`] gives it;
//!   `motion2d.sensor_offset` in the configuration overrides it.
//!
//! The messages of the chosen topics are read up front (the raw bytes: about
//! the size of those topics in the bag); scans are decoded one at a time.

use super::messages::{LaserScan, Odometry, TransformStamped, decode_tf};
use super::{Bag, RawMessage, message_error};
use crate::geometry::{Pose2, Pose3};
use crate::scan::LaserScan2d;
use crate::{Error, Result};
use std::collections::HashMap;
use std::path::Path;

/// Message types of tf topics (ROS 2, ROS 1 `tf2_msgs`, ROS 1 `tf`).
pub const TF_TYPES: &[&str] = &["tf2_msgs/TFMessage", "tf/tfMessage"];
/// The odometry message type.
pub const ODOM_TYPE: &str = "nav_msgs/Odometry";
/// The 2-D laser message type.
pub const SCAN_TYPE: &str = "sensor_msgs/LaserScan";

/// Which topics to read; `None` = guess (see the module docs). The `[bag]`
/// section of the configuration.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TopicChoice {
    /// The LaserScan (2-D) or PointCloud2 (3-D) topic.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_topic: Option<String>,
    /// The nav_msgs/Odometry or tf topic.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub odom_topic: Option<String>,
}

pub use crate::io::odometry::{Track, planar};

/// Transforms by (parent, child) frame names.
type Edges = HashMap<(String, String), Vec<(i64, Pose3)>>;

fn strip(f: &str) -> &str {
    f.trim_start_matches('/')
}

/// The bag's motion and mount information, shared by 2-D and 3-D.
#[derive(Debug, Clone)]
pub struct Frames {
    /// Odometry of the robot's base frame (`None`: the bag has none).
    pub odometry: Option<Track>,
    /// What the odometry came from, for messages.
    pub odometry_source: String,
    /// The sensor's pose in the base frame, when the transforms give it.
    pub mount: Option<Pose3>,
    /// The base frame's name.
    pub base_frame: Option<String>,
}

impl Frames {
    /// Reads odometry and the mount of `sensor_frame` from `bag`.
    /// `odom_required`: a bag without odometry is an error (2-D).
    pub fn read(
        bag: &Bag,
        odom_topic: Option<&str>,
        sensor_frame: &str,
        odom_required: bool,
    ) -> Result<Frames> {
        let mut odom_types: Vec<&str> = vec![ODOM_TYPE];
        odom_types.extend(TF_TYPES);
        // The odometry topic: given, else the only Odometry topic.
        let odom = match odom_topic {
            Some(_) => {
                bag.choose_topic("odometry", "--odom-topic", odom_topic, &odom_types, true)?
            }
            None => bag.choose_topic("odometry", "--odom-topic", None, &[ODOM_TYPE], false)?,
        };
        if let Some(o) = odom
            && bag.topics[o].count == 0
        {
            return Err(Error::in_file(
                &bag.path,
                format!(
                    "the odometry topic {} has no messages; the bag's topics:\n{}",
                    bag.topics[o].name,
                    bag.describe_topics()
                ),
            ));
        }
        let tf_topics: Vec<usize> = (0..bag.topics.len())
            .filter(|&i| TF_TYPES.contains(&bag.topics[i].msg_type.as_str()))
            .collect();
        let mut wanted: Vec<usize> = tf_topics.clone();
        if let Some(o) = odom
            && !wanted.contains(&o)
        {
            wanted.push(o);
        }
        let msgs = bag.read(&wanted)?;
        // Static edges (tf_static, or /tf edges whose value never changes)
        // and dynamic ones.
        let mut statics: Edges = HashMap::new();
        let mut dynamics: Edges = HashMap::new();
        let mut odom_track = Track::default();
        let mut odom_child: Option<String> = None;
        for m in &msgs {
            let info = &bag.topics[m.topic];
            if info.msg_type == ODOM_TYPE {
                let o: Odometry = bag.decode(m, Odometry::decode)?;
                match &odom_child {
                    None => odom_child = Some(strip(&o.child_frame_id).to_string()),
                    Some(c) if c != strip(&o.child_frame_id) => {
                        return Err(message_error(
                            bag.file_for_messages(),
                            &info.name,
                            m.index,
                            format!(
                                "child_frame_id {} after {c}: one odometry topic must \
                                 describe one frame",
                                o.child_frame_id
                            ),
                        ));
                    }
                    _ => {}
                }
                odom_track.push(o.header.stamp_ns, o.pose.to_pose3());
            } else {
                let tfs: Vec<TransformStamped> = bag.decode(m, decode_tf)?;
                let is_static = info.name.ends_with("tf_static");
                for t in tfs {
                    let key = (
                        strip(&t.header.frame_id).to_string(),
                        strip(&t.child_frame_id).to_string(),
                    );
                    let e = if is_static {
                        &mut statics
                    } else {
                        &mut dynamics
                    };
                    e.entry(key)
                        .or_default()
                        .push((t.header.stamp_ns, t.transform.to_pose3()));
                }
            }
        }
        // /tf edges that never change count as static.
        let constant: Vec<_> = dynamics
            .iter()
            .filter(|(k, v)| {
                !statics.contains_key(*k)
                    && v.iter().all(|(_, p)| {
                        let d = v[0].1.inverse() * p;
                        d.translation.vector.norm() < 1e-9 && d.rotation.angle() < 1e-9
                    })
                    && v.len() > 1
            })
            .map(|(k, _)| k.clone())
            .collect();
        for k in constant {
            let v = dynamics.remove(&k).expect("listed");
            statics.insert(k, v);
        }
        let static_parent = |child: &str| -> Option<(String, Pose3)> {
            statics
                .iter()
                .find(|((_, c), _)| c == child)
                .map(|((p, _), v)| (p.clone(), v[v.len() - 1].1))
        };
        // Climb the static tree from the sensor to `stop` (or its top).
        let climb = |stop: Option<&str>| -> (String, Pose3) {
            let mut frame = strip(sensor_frame).to_string();
            let mut pose = Pose3::identity();
            for _ in 0..32 {
                if Some(frame.as_str()) == stop {
                    break;
                }
                match static_parent(&frame) {
                    Some((p, t)) => {
                        pose = t * pose;
                        frame = p;
                    }
                    None => break,
                }
            }
            (frame, pose)
        };
        let odom_name = odom.map(|o| bag.topics[o].name.clone());
        let (odometry, source, base, mount) = if let Some(child) = odom_child {
            let (top, mount) = climb(Some(&child));
            let mount = (top == child).then_some(mount);
            odom_track.sort();
            (
                Some(odom_track),
                format!(
                    "{} (nav_msgs/Odometry of {child})",
                    odom_name.unwrap_or_default()
                ),
                Some(child),
                mount,
            )
        } else {
            // From tf: the sensor's static chain up to a frame that a
            // dynamic transform moves; that transform's parent is the
            // odometry frame.
            let (top, mount) = climb(None);
            let edge = dynamics.iter().find(|((_, c), _)| *c == top);
            match edge {
                Some(((parent, child), v)) => {
                    let mut tr = Track::default();
                    for (t, p) in v {
                        tr.push(*t, *p);
                    }
                    tr.sort();
                    (
                        Some(tr),
                        format!("tf {parent} -> {child}"),
                        Some(child.clone()),
                        Some(mount),
                    )
                }
                None => {
                    if odom_required {
                        return Err(Error::in_file(
                            &bag.path,
                            format!(
                                "no odometry for frame {sensor_frame}: no nav_msgs/Odometry \
                                 topic and no tf transform moving it or its static parents \
                                 (--odom-topic chooses one); the bag's topics:\n{}",
                                bag.describe_topics()
                            ),
                        ));
                    }
                    (
                        None,
                        String::new(),
                        None,
                        (top != strip(sensor_frame)).then_some(mount),
                    )
                }
            }
        };
        if odom_required && odometry.as_ref().is_some_and(Track::is_empty) {
            return Err(Error::in_file(
                &bag.path,
                format!("the odometry topic {source} has no messages"),
            ));
        }
        Ok(Frames {
            odometry,
            odometry_source: source,
            mount,
            base_frame: base,
        })
    }
}

/// Streaming iterator over the scans of a bag, as [`LaserScan2d`]s.
pub struct BagScans2d {
    bag: Bag,
    topic: String,
    scans: std::vec::IntoIter<RawMessage>,
    total: usize,
    delivered: usize,
    frames: Frames,
    done: bool,
}

/// `v` at its shortest decimal form, as f64.
pub fn f32_decimal(v: f32) -> f64 {
    if v.is_finite() {
        format!("{v}").parse().unwrap_or(v as f64)
    } else {
        v as f64
    }
}

impl BagScans2d {
    /// Opens `path` and prepares its scans, odometry and laser mount.
    pub fn open(path: &Path, choice: &TopicChoice) -> Result<Self> {
        let bag = Bag::open(path)?;
        let t = bag
            .choose_topic(
                "laser scan",
                "--scan-topic",
                choice.scan_topic.as_deref(),
                &[SCAN_TYPE],
                true,
            )?
            .expect("required");
        let topic = bag.topics[t].name.clone();
        let scans = bag.read(&[t])?;
        let Some(first) = scans.first() else {
            return Err(Error::in_file(
                &bag.path,
                format!("topic {topic} has no messages: no laser scans"),
            ));
        };
        let frame = bag.decode(first, LaserScan::decode)?.header.frame_id;
        let frames = Frames::read(&bag, choice.odom_topic.as_deref(), &frame, true)?;
        Ok(BagScans2d {
            total: scans.len(),
            scans: scans.into_iter(),
            bag,
            topic,
            delivered: 0,
            frames,
            done: false,
        })
    }

    /// The bag.
    pub fn bag(&self) -> &Bag {
        &self.bag
    }

    /// The scan topic read.
    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// Where odometry came from (topic or tf edge).
    pub fn odometry_source(&self) -> &str {
        &self.frames.odometry_source
    }

    /// Scans in the topic.
    pub fn total_scans(&self) -> usize {
        self.total
    }

    /// Scans delivered so far.
    pub fn scans_read(&self) -> usize {
        self.delivered
    }

    /// The laser's pose in the robot frame from the static transforms.
    pub fn sensor_offset(&self) -> Option<Pose2> {
        self.frames.mount.as_ref().map(planar)
    }

    fn convert(&self, m: &RawMessage) -> Result<LaserScan2d> {
        let s = self.bag.decode(m, LaserScan::decode)?;
        let odo = self
            .frames
            .odometry
            .as_ref()
            .and_then(|t| t.at(s.header.stamp_ns))
            .expect("2-D bags have odometry");
        let (lo, hi) = (s.range_min, s.range_max);
        let ranges = s
            .ranges
            .iter()
            .map(|&r| {
                if r.is_finite() && r >= lo && r <= hi {
                    f32_decimal(r)
                } else {
                    f64::INFINITY
                }
            })
            .collect();
        Ok(LaserScan2d {
            timestamp: Some(s.header.stamp_s()),
            odometry: planar(&odo),
            logged_pose: None,
            ranges,
            angle_min: s.angle_min as f64,
            angle_increment: s.angle_increment as f64,
            max_range: f32_decimal(s.range_max),
            line: m.index + 1,
        })
    }
}

impl Iterator for BagScans2d {
    type Item = Result<LaserScan2d>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let m = self.scans.next()?;
        let r = self.convert(&m);
        if r.is_err() {
            self.done = true;
        } else {
            self.delivered += 1;
        }
        Some(r)
    }
}

impl std::iter::FusedIterator for BagScans2d {}
