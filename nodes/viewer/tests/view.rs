//! The `microstereo-viewer` binary on the bundled recording and on bad input. (Having an
//! integration test also makes `cargo test --workspace` build the binary, which
//! `microstereo run --viewer` and `microstereo view` run.)

use std::path::Path;
use std::process::Command;

fn viewer() -> Command {
    Command::new(env!("CARGO_BIN_EXE_microstereo-viewer"))
}

#[test]
fn a_recording_becomes_an_rrd_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("default.rrd");
    let rec = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/default.mcap");
    let o = viewer()
        .args(["view", rec.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("28 message(s)"), "{err}");
    let b = std::fs::read(&out).unwrap();
    // Two 640×512 frames within the 1.5 MB a 1280×1024 frame may take, scaled to their
    // pixels; the intermediate stages (`--all`) add the label images and disparity maps.
    let budget = 2 * 1_500_000 * (640 * 512) / (1280 * 1024);
    assert!(
        b.starts_with(b"RRF2") && (100_000..=budget).contains(&b.len()),
        "{} bytes",
        b.len()
    );
    let all = dir.path().join("all.rrd");
    let o = viewer()
        .args(["view", rec.to_str().unwrap(), "-o", all.to_str().unwrap()])
        .args(["--stages", "all"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let every = std::fs::metadata(&all).unwrap().len() as usize;
    assert!(every > b.len() + 500_000, "{every} bytes with every stage");
}

#[test]
fn bad_input_is_one_error_and_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"not mcap").unwrap();
    let o = viewer()
        .args([
            "view",
            junk.to_str().unwrap(),
            "-o",
            dir.path().join("x.rrd").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("not an MCAP file") && !err.contains("panicked"),
        "{err}"
    );
    assert!(!dir.path().join("x.rrd").exists());
    // As a graph node it needs the node arguments, and a graph file that exists.
    let o = viewer().arg("--graph").output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--graph needs a value"), "{err}");
    let missing = dir.path().join("none.json");
    let o = viewer()
        .args(["--graph", missing.to_str().unwrap(), "--id", "viewer"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("cannot read the graph file"), "{err}");
}
