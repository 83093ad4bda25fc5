//! Sweep readers on the real 3-D datasets, their error reports, and the PLY
//! exports parsed back with ply-rs-bw's own parser.
//!
//! The datasets are read in place from `../shared/datasets/3d` (or from
//! `$DPSLAM_DATASETS/3d`); they are never copied into the repository.

use dpslam::io::ply::{VoxelPoint, read_ply_points, write_points_ply, write_voxel_ply};
use dpslam::io::sweeps::{
    Sweep, SweepFormat, list_sweeps, read_sweep, sweep_format, threedtk_point, threedtk_pose,
};
use nalgebra::Point3;
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{PropertyAccess, PropertyAccessResult, PropertyType, ScalarType};
use std::io::Write;
use std::path::{Path, PathBuf};

fn data3d() -> PathBuf {
    let root = std::env::var_os("DPSLAM_DATASETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets"));
    let d = root.join("3d");
    assert!(
        d.is_dir(),
        "3-D datasets not found at {} (set DPSLAM_DATASETS)",
        d.display()
    );
    d
}

fn all_finite(s: &Sweep) -> bool {
    s.points.iter().all(|p| p.iter().all(|v| v.is_finite()))
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// Splits a PCD file into its header text and the byte offset of its body.
fn pcd_header(bytes: &[u8]) -> (String, usize) {
    let key = b"DATA binary\n";
    let at = bytes.windows(key.len()).position(|w| w == key).unwrap() + key.len();
    (String::from_utf8(bytes[..at].to_vec()).unwrap(), at)
}

fn header_value(header: &str, key: &str) -> usize {
    header
        .lines()
        .find_map(|l| l.strip_prefix(key))
        .unwrap()
        .trim()
        .parse()
        .unwrap()
}

// ------------------------------------------------------------- real data ---

#[test]
fn fast_gicp_binary_pcd_counts_match_header_less_zero_returns() {
    let dir = data3d().join("fast_gicp");
    for (name, expect_zero) in [("251370668.pcd", 5032), ("251371071.pcd", 5107)] {
        let path = dir.join(name);
        let bytes = std::fs::read(&path).unwrap();
        let (header, body) = pcd_header(&bytes);
        let declared = header_value(&header, "POINTS ");
        assert_eq!(declared, header_value(&header, "WIDTH "));
        // Independent decode: records of 4 little-endian f32 (x y z intensity).
        let raw: Vec<[f32; 3]> = bytes[body..]
            .chunks_exact(16)
            .map(|r| [0, 1, 2].map(|k| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap())))
            .collect();
        assert_eq!(raw.len(), declared);
        let zeros = raw.iter().filter(|p| **p == [0.0; 3]).count();
        assert_eq!(zeros, expect_zero, "{name}");

        let s = read_sweep(&path).unwrap();
        assert_eq!(s.points.len(), declared - zeros, "{name}");
        assert!(all_finite(&s));
        assert_eq!(s.prior, None, "identity VIEWPOINT carries no pose");
        assert_eq!(s.source, path);
        let kept: Vec<[f32; 3]> = raw.into_iter().filter(|p| *p != [0.0; 3]).collect();
        assert_eq!(s.points, kept, "points in file order, bit-exact");
        // A Velodyne sweep: everything within 150 m of the sensor.
        let max_r = s
            .points
            .iter()
            .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
            .fold(0.0f32, f32::max);
        assert!(max_r > 10.0 && max_r < 150.0, "max range {max_r}");
    }
}

#[test]
fn listing_fast_gicp_ignores_the_relative_transform_txt() {
    let dir = data3d().join("fast_gicp");
    let files = list_sweeps(&dir).unwrap();
    let names: Vec<_> = files
        .iter()
        .map(|p| p.file_name().unwrap().to_str().unwrap())
        .collect();
    assert_eq!(names, ["251370668.pcd", "251371071.pcd"]);
}

