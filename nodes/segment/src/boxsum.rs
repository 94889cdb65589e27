//! Summed-area tables: sums over any axis-aligned window in O(1) after one O(n) pass.

/// An integer a [`BoxSums`] table adds, with wrap-around: a window's sum comes out exact
/// whenever it fits the type (the wrapped differences come back to it), whatever the whole
/// grid's sum, so a `u32` table serves where windows are small (half the memory of `u64`).
pub trait Summable: Copy + Default {
    /// `self + o`, wrapping.
    fn plus(self, o: Self) -> Self;
    /// `self − o`, wrapping.
    fn minus(self, o: Self) -> Self;
}

impl Summable for u32 {
    fn plus(self, o: Self) -> Self {
        self.wrapping_add(o)
    }
    fn minus(self, o: Self) -> Self {
        self.wrapping_sub(o)
    }
}

impl Summable for u64 {
    fn plus(self, o: Self) -> Self {
        self.wrapping_add(o)
    }
    fn minus(self, o: Self) -> Self {
        self.wrapping_sub(o)
    }
}

/// A summed-area table of integer values over a `width × height` grid.
#[derive(Clone, Debug)]
pub struct BoxSums<T = u64> {
    w1: usize,
    h: usize,
    t: Vec<T>,
}

impl<T: Summable> BoxSums<T> {
    /// Tabulates `f(x, y)` over the grid.
    pub fn new(width: usize, height: usize, f: impl Fn(usize, usize) -> T) -> Self {
        Self::from_rows(width, height, |y, row| {
            for (x, v) in row.iter_mut().enumerate() {
                *v = f(x, y);
            }
        })
    }

    /// Tabulates a grid given row by row: `fill(y, row)` writes row `y`'s values into `row`
    /// (no call per cell).
    pub fn from_rows(width: usize, height: usize, mut fill: impl FnMut(usize, &mut [T])) -> Self {
        let w1 = width + 1;
        let mut t = vec![T::default(); w1 * (height + 1)];
        let mut row = vec![T::default(); width];
        for y in 0..height {
            fill(y, &mut row);
            let (above, below) = t.split_at_mut((y + 1) * w1);
            let above = &above[y * w1 + 1..];
            let mut acc = T::default();
            for ((out, &up), &v) in below[1..w1].iter_mut().zip(above).zip(&row) {
                acc = acc.plus(v);
                *out = up.plus(acc);
            }
        }
        Self { w1, h: height, t }
    }

    /// Sum over `[x0, x1) × [y0, y1)`.
    pub fn rect(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> T {
        let w1 = self.w1;
        self.t[y1 * w1 + x1]
            .plus(self.t[y0 * w1 + x0])
            .minus(self.t[y0 * w1 + x1])
            .minus(self.t[y1 * w1 + x0])
    }

    /// The table's rows `y0` and `y1`: the window `[x0, x1) × [y0, y1)` sums to
    /// `b[x1] + a[x0] − a[x1] − b[x0]` (wrapping) for `(a, b)`, as [`BoxSums::rect`] adds.
    pub fn rows(&self, y0: usize, y1: usize) -> (&[T], &[T]) {
        let w1 = self.w1;
        (&self.t[y0 * w1..][..w1], &self.t[y1 * w1..][..w1])
    }

    /// Sum over the `(2r+1)²` window centred on `(x, y)`, clipped to the grid, and the
    /// number of grid cells it covers.
    pub fn around(&self, x: usize, y: usize, r: usize) -> (T, u64) {
        let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(self.w1 - 1));
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(self.h));
        (self.rect(x0, y0, x1, y1), ((x1 - x0) * (y1 - y0)) as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_sums_match_brute_force() {
        let f = |x: usize, y: usize| ((x * 7 + y * 13) % 11) as u64;
        let b = BoxSums::new(9, 6, f);
        for y in 0..6usize {
            for x in 0..9usize {
                for r in 0..4 {
                    let mut s = 0;
                    let mut n = 0;
                    for v in y.saturating_sub(r)..(y + r + 1).min(6) {
                        for u in x.saturating_sub(r)..(x + r + 1).min(9) {
                            s += f(u, v);
                            n += 1;
                        }
                    }
                    assert_eq!(b.around(x, y, r), (s, n), "({x}, {y}) r {r}");
                }
            }
        }
        assert_eq!(b.rect(2, 1, 2, 5), 0);
    }

    #[test]
    fn wrapped_window_sums_are_exact_below_two_to_the_32() {
        // Values large enough for the whole grid's sum to wrap many times over.
        let f = |x: usize, y: usize| ((x * 7919 + y * 104_729) % 1_000_003) as u64 * 97;
        let (w, h) = (40, 30);
        let wide = BoxSums::new(w, h, f);
        let wrapped = BoxSums::<u32>::from_rows(w, h, |y, row| {
            for (x, v) in row.iter_mut().enumerate() {
                *v = f(x, y) as u32;
            }
        });
        assert!(wide.rect(0, 0, w, h) > 1 << 35);
        for y in 0..h {
            for x in 0..w {
                for r in 0..3 {
                    let (s, _) = wide.around(x, y, r);
                    assert!(s < 1 << 32);
                    assert_eq!(wrapped.around(x, y, r).0 as u64, s, "({x}, {y}) r {r}");
                }
            }
        }
    }
}
