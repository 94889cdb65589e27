//! Fusing one cell's per-frame heights: uncertainty-weighted, robust to frames that lie
//! (a pipette over the cell), quick to follow a real change, honest about what repeated
//! frames cannot average away.

/// One frame's measurement of a cell's height and volume.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// Frame number.
    pub frame: u64,
    /// Height above the substrate.
    pub height: f64,
    /// Its stated standard error.
    pub std: f64,
    /// Whether the frame's own checks trusted it.
    pub trusted: bool,
    /// Volume between the surface and the substrate.
    pub volume: f64,
}

/// What the frames of a track say together.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fused {
    /// Fused height.
    pub height: f64,
    /// Its standard error: the frames' noise averaged, the share they have in common not.
    pub std: f64,
    /// Fused volume.
    pub volume: f64,
    /// Its standard error.
    pub volume_std: f64,
    /// Frames used (outliers left out).
    pub used: u32,
    /// Of them, trusted by their own frame.
    pub trusted_used: u32,
}

/// Share of a single frame's stated error that every frame of the same scene shares (the
/// model's error: a shape the top fit does not describe, the substrate under the cell), so
/// that no number of frames averages it away.
pub const SHARED_ERROR: f64 = 0.35;

/// How many times its stated error (with the shared part) a frame may lie from the
/// others' median before it is left out.
const OUTLIER_SIGMAS: f64 = 3.0;

/// Weight of a frame its own checks doubted, against a trusted one of the same error.
const DOUBTFUL_WEIGHT: f64 = 1.0 / 9.0;

/// The median of `v` (not empty); sorts it.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Fuses the observations (oldest first); `None` without any usable one.
///
/// Frames lying more than three of their errors from the median of all are left out;
/// the rest are averaged with weights 1/σ² (a doubtful frame a ninth of that). The
/// stated error is the larger of the weighted mean's and the scatter's, plus the part
/// every frame shares ([`SHARED_ERROR`] of the median frame's own error).
pub fn fuse_heights(obs: &[Observation]) -> Option<Fused> {
    let usable: Vec<&Observation> = obs
        .iter()
        .filter(|o| o.height.is_finite() && o.std.is_finite() && o.std > 0.0)
        .collect();
    if usable.is_empty() {
        return None;
    }
    let mid = median(&mut usable.iter().map(|o| o.height).collect::<Vec<_>>());
    let typical = median(&mut usable.iter().map(|o| o.std).collect::<Vec<_>>());
    let spread = 1.4826
        * median(
            &mut usable
                .iter()
                .map(|o| (o.height - mid).abs())
                .collect::<Vec<_>>(),
        );
    let kept: Vec<&&Observation> = usable
        .iter()
        .filter(|o| {
            let s = o.std.hypot(spread).max(typical * 0.5);
            (o.height - mid).abs() <= OUTLIER_SIGMAS * s
        })
        .collect();
    // At least the median frame stays: the filter above keeps every frame within its
    // error of the median, and the median lies within the frames.
    let kept = if kept.is_empty() {
        usable.iter().collect()
    } else {
        kept
    };
    let w = |o: &Observation| {
        let base = 1.0 / (o.std * o.std);
        if o.trusted {
            base
        } else {
            base * DOUBTFUL_WEIGHT
        }
    };
    let sw: f64 = kept.iter().map(|o| w(o)).sum();
    let height = kept.iter().map(|o| w(o) * o.height).sum::<f64>() / sw;
    let volume = kept.iter().map(|o| w(o) * o.volume).sum::<f64>() / sw;
    let n = kept.len() as f64;
    let mean_err2 = 1.0 / sw;
    let scatter2 = if kept.len() > 1 {
        kept.iter()
            .map(|o| w(o) * (o.height - height).powi(2))
            .sum::<f64>()
            / sw
            / (n - 1.0)
    } else {
        0.0
    };
    let shared = SHARED_ERROR * median(&mut kept.iter().map(|o| o.std).collect::<Vec<_>>());
    let std = (mean_err2.max(scatter2) + shared * shared).sqrt();
    let rel = if height > 0.0 { std / height } else { 1.0 };
    Some(Fused {
        height,
        std,
        volume,
        volume_std: volume.abs() * rel,
        used: kept.len() as u32,
        trusted_used: kept.iter().filter(|o| o.trusted).count() as u32,
    })
}

