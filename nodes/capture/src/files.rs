//! Image pairs on disk as a frame source.

use runtime::process::now_ns;
use runtime::step::{GraphNode, Outputs, params, send_planes};
use schemas::{MessageKind, Plane};
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
        params(t)
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
}

fn load(p: &Path) -> Result<Plane<u8>, String> {
    let img = image::open(p)
        .map_err(|e| format!("cannot read '{}': {e}", p.display()))?
        .to_luma8();
    let (w, h) = img.dimensions();
    Ok(Plane::from_vec(w as usize, h as usize, img.into_raw()).expect("size"))
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
        })
    }
}

impl GraphNode for FileCapture {
    fn produce(&mut self, seq: u64, out: &mut dyn Outputs) -> Result<bool, String> {
        let n = self.pairs.len() as u64;
        if seq >= n && !self.repeat {
            return Ok(false);
        }
        let (lp, rp) = &self.pairs[(seq % n) as usize];
        let (l, r) = (load(lp)?, load(rp)?);
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
        send_planes(out, 0, MessageKind::StereoFrame, (seq, now_ns()), &[&l, &r])?;
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use runtime::step::Collected;
    use schemas::wire::read_planes;

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
        let mut out = Collected::default();
        for seq in 0..3 {
            assert!(cap.produce(seq, &mut out).unwrap());
        }
        assert!(
            !cap.produce(3, &mut out).unwrap(),
            "three pairs, then the end"
        );
        for (i, (h, b)) in out.ports[0].iter().enumerate() {
            assert_eq!(h.sequence, i as u64);
            let v = read_planes::<u8>(h, b).unwrap();
            assert_eq!(
                (v[0].data[0], v[1].data[0]),
                (10 * i as u8, 10 * i as u8 + 1)
            );
        }
        let mut looped = FileCapture::new(p(true)).unwrap();
        let mut out = Collected::default();
        assert!(looped.produce(4, &mut out).unwrap());
        let v = read_planes::<u8>(&out.ports[0][0].0, &out.ports[0][0].1).unwrap();
        assert_eq!(v[0].data[0], 10, "frame 4 of a 3-pair loop is pair 1");
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