#[test]
fn threedtk_kurt3d_scans_convert_points_and_poses() {
    let dir = data3d().join("3dtk-kurt3d");
    let files = list_sweeps(&dir).unwrap();
    let names: Vec<_> = files
        .iter()
        .map(|p| p.file_name().unwrap().to_str().unwrap())
        .collect();
    assert_eq!(names, ["scan000.3d", "scan001.3d", "scan002.3d"]);
    for f in &files {
        assert_eq!(sweep_format(f).unwrap(), SweepFormat::ThreeDtk);
        let s = read_sweep(f).unwrap();
        assert_eq!(s.points.len(), 81_360, "{}", f.display());
        assert!(all_finite(&s));
        assert!(s.prior.is_some());
    }

    // scan000.pose is "0 0 0 / -0 0 -0": the identity.
    let s0 = read_sweep(&files[0]).unwrap();
    let p0 = s0.prior.unwrap();
    assert!(p0.translation.vector.norm() < 1e-15 && p0.rotation.angle() < 1e-15);
    // Its first line "10.1 0 0" (cm, 3DTK x = right) is 0.101 m to the right,
    // i.e. y = -0.101 in the right-handed z-up frame.
    assert_eq!(s0.points[0], [0.0, -0.101, 0.0]);

    // scan001.pose: t = (-3.10605, -7.50803, 156.917) cm,
    // angles = (1.35694, -0.852409, -0.56224) deg. Line 40000 of scan001.3d is
    // "121.695 6.49968 42.6015". Hand computation (3DTK's EulerToMatrix4,
    // w = M·p + t in 3DTK's frame, then (x, y, z) -> (z, -x, y)/100):
    //   sensor frame: (0.426015, -1.21695, 0.0649968) m
    //   3DTK world:   (117.99962311, -3.25593850, 201.43825700) cm
    //   world frame:  (2.0143825700, -1.1799962311, -0.0325593850) m
    let s1 = read_sweep(&files[1]).unwrap();
    let p = s1.points[39_999];
    let want_sensor = [0.426015f32, -1.21695, 0.0649968];
    for k in 0..3 {
        assert!((p[k] - want_sensor[k]).abs() < 1e-6, "{p:?}");
    }
    let w = s1.prior.unwrap() * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
    let want_world = [2.0143825700, -1.1799962311, -0.0325593850];
    for k in 0..3 {
        assert!((w[k] - want_world[k]).abs() < 1e-6, "{w:?}");
    }
    // The robot drove ~1.57 m forward (+x) between scan000 and scan001.
    let t = s1.prior.unwrap().translation.vector;
    assert!((t.x - 1.56917).abs() < 1e-9 && (t.y - 0.0310605).abs() < 1e-9);
    assert!((t.z + 0.0750803).abs() < 1e-9);
}

#[test]
fn libpointmatcher_vtk_reads_declared_points() {
    let dir = data3d().join("libpointmatcher");
    let files = list_sweeps(&dir).unwrap();
    assert_eq!(files.len(), 3, "cloudList.csv is not a sweep");
    let s = read_sweep(&dir.join("cloud.00000.vtk")).unwrap();
    assert_eq!(s.points.len(), 24_989);
    assert!(all_finite(&s));
    assert_eq!(s.points[0], [-3.79521, 0.0131325, -0.95763]);
    assert_eq!(*s.points.last().unwrap(), [0.438149, -0.000387187, 6.72051]);
    for f in &files[1..] {
        let s = read_sweep(f).unwrap();
        assert!(s.points.len() > 20_000 && all_finite(&s));
    }
}

