//! The drivable path both simulators follow: the waypoint polyline with its
//! corners rounded into circular arcs, parameterised by arc length.

use crate::geometry::{Pose2, pose2, wrap_angle};
use crate::{Error, Result};
use std::f64::consts::PI;

/// Turns sharper than this (rad) cannot be filleted into a drivable arc.
const MAX_TURN: f64 = 179.0 * PI / 180.0;

/// One drivable piece of the path.
#[derive(Debug, Clone, Copy)]
enum Piece {
    /// Straight from `p0` along `heading` (rad) for `len` (m).
    Line {
        p0: [f64; 2],
        heading: f64,
        len: f64,
    },
    /// Arc about `centre` of radius `r` (m), starting at heading `h0` (rad),
    /// turning left (`sign` = 1) or right (−1) for `len` (m).
    Arc {
        centre: [f64; 2],
        r: f64,
        h0: f64,
        sign: f64,
        len: f64,
    },
}

impl Piece {
    fn len(&self) -> f64 {
        match *self {
            Piece::Line { len, .. } | Piece::Arc { len, .. } => len,
        }
    }

    /// `(x, y, heading)` at arc length `s` (m) into the piece.
    fn at(&self, s: f64) -> (f64, f64, f64) {
        match *self {
            Piece::Line { p0, heading, .. } => (
                p0[0] + s * heading.cos(),
                p0[1] + s * heading.sin(),
                heading,
            ),
            Piece::Arc {
                centre,
                r,
                h0,
                sign,
                ..
            } => {
                let h = h0 + sign * s / r;
                // The centre lies on the side the vehicle turns to, so the
                // vehicle sits at r on the other side, perpendicular to its
                // heading.
                (
                    centre[0] + sign * r * h.sin(),
                    centre[1] - sign * r * h.cos(),
                    h,
                )
            }
        }
    }
}

/// The waypoint polyline with rounded corners, parameterised by arc length.
pub(crate) struct SmoothPath {
    pieces: Vec<Piece>,
}

impl SmoothPath {
    /// Rounds each corner of `waypoints` (at least two) into an arc of
    /// `radius` (m; 0 keeps sharp corners), shrunk where a leg is too short.
    ///
    /// Fails with [`Error::Config`], its message starting with `who` (the
    /// caller's name, e.g. `simulate2d`), if two consecutive waypoints
    /// coincide or the path turns back on itself.
    pub(crate) fn new(waypoints: &[[f64; 2]], radius: f64, who: &str) -> Result<Self> {
        let n = waypoints.len();
        let mut dirs = Vec::with_capacity(n - 1);
        let mut lens = Vec::with_capacity(n - 1);
        for (i, w) in waypoints.windows(2).enumerate() {
            let d = [w[1][0] - w[0][0], w[1][1] - w[0][1]];
            let len = d[0].hypot(d[1]);
            if len < 1e-6 {
                return Err(Error::Config(format!(
                    "{who}: waypoints {i} and {} coincide",
                    i + 1
                )));
            }
            dirs.push(d[1].atan2(d[0]));
            lens.push(len);
        }
        // For each interior waypoint: signed turn, tangent length, arc radius.
        // A leg lends at most half its length to each of its two corners.
        let mut corners = vec![(0.0, 0.0, 0.0); n];
        for i in 1..n - 1 {
            let turn = wrap_angle(dirs[i] - dirs[i - 1]);
            if turn.abs() < 1e-12 || radius == 0.0 {
                continue;
            }
            if turn.abs() > MAX_TURN {
                return Err(Error::Config(format!(
                    "{who}: the path reverses at waypoint {i} (turn of {:.1}°)",
                    turn.to_degrees()
                )));
            }
            let half = (turn.abs() / 2.0).tan();
            let tangent = (radius * half).min(lens[i - 1] / 2.0).min(lens[i] / 2.0);
            corners[i] = (turn, tangent, tangent / half);
        }
        let mut pieces = Vec::new();
        for i in 0..n - 1 {
            let (a, h) = (waypoints[i], dirs[i]);
            let (cos, sin) = (h.cos(), h.sin());
            let start = corners[i].1;
            let end = lens[i] - corners[i + 1].1;
            pieces.push(Piece::Line {
                p0: [a[0] + start * cos, a[1] + start * sin],
                heading: h,
                len: end - start,
            });
            let (turn, _, r) = corners[i + 1];
            if r > 0.0 {
                let sign = turn.signum();
                let p = [a[0] + end * cos, a[1] + end * sin];
                pieces.push(Piece::Arc {
                    centre: [p[0] - sign * r * sin, p[1] + sign * r * cos],
                    r,
                    h0: h,
                    sign,
                    len: r * turn.abs(),
                });
            }
        }
        Ok(SmoothPath { pieces })
    }

    /// Total length (m).
    pub(crate) fn length(&self) -> f64 {
        self.pieces.iter().map(Piece::len).sum()
    }

    /// `(x, y, heading)` at the (non-decreasing) arc lengths `s` (m), each
    /// clamped to the path.
    pub(crate) fn sample_xyh(&self, s: impl Iterator<Item = f64>) -> Vec<(f64, f64, f64)> {
        let mut k = 0;
        let mut before = 0.0;
        s.map(|s| {
            while k + 1 < self.pieces.len() && s > before + self.pieces[k].len() {
                before += self.pieces[k].len();
                k += 1;
            }
            let p = &self.pieces[k];
            p.at((s - before).clamp(0.0, p.len()))
        })
        .collect()
    }

    /// Poses at the (non-decreasing) arc lengths `s` (m); see
    /// [`SmoothPath::sample_xyh`].
    pub(crate) fn sample(&self, s: impl Iterator<Item = f64>) -> Vec<Pose2> {
        self.sample_xyh(s)
            .into_iter()
            .map(|(x, y, h)| pose2(x, y, h))
            .collect()
    }
}

/// Why `waypoints` cannot make a path (fewer than two, or not finite), if so.
pub fn waypoint_problem(waypoints: &[[f64; 2]]) -> Option<String> {
    if waypoints.len() < 2 {
        return Some("at least two waypoints are needed".into());
    }
    waypoints
        .iter()
        .find(|w| !(w[0].is_finite() && w[1].is_finite()))
        .map(|w| format!("waypoint {w:?} is not finite"))
}
