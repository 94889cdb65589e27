//! The fuzz targets' entry points (`fuzz/`, run with cargo-afl): each takes arbitrary bytes
//! and must return without panicking, whatever they hold. They live here, in the normal
//! build, so that `tests/fuzz_corpus.rs` replays every corpus file and every input a
//! fuzzer ever crashed on through the same code on each test run.

use std::path::{Path, PathBuf};

/// A fuzz target: arbitrary bytes in, no panic whatever they hold.
pub type Target = fn(&[u8]);

/// The targets by name, as `fuzz/` builds them and the corpus folders are named.
pub const TARGETS: [(&str, Target); 6] = [
    ("launch", launch),
    ("calibration", calibration),
    ("pfm", pfm),
    ("image", image),
    ("mcap", mcap),
    ("bridge_line", bridge_line),
];

/// A launch file: parsed, then checked against the built-in node kinds (every error a
/// message, never a panic).
pub fn launch(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(f) = runtime::launch::LaunchFile::parse(Path::new("fuzz.toml"), text) {
        let _ = f.validate(&crate::registry::builtin());
    }
}

/// A calibration in one of the four forms read (the first byte picks): microstereo's TOML
/// or JSON (resolved for a 640×480 image), OpenCV stereo YAML, or a ROS camera_info pair
/// (split at the first NUL); a calibration that reads is rectified and remapped on a small
/// image.
pub fn calibration(data: &[u8]) {
    let Some((&pick, rest)) = data.split_first() else {
        return;
    };
    let Ok(text) = std::str::from_utf8(rest) else {
        return;
    };
    let rect = match pick % 4 {
        0 => {
            if let Ok(f) = toml::from_str::<calibration::file::CalibrationFile>(text) {
                let _ = f.resolve(640, 480, "fuzz");
            }
            return;
        }
        1 => {
            if let Ok(f) = serde_json::from_str::<calibration::file::CalibrationFile>(text) {
                let _ = f.resolve(640, 480, "fuzz");
            }
            return;
        }
        2 => calibration::stereo::StereoCalibration::from_opencv_yaml(text)
            .map(|c| calibration::stereo::Rectification::bouguet(&c)),
        _ => {
            let (l, r) = text.split_once('\0').unwrap_or((text, ""));
            calibration::stereo::Rectification::from_camera_info(l, r)
        }
    };
    if let Ok(rect) = rect.map(calibration::stereo::Rectifier::from) {
        let img =
            schemas::Plane::from_vec(16, 12, (0..192).map(|i| i as u8).collect()).expect("size");
        for right in [false, true] {
            let _ = rectify::RemapLut::new(&rect, right, 16, 12).apply(&img);
        }
    }
}

/// A PFM disparity map.
pub fn pfm(data: &[u8]) {
    with_file(data, "pfm", |p| {
        let _ = formats::read_disparity(p, None, "fuzz");
    });
}

/// An image file (PNG, JPEG, TIFF …) as the capture and `reconstruct` load it.
pub fn image(data: &[u8]) {
    with_file(data, "png", |p| {
        let _ = capture::image::load(p, "fuzz");
    });
}

/// A recording: its overview, every edge message, and the frames of its edges.
pub fn mcap(data: &[u8]) {
    with_file(data, "mcap", |p| {
        let Ok(o) = recorder::overview(p) else {
            return;
        };
        if let Ok(r) = recorder::EdgeReader::open(p, None) {
            for m in r.take(10_000) {
                if m.is_err() {
                    break;
                }
            }
        }
        let mut edges: Vec<String> = o.channels.iter().filter_map(|c| c.edge.clone()).collect();
        edges.sort();
        edges.dedup();
        if !edges.is_empty()
            && let Ok(f) = recorder::FrameReader::open(p, edges)
        {
            for m in f.take(10_000) {
                if m.is_err() {
                    break;
                }
            }
        }
    });
}

/// What one controller connection sends the bridge: lines cut at a small limit, each
/// parsed as a command and echoed back shortened, as the bridge does.
pub fn bridge_line(data: &[u8]) {
    use manipulator_bridge::protocol::{Line, parse_command, read_line, shorten};
    let mut r = std::io::BufReader::with_capacity(64, data);
    for _ in 0..10_000 {
        match read_line(&mut r, 4096) {
            Ok(Line::Text(t)) => {
                if let Err(e) = parse_command(&t) {
                    let _ = shorten(&e, 200);
                }
                let _ = shorten(&t, 200);
            }
            Ok(Line::NotUtf8) => {}
            Ok(Line::TooLong | Line::End) | Err(_) => return,
        }
    }
}

/// Runs `f` on `data` written to a file of this process (in memory where /dev/shm is):
/// the readers take paths.
fn with_file(data: &[u8], ext: &str, f: impl FnOnce(&Path)) {
    let dir = if Path::new("/dev/shm").is_dir() {
        PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    let p = dir.join(format!("microstereo-fuzz-{}.{ext}", std::process::id()));
    if std::fs::write(&p, data).is_ok() {
        f(&p);
    }
    let _ = std::fs::remove_file(&p);
}