#[test]
fn bzip2_scan_is_refused_with_advice() {
    let path = data3d().join("octomap/scan.dat.bz2");
    let e = read_sweep(&path).unwrap_err().to_string();
    assert!(
        e.contains("scan.dat.bz2") && e.contains("bzip2 not supported"),
        "{e}"
    );
    assert!(e.contains("decompress first"), "{e}");
    let e = list_sweeps(&data3d().join("octomap"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("bzip2 not supported"), "{e}");
    // Recognised by content too, whatever the name.
    let dir = tempfile::tempdir().unwrap();
    let renamed = dir.path().join("scan.xyz");
    std::fs::copy(&path, &renamed).unwrap();
    let e = read_sweep(&renamed).unwrap_err().to_string();
    assert!(e.contains("bzip2 not supported"), "{e}");
}

// ---------------------------------------------------------------- errors ---

#[test]
fn truncated_binary_pcd_names_the_byte_offset() {
    let src = std::fs::read(data3d().join("fast_gicp/251370668.pcd")).unwrap();
    let (_, body) = pcd_header(&src);
    let dir = tempfile::tempdir().unwrap();
    let cut = dir.path().join("cut.pcd");
    // 1000 whole points and half of the next.
    std::fs::write(&cut, &src[..body + 1000 * 16 + 8]).unwrap();
    let e = read_sweep(&cut).unwrap_err().to_string();
    assert!(e.contains("cut.pcd"), "{e}");
    assert!(e.contains(&format!("byte {}", body + 1000 * 16)), "{e}");
    assert!(
        e.contains("truncated") && e.contains("point 1000 of 69088"),
        "{e}"
    );
}

#[test]
fn truncated_gzip_pcd_is_an_error() {
    let src = std::fs::read(data3d().join("fast_gicp/251370668.pcd")).unwrap();
    let gz = gzip(&src);
    let dir = tempfile::tempdir().unwrap();
    let whole = dir.path().join("a.pcd.gz");
    std::fs::write(&whole, &gz).unwrap();
    let plain = read_sweep(&data3d().join("fast_gicp/251370668.pcd")).unwrap();
    assert_eq!(read_sweep(&whole).unwrap().points, plain.points);
    let cut = dir.path().join("cut.pcd.gz");
    std::fs::write(&cut, &gz[..gz.len() / 2]).unwrap();
    let e = read_sweep(&cut).unwrap_err().to_string();
    assert!(e.contains("cut.pcd.gz") && e.contains("truncated"), "{e}");
}

#[test]
fn kitti_bin_reads_records_and_rejects_ragged_size() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("000000.bin");
    let mut b = Vec::new();
    for rec in [
        [1.0f32, 2.0, 3.0, 0.5],
        [0.0, 0.0, 0.0, 0.0],
        [-4.0, 5.5, f32::NAN, 0.1],
        [7.0, 8.0, 9.0, 1.0],
    ] {
        for v in rec {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(&good, &b).unwrap();
    let s = read_sweep(&good).unwrap();
    assert_eq!(
        s.points,
        vec![[1.0, 2.0, 3.0], [7.0, 8.0, 9.0]],
        "zero and NaN dropped"
    );

    let bad = dir.path().join("000001.bin");
    std::fs::write(&bad, &b[..b.len() - 5]).unwrap();
    let e = read_sweep(&bad).unwrap_err().to_string();
    assert!(
        e.contains("000001.bin") && e.contains("multiple of 16"),
        "{e}"
    );
    assert!(e.contains(&format!("byte {}", 48)), "{e}");

    let inf = dir.path().join("000002.bin");
    let mut b2 = b.clone();
    b2[16 * 3..16 * 3 + 4].copy_from_slice(&f32::INFINITY.to_le_bytes());
    std::fs::write(&inf, &b2).unwrap();
    let e = read_sweep(&inf).unwrap_err().to_string();
    assert!(e.contains("byte 48") && e.contains("infinite"), "{e}");
}

#[test]
fn malformed_text_line_names_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("cloud.xyz");
    std::fs::write(&p, "# x y z\n1 2 3 99\n\n4,5,6\n7 8 oops\n").unwrap();
    let e = read_sweep(&p).unwrap_err().to_string();
    assert!(e.contains("cloud.xyz:line 5") && e.contains("oops"), "{e}");
    let p2 = dir.path().join("short.txt");
    std::fs::write(&p2, "1 2 3\n4 5\n").unwrap();
    let e = read_sweep(&p2).unwrap_err().to_string();
    assert!(
        e.contains("short.txt:line 2") && e.contains("missing z"),
        "{e}"
    );
    let ok = dir.path().join("ok.txt");
    std::fs::write(&ok, "1 2 3 99\r\n\r\n4,5,6\r\nnan 1 1\r\n").unwrap();
    let s = read_sweep(&ok).unwrap();
    assert_eq!(s.points, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
}

#[test]
fn empty_files_are_errors_in_every_format() {
    let dir = tempfile::tempdir().unwrap();
    for name in [
        "e.pcd",
        "e.ply",
        "e.bin",
        "e.xyz",
        "e.txt",
        "e.vtk",
        "scan000.3d",
    ] {
        let p = dir.path().join(name);
        std::fs::write(&p, b"").unwrap();
        let e = read_sweep(&p).unwrap_err().to_string();
        assert!(e.contains(name) && e.contains("empty"), "{e}");
    }
    // Only comments: no points either.
    let p = dir.path().join("c.xyz");
    std::fs::write(&p, "# nothing\n\n").unwrap();
    let e = read_sweep(&p).unwrap_err().to_string();
    assert!(e.contains("no points"), "{e}");
    // A directory with no sweep file (only a pose and a csv).
    let empty = tempfile::tempdir().unwrap();
    let e = list_sweeps(empty.path()).unwrap_err().to_string();
    assert!(e.contains("no sweep files"), "{e}");
    std::fs::write(empty.path().join("scan000.pose"), "0 0 0\n0 0 0\n").unwrap();
    std::fs::write(empty.path().join("list.csv"), "a\n").unwrap();
    let e = list_sweeps(empty.path()).unwrap_err().to_string();
    assert!(e.contains("no sweep files"), "{e}");
    // Two formats, one file each: ambiguous.
    std::fs::write(empty.path().join("a.pcd"), "x").unwrap();
    std::fs::write(empty.path().join("b.ply"), "x").unwrap();
    let e = list_sweeps(empty.path()).unwrap_err().to_string();
    assert!(e.contains("one format per directory"), "{e}");
}

#[test]
fn pcd_ascii_organised_with_extra_fields_and_viewpoint() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("org.pcd");
    // 2 × 2 organised cloud, a 3-wide normal field before x, NaN = no return,
    // the sensor 1 m up and yawed 90°: stored points are in the cloud frame.
    let s = std::f64::consts::FRAC_1_SQRT_2;
    let text = format!(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS normal x y z rgb\nSIZE 4 4 4 8 4\nTYPE F F F F U\n\
COUNT 3 1 1 1 1\nWIDTH 2\nHEIGHT 2\nVIEWPOINT 0 0 1 {s} 0 0 {s}\nPOINTS 4\nDATA ascii\n\
0 0 1 2 0 1 7\n0 0 1 nan nan nan 0\n0 0 1 0 3 1 5\n0 0 1 1 1 1 5\n"
    );
    std::fs::write(&p, text).unwrap();
    let sw = read_sweep(&p).unwrap();
    let v = sw.prior.expect("non-identity viewpoint is the prior");
    assert_eq!(sw.points.len(), 3);
    // Mapping the sensor-frame points back through the prior gives the file's values.
    let back: Vec<[f64; 3]> = sw
        .points
        .iter()
        .map(|q| {
            let w = v * Point3::new(q[0] as f64, q[1] as f64, q[2] as f64);
            [w.x, w.y, w.z]
        })
        .collect();
    for (b, want) in back
        .iter()
        .zip([[2.0, 0.0, 1.0], [0.0, 3.0, 1.0], [1.0, 1.0, 1.0]])
    {
        for k in 0..3 {
            assert!((b[k] - want[k]).abs() < 1e-6, "{back:?}");
        }
    }
    // (2, 0, 1) in the cloud frame is 2 m to the sensor's right: y = -2.
    assert!((sw.points[0][1] + 2.0).abs() < 1e-6 && sw.points[0][2].abs() < 1e-6);

    // Wrong column count, POINTS vs WIDTH×HEIGHT, missing lines, compressed.
    let hdr = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n";
    let cases = [
        (
            format!("{hdr}POINTS 2\nDATA ascii\n1 2 3\n4 5\n"),
            "line 11",
        ),
        (
            format!("{hdr}POINTS 3\nDATA ascii\n1 2 3\n4 5 6\n"),
            "line 8",
        ),
        (format!("{hdr}POINTS 2\nDATA ascii\n1 2 3\n"), "1 of the 2"),
        (
            format!("{hdr}POINTS 2\nDATA binary_compressed\n"),
            "not supported",
        ),
        (
            format!("{hdr}POINTS 2\nDATA ascii\n1 2 3\n4 5 6\n7 8 9\n"),
            "line 12",
        ),
        (hdr.replace("FIELDS x y z", "FIELDS x y w"), "no 'z'"),
    ];
    for (i, (text, want)) in cases.iter().enumerate() {
        let p = dir.path().join(format!("bad{i}.pcd"));
        let text = if text.contains("DATA") {
            text.clone()
        } else {
            format!("{text}POINTS 2\nDATA ascii\n1 2 3\n4 5 6\n")
        };
        std::fs::write(&p, text).unwrap();
        let e = read_sweep(&p).unwrap_err().to_string();
        assert!(
            e.contains(&format!("bad{i}.pcd")) && e.contains(want),
            "case {i}: {e}"
        );
    }
}

#[test]
fn pcd_binary_with_doubles_and_padding_and_trailing_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = b"VERSION 0.7\nFIELDS _ x y z\nSIZE 2 8 8 8\nTYPE U F F F\nCOUNT 1 1 1 1\n\
WIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n"
        .to_vec();
    let body = b.len();
    for rec in [[1.5f64, -2.0, 3.0], [4.0, 5.0, 6.25]] {
        b.extend_from_slice(&7u16.to_le_bytes());
        for v in rec {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    let p = dir.path().join("d.pcd");
    std::fs::write(&p, &b).unwrap();
    assert_eq!(
        read_sweep(&p).unwrap().points,
        vec![[1.5, -2.0, 3.0], [4.0, 5.0, 6.25]]
    );
    b.extend_from_slice(&[0; 26]);
    std::fs::write(&p, &b).unwrap();
    let e = read_sweep(&p).unwrap_err().to_string();
    assert!(
        e.contains(&format!("byte {}", body + 52)) && e.contains("26 bytes after"),
        "{e}"
    );
}

#[test]
fn threedtk_with_uos_header_gzip_and_no_pose() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scan007.3d.gz");
    std::fs::write(&p, gzip(b"2 x 2\n100 200 300 9\n0 0 0\n\n-50 0 1000\n")).unwrap();
    let s = read_sweep(&p).unwrap();
    assert_eq!(s.prior, None, "no scan007.pose beside it");
    assert_eq!(s.points, vec![[3.0, -1.0, 2.0], [10.0, 0.5, 0.0]]);
    // Now give it a pose: 3DTK yaw of +90° about its up axis (y).
    std::fs::write(dir.path().join("scan007.pose"), "100 0 0\n0 90 0\n").unwrap();
    let s = read_sweep(&p).unwrap();
    let pose = s.prior.unwrap();
    assert_eq!(pose, threedtk_pose([100.0, 0.0, 0.0], [0.0, 90.0, 0.0]));
    // 3DTK: Ry(90°) maps forward (0,0,1) to (1,0,0) = right, so in the
    // right-handed frame forward (1,0,0) goes to right (0,-1,0): yaw -90°.
    let f = pose.rotation * nalgebra::Vector3::new(1.0, 0.0, 0.0);
    assert!((f - nalgebra::Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    assert_eq!(threedtk_point([100.0, 0.0, 0.0]), [0.0, -1.0, 0.0]);
    // A malformed pose names its line.
    std::fs::write(dir.path().join("scan007.pose"), "100 0 0\n0 ninety 0\n").unwrap();
    let e = read_sweep(&p).unwrap_err().to_string();
    assert!(
        e.contains("scan007.pose:line 2") && e.contains("ninety"),
        "{e}"
    );
    std::fs::write(dir.path().join("scan007.pose"), "100 0 0\n").unwrap();
    let e = read_sweep(&p).unwrap_err().to_string();
    assert!(e.contains("found 3 numbers, expected 6"), "{e}");
}

#[test]
fn vtk_errors_name_lines() {
    let dir = tempfile::tempdir().unwrap();
    let head = "# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\n";
    let cases = [
        (
            format!("{head}POINTS 2 float\n1 2 3 4 5\n"),
            "line 6",
            "1 of the 2",
        ),
        (
            format!("{head}POINTS 2 float\n1 2 3\n4 x 6\n"),
            "line 7",
            "'x'",
        ),
        (
            "# vtk DataFile Version 3.0\nt\nBINARY\n".to_string(),
            "line 3",
            "not supported",
        ),
        ("hello\n".to_string(), "line 1", "not a legacy VTK"),
    ];
    for (i, (text, line, why)) in cases.iter().enumerate() {
        let p = dir.path().join(format!("v{i}.vtk"));
        std::fs::write(&p, text).unwrap();
        let e = read_sweep(&p).unwrap_err().to_string();
        assert!(e.contains(line) && e.contains(why), "case {i}: {e}");
    }
    // Several points per line, as VTK allows.
    let p = dir.path().join("multi.vtk");
    std::fs::write(
        &p,
        format!("{head}POINTS 2 double\n1 2 3 4 5 6\nVERTICES 2 4\n1 0\n1 1\n"),
    )
    .unwrap();
    assert_eq!(
        read_sweep(&p).unwrap().points,
        vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    );
}

// ------------------------------------------------------------------- PLY ---

#[derive(Debug, Default, PartialEq)]
struct PlyVertex {
    x: f32,
    y: f32,
    z: f32,
    density: f32,
    hits: u32,
}

impl PropertyAccess for PlyVertex {
    fn new() -> Self {
        Self::default()
    }
    fn set_float(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        match name {
            "x" => self.x = v,
            "y" => self.y = v,
            "z" => self.z = v,
            "density" => self.density = v,
            _ => return PropertyAccessResult::UnsupportedType,
        }
        PropertyAccessResult::Set
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        match name {
            "hits" => self.hits = v,
            _ => return PropertyAccessResult::UnsupportedType,
        }
        PropertyAccessResult::Set
    }
}

fn parse_with_ply_rs(path: &Path) -> ply_rs_bw::ply::Ply<PlyVertex> {
    let mut f = std::fs::File::open(path).unwrap();
    Parser::<PlyVertex>::new().read_ply(&mut f).unwrap()
}

#[test]
fn voxel_ply_parses_back_with_ply_rs_bw() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("map.ply");
    let voxels: Vec<VoxelPoint> = (0..5000u32)
        .map(|i| VoxelPoint {
            position: [
                i as f32 * 0.1 - 3.0,
                (i % 17) as f32 * -0.25,
                1e-3 * i as f32,
            ],
            density: (i as f32).sqrt(),
            hits: i * 7 + 1,
        })
        .collect();
    write_voxel_ply(&path, &voxels).unwrap();
    let ply = parse_with_ply_rs(&path);
    assert_eq!(
        ply.header.encoding,
        ply_rs_bw::ply::Encoding::BinaryLittleEndian
    );
    let el = &ply.header.elements["vertex"];
    assert_eq!(el.count, voxels.len());
    let types: Vec<(&str, &PropertyType)> = el
        .properties
        .iter()
        .map(|(k, p)| (k.as_str(), &p.data_type))
        .collect();
    assert_eq!(
        types,
        [
            ("x", &PropertyType::Scalar(ScalarType::Float)),
            ("y", &PropertyType::Scalar(ScalarType::Float)),
            ("z", &PropertyType::Scalar(ScalarType::Float)),
            ("density", &PropertyType::Scalar(ScalarType::Float)),
            ("hits", &PropertyType::Scalar(ScalarType::UInt)),
        ]
    );
    let got = &ply.payload["vertex"];
    assert_eq!(got.len(), voxels.len());
    for (g, v) in got.iter().zip(&voxels) {
        assert_eq!(
            *g,
            PlyVertex {
                x: v.position[0],
                y: v.position[1],
                z: v.position[2],
                density: v.density,
                hits: v.hits
            }
        );
    }
    // Our reader agrees, and no temporary file is left behind.
    let pts = read_ply_points(&path).unwrap();
    assert_eq!(pts, voxels.iter().map(|v| v.position).collect::<Vec<_>>());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn point_ply_parses_back_with_ply_rs_bw_and_as_a_sweep() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("registered.ply");
    let sweep = read_sweep(&data3d().join("libpointmatcher/cloud.00001.vtk")).unwrap();
    write_points_ply(&path, &sweep.points).unwrap();
    let ply = parse_with_ply_rs(&path);
    let got = &ply.payload["vertex"];
    assert_eq!(got.len(), sweep.points.len());
    assert_eq!(ply.header.elements["vertex"].properties.len(), 3);
    for (g, p) in got.iter().zip(&sweep.points) {
        assert_eq!([g.x, g.y, g.z], *p);
    }
    let again = read_sweep(&path).unwrap();
    assert_eq!(again.points, sweep.points);
    // Overwriting replaces the file whole.
    write_points_ply(&path, &sweep.points[..10]).unwrap();
    assert_eq!(read_ply_points(&path).unwrap().len(), 10);
    // An empty export is a valid PLY with zero vertices; as a sweep it has no points.
    write_points_ply(&path, &[]).unwrap();
    assert!(parse_with_ply_rs(&path).payload["vertex"].is_empty());
    assert!(read_ply_points(&path).unwrap().is_empty());
    let e = read_sweep(&path).unwrap_err().to_string();
    assert!(e.contains("no points"), "{e}");
}

#[test]
fn truncated_ply_export_is_an_error_with_byte_offset() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ply");
    let pts: Vec<[f32; 3]> = (0..100).map(|i| [i as f32, 1.0, 2.0]).collect();
    write_points_ply(&path, &pts).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let body = bytes.len() - 100 * 12;
    std::fs::write(&path, &bytes[..body + 50 * 12 + 7]).unwrap();
    let e = read_ply_points(&path).unwrap_err().to_string();
    assert!(
        e.contains(&format!("byte {}", body + 600)) && e.contains("vertex 50 of 100"),
        "{e}"
    );
}
