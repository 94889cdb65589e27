//! A small dense Levenberg–Marquardt for reprojection errors and image-model fits.

use nalgebra::{DMatrix, DVector};

/// Minimises `Σ r(p)²` from `p` by Levenberg–Marquardt with Marquardt's diagonal scaling
/// and a central-difference Jacobian; `steps[i]` is parameter `i`'s difference step.
/// Returns the final sum of squares.
pub fn minimise(
    p: &mut [f64],
    steps: &[f64],
    residuals: &dyn Fn(&[f64], &mut Vec<f64>),
    iterations: usize,
) -> f64 {
    let n = p.len();
    let mut r = Vec::new();
    residuals(p, &mut r);
    let m = r.len();
    let mut cost: f64 = r.iter().map(|e| e * e).sum();
    let mut lambda = 1e-3;
    let (mut rp, mut rm) = (Vec::with_capacity(m), Vec::with_capacity(m));
    let mut jac = DMatrix::<f64>::zeros(m, n);
    let mut trial = p.to_vec();
    for _ in 0..iterations {
        let mut q = p.to_vec();
        for j in 0..n {
            let h = steps[j];
            q[j] = p[j] + h;
            residuals(&q, &mut rp);
            q[j] = p[j] - h;
            residuals(&q, &mut rm);
            q[j] = p[j];
            for i in 0..m {
                jac[(i, j)] = (rp[i] - rm[i]) / (2.0 * h);
            }
        }
        let jt = jac.transpose();
        let jtj = &jt * &jac;
        let g = &jt * DVector::from_column_slice(&r);
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj.clone();
            for j in 0..n {
                a[(j, j)] += lambda * jtj[(j, j)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = chol.solve(&(-&g));
            for j in 0..n {
                trial[j] = p[j] + delta[j];
            }
            residuals(&trial, &mut rp);
            let c: f64 = rp.iter().map(|e| e * e).sum();
            if c.is_finite() && c < cost {
                let gain = (cost - c) / cost.max(1e-300);
                p.copy_from_slice(&trial);
                std::mem::swap(&mut r, &mut rp);
                cost = c;
                lambda = (lambda * 0.1).max(1e-12);
                improved = gain > 1e-12;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    cost
}

#[cfg(test)]
mod tests {
    #[test]
    fn fits_an_exponential_exactly() {
        // y = a·exp(b·x) through five exact points, from a poor start.
        let xs = [0.0, 0.5, 1.0, 1.5, 2.0];
        let res = |p: &[f64], r: &mut Vec<f64>| {
            r.clear();
            r.extend(
                xs.iter()
                    .map(|x| p[0] * (p[1] * x).exp() - 2.0 * (-0.7 * x).exp()),
            );
        };
        let mut p = [1.0, 0.0];
        let cost = super::minimise(&mut p, &[1e-6, 1e-6], &res, 100);
        assert!(cost < 1e-20, "{cost}");
        assert!(
            (p[0] - 2.0).abs() < 1e-8 && (p[1] + 0.7).abs() < 1e-8,
            "{p:?}"
        );
    }
}
