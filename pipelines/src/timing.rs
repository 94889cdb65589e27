//! The stereo graph timed node by node over a stream of frames (`microstereo bench`).

use crate::Error;
use crate::stereo::{Stereo, ids};
use matcher::Mode;
use schemas::{DisparityRange, DisparityTiles};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// One pair through one matcher: the median time of each node and of the whole graph.
#[derive(Clone, Debug, Serialize)]
pub struct BenchLine {
    /// The pair's name.
    pub pair: String,
    /// The matcher.
    pub mode: Mode,
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// The disparity range searched.
    pub range: DisparityRange,
    /// Each node after the source, with its median step time in ms.
    pub stages_ms: Vec<(String, f64)>,
    /// The median of the frames' summed step times, ms.
    pub total_ms: f64,
    /// The matcher's disparity evaluations per second, in millions.
    pub mevals_per_s: f64,
}

impl BenchLine {
    /// The line `microstereo bench` prints for it.
    pub fn summary(&self) -> String {
        let st: Vec<String> = self
            .stages_ms
            .iter()
            .map(|(n, v)| format!("{n} {v:.1}"))
            .collect();
        format!(
            "{:<10} {:<8} {:>4}×{:<4} total {:>7.1} ms  [{}]  {:.0} M disparity evaluations/s",
            self.pair,
            format!("{:?}", self.mode).to_lowercase(),
            self.width,
            self.height,
            self.total_ms,
            st.join(", "),
            self.mevals_per_s
        )
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Whole-frame matching of `left` and `right` over `range` by `mode` (with `paths` SGM
/// paths where given), `repeat` frames through one graph (as a live graph keeps its buffers
/// from frame to frame); the medians over those frames.
pub fn bench_pair(
    name: &str,
    (left, right): (&Path, &Path),
    mode: Mode,
    range: DisparityRange,
    repeat: usize,
    paths: Option<u8>,
) -> Result<BenchLine, Error> {
    let mut preset = Stereo {
        frames: repeat as u64,
        ..Stereo::whole_frame(left.to_path_buf(), right.to_path_buf(), mode, range)
    };
    if let Some(p) = paths {
        preset.matching.paths = p;
    }
    let (_, mut run) = preset.start()?;
    let matched = preset.outs().matched;
    let mut runs: Vec<Vec<(String, f64)>> = Vec::new();
    let (mut evals, mut size) = (0, (0, 0));
    while let Some(f) = run.step().map_err(Error::Node)? {
        let tiles: DisparityTiles = f.read(&matched).map_err(Error::Node)?;
        evals = tiles.evaluations();
        size = (tiles.width, tiles.height);
        runs.push(f.ms.into_iter().filter(|(n, _)| n != ids::PAIR).collect());
    }
    let first = runs.first().ok_or(Error::NoFrame)?;
    let stages: Vec<(String, f64)> = first
        .iter()
        .enumerate()
        .map(|(i, (n, _))| (n.clone(), median(runs.iter().map(|r| r[i].1).collect())))
        .collect();
    let total = median(runs.iter().map(|r| r.iter().map(|s| s.1).sum()).collect());
    let match_ms = stages
        .iter()
        .find(|(n, _)| n == ids::MATCH)
        .map_or(total, |s| s.1);
    Ok(BenchLine {
        pair: name.to_string(),
        mode,
        width: size.0,
        height: size.1,
        range,
        stages_ms: stages,
        total_ms: total,
        mevals_per_s: evals as f64 / (match_ms * 1e3),
    })
}

/// [`bench_pair`] for each of `pairs` (name, left, right) through the paper's matcher, then
/// the quality one; `on_line` sees each line as it is measured.
pub fn bench_pairs(
    pairs: &[(String, PathBuf, PathBuf)],
    range: DisparityRange,
    repeat: usize,
    paths: Option<u8>,
    mut on_line: impl FnMut(&BenchLine),
) -> Result<Vec<BenchLine>, Error> {
    let mut lines = Vec::new();
    for (name, left, right) in pairs {
        for mode in [Mode::Paper, Mode::Quality] {
            let line = bench_pair(name, (left, right), mode, range, repeat, paths)?;
            on_line(&line);
            lines.push(line);
        }
    }
    Ok(lines)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summary_is_the_printed_line() {
        let line = BenchLine {
            pair: "cones".into(),
            mode: Mode::Quality,
            width: 450,
            height: 375,
            range: DisparityRange::new(0, 63),
            stages_ms: vec![("match".into(), 11.54), ("validate".into(), 1.8)],
            total_ms: 15.66,
            mevals_per_s: 940.6,
        };
        assert_eq!(
            line.summary(),
            "cones      quality   450×375  total    15.7 ms  [match 11.5, validate 1.8]  941 M disparity evaluations/s"
        );
    }

    #[test]
    fn median_takes_the_middle_run() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0]), 4.0);
    }
}
