//! Finding a pipette's tip in one view: the dark, tapered glass that enters the field from
//! its border, its axis, and the front of its tip to a fraction of a pixel, sharp or out
//! of focus.
//!
//! The smooth background (illumination gradient, vignetting) is fitted and taken away;
//! the pipette is the largest dark region that reaches the border and is long rather than
//! round; its axis is the region's principal direction, refined from the cross-sections'
//! centres. Along the axis, the darkness summed across the glass is its width times its
//! contrast, which the camera's and the defocus's blur only spread along the axis: a model
//! of a cone ending in a round cap, blurred by a Gaussian, fitted to that profile, puts the
//! front where the glass ends, whatever the blur.

use calibration::bilinear;
use calibration::lm::minimise;
use schemas::Plane;
use segment::{Connectivity, components_where};

/// A pipette tip found in one view.
#[derive(Clone, Debug, PartialEq)]
pub struct Tip {
    /// The front of the tip (the glass's farthest point along the pipette), px.
    pub front: [f64; 2],
    /// Unit vector of the pipette's axis, pointing where the tip points.
    pub axis: [f64; 2],
    /// Blur of the tip's image along the axis (Gaussian sigma, px): the defocus.
    pub blur: f64,
    /// Radius of the glass at its tip, px (as the fitted cap).
    pub radius: f64,
    /// How much darker than the background the glass is (grey levels).
    pub contrast: f64,
}

/// Why no tip was found.
#[derive(Clone, Debug, PartialEq)]
pub struct NoTip(pub String);

