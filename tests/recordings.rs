//! Every node on the bundled recording: fed its recorded inputs, it must send exactly the
//! recorded outputs (recordings/default.mcap, made by recordings/make.sh).

use pipelines::recording::test_node;
use runtime::harness::NodeCheck;
use std::path::{Path, PathBuf};

fn bundled() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/default.mcap")
}

/// Frames in the bundled recording.
const FRAMES: u64 = 2;

fn check(node: &str, outputs: &[&str]) -> NodeCheck {
    let c = test_node(&bundled(), None, node, 0.0).unwrap_or_else(|e| panic!("{node}: {e}"));
    let edges: Vec<&str> = c.outputs.iter().map(|o| o.edge.as_str()).collect();
    assert_eq!(edges, outputs, "{node}");
    assert_eq!((c.frames, c.incomplete), (FRAMES, 0), "{node}: {c:?}");
    for o in &c.outputs {
        assert_eq!(
            (o.compared, o.identical),
            (FRAMES, FRAMES),
            "{node} {}: {:?}",
            o.edge,
            o.first_difference
        );
    }
    assert!(c.passed());
    c
}

#[test]
fn capture_renders_the_recorded_frames() {
    check("capture", &["capture/frame"]);
}

#[test]
fn rectify_reproduces_its_recorded_output() {
    check("rectify", &["rectify/frame"]);
}

#[test]
fn segment_reproduces_labels_and_cells() {
    check("segment", &["segment/labels", "segment/cells"]);
}

#[test]
fn the_matcher_reproduces_both_directions_tiles() {
    check("match", &["match/left", "match/right"]);
}

#[test]
fn validate_reproduces_both_checked_directions() {
    check("validate", &["validate/left", "validate/right"]);
}

#[test]
fn postprocess_reproduces_the_final_map() {
    check("postprocess", &["postprocess/disparity"]);
}

#[test]
fn triangulate_reproduces_the_cloud_and_the_targets() {
    check(
        "triangulate",
        &[
            "triangulate/cloud",
            "triangulate/targets",
            "triangulate/disparity",
        ],
    );
}

#[test]
fn the_track_node_reproduces_the_recorded_tracks() {
    check("track", &["track/tracks"]);
}

#[test]
fn the_bridge_serves_the_recorded_tracks_over_tcp() {
    check("manipulator-bridge", &["TCP lines"]);
}

#[test]
fn a_changed_parameter_is_caught_as_a_difference() {
    // The same recording against a launch file whose post-processing differs: the check
    // must fail, with the frame and the value that differ.
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/default.toml"),
    )
    .unwrap()
    .replace(
        "id = \"postprocess\"\nkind = \"postprocess\"\n",
        "id = \"postprocess\"\nkind = \"postprocess\"\nparams = { median_radius = 0 }\n",
    );
    assert!(text.contains("median_radius = 0"));
    let launch = dir.path().join("changed.toml");
    std::fs::write(&launch, text).unwrap();
    let c = test_node(&bundled(), Some(&launch), "postprocess", 0.0).unwrap();
    assert!(!c.passed());
    let o = &c.outputs[0];
    assert_eq!((o.compared, o.identical), (FRAMES, 0));
    assert!(o.max_diff > 0.0);
    let d = o.first_difference.as_deref().unwrap();
    assert!(d.starts_with("frame 0: value "), "{d}");
    // A tolerance for float noise does not hide it: the difference is whole pixels.
    let c = test_node(&bundled(), Some(&launch), "postprocess", 1e-3).unwrap();
    assert!(!c.passed());
}

#[test]
fn test_node_refuses_a_recording_without_the_nodes_edges() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("only-frames.mcap");
    let mut w = recorder::RecordingWriter::create(&path, false).unwrap();
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/default.toml"),
    )
    .unwrap();
    w.write_launch(Path::new("default.toml"), &text).unwrap();
    for m in recorder::EdgeReader::open(&bundled(), Some(vec!["rectify/frame".into()])).unwrap() {
        let m = m.unwrap();
        w.write(&m.edge, m.kind, &m.header, &m.payload, m.log_time)
            .unwrap();
    }
    w.finish().unwrap();
    let e = test_node(&path, None, "segment", 0.0)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no channel for edge 'segment/labels'") && e.contains("it holds: rectify/frame"),
        "{e}"
    );
    let e = test_node(&path, None, "nope", 0.0).unwrap_err().to_string();
    assert!(
        e.contains("no node 'nope'") && e.contains("capture, rectify"),
        "{e}"
    );
}

