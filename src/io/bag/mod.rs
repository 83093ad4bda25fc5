//! ROS bags in: ROS 1 `.bag`, MCAP `.mcap`, rosbag2 sqlite3 `.db3`, and ROS 2
//! bag directories (a folder with `metadata.yaml` and one of those files).
//!
//! A [`Bag`] lists its topics (name, message type, count, serialisation)
//! and reads the raw messages of chosen topics; [`messages`] decodes the few
//! types dpslam needs by hand ([`wire`] has the two wire formats). The
//! storages use the ecosystem's crates: `rosbag` (ROS 1, bz2 and lz4
//! chunks), `mcap` (zstd and lz4 chunks), `rusqlite` with its bundled SQLite.
//!
//! [`scans2d`] turns a bag into the 2-D laser scans of
//! [`crate::io::log2d`]; [`sweeps3d`] into the 3-D sweeps of `map3d`. The
//! filter never knows where data came from.
//!
//! Every problem is an error naming the file and, where it is about one
//! message, the topic and the message's index in it (0-based, in bag order):
//! `FILE:topic /scan, message 12: reason`.

pub mod mcap;
pub mod messages;
pub mod ros1;
pub mod scans2d;
pub mod sqlite;
pub mod sweeps3d;
pub mod wire;

use crate::error::Location;
use crate::{Error, Result};
use std::path::{Path, PathBuf};
pub use wire::Encoding;

/// Where a bag's messages are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Storage {
    /// ROS 1 bag v2.0.
    Ros1,
    /// MCAP.
    Mcap,
    /// rosbag2 sqlite3.
    Sqlite3,
}

impl Storage {
    /// A short name for messages and `run.json`.
    pub fn name(self) -> &'static str {
        match self {
            Storage::Ros1 => "ros1 bag",
            Storage::Mcap => "mcap",
            Storage::Sqlite3 => "rosbag2 sqlite3",
        }
    }
}

/// One topic of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct TopicInfo {
    /// Topic name (`/scan`).
    pub name: String,
    /// Message type in ROS 1 spelling (`sensor_msgs/LaserScan`; ROS 2's
    /// `sensor_msgs/msg/LaserScan` is shortened to it).
    pub msg_type: String,
    /// Messages on the topic.
    pub count: u64,
    /// Serialisation, `None` when the bag names one dpslam does not read.
    pub encoding: Option<Encoding>,
    /// The serialisation's name as the bag gives it.
    pub encoding_name: String,
}

/// One message as stored: topic (index into [`Bag::topics`]), its 0-based
/// index among that topic's messages, the recording time and the bytes.
#[derive(Debug, Clone)]
pub struct RawMessage {
    /// Index into [`Bag::topics`].
    pub topic: usize,
    /// 0-based index among the topic's messages.
    pub index: usize,
    /// Recording time, ns since the epoch.
    pub log_time_ns: u64,
    /// The serialised message (ROS 1 or CDR, per the storage).
    pub data: Vec<u8>,
}

/// An opened bag: its files and topics.
#[derive(Debug, Clone)]
pub struct Bag {
    /// What the user named (file or directory).
    pub path: PathBuf,
    /// The storage files, in order (one, except for split ROS 2 bags).
    pub files: Vec<PathBuf>,
    /// How the messages are stored.
    pub storage: Storage,
    /// The topics recorded, with their types and message counts.
    pub topics: Vec<TopicInfo>,
}

/// The shortened type name: `pkg/msg/Name` → `pkg/Name`.
pub fn normalise_type(t: &str) -> String {
    match t.split('/').collect::<Vec<_>>().as_slice() {
        [pkg, "msg", name] => format!("{pkg}/{name}"),
        _ => t.to_string(),
    }
}

/// The storage of `path` when it is a bag: a ROS 2 bag directory, or a file
/// whose first bytes are a ROS 1 bag's, an MCAP's or an SQLite database's
/// (whatever its name), or whose extension is `.bag`, `.mcap` or `.db3`.
pub fn bag_storage(path: &Path) -> Option<Storage> {
    if path.is_dir() {
        return ros2_dir_files(path).ok().map(|(s, _)| s);
    }
    let mut head = [0u8; 16];
    let n = std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read(&mut f, &mut head))
        .unwrap_or(0);
    let head = &head[..n];
    if head.starts_with(b"#ROSBAG") {
        return Some(Storage::Ros1);
    }
    if head.starts_with(b"\x89MCAP") {
        return Some(Storage::Mcap);
    }
    if head.starts_with(b"SQLite format 3\0") {
        return Some(Storage::Sqlite3);
    }
    match path.extension().and_then(|e| e.to_str()) {
        Some("bag") => Some(Storage::Ros1),
        Some("mcap") => Some(Storage::Mcap),
        Some("db3") => Some(Storage::Sqlite3),
        _ => None,
    }
}

/// Whether `path` is a bag (see [`bag_storage`]).
pub fn is_bag(path: &Path) -> bool {
    bag_storage(path).is_some()
}

