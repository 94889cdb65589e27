//! `report.html`: one self-contained page (figures inlined, no script from elsewhere) with
//! the paper's figures of a `reconstruct` run and the numbers behind them.

use base64::Engine;
use image::RgbImage;
use std::fmt::Write;
use std::path::Path;

/// One figure of the page: a PNG, its title and what it shows.
#[derive(Clone, Debug)]
pub struct Figure {
    /// Heading.
    pub title: String,
    /// What the figure shows and how to read it.
    pub caption: String,
    /// The PNG bytes.
    pub png: Vec<u8>,
}

impl Figure {
    /// A figure of image `img`.
    pub fn of(title: &str, caption: &str, img: &RgbImage) -> Self {
        let mut png = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .expect("a PNG encodes into memory");
        Self {
            title: title.into(),
            caption: caption.into(),
            png,
        }
    }

    /// A figure of the PNG `name` that the run wrote into `dir` (`None` when it is not there).
    pub fn file(dir: &Path, name: &str, title: &str, caption: &str) -> Option<Self> {
        std::fs::read(dir.join(name)).ok().map(|png| Self {
            title: title.into(),
            caption: format!("{caption} ({name})"),
            png,
        })
    }
}

/// A table of the page: its heading, column names and rows.
#[derive(Clone, Debug, Default)]
pub struct Table {
    /// Heading.
    pub title: String,
    /// Column names.
    pub columns: Vec<String>,
    /// Rows, as many cells as columns.
    pub rows: Vec<Vec<String>>,
}

impl Table {
    /// Every number, string and flag of `report` (a run's JSON report), one row each named
    /// by its path (`validation.off_by_one`); long lists only counted.
    pub fn of_report(title: &str, report: &serde_json::Value) -> Self {
        fn walk(v: &serde_json::Value, path: &str, rows: &mut Vec<Vec<String>>) {
            use serde_json::Value;
            let join = |k: &str| {
                if path.is_empty() {
                    k.to_string()
                } else {
                    format!("{path}.{k}")
                }
            };
            match v {
                Value::Object(m) => m.iter().for_each(|(k, v)| walk(v, &join(k), rows)),
                Value::Array(a) if a.iter().all(|x| !x.is_object()) && a.len() <= 8 => {
                    let items: Vec<String> = a.iter().map(scalar).collect();
                    rows.push(vec![path.into(), format!("[{}]", items.join(", "))]);
                }
                Value::Array(a) => rows.push(vec![path.into(), format!("{} entries", a.len())]),
                _ => rows.push(vec![path.into(), scalar(v)]),
            }
        }
        let mut rows = Vec::new();
        walk(report, "", &mut rows);
        Self {
            title: title.into(),
            columns: vec!["figure".into(), "value".into()],
            rows,
        }
    }
}

fn scalar(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::String(s) => s.clone(),
        serde_json::Value::Null => "—".into(),
        other => other.to_string(),
    }
}

