//! The controller a user copies first (`examples/controller.py`, quoted in the README),
//! against the default graph as `run` starts it: ten approaches into tracked cells from rest, each
//! followed by a retract, all arrive.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[test]
fn the_example_controller_sends_the_pipette_into_ten_cells_of_the_default_graph() {
    let python = Command::new("python3").arg("--version").output();
    assert!(
        python.is_ok_and(|o| o.status.success()),
        "python3 is needed to run the example controller"
    );
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let instance = format!("controller{}", std::process::id());
    let listen = format!("manipulator-bridge.listen=\"127.0.0.1:{port}\"");
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("run.log");
    let mut graph = {
        use std::os::unix::process::CommandExt;
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_microstereo"));
        cmd.args(["run", "--quiet", "--instance", &instance, "--set", &listen])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap());
        // SAFETY: only async-signal-safe prctl between fork and exec.
        unsafe {
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
        cmd.spawn().unwrap()
    };
    // The bridge listens once the graph's nodes are up.
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t0.elapsed() < Duration::from_secs(60), "no bridge");
        std::thread::sleep(Duration::from_millis(100));
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/controller.py");
    let mut ctl = Command::new("python3")
        .arg(&script)
        .arg(format!("127.0.0.1:{port}"))
        .args(["--times", "10"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = ctl.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > Duration::from_secs(240) {
            let _ = ctl.kill();
            break ctl.wait().unwrap();
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let said = ctl.wait_with_output().unwrap();
    let (out, err) = (
        String::from_utf8_lossy(&said.stdout),
        String::from_utf8_lossy(&said.stderr),
    );
    // SAFETY: kill(2) on the run this test started.
    unsafe {
        libc::kill(graph.id() as i32, libc::SIGINT);
    }
    let run_status = graph.wait().unwrap();
    let log = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(
        status.success(),
        "the controller failed:\n{out}\n{err}\nthe run said:\n{log}"
    );
    assert_eq!(
        out.lines().filter(|l| l.starts_with("in track ")).count(),
        10,
        "{out}"
    );
    assert!(out.contains("10 of 10 approaches arrived"), "{out}");
    assert!(
        run_status.success(),
        "the run ended with {run_status}:\n{log}"
    );
}
