//! MCAP files through the `mcap` crate (zstd and lz4 chunks, CRCs checked).
//!
//! Topics come from the summary section; a file without one (a streamed or
//! cut recording) is scanned instead, so that a truncated file is an error
//! at the message where it breaks.

use super::{RawMessage, TopicInfo, encoding_of, normalise_type};
use crate::{Error, Result};
use mcap::read::Options;
use std::collections::BTreeMap;
use std::path::Path;

fn load(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

fn stream(buf: &[u8]) -> mcap::McapResult<mcap::MessageStream<'_>> {
    mcap::MessageStream::new_with_options(buf, Options::ValidateChunkCrcs.into())
}

fn info_of(ch: &mcap::Channel) -> TopicInfo {
    let ty = ch.schema.as_ref().map_or("", |s| s.name.as_str());
    TopicInfo {
        name: ch.topic.clone(),
        msg_type: normalise_type(ty),
        count: 0,
        encoding: encoding_of(&ch.message_encoding),
        encoding_name: ch.message_encoding.clone(),
    }
}

fn mcap_err(path: &Path, after: usize, e: mcap::McapError) -> Error {
    Error::in_file(
        path,
        format!("MCAP: {e} (after {after} messages; truncated or corrupt file?)"),
    )
}

/// The topics of the MCAP file at `path`.
pub fn topics(path: &Path) -> Result<Vec<TopicInfo>> {
    let buf = load(path)?;
    let summary = mcap::Summary::read(&buf).ok().flatten();
    let mut out: Vec<TopicInfo> = Vec::new();
    let mut push = |info: TopicInfo, n: u64| match out.iter_mut().find(|t| t.name == info.name) {
        Some(t) => t.count += n,
        None => out.push(TopicInfo { count: n, ..info }),
    };
    match summary {
        Some(s) if s.stats.is_some() => {
            let counts = &s.stats.as_ref().expect("checked").channel_message_counts;
            let chans: BTreeMap<u16, _> = s.channels.iter().map(|(k, v)| (*k, v)).collect();
            for (id, ch) in chans {
                push(info_of(ch), counts.get(&id).copied().unwrap_or(0));
            }
        }
        _ => {
            for (n, m) in stream(&buf).map_err(|e| mcap_err(path, 0, e))?.enumerate() {
                let m = m.map_err(|e| mcap_err(path, n, e))?;
                push(info_of(&m.channel), 1);
            }
        }
    }
    Ok(out)
}

/// The messages of `topics` in file order; `RawMessage::topic` is the
/// position in `topics`.
pub fn read(path: &Path, topics: &[&str]) -> Result<Vec<RawMessage>> {
    let buf = load(path)?;
    let mut out = Vec::new();
    for (n, m) in stream(&buf).map_err(|e| mcap_err(path, 0, e))?.enumerate() {
        let m = m.map_err(|e| mcap_err(path, n, e))?;
        if let Some(t) = topics.iter().position(|t| *t == m.channel.topic) {
            out.push(RawMessage {
                topic: t,
                index: 0,
                log_time_ns: m.log_time,
                data: m.data.into_owned(),
            });
        }
    }
    Ok(out)
}
