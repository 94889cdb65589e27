//! Stereo matching for microstereo: rectified grey pair in, disparity maps out.
//!
//! Two modes share one input contract ([`check_inputs`]) and one sign convention (left
//! pixel `x` with disparity `d` matches right pixel `x − d`; negative `d` is allowed):
//!
//! - [`paper`]: the published method, exactly — bit-packed support values ([`sv`]) pick
//!   the top-k candidates, NCC + SV/SVmax decides, row constraints (uniqueness, ordering,
//!   continuity). Integer disparities, both directions from one shared cost slab.
//! - [`quality`]: our own design on the same kind of costs — census + gradient cost,
//!   semi-global aggregation over 4 (default) or 8 paths, uniqueness ratio, sub-pixel
//!   parabola. It returns both a left- and a right-based map so the same validation and
//!   post-processing apply.
//!
//! The crate is a pure library: no I/O, no CLI. Validation (LR check) and post-processing
//! live in the `validate` and `postprocess` crates.

// Inner loops walk several arrays with one index (costs, sums, outputs); iterator
// chains over four zipped slices would hide the arithmetic.
#![allow(clippy::needless_range_loop)]

pub mod node;
pub mod paper;
pub mod quality;
pub mod sv;

pub use paper::{Directions, PaperMatch, PaperParams, match_paper};
pub use quality::{QualityParams, QualityWorkspace, match_quality, match_quality_in};
pub use sv::{SvKernel, Weights};

use schemas::{DisparityRange, Plane};
use serde::{Deserialize, Serialize};

/// Which matcher to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Mode {
    /// Semi-global census matcher (default).
    #[default]
    Quality,
    /// The published support-value matcher.
    Paper,
}

/// Why a pair cannot be matched with the given parameters.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum InputError {
    /// Left and right differ in size.
    #[error(
        "left image is {lw}×{lh} but right image is {rw}×{rh}; a rectified pair must have the same size"
    )]
    SizeMismatch {
        /// Left width.
        lw: usize,
        /// Left height.
        lh: usize,
        /// Right width.
        rw: usize,
        /// Right height.
        rh: usize,
    },
    /// An image has no pixels.
    #[error("the images are empty ({w}×{h})")]
    Empty {
        /// Width.
        w: usize,
        /// Height.
        h: usize,
    },
    /// min ≥ max.
    #[error(
        "disparity range {min}..{max} is empty: --min-disparity must be smaller than --max-disparity"
    )]
    EmptyRange {
        /// Requested minimum.
        min: i32,
        /// Requested maximum.
        max: i32,
    },
    /// The range asks for shifts as large as the image.
    #[error(
        "disparity range {min}..{max} is wider than the image ({width} px): every |d| must be below the width"
    )]
    RangeTooWide {
        /// Requested minimum.
        min: i32,
        /// Requested maximum.
        max: i32,
        /// Image width.
        width: usize,
    },
    /// Window side is even or out of bounds.
    #[error("window {window} is not allowed: use an odd size between 3 and 31")]
    BadWindow {
        /// Requested window.
        window: usize,
    },
    /// Window larger than the image.
    #[error("window {window} does not fit a {w}×{h} image; use a smaller --window")]
    WindowTooLarge {
        /// Requested window.
        window: usize,
        /// Width.
        w: usize,
        /// Height.
        h: usize,
    },
}

/// Checks a pair, a range and a window (`None`: the matcher has none) before matching;
/// the matchers assume these hold.
pub fn check_inputs<T>(
    left: &Plane<T>,
    right: &Plane<T>,
    range: DisparityRange,
    window: Option<usize>,
) -> Result<(), InputError> {
    if left.width != right.width || left.height != right.height {
        return Err(InputError::SizeMismatch {
            lw: left.width,
            lh: left.height,
            rw: right.width,
            rh: right.height,
        });
    }
    if left.is_empty() {
        return Err(InputError::Empty {
            w: left.width,
            h: left.height,
        });
    }
    if range.min >= range.max {
        return Err(InputError::EmptyRange {
            min: range.min,
            max: range.max,
        });
    }
    let width = left.width;
    if range.min.unsigned_abs() as usize >= width || range.max.unsigned_abs() as usize >= width {
        return Err(InputError::RangeTooWide {
            min: range.min,
            max: range.max,
            width,
        });
    }
    let Some(window) = window else {
        return Ok(());
    };
    if window.is_multiple_of(2) || !(sv::MIN_WINDOW..=sv::MAX_WINDOW).contains(&window) {
        return Err(InputError::BadWindow { window });
    }
    if window > left.width || window > left.height {
        return Err(InputError::WindowTooLarge {
            window,
            w: left.width,
            h: left.height,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_inputs_are_named() {
        let a = Plane::filled(40, 30, 0u8);
        let b = Plane::filled(41, 30, 0u8);
        let r = DisparityRange::new(0, 10);
        assert!(matches!(
            check_inputs(&a, &b, r, Some(5)),
            Err(InputError::SizeMismatch { .. })
        ));
        assert!(matches!(
            check_inputs(&a, &a, DisparityRange::new(5, 5), Some(5)),
            Err(InputError::EmptyRange { .. })
        ));
        assert!(matches!(
            check_inputs(&a, &a, DisparityRange::new(-40, 3), Some(5)),
            Err(InputError::RangeTooWide { .. })
        ));
        assert_eq!(
            check_inputs(&a, &a, r, Some(4)),
            Err(InputError::BadWindow { window: 4 })
        );
        assert_eq!(
            check_inputs(&a, &a, r, Some(33)),
            Err(InputError::BadWindow { window: 33 })
        );
        assert!(matches!(
            check_inputs(&a, &a, r, Some(31)),
            Err(InputError::WindowTooLarge { .. })
        ));
        assert_eq!(check_inputs(&a, &a, r, Some(13)), Ok(()));
        // No window (quality mode): a 2-row image is fine.
        let thin = Plane::filled(40, 2, 0u8);
        assert_eq!(check_inputs(&thin, &thin, r, None), Ok(()));
        let e = Plane::filled(0, 0, 0u8);
        assert!(matches!(
            check_inputs(&e, &e, r, Some(3)),
            Err(InputError::Empty { .. })
        ));
    }
}
