//! ROS 1 bags (format 2.0) through the `rosbag` crate: uncompressed, bz2
//! and lz4 chunks.
//!
//! The crate trusts the bag header's `index_pos` (it slices the file with
//! it), so the header is checked here first: an unfinished recording (index
//! position 0, or beyond the end of a truncated file) is an error telling
//! the user to `rosbag reindex` it, not a panic.

use super::{RawMessage, TopicInfo, encoding_of, normalise_type};
use crate::{Error, Result};
use rosbag::{ChunkRecord, IndexRecord, MessageRecord, RosBag};
use std::collections::HashMap;
use std::path::Path;

const MAGIC: &[u8] = b"#ROSBAG V2.0\n";

/// Reads the bag header's `index_pos` and checks it against the file.
fn check_header(path: &Path) -> Result<()> {
    let bytes = {
        use std::io::Read;
        let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut b = vec![0u8; 4096];
        let mut n = 0;
        while n < b.len() {
            match f.read(&mut b[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) => return Err(Error::io(path, e)),
            }
        }
        b.truncate(n);
        b
    };
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    if !bytes.starts_with(MAGIC) {
        let reason = if bytes.starts_with(b"#ROSBAG V") {
            "unsupported ROS bag version (only 2.0 is read)"
        } else {
            "not a ROS 1 bag (no '#ROSBAG V2.0' line)"
        };
        return Err(Error::in_file(path, reason));
    }
    let trunc = || Error::in_file(path, "truncated in the bag header");
    let rest = &bytes[MAGIC.len()..];
    let hlen = u32::from_le_bytes(rest.get(..4).ok_or_else(trunc)?.try_into().unwrap()) as usize;
    let header = rest.get(4..4 + hlen).ok_or_else(trunc)?;
    let mut index_pos = None;
    let mut p = 0;
    while p + 4 <= header.len() {
        let n = u32::from_le_bytes(header[p..p + 4].try_into().unwrap()) as usize;
        let field = header.get(p + 4..p + 4 + n).ok_or_else(trunc)?;
        if let Some(v) = field.strip_prefix(b"index_pos=")
            && v.len() == 8
        {
            index_pos = Some(u64::from_le_bytes(v.try_into().unwrap()));
        }
        p += 4 + n;
    }
    let index_pos =
        index_pos.ok_or_else(|| Error::in_file(path, "bag header without index_pos"))?;
    let start = (MAGIC.len() + 4 + hlen) as u64;
    if index_pos == 0 {
        return Err(Error::in_file(
            path,
            "the bag has no index (an unfinished recording): run `rosbag reindex` on it first",
        ));
    }
    if index_pos < start || index_pos > len {
        return Err(Error::in_file(
            path,
            format!(
                "truncated or corrupt: the bag header puts the index at byte {index_pos}, \
                 the file has {len} bytes (`rosbag reindex` may recover a cut recording)"
            ),
        ));
    }
    Ok(())
}

fn open(path: &Path) -> Result<RosBag> {
    check_header(path)?;
    RosBag::new(path).map_err(|e| Error::in_file(path, format!("ROS 1 bag: {e}")))
}

fn bag_err(path: &Path, what: &str, e: rosbag::Error) -> Error {
    let e = e.to_string();
    let e = e.strip_prefix("rosbag::Error: ").unwrap_or(&e);
    Error::in_file(path, format!("{what}: {e} (truncated or corrupt bag?)"))
}

/// The topics of the bag at `path`, from its index section.
pub fn topics(path: &Path) -> Result<Vec<TopicInfo>> {
    let bag = open(path)?;
    let mut conns: HashMap<u32, usize> = HashMap::new();
    let mut out: Vec<TopicInfo> = Vec::new();
    let mut counts: HashMap<u32, u64> = HashMap::new();
    for rec in bag.index_records() {
        match rec.map_err(|e| bag_err(path, "index section", e))? {
            IndexRecord::Connection(c) => {
                let ty = normalise_type(c.tp);
                let i = match out.iter().position(|t| t.name == c.topic) {
                    Some(i) => {
                        if out[i].msg_type != ty {
                            return Err(Error::in_file(
                                path,
                                format!(
                                    "topic {} has two types: {} and {ty}",
                                    c.topic, out[i].msg_type
                                ),
                            ));
                        }
                        i
                    }
                    None => {
                        out.push(TopicInfo {
                            name: c.topic.to_string(),
                            msg_type: ty,
                            count: 0,
                            encoding: encoding_of("ros1"),
                            encoding_name: "ros1".into(),
                        });
                        out.len() - 1
                    }
                };
                conns.insert(c.id, i);
            }
            IndexRecord::ChunkInfo(ci) => {
                for e in ci.entries() {
                    *counts.entry(e.conn_id).or_default() += e.count as u64;
                }
            }
            IndexRecord::IndexData(_) => {}
        }
    }
    for (conn, n) in counts {
        if let Some(&i) = conns.get(&conn) {
            out[i].count += n;
        }
    }
    Ok(out)
}

/// The messages of `topics` in file order; `RawMessage::topic` is the
/// position in `topics`, `index` is filled in by the caller.
pub fn read(path: &Path, topics: &[&str]) -> Result<Vec<RawMessage>> {
    let bag = open(path)?;
    // Connection id → position in `topics` (None: not wanted). Connection
    // records come before their messages, in the chunk that first uses them.
    let mut conns: HashMap<u32, Option<usize>> = HashMap::new();
    for rec in bag.index_records() {
        if let IndexRecord::Connection(c) = rec.map_err(|e| bag_err(path, "index section", e))? {
            conns.insert(c.id, topics.iter().position(|t| *t == c.topic));
        }
    }
    let mut out = Vec::new();
    for (k, rec) in bag.chunk_records().enumerate() {
        let rec = rec.map_err(|e| bag_err(path, &format!("chunk record {k}"), e))?;
        let ChunkRecord::Chunk(chunk) = rec else {
            continue;
        };
        for msg in chunk.messages() {
            match msg.map_err(|e| bag_err(path, &format!("chunk record {k}"), e))? {
                MessageRecord::Connection(c) => {
                    conns.insert(c.id, topics.iter().position(|t| *t == c.topic));
                }
                MessageRecord::MessageData(m) => match conns.get(&m.conn_id) {
                    Some(Some(t)) => out.push(RawMessage {
                        topic: *t,
                        index: 0,
                        log_time_ns: m.time,
                        data: m.data.to_vec(),
                    }),
                    Some(None) => {}
                    None => {
                        return Err(Error::in_file(
                            path,
                            format!(
                                "chunk record {k}: a message of connection {} that no \
                                 connection record declares (corrupt bag?)",
                                m.conn_id
                            ),
                        ));
                    }
                },
            }
        }
    }
    Ok(out)
}
