//! The bridge under `test-node`: it cannot be compared by its state (that follows the
//! wall clock), so it is checked by what it serves a controller over TCP.

use crate::node::{BridgeNode, BridgeParams};
use node_api::GraphNode;
use runtime::harness::{ExtraCheck, Recorded};
use std::io::BufRead;
use std::time::{Duration, Instant};

/// A bridge built from `params` but listening on a free port (never the production one),
/// with a controller connected, and the check that each frame's served scene line is the
/// frame's targets as given, or on tracks (`connected` holds `tracks`) the frame's tracks
/// by their ids.
pub fn under_test(
    params: &toml::Table,
    connected: &[String],
) -> Result<(Box<dyn GraphNode>, ExtraCheck<'static>), String> {
    let mut params = params.clone();
    params.insert("listen".into(), toml::Value::String("127.0.0.1:0".into()));
    let p: BridgeParams = runtime::registry::parse_params(&params)?;
    let b = BridgeNode::new(&p)?;
    let client = std::net::TcpStream::connect(b.addr)
        .map_err(|e| format!("cannot connect to the bridge: {e}"))?;
    client
        .set_read_timeout(Some(Duration::from_secs(10)))
        .map_err(|e| e.to_string())?;
    let mut served = std::io::BufReader::new(client);
    // The bridge takes controllers on its own thread: wait until it holds this one.
    let t0 = Instant::now();
    while b.controllers() == 0 {
        if t0.elapsed() > Duration::from_secs(10) {
            return Err("the bridge did not take a controller within 10 s".into());
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    let on_tracks = connected.iter().any(|p| p == "tracks");
    let node = node_api::task_node(b, connected);
    let check = Box::new(move |_seq: u64, inputs: &[Recorded]| -> Option<String> {
        let want = &inputs[0].1;
        let mut line = String::new();
        if on_tracks {
            return match served.read_line(&mut line) {
                Ok(_) => tracks_served(want, &line),
                Err(e) => Some(format!("nothing served ({e})")),
            };
        }
        match served.read_line(&mut line) {
            Ok(_)
                if line
                    .trim_end_matches('\n')
                    .strip_prefix("{\"event\":\"scene\",")
                    .is_some_and(|rest| want.get(1..).is_some_and(|w| rest.as_bytes() == w)) =>
            {
                None
            }
            Ok(_) => Some("served a line other than the targets given".into()),
            Err(e) => Some(format!("nothing served ({e})")),
        }
    });
    Ok((node, check))
}

/// Why a scene line served on tracks is not the frame's `tracks` (its JSON), if it is not:
/// the same frame, ids marked as tracks, the same tracks in the same order.
fn tracks_served(tracks: &[u8], line: &str) -> Option<String> {
    let Ok(given) = serde_json::from_slice::<schemas::Tracks>(tracks) else {
        return Some("the recorded input is not a tracks message".into());
    };
    let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else {
        return Some("served a line that is not JSON".into());
    };
    let ids: Vec<u64> = given.tracks.iter().map(|t| u64::from(t.id)).collect();
    let served: Option<Vec<u64>> = v["tracks"]
        .as_array()
        .map(|a| a.iter().filter_map(|t| t["id"].as_u64()).collect());
    if v["event"] != "scene" || v["ids"] != "track" || v["frame"] != given.frame {
        Some(format!(
            "served a line other than frame {}'s scene on tracks",
            given.frame
        ))
    } else if served.as_deref() != Some(&ids[..]) {
        Some(format!("served tracks {served:?}, given {ids:?}"))
    } else {
        None
    }
}
