//! Every subcommand, every flag, walked with a table of bad values (issue 19): the flags
//! are read from the command line's own definition (clap), so a flag added later is walked
//! too. Each bad value must give exit code 2, an error message and no panic, before
//! anything is written, and within a time and memory limit (a huge count that is not
//! refused would run on or grow: both fail here).

use clap::CommandFactory;
use std::any::TypeId;
use std::io::Read;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(name)
}

/// Valid positional arguments that take each subcommand past its parsing, and the output
/// (file or directory) a run would create there, which must not appear.
fn base(sub: &str, dir: &Path, stack: &Path) -> Option<(Vec<String>, Option<PathBuf>)> {
    let s = |p: PathBuf| p.display().to_string();
    let out = dir.join("out");
    let bundled = s(data("recordings/default.mcap"));
    Some(match sub {
        "reconstruct" => (
            vec![
                s(data("tests/data/cones/im2.png")),
                s(data("tests/data/cones/im6.png")),
                "-o".into(),
                s(out.clone()),
            ],
            Some(out),
        ),
        "eval" => (
            vec![
                s(data("fuzz/corpus/pfm/small.pfm")),
                "--gt".into(),
                s(data("fuzz/corpus/pfm/small.pfm")),
            ],
            None,
        ),
        "bench" => (vec!["--cones-only".into()], None),
        "segment" => (
            vec![
                s(data("tests/data/cells/cho22_crop.png")),
                "-o".into(),
                s(out.clone()),
            ],
            Some(out),
        ),
        "synth" => (vec!["-o".into(), s(out.clone())], Some(out)),
        "calibrate-depth" => (
            vec![s(stack.to_path_buf()), "--baseline".into(), "1200".into()],
            Some(stack.join("calibration-fitted.toml")),
        ),
        "run" => (
            vec![
                s(data("tests/data/graph/small.toml")),
                "--frames".into(),
                "2".into(),
            ],
            None,
        ),
        "bench-transport" => (vec![], None),
        "calibrate-stereo" => (
            vec![
                s(data("tests/data/calibration/pairs")),
                "--inner".into(),
                "9x6".into(),
                "--square".into(),
                "25".into(),
                "--unit".into(),
                "mm".into(),
                "-o".into(),
                s(out.clone()),
            ],
            Some(out),
        ),
        // A stack without a board: every bad flag is refused before the board is looked for.
        "calibrate-microscope" => (
            vec![
                s(stack.to_path_buf()),
                "--inner".into(),
                "9x6".into(),
                "--square".into(),
                "100".into(),
                "-o".into(),
                s(out.clone()),
            ],
            Some(out),
        ),
        // Its own arguments are its subcommands'.
        "calibration" => (vec![], None),
        "calibrate-manipulator" => (
            vec!["-o".into(), s(dir.join("registration.toml"))],
            Some(dir.join("registration.toml")),
        ),
        "top" => (
            vec!["--once".into(), "--instance".into(), "walk-none".into()],
            None,
        ),
        // Its own arguments are its subcommands'.
        "topic" => (vec![], None),
        "inspect" => (vec![bundled], None),
        "replay" => (vec![bundled, "--frames".into(), "1".into()], None),
        "test-node" => (vec![bundled, "segment".into()], None),
        "view" => (
            vec![bundled, "-o".into(), s(dir.join("v.rrd"))],
            Some(dir.join("v.rrd")),
        ),
        _ => return None,
    })
}

/// Flags where any value of their type is a valid one (a seed, a frame count: a huge one
/// only means a long run, which Ctrl-C ends).
const ANY_VALUE: &[&str] = &["seed", "rig_seed", "frames"];

/// One run of the binary under a 4 GiB address-space limit and a time limit: its exit
/// code (None: killed by a signal or the limit) and stderr.
fn run(args: &[String], limit: Duration) -> (Option<i32>, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_microstereo"));
    cmd.args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    // SAFETY: setrlimit is async-signal-safe and touches no memory of the parent.
    unsafe {
        cmd.pre_exec(|| {
            let lim = libc::rlimit {
                rlim_cur: 4 << 30,
                rlim_max: 4 << 30,
            };
            libc::setrlimit(libc::RLIMIT_AS, &lim);
            Ok(())
        });
    }
    let mut child = cmd.spawn().expect("binary runs");
    let mut err = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = err.read_to_string(&mut s);
        s
    });
    let t0 = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break Some(st);
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    (status.and_then(|s| s.code()), reader.join().unwrap())
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Class {
    Float,
    Int,
    InPath,
    OutPath,
    Other,
}

