//! What running a built-in pipeline can fail with.

use runtime::launch::LaunchErrors;

/// A built-in pipeline's failure, with the field at fault where one is.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A preset's parameters do not pass the launch check: one finding per problem, each
    /// said by its message alone (a preset has no file or line to point at).
    #[error("{}", findings(.0))]
    Invalid(LaunchErrors),
    /// A launch file does not pass the launch check: each finding with its line and fix.
    #[error("{0}\n({n} problem(s) in the launch file)", n = .0.0.len())]
    LaunchFile(LaunchErrors),
    /// A launch file could not be read, or its overrides not applied.
    #[error("{0}")]
    Launch(String),
    /// A node could not be built.
    #[error("{0}")]
    Start(String),
    /// A node failed on a frame (its message names the node and the parameter).
    #[error("{0}")]
    Node(String),
    /// A recording cannot be used as asked (its message says what was read and what to do).
    #[error("{0}")]
    Recording(String),
    /// A run's option out of range (its message names the flag and the range).
    #[error("{0}")]
    Options(String),
    /// A run ended early (its message says why and what was kept).
    #[error("{0}")]
    Stopped(String),
    /// An output that may not be written.
    #[error(transparent)]
    Refused(#[from] formats::outputs::Refused),
    /// The viewer binary could not be run, or was killed.
    #[error("{0}")]
    Viewer(String),
    /// The viewer binary failed and has said why: its exit code.
    #[error("the viewer exited with code {0}")]
    ViewerExit(i32),
    /// A replay would start past the recording's end.
    #[error("--start {start} is past the end of {file}: it holds {span:.2} s")]
    PastTheEnd {
        /// Seconds into the recording asked for.
        start: f64,
        /// The recording.
        file: String,
        /// Seconds it holds.
        span: f64,
    },
    /// A replay was asked to replace a node its graph does not have.
    #[error("--replace {id}: {file} has no node '{id}'")]
    NoSuchNode {
        /// The node asked for.
        id: String,
        /// The launch file.
        file: String,
    },
    /// The source ended before the first frame.
    #[error("the image pair sent no frame")]
    NoFrame,
    /// A command asked for the output of a node its graph does not have.
    #[error("this graph has no such output")]
    NoSuchOutput,
    /// The range selection was given no range.
    #[error("no range to try")]
    NoRange,
    /// A target's pair matched at too few pixels to measure its disparity.
    #[error(
        "'{file}': the target matched at only {pixels} pixels; check the pair and the disparity range {min}..{max}"
    )]
    TooFewMatches {
        /// The left image.
        file: String,
        /// Pixels with a consistent disparity in the central half.
        pixels: usize,
        /// The range's lower end.
        min: i32,
        /// The range's upper end.
        max: i32,
    },
}

/// The findings' messages, one per line, without the node and the "bad params" lead-in.
fn findings(e: &LaunchErrors) -> String {
    let lines: Vec<&str> =
        e.0.iter()
            .map(|e| {
                e.message
                    .split_once(": bad params: ")
                    .map_or(e.message.as_str(), |(_, m)| m)
            })
            .collect();
    lines.join("\n")
}
