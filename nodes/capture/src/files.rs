//! Image pairs on disk as a frame source.

use schemas::StereoFrame;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// `params` of a `capture` node with `source = "files"`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileParams {
    /// `files`.
    pub source: String,
    /// Left images: a path whose file name may hold `*` and `?`.
    pub left: String,
    /// Right images, the same way; paired with the left ones in sorted order.
    pub right: String,
    /// Start again after the last pair.
    #[serde(default)]
    pub repeat: bool,
    /// Frames per second (as fast as possible without it).
    #[serde(default)]
    pub fps: Option<f64>,
}

impl FileParams {
    /// Reads a `params` table.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        runtime::registry::from_table(t)
    }
}

/// Whether `name` matches `pat` (`*` any run, `?` any one character).
fn matches(pat: &[char], name: &[char]) -> bool {
    match (pat.first(), name.first()) {
        (None, None) => true,
        (Some('*'), _) => {
            matches(&pat[1..], name) || (!name.is_empty() && matches(pat, &name[1..]))
        }
        (Some('?'), Some(_)) => matches(&pat[1..], &name[1..]),
        (Some(p), Some(n)) if p == n => matches(&pat[1..], &name[1..]),
        _ => false,
    }
}

/// The files a pattern names, sorted.
pub fn expand(pattern: &str) -> Result<Vec<PathBuf>, String> {
    let path = Path::new(pattern);
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let pat: Vec<char> = path
        .file_name()
        .ok_or_else(|| format!("'{pattern}' names no file"))?
        .to_string_lossy()
        .chars()
        .collect();
    let entries =
        std::fs::read_dir(dir).map_err(|e| format!("cannot list '{}': {e}", dir.display()))?;
    let mut out: Vec<PathBuf> = entries
        .filter_map(|e| e.ok())
        .filter(|e| {
            let n: Vec<char> = e.file_name().to_string_lossy().chars().collect();
            matches(&pat, &n)
        })
        .map(|e| e.path())
        .collect();
    out.sort();
    Ok(out)
}

/// Sends stored pairs one per step.
#[derive(Debug)]
pub struct FileCapture {
    pairs: Vec<(PathBuf, PathBuf)>,
    repeat: bool,
    /// Unpaced, the next pair is read while the graph works on this one (as a camera's
    /// frame is ready when it is asked for): decoding two PNGs of 1280×1024 took 16 ms of
    /// each frame's turn at the entrance, where the graph waited on it.
    read_ahead: bool,
    /// The pair being read ahead: its frame number and the reader.
    ahead: Option<(u64, std::thread::JoinHandle<Result<StereoFrame, String>>)>,
}

impl FileCapture {
    /// Lists the pairs; none, or unequal counts, is an error that says which pattern.
    pub fn new(p: FileParams) -> Result<Self, String> {
        let (l, r) = (expand(&p.left)?, expand(&p.right)?);
        if l.is_empty() || l.len() != r.len() {
            return Err(format!(
                "left '{}' names {} file(s) and right '{}' {}; they must name the same number, at least one",
                p.left,
                l.len(),
                p.right,
                r.len()
            ));
        }
        Ok(Self {
            pairs: l.into_iter().zip(r).collect(),
            repeat: p.repeat,
            read_ahead: p.fps.is_none(),
            ahead: None,
        })
    }
}

impl FileCapture {
    /// Frame `seq`'s pair (`None` after the last when not repeating).
    pub fn frame(&mut self, seq: u64) -> Result<Option<StereoFrame>, String> {
        let n = self.pairs.len() as u64;
        if seq >= n && !self.repeat {
            return Ok(None);
        }
        let frame = match self.ahead.take() {
            Some((s, reader)) if s == seq => reader
                .join()
                .map_err(|_| "the reader of the next pair panicked".to_string())?,
            // Another frame was read ahead (a paced source skips frames): it is let go.
            _ => {
                let (lp, rp) = &self.pairs[(seq % n) as usize];
                read_pair(lp, rp)
            }
        }?;
        let next = seq + 1;
        if self.read_ahead && (next < n || self.repeat) {
            let (lp, rp) = self.pairs[(next % n) as usize].clone();
            self.ahead = Some((next, std::thread::spawn(move || read_pair(&lp, &rp))));
        }
        Ok(Some(frame))
    }
}

/// Reads and checks one pair.
fn read_pair(lp: &Path, rp: &Path) -> Result<StereoFrame, String> {
    let (l, r) = (
        crate::image::load(lp, "left image")?.grey,
        crate::image::load(rp, "right image")?.grey,
    );
    if (l.width, l.height) != (r.width, r.height) {
        return Err(format!(
            "'{}' is {}×{} but '{}' is {}×{}; a pair must have one size",
            lp.display(),
            l.width,
            l.height,
            rp.display(),
            r.width,
            r.height
        ));
    }
    Ok(StereoFrame { left: l, right: r })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_pick_sorted_pairs_and_the_source_sends_them_in_order() {
        let dir = tempfile::tempdir().unwrap();
        for i in 0..3u8 {
            for side in ["left", "right"] {
                let v = if side == "left" { 10 * i } else { 10 * i + 1 };
                image::GrayImage::from_pixel(4, 3, image::Luma([v]))
                    .save(dir.path().join(format!("{side}_{i}.png")))
                    .unwrap();
            }
        }
        std::fs::write(dir.path().join("left_notes.txt"), "x").unwrap();
        let d = dir.path().display();
        let p = |repeat| FileParams {
            source: "files".into(),
            left: format!("{d}/left_?.png"),
            right: format!("{d}/right_*.png"),
            repeat,
            fps: None,
        };
        let mut cap = FileCapture::new(p(false)).unwrap();
        assert!(cap.read_ahead, "unpaced, the next pair is read ahead");
        for i in 0..3u8 {
            let f = cap.frame(i as u64).unwrap().unwrap();
            assert_eq!((f.left.data[0], f.right.data[0]), (10 * i, 10 * i + 1));
        }
        assert!(cap.frame(3).unwrap().is_none(), "three pairs, then the end");
        // Frames asked out of turn (a paced source skips some) are still their own pairs,
        // read ahead or not.
        for read_ahead in [true, false] {
            let mut cap = FileCapture::new(p(true)).unwrap();
            cap.read_ahead = read_ahead;
            for i in [0u64, 2, 3, 5, 4, 4] {
                let f = cap.frame(i).unwrap().unwrap();
                let k = (i % 3) as u8;
                assert_eq!((f.left.data[0], f.right.data[0]), (10 * k, 10 * k + 1));
            }
        }
        let mut looped = FileCapture::new(p(true)).unwrap();
        let f = looped.frame(4).unwrap().unwrap();
        assert_eq!(f.left.data[0], 10, "frame 4 of a 3-pair loop is pair 1");
        // A pair that cannot be read is that frame's error, read ahead or not, and the
        // frames before it arrive.
        std::fs::write(dir.path().join("left_2.png"), "not a png").unwrap();
        let mut cap = FileCapture::new(p(false)).unwrap();
        assert!(cap.frame(0).unwrap().is_some() && cap.frame(1).unwrap().is_some());
        let e = cap.frame(2).unwrap_err();
        assert!(e.contains("left_2.png"), "{e}");
        let bad = FileParams {
            right: format!("{d}/nothing_*.png"),
            ..p(false)
        };
        let e = FileCapture::new(bad).unwrap_err();
        assert!(
            e.contains("names 3 file(s)") && e.contains("nothing_*.png' 0"),
            "{e}"
        );
    }
}