fn class(a: &clap::Arg) -> Class {
    let t = a.get_value_parser().type_id();
    let id = a.get_id().as_str();
    if t == TypeId::of::<f64>() || t == TypeId::of::<f32>() {
        Class::Float
    } else if [
        TypeId::of::<usize>(),
        TypeId::of::<u64>(),
        TypeId::of::<u32>(),
        TypeId::of::<u16>(),
        TypeId::of::<u8>(),
        TypeId::of::<i32>(),
        TypeId::of::<i64>(),
    ]
    .iter()
    .any(|i| t == *i)
    {
        Class::Int
    } else if t == TypeId::of::<PathBuf>() {
        if ["output", "json", "write_pairs", "record"].contains(&id) {
            Class::OutPath
        } else {
            Class::InPath
        }
    } else {
        Class::Other
    }
}

#[test]
fn every_flag_of_every_subcommand_refuses_bad_values_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let stack = dir.path().join("stack");
    let (code, err) = run(
        &[
            "synth",
            "-o",
            stack.to_str().unwrap(),
            "--width",
            "96",
            "--height",
            "64",
            "--stage-heights=-60,0,60",
        ]
        .map(String::from),
        Duration::from_secs(60),
    );
    assert_eq!(code, Some(0), "{err}");
    let truncated_png = dir.path().join("truncated.png");
    let png = std::fs::read(data("tests/data/cones/im2.png")).unwrap();
    std::fs::write(&truncated_png, &png[..png.len() / 3]).unwrap();
    let truncated_mcap = dir.path().join("truncated.mcap");
    let mcap = std::fs::read(data("recordings/default.mcap")).unwrap();
    std::fs::write(&truncated_mcap, &mcap[..mcap.len() / 3]).unwrap();
    let empty = dir.path().join("empty.toml");
    std::fs::write(&empty, "").unwrap();
    let p = |p: &Path| p.display().to_string();
    let mut failures = Vec::new();
    let mut walked = 0;
    let cli = microstereo::cli::Cli::command();
    for sub in cli.get_subcommands() {
        let name = sub.get_name();
        let Some((base_args, output)) = base(name, dir.path(), &stack) else {
            assert!(
                sub.is_hide_set(),
                "subcommand {name} has no base invocation in this test: add one"
            );
            continue;
        };
        for a in sub.get_arguments() {
            let id = a.get_id().as_str();
            if id == "help" || id == "version" || !a.get_action().takes_values() {
                continue;
            }
            let values: Vec<String> = match class(a) {
                Class::Float => ["NaN", "inf", "-inf", "1e400", "1e300"]
                    .map(String::from)
                    .to_vec(),
                Class::Int if ANY_VALUE.contains(&id) => vec!["abc".into()],
                Class::Int => ["abc", "2.5", "4000000000"].map(String::from).to_vec(),
                Class::InPath => vec![
                    "/nonexistent/input".into(),
                    p(dir.path()),
                    p(&truncated_png),
                    p(&truncated_mcap),
                    p(&empty),
                ],
                Class::OutPath => vec!["/proc/no/such/dir/out".into()],
                Class::Other => continue,
            };
            for v in values {
                let mut args = vec![name.to_string()];
                let flag = a.get_long().map(|l| format!("--{l}"));
                match &flag {
                    // A flag already in the base invocation is replaced, not repeated.
                    Some(f) => {
                        let mut b = base_args.clone();
                        if let Some(i) = b.iter().position(|x| x == f) {
                            b.drain(i..=i + 1);
                        }
                        if a.get_short()
                            .is_some_and(|s| b.iter().any(|x| *x == format!("-{s}")))
                        {
                            let i = b
                                .iter()
                                .position(|x| *x == format!("-{}", a.get_short().unwrap()))
                                .unwrap();
                            b.drain(i..=i + 1);
                        }
                        args.extend(b);
                        args.push(format!("{f}={v}"));
                    }
                    // A positional: the base's value at its index is replaced.
                    None => {
                        let idx = a.get_index().unwrap_or(1) - 1;
                        let mut b = base_args.clone();
                        if idx < b.len() {
                            b[idx] = v.clone();
                        } else {
                            b.push(v.clone());
                        }
                        args.extend(b);
                    }
                }
                walked += 1;
                let (code, err) = run(&args, Duration::from_secs(20));
                let what = format!("microstereo {}", args.join(" "));
                if code != Some(2) {
                    failures.push(format!(
                        "{what}: exit {code:?} (2 expected): {}",
                        err.lines().last().unwrap_or("")
                    ));
                } else if err.contains("panicked") || !err.contains("error") {
                    failures.push(format!("{what}: {err}"));
                } else if output.as_ref().is_some_and(|o| o.exists()) {
                    failures.push(format!("{what}: wrote its output before failing"));
                }
                if let Some(o) = &output {
                    let _ = std::fs::remove_dir_all(o);
                    let _ = std::fs::remove_file(o);
                }
            }
        }
    }
    eprintln!("{walked} bad invocations walked");
    assert!(walked > 100, "only {walked} bad invocations");
    assert!(
        failures.is_empty(),
        "{} of {walked} bad invocations were not one clean error:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// Every number among the parameters of every node in the shipped launch files (nested
/// tables and arrays included), replaced by a bad value in turn: the launch check must
/// refuse it, naming the file's line, before anything starts. Seeds and frame counts take
/// any value of their type; the rest are physical quantities with a range.
#[test]
fn every_numeric_launch_parameter_refuses_bad_values() {
    let files = [
        "launch.toml",
        "tests/data/graph/small.toml",
        "tests/data/graph/manipulator.toml",
        "recordings/default.toml",
    ];
    let registry = pipelines::registry::builtin();
    let mut walked = 0;
    let mut failures = Vec::new();
    for f in files {
        let path = data(f);
        let text = std::fs::read_to_string(&path).unwrap();
        let doc: toml::Table = toml::from_str(&text).unwrap();
        let nodes = doc["node"].as_array().unwrap();
        for (i, node) in nodes.iter().enumerate() {
            let Some(params) = node.get("params").and_then(|p| p.as_table()) else {
                continue;
            };
            let mut paths = Vec::new();
            numbers(&toml::Value::Table(params.clone()), &mut vec![], &mut paths);
            for (key, is_int) in paths {
                let last = key.last().unwrap().as_str();
                if ANY_VALUE.contains(&last) {
                    continue;
                }
                let bad: Vec<toml::Value> = if is_int {
                    vec![toml::Value::Integer(4_000_000_000_000)]
                } else {
                    [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300]
                        .map(toml::Value::Float)
                        .to_vec()
                };
                for v in bad {
                    let mut d = doc.clone();
                    let n = &mut d["node"].as_array_mut().unwrap()[i];
                    set(n.get_mut("params").unwrap(), &key, v.clone());
                    let edited = toml::to_string(&d).unwrap();
                    walked += 1;
                    let r = runtime::launch::LaunchFile::parse(&path, &edited)
                        .and_then(|l| l.validate(&registry));
                    if r.is_ok() {
                        failures.push(format!(
                            "{f}: node {} params.{} = {v} was accepted",
                            node["id"],
                            key.join(".")
                        ));
                    }
                }
            }
        }
    }
    eprintln!("{walked} bad launch parameters walked");
    assert!(walked > 20, "only {walked}");
    assert!(
        failures.is_empty(),
        "{} of {walked} accepted:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// The paths of the numbers in `v`, with whether each is an integer.
fn numbers(v: &toml::Value, at: &mut Vec<String>, out: &mut Vec<(Vec<String>, bool)>) {
    match v {
        toml::Value::Integer(_) => out.push((at.clone(), true)),
        toml::Value::Float(_) => out.push((at.clone(), false)),
        toml::Value::Table(t) => {
            for (k, x) in t {
                at.push(k.clone());
                numbers(x, at, out);
                at.pop();
            }
        }
        toml::Value::Array(a) => {
            for (k, x) in a.iter().enumerate() {
                at.push(k.to_string());
                numbers(x, at, out);
                at.pop();
            }
        }
        _ => {}
    }
}

fn set(v: &mut toml::Value, at: &[String], to: toml::Value) {
    match at.split_first() {
        None => *v = to,
        Some((k, rest)) => match v {
            toml::Value::Table(t) => set(t.get_mut(k).unwrap(), rest, to),
            toml::Value::Array(a) => set(&mut a[k.parse::<usize>().unwrap()], rest, to),
            _ => unreachable!(),
        },
    }
}
