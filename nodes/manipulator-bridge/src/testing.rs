//! The bridge under `test-node`: it cannot be compared by its state (that follows the
//! wall clock), so it is checked by what it serves a controller over TCP.

use crate::node::{BridgeNode, BridgeParams};
use runtime::harness::{ExtraCheck, Recorded};
use runtime::node::GraphNode;
use std::io::BufRead;
use std::time::{Duration, Instant};

/// A bridge built from `params` but listening on a free port (never the production one),
/// with a controller connected, and the check that each frame's served scene line is the
/// frame's targets as given.
pub fn under_test(
    params: &toml::Table,
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
    let node = runtime::node::task_node(b, &["targets".to_string()]);
    let check = Box::new(move |_seq: u64, inputs: &[Recorded]| -> Option<String> {
        let want = &inputs[0].1;
        let mut line = String::new();
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