impl std::fmt::Display for NoTip {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// Least darkness (grey levels below the background) of a pipette's pixels.
const MIN_DARK: f64 = 12.0;

/// Finds the pipette's tip in `img`.
pub fn find_tip(img: &Plane<u8>) -> Result<Tip, NoTip> {
    let (w, h) = (img.width, img.height);
    if w < 16 || h < 16 {
        return Err(NoTip(format!(
            "a {w}×{h} image is too small to hold a pipette"
        )));
    }
    let dark = darkness(img);
    // The glass's core: darker than 60 % of its darkest part (a dark cell rim the tip
    // touches stays out), and at least MIN_DARK.
    let mut sorted: Vec<f64> = dark.data.iter().copied().filter(|d| *d > 0.0).collect();
    sorted.sort_by(f64::total_cmp);
    let top = sorted
        .get(sorted.len().saturating_sub(1 + sorted.len() / 2000))
        .copied()
        .unwrap_or(0.0);
    let threshold = (0.6 * top).max(MIN_DARK);
    let region = pipette_region(&dark, threshold)?;
    // The axis: the region's principal direction, pointing away from where it meets the
    // border.
    let (mut c, mut m, mut n) = ([0.0, 0.0], 0.0, 0usize);
    let mut edge = [0.0, 0.0];
    for &(x, y) in &region {
        let d = *dark.get(x, y);
        c[0] += d * x as f64;
        c[1] += d * y as f64;
        m += d;
        if x == 0 || y == 0 || x == w - 1 || y == h - 1 {
            edge[0] += x as f64;
            edge[1] += y as f64;
            n += 1;
        }
    }
    c = [c[0] / m, c[1] / m];
    edge = [edge[0] / n as f64, edge[1] / n as f64];
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for &(x, y) in &region {
        let d = *dark.get(x, y);
        let (dx, dy) = (x as f64 - c[0], y as f64 - c[1]);
        sxx += d * dx * dx;
        sxy += d * dx * dy;
        syy += d * dy * dy;
    }
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let mut a = [theta.cos(), theta.sin()];
    if (c[0] - edge[0]) * a[0] + (c[1] - edge[1]) * a[1] < 0.0 {
        a = [-a[0], -a[1]];
    }
    let along = |x: usize, y: usize, o: [f64; 2], a: [f64; 2]| {
        (x as f64 - o[0]) * a[0] + (y as f64 - o[1]) * a[1]
    };
    let t_end = region
        .iter()
        .map(|&(x, y)| along(x, y, c, a))
        .fold(f64::MIN, f64::max);
    // How wide the glass is a little behind its end: the cross-sections reach past it.
    let half = region
        .iter()
        .filter(|&&(x, y)| (t_end - 45.0..t_end - 30.0).contains(&along(x, y, c, a)))
        .map(|&(x, y)| ((x as f64 - c[0]) * -a[1] + (y as f64 - c[1]) * a[0]).abs())
        .fold(0.0, f64::max);
    let reach = half.max(4.0) + 20.0;
    // The axis again from the cross-sections' centres along the whole visible body (a
    // line through them, those off it by more than 3 MADs left out: where the glass
    // crosses a cell, its image's blur mixes with the cell's and pulls the centres aside).
    let t_back = region
        .iter()
        .map(|&(x, y)| along(x, y, c, a))
        .fold(f64::MAX, f64::min);
    let mut origin = c;
    for _ in 0..2 {
        let nrm = [-a[1], a[0]];
        let mut pts: Vec<(f64, f64)> = (0..)
            .map(|k| t_back + 2.0 + 2.0 * k as f64)
            .take_while(|t| *t < t_end - 5.0)
            .filter(|&t| {
                // Whole sections only: one the border cuts has its centre pulled inward.
                [-reach, reach].iter().all(|&e| {
                    let (x, y) = (
                        origin[0] + t * a[0] + e * nrm[0],
                        origin[1] + t * a[1] + e * nrm[1],
                    );
                    x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64
                })
            })
            .filter_map(|t| {
                let (mass, centre) = section(&dark, origin, a, nrm, t, reach);
                (mass > 0.0).then_some((t, centre))
            })
            .collect();
        let mut line = (0.0, 0.0);
        for _ in 0..3 {
            if pts.len() < 5 {
                break;
            }
            let k = pts.len() as f64;
            let (mt, ms) = pts
                .iter()
                .fold((0.0, 0.0), |s, p| (s.0 + p.0 / k, s.1 + p.1 / k));
            let stt: f64 = pts.iter().map(|p| (p.0 - mt).powi(2)).sum();
            let sts: f64 = pts.iter().map(|p| (p.0 - mt) * (p.1 - ms)).sum();
            let beta = if stt > 0.0 { sts / stt } else { 0.0 };
            line = (ms - beta * mt, beta);
            let mut dev: Vec<f64> = pts
                .iter()
                .map(|p| (p.1 - line.0 - line.1 * p.0).abs())
                .collect();
            dev.sort_by(f64::total_cmp);
            let limit = (3.0 * 1.4826 * dev[dev.len() / 2]).max(0.3);
            pts.retain(|p| (p.1 - line.0 - line.1 * p.0).abs() <= limit);
        }
        // s = α + β·t: move the origin by α, turn the axis by β.
        let (alpha, beta) = line;
        origin = [origin[0] + alpha * nrm[0], origin[1] + alpha * nrm[1]];
        let na = [a[0] + beta * nrm[0], a[1] + beta * nrm[1]];
        let l = na[0].hypot(na[1]);
        a = [na[0] / l, na[1] / l];
    }
    let nrm = [-a[1], a[0]];
    let t_end = region
        .iter()
        .map(|&(x, y)| along(x, y, origin, a))
        .fold(f64::MIN, f64::max);
    // The profile along the axis: the darkness summed across the glass, from 40 px behind
    // the core's end to where it stops falling past it (beyond, a cell the tip touches may
    // darken the sections again) or has gone, at most 80 px on.
    let mut ts: Vec<f64> = (0..240).map(|k| t_end - 40.0 + 0.5 * k as f64).collect();
    let mut profile: Vec<f64> = ts
        .iter()
        .map(|&t| section(&dark, origin, a, nrm, t, reach).0)
        .collect();
    let smooth = |k: usize| {
        profile[k.saturating_sub(2)..(k + 3).min(profile.len())]
            .iter()
            .sum::<f64>()
    };
    let after = 80;
    // A rise counts once the glass has thinned to under half its width 40 px back (before
    // that, the sections' noise on a wide blurred body rises and falls too).
    let back = profile[0];
    if let Some(stop) = (after..profile.len() - 3)
        .find(|&k| profile[k] < 0.5 * back && smooth(k + 1) > smooth(k) + 5.0 * MIN_DARK)
    {
        ts.truncate(stop + 1);
        profile.truncate(stop + 1);
    }
    // A blurred tip fades over a few blurs past the core's end: 10 px past where the
    // glass has gone (under 3 % of its width 40 px back) is enough.
    if let Some(gone) = (after..profile.len()).find(|&k| profile[k] < 0.03 * back) {
        let end = (gone + 20).min(profile.len());
        ts.truncate(end);
        profile.truncate(end);
    }
    let fit = fit_profile(&ts, &profile, t_end)?;
    let front_t = fit.front;
    Ok(Tip {
        front: [origin[0] + front_t * a[0], origin[1] + front_t * a[1]],
        axis: a,
        blur: fit.blur,
        radius: fit.radius,
        contrast: fit.contrast,
    })
}

/// The image's darkness below its smooth background: a quadratic surface fitted to the
/// pixels (every fourth row and column) with the darkest and brightest left out until it
/// settles.
fn darkness(img: &Plane<u8>) -> Plane<f64> {
    let (w, h) = (img.width, img.height);
    let (sx, sy) = (2.0 / w as f64, 2.0 / h as f64);
    let basis = |x: usize, y: usize| {
        let (u, v) = (x as f64 * sx - 1.0, y as f64 * sy - 1.0);
        [1.0, u, v, u * u, u * v, v * v]
    };
    let samples: Vec<(usize, usize, f64)> = (0..h)
        .step_by(4)
        .flat_map(|y| (0..w).step_by(4).map(move |x| (x, y)))
        .map(|(x, y)| (x, y, *img.get(x, y) as f64))
        .collect();
    let mut coef = [0.0; 6];
    let mut keep = vec![true; samples.len()];
    for _ in 0..6 {
        let mut ata = nalgebra::Matrix6::<f64>::zeros();
        let mut atb = nalgebra::Vector6::<f64>::zeros();
        for (s, k) in samples.iter().zip(&keep) {
            if *k {
                let b = nalgebra::Vector6::from(basis(s.0, s.1));
                ata += b * b.transpose();
                atb += b * s.2;
            }
        }
        let Some(sol) = ata.try_inverse().map(|m| m * atb) else {
            break;
        };
        coef.copy_from_slice(sol.as_slice());
        let res: Vec<f64> = samples
            .iter()
            .map(|s| {
                s.2 - basis(s.0, s.1)
                    .iter()
                    .zip(&coef)
                    .map(|(b, c)| b * c)
                    .sum::<f64>()
            })
            .collect();
        let mut abs: Vec<f64> = res.iter().map(|r| r.abs()).collect();
        abs.sort_by(f64::total_cmp);
        let sigma = (1.4826 * abs[abs.len() / 2]).max(1.0);
        for (k, r) in keep.iter_mut().zip(&res) {
            *k = r.abs() <= 2.5 * sigma;
        }
    }
    let data = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let bg: f64 = basis(x, y).iter().zip(&coef).map(|(b, c)| b * c).sum();
            bg - *img.get(x, y) as f64
        })
        .collect();
    Plane::from_vec(w, h, data).expect("size")
}

