//! rosbag2 sqlite3 storage (`.db3`) through `rusqlite` with its bundled
//! SQLite: tables `topics(id, name, type, serialization_format, …)` and
//! `messages(id, topic_id, timestamp, data)`. Opened read-only.

use super::{RawMessage, TopicInfo, encoding_of, normalise_type};
use crate::{Error, Result};
use rusqlite::{Connection, OpenFlags};
use std::path::Path;

fn open(path: &Path) -> Result<Connection> {
    let c = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(|e| sql_err(path, e))?;
    Ok(c)
}

fn sql_err(path: &Path, e: rusqlite::Error) -> Error {
    Error::in_file(
        path,
        format!("rosbag2 sqlite3: {e} (truncated or corrupt database?)"),
    )
}

/// The topics of the database at `path`, with their message counts.
pub fn topics(path: &Path) -> Result<Vec<TopicInfo>> {
    let c = open(path)?;
    let mut st = c
        .prepare(
            "SELECT t.name, t.type, t.serialization_format, \
             (SELECT COUNT(*) FROM messages m WHERE m.topic_id = t.id) \
             FROM topics t ORDER BY t.id",
        )
        .map_err(|e| sql_err(path, e))?;
    let rows = st
        .query_map([], |r| {
            Ok((
                r.get::<_, String>(0)?,
                r.get::<_, String>(1)?,
                r.get::<_, String>(2)?,
                r.get::<_, i64>(3)?,
            ))
        })
        .map_err(|e| sql_err(path, e))?;
    let mut out = Vec::new();
    for r in rows {
        let (name, ty, fmt, n) = r.map_err(|e| sql_err(path, e))?;
        out.push(TopicInfo {
            name,
            msg_type: normalise_type(&ty),
            count: n.max(0) as u64,
            encoding: encoding_of(&fmt),
            encoding_name: fmt,
        });
    }
    Ok(out)
}

/// The messages of `topics`, by timestamp then row id; `RawMessage::topic`
/// is the position in `topics`.
pub fn read(path: &Path, topics: &[&str]) -> Result<Vec<RawMessage>> {
    let c = open(path)?;
    let mut st = c
        .prepare(
            "SELECT t.name, m.timestamp, m.data FROM messages m \
             JOIN topics t ON m.topic_id = t.id ORDER BY m.timestamp, m.id",
        )
        .map_err(|e| sql_err(path, e))?;
    let mut rows = st.query([]).map_err(|e| sql_err(path, e))?;
    let mut out = Vec::new();
    while let Some(r) = rows.next().map_err(|e| sql_err(path, e))? {
        let name: String = r.get(0).map_err(|e| sql_err(path, e))?;
        let Some(t) = topics.iter().position(|t| *t == name) else {
            continue;
        };
        let time: i64 = r.get(1).map_err(|e| sql_err(path, e))?;
        let data: Vec<u8> = r.get(2).map_err(|e| sql_err(path, e))?;
        out.push(RawMessage {
            topic: t,
            index: 0,
            log_time_ns: time.max(0) as u64,
            data,
        });
    }
    Ok(out)
}
