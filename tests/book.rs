//! Every command the README and the book show: each one parses as the command line reads
//! it (a renamed flag fails here, not in a reader's terminal), and each one-shot command
//! shown as `cargo run --release -- …` runs, in the order shown, one scratch folder per
//! page, beside the repository's data.

use clap::Parser;
use microstereo::cli::Cli;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A command shown on a page.
struct Shown {
    /// Page and line, for the message.
    at: String,
    /// Its words after `microstereo` (or `cargo run --release --`).
    args: Vec<String>,
    /// Shown as something to run (`cargo run`), not as a transcript (`$ microstereo`).
    to_run: bool,
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The README and every page of the book, in order.
fn pages() -> Vec<PathBuf> {
    fn walk(d: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|e| e == "md") {
                out.push(p);
            }
        }
    }
    let mut out = vec![root().join("README.md")];
    walk(&root().join("docs/src"), &mut out);
    out
}

/// Shell words of `line` (quotes removed), up to a `#` comment outside quotes.
fn words(line: &str) -> Vec<String> {
    let (mut out, mut word, mut quote, mut any) = (Vec::new(), String::new(), None, false);
    for c in line.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), c) => word.push(c),
            (None, '\'' | '"') => {
                quote = Some(c);
                any = true;
            }
            (None, '#') if !any && word.is_empty() => break,
            (None, c) if c.is_whitespace() => {
                if any || !word.is_empty() {
                    out.push(std::mem::take(&mut word));
                }
                any = false;
            }
            (None, c) => {
                word.push(c);
                any = true;
            }
        }
    }
    if any || !word.is_empty() {
        out.push(word);
    }
    out
}

/// The commands shown in the code blocks of `page`.
fn shown_on(page: &Path) -> Vec<Shown> {
    let text = std::fs::read_to_string(page).unwrap();
    let name = page.strip_prefix(root()).unwrap().display().to_string();
    let (mut out, mut in_block, mut pending): (Vec<Shown>, bool, Option<(usize, String)>) =
        (Vec::new(), false, None);
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.starts_with("```") {
            in_block = !in_block;
            continue;
        }
        if !in_block {
            continue;
        }
        let (start, body) = match pending.take() {
            Some((at, so_far)) => (at, format!("{so_far} {line}")),
            None => (i + 1, line.to_string()),
        };
        if let Some(head) = body.strip_suffix('\\') {
            pending = Some((start, head.to_string()));
            continue;
        }
        let (rest, to_run) = if let Some(r) = body.strip_prefix("cargo run --release -- ") {
            (r, true)
        } else if let Some(r) = body
            .strip_prefix("$ microstereo ")
            .or_else(|| body.strip_prefix("microstereo "))
        {
            (r, false)
        } else {
            continue;
        };
        out.push(Shown {
            at: format!("{name}:{start}"),
            args: words(rest),
            to_run,
        });
    }
    out
}

/// Whether a shown command can run here, alone, in seconds: one-shot commands, and graphs
/// that end by themselves within a few seconds of frames; a recording's readers only where
/// a command shown before made it (`made`).
fn runs_alone(args: &[String], made: impl Fn(&str) -> bool) -> bool {
    let has = |f: &str| args.iter().any(|a| a == f);
    let frames = args
        .iter()
        .position(|a| a == "--frames")
        .and_then(|i| args.get(i + 1))
        .and_then(|n| n.parse::<u64>().ok());
    match args[0].as_str() {
        "reconstruct"
        | "eval"
        | "segment"
        | "synth"
        | "calibrate-stereo"
        | "calibrate-depth"
        | "calibrate-microscope"
        | "calibration" => true,
        "inspect" | "test-node" => made(&args[1]),
        "replay" => made(&args[1]) && !has("--loop"),
        // Until Ctrl-C, on two hosts, a file the reader writes first, or a viewer to show
        // on a screen: parsed only.
        "run" => {
            frames.is_some_and(|n| n <= 60)
                && !has("--host")
                && !has("--instance")
                && !has("--viewer")
        }
        _ => false,
    }
}

/// Runs `exe args` in `dir`; a command still running after two minutes is killed.
fn run(exe: &str, args: &[String], dir: &Path) -> Result<(), String> {
    let mut child = Command::new(exe)
        .args(args)
        .current_dir(dir)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let err = child.stderr.take().unwrap();
    let said = std::thread::spawn(move || std::io::read_to_string(err).unwrap_or_default());
    let t0 = std::time::Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > std::time::Duration::from_secs(120) {
            let _ = child.kill();
            let _ = child.wait();
            return Err("still ran after 120 s".into());
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    let said = said.join().unwrap();
    if status.success() {
        Ok(())
    } else {
        Err(format!("failed ({status}): {said}"))
    }
}

#[test]
fn every_command_the_book_shows_parses_and_the_one_shot_ones_run() {
    let exe = env!("CARGO_BIN_EXE_microstereo");
    let (mut seen, mut ran, mut problems) = (0, 0, Vec::new());
    for page in pages() {
        let shown = shown_on(&page);
        if shown.is_empty() {
            continue;
        }
        let scratch = tempfile::tempdir().unwrap();
        for d in ["tests", "examples", "recordings", "launch.toml"] {
            std::os::unix::fs::symlink(root().join(d), scratch.path().join(d)).unwrap();
        }
        for s in shown {
            seen += 1;
            let argv = std::iter::once("microstereo".to_string()).chain(s.args.iter().cloned());
            if let Err(e) = Cli::try_parse_from(argv) {
                problems.push(format!(
                    "{}: `{}` does not parse: {e}",
                    s.at,
                    s.args.join(" ")
                ));
                continue;
            }
            let made = |f: &str| scratch.path().join(f).exists();
            if !(s.to_run && runs_alone(&s.args, made)) {
                continue;
            }
            ran += 1;
            if let Err(why) = run(exe, &s.args, scratch.path()) {
                problems.push(format!("{}: `{}` {why}", s.at, s.args.join(" ")));
            }
        }
    }
    eprintln!("{seen} commands shown, {ran} run");
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    // The README's two commands and the guide's pages hold a few dozen; most run.
    assert!(seen >= 25 && ran >= 12, "{seen} commands seen, {ran} run");
}

#[test]
fn shell_words_keep_quotes_and_drop_comments() {
    assert_eq!(
        words("run --edges 'rectify/*' \"*/disparity\"   # every edge"),
        ["run", "--edges", "rectify/*", "*/disparity"]
    );
    assert_eq!(words("topic hz a/b#c"), ["topic", "hz", "a/b#c"]);
    assert_eq!(words("x ''"), ["x", ""]);
}