/// The pixels of the pipette: of the regions darker than `threshold` (8-connected, by the
/// segmentation's labelling), the largest that reaches the image's border and is at least
/// three times as long as it is wide.
fn pipette_region(dark: &Plane<f64>, threshold: f64) -> Result<Vec<(usize, usize)>, NoTip> {
    let (w, h) = (dark.width, dark.height);
    let c = components_where(dark, |d| *d >= threshold, Connectivity::Eight);
    let mut regions: Vec<Vec<(usize, usize)>> = vec![Vec::new(); c.n as usize];
    for &(y, x0, x1, l) in &c.runs {
        regions[l as usize - 1].extend((x0..x1).map(|x| (x, y)));
    }
    let border = |r: &[(usize, usize)]| {
        r.iter()
            .any(|&(x, y)| x == 0 || y == 0 || x == w - 1 || y == h - 1)
    };
    regions
        .into_iter()
        .filter(|r| r.len() >= 30 && border(r) && elongated(r))
        .reduce(|best, r| if r.len() > best.len() { r } else { best })
        .ok_or_else(|| {
            NoTip(format!(
                "no pipette in view: no long dark region (at least {threshold:.0} grey levels below the background) enters from the image's border"
            ))
        })
}

/// Whether a region is at least three times as long as it is wide (second moments).
fn elongated(region: &[(usize, usize)]) -> bool {
    let n = region.len() as f64;
    let (mx, my) = region.iter().fold((0.0, 0.0), |s, p| {
        (s.0 + p.0 as f64 / n, s.1 + p.1 as f64 / n)
    });
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for p in region {
        let (dx, dy) = (p.0 as f64 - mx, p.1 as f64 - my);
        a += dx * dx / n;
        b += dx * dy / n;
        c += dy * dy / n;
    }
    let tr = a + c;
    let disc = ((a - c).powi(2) + 4.0 * b * b).sqrt();
    let (l1, l2) = (0.5 * (tr + disc), 0.5 * (tr - disc));
    l1 >= 9.0 * l2.max(1e-9)
}