/// Where a real change (a cell pushed, injected, dividing) began: the index of the first
/// of the last `frames` usable observations when all of them lie on one side of what the
/// earlier ones say, beyond three errors; `None` when nothing changed.
pub fn change_point(obs: &[Observation], frames: usize) -> Option<usize> {
    if frames == 0 || obs.len() < frames + 2 {
        return None;
    }
    let split = obs.len() - frames;
    let before = fuse_heights(&obs[..split])?;
    let recent = &obs[split..];
    let side = |o: &Observation| {
        let s = o.std.hypot(before.std);
        if o.height > before.height + OUTLIER_SIGMAS * s {
            1
        } else if o.height < before.height - OUTLIER_SIGMAS * s {
            -1
        } else {
            0
        }
    };
    let first = side(&recent[0]);
    (first != 0 && recent.iter().all(|o| side(o) == first)).then_some(split)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ob(frame: u64, height: f64, std: f64) -> Observation {
        Observation {
            frame,
            height,
            std,
            trusted: true,
            volume: height * 100.0,
        }
    }

    #[test]
    fn equal_frames_average_and_their_error_shrinks_to_the_shared_part() {
        let one = fuse_heights(&[ob(0, 10.0, 0.4)]).unwrap();
        assert!((one.height - 10.0).abs() < 1e-12);
        // One frame: its own error and the shared part together.
        assert!((one.std - (0.16f64 + (0.35 * 0.4f64).powi(2)).sqrt()).abs() < 1e-12);
        let many: Vec<_> = (0..16)
            .map(|i| ob(i, 10.0 + if i % 2 == 0 { 0.2 } else { -0.2 }, 0.4))
            .collect();
        let f = fuse_heights(&many).unwrap();
        assert!((f.height - 10.0).abs() < 1e-12);
        assert_eq!(f.used, 16);
        // sqrt(max(0.4²/16, scatter²/16) + (0.35·0.4)²)
        let scatter2 = 16.0 * 0.04 / 16.0 / 15.0;
        let expect = ((0.16f64 / 16.0).max(scatter2) + 0.14f64 * 0.14).sqrt();
        assert!((f.std - expect).abs() < 1e-12, "{} {}", f.std, expect);
        assert!(f.std < one.std);
    }

    #[test]
    fn a_frame_that_lies_is_left_out() {
        let mut v: Vec<_> = (0..9).map(|i| ob(i, 12.0, 0.3)).collect();
        // The pipette over the cell: its top read 30 % higher.
        v.push(ob(9, 15.6, 0.3));
        let f = fuse_heights(&v).unwrap();
        assert!((f.height - 12.0).abs() < 1e-9, "{}", f.height);
        assert_eq!(f.used, 9);
    }

    #[test]
    fn doubtful_frames_weigh_less_and_unusable_ones_nothing() {
        let mut d = ob(1, 14.0, 1.0);
        d.trusted = false;
        let f = fuse_heights(&[ob(0, 13.0, 1.0), d, ob(2, f64::NAN, 1.0)]).unwrap();
        // (13 + 14/9) / (1 + 1/9)
        assert!((f.height - (13.0 + 14.0 / 9.0) / (10.0 / 9.0)).abs() < 1e-12);
        assert_eq!((f.used, f.trusted_used), (2, 1));
        assert!(fuse_heights(&[ob(0, f64::NAN, 1.0)]).is_none());
        assert!(fuse_heights(&[]).is_none());
    }

    #[test]
    fn a_real_change_is_found_after_its_frames_and_noise_is_not() {
        let mut v: Vec<_> = (0..10)
            .map(|i| ob(i, 10.0 + 0.1 * ((i % 3) as f64 - 1.0), 0.3))
            .collect();
        assert_eq!(change_point(&v, 3), None);
        v.push(ob(10, 13.0, 0.3));
        v.push(ob(11, 13.1, 0.3));
        assert_eq!(change_point(&v, 3), None, "two frames are not yet a change");
        v.push(ob(12, 12.9, 0.3));
        assert_eq!(change_point(&v, 3), Some(10));
        // One wild frame among them is no change.
        let mut w: Vec<_> = (0..10).map(|i| ob(i, 10.0, 0.3)).collect();
        w.extend([ob(10, 13.0, 0.3), ob(11, 10.1, 0.3), ob(12, 13.0, 0.3)]);
        assert_eq!(change_point(&w, 3), None);
    }
}
