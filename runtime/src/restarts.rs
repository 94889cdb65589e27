//! What a joining node does when a node upstream of it was restarted.
//!
//! A node that dies takes the frames it held with it. Downstream, a node that joins inputs
//! by frame number then waits for those frames on the inputs that came through the dead
//! node, while it holds their partners from the other inputs; on lossless edges their
//! writers wait for it in turn, the restarted node is starved of input, and the graph
//! stands still. So a restarted node first sends a restart marker on each of its outputs
//! ([`crate::transport::EdgePublisher::send_restart`]). Until every input of a node that
//! comes through the restarted node has delivered a frame after its marker, the node lets
//! the oldest held frame of any input go at the borrow limit instead of making the writer
//! wait, and it passes the marker on once every such input has delivered it. A frame
//! that one input has passed over (it delivered a later one) is let go on the others
//! ([`crate::process`]'s join): those are the frames lost with the killed node.

use crate::launch::{Graph, NodeSpec};

/// One restart seen on this node's inputs.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Restart {
    generation: u64,
    node: String,
    /// The joined inputs that come through the restarted node.
    through: Vec<bool>,
    /// Those that delivered its marker.
    marked: Vec<bool>,
    /// Those that delivered a frame after its marker.
    fresh: Vec<bool>,
    /// The marker went on to this node's outputs.
    passed_on: bool,
}

/// The restarts a node's joined inputs have seen and not yet got over.
#[derive(Clone, Debug)]
pub struct Restarts {
    /// For each joined input, the nodes upstream of it (its writer included).
    upstream: Vec<Vec<String>>,
    open: Vec<Restart>,
}

impl Restarts {
    /// For node `spec` of `graph`, whose first `joined` inputs are joined by frame.
    pub fn new(graph: &Graph, spec: &NodeSpec, joined: usize) -> Self {
        let upstream = spec
            .inputs
            .iter()
            .take(joined)
            .map(|i| upstream_of(graph, &i.node))
            .collect();
        Self {
            upstream,
            open: Vec::new(),
        }
    }

    /// Whether a restart upstream is not yet got over: held frames give way at the borrow
    /// limit.
    pub fn active(&self) -> bool {
        self.open.iter().any(|r| r.fresh.iter().any(|f| !f))
    }

    /// Input `i` delivered a frame.
    pub fn frame(&mut self, i: usize) {
        for r in &mut self.open {
            if r.marked[i] {
                r.fresh[i] = true;
            }
        }
        self.close();
    }

    /// Input `i` delivered the marker of restart `generation` of `node`; returns the markers
    /// to pass on to this node's outputs now.
    pub fn marker(&mut self, i: usize, generation: u64, node: &str) -> Vec<(u64, String)> {
        let n = self.upstream.len();
        if i >= n {
            return Vec::new();
        }
        let r = match self.open.iter().position(|r| r.generation == generation) {
            Some(k) => &mut self.open[k],
            None => {
                let mut through: Vec<bool> = self
                    .upstream
                    .iter()
                    .map(|u| u.iter().any(|x| x == node))
                    .collect();
                // The marker came this way, whatever the graph says.
                through[i] = true;
                self.open.push(Restart {
                    generation,
                    node: node.to_string(),
                    fresh: through.iter().map(|t| !t).collect(),
                    marked: through.iter().map(|t| !t).collect(),
                    through,
                    passed_on: false,
                });
                self.open.last_mut().expect("just pushed")
            }
        };
        r.through[i] = true;
        r.marked[i] = true;
        r.fresh[i] = false;
        let mut out = Vec::new();
        if !r.passed_on && r.marked.iter().all(|m| *m) {
            r.passed_on = true;
            out.push((r.generation, r.node.clone()));
        }
        self.close();
        out
    }

    fn close(&mut self) {
        self.open
            .retain(|r| !(r.passed_on && r.fresh.iter().all(|f| *f)));
    }
}

