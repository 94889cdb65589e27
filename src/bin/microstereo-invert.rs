//! An example of a custom node (an `exec` node in a launch file): it inverts the grey levels
//! of each stereo frame. The whole protocol — arguments, shared memory, statistics — is
//! `microstereo::graph::exec_main`; a custom node only says what one step does.
//!
//! ```toml
//! [[node]]
//! id = "invert"
//! exec = "target/release/microstereo-invert"
//! inputs = { frame = "capture/frame" }
//! ports = { inputs = { frame = "stereo-frame" }, outputs = { frame = "stereo-frame" } }
//! ```

use runtime::step::{GraphNode, Msg, Outputs};

struct Invert;

impl GraphNode for Invert {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let m = &inputs[0];
        out.send(0, m.header, m.payload.len(), &mut |b| {
            for (o, i) in b.iter_mut().zip(m.payload) {
                *o = 255 - i;
            }
        })
    }
}

fn main() {
    std::process::exit(microstereo::graph::exec_main(|_spec| Ok(Box::new(Invert))));
}
