//! The two wire formats of ROS messages, decoded by hand for the few types
//! [`super::messages`] needs.
//!
//! - **ROS 1** serialisation: little-endian, packed (no alignment), strings
//!   and sequences as a `u32` count then the items, strings without a NUL.
//! - **CDR** (ROS 2, OMG classic CDR as Fast DDS and Cyclone write it): a
//!   4-byte encapsulation header (`00 00` big-endian, `00 01` little-endian,
//!   then two option bytes), then every primitive aligned to its own size
//!   (1, 2, 4, 8) counted from the byte after the header; strings are a
//!   `u32` length that includes the terminating NUL.
//!
//! Every read checks the remaining length: a short or inconsistent message
//! is an error saying what was being read and where, never a panic.

/// Which serialisation a message is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// ROS 1 (packed little-endian).
    Ros1,
    /// ROS 2 CDR with its encapsulation header.
    Cdr,
}

/// A cursor over one serialised message.
pub struct Wire<'a> {
    buf: &'a [u8],
    pos: usize,
    /// Start of the aligned body (after the CDR header), 0 for ROS 1.
    origin: usize,
    little: bool,
    align: bool,
}

/// Why a message could not be decoded (the caller adds file, topic, index).
pub type WireResult<T> = std::result::Result<T, String>;

impl<'a> Wire<'a> {
    /// A cursor over `buf` in `encoding`; CDR reads and checks the header.
    pub fn new(buf: &'a [u8], encoding: Encoding) -> WireResult<Self> {
        match encoding {
            Encoding::Ros1 => Ok(Wire {
                buf,
                pos: 0,
                origin: 0,
                little: true,
                align: false,
            }),
            Encoding::Cdr => {
                if buf.len() < 4 {
                    return Err(format!(
                        "{} bytes: too short for a CDR encapsulation header",
                        buf.len()
                    ));
                }
                let little = match (buf[0], buf[1]) {
                    (0, 0) => false,
                    (0, 1) => true,
                    (a, b) => {
                        return Err(format!(
                            "CDR encapsulation {a:#04x} {b:#04x} not supported \
                             (expected plain CDR: 00 00 big-endian or 00 01 little-endian)"
                        ));
                    }
                };
                Ok(Wire {
                    buf,
                    pos: 4,
                    origin: 4,
                    little,
                    align: true,
                })
            }
        }
    }

    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    fn align_to(&mut self, n: usize) -> WireResult<()> {
        if self.align {
            let off = (self.pos - self.origin) % n;
            if off != 0 {
                self.take(n - off, "alignment padding")?;
            }
        }
        Ok(())
    }

    fn take(&mut self, n: usize, what: &str) -> WireResult<&'a [u8]> {
        if self.remaining() < n {
            return Err(format!(
                "message ends early: {what} needs {n} bytes at byte {}, {} left \
                 (message of {} bytes)",
                self.pos,
                self.remaining(),
                self.buf.len()
            ));
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn fixed<const N: usize>(&mut self, what: &str) -> WireResult<[u8; N]> {
        self.align_to(N)?;
        let mut b: [u8; N] = self.take(N, what)?.try_into().expect("N bytes taken");
        if !self.little {
            b.reverse();
        }
        Ok(b)
    }

    /// One byte.
    /// A little-endian `u8`; `what` names the field in errors.
    pub fn u8(&mut self, what: &str) -> WireResult<u8> {
        Ok(self.take(1, what)?[0])
    }

    /// A bool (any non-zero byte is true).
    pub fn bool(&mut self, what: &str) -> WireResult<bool> {
        Ok(self.u8(what)? != 0)
    }

    /// A little-endian `u32`; `what` names the field in errors.
    pub fn u32(&mut self, what: &str) -> WireResult<u32> {
        Ok(u32::from_le_bytes(self.fixed::<4>(what)?))
    }

    /// A little-endian `i32`; `what` names the field in errors.
    pub fn i32(&mut self, what: &str) -> WireResult<i32> {
        Ok(i32::from_le_bytes(self.fixed::<4>(what)?))
    }

    /// A little-endian `f32`; `what` names the field in errors.
    pub fn f32(&mut self, what: &str) -> WireResult<f32> {
        Ok(f32::from_le_bytes(self.fixed::<4>(what)?))
    }

    /// A little-endian `f64`; `what` names the field in errors.
    pub fn f64(&mut self, what: &str) -> WireResult<f64> {
        Ok(f64::from_le_bytes(self.fixed::<8>(what)?))
    }

    /// A string (ROS 1: count then bytes; CDR: count with NUL, bytes, NUL).
    pub fn string(&mut self, what: &str) -> WireResult<String> {
        let n = self.u32(what)? as usize;
        let bytes = self.take(n, what)?;
        let bytes = if self.align {
            match bytes.split_last() {
                Some((0, s)) => s,
                None => bytes,
                Some(_) => return Err(format!("{what}: CDR string without its NUL")),
            }
        } else {
            bytes
        };
        String::from_utf8(bytes.to_vec()).map_err(|_| format!("{what}: not UTF-8"))
    }

    /// A sequence length, checked against the bytes left for items of
    /// `item_size` bytes each (at least 1), so that a corrupt count cannot
    /// ask for gigabytes.
    pub fn seq_len(&mut self, what: &str, item_size: usize) -> WireResult<usize> {
        let n = self.u32(what)? as usize;
        if n.saturating_mul(item_size.max(1)) > self.remaining() {
            return Err(format!(
                "{what}: {n} items of {} bytes do not fit in the {} bytes left",
                item_size.max(1),
                self.remaining()
            ));
        }
        Ok(n)
    }

    /// A sequence of f32.
    pub fn f32_seq(&mut self, what: &str) -> WireResult<Vec<f32>> {
        let n = self.seq_len(what, 4)?;
        (0..n).map(|_| self.f32(what)).collect()
    }

    /// A sequence of bytes, borrowed.
    pub fn byte_seq(&mut self, what: &str) -> WireResult<&'a [u8]> {
        let n = self.seq_len(what, 1)?;
        self.take(n, what)
    }