/// The darkness summed across the axis at `t` (over `±reach`, in half-pixel steps), and
/// where across the axis its centre lies.
fn section(
    dark: &Plane<f64>,
    o: [f64; 2],
    a: [f64; 2],
    n: [f64; 2],
    t: f64,
    reach: f64,
) -> (f64, f64) {
    let steps = (2.0 * reach) as i64;
    let (mut mass, mut moment) = (0.0, 0.0);
    for k in -steps..=steps {
        let s = 0.5 * k as f64;
        let d = bilinear(dark, o[0] + t * a[0] + s * n[0], o[1] + t * a[1] + s * n[1])
            .unwrap_or(0.0)
            .max(0.0);
        mass += 0.5 * d;
        moment += 0.5 * d * s;
    }
    (mass, if mass > 0.0 { moment / mass } else { 0.0 })
}

/// A fitted profile.
struct ProfileFit {
    front: f64,
    blur: f64,
    radius: f64,
    contrast: f64,
}

/// The unblurred profile of a cone `r(t) = radius + taper·(t_cap − t)` ending in a round
/// cap of `radius` centred at `t_cap`: its width times `contrast`.
fn sharp(t: f64, cap: f64, radius: f64, taper: f64, contrast: f64) -> f64 {
    let width = if t <= cap {
        2.0 * (radius + taper * (cap - t))
    } else if t < cap + radius {
        2.0 * (radius * radius - (t - cap).powi(2)).max(0.0).sqrt()
    } else {
        0.0
    };
    contrast * width
}

/// The profile blurred along the axis by a Gaussian of `blur` (numerically, in steps of
/// a tenth of the blur).
fn blurred(t: f64, p: &[f64]) -> f64 {
    let (cap, radius, taper, contrast, blur, offset) =
        (p[0], p[1].abs(), p[2], p[3], p[4].abs().max(0.2), p[5]);
    let step = 0.1 * blur;
    let half = 40;
    let (mut s, mut wsum) = (0.0, 0.0);
    for k in -half..=half {
        let d = step * k as f64;
        let g = (-0.5 * (d / blur).powi(2)).exp();
        s += g * sharp(t - d, cap, radius, taper, contrast);
        wsum += g;
    }
    s / wsum + offset
}

fn fit_profile(ts: &[f64], profile: &[f64], t_end: f64) -> Result<ProfileFit, NoTip> {
    // A start: the contrast and taper from the profile behind the end, the cap at the end.
    let back = profile[..20].iter().sum::<f64>() / 20.0;
    let mid = profile[40..60].iter().sum::<f64>() / 20.0;
    let slope = ((back - mid) / 20.0).max(0.0);
    let contrast = 40.0;
    let res = |p: &[f64], r: &mut Vec<f64>| {
        r.clear();
        r.extend(ts.iter().zip(profile).map(|(&t, &v)| blurred(t, p) - v));
    };
    let mut best: Option<(f64, Vec<f64>)> = None;
    // The core ends short of a blurred tip's front: starts up to 8 px past it.
    for blur in [0.7, 2.0, 4.0] {
        for shift in [-3.0, 0.0, 4.0, 8.0] {
            let mut p = vec![
                t_end + shift,
                1.5,
                slope / (2.0 * contrast),
                contrast,
                blur,
                0.0,
            ];
            let cost = minimise(&mut p, &[1e-4, 1e-4, 1e-6, 1e-4, 1e-4, 1e-4], &res, 100);
            if best.as_ref().is_none_or(|b| cost < b.0) {
                best = Some((cost, p));
            }
        }
    }
    let (_, p) = best.expect("fits");
    if !(p[3] > 0.0 && p.iter().all(|v| v.is_finite())) {
        return Err(NoTip(
            "the pipette's profile does not fit a tapered tip".into(),
        ));
    }
    Ok(ProfileFit {
        front: p[0] + p[1].abs(),
        blur: p[4].abs(),
        radius: p[1].abs(),
        contrast: p[3],
    })
}
