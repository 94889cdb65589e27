//! The one error type of the commands: printed once, exit code 2 (1 for a check that
//! found a difference).

use formats::IoError;

/// A command failure.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// A file problem.
    #[error(transparent)]
    Io(#[from] IoError),
    /// A folder of chessboard pairs that gave no calibration (`calibrate-stereo`).
    #[error(transparent)]
    Pairs(#[from] calibration::pairs::PairsError),
    /// Anything else, already phrased for the user.
    #[error("{0}")]
    Other(String),
    /// A check ran and found a difference (exit code 1, not 2).
    #[error("{0}")]
    Failed(String),
    /// A child program failed and has said why already: exit with its code, print nothing.
    #[error("exit code {0}")]
    Reported(i32),
}

impl From<&str> for CliError {
    fn from(s: &str) -> Self {
        CliError::Other(s.into())
    }
}

impl From<String> for CliError {
    fn from(s: String) -> Self {
        CliError::Other(s)
    }
}
