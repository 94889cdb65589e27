//! What can go wrong watching a run: each message is what the user reads after `error:`.

use runtime::transport::TransportError;

/// A failure of `top` or `topic`.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// No run was named and none runs on this machine.
    #[error(
        "no graph is running on this machine: start one with `microstereo run` (or name a run on another host with --instance)"
    )]
    NoRun,
    /// The run's status service could not be opened or read (already phrased by runtime).
    #[error("{0}")]
    Status(String),
    /// The run was found but sent no first snapshot in time.
    #[error("run '{instance}' published no status within {secs} s: is it still running?")]
    NoStatus {
        /// The run attached to.
        instance: String,
        /// How long it was waited for, in seconds.
        secs: u64,
    },
    /// The run's status stopped coming while `top` printed tables.
    #[error("run '{0}' stopped publishing its status")]
    StoppedPublishing(String),
    /// A refresh interval outside 0.05..3600 seconds.
    #[error("{flag} {seconds} is out of range: use 0.05..3600 seconds")]
    Interval {
        /// The flag that gave it.
        flag: &'static str,
        /// The seconds given.
        seconds: f64,
    },
    /// `--count 0`.
    #[error("--count 0 would print nothing: give at least 1")]
    ZeroCount,
    /// The run has no edge of that name.
    #[error("run '{instance}' has no edge '{edge}': its edges are {known}")]
    NoEdge {
        /// The run attached to.
        instance: String,
        /// The edge asked for.
        edge: String,
        /// The run's edges, comma-separated.
        known: String,
    },
    /// Watching the edge failed.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// The live view could not draw.
    #[error("cannot draw on the terminal: {0}")]
    Draw(#[source] std::io::Error),
    /// The live view could not read the keys.
    #[error("cannot read the terminal: {0}")]
    ReadTerminal(#[source] std::io::Error),
}
