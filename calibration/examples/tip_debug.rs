//! Debug: one synthetic scene's tip, written as PNGs to /tmp.
use camera_calibration::pipette::find_tip;
use synth::{CellSpec, Look, Optics, Pipette, Scene};
fn main() {
    let a: Vec<f64> = std::env::args()
        .skip(1)
        .map(|s| s.parse().unwrap())
        .collect();
    let (az, height, aperture, seed, bright) = (a[0], a[1], a[2], a[3] as u64, a[4] > 0.0);
    let elev = a.get(5).copied().unwrap_or(0.0).to_radians();
    let optics = Optics {
        width: 640,
        height: 480,
        ..Optics::default()
    };
    let look = if bright {
        Look::brightfield()
    } else {
        Look::default()
    };
    let mut scene = Scene::random(
        optics,
        Look { aperture, ..look },
        &CellSpec {
            count: 5,
            ..CellSpec::default()
        },
        seed,
    );
    let azr = az.to_radians();
    let r = 60.0 + 10.0 * (seed % 5) as f64;
    scene.pipette = Some(Pipette {
        tip: [-r * azr.cos() * 0.5, -r * azr.sin() * 0.5],
        height,
        tip_radius: 1.5,
        taper: 0.08,
        elevation: 0.0,
        azimuth: azr,
    });
    let truth = scene.project(scene.pipette.unwrap().front());
    let (l, _r) = scene.render_views();
    image::GrayImage::from_raw(640, 480, l.data.clone())
        .unwrap()
        .save("/tmp/tip_left.png")
        .unwrap();
    println!("truth {:?} -> {:?}", truth[0], find_tip(&l));
}
