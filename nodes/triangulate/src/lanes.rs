//! Four `f64` values that take every arithmetic step together: code written once over
//! [`Real`] runs on one ray or on four side by side (one AVX register), with each lane's
//! value rounded exactly as the scalar one is (IEEE operations, one at a time, in the same
//! order), so batching changes no result.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// The number types the top fits' geometry is written over: `f64`, one value, or
/// [`Lanes`], four.
pub(crate) trait Real:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    /// A constant in every lane.
    fn splat(x: f64) -> Self;
}

impl Real for f64 {
    #[inline(always)]
    fn splat(x: f64) -> Self {
        x
    }
}

/// Lanes side by side.
pub(crate) const WIDTH: usize = 4;

/// [`WIDTH`] values, each operated on as an `f64` alone.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Lanes(pub [f64; WIDTH]);

impl Real for Lanes {
    #[inline(always)]
    fn splat(x: f64) -> Self {
        Self([x; WIDTH])
    }
}

macro_rules! lanewise {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for Lanes {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                Self(std::array::from_fn(|l| self.0[l] $op o.0[l]))
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);
lanewise!(Div, div, /);

impl Neg for Lanes {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Self(self.0.map(|x| -x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lanes give the scalar results to the bit, including signed zeros and NaN.
    #[test]
    fn lanes_round_as_scalars() {
        let xs = [1.0 / 3.0, -0.0, 7.5e-300, f64::NAN];
        let ys = [3.0, 0.0, 1.0e300, 2.0];
        let (a, b) = (Lanes(xs), Lanes(ys));
        let got = [a + b, a - b, a * b, a / b, -a, Lanes::splat(2.0) * a];
        for l in 0..WIDTH {
            let (x, y) = (xs[l], ys[l]);
            let want = [x + y, x - y, x * y, x / y, -x, 2.0 * x];
            for (g, w) in got.iter().zip(want) {
                assert_eq!(g.0[l].to_bits(), w.to_bits(), "lane {l}");
            }
        }
    }
}
