//! Every seed of the fuzz corpus (`fuzz/corpus/TARGET`) and every input a fuzzer ever
//! crashed or hung on (`fuzz/regressions/TARGET`, kept there as the crash's regression
//! test) goes through its target's entry point, the code `fuzz/` builds with cargo-afl:
//! none may panic. The seeds are also checked to reach past the first parse, so that the
//! fuzzers start from inputs that exercise the readers whole.

use std::path::PathBuf;

fn files(dir: &std::path::Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|d| d.map(|e| e.unwrap().path()).collect())
        .unwrap_or_default();
    v.retain(|p| p.is_file() && p.file_name().is_none_or(|n| n != "README.md"));
    v.sort();
    v
}

#[test]
fn every_seed_and_every_crash_found_runs_without_panic() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    for (name, target) in pipelines::fuzzing::TARGETS {
        let seeds = files(&root.join("corpus").join(name));
        assert!(!seeds.is_empty(), "no seed for the fuzz target {name}");
        for p in seeds
            .iter()
            .chain(&files(&root.join("regressions").join(name)))
        {
            let data = std::fs::read(p).unwrap();
            // A panic names the input it came from.
            let r = std::panic::catch_unwind(|| target(&data));
            assert!(r.is_ok(), "fuzz target {name} panicked on {}", p.display());
        }
    }
}

/// The seeds are good inputs: each reads whole, so mutations start deep in each reader.
#[test]
fn the_seeds_read_whole() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus");
    for p in files(&root.join("launch")) {
        let text = std::fs::read_to_string(&p).unwrap();
        runtime::launch::LaunchFile::parse(&p, &text)
            .and_then(|f| f.validate(&pipelines::registry::builtin()))
            .unwrap_or_else(|e| panic!("{}: {e:?}", p.display()));
    }
    for p in files(&root.join("pfm")) {
        formats::read_pfm(&p, "seed").unwrap();
    }
    for p in files(&root.join("image")) {
        capture::image::load(&p, "seed").unwrap();
    }
    for p in files(&root.join("mcap")) {
        let o = recorder::overview(&p).unwrap();
        assert!(o.error.is_none() && o.damaged.is_empty(), "{o:?}");
        assert!(!o.channels.is_empty(), "{}", p.display());
    }
    for p in files(&root.join("calibration")) {
        let d = std::fs::read(&p).unwrap();
        let text = std::str::from_utf8(&d[1..]).unwrap();
        let ok = match d[0] {
            0 => toml::from_str::<calibration::file::CalibrationFile>(text).is_ok(),
            1 => serde_json::from_str::<calibration::file::CalibrationFile>(text).is_ok(),
            2 => calibration::stereo::StereoCalibration::from_opencv_yaml(text).is_ok(),
            _ => {
                let (l, r) = text.split_once('\0').unwrap();
                calibration::stereo::Rectification::from_camera_info(l, r).is_ok()
            }
        };
        assert!(ok, "{}", p.display());
    }
}