/// Node `id` and every node upstream of it over joined inputs.
fn upstream_of(graph: &Graph, id: &str) -> Vec<String> {
    let mut seen = vec![id.to_string()];
    let mut k = 0;
    while k < seen.len() {
        if let Some(n) = graph.node(&seen[k]) {
            for i in n.inputs.iter().filter(|i| !i.feedback) {
                if !seen.contains(&i.node) {
                    seen.push(i.node.clone());
                }
            }
        }
        k += 1;
    }
    seen
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(id: &str, inputs: &[(&str, &str)]) -> NodeSpec {
        NodeSpec {
            id: id.into(),
            runner: crate::launch::Runner::Builtin(id.into()),
            inputs: inputs
                .iter()
                .map(|(port, from)| {
                    let (node, output) = from.split_once('/').unwrap();
                    crate::launch::Input {
                        port: port.to_string(),
                        node: node.into(),
                        output: output.into(),
                        edge: Default::default(),
                        feedback: false,
                    }
                })
                .collect(),
            outputs: Vec::new(),
            params: Default::default(),
            restart: Default::default(),
            tap: false,
            logs: false,
            in_flight: None,
            host: None,
        }
    }

    /// capture → (segment, match); validate ← match; triangulate ← (capture, segment,
    /// validate).
    fn graph() -> Graph {
        Graph {
            file: "test.toml".into(),
            text: String::new(),
            hosts: Default::default(),
            nodes: vec![
                node("capture", &[]),
                node("segment", &[("frame", "capture/frame")]),
                node(
                    "match",
                    &[("frame", "capture/frame"), ("cells", "segment/cells")],
                ),
                node(
                    "validate",
                    &[("left", "match/left"), ("right", "match/right")],
                ),
                node(
                    "triangulate",
                    &[
                        ("frame", "capture/frame"),
                        ("labels", "segment/labels"),
                        ("cells", "segment/cells"),
                        ("disparity", "validate/left"),
                        ("checked", "validate/left"),
                    ],
                ),
            ],
        }
    }

    #[test]
    fn a_restart_is_got_over_once_every_input_through_it_delivers_after_its_marker() {
        let g = graph();
        let spec = g.node("triangulate").unwrap();
        let mut r = Restarts::new(&g, spec, spec.inputs.len());
        assert!(!r.active());
        // match restarted: disparity and checked come through it, the rest do not.
        assert_eq!(r.marker(3, 1, "match"), vec![]);
        assert!(r.active());
        r.frame(0);
        r.frame(3);
        assert!(r.active(), "checked has not delivered the marker yet");
        assert_eq!(r.marker(4, 1, "match"), vec![(1, "match".to_string())]);
        assert!(r.active(), "checked has no frame after the marker yet");
        r.frame(4);
        assert!(!r.active());
    }

    #[test]
    fn a_marker_on_an_input_the_graph_does_not_lead_through_the_node_still_counts() {
        let g = graph();
        let spec = g.node("validate").unwrap();
        let mut r = Restarts::new(&g, spec, spec.inputs.len());
        // Both inputs come from match; a restart of capture reaches both.
        assert_eq!(r.marker(0, 2, "capture"), vec![]);
        r.frame(0);
        assert!(r.active());
        assert_eq!(r.marker(1, 2, "capture"), vec![(2, "capture".to_string())]);
        r.frame(1);
        assert!(!r.active());
        // An unknown node's marker makes its own input the only one through it: passed on
        // at once, got over with that input's next frame.
        assert_eq!(
            r.marker(1, 3, "elsewhere"),
            vec![(3, "elsewhere".to_string())]
        );
        assert!(r.active());
        r.frame(0);
        assert!(r.active());
        r.frame(1);
        assert!(!r.active());
    }

    #[test]
    fn two_restarts_are_followed_apart() {
        let g = graph();
        let spec = g.node("triangulate").unwrap();
        let mut r = Restarts::new(&g, spec, spec.inputs.len());
        // segment restarted (labels, cells and, through match, disparity and checked), then
        // validate (disparity and checked only).
        for i in [1, 2] {
            assert_eq!(r.marker(i, 1, "segment"), vec![]);
        }
        assert_eq!(r.marker(3, 2, "validate"), vec![]);
        assert_eq!(
            r.marker(4, 2, "validate"),
            vec![(2, "validate".to_string())]
        );
        for i in 0..5 {
            r.frame(i);
        }
        assert!(r.active(), "segment's marker has not come through validate");
        assert_eq!(r.marker(3, 1, "segment"), vec![]);
        assert_eq!(r.marker(4, 1, "segment"), vec![(1, "segment".to_string())]);
        r.frame(3);
        assert!(r.active());
        r.frame(4);
        assert!(!r.active());
    }
}