/// A bit flipped inside a compressed chunk is caught by the chunk's CRC: `inspect` reports
/// the chunk, lists the rest and exits 2 (issue 19 #8).
#[test]
fn a_corrupt_chunk_is_reported() {
    let mut d = std::fs::read(bundled()).unwrap();
    // Records after the 8-byte magic: opcode (1 byte), length (u64 LE), body. A chunk
    // (0x06) holds start, end, size (3 × u64), its CRC (u32), the compression's name (u32
    // length + bytes), the records' length (u64), then the compressed records.
    let mut at = 8;
    let chunk = loop {
        let op = d[at];
        let len = u64::from_le_bytes(d[at + 1..at + 9].try_into().unwrap()) as usize;
        if op == 0x06 {
            break at + 9;
        }
        at += 9 + len;
        assert!(at < d.len(), "no chunk in the bundled recording");
    };
    let name_len = u32::from_le_bytes(d[chunk + 28..chunk + 32].try_into().unwrap()) as usize;
    let records = chunk + 32 + name_len + 8;
    let records_len = u64::from_le_bytes(d[records - 8..records].try_into().unwrap()) as usize;
    // Two bytes of the compressed records: one flipped bit can land where the decoder
    // never looks (the exact middle of the recording made in December 2026 did).
    d[records + records_len / 3] ^= 0x10;
    d[records + 2 * records_len / 3] ^= 0x10;
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.mcap");
    std::fs::write(&bad, &d).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_microstereo"))
        .args(["inspect", bad.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    // Where the flipped bit lands decides which check sees it first: the chunk's CRC over
    // the decompressed records, or the decompression itself. Either way the chunk is named
    // by its place, skipped, and the rest is listed.
    assert!(
        err.contains(&format!("the chunk at byte {} is damaged", chunk - 9)),
        "{err}"
    );
    assert!(err.contains("bad.mcap"), "{err}");
    assert!(err.contains("the figures above are the rest"), "{err}");
    // Later chunks are read in full, their channels typed even where the damaged chunk
    // declared their schema (the summary repeats it).
    let listed = String::from_utf8_lossy(&out.stdout);
    assert!(listed.contains("/triangulate/targets"), "{listed}");
    for line in listed.lines().filter(|l| l.starts_with("  /")) {
        assert!(line.contains("msg/"), "untyped channel: {line}");
    }
}

/// A recording of the default graph (tracks between triangulate and the bridge), made now
/// on a small scene: the track node reproduces every recorded frame's tracks exactly, and
/// the bridge on tracks serves each frame's tracks.
#[test]
fn the_track_node_and_the_bridge_on_tracks_reproduce_a_recording_of_the_default_graph() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("launch.toml"))
        .unwrap()
        .replace(
            "width = 1280, height = 1024, cells = 10, seed = 1, repeat = 30, fps = 30 }",
            "width = 320, height = 256, cells = 4, seed = 1, repeat = 30 }",
        )
        .replace("127.0.0.1:7878", "127.0.0.1:0");
    assert!(text.contains("cells = 4") && text.contains("127.0.0.1:0"));
    let launch = dir.path().join("default.toml");
    std::fs::write(&launch, text).unwrap();
    let rec = dir.path().join("default.mcap");
    let instance = format!("tracksrec{}", std::process::id());
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_microstereo"))
        .args([
            "run",
            "--quiet",
            "--instance",
            &instance,
            "--frames",
            "12",
            "--record",
        ])
        .arg(&rec)
        .arg(&launch)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let c = test_node(&rec, None, "track", 0.0).unwrap();
    assert_eq!(c.outputs.len(), 1);
    let o = &c.outputs[0];
    assert_eq!(o.edge, "track/tracks");
    assert!(o.compared >= 3, "{c:?}");
    assert_eq!(o.identical, o.compared, "{:?}", o.first_difference);
    assert!(c.passed());
    let c = test_node(&rec, None, "manipulator-bridge", 0.0).unwrap();
    let o = &c.outputs[0];
    assert_eq!(o.edge, "TCP lines");
    assert!(o.compared >= 3, "{c:?}");
    assert!(c.passed(), "{:?}", o.first_difference);
}