/// The storage files of a ROS 2 bag directory: from `metadata.yaml`
/// (`storage_identifier`, `relative_file_paths`), else the directory's
/// `.mcap` or `.db3` files in name order.
fn ros2_dir_files(dir: &Path) -> Result<(Storage, Vec<PathBuf>)> {
    let meta = dir.join("metadata.yaml");
    let text = std::fs::read_to_string(&meta).map_err(|e| Error::io(&meta, e))?;
    let mut storage = None;
    let mut files = Vec::new();
    let mut in_paths = false;
    for line in text.lines() {
        let t = line.trim();
        if let Some(v) = t.strip_prefix("storage_identifier:") {
            storage = match v.trim().trim_matches(['\'', '"']) {
                "mcap" => Some(Storage::Mcap),
                "sqlite3" => Some(Storage::Sqlite3),
                other => {
                    return Err(Error::in_file(
                        &meta,
                        format!("storage_identifier '{other}': only mcap and sqlite3 are read"),
                    ));
                }
            };
        }
        if t.starts_with("relative_file_paths:") {
            in_paths = true;
            continue;
        }
        if in_paths {
            match t.strip_prefix("- ") {
                Some(f) => files.push(dir.join(f.trim().trim_matches(['\'', '"']))),
                None => in_paths = false,
            }
        }
    }
    if files.is_empty() {
        let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| matches!(p.extension().and_then(|e| e.to_str()), Some("mcap" | "db3")))
            .collect();
        found.sort();
        files = found;
    }
    let storage = storage
        .or_else(|| files.first().and_then(|f| bag_storage(f)))
        .ok_or_else(|| {
            Error::in_file(
                &meta,
                "no storage_identifier and no .mcap or .db3 file in the bag directory",
            )
        })?;
    if files.is_empty() {
        return Err(Error::in_file(
            &meta,
            "the bag directory holds no storage file",
        ));
    }
    for f in &files {
        if !f.is_file() {
            return Err(Error::in_file(
                &meta,
                format!("lists {}, which does not exist", f.display()),
            ));
        }
    }
    Ok((storage, files))
}

/// A problem with message `index` of `topic` in `path`.
pub fn message_error(path: &Path, topic: &str, index: usize, reason: impl Into<String>) -> Error {
    Error::Parse {
        path: path.to_path_buf(),
        location: Location::Message {
            topic: topic.to_string(),
            index,
        },
        reason: reason.into(),
    }
}

impl Bag {
    /// Opens the bag at `path` (file or ROS 2 bag directory) and lists its
    /// topics.
    pub fn open(path: &Path) -> Result<Bag> {
        if !path.exists() {
            return Err(Error::io(
                path,
                std::io::Error::new(std::io::ErrorKind::NotFound, "no such file or directory"),
            ));
        }
        let (storage, files) = if path.is_dir() {
            ros2_dir_files(path)?
        } else {
            let s = bag_storage(path).ok_or_else(|| {
                Error::in_file(path, "not a ROS bag (.bag, .mcap, .db3 or a bag directory)")
            })?;
            (s, vec![path.to_path_buf()])
        };
        let mut topics: Vec<TopicInfo> = Vec::new();
        for f in &files {
            let list = match storage {
                Storage::Ros1 => ros1::topics(f)?,
                Storage::Mcap => mcap::topics(f)?,
                Storage::Sqlite3 => sqlite::topics(f)?,
            };
            for t in list {
                match topics.iter_mut().find(|u| u.name == t.name) {
                    Some(u) if u.msg_type == t.msg_type => u.count += t.count,
                    Some(u) => {
                        return Err(Error::in_file(
                            f,
                            format!(
                                "topic {} has two types: {} and {}",
                                t.name, u.msg_type, t.msg_type
                            ),
                        ));
                    }
                    None => topics.push(t),
                }
            }
        }
        Ok(Bag {
            path: path.to_path_buf(),
            files,
            storage,
            topics,
        })
    }

    /// The topics, one per line: `  /scan  sensor_msgs/LaserScan  (7374 messages)`.
    pub fn describe_topics(&self) -> String {
        if self.topics.is_empty() {
            return "  (no topics)".into();
        }
        self.topics
            .iter()
            .map(|t| format!("  {}  {}  ({} messages)", t.name, t.msg_type, t.count))
            .collect::<Vec<_>>()
            .join("\n")
    }

    /// The index of the topic named `name`.
    pub fn topic_index(&self, name: &str) -> Option<usize> {
        self.topics.iter().position(|t| t.name == name)
    }

