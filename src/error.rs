//! The one error type of the commands: printed once, exit code 2 (1 for a check that
//! found a difference).

use formats::IoError;

/// A command failure.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// A file problem.
    #[error(transparent)]
    Io(#[from] IoError),
    /// An output the command may not write.
    #[error(transparent)]
    Refused(#[from] formats::outputs::Refused),
    /// A folder of chessboard pairs that gave no calibration (`calibrate-stereo`).
    #[error(transparent)]
    Pairs(#[from] calibration::pairs::PairsError),
    /// A `synth` request that makes no scene.
    #[error(transparent)]
    Synth(#[from] synth::request::RequestError),
    /// A truth mask that cannot score the image (`segment`).
    #[error(transparent)]
    Truth(#[from] segment::report::TruthError),
    /// A map that is not the size of its ground truth (`eval`).
    #[error(transparent)]
    EvalSize(#[from] validate::eval::SizeError),
    /// Anything else, already phrased for the user.
    #[error("{0}")]
    Other(String),
    /// A check ran and found a difference (exit code 1, not 2).
    #[error("{0}")]
    Failed(String),
    /// A built-in pipeline failed.
    #[error(transparent)]
    Pipeline(#[from] pipelines::Error),
    /// `top` or `topic` could not watch the run.
    #[error(transparent)]
    Monitor(#[from] monitor::Error),
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

impl CliError {
    /// A pipeline's error in the terms of a command line: each parameter its nodes name is
    /// named by its flag (`flags`: parameter, flag).
    pub fn with_flags(e: pipelines::Error, flags: &[(&str, &str)]) -> CliError {
        match e {
            pipelines::Error::Invalid(_) | pipelines::Error::Node(_) => {
                CliError::Other(in_flag_terms(&e.to_string(), flags))
            }
            e => CliError::Pipeline(e),
        }
    }
}

/// A node's message in the terms of a command line: `node 'x': bad params: ` dropped and
/// each parameter named by its flag.
pub fn in_flag_terms(message: &str, flags: &[(&str, &str)]) -> String {
    let m = message
        .split_once(": bad params: ")
        .map_or(message, |(_, m)| m);
    let mut out = String::with_capacity(m.len());
    let mut word = String::new();
    let flush = |word: &mut String, out: &mut String| {
        match flags.iter().find(|(p, _)| *p == word) {
            Some((_, f)) => out.push_str(f),
            None => out.push_str(word),
        }
        word.clear();
    };
    for c in m.chars() {
        if c.is_ascii_alphanumeric() || c == '_' {
            word.push(c);
        } else {
            flush(&mut word, &mut out);
            out.push(c);
        }
    }
    flush(&mut word, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameters_are_named_by_their_flags() {
        let flags = [("window", "--window"), ("min_disparity", "--min-disparity")];
        assert_eq!(
            in_flag_terms(
                "node 'match': bad params: window 12 is not allowed; min_disparity_x window",
                &flags
            ),
            "--window 12 is not allowed; min_disparity_x --window"
        );
    }
}
