//! The `microstereo_msgs` package (ros/microstereo_msgs) is what the recorder writes: each
//! `.msg` file is the definition of its type in the recorder's schemas, and in the schemas
//! that the bundled recording holds.

use recorder::ros2::{
    CELL, CELL_ARRAY, CELL3, DISPARITY_TILES, MANIPULATOR_STATE, MsgType, TARGETS, TRACKS,
};
use std::collections::BTreeMap;
use std::path::PathBuf;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The `microstereo_msgs` types a schema's text defines (its own and those appended after
/// `=` lines, as rosbag2 writes them), each as its lines without comments or blanks.
fn ours(name: &str, text: &str) -> BTreeMap<String, Vec<String>> {
    let mut out = BTreeMap::new();
    let mut current = name.replace("/msg/", "/");
    let mut lines = Vec::new();
    let mut done = |n: &str, l: &mut Vec<String>| {
        if let Some(short) = n.strip_prefix("microstereo_msgs/") {
            out.insert(short.to_string(), std::mem::take(l));
        }
        l.clear();
    };
    for line in text.lines() {
        if line.starts_with("==") {
            done(&current, &mut lines);
        } else if let Some(n) = line.strip_prefix("MSG: ") {
            current = n.trim().to_string();
        } else {
            let l = line.split('#').next().unwrap().trim();
            if !l.is_empty() {
                lines.push(l.to_string());
            }
        }
    }
    done(&current, &mut lines);
    out
}

#[test]
fn the_msg_files_are_the_recorded_definitions() {
    let types: [MsgType; 7] = [
        CELL,
        CELL_ARRAY,
        CELL3,
        TARGETS,
        TRACKS,
        DISPARITY_TILES,
        MANIPULATOR_STATE,
    ];
    let mut defined = BTreeMap::new();
    for t in types {
        for (name, body) in ours(t.name, t.definition) {
            // A type nested in two messages is defined the same in both.
            if let Some(other) = defined.insert(name.clone(), body.clone()) {
                assert_eq!(other, body, "{name} in {}", t.name);
            }
        }
    }
    let dir = root().join("ros/microstereo_msgs/msg");
    let mut files = BTreeMap::new();
    for e in std::fs::read_dir(&dir).unwrap() {
        let path = e.unwrap().path();
        let name = path.file_stem().unwrap().to_string_lossy().into_owned();
        let text = std::fs::read_to_string(&path).unwrap();
        let parsed = ours(&format!("microstereo_msgs/msg/{name}"), &text);
        files.insert(name.clone(), parsed[&name].clone());
    }
    assert_eq!(
        files.keys().collect::<Vec<_>>(),
        defined.keys().collect::<Vec<_>>(),
        "one .msg file per type"
    );
    for (name, body) in &defined {
        assert_eq!(&files[name], body, "{name}.msg");
    }
    assert!(defined.len() >= 11, "{:?}", defined.keys());
    // The bundled recording holds the same definitions.
    let bytes = std::fs::read(root().join("recordings/default.mcap")).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let mut seen = 0;
    for s in summary.schemas.values() {
        for (name, body) in ours(&s.name, &String::from_utf8_lossy(&s.data)) {
            assert_eq!(&defined[&name], &body, "{name} in the recording");
            seen += 1;
        }
    }
    assert!(seen >= 11, "{seen} definitions in the recording");
}
