//! A z-stack: pairs of a target at known stage heights, as `calibrate-depth` reads them.

use std::path::{Path, PathBuf};

/// The pairs `(left, right, z µm)` of the z-stack in `dir`: the rows of its
/// `heights.csv` (`left,right,z_um`), or else its `left_z<Z>um.<ext>` files and their
/// `right_z<Z>um.<ext>` partners, in order of height.
pub fn read_stack(dir: &Path) -> Result<Vec<(PathBuf, PathBuf, f64)>, String> {
    let csv = dir.join("heights.csv");
    if !dir.is_dir() {
        return Err(format!(
            "z-stack directory '{}' does not exist",
            dir.display()
        ));
    }
    let mut out = Vec::new();
    if csv.exists() {
        let text = std::fs::read_to_string(&csv)
            .map_err(|e| format!("'{}' cannot be read: {e}", csv.display()))?;
        for (i, line) in text.lines().enumerate().skip(1) {
            if line.trim().is_empty() {
                continue;
            }
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            let z = (f.len() == 3)
                .then(|| f[2].parse::<f64>().ok())
                .flatten()
                .filter(|z| z.is_finite());
            let Some(z) = z else {
                return Err(format!(
                    "{}:{}: expected 'left,right,z_um' with z a number, got '{line}'",
                    csv.display(),
                    i + 1
                ));
            };
            out.push((dir.join(f[0]), dir.join(f[1]), z));
        }
    } else {
        let entries = std::fs::read_dir(dir)
            .map_err(|e| format!("'{}' cannot be listed: {e}", dir.display()))?;
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            let Some(rest) = name.strip_prefix("left_z") else {
                continue;
            };
            let Some((zs, ext)) = rest.rsplit_once('.') else {
                continue;
            };
            if let Ok(z) = zs.trim_end_matches("um").parse::<f64>() {
                out.push((e.path(), dir.join(format!("right_z{zs}.{ext}")), z));
            }
        }
        out.sort_by(|a, b| a.2.total_cmp(&b.2));
    }
    Ok(out)
}
