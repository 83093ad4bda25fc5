//! Opening input files: gzip detection, line-by-line reading with line
//! numbers, and whole-file reads for binary formats.
//!
//! A truncated gzip stream surfaces as an error naming the file and the line
//! (or byte) where the data ended, never as a silently short read.

use crate::{Error, Result};
use flate2::read::MultiGzDecoder;
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];

/// Counts the bytes read from the underlying (possibly compressed) file, for progress.
struct Counting<R> {
    inner: R,
    count: Arc<AtomicU64>,
}

impl<R: Read> Read for Counting<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.count.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }
}

/// Whether the file at `path` starts with the gzip magic bytes.
pub fn is_gzip(path: &Path) -> Result<bool> {
    let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
    let mut magic = [0u8; 2];
    let mut got = 0;
    while got < 2 {
        match f.read(&mut magic[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) => return Err(Error::io(path, e)),
        }
    }
    Ok(got == 2 && magic == GZIP_MAGIC)
}

/// Opens `path` for reading, decompressing gzip transparently.
/// Returns the reader, the shared count of file bytes consumed, and the file size.
fn open_counted(path: &Path) -> Result<(Box<dyn BufRead + Send>, Arc<AtomicU64>, u64)> {
    let gz = is_gzip(path)?;
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let total = file.metadata().map(|m| m.len()).unwrap_or(0);
    let count = Arc::new(AtomicU64::new(0));
    let counted = Counting {
        inner: file,
        count: Arc::clone(&count),
    };
    let reader: Box<dyn BufRead + Send> = if gz {
        Box::new(BufReader::with_capacity(
            1 << 16,
            MultiGzDecoder::new(BufReader::new(counted)),
        ))
    } else {
        Box::new(BufReader::with_capacity(1 << 16, counted))
    };
    Ok((reader, count, total))
}

/// Reads a whole file into memory, decompressing gzip. For binary formats.
pub fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    let (mut r, _, _) = open_counted(path)?;
    let mut buf = Vec::new();
    r.read_to_end(&mut buf)
        .map_err(|e| describe_read_error(path, e, None))?;
    Ok(buf)
}

/// Turns an I/O error during reading into a user-facing error.
fn describe_read_error(path: &Path, e: std::io::Error, line: Option<usize>) -> Error {
    let reason = match e.kind() {
        std::io::ErrorKind::UnexpectedEof => {
            "compressed data ends early (truncated gzip file)".to_string()
        }
        std::io::ErrorKind::InvalidData | std::io::ErrorKind::InvalidInput => {
            format!("corrupt or non-text data: {e}")
        }
        _ => return Error::io(path, e),
    };
    match line {
        Some(l) => Error::at_line(path, l, reason),
        None => Error::in_file(path, reason),
    }
}

/// A text file read line by line, with 1-based line numbers.
pub struct TextSource {
    path: PathBuf,
    reader: Box<dyn BufRead + Send>,
    line_no: usize,
    buf: String,
    bytes: Arc<AtomicU64>,
    total: u64,
}

impl TextSource {
    /// Opens `path` (plain or gzip).
    pub fn open(path: &Path) -> Result<Self> {
        let (reader, bytes, total) = open_counted(path)?;
        Ok(Self {
            path: path.to_path_buf(),
            reader,
            line_no: 0,
            buf: String::new(),
            bytes,
            total,
        })
    }

    /// The next line without its line terminator, with its 1-based number;
    /// `None` at the end of the file.
    pub fn next_line(&mut self) -> Result<Option<(usize, &str)>> {
        self.buf.clear();
        let n = self
            .reader
            .read_line(&mut self.buf)
            .map_err(|e| describe_read_error(&self.path, e, Some(self.line_no + 1)))?;
        if n == 0 {
            return Ok(None);
        }
        self.line_no += 1;
        let line = self.buf.trim_end_matches(['\n', '\r']);
        Ok(Some((self.line_no, line)))
    }

    /// The path this source reads.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes of the file on disk consumed so far (compressed bytes for gzip).
    pub fn bytes_read(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    /// Size of the file on disk in bytes.
    pub fn total_bytes(&self) -> u64 {
        self.total
    }

    /// A parse error at the current line.
    pub fn error(&self, reason: impl Into<String>) -> Error {
        Error::at_line(&self.path, self.line_no, reason)
    }
}

/// Parses a whitespace-separated field as a finite or non-finite f64, with a
/// message naming the field on failure.
pub fn parse_f64(tok: Option<&str>, what: &str) -> std::result::Result<f64, String> {
    let t = tok.ok_or_else(|| format!("missing {what}"))?;
    t.parse::<f64>()
        .map_err(|_| format!("{what}: '{t}' is not a number"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn reads_plain_and_gzip_lines_with_numbers() {
        let dir = tempfile::tempdir().unwrap();
        let plain = dir.path().join("a.txt");
        std::fs::write(&plain, "one\ntwo\r\nthree").unwrap();
        let gz = dir.path().join("a.gz");
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(b"one\ntwo\r\nthree").unwrap();
        std::fs::write(&gz, e.finish().unwrap()).unwrap();
        for p in [&plain, &gz] {
            let mut s = TextSource::open(p).unwrap();
            let mut got = Vec::new();
            while let Some((n, l)) = s.next_line().unwrap() {
                got.push((n, l.to_string()));
            }
            assert_eq!(
                got,
                vec![(1, "one".into()), (2, "two".into()), (3, "three".into())]
            );
        }
    }

    #[test]
    fn truncated_gzip_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let gz = dir.path().join("cut.log.gz");
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        for i in 0..5000 {
            writeln!(e, "ODOM {i} 0 0 0 0 0 {i}.0 host 0").unwrap();
        }
        let bytes = e.finish().unwrap();
        std::fs::write(&gz, &bytes[..bytes.len() / 2]).unwrap();
        let mut s = TextSource::open(&gz).unwrap();
        let err = loop {
            match s.next_line() {
                Ok(Some(_)) => continue,
                Ok(None) => panic!("truncated file read to the end without error"),
                Err(e) => break e,
            }
        };
        let msg = err.to_string();
        assert!(
            msg.contains("cut.log.gz") && msg.contains("truncated"),
            "{msg}"
        );
        assert!(read_bytes(&gz).is_err());
    }
}
