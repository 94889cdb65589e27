//! Mask clean-up: hole filling, small-blob removal, opening and closing.

use crate::label::{Connectivity, label, label_where};
use image::GrayImage;
use imageproc::distance_transform::Norm;
use schemas::{Mask, Plane};

/// Sets every background pixel that is not 4-connected to the image border (a hole in an
/// 8-connected foreground) to foreground.
pub fn fill_holes(mask: &Mask) -> Mask {
    let (bg, n) = label_where(mask, |&v| v == 0, Connectivity::Four);
    let (w, h) = (mask.width, mask.height);
    let mut outside = vec![false; n as usize + 1];
    for x in 0..w {
        outside[*bg.get(x, 0) as usize] = true;
        outside[*bg.get(x, h - 1) as usize] = true;
    }
    for y in 0..h {
        outside[*bg.get(0, y) as usize] = true;
        outside[*bg.get(w - 1, y) as usize] = true;
    }
    let data = mask
        .data
        .iter()
        .zip(&bg.data)
        .map(|(&m, &l)| {
            if m != 0 || !outside[l as usize] {
                255
            } else {
                0
            }
        })
        .collect();
    Plane::from_vec(w, h, data).expect("same size")
}

/// Drops 8-connected blobs of fewer than `min_area` pixels.
pub fn remove_small(mask: &Mask, min_area: usize) -> Mask {
    let (labels, n) = label(mask, Connectivity::Eight);
    let mut area = vec![0usize; n as usize + 1];
    for &l in &labels.data {
        area[l as usize] += 1;
    }
    let data = labels
        .data
        .iter()
        .map(|&l| {
            if l != 0 && area[l as usize] >= min_area {
                255
            } else {
                0
            }
        })
        .collect();
    Plane::from_vec(mask.width, mask.height, data).expect("same size")
}

/// Applies an imageproc binary morphology operation with a disc of `radius` (0 = none).
fn disc_op(mask: &Mask, radius: u8, op: fn(&GrayImage, Norm, u8) -> GrayImage) -> Mask {
    if radius == 0 {
        return mask.clone();
    }
    let g = GrayImage::from_raw(mask.width as u32, mask.height as u32, mask.data.clone())
        .expect("size");
    Plane::from_vec(mask.width, mask.height, op(&g, Norm::L2, radius).into_raw()).expect("size")
}

/// Morphological opening with a disc of `radius` (removes specks and thin spurs).
pub fn open(mask: &Mask, radius: u8) -> Mask {
    disc_op(mask, radius, imageproc::morphology::open)
}

/// Morphological closing with a disc of `radius` (bridges small gaps in a cell's outline).
pub fn close(mask: &Mask, radius: u8) -> Mask {
    disc_op(mask, radius, imageproc::morphology::close)
}

/// Dilates with a disc of `radius`.
pub fn dilate(mask: &Mask, radius: u8) -> Mask {
    disc_op(mask, radius, imageproc::morphology::dilate)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::mask;

    #[test]
    fn holes_fill_but_bays_open_to_the_border_stay() {
        let m = mask(&["#####.", "#..#..", "#####.", "#.#...", "#.#..."]);
        let f = fill_holes(&m);
        assert_eq!(f, mask(&["#####.", "####..", "#####.", "#.#...", "#.#..."]));
    }

    #[test]
    fn diagonal_gap_does_not_let_a_hole_leak() {
        // The centre touches the outside only through a corner: a hole for 8-connected cells.
        let m = mask(&["##.", "#.#", ".##"]);
        assert_eq!(fill_holes(&m), mask(&["##.", "###", ".##"]));
    }

    #[test]
    fn small_blobs_go_large_stay() {
        let m = mask(&["##....", "##..#.", "......", "###..."]);
        assert_eq!(
            remove_small(&m, 3),
            mask(&["##....", "##....", "......", "###..."])
        );
    }

    #[test]
    fn opening_removes_a_speck_closing_fills_a_pinhole() {
        let mut m = Plane::filled(20, 20, 0u8);
        for y in 5..15 {
            for x in 5..15 {
                *m.get_mut(x, y) = 255;
            }
        }
        *m.get_mut(1, 1) = 255;
        let o = open(&m, 1);
        assert_eq!(*o.get(1, 1), 0);
        assert_eq!(*o.get(10, 10), 255);
        *m.get_mut(10, 10) = 0;
        let c = close(&m, 1);
        assert_eq!(*c.get(10, 10), 255);
        assert_eq!(*c.get(10, 4), 0);
    }
}