/// `text` safe inside HTML.
fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The page: `title`, a `summary` line, the figures, then the tables. A script of its own
/// counts the figures the browser could show (`data-shown` of `data-figures` on the body,
/// and a line at the top), so that a headless browser can tell.
pub fn page(title: &str, summary: &str, figures: &[Figure], tables: &[Table]) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{t}</title><style>\
         body{{font-family:sans-serif;margin:2em;max-width:1400px;color:#222}}\
         figure{{display:inline-block;vertical-align:top;margin:0 1.5em 1.5em 0;max-width:660px}}\
         figure img{{max-width:640px;border:1px solid #ccc}}figcaption{{font-size:90%;color:#555}}\
         table{{border-collapse:collapse;margin-bottom:1.5em}}td,th{{border:1px solid #ddd;padding:2px 8px;text-align:left}}\
         </style></head>\n<body data-figures=\"{n}\" data-shown=\"0\">\n<h1>{t}</h1>\n<p>{s}</p>\n\
         <p id=\"shown\">{n} figures</p>\n",
        t = escape(title),
        s = escape(summary),
        n = figures.len()
    );
    for f in figures {
        let data = base64::engine::general_purpose::STANDARD.encode(&f.png);
        let _ = writeln!(
            h,
            "<figure><h2>{}</h2><img alt=\"{}\" src=\"data:image/png;base64,{data}\">\
             <figcaption>{}</figcaption></figure>",
            escape(&f.title),
            escape(&f.title),
            escape(&f.caption)
        );
    }
    for t in tables {
        let _ = write!(h, "<h2>{}</h2>\n<table><tr>", escape(&t.title));
        for c in &t.columns {
            let _ = write!(h, "<th>{}</th>", escape(c));
        }
        h += "</tr>\n";
        for r in &t.rows {
            h += "<tr>";
            for c in r {
                let _ = write!(h, "<td>{}</td>", escape(c));
            }
            h += "</tr>\n";
        }
        h += "</table>\n";
    }
    h += "<script>\nwindow.addEventListener('load', () => {\n\
          const imgs = [...document.images];\n\
          const shown = imgs.filter(i => i.complete && i.naturalWidth > 0).length;\n\
          document.body.dataset.shown = shown;\n\
          document.getElementById('shown').textContent = shown + ' of ' + imgs.length + ' figures shown';\n\
          });\n</script>\n</body></html>\n";
    h
}

/// The range-selection curve of `curve` (the paper's Fig. 12), `chosen` in red: each
/// range by its radius.
pub fn range_curve(
    curve: &[crate::range::RangeScore],
    chosen: schemas::DisparityRange,
) -> RgbImage {
    let pts: Vec<(u32, f64)> = curve
        .iter()
        .map(|s| {
            let r = s.range.max.unsigned_abs().max(s.range.min.unsigned_abs());
            (r, s.consistency_ratio)
        })
        .collect();
    let best = curve.iter().position(|s| s.range == chosen).unwrap_or(0);
    formats::render::range_curve_chart(&pts, best)
}

/// The validation split figure of `v` (the LR check's shares).
fn validation_figure(v: &schemas::ValidationFigures) -> Figure {
    Figure::of(
        "Validation",
        &format!(
            "Of {} matched pixels, the share whose left→right and right→left matches agree exactly (green), within one pixel (amber) and beyond (red), per cent; the paper's Table 2.",
            v.matched
        ),
        &formats::render::validation_chart(v.consistent_exact, v.off_by_one, v.off_by_more),
    )
}

/// The 3D view figure of `cloud` (`None` for no points).
fn cloud_figure(cloud: &schemas::Cloud, unit: &str) -> Option<Figure> {
    (!cloud.points.is_empty()).then(|| {
        let pts: Vec<([f32; 3], [u8; 3])> = cloud.points.iter().map(|p| (p.xyz, p.rgb)).collect();
        let (img, stretch) = formats::render::cloud_view(&pts);
        Figure::of(
            "3D view",
            &format!(
                "{} triangulated points in their own colours ({unit}), seen from above and to one side; depth drawn ×{} so that it spreads half as wide as the scene.",
                cloud.points.len(),
                if stretch >= 10.0 { format!("{stretch:.0}") } else { format!("{stretch:.2}") }
            ),
            &img,
        )
    })
}

/// The page of a pair run whose outputs are in `dir`: the range curve (when the range was
/// chosen), the validation split, the disparity map, the occlusions and the 3D view, then
/// every number of `report` (report.json).
pub fn pair_page(
    dir: &Path,
    report: &impl serde::Serialize,
    validation: &schemas::ValidationFigures,
    cloud: Option<&schemas::Cloud>,
) -> String {
    let report = &serde_json::to_value(report).expect("a report serialises");
    let unit = report["unit"].as_str().unwrap_or("");
    let mut figures: Vec<Figure> = [
        Figure::file(
            dir,
            "range_curve.png",
            "Range selection",
            "The consistency ratio of each disparity range tried; the chosen range in red (the paper's Fig. 12)",
        ),
        Some(validation_figure(validation)),
        Figure::file(
            dir,
            "disparity_color.png",
            "Disparity",
            "The final disparity map, colour for disparity, black where none",
        ),
        Figure::file(
            dir,
            "occlusion_left.png",
            "Occlusions",
            "White: pixels whose two matches disagree, the occlusions and mismatches the LR check refused",
        ),
    ]
    .into_iter()
    .flatten()
    .collect();
    figures.extend(cloud.and_then(|c| cloud_figure(c, unit)));
    page(
        "microstereo reconstruct",
        &format!(
            "{} and {}: {}×{}, disparities {}..{}",
            scalar(&report["left"]),
            scalar(&report["right"]),
            report["width"],
            report["height"],
            report["range"]["min"],
            report["range"]["max"]
        ),
        &figures,
        &[Table::of_report("The numbers (report.json)", report)],
    )
}

/// The page of a cells run whose outputs are in `dir`: the variance histogram with its
/// threshold, the boundaries, the validation split over the cells' tiles, the disparity
/// map, the occlusions and the 3D view, then each cell's figures and every number of
/// `report` (cells.json).
pub fn cells_page(
    dir: &Path,
    report: &impl serde::Serialize,
    (targets, tiles, cloud): (&schemas::Targets, &schemas::DisparityTiles, &schemas::Cloud),
    histogram: Option<&([u64; 256], u16)>,
) -> String {
    let report = &serde_json::to_value(report).expect("a report serialises");
    let mut figures = Vec::new();
    if let Some((h, t)) = histogram {
        figures.push(Figure::of(
            "Segmentation",
            &format!(
                "The left view's local-variance histogram (log counts) and the threshold {t} that parts cells from background (the paper's Fig. 17)."
            ),
            &formats::render::histogram_chart(h, Some(*t)),
        ));
    }
    figures.extend(Figure::file(
        dir,
        "overlay_left.png",
        "Boundaries",
        "Each cell's boundary and id over the left view",
    ));
    let mut v = schemas::ValidationFigures::default();
    let mut n = 0.0;
    for f in tiles.tiles.iter().filter_map(|t| t.figures) {
        let w = f.matched as f64;
        v.matched += f.matched;
        v.consistent_exact += w * f.consistent_exact;
        v.off_by_one += w * f.off_by_one;
        v.off_by_more += w * f.off_by_more;
        n += w;
    }
    if n > 0.0 {
        v.consistent_exact /= n;
        v.off_by_one /= n;
        v.off_by_more /= n;
        figures.push(validation_figure(&v));
    }
    figures.extend(Figure::file(
        dir,
        "disparity_color.png",
        "Disparity",
        "The cells' disparity maps, colour for disparity",
    ));
    figures.extend(Figure::file(
        dir,
        "occlusion_left.png",
        "Occlusions",
        "White: pixels of the cells whose two matches disagree",
    ));
    figures.extend(cloud_figure(cloud, &targets.unit));
    let u = &targets.unit;
    let cells = Table {
        title: "Cells".into(),
        columns: ["cell", "centroid", "height", "volume", "trusted", "why not"]
            .map(String::from)
            .to_vec(),
        rows: targets
            .cells
            .iter()
            .map(|c| {
                let height = match (c.height, c.quality.height_std) {
                    (Some(h), Some(s)) => format!("{h:.2} ± {s:.2} {u}"),
                    (Some(h), None) => format!("{h:.2} {u}"),
                    (None, _) => "—".into(),
                };
                vec![
                    c.id.to_string(),
                    format!(
                        "{:.1}, {:.1}, {:.1} {u}",
                        c.centroid[0], c.centroid[1], c.centroid[2]
                    ),
                    height,
                    format!("{:.0} {u}³", c.volume),
                    if c.quality.trusted { "yes" } else { "no" }.into(),
                    c.quality.doubt.clone().unwrap_or_default(),
                ]
            })
            .collect(),
    };
    let mut numbers = report.clone();
    if let Some(m) = numbers.as_object_mut() {
        m.remove("cells");
    }
    page(
        "microstereo reconstruct --cells",
        &format!(
            "{} and {}: {} cells left, {} right, {} paired",
            scalar(&report["left"]),
            scalar(&report["right"]),
            report["cells_left"],
            report["cells_right"],
            report["pairs"]
        ),
        &figures,
        &[
            cells,
            Table::of_report("The numbers (cells.json)", &numbers),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_page_inlines_its_figures_and_escapes_its_text() {
        let img = RgbImage::from_pixel(3, 2, image::Rgb([10, 20, 30]));
        let f = Figure::of("a <b>", "c & d", &img);
        let t = Table::of_report(
            "numbers",
            &serde_json::json!({"validation": {"off_by_one": 0.25}, "mode": "fast", "curve": [{"a": 1}]}),
        );
        let html = page("run", "x < y", std::slice::from_ref(&f), &[t]);
        assert!(html.contains("data-figures=\"1\""));
        assert!(html.contains("<h2>a &lt;b&gt;</h2>"));
        assert!(html.contains("c &amp; d"));
        assert!(html.contains("<td>validation.off_by_one</td><td>0.25</td>"));
        assert!(html.contains("<td>curve</td><td>1 entries</td>"));
        // The PNG comes back from the page whole.
        let start = html.find("base64,").unwrap() + 7;
        let end = start + html[start..].find('"').unwrap();
        let png = base64::engine::general_purpose::STANDARD
            .decode(&html[start..end])
            .unwrap();
        assert_eq!(png, f.png);
        let back = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(back, img);
    }
}