    /// A fixed array of `N` f64.
    pub fn f64_array<const N: usize>(&mut self, what: &str) -> WireResult<[f64; N]> {
        let mut a = [0.0; N];
        for v in &mut a {
            *v = self.f64(what)?;
        }
        Ok(a)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdr_aligns_from_the_end_of_the_header_in_both_byte_orders() {
        // u8 1, pad 3, u32 7, pad 4 (relative offset 8 is aligned for f64), f64 2.5
        let mut le = vec![0, 1, 0, 0, 1, 0, 0, 0];
        le.extend(7u32.to_le_bytes());
        le.extend(2.5f64.to_le_bytes());
        let mut be = vec![0, 0, 0, 0, 1, 0, 0, 0];
        be.extend(7u32.to_be_bytes());
        be.extend(2.5f64.to_be_bytes());
        for buf in [le, be] {
            let mut w = Wire::new(&buf, Encoding::Cdr).unwrap();
            assert_eq!(w.u8("a").unwrap(), 1);
            assert_eq!(w.u32("b").unwrap(), 7);
            assert_eq!(w.f64("c").unwrap(), 2.5);
            assert_eq!(w.remaining(), 0);
        }
        // After a 5-byte string (len 6 with NUL) at relative 0: next u32 at 12, f64 at 16.
        let mut s = vec![0, 1, 0, 0];
        s.extend(6u32.to_le_bytes());
        s.extend(b"laser\0");
        s.extend([0, 0]);
        s.extend(9u32.to_le_bytes());
        s.extend(1.0f64.to_le_bytes());
        let mut w = Wire::new(&s, Encoding::Cdr).unwrap();
        assert_eq!(w.string("frame").unwrap(), "laser");
        assert_eq!(w.u32("n").unwrap(), 9);
        assert_eq!(w.f64("x").unwrap(), 1.0);
    }

    #[test]
    fn ros1_is_packed_and_strings_have_no_nul() {
        let mut b = vec![1u8];
        b.extend(5u32.to_le_bytes());
        b.extend(b"laser");
        b.extend(3.0f64.to_le_bytes());
        let mut w = Wire::new(&b, Encoding::Ros1).unwrap();
        assert!(w.bool("flag").unwrap());
        assert_eq!(w.string("frame").unwrap(), "laser");
        assert_eq!(w.f64("x").unwrap(), 3.0);
    }

    #[test]
    fn short_messages_and_huge_counts_are_errors() {
        let b = [0u8, 1, 0, 0, 0xff, 0xff, 0xff, 0x7f, 1, 2];
        let mut w = Wire::new(&b, Encoding::Cdr).unwrap();
        let e = w.f32_seq("ranges").unwrap_err();
        assert!(e.contains("ranges") && e.contains("do not fit"), "{e}");
        let mut w = Wire::new(&b[..6], Encoding::Cdr).unwrap();
        let e = w.u32("height").unwrap_err();
        assert!(e.contains("height") && e.contains("ends early"), "{e}");
        assert!(Wire::new(&[0, 1], Encoding::Cdr).is_err());
        let e = Wire::new(&[0, 7, 0, 0], Encoding::Cdr).err().unwrap();
        assert!(e.contains("not supported"), "{e}");
    }
}
