//! Runtime of microstereo: the [`Node`] trait and stage timing.
//!
//! A node is one processing step with its parameters held inside it (configuration comes
//! from the launch file or the CLI, never from code). The same node value runs in-process
//! (tests, one-shot commands such as `microstereo reconstruct`) and, once the process graph
//! lands, inside a node process behind the shared-memory transport.

pub mod hop;
pub mod launch;
pub mod process;
pub mod step;
pub mod transport;

use serde::Serialize;
use std::time::Instant;

/// One processing step of the graph.
pub trait Node {
    /// What one step consumes.
    type Input<'a>;
    /// What one step produces.
    type Output;
    /// Why a step can fail.
    type Error: std::error::Error;

    /// The node kind as written in launch files (`match-lr`, `validate`, …).
    fn kind(&self) -> &'static str;

    /// Runs one step.
    fn process(&mut self, input: Self::Input<'_>) -> Result<Self::Output, Self::Error>;
}

/// Wall-clock time spent per named stage, in insertion order.
#[derive(Clone, Debug, Default, Serialize)]
pub struct StageTimes {
    /// `(stage, milliseconds)` pairs.
    pub stages: Vec<(String, f64)>,
}

impl StageTimes {
    /// Runs `f`, records its duration under `name`, and returns its result.
    pub fn time<T>(&mut self, name: &str, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let out = f();
        self.add(name, start.elapsed().as_secs_f64() * 1e3);
        out
    }

    /// Adds `ms` to stage `name` (accumulates when the stage repeats).
    pub fn add(&mut self, name: &str, ms: f64) {
        if let Some(slot) = self.stages.iter_mut().find(|(n, _)| n == name) {
            slot.1 += ms;
        } else {
            self.stages.push((name.to_string(), ms));
        }
    }

    /// Sum over all stages, in milliseconds.
    pub fn total_ms(&self) -> f64 {
        self.stages.iter().map(|(_, ms)| ms).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repeated_stages_accumulate_in_order() {
        let mut t = StageTimes::default();
        t.add("a", 1.5);
        t.add("b", 2.0);
        t.add("a", 0.5);
        assert_eq!(t.stages, vec![("a".into(), 2.0), ("b".into(), 2.0)]);
        assert_eq!(t.total_ms(), 4.0);
        let v = t.time("c", || 7);
        assert_eq!(v, 7);
        assert_eq!(t.stages.len(), 3);
    }
}
