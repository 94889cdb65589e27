//! What a command is about to write, checked before any work: no input is ever
//! overwritten, and no earlier output without `--overwrite`. The files themselves are
//! written whole or not at all ([`crate::atomic`]).

use std::path::{Path, PathBuf};

/// Why a command may not write one of its outputs; `elsewhere` says how to choose others.
#[derive(Debug, thiserror::Error)]
pub enum Refused {
    /// The output is one of the command's inputs.
    #[error("input '{}' would be overwritten by the output '{}': {elsewhere}", .input.display(), .output.display())]
    Input {
        /// The input, as given.
        input: PathBuf,
        /// The output at the same place.
        output: PathBuf,
        /// How to choose other outputs.
        elsewhere: String,
    },
    /// The output is a directory.
    #[error("output '{}' is a directory: {elsewhere}", .output.display())]
    Directory {
        /// The output.
        output: PathBuf,
        /// How to choose other outputs.
        elsewhere: String,
    },
    /// The output exists and replacing was not asked for.
    #[error("output '{}' exists (from an earlier run?): add --overwrite to replace it, or {elsewhere}", .output.display())]
    Exists {
        /// The output.
        output: PathBuf,
        /// How to choose other outputs.
        elsewhere: String,
    },
}

/// Refuses `files` (the outputs a command will write) when one of them is one of `inputs`
/// (always, `--overwrite` or not) or exists and `overwrite` is false. `elsewhere` says how
/// to choose other outputs ("give -o another directory").
pub fn check(
    files: &[PathBuf],
    inputs: &[&Path],
    overwrite: bool,
    elsewhere: &str,
) -> Result<(), Refused> {
    let inputs: Vec<(&Path, PathBuf)> = inputs
        .iter()
        .filter_map(|i| std::fs::canonicalize(i).ok().map(|c| (*i, c)))
        .collect();
    for f in files {
        let canonical = std::fs::canonicalize(f).ok();
        if let Some((input, _)) = inputs.iter().find(|(_, c)| Some(c) == canonical.as_ref()) {
            return Err(Refused::Input {
                input: input.to_path_buf(),
                output: f.clone(),
                elsewhere: elsewhere.into(),
            });
        }
        if f.is_dir() {
            return Err(Refused::Directory {
                output: f.clone(),
                elsewhere: elsewhere.into(),
            });
        }
        if !overwrite && f.exists() {
            return Err(Refused::Exists {
                output: f.clone(),
                elsewhere: elsewhere.into(),
            });
        }
    }
    Ok(())
}

/// The files `names` in `dir`.
pub fn in_dir(dir: &Path, names: impl IntoIterator<Item = impl AsRef<str>>) -> Vec<PathBuf> {
    names.into_iter().map(|n| dir.join(n.as_ref())).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inputs_are_refused_always_and_outputs_without_overwrite() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("left.png");
        std::fs::write(&input, "x").unwrap();
        let earlier = dir.path().join("cells.json");
        std::fs::write(&earlier, "{}").unwrap();
        let fresh = dir.path().join("new.json");
        let e = check(
            std::slice::from_ref(&input),
            &[&input],
            true,
            "give -o another directory",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("input") && e.contains("would be overwritten"),
            "{e}"
        );
        // The same file by another spelling.
        let other = dir.path().join(".").join("left.png");
        assert!(check(&[other], &[&input], true, "-").is_err());
        let e = check(
            std::slice::from_ref(&earlier),
            &[&input],
            false,
            "give -o another directory",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("exists") && e.contains("--overwrite"), "{e}");
        check(&[earlier, fresh.clone()], &[&input], true, "-").unwrap();
        check(&[fresh], &[&input], false, "-").unwrap();
        assert!(check(&[dir.path().to_path_buf()], &[], true, "-").is_err());
    }
}