    /// The topic to read for `role` (e.g. "scan"): `wanted` when given (it
    /// must exist and have one of `types`), else the only topic of one of
    /// `types` (`None` when there is none and `required` is false). Errors
    /// list the bag's topics and types and name the flag that chooses.
    pub fn choose_topic(
        &self,
        role: &str,
        flag: &str,
        wanted: Option<&str>,
        types: &[&str],
        required: bool,
    ) -> Result<Option<usize>> {
        let types_text = types.join(" or ");
        if let Some(name) = wanted {
            let i = self.topic_index(name).ok_or_else(|| {
                Error::in_file(
                    &self.path,
                    format!(
                        "no topic {name} ({flag}); the bag's topics:\n{}",
                        self.describe_topics()
                    ),
                )
            })?;
            if !types.contains(&self.topics[i].msg_type.as_str()) {
                return Err(Error::in_file(
                    &self.path,
                    format!(
                        "topic {name} ({flag}) is {}, not {types_text}; the bag's topics:\n{}",
                        self.topics[i].msg_type,
                        self.describe_topics()
                    ),
                ));
            }
            return Ok(Some(i));
        }
        let candidates: Vec<usize> = (0..self.topics.len())
            .filter(|&i| types.contains(&self.topics[i].msg_type.as_str()))
            .collect();
        match candidates.as_slice() {
            [i] => Ok(Some(*i)),
            [] if !required => Ok(None),
            [] => Err(Error::in_file(
                &self.path,
                format!(
                    "no {role} topic ({types_text}); the bag's topics:\n{}",
                    self.describe_topics()
                ),
            )),
            many => Err(Error::in_file(
                &self.path,
                format!(
                    "{} {role} topics ({}): choose one with {flag}; the bag's topics:\n{}",
                    many.len(),
                    many.iter()
                        .map(|&i| self.topics[i].name.as_str())
                        .collect::<Vec<_>>()
                        .join(", "),
                    self.describe_topics()
                ),
            )),
        }
    }

    /// The file that holds topic messages (for messages about one message).
    pub fn file_for_messages(&self) -> &Path {
        if self.files.len() == 1 {
            &self.files[0]
        } else {
            &self.path
        }
    }

    /// Reads every message of `topics` (indices into [`Bag::topics`]), in
    /// recording order (stable: equal times keep their storage order), each
    /// with its index within its topic.
    pub fn read(&self, topics: &[usize]) -> Result<Vec<RawMessage>> {
        for &t in topics {
            let info = &self.topics[t];
            if info.encoding.is_none() {
                return Err(Error::in_file(
                    &self.path,
                    format!(
                        "topic {} is serialised as '{}': only ros1 and cdr are read",
                        info.name, info.encoding_name
                    ),
                ));
            }
        }
        let names: Vec<&str> = topics
            .iter()
            .map(|&t| self.topics[t].name.as_str())
            .collect();
        let mut out: Vec<RawMessage> = Vec::new();
        for f in &self.files {
            let mut part = match self.storage {
                Storage::Ros1 => ros1::read(f, &names)?,
                Storage::Mcap => mcap::read(f, &names)?,
                Storage::Sqlite3 => sqlite::read(f, &names)?,
            };
            // Storage-local topic positions (in `names`) → bag topic indices.
            for m in &mut part {
                m.topic = topics[m.topic];
            }
            out.append(&mut part);
        }
        out.sort_by_key(|m| m.log_time_ns);
        let mut counts = vec![0usize; self.topics.len()];
        for m in &mut out {
            m.index = counts[m.topic];
            counts[m.topic] += 1;
        }
        Ok(out)
    }

    /// The encoding of `topic` (checked by [`Bag::read`]).
    pub fn encoding(&self, topic: usize) -> Encoding {
        self.topics[topic].encoding.unwrap_or(Encoding::Cdr)
    }

    /// Decodes `m` with `decode`, turning a failure into an error naming
    /// the file, the topic and the message index.
    pub fn decode<'a, T>(
        &self,
        m: &'a RawMessage,
        decode: impl FnOnce(&'a [u8], Encoding) -> wire::WireResult<T>,
    ) -> Result<T> {
        decode(&m.data, self.encoding(m.topic)).map_err(|e| {
            message_error(
                self.file_for_messages(),
                &self.topics[m.topic].name,
                m.index,
                format!("{}: {e}", self.topics[m.topic].msg_type),
            )
        })
    }
}

/// The serialisation named `name` (`ros1`, `cdr`), if dpslam reads it.
pub fn encoding_of(name: &str) -> Option<Encoding> {
    match name {
        "ros1" => Some(Encoding::Ros1),
        "cdr" => Some(Encoding::Cdr),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros2_type_names_are_shortened() {
        assert_eq!(
            normalise_type("sensor_msgs/msg/LaserScan"),
            "sensor_msgs/LaserScan"
        );
        assert_eq!(normalise_type("tf/tfMessage"), "tf/tfMessage");
    }

    #[test]
    fn bags_are_told_by_their_first_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.dat");
        std::fs::write(&p, b"#ROSBAG V2.0\n").unwrap();
        assert_eq!(bag_storage(&p), Some(Storage::Ros1));
        std::fs::write(&p, b"\x89MCAP0\r\n").unwrap();
        assert_eq!(bag_storage(&p), Some(Storage::Mcap));
        std::fs::write(&p, b"FLASER 1 2\n").unwrap();
        assert_eq!(bag_storage(&p), None);
        assert_eq!(
            bag_storage(dir.path()),
            None,
            "a folder without metadata.yaml"
        );
    }
}
